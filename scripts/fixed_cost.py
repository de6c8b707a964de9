"""The fixed cost of a run, per part: ``rlpipe train ...`` with a timestamp at each stage (seconds from the
process's start, interpreter start-up included), printed as one line on stderr at exit.

    python -m rlpipe.scripts.fixed_cost train sac-pendulum num_iterations=1 initial_collect_steps=100 --out DIR

The stages are marked by wrapping the methods that begin and end them (the CLI's own code runs
unchanged): imports, pipeline built, thread count, random baseline, the triggers' start (a background
evaluator's process), the untrained evaluation, the first block (a collector process's start), the
final triggers (last evaluation, report, export, checkpoint), exit.
"""

from __future__ import annotations

import atexit
import os
import sys
import time


def _process_start() -> float:
    """The wall-clock time this process started (Linux: /proc), so the interpreter's start-up counts."""
    ticks = float(open(f"/proc/{os.getpid()}/stat").read().split()[21])
    boot = time.time() - float(open("/proc/uptime").read().split()[0])
    return boot + ticks / os.sysconf("SC_CLK_TCK")


class Marks:
    def __init__(self):
        self.start = _process_start()
        self.marks: list[tuple[str, float]] = []

    def __call__(self, what: str) -> None:
        self.marks.append((what, time.time() - self.start))

    def line(self) -> str:
        before = [0.0] + [t for _, t in self.marks]
        return "fixed cost: " + " | ".join(f"{w} {t:.2f} (+{t - p:.2f})" for (w, t), p in zip(self.marks, before))


def _wrap(owner, name: str, before: str | None = None, after=None) -> None:
    """``owner.name`` marked ``before`` it starts and ``after(seconds)`` once it returns."""
    original = getattr(owner, name)

    def wrapped(*args, **kwargs):
        if before:
            MARK(before)
        t = time.time()
        result = original(*args, **kwargs)
        if after:
            MARK(after(time.time() - t, result))
        return result

    setattr(owner, name, wrapped)


MARK = Marks()


def main(argv: list[str]) -> int:
    MARK("python up")
    import rlpipe.pipelines as pipelines
    from rlpipe.pipelines import base
    from rlpipe.pipelines.training import evaluations, loop, run, triggers
    from rlpipe.scripts import cli

    _wrap(pipelines, "resolve_preset", after=lambda s, r: "imports (preset resolved)")
    _wrap(base.OffPolicyPipeline, "__init__", after=lambda s, r: "pipeline built")
    _wrap(evaluations.Evaluations, "measure_random_baseline", after=lambda s, r: f"random baseline ({s:.2f} s)")
    _wrap(loop.Loop, "start", after=lambda s, r: "triggers started (checkpoint 0, evaluator process)")
    _wrap(triggers.EvalTrigger, "__call__", after=lambda s, r: f"evaluation asked ({s:.2f} s)")
    first = loop.Loop.insert

    def insert(self, batch):
        if not getattr(self, "_first_block_marked", False):
            MARK("first block collected")
            self._first_block_marked = True
        return first(self, batch)

    loop.Loop.insert = insert
    fire = loop.Loop.fire

    def fire_marked(self, moment, *args):
        if moment == "final":
            MARK("last block done")
        return fire(self, moment, *args)

    loop.Loop.fire = fire_marked
    for name in ("EvalTrigger", "ExportTrigger", "CheckpointTrigger"):
        _wrap(getattr(triggers, name), "final", after=lambda s, r, name=name: f"{name}.final ({s:.2f} s)")
    _wrap(run.Run, "finish", after=lambda s, r: "summary and report written")
    return cli.main(argv, fork_server=True)  # as `rlpipe` runs


if __name__ == "__main__":  # spawned collector and evaluator processes import this module: no run there
    atexit.register(lambda: print(MARK.line() + f" | exit {time.time() - MARK.start:.2f}", file=sys.stderr))
    sys.exit(main(sys.argv[1:]))
