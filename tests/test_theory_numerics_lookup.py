"""Theory records stay findable across a bump of TRAINING_NUMERICS (issue 58, appendix 08c).

Notebook 08's records carry TRAINING_NUMERICS in their parameters, because the learner trains with
the shared training arithmetic. A bump of it changes the parameters the notebook asks for, yet a
committed record is evidence made by the commit that made it: the notebook (and so `make figures`)
keeps reading it and computes nothing; a record of a newer version, once there, wins; a new record
is written beside the old ones, never over them. A bump of THEORY_NUMERICS (the experiment's own
code changed what it computes) is not looked across: it is computed again, beside the old record.
Every test simulates the bump by setting `pemamoe.train_config.TRAINING_NUMERICS` alone.
"""
import hashlib
import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

import pemamoe.theory_records as tr
import pemamoe.train_config as tc
from pemamoe.commands import figures_plan
from pemamoe.core import SCALES
from pemamoe.records import RECORDS_DIR
from pemamoe.toy_tracking import TrackerConfig, TrackingProblemConfig

NOW = 2  # the version the committed records carry; each test starts there (see `at_now`) and bumps
NEXT = NOW + 1
COMMITTED = sorted(p for p in RECORDS_DIR.glob(f"*/{tr.THEORY_DIR}/*.json") if not p.name.endswith(".timing.json"))
THEORY_SCALES = [s for s in SCALES if s != "ci" and any(nb.name == "08_theory.py" for nb in figures_plan(s)[1])]


def bump(monkeypatch, version: int = NEXT) -> None:
    monkeypatch.setattr(tc, "TRAINING_NUMERICS", version)


@pytest.fixture(autouse=True)
def at_now(monkeypatch):
    """The code at the committed records' version, whatever the constant is today: every test
    then models the bump NOW -> NEXT by hand (a later real bump leaves these tests as they are)."""
    monkeypatch.setattr(tc, "TRAINING_NUMERICS", NOW)


def refuse():
    raise AssertionError("a theory record was computed")


def digests(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def quiet(_line):
    pass


def record(x: float):
    """A compute function of a one-table record whose value says which computation made it."""
    return lambda: ({"pairs": pd.DataFrame({"x": [x]})}, {"made": x})


# --- names and parameters ------------------------------------------------------------------------
def test_names_are_unchanged_at_the_current_numerics_and_tagged_after_a_bump(monkeypatch, tmp_path):
    assert tr.theory_record_name("noise") == "noise"  # the committed records' names
    assert tr.theory_record_path(tmp_path, "medium", "noise") == tmp_path / "medium" / "theory" / "noise.json"
    bump(monkeypatch)
    assert tr.theory_record_name("noise") == f"noise-n{NEXT}"
    assert tr.theory_record_name("noise", {"theory": 1, "training": NOW}) == "noise"  # the old one is still reachable
    monkeypatch.setattr(tr, "THEORY_NUMERICS", 2)
    assert tr.theory_record_name("noise") == f"noise-t2-n{NEXT}"
    for bad in (0, "2", 2.0, True):
        with pytest.raises(ValueError, match="numerics.training must be an int"):
            tr.theory_record_name("noise", {"theory": 1, "training": bad})


def test_a_bump_changes_the_parameters_in_their_training_version_alone(monkeypatch):
    problem = TrackingProblemConfig(n_phases=3, probe_size=32)
    jobs = [(problem, TrackerConfig(controller=c, iterations=16, n_switches=2, batch=8), 0, 3, False)
            for c in ("off", "noise")]
    before = tr.theory_parameters({"T": 16}, jobs)
    bump(monkeypatch)
    after = tr.theory_parameters({"T": 16}, jobs)  # the learner jobs' identity does not move with the version
    assert after["numerics"] == {"theory": tr.THEORY_NUMERICS, "training": NEXT}
    assert {**after, "numerics": before["numerics"]} == before
    assert tr.theory_parameters_at(after, NOW) == before
    assert tr.parameters_hash(after) != tr.parameters_hash(before)  # so a lookup by the asked parameters alone misses


# --- the committed records, after a simulated bump ------------------------------------------------
@pytest.fixture()
def committed(tmp_path) -> Path:
    """A copy of the committed theory records (nothing here may write into the repository's)."""
    root = tmp_path / "records"
    for marker in COMMITTED:
        scale = marker.parent.parent.name
        shutil.copytree(marker.parent, root / scale / tr.THEORY_DIR, dirs_exist_ok=True)
    return root


def test_the_committed_records_are_named_by_their_experiment_and_versions():
    assert COMMITTED and THEORY_SCALES  # the premise: records to find, scales whose figures read them
    for marker in COMMITTED:
        made = tr.read_theory_marker(marker)  # the name check included
        assert marker == tr.theory_record_path(RECORDS_DIR, marker.parent.parent.name, made["experiment"],
                                               made["parameters"])
        assert made["parameters"]["numerics"]["training"] <= NOW
    assert {"noise", "routing", "regret"} <= {m.stem for m in COMMITTED}  # never renamed, never overwritten


@pytest.mark.parametrize("scale", THEORY_SCALES)
def test_after_a_bump_the_committed_records_are_read_and_nothing_is_computed(committed, scale, monkeypatch):
    before = digests(committed)
    experiments = sorted({tr.read_theory_marker(m)["experiment"] for m in COMMITTED})
    made = {e: tr.read_theory_marker(tr.find_theory_record(committed, scale, e, _newest_committed(e)))
            for e in experiments}
    bump(monkeypatch)
    for experiment, marker in made.items():
        # what notebook 08 asks after the bump: the same settings and jobs, the code's numerics now
        asked = {**marker["parameters"], "numerics": tr.theory_parameters({})["numerics"]}
        assert asked["numerics"]["training"] == NEXT and tr.parameters_hash(asked) != marker["parameters_hash"]
        lines = []
        tables, values = tr.theory_record(committed, scale, experiment, asked, refuse, say=lines.append)
        assert values == marker["values"] and set(tables) == set(marker["tables"])
        found = tr.find_theory_record(committed, scale, experiment, asked)
        expected, _ = tr.read_theory_record(found, marker["parameters"])
        for name, frame in tables.items():
            pd.testing.assert_frame_equal(frame, expected[name], check_exact=True)
        assert len(lines) == 1 and ": read " in lines[0] and f"under TRAINING_NUMERICS {NOW}" in lines[0], lines
    assert digests(committed) == before  # nothing written, nothing rewritten


def _newest_committed(experiment: str) -> dict:
    """The parameters of the newest-version committed record of `experiment`."""
    markers = [tr.read_theory_marker(m) for m in COMMITTED]
    return max((m["parameters"] for m in markers if m["experiment"] == experiment),
               key=lambda p: (p["numerics"]["theory"], p["numerics"]["training"]))


# --- several versions ---------------------------------------------------------------------------
def test_a_newer_versions_record_wins_and_the_older_stays_byte_identical(tmp_path, monkeypatch):
    params = tr.theory_parameters({"T": 10})
    tr.theory_record(tmp_path, "medium", "noise", params, record(1.0), say=quiet)
    old = tr.theory_record_path(tmp_path, "medium", "noise")
    old_bytes = digests(tmp_path)
    bump(monkeypatch)
    asked = tr.theory_parameters({"T": 10})
    assert tr.theory_record(tmp_path, "small", "noise", asked, refuse, say=quiet)[1] == {"made": 1.0}
    # retrain=True computes under the new version: its record goes beside the old one
    lines = []
    tr.theory_record(tmp_path, "small", "noise", asked, record(2.0), retrain=True, say=lines.append)
    new = tmp_path / "small" / "theory" / f"noise-n{NEXT}.json"
    assert new.is_file() and lines[-1].endswith(f"small/theory/noise-n{NEXT}.json"), lines
    after = digests(tmp_path)
    assert {k: after[k] for k in old_bytes} == old_bytes  # the old record, byte for byte
    # the newest version wins, at its own scale and at another scale that holds only an older one
    for scale in ("small", "medium"):
        assert tr.find_theory_record(tmp_path, scale, "noise", asked) == new
        assert tr.theory_record(tmp_path, scale, "noise", asked, refuse, say=quiet)[1] == {"made": 2.0}
    bump(monkeypatch, NEXT + 1)  # a further bump: NEXT's record wins over NOW's
    assert tr.theory_record(tmp_path, "medium", "noise", tr.theory_parameters({"T": 10}), refuse, say=quiet)[1] == \
        {"made": 2.0}
    assert tr.read_theory_record(old, params)[1] == {"made": 1.0}  # and the old one reads as it always did
    assert digests(tmp_path) == after


def test_after_a_bump_other_parameters_are_computed_beside_the_old_record(tmp_path, monkeypatch):
    tr.theory_record(tmp_path, "medium", "regret", tr.theory_parameters({"T": 10}), record(1.0), say=quiet)
    before = digests(tmp_path)
    bump(monkeypatch)
    lines = []
    tables, values = tr.theory_record(tmp_path, "medium", "regret", tr.theory_parameters({"T": 20}), record(3.0),
                                      say=lines.append)
    assert values == {"made": 3.0} and "it stays, this one goes beside it" in lines[0], lines
    after = digests(tmp_path)
    assert {k: after[k] for k in before} == before
    assert (tmp_path / "medium" / "theory" / f"regret-n{NEXT}.json").is_file()


def test_a_theory_numerics_bump_computes_again_beside_the_old_record(tmp_path, monkeypatch):
    tr.theory_record(tmp_path, "medium", "routing", tr.theory_parameters({"T": 10}), record(1.0), say=quiet)
    before = digests(tmp_path)
    monkeypatch.setattr(tr, "THEORY_NUMERICS", tr.THEORY_NUMERICS + 1)
    with pytest.raises(AssertionError, match="was computed"):  # not looked across: the old record is not the answer
        tr.theory_record(tmp_path, "medium", "routing", tr.theory_parameters({"T": 10}), refuse, say=quiet)
    lines = []
    _, values = tr.theory_record(tmp_path, "medium", "routing", tr.theory_parameters({"T": 10}), record(4.0),
                                 say=lines.append)
    assert values == {"made": 4.0} and "numerics.theory" in lines[0], lines
    after = digests(tmp_path)
    assert {k: after[k] for k in before} == before
    assert (tmp_path / "medium" / "theory" / f"routing-t{tr.THEORY_NUMERICS}.json").is_file()


def test_a_damaged_newest_record_is_refused_not_passed_over(tmp_path, monkeypatch):
    tr.theory_record(tmp_path, "medium", "noise", tr.theory_parameters({"T": 10}), record(1.0), say=quiet)
    bump(monkeypatch)
    tr.theory_record(tmp_path, "medium", "noise", tr.theory_parameters({"T": 10}), record(2.0), retrain=True,
                     say=quiet)
    new = tr.theory_record_path(tmp_path, "medium", "noise")
    table = new.with_name(f"{new.stem}.pairs.parquet")
    table.write_bytes(table.read_bytes()[:-2] + b"\0\0")
    with pytest.raises(tr.TheoryRecordError, match=f"noise-n{NEXT}.pairs.parquet"):
        tr.theory_record(tmp_path, "medium", "noise", tr.theory_parameters({"T": 10}), refuse, say=quiet)


def test_a_record_under_another_versions_name_is_refused(tmp_path, monkeypatch):
    tr.theory_record(tmp_path, "medium", "noise", tr.theory_parameters({"T": 10}), record(1.0), say=quiet)
    old = tr.theory_record_path(tmp_path, "medium", "noise")
    bump(monkeypatch)
    shutil.copy(old, old.with_name(f"noise-n{NEXT}.json"))  # an old record passed off as the new version's
    with pytest.raises(tr.TheoryRecordError, match=f"named 'noise', not of its file's name 'noise-n{NEXT}'"):
        tr.theory_record(tmp_path, "medium", "noise", tr.theory_parameters({"T": 10}), refuse, say=quiet)
    with pytest.raises(ValueError, match="is named 'noise', not 'noise-n"):  # nor can one be written so
        tr.write_theory_record(old.with_name(f"noise-n{NEXT}.json"), json.loads(old.read_text())["parameters"],
                               {"pairs": pd.DataFrame({"x": [1.0]})})
