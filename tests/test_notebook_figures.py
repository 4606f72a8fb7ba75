"""The notebooks show the figures they write, and the reading notebooks' prose names no commits.

Issue 42: a reader on GitHub or in JupyterLab should see a notebook's figures without running it,
so each figure a reading notebook (00-10, no letter after the number) writes into `paper_figures/`
is linked from a markdown cell, `![...](../paper_figures/<name>.png)`, and no link in any notebook
points to a file that is not there.

Issue 39: the reading notebooks explain ideas; the commit a number was measured at belongs in
`benchmarks/HISTORY.md` (or `paper_figures/README.md`), not in their prose.

Which figures a notebook writes is found by a static scan of its code cells: the names passed to
`save_figure` (an f-string's `{scale}` read as `medium`, the default of `make figures`, any other
placeholder as any name), and the string literals of a notebook that calls `save_figure` through a
helper (notebook 09's `figure(...)`) that name a committed figure.
"""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]*.py"))
READING = [p for p in NOTEBOOKS if re.fullmatch(r"\d\d_\w+\.py", p.name)]
FIGURES = ROOT / "paper_figures"
LINK_PREFIX = "../paper_figures/"
PAPER_SCALE = "paper_scale/"  # the folder `make figures SCALE=paper` writes

# Figures linked before any regeneration has committed them: file -> the notebook that links it,
# which must also be the notebook that writes it (checked below). Once `make figures` has committed
# a file, its entry is harmless and can go.
AWAITING_REGENERATION: dict[str, str] = {}

IMAGE_LINK = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)")
SAVE_FIGURE = re.compile(r"""save_figure\(\s*\w+\s*,\s*(f?)(["'])([^"']+)\2""")
STRING_LITERAL = re.compile(r"""["']([A-Za-z0-9_]+)["']""")
F_STRING_NAME = re.compile(r"""\bf(["'])([A-Za-z0-9_]+_\{scale\})\1""")  # f"plasticity_loss_{scale}"
# A commit-like token: 7 to 40 hexadecimal characters with at least one digit and one letter
# (so neither a plain number nor an English word such as "defaced"), standing alone.
COMMIT_LIKE = re.compile(r"(?<![0-9A-Za-z])(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![0-9A-Za-z])")


def cell_lines(path: Path, kind: str) -> list[tuple[int, str]]:
    """(line number, line) of every line inside the notebook's cells of `kind` ("markdown" or "code")."""
    out, current = [], None
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if line.startswith("# %%"):
            current = "markdown" if "[markdown]" in line or "[md]" in line else "code"
            continue
        if current == kind:
            out.append((number, line))
    return out


def figure_links(path: Path) -> list[tuple[int, str]]:
    """(line, target) of every markdown image link that mentions paper_figures."""
    return [(n, target) for n, line in cell_lines(path, "markdown") for target in IMAGE_LINK.findall(line)
            if "paper_figures" in target]


def committed_figures() -> set[str]:
    return {p.name for p in FIGURES.glob("*.png")}


def written_figures(path: Path) -> set[str]:
    """The .png files of paper_figures/ that the notebook's code writes (at the medium scale)."""
    code = "\n".join(line for _, line in cell_lines(path, "code"))
    calls = SAVE_FIGURE.findall(code)
    if "save_figure(" not in code:
        return set()
    known = committed_figures() | set(AWAITING_REGENERATION)
    names = set()
    # names handed to a helper that calls save_figure with a variable (09's figure(...), plot_visits(...))
    helper_f_strings = [("f", None, name) for _, name in F_STRING_NAME.findall(code)]
    for is_f, _, name in calls + helper_f_strings:
        if not is_f:
            names.add(f"{name}.png")
            continue
        parts = re.split(r"(\{[^}]*\})", name)
        pattern = "".join("medium" if p == "{scale}" else r"[A-Za-z0-9_]+" if p.startswith("{") else re.escape(p)
                          for p in parts)
        names |= {f for f in known if re.fullmatch(pattern + r"\.png", f)}
    # names handed to a helper that calls save_figure with a variable (notebook 09's figure(...))
    names |= {f"{s}.png" for s in STRING_LITERAL.findall(code)} & committed_figures()
    return names


def provenance() -> dict[str, str]:
    """paper_figures/README.md's table: .png file -> notebook file name."""
    table = {}
    for line in (FIGURES / "README.md").read_text(encoding="utf-8").splitlines():
        cols = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cols) >= 3 and cols[0].endswith(".png") and cols[2].startswith("notebooks/"):
            table[cols[0]] = cols[2].removeprefix("notebooks/")
    return table


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_figure_links_resolve(path):
    bad = []
    for line, target in figure_links(path):
        name = target.removeprefix(LINK_PREFIX)
        if not target.startswith(LINK_PREFIX) or "/" in name.removeprefix(PAPER_SCALE):
            bad.append(f"line {line}: {target} (link as {LINK_PREFIX}<file> or {LINK_PREFIX}{PAPER_SCALE}<file>, "
                       "relative to notebooks/)")
        elif not (FIGURES / name).is_file() and AWAITING_REGENERATION.get(name) != path.name:
            bad.append(f"line {line}: {target} does not exist")
    assert not bad, f"{path.name}: dangling figure links:\n" + "\n".join(bad)


@pytest.mark.parametrize("path", READING, ids=lambda p: p.name)
def test_reading_notebook_shows_the_figures_it_writes(path):
    written = written_figures(path)
    # a figure the paper scale alone writes (into paper_scale/) is shown from there
    linked = {target.removeprefix(LINK_PREFIX).removeprefix(PAPER_SCALE) for _, target in figure_links(path)}
    if written:
        assert linked, f"{path.name} writes {sorted(written)} but links none of them"
    missing = sorted(written - linked)
    assert not missing, f"{path.name} writes but does not show: {missing}"


@pytest.mark.parametrize("name", ["00_index.py", "09_experiments.py", "10_ablations.py"])
def test_the_notebooks_that_discuss_the_paper_scale_show_its_figures(name):
    """Issue 60: the notebooks whose prose reads the paper-scale campaign show its figures."""
    shown = [t for _, t in figure_links(ROOT / "notebooks" / name) if t.startswith(LINK_PREFIX + PAPER_SCALE)]
    assert shown, f"{name} discusses the paper scale but shows none of paper_figures/{PAPER_SCALE}"


def test_no_two_files_of_paper_figures_have_the_same_bytes():
    """Issue 60: one image was stored three times under three names."""
    import hashlib

    seen = {}
    for path in sorted(p for p in FIGURES.rglob("*") if p.is_file()):
        seen.setdefault(hashlib.sha256(path.read_bytes()).hexdigest(), []).append(str(path.relative_to(FIGURES)))
    assert not [names for names in seen.values() if len(names) > 1]


def test_the_scan_sees_the_figures_of_the_provenance_table():
    """The static scan agrees with paper_figures/README.md about who writes what."""
    table = provenance()
    assert len(table) >= 30, "paper_figures/README.md's table was not read"
    by_name = {p.name: p for p in NOTEBOOKS}
    missed = sorted(f"{f} ({nb})" for f, nb in table.items()
                    if nb in by_name and (FIGURES / f).is_file() and f not in written_figures(by_name[nb]))
    assert not missed, f"the scan misses figures the README says these notebooks write: {missed}"
    writers = {p.name for p in READING if written_figures(p)}
    assert {"01_channel.py", "05_nets.py", "09_experiments.py", "10_ablations.py"} <= writers


def test_awaiting_regeneration_entries_are_written_and_linked_by_their_notebook():
    for name, notebook in AWAITING_REGENERATION.items():
        path = ROOT / "notebooks" / notebook
        assert name in written_figures(path), f"{notebook} does not write {name}; drop it from AWAITING_REGENERATION"
        assert name in {t.removeprefix(LINK_PREFIX) for _, t in figure_links(path)}, f"{notebook} does not link {name}"


def commit_references(path: Path) -> list[str]:
    return [f"line {n}: {line.strip()}" for n, line in cell_lines(path, "markdown") if COMMIT_LIKE.search(line)]


@pytest.mark.parametrize("path", READING, ids=lambda p: p.name)
def test_reading_notebook_prose_names_no_commits(path):
    found = commit_references(path)
    assert not found, (f"{path.name}: commit references in markdown; explain the idea without the hash and move the "
                       "history to benchmarks/HISTORY.md:\n" + "\n".join(found))


@pytest.mark.parametrize("text, is_commit", [
    ("#   (observed with the code before `4233dde`, the commit that fixed it), well inside the anchor", True),
    ("# of a fresh-clone `make figures` at `57e8a18`. The cells above print the values of whatever scale", True),
    ("# Read at `medium` from the records committed at `6f87d82` (39 runs, 3 seeds each; the numbers", True),
    ("# records of commit fe051aa4c1f0e5d9b3a2c7e6f8d0b1a2c3d4e5f6 (a full hash)", True),
    ("# 0.84–1.27 of its own plateau; 1,024,000 env steps per phase; 22,118,400 in all", False),
    ("# colours #7f7f7f and #d62728; the word defaced; 1e-5 and 12345678", False),
])
def test_commit_pattern(text, is_commit):
    assert bool(COMMIT_LIKE.search(text)) is is_commit
