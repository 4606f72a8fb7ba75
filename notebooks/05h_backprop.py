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
# # 05h · Appendix: the networks' gradients, written out
#
# The PPO update (notebook 07) takes 256 gradient steps per iteration on minibatches of 192 agent
# rows. At that size a step costs almost nothing in arithmetic and almost everything in the
# number of tensor operations dispatched: autograd records every view, product and mask of the
# forward pass and replays a backward operation for each, about 550 operations per step for
# PE-MAMoE. Every network kind here is a short chain of batched linear layers, ReLUs, a softmax
# router and a mixing sum, so its backward pass fits in a few lines per block. This appendix holds
# those lines, in the module `pemamoe.backprop`:
#
# * the forward pass runs once, without autograd, and keeps what the backward reads in a dict
#   `saved` (the activations of each layer, the router's probabilities, the chosen experts and
#   their weights, each expert's output before mixing); `run_experts`, `run_gate` (appendices 05b
#   and 05g) and the kinds' `run_features` / `run_mean` (notebook 05) fill it when given one;
# * the update computes the gradient of each member's loss with respect to what the networks
#   output (the policy mean and log-std, the value), notebook 07;
# * `actor_grads` and `critic_grads` carry those back to every parameter, one function per block:
#   a member-wise linear layer, the ReLU trunk of every expert, the per-expert heads, the gate's
#   mixing, top-k weights and softmax router.
#
# Nothing here changes what a network computes: the forward pass is the one every caller runs.
# The tests compare every gradient with autograd's on the same forward pass, for every kind and
# gate setting, at several population sizes (`tests/test_backprop.py`), and the trainer's own tests
# check that a member's gradient does not depend on its population. A network kind from a plugin
# needs none of this: without a hand-written backward its gradient comes from autograd
# (`autograd_grads`), at autograd's cost; a kind opts in with `hand_written_backward = True` in its
# own class body once its gradient is written here.
#
# **The blocks, per member** (shapes without the leading run axis R; n rows, E experts):
#
# * linear layer $y = x W^\top + b$: $\partial W = \bar y^\top x$, $\partial b = \sum_n \bar y$,
#   $\bar x = \bar y W$;
# * ReLU $a = \max(z, 0)$: $\bar z = \bar a \cdot [a > 0]$;
# * mixing $o = \sum_e m_e\, y_e$ with weights $m$ (the router's probabilities for the dense
#   mixture; the top-k weights at the chosen experts and 0 elsewhere for the sparse gate):
#   $\bar y_e = m_e\, \bar o$, $\bar m_e = \langle \bar o, y_e \rangle$;
# * top-k weights $w_j = g_j / \sum_i g_i$ over the kept probabilities:
#   $\bar g_j = (\bar w_j - \sum_i \bar w_i w_i)/\sum_i g_i$; at k = 1 the weight is exactly 1 and
#   its gradient is what `top1_weight` says (straight-through and `switch`: $\bar g = \bar w$;
#   `paper`: none);
# * softmax $g = \mathrm{softmax}(\ell)$: $\bar\ell = g \odot (\bar g - \langle \bar g, g\rangle)$,
#   then $\ell = (x W_r^\top + b_r)/\tau + \varepsilon \cdot s$ gives the router's gradient through
#   $1/\tau$, and, for learned noise $s = \mathrm{softplus}(q)$, the noise gate's through
#   $\varepsilon \cdot \sigma(q)$ (with $\sigma(q) = 1 - e^{-s}$);
# * the balance loss $c\,E \sum_i f_i \bar P_i$ adds $c\,E f_i / n$ to every row's $\bar g_i$ ($f$,
#   the share of routing slots, carries no gradient).

# %%
#| default_exp backprop

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %%
#| export
import torch

from pemamoe.gating import GatedExperts
from pemamoe.nets import MLPActor, MLPCritic
from pemamoe.popnets import PopulationActor, PopulationCritic, routing_counts


def linear_grads(x, g_out):
    """`run_linear`'s weight and bias gradients: x (R, n, in), g_out (R, n, out) -> ((R, out, in), (R, out))."""
    if g_out.shape[-1] == 1:  # the value head: a product and a row sum, as its forward (appendix 05b)
        return (g_out * x).sum(1, keepdim=True), g_out.sum(1)
    return torch.bmm(g_out.transpose(1, 2), x), g_out.sum(1)


def linear_input_grad(g_out, weight):
    """The gradient reaching `run_linear`'s input: g_out (R, n, out), weight (R, out, in) -> (R, n, in)."""
    if weight.shape[1] == 1:
        return g_out * weight
    return torch.bmm(g_out, weight.contiguous())


def relu_input_grad(g_a, a):
    """The gradient reaching a ReLU's input from that of its output a: g_a where a > 0, else 0.
    Computed as autograd computes it (aten.threshold_backward), in one pass: g_a * (a > 0) is the
    same numbers (but the sign of a zero, which no sum or optimizer step below can tell apart) and
    about 10x slower on the CPU, where making the boolean mask dominates."""
    return torch.ops.aten.threshold_backward(g_a, a, 0)


def mlp_trunk_grads(p, saved, g_a2) -> dict:
    """fc1 and fc2 of an MLP trunk (x -> a1 -> a2, ReLU after each) from the gradient of its output a2."""
    g_p2 = relu_input_grad(g_a2, saved["a2"])
    g_p1 = relu_input_grad(linear_input_grad(g_p2, p["fc2.weight"]), saved["a1"])
    (g_w2, g_b2), (g_w1, g_b1) = linear_grads(saved["a1"], g_p2), linear_grads(saved["x"], g_p1)
    return {"fc1.weight": g_w1, "fc1.bias": g_b1, "fc2.weight": g_w2, "fc2.bias": g_b2}


def expert_trunk_grads(p, prefix, saved, g_a2) -> dict:
    """w1, b1, w2, b2 of every expert (`run_experts`) from the gradient of their outputs a2 (R, E, n, h)."""
    xe, a1, a2 = saved["xe"], saved["a1"], saved["a2"]
    R, E, n, h = a2.shape
    g_p2 = relu_input_grad(g_a2, a2).reshape(R * E, n, h)
    g_w2 = torch.bmm(a1.transpose(1, 2), g_p2)
    g_p1 = relu_input_grad(torch.bmm(g_p2, p[prefix + "experts.w2"].contiguous().reshape(R * E, h, h).transpose(1, 2)), a1)
    g_w1 = torch.bmm(xe.transpose(1, 2), g_p1)
    return {prefix + "experts.w1": g_w1.reshape(R, E, -1, h), prefix + "experts.b1": g_p1.sum(1).reshape(R, E, h),
            prefix + "experts.w2": g_w2.reshape(R, E, h, h), prefix + "experts.b2": g_p2.sum(1).reshape(R, E, h)}


def expert_heads_grads(p, saved, g_y) -> tuple:
    """The per-expert heads' gradients and the one reaching each expert's features:
    g_y (R, E, n, out) -> ({head.weight, head.bias}, g_a2 (R, E, n, h))."""
    a2 = saved["a2"]
    R, E, n, h = a2.shape
    g = g_y.reshape(R * E, n, -1)
    g_hw = torch.bmm(g.transpose(1, 2), a2.reshape(R * E, n, h))
    g_a2 = torch.bmm(g, p["head.weight"].contiguous().reshape(R * E, -1, h)).reshape(R, E, n, h)
    return {"head.weight": g_hw.reshape(R, E, -1, h), "head.bias": g.sum(1).reshape(R, E, -1)}, g_a2


def gate_grads(p, prefix, gate: GatedExperts, saved, g_out, balance_coef: float) -> tuple:
    """The router's (and a learned noise gate's) gradients and the one reaching every expert's
    output y (R, E, n, out), from the gradient of the mixed output g_out (R, n, out); the balance
    loss, at `balance_coef`, adds its own gradient on the probabilities."""
    probs, y, x, mix = saved["probs"], saved["y"], saved["x"], saved["mix"]
    R, n, E = probs.shape
    experts, weights = saved["experts"], saved["weights"]
    # contiguous: a broadcast product's memory order can follow its inputs' strides, which differ
    # between one member and several, and the sums below would then add in another order
    g_y = (mix.transpose(1, 2).unsqueeze(-1) * g_out.unsqueeze(1)).contiguous()
    g_mix = (y * g_out.unsqueeze(1)).sum(-1).transpose(1, 2)  # (R, n, E)
    if not gate.sparse:
        g_probs = g_mix
    elif experts.shape[-1] == 1 and gate.top1_weight == "paper":  # the weight 1 carries no gradient
        g_probs = torch.zeros_like(probs)
    else:
        g_kept = g_mix.gather(2, experts)
        if experts.shape[-1] > 1:  # through the renormalisation over the kept probabilities
            g_kept = (g_kept - (g_kept * weights).sum(-1, keepdim=True)) / probs.gather(2, experts).sum(-1, keepdim=True)
        g_probs = torch.zeros_like(probs).scatter_(2, experts, g_kept)
    if balance_coef:
        chosen = saved["experts"] if gate.sparse else probs.argmax(-1, keepdim=True)
        counts = routing_counts(chosen, probs)  # (R, E), as the balance loss counts them
        g_probs = g_probs + (balance_coef * E / n) * (counts / counts.sum(-1, keepdim=True)).unsqueeze(1)
    g_logits = probs * (g_probs - (g_probs * probs).sum(-1, keepdim=True))
    grads = {}
    if gate.noise == "learned":
        g_q = torch.zeros_like(g_logits) if saved["noise"] is None else \
            g_logits * saved["noise"] * (1 - torch.exp(-saved["scale"]))
        grads[prefix + "noise_gate.weight"], grads[prefix + "noise_gate.bias"] = linear_grads(x, g_q)
    grads[prefix + "router.weight"], grads[prefix + "router.bias"] = linear_grads(x, g_logits / saved["tau"].unsqueeze(-1))
    return grads, g_y


def gated_grads(p, prefix, gate, saved, g_out, balance_coef, heads: bool) -> dict:
    """Every parameter of a gated trunk (with per-expert heads when `heads`) from g_out (R, n, out)."""
    grads, g_y = gate_grads(p, prefix, gate, saved, g_out, balance_coef)
    if heads:
        head, g_y = expert_heads_grads(p, saved, g_y)
        grads.update(head)
    grads.update(expert_trunk_grads(p, prefix, saved, g_y))
    return grads


def _flat_grad(pop, grads: dict) -> torch.Tensor:
    """The population's gradient buffer (R, P) holding `grads` ({name: (R, *shape)}; a parameter
    without an entry gets zeros), written by one fused copy into the buffer's views."""
    buffer, views = pop.grad_views()
    names = pop.layout.names
    torch._foreach_copy_([views[n] for n in names], [grads[n] if n in grads else views[n].new_zeros(()).expand_as(views[n])
                                                     for n in names])
    return buffer


def autograd_grads(pop, forward, g_out) -> torch.Tensor:
    """(R, P) gradient of <g_out, forward(flat)> by autograd: for a network kind without a
    hand-written backward (forward: flat parameters -> a tuple of outputs, g_out their gradients)."""
    flat = pop.flat.detach().requires_grad_(True)
    with torch.enable_grad():
        pairs = [(o, g) for o, g in zip(forward(flat), g_out) if o.requires_grad]  # (an ungated kind's balance loss is a constant 0)
        grad = torch.autograd.grad([o for o, _ in pairs], flat, [g for _, g in pairs], allow_unused=True)[0]
    return torch.zeros_like(flat) if grad is None else grad


def head_and_trunk_grads(p, saved, g_out, gate, lb_coef) -> dict:
    """One linear head on a trunk's features, and the trunk under it (an MLP's when `gate` is None,
    else the gated experts'), from the gradient in the head's outputs g_out (R, n, out)."""
    grads = dict(zip(("head.weight", "head.bias"), linear_grads(saved["features"], g_out)))
    g_feat = linear_input_grad(g_out, p["head.weight"])
    if gate is None:
        return {**grads, **mlp_trunk_grads(p, saved, g_feat)}
    return {**grads, **gated_grads(p, "gate.", gate, saved, g_feat, lb_coef, heads=False)}


def actor_grads(actor: PopulationActor, saved: dict, g_mean, g_log_std) -> torch.Tensor:
    """(R, P): the gradient of each member's loss in the actor's parameters, from its gradient in
    the policy mean (R, n, A) and log-std (R, A), plus the router's balance loss at the kind's
    coefficient; `saved` from `actor.evaluate(..., saved=saved)`."""
    t, p = actor.template, actor.params()
    if not actor.by_hand:
        obs, action, routing = saved["inputs"]
        balance = torch.full((actor.R,), float(actor.lb_coef), device=g_mean.device)
        return autograd_grads(actor, lambda flat: (lambda e: (e.mean, e.log_std, e.load_balance))(
            actor.evaluate(obs, action, routing, flat=flat)), (g_mean, g_log_std, balance))
    grads = {"log_std": g_log_std}
    if isinstance(t, MLPActor) or t.cfg.expert_heads == "shared":
        grads.update(head_and_trunk_grads(p, saved, g_mean, None if isinstance(t, MLPActor) else t.gate, actor.lb_coef))
    else:
        grads.update(gated_grads(p, "gate.", t.gate, saved, g_mean, actor.lb_coef, heads=True))
    return _flat_grad(actor, grads)


def critic_grads(critic: PopulationCritic, saved: dict, g_value) -> torch.Tensor:
    """(R, Q): the gradient of each member's loss in the critic's parameters from its gradient in
    the values g_value (R, n), plus the balance loss at the kind's coefficient; `saved` from
    `critic(state, tau, saved=saved)`."""
    t, p = critic.template, critic.params()
    if not critic.by_hand:
        state, tau = saved["inputs"]
        balance = torch.full((critic.R,), float(critic.lb_coef), device=g_value.device)
        return autograd_grads(critic, lambda flat: critic(state, tau, flat=flat)[:2], (g_value, balance))
    gate = None if isinstance(t, MLPCritic) else t.gate
    return _flat_grad(critic, head_and_trunk_grads(p, saved, g_value.unsqueeze(-1), gate, critic.lb_coef))

# %% [markdown]
# **Checked against autograd.** One population of two members per network kind, a random
# gradient on its outputs: the largest difference between the written-out gradient and the one
# autograd takes through the same forward pass, relative to the gradient's largest entry. Where
# they differ at all it is rounding (the same products added in another order); the tests hold every
# gate setting to the same bound.

# %%
from pemamoe.nets import NetConfig, make_actor, make_critic

torch.manual_seed(seed)
for kind in ("mlp", "moe", "smoe"):
    actor = PopulationActor([make_actor(kind, 12, 2, NetConfig(hidden=16)) for _ in range(2)])
    obs = torch.randn(2, 40, 12)
    step = actor.act(obs, torch.ones(2), [torch.Generator().manual_seed(r) for r in range(2)])
    g_mean, g_log_std = torch.randn(2, 40, 2), torch.randn(2, 2)
    saved = {}
    with torch.no_grad():
        actor.evaluate(obs, step.action, step.routing, saved=saved)
        by_hand = actor_grads(actor, saved, g_mean, g_log_std)
    flat = actor.flat.detach().requires_grad_(True)
    new = actor.evaluate(obs, step.action, step.routing, flat=flat)
    (by_autograd,) = torch.autograd.grad(((new.mean * g_mean).sum() + (new.log_std * g_log_std).sum()), flat)
    critic = PopulationCritic([make_critic(kind, 20, NetConfig(hidden=16)) for _ in range(2)])
    state, g_value, saved = torch.randn(2, 30, 20), torch.randn(2, 30), {}
    with torch.no_grad():
        critic(state, torch.ones(2), saved=saved)
        critic_by_hand = critic_grads(critic, saved, g_value)
    cflat = critic.flat.detach().requires_grad_(True)
    (critic_by_autograd,) = torch.autograd.grad((critic(state, torch.ones(2), flat=cflat)[0] * g_value).sum(), cflat)
    gap = ((by_hand - by_autograd).abs().max() / by_autograd.abs().max()).item()
    cgap = ((critic_by_hand - critic_by_autograd).abs().max() / critic_by_autograd.abs().max()).item()
    print(f"{kind:5s} actor: largest relative difference {gap:.1e}; critic: {cgap:.1e}")
    assert gap < 1e-5 and cgap < 1e-5
