"""Before against after, alternated in one command, with CleanRL beside where it runs (``python -m``).

    git worktree add --detach /tmp/before COMMIT
    python -m rlpipe.scripts.bench.before_after --before /tmp/before dqn          # DQN with CleanRL's settings, one env
    python -m rlpipe.scripts.bench.before_after --before /tmp/before whole dqn    # whole `rlpipe train dqn` runs

"After" is the installed rlpipe; "before" is the tree at ``--before``, imported in its runs' processes
through ``PYTHONPATH`` (a folder whose ``rlpipe/{pipelines,modules,envs,scripts,presets}`` link to that tree, found
before the editable install's finder). ``dqn``: the runs ``dqn_one_env`` makes (CleanRL's settings, one env
in the learner's process), each side timed as ``rlpipe bench cleanrl`` times it, CleanRL first in each
round. ``whole PRESET [key=value ...]``: wall clock, training time and final return of whole runs.
Figures: BENCHMARKS.md ("Evaluations on the same path", "DQN with CleanRL's settings, one env").
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def shim(tree: Path) -> Path:
    """A folder to put on PYTHONPATH so that ``import rlpipe...`` imports ``tree``'s code."""
    root = Path(tempfile.mkdtemp(prefix="rlpipe-before-"))
    (root / "rlpipe").mkdir()
    for part in ("pipelines", "modules", "envs", "scripts", "presets"):  # presets: the files that tree reads
        if (tree / part).is_dir():
            (root / "rlpipe" / part).symlink_to(tree.resolve() / part)
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", type=Path, required=True, help="the older tree (a git worktree)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("what", choices=["dqn", "whole"])
    parser.add_argument("rest", nargs="*", help="whole: PRESET [key=value ...]")
    args = parser.parse_args()
    if not (args.before / "pipelines").is_dir():
        parser.exit(2, f"--before {args.before}: expected an rlpipe tree (with pipelines/)\n")
    if args.what == "whole" and not args.rest:
        parser.exit(2, "whole: expected a preset name\n")
    old = str(shim(args.before))
    out = Path(tempfile.mkdtemp(prefix="rlpipe-before-after-"))

    def side(before: bool) -> None:
        if before:
            os.environ["PYTHONPATH"] = old
        else:
            os.environ.pop("PYTHONPATH", None)

    sides = (("before", True), ("after", False))
    if args.what == "dqn":
        from rlpipe.scripts.bench.dqn_one_env import rounds

        rounds({label: (["collector.direct=true"], (lambda on, b=before: side(b and on))) for label, before in sides},
               args.rounds, out=out, label="rlpipe ")
    else:
        preset, *extra = args.rest
        for i in range(args.rounds):
            for label, before in sides:
                side(before)
                run = out / f"{label}-{i}"
                t0 = time.perf_counter()
                proc = subprocess.run([sys.executable, "-m", "rlpipe.scripts.cli", "train", preset, *extra, "--out",
                                       str(run), "--no-progress"], capture_output=True, text=True, check=False)
                wall = time.perf_counter() - t0
                summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").exists() else {}
                print(f"round {i + 1} {preset} {label}: exit {proc.returncode}, {wall:.1f} s wall, "
                      f"train_time {summary.get('train_time_s', 0):.1f} s, final return {summary.get('final_average_return')}",
                      flush=True)
    side(False)


if __name__ == "__main__":
    main()
