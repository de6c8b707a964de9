"""The collect/learn loop: TF-Agents' ``Learner.run`` on TorchRL parts.

``Loop.run`` collects a block of env steps with a TorchRL collector, makes the updates that block
paid for (``updates_per_frame = 1 / collect_steps_per_iteration``, held by ``SampleToInsertRatio``),
then runs the triggers whose interval the block crossed (log, evaluate, export, checkpoint, and any
a user adds). Everything else is a part with its own module: the run's state (``state``), the
triggers (``triggers``), evaluation in the background (``evaluation``), Ctrl-C and worker start-up
(``runtime``), speeds and losses (``meters``), the run directory and checkpoints.

Ctrl-C, SIGTERM or SIGHUP stops at the next safe point (between two updates, two env steps of an
evaluation, or two triggers); the checkpoint saved then records what that iteration still owes, and
``--resume`` does exactly that first. Collector and evaluator processes never see those signals:
they start with them blocked, and the learner stops them. A second signal stops at once, unsaved.

Workers are supervised (``supervision``): a collector or evaluator process that dies or stops
answering is replaced, up to ``collector.max_restarts`` times; one more failure saves a checkpoint
and ends the run with ``NoRestartLeft``.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs.utils import RandomPolicy
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.artifacts.export import export_policy
from rlpipe.pipelines.artifacts.files import write_json_atomic
from rlpipe.pipelines.artifacts.rundir import MetricsCSV, RunDir
from rlpipe.pipelines.errors import InputError, TrainingDiverged
from rlpipe.pipelines.system.runtime import (
    DeferredInterrupt,
    Interrupted,
    Stopped,
    fault_point,
    gc_frozen,
    keep_freed_memory,
    stop_signals_blocked,
)
from rlpipe.pipelines.training.meters import Clock, IntervalStats
from rlpipe.pipelines.training.triggers import Trigger, eval_line
from rlpipe.pipelines.workers.evaluation import AsyncEvaluator, BackgroundEvaluator, evaluate
from rlpipe.pipelines.workers.supervision import (
    NoRestartLeft,
    SupervisedCollector,
    Supervisor,
    Watchdog,
    WorkerFailure,
    kill_new_children,
)

if TYPE_CHECKING:
    from rlpipe.pipelines.base import OffPolicyPipeline
    from rlpipe.pipelines.workers.backend import CollectorBackend

__all__ = ["LIVE_LOG", "Loop", "TrainResult"]

LIVE_LOG = logging.getLogger("rlpipe.train")
"""The live log, the tutorials' printed lines (``step = 1000: AverageReturn = ...``), as INFO records.
``rlpipe train`` shows them on stdout; from Python, ``logging.basicConfig(level=logging.INFO,
format="%(message)s")`` does (a library leaves where its records go to the application)."""


@dataclass
class TrainResult:
    """What ``train`` hands back: the trained policy, the metrics rows and where the run lives."""

    policy: nn.Module
    run_dir: Path
    metrics: list[dict[str, str]]
    summary: dict[str, Any]
    evaluations: list[dict[str, Any]] = field(default_factory=list)


class Loop:
    """One run of ``pipeline`` into ``run``, from where ``pipeline.state`` says it is to its end.

    Triggers get this object; what they may use: ``pipeline``, ``config``, ``state`` (counters),
    ``run_dir`` (the ``RunDir``), ``evaluations``, ``last_return``, ``clock``, ``interval_stats``,
    ``supervisor`` (workers alive, restarts), and the methods ``log``, ``evaluate``, ``export``, ``save``.
    """

    def __init__(self, pipeline: OffPolicyPipeline, run: RunDir, metrics: MetricsCSV, *, fresh: bool,
                 evaluations: list[dict], triggers: Sequence[Trigger], logger: Logger,
                 callbacks: Sequence[Callable[[dict], None]] = (), progress: bool = True):
        self.pipeline, self.config, self.state = pipeline, pipeline.config, pipeline.state
        self.run_dir, self.metrics, self.fresh, self.evaluations = run, metrics, fresh, evaluations
        self.triggers = {t.name: t for t in triggers}
        self.logger, self.callbacks = logger, list(callbacks)
        self.clock, self.interval_stats, self.stop = Clock(), IntervalStats(), DeferredInterrupt()
        self.supervisor = Supervisor(self.config.collector.max_restarts, self.config.collector.timeout)
        self.collection: SupervisedCollector | None = None
        self.watchdog: Watchdog | None = None
        self.background: AsyncEvaluator | None = None
        self.ray = None  # the run's hold on Ray while its evaluator is a Ray actor (ray_eval.hold_ray)
        self.exported_at = None
        self._counts_at_start = (self.state.frames, self.state.updates)  # this session's speeds
        self.bar = tqdm(total=self.config.num_iterations, initial=self.state.iteration, unit="it", disable=not progress,
                        desc=f"{pipeline.algo} {self.config.env}", dynamic_ncols=True)

    @property
    def collector(self):
        """The collector backend collecting now (None outside ``collect``, or while one is replaced)."""
        return None if self.collection is None else self.collection.collector

    @property
    def last_return(self) -> float:
        return self.evaluations[-1]["average_return"] if self.evaluations else math.nan

    def run(self) -> TrainResult:
        # The deferred stop-signal handler stays on through the checkpoint saved on an interrupt: a
        # SIGINT delivered twice (the terminal's and a parent's) must not cut that save short.
        keep_freed_memory()
        # Console log handlers write through tqdm while the bar is up, so no line breaks it.
        with self.stop, gc_frozen(), logging_redirect_tqdm([logging.root, LIVE_LOG.parent]):
            with self._workers():
                try:
                    self.start()
                    self.pay_updates()  # owed by a run stopped in the middle of a block ...
                    self.run_triggers()  # ... and what its iteration still had to do
                    with contextlib.closing(self.collect()) as blocks:
                        for batch in blocks:
                            self.insert(batch)
                            self.pay_updates()
                            self.run_triggers()
                            self.take_background_results()
                    self.take_background_results(block=True)
                    if not self.evaluations or self.evaluations[-1]["step"] != self.state.iteration:
                        self.evaluate_now()
                except Stopped as stop:
                    self.take_background_results(feed=False)  # one already back is kept; the others are saved
                    self.save()  # with what this iteration still owes: --resume does that first
                    raise Interrupted(stop.signum) from None
                except NoRestartLeft as lost:
                    with contextlib.suppress(WorkerFailure):
                        self.take_background_results(feed=False)
                    owed, pending = self.state.owed, self.state.pending_evals
                    if owed[:1] == ["eval"] and any(at["step"] == self.state.iteration for at, _ in pending):
                        owed.pop(0)  # asked before its evaluator failed: saved as pending, not asked twice
                    self.save()  # the collector's blocks handed out so far are in the replay buffer
                    lost.saved_at = self.state.iteration
                    raise
            if self.exported_at != self.state.iteration:
                self.export()
            self.save()
            if self.config.video:
                self.make_video()
            return self.finish()

    # --- the steps of a run ---------------------------------------------------------------------

    def start(self) -> None:
        if self.fresh:
            self.save()  # iteration 0: a run stopped at any point from here on can be resumed
        self.measure_random_baseline()
        pending = self.state.pending_evals
        self.watchdog = Watchdog()
        if self.config.eval_in_background:
            self.background = self._start_evaluator()
        while pending and self.background is None:  # asked for in the background before a resume that turned it off
            at, weights = pending[0]
            self.evaluate_now(weights, at)
            pending.popleft()
        self.clock.start()

    def collect(self) -> Iterator[TensorDictBase]:
        """Blocks of env steps from a TorchRL collector, until the run's frame budget is met.

        The collector is supervised (``SupervisedCollector``): one whose worker fails is replaced by a
        new one for the frames still to collect. Closed (``contextlib.closing``) however the run leaves
        it, so that TorchRL's iterator is closed while its workers still run, and the workers are then
        shut down (within seconds: one that does not stop when asked is killed).
        """
        cfg, state = self.config, self.state
        if cfg.total_frames - state.frames <= 0:
            return
        self.collection = SupervisedCollector(self._make_collector, self.supervisor, self.watchdog)
        try:
            for batch in self.collection:
                yield batch
                fault_point("collected", state.iteration)  # the learner, once the block's work is done
                fault_point("collector_worker", state.iteration,
                            worker=lambda: next(iter(self.collection.pids()), None))
                if state.frames >= cfg.total_frames:
                    break
        finally:
            self.collection.close()
            self.collection = None

    def _make_collector(self, restarts: int) -> CollectorBackend:
        """A started collector backend for the frames still to collect, seeded; after a restart, with a seed
        stream no earlier collector of the run used."""
        cfg, state = self.config, self.state
        seed = cfg.seed + state.frames
        if restarts:
            seed = int(np.random.SeedSequence([cfg.seed, state.frames, restarts]).generate_state(1)[0])
        with stop_signals_blocked(), self.clock.paused():  # worker start-up is not training time
            return self.pipeline.make_backend().start(cfg.total_frames - state.frames,
                                                      max(0, cfg.initial_collect_steps - state.frames), seed)

    def insert(self, batch: TensorDictBase) -> None:
        """Store a block in the replay buffer, count it, and note the triggers its iterations crossed."""
        cfg, pipeline = self.config, self.pipeline
        # Collectors round their budget up to whole blocks; the run stops at its own.
        batch = batch.reshape(-1)[: cfg.total_frames - self.state.frames]
        keys = pipeline.replay_keys
        pipeline.replay_buffer.extend(batch if keys is None else batch.select(*keys))
        self.state.episodes += self.interval_stats.add_frames(batch)
        pipeline.on_frames(batch.numel())
        before, now = self.state.insert(batch.numel(), cfg)
        self.state.owed = [t.name for t in self.triggers.values() if t.due(before, now, cfg.num_iterations)]
        self.bar.update(now - before)

    def pay_updates(self) -> None:
        """Make the updates the frames so far paid for; push the new weights to collector processes."""
        made = 0
        while self.state.limiter.owed:
            self.stop.check()
            losses = self.pipeline.update_step(self.pipeline.replay_buffer.sample(), self.state.updates + 1)
            if fault_point("update", self.state.updated()):  # the test hook: a parameter turns NaN here
                next(self.pipeline.loss_module.parameters()).data.fill_(math.nan)
            made += 1
            self.interval_stats.add_losses(losses)
        if made:
            self.check_finite()  # once per block: a few scalars, before the collectors get the weights
        if made and self.collection is not None and self.state.updates % self.config.collector.weight_sync_interval < made:
            self.collection.push_weights()

    def run_triggers(self) -> None:
        """Run what the current iteration owes, in order; each is crossed off once done."""
        owed = self.state.owed
        while owed:
            self.stop.check()
            trigger = self.triggers.get(owed[0])
            if trigger is None or trigger.crossed_off_first:  # None: a trigger of an earlier session, not passed now
                owed.pop(0)
            if trigger is not None:
                trigger(self)
                if not trigger.crossed_off_first:
                    owed.pop(0)

    def finish(self) -> TrainResult:
        summary = self.pipeline.summary(self.state, self.evaluations, self.clock)
        write_json_atomic(self.run_dir.summary_path, summary)
        self.write_report()
        return TrainResult(policy=self.pipeline.policy, run_dir=self.run_dir.path, metrics=self.metrics.rows(),
                           summary=summary, evaluations=self.evaluations)

    # --- what triggers call ---------------------------------------------------------------------

    def log(self, row: dict[str, Any], at: dict[str, int] | None = None) -> None:
        """Write a metrics row (at the current position unless ``at``): CSV, logger, callbacks."""
        row = {**(at or self.state.position()), **row}
        self.metrics.append(row)
        for key, value in row.items():
            if key != "step" and isinstance(value, (int, float)) and not math.isnan(value):
                self.logger.log_scalar(key, value, step=row["step"])
        for callback in self.callbacks:
            callback(row)

    def evaluate(self) -> None:
        """Evaluate the policy as it is now: in the background if the run does so, else here."""
        if self.background is not None and self.state.iteration > 0:
            self.background.ask(self.state.position(), self.background.snapshot(self.pipeline.policy))
            fault_point("evaluator_worker", self.state.iteration, worker=lambda: self.background.worker_pid)
            self.take_background_results()
        else:
            self.evaluate_now()

    def evaluate_now(self, weights: TensorDictBase | None = None, at: dict[str, int] | None = None) -> None:
        """Evaluate the policy (or ``weights``, taken at ``at``) in this process."""
        at = at or self.state.position()
        fault_point("evaluate", at["step"])
        policy = self.pipeline.policy
        if weights is not None:
            policy = copy.deepcopy(policy)
            weights.to_module(policy)
        with self.clock.paused():
            result = evaluate(self.pipeline.eval_env, policy, self.config.num_eval_episodes, interrupt=self.stop.check)
        self._record_evaluation(result, at)

    def take_background_results(self, block: bool = False, feed: bool = True) -> None:
        """Record the background evaluations that are back (``block``: wait for all of them); an
        evaluator that failed is replaced, and asked again for what it had not answered."""
        while self.background is not None:
            try:
                with self.clock.paused() if block else contextlib.nullcontext():
                    for at, result in self.background.results(block=block, feed=feed, interrupt=self.stop.check):
                        self._record_evaluation(result, at)
                return
            except WorkerFailure as failure:
                self._restart_evaluator(failure)

    def _start_evaluator(self) -> AsyncEvaluator:
        cfg = self.config
        if cfg.collector.backend == "ray":  # on a Ray actor, on the Ray the run holds until its end
            from rlpipe.pipelines.workers.ray_eval import RayEvaluator, hold_ray

            # a local Ray's processes start deaf to the stop signals, as Ray collectors start it (_make_collector)
            with self.clock.paused(), stop_signals_blocked():
                self.ray = self.ray or hold_ray(cfg)
                evaluator = RayEvaluator(self.pipeline.eval_env_fn, self.pipeline.policy, cfg.num_eval_episodes,
                                         self.state.pending_evals, config=cfg, timeout=cfg.eval_timeout,
                                         start_timeout=self.supervisor.start_timeout)
            self.supervisor.report("evaluator", 1, 1)
            return evaluator
        # TorchRL reads the new worker's first message with no timeout: the watchdog kills one that hangs
        with self.clock.paused(), self.watchdog.limit(self.supervisor.start_timeout, kill_new_children()):
            evaluator = BackgroundEvaluator(self.pipeline.eval_env_fn, self.pipeline.policy, cfg.num_eval_episodes,
                                            self.state.pending_evals, timeout=cfg.eval_timeout,
                                            ack_timeout=cfg.collector.timeout)
        self.supervisor.report("evaluator", 1, 1)
        return evaluator

    def _restart_evaluator(self, failure: WorkerFailure) -> None:
        with self.clock.paused():
            self.background.close()
        self.background = None
        self.supervisor.report("evaluator", 0, 1)
        while self.background is None:
            self.supervisor.failed("evaluator", failure)  # NoRestartLeft when no restart is left
            try:
                self.background = self._start_evaluator()  # it asks again for the oldest pending evaluation
            except (RuntimeError, ValueError, EOFError, OSError) as exc:
                failure = WorkerFailure("evaluator", f"the evaluator did not start again: {exc}")

    def _record_evaluation(self, result: dict[str, Any], at: dict[str, int]) -> None:
        from rlpipe.pipelines.analysis import plot_training_returns  # matplotlib: imported when first needed

        self.evaluations.append({**at, **result})
        self.log({"average_return": result["average_return"],
                  "average_episode_length": result["average_episode_length"], "wall_time": self.clock.wall()}, at)
        self.echo(eval_line(at["step"], result, *self.speeds()))
        with self.clock.paused():  # from the evaluations in memory: metrics.csv is not read again
            plot_training_returns(self.evaluations, self.run_dir.returns_png,
                                  title=f"{self.pipeline.algo} on {self.config.env}")
            self.write_report()
        self.bar.set_postfix(avg_return=f"{self.last_return:.1f}", refresh=False)

    def write_report(self) -> None:
        """RUN/report.html from what the run directory holds now."""
        from rlpipe.pipelines.analysis.pages import write_run_report

        write_run_report(self.run_dir.path)

    def echo(self, line: str) -> None:
        """A line of the live log (``LIVE_LOG``): above the progress bar when there is one."""
        LIVE_LOG.info(line)

    def speeds(self) -> tuple[float, float]:
        """Env steps and updates per second of training time in this session (evaluations and saving left out)."""
        seconds = self.clock.train_seconds()
        if seconds <= 0:
            return math.nan, math.nan
        frames, updates = self._counts_at_start
        return (self.state.frames - frames) / seconds, (self.state.updates - updates) / seconds

    def measure_random_baseline(self) -> None:
        """The random agent's return on the eval env (the DQN tutorial's baseline), once per run: RUN/baseline.json.

        Played on an env of its own, with the run's random generators (torch, numpy, Python) put back
        afterwards, so the run's own evaluations and draws are those of a run without it, and a run
        resumed from its first checkpoint (saved before this) goes on as the uninterrupted one. A
        pipeline handed env instances (no function to make another) has no baseline.
        """
        from rlpipe.pipelines.analysis.pages import read_baseline, write_baseline

        episodes = self.config.baseline_episodes
        episodes = self.config.num_eval_episodes if episodes == -1 else episodes
        if episodes == 0 or read_baseline(self.run_dir.path) is not None or self.pipeline.eval_env_fn is None:
            return
        self.echo(f"random agent: playing {episodes} episodes for its baseline return (baseline_episodes)")
        generators = ckpt.rng_state()
        env = self.pipeline.eval_env_fn()
        try:
            env.set_seed(self.config.seed + 20_000)
            result = evaluate(env, RandomPolicy(env.full_action_spec), episodes, interrupt=self.stop.check)
        finally:
            env.close()
            ckpt.set_rng_state(generators)
        write_baseline(self.run_dir.path, result)
        self.echo(f"random agent: AverageReturn = {result['average_return']:.6f}, "
                  f"AverageEpisodeLength = {result['average_episode_length']:.6f} "
                  f"({episodes} episodes)")

    def make_video(self) -> None:
        """``video=true``: the trained policy filmed to RUN/trained-agent.mp4, as ``rlpipe video RUN`` does."""
        from rlpipe.pipelines.analysis.pages import VIDEO_FILE
        from rlpipe.pipelines.artifacts.export import load_policy
        from rlpipe.pipelines.artifacts.video import record_video

        # the policy this run exported a moment ago: its own file, so a .pt2-only export (a plug-in
        # actor ONNX cannot express) is trusted here, as it would not be from someone else's run
        policy = load_policy(self.run_dir.policy_dir, trust=True)[0]
        path = record_video(self.config.env, policy, self.run_dir.path / VIDEO_FILE)
        self.echo(f"video: {path}")

    def export(self) -> None:
        with self.clock.paused():
            export_policy(self.pipeline.export_module(), self.pipeline.observation_dim, self.run_dir.policy_dir,
                          self.pipeline.export_info(), step=self.state.iteration, keep=self.config.policy_keep)
        self.exported_at = self.state.iteration

    def check_finite(self) -> None:
        """Stop with ``TrainingDiverged`` if a loss since the last log row or a parameter is NaN or infinite.

        Nothing is saved then: every checkpoint passed this check, so the last one on disk is the
        run's last finite state, and ``--resume`` (with, say, a lower learning rate) continues from it.
        """
        sums = self.interval_stats.loss_sums
        tensors = [torch.as_tensor(v).reshape(-1) for v in sums.values()]
        tensors += [p.detach().reshape(-1).isfinite().all().reshape(1) for p in self.pipeline.loss_module.parameters()]
        if not tensors or bool(torch.cat([t.float() for t in tensors]).isfinite().all()):
            return
        bad = [f"loss_{k}={float(v)}" for k, v in sums.items() if not torch.as_tensor(v).isfinite().all()]
        try:
            last = f"the checkpoint {ckpt.latest_checkpoint(self.run_dir.checkpoints)}"
        except InputError:
            last = "not saved (no checkpoint yet)"
        raise TrainingDiverged(
            f"training diverged by iteration {self.state.iteration} ({self.state.updates} updates): "
            f"{', '.join(bad) or 'a parameter'} is not finite; stopped without saving: the last finite state is "
            f"{last}; expected finite losses: lower the learning rates, then continue with --resume {self.run_dir.path}"
        )

    def save(self) -> None:
        self.check_finite()
        with self.clock.paused():
            self.metrics.sync()  # the rows this checkpoint counts reach the disk before it does
            ckpt.save_checkpoint(self.run_dir.checkpoints, self.state.iteration, self.pipeline.state_dict(),
                                 keep=self.config.checkpoint_keep)

    @contextlib.contextmanager
    def _workers(self):
        """Stop the evaluator (its process or Ray actor, then the run's hold on Ray) and the watchdog
        however the run ends (``collect`` stops the collector's processes)."""
        try:
            yield
        finally:
            if self.background is not None:
                self.background.close()
            if self.ray is not None:
                self.ray.close()
            if self.watchdog is not None:
                self.watchdog.close()
            self.bar.close()
