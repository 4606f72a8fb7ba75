"""The README's commands stay runnable: every `python -m pemamoe COMMAND` it names answers `--help`,
every `make TARGET` it names is a target of the Makefile, and every repository path it names
exists (or is one git ignores: a cache or output the commands create). Each checker is also run on
a text naming something that does not exist, so a checker that finds nothing cannot pass unseen.
"""

import re
import subprocess
from pathlib import Path

import pytest

from pemamoe.__main__ import main as cli_main

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
MAX_README_LINES = 150  # a user's page; measurements go to benchmarks/HISTORY.md and RESULTS.md
# Files of a run folder that the README names by their bare names (`train` writes them there).
RUN_FOLDER_FILES = {"config.json", "metrics.parquet", "episodes.parquet", "checkpoint.pt", "done.json"}
BARE_FILE = re.compile(r"^[\w.-]+\.(py|md|toml|lock|in|json|parquet|pt|sh|txt|csv|cfg)$")
BOGUS = ("Run `python -m pemamoe frobnicate --fast`, then `make frobnicate`;\n"
         "```bash\nmake test && make unbuilt-target   # see notebooks/99_missing.py\n```\n"
         "The map is `notebooks/00_index.py`, the rest in `benchmarks/NOWHERE.md` and `nowhere.toml`.\n")


def code_pieces(text: str) -> tuple:
    """(lines of fenced code blocks, inline code spans outside them)."""
    blocks, prose, fenced = [], [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif fenced:
            blocks.append(line)
        else:
            prose.append(line)
    spans = re.findall(r"`([^`\n]+)`", "\n".join(prose))
    return blocks, spans


def cli_commands(text: str) -> set:
    """The COMMAND of every `python -m pemamoe COMMAND ...` in the text's code."""
    blocks, spans = code_pieces(text)
    return set(re.findall(r"python -m pemamoe\s+([a-z][\w-]*)", "\n".join(blocks + spans)))


def make_targets(text: str) -> set:
    """The TARGET of every `make TARGET ...` in the text's code."""
    blocks, spans = code_pieces(text)
    return set(re.findall(r"(?:^|[\s;&|(])make\s+([a-z][\w-]*)", "\n".join(blocks + spans), flags=re.M))


def named_paths(text: str) -> set:
    """Repository paths in the text's code: spans or code tokens with a `/`, and bare file names
    in spans; templates and globs (`<scale>`, `*.py`, `{png,pdf}`) are left out."""
    blocks, spans = code_pieces(text)
    tokens = [t.strip("`'\"(),;:") for line in blocks for t in line.split()]
    found = {t for t in tokens + spans if "/" in t and " " not in t}
    found |= {s for s in spans if BARE_FILE.match(s) and s not in RUN_FOLDER_FILES}
    # URLs (s3://..., https://...) and home-directory paths (~/...) are not repository paths
    return {p for p in found if not re.search(r"[<>*{}$=]", p) and not p.startswith(("-", "http", "~"))
            and "://" not in p}


def makefile_targets() -> set:
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    return set(re.findall(r"^([\w.-]+)\s*:(?!=)", text, flags=re.M))


def help_exit_code(command: str) -> int:
    try:
        returned = cli_main([command, "--help"])
    except SystemExit as stop:
        return stop.code if isinstance(stop.code, int) else 1
    return returned or 0


def missing_paths(paths) -> list:
    """The paths that neither exist nor are ignored by git (outputs the commands create)."""
    missing = []
    for p in sorted(paths):
        if (ROOT / p).exists():
            continue
        ignored = subprocess.run(["git", "check-ignore", "-q", "--no-index", p], cwd=ROOT).returncode == 0
        if not ignored:
            missing.append(p)
    return missing


def test_the_extractors_find_what_the_readme_names():
    assert {"train", "sweep", "figures"} <= cli_commands(README)
    assert {"test", "figures", "lab", "bench"} <= make_targets(README)
    assert {"notebooks/00_index.py", "paper_figures/README.md", "CONTRIBUTING.md",
            "benchmarks/HISTORY.md", "benchmarks/RESULTS.md"} <= named_paths(README)


@pytest.mark.parametrize("command", sorted(cli_commands(README)))
def test_every_cli_command_the_readme_names_answers_help(command, capsys):
    assert help_exit_code(command) == 0, f"README names `python -m pemamoe {command}`, whose --help fails"
    assert "usage:" in capsys.readouterr().out


def test_every_make_target_the_readme_names_is_in_the_makefile():
    unknown = make_targets(README) - makefile_targets()
    assert not unknown, f"README names make targets the Makefile lacks: {sorted(unknown)}"


def test_every_path_the_readme_names_exists():
    missing = missing_paths(named_paths(README))
    assert not missing, f"README names paths that do not exist: {missing}"


def test_the_checks_fail_on_a_text_naming_what_does_not_exist(capsys):
    assert cli_commands(BOGUS) == {"frobnicate"}
    assert help_exit_code("frobnicate") != 0
    assert make_targets(BOGUS) - makefile_targets() == {"frobnicate", "unbuilt-target"}
    assert missing_paths(named_paths(BOGUS)) == ["benchmarks/NOWHERE.md", "notebooks/99_missing.py", "nowhere.toml"]


def test_the_readme_names_the_command_ci_runs_and_stays_short():
    ci_commands = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines() if line.startswith("make ")]
    assert ci_commands == ["make test"]
    assert all(command in README for command in ci_commands)
    assert len(README.splitlines()) <= MAX_README_LINES, "measurements belong in benchmarks/HISTORY.md"


def test_the_run_folder_files_named_bare_are_ones_the_package_writes():
    source = "\n".join(p.read_text(encoding="utf-8") for p in (ROOT / "pemamoe").glob("*.py"))
    assert all(f'"{name}"' in source for name in RUN_FOLDER_FILES)
