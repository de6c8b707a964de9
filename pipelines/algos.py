"""The algorithms rlpipe ships, by name: ``ALGOS`` (name -> ``"module:class"``) and ``pipeline_class``.

Another algorithm is one new module under ``pipelines/`` and one line here. The classes are imported when
asked for, so that this registry sits below them (what checks a user's input names them from here).
"""

from __future__ import annotations

import importlib

from rlpipe.pipelines.errors import InputError

__all__ = ["ALGOS", "pipeline_class"]

ALGOS = {
    "dqn": "rlpipe.pipelines.dqn:DQN",
    "td3": "rlpipe.pipelines.td3:TD3",
    "sac": "rlpipe.pipelines.sac:SAC",
    "crossq": "rlpipe.pipelines.crossq:CrossQ",
}


def pipeline_class(algo: str):
    """The pipeline class of ``algo`` (it holds ``Config``, ``presets``, ``preset()``)."""
    if algo not in ALGOS:
        raise InputError(f"unknown algorithm {algo!r}; expected one of {', '.join(ALGOS)}")
    module, name = ALGOS[algo].split(":")
    return getattr(importlib.import_module(module), name)
