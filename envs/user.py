"""A user's own env named by a string, as gymnasium and entry points name things: ``module:target``.

* ``my_package.envs:MyArm``: a ``gymnasium.Env`` subclass in an importable module, or a function
  annotated to return a ``gymnasium.Env`` (``def make_arm(size: int = 3) -> gymnasium.Env``);
* ``my_package:MyArm-v0``: gymnasium's own form: importing the module registers the id.

``resolve`` imports the module and returns the gymnasium id to make: the registered one, or for a
class or function one it registers under ``user/module.target`` (in each process that resolves the
string: collector and evaluator processes and Ray actors import the module themselves, found on
their ``sys.path`` as in the trainer's: installed, or on ``PYTHONPATH``).

What a run's config names is constructed only if it says it is an env (an ``Env`` subclass, or a
function whose return annotation is one): a run directory handed to ``rlpipe eval`` cannot make
rlpipe call an arbitrary function of an installed package with keywords of its choosing.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import inspect
import typing
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium
from gymnasium.envs.registration import load_env_creator

__all__ = ["check_kwargs", "is_user_env", "resolve"]

NAMESPACE = "user"
"""gymnasium's namespace for the ids a class or function target is registered under (``user/my_package.envs.MyArm``)"""
EXPECTED = "a gymnasium.Env subclass, or a function annotated to return one (def make(...) -> gymnasium.Env)"


def is_user_env(env: str) -> bool:
    """Whether ``env`` names a module to import (``module:target``) rather than an id in gymnasium's registry."""
    return ":" in env


def resolve(env: str, error: type[Exception]) -> str:
    """The gymnasium id ``env`` (``module:Target`` or ``module:Id-v0``) names, its module imported and a
    class or function target registered; ``error`` (one line: what is wrong, what is expected) otherwise."""
    module_name, _, name = env.partition(":")
    if not module_name or not name or ":" in name:
        raise error(f"env {env!r}: expected module:Target ({EXPECTED}) or module:Id-v0 (an id the module registers)")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise error(f"env {env!r}: cannot import {module_name} ({type(exc).__name__}: {exc}); expected a module "
                    "importable here and in fresh processes: an installed package (pip install -e .) or one on "
                    "PYTHONPATH") from None
    if name in gymnasium.registry:
        return name  # gymnasium's own reading of `module:id`
    target = getattr(module, name, None)
    if target is None:
        close = difflib.get_close_matches(name, [*dir(module), *gymnasium.registry], n=3, cutoff=0.6)
        hint = f" (did you mean {', '.join(repr(c) for c in close)}?)" if close else ""
        raise error(f"env {env!r}: {module_name} has no attribute {name!r} and registers no gymnasium id {name!r}"
                    f"{hint}; expected {EXPECTED}, or an id the module registers")
    _check_target(env, target, error)
    gym_id = f"{NAMESPACE}/{module_name}.{name}"
    if gym_id not in gymnasium.registry:
        gymnasium.register(id=gym_id, entry_point=functools.partial(_construct, env, target, error),
                           disable_env_checker=True)
    return gym_id


def _check_target(env: str, target: Any, error: type[Exception]) -> None:
    if inspect.isclass(target):
        if not issubclass(target, gymnasium.Env):
            raise error(f"env {env!r} is the class {target.__qualname__}, not a gymnasium.Env subclass; expected {EXPECTED}")
        return
    if not inspect.isfunction(target):
        raise error(f"env {env!r} is a {type(target).__name__}; expected {EXPECTED}")
    try:
        returns = typing.get_type_hints(target).get("return")
    except Exception:  # an annotation naming what its module cannot resolve
        returns = None
    origin = typing.get_origin(returns) or returns
    if not (inspect.isclass(origin) and issubclass(origin, gymnasium.Env)):
        shown = "no return annotation" if returns is None else f"a return annotation of {returns!r}"
        raise error(f"env {env!r} is a function with {shown}; expected {EXPECTED}: a run's config constructs only "
                    "what says it is an env")


def _construct(env: str, target: Callable[..., Any], error: type[Exception], **kwargs) -> gymnasium.Env:
    """The entry point registered for a class or function target: its env, checked to be one."""
    made = target(**kwargs)
    if not isinstance(made, gymnasium.Env):
        raise error(f"env {env!r}: {target.__qualname__}() returned a {type(made).__name__}; expected a gymnasium.Env")
    return made


def check_kwargs(gym_id: str, kwargs: Mapping[str, Any], env: str, error: type[Exception]) -> None:
    """``error`` unless the constructor behind ``gym_id`` takes ``kwargs`` (with the id's registered ones):
    the keywords are checked against its signature, so a ``TypeError`` raised inside it stays the env's own."""
    spec = gymnasium.spec(gym_id)
    creator = spec.entry_point if callable(spec.entry_point) else load_env_creator(spec.entry_point)
    if isinstance(creator, functools.partial) and creator.func is _construct:
        creator = creator.args[1]
    try:
        signature = inspect.signature(creator)
    except (TypeError, ValueError):  # a builtin without one: the constructor's own error will say
        return
    try:
        signature.bind(**{**spec.kwargs, **kwargs})
    except TypeError as exc:
        given = ", ".join(f"{k}={v!r}" for k, v in kwargs.items()) or "none"
        name = getattr(creator, "__qualname__", str(creator))
        raise error(f"env {env!r}: env_kwargs ({given}) do not fit {name}{signature}: {exc}; expected keywords its "
                    "constructor takes (env_kwargs.KEY=VALUE)") from None
