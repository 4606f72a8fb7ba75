"""A record's marker is checked against itself before anything reads it (issue 41): it names its
own file's run, its config hashes to its config_hash, and no key is missing."""

import json
import shutil
from pathlib import Path

import pytest

from pemamoe.mappo import TrainConfig, train
from pemamoe.records import (RECORDS_DIR, RecordError, load_runs, read_marker, read_record, read_record_actor,
                             verify_record, write_record)

CONFIGS = [TrainConfig.for_scale("ci", method="mlp", seed=seed, iterations=2) for seed in (0, 1)]


@pytest.fixture(scope="module")
def made_records(tmp_path_factory) -> Path:
    """records/ci of two finished ci runs (seeds 0 and 1), made once; tests change copies only."""
    root = tmp_path_factory.mktemp("made")
    for cfg in CONFIGS:
        train(cfg, root / "results" / cfg.run_name())
        write_record(root / "results" / cfg.run_name(), "ci", root / "records")
    return root / "records" / "ci"


@pytest.fixture
def ci_records(made_records, tmp_path) -> Path:
    return Path(shutil.copytree(made_records, tmp_path / "records" / "ci"))


def _marker(folder: Path, cfg: TrainConfig) -> Path:
    return folder / f"{cfg.run_name()}.json"


def _edit(marker: Path, change) -> None:
    data = json.loads(marker.read_text())
    change(data)
    marker.write_text(json.dumps(data))


def _refused(marker: Path, *words) -> str:
    """The one-line RecordError of reading `marker`, which names the file and every one of `words`."""
    with pytest.raises(RecordError) as caught:
        read_record(marker)
    message = str(caught.value)
    assert "\n" not in message and str(marker) in message, message
    for word in words:
        assert word in message, message
    return message


def test_a_valid_record_still_reads(ci_records):
    cfg = CONFIGS[0]
    marker = _marker(ci_records, cfg)
    assert verify_record(marker, cfg)["run"] == cfg.run_name()
    config, frame = read_record(marker)
    assert config == cfg.to_dict() and len(frame) == 2
    assert read_record_actor(marker) is not None
    metrics, _ = load_runs([marker, _marker(ci_records, CONFIGS[1])])
    assert sorted(metrics.seed.unique()) == [0, 1]


def test_a_marker_naming_another_run_is_refused(ci_records):
    # (a) before: the figures read seed 1's data under seed 0's label
    marker, other = _marker(ci_records, CONFIGS[0]), CONFIGS[1].run_name()
    _edit(marker, lambda m: m.update(run=other))
    _refused(marker, "run", repr(other), repr(CONFIGS[0].run_name()))


def test_a_marker_whose_config_was_edited_is_refused(ci_records):
    # (b) the seed changed, the config_hash left as it was: before, accepted with seed 1
    marker = _marker(ci_records, CONFIGS[0])
    _edit(marker, lambda m: m["config"].update(seed=1))
    _refused(marker, "config_hash", repr(CONFIGS[0].config_hash()), repr(CONFIGS[0].replace(seed=1).config_hash()))


def test_a_marker_without_sha256_is_a_record_error_not_a_key_error(ci_records):
    # (c) before: KeyError 'sha256'
    marker = _marker(ci_records, CONFIGS[0])
    _edit(marker, lambda m: m.pop("sha256"))
    _refused(marker, "sha256")
    with pytest.raises(RecordError, match="sha256"):
        read_record_actor(marker)


def test_every_committed_marker_checks_against_itself():
    markers = [p for p in sorted(RECORDS_DIR.glob("*/*.json")) if not p.name.endswith(".timing.json")]
    for marker in markers:  # read only: no record of the repository is changed
        assert read_marker(marker)["run"] == marker.stem


@pytest.mark.parametrize("key, value", [("env_steps", lambda v: 2 * v), ("rows", lambda v: v + 1),
                                        ("block", lambda v: v + 1), ("iterations", lambda v: v * 10),
                                        ("numerics", lambda v: v + 1), ("env_steps", lambda v: float(v))])
def test_a_marker_stamp_that_its_config_does_not_give_is_refused(ci_records, key, value):
    """Issue 59: env_steps, rows, block and numerics were never checked (a doubled env_steps was read)."""
    marker = _marker(ci_records, CONFIGS[0])
    _edit(marker, lambda d: d.__setitem__(key, value(d[key])))
    _refused(marker, f"has {key} ", "but its config gives", "marker edited?")


def test_a_log_whose_rows_do_not_match_the_marker_is_refused(ci_records):
    """A marker and a log that both check (config, sha256) but disagree on rows: refused by the reader."""
    import hashlib

    import pandas as pd

    from pemamoe.records import parquet_bytes

    marker = _marker(ci_records, CONFIGS[0])
    log = marker.with_name(marker.stem + ".parquet")
    frame = pd.read_parquet(log)
    log.write_bytes(parquet_bytes(frame.iloc[:1]))
    _edit(marker, lambda d: d["sha256"].__setitem__("data", hashlib.sha256(log.read_bytes()).hexdigest()))
    _refused(marker, "has rows 2 and env_steps", "but its log has 1 rows")


def test_a_damaged_timing_file_is_named_as_a_records_file_not_a_run_folder(ci_records):
    """Issue 59: `sweep --status` called records/<scale> a run folder and advised deleting it."""
    from pemamoe.commands import error_line
    from pemamoe.records import record_timing

    marker = _marker(ci_records, CONFIGS[0])
    timing = marker.with_name(marker.stem + ".timing.json")
    timing.write_text("{not json")
    with pytest.raises(RecordError) as caught:
        record_timing(marker)
    line = error_line(caught.value)
    assert line.startswith(f"run record {timing}: is not valid JSON") and "run folder" not in line, line
    assert f"restore it (git checkout -- {timing}) or delete it" in line
    assert marker.exists() and read_record(marker)  # the record itself is untouched and still reads
