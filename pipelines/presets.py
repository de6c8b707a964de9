"""Presets as files: one YAML file per preset, read by the command line and Python alike.

    from rlpipe.pipelines import presets
    algo, cfg = presets.load("sac-pendulum")          # a preset shipped in presets/, by name
    algo, cfg = presets.load("my-runs/arm.yaml")      # or a file of your own
    presets.save("my-runs/arm.yaml", algo, cfg, comment="arm: sized for time to 100")

A preset file names its algorithm, optionally the task it is for, and the keys of the algorithm's config
that differ from the config class's defaults (a key not given keeps its default; a group such as
``collector`` is a mapping of its own keys)::

    # sac-pendulum: Pendulum-v1 to -200, sized for time to target on a 2-core CPU; figures: BENCHMARKS.md, ...
    algo: sac
    info: {env: Pendulum-v1, targets: [-200.0], task: sized for time to -200, sized: true}
    config:
      env: Pendulum-v1
      num_iterations: 7500
      collector: {workers: 1, sync: true}

The name of a preset is its file's stem. The shipped files are the package ``rlpipe.presets`` (the
repository's top-level ``presets/`` folder). A file is read with YAML's safe loader (data only), and its keys
are checked as ``key=value`` overrides are (``config.apply_mapping``): an unknown key or a bad value is the
same one line, naming the file.
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
import difflib
import functools
import importlib.resources
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from rlpipe.pipelines.artifacts.files import write_text_atomic
from rlpipe.pipelines.config import PresetInfo, TrainConfig, apply_mapping, flat_keys
from rlpipe.pipelines.errors import InputError

__all__ = ["Preset", "info", "is_file", "load", "names", "read", "save", "source", "text"]

SUFFIXES = (".yaml", ".yml")
"""what makes the first argument of ``rlpipe train`` a file rather than a preset's name (as does a '/')"""

TOP_KEYS = ("algo", "info", "config")
INFO_KEYS = tuple(f.name for f in dataclasses.fields(PresetInfo))


@dataclass(frozen=True)
class Preset:
    """One preset file, read and checked."""

    name: str
    """the file's stem"""
    algo: str
    """one of ``rlpipe.pipelines.ALGOS``"""
    config: TrainConfig
    """the algorithm's config: its class's defaults with the file's keys applied"""
    info: PresetInfo | None
    """the task the preset is for (env, targets), where the file says"""
    where: str
    """the file, as errors name it"""


class _Loader(yaml.SafeLoader):
    """YAML's safe loader (data only), with YAML 1.2's floats (``1e-3`` is a number, not a string) and a key
    given twice refused (its first value would be lost without a word)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"key {key!r} given twice", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _shipped():
    return importlib.resources.files("rlpipe.presets")


def is_file(name_or_path: str | os.PathLike) -> bool:
    """Whether ``name_or_path`` names a file (a path, or a name ending in .yaml/.yml) rather than a shipped preset."""
    text = os.fspath(name_or_path)
    return isinstance(name_or_path, os.PathLike) or text.endswith(SUFFIXES) or "/" in text or os.sep in text


@functools.cache
def _catalogue() -> dict[str, tuple[str, dict]]:
    """name -> (algo, the file's data) for every shipped preset, in ``ALGOS`` order, then by name."""
    from rlpipe.pipelines import ALGOS

    files = sorted(f for f in _shipped().iterdir() if f.name.endswith(SUFFIXES))
    found = {}
    for f in files:
        name = f.name.rsplit(".", 1)[0]
        data = _parse(f.read_text(encoding="utf-8"), f"presets/{f.name}")
        found[name] = (data["algo"], data)
    order = list(ALGOS)
    return dict(sorted(found.items(), key=lambda item: (order.index(item[1][0]), item[0])))


def names() -> dict[str, str]:
    """Every shipped preset's name -> its algorithm, in ``ALGOS`` order, each algorithm's by name (its tutorial's,
    named for the algorithm, first)."""
    return {name: algo for name, (algo, _) in _catalogue().items()}


def source(name_or_path: str | os.PathLike) -> str:
    """Where a preset's file is (the shipped file for a name); ``InputError`` for an unknown name."""
    if is_file(name_or_path):
        return os.fspath(name_or_path)
    known = names()
    if name_or_path not in known:
        close = difflib.get_close_matches(name_or_path, list(known), n=3, cutoff=0.4)
        hint = f"did you mean {', '.join(close)}?" if close else f"expected one of {', '.join(known)}"
        raise InputError(f"unknown preset {name_or_path!r}; {hint} (or a preset file: PATH.yaml)")
    return str(next(f for f in _shipped().iterdir() if f.name.rsplit(".", 1)[0] == name_or_path
                    and f.name.endswith(SUFFIXES)))


def text(name_or_path: str | os.PathLike) -> str:
    """The preset file as written (``rlpipe presets --show NAME``)."""
    if not is_file(name_or_path):
        source(name_or_path)  # an unknown name: its line
        return next(f for f in _shipped().iterdir() if f.name in {f"{name_or_path}{s}" for s in SUFFIXES}).read_text(
            encoding="utf-8")
    return _read_file(Path(name_or_path))


def read(name_or_path: str | os.PathLike) -> Preset:
    """The preset of a shipped name (``"sac-pendulum"``) or in a file (``"path/to/my.yaml"``), checked."""
    if is_file(name_or_path):
        path = Path(name_or_path)
        where = os.fspath(name_or_path)
        data = _parse(_read_file(path), where)
        name = path.name.rsplit(".", 1)[0] if path.name.endswith(SUFFIXES) else path.name
        return _build(name, data, where)
    source(name_or_path)  # an unknown name: its line
    shipped = _shipped_preset(name_or_path)
    return dataclasses.replace(shipped, config=copy.deepcopy(shipped.config))  # a config of its own to change


@functools.cache
def _shipped_preset(name: str) -> Preset:
    return _build(name, _catalogue()[name][1], f"presets/{name}.yaml")


def load(name_or_path: str | os.PathLike) -> tuple[str, TrainConfig]:
    """(algo, config) of a shipped preset's name or a preset file; a fresh config each call."""
    preset = read(name_or_path)
    return preset.algo, preset.config


def info(name_or_path: str | os.PathLike) -> PresetInfo | None:
    """The task a preset is for (env, targets, whether it is sized for time to them); None where its file says none."""
    return read(name_or_path).info


def save(path: str | os.PathLike, algo: str, config: TrainConfig, info: PresetInfo | None = None,
         comment: str = "") -> Path:
    """Write ``config`` as a preset file: the keys that differ from the algorithm's config defaults, ``info`` if
    given, and ``comment`` as its first lines (default: the preset's name, algorithm and env). The file is
    replaced whole (written beside it, then renamed), and read back to check it loads to ``config``."""
    from rlpipe.pipelines import pipeline_class

    Config = pipeline_class(algo).Config
    if not isinstance(config, Config):
        raise InputError(f"config is a {type(config).__name__}; expected {Config.__name__} for {algo}")
    path = Path(path)
    if not path.name.endswith(SUFFIXES):
        raise InputError(f"{path}: a preset file's name ends in .yaml (the preset's name is its stem)")
    name = path.name.rsplit(".", 1)[0]
    data: dict[str, Any] = {"algo": algo}
    if info is not None:
        data["info"] = {"env": info.env, "targets": [float(t) for t in info.targets], "task": info.task,
                        "sized": bool(info.sized), **({"measured": dict(info.measured)} if info.measured else {})}
    data["config"] = _differences(config, Config())
    lines = (comment or f"{name}: {algo} on {config.env}").splitlines()
    body = "".join(f"# {line}".rstrip() + "\n" for line in lines)
    body += yaml.safe_dump(data, sort_keys=False, default_flow_style=None, allow_unicode=True, width=120)
    written = _build(name, _parse(body, os.fspath(path)), os.fspath(path))
    if written.config != config or written.info != (_as_info(info) if info is not None else None):
        raise ValueError(f"{path}: the preset does not read back as the config given")  # a value YAML cannot hold
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, body)  # readable as any other file (0o644), replaced whole, fsynced


# --- reading and checking a file ------------------------------------------------------------------


def _read_file(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        stem = path.name.rsplit(".", 1)[0]
        if stem in names():
            raise InputError(f"{path}: no such preset file; expected a preset file, or a preset's name such as "
                             f"{stem} (the shipped {stem!r}: rlpipe train {stem})") from None
        raise InputError(f"{path}: no such preset file; expected a YAML preset file (`rlpipe presets --show sac` "
                         "prints one) or a preset's name (`rlpipe presets` lists them)") from None
    except (OSError, UnicodeDecodeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise InputError(f"{path}: cannot be read ({why}); expected a readable YAML preset file") from None


def _parse(body: str, where: str) -> dict:
    """The file's top-level mapping, its algorithm checked."""
    from rlpipe.pipelines import ALGOS

    try:
        data = yaml.load(body, Loader=_Loader)  # noqa: S506 (a SafeLoader: data only)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise InputError(f"{where}: not valid YAML{at}: {problem}; expected a preset file "
                         "(`rlpipe presets --show sac` prints one)") from None
    if not isinstance(data, dict):
        raise InputError(f"{where}: holds {type(data).__name__ if data is not None else 'nothing'}; expected a "
                         "mapping with algo, config and optionally info (`rlpipe presets --show sac` prints one)")
    unknown = [k for k in data if k not in TOP_KEYS]
    if unknown:
        raise InputError(f"{where}: unknown key {unknown[0]!r} at the top level; expected {', '.join(TOP_KEYS)} "
                         "(a config key goes under config:)")
    if "algo" not in data:
        raise InputError(f"{where}: no algo; expected algo: one of {', '.join(ALGOS)}")
    if data["algo"] not in ALGOS:
        raise InputError(f"{where}: algo={data['algo']!r}: expected one of {', '.join(ALGOS)}")
    return data


def _build(name: str, data: dict, where: str) -> Preset:
    from rlpipe.pipelines import pipeline_class

    algo = data["algo"]
    keys = data.get("config")
    try:
        config = apply_mapping(pipeline_class(algo).Config(), {} if keys is None else keys)
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None
    return Preset(name=name, algo=algo, config=config, info=_info(data.get("info"), config, where), where=where)


def _info(data, config: TrainConfig, where: str) -> PresetInfo | None:
    if data is None:
        return None
    if not isinstance(data, dict):
        raise InputError(f"{where}: info={data!r}: expected a mapping such as {{env: Pendulum-v1, targets: [-200]}}")
    unknown = [k for k in data if k not in INFO_KEYS]
    if unknown:
        raise InputError(f"{where}: unknown key 'info.{unknown[0]}'; expected one of "
                         f"{', '.join('info.' + k for k in INFO_KEYS)}")
    env = data.get("env", config.env)
    targets = data.get("targets", [])
    targets = [targets] if isinstance(targets, int | float) and not isinstance(targets, bool) else targets
    task, sized, measured = data.get("task", ""), data.get("sized", True), data.get("measured", {})
    if not isinstance(env, str) or not env:
        raise InputError(f"{where}: info.env={env!r}: expected a gymnasium env id such as Pendulum-v1")
    if not isinstance(targets, list) or not all(isinstance(t, int | float) and not isinstance(t, bool) for t in targets):
        raise InputError(f"{where}: info.targets={targets!r}: expected a list of returns such as [-200]")
    if not isinstance(task, str):
        raise InputError(f"{where}: info.task={task!r}: expected a few words such as 'sized for time to -200'")
    if not isinstance(sized, bool):
        raise InputError(f"{where}: info.sized={sized!r}: expected true or false")
    return PresetInfo(env, tuple(float(t) for t in targets), task, sized, _measured(measured, where))


MEASURED_KEYS = {"seconds": (int, float), "target": (int, float), "date": (str, datetime.date), "commit": (str,)}


def _measured(data, where: str) -> tuple[tuple[str, Any], ...]:
    """``info.measured``: ``{seconds: 7.3, date: '2026-11-29', commit: c98d626}`` (``target`` too, for a preset with two)."""
    expected = "expected a mapping such as {seconds: 7.3, date: '2026-11-29', commit: c98d626}"
    if not isinstance(data, dict) or (data and "seconds" not in data):
        raise InputError(f"{where}: info.measured={data!r}: {expected}")
    for key, value in data.items():
        if key not in MEASURED_KEYS or not isinstance(value, MEASURED_KEYS[key]) or isinstance(value, bool):
            raise InputError(f"{where}: info.measured.{key}={value!r}: {expected}")
    return tuple((key, str(value) if isinstance(value, datetime.date) else value) for key, value in data.items())


def _as_info(info: PresetInfo) -> PresetInfo:
    return PresetInfo(info.env, tuple(float(t) for t in info.targets), info.task, bool(info.sized), info.measured)


def _differences(config: TrainConfig, defaults: TrainConfig) -> dict:
    """The keys of ``config`` whose value differs from ``defaults``, a group's (``collector.workers``) in a mapping
    of its own, in the config class's order."""
    out: dict[str, Any] = {}
    for key in flat_keys(type(config)):
        value = functools.reduce(getattr, key.split("."), config)
        if value != functools.reduce(getattr, key.split("."), defaults):
            *groups, leaf = key.split(".")
            into = out
            for group in groups:
                into = into.setdefault(group, {})
            into[leaf] = list(value) if isinstance(value, tuple) else value
    return out
