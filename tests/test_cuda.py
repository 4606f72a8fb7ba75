"""The CUDA path (`TrainConfig(device="cuda")`, notebook 07): networks, buffers and the update on a
GPU, the environment on the CPU.

These tests need a CUDA GPU and are skipped without one; CI has none. They run in one prepared
call on a lent GPU machine through `benchmarks/device_check.sh`; benchmarks/HISTORY.md says what
they found when they ran (first on an H200, 2026-12-04).

Here: a CUDA run trains, is a different run from a CPU one, makes the first PPO ratio 1 up to rounding
(routing replay) and reads back on the CPU. Member independence and resume on the GPU are the
`cuda` cases of tests/test_population.py.
"""

import math

import pytest
import torch

from pemamoe.mappo import TrainConfig, load_run, train

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
    # routing replay: the first ratio is 1 up to float rounding, as on the CPU (tests/test_population.py):
    # the rollout's pass and the minibatch's see different row counts (2.4e-7 seen on an H200)
    assert (res.metrics["first_ratio_dev"] <= 1e-5).all()
    back = load_run(tmp_path / "run")  # networks come back as CPU modules
    for (name, a), (_, b) in zip(res.actor.state_dict().items(), back.actor.state_dict().items()):
        assert a.device.type == "cpu" and torch.equal(a, b), name
