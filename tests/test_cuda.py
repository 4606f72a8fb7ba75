"""The CUDA path (`TrainConfig(device="cuda")`, notebook 07): networks, buffers and the update on a
GPU, the environment on the CPU.

These tests need a CUDA GPU and are skipped without one; CI has none. They run in one prepared
call on a lent GPU machine through `benchmarks/device_check.sh`. At the commit that added them no
session had been lent a GPU, so they had never run: the README's CUDA paragraph says when that
changes.

They ask what the CPU tests ask of the population trainer, on the GPU: a member's run is the same
bits alone and in a population (cuBLAS may choose its kernels by batch count, and GPU reductions
their order by tensor shape: if this fails, the population layout has to join a CUDA run's
identity, as notebook 07 explains); a killed population resumes bit-identically; routing replay
makes the first PPO ratio exactly 1; and a CUDA run is a different run from a CPU one.
"""

import math

import pytest
import torch

from pemamoe.mappo import TrainConfig, load_run, train, train_population
from test_population import _assert_same_run  # the CPU suite's bit-for-bit run comparison

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(),
                                reason="needs a CUDA GPU (CI has none); benchmarks/device_check.sh runs these")


def cuda_ci(method="pemamoe", seed=0, **kw):
    return TrainConfig.for_scale("ci", method=method, seed=seed, device="cuda", **kw)


def test_cuda_run_trains_is_its_own_run_and_reads_back_on_the_cpu(tmp_path):
    cfg = cuda_ci(iterations=4)
    assert cfg.config_hash() != TrainConfig.for_scale("ci", method="pemamoe", seed=0, iterations=4).config_hash()
    res = train(cfg, tmp_path / "run")
    assert res.finished and len(res.metrics) == 4
    assert all(math.isfinite(x) for x in res.metrics["policy_loss"].dropna())
    assert (res.metrics["first_ratio_dev"] == 0.0).all()  # routing replay: ratio exactly 1 per member
    back = load_run(tmp_path / "run")  # networks come back as CPU modules
    for (name, a), (_, b) in zip(res.actor.state_dict().items(), back.actor.state_dict().items()):
        assert a.device.type == "cpu" and torch.equal(a, b), name


@pytest.mark.parametrize("method", ["pemamoe", "mlp"])
def test_cuda_member_is_bit_identical_alone_and_in_a_population(method, tmp_path):
    cfgs = [cuda_ci(method, 0, iterations=4),
            cuda_ci(method, 1, iterations=4, without=("router_freeze",)),
            cuda_ci(method, 2, iterations=4, noise_gamma=0.05, force_controller=True)]
    alone = train(cfgs[0], tmp_path / "alone")
    pop = train_population(cfgs[::-1], [tmp_path / f"p{i}" for i in range(3)])
    _assert_same_run(alone, pop[2], tmp_path / "alone", tmp_path / "p2")


def test_cuda_killed_population_resumes_bit_identically(tmp_path):
    cfgs = [cuda_ci("pemamoe", s, iterations=4, checkpoint_every=2) for s in (0, 1)]
    straight = train_population(cfgs, [tmp_path / "s0", tmp_path / "s1"])
    train_population(cfgs, [tmp_path / "r0", tmp_path / "r1"], max_iterations=2)
    resumed = train_population(cfgs, [tmp_path / "r0", tmp_path / "r1"])
    for r in range(2):
        assert resumed[r].resumed_from == 2 and resumed[r].finished
        _assert_same_run(straight[r], resumed[r], tmp_path / f"s{r}", tmp_path / f"r{r}")
