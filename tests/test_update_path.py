"""The path of one update, from the `train` command to the optimiser's step: docs/guides/one-update.md's table.

Each algorithm trains from the command line in this process; a global optimiser hook takes the call stack at the
first step and ends the run there. The stack from the command's handler on is the page's table for SAC, and at
most five hops in five files for every algorithm: a new layer between the CLI and the step fails here.
"""

from __future__ import annotations

import re
import traceback
from pathlib import Path

import pytest
from torch.optim.optimizer import register_optimizer_step_pre_hook

import rlpipe.pipelines
from rlpipe.scripts import cli

ROOT = Path(rlpipe.pipelines.__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "guides" / "one-update.md"
SHORT = {"sac": ["sac-pendulum"], "td3": ["td3-pendulum", "learning_starts=64"], "dqn": ["dqn"],
         "crossq": ["crossq-pendulum"]}


class _Stepped(Exception):
    """Raised by the hook at the first optimiser step: the run ends there."""


def path_to_first_step(algo: str, out: Path) -> list[tuple[str, str]]:
    """(file relative to the repository, function) of each frame from ``cmd_train`` to the first optimiser step
    (``torch.optim``'s own wrapper left out)."""
    stacks = []

    def hook(optimizer, args, kwargs):
        stacks.append(traceback.extract_stack()[:-1])
        raise _Stepped

    handle = register_optimizer_step_pre_hook(hook)
    try:
        code = cli.main(["train", *SHORT[algo], "initial_collect_steps=64", "batch_size=16", "num_eval_episodes=1",
                         "eval_in_background=false", "collector.workers=1", "collector.sync=true",
                         "--out", str(out), "--no-progress"])
    finally:
        handle.remove()
    assert code != 0 and stacks, "the run ended before its first optimiser step"
    frames = [(Path(f.filename).resolve(), f.name) for f in stacks[0]]
    start = next(i for i, (path, name) in enumerate(frames) if name == "cmd_train")
    return [(str(path.relative_to(ROOT)), name) for path, name in frames[start:]
            if path.is_relative_to(ROOT) and ".venv" not in path.parts]


def page_table() -> list[tuple[str, str]]:
    rows = re.findall(r"^\| (\d+) \| `([^`]+)` \| `([^`]+)` \|", PAGE.read_text(), re.MULTILINE)
    assert [int(hop) for hop, _, _ in rows] == list(range(len(rows))), rows
    return [(file, function) for _, file, function in rows]


def test_the_sac_update_path_is_the_walkthrough_pages_table(tmp_path, capfd):
    assert path_to_first_step("sac", tmp_path / "run") == page_table()
    capfd.readouterr()


@pytest.mark.parametrize("algo", ["td3", "dqn", "crossq"])
def test_every_algorithms_update_is_five_hops_in_five_files_from_the_command(tmp_path, capfd, algo):
    path = path_to_first_step(algo, tmp_path / "run")
    hops = len(path) - 1
    assert hops <= 5 and len({file for file, _ in path}) <= 5, path
    assert path[-2] == (f"pipelines/{algo}.py", "update"), path  # the update is read in the algorithm's own file
    capfd.readouterr()
