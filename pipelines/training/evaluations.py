"""A run's evaluations, as the eval trigger runs them: here, in a background process, or on a Ray
actor (started, restarted when it fails, its results taken and recorded), and the random agent's
baseline played once at the start.

An evaluation's result becomes a metrics row (``average_return``, ``average_episode_length``), the
tutorials' live line, and (``live_report``, at a bounded cost: ``page``) a point of RUN/returns.png and a
refreshed RUN/report.html.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from tensordict import TensorDictBase
from torchrl.envs.utils import RandomPolicy

from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.config import BASELINE_SEED_OFFSET, eval_seed
from rlpipe.pipelines.system.faults import fault_point
from rlpipe.pipelines.system.runtime import stop_signals_blocked
from rlpipe.pipelines.workers.evaluation import AsyncEvaluator, evaluate
from rlpipe.pipelines.workers.factory import backend_class
from rlpipe.pipelines.workers.supervision import WorkerFailure

if TYPE_CHECKING:
    from torch import nn

    from rlpipe.pipelines.training.loop import Loop

__all__ = ["Evaluations", "eval_line"]


class Evaluations:
    """The evaluations of ``loop``'s run; ``loop.evaluations`` holds their results, oldest first."""

    def __init__(self, loop: Loop):
        self.loop = loop
        self.background: AsyncEvaluator | None = None
        self.ray = None  # the run's hold on Ray while its evaluator is a Ray actor (ray_eval.hold_ray)

    def start(self) -> None:
        """The random baseline, then the background evaluator (``eval_in_background``), which asks
        again for what a stopped run left pending; without one, those are evaluated here."""
        loop = self.loop
        self.measure_random_baseline()
        pending = loop.state.pending_evals
        if loop.config.eval_in_background:
            self.background = self._start_evaluator()
        while pending and self.background is None:  # asked for in the background before a resume that turned it off
            at, weights = pending[0]
            self.now(weights, at)
            pending.popleft()

    def ask(self) -> None:
        """Evaluate the policy as it is now: in the background if the run does so, else here."""
        loop = self.loop
        if self.background is not None and loop.state.iteration > 0:
            self.background.ask(loop.state.position(), self.background.snapshot(loop.pipeline.policy))
            fault_point("evaluator_worker", loop.state.iteration, worker=lambda: self.background.worker_pid)
            self.take()
        else:
            self.now()

    def now(self, weights: TensorDictBase | None = None, at: dict[str, int] | None = None) -> None:
        """Evaluate the policy (or ``weights``, taken at ``at``) in this process."""
        loop = self.loop
        at = at or loop.state.position()
        fault_point("evaluate", at["step"])
        policy = loop.pipeline.policy
        if weights is not None:
            policy = copy.deepcopy(policy)
            weights.to_module(policy)
        with loop.clock.paused():
            loop.pipeline.eval_env.set_seed(eval_seed(loop.config.seed, at["step"]))
            result = evaluate(loop.pipeline.eval_env, policy, loop.config.num_eval_episodes, interrupt=loop.stop.check,
                              direct=loop.config.fast)
        self.record(result, at, weights if weights is not None else AsyncEvaluator.snapshot)

    def take(self, block: bool = False, feed: bool = True) -> None:
        """Record the background evaluations that are back (``block``: wait for all of them); an
        evaluator that failed is replaced, and asked again for what it had not answered."""
        loop = self.loop
        while self.background is not None:
            try:
                with loop.clock.paused() if block else contextlib.nullcontext():
                    for at, result, weights in self.background.results(block=block, feed=feed,
                                                                       interrupt=loop.stop.check):
                        self.record(result, at, weights)
                return
            except WorkerFailure as failure:
                self._restart_evaluator(failure)

    def finish(self) -> None:
        """The run's last evaluations: those still in the background, then the last iteration's."""
        loop = self.loop
        self.take(block=True)
        if not loop.evaluations or loop.evaluations[-1]["step"] != loop.state.iteration:
            self.now()

    def close(self) -> None:
        """Stop the evaluator (its process or Ray actor), then the run's hold on Ray."""
        if self.background is not None:
            self.background.close()
        if self.ray is not None:
            self.ray.close()

    def _start_evaluator(self) -> AsyncEvaluator:
        """The collector backend's evaluator (a process beside local collectors, a Ray actor beside Ray's),
        started with the stop signals blocked (its processes must not see them) and outside training time."""
        loop, cfg = self.loop, self.loop.config
        backend, supervisor = backend_class(cfg), loop.supervisor
        with loop.clock.paused(), stop_signals_blocked():
            self.ray = self.ray or backend.hold(cfg)
            evaluator = backend.start_evaluator(cfg, env_fn=loop.pipeline.eval_env_fn, policy=loop.pipeline.policy,
                                                pending=loop.state.pending_evals,
                                                start_timeout=supervisor.start_timeout, watchdog=loop.watchdog)
        supervisor.report("evaluator", 1, 1)
        return evaluator

    def _restart_evaluator(self, failure: WorkerFailure) -> None:
        loop = self.loop
        with loop.clock.paused():
            self.background.close()
        self.background = None
        loop.supervisor.report("evaluator", 0, 1)
        while self.background is None:
            loop.supervisor.failed("evaluator", failure)  # NoRestartLeft when no restart is left
            try:
                self.background = self._start_evaluator()  # it asks again for the oldest pending evaluation
            except (RuntimeError, ValueError, EOFError, OSError) as exc:
                failure = WorkerFailure("evaluator", f"the evaluator did not start again: {exc}")

    def record(self, result: dict[str, Any], at: dict[str, int],
               weights: TensorDictBase | Callable[[nn.Module], TensorDictBase] | None = None) -> None:
        """An evaluation's result, taken at ``at`` of the policy's ``weights`` (or of the policy as it is now,
        ``weights`` then being the function that snapshots it): its metrics row and live line, the best one so far
        (``keep_best``: with its weights), and a plateau (``plateau``) that ends the run."""
        loop = self.loop
        loop.evaluations.append({**at, **result})
        best = loop.state.best
        if best is None or result["average_return"] > best["return"]:
            if callable(weights):
                weights = weights(loop.pipeline.policy)
            kept = weights.detach().clone() if loop.config.keep_best and weights is not None else None
            loop.state.best = {"at": dict(at), "return": float(result["average_return"]), "weights": kept}
        success = {"success_rate": result["success_rate"]} if "success_rate" in result else {}
        loop.log({"average_return": result["average_return"],
                  "average_episode_length": result["average_episode_length"], **success,
                  "wall_time": loop.clock.wall()}, at)
        loop.echo(eval_line(at["step"], result, *loop.speeds()))
        if loop.config.live_report and at["step"] < loop.config.num_iterations:  # the last: the run's end draws it
            with loop.clock.paused():  # returns.png from the evaluations in memory, and the page: at a bounded cost
                loop.page.evaluated()
        loop.bar.set_postfix(avg_return=f"{loop.last_return:.1f}", refresh=False)
        self._plateau(at)

    def _plateau(self, at: dict[str, int]) -> None:
        """End the run (``finish_early("plateau")``) when, from ``plateau_min_iterations`` on, the best evaluation
        lies ``plateau`` of the run's iterations back and at least ``plateau_evaluations`` evaluations ago."""
        loop, cfg = self.loop, self.loop.config
        if (not cfg.plateau or loop.finished_early is not None or at["step"] >= cfg.num_iterations
                or at["step"] < cfg.plateau_min_iterations):
            return
        best_step = loop.state.best["at"]["step"]
        since = sum(1 for e in loop.evaluations if e["step"] > best_step)
        if since >= cfg.plateau_evaluations and at["step"] - best_step >= cfg.plateau * at["step"]:
            loop.echo(f"step = {at['step']}: plateau: the best greedy evaluation ({loop.state.best['return']:.6g}, "
                      f"step {best_step}) is {since} evaluations and {at['step'] - best_step} iterations back, "
                      f"over {cfg.plateau:g} of the run; training stops")
            loop.finish_early("plateau")

    def measure_random_baseline(self) -> None:
        """The random agent's return on the eval env (the DQN tutorial's baseline), once per run: RUN/baseline.json.

        Played on an env of its own, with the run's random generators (torch, numpy, Python) put back
        afterwards, so the run's own evaluations and draws are those of a run without it, and a run
        resumed from its first checkpoint (saved before this) goes on as the uninterrupted one. A
        pipeline handed env instances (no function to make another) has no baseline.
        """
        loop, cfg = self.loop, self.loop.config
        episodes = cfg.num_eval_episodes if cfg.baseline_episodes == -1 else cfg.baseline_episodes
        if episodes == 0 or loop.pipeline.eval_env_fn is None:
            return  # before importing the report pages (pandas, matplotlib): ~2 s before the first env step
        from rlpipe.pipelines.analysis.report_pages import read_baseline, write_baseline

        if read_baseline(loop.run_dir.path) is not None:
            return
        loop.echo(f"random agent: playing {episodes} episodes for its baseline return (baseline_episodes)")
        generators = ckpt.rng_state()
        env = loop.pipeline.eval_env_fn()
        try:
            env.set_seed(cfg.seed + BASELINE_SEED_OFFSET)
            result = evaluate(env, RandomPolicy(env.full_action_spec), episodes, interrupt=loop.stop.check,
                              direct=loop.config.fast)
        finally:
            env.close()
            ckpt.set_rng_state(generators)
        write_baseline(loop.run_dir.path, result)
        loop.echo(f"random agent: AverageReturn = {result['average_return']:.6f}, "
                  f"AverageEpisodeLength = {result['average_episode_length']:.6f} "
                  f"({episodes} episodes)")


def eval_line(step: int, result: Mapping[str, Any], steps_per_s: float, updates_per_s: float) -> str:
    """``step = 1000: AverageReturn = ..., AverageEpisodeLength = ..., ...``: the tutorials' evaluation line.

    The speeds are training time's (evaluations and saving left out) since this session started.
    """
    success = f"SuccessRate = {result['success_rate']:.3f}, " if "success_rate" in result else ""
    return (f"step = {step}: AverageReturn = {result['average_return']:.6f}, "
            f"AverageEpisodeLength = {result['average_episode_length']:.6f}, {success}"
            f"env steps/s = {steps_per_s:.1f}, updates/s = {updates_per_s:.1f}")
