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


CHOICES: dict[str, tuple[Any, ...]] = {
    "width": (64, 128, 256), "collect_steps_per_iteration": (1, 2, 4), "n_step": (1, 2, 3, 5),
    "batch_size": (64, 128, 256), "collector.workers": (1, 2), "collector.sync": (True, False)}
"""the categorical dimensions' choices (as DIMS draws them)"""
RANGES: dict[str, tuple[float, float]] = {"learning_rate": (1e-4, 3e-3), "initial_collect_steps": (100, 10_000),
                                          "policy_delay": (1, 3)}
"""the numeric dimensions' bounds (as DIMS draws them)"""


def params_of(algo: str, cfg) -> dict[str, Any]:
    """The parameters that give ``cfg`` back, as far as the search space holds its values: the study's first trial
    is the config ``rlpipe train ALGO env=ENV`` trains (the sized default), so that the best setting found is never
    slower than where the search started, and TPE starts from it. A value the space does not hold is left to Optuna."""
    import functools

    values = {key: functools.reduce(getattr, key.split("."), cfg) for key in flat_keys(type(cfg))}
    found: dict[str, Any] = {}
    for d in dims(algo):
        key = next(k for k in d.keys if k in values)
        value = values[key]
        if d.name == "width":
            value = value[0] if isinstance(value, list) and value and len(set(value)) == 1 else None
        if d.name in CHOICES and value in CHOICES[d.name] and type(value) is type(CHOICES[d.name][0]):
            found[d.name] = value
        elif d.name in RANGES and isinstance(value, (int, float)) and not isinstance(value, bool) \
                and RANGES[d.name][0] <= value <= RANGES[d.name][1]:
            found[d.name] = value
    return found


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
