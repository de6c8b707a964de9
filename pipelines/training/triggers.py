"""Triggers: what the loop does every so many iterations, after the updates (TF-Agents' triggers).

A trigger has a ``name`` (saved in checkpoints: a run stopped between two triggers of the same
iteration resumes with those it still owes; the built-in names are the constants ``LOG``, ``EVAL``,
``EXPORT``, ``SAVE``, ``VIDEO`` and never change) and an ``interval`` in iterations, and is called
with the running ``Loop``. The built-in ones log, evaluate, export the policy and checkpoint, and do
that work themselves; add your own by passing them to ``train(triggers=[...])``::

    from rlpipe.pipelines.training.triggers import IntervalTrigger

    def print_return(loop):
        print(loop.state.iteration, loop.last_return)

    pipeline.train("runs/x", triggers=[IntervalTrigger(1000, print_return, name="print")])

What a trigger may use of the loop is ``context.LoopContext``: ``pipeline``, ``config``, ``state``
(counters), ``run_dir`` (the ``RunDir``), ``evaluations`` (results so far, oldest first), ``last_return``,
``clock``, ``interval_stats``, ``supervisor`` (workers alive, restarts), ``collector`` (the collector
backend collecting now, or None: a ``workers.backend.CollectorBackend``, whose ``.collector`` is
TorchRL's), ``triggers`` (the run's triggers by name), and the methods ``log(row)`` (a metrics row: CSV,
where a key new to metrics.csv gets a column; logger; callbacks), ``echo(line)`` (the live log),
``speeds()``, ``evaluate()``, ``export()``, ``save()``.

Besides ``__call__``, a trigger may define the run's other moments (each does nothing unless
overridden), called on every trigger in the order given to ``train``:

* ``start(loop)``: before the first block (after the checkpoint of a fresh run's iteration 0);
* ``poll(loop)``: after each block's triggers (the eval trigger takes background results);
* ``final(loop)``: once, at the run's end: the "final" firing (the last export, checkpoint and video
  are the built-in triggers' final firings, which is why ``at_last_iteration`` keeps the checkpoint's
  interval firing off the last iteration; the last evaluation is the last iteration's own, before a
  user's triggers of that iteration, so that they see its return);
* ``stopped(loop, lost)``: the run stops early, on a stop signal (``lost`` None) or on lost workers
  (``lost``: the ``NoRestartLeft``); the checkpoint trigger saves what the iteration still owes;
* ``close(loop)``: however the run ends (processes a trigger started are stopped here);
* ``summary(loop)``: keys it adds to summary.json (``TargetTrigger``'s ``"target"``).

``TargetTrigger`` (``target_return``) ends a run early: ``loop.finish_early(why)`` stops collecting
after the current block, and the final firing follows as at the last iteration.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.artifacts.export import export_policy, step_name
from rlpipe.pipelines.config import TrainConfig, duration_seconds, env_options
from rlpipe.pipelines.training.evaluations import Evaluations, eval_line
from rlpipe.pipelines.training.state import EVAL, EXPORT, LOG, SAVE, TARGET, VIDEO
from rlpipe.pipelines.workers.evaluation import evaluate
from rlpipe.pipelines.workers.factory import backend_class
from rlpipe.pipelines.workers.supervision import WorkerFailure

if TYPE_CHECKING:
    from rlpipe.pipelines.training.loop import Loop
    from rlpipe.pipelines.workers.supervision import NoRestartLeft

__all__ = [
    "EVAL", "EXPORT", "LOG", "SAVE", "TARGET", "VIDEO",
    "CheckpointTrigger", "EvalTrigger", "ExportTrigger", "IntervalTrigger", "LogTrigger", "TargetTrigger",
    "TimeBudgetTrigger", "Trigger",
    "VideoTrigger",
    "crossed", "default_triggers", "eval_line", "log_line",
]

# What a pipeline's update returns besides the terms of its objective (SAC's temperature and policy
# entropy): left out of the total ``loss`` the tutorials print, shown after it.
DIAGNOSTICS = ("alpha_value", "entropy")


def crossed(previous: int, now: int, interval: int) -> bool:
    """Whether a multiple of ``interval`` lies in (previous, now]."""
    return interval > 0 and now // interval > previous // interval


class Trigger:
    """Runs every ``interval`` iterations; subclasses set ``name`` and define ``__call__(loop)``.

    ``at_last_iteration=False``: not at the run's last iteration (its ``final`` firing does that
    work: the final evaluation, the final checkpoint).
    """

    name: str = ""
    at_last_iteration: bool = True
    crossed_off_first: bool = False
    """True: counted as done before it runs (a checkpoint, which records what is still owed, owes nothing more itself)"""

    def __init__(self, interval: int):
        self.interval = int(interval)

    def due(self, previous: int, now: int, last: int) -> bool:
        """Whether this trigger runs when the run moves from iteration ``previous`` to ``now``."""
        return crossed(previous, now, self.interval) and (self.at_last_iteration or now < last)

    def __call__(self, loop: Loop) -> None:
        raise NotImplementedError

    def start(self, loop: Loop) -> None:
        """Before the run's first block."""

    def poll(self, loop: Loop) -> None:
        """After each block's triggers."""

    def final(self, loop: Loop) -> None:
        """Once, at the run's end."""

    def stopped(self, loop: Loop, lost: NoRestartLeft | None = None) -> None:
        """The run stops early: on a stop signal (``lost`` None) or because its workers are lost."""

    def close(self, loop: Loop) -> None:
        """However the run ends."""

    def summary(self, loop: Loop) -> dict[str, Any]:
        """Keys this trigger adds to summary.json (none by default)."""
        return {}


class IntervalTrigger(Trigger):
    """``fn(loop)`` every ``interval`` iterations, under ``name``."""

    def __init__(self, interval: int, fn: Callable[[Loop], None], name: str | None = None):
        super().__init__(interval)
        self.fn = fn
        self.name = name or getattr(fn, "__name__", "trigger")

    def __call__(self, loop: Loop) -> None:
        self.fn(loop)


class LogTrigger(Trigger):
    """A metrics row of losses, speeds, training episodes' mean return and length, the episodes
    finished so far (TF-Agents' StepPerSecondLogTrigger and train metrics: NumberOfEpisodes,
    AverageReturnMetric, AverageEpisodeLengthMetric) and the workers' state (alive, restarts)."""

    name = LOG

    def __call__(self, loop: Loop) -> None:
        row = {**loop.interval_stats.flush(loop.clock), "episodes": loop.state.episodes, **loop.supervisor.columns()}
        if loop.collector is not None:  # the backend's own figures (Ray: weight versions)
            row.update(loop.collector.metrics())
        elif loop.state.backend_metrics is not None:  # a resumed run's row owed before its collector starts
            row.update(backend_class(loop.config).metrics_between(loop.state.backend_metrics, loop.state.updates))
            loop.state.backend_metrics = None
        loop.log(row)
        if any(k.startswith("loss_") for k in row):  # nothing to say before the first update
            loop.echo(log_line(loop.state.iteration, row))
        with loop.clock.paused():
            if loop.config.live_report:
                loop.page.refresh()  # the page's losses and speeds between evaluations, at a bounded cost


class EvalTrigger(Trigger):
    """An evaluation of the deterministic policy, here or in the background (``Evaluations``); the
    random baseline at the start. The last iteration is always evaluated, whatever the interval, within
    that iteration's triggers and waited for: the triggers after it (a user's) see its return."""

    name = EVAL

    def __init__(self, interval: int):
        super().__init__(interval)
        self.evaluations: Evaluations | None = None

    def due(self, previous: int, now: int, last: int) -> bool:
        return now >= last > previous or super().due(previous, now, last)

    def __call__(self, loop: Loop) -> None:
        if loop.state.iteration >= loop.config.num_iterations:
            self.evaluations.finish()  # the background ones still out, then this one, here
        else:
            self.evaluations.ask()

    def start(self, loop: Loop) -> None:
        self.evaluations = Evaluations(loop)
        self.evaluations.start()

    def poll(self, loop: Loop) -> None:
        self.evaluations.take()

    def final(self, loop: Loop) -> None:
        self.evaluations.finish()

    def stopped(self, loop: Loop, lost: NoRestartLeft | None = None) -> None:
        if self.evaluations is None:  # stopped before the run's start reached this trigger
            return
        if lost is None:
            self.evaluations.take(feed=False)  # one already back is kept; the others are saved
            return
        try:
            self.evaluations.take(feed=False)
        except WorkerFailure:
            pass
        owed, pending = loop.state.owed, loop.state.pending_evals
        if owed[:1] == [EVAL] and any(at["step"] == loop.state.iteration for at, _ in pending):
            owed.pop(0)  # asked before its evaluator failed: saved as pending, not asked twice

    def close(self, loop: Loop) -> None:
        if self.evaluations is not None:
            self.evaluations.close()


class ExportTrigger(Trigger):
    """The deterministic policy exported to ``RUN/policy`` as ``step_NNNNNNN.onnx/.pt2`` and ``policy.onnx/.pt2``
    (TF-Agents' PolicySavedModelTrigger; ``policy_keep`` says how many steps stay), and at the end."""

    name = EXPORT

    def __init__(self, interval: int):
        super().__init__(interval)
        self.exported_at: int | None = None

    def __call__(self, loop: Loop) -> None:
        pipeline = loop.pipeline
        with loop.clock.paused():
            export_policy(pipeline.exported_policy(), pipeline.observation_shape, loop.run_dir.policy_dir,
                          pipeline.export_info(), step=loop.state.iteration, keep=loop.config.policy_keep,
                          dtype=pipeline.observation_dtype, **pipeline.export_inputs())
        self.exported_at = loop.state.iteration

    def final(self, loop: Loop) -> None:
        if self.exported_at != loop.state.iteration:
            self(loop)
        best = kept_best(loop)
        if best is not None:
            self.export_best(loop, best)

    @staticmethod
    def export_best(loop: Loop, best: dict[str, Any]) -> None:
        """``keep_best``: ``policy.onnx/.pt2`` become the policy of the best evaluation (its weights put in the
        policy for the export, then the last ones back); the last stays as its ``step_NNNNNNN`` files."""
        pipeline = loop.pipeline
        device = next(pipeline.policy.parameters()).device
        last = best["weights"].to(device).to_module(pipeline.policy, return_swap=True)
        try:
            module = pipeline.exported_policy()
        finally:
            last.to_module(pipeline.policy)
        info = {**pipeline.export_info(), "chosen": "best", "best": {
            "step": best["at"]["step"], "env_steps": best["at"].get("frames"), "average_return": best["return"],
            "last_step": loop.state.iteration, "last_average_return": loop.last_return}}
        with loop.clock.paused():
            export_policy(module, pipeline.observation_shape, loop.run_dir.policy_dir, info,
                          dtype=pipeline.observation_dtype, **pipeline.export_inputs())
        loop.echo(f"policy: the best greedy evaluation's (step {best['at']['step']}, AverageReturn "
                  f"{best['return']:.6g}; the last, {loop.last_return:.6g}, is "
                  f"policy/{step_name(loop.state.iteration, '.onnx')})")


def kept_best(loop: Loop) -> dict[str, Any] | None:
    """The best evaluation's record when ``keep_best`` makes it the exported policy: kept with its weights and
    better than the last evaluation (else None: the last policy is the best)."""
    best = loop.state.best
    if not loop.config.keep_best or best is None or best.get("weights") is None or not loop.evaluations:
        return None
    if best["at"]["step"] == loop.state.iteration or best["return"] <= loop.evaluations[-1]["average_return"]:
        return None
    return best


class CheckpointTrigger(Trigger):
    """A checkpoint that ``--resume`` continues from: every ``interval``, at the end, and when the run
    stops early (recording what its iteration still owes)."""

    name = SAVE
    at_last_iteration = False
    crossed_off_first = True

    def __call__(self, loop: Loop) -> None:
        loop.check_finite()  # every checkpoint is a finite state (TrainingDiverged otherwise)
        loop.state.wall_time_s, loop.state.train_time_s = loop.clock.wall(), loop.clock.train_seconds()
        with loop.clock.paused():
            loop.metrics.sync()  # the rows this checkpoint counts reach the disk before it does
            loop.resume.capture(loop.collection)
            ckpt.save_checkpoint(loop.run_dir.checkpoints, loop.state.iteration, loop.pipeline.state_dict(),
                                 keep=loop.config.checkpoint_keep)

    def final(self, loop: Loop) -> None:
        self(loop)

    def stopped(self, loop: Loop, lost: NoRestartLeft | None = None) -> None:
        self(loop)  # with what this iteration still owes: --resume does that first


class VideoTrigger(Trigger):
    """``video=true``: at the end, the exported policy filmed to RUN/trained-agent.mp4, as ``rlpipe video RUN`` does."""

    name = VIDEO

    def __init__(self):
        super().__init__(0)  # no interval: only the final firing

    def __call__(self, loop: Loop) -> None:
        from rlpipe.pipelines.analysis.report_pages import VIDEO_FILE
        from rlpipe.pipelines.artifacts.export import load_policy
        from rlpipe.pipelines.artifacts.video import record_video

        # the policy this run exported a moment ago: its own file, so a .pt2-only export (a plug-in
        # actor ONNX cannot express) is trusted here, as it would not be from someone else's run
        policy = load_policy(loop.run_dir.policy_dir, trust=True)[0]
        path = record_video(loop.config.env, policy, loop.run_dir.path / VIDEO_FILE, env_kwargs=loop.config.env_kwargs,
                            observation_options=env_options(loop.config, rescaled=False))
        loop.echo(f"video: {path}")

    def final(self, loop: Loop) -> None:
        self(loop)


class TargetTrigger(Trigger):
    """``target_return``: ends the run once the mean return of the last ``target_window`` finished
    training episodes reaches the target and a greedy evaluation of ``target_eval_episodes`` episodes,
    made there and then, confirms it; one that does not confirm it is tried again after
    ``target_recheck_episodes`` more finished episodes. Checked after every block (``poll``), so no
    interval; summary.json's ``"target"`` says whether and when (``rlpipe bench time-to-return``
    times a run with it: ``time_unix`` minus the launch, less ``eval_seconds``).

    The training episodes' returns are the env's own undiscounted rewards (``RewardSum``), as gymnasium's
    ``RecordEpisodeStatistics`` and SB3's ``Monitor`` count them for the peers.
    """

    name = TARGET

    def __init__(self, target: float, window: int = 5, eval_episodes: int = 10, recheck_episodes: int = 5):
        super().__init__(0)  # never by interval: after each block
        self.target, self.window, self.eval_episodes = float(target), int(window), int(eval_episodes)
        self.recheck_episodes = int(recheck_episodes)
        self.episodes = 0  # finished training episodes seen by ``poll`` in this session
        self.counted: int | None = None  # ``loop.state.episodes`` at the last ``poll``
        self.next_check = self.window  # ``episodes`` from which the next check may be made
        self.eval_seconds = 0.0  # spent in confirmations that did not confirm (before ``time_unix``)
        self.confirm_seconds = 0.0  # the one that did
        self.checks = 0
        self.reached: dict[str, Any] | None = None
        self.train_mean: float | None = None
        self.eval_return: float | None = None
        self.eval_length: float | None = None  # the confirming episodes' mean length: a short one is a lunge, not a walk
        self.last_block_unix: float | None = None

    def __call__(self, loop: Loop) -> None:
        self.poll(loop)

    def poll(self, loop: Loop) -> None:
        self.last_block_unix = time.time()
        returns = loop.recent_returns
        if self.counted is not None:
            self.episodes += loop.state.episodes - self.counted
        else:  # this session's first block: those it finished are all in ``returns``
            self.episodes = len(returns)
        self.counted = loop.state.episodes
        if self.reached is not None or len(returns) < self.window or self.episodes < self.next_check:
            return
        recent = list(returns)[-self.window:]
        mean = sum(recent) / len(recent)
        self.train_mean = mean
        if mean < self.target:
            return
        met_unix = time.time()
        state = loop.state
        with loop.clock.paused():
            result = evaluate(loop.pipeline.eval_env, loop.pipeline.policy, self.eval_episodes, interrupt=loop.stop.check,
                              direct=loop.config.fast)
        seconds = time.time() - met_unix
        self.checks += 1
        self.eval_return = result["average_return"]
        self.eval_length = result["average_episode_length"]
        if self.eval_return < self.target:
            self.eval_seconds += seconds
            self.next_check = self.episodes + self.recheck_episodes
            loop.echo(f"step = {state.iteration}: target {self.target:g} not confirmed: training episodes' mean "
                      f"{mean:.6g}, greedy evaluation {self.eval_return:.6g}; training goes on")
            return
        self.confirm_seconds = seconds
        self.reached = {"iteration": state.iteration, "env_steps": state.frames, "updates": state.updates,
                        "train_mean": mean, "eval_return": self.eval_return, "eval_episode_length": self.eval_length,
                        "time_unix": met_unix}
        loop.echo(f"step = {state.iteration}: target {self.target:g} reached: training episodes' mean {mean:.6g}, "
                  f"greedy evaluation {self.eval_return:.6g} over {self.eval_episodes} episodes "
                  f"(mean length {self.eval_length:g}); training stops")
        loop.finish_early("target")

    def summary(self, loop: Loop) -> dict[str, Any]:
        state = loop.state
        at = self.reached or {"iteration": state.iteration, "env_steps": state.frames, "updates": state.updates,
                              "train_mean": self.train_mean, "eval_return": self.eval_return,
                              "eval_episode_length": self.eval_length, "time_unix": None}
        return {"target": {
            "return": self.target, "reached": self.reached is not None, **at,
            "window": self.window, "eval_episodes": self.eval_episodes, "confirmations": self.checks,
            "eval_seconds": self.eval_seconds, "confirm_seconds": self.confirm_seconds,
            "first_step_unix": loop.first_block_unix, "last_block_unix": self.last_block_unix,
        }}


class TimeBudgetTrigger(Trigger):
    """``time_budget``: ends the run (``loop.finish_early("time_budget")``) at the end of the collected block in
    which the run's wall-clock time, every session of a resumed run included, reaches the budget."""

    name = "time_budget"

    def __init__(self, seconds: float, text: str):
        super().__init__(1)
        self.seconds, self.text = seconds, text

    def due(self, previous: int, now: int, last: int) -> bool:
        return False  # polled after every block instead

    def poll(self, loop: Loop) -> None:
        if loop.finished_early is None and loop.clock.wall() >= self.seconds:
            loop.echo(f"step = {loop.state.iteration}: time budget {self.text} reached after "
                      f"{loop.clock.wall():.0f} s; training stops")
            loop.finish_early("time_budget")


def default_triggers(cfg: TrainConfig) -> list[Trigger]:
    """The tutorials' triggers, in the order they run within an iteration (and in the final firing)."""
    triggers = [
        LogTrigger(cfg.log_interval),
        EvalTrigger(cfg.eval_interval),
        ExportTrigger(cfg.policy_save_interval),
        CheckpointTrigger(cfg.checkpoint_interval),
    ]
    if cfg.video:
        triggers.append(VideoTrigger())
    if cfg.target_return is not None:
        triggers.append(TargetTrigger(cfg.target_return, cfg.target_window, cfg.target_eval_episodes,
                                      cfg.target_recheck_episodes))
    if cfg.time_budget is not None:
        triggers.append(TimeBudgetTrigger(duration_seconds(cfg.time_budget), str(cfg.time_budget)))
    return triggers


# --- the live log: the tutorials' printed lines ------------------------------------------------------


def _num(value: float) -> str:
    return f"{value:.6g}" if math.isfinite(value) else "nan"


def log_line(step: int, row: Mapping[str, Any]) -> str:
    """``step = 200: loss = 0.41, ...``: the tutorials' loss line for a log row.

    ``loss`` is the total the TF-Agents agents report (SAC: actor + critic + alpha losses, TD3: actor
    + critic, DQN: its one loss), each term after it, then the diagnostics and the training episodes'
    mean return.
    """
    terms = {k.removeprefix("loss_"): float(v) for k, v in row.items() if k.startswith("loss_")}
    losses = {k: v for k, v in terms.items() if k not in DIAGNOSTICS}
    parts = [f"loss = {_num(sum(losses.values()))}"]
    if len(losses) > 1:
        parts += [f"{k}_loss = {_num(v)}" for k, v in losses.items()]
    parts += [f"{k} = {_num(v)}" for k, v in terms.items() if k in DIAGNOSTICS]
    if "train_episode_return" in row:
        parts.append(f"train episode return = {_num(float(row['train_episode_return']))}")
    return f"step = {step}: " + ", ".join(parts)
