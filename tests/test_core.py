"""Shared utilities: scales, atomic writes, figure and table output, provenance README."""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pandas as pd
import pytest

from pemamoe import core


def test_by_scale_picks_and_rejects():
    assert core.by_scale("ci", ci=1, small=2, paper=3) == 1
    assert core.by_scale("paper", ci=1, small=2, paper=3) == 3
    with pytest.raises(ValueError, match="scale must be one of ci, small, paper; got 'huge'"):
        core.by_scale("huge", ci=1, small=2, paper=3)


def test_atomic_write_leaves_old_file_when_writer_fails(tmp_path):
    target = tmp_path / "result.json"
    core.atomic_write_json(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with core.atomic_path(target) as tmp:
            tmp.write_text("half written")
            raise RuntimeError("killed")
    assert target.read_text() == '{\n  "a": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]


def test_save_figure_and_table(tmp_path):
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    assert core.save_figure(fig, "demo", tmp_path) is None  # a cell ending with it prints nothing
    plt.close(fig)
    assert (tmp_path / "demo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "demo.pdf").read_bytes()[:4] == b"%PDF"
    assert core.write_table(pd.DataFrame({"method": ["mlp"], "params": [6820]}), "t", tmp_path) is None
    md, csv = tmp_path / "t.md", tmp_path / "t.csv"
    assert md.read_text().splitlines() == ["| method | params |", "|---|---|", "| mlp | 6820 |"]
    assert pd.read_csv(csv).to_dict("list") == {"method": ["mlp"], "params": [6820]}


def test_figures_readme_keeps_rows_of_untouched_files(tmp_path):
    (tmp_path / "a.png").write_bytes(b"x")
    (tmp_path / "cost_table.md").write_text("x")
    core.write_figures_readme(tmp_path, {"a.png": "01_channel.py"}, scale="ci", commit="abc")
    core.write_figures_readme(tmp_path, {"cost_table.md": "05_moe_actor.py"}, scale="small", commit="def")
    text = (tmp_path / "README.md").read_text()
    assert "| a.png | model illustration (no paper figure) | notebooks/01_channel.py | ci |" in text
    assert "| cost_table.md | Table 'Computational cost comparison (actor network)' |" in text
    assert "`make figures SCALE=small` | def |" in text


def test_run_notebook_rejects_unknown_scale(tmp_path):
    with pytest.raises(ValueError, match="got 'tiny'"):
        core.run_notebook(core.figure_notebooks()[0], {"scale": "tiny"}, output_dir=tmp_path)
