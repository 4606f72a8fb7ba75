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
# # 04c · Appendix: one random stream per environment, read as a batch
#
# The physics of notebooks 01–03 draws its randomness as arrays whose leading axis is the batch of
# environments. For a batch to be exact, environment b must draw what a lone environment with its
# seed would draw. This appendix holds the generator that guarantees it, in the module
# `pemamoe.streams`. It sits below notebook 04's model and imports nothing of the environment.

# %%
#| default_exp streams

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## Per-environment random streams, drawn as one batch
#
# The physics functions of notebooks 01–03 take a random generator and draw arrays whose leading
# axis is the batch. `BatchRandom` is a generator for that purpose: a draw of shape `(B, ...)`
# takes row `b` from environment `b`'s own stream. Each environment has two numpy generators (one
# for normal variates, one for uniforms), read through buffers of `rng_chunk` numbers so that a
# step costs a few array slices rather than B generator calls. Gamma variates come from uniforms
# through the inverse regularised incomplete gamma function, which keeps the count of uniforms per
# draw fixed; every draw of every step consumes a fixed count of numbers, whatever the values.
# Resetting environment b with a seed rebuilds only its streams.

# %%
#| export
import math

import numpy as np
from scipy import special


class BatchRandom:
    """Duck-typed numpy Generator whose (B, ...) draws take row b from environment b's stream."""

    def __init__(self, seeds, chunk: int = 4096):
        self.chunk = int(chunk)
        n = len(seeds)
        self._buffers = {"normal": np.empty((n, self.chunk)), "uniform": np.empty((n, self.chunk))}
        self._cursor = {kind: np.full(n, self.chunk) for kind in self._buffers}
        # While every environment has read the same amount (the usual case: whole-batch draws),
        # the shared position lives here and a draw is one slice; None means "use _cursor".
        self._common = {kind: self.chunk for kind in self._buffers}
        self._gens = [None] * n
        self._rows = np.arange(n)
        self._full = True
        for b, s in enumerate(seeds):
            self.reseed(b, s)

    @property
    def batch(self) -> int:
        return len(self._rows)

    def reseed(self, b: int, seed) -> None:
        """Restart environment b's streams from `seed` (an int, a SeedSequence or None)."""
        seq = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        normal_seq, uniform_seq = seq.spawn(2)
        self._gens[b] = {"normal": np.random.default_rng(normal_seq), "uniform": np.random.default_rng(uniform_seq)}
        for kind in self._buffers:
            self._desync(kind)
            self._cursor[kind][b] = self.chunk
            self._resync(kind)

    def select(self, rows) -> "BatchRandom":
        """A view drawing only for environments `rows` (used to reset some environments)."""
        rows = np.asarray(rows, dtype=int)
        if len(rows) == len(self._gens) and np.array_equal(rows, self._rows):
            return self
        view = object.__new__(BatchRandom)
        view.__dict__.update(self.__dict__)  # shares buffers, cursors and generators
        view._rows, view._full = rows, False
        return view

    def _desync(self, kind: str) -> None:
        if self._common[kind] is not None:
            self._cursor[kind][:] = self._common[kind]
            self._common[kind] = None

    def _resync(self, kind: str) -> None:
        cur = self._cursor[kind]
        if self._common[kind] is None and np.all(cur == cur[0]):
            self._common[kind] = int(cur[0])

    def _take(self, kind: str, size) -> np.ndarray:
        size = (size,) if isinstance(size, (int, np.integer)) else tuple(size)
        if not size or size[0] != len(self._rows):
            raise ValueError(f"BatchRandom draws need a leading batch axis of {len(self._rows)}, got size={size}")
        k = math.prod(size[1:])
        if k > self.chunk:
            raise ValueError(f"a draw of {k} numbers per environment exceeds rng_chunk={self.chunk}")
        buf = self._buffers[kind]
        common = self._common[kind]
        if self._full and common is not None:  # fast path: one slice for the whole batch
            if common + k > self.chunk:
                for b in range(len(self._gens)):
                    buf[b] = np.concatenate([buf[b, common:], self._draw(self._gens[b][kind], kind, common)])
                common = 0
            self._common[kind] = common + k
            # A copy, not a view: a later refill rewrites the buffer, and a caller may still be
            # holding this draw (sample_channel draws Rician x, then y, then uses both).
            return np.array(buf[:, common:common + k]).reshape(size)
        self._desync(kind)
        cur, rows = self._cursor[kind], self._rows
        for b in rows[cur[rows] + k > self.chunk]:
            # Refill: keep the unread tail, then append fresh numbers from b's own generator.
            tail = buf[b, cur[b]:].copy()
            fresh = self._draw(self._gens[b][kind], kind, self.chunk - tail.size)
            buf[b] = np.concatenate([tail, fresh])
            cur[b] = 0
        start = cur[rows]
        if np.all(start == start[0]):
            out = buf[rows, start[0]:start[0] + k]
        else:
            out = buf[rows[:, None], start[:, None] + np.arange(k)]
        cur[rows] = start + k
        self._resync(kind)
        return out.reshape(size)

    def state_dict(self) -> dict:
        """Everything needed to continue every stream exactly (numpy arrays and plain dicts)."""
        for kind in self._buffers:
            self._desync(kind)
            self._resync(kind)
        return {
            "buffers": {k: v.copy() for k, v in self._buffers.items()},
            "cursor": {k: v.copy() for k, v in self._cursor.items()},
            "generators": [{k: g.bit_generator.state for k, g in gens.items()} for gens in self._gens],
        }

    def load_state_dict(self, state: dict) -> None:
        if len(state["generators"]) != len(self._gens):
            raise ValueError(f"state holds {len(state['generators'])} streams, this batch has {len(self._gens)}")
        for kind in self._buffers:
            self._buffers[kind][...] = state["buffers"][kind]
            self._common[kind] = None
            self._cursor[kind][...] = state["cursor"][kind]
            self._resync(kind)
        for gens, saved in zip(self._gens, state["generators"]):
            for kind, g in gens.items():
                g.bit_generator.state = saved[kind]

    @staticmethod
    def _draw(gen, kind, n):
        return gen.standard_normal(n) if kind == "normal" else gen.random(n)

    # The subset of numpy.random.Generator's interface that the physics functions use.
    def random(self, size):
        return self._take("uniform", size)

    def uniform(self, low=0.0, high=1.0, size=None):
        return low + (np.asarray(high) - low) * self._take("uniform", size)

    def standard_normal(self, size):
        return self._take("normal", size)

    def normal(self, loc=0.0, scale=1.0, size=None):
        return loc + np.asarray(scale) * self._take("normal", size)

    def integers(self, low, high=None, size=None):
        low, high = (0, low) if high is None else (low, high)
        return (low + np.floor(self._take("uniform", size) * (high - low))).astype(int)

    def gamma(self, shape, scale=1.0, size=None):
        return self.gamma_from_uniform(self._take("uniform", size), shape, scale)

    @staticmethod
    def gamma_from_uniform(u, shape, scale=1.0):
        """Gamma(shape, scale) variates by inversion of the uniforms u."""
        if np.all(np.asarray(shape) == 1.0):  # exponential: the common Nakagami m = 1, and cheap
            return -np.asarray(scale) * np.log1p(-u)
        return np.asarray(scale) * special.gammaincinv(shape, u)


# %% [markdown]
# A batch's streams do not depend on the batch: environment 1 of a batch seeded (5, 6, 7) draws the
# numbers a lone environment seeded 6 draws, across buffer refills.

# %%
wide, alone = BatchRandom([5, 6, 7], chunk=128), BatchRandom([6], chunk=128)
same = all(np.array_equal(wide.standard_normal((3, n))[1], alone.standard_normal((1, n))[0]) for n in (50, 70, 90))
print("environment 1 of the batch draws what a lone environment draws:", same)
