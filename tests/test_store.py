"""Work in progress that moves between machines (appendix 09d, portable state): a sweep stopped by
its deadline leaves each unfinished run's state beside the records; a fresh machine with only the
records folder resumes from it, losing no iteration, and the finished record is byte-identical to
an uninterrupted run's."""

import shutil
import time

import pytest

from pemamoe.execution import execute_population
from pemamoe.records import (PORTABLE_DIR, RecordError, portable_state_mb, portable_state_path,
                             read_portable_state, restore_portable_state, write_portable_state)
from pemamoe.runs import load_checkpoint, parquet_rows, read_json
from pemamoe.mappo import train_population
from pemamoe.sweep import RunSpec, record_marker


def _record_bytes(marker):
    stem = marker.name[: -len(".json")]
    return {f.name: f.read_bytes() for f in marker.parent.iterdir()
            if f.name.startswith(stem) and not f.name.endswith(".timing.json")}


def test_a_run_moved_mid_way_to_a_fresh_machine_records_the_same_bytes(tmp_path):
    specs = [RunSpec("smoe", 0, "ci", overrides=(("iterations", 12),)), RunSpec("smoe", 1, "ci", overrides=(("iterations", 12),))]
    assert execute_population(specs, tmp_path / "reference", records_dir=tmp_path / "reference_records")

    # the first machine: five iterations, then its portable states go to the (committed) records
    first, committed = tmp_path / "first", tmp_path / "committed"
    train_population([s.to_config() for s in specs], [s.run_dir(first) for s in specs], max_iterations=5)
    for spec in specs:
        path = write_portable_state(spec.run_dir(first), "ci", committed)
        assert path == portable_state_path(committed, "ci", spec.to_config().run_name())
        unpacked = tmp_path / "unpacked.pt"
        unpacked.write_bytes(read_portable_state(path))
        ck = load_checkpoint(unpacked, spec.to_config())  # sealed, and a valid checkpoint of this run
        assert ck["iteration"] == 5 and ck["episode_rows"] == []
        assert path.stat().st_size < (spec.run_dir(first) / "checkpoint.pt").stat().st_size
    assert portable_state_mb(committed)["ci"] > 0

    # a fresh machine: nothing but a copy of the records folder
    clone = tmp_path / "clone_records"
    shutil.copytree(committed, clone)
    fresh = tmp_path / "fresh"
    finished = execute_population(specs, fresh, records_dir=clone)
    assert len(finished) == 2
    for spec in specs:
        run_dir = spec.run_dir(fresh)
        metrics_iterations = read_json(run_dir / "moved.json")["episodes_from_iteration"]
        assert metrics_iterations == 5  # resumed where the first machine stopped: no iteration lost
        assert _record_bytes(record_marker(spec, clone)) == _record_bytes(record_marker(spec, tmp_path / "reference_records"))
        assert not portable_state_path(clone, "ci", run_dir.name).exists()  # the record carries the run now
        assert parquet_rows(run_dir / "episodes.parquet") < parquet_rows(spec.run_dir(tmp_path / "reference") / "episodes.parquet")
    assert not any((clone / "ci" / PORTABLE_DIR).glob("*.pt.zst"))


def test_a_deadline_stop_leaves_a_portable_state_that_restores_once(tmp_path):
    spec = RunSpec("mlp", 0, "ci", overrides=(("iterations", 400),))
    records = tmp_path / "records"
    assert execute_population([spec], tmp_path / "a", deadline=time.time() + 8, records_dir=records) == []
    path = portable_state_path(records, "ci", spec.to_config().run_name())
    fresh = spec.run_dir(tmp_path / "b")
    assert restore_portable_state(fresh, "ci", records)
    stopped_at = load_checkpoint(fresh / "checkpoint.pt", spec.to_config())["iteration"]
    assert 0 < stopped_at < 400 and not record_marker(spec, records).exists()
    assert stopped_at == load_checkpoint(spec.run_dir(tmp_path / "a") / "checkpoint.pt", spec.to_config())["iteration"]
    assert not restore_portable_state(fresh, "ci", records)  # the folder is as far along already
    assert not restore_portable_state(spec.run_dir(tmp_path / "a"), "ci", records)  # the first machine's too

    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside the compressed stream: decompression or the seal catches it
    path.write_bytes(bytes(data))
    with pytest.raises(RecordError, match="content check|cannot be decompressed"):
        restore_portable_state(spec.run_dir(tmp_path / "c"), "ci", records)
    path.write_bytes(b"not a portable state")
    with pytest.raises(RecordError, match="no pemamoe-portable header"):
        restore_portable_state(spec.run_dir(tmp_path / "c"), "ci", records)


def test_a_portable_state_of_another_run_is_refused(tmp_path):
    a, b = RunSpec("mlp", 0, "ci"), RunSpec("mlp", 1, "ci")
    train_population([a.to_config()], [a.run_dir(tmp_path / "res")], max_iterations=2)
    path = write_portable_state(a.run_dir(tmp_path / "res"), "ci", tmp_path / "rec")
    path.rename(portable_state_path(tmp_path / "rec", "ci", b.to_config().run_name()))
    with pytest.raises(RecordError, match="holds run 'mlp-s0-"):
        restore_portable_state(b.run_dir(tmp_path / "other"), "ci", tmp_path / "rec")


def test_a_finished_run_has_no_portable_state(tmp_path):
    spec = RunSpec("mlp", 0, "ci")
    execute_population([spec], tmp_path / "res")
    assert write_portable_state(spec.run_dir(tmp_path / "res"), "ci", tmp_path / "rec") is None


def test_status_on_a_fresh_machine_counts_the_committed_portable_state(tmp_path):
    from pemamoe.execution import sweep_status
    from pemamoe.records import portable_state_iteration

    spec = RunSpec("mlp", 0, "ci", overrides=(("iterations", 12),))
    train_population([spec.to_config()], [spec.run_dir(tmp_path / "first")], max_iterations=5)
    records = tmp_path / "records"
    write_portable_state(spec.run_dir(tmp_path / "first"), "ci", records)
    assert portable_state_iteration(records, "ci", spec.to_config().run_name()) == 5
    assert portable_state_iteration(records, "ci", "mlp-s9-000000000000") is None
    fresh = tmp_path / "fresh"  # nothing restored here yet
    assert sweep_status([spec], fresh, workers=1).iteration.tolist() == [0]
    assert sweep_status([spec], fresh, workers=1, records_dir=records).iteration.tolist() == [5]
    assert not spec.run_dir(fresh).exists()  # status restores nothing
