"""The documentation site's promises: it builds with no warning (``mkdocs build --strict``), readable offline, its
command-line reference names every key, and every code block on it runs as written.

How a page's code blocks are checked (write pages to these rules; they are invisible on the site):

* ``python`` blocks run: all of a page's, in page order, as one script in a fresh folder (the working directory,
  also on ``PYTHONPATH``), so a later block may use an earlier one's names. Keep training in them tiny.
* a ``python`` block with a title (```` ```python title="my_package/envs.py" ````) is a file: it is written at
  that path in the folder and not run itself; the page's other blocks and commands import it.
* ``<!-- test: ... -->``, an HTML comment holding Python: runs at its place in the page's script, unseen by
  the reader (a tiny run whose directory a later block reads, or a check of what a block printed).
* ``bash``/``sh``/``shell``/``console`` blocks: each command line starting with ``rlpipe`` (after a ``$``
  prompt, ``VAR=value`` settings and ``.venv/bin/``) is parsed by the CLI's own parser and resolved, in the same
  folder once the page's Python has run: ``train`` resolves the config that ``--keys`` would print (preset or
  file, overrides, env; ``--resume`` left out), ``presets --show`` loads the preset, ``tune`` and ``ablate``
  make their plans, ``eval --env`` resolves the id. Other lines (pip, cd, pytest) are not checked.
* ``yaml`` blocks with a top-level ``algo:`` are preset files: loaded as ``rlpipe train FILE.yaml`` loads them.
* ``<!-- no-run: why -->`` on the line before a block: the block is neither run nor checked. Such blocks are
  counted per page in ``NO_RUN`` below, so that a new one is a decision someone wrote down.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

NO_RUN: dict[str, int] = {"guides/exported-policy.md": 2, "guides/presets.md": 1, "guides/tune.md": 1}
"""page (relative to docs/) -> how many of its blocks are marked ``<!-- no-run: why -->``"""

SHELL = ("bash", "sh", "shell", "console")


@dataclasses.dataclass
class Block:
    page: str
    line: int
    lang: str
    body: str
    title: str | None = None
    no_run: str | None = None
    hidden: bool = False


def page_blocks(page: Path) -> list[Block]:
    """The fenced code blocks of a page (indented ones inside admonitions and tabs too), and its hidden Python."""
    name = page.relative_to(DOCS).as_posix()
    lines = page.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        stripped = lines[i].lstrip()
        indent = len(lines[i]) - len(stripped)
        fence = re.match(r"(`{3,}|~{3,})\s*([\w+-]*)(.*)$", stripped)
        if stripped.startswith("<!-- test:"):
            start, body = i, [stripped[len("<!-- test:"):]]
            while "-->" not in body[-1] and i + 1 < len(lines):
                i += 1
                body.append(lines[i][indent:])
            body[-1] = body[-1].split("-->")[0]
            blocks.append(Block(name, start + 1, "python", "\n".join(body).strip("\n") + "\n", hidden=True))
        elif fence:
            marker, lang, rest = fence.groups()
            title = re.search(r'title="([^"]+)"', rest)
            previous = next((lines[j].strip() for j in range(i - 1, -1, -1) if lines[j].strip()), "")
            no_run = re.fullmatch(r"<!-- no-run: (.+) -->", previous)
            start, body = i, []
            i += 1
            while i < len(lines) and not lines[i].strip().startswith(marker):
                line = lines[i]
                body.append(line[indent:] if line[:indent].isspace() or not indent else line.lstrip())
                i += 1
            blocks.append(Block(name, start + 1, lang.lower(), "\n".join(body) + "\n",
                                title.group(1) if title else None, no_run.group(1) if no_run else None))
        i += 1
    return blocks


def all_blocks() -> dict[str, list[Block]]:
    return {page.relative_to(DOCS).as_posix(): page_blocks(page) for page in sorted(DOCS.rglob("*.md"))}


def checked(blocks: list[Block]) -> list[Block]:
    return [b for b in blocks if b.no_run is None and (b.lang == "python" or b.lang in SHELL and shell_commands(b)
                                                          or b.lang == "yaml" and is_preset(b))]


def shell_commands(block: Block) -> list[list[str]]:
    """The ``rlpipe`` command lines of a shell block, as argv lists (without ``rlpipe``; a ``> FILE`` stays on)."""
    commands = []
    for line in block.body.replace("\\\n", " ").splitlines():
        line = line.strip().removeprefix("$ ")
        try:
            words = shlex.split(line, comments=True)
        except ValueError as exc:
            raise AssertionError(f"{block.page}:{block.line}: cannot split {line!r}: {exc}") from None
        while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", words[0]):  # PYTHONPATH=. rlpipe ...
            words = words[1:]
        cut = next((i for i, w in enumerate(words) if w in ("|", "&&", ";", "||", "&")), len(words))
        words = words[:cut]
        if words and words[0].removeprefix(".venv/bin/") == "rlpipe":
            commands.append(words[1:])
    return commands


def is_preset(block: Block) -> bool:
    return re.search(r"^algo:", block.body, re.M) is not None


PAGES = {name: blocks for name, blocks in all_blocks().items() if checked(blocks)}


# --- the site builds ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_the_site_builds_strict_offline_with_every_key_and_command(tmp_path):
    site = tmp_path / "site"
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                           "-d", str(site)], cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]  # mkdocs not installed: "No module named mkdocs" (the docs extra)
    warnings = [line for line in log.splitlines() if line.startswith(("WARNING", "ERROR"))]
    assert warnings == [], "\n".join(warnings)

    # the command-line reference: every key of every algorithm, every command's help
    from rlpipe.pipelines import ALGOS, pipeline_class
    from rlpipe.pipelines.config import flat_keys

    cli = (site / "reference" / "cli" / "index.html").read_text()
    for algo in ALGOS:
        missing = [k for k in flat_keys(pipeline_class(algo).Config) if f"<code>{k}</code>" not in cli]
        assert missing == [], f"{algo}: keys missing from reference/cli.md: {missing}"
    for command in ("train", "eval", "video", "plot", "report", "presets", "ablate", "bench", "tune"):
        assert f"usage: rlpipe {command}" in cli, command

    # offline: no page asks another host for a stylesheet, script, font or image
    for page in site.rglob("*.html"):
        html = page.read_text()
        remote = re.findall(r"""<(?:link|script|img)\b[^>]*?(?:href|src)=["']((?:https?:)?//[^"']+)""", html)
        assert remote == [], f"{page.relative_to(site)} loads {remote}"
        assert "fonts.googleapis" not in html and "fonts.gstatic" not in html, page.relative_to(site)
    assert (site / "search" / "search_index.json").exists()


# --- every code block runs -------------------------------------------------------------------------


def test_the_blocks_left_unrun_are_the_ones_listed():
    found = {}
    for name, blocks in all_blocks().items():
        reasons = [f"line {b.line}: {b.no_run}" for b in blocks if b.no_run is not None]
        if reasons:
            found[name] = reasons
    assert {name: len(reasons) for name, reasons in found.items()} == NO_RUN, found


def test_there_are_code_blocks_to_check():
    # a change to the rules above that stopped finding blocks would pass every page test by having none
    assert sum(len(checked(blocks)) for blocks in PAGES.values()) >= 5


def _write_files(blocks: list[Block], folder: Path) -> None:
    for block in blocks:
        if block.title is not None and block.no_run is None:
            path = folder / block.title
            assert not Path(block.title).is_absolute() and ".." not in Path(block.title).parts, \
                f"docs/{block.page}:{block.line}: title={block.title!r}: expected a path inside the page's folder"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(block.body)


def _run_python(blocks: list[Block], folder: Path) -> None:
    runs = [b for b in blocks if b.lang == "python" and b.title is None and b.no_run is None]
    if not runs:
        return
    script = "".join(f"# --- docs/{b.page}:{b.line}{' (hidden)' if b.hidden else ''}\n{b.body}" for b in runs)
    (folder / "_page.py").write_text(script)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(folder), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.run([sys.executable, "_page.py"], cwd=folder, capture_output=True, text=True, timeout=600,
                          env=env)
    assert proc.returncode == 0, f"docs/{runs[0].page}: its Python failed (script: {folder / '_page.py'}):\n" \
                                 f"{proc.stderr[-3000:]}"


def check_command(argv: list[str]) -> None:
    """What ``rlpipe ARGV`` would run with, resolved as the command resolves it; raises on a command that is not real.

    ``rlpipe presets ... > FILE`` runs (it only prints), writing FILE for the page's later commands."""
    from rlpipe.envs import resolve_env_id
    from rlpipe.scripts import ablate, cli, tune

    redirect = next((i for i, w in enumerate(argv) if w.startswith(">")), None)
    target = None
    if redirect is not None:
        target = argv[redirect][1:] or argv[redirect + 1]
        argv = argv[:redirect]
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            args, extra = cli._parser().parse_known_args(argv)
        except SystemExit:
            raise AssertionError(err.getvalue().strip()) from None
    if extra and not (hasattr(args, "overrides") and all("=" in e and not e.startswith("-") for e in extra)):
        raise AssertionError(f"unrecognized arguments: {extra}")
    args.overrides = [*getattr(args, "overrides", []), *extra]
    if args.command == "train":
        keep = [a for i, a in enumerate(argv) if a != "--resume" and (i == 0 or argv[i - 1] != "--resume")]
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = cli.main([*keep, "--keys"], fork_server=False)
        assert code == 0, err.getvalue().strip()
    elif args.command == "presets":
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = cli.main(argv)
        assert code == 0, err.getvalue().strip()
        if target is not None:
            Path(target).write_text(out.getvalue())
    elif args.command == "tune":
        tune.make_plan(args)
    elif args.command == "ablate":
        args.seeds = min(args.seeds, 1)  # the plan's checks (envs, steps, keys) are the same for every seed
        ablate.plan(args)
    elif args.command == "eval" and args.env is not None:
        resolve_env_id(args.env)


@pytest.mark.slow
@pytest.mark.parametrize("page", sorted(PAGES))
def test_every_code_block_of_the_page_runs(page, tmp_path, monkeypatch):
    from rlpipe.pipelines import presets

    blocks = PAGES[page]
    _write_files(blocks, tmp_path)
    _run_python(blocks, tmp_path)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    for block in blocks:
        if block.no_run is not None:
            continue
        if block.lang in SHELL:
            for argv in shell_commands(block):
                try:
                    check_command(argv)
                except Exception as exc:
                    raise AssertionError(f"docs/{page}:{block.line}: rlpipe {shlex.join(argv)}: {exc}") from exc
        elif block.lang == "yaml" and is_preset(block):
            path = tmp_path / (block.title or f"preset-{block.line}.yaml")
            path.write_text(block.body)
            try:
                presets.load(path)
            except Exception as exc:
                raise AssertionError(f"docs/{page}:{block.line}: the preset file does not load: {exc}") from exc
