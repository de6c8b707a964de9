"""Pipelines: one module per algorithm (``dqn``, ``td3``, ``sac``) on one shared loop.

    from rlpipe.pipelines import dqn
    result = dqn.DQN(dqn.preset("dqn")).train("runs/dqn")

The map of this package:

    base         OffPolicyPipeline: the algorithm contract, the plug-in surface (env, eval_env,
                 actor, qvalue, loss_module, observation_key), device, collector, replay buffer
    loop         Loop: collect, update, triggers (TF-Agents' Learner.run)
    triggers     Trigger and the built-in ones (log, eval, export, save); add your own
    state        RunState: counters and the work an iteration still owes (saved in checkpoints)
    evaluation   evaluate(), AsyncEvaluator (evaluations while training goes on), BackgroundEvaluator
                 (TorchRL's Evaluator in a process; ray_eval: on a Ray actor)
    runtime      Ctrl-C at safe points, workers deaf to Ctrl-C, GC freeze
    meters       Clock, IntervalStats: speeds, mean losses, training returns
    config       typed configs, key=value overrides, validation (this machine's limits included)
    memory       what a run will allocate, from the env's specs, against the memory available
    rundir, checkpoint, export, files, video, analysis   what a run leaves on disk, and reading it back
    rate_limiter SampleToInsertRatio (Reverb's, for TorchRL collectors)

Presets are named after the tutorials they reproduce; ``presets()`` lists them.
"""

from __future__ import annotations

import difflib
import importlib

from rlpipe.pipelines import _moved
from rlpipe.pipelines.errors import InputError

_moved.install()  # the module paths from before the rooms (``rlpipe.pipelines.loop``, ...), with a DeprecationWarning

__all__ = ["ALGOS", "InputError", "pipeline_class", "presets", "resolve_preset"]

# algorithm -> "module:class"; a fourth algorithm is one new module and one line here.
ALGOS = {
    "dqn": "rlpipe.pipelines.dqn:DQN",
    "td3": "rlpipe.pipelines.td3:TD3",
    "sac": "rlpipe.pipelines.sac:SAC",
}


def pipeline_class(algo: str):
    """The pipeline class of ``algo`` (it holds ``Config``, ``presets``, ``preset()``)."""
    if algo not in ALGOS:
        raise InputError(f"unknown algorithm {algo!r}; expected one of {', '.join(ALGOS)}")
    module, name = ALGOS[algo].split(":")
    return getattr(importlib.import_module(module), name)


def presets() -> dict[str, str]:
    """Every preset name -> its algorithm."""
    return {name: algo for algo in ALGOS for name in pipeline_class(algo).presets}


def resolve_preset(name: str):
    """(algo, config) for a preset name such as 'dqn' or 'td3-hopper'."""
    known = presets()
    if name not in known:
        close = difflib.get_close_matches(name, list(known), n=3, cutoff=0.4)
        hint = f"did you mean {', '.join(close)}?" if close else f"expected one of {', '.join(known)}"
        raise InputError(f"unknown preset {name!r}; {hint}")
    algo = known[name]
    return algo, pipeline_class(algo).preset(name)
