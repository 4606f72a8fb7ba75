"""Environment speed: PettingZoo step latency and batched env-steps/s (targets in the env issue).

Targets on the 2-core machine: parallel-env step <= 200 us; vector env >= 50,000 env-steps/s at B=64.
The targets are measured on the default (compiled) engine with uniformly random actions. Two more
lines put them in context: the numpy reference engine, and a busy state in which the service radius
covers every user, so that the scheduler and the channel run for every link (the compiled step skips
the links of uncovered users; a good policy covers more users than random flight does).
"""

import time

import numpy as np

from pemamoe.env import compile_step_kernels, make_env, make_vector_env

BUSY = {"service_radius_m": (2000.0, 2000.0, 2000.0)}  # every user in range of its nearest UAV


def parallel_step_us(repeats: int = 2000, **overrides) -> float:
    env = make_env(render_mode=None, **overrides)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (repeats, 3, 2)).astype(np.float32)
    times = []
    for i in range(repeats):
        if not env.agents:
            env.reset()
        act = {a: actions[i, j] for j, a in enumerate(env.possible_agents)}
        start = time.perf_counter()
        env.step(act)
        times.append(time.perf_counter() - start)
    return float(np.median(times) * 1e6)


def vector_steps_per_s(batch: int, seconds: float = 1.5, **overrides) -> float:
    """Env-steps/s of the autoresetting vector env (episode resets included)."""
    env = make_vector_env(batch, seed=0, **overrides)
    env.reset()
    actions = np.random.default_rng(0).uniform(-1, 1, (64, batch, 3, 2))
    for i in range(5):  # warm-up, fills the random buffers
        env.step(actions[i])
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        env.step(actions[steps % 64])
        steps += 1
    return steps * batch / (time.perf_counter() - start)


if __name__ == "__main__":
    start = time.perf_counter()
    compile_step_kernels()
    print(f"env: compiled kernels ready in {time.perf_counter() - start:.1f} s (numba; cached on disk after the first build)")
    us = parallel_step_us()
    print(f"env: parallel-env step (3 UAVs, 20 users) median {us:.1f} us  [target <= 200 us]")
    for batch in (1, 16, 64, 256):
        rate = vector_steps_per_s(batch)
        target = "  [target >= 50,000 at B=64]" if batch == 64 else ""
        print(f"env: vector env batch={batch:4d}: {rate:,.0f} env-steps/s{target}")
    print(f"env: busy state, every user covered: parallel step {parallel_step_us(**BUSY):.1f} us, "
          f"vector env B=64 {vector_steps_per_s(64, **BUSY):,.0f} env-steps/s")
    print(f"env: numpy reference engine: parallel step {parallel_step_us(500, step_engine='numpy'):.1f} us, "
          f"vector env B=64 {vector_steps_per_s(64, step_engine='numpy'):,.0f} env-steps/s")
