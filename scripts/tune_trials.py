"""A trial of ``rlpipe tune``: its seeds as ``rlpipe train`` processes side by side, watched and timed.

Each seed's run is the bench's rlpipe side (``bench/time_to_return.py`` ``rlpipe_launch``: the same
command, ``target_return`` and step cap) timed by the bench's rule (``timed_result``: seconds from its
launch to the target, less unconfirmed evaluations); for ``--objective return-at=T``, ``rlpipe train`` with
``time_budget=T`` (``budget_launch``), read from its summary.json (``returned_result``). While the runs go,
the trial's curve (the mean over its seeds of each run's latest training return, at each elapsed second) is
reported to Optuna, and ``BehindBestPruner`` stops a trial whose curve falls behind the best finished trial's.
"""

from __future__ import annotations

import csv
import functools
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import optuna

from rlpipe.scripts.bench.time_to_return import Launch, _here_environ, _rlpipe_exe, _version, timed_result

STOP_TIMEOUT_S = 10.0
"""a run stopped (pruned, past its cap, Ctrl-C) has this long to end on SIGTERM before SIGKILL: enough to write
the files of a run that met its target just before its cap; the checkpoint a SIGTERM saves is never resumed"""
PR_SET_PDEATHSIG = 1


class SeedRun:
    """One seed's ``rlpipe train`` process: launched in a session of its own (a Ctrl-C to the tuner's
    terminal is the tuner's to pass on), its return read from its metrics.csv, ended at ``cap_s``."""

    def __init__(self, launch: Launch, run_dir: Path, log: Path, cap_s: float,
                 result_of: Callable[..., dict[str, Any]] = timed_result):
        self.launch, self.run_dir, self.log, self.cap_s, self.result_of = launch, run_dir, log, cap_s, result_of
        self.proc: subprocess.Popen | None = None
        self.start = self.end = 0.0
        self.capped = False

    def begin(self) -> None:
        self.log.parent.mkdir(parents=True, exist_ok=True)
        with self.log.open("w") as out:
            out.write(" ".join(self.launch.cmd) + "\n")
            out.flush()
            self.start = time.time()
            self.proc = subprocess.Popen(self.launch.cmd, stdout=out, stderr=subprocess.STDOUT, env=self.launch.env,
                                         cwd=self.launch.cwd, start_new_session=True,
                                         preexec_fn=None if _ray_node() else _ending_with_parent())

    def done(self) -> bool:
        """Whether the run has ended; one past its cap is stopped here (as Ctrl-C stops it: a run that met the
        target before the cap and is writing its files finishes them, and counts; one still training misses)."""
        if self.end:
            return True
        if self.proc.poll() is None:
            if time.time() - self.start < self.cap_s:
                return False
            self.capped = True
            self.stop()
        self.end = time.time()
        return True

    def latest_return(self) -> float | None:
        """The run's latest logged training return (metrics.csv ``train_episode_return``), None before its first."""
        try:
            with (self.run_dir / "metrics.csv").open(newline="") as fh:
                rows = [r.get("train_episode_return") for r in csv.DictReader(fh)]
        except OSError:
            return None
        values = [float(v) for v in rows if v not in (None, "")]
        return values[-1] if values else None

    def stop(self, sig: int = signal.SIGTERM) -> None:
        """End the run with its collector processes (its process group); SIGKILL if it outlives STOP_TIMEOUT_S."""
        if self.proc is None or self.proc.poll() is not None:
            return
        try:
            os.killpg(self.proc.pid, sig)
            self.proc.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        except ProcessLookupError:
            pass

    def result(self) -> dict[str, Any]:
        """The ended run's figures: the bench's (``seconds`` to the target, None where not reached), or
        ``returned_result``'s (``return``)."""
        result = self.result_of(self.launch, self.log, self.proc.returncode, self.start, self.end)
        return {**result, "capped": self.capped, "node": _ray_node()}


@functools.cache
def _ending_with_parent():
    """What a run's process calls before it starts (Linux): SIGTERM to it when the tuner dies, so a tuner that
    crashed or was killed leaves no run going (the run is in a session of its own, which no terminal signal
    reaches). None elsewhere: there a crashed tuner's runs end at their own step cap."""
    import ctypes
    import ctypes.util

    try:
        prctl = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True).prctl
    except (OSError, AttributeError, TypeError):
        return None
    return lambda: prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def _ray_node() -> str | None:
    """The Ray node this process is on (a ``RemoteRun``'s actor), None outside Ray."""
    ray = sys.modules.get("ray")
    return ray.get_runtime_context().get_node_id() if ray is not None and ray.is_initialized() else None


class RemoteRun:
    """A ``SeedRun`` on a Ray actor (``ray.address=``): the same calls, on the node Ray places it on (one CPU).
    The run's command, paths and timing are the node's: a cluster's nodes share rlpipe's install path."""

    def __init__(self, launch: Launch, run_dir: Path, log: Path, cap_s: float,
                 result_of: Callable[..., dict[str, Any]] = timed_result):
        import ray

        self.actor = ray.remote(num_cpus=1)(SeedRun).remote(launch, run_dir, log, cap_s, result_of)

    def _call(self, method: str, *args):
        import ray

        return ray.get(getattr(self.actor, method).remote(*args))

    def begin(self) -> None:
        self._call("begin")

    def done(self) -> bool:
        return self._call("done")

    def latest_return(self) -> float | None:
        return self._call("latest_return")

    def stop(self, sig: int = signal.SIGTERM) -> None:
        self._call("stop", sig)

    def result(self) -> dict[str, Any]:
        return self._call("result")

    def close(self) -> None:
        import ray

        ray.kill(self.actor)


def budget_launch(algo: str, seed: int, run_dir: Path, threads: int | None, overrides: list[str]) -> Launch:
    """A return-at trial's seed: ``rlpipe train ALGO key=value ... seed=S`` (the overrides hold env= and
    time_budget=), in the run's own folder."""
    keys = [*overrides, f"seed={seed}", *([f"num_threads={threads}"] if threads else [])]
    cmd = [*_rlpipe_exe(), "train", algo, *keys, "--out", str(run_dir), "--no-progress"]
    return Launch(cmd, _here_environ(), run_dir.parent, f"`rlpipe train {algo} {' '.join(overrides)}`",
                  lambda _log: None, {"rlpipe": _version()})


def returned_result(launch: Launch, log: Path, rc: int, start: float, end: float) -> dict[str, Any]:
    """An ended return-at run's figure: ``return``, the greedy evaluation return of the policy it exports (its kept
    best evaluation's, else its last evaluation's), from its summary.json; None where it has none (a crash, its
    cap), with the log's last line as ``error``."""
    run_dir = Path(launch.cmd[launch.cmd.index("--out") + 1])
    result: dict[str, Any] = {"rc": rc, "wall_s": end - start, "log": str(log), "return": None}
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError) as exc:
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()] if log.exists() else []
        return {**result, "failed": True, "error": lines[-1] if lines else f"{type(exc).__name__}: {exc}"}
    best = summary.get("best_evaluation") or {}
    value = best.get("average_return") if best.get("exported") else summary.get("final_average_return")
    return {**result, "failed": rc != 0, "return": value, "chosen": "best" if best.get("exported") else "last",
            "stopped_because": summary.get("stopped_because"), "frames": summary.get("frames")}


def seconds(result: dict[str, Any], cap_s: float, penalty_s: float) -> float:
    """A run's time to the target; a run that missed it (its cap, its steps, or a failure) counts as cap + penalty."""
    return result["seconds"] if result.get("reached") else cap_s + penalty_s


def trial_value(results: list[dict[str, Any]], cap_s: float, penalty_s: float) -> float:
    """The trial's objective: the mean over its seeds of their times (misses counted as cap + penalty)."""
    return statistics.fmean(seconds(r, cap_s, penalty_s) for r in results)


class TrialRuns:
    """A trial's seeds, run side by side on one clock; ``poll`` reports their curve to Optuna."""

    def __init__(self, trial: optuna.trial.Trial, algo: str, overrides: list[str], runs: list[SeedRun]):
        self.trial, self.algo, self.overrides, self.runs = trial, algo, overrides, runs
        self.start = 0.0
        self.reported = -1
        self.pruned = False

    def begin(self) -> None:
        self.start = time.time()
        for run in self.runs:
            run.begin()

    def poll(self) -> bool:
        """Report the curve's new point; True once every run has ended or the trial is pruned (its runs ended).
        The curve is the mean of the latest returns of the runs that have logged one (a run still in its start-up
        or random steps has none yet)."""
        if all([run.done() for run in self.runs]):
            return True
        step = int(time.time() - self.start)
        latest = [v for v in (run.latest_return() for run in self.runs) if v is not None]
        if step > self.reported and latest:
            self.trial.report(statistics.fmean(latest), step)
            self.reported = step
            if self.trial.should_prune():
                self.pruned = True
                self.stop()
                return True
        return False

    def stop(self, sig: int = signal.SIGTERM) -> None:
        for run in self.runs:
            run.stop(sig)
        for run in self.runs:
            run.done()

    def results(self) -> list[dict[str, Any]]:
        return [run.result() for run in self.runs]

    def close(self) -> None:
        """Let go of the runs' Ray actors (none for runs on this machine)."""
        for run in self.runs:
            getattr(run, "close", lambda: None)()


class BehindBestPruner(optuna.pruners.BasePruner):
    """Prunes a trial whose curve (return at each elapsed second) is below the best finished trial's at the
    same second, once it has run ``warmup`` of the best trial's time, or of ``horizon_s`` where every trial has
    that long (the first seconds are imports and random steps, where a curve says little)."""

    def __init__(self, warmup: float = 0.5, horizon_s: float | None = None):
        self.warmup, self.horizon_s = warmup, horizon_s

    def prune(self, study: optuna.study.Study, trial: optuna.trial.FrozenTrial) -> bool:
        step = trial.last_step
        if step is None:
            return False
        try:
            best = study.best_trial
        except ValueError:  # no finished trial yet
            return False
        curve = best.intermediate_values
        if best.number == trial.number or not curve or step < self.warmup * (self.horizon_s or best.value):
            return False
        reference = _at(curve, step)
        return reference is not None and trial.intermediate_values[step] < reference


def _at(curve: dict[int, float], step: int) -> float | None:
    """The curve's value at ``step``: its latest point at or before it (after its end: its last point)."""
    before = [s for s in curve if s <= step]
    return curve[max(before)] if before else None
