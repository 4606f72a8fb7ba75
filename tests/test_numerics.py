"""The training arithmetic against a stored fingerprint (pemamoe.train_config.TRAINING_NUMERICS).

Cached results are keyed by the config alone (plus TRAINING_NUMERICS once it is above 1), so a
code change that moves the numbers a run computes, without a bump of TRAINING_NUMERICS, would
serve old results as if they came from the new code. This test trains a short population of
every registered method on the CPU and compares sums of its logged training statistics with
tests/numerics_fingerprint.json. When it fails after an intended change of the arithmetic: bump
TRAINING_NUMERICS in notebooks/07c_config_and_bookkeeping.py, export, and run
`python tests/test_numerics.py --write`. The tolerances (below) sit about 100x above the float
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
# Statistics of the rollout (environment and sampling) and of the update (losses, gradients, policy)
COLUMNS = ("step/reward", "coverage", "value_loss", "policy_loss", "entropy", "grad_norm_actor",
           "grad_norm_critic", "approx_kl", "log_std_mean")
# Relative tolerances: 1e-5 by default; the policy loss and the approximate KL are small differences
# of large terms, so the order of a reduction moves them more (up to 4e-5 and 4e-6 with 2 threads
# instead of 1, against at most 1e-7 for the other sums).
RTOL = {"policy_loss": 1e-3, "approx_kl": 1e-4}
DEFAULT_RTOL, ATOL = 1e-5, 1e-9
SEEDS = (0, 1)


def fingerprint(methods=tuple(METHOD_REGISTRY)) -> dict:
    """Per method: the sum over iterations and members of each COLUMNS statistic, for a 2-member
    ci-scale population with one phase switch per 2 iterations, trained on the CPU."""
    out = {}
    for method in methods:
        configs = [TrainConfig.for_scale("ci", method=method, seed=s, device="cpu") for s in SEEDS]
        with tempfile.TemporaryDirectory() as tmp:
            results = train_population(configs, run_dirs=[Path(tmp) / f"m{s}" for s in SEEDS], threads=1,
                                       progress=False)
        out[method] = {c: float(np.nansum([r.metrics[c].to_numpy(dtype=float) for r in results]))
                       for c in COLUMNS}
    return out


def differences(stored: dict, got: dict) -> list:
    bad = []
    for method, stats in got.items():
        for column, value in stats.items():
            ref = stored.get(method, {}).get(column)
            if ref is None or not np.isclose(value, ref, rtol=RTOL.get(column, DEFAULT_RTOL), atol=ATOL):
                bad.append(f"{method} {column}: stored {ref!r}, computed {value!r}")
    return bad


def test_training_arithmetic_matches_its_fingerprint():
    stored = json.loads(FINGERPRINT.read_text())
    assert stored["numerics"] == TRAINING_NUMERICS, (
        f"{FINGERPRINT.name} was written for TRAINING_NUMERICS={stored['numerics']}, the code has "
        f"{TRAINING_NUMERICS}: run `python tests/test_numerics.py --write`")
    bad = differences(stored["methods"], fingerprint())
    assert not bad, ("the training arithmetic changed without a bump of TRAINING_NUMERICS (old cached runs would "
                     "pass for new ones); if the change is intended, bump it in notebooks/07c, export, and run "
                     "`python tests/test_numerics.py --write`:\n" + "\n".join(bad))


def test_a_numerics_bump_renames_every_run(monkeypatch):
    import pemamoe.train_config as tc
    cfg = TrainConfig.for_scale("ci", method="pemamoe")
    before = cfg.config_hash()
    assert "numerics" not in cfg.identity()  # version 1 keeps every existing run's folder
    monkeypatch.setattr(tc, "TRAINING_NUMERICS", 2)
    assert cfg.identity()["numerics"] == 2 and cfg.config_hash() != before


def write(force: bool = False) -> None:
    """Refresh the fingerprint; refuse to overwrite a different one of the same version (that is
    exactly the silent change the test exists to catch) unless forced (e.g. a new CPU kind)."""
    got = fingerprint()
    if FINGERPRINT.exists() and not force:
        stored = json.loads(FINGERPRINT.read_text())
        bad = differences(stored["methods"], got)
        if stored["numerics"] == TRAINING_NUMERICS and bad:
            sys.exit("the numbers moved but TRAINING_NUMERICS is still "
                     f"{TRAINING_NUMERICS}: bump it first (or pass --force):\n" + "\n".join(bad))
    FINGERPRINT.write_text(json.dumps({"numerics": TRAINING_NUMERICS, "methods": got}, indent=1, sort_keys=True) + "\n")
    print(f"wrote {FINGERPRINT} for TRAINING_NUMERICS={TRAINING_NUMERICS}")


if __name__ == "__main__":
    if not set(sys.argv[1:]) <= {"--write", "--force"} or "--write" not in sys.argv:
        sys.exit("usage: python tests/test_numerics.py --write [--force]")
    write(force="--force" in sys.argv)
