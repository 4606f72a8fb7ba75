"""CONTRIBUTING.md's "Extending" example works as written, through the registries alone.

The test takes the example's code from CONTRIBUTING.md itself, installs it as a plugin module,
runs it in a ci-scale sweep next to a built-in method (worker processes load it through
$PEMAMOE_PLUGINS), draws it in a training-curve figure with its own label, and checks that no
file of the package or the notebooks names it. A second one-file plugin, which reads the probe
batch at a switch and logs a metric of its own, trains through `python -m pemamoe train`.
"""

import re
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _example_code() -> str:
    text = (ROOT / "CONTRIBUTING.md").read_text()
    match = re.search(r"<!-- extending-example -->\s*```python\n(.*?)```", text, re.S)
    assert match, "CONTRIBUTING.md lost its extending example"
    return match.group(1)


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    (tmp_path / "my_methods.py").write_text(_example_code())
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", f"{tmp_path}:{ROOT}")
    monkeypatch.setenv("PEMAMOE_PLUGINS", "my_methods")
    yield "ln_mlp_sp"
    from pemamoe.methods import METHOD_REGISTRY, _LOADED_PLUGINS
    from pemamoe.nets import NETWORKS
    from pemamoe.plasticity import PLASTICITY_METHODS

    METHOD_REGISTRY.pop("ln_mlp_sp", None), NETWORKS.pop("ln_mlp", None), PLASTICITY_METHODS.pop("shrink_perturb", None)
    _LOADED_PLUGINS.discard("my_methods")
    sys.modules.pop("my_methods", None)


def test_the_contributing_example_runs_in_a_sweep_and_a_figure(plugin, tmp_path):
    from pemamoe.analysis import load_runs, plot_over_training
    from pemamoe.methods import method_label, method_spec
    from pemamoe.experiments import main_specs, sweep_records

    assert method_spec(plugin).plasticity == "shrink_perturb"  # loaded from $PEMAMOE_PLUGINS on first use
    specs = main_specs("ci", seeds=(0,), methods=("mlp", plugin))
    records = sweep_records(specs, "local", workers=2, results_dir=tmp_path / "results", verbose=False,
                            records_dir=tmp_path / "records")
    metrics, _ = load_runs(records)
    assert set(metrics.method) == {"mlp", plugin}
    toy = metrics[metrics.method == plugin]
    assert toy.switch.any() and toy.episode_return.notna().any()

    fig, ax = plt.subplots()
    plot_over_training(ax, metrics, "episode_return", methods=("mlp", plugin))
    labels = [line.get_label() for line in ax.get_lines()]
    plt.close(fig)
    assert method_label(plugin) in labels and method_label("mlp") in labels


def test_shrink_and_perturb_acts_at_the_switch_on_its_own_member(plugin):
    import torch

    from pemamoe.mappo import TrainConfig, train_population

    cfgs = [TrainConfig.for_scale("ci", method=plugin, seed=s, iterations=3, phase_length_iters=2) for s in (0, 1)]
    before = train_population(cfgs, max_iterations=2)
    after = train_population(cfgs)
    for b, a in zip(before, after):  # iteration 2 is a switch: every actor weight shrank towards 0
        wb, wa = b.actor.fc1.weight.detach(), a.actor.fc1.weight.detach()
        assert wa.norm() < 0.9 * wb.norm()
    assert not torch.equal(after[0].actor.fc1.weight, after[1].actor.fc1.weight)


def test_the_example_kind_logs_the_mean_action_it_takes(plugin):
    # the example writes run_features only: its features, probe and so the logged mean action
    # are the layer-normalised network that acts (an inherited MLP probe would skip the norm)
    import torch

    from pemamoe.diagnostics import plasticity_diagnostics
    from pemamoe.methods import method_spec
    from pemamoe.nets import make_actor

    actor = make_actor(method_spec(plugin).network, 12)
    with torch.no_grad():
        actor.head.weight.mul_(100)  # a head large enough that the norm visibly moves the mean
        obs = torch.randn(64, 12)
        mean = actor(obs, deterministic_gate=True)[0].mean
        probe = actor.probe(obs)
    assert torch.equal(probe["mean"], mean)
    torch.testing.assert_close(probe["features"].mean(-1), torch.zeros(64), atol=1e-5, rtol=0)
    logged = plasticity_diagnostics(actor, None, obs)
    assert logged["action/mean_x"] == pytest.approx(float(mean[:, 0].mean()), abs=1e-7)
    assert logged["action/mean_y"] == pytest.approx(float(mean[:, 1].mean()), abs=1e-7)


def test_no_package_file_names_the_example():
    names = ("ln_mlp", "shrink_perturb", "ShrinkPerturb", "LayerNormMLPActor")
    for folder in ("pemamoe", "notebooks"):
        for path in (ROOT / folder).rglob("*.py"):
            text = path.read_text()
            assert not any(n in text for n in names), f"{path} names the CONTRIBUTING example"


def test_a_method_preset_sets_its_controller_and_combinations_keep_their_labels():
    # an MLP with PE-MAMoE's switch-time mechanisms, with a gentler noise preset, is one registry entry
    from pemamoe.mappo import TrainConfig
    from pemamoe.methods import METHOD_REGISTRY, MethodSpec, register_method

    spec = register_method(MethodSpec("mlp_pc_test", network="mlp", plasticity="phase_controller",
                                      label="MLP + phase controller", plasticity_preset=(("noise_gamma", 0.001),)))
    try:
        cfg = TrainConfig.for_scale("ci", method="mlp_pc_test")
        assert cfg.controller_enabled and cfg.controller.noise_gamma == 0.001
        assert TrainConfig.for_scale("ci", method="mlp_pc_test", noise_gamma=0.01).controller.noise_gamma == 0.01
        assert cfg.label() == "MLP + phase controller" and spec.label == cfg.label()
        assert TrainConfig.for_scale("ci", method="pemamoe").controller.noise_gamma == 0.005
    finally:
        METHOD_REGISTRY.pop("mlp_pc_test", None)


PROBE_PLUGIN = '''
import torch

from pemamoe.methods import MethodSpec, register_method
from pemamoe.plasticity import NoPlasticity, register_plasticity


@register_plasticity
class ProbeMean(NoPlasticity):
    """At each switch, read each member's probe batch and log its mean |observation|."""

    name = "probe_mean"
    probe_rows = 64

    def __init__(self, *args):
        super().__init__(*args)
        self.seen = [float("nan")] * self.R

    @torch.no_grad()
    def on_switch(self, iteration):
        self.seen = [float(self.probe_batch(r).abs().mean()) for r in range(self.R)]

    def metrics(self, r):
        return {"probe_mean/abs_obs": self.seen[r]}


register_method(MethodSpec("mlp_probe_mean", network="mlp", plasticity="probe_mean", label="MLP + probe mean"))
'''


def test_a_one_file_plugin_trains_from_the_command_line_with_its_own_metric(tmp_path):
    import os
    import subprocess

    import pandas as pd

    (tmp_path / "probe_plugin.py").write_text(PROBE_PLUGIN)
    env = {**os.environ, "PEMAMOE_PLUGINS": "probe_plugin", "PYTHONPATH": f"{tmp_path}:{ROOT}"}
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "pemamoe", "train", "--method", "mlp_probe_mean", "--scale", "ci",
                           "--iterations", "3", "--out", str(out)], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    metrics = pd.read_parquet(out / "metrics.parquet")
    assert len(metrics) == 3 and metrics.switch.tolist() == [False, False, True]
    seen = metrics["probe_mean/abs_obs"]
    assert seen.iloc[:2].isna().all() and seen.iloc[2] > 0  # read at the switch, from the last rollout
    refused = subprocess.run([sys.executable, "-m", "pemamoe", "train", "--method", "mlp_probe_mean", "--scale", "ci"],
                             cwd=tmp_path, env={**env, "PEMAMOE_PLUGINS": ""}, capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and "mlp_probe_mean" in refused.stderr  # without the plugin: a usage error
