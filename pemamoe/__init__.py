"""pemamoe: the reproducible companion to PE-MAMoE (plasticity-enhanced multi-agent mixture of
experts for UAV-assisted emergency communication networks).

Hand-written (with __main__.py and literate.py); every other module is exported from notebooks/.
Submodules are imported lazily, so `import pemamoe` stays cheap and the exporter can run even
while a generated module is broken.
"""

import importlib

__version__ = "0.1.0"

# Public names re-exported at the top level, and the module each lives in.
_LAZY = {
    "make_env": "env",
    "parallel_env": "env",
    "aec_env": "env",
    "train": "mappo",
    "train_population": "mappo",
    "TrainConfig": "mappo",
    "register_method": "methods",
    "MethodSpec": "methods",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
