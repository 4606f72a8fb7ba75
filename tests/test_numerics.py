"""The training arithmetic against a stored fingerprint (pemamoe.train_config.TRAINING_NUMERICS).

Cached results are keyed by the config alone (plus TRAINING_NUMERICS once it is above 1), so a
code change that moves the numbers a run computes, without a bump of TRAINING_NUMERICS, would
serve old results as if they came from the new code. This test trains a short population of
every registered method on the CPU and compares sums of its logged training statistics with
tests/numerics_fingerprint.json. When it fails after an intended change of the arithmetic: bump
TRAINING_NUMERICS in notebooks/07c_train_config.py, export, and run
`python tests/test_numerics.py --write`. A changed default configuration renames the runs instead
(their identity hash, stored beside the numbers, moves): --write takes it without a bump. The tolerances (below) sit 25x (policy loss) to 1000x above the float
noise of another reduction order (2 torch threads instead of 1), which stands in for another CPU.
"""
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from pemamoe.mappo import TrainConfig, train_population
from pemamoe.methods import METHOD_REGISTRY
from pemamoe.train_config import TRAINING_NUMERICS

FINGERPRINT = Path(__file__).with_name("numerics_fingerprint.json")
ROOT = Path(__file__).resolve().parents[1]
# Sums over iterations and members of logged statistics: the rollout (environment and sampling), the
# episode log the figures read, the update (losses, gradients, policy) and the plasticity
# diagnostics. Dormant-unit fractions are left out: they count units against a threshold, so an
# ulp on another CPU can move them by a whole unit.
COLUMNS = ("step/reward", "coverage", "episode_return", "served_users", "collisions_per_episode",
           "energy_rate_kj", "value_loss", "policy_loss", "entropy", "grad_norm_actor", "grad_norm_critic",
           "approx_kl", "explained_variance", "log_std_mean", "rank/effective/mean", "rank/stable/mean")
EPISODE_COLUMNS = ("return", "coverage", "served_users", "energy_rate_kj")  # episodes.parquet, summed
# Relative tolerances: 1e-4 by default; the policy loss and the approximate KL are small differences
# of large terms, so the order of a reduction moves them more (up to 4e-5 and 4e-6 with 2 threads
# instead of 1, against at most 1e-7 for the other sums). A change of a formula moves these sums by
# far more (making the advantage's standard deviation biased moved the actor's gradient norm by 5e-3).
RTOL = {"policy_loss": 1e-3}
DEFAULT_RTOL, ATOL = 1e-4, 1e-9
SEEDS = (0, 1)


def platform() -> dict:
    """What the stored numbers depend on besides the code: the CPU architecture and the numeric libraries."""
    import platform as _platform

    import numba
    import torch

    return {"machine": _platform.machine(), "torch": torch.__version__, "numpy": np.__version__,
            "numba": numba.__version__}


def fingerprint(methods=tuple(METHOD_REGISTRY)) -> dict:
    """Per method: the sums of COLUMNS (metrics) and EPISODE_COLUMNS (episodes, plus their count)
    over a 2-member ci-scale population with a phase switch every 2 iterations, trained on the CPU."""
    out = {}
    for method in methods:
        configs = [TrainConfig.for_scale("ci", method=method, seed=s, device="cpu") for s in SEEDS]
        with tempfile.TemporaryDirectory() as tmp:
            results = train_population(configs, run_dirs=[Path(tmp) / f"m{s}" for s in SEEDS], threads=1,
                                       progress=False)
        sums = {c: float(np.nansum([r.metrics[c].to_numpy(dtype=float) for r in results])) for c in COLUMNS}
        sums.update({f"episodes/{c}": float(sum(r.episodes[c].sum() for r in results)) for c in EPISODE_COLUMNS})
        sums["episodes/count"] = float(sum(len(r.episodes) for r in results))
        out[method] = sums
    return out


def config_hashes(methods=tuple(METHOD_REGISTRY)) -> dict:
    """Per method: the identity hash of the fingerprint's first member. A changed default (of a
    network reading, say) moves a method's numbers and its hash together: its runs are renamed,
    so no cached result is served for the new configuration, and no bump is needed."""
    return {m: TrainConfig.for_scale("ci", method=m, seed=SEEDS[0], device="cpu").config_hash() for m in methods}


def reconfigured(stored: dict) -> list:
    """The methods whose stored configuration hash differs from the code's (see config_hashes)."""
    now = config_hashes()
    return [m for m, h in stored.get("configs", {}).items() if m in now and now[m] != h]


def differences(stored: dict, got: dict) -> tuple:
    """(changed: statistics that moved, missing: methods with no stored fingerprint)."""
    changed, missing = [], [m for m in got if m not in stored]
    for method, stats in got.items():
        if method in missing:
            continue
        for column, value in stats.items():
            ref = stored[method].get(column)
            if ref is None or not np.isclose(value, ref, rtol=RTOL.get(column, DEFAULT_RTOL), atol=ATOL):
                changed.append(f"{method} {column}: stored {ref!r}, computed {value!r}")
    return changed, missing


def test_training_arithmetic_matches_its_fingerprint():
    stored = json.loads(FINGERPRINT.read_text())
    assert stored["numerics"] == TRAINING_NUMERICS, (
        f"{FINGERPRINT.name} was written for TRAINING_NUMERICS={stored['numerics']}, the code has "
        f"{TRAINING_NUMERICS}: run `python tests/test_numerics.py --write`")
    if stored["platform"] != platform():
        pytest.skip(f"{FINGERPRINT.name} was written on {stored['platform']}, this is {platform()}: float results "
                    "may differ in the last bits, so the comparison would not show a code change")
    moved = reconfigured(stored)
    assert not moved, (f"the default configuration of {', '.join(moved)} changed (its identity hash moved, so its "
                       "runs are renamed and no cached result is reused): run `python tests/test_numerics.py --write`")
    changed, missing = differences(stored["methods"], fingerprint())
    assert not missing, (f"no fingerprint for {', '.join(missing)} (a new method): run `python tests/test_numerics.py "
                         "--write` (no bump of TRAINING_NUMERICS needed)")
    assert not changed, ("the training arithmetic changed without a bump of TRAINING_NUMERICS (old cached runs would "
                         "pass for new ones); if the change is intended, bump it in notebooks/07c, export, and run "
                         "`python tests/test_numerics.py --write`. If no training code changed, the float results of "
                         "this machine differ from those of the one that wrote the fingerprint:\n" + "\n".join(changed))


def test_a_numerics_bump_renames_every_run(monkeypatch):
    import pemamoe.train_config as tc
    cfg = TrainConfig.for_scale("ci", method="pemamoe")
    now = cfg.config_hash()
    assert cfg.identity()["numerics"] == tc.TRAINING_NUMERICS > 1
    monkeypatch.setattr(tc, "TRAINING_NUMERICS", tc.TRAINING_NUMERICS + 1)
    assert cfg.identity()["numerics"] == tc.TRAINING_NUMERICS and cfg.config_hash() != now
    monkeypatch.setattr(tc, "TRAINING_NUMERICS", 1)  # version 1 leaves the key out (runs made before it existed)
    assert "numerics" not in cfg.identity() and cfg.config_hash() != now


def test_gating_settings_leave_an_mlp_run_where_it_is():
    """A gating default or field is inert for an MLP: changing it must not rename MLP runs (their
    records would be orphaned), while it does rename every gated run. The pinned values are the
    ones the committed MLP records were made under."""
    import dataclasses
    from pemamoe.train_config import MLP_INERT_NET_IDENTITY, MLP_NET_FIELDS
    for method in ("mlp", "mlp_redo", "mlp_snp"):
        cfg = TrainConfig.for_scale("medium", method=method)
        assert cfg.identity()["net"] == {**{k: getattr(cfg.net, k) for k in MLP_NET_FIELDS}, **MLP_INERT_NET_IDENTITY}
        for field, value in (("load_balance_coef", 0.0), ("top_k", 2), ("routing_noise", "fixed"), ("n_experts", 5),
                             ("expert_heads", "per_expert"), ("update_routing", "current")):
            changed = cfg.replace(net=dataclasses.replace(cfg.net, **{field: value}))
            assert changed.config_hash() == cfg.config_hash(), field
        wider = cfg.replace(net=dataclasses.replace(cfg.net, hidden=64))
        assert wider.config_hash() != cfg.config_hash()  # a field the MLP reads still counts
    gated = TrainConfig.for_scale("medium", method="smoe")
    for field, values in (("load_balance_coef", (0.0, 0.01)), ("expert_heads", ("per_expert", "shared")),
                          ("update_routing", ("current", "replay"))):
        other = next(v for v in values if v != getattr(gated.net, field))  # whichever the default is not
        assert gated.replace(net=dataclasses.replace(gated.net, **{field: other})).config_hash() != gated.config_hash()
    # fields added later are absent from the identity at the value the earlier runs had
    from pemamoe.train_config import NET_FIELDS_ADDED
    earlier = gated.replace(net=dataclasses.replace(gated.net, **NET_FIELDS_ADDED))
    assert not NET_FIELDS_ADDED.keys() & earlier.identity()["net"].keys()
    assert TrainConfig.from_dict({**earlier.to_dict(), "net": {k: v for k, v in earlier.to_dict()["net"].items()
                                                              if k not in NET_FIELDS_ADDED}}) == earlier
    from pemamoe.records import find_record  # the committed records, of whichever numerics version made them
    assert all(find_record(ROOT / "records", "medium", TrainConfig.for_scale("medium", method="smoe", seed=s)).exists()
               for s in range(3))
    # the medium MLP records on disk were made under these values: their names still resolve
    from pemamoe.records import find_record  # the committed records, of whichever numerics version made them
    assert all(find_record(ROOT / "records", "medium", TrainConfig.for_scale("medium", method="mlp", seed=s)).exists()
               for s in range(3))


def test_runs_train_to_the_same_bits_without_the_nan_fill_of_new_tensors(monkeypatch):
    """The trainer turns off deterministic mode's NaN fill of uninitialised tensors (a speed-up):
    if any code read such memory, the fill (NaN) and no fill (whatever was there) would train to
    different numbers. A sparse and a dense gated method with the paper's actor readings, an MLP
    with ReDo, compared column for column, every bit."""
    import dataclasses
    import pemamoe.bookkeeping as bk
    paper = {"expert_heads": "per_expert", "update_routing": "current", "load_balance_coef": 0.0}

    def train(fill):
        monkeypatch.setattr(bk, "FILL_UNINITIALIZED_MEMORY", fill)
        configs = []
        for method in ("pemamoe", "moe", "mlp_redo"):
            cfg = TrainConfig.for_scale("ci", method=method, seed=0, device="cpu")
            if method != "mlp_redo":
                cfg = cfg.replace(net=dataclasses.replace(cfg.net, **paper))
            configs.append(cfg)
        out = []
        for cfg in configs:
            with tempfile.TemporaryDirectory() as tmp:
                out += train_population([cfg], run_dirs=[Path(tmp) / "run"], threads=1, progress=False)
        return out

    timing = ("time", "sps", "rollout_time", "update_time")
    for a, b in zip(train(True), train(False)):
        cols = [c for c in a.metrics.columns if not any(t in c for t in timing)]
        assert a.metrics[cols].equals(b.metrics[cols])
        assert a.episodes.equals(b.episodes)


def write(force: bool = False) -> None:
    """Refresh the fingerprint. It refuses to overwrite different numbers of the same version (that
    is exactly the silent change the test exists to catch) unless forced; new methods are added
    without a bump."""
    got = fingerprint()
    if FINGERPRINT.exists() and not force:
        stored = json.loads(FINGERPRINT.read_text())
        moved = set(reconfigured(stored))  # a renamed configuration may move its numbers
        changed, _ = differences({m: v for m, v in stored["methods"].items() if m not in moved}, got)
        if stored["numerics"] == TRAINING_NUMERICS and changed:
            sys.exit("the numbers moved but TRAINING_NUMERICS is still "
                     f"{TRAINING_NUMERICS}: bump it first (or pass --force):\n" + "\n".join(changed))
    FINGERPRINT.write_text(json.dumps({"numerics": TRAINING_NUMERICS, "platform": platform(), "methods": got,
                                       "configs": config_hashes()}, indent=1, sort_keys=True) + "\n")
    print(f"wrote {FINGERPRINT} for TRAINING_NUMERICS={TRAINING_NUMERICS}")


if __name__ == "__main__":
    if not set(sys.argv[1:]) <= {"--write", "--force"} or "--write" not in sys.argv:
        sys.exit("usage: python tests/test_numerics.py --write [--force]")
    write(force="--force" in sys.argv)
