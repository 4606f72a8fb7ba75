"""Records stay findable across a bump of TRAINING_NUMERICS (issue 58).

A bump renames every run (its identity carries the version), but a record is evidence made by the
commit that made it: the figures keep reading the committed records, and the sweep (the figures'
first step, `sweep --status`) counts them as done, so nothing is retrained. When one config has
records of several versions, the newest is read. Resuming a checkpoint of an older version stays
refused. Every test simulates the bump by setting `pemamoe.train_config.TRAINING_NUMERICS` alone.
"""
import shutil
from pathlib import Path

import pytest

import pemamoe.sweep_runner as sweep_runner
import pemamoe.train_config as tc
from pemamoe.commands import figures_plan
from pemamoe.experiments import RunSpec, experiment_specs, pending_runs, record_marker, run_sweep, sweep_records
from pemamoe.mappo import TrainConfig, train
from pemamoe.records import (RECORDS_DIR, RecordError, find_record, load_runs, read_marker, read_record,
                             record_files, superseded, verify_record)
from pemamoe.runs import RunFolderError
from pemamoe.sweep_runner import older_unfinished, sweep_status

NOW = 2  # the version the committed records carry; each test starts there (see `at_now`) and bumps
NEXT = NOW + 1
SPEC = RunSpec("mlp", 0, "ci", overrides=(("iterations", 2),))  # seconds to train


def bump(monkeypatch, version: int = NEXT) -> None:
    monkeypatch.setattr(tc, "TRAINING_NUMERICS", version)


@pytest.fixture(autouse=True)
def at_now(monkeypatch):
    """The code at the committed records' version, whatever the constant is today: every test
    then models the bump NOW -> NEXT by hand (a later real bump leaves these tests as they are)."""
    monkeypatch.setattr(tc, "TRAINING_NUMERICS", NOW)


# --- the identity at a given version ------------------------------------------------------------
def test_the_identity_at_a_version_is_the_identity_the_code_had_at_that_version(monkeypatch):
    cfg = TrainConfig.for_scale("ci", method="pemamoe")
    now = cfg.config_hash()
    assert cfg.config_hash(NOW) == now and cfg.run_name(NOW) == cfg.run_name()
    assert "numerics" not in cfg.identity(1) and cfg.config_hash(1) != now  # version 1 leaves the key out
    assert list(cfg.run_names()) == list(range(NOW, 0, -1)) and cfg.run_names()[NOW] == cfg.run_name()
    bump(monkeypatch)
    assert cfg.config_hash() != now and cfg.config_hash(NOW) == now  # the old name is still reachable
    assert list(cfg.run_names()) == list(range(NEXT, 0, -1))
    for bad in (0, NEXT + 1, "2", 2.0, True):
        with pytest.raises(ValueError, match="numerics must be an int from 1"):
            cfg.config_hash(bad)


# --- the committed records, after a simulated bump ------------------------------------------------
def _figure_specs(scale: str) -> list:
    return [spec for name in figures_plan(scale)[2] for spec in experiment_specs(name, scale)]


@pytest.fixture(scope="module")
def committed(tmp_path_factory) -> Path:
    """A copy of the committed records (nothing here may write into the repository's; the medium
    figures read the small-scale budget study too)."""
    root = tmp_path_factory.mktemp("committed") / "records"
    shutil.copytree(RECORDS_DIR, root, ignore=shutil.ignore_patterns("in_progress", "ci"))
    return root


@pytest.mark.parametrize("scale", ["medium", "paper"])
def test_after_a_bump_the_committed_records_are_read_and_nothing_is_trained(committed, scale, tmp_path, monkeypatch,
                                                                           capsys):
    specs = _figure_specs(scale)
    before = [record_marker(spec, committed) for spec in specs]
    assert before and pending_runs(specs, tmp_path / "results", committed)[1] == []  # the premise: all recorded
    bump(monkeypatch)
    # the names the code now gives the runs have no record: a lookup by the current name alone finds nothing
    assert not any(record_files(committed, s.scale, s.to_config().run_name())["marker"].exists() for s in specs)
    assert [record_marker(spec, committed) for spec in specs] == before  # found under the version that made them
    assert {read_marker(m)["numerics"] for m in before} == {NOW}
    first = specs[0]
    assert verify_record(before[0], first.to_config())["run"] == first.to_config().run_name(NOW)
    metrics, _ = load_runs(before[:2])  # what the figures read
    assert set(metrics.run) == {Path(m).stem for m in before[:2]}
    # what the figures' first sweep, `sweep`, and `sweep --status` decide: nothing to train
    assert pending_runs(specs, tmp_path / "results", committed)[1] == []
    status = sweep_status(specs, tmp_path / "results", records_dir=committed)
    assert status.empty and status.attrs["finished"] == status.attrs["runs"] > 0

    def no_training(*args, **kwargs):
        raise AssertionError("the sweep trained a run that has a record")

    monkeypatch.setattr(sweep_runner, "_run_local", no_training)
    run_sweep(specs, "local", 1, tmp_path / "results", records_dir=committed)
    assert f"{len(set(before))} cached, 0 to run" in capsys.readouterr().out
    assert not any((committed / s.scale / f"{s.to_config().run_name()}.json").exists() for s in specs)  # none written


def test_after_a_bump_the_small_records_that_counted_as_done_still_do(tmp_path, monkeypatch):
    specs = _figure_specs("small")
    todo = {s.run_dir(tmp_path) for s in pending_runs(specs, tmp_path, RECORDS_DIR)[1]}  # small's main runs, today
    done = [s for s in specs if s.run_dir(tmp_path) not in todo]
    assert len(done) > 100
    markers = [record_marker(s, RECORDS_DIR) for s in done]
    bump(monkeypatch)
    assert pending_runs(done, tmp_path, RECORDS_DIR)[1] == []
    assert [record_marker(s, RECORDS_DIR) for s in done] == markers


# --- a config recorded under two versions ---------------------------------------------------------
def test_a_fresh_record_is_found_after_a_bump_and_a_newer_version_s_record_wins(tmp_path, monkeypatch):
    results, records = tmp_path / "results", tmp_path / "records"
    old = Path(sweep_records([SPEC], "local", 1, results, records_dir=records, verbose=False)[0])
    assert old.stem == SPEC.to_config().run_name() and read_marker(old)["numerics"] == NOW
    old_bytes = {p.name: p.read_bytes() for p in old.parent.iterdir()}

    bump(monkeypatch)
    assert SPEC.to_config().run_name() != old.stem
    assert pending_runs([SPEC], results, records)[1] == []  # the record counts: nothing to train
    assert record_marker(SPEC, records) == old and not superseded(old)
    assert read_record(old)[0] == SPEC.to_config().to_dict()

    # retrained under the new version: a record of its own, beside the old one, and the one read from now on
    new = Path(sweep_records([SPEC], "local", 1, results, records_dir=records, retrain=True, verbose=False)[0])
    assert new != old and new.stem == SPEC.to_config().run_name() and read_marker(new)["numerics"] == NEXT
    assert find_record(records, "ci", SPEC.to_config()) == new == record_marker(SPEC, records)
    assert all((old.parent / name).read_bytes() == data for name, data in old_bytes.items())  # the old one kept
    assert superseded(old) and not superseded(new)
    assert read_record(old)[1].shape == read_record(new)[1].shape  # both still read; the same arithmetic here
    assert pending_runs([SPEC], tmp_path / "elsewhere", records)[1] == []

    # code of the older version does not read the newer record as its own, and refuses it when asked
    bump(monkeypatch, NOW)
    assert record_marker(SPEC, records) == old
    with pytest.raises(RecordError, match=rf"has numerics {NEXT}, but its config gives a version from 1 to {NOW}"):
        read_marker(new)


def test_an_edited_numerics_stamp_is_still_refused(tmp_path, monkeypatch):
    import json

    marker = Path(sweep_records([SPEC], "local", 1, tmp_path / "results", records_dir=tmp_path / "records",
                                verbose=False)[0])
    bump(monkeypatch)
    data = json.loads(marker.read_text())
    marker.write_text(json.dumps({**data, "numerics": 1}))  # an older version: the config hashes otherwise
    with pytest.raises(RecordError, match="config edited"):
        read_marker(marker)


# --- an unfinished run of the older version --------------------------------------------------------
def test_an_old_checkpoint_is_not_resumed_and_is_left_as_it_is(tmp_path, monkeypatch, capsys):
    results, records = tmp_path / "results", tmp_path / "records"
    cfg = SPEC.to_config()
    folder = results / "ci" / cfg.run_name()
    train(cfg, folder, max_iterations=1)  # stopped at iteration 1 of 2, under the current version
    kept = {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file() and p.name != ".lock"}
    assert "checkpoint.pt" in kept and "done.json" not in kept

    bump(monkeypatch)
    with pytest.raises(RunFolderError, match=rf"checkpoint.pt was computed under training numerics version {NOW}, "
                                             rf"but this code computes version {NEXT}") as caught:
        train(cfg, folder)
    assert "left as it is" in str(caught.value) and "delete the folder" not in str(caught.value)
    assert older_unfinished([SPEC], results, records) == {SPEC: [folder]}

    new = Path(sweep_records([SPEC], "local", 1, results, records_dir=records)[0])
    assert "unfinished work of an older training numerics version" in capsys.readouterr().out
    assert new.stem == cfg.run_name() != folder.name and read_marker(new)["numerics"] == NEXT
    assert all((folder / name).read_bytes() == data for name, data in kept.items())  # untouched
    assert not (folder / "done.json").exists()
