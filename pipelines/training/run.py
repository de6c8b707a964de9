"""A run's lifecycle: open a run directory (new, or resumed from its newest whole checkpoint), train
a pipeline in it with the ``Loop``, write its summary, and stop with one line when the storage
refuses a write (disk full, permissions), after saving what can be saved.

``OffPolicyPipeline.train(out, ...)`` is ``with Run(pipeline).session(out, ...) as loop: loop.run()``: the lifecycle
sets the run up and finishes it around the loop, and is not on the call path from the loop to an update.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import random
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torchrl.record.loggers import Logger
from tqdm.contrib.logging import logging_redirect_tqdm

from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.artifacts.files import STORAGE_ERRNOS, FileWriteError, write_json_atomic
from rlpipe.pipelines.artifacts.loggers import close_logger, run_logger
from rlpipe.pipelines.artifacts.rundir import MetricsCSV, RunDir, default_run_dir, notice
from rlpipe.pipelines.config import config_to_dict
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.system.runtime import DeferredInterrupt, gc_frozen, keep_freed_memory
from rlpipe.pipelines.training.context import LIVE_LOG
from rlpipe.pipelines.training.determinism import NOT_ARITHMETIC, arithmetic_record, changed_arithmetic
from rlpipe.pipelines.training.faults import fault_triggers
from rlpipe.pipelines.training.live_report import ReportPage
from rlpipe.pipelines.training.loop import Loop, TrainResult
from rlpipe.pipelines.training.meters import Clock
from rlpipe.pipelines.training.state import EVAL, RunState
from rlpipe.pipelines.training.threads import choose_threads, torch_threads
from rlpipe.pipelines.training.triggers import Trigger, default_triggers, kept_best
from rlpipe.pipelines.workers.factory import backend_class

if TYPE_CHECKING:
    from rlpipe.pipelines.base import OffPolicyPipeline

__all__ = ["Run", "seed_everything"]


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators (what TorchRL's samplers and exploration draw from)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


class Run:
    """``pipeline``'s run into a run directory, from its start or from where a checkpoint left it."""

    def __init__(self, pipeline: OffPolicyPipeline):
        self.pipeline = pipeline
        self.run_dir: RunDir | None = None
        self.result: TrainResult | None = None

    @contextlib.contextmanager
    def session(self, out: str | Path | None = None, *, resume: bool = False, progress: bool = True,
                logger: Logger | None = None, callbacks: Sequence[Callable[[dict], None]] = (),
                triggers: Sequence[Trigger] = ()) -> Iterator[Loop | None]:
        """``OffPolicyPipeline.train``'s run (see there) around its loop: the run directory made or resumed, the
        logger, threads and stop signals set up, then the ``Loop`` handed to the caller to ``run()``; on leaving,
        summary.json and the report page of the finished run (``result``), or what a stop or a refused write
        needs. ``None`` instead of a loop: a finished run, resumed with nothing owed (``result`` is set already)."""
        pipeline = self.pipeline
        triggers = [*default_triggers(pipeline.config), *triggers, *fault_triggers()]
        names = [t.name for t in triggers]
        if len(set(names)) != len(names):
            raise InputError(f"trigger names must be unique (they are saved in checkpoints); got {', '.join(names)}")
        if pipeline.config.num_threads == -1:  # chosen once, before the run directory records the config
            pipeline.config = dataclasses.replace(pipeline.config, num_threads=choose_threads(pipeline.config))
        backend_class(pipeline.config).preflight(pipeline.config)  # e.g. no Ray at ray.address: one line, nothing written
        run, metrics, evaluations, fresh = self._resume(out) if resume else self._start(out)
        self.run_dir = pipeline.run_dir = run
        if metrics is None:  # a finished run, resumed with nothing owed
            try:
                self.result = self._unchanged(run)
                yield None
                return
            finally:
                run.close()
        loop, own_logger = None, None
        try:
            if logger is None:
                with FileWriteError.on_failure(run.path):
                    logger = own_logger = run_logger(pipeline.config, run.path, fresh)
            loop = Loop(pipeline, run, metrics, fresh=fresh, evaluations=evaluations, triggers=triggers,
                        logger=logger, callbacks=callbacks, progress=progress)
            with torch_threads(pipeline.config.num_threads), running(loop.stop):
                yield loop
                self.result = self.finish(loop)
        except OSError as exc:  # a write the storage refused, outside rlpipe's own (TensorBoard's writer)
            if exc.errno not in STORAGE_ERRNOS:
                raise
            # raised from no known place (rlpipe's own writes raise FileWriteError, at safe points): no save from there
            raise self._stopped_writing(FileWriteError(exc.filename or run.path, exc), None) from exc
        except FileWriteError as exc:
            raise self._stopped_writing(exc, loop) from exc
        finally:
            if own_logger is not None:
                close_logger(own_logger)
            run.close()

    def finish(self, loop: Loop) -> TrainResult:
        """summary.json and the report page of the finished run; what ``train`` hands back."""
        summary = self.summary(loop.state, loop.evaluations, loop.clock)
        # why the run ended: a trigger's reason (the target, the time budget), else its last iteration
        summary["stopped_because"] = loop.finished_early or "num_iterations"
        best = loop.state.best
        if best is not None:  # "exported": policy/policy.onnx is its policy (keep_best), not the last
            summary["best_evaluation"] = {"step": best["at"]["step"], "frames": best["at"].get("frames"),
                                          "average_return": best["return"], "exported": kept_best(loop) is not None}
        for trigger in loop.triggers.values():
            summary.update(getattr(trigger, "summary", lambda _: {})(loop))  # a trigger not made from ``Trigger``: none
        write_json_atomic(loop.run_dir.summary_path, summary)
        loop.page.write(running=False)  # returns.png and the page; it still holds the run's lock: done, all the same
        return TrainResult(policy=self.pipeline.policy, run_dir=loop.run_dir.path, metrics=loop.metrics.rows(),
                           summary=summary, evaluations=loop.evaluations)

    def _stopped_writing(self, exc: FileWriteError, loop: Loop | None) -> InputError:
        """The one line for a run stopped by a refused write (disk full, permissions), after saving
        what can be saved: a checkpoint of where the run is, unless the checkpoint was what failed."""
        run = self.run_dir
        saved = None
        if loop is not None and run.checkpoints not in (exc.path, *exc.path.parents):
            try:
                loop.save()
                saved = f"saved a checkpoint at iteration {self.pipeline.state.iteration}"
            except Exception:  # noqa: BLE001 - the refused write is the run's line, not this save's failure
                pass
        if saved is None:
            try:
                path = ckpt.newest_whole(run.checkpoints)[0]
            except InputError:
                path = None
            saved = f"its last checkpoint, {path.name}, is intact" if path else "no checkpoint was saved"
        return InputError(f"{exc}; {saved}: make room or allow writing there, then continue with --resume {run.path}")

    def _start(self, out) -> tuple[RunDir, MetricsCSV, list[dict], bool]:
        pipeline = self.pipeline
        run = RunDir.create(out or default_run_dir(pipeline.algo, pipeline.config.env), pipeline.algo,
                            config_to_dict(pipeline.config))
        return _opened(run, self._begin)

    def _begin(self, run: RunDir) -> tuple[MetricsCSV, list[dict], bool]:
        """A run from its first iteration: (its empty metrics table, no evaluations, fresh)."""
        pipeline = self.pipeline
        seed_everything(pipeline.config.seed)  # replay sampling, exploration: the same seed gives the same run
        pipeline.state.arithmetic = arithmetic_record(pipeline.config)
        pipeline.state.owed = [EVAL] if pipeline.config.initial_eval else []  # the tutorials evaluate once before training
        return MetricsCSV(run.metrics_path, list(pipeline.loss_names), extra_columns=pipeline.metrics_columns()), [], True

    def _resume(self, out) -> tuple[RunDir, MetricsCSV, list[dict], bool]:
        if out is None:
            raise InputError("resume needs the run directory to continue")
        return _opened(RunDir.resume(out), self._continue)

    def _continue(self, run: RunDir) -> tuple[MetricsCSV, list[dict], bool]:
        """Load the newest whole checkpoint of ``run``; (metrics table, evaluations so far, fresh)."""
        pipeline = self.pipeline
        path, skipped = ckpt.newest_whole(run.checkpoints)
        if path is None:
            if skipped:
                raise InputError(f"{run.checkpoints}: no whole checkpoint to resume from ({'; '.join(skipped)})")
            if run.has_progress():
                raise InputError(f"{run.checkpoints}: no checkpoint to resume from; expected a run that saved one")
            # killed while starting, before its first checkpoint: there is nothing to lose
            notice(f"{run.path} stopped before its first checkpoint; starting it from the beginning")
            run.write_config(pipeline.algo, config_to_dict(pipeline.config))
            return self._begin(run)
        try:
            pipeline.load_state_dict(ckpt.load_checkpoint(path, pipeline.algo, pipeline.config.env))
        except InputError as exc:
            changed = changed_keys(run.read_config()[1], config_to_dict(pipeline.config))
            hint = f" (keys changed since it was saved: {', '.join(changed)})" if changed else ""
            raise InputError(f"{path / 'state.pt'}: {exc}{hint}") from exc
        if skipped:
            notice(f"{run.checkpoints}: {'; '.join(skipped)}; resuming from {path.name}")
        if self._nothing_owed(run):
            return None, [], False  # nothing to write: not the config, the metrics, a checkpoint, a page
        metrics = MetricsCSV(run.metrics_path, list(pipeline.loss_names), resume_after_step=pipeline.state.iteration,
                             extra_columns=pipeline.metrics_columns())
        self._compare_arithmetic(run.read_config()[1])
        run.write_config(pipeline.algo, config_to_dict(pipeline.config))  # keys changed on resume are recorded
        rows = metrics.rows()
        pipeline.state.forget_done(rows)
        evaluations = [evaluation_of(r) for r in rows if r.get("average_return") not in ("", None)]
        return metrics, evaluations, False

    def _compare_arithmetic(self, saved_config: dict) -> None:
        """At a resume: record the config keys it changed, and where a changed key or the arithmetic record
        (threads, device, CPU float paths, library versions) differs from the checkpoint's, say so in one line
        and mark the run not exact. Changing only how long the run goes and how it is recorded keeps it exact."""
        state, now = self.pipeline.state, config_to_dict(self.pipeline.config)
        changed = {key: [_value_at(saved_config, key), _value_at(now, key)] for key in changed_keys(saved_config, now)}
        if changed:
            state.config_changes.append({"iteration": state.iteration, "changed": changed})
        record = arithmetic_record(self.pipeline.config)
        differences = [f"{key}={after} (was {before})" for key, (before, after) in changed.items()
                       if key not in NOT_ARITHMETIC and key != "num_threads"]  # the record says threads
        differences += changed_arithmetic(state.arithmetic, record)
        state.arithmetic = record
        if differences:
            why = f"resumed at iteration {state.iteration:,} with {', '.join(differences)}"
            notice(f"{why}: the run is no longer exact (it cannot equal an uninterrupted run of its seed)")
            state.not_exact(why)

    def _nothing_owed(self, run: RunDir) -> bool:
        """Whether the run as loaded is finished (its summary is of this checkpoint's iteration) and owes
        nothing: no update, trigger or evaluation, and no more iterations (the config reaches no further, or,
        for a run that ended before its last iteration by a rule of its own, is the one it ended by)."""
        state, cfg = self.pipeline.state, self.pipeline.config
        try:
            summary = json.loads(run.summary_path.read_text())
        except (OSError, ValueError):
            return False
        if not isinstance(summary, dict) or summary.get("iterations") != state.iteration:
            return False
        if state.owed or state.pending_evals or state.limiter.owed:
            return False
        return state.iteration >= cfg.num_iterations or not changed_keys(run.read_config()[1], config_to_dict(cfg))

    def _unchanged(self, run: RunDir) -> TrainResult:
        """What ``train`` hands back for a finished run resumed with nothing owed, after saying so: its own files,
        and its report page where the run's end could not write it (the disk full after summary.json)."""
        cfg, iteration = self.pipeline.config, self.pipeline.state.iteration
        done = (f"finished all {cfg.num_iterations:,} iterations" if iteration >= cfg.num_iterations
                else f"finished at iteration {iteration:,} of {cfg.num_iterations:,}")
        rows = MetricsCSV.read_rows(run.metrics_path)
        summary = json.loads(run.summary_path.read_text())
        evaluations = [evaluation_of(r) for r in rows if r.get("average_return") not in ("", None)]
        page = _page_behind(run)
        if page is not None:
            ReportPage(run.path, evaluations, title=f"{self.pipeline.algo} on {cfg.env}").write(running=False)
            notice(f"{run.path} {done}; it owed only its report page, which its end could not write: {page}")
        else:
            notice(f"{run.path} {done} and owes nothing: nothing changed (to train on, resume with a larger "
                   f"num_iterations=N)")
        return TrainResult(policy=self.pipeline.policy, run_dir=run.path, metrics=rows, summary=summary,
                           evaluations=evaluations)

    def summary(self, state: RunState, evaluations: list[dict], clock: Clock) -> dict[str, Any]:
        """summary.json: the run's final figures, counters and speeds, of the whole run (every stretch of a resumed one)."""
        pipeline = self.pipeline
        last = evaluations[-1] if evaluations else {}
        train_s = clock.train_seconds()
        return {
            "algo": pipeline.algo,
            "env": pipeline.config.env,
            "seed": pipeline.config.seed,
            "iterations": state.iteration,
            "frames": state.frames,
            "updates": state.updates,
            "final_average_return": last.get("average_return"),
            "final_average_episode_length": last.get("average_episode_length"),
            **({"final_success_rate": last["success_rate"]} if "success_rate" in last else {}),
            "wall_time_s": clock.wall(),
            "train_time_s": train_s,
            "env_steps_per_s": state.frames / train_s if train_s > 0 else None,
            "updates_per_s": state.updates / train_s if train_s > 0 else None,
            # whether the run equals an uninterrupted one of its seed, and if not, why (README: resuming)
            "exact": state.inexact is None,
            **({"why": state.inexact} if state.inexact is not None else {}),
            "arithmetic": state.arithmetic,
            **({"config_changes": state.config_changes} if state.config_changes else {}),
        }


@contextlib.contextmanager
def running(stop: DeferredInterrupt):
    """What the loop and the run's last writes happen in: stop signals deferred to safe points (``stop``),
    the garbage collector off what exists now, console log lines above the progress bar."""
    keep_freed_memory()
    # The deferred stop-signal handler stays on through the checkpoint saved on an interrupt: a
    # SIGINT delivered twice (the terminal's and a parent's) must not cut that save short.
    with stop, gc_frozen(), logging_redirect_tqdm([logging.root, LIVE_LOG.parent]):
        yield


def _opened(run: RunDir, then: Callable[[RunDir], tuple]) -> tuple:
    """``(run, *then(run))``; the run directory's lock let go if ``then`` fails."""
    try:
        return run, *then(run)
    except BaseException:
        run.close()
        raise


def _page_behind(run: RunDir) -> Path | None:
    """The run's report page where it is missing or older than its summary.json (a finished run writes it right
    after, from the summary: that write failed), else None."""
    from rlpipe.pipelines.analysis.report_pages import REPORT_FILE

    page = run.path / REPORT_FILE
    try:
        return page if page.stat().st_mtime_ns < run.summary_path.stat().st_mtime_ns else None
    except FileNotFoundError:
        return page


def changed_keys(saved: dict, current: dict, prefix: str = "") -> list[str]:
    """The dotted config keys whose value in ``current`` differs from ``saved`` (a key ``saved`` lacks, one an
    older rlpipe did not have, counts as its default)."""
    changed = []
    for key, value in current.items():
        if isinstance(value, dict) and isinstance(saved.get(key), dict):
            changed += changed_keys(saved[key], value, prefix + key + ".")
        elif key in saved and saved[key] != value:
            changed.append(prefix + key)
    return changed


def _value_at(config: dict, dotted: str) -> Any:
    """The value of a dotted key in a nested config dict (None where it is missing)."""
    for part in dotted.split("."):
        config = config.get(part) if isinstance(config, dict) else None
    return config


def evaluation_of(row: dict[str, str]) -> dict[str, Any]:
    """An evaluation as ``Loop.evaluations`` holds it, from its metrics row (a resumed run's)."""
    return {"step": int(row["step"]), "frames": int(row["frames"]), "updates": int(row["updates"]),
            "average_return": float(row["average_return"]),
            "average_episode_length": float(row["average_episode_length"]), "returns": None}
