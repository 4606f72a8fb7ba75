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
# # 08c · Appendix: the records of the theory check
#
# Notebook 08's measurements come from a few hundred short trainings of the tracking learner and a
# Monte-Carlo perturbation sweep of a trained actor. They are kept as **records**, like the run
# records of appendix 09d: computed once, committed, and read by every later run of the
# notebook. There are two reasons.
#
# * `make figures` then trains nothing at all, here as in the experiment notebooks.
# * Computing them is **not reproducible across processors**, and reading them is. The learner
#   trains in float32 on torch's CPU kernels, and which kernels run depends on the processor:
#   ATen picks its vectorised kernels by instruction set (AVX2, AVX-512, or none), MKL picks its
#   matrix-product code path likewise. The kernels sum in different orders, so results differ in
#   the last bits, and a PPO loop amplifies that: on one machine, the same 120-iteration run of
#   the learner reached a total regret of 11.126 with ATen's AVX2 kernels, 11.046 with its generic
#   ones (`ATEN_CPU_CAPABILITY=default`) and 10.813 with MKL's compatibility path
#   (`MKL_CBWR=COMPATIBLE`), and differed from the first iteration on. The probes of the actor
#   (float32 forwards, and the argmax that `tie_states` bisects on) and numpy's `tanh` in
#   `mc_l1_distance` (a SIMD implementation chosen by the processor: on an AVX2 machine it
#   differs from the C library's in the last bit for 0.4 % of arguments) depend on the processor
#   in the same way. Threads do not enter: the notebooks run torch with one thread, and each
#   learner job of `run_many` runs alone in a worker with one thread, its results returned in
#   job order, so the number of workers changes nothing.
#
# A record is one experiment of notebook 08 (`noise`, `routing`, `regret`), in
# `records/<scale>/theory/`, under a name that is the experiment's, tagged with the numerics
# versions it was computed under when they are newer than the first records' (below):
#
# * `<name>.json`, the **marker**: `format`, `experiment`, `parameters` and their
#   `parameters_hash`, `tables` (for each table its file, row count and sha256), `values`
#   (the experiment's scalar results, JSON numbers, which read back exactly) with their
#   `values_sha256`, and `made_on` (library versions and the processor, for the record's
#   provenance, not its identity);
# * `<name>.<table>.parquet`, one file per table, written as the run records write theirs;
# * `<name>.timing.json`: how long computing it took, and where (a measurement, not part of
#   the record).
#
# The **parameters** are everything the results depend on: the notebook's sizes and seeds
# (`settings`), the sha256 of the learner jobs (each job's task, learner, network and controller
# configuration, with the defaults in force, so a changed default of `NetConfig` or
# `PhaseControllerConfig` is a change of parameters), and two version numbers: the trainer's
# `TRAINING_NUMERICS` and `THEORY_NUMERICS` below, to be raised when a change of the learner's or
# an experiment's code changes what it computes. Neither the number of workers (see above) nor
# the library versions are parameters: a new torch must not make `make figures` recompute.
#
# `theory_record` serves the notebook: it returns a record's tables and values when the record's
# parameters hash to those asked for; otherwise it computes them, writes the record (tables
# first, marker last, each atomically) and returns what it **reads back**, so the numbers the
# notebook goes on with are always a record's, whether written a moment or a year ago. It looks
# in the scale's own folder first, then in the other scales' folders for a record of the same
# parameters (notebook 08 uses the same sizes at `small` and `medium`, so one committed record
# serves both). A record with other parameters is not used: it is computed again and rewritten,
# with one line saying which parameters differ. A damaged one (unreadable, a field missing, an
# edited parameter or value, a table missing or changed) is refused with a `TheoryRecordError`
# naming the file; delete it, or run with `retrain=True`, which ignores the records and rewrites
# them.
#
# **Across a bump of the numerics.** The two versions are parameters, but they are not treated
# alike. A bump of `TRAINING_NUMERICS` says that the shared training arithmetic (the PPO update,
# `RunAdamW` of 06d, which the learner uses too) now rounds differently; a record computed before it
# is still the evidence of the commit that made it, as a record made on another processor is, and
# the run records of appendix 09d are read across such a bump for the same reason. So the lookup,
# `find_theory_record`, asks first for the parameters as given and then for the same parameters at
# each older training version, newest first, and takes the first record that holds them (at each
# version the scale's own folder first, then the other scales'): after a bump, notebook 08, and with
# it `make figures`, reads the committed records and computes nothing, and once a record of the new
# version exists it wins over the older ones. What is written is named by its own versions: the
# first records (`THEORY_NUMERICS` 1, `TRAINING_NUMERICS` 2, `THEORY_NAME_BASE`) by the experiment
# alone, `noise.json`, a later version with a tag, `noise-n3.json` for training version 3. A
# computation after a bump (a changed setting, or `retrain=True`) therefore lands beside the old
# record and never over it; only a record of the very same versions is rewritten in place, as
# before. A marker must sit under the name its parameters give, so an old record copied over a new
# one's name is refused, and a damaged newest record is refused rather than passed over for an
# older one.
#
# `THEORY_NUMERICS` is not looked across: it is raised when the learner's or an experiment's code
# changes *what* it computes, so an older record answers another question and is not the
# experiment's answer. Notebook 08 computes the experiment again, as for any change of its
# parameters, and says so; but the new record is named `noise-t2.json` and goes beside the old one,
# which stays, byte for byte, readable by its path. Refusing instead would stop `make figures`
# until someone recomputed by hand, and rewriting in place would replace committed evidence with
# one progress line as the only trace; writing beside does neither, and the commit that raises the
# version is the place to commit the new records (and, if wanted, to delete the old ones).
#
# What stays processor-dependent is the analysis that notebook 08 runs on the records, in float64:
# the logarithms and least squares of `fit_power_law` (numpy's `log` has an AVX-512
# implementation, and OpenBLAS chooses its kernels by processor: forcing its generic ones changes
# a two-regressor fit in the sixteenth digit) and the Lipschitz fits. Those differences are in the
# last bits; the notebook prints three decimals and its Markdown tables four significant digits,
# and `round_reported` rounds the tables it writes to six significant digits, so their CSV files
# no longer carry the bits that differ.


# %%
#| default_exp theory_records

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
import math
import time

T0 = time.perf_counter()

# %%
#| export
import hashlib
import json
import platform
import re
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd

from pemamoe.core import REPO_ROOT, SCALES, atomic_write_bytes, atomic_write_json, check_scale, cpu_model
from pemamoe.nets import NetConfig
from pemamoe.records import RecordError, parquet_bytes
from pemamoe.runs import read_json, read_parquet
from pemamoe.toy_tracking import tracker_controller_config
from pemamoe.train_config import training_numerics

THEORY_RECORD_FORMAT = 1
THEORY_NUMERICS = 1  # raise when the learner's or an experiment's code changes what it computes
THEORY_DIR = "theory"  # records/<scale>/theory/<name>.json (+ .<table>.parquet, .timing.json); see theory_record_name
# The numerics versions the first records were made under: a record of these versions (or older ones)
# is named by its experiment alone; a later version adds a tag ("-t2": THEORY_NUMERICS 2, "-n3":
# TRAINING_NUMERICS 3), so a record of a newer version is written beside the older ones, never over them.
THEORY_NAME_BASE = {"theory": 1, "training": 2}
_NAME_TAGS = (("theory", "t"), ("training", "n"))
THEORY_MARKER_KEYS = ("format", "experiment", "parameters", "parameters_hash", "tables", "values", "values_sha256",
                      "made_on")
REPORTED_DIGITS = 6  # significant digits of the tables notebook 08 writes
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


class TheoryRecordError(RecordError):
    """A theory record that cannot be trusted: names the file and what is wrong with it."""

    def __init__(self, path, problem: str):
        super().__init__(path, problem)
        self.args = (f"theory record {self.path}: {problem}",)


def _plain(obj):
    """`obj` as plain JSON values (dict, list, str, int, float, bool, None): tuples and arrays
    become lists, numpy scalars Python ones, dataclasses dicts."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if hasattr(obj, "__dataclass_fields__"):
        return _plain(asdict(obj))
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_plain(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj)
    if obj is None or isinstance(obj, str):
        return obj
    raise TypeError(f"theory record: {type(obj).__name__} {obj!r} is not a JSON value")


def _canonical(obj) -> str:
    return json.dumps(_plain(obj), sort_keys=True, separators=(",", ":"))


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def tracker_job_identity(job) -> dict:
    """What a job of `run_many` computes from: the task, the learner, the network and controller
    configurations they imply (defaults included), the seeds. keep_actor changes nothing computed."""
    problem_cfg, tracker_cfg, problem_seed, seed = job[:4]
    return _plain({"problem": problem_cfg, "problem_seed": problem_seed, "seed": seed, "tracker": tracker_cfg,
                   "net": NetConfig(hidden=tracker_cfg.hidden, n_experts=tracker_cfg.n_experts),
                   "controller": tracker_controller_config(tracker_cfg)})


def theory_parameters(settings: dict, jobs=()) -> dict:
    """The parameters of an experiment: its settings (sizes, seeds), the count and sha256 of its
    learner jobs (`tracker_job_identity`), THEORY_NUMERICS and TRAINING_NUMERICS (`training_numerics()`,
    read at each call)."""
    jobs = list(jobs)
    return _plain({"settings": settings, "jobs": len(jobs),
                   "jobs_sha256": _sha256(_canonical([tracker_job_identity(j) for j in jobs])),
                   "numerics": {"theory": THEORY_NUMERICS, "training": training_numerics()}})


def _numerics(parameters) -> dict:
    """The numerics versions {"theory", "training"} of a record's parameters; THEORY_NAME_BASE's for
    parameters that carry none (a record written by hand, as the tests do)."""
    numerics = parameters.get("numerics") if isinstance(parameters, dict) else None
    numerics = numerics if isinstance(numerics, dict) else {}
    return {key: numerics.get(key, base) for key, base in THEORY_NAME_BASE.items()}


def theory_record_name(experiment: str, numerics: dict | None = None) -> str:
    """The file name (stem) of `experiment`'s record at these numerics versions (a parameters dict
    or {"theory", "training"}; default: this code's): the experiment, tagged with each version above
    THEORY_NAME_BASE, so "noise" up to THEORY_NUMERICS 1 and TRAINING_NUMERICS 2, "noise-n3" under
    TRAINING_NUMERICS 3, "noise-t2-n3" under both bumps."""
    if not _NAME.match(str(experiment)):
        raise ValueError(f"theory record: experiment must match {_NAME.pattern}, got {experiment!r}")
    if numerics is None:
        numerics = {"theory": THEORY_NUMERICS, "training": training_numerics()}
    versions = _numerics(numerics if "numerics" in numerics else {"numerics": numerics})
    for key, _ in _NAME_TAGS:
        if not (isinstance(versions[key], int) and not isinstance(versions[key], bool) and versions[key] >= 1):
            raise ValueError(f"theory record: numerics.{key} must be an int >= 1, got {versions[key]!r}")
    return str(experiment) + "".join(f"-{tag}{versions[key]}" for key, tag in _NAME_TAGS
                                     if versions[key] > THEORY_NAME_BASE[key])


def theory_parameters_at(parameters: dict, training: int) -> dict:
    """`parameters` as they were asked under TRAINING_NUMERICS `training`: the same settings, jobs
    and THEORY_NUMERICS, another training version (what a record of that version holds)."""
    return _plain({**parameters, "numerics": {**parameters["numerics"], "training": training}})


def _lookup_parameters(parameters: dict) -> list:
    """The parameters whose record answers `parameters`, newest training version first: the asked
    ones, then the same at each older TRAINING_NUMERICS (a record is the evidence of the commit that
    made it; a bump of the training arithmetic leaves it readable). Parameters without a training
    version (or THEORY_NUMERICS, which is never looked up across) have only themselves."""
    training = parameters.get("numerics", {}).get("training") if isinstance(parameters.get("numerics"), dict) else None
    if not (isinstance(training, int) and not isinstance(training, bool) and training >= 1):
        return [_plain(parameters)]
    return [theory_parameters_at(parameters, v) for v in range(training, 0, -1)]


def parameters_hash(parameters: dict) -> str:
    """12 hex digits identifying a record's parameters."""
    return _sha256(_canonical(parameters))[:12]


def theory_record_path(records_dir, scale: str, experiment: str, numerics: dict | None = None) -> Path:
    """The marker of one experiment's record at `scale` and these numerics versions (a parameters
    dict or {"theory", "training"}; default: this code's), named by `theory_record_name`."""
    return Path(records_dir) / check_scale(scale) / THEORY_DIR / f"{theory_record_name(experiment, numerics)}.json"


def _table_path(marker_path: Path, name: str) -> Path:
    return marker_path.with_name(f"{marker_path.stem}.{name}.parquet")


def _timing_path(marker_path: Path) -> Path:
    return marker_path.with_name(f"{marker_path.stem}.timing.json")


def _differences(a, b, prefix: str = "") -> list:
    """Dotted keys at which two parameter dicts differ."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return [] if a == b else [prefix or "(all)"]
    out = []
    for key in sorted(set(a) | set(b)):
        name = f"{prefix}.{key}" if prefix else key
        out += [name] if (key in a) != (key in b) else _differences(a[key], b[key], name)
    return out


def _made_on() -> dict:
    import torch

    return {"cpu": cpu_model(), "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
            "pandas": pd.__version__}


def read_theory_marker(marker_path) -> dict:
    """A theory record's marker, checked against itself: TheoryRecordError (naming the file) when it
    cannot be read, is of another format, lacks a field, or its parameters or values were edited."""
    path = Path(marker_path)
    try:
        marker = read_json(path)
    except Exception as err:  # noqa: BLE001 - any unreadable marker is named
        raise TheoryRecordError(path, f"cannot be read ({getattr(err, 'problem', err)})") from None
    if not isinstance(marker, dict):
        raise TheoryRecordError(path, f"holds a {type(marker).__name__}, not a JSON object")
    if marker.get("format") != THEORY_RECORD_FORMAT:
        raise TheoryRecordError(path, f"has format {marker.get('format')!r}, this code reads {THEORY_RECORD_FORMAT}")
    missing = [key for key in THEORY_MARKER_KEYS if key not in marker]
    if missing:
        raise TheoryRecordError(path, f"lacks the field(s) {', '.join(missing)}")
    if parameters_hash(marker["parameters"]) != marker["parameters_hash"]:
        raise TheoryRecordError(path, f"has parameters_hash {marker['parameters_hash']!r}, but its parameters hash to "
                                f"{parameters_hash(marker['parameters'])!r} (parameters edited?)")
    try:
        name = theory_record_name(marker["experiment"], marker["parameters"])
    except ValueError as err:
        raise TheoryRecordError(path, str(err).removeprefix("theory record: ")) from None
    if name != path.stem:
        numerics = _numerics(marker["parameters"])
        raise TheoryRecordError(path, f"is the record of {marker['experiment']!r} at THEORY_NUMERICS {numerics['theory']}"
                                f" and TRAINING_NUMERICS {numerics['training']}, so named {name!r}, not of its file's "
                                f"name {path.stem!r}")
    if _sha256(_canonical(marker["values"])) != marker["values_sha256"]:
        raise TheoryRecordError(path, "has values that differ from the ones it sealed (values_sha256; edited?)")
    tables = marker["tables"]
    if not (isinstance(tables, dict) and all(_NAME.match(k) and isinstance(v, dict) and isinstance(v.get("sha256"), str)
                                             for k, v in tables.items())):
        raise TheoryRecordError(path, "has tables that are not {name: {'sha256': <hex>, ...}}")
    return marker


def verify_theory_record(marker_path, parameters: dict | None = None) -> dict | None:
    """The marker of a theory record after checking it and its tables; None when there is no
    marker. TheoryRecordError when it is damaged, or made with other parameters than `parameters`."""
    path = Path(marker_path)
    if not path.exists():
        return None
    marker = read_theory_marker(path)
    if parameters is not None and marker["parameters_hash"] != parameters_hash(parameters):
        diff = _differences(marker["parameters"], _plain(parameters))
        raise TheoryRecordError(path, f"was made with other parameters (hash {marker['parameters_hash']}, not "
                                f"{parameters_hash(parameters)}; they differ in {', '.join(diff[:4]) or '?'})")
    for name, table in marker["tables"].items():
        file = _table_path(path, name)
        if not file.is_file():
            raise TheoryRecordError(file, f"is missing (its marker {path.name} seals it)")
        if hashlib.sha256(file.read_bytes()).hexdigest() != table["sha256"]:
            raise TheoryRecordError(file, f"differs from the file its marker {path.name} sealed (changed or damaged)")
    return marker


def read_theory_record(marker_path, parameters: dict | None = None) -> tuple:
    """(tables {name: DataFrame}, values dict) of a verified theory record (see verify_theory_record);
    TheoryRecordError when it is missing."""
    path = Path(marker_path)
    marker = verify_theory_record(path, parameters)
    if marker is None:
        raise TheoryRecordError(path, "is missing: run notebook 08 to compute and write it")
    return {name: read_parquet(_table_path(path, name)) for name in marker["tables"]}, marker["values"]


def write_theory_record(marker_path, parameters: dict, tables: dict, values: dict | None = None,
                        compute_s: float | None = None) -> Path:
    """Write one experiment's record: every table (a DataFrame with a default index) as parquet,
    then the marker that seals them, each atomically; `compute_s` goes to the timing file. Tables of
    an earlier record of the experiment that this one has not are removed. Returns the marker."""
    path = Path(marker_path)
    experiment = path.stem.split("-")[0]
    if theory_record_name(experiment, parameters) != path.stem:
        raise ValueError(f"theory record: a record of {experiment!r} with these parameters is named "
                         f"{theory_record_name(experiment, parameters)!r}, not {path.stem!r}")
    values = _plain(values or {})
    seals = {}
    for name, frame in tables.items():
        if not _NAME.match(str(name)):
            raise ValueError(f"theory record: table names must match {_NAME.pattern}, got {name!r}")
        if not isinstance(frame, pd.DataFrame):
            raise TypeError(f"theory record: table {name!r} is a {type(frame).__name__}, not a DataFrame")
        if not frame.index.equals(pd.RangeIndex(len(frame))):
            raise ValueError(f"theory record: table {name!r} must have the default index 0..n-1 (reset_index)")
        if not all(isinstance(c, str) for c in frame.columns):
            raise ValueError(f"theory record: table {name!r} has column names that are not strings")
        data = parquet_bytes(frame)
        atomic_write_bytes(_table_path(path, name), data)
        seals[name] = {"file": _table_path(path, name).name, "rows": int(len(frame)),
                       "sha256": hashlib.sha256(data).hexdigest()}
    marker = {"format": THEORY_RECORD_FORMAT, "experiment": experiment, "parameters": _plain(parameters),
              "parameters_hash": parameters_hash(parameters), "tables": seals, "values": values,
              "values_sha256": _sha256(_canonical(values)), "made_on": _made_on()}
    atomic_write_json(path, marker)
    for old in path.parent.glob(f"{path.stem}.*.parquet"):
        if old.name not in {s["file"] for s in seals.values()}:
            old.unlink(missing_ok=True)
    if compute_s is not None:
        atomic_write_json(_timing_path(path), {"compute_s": round(float(compute_s), 1), "cpu": marker["made_on"]["cpu"],
                                               "note": "measured; differs between computations of the same record"})
    return path


def find_theory_record(records_dir, scale: str, experiment: str, parameters: dict) -> Path | None:
    """The marker of the record that answers `parameters`: one of exactly these parameters, else of
    the same at the newest older TRAINING_NUMERICS that has one (`_lookup_parameters`); at each
    version the scale's own record, else another scale's (the parameters, not the scale, say what
    was computed). None when there is none. A damaged marker on the way is refused, not passed over."""
    scales = [scale, *(s for s in SCALES if s != scale)]
    for asked in _lookup_parameters(parameters):
        want = parameters_hash(asked)
        for path in (theory_record_path(records_dir, s, experiment, asked) for s in scales):
            if path.exists() and read_theory_marker(path)["parameters_hash"] == want:
                return path
    return None


def _other_records(folder: Path, experiment: str, own: Path) -> list:
    """The markers of `experiment`'s records of other numerics versions in `folder`."""
    pattern = re.compile(rf"^{experiment}(-t[0-9]+)?(-n[0-9]+)?\.json$")
    return sorted(p for p in folder.glob(f"{experiment}*.json") if pattern.match(p.name) and p != own)


def _shown(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(REPO_ROOT))
    except ValueError:
        return str(path)


def theory_record(records_dir, scale: str, experiment: str, parameters: dict, compute, retrain: bool = False,
                  say=print) -> tuple:
    """(tables, values) of `experiment` with these parameters: read from its record when one
    matches (see find_theory_record), else compute() -> (tables, values), written to the scale's
    record and read back from it. The record written is named by the parameters' numerics versions
    (`theory_record_path`), so after a bump it lies beside the older versions' records, never over
    them. retrain: compute and rewrite the record of these parameters' versions, whatever is
    recorded. A damaged record raises TheoryRecordError; one of other parameters is computed again
    (one line says so)."""
    own = theory_record_path(records_dir, scale, experiment, parameters)
    found = None if retrain else find_theory_record(records_dir, scale, experiment, parameters)
    if found is not None:
        made = read_theory_marker(found)
        asked = next(p for p in _lookup_parameters(parameters) if parameters_hash(p) == made["parameters_hash"])
        tables, values = read_theory_record(found, asked)
        timing = read_json(_timing_path(found)) if _timing_path(found).exists() else {}
        took = f", computing it took {timing['compute_s']:.0f} s" if "compute_s" in timing else ""
        older = (f", under TRAINING_NUMERICS {_numerics(made['parameters'])['training']}"
                 if made["parameters_hash"] != parameters_hash(parameters) else "")
        say(f"[theory record] {experiment}: read {_shown(found)} (made on {made['made_on']['cpu']}{older}{took})")
        return tables, values
    if retrain:
        why = "retrain=True"
    elif own.exists():
        old = read_theory_marker(own)
        why = f"{_shown(own)} holds other parameters ({', '.join(_differences(old['parameters'], parameters)[:4])})"
    elif _other_records(own.parent, experiment, own):
        other = _other_records(own.parent, experiment, own)[-1]
        diff = _differences(read_theory_marker(other)["parameters"], parameters)
        why = f"{_shown(other)} holds other parameters ({', '.join(diff[:4])}); it stays, this one goes beside it"
    else:
        why = "no record"
    say(f"[theory record] {experiment}: computing ({why})")
    start = time.perf_counter()
    tables, values = compute()
    elapsed = time.perf_counter() - start
    write_theory_record(own, parameters, tables, values, compute_s=elapsed)
    say(f"[theory record] {experiment}: computed in {elapsed:.1f} s, written to {_shown(own)}")
    return read_theory_record(own, parameters)


def round_reported(frame: pd.DataFrame, digits: int = REPORTED_DIGITS) -> pd.DataFrame:
    """A copy of `frame` with every float column rounded to `digits` significant digits: what the
    tables report, without the last bits that differ between processors."""
    out = frame.copy()
    for column in out.columns:
        if pd.api.types.is_float_dtype(out[column]):
            out[column] = [float(f"{v:.{digits}g}") for v in out[column]]
    return out

# %% [markdown]
# A check on a small case: a record written and read back gives the same tables and values, bit
# for bit; asked with other parameters, `theory_record` computes again and rewrites it; a table
# changed on disk is refused, naming the file.

# %%
import tempfile

with tempfile.TemporaryDirectory() as scratch:
    demo_tables = {"runs": pd.DataFrame({"kind": ["mlp", "pemamoe"], "seed": [0, 1], "regret": [1.0 / 3, math.pi],
                                         "ok": [True, False]})}
    demo_values = {"gap": 0.1 + 0.2, "spread": np.array([0.25, 1e-17])}
    calls = []

    def demo_compute():
        calls.append(1)
        return demo_tables, demo_values

    said = []  # the demo's progress lines, kept off stdout (where `make figures` counts computed records)
    p1 = theory_parameters({"T": 10, "seed": seed})
    got, vals = theory_record(scratch, "ci", "demo", p1, demo_compute, say=said.append)
    pd.testing.assert_frame_equal(got["runs"], demo_tables["runs"], check_exact=True)
    assert vals == _plain(demo_values)
    theory_record(scratch, "ci", "demo", p1, demo_compute, say=said.append)  # read, not computed
    theory_record(scratch, "ci", "demo", theory_parameters({"T": 20, "seed": seed}), demo_compute, say=said.append)
    assert len(calls) == 2
    assert [line.split(": ")[1].split(" ")[0] for line in said] == ["computing", "computed", "read", "computing",
                                                                    "computed"], said
    print("the demo's progress lines:", *(line.replace("[theory record] ", "").replace(scratch, "<tmp>")
                                          for line in said), sep="\n  ")
    marker = theory_record_path(scratch, "ci", "demo")
    table = marker.with_name(marker.stem + ".runs.parquet")
    table.write_bytes(table.read_bytes()[:-1] + b"\0")
    try:
        read_theory_record(marker)
        raise AssertionError("a damaged record was read")
    except TheoryRecordError as err:
        print("refused:", str(err).replace(scratch, "<tmp>"))
print("rounded to six significant digits:", round_reported(pd.DataFrame({"x": [0.019624571464290558,
                                                                               0.019624571464290613]})).x.tolist())

# %%
print(f"appendix ran in {time.perf_counter() - T0:.1f} s at scale {scale!r}")
