"""mkdocs hook (``hooks:`` in mkdocs.yml): the command-line reference, made at build time from the code.

``reference/cli.md`` holds the prose and two markers; the build puts in their place

* ``<!-- rlpipe: keys -->``: one table of the keys every algorithm shares and one per algorithm (its own
  keys), each key with its default, what it accepts and its docstring. The source is the one
  ``rlpipe train PRESET --keys`` prints from: the config dataclasses through ``pipelines.config``'s
  ``flat_keys`` and ``field_docs``, each key's declared rule (``checked(default, RULE)``) and its type as
  ``apply_overrides`` names it in its errors;
* ``<!-- rlpipe: commands -->``: the ``--help`` of every ``rlpipe`` command, from the CLI's own parsers.

A hook rather than mkdocs-gen-files: no plugin to install, the page keeps its hand-written prose in
``docs/`` where its readers and editors look, and ``mkdocs serve`` remakes it on each rebuild.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import tomllib
from pathlib import Path

from mkdocs.plugins import event_priority

ROOT = Path(__file__).resolve().parents[1]
SOURCE_TREE = ROOT / "build" / "griffe-src"
"""``rlpipe/<package>`` links to the code folders, for mkdocstrings (its ``paths`` in mkdocs.yml): the folders
install under other names (pyproject's package-dir: ``pipelines/`` is ``rlpipe.pipelines``), which griffe,
reading the source where it lies, cannot follow"""
KEYS_MARKER = "<!-- rlpipe: keys -->"
COMMANDS_MARKER = "<!-- rlpipe: commands -->"
PAGE = "reference/cli.md"
HELP_COLUMNS = "100"
"""argparse wraps its help to the terminal's width (``COLUMNS``): a fixed one makes the page the same everywhere"""


def _markdown_text(text: str) -> str:
    """A docstring as one table cell: one line, Markdown's special characters escaped outside `code`."""
    parts = " ".join(text.split()).split("`")
    for i in range(0, len(parts), 2):  # the even parts lie outside code spans
        parts[i] = re.sub(r"([\\*_\[\]|])", r"\\\1", parts[i]).replace("<", "&lt;").replace(">", "&gt;")
    return "`".join(parts)


def _value(cfg, key: str):
    for part in key.split("."):
        cfg = getattr(cfg, part)
    return cfg


def _code(value) -> str:
    return f"`{json.dumps(value)}`"


def key_rows(cls: type, keys: list[str]) -> list[tuple[str, str, str]]:
    """(key, what it accepts, its docstring) for ``keys`` of config class ``cls``."""
    from rlpipe.pipelines.config.overrides import _describe_type
    from rlpipe.pipelines.config.schema import _checks, field_docs

    cfg, docs, rules = cls(), field_docs(cls), _checks(cls)
    rows = []
    for key in keys:
        rule = rules.get(key)
        accepts = rule.describe(_value(cfg, key)) if rule is not None else _describe_type(cfg, key)
        rows.append((key, accepts, docs.get(key, "")))
    return rows


def keys_markdown() -> str:
    from rlpipe.pipelines import ALGOS, pipeline_class
    from rlpipe.pipelines.config import TrainConfig, flat_keys

    configs = {algo: pipeline_class(algo).Config for algo in ALGOS}
    defaults = {algo: cls() for algo, cls in configs.items()}
    shared = flat_keys(TrainConfig)
    out = ["### Keys every algorithm shares", "",
           "The default is each algorithm's where they differ.", "",
           "| key | default | accepts | what it does |", "| --- | --- | --- | --- |"]
    for key, accepts, doc in key_rows(TrainConfig, shared):
        values = {algo: _value(cfg, key) for algo, cfg in defaults.items()}
        if len({json.dumps(v) for v in values.values()}) == 1:
            default = _code(next(iter(values.values())))
        else:
            default = "<br>".join(f"{algo}: {_code(v)}" for algo, v in values.items())
        out.append(f"| `{key}` | {default} | {_markdown_text(accepts)} | {_markdown_text(doc)} |")
    for algo, cls in configs.items():
        own = [k for k in flat_keys(cls) if k not in shared]
        out += ["", f"### {algo}: its own keys", "",
                f"`{cls.__module__.replace('rlpipe.', '', 1)}.{cls.__qualname__}`, beside the shared keys above.", "",
                "| key | default | accepts | what it does |", "| --- | --- | --- | --- |"]
        for key, accepts, doc in key_rows(cls, own):
            out.append(f"| `{key}` | {_code(_value(defaults[algo], key))} | {_markdown_text(accepts)} | "
                       f"{_markdown_text(doc)} |")
    return "\n".join(out) + "\n"


def _commands(parser: argparse.ArgumentParser):
    """``parser`` and each of its subcommands' parsers, depth first, in the order they were added."""
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):  # an alias names the same parser again
                yield from _commands(sub)


def commands_markdown() -> str:
    from rlpipe.scripts.cli import _parser

    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = HELP_COLUMNS
    try:
        out = []
        for parser in _commands(_parser()):
            out += [f"### `{parser.prog}`", "", "```text", parser.format_help().rstrip(), "```", ""]
    finally:
        if before is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = before
    return "\n".join(out)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri != PAGE:
        return markdown
    from mkdocs.exceptions import PluginError

    for marker in (KEYS_MARKER, COMMANDS_MARKER):
        if markdown.count(marker) != 1:
            raise PluginError(f"{PAGE}: expected the marker {marker!r} once, where the build puts what it makes")
    return markdown.replace(KEYS_MARKER, keys_markdown()).replace(COMMANDS_MARKER, commands_markdown())


def link_source_tree() -> None:
    """``SOURCE_TREE/rlpipe/NAME`` -> the folder of each top-level package ``rlpipe.NAME`` (pyproject's package-dir)."""
    package_dir = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    (SOURCE_TREE / "rlpipe").mkdir(parents=True, exist_ok=True)
    for package, folder in package_dir.items():
        if package.count(".") != 1:  # a nested package lies inside its parent's folder
            continue
        link, target = SOURCE_TREE / package.replace(".", "/"), ROOT / folder
        if link.is_symlink() and link.resolve() == target.resolve():
            continue
        tmp = link.with_name(f".{link.name}.{os.getpid()}")  # made aside, then renamed over: builds side by side
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(target, target_is_directory=True)
        os.replace(tmp, link)


@event_priority(100)  # before mkdocstrings reads its paths: a fresh clone has no SOURCE_TREE yet
def on_config(config):
    link_source_tree()
    return config
