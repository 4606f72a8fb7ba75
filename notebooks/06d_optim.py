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
# # 06d · Appendix: AdamW over the run axis
#
# The trainer of notebook 07 keeps a population's parameters as one (R, P) tensor, and a
# plasticity method of notebook 06 acts on one member's optimizer state at a time (an Adam reset,
# a router freeze). This appendix holds the optimizer that serves both, in the module
# `pemamoe.optim`: `RunAdamW` and `group_index`. It knows nothing of plasticity methods.

# %%
#| default_exp optim

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## AdamW for a population
#
# The trainer keeps a population's parameters as one (R, P) tensor, so one optimizer step updates
# every member at once. `RunAdamW` is `torch.optim.AdamW`'s update (decoupled weight decay, bias
# correction) written over that tensor, with what a plasticity method needs per member: its own
# learning rate, moments and step counts per parameter group, a `stepping` mask (a member that
# stopped early on its KL budget does not move), a `frozen` mask per member and group (the router
# freeze), and `reset(member)` (the Adam reset). Where a member does not step, its parameters,
# moments and step counts stay bit-identical. `group_index` assigns each parameter of the flat row
# to the actor's `param_groups()` group. Both are the module `pemamoe.optim`, which knows nothing of
# plasticity methods.
#
# **A partial reset.** `reset(member, mask)` forgets the moments of the masked entries only (ReDo,
# appendix 06c, resets the weights of a few recycled units). Their bias correction must then start
# again as well: with the moments at zero and the group's count $t$ kept, the first step would be
# $\mathrm{lr}\,(1-\beta_1)g / \sqrt{(1-\beta_2)g^2} \approx 3.2\,\mathrm{lr}$, growing to about
# $6.5\,\mathrm{lr}$ ten steps later, instead of a fresh Adam's $\mathrm{lr}$. So a masked entry
# gets a clock of its own: `RunAdamW` remembers its group's count at the reset (`clock_offset`)
# and corrects with the count since then, exactly what a fresh `torch.optim.AdamW` on those
# entries would do. The group's count is untouched, so the other entries of the group go on as
# before; only where the mask covers a whole group is that group's count set back to zero (a
# reset of everything is the plain Adam reset). Until the first partial reset there is no clock
# offset, and the update is the one above, bit for bit.

# %%
#| export
import math

import torch
import torch.nn.functional as F

from pemamoe.methods import ACTOR_PARAM_GROUPS, CRITIC_PARAM_GROUPS

GROUP_NAMES = ACTOR_PARAM_GROUPS + CRITIC_PARAM_GROUPS  # the networks' declared groups (05e), in group_index's order


class RunAdamW:
    """AdamW over a population's flat parameters (R, P), every member with its own learning
    rate, step counts and moments; same update as torch.optim.AdamW (decoupled weight decay).

    `group_of` (P,) assigns each parameter to one of G groups (step counts are per member and
    group, as torch keeps them per parameter). `step(lr, stepping, frozen)` updates member r only
    where stepping[r] and the group is not frozen[r, g]; elsewhere parameters, moments and step
    counts stay bit-identical. `reset(r, mask)` forgets member r's moments where `mask` is True and
    restarts their bias correction there (see `reset`).
    """

    def __init__(self, flat: torch.Tensor, group_of: torch.Tensor, n_groups: int, betas=(0.9, 0.999),
                 eps: float = 1e-5, weight_decay: float = 0.0):
        self.flat = flat
        self.group_of = group_of.to(flat.device)
        self.n_groups = int(n_groups)
        self.beta1, self.beta2 = float(betas[0]), float(betas[1])
        self.eps, self.weight_decay = float(eps), float(weight_decay)
        R = flat.shape[0]
        self.exp_avg = torch.zeros_like(flat, requires_grad=False)
        self.exp_avg_sq = torch.zeros_like(flat, requires_grad=False)
        self.steps = torch.zeros(R, self.n_groups, dtype=flat.dtype, device=flat.device)
        # (R, P): the group's step count at each entry's last partial reset (None until one happens)
        self.clock_offset = None
        # torch's vectorised CPU sqrt takes about 30x longer on an exact zero than on a positive
        # float, and about a third of the second moments are exactly zero (entries no gradient
        # reaches: unchosen experts, dead units, always-zero inputs). Raised to the smallest normal
        # float first, a zero adds at most sqrt(tiny) / sqrt(1 - beta2) to a denominator that then
        # adds eps: when that is far below half a unit in eps's last place, as it is here, the
        # denominator and so the step are the same bits; otherwise no floor.
        finfo = torch.finfo(flat.dtype)
        tiny, half_ulp = finfo.tiny, self.eps * finfo.eps / 8  # a lower bound of half eps's last place, with room
        self.sqrt_floor = tiny if self.beta2 < 1 and math.sqrt(tiny / (1 - self.beta2)) < half_ulp else 0.0

    @torch.no_grad()
    def step(self, lr: torch.Tensor, stepping: torch.Tensor, frozen: torch.Tensor | None = None) -> None:
        """lr (R,), stepping (R,) bool, frozen (R, G) bool or None. Uses and clears flat.grad."""
        p, grad = self.flat, self.flat.grad
        lr = lr.to(p.dtype).unsqueeze(1)
        active_g = stepping.unsqueeze(1) if frozen is None else stepping.unsqueeze(1) & ~frozen  # (R, 1 or G)
        steps = self.steps + active_g
        active_g = active_g.expand(-1, self.n_groups)
        cpu = p.device.type == "cpu"  # on the CPU a data-dependent branch costs nothing; on a GPU it syncs
        if self.clock_offset is not None:  # entries reset on their own count from their reset (see reset)
            onehot = self._onehot()
            active = (active_g.to(p.dtype) @ onehot) > 0.5
            safe = (steps.to(p.dtype) @ onehot - self.clock_offset).clamp(min=1)
            step_size = lr / (1 - self.beta1 ** safe)
            bc2_sqrt = (1 - self.beta2 ** safe).sqrt()
        elif self.n_groups == 1 or (cpu and frozen is None and bool((steps == steps[:, :1]).all())):
            # every group of a member has the same step count: (R, 1) factors broadcast
            active = stepping.unsqueeze(1)
            safe = steps[:, :1].clamp(min=1)
            step_size = lr / (1 - self.beta1 ** safe)
            bc2_sqrt = (1 - self.beta2 ** safe).sqrt()
        else:  # per-element factors: group values spread by a one-hot product (exact: x * 1 + 0)
            onehot = self._onehot()
            active = (active_g.to(p.dtype) @ onehot) > 0.5
            safe = steps.clamp(min=1)
            step_size = (lr / (1 - self.beta1 ** safe)).to(p.dtype) @ onehot
            bc2_sqrt = (1 - self.beta2 ** safe).sqrt().to(p.dtype) @ onehot
        if cpu and frozen is None and bool(stepping.all()):
            # the usual case, in place (on the CPU the check costs nothing; on a GPU it would sync)
            if self.weight_decay:
                p.mul_(1 - lr * self.weight_decay)
            self.exp_avg.lerp_(grad, 1 - self.beta1)
            self.exp_avg_sq.mul_(self.beta2).addcmul_(grad, grad, value=1 - self.beta2)
            p.addcdiv_(self.exp_avg * step_size, self._root(self.exp_avg_sq).div_(bc2_sqrt).add_(self.eps), value=-1.0)
        else:
            m = torch.where(active, self.exp_avg.lerp(grad, 1 - self.beta1), self.exp_avg)
            v = torch.where(active, (self.exp_avg_sq * self.beta2).addcmul_(grad, grad, value=1 - self.beta2), self.exp_avg_sq)
            new = (p * (1 - lr * self.weight_decay)).addcdiv_(m * step_size, self._root(v).div_(bc2_sqrt).add_(self.eps), value=-1.0)
            p.copy_(torch.where(active, new, p))
            self.exp_avg, self.exp_avg_sq = m, v
        self.steps = steps
        self.flat.grad = None

    def _root(self, v: torch.Tensor) -> torch.Tensor:
        """sqrt(v) for the second moments v >= 0, zeros raised to the floor first (see __init__)."""
        return v.clamp(min=self.sqrt_floor).sqrt_() if self.sqrt_floor else v.sqrt()

    def _onehot(self) -> torch.Tensor:
        if getattr(self, "_onehot_cache", None) is None:
            self._onehot_cache = F.one_hot(self.group_of, self.n_groups).T.to(self.flat.dtype).contiguous()
        return self._onehot_cache

    @torch.no_grad()
    def reset(self, member: int, mask: torch.Tensor | None = None) -> None:
        """The Adam reset of a plasticity method, for one member; the other members stay bit-identical.

        mask None: forget all of member's moments and step counts. mask (P,) bool, or a tensor of
        flat indices: forget the moments of those entries only, and restart their bias correction
        (they count their steps from now, as a fresh AdamW would); a group's step count is set
        back to zero only where the mask covers the whole group, so the group's other entries go
        on exactly as before."""
        if mask is None:
            self.exp_avg[member].zero_()
            self.exp_avg_sq[member].zero_()
            self.steps[member].zero_()
            if self.clock_offset is not None:
                self.clock_offset[member].zero_()
            return
        mask = torch.as_tensor(mask, device=self.flat.device)
        if mask.dtype != torch.bool:  # flat indices
            mask = torch.zeros(self.flat.shape[1], dtype=torch.bool, device=self.flat.device).index_fill_(0, mask.reshape(-1), True)
        if mask.shape != self.flat.shape[1:]:
            raise ValueError(f"RunAdamW.reset: mask must have shape ({self.flat.shape[1]},), got {tuple(mask.shape)}")
        self.exp_avg[member].masked_fill_(mask, 0.0)
        self.exp_avg_sq[member].masked_fill_(mask, 0.0)
        hit = torch.bincount(self.group_of[mask], minlength=self.n_groups)
        whole = hit == torch.bincount(self.group_of, minlength=self.n_groups)
        self.steps[member, whole] = 0.0
        partial = mask & ~whole[self.group_of]
        if self.clock_offset is None and bool(partial.any()):
            self.clock_offset = torch.zeros_like(self.exp_avg)
        if self.clock_offset is not None:
            self.clock_offset[member, whole[self.group_of]] = 0.0
            self.clock_offset[member, partial] = self.steps[member][self.group_of[partial]]

    def member_state(self, r: int) -> dict:
        state = {"exp_avg": self.exp_avg[r].detach().cpu().clone(), "exp_avg_sq": self.exp_avg_sq[r].detach().cpu().clone(),
                 "steps": self.steps[r].detach().cpu().clone()}
        if self.clock_offset is not None:  # only after a partial reset: other checkpoints keep their keys
            state["clock_offset"] = self.clock_offset[r].detach().cpu().clone()
        return state

    @torch.no_grad()
    def load_member_state(self, r: int, state: dict) -> None:
        if "clock_offset" in state and self.clock_offset is None:
            self.clock_offset = torch.zeros_like(self.exp_avg)
        if self.clock_offset is not None and "clock_offset" not in state:
            self.clock_offset[r].zero_()
        for name in ("exp_avg", "exp_avg_sq", "steps") + (("clock_offset",) if "clock_offset" in state else ()):
            target = getattr(self, name)[r]
            if tuple(state[name].shape) != tuple(target.shape):
                raise ValueError(f"optimizer state {name!r} has shape {tuple(state[name].shape)}, expected {tuple(target.shape)}")
            target.copy_(state[name].to(target.device))


def group_index(module, layout, group_names=GROUP_NAMES) -> tuple:
    """(group_of (P,) long, names): each parameter of `module` to its param_groups() group."""
    by_id = {id(p): g for g, params in module.param_groups().items() for p in params}
    names = [g for g in group_names if any(by_id.get(id(p)) == g for p in module.parameters())]
    group_of = torch.zeros(layout.size, dtype=torch.long)
    params = dict(module.named_parameters())
    for name in layout.names:
        a, b = layout.span(name)
        group_of[a:b] = names.index(by_id[id(params[name])])
    return group_of, names


# %% [markdown]
# ## Checks
#
# Three members of the SMoE network kind, each from its own seed, stacked into a population, with
# one `RunAdamW` over the actors' flat parameters.

# %%
import copy

from pemamoe.nets import make_actor
from pemamoe.popnets import PopulationActor

obs_dim, R = 24, 3
singles = []
for r in range(R):
    torch.manual_seed(r)
    singles.append(make_actor("smoe", obs_dim))
actor = PopulationActor(singles)
group_of, names = group_index(singles[0], actor.layout)
actor_opt = RunAdamW(actor.flat, group_of, len(names), eps=1e-5, weight_decay=1e-4)
print("groups:", names, "; parameters per member:", actor.layout.size)

# %% [markdown]
# **`RunAdamW` makes AdamW's step.** Member 0 against `torch.optim.AdamW` on a copy of its actor,
# fed the same gradients; member 2 does not step and must stay bit-identical.

# %%
single = copy.deepcopy(singles[0])
torch_opt = torch.optim.AdamW(single.parameters(), lr=1e-3, eps=1e-5, weight_decay=1e-4)
start = actor.flat.detach().clone()
g = torch.Generator().manual_seed(seed)
for _ in range(5):
    grad = torch.randn(actor.flat.shape, generator=g)
    actor.flat.grad = grad.clone()
    actor_opt.step(torch.full((R,), 1e-3, dtype=torch.float64), torch.tensor([True, True, False]))
    for name, p in single.named_parameters():
        a, b = actor.layout.span(name)
        p.grad = grad[0, a:b].reshape(p.shape).clone()
    torch_opt.step()
gap = float((actor.flat[0].detach() - actor.layout.flatten([single])[0]).abs().max())
print(f"largest difference to torch.optim.AdamW after 5 steps: {gap:.2e}; step counts per group {actor_opt.steps.tolist()}")
assert gap < 1e-6
assert torch.equal(actor.flat[2].detach(), start[2]) and actor_opt.steps[2].sum() == 0

# %% [markdown]
# **The square root's floor changes no bit.** Half of every member's gradient entries are exactly
# zero for five steps (as for experts no row reaches), so their second moments stay zero; the same
# steps with the floor switched off must give the same parameters and moments, bit for bit.

# %%
def steps_with_floor(floor: float):
    torch.manual_seed(0)
    flat = actor.layout.flatten(singles).requires_grad_(True)
    opt = RunAdamW(flat, group_of, len(names), eps=1e-5)
    opt.sqrt_floor = floor
    g = torch.Generator().manual_seed(seed)
    for _ in range(5):
        grad = torch.randn(flat.shape, generator=g) * 1e-3
        grad[:, : flat.shape[1] // 2] = 0.0
        flat.grad = grad
        opt.step(torch.full((R,), 1e-3, dtype=torch.float64), torch.tensor([True, True, True]))
    return flat.detach(), opt.exp_avg, opt.exp_avg_sq


floored, plain = steps_with_floor(actor_opt.sqrt_floor), steps_with_floor(0.0)
assert actor_opt.sqrt_floor > 0 and (floored[2] == 0).any()
assert all(torch.equal(a, b) for a, b in zip(floored, plain))
print(f"floor {actor_opt.sqrt_floor:.2e}: {int((floored[2] == 0).sum())} zero second moments, same bits as without it")
