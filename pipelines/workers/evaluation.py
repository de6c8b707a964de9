"""Evaluation of the deterministic policy: TF-Agents' AverageReturn and AverageEpisodeLength, in the
learner's process (``evaluate``) or elsewhere while training goes on (``AsyncEvaluator``, the queue
of requests; ``BackgroundEvaluator``, TorchRL's ``Evaluator`` in a process of its own, with the one
workaround it needs; ``ray_eval.RayEvaluator``, on a Ray actor)."""

from __future__ import annotations

import copy
import sys
import threading
import time
from collections import deque
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.collectors import Evaluator
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rlpipe.pipelines.compat.torchrl import (
    EVALUATOR_COLLECTOR_KWARGS,
    close_weight_sync_queues,
    evaluator_collector,
    evaluator_threads,
    start_evaluator_worker,
    stop_evaluator_threads,
)
from rlpipe.pipelines.system.runtime import stop_signals_blocked
from rlpipe.pipelines.workers.supervision import TimedMultiProcessScheme, WorkerFailure, dead_worker, kill_processes

__all__ = ["AsyncEvaluator", "BackgroundEvaluator", "evaluate"]


@torch.no_grad()
def evaluate(env: EnvBase, policy, num_episodes: int, max_steps: int = 100_000, interrupt=None) -> dict:
    """Run ``num_episodes`` full episodes of ``policy`` (deterministic) on ``env``.

    ``env`` may be batched (``SerialEnv``, ``ParallelEnv``): each rollout then plays one episode
    in every sub-env, and the first ``num_episodes`` episodes count. ``interrupt``, if given, is
    called before every env step; an exception it raises ends the evaluation (the training loop
    uses it to stop at Ctrl-C in the middle of a long evaluation).

    Returns ``average_return``, ``average_episode_length`` and the per-episode ``returns``.
    Episodes end when the env says done (terminated or truncated by its time limit).
    """
    returns: list[float] = []
    lengths: list[int] = []
    callback = None if interrupt is None else (lambda *_: interrupt())
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        while len(returns) < num_episodes:
            rollout = env.rollout(max_steps, policy, auto_cast_to_device=True, callback=callback,
                                  break_when_any_done=not env.batch_size, break_when_all_done=bool(env.batch_size))
            # [*env batch, time]: an episode is its sub-env's steps up to and with its first done
            done = rollout["next", "done"].reshape(*rollout.shape, -1).any(-1)
            before_first_done = (done.cumsum(-1) - done.long()) == 0
            reward = rollout["next", "reward"].reshape(*rollout.shape, -1).sum(-1)
            returns += (reward * before_first_done).sum(-1).flatten().tolist()
            lengths += before_first_done.sum(-1).flatten().tolist()
    returns, lengths = returns[:num_episodes], lengths[:num_episodes]
    return {
        "average_return": sum(returns) / len(returns),
        "average_episode_length": sum(lengths) / len(lengths),
        "returns": returns,
    }


class AsyncEvaluator:
    """Evaluations on snapshots of the policy's weights, away from the learner, while training goes on:
    the request queue that the process evaluator (``BackgroundEvaluator``) and the Ray actor's
    (``ray_eval.RayEvaluator``) share.

    ``pending`` is the queue of evaluations asked for and not back yet, oldest first, as
    ``(position, weights)``; it belongs to the run's state (checkpoints save it), and this object
    works through it: ``ask`` appends, ``results`` hands back those finished. One evaluation is in
    flight at a time, so ``timeout`` (``eval_timeout``) counts from when it was sent. An evaluator
    that fails (``results`` raises ``WorkerFailure``: its worker died, or an evaluation was not back
    within ``timeout`` seconds) is closed and replaced by a new one on the same ``pending``, which
    asks again for the evaluation that was in flight.

    A backend supplies ``_send`` (hand the worker the request in flight), ``_take`` (its result, if
    back within a wait), ``check`` (with ``_overdue`` for the timeout) and ``close``.
    """

    role = "evaluator"

    def __init__(self, pending: deque[tuple[dict, TensorDictBase]], timeout: float):
        self.pending, self.timeout = pending, float(timeout)
        self._in_flight: tuple[dict, TensorDictBase] | None = None
        self._asked_at = 0.0

    @staticmethod
    def snapshot(policy: nn.Module) -> TensorDictBase:
        """The policy's weights now, to evaluate later."""
        return Evaluator.extract_weights(policy)

    def ask(self, at: dict, weights: TensorDictBase) -> None:
        self.pending.append((at, weights))
        self._feed()

    def _feed(self) -> None:
        if self.pending and self._in_flight is None:
            at, weights = self._in_flight = self.pending[0]
            self._asked_at = time.monotonic()
            self._send(at, weights)

    def results(self, block: bool = False, feed: bool = True, interrupt: Callable[[], None] | None = None):
        """Yield ``(position, result)`` of the evaluations that are back, oldest first.

        ``block``: wait for all of them (calling ``interrupt`` between polls); ``feed=False``: only
        take the one in flight, if it is back, and hand out no new request. Raises ``WorkerFailure``
        when the evaluator has failed (see the class).
        """
        while self.pending:
            if feed:
                self._feed()
            elif self._in_flight is None:
                return
            result = self._take(timeout=0.2 if block else 0)
            if result is None:
                # results(feed=False) (the loop at a stop) leaves check out: a failure found there
                # would restart the evaluator on the run's way out instead of stopping
                if feed:
                    self.check()
                if not block:
                    return
                if interrupt is not None:
                    interrupt()
                continue
            at, _ = self._in_flight
            self._in_flight = None
            self.pending.popleft()
            yield at, result

    def _overdue(self) -> WorkerFailure | None:
        """The failure of the evaluation in flight if it is past ``timeout``, else None."""
        if self._in_flight is not None and time.monotonic() - self._asked_at > self.timeout:
            return WorkerFailure(self.role, f"the evaluation at step {self._in_flight[0]['step']} was not back "
                                            f"within eval_timeout={self.timeout:g} s")
        return None

    def _send(self, at: dict, weights: TensorDictBase) -> None:
        """Hand the worker the evaluation of ``weights`` (taken at ``at``), now in flight."""
        raise NotImplementedError

    def _take(self, timeout: float) -> dict | None:
        """The result of the evaluation in flight if it is back within ``timeout`` seconds, else None;
        raises if the worker answered wrongly or failed on it."""
        raise NotImplementedError

    def check(self) -> None:
        """Raise ``WorkerFailure`` if the evaluator cannot answer."""
        raise NotImplementedError

    def close(self, timeout: float = 30.0) -> None:
        """Stop the worker; an evaluation in flight is dropped (``pending`` still lists it)."""
        raise NotImplementedError


class BackgroundEvaluator(AsyncEvaluator):
    """Evaluations in a child process: TorchRL's ``Evaluator`` (process backend) behind ``AsyncEvaluator``'s queue.

    TorchRL 0.14's ``Evaluator`` loses a request when a second one is queued while the first
    finishes (its backend's poll clears the pending flag of the next request), and the run then
    waits forever for that result: ``AsyncEvaluator`` hands it one request at a time (which
    ``eval_timeout`` needs too, so nothing is left to delete when TorchRL's queue holds).
    """

    def __init__(self, env_fn: Callable[[], EnvBase], policy: nn.Module, num_episodes: int,
                 pending: deque[tuple[dict, TensorDictBase]], timeout: float = 600.0, ack_timeout: float = 60.0):
        super().__init__(pending, timeout)
        self._evaluator = Evaluator(
            env_fn,
            policy_factory=_PolicyCopy(policy),
            num_trajectories=num_episodes,
            max_steps=None,  # our envs end episodes themselves (time limits)
            backend="process",
            busy_policy="queue",
            collector_kwargs=EVALUATOR_COLLECTOR_KWARGS,
            # TorchRL's default for the process backend, with a deadline on its acknowledgements
            weight_sync_schemes={"policy": TimedMultiProcessScheme(ack_timeout, role=self.role)},
        )
        self._thread_errors = _ThreadErrors(self._threads)
        with stop_signals_blocked():
            start_evaluator_worker(self._evaluator)

    @property
    def worker_pid(self) -> int | None:
        procs = self._procs()
        return procs[0].pid if procs else None

    def _send(self, at: dict, weights: TensorDictBase) -> None:
        with stop_signals_blocked():  # the evaluator starts its thread at the first request
            self._evaluator.trigger_eval(weights, step=at["step"])

    def _take(self, timeout: float) -> dict | None:
        reply = self._evaluator.poll(timeout=timeout)
        if reply is None:
            return None
        at, _ = self._in_flight
        if int(reply["eval/step"]) != at["step"]:
            raise RuntimeError(f"the background evaluator answered for step {int(reply['eval/step'])}, "
                               f"expected step {at['step']}")
        return {"average_return": float(reply["eval/reward"]),
                "average_episode_length": float(reply["eval/episode_length"]), "returns": None}

    def check(self) -> None:
        """Raise ``WorkerFailure`` if the evaluator cannot answer: its process is gone, one of its
        threads ended on an error, or the evaluation in flight is past ``timeout``."""
        failure = dead_worker(self.role, self._procs())
        error = self._thread_errors.first
        if failure is None and isinstance(error, WorkerFailure):  # its weight push timed out
            failure = error
        elif failure is None and error is not None:
            first = str(error).strip().splitlines()[0] if str(error).strip() else ""
            failure = WorkerFailure(self.role, f"the {self.role} stopped on {type(error).__name__}: {first}")
        if failure is None:
            failure = self._overdue()
        if failure is not None:
            raise failure

    def close(self, timeout: float = 30.0) -> None:
        """Stop the evaluator, its threads and its worker process, within about ``timeout`` seconds; an
        evaluation in flight is dropped (the run's ``pending`` still lists it, so a checkpoint keeps it).

        The order matters. The worker is killed first (an evaluation has nothing to save; asked to close,
        it would finish its episodes first), which ends every wait of TorchRL's two evaluator threads
        within a second; the threads are then joined until they have ended, before anything they use is
        closed. A thread left running when Python exits is stopped mid-call by the interpreter
        (``pthread_exit`` at its next take of the GIL), which aborts the process when that call is in
        torch's C++ ("terminate called without an active exception", "Fatal Python error: Aborted"):
        TorchRL 0.14's ``Evaluator.shutdown`` joins them for a few seconds only (``compat.torchrl``).
        """
        deadline = time.monotonic() + timeout
        evaluator = self._evaluator
        with self._thread_errors:  # an error that ends a thread now is the shutdown itself: not printed
            stop_evaluator_threads(evaluator)
            kill_processes(self._procs(), timeout=max(0.0, deadline - time.monotonic()))
            for thread in self._threads():
                thread.join(timeout=max(0.0, deadline - time.monotonic()))
            collector = evaluator_collector(evaluator)
            if collector is not None:
                collector.shutdown(timeout=2.0, raise_on_error=False)
            evaluator.shutdown(timeout=max(0.0, deadline - time.monotonic()))
            close_weight_sync_queues(collector)
        left = [t.name for t in self._threads() if t.is_alive()]
        if left:
            print(f"rlpipe: warning: the evaluator's threads {', '.join(left)} did not stop within {timeout:g} s",
                  file=sys.stderr, flush=True)

    def _procs(self) -> list:
        return list(getattr(evaluator_collector(self._evaluator), "procs", None) or [])

    def _threads(self) -> list[threading.Thread]:
        """TorchRL's evaluator threads: the one feeding requests, the one running them."""
        return evaluator_threads(self._evaluator)


class _ThreadErrors:
    """Records (instead of printing) the exception that ends one of ``threads()``; as a context
    manager, also restores ``threading.excepthook`` on leaving (installed from construction on)."""

    def __init__(self, threads: Callable[[], list[threading.Thread]]):
        self.threads = threads
        self.first: BaseException | None = None
        self._previous = threading.excepthook
        threading.excepthook = self._hook

    def _hook(self, args) -> None:
        if args.thread is not None and any(args.thread is t for t in self.threads()):
            if self.first is None:
                self.first = args.exc_value
            return
        self._previous(args)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        if threading.excepthook is self._hook:
            threading.excepthook = self._previous


class _PolicyCopy:
    """A picklable policy factory for an evaluator process: a CPU copy of the policy's structure."""

    def __init__(self, policy: nn.Module):
        self.policy = copy.deepcopy(policy).cpu()

    def __call__(self, env=None) -> nn.Module:
        return copy.deepcopy(self.policy)
