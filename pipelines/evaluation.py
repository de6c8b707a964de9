"""Evaluation of the deterministic policy: TF-Agents' AverageReturn and AverageEpisodeLength, in the
learner's process (``evaluate``) or in a process of its own while training goes on
(``BackgroundEvaluator``, TorchRL's ``Evaluator`` with the one workaround it needs)."""

from __future__ import annotations

import copy
import threading
from collections import deque
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.collectors import Evaluator
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rlpipe.pipelines.runtime import sigint_blocked

__all__ = ["BackgroundEvaluator", "evaluate"]


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


class BackgroundEvaluator:
    """Evaluations on snapshots of the policy's weights, in a child process, while training goes on.

    ``pending`` is the queue of evaluations asked for and not back yet, oldest first, as
    ``(position, weights)``; it belongs to the run's state (checkpoints save it), and this object
    works through it: ``ask`` appends, ``results`` hands back those finished.

    TorchRL 0.14's ``Evaluator`` loses a request when a second one is queued while the first
    finishes (its backend's poll clears the pending flag of the next request), and the run then
    waits forever for that result: this class hands it one request at a time. Delete the
    ``in_flight`` bookkeeping when TorchRL's queue holds.
    """

    def __init__(self, env_fn: Callable[[], EnvBase], policy: nn.Module, num_episodes: int,
                 pending: deque[tuple[dict, TensorDictBase]]):
        self.pending = pending
        self._in_flight: tuple[dict, TensorDictBase] | None = None
        self._evaluator = Evaluator(
            env_fn,
            policy_factory=_PolicyCopy(policy),
            num_trajectories=num_episodes,
            max_steps=None,  # our envs end episodes themselves (time limits)
            backend="process",
            busy_policy="queue",
            collector_kwargs={"traj_format": "padded"},  # what 0.14 does by default, without its FutureWarning
        )
        # TorchRL 0.14 starts the worker process at the first request, from the evaluator's thread,
        # where its seconds of start-up can be neither waited for briefly nor stopped: start it here,
        # with the weight-sync scheme that first request would install (else it restarts the worker).
        backend = self._evaluator._backend
        with sigint_blocked():
            backend._enable_process_weight_sync()
            backend._ensure_collector()

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
            with sigint_blocked():  # the evaluator starts its thread at the first request
                self._evaluator.trigger_eval(weights, step=at["step"])

    def results(self, block: bool = False, feed: bool = True, interrupt: Callable[[], None] | None = None):
        """Yield ``(position, result)`` of the evaluations that are back, oldest first.

        ``block``: wait for all of them (calling ``interrupt`` between polls); ``feed=False``: only
        take the one in flight, if it is back, and hand out no new request.
        """
        while self.pending:
            if feed:
                self._feed()
            elif self._in_flight is None:
                return
            reply = self._evaluator.poll(timeout=0.2 if block else 0)
            if reply is None:
                if not block:
                    return
                if interrupt is not None:
                    interrupt()
                continue
            at, _ = self._in_flight
            if int(reply["eval/step"]) != at["step"]:
                raise RuntimeError(f"the background evaluator answered for step {int(reply['eval/step'])}, "
                                   f"expected step {at['step']}")
            self._in_flight = None
            self.pending.popleft()
            yield at, {"average_return": float(reply["eval/reward"]),
                       "average_episode_length": float(reply["eval/episode_length"]), "returns": None}

    def close(self, timeout: float = 2.0) -> None:
        """Stop the evaluator and its worker process within about ``timeout`` seconds; an evaluation
        in flight is dropped (the run's ``pending`` still lists it, so a checkpoint keeps it).

        TorchRL 0.14's ``Evaluator.shutdown`` first joins its thread, which waits for the evaluation in
        flight, then shuts the worker down with TorchRL's default 10 s: so the worker is stopped first
        here, and the thread, which then finds its collector gone, ends without printing that as an error.
        """
        backend = self._evaluator._backend
        with _QuietThreadEnd(backend._thread):
            backend._shutdown_flag = True
            if backend._collector is not None:
                backend._collector.shutdown(timeout=timeout, raise_on_error=False)
            self._evaluator.shutdown(timeout=timeout)


class _QuietThreadEnd:
    """While inside, an exception that ends ``thread`` is not printed (it is the shutdown itself)."""

    def __init__(self, thread: threading.Thread | None):
        self.thread = thread

    def __enter__(self):
        self._previous = threading.excepthook
        if self.thread is not None:
            threading.excepthook = self._hook
        return self

    def _hook(self, args) -> None:
        if args.thread is not self.thread:
            self._previous(args)

    def __exit__(self, *exc) -> None:
        if self.thread is not None and self.thread.is_alive():
            self.thread.join(timeout=1.0)
        threading.excepthook = self._previous


class _PolicyCopy:
    """A picklable policy factory for an evaluator process: a CPU copy of the policy's structure."""

    def __init__(self, policy: nn.Module):
        self.policy = copy.deepcopy(policy).cpu()

    def __call__(self, env=None) -> nn.Module:
        return copy.deepcopy(self.policy)
