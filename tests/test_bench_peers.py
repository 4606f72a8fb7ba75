"""benchmarks/bench_peers.py's bookkeeping (its timings belong to `make bench`, not here): the peers
take the preset's PPO numbers, a missing peer is named with the extra that installs it, and the
compute floor counts the networks' products by hand."""
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _bench_peers():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        spec = importlib.util.spec_from_file_location("bench_peers", ROOT / "benchmarks" / "bench_peers.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


def test_the_peers_take_the_paper_presets_ppo_numbers():
    bp = _bench_peers()
    s = bp.ppo_settings(bp.preset())
    assert (s["envs"], s["steps"], s["epochs"], s["minibatches"], s["agents"], s["hidden"]) == (64, 32, 8, 32, 3, 32)
    assert (s["lr"], s["clip"], s["gamma"], s["gae_lambda"]) == (3e-4, 0.15, 0.99, 0.95)


def test_a_missing_peer_is_named_with_the_extra_that_installs_it():
    bp = _bench_peers()

    class Absent:
        name, requires = "Nowhere PPO", ("no_such_module_pemamoe_test",)

    found, missing = bp.available_peers((Absent,))
    assert found == [] and len(missing) == 1
    assert "Nowhere PPO skipped: no_such_module_pemamoe_test not installed" in missing[0] and ".[bench]" in missing[0]


def test_the_compute_floor_counts_every_weight_matrix_once_per_row_and_pass():
    bp = _bench_peers()
    # MLP, paper preset: actor 149 -> 32 -> 32 -> 2 on 3 agent rows per step, critic 190 -> 32 -> 32 -> 1;
    # 2,048 steps; the rollout's forward pass and 8 epochs of forward + backward (3 passes' worth)
    actor, critic = 149 * 32 + 32 * 32 + 32 * 2, 190 * 32 + 32 * 32 + 32 * 1
    assert bp.matmul_macs("mlp") == 2048 * (3 * actor + critic) * (1 + 3 * 8)
