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
# # 09h · Appendix: the codecs of a portable state
#
# A portable state (appendix 09d) carries an unfinished run between machines through git, which
# keeps every version committed. It is a small state file and the run's metric rows in chunks,
# each written once. This appendix holds the two codecs that make the state small and the chunks
# exact: log rows to columns and back, and the environments' random buffers to where their
# generators drew them and back. Both are checked where they are written: a chunk is decoded and
# compared with the rows it came from, a buffer redrawn and compared with the buffer.

# %%
#| default_exp portable_codecs

# %% tags=["parameters"]
scale = "small"
figures_dir = "paper_figures"
seed = 0

# %% [markdown]
# ## Rows in columns
#
# The rows are stored column by column (floats as their 8 bytes, byte-shuffled, ints and booleans
# as arrays, anything else as a plain list), with the keys each row has, in its order; the chunk is
# pickled (read back by the unpickler of appendix 07e, which refuses any class) and compared, at the
# write, with the rows it came from. Rows come back as the very numbers they were, NaN payloads and
# signed zeros included, so the run's final logs are the same bytes. Not parquet: a table would
# give a row without a key (the diagnostics are logged every `diag_every` iterations) a null, and
# a column of mixed types one type. The pickle keeps no memo, so equal rows always give equal
# bytes: that is how a later stop recognises a chunk it can list again.

# %%
#| export
import hashlib
import io
import pickle

import numpy as np


class PlainUnpickler(pickle.Unpickler):
    """Unpickles plain data only: any class or function in the stream is refused (as appendix 07e
    reads a checkpoint's log rows)."""

    def find_class(self, module, name):
        raise pickle.UnpicklingError(f"a rows chunk may hold only plain data, found {module}.{name}")


# %%
#| export
def _shuffled(values) -> bytes:
    return np.asarray(values, dtype="<f8").view(np.uint8).reshape(-1, 8).T.tobytes()  # byte planes compress better


def encode_rows(rows) -> bytes:
    """Log rows (dicts of plain data) as one chunk's bytes: columns of the keys in their first
    order, each row's key order, floats byte-shuffled. A function of the values alone (no pickle
    memo), so the same rows always give the same bytes. ValueError if they do not come back whole."""
    keys = list(dict.fromkeys(k for row in rows for k in row))
    index = {k: i for i, k in enumerate(keys)}
    schemas = {}
    schema_of = [schemas.setdefault(tuple(index[k] for k in row), len(schemas)) for row in rows]
    columns = []
    for key in keys:
        values = [row[key] for row in rows if key in row]
        kinds = {type(v) for v in values}
        if kinds == {float}:
            columns.append(("f8", _shuffled(values)))
        elif kinds == {bool}:
            columns.append(("b1", np.asarray(values, dtype=bool).tobytes()))
        elif kinds == {int} and all(-2**63 <= v < 2**63 for v in values):
            columns.append(("i8", np.asarray(values, dtype="<i8").tobytes()))
        else:
            columns.append(("py", values))
    payload = {"rows": len(rows), "keys": keys, "schemas": [list(s) for s in schemas],
               "schema_of_row": np.asarray(schema_of, dtype="<u4").tobytes(), "columns": columns}
    buffer = io.BytesIO()
    pickler = pickle.Pickler(buffer, protocol=5)
    pickler.fast = True  # no memo: the bytes depend on the values, not on which objects were shared
    pickler.dump(payload)
    data = buffer.getvalue()
    try:
        same = _plain_bytes(decode_rows(data)) == _plain_bytes(list(rows))
    except pickle.UnpicklingError as err:  # a class: no checkpoint holds one either
        raise ValueError(f"these log rows do not survive their encoding ({err})") from None
    if not same:
        raise ValueError("these log rows do not survive their encoding")
    return data


def _plain_bytes(obj) -> bytes:
    buffer = io.BytesIO()
    pickler = pickle.Pickler(buffer, protocol=5)
    pickler.fast = True
    pickler.dump(obj)
    return buffer.getvalue()


def decode_rows(data: bytes) -> list:
    """The rows of a chunk (`encode_rows`), as the plain objects they were."""
    payload = PlainUnpickler(io.BytesIO(data)).load()  # refuses any class: the chunk holds plain data only
    columns = []
    for kind, values in payload["columns"]:
        if kind == "f8":
            values = np.frombuffer(values, np.uint8).reshape(8, -1).T.copy().view("<f8").ravel().tolist()
        elif kind in ("b1", "i8"):
            values = np.frombuffer(values, bool if kind == "b1" else "<i8").tolist()  # python bools and ints
        columns.append(iter(values))
    keys, schemas = payload["keys"], payload["schemas"]
    return [{keys[k]: next(columns[k]) for k in schemas[s]}
            for s in np.frombuffer(payload["schema_of_row"], "<u4").tolist()]


# %% [markdown]
# ## Random buffers as where they were drawn
#
# The state alone is small only if the environments' random streams are: each environment reads
# its normal and uniform variates through a buffer of `rng_chunk` numbers (appendix 04c), 64 x
# 4,096 x 2 doubles at the paper scale, 4 MB of random bits that no compressor shrinks, and most of
# a format-1 portable state. But a buffer is always the last `rng_chunk` numbers its generator drew, so
# the state stores, per environment, only how far back in the generator's stream the buffer starts
# (numpy's PCG64 steps backwards as cheaply as forwards); every buffer is redrawn at a write and
# compared bit for bit, and one that does not redraw (never filled, another generator) is stored
# as it is. The state keeps each buffer's sha256, so a numpy that draws differently is refused.

# %%
#| export
def _redraw(state: dict, kind: str, back: int, n: int) -> np.ndarray:
    """The `n` numbers of `kind` a generator in `state` draws after stepping `back` draws backwards."""
    bits = np.random.PCG64()
    bits.state = state
    bits.advance((1 << 128) - back)  # PCG64 walks a cycle of 2**128 states: forwards by that much less is backwards
    gen = np.random.Generator(bits)
    return gen.standard_normal(n) if kind == "normal" else gen.random(n)


def _where_drawn(row: np.ndarray, state: dict, kind: str):
    """How many raw draws back from `state` the numbers of `row` start, or None when they are not
    the last ones its generator drew. A uniform takes one draw, a normal one or more."""
    if not (isinstance(state, dict) and state.get("bit_generator") == "PCG64" and kind in ("normal", "uniform")):
        return None
    n = len(row)
    for back in range(n, 2 * n + 1 if kind == "normal" else n + 1):
        first = _redraw(state, kind, back, 1)
        if first.tobytes() == row[:1].tobytes() and _redraw(state, kind, back, n).tobytes() == row.tobytes():
            return back
    return None


def compact_env_state(env: dict) -> dict:
    """A checkpoint's (encoded) environment state with each random buffer replaced by where its
    generator drew it (rows that do not redraw kept as they are) and its sha256."""
    import torch

    rng = env.get("rng") if isinstance(env, dict) else None
    if not (isinstance(rng, dict) and isinstance(rng.get("buffers"), dict) and isinstance(rng.get("generators"), list)):
        return env
    buffers = {}
    for kind, encoded in rng["buffers"].items():
        buf = encoded["__ndarray__"].numpy() if isinstance(encoded, dict) and set(encoded) == {"__ndarray__"} else None
        if buf is None or buf.ndim != 2 or buf.dtype != np.float64 or len(buf) != len(rng["generators"]):
            buffers[kind] = encoded
            continue
        back = [_where_drawn(buf[b], gens.get(kind), kind) for b, gens in enumerate(rng["generators"])]
        raw = [b for b, k in enumerate(back) if k is None]
        buffers[kind] = {"__redrawn__": {
            "back": torch.tensor([-1 if k is None else k for k in back], dtype=torch.int64),
            "raw": torch.from_numpy(buf[raw].copy()), "columns": int(buf.shape[1]),
            "sha256": hashlib.sha256(buf.tobytes()).hexdigest()}}
    return {**env, "rng": {**rng, "buffers": buffers}}


def expand_env_state(env: dict) -> dict:
    """The inverse of `compact_env_state`; ValueError when a buffer does not
    redraw to the sha256 it had."""
    import torch

    rng = env.get("rng") if isinstance(env, dict) else None
    if not (isinstance(rng, dict) and isinstance(rng.get("buffers"), dict)):
        return env
    buffers = {}
    for kind, stored in rng["buffers"].items():
        if not (isinstance(stored, dict) and set(stored) == {"__redrawn__"}):
            buffers[kind] = stored
            continue
        s = stored["__redrawn__"]
        back, raw = s["back"].tolist(), iter(s["raw"].numpy())
        buf = np.stack([next(raw) if k < 0 else _redraw(rng["generators"][b][kind], kind, k, s["columns"])
                        for b, k in enumerate(back)]) if back else np.empty((0, s["columns"]))
        if hashlib.sha256(buf.tobytes()).hexdigest() != s["sha256"]:
            raise ValueError(f"holds {kind} random buffers that redraw to other numbers under numpy {np.__version__} "
                             "than they held (sha256 differs): resume it with the numpy that wrote it")
        buffers[kind] = {"__ndarray__": torch.from_numpy(buf)}
    return {**env, "rng": {**rng, "buffers": buffers}}


# %% [markdown]
# ## Demonstration
#
# Rows with a missing key, a NaN with its sign and payload set, a signed zero and an integer past
# 64 bits come back as the very objects they were; the random buffers of a batch of environments
# that have drawn a few numbers come back bit for bit from a few integers per environment.

# %%
import struct

from pemamoe.bookkeeping import encode_arrays
from pemamoe.streams import BatchRandom

nan = struct.unpack("<d", struct.pack("<Q", 0xFFF8000000000001))[0]
rows = [{"iteration": 0, "loss": 0.25, "diag": 1.0}, {"iteration": 1, "loss": nan}, {"loss": -0.0, "iteration": 2**70}]
back = decode_rows(encode_rows(rows))
assert _plain_bytes(back) == _plain_bytes(rows) and [list(r) for r in back] == [list(r) for r in rows]
print(f"{len(rows)} rows in {len(encode_rows(rows))} bytes, back as they were")

streams = BatchRandom(range(8), chunk=256)
streams.standard_normal((8, 100)), streams.random((8, 200)), streams.random((8, 200))  # one refill
env = {"rng": encode_arrays(streams.state_dict())}  # as a checkpoint holds it (appendix 07e)
small = compact_env_state(env)
print({kind: b["__redrawn__"]["back"].tolist()[:3] for kind, b in small["rng"]["buffers"].items()},
      "raw draws back, for the first 3 of 8 environments")
again = expand_env_state(small)["rng"]["buffers"]
assert all(np.array_equal(again[k]["__ndarray__"].numpy(), v) for k, v in streams.state_dict()["buffers"].items())
print("every buffer redrawn bit for bit")
