"""Run records (appendix 09d): the published data of a finished run, the same bytes however the run
was trained, checked on read, read by the figures instead of the run folders, within the budget."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import pemamoe.records as records
from pemamoe.core import REPO_ROOT, run_notebook
from pemamoe.mappo import TrainConfig, train, train_population
from pemamoe.records import (RECORD_BUDGET_MB, RecordError, committed_records_mb, read_record, read_record_actor,
                             record_block, record_frame, record_timing, verify_record, write_record)
from pemamoe.experiments import RunSpec, record_marker, run_sweep, sweep_records


def test_record_frame_averages_blocks_by_hand():
    m = pd.DataFrame({"iteration": [0, 1, 2, 3], "phase": [0, 0, 1, 1], "switch": [False, False, True, False],
                      "env_steps": [10, 20, 30, 40], "episodes": [1, 3, 0, 2],
                      "coverage": [0.2, 0.6, np.nan, 0.4], "policy_loss": [1.0, 3.0, 5.0, 7.0],
                      "rank/stable/mean": [np.nan, 2.0, np.nan, np.nan], "wall_time": [1.0, 2.0, 3.0, 4.0]})
    r = record_frame(m, 2)
    assert list(r.iteration) == [0, 2] and list(r.phase) == [0, 1] and list(r.switch) == [False, True]
    assert list(r.env_steps) == [20, 40] and list(r.episodes) == [4, 2] and list(r.iterations) == [2, 2]
    assert r.coverage.tolist() == pytest.approx([(0.2 + 3 * 0.6) / 4, 0.4])  # weighted by episodes
    assert r.policy_loss.tolist() == [2.0, 6.0]
    assert r["rank/stable/mean"].iloc[0] == 2.0 and np.isnan(r["rank/stable/mean"].iloc[1])  # logged rows only
    assert "wall_time" not in r and r.coverage.dtype == np.float32


def test_a_block_never_straddles_a_switch():
    medium = TrainConfig.for_scale("medium", "mlp")
    assert record_block(medium) == 22 and medium.phase_length_iters % 22 == 0
    paper = TrainConfig.for_scale("paper", "mlp")
    block = record_block(paper)
    assert paper.phase_length_iters % block == 0 and -(-paper.iterations // block) <= records.RECORD_ROWS
    fixed = TrainConfig.for_scale("small", "mlp", fixed_phase=1, iterations=3907, phase_length_iters=3907)
    assert record_block(fixed) == -(-3907 // records.RECORD_ROWS)


def _record_bytes(marker: Path) -> dict:
    stem = marker.name[: -len(".json")]
    return {f.name: f.read_bytes() for f in marker.parent.iterdir() if f.name.startswith(stem)
            and not f.name.endswith(".timing.json")}


def test_a_record_is_the_same_bytes_alone_in_a_population_and_resumed(tmp_path, monkeypatch):
    monkeypatch.setattr(records, "RECORD_ROWS", 4)  # 12 iterations in blocks of 3: the block path too
    cfg = TrainConfig.for_scale("ci", method="smoe", seed=0, iterations=12, phase_length_iters=3)
    assert record_block(cfg) == 3
    train(cfg, tmp_path / "alone")
    train_population([cfg.replace(seed=5), cfg], [tmp_path / "p5", tmp_path / "p0"])
    train(cfg, tmp_path / "resumed", max_iterations=5)
    train(cfg, tmp_path / "resumed")
    got = [_record_bytes(write_record(tmp_path / d, "ci", tmp_path / f"rec_{d}")) for d in ("alone", "p0", "resumed")]
    assert got[0] == got[1] == got[2] and len(got[0]) == 3  # data, actor, marker
    marker = tmp_path / "rec_alone" / "ci" / f"{cfg.run_name()}.json"
    config, frame = read_record(marker)
    assert config == cfg.to_dict() and len(frame) == 4 and frame.iterations.sum() == 12
    actor = read_record_actor(marker)
    final = train(cfg, tmp_path / "alone").actor  # the finished run, read back from its folder
    for (name, a), (_, b) in zip(actor.state_dict().items(), final.state_dict().items()):
        assert np.array_equal(a.numpy(), b.numpy()), name


def test_a_record_is_checked_when_read(tmp_path):
    cfg = TrainConfig.for_scale("ci", method="mlp", seed=0, iterations=2)
    train(cfg, tmp_path / "run")
    marker = write_record(tmp_path / "run", "ci", tmp_path / "records")
    assert verify_record(marker, cfg)["run"] == cfg.run_name()
    assert verify_record(tmp_path / "records" / "ci" / "other.json") is None
    with pytest.raises(RecordError, match="config hash"):
        verify_record(marker, cfg.replace(seed=1))
    data = marker.with_name(cfg.run_name() + ".parquet")
    data.write_bytes(data.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(RecordError, match="differs from the file it sealed"):
        read_record(marker)
    marker.write_text(json.dumps({"format": 99}))
    with pytest.raises(RecordError, match="format 99"):
        verify_record(marker)
    with pytest.raises(RecordError, match="not a finished run"):
        train(cfg, tmp_path / "partial", max_iterations=1)
        write_record(tmp_path / "partial", "ci", tmp_path / "records")


def test_a_recorded_run_is_not_trained_again_and_retrain_writes_the_same_bytes(tmp_path, capsys):
    specs = [RunSpec("mlp", 0, "ci"), RunSpec("smoe", 0, "ci")]
    markers = sweep_records(specs, workers=1, results_dir=tmp_path / "results", records_dir=tmp_path / "records")
    before = {m: _record_bytes(m) for m in markers}
    capsys.readouterr()
    fresh = tmp_path / "fresh_results"  # a new machine: the records, but no run folders
    sweep_records(specs, workers=1, results_dir=fresh, records_dir=tmp_path / "records")
    assert "0 to run" in capsys.readouterr().out and not fresh.exists()
    run_sweep(specs, workers=1, results_dir=fresh, records_dir=tmp_path / "records", retrain=True)
    assert "2 to run" in capsys.readouterr().out
    assert {m: _record_bytes(m) for m in markers} == before  # retrained: the same records, bit for bit
    assert record_marker(specs[0], tmp_path / "records") == markers[0]


def test_figures_from_records_alone_train_nothing_and_write_the_same_files(tmp_path):
    notebook = REPO_ROOT / "notebooks" / "09b_budget.py"
    params = {"scale": "ci", "records_dir": str(tmp_path / "records")}
    run_notebook(notebook, {**params, "figures_dir": str(tmp_path / "trained"), "results_dir": str(tmp_path / "r1")},
                 output_dir=tmp_path / "x1", timeout=600)
    run_notebook(notebook, {**params, "figures_dir": str(tmp_path / "read"), "results_dir": str(tmp_path / "r2")},
                 output_dir=tmp_path / "x2", timeout=600)
    trained = lambda root: [p.parent.name for p in root.rglob("config.json")]  # noqa: E731 - run folders
    assert trained(tmp_path / "r1") and not trained(tmp_path / "r2")  # the second run trained nothing
    written = sorted(p.name for p in (tmp_path / "trained").iterdir())
    assert written and written == sorted(p.name for p in (tmp_path / "read").iterdir())
    for name in written:
        assert (tmp_path / "trained" / name).read_bytes() == (tmp_path / "read" / name).read_bytes(), name


def test_committed_records_fit_the_budget(capsys):
    sizes = committed_records_mb()
    committed = {scale: mb for scale, mb in sizes.items() if scale != "ci"}
    total = sum(committed.values())
    per_medium = [f.stat().st_size / 1e6 for f in (REPO_ROOT / "records" / "medium").glob("*")
                  if not f.name.endswith(".timing.json")] if (REPO_ROOT / "records" / "medium").is_dir() else []
    with capsys.disabled():
        print(f"\n[records] committed: {total:.1f} MB of {RECORD_BUDGET_MB['committed']:g} MB "
              f"({', '.join(f'{s} {mb:.1f} MB' for s, mb in committed.items()) or 'none'})")
    assert total <= RECORD_BUDGET_MB["committed"]
    # a medium record (data, actor, marker) stays under its budget
    stems = {}
    for f in (REPO_ROOT / "records" / "medium").glob("*") if per_medium else ():
        if not f.name.endswith(".timing.json"):
            stems.setdefault(f.name.split(".")[0], 0.0)
            stems[f.name.split(".")[0]] += f.stat().st_size / 1e6
    assert all(mb <= RECORD_BUDGET_MB["per_medium_run"] for mb in stems.values()), stems


def test_a_record_says_which_processors_trained_it_and_when_that_is_not_known(tmp_path):
    """Training floats differ between processor families (a paper-scale MLP trained on another
    machine differs from iteration 0), so the timing file names the processors of every session;
    a run resumed from a checkpoint older than that record says part of it is not known."""
    import torch

    from pemamoe.runs import UNRECORDED_PROCESSOR, seal_checkpoint, training_processor

    cfg = TrainConfig.for_scale("ci", method="mlp", seed=0, iterations=4, phase_length_iters=2)
    train(cfg, tmp_path / "whole")
    timing = record_timing(write_record(tmp_path / "whole", "ci", tmp_path / "rec_whole"))
    assert timing["processors"] == [training_processor()]
    train(cfg, tmp_path / "old", max_iterations=2)
    ck_path = tmp_path / "old" / "checkpoint.pt"
    ck = torch.load(ck_path, weights_only=False)
    ck.pop("processors")  # as the checkpoints written before it was recorded
    torch.save(ck, ck_path)
    seal_checkpoint(ck_path)
    train(cfg, tmp_path / "old")
    timing = record_timing(write_record(tmp_path / "old", "ci", tmp_path / "rec_old"))
    assert timing["processors"] == sorted([training_processor(), UNRECORDED_PROCESSOR])
    # the same record written again from the whole run: the bytes' processors, the first compute kept
    again = record_timing(write_record(tmp_path / "whole", "ci", tmp_path / "rec_old"))
    assert again["processors"] == [training_processor()] and again["member_compute_s"] == timing["member_compute_s"]
