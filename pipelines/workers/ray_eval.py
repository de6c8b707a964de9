"""The background evaluation on a Ray actor (``collector.backend=ray`` with ``eval_in_background=true``).

``RayEvaluator`` is an ``evaluation.AsyncEvaluator``, as ``BackgroundEvaluator`` is (``ask``, ``results``,
``check``, ``close``, ``worker_pid``, ``snapshot``), with the evaluation in a Ray actor that Ray
places on any node with ``ray.num_cpus_per_worker`` CPUs free: one actor, ``EvalActor``, that makes
the eval env (seeded for each evaluation from the run's seed and its step, ``config.eval_seed``, as the learner's own is) and a CPU copy of the
policy, and runs ``evaluation.evaluate`` on each snapshot of weights sent to it. The same weights on
the same seed give the same result as an evaluation in the learner's process.

Why not TorchRL's ``Evaluator(backend="ray")`` (``RayEvalWorker``): in 0.14 it plays one rollout
of at most ``max_steps`` steps and reports the mean reward per step of it; it ignores
``num_trajectories``, so it cannot give the average return and episode length over
``num_eval_episodes`` full episodes that the tutorials' metrics are. Ray's own actor calls carry
the weights (a TensorDict, as RayEvalWorker sends them) and the result.

Supervision, as for the process evaluator: an actor that dies (its process killed, its node gone)
makes ``results``/``check`` raise ``WorkerFailure("evaluator", ...)`` within seconds (Ray fails the
call in flight; an idle actor is looked up in Ray's actor table); so does an evaluation not back
within ``eval_timeout``. The loop then closes it (``ray.kill``) and starts another on the same
``pending`` queue, which asks again for the evaluation that was in flight.

The run holds Ray for its whole length (``hold_ray``): the evaluator and the Ray collectors come
and go on it (each restart of one leaves the other running), and it is let go at the run's end.
"""

from __future__ import annotations

import contextlib
import time
from collections import deque
from collections.abc import Callable

from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from rlpipe.pipelines.config import EVAL_SEED_OFFSET, TrainConfig, eval_seed
from rlpipe.pipelines.system.runtime import say
from rlpipe.pipelines.workers.evaluation import AsyncEvaluator, EvalActor, _PolicyCopy
from rlpipe.pipelines.workers.ray_runtime import RayRuntime, check_cpus
from rlpipe.pipelines.workers.supervision import MIN_START_TIMEOUT_S, WorkerFailure, first_line

__all__ = ["EvalActor", "RayEvaluator", "hold_ray"]

def hold_ray(config: TrainConfig) -> RayRuntime:
    """The run's hold on Ray while its evaluator lives there: joins ``ray.address`` or starts a local
    instance with a CPU for each collector actor and one for the evaluator; ``close()`` lets go."""
    c, r = config.collector, config.ray
    return RayRuntime(r.address, (c.workers + 1) * r.num_cpus_per_worker)


class RayEvaluator(AsyncEvaluator):
    """Evaluations on snapshots of the policy's weights, on a Ray actor, while training goes on.

    The ``pending`` queue, one evaluation in flight at a time and ``eval_timeout`` counted from when
    it was sent are ``AsyncEvaluator``'s (see there). ``Ray`` must be up (``hold_ray``).
    """

    _CHECK_EVERY_S = 1.0
    """how often an idle actor is looked up in Ray's actor table (one call to Ray's GCS)"""

    def __init__(self, env_fn: Callable[[], EnvBase], policy: nn.Module, num_episodes: int,
                 pending: deque[tuple[dict, TensorDictBase]], *, config: TrainConfig, timeout: float = 600.0,
                 start_timeout: float = MIN_START_TIMEOUT_S):
        import ray

        super().__init__(pending, timeout)
        self.num_episodes, self.seed = int(num_episodes), config.seed
        self._ref = None
        self._checked_at = 0.0
        self.worker_pid: int | None = None  # the actor's process on its node (the test hook kills it there)
        cpus = config.ray.num_cpus_per_worker
        check_cpus(ray, config, evaluator=True)
        remote = ray.remote(num_cpus=cpus, num_gpus=0, max_restarts=0, max_task_retries=0)(EvalActor)
        self._actor = remote.remote(env_fn, _PolicyCopy(policy), config.seed + EVAL_SEED_OFFSET, config.fast)
        try:
            ready, _ = ray.wait([ref := self._actor.pid.remote()], timeout=start_timeout)
            if not ready:
                free = ray.available_resources().get("CPU", 0.0)
                raise WorkerFailure(self.role, f"Ray did not place the evaluator actor within {start_timeout:g} s "
                                               f"({free:g} CPUs free, {cpus:g} asked)")
            try:
                self.worker_pid = ray.get(ref)
            except ray.exceptions.RayError as exc:
                raise WorkerFailure(self.role, f"the evaluator actor did not start: {first_line(exc)}") from exc
        except BaseException:
            self.close()
            raise

    def _send(self, at: dict, weights: TensorDictBase) -> None:
        self._ref = self._actor.evaluate.remote(weights, self.num_episodes, eval_seed(self.seed, at["step"]))

    def _take(self, timeout: float) -> dict | None:
        import ray

        ready, _ = ray.wait([self._ref], timeout=timeout)
        if not ready:
            return None
        try:
            result = ray.get(self._ref)
        except ray.exceptions.RayActorError as exc:  # its process or node is gone
            raise WorkerFailure(self.role, f"the evaluator actor (pid {self.worker_pid}) died "
                                           f"({first_line(exc).rstrip('.')})") from exc
        except ray.exceptions.RayError as exc:  # the evaluation raised: as the process evaluator's thread
            cause = getattr(exc, "cause", None) or exc
            raise WorkerFailure(self.role, f"the evaluator stopped on {type(cause).__name__}: "
                                           f"{first_line(cause)}") from exc
        self._ref = None
        return result

    def check(self) -> None:
        """Raise ``WorkerFailure`` if the evaluation in flight is past ``timeout``, or if Ray's actor
        table says the actor is dead (looked up at most once a second)."""
        failure = self._overdue()
        if failure is not None:
            raise failure
        now = time.monotonic()
        if now - self._checked_at < self._CHECK_EVERY_S:
            return
        self._checked_at = now
        state = _actor_state(self._actor)
        if state == "DEAD":
            raise WorkerFailure(self.role, f"the evaluator actor (pid {self.worker_pid}) died")

    def close(self, timeout: float = 30.0) -> None:
        """Kill the actor (an evaluation in flight is dropped: ``pending`` still lists it) and wait, at
        most ``timeout`` seconds, until Ray's actor table says it is dead."""
        import ray

        actor, self._actor, self._ref, self._in_flight = self._actor, None, None, None
        if actor is None or not ray.is_initialized():
            return
        with contextlib.suppress(Exception):
            ray.kill(actor, no_restart=True)
        deadline = time.monotonic() + timeout
        while _actor_state(actor) not in ("DEAD", None):
            if time.monotonic() > deadline:
                say(f"rlpipe: warning: the evaluator actor (pid {self.worker_pid}) did not stop within {timeout:g} s")
                return
            time.sleep(0.05)


def _actor_state(actor) -> str | None:
    """The actor's state in Ray's actor table (GCS): "ALIVE", "DEAD", ...; None if Ray does not know it.

    The table, not a ping: a ping would queue behind the evaluation in flight; the public state API
    (ray.util.state) needs the dashboard, which the run does not start (as ``RayBackend.health``)."""
    import ray
    from ray._private.state import actors

    if not ray.is_initialized():
        return None
    try:
        state = actors(actor_id=actor._actor_id.hex()).get("State")
    except Exception:
        return None
    return {2: "ALIVE", 4: "DEAD"}.get(state, state) if isinstance(state, int) else state
