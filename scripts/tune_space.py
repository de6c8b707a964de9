"""What ``rlpipe tune`` searches: the settings that decide time to a target on a CPU.

Each dimension is one Optuna parameter that sets one or more config keys; an algorithm is searched only
on the dimensions whose keys its config has (``rlpipe train ALGO --keys``), so one table serves SAC,
CrossQ, TD3 and DQN. Several algorithms (``rlpipe tune sac,crossq``) make the algorithm itself a
categorical parameter, and the dimensions are drawn for the one chosen.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rlpipe.pipelines import pipeline_class
from rlpipe.pipelines.config import flat_keys


@dataclass(frozen=True)
class Dim:
    name: str
    """the Optuna parameter"""
    keys: tuple[str, ...]
    """config keys it sets (those the algorithm's config has)"""
    suggest: Callable[[Any, str], Any]
    """(trial, name) -> the value Optuna draws"""
    value: Callable[[Any], Any] = lambda v: v
    """the drawn value -> the config keys' value"""


def _width(v: int) -> list[int]:
    return [v, v]


DIMS: tuple[Dim, ...] = (
    Dim("width", ("actor_fc_layer_params", "critic_fc_layer_params", "critic_joint_fc_layer_params", "fc_layer_params"),
        lambda t, n: t.suggest_categorical(n, [64, 128, 256]), _width),
    Dim("learning_rate", ("learning_rate", "actor_learning_rate", "critic_learning_rate"),
        lambda t, n: t.suggest_float(n, 1e-4, 3e-3, log=True)),
    # random steps, and updates from their end (a preset's own learning_starts would hide the draw)
    Dim("initial_collect_steps", ("initial_collect_steps", "learning_starts"),
        lambda t, n: t.suggest_int(n, 100, 10_000, log=True)),
    Dim("collect_steps_per_iteration", ("collect_steps_per_iteration",),
        lambda t, n: t.suggest_categorical(n, [1, 2, 4])),
    Dim("policy_delay", ("policy_delay",), lambda t, n: t.suggest_int(n, 1, 3)),
    Dim("n_step", ("n_step",), lambda t, n: t.suggest_categorical(n, [1, 2, 3, 5])),
    Dim("batch_size", ("batch_size",), lambda t, n: t.suggest_categorical(n, [64, 128, 256])),
    Dim("collector.workers", ("collector.workers",), lambda t, n: t.suggest_categorical(n, [1, 2])),
    Dim("collector.sync", ("collector.sync",), lambda t, n: t.suggest_categorical(n, [True, False])),
)


def suggest(trial, algos: list[str]) -> tuple[str, list[str]]:
    """(algorithm, its ``key=value`` overrides) for ``trial``: Optuna's draws over ``DIMS``."""
    algo = trial.suggest_categorical("algo", algos) if len(algos) > 1 else algos[0]
    return algo, overrides(algo, {d.name: d.suggest(trial, d.name) for d in dims(algo)})


def dims(algo: str) -> list[Dim]:
    """The dimensions ``algo``'s config has keys for."""
    have = set(flat_keys(pipeline_class(algo).Config))
    return [d for d in DIMS if have.intersection(d.keys)]


def overrides(algo: str, params: dict[str, Any]) -> list[str]:
    """A trial's parameters (``trial.params``) as ``key=value`` overrides of ``algo``'s config."""
    have = set(flat_keys(pipeline_class(algo).Config))
    out: list[str] = []
    for d in dims(algo):
        if d.name in params:
            out += [f"{key}={_text(d.value(params[d.name]))}" for key in d.keys if key in have]
    return out


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ",".join(map(str, value)) + "]"
    return str(value)
