"""Peers: pemamoe's trainer beside two common ways of training PPO on the same environment.

One invocation, interleaved rounds (every contender once per round, so drift of the shared 2-core
machine hits them alike), one torch thread each, the paper preset's batch: 64 environments x 32
steps = 2,048 environment steps (6,144 agent rows) per iteration, 8 epochs x 32 minibatches.

* pemamoe MLP and PE-MAMoE at R = 1, 5 (campaign v2's population) and 16 (the population trainer,
  benchmarks/bench_train.py's `measure`: one warm-up iteration, the median of two timed ones);
* Stable-Baselines3 PPO on the PettingZoo environment through SuperSuit (each UAV a vector entry,
  parameters shared, a critic on the agent's own observation: independent PPO, the common
  parameter-shared baseline), actor and critic 149 -> 32 -> 32 with ReLU as pemamoe's MLP;
* TorchRL MAPPO (MultiAgentMLP with shared parameters, a centralised critic on the agents'
  concatenated observations, ClipPPOLoss and GAE, TorchRL's own collector over a SerialEnv of 64
  PettingZoo environments), the same widths.

Beside them, the compute floor of an iteration: the floating-point work of its matrix products
(counted from the networks' shapes) at the rate this machine's one thread reaches on matrix
products of those shapes, plus the batched environment's own stepping time, both measured here.

The peers need the optional extra `bench` (`pip install -e ".[bench]"`, pinned in pyproject.toml so
that torch stays 2.13.0 CPU). Without it this prints pemamoe's rows and the floor and says which
peer is missing. Run: `python benchmarks/run.py bench_peers` (about 6 minutes on the 2-core machine).
"""

import importlib.util
import logging
import statistics
import sys
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench_train import measure  # noqa: E402
from pemamoe.env import UAVVectorEnv, observation_dim, state_dim, vector_seeds  # noqa: E402
from pemamoe.mappo import TrainConfig, build_population  # noqa: E402

ROUNDS = 3
TIMED = 2  # iterations timed after one warm-up, per round and contender
# R = 5: the population campaign v2 trains (five seeds of one method, issue 57)
CONTENDERS = (("pemamoe MLP", "mlp", 1), ("pemamoe MLP", "mlp", 5), ("pemamoe MLP", "mlp", 16),
              ("pemamoe PE-MAMoE", "pemamoe", 1), ("pemamoe PE-MAMoE", "pemamoe", 5),
              ("pemamoe PE-MAMoE", "pemamoe", 16))


def preset() -> TrainConfig:
    return TrainConfig.for_scale("paper", method="mlp", seed=0)


def ppo_settings(cfg: TrainConfig) -> dict:
    """The preset's PPO numbers that every contender takes."""
    n_agents = cfg.env_config().n_uavs
    return dict(envs=cfg.num_envs, steps=cfg.rollout_steps, epochs=cfg.update_epochs,
                minibatches=cfg.num_minibatches, agents=n_agents, hidden=cfg.net.hidden, lr=cfg.lr,
                gamma=cfg.gamma, gae_lambda=cfg.gae_lambda, clip=cfg.clip_coef, vf_coef=cfg.vf_coef,
                max_grad_norm=cfg.max_grad_norm)


class SB3Peer:
    """Stable-Baselines3 PPO over SuperSuit's vector of the PettingZoo environment."""

    name = "SB3 PPO + SuperSuit"
    requires = ("stable_baselines3", "supersuit")

    def __init__(self, cfg: TrainConfig, seed: int = 0):
        import supersuit as ss
        from stable_baselines3 import PPO

        from pemamoe.env_wrappers import UAVParallelEnv

        s = ppo_settings(cfg)
        vec = ss.pettingzoo_env_to_vec_env_v1(UAVParallelEnv(cfg.env_config()))
        vec = ss.concat_vec_envs_v1(vec, s["envs"], num_cpus=0, base_class="stable_baselines3")
        rows = s["envs"] * s["agents"] * s["steps"]  # agent rows per iteration
        torch.manual_seed(seed)  # SuperSuit's vector has no seed(), which PPO(seed=...) would call
        self.rows_per_iteration = rows
        self.model = PPO("MlpPolicy", vec, n_steps=s["steps"], batch_size=rows // s["minibatches"], n_epochs=s["epochs"],
                         learning_rate=s["lr"], gamma=s["gamma"], gae_lambda=s["gae_lambda"], clip_range=s["clip"],
                         ent_coef=0.0, vf_coef=s["vf_coef"], max_grad_norm=s["max_grad_norm"], device="cpu",
                         policy_kwargs=dict(net_arch=dict(pi=[s["hidden"]] * 2, vf=[s["hidden"]] * 2),
                                            activation_fn=torch.nn.ReLU), verbose=0)

    def iteration(self) -> float:
        """Seconds of one rollout of every environment plus its update."""
        start = time.perf_counter()
        self.model.learn(total_timesteps=self.rows_per_iteration, reset_num_timesteps=False)
        return time.perf_counter() - start


class TorchRLPeer:
    """TorchRL MAPPO: shared-parameter actor, centralised critic, TorchRL's collector and loss."""

    name = "TorchRL MAPPO"
    requires = ("torchrl", "tensordict")

    def __init__(self, cfg: TrainConfig, seed: int = 0):
        from tensordict.nn import NormalParamExtractor, TensorDictModule
        from torchrl.collectors import Collector
        from torchrl.data.replay_buffers import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
        from torchrl.envs import SerialEnv
        from torchrl.envs.libs.pettingzoo import PettingZooWrapper
        from torchrl.modules import MultiAgentMLP, ProbabilisticActor, TanhNormal
        from torchrl.objectives import ClipPPOLoss, ValueEstimators

        from pemamoe.env_wrappers import UAVParallelEnv

        logging.getLogger("torchrl").setLevel(logging.WARNING)  # its storage's size is not a result
        s = ppo_settings(cfg)
        env_cfg = cfg.env_config()

        def make_env():
            return PettingZooWrapper(UAVParallelEnv(env_cfg), categorical_actions=False)

        probe = PettingZooWrapper(UAVParallelEnv(env_cfg), categorical_actions=False)  # one env: names and specs
        (name,) = probe.group_map  # one group holding every agent
        action_key = (name, "action")
        spec = probe.full_action_spec[action_key]
        env = SerialEnv(s["envs"], make_env)
        env.set_seed(seed)  # environment i gets seed + i
        torch.manual_seed(seed)
        obs_dim, width, n_agents = observation_dim(env_cfg), s["hidden"], s["agents"]

        def mlp(outputs, centralised):
            return MultiAgentMLP(n_agent_inputs=obs_dim, n_agent_outputs=outputs, n_agents=n_agents,
                                 centralized=centralised, share_params=True, depth=2, num_cells=width,
                                 activation_class=torch.nn.ReLU)

        actor = TensorDictModule(torch.nn.Sequential(mlp(4, False), NormalParamExtractor()),
                                 in_keys=[(name, "observation")], out_keys=[(name, "loc"), (name, "scale")])
        self.policy = ProbabilisticActor(actor, spec=spec, in_keys=[(name, "loc"), (name, "scale")],
                                         out_keys=[action_key], distribution_class=TanhNormal,
                                         distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
                                         return_log_prob=True)
        critic = TensorDictModule(mlp(1, True), in_keys=[(name, "observation")], out_keys=[(name, "state_value")])
        self.loss = ClipPPOLoss(self.policy, critic, clip_epsilon=s["clip"], entropy_coeff=0.0,
                                critic_coeff=s["vf_coef"], normalize_advantage=False)
        self.loss.set_keys(reward=(name, "reward"), action=action_key, value=(name, "state_value"),
                           done=(name, "done"), terminated=(name, "terminated"))
        self.loss.make_value_estimator(ValueEstimators.GAE, gamma=s["gamma"], lmbda=s["gae_lambda"])
        self.optim = torch.optim.Adam(self.loss.parameters(), s["lr"])
        frames = s["envs"] * s["steps"]
        self.collector = iter(Collector(env, self.policy, frames_per_batch=frames, total_frames=-1,
                                        auto_register_policy_transforms=False))
        self.buffer = ReplayBuffer(storage=LazyTensorStorage(frames), sampler=SamplerWithoutReplacement(),
                                   batch_size=frames // s["minibatches"])
        self.s = s

    def iteration(self) -> float:
        start = time.perf_counter()
        data = next(self.collector)
        with torch.no_grad():
            self.loss.value_estimator(data, params=self.loss.critic_network_params,
                                      target_params=self.loss.target_critic_network_params)
        self.buffer.extend(data.reshape(-1))
        for _ in range(self.s["epochs"]):
            for _ in range(self.s["minibatches"]):
                out = self.loss(self.buffer.sample())
                (out["loss_objective"] + out["loss_critic"] + out.get("loss_entropy", 0.0)).backward()
                torch.nn.utils.clip_grad_norm_(self.loss.parameters(), self.s["max_grad_norm"])
                self.optim.step()
                self.optim.zero_grad()
        return time.perf_counter() - start


PEERS = (SB3Peer, TorchRLPeer)


def available_peers(peers=PEERS) -> tuple:
    """(the peers whose packages are installed, a line for each that is not)."""
    found, missing = [], []
    for peer in peers:
        absent = [m for m in peer.requires if importlib.util.find_spec(m) is None]
        if absent:
            missing.append(f"peers: {peer.name} skipped: {', '.join(absent)} not installed "
                           f"(pip install -e \".[bench]\", which `make bench` does)")
        else:
            found.append(peer)
    return found, missing


def time_peer(peer_class, cfg: TrainConfig) -> float:
    """Median seconds per iteration: built fresh, one warm-up iteration, then TIMED timed ones."""
    peer = peer_class(cfg)
    peer.iteration()
    return statistics.median(peer.iteration() for _ in range(TIMED))


def matmul_macs(method: str) -> int:
    """Multiply-accumulates of every matrix product in one paper-preset iteration at R = 1: the
    rollout's forward passes, then per epoch a forward and a backward (twice the forward's
    products: input and weight gradients) of actor and critic over the batch. Every expert is
    counted, as the trainer computes them all at this size."""
    cfg = TrainConfig.for_scale("paper", method=method, seed=0)
    pop = build_population([cfg])
    agents = cfg.env_config().n_uavs

    def per_row(net):  # weights' numel: one MAC per weight per row (biases and log-std aside)
        return sum(int(np.prod(s)) for n, s in zip(net.layout.names, net.layout.shapes) if len(s) >= 2)

    rows = cfg.batch_env_steps
    forward = rows * (agents * per_row(pop.actor) + per_row(pop.critic))
    return forward * (1 + 3 * cfg.update_epochs)


def matmul_rate() -> float:
    """MACs per second of one thread on the networks' product shapes (192 rows x 149 -> 96, the
    update's minibatch of agent rows through three experts' first layers at once)."""
    x, w = torch.randn(1, 192, 149), torch.randn(1, 149, 96)
    b = torch.zeros(1, 1, 96)
    for _ in range(50):
        torch.baddbmm(b, x, w)
    n, start = 2000, time.perf_counter()
    for _ in range(n):
        torch.baddbmm(b, x, w)
    return n * 192 * 149 * 96 / (time.perf_counter() - start)


def env_seconds(cfg: TrainConfig) -> float:
    """Seconds the batched environment takes for one iteration's steps with random actions."""
    venv = UAVVectorEnv(seeds=vector_seeds(0, cfg.num_envs), cfg=cfg.env_config())
    venv.reset()
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (cfg.rollout_steps, cfg.num_envs, venv.n_agents, 2))
    venv.step(actions[0])
    start = time.perf_counter()
    for a in actions:
        venv.step(a)
    return time.perf_counter() - start


def main() -> None:
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore", module="torchrl")  # the PettingZoo version TorchRL was tested with
    cfg = preset()
    steps = cfg.batch_env_steps
    peers, missing = available_peers()
    for line in missing:
        print(line)
    times = {c: [] for c in CONTENDERS + tuple(p.name for p in peers)}
    for r in range(ROUNDS):
        for label, method, R in CONTENDERS:
            times[(label, method, R)].append(measure(method, R)["iteration_s"])
        for peer in peers:
            times[peer.name].append(time_peer(peer, cfg))
        print(f"peers: round {r + 1} of {ROUNDS} done", flush=True)

    rate = statistics.median(matmul_rate() for _ in range(3))
    env_s = statistics.median(env_seconds(cfg) for _ in range(3))
    print(f"peers: paper preset, {steps} environment steps per iteration, {cfg.update_epochs} epochs x "
          f"{cfg.num_minibatches} minibatches, one thread; {ROUNDS} interleaved rounds, median (range) of the rounds")
    print(f"{'contender':<26} {'R':>3} {'s/iteration':>12} {'env steps/s':>12} {'range':>17} {'per run':>8}")
    sps = {}
    for key, seconds in times.items():
        label, R = (key[0], key[2]) if isinstance(key, tuple) else (key, 1)
        rates = [R * steps / s for s in seconds]
        sps[key] = statistics.median(rates)
        print(f"{label:<26} {R:>3} {statistics.median(seconds):>12.3f} {sps[key]:>12,.0f} "
              f"{min(rates):>8,.0f}-{max(rates):<8,.0f} {sps[key] / R:>8,.0f}")
    for method, label in (("mlp", "MLP"), ("pemamoe", "PE-MAMoE")):
        floor = matmul_macs(method) / rate + env_s
        print(f"compute floor, {label} R = 1: {floor:.3f} s per iteration ({steps / floor:,.0f} env steps/s): "
              f"{matmul_macs(method) * 2 / 1e9:.2f} GFLOP of matrix products at {2 * rate / 1e9:.1f} GFLOP/s "
              f"(one thread, measured) + {env_s:.3f} s of batched environment")
    mamoe = ("pemamoe PE-MAMoE", "pemamoe", 1)
    for peer in peers:
        print(f"PE-MAMoE R = 1 / {peer.name}: {sps[mamoe] / sps[peer.name]:.2f}x; "
              f"MLP R = 1 / {peer.name}: {sps[('pemamoe MLP', 'mlp', 1)] / sps[peer.name]:.2f}x")


if __name__ == "__main__":
    main()
