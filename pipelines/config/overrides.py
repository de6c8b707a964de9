"""A config changed from outside: ``key=value`` overrides (the command line), a mapping (a preset file's
``config``), and a config to and from plain data (a run's config.json), each type-checked by OmegaConf's
structured configs and then validated."""

from __future__ import annotations

import dataclasses
import difflib
import typing
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from rlpipe.pipelines.config.schema import _get, flat_keys
from rlpipe.pipelines.config.validation import validate
from rlpipe.pipelines.errors import InputError

__all__ = ["apply_mapping", "apply_overrides", "config_from_dict", "config_to_dict"]


def apply_overrides(cfg, overrides: list[str]):
    """Return a copy of ``cfg`` with ``key=value`` overrides applied, type-checked and validated."""
    keys = flat_keys(type(cfg))
    base = OmegaConf.structured(cfg)
    items = []
    for item in overrides:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise InputError(f"override {item!r} is not of the form key=value (e.g. batch_size=128)")
        entry = _mapping_entry(cfg, key, keys)
        if key not in keys and not entry:
            raise _unknown_key(key, keys)
        if not entry and not value.strip() and _describe_type(cfg, key) == "a string":
            value = "''"  # `ray.address=`: the empty string (OmegaConf reads an empty value as null)
        items.append((key, value))
    try:  # in one merge: each merge copies the whole config (~15 ms a merge here)
        conf = OmegaConf.merge(base, OmegaConf.from_dotlist([f"{key}={value}" for key, value in items]))
    except OmegaConfBaseException as exc:
        conf = base
        for key, value in items:  # one at a time: the first override whose value does not fit, for its line
            try:
                conf = OmegaConf.merge(conf, OmegaConf.from_dotlist([f"{key}={value}"]))
            except OmegaConfBaseException:
                raise InputError(f"{key}={value!r}: expected {_describe_type(cfg, key)}") from exc
    result = OmegaConf.to_object(conf)
    validate(result)
    return result


def apply_mapping(cfg, data: dict[str, Any]):
    """Return a copy of ``cfg`` with a mapping's keys applied (a preset file's ``config``: nested groups as
    mappings, ``collector: {workers: 1}``), each key checked as ``apply_overrides`` checks a ``key=value``, with
    the same errors. Validated without this machine's checks: a file may come from another machine, and the
    overrides given with it fix that (``apply_overrides`` checks the machine)."""
    keys = flat_keys(type(cfg))
    leaves = list(_leaves(data, keys))
    nested: dict[str, Any] = {}
    for key, value in leaves:
        if key not in keys:
            raise _unknown_key(key, keys)
        *groups, leaf = key.split(".")
        into = nested
        for group in groups:
            into = into.setdefault(group, {})
        into[leaf] = value
    base = OmegaConf.structured(cfg)
    try:
        conf = OmegaConf.merge(base, nested)  # in one merge: each merge copies the whole config
    except OmegaConfBaseException as exc:
        for key, value in leaves:  # the key whose value does not fit, for its line
            try:
                OmegaConf.update(base, key, value, merge=False)
            except OmegaConfBaseException:
                raise InputError(f"{key}={value!r}: expected {_describe_type(cfg, key)}") from exc
        raise
    result = OmegaConf.to_object(conf)
    validate(result, machine=False)
    return result


def _leaves(data, keys: list[str], prefix: str = ""):
    """(dotted key, value) for each leaf of a nested mapping; a group's keys come from its mapping."""
    if not isinstance(data, dict):
        example = next(k for k in keys if k.startswith(prefix))[len(prefix):]
        raise InputError(f"{prefix.rstrip('.') or 'config'}={data!r}: expected a mapping of keys to values such as "
                         f"{{{example}: ...}}")
    for name, value in data.items():
        key = f"{prefix}{name}"
        if key not in keys and any(k.startswith(key + ".") for k in keys):
            yield from _leaves(value, keys, key + ".")
        else:
            yield key, value


def _unknown_key(key: str, keys: list[str]) -> InputError:
    close = difflib.get_close_matches(key, keys, n=3, cutoff=0.5)
    hint = f"; closest valid keys: {', '.join(close)}" if close else f"; valid keys: {', '.join(keys)}"
    return InputError(f"unknown config key {key!r}{hint}")


def _mapping_entry(cfg, key: str, keys: list[str]) -> bool:
    """Whether ``key`` is an entry of a mapping key (``env_kwargs.size``): its name is the user's own."""
    parent, _, name = key.rpartition(".")
    return bool(name) and parent in keys and isinstance(_get(cfg, parent), dict)


def _describe_type(cfg, key: str) -> str:
    owner = cfg
    *parents, leaf = key.split(".")
    for p in parents:
        owner = getattr(owner, p)
    ftype = typing.get_type_hints(type(owner))[leaf]
    text = getattr(ftype, "__name__", None) if isinstance(ftype, type) else str(ftype).replace("typing.", "")
    names = {"int": "an integer", "float": "a number", "bool": "true or false", "str": "a string",
             "Optional[int]": "an integer or null", "int | None": "an integer or null",
             "Optional[float]": "a number or null", "float | None": "a number or null", "List[int]": "a list of integers such as [256,256]",
             "list[int]": "a list of integers such as [256,256]"}
    return names.get(text, text)




def config_to_dict(cfg) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def config_from_dict(cls: type, data: dict[str, Any]):
    """Rebuild a config from ``config_to_dict`` output (e.g. a run's config.json), type-checked."""
    try:
        conf = OmegaConf.merge(OmegaConf.structured(cls), OmegaConf.create(data))
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None) or "?"
        raise InputError(f"config does not fit {cls.__name__}: key {key!r}: {str(exc).splitlines()[0]}") from exc
    result = OmegaConf.to_object(conf)
    validate(result, machine=False)  # a saved config may come from another machine: the overrides fix that
    return result
