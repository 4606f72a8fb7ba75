# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 09d · Appendix: run records, the published data of a finished run
#
# A run folder under `results/` is a training cache: its checkpoint (tens of megabytes late in a
# medium run) and its full logs let a run resume bit for bit, but they live only as long as the
# machine does, and git ignores them. What the figures and tables need from a finished run is far
# smaller, and it is what this appendix writes as the run's **record**, in a folder git tracks
# (`records/<scale>/`):
#
# * `<run>.parquet`: the per-iteration log (`metrics.parquet`) without the timing columns, which
#   differ from one training to the next, in float32, averaged over blocks of iterations when a run
#   is long (at most `RECORD_ROWS` rows: a medium run of 13,200 iterations keeps one row per 22).
#   A block never straddles a phase switch (its length divides the phase length). The episode
#   columns (return, coverage, ...) are averaged with the number of episodes that ended in each
#   iteration as the weight, `episodes` is summed, and the diagnostics, which are logged every
#   `diag_every` iterations, are averaged over the iterations that logged them;
# * `<run>.actor.parquet`: the final actor's parameters, so that a published policy can be
#   evaluated without retraining it (appendix 05c does);
# * `<run>.json`, written last: the record's format, the run's name, scale and full config, the
#   numerics version, and the sha256 of the two files. It is the record's done marker.
#
# A record is computed from the run's sealed files alone, so it is byte-identical however the run
# was trained: alone, in a population, or resumed (tests/test_records.py checks all three). The
# compute the run took is a measurement, not a result; it goes to a fourth file,
# `<run>.timing.json`, written once, when the record is first made, with the processors that trained
# it (their names follow the record's bytes when a retraining rewrites them).

# %%
#| default_exp records

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import hashlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from pemamoe.core import REPO_ROOT, atomic_path, atomic_write_bytes, atomic_write_json, check_scale
from pemamoe.runs import RunFolderError, read_config, read_json, read_parquet, verify_done
from pemamoe.train_config import TIMING_COLUMNS, TrainConfig, training_numerics

RECORD_FORMAT = 1
RECORDS_DIR = REPO_ROOT / "records"  # tracked by git, one folder per scale (ci's is ignored)
RECORD_ROWS = 600  # at most this many rows per record: longer runs are averaged over blocks
RECORD_BUDGET_MB = {"per_medium_run": 0.5, "committed": 60.0}
# Per-iteration means over the episodes that ended in the iteration: averaged with those counts
EPISODE_COLUMNS = ("episode_return", "episode_length", "coverage", "served_users", "uav_using_rate",
                   "energy_rate_kj", "collisions_per_episode")


class RecordError(ValueError):
    """A record that cannot be trusted: names the file and what is wrong with it."""

    def __init__(self, path, problem: str):
        self.path, self.problem = Path(path), problem
        super().__init__(f"run record {self.path}: {problem}")

    def __reduce__(self):  # pickles (a process pool sends exceptions back)
        return type(self), (self.path, self.problem)


# %% [markdown]
# ## Blocks
#
# The block length is the smallest that keeps a record within `RECORD_ROWS` rows, rounded up to a
# divisor of the phase length, so that a block lies inside one phase visit (a run with a fixed phase
# has no switch and takes the length as it is).

# %%
#| export
def record_block(config: TrainConfig) -> int:
    """Iterations per record row for `config`."""
    target = max(1, math.ceil(config.iterations / RECORD_ROWS))
    if config.fixed_phase is not None:
        return target
    length = config.phase_length_iters
    return min((d for d in range(target, length + 1) if length % d == 0), default=length)


def record_frame(metrics: pd.DataFrame, block: int) -> pd.DataFrame:
    """The record's table from a run's per-iteration log: timing columns dropped, rows averaged
    over blocks of `block` iterations (episode columns weighted by episodes, `episodes` summed,
    `env_steps` at the block's end, `switch` if any iteration switched), floats as float32, and
    `iterations`, the number of iterations in each row."""
    m = metrics.drop(columns=[c for c in TIMING_COLUMNS if c in metrics.columns]).reset_index(drop=True)
    key = m.iteration // block
    groups = m.groupby(key, sort=True)
    out = groups.mean(numeric_only=True)
    episodes = groups.episodes.sum()
    for column in EPISODE_COLUMNS:
        if column in m:
            total = (m[column].fillna(0.0) * m.episodes).groupby(key).sum()
            out[column] = (total / episodes.where(episodes > 0)).astype(float)
    out["episodes"] = episodes
    for column, how in (("iteration", "first"), ("phase", "first"), ("env_steps", "last"), ("agent_steps", "last"),
                        ("switch", "any")):
        if column in m:
            out[column] = getattr(groups[column], how)()
    out["iterations"] = groups.size()
    out = out[[c for c in m.columns if c in out.columns] + ["iterations"]].reset_index(drop=True)
    for column in out.columns:
        if out[column].dtype == np.float64:
            out[column] = out[column].astype(np.float32)
    return out


# %% [markdown]
# ## Writing and checking a record
#
# A marker is trusted only when it checks against itself: its `run` is its file's name, its `config`
# hashes to its `config_hash`, no key is missing, and every stamp the writer derived from the
# config (`numerics`, `iterations`, `block`, `rows`, `env_steps`) is what the config gives. A marker
# edited by hand (a run renamed, a seed changed, `env_steps` doubled) is refused, naming the field,
# rather than read as something it is not; `read_record` also checks the log's rows and its last
# `env_steps` against the marker.

# %%
#| export
def record_files(records_dir, scale: str, run_name: str) -> dict:
    """{"data", "actor", "marker", "timing"}: the paths of one run's record."""
    base = Path(records_dir) / check_scale(scale)
    return {"data": base / f"{run_name}.parquet", "actor": base / f"{run_name}.actor.parquet",
            "marker": base / f"{run_name}.json", "timing": base / f"{run_name}.timing.json"}


def parquet_bytes(frame: pd.DataFrame) -> bytes:
    """`frame` as the compact parquet file of a record (zstd, no pandas schema, no column
    statistics); the theory records of appendix 08c use it too."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    buffer = io.BytesIO()
    # No pandas schema and no column statistics: together they were about half of a small record.
    table = pa.Table.from_pandas(frame, preserve_index=False).replace_schema_metadata(None)
    pq.write_table(table, buffer, compression="zstd", compression_level=9, write_statistics=False)
    return buffer.getvalue()


def _actor_frame(state: dict) -> pd.DataFrame:
    return pd.DataFrame({"name": list(state), "shape": [",".join(map(str, t.shape)) for t in state.values()],
                         "values": [t.detach().cpu().float().contiguous().numpy().astype("<f4").tobytes()
                                    for t in state.values()]})


def write_record(run_dir, scale: str, records_dir=RECORDS_DIR) -> Path:
    """Write the record of the finished run in `run_dir` (trained at `scale`); returns its marker.
    RecordError when the run is not finished."""
    from pemamoe.runs import UNRECORDED_PROCESSOR, load_checkpoint  # the checkpoint: only for the final actor

    run_dir = Path(run_dir)
    config = read_config(run_dir / "config.json", TrainConfig)
    done = verify_done(run_dir, config)
    if not done:
        raise RecordError(run_dir, "is not a finished run (no done.json): only finished runs have records")
    name = config.run_name()  # the sweep's folder name; a folder elsewhere gets the same record
    files = record_files(records_dir, scale, name)
    metrics = read_parquet(run_dir / "metrics.parquet")
    block = record_block(config)
    data = parquet_bytes(record_frame(metrics, block))
    ckpt = load_checkpoint(run_dir / "checkpoint.pt", config, iteration=config.iterations, resuming=False)
    actor = parquet_bytes(_actor_frame(ckpt["actor"]))
    atomic_write_bytes(files["data"], data)
    atomic_write_bytes(files["actor"], actor)
    processors = done.get("processors", [UNRECORDED_PROCESSOR])  # of the training whose bytes these are
    timing = read_json(files["timing"]) if files["timing"].exists() else None
    if timing is None:  # a measurement of the training that made the record first
        member_s = float(((metrics.rollout_time + metrics.update_time) / metrics.population).sum())
        atomic_write_json(files["timing"], {"member_compute_s": member_s, "wall_time_s": float(metrics.wall_time.max()),
                                            "population": int(metrics.population.iloc[-1]), "processors": processors,
                                            "note": "measured; differs between trainings of the same run"})
    elif timing.get("processors") != processors:  # retrained: the bytes' processors
        atomic_write_json(files["timing"], {**timing, "processors": processors})
    marker = {"format": RECORD_FORMAT, "run": name, "scale": scale, "config": config.to_dict(),
              "config_hash": config.config_hash(), "numerics": training_numerics(), "iterations": int(config.iterations),
              "block": block, "rows": int(-(-config.iterations // block)), "env_steps": int(metrics.env_steps.max()),
              "sha256": {"data": hashlib.sha256(data).hexdigest(), "actor": hashlib.sha256(actor).hexdigest()}}
    return atomic_write_json(files["marker"], marker)


MARKER_KEYS = ("format", "run", "scale", "config", "config_hash", "numerics", "iterations", "block", "rows",
               "env_steps", "sha256")


def read_marker(marker_path) -> dict:
    """A record's marker, checked against itself (every read of a marker goes through here).
    RecordError, naming the field, when it is of another format, lacks a key, names another run
    than its file, or its config does not hash to its config_hash (an edited config)."""
    path = Path(marker_path)
    try:
        marker = read_json(path)
    except Exception as err:  # noqa: BLE001 - any unreadable marker is named
        raise RecordError(path, f"cannot be read ({err})") from None
    if not isinstance(marker, dict):
        raise RecordError(path, f"holds a {type(marker).__name__}, not a JSON object")
    if marker.get("format") != RECORD_FORMAT:
        raise RecordError(path, f"has format {marker.get('format')!r}, this code reads {RECORD_FORMAT}")
    missing = [key for key in MARKER_KEYS if key not in marker]
    if missing:
        raise RecordError(path, f"lacks the field(s) {', '.join(missing)}")
    seals = marker["sha256"]
    if not (isinstance(seals, dict) and all(isinstance(seals.get(k), str) for k in ("data", "actor"))):
        raise RecordError(path, f"has sha256 {seals!r}, not {{'data': <hex>, 'actor': <hex>}}")
    if marker["run"] != path.stem:  # else the figures would read another run's files under this label
        raise RecordError(path, f"has run {marker['run']!r}, not its file's name {path.stem!r}")
    numerics, current = marker["numerics"], training_numerics()
    if type(numerics) is not int or not 1 <= numerics <= current:  # the version the config is hashed under
        raise RecordError(path, f"has numerics {numerics!r}, but its config gives a version from 1 to {current} "
                          "(this code's TRAINING_NUMERICS; marker edited?)")
    try:
        config = TrainConfig.from_dict(marker["config"])
        config_hash = config.config_hash(numerics)  # its identity under the arithmetic that made it
    except (TypeError, ValueError, AttributeError) as err:
        raise RecordError(path, f"has a config that is not a TrainConfig ({err})") from None
    if config_hash != marker["config_hash"]:
        raise RecordError(path, f"has config_hash {marker['config_hash']!r}, but its config hashes to "
                          f"{config_hash!r} (config edited?)")
    if config.run_name(numerics) != marker["run"]:  # a record renamed as a whole
        raise RecordError(path, f"has run {marker['run']!r}, but its config is run {config.run_name(numerics)!r}")
    block = record_block(config)  # the stamps the writer derived from the config: each checked against it
    derived = {"iterations": config.iterations, "block": block,
               "rows": -(-config.iterations // block), "env_steps": config.total_env_steps}
    for key, value in derived.items():
        if marker[key] != value or type(marker[key]) is not int:
            raise RecordError(path, f"has {key} {marker[key]!r}, but its config gives {value!r} (marker edited?)")
    return marker


def verify_record(marker_path, config: TrainConfig | None = None) -> dict | None:
    """The record's marker after checking it (`read_marker`) and its files; None when there is no
    marker. RecordError when it is damaged, of another config, or a file differs."""
    path = Path(marker_path)
    if not path.exists():
        return None
    marker = read_marker(path)
    if config is not None and marker["config_hash"] != config.config_hash(marker["numerics"]):
        raise RecordError(path, f"belongs to config hash {marker['config_hash']!r}, not the requested "
                          f"{config.config_hash(marker['numerics'])!r} (its hash under numerics {marker['numerics']})")
    for kind, suffix in (("data", ".parquet"), ("actor", ".actor.parquet")):
        file = path.with_name(path.stem + suffix)
        if not file.is_file():
            raise RecordError(path, f"seals {file.name}, which is missing")
        if hashlib.sha256(file.read_bytes()).hexdigest() != marker["sha256"][kind]:
            raise RecordError(path, f"{file.name} differs from the file it sealed (changed or damaged)")
    return marker


def _existing_record(marker_path) -> dict:
    marker = verify_record(marker_path)
    if marker is None:
        raise RecordError(marker_path, "is missing: train the run (python -m pemamoe sweep ...) to write it")
    return marker


def read_record(marker_path) -> tuple:
    """(config dict, per-row frame) of a verified record."""
    marker = _existing_record(marker_path)
    frame = read_parquet(Path(marker_path).with_name(Path(marker_path).stem + ".parquet"))
    last = int(frame["env_steps"].iloc[-1]) if len(frame) and "env_steps" in frame else None
    if len(frame) != marker["rows"] or last != marker["env_steps"]:  # a log sealed under a wrong marker
        raise RecordError(marker_path, f"has rows {marker['rows']} and env_steps {marker['env_steps']}, but its log "
                                       f"has {len(frame)} rows ending at env_steps {last}")
    return marker["config"], frame


def read_record_actor(marker_path):
    """The final actor of a recorded run, as a single-run module (float32)."""
    import torch

    from pemamoe.env import observation_dim
    from pemamoe.nets import make_actor

    config = TrainConfig.from_dict(_existing_record(marker_path)["config"])  # the marker alone: no log read
    actor = make_actor(config.method_spec().network, observation_dim(config.env_config()), 2, config.net)
    table = read_parquet(Path(marker_path).with_name(Path(marker_path).stem + ".actor.parquet"))
    state = {row.name: torch.from_numpy(np.frombuffer(row.values, dtype="<f4").copy()).reshape(
        [int(s) for s in row.shape.split(",") if s]) for row in table.itertuples()}
    actor.load_state_dict(state)
    return actor


def record_timing(marker_path) -> dict:
    """The measured compute of the training that first made the record, and the processors of the
    training whose bytes it holds ({} if none; records before December 2026 name no processors)."""
    path = Path(marker_path).with_name(Path(marker_path).stem + ".timing.json")
    if not path.exists():
        return {}
    try:
        return read_json(path)
    except RunFolderError as err:  # a record's file, not a run folder's: nothing to delete but the file
        raise RecordError(path, f"{err.problem}; it holds only the measured compute and processors of the record "
                                f"{Path(marker_path).name}: restore it (git checkout -- {path}) or delete it") from None


def committed_records_mb(records_dir=RECORDS_DIR) -> dict:
    """{scale: megabytes} of the record files under records_dir (every scale but ci is committed)."""
    out = {}
    for folder in sorted(p for p in Path(records_dir).glob("*") if p.is_dir()):
        out[folder.name] = sum(f.stat().st_size for f in folder.iterdir() if f.is_file()) / 1e6
    return out


# %% [markdown]
# ## Finding a config's record, across numerics versions
#
# A record is named by its run, `<method>-s<seed>-<hash>`, and the hash carries the version of the
# training arithmetic, `TRAINING_NUMERICS` (appendix 07c). A bump of that version (a faster update
# whose floats round differently, say) renames every config, yet the records already committed
# stay what they are: evidence made by the commit that made them, stamped with their version,
# like a record made on another processor. So whatever *reads* a config's record asks
# `find_record`, which tries the config's name under the current version first and then under each
# older one (`TrainConfig.run_names()`), and takes the first marker that exists: the newest version
# of the config's records wins, and a damaged newest record is refused by the reader rather than
# quietly passed over for an older one. `read_marker` checks a marker against the version it is
# stamped with (its config must hash to its `config_hash` under that version; a version newer than
# the code's is refused), so an old record reads exactly as it did under the code that wrote it.
#
# Everything that decides what to read or to train goes through it: `record_marker` and with it
# `pending_runs` (the sweep's "already done" test, `sweep --status` and the figures' first sweep),
# `sweep_records` (what the notebooks read) and notebook 07's demonstration. What *writes* stays at
# the current version: `write_record` names and stamps a record with the code's own version, and a
# run folder in the results cache is named the same way, so after a bump a fresh training, or a
# retraining with `retrain=True`, lands beside the old record without replacing it, and from then
# on is the one read. An unfinished run of an older version is never resumed (appendix 07b): its
# folder and its portable state stay where they are, and the sweep trains the config afresh under
# its new name, saying so. Code that lists records by name instead (appendix 10b's campaign logs)
# drops those `superseded` by a newer version's record of the same config.

# %%
#| export
def find_record(records_dir, scale: str, config: TrainConfig) -> Path:
    """The marker of `config`'s record at `scale`: the first that exists of its names under the
    current numerics version and then each older one (`TrainConfig.run_names()`), so the newest
    version wins; the current version's path when none exists (what a new record will be)."""
    names = config.run_names()
    for name in names.values():
        marker = record_files(records_dir, scale, name)["marker"]
        if marker.exists():
            return marker
    return record_files(records_dir, scale, next(iter(names.values())))["marker"]


def superseded(marker_path) -> bool:
    """Whether a newer numerics version's record of the same config lies beside this record (its
    marker checked first, `read_marker`): then `find_record` reads that one, never this one."""
    path = Path(marker_path)
    marker = read_marker(path)
    config = TrainConfig.from_dict(marker["config"])
    return any(n > marker["numerics"] and path.with_name(f"{name}.json").exists()
               for n, name in config.run_names().items())


# %% [markdown]
# ## Work in progress that moves: portable state
#
# A record exists only once a run has finished, and a medium population trains for hours: longer
# than some machines live. So a sweep stopped by `--hours` (appendix 09c) also leaves, for each
# run it did not finish, a **portable state** beside the records, in
# `records/<scale>/in_progress/`, which is committed with them. Everything that decides the next
# numbers (parameters, optimizer moments, generators, the environments' state, the per-iteration
# log that the record is computed from) travels, so a run resumed from it on another machine
# computes the same bits, and its record is byte-identical to an uninterrupted run's. The
# per-episode rows stay behind: raw data that no record reads.
#
# A campaign commits a new portable state of every unfinished run at every stop, and git keeps
# every version. So a portable state is cut in two, to make a commit of an advanced state add only
# what changed:
#
# * `<run>.pt.zst`, the **state**: the run's sealed checkpoint, zstd-compressed, without any log
#   rows, and with a list of the chunks that hold its metric rows (their row ranges and sha256);
# * `<run>.rows-<first>-<last>-<sha>.zst`, the **chunks**: the per-iteration log rows `first` to
#   `last`, each chunk written once, never rewritten, and named by its content. A later stop keeps
#   the chunks the state before it listed (after checking that they hold the very rows the run
#   has) and writes one chunk of the rows logged since.
#
# The state is small because its environments' random buffers travel as where their generators
# drew them, and the rows are stored column by column: appendix 09h has both codecs.
#
# On the next machine the sweep rebuilds each portable state into a checkpoint in its run folder
# (unless that folder's own checkpoint is further along) and resumes it. The folder then also gets
# a `moved.json` saying from which iteration on its `episodes.parquet` holds episodes: the raw
# episode log of a moved run is partial, and says so. When a run finishes, its record is written
# and its portable state deleted, chunks too; `in_progress/` is empty when a campaign is done.
# Restoring one checks it first (a portable state, its checkpoint's sha256 seal, the run it is
# named for, every chunk present with the sha256 the state sealed, the rows contiguous, the
# buffers redrawn to their sha256), and so does `sweep --status` before it reports the iteration
# one has reached: a damaged or missing file is refused in one line naming it, never counted as
# progress. A portable state of format 1 (one file, the whole checkpoint but the episode rows, as
# the campaign committed them until December 2026) is read as before; the next stop of its run
# writes format 2. `benchmarks/bench_portable.py` measures what a stop adds to git.

# %%
#| export
PORTABLE_DIR = "in_progress"  # records/<scale>/in_progress/: unfinished runs (committed while a campaign runs)
PORTABLE_FORMAT = 2
# a state: this magic, the checkpoint's size (8 bytes, little endian), its zstd bytes; format 1 had the same layout
_PORTABLE_MAGIC = b"pemamoe-portable-2\n"
_PORTABLE_MAGIC_1 = b"pemamoe-portable-1\n"  # format 1: the whole checkpoint but its episode rows
_ROWS_MAGIC = b"pemamoe-rows-1\n"  # a chunk of rows: the same layout
PORTABLE_ZSTD_LEVEL = 19  # written once per stop, read once per machine: the slow, small end of zstd


def portable_state_path(records_dir, scale: str, run_name: str) -> Path:
    """Where the portable state of the unfinished run `run_name` lives."""
    return Path(records_dir) / check_scale(scale) / PORTABLE_DIR / f"{run_name}.pt.zst"


def portable_chunk_files(records_dir, scale: str, run_name: str) -> list:
    """The rows chunks of `run_name` in its scale's in_progress folder (listed or not), sorted."""
    return sorted(portable_state_path(records_dir, scale, run_name).parent.glob(f"{run_name}.rows-*.zst"))


def _zstd_pack(magic: bytes, data: bytes) -> bytes:
    import pyarrow as pa

    return magic + len(data).to_bytes(8, "little") + pa.Codec("zstd", PORTABLE_ZSTD_LEVEL).compress(data, asbytes=True)


def _zstd_unpack(path, magics) -> tuple:
    """(the magic, the bytes) of a file written by `_zstd_pack` with one of `magics`."""
    import pyarrow as pa

    raw = Path(path).read_bytes()
    magic = next((m for m in magics if raw.startswith(m)), None)
    if magic is None or len(raw) <= len(magic) + 8:
        kind = "portable state (no pemamoe-portable header)" if _PORTABLE_MAGIC in magics else "rows chunk"
        raise RecordError(path, f"is not a {kind}{_PORTABLE_HINT}")
    size = int.from_bytes(raw[len(magic):len(magic) + 8], "little")
    try:
        return magic, pa.Codec("zstd").decompress(raw[len(magic) + 8:], decompressed_size=size, asbytes=True)
    except (pa.ArrowException, OSError) as err:
        raise RecordError(path, f"cannot be decompressed ({type(err).__name__}: {err}){_PORTABLE_HINT}") from None


def read_portable_state(path) -> bytes:
    """The sealed checkpoint bytes of a portable state's state file (format 2: without its rows,
    which its chunks hold; format 1: the whole checkpoint but the episode rows). RecordError when
    the file is not one."""
    return _zstd_unpack(path, (_PORTABLE_MAGIC, _PORTABLE_MAGIC_1))[1]


# the end of the message of a portable state that cannot be trusted
_PORTABLE_HINT = ("; restore it from git (git checkout -- <the file>), or delete it to train the run on from this "
                  "machine's own checkpoint, or from the start")
# the end of the message of a chunk that is missing or damaged
_CHUNK_HINT = ("; restore it from git (git checkout -- <the file>), or delete the run's portable state and chunks "
               "to train it on from this machine's own checkpoint, or from the start")


# %% [markdown]
# Writing, checking, restoring and dropping a portable state.

# %%
#| export
def _chunk_name(run_name: str, first: int, last: int, sha: str) -> str:
    return f"{run_name}.rows-{first:06d}-{last:06d}-{sha[:12]}.zst"


def _chunk_rows(file: Path, entry: dict, source: Path) -> list:
    """The rows of the chunk `file` that the state `source` lists as `entry`, checked."""
    from pemamoe.portable_codecs import decode_rows

    if not file.is_file():
        raise RecordError(file, f"is missing: the portable state {source.name} holds its rows {entry['first']} to "
                          f"{entry['last']} there{_CHUNK_HINT}")
    data = _zstd_unpack(file, (_ROWS_MAGIC,))[1]
    if hashlib.sha256(data).hexdigest() != entry["sha256"]:
        raise RecordError(file, f"differs from the rows chunk that {source.name} sealed (changed or damaged){_CHUNK_HINT}")
    rows = decode_rows(data)
    if len(rows) != entry["last"] - entry["first"] + 1:
        raise RecordError(file, f"holds {len(rows)} rows, not rows {entry['first']} to {entry['last']}{_CHUNK_HINT}")
    return rows


def _kept_chunks(path: Path, run_name: str, rows: list) -> list:
    """The chunks of the portable state at `path` that hold, intact, rows this run has too (from
    its first row on, in order): what a new state of the run can list again without rewriting."""
    from pemamoe.portable_codecs import encode_rows
    from pemamoe.runs import RunFolderError

    if not path.is_file():
        return []
    try:
        fmt, _, ck = _unpacked_checkpoint(path)
        same_run = TrainConfig.from_dict(ck["config"]).run_name() == run_name
        listed = ck["portable"]["chunks"] if fmt == PORTABLE_FORMAT and same_run else []
    except (RecordError, RunFolderError, KeyError, TypeError, ValueError):
        return []  # none, of format 1, or damaged: the new state writes its rows afresh
    kept = []
    for entry in listed:
        first, last = entry["first"], entry["last"]
        if first != (kept[-1]["last"] + 1 if kept else 0) or last >= len(rows):
            break
        try:
            same = (hashlib.sha256(encode_rows(rows[first:last + 1])).hexdigest() == entry["sha256"]
                    and _chunk_rows(path.parent / entry["file"], entry, path) is not None)
        except RecordError:
            same = False
        if not same:
            break
        kept.append(entry)
    return kept


def _unpacked_checkpoint(source: Path) -> tuple:
    """(its format, its bytes, the checkpoint) of a portable state's state file, the seal checked
    (a RunFolderError names a temporary file: callers name `source`)."""
    import tempfile

    from pemamoe.runs import load_checkpoint

    magic, data = _zstd_unpack(source, (_PORTABLE_MAGIC, _PORTABLE_MAGIC_1))
    with tempfile.TemporaryDirectory() as scratch:
        unpacked = Path(scratch) / "checkpoint.pt"
        unpacked.write_bytes(data)
        ck = load_checkpoint(unpacked)  # its seal is checked: a damaged portable state is refused here
    return (PORTABLE_FORMAT if magic == _PORTABLE_MAGIC else 1), data, ck


def write_portable_state(run_dir, scale: str, records_dir=RECORDS_DIR) -> Path | None:
    """Pack the unfinished run in `run_dir` into its portable state: the state file (its checkpoint
    without log rows, its random buffers compacted, sealed, zstd-compressed) and a chunk of the
    metric rows that the run's previous portable state does not hold already; returns the state's
    path, or None when the run is finished or has no checkpoint yet (then there is nothing to
    carry). Chunks no longer listed are deleted after the state is in place."""
    import torch

    from pemamoe.bookkeeping import RowLog
    from pemamoe.portable_codecs import compact_env_state, encode_rows
    from pemamoe.runs import load_checkpoint, seal_checkpoint

    run_dir = Path(run_dir)
    config = read_config(run_dir / "config.json", TrainConfig)
    if verify_done(run_dir, config) or not (run_dir / "checkpoint.pt").exists():
        return None
    ck = load_checkpoint(run_dir / "checkpoint.pt", config)
    name = config.run_name()
    path = portable_state_path(records_dir, scale, name)
    rows = list(RowLog.from_checkpoint(ck["metrics_rows"]))
    chunks = _kept_chunks(path, name, rows)
    first = chunks[-1]["last"] + 1 if chunks else 0
    if first < len(rows):  # the rows logged since: one new chunk, named by its content
        data = encode_rows(rows[first:])
        entry = {"first": first, "last": len(rows) - 1, "sha256": hashlib.sha256(data).hexdigest()}
        entry["file"] = _chunk_name(name, first, len(rows) - 1, entry["sha256"])
        atomic_write_bytes(path.parent / entry["file"], _zstd_pack(_ROWS_MAGIC, data))
        chunks.append(entry)
    state = {**ck, "metrics_rows": [], "episode_rows": [], "env": compact_env_state(ck["env"]),
             "portable": {"format": PORTABLE_FORMAT, "metrics_rows": len(rows), "chunks": chunks}}
    with atomic_path(path) as tmp:  # format and numerics stamps kept as the trainer wrote them
        torch.save(state, tmp)
        seal_checkpoint(tmp)
        tmp.write_bytes(_zstd_pack(_PORTABLE_MAGIC, tmp.read_bytes()))
    listed = {entry["file"] for entry in chunks}
    for stale in portable_chunk_files(records_dir, scale, name):
        if stale.name not in listed:
            stale.unlink(missing_ok=True)
    return path


def _open_portable_state(source: Path, run_name: str, rebuild: bool = True) -> tuple:
    """(the checkpoint's bytes, the checkpoint, its TrainConfig) of the portable state `source`,
    rebuilt from its chunks, after the checks a resume makes: a portable state, its checkpoint's
    seal (sha256) intact, a checkpoint of the run `run_name`, its chunks present, intact and
    contiguous, its buffers redrawn. RecordError naming the file at fault otherwise. rebuild=False:
    the same checks, but no checkpoint bytes (None) for a format-2 state: what a status needs."""
    import tempfile

    import torch

    from pemamoe.bookkeeping import RowLog
    from pemamoe.portable_codecs import expand_env_state
    from pemamoe.runs import RunFolderError, seal_checkpoint

    try:
        fmt, data, ck = _unpacked_checkpoint(source)
    except RunFolderError as err:
        raise RecordError(source, err.problem + _PORTABLE_HINT) from None
    try:
        config = TrainConfig.from_dict(ck["config"])
    except (TypeError, ValueError, KeyError) as err:
        raise RecordError(source, f"holds no valid TrainConfig ({type(err).__name__}: {err}){_PORTABLE_HINT}") from None
    if config.run_name() != run_name:
        raise RecordError(source, f"holds run {config.run_name()!r}, not {run_name!r}")
    if fmt == 1:
        return data, ck, config  # the checkpoint as it is
    manifest = ck.pop("portable", None)
    if not isinstance(manifest, dict) or manifest.get("format") != PORTABLE_FORMAT:
        raise RecordError(source, f"has no chunk list of format {PORTABLE_FORMAT}{_PORTABLE_HINT}")
    rows = []
    for entry in manifest["chunks"]:
        if entry["first"] != len(rows):
            raise RecordError(source, f"lists {entry['file']} from row {entry['first']}, but its chunks before it end "
                              f"at row {len(rows) - 1}{_PORTABLE_HINT}")
        rows += _chunk_rows(source.parent / entry["file"], entry, source)
    if len(rows) != manifest["metrics_rows"]:
        raise RecordError(source, f"lists chunks of {len(rows)} rows, but sealed {manifest['metrics_rows']}{_PORTABLE_HINT}")
    try:
        env = expand_env_state(ck["env"])
    except ValueError as err:  # buffers that redraw to other numbers
        raise RecordError(source, f"{err}{_PORTABLE_HINT}") from None
    ck = {**ck, "metrics_rows": RowLog(rows).packed(), "env": env}
    if not rebuild:
        return None, ck, config
    with tempfile.TemporaryDirectory() as scratch:
        rebuilt = Path(scratch) / "checkpoint.pt"
        torch.save(ck, rebuilt)
        seal_checkpoint(rebuilt)
        return rebuilt.read_bytes(), ck, config


def restore_portable_state(run_dir, scale: str, records_dir=RECORDS_DIR) -> bool:
    """Copy the portable state of `run_dir`'s run (named by the folder) into the folder when the
    folder is not already as far along; returns whether it did. The folder gets `config.json`,
    the checkpoint and `moved.json` (from which iteration on its episode log is complete)."""
    from pemamoe.runs import RunFolderError, load_checkpoint

    run_dir = Path(run_dir)
    source = portable_state_path(records_dir, scale, run_dir.name)
    if not source.exists():
        return False
    data, ck, config = _open_portable_state(source, run_dir.name)
    here = run_dir / "checkpoint.pt"
    if verify_done(run_dir, config):
        return False
    if here.exists():
        try:
            if int(load_checkpoint(here, config)["iteration"]) >= int(ck["iteration"]):
                return False  # this machine's own checkpoint is as far along: it keeps its episode log
        except RunFolderError:
            pass  # a damaged local checkpoint: the portable state replaces it
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(run_dir / "config.json", config.to_dict())
    with atomic_path(here) as tmp:
        tmp.write_bytes(data)
    atomic_write_json(run_dir / "moved.json", {"episodes_from_iteration": int(ck["iteration"]),
                                               "note": "resumed from a portable state: episodes.parquet holds only the "
                                                       "episodes that ended after this iteration"})
    return True


def drop_portable_state(run_name: str, scale: str, records_dir=RECORDS_DIR) -> None:
    """Delete a finished run's portable state and its chunks (its record now carries the run)."""
    portable_state_path(records_dir, scale, run_name).unlink(missing_ok=True)
    for chunk in portable_chunk_files(records_dir, scale, run_name):
        chunk.unlink(missing_ok=True)


def portable_state_progress(records_dir, scale: str, run_name: str) -> tuple | None:
    """(the iteration the portable state of `run_name` has reached, its wall seconds per iteration
    so far, or None before the first), or None when there is no portable state: what `sweep
    --status` reports for a run this machine has not restored yet. The rate is the checkpoint's
    training seconds over its iterations, every session that trained it averaged alike. The state
    is verified as a resume would verify it (seal, run, chunks): a damaged one raises RecordError
    naming the file, rather than reporting an iteration that the sweep would then refuse to resume from."""
    source = portable_state_path(records_dir, scale, run_name)
    if not source.exists():
        return None
    ck = _open_portable_state(source, run_name, rebuild=False)[1]
    iteration = int(ck["iteration"])
    return iteration, (float(ck["elapsed"]) / iteration if iteration else None)


def portable_state_mb(records_dir=RECORDS_DIR) -> dict:
    """{scale: megabytes} of the portable states under records_dir, chunks included."""
    return {folder.parent.name: sum(f.stat().st_size for f in folder.glob("*.zst")) / 1e6
            for folder in sorted(Path(records_dir).glob(f"*/{PORTABLE_DIR}"))}


# %% [markdown]
# ## Reading records back into frames
#
# `load_runs` stacks the records of a list of runs into two tidy frames: the per-iteration log (one
# row per block of iterations in a long run), and the rows in which episodes ended, with each
# metric's mean over those episodes. Each row carries its run's labels, read from **that run's own
# config** (the resolved `TrainConfig` the record holds), never from a marker left by whichever
# experiment asked for the run first: the method, the seed, the phase-controller mechanisms switched
# off, whether a baseline ran the controller, the noise scale γ, a short `variant` ("", "w/o
# lr_drop", "+ noise_injection") and the display `label` of `TrainConfig.label()`. The figures of
# notebook 09 and after read their runs this way; `pemamoe.analysis` re-exports these names.

# %%
#| export
# The columns that label each row of load_runs' frames (one value per run).
RUN_COLUMNS = ("run", "method", "seed", "without", "force_controller", "noise_gamma", "variant", "label")


def run_labels(config: dict, run: str = "") -> dict:
    """The labels of one run, from its config.json (a TrainConfig.to_dict())."""
    from pemamoe.mappo import TrainConfig
    from pemamoe.phase_controller import MECHANISMS

    ctrl = config.get("controller", {})
    force = bool(config.get("force_controller", False))
    try:
        cfg = TrainConfig.from_dict(config)
        enabled, label = cfg.controller_enabled, cfg.label()
    except ValueError:  # a method no loaded plugin registers: describe it from the dict alone
        enabled, label = force, config["method"]
    off = [m for m in MECHANISMS if enabled and not ctrl.get(m, True)]
    on = [m for m in MECHANISMS if enabled and ctrl.get(m, True)]
    variant = ("+ " + "+".join(on) if on else "+ controller") if force else ("w/o " + "+".join(off) if off else "")
    return {"run": run, "method": config["method"], "seed": int(config["seed"]),
            "without": "+".join(off) or "none", "force_controller": force,
            "noise_gamma": float(ctrl.get("noise_gamma", float("nan"))), "variant": variant, "label": label}


# The per-iteration episode means of a record, under the names of the per-episode log
RECORD_EPISODE_COLUMNS = {"episode_return": "return", "coverage": "coverage", "served_users": "served_users",
                          "energy_rate_kj": "energy_rate_kj", "collisions_per_episode": "collisions"}


def load_runs(records) -> tuple:
    """(metrics, episode_means) DataFrames of recorded runs (paths of record markers, appendix
    09d); every row carries RUN_COLUMNS, from the run's own config. metrics: one row per record row
    (an iteration, or a block of them in a long run). episode_means: the rows in which episodes
    ended, with the episode columns under the per-episode log's names (return, coverage, ...) and
    `episodes`, the number that ended there: what the run scores are computed from."""
    metrics, episodes = [], []
    for marker in map(Path, records):
        config, frame = read_record(marker)  # a missing, damaged or foreign record raises, naming it
        label = run_labels(config, marker.stem)
        metrics.append(frame.assign(**label))
        ended = frame[frame.episodes > 0]
        episodes.append(ended[["iteration", "phase", "episodes", *RECORD_EPISODE_COLUMNS]].rename(
            columns=RECORD_EPISODE_COLUMNS).assign(**label))
    return pd.concat(metrics, ignore_index=True), pd.concat(episodes, ignore_index=True)


# %% [markdown]
# ## Demonstration: a ci run and its record
#
# One short run, trained into a temporary folder; its record; the record read back; and the same
# run trained again in a population of two, whose record is byte-identical.

# %%
import tempfile

from pemamoe.mappo import train, train_population

with tempfile.TemporaryDirectory() as tmp:
    tmp = Path(tmp)
    cfg = TrainConfig.for_scale("ci", method="smoe", seed=0, iterations=6)
    train(cfg, tmp / "alone")
    marker = write_record(tmp / "alone", "ci", tmp / "records")
    config_dict, frame = read_record(marker)
    print(f"{marker.name}: {len(frame)} rows x {frame.shape[1]} columns, block {record_block(cfg)}, "
          f"{sum(f.stat().st_size for f in marker.parent.iterdir()) / 1e3:.1f} kB in all")
    train_population([cfg, cfg.replace(seed=1)], [tmp / "pop0", tmp / "pop1"])
    again = write_record(tmp / "pop0", "ci", tmp / "records2")
    same = all((marker.parent / f.name).read_bytes() == f.read_bytes() for f in again.parent.iterdir()
               if not f.name.endswith(".timing.json"))
    print("record of the same run trained in a population: byte-identical" if same else "RECORDS DIFFER")
    assert same
    print(read_record_actor(marker).__class__.__name__, "read back from the record")
