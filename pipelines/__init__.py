"""Pipelines: one module per algorithm (``dqn``, ``td3``, ``sac``) on one shared loop (``loop``).

    from rlpipe.pipelines import dqn
    result = dqn.DQN(dqn.preset("dqn")).train("runs/dqn")

Presets are named after the tutorials they reproduce; ``presets()`` lists them.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from rlpipe.pipelines.errors import InputError

__all__ = ["ALGOS", "InputError", "algo_module", "presets", "resolve_preset"]

ALGOS = ("dqn", "td3", "sac")


def algo_module(algo: str) -> ModuleType:
    """The module of pipeline ``algo`` (it holds ``Config``, ``PIPELINE``, ``PRESETS``)."""
    if algo not in ALGOS:
        raise InputError(f"unknown algorithm {algo!r}; expected one of {', '.join(ALGOS)}")
    return importlib.import_module(f"rlpipe.pipelines.{algo}")


def presets() -> dict[str, str]:
    """Every preset name -> its algorithm."""
    names: dict[str, str] = {}
    for algo in ALGOS:
        try:
            module = algo_module(algo)
        except ImportError:
            continue
        names.update({name: algo for name in module.PRESETS})
    return names


def resolve_preset(name: str):
    """(algo, config) for a preset name such as 'dqn' or 'td3-hopper'."""
    known = presets()
    if name not in known:
        import difflib

        close = difflib.get_close_matches(name, list(known), n=3, cutoff=0.4)
        hint = f"did you mean {', '.join(close)}?" if close else f"expected one of {', '.join(known)}"
        raise InputError(f"unknown preset {name!r}; {hint}")
    algo = known[name]
    return algo, algo_module(algo).PRESETS[name]()
