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
# # 05e · Appendix: the registries of methods and network kinds
#
# A method in the experiments is a network kind of notebook 05 paired with a plasticity method of
# notebook 06, with the label and colour every figure uses. This appendix holds the two registries
# that name them, in the module `pemamoe.methods`: `METHOD_REGISTRY` (`register_method`,
# `method_spec`, the compared methods and the proposed one) and `NETWORKS` (`register_network`,
# `network_kind`), with the check of the parameter groups every actor and critic must file its
# parameters under. Read it when you add a method or a network kind (CONTRIBUTING.md shows a
# plugin). The module imports nothing from `pemamoe.nets`, so `pemamoe.nets` can register its
# kinds here.

# %%
#| default_exp methods

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## The methods: a network kind plus a plasticity method
#
# A *method* in the experiments is a pair: the network kind that computes the policy (notebook 05)
# and the plasticity method that acts at phase switches (notebook 06). The registry below is the one
# place that names the methods; the trainer, the sweeps, the figures and the tests read names,
# labels, colours and dispatch from it. PE-MAMoE is the SMoE network with the Phase Controller;
# any other pairing (an MLP with the controller's switch-time mechanisms, say) is one more entry
# with its own label. The paper's cost-table numbers ride along in each entry, for comparison only
# (notebook 05 reads them as `PAPER_ACTOR_PARAMS` and `PAPER_ACTIVE_PARAMS`).

# %%
#| export
from dataclasses import dataclass


@dataclass(frozen=True)
class MethodSpec:
    """One comparable method: what it trains (network kind) and how it treats plasticity."""

    name: str
    network: str  # a kind of pemamoe.nets.make_actor / make_critic
    plasticity: str = "none"  # a name in pemamoe.plasticity.PLASTICITY_METHODS
    label: str = ""  # display label in figures and tables
    colour: str = "#333333"
    proposed: bool = False  # the paper's method (the headline comparisons are against it)
    paper_actor_params: int | None = None  # the paper's cost table, for comparison only
    paper_active_params: int | None = None
    # the plasticity method's preset: (field, value) pairs applied to the run's PhaseControllerConfig
    # before the scale's rescaling and any override (empty: the defaults of notebook 06)
    plasticity_preset: tuple = ()
    # in the experiments' default comparison (`compared_methods()`: the paper's four and, unless
    # they say otherwise, a plug-in's); False: registered and run by name, in a sweep only when named
    compared: bool = True


METHOD_REGISTRY: dict = {}


def register_method(spec: MethodSpec) -> MethodSpec:
    """Add a method (or replace one of the same name); returns it."""
    if not isinstance(spec, MethodSpec):
        raise ValueError(f"register_method needs a MethodSpec, got {type(spec).__name__}")
    if not spec.name or not isinstance(spec.name, str):
        raise ValueError(f"MethodSpec.name must be a non-empty string, got {spec.name!r}")
    METHOD_REGISTRY[spec.name] = spec if spec.label else MethodSpec(**{**spec.__dict__, "label": spec.name})
    return METHOD_REGISTRY[spec.name]


PLUGINS_ENV = "PEMAMOE_PLUGINS"


class PluginError(ValueError):
    """A module named in $PEMAMOE_PLUGINS that cannot be found: one line naming it and what is allowed."""


def plugin_modules() -> list:
    """The module names in $PEMAMOE_PLUGINS (comma-separated), in order."""
    import os

    return [m for m in (m.strip() for m in os.environ.get(PLUGINS_ENV, "").split(",")) if m]


def missing_plugin_error(module: str, why: str = "") -> PluginError:
    return PluginError(f"{PLUGINS_ENV} names the module {module!r}, which cannot be imported{why}; name modules "
                       "importable from PYTHONPATH, comma-separated (e.g. PYTHONPATH=. PEMAMOE_PLUGINS=my_methods), "
                       f"or unset {PLUGINS_ENV}")


def load_plugins() -> None:
    """Import the modules named in $PEMAMOE_PLUGINS (comma-separated), once: how methods, network
    kinds and plasticity methods defined outside the package reach every process of a sweep.
    A module that is not there raises PluginError, one line naming it (an error inside a plugin
    that is there propagates as it is: it is the plugin's)."""
    import importlib

    for module in plugin_modules():
        if module not in _LOADED_PLUGINS:
            try:
                importlib.import_module(module)
            except ModuleNotFoundError as err:
                if err.name is None or not (module == err.name or module.startswith(err.name + ".")):
                    raise  # the plugin is there; something it imports is not
                raise missing_plugin_error(module) from None
            _LOADED_PLUGINS.add(module)


_LOADED_PLUGINS: set = set()


def method_spec(name: str) -> MethodSpec:
    if name not in METHOD_REGISTRY:
        load_plugins()
    if name not in METHOD_REGISTRY:
        raise ValueError(f"method must be one of {', '.join(METHOD_REGISTRY)}, got {name!r}")
    return METHOD_REGISTRY[name]


def method_names(proposed_last: bool = True) -> tuple:
    """Registered method names in registration order (the figures' order)."""
    return tuple(METHOD_REGISTRY)


def compared_methods() -> tuple:
    """The methods the experiments compare unless told otherwise, in registration order (every
    registered method except those registered with compared=False)."""
    return tuple(name for name, spec in METHOD_REGISTRY.items() if spec.compared)


def method_label(name: str) -> str:
    return METHOD_REGISTRY[name].label if name in METHOD_REGISTRY else name


def method_colour(name: str) -> str:
    return METHOD_REGISTRY[name].colour if name in METHOD_REGISTRY else "#333333"


def proposed_method() -> str:
    return next(name for name, spec in METHOD_REGISTRY.items() if spec.proposed)


# The paper's four methods, in the order the figures use.
register_method(MethodSpec("mlp", network="mlp", label="MLP", colour="#7f7f7f",
                           paper_actor_params=6820, paper_active_params=6820))
register_method(MethodSpec("moe", network="moe", label="MoE", colour="#1f77b4",
                           paper_actor_params=20858, paper_active_params=20858))
register_method(MethodSpec("smoe", network="smoe", label="SMoE", colour="#ff7f0e",
                           paper_actor_params=21392, paper_active_params=7820))
register_method(MethodSpec("pemamoe", network="smoe", plasticity="phase_controller", label="PE-MAMoE",
                           colour="#d62728", proposed=True, paper_actor_params=21392, paper_active_params=7820))
# Two plasticity baselines from the literature (appendix 06c), each on the MLP and on the SMoE
# network: run by name (`--methods smoe_redo`), outside the default comparison.
register_method(MethodSpec("mlp_redo", network="mlp", plasticity="redo", label="MLP + ReDo", colour="#9467bd",
                           compared=False))
register_method(MethodSpec("smoe_redo", network="smoe", plasticity="redo", label="SMoE + ReDo", colour="#8c564b",
                           compared=False))
register_method(MethodSpec("mlp_snp", network="mlp", plasticity="shrink_and_perturb",
                           label="MLP + shrink-and-perturb", colour="#e377c2", compared=False))
register_method(MethodSpec("smoe_snp", network="smoe", plasticity="shrink_and_perturb",
                           label="SMoE + shrink-and-perturb", colour="#17becf", compared=False))


# %% [markdown]
# ## The network kinds: a registry and its contract
#
# A network kind is an actor class and a critic class under one name. `register_network` adds
# one (notebook 05 registers `mlp`, `moe` and `smoe`; a plugin may add more, see CONTRIBUTING.md);
# `network_kind` resolves a kind or a method's name. What an actor class writes is listed in
# notebook 05 ("What a network kind writes"). One part of the contract is checked whenever a
# network is built: the parameter groups. The optimizer and the phase controller schedule
# parameters by group name (learning-rate drops, the router freeze), so an actor's
# `param_groups()` must file every parameter exactly once under one of `ACTOR_PARAM_GROUPS`, a
# critic's under `CRITIC_PARAM_GROUPS`; `check_param_groups` says which group or parameter breaks
# it, and which names are allowed.

# %%
#| export
ACTOR_PARAM_GROUPS = ("router", "experts", "head", "log_std")  # the groups the phase controller schedules
CRITIC_PARAM_GROUPS = ("critic",)
NETWORKS: dict = {}  # network kind -> (actor class, critic class)


def register_network(kind: str, actor_cls, critic_cls) -> None:
    """Make a network kind available to make_actor / make_critic (and so to the method registry).
    The actor subclasses pemamoe.nets.GaussianActor (run_features, trunk_parameters, param_groups
    over ACTOR_PARAM_GROUPS, cost_parts; see notebook 05); the critic provides forward,
    run_features and param_groups over CRITIC_PARAM_GROUPS."""
    if not isinstance(kind, str) or not kind:
        raise ValueError(f"network kind must be a non-empty string, got {kind!r}")
    NETWORKS[kind] = (actor_cls, critic_cls)


def network_kind(name: str) -> str:
    """A network kind, or a method name resolved through the method registry."""
    if name not in NETWORKS and name not in METHOD_REGISTRY:
        load_plugins()
    if name in NETWORKS:
        return name
    if name in METHOD_REGISTRY:
        return METHOD_REGISTRY[name].network
    raise ValueError(f"network kind must be one of {', '.join(NETWORKS)} (or a method: {', '.join(METHOD_REGISTRY)}), "
                     f"got {name!r}")


def check_param_groups(module, allowed: tuple):
    """`module` if its param_groups() files every parameter once, under names from `allowed`;
    else a ValueError naming the class, the offending group or parameter, and the allowed groups."""
    where = f"{type(module).__name__}.param_groups()"
    seen = {}
    for group, params in module.param_groups().items():
        if group not in allowed:
            raise ValueError(f"{where} has group {group!r}; the groups are {', '.join(allowed)}")
        for p in params:
            if id(p) in seen:
                raise ValueError(f"{where} files a parameter under both {seen[id(p)]!r} and {group!r}")
            seen[id(p)] = group
    missing = [name for name, p in module.named_parameters() if id(p) not in seen]
    if missing:
        raise ValueError(f"{where} leaves out {', '.join(missing)}; file each under one of {', '.join(allowed)}")
    return module


# %% [markdown]
# ## Demonstration: the registered methods
#
# The paper's four methods, in the order the figures use, with their network kind, plasticity
# method and the paper's counts.

# %%
import pandas as pd

registry = pd.DataFrame([{k: v for k, v in spec.__dict__.items() if k != "plasticity_preset"}
                         for spec in METHOD_REGISTRY.values()]).set_index("name")
print(registry.to_string())
assert method_names()[:4] == ("mlp", "moe", "smoe", "pemamoe") and proposed_method() == "pemamoe"
