"""Evaluation of the deterministic policy: TF-Agents' AverageReturn and AverageEpisodeLength, in the
learner's process (``evaluate``) or elsewhere while training goes on (``AsyncEvaluator``, the queue
of requests; ``BackgroundEvaluator``, in a process of its own; ``ray_eval.RayEvaluator``, on a Ray actor)."""

from __future__ import annotations

import contextlib
import copy
import io
import itertools
import os
import signal
import time
from collections import deque
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.collectors import Evaluator
from torchrl.data import OneHot
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from rlpipe.envs import is_discrete
from rlpipe.modules.fast.tensor_policy import greedy_step
from rlpipe.pipelines.config import EVAL_SEED_OFFSET, eval_seed
from rlpipe.pipelines.system.runtime import STOP_SIGNALS, stop_signals_blocked
from rlpipe.pipelines.workers.gym_collector import gym_env_of
from rlpipe.pipelines.workers.supervision import (
    MIN_START_TIMEOUT_S,
    WorkerFailure,
    dead_worker,
    first_line,
    kill_processes,
)

__all__ = ["AsyncEvaluator", "BackgroundEvaluator", "EvalActor", "evaluate"]


@torch.no_grad()
def evaluate(env: EnvBase, policy, num_episodes: int, max_steps: int = 100_000, interrupt=None, *,
             direct: bool = True) -> dict:
    """Run ``num_episodes`` full episodes of ``policy`` (deterministic) on ``env``.

    ``env`` may be batched (``SerialEnv``, ``ParallelEnv``): each rollout then plays one episode
    in every sub-env, and the first ``num_episodes`` episodes count. ``interrupt``, if given, is
    called at every env step; an exception it raises ends the evaluation (the training loop
    uses it to stop at Ctrl-C in the middle of a long evaluation).

    Returns ``average_return``, ``average_episode_length`` and the per-episode ``returns``.
    Episodes end when the env says done (terminated or truncated by its time limit).

    On ``rlpipe.envs.make_env``'s one-copy env with a policy on the CPU, the episodes are played on the
    gymnasium env under it directly (``_evaluate_directly``): the same episodes and returns, number for
    number, at a fraction of the cost; ``direct=False`` (a run's ``fast=false``): TorchRL's ``env.rollout``.
    """
    gym_env = gym_env_of(env) if direct else None
    if gym_env is not None and not isinstance(env.action_spec_unbatched, OneHot) and _on_cpu(policy):
        return _evaluate_directly(env, gym_env, policy, num_episodes, max_steps, interrupt)
    return _evaluate_rollouts(env, policy, num_episodes, max_steps, interrupt)


def _evaluate_rollouts(env: EnvBase, policy, num_episodes: int, max_steps: int, interrupt) -> dict:
    """``evaluate`` through TorchRL's ``env.rollout``: any TorchRL env, batched ones too."""
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
    return _result(returns, lengths)


def _result(returns: list[float], lengths: list[int], successes: list[float] = ()) -> dict:
    result = {
        "average_return": sum(returns) / len(returns),
        "average_episode_length": sum(lengths) / len(lengths),
        "returns": returns,
    }
    if successes:  # every episode said: the share that ended in success
        result["success_rate"] = sum(successes) / len(successes)
    return result


def _on_cpu(policy) -> bool:
    """``policy`` is a module whose parameters and buffers are all on the CPU."""
    return isinstance(policy, nn.Module) and all(p.device.type == "cpu" for p in itertools.chain(policy.parameters(), policy.buffers()))


def _evaluate_directly(env: EnvBase, gym_env, policy: nn.Module, num_episodes: int, max_steps: int,
                       interrupt) -> dict:
    """``evaluate`` on the gymnasium env under ``make_env``'s ``env``, stepped with numpy and the policy's
    deterministic action on one observation tensor (``modules.tensor_policy.greedy_step``).

    Why: TorchRL's ``env.rollout`` through ``GymEnv`` and the standard transforms costs ~600-700 us a
    step on this 2-core CPU where CartPole's own step takes ~8 us (the same per-step TensorDict path that
    ``GymCollector`` avoids, BENCHMARKS.md); an evaluation of 10 CartPole-v1 episodes is 5,000 steps.
    What ``rollout`` does is kept: each episode starts with an unseeded ``reset()`` (``env.set_seed``
    seeded the generator), the observation is cast to the observation spec's dtype (``DoubleToFloat``),
    an episode ends at the first done or after ``max_steps`` steps, and its return is the float sum of
    its rewards cast to the reward spec's dtype, summed as ``evaluate`` sums them
    (``tests/test_evaluation.py`` compares both paths return for return).
    """
    obs_key = next(k for k in env.observation_spec.keys() if k not in ("step_count", "episode_reward", "is_init"))
    obs_dtype = env.observation_spec[obs_key].dtype
    reward_dtype = env.reward_spec.dtype
    discrete = is_discrete(env.action_spec_unbatched)
    act = greedy_step(policy, obs_key)
    returns: list[float] = []
    lengths: list[int] = []
    successes: list[float] = []  # goal envs' info["is_success"] at each episode's end
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        while len(returns) < num_episodes:
            obs, _ = gym_env.reset()
            rewards: list[float] = []
            info: dict = {}
            for _ in range(max_steps):
                action = act(torch.as_tensor(obs).to(obs_dtype))
                obs, reward, terminated, truncated, info = gym_env.step(action.item() if discrete else action.numpy())
                rewards.append(reward)
                if interrupt is not None:
                    interrupt()
                if terminated or truncated:
                    break
            returns.append(torch.tensor(rewards, dtype=torch.float64).to(reward_dtype).sum(-1).item())
            lengths.append(len(rewards))
            if "is_success" in info:
                successes.append(float(info["is_success"]))
    return _result(returns, lengths, successes)


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
        """Yield ``(position, result, weights)`` of the evaluations that are back, oldest first.

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
            at, weights = self._in_flight
            self._in_flight = None
            self.pending.popleft()
            yield at, result, weights

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
    """Evaluations in a child process of their own, behind ``AsyncEvaluator``'s queue: the process
    makes the eval env and a CPU copy of the policy once, then for each request loads the weights,
    seeds the env with that evaluation's own seed (``config.eval_seed(seed, step)``, as the learner's
    and the Ray actor's evaluations are) and plays ``num_episodes`` full episodes with ``evaluate``.
    The same weights at the same step give the same episodes wherever they are played, so a run
    resumed from a checkpoint evaluates as the uninterrupted one did.

    Why not TorchRL's ``Evaluator(backend="process")``: in 0.14 it takes no
    seed per request (each evaluation plays on from where the last one left the env, so a resumed
    run's evaluations differ from the uninterrupted run's), returns the mean return only (not the
    episodes' returns), loses a request queued while another finishes, starts its worker only at the
    first request, from a thread, and its shutdown leaves that thread running (aborting the
    interpreter at exit).

    The process starts with the stop signals blocked and ignores them (the learner stops it);
    ``check`` finds it dead, ``close`` kills it (an evaluation has nothing to save).
    """

    def __init__(self, env_fn: Callable[[], EnvBase], policy: nn.Module, num_episodes: int,
                 pending: deque[tuple[dict, TensorDictBase]], timeout: float = 600.0, *, seed: int = 0,
                 start_timeout: float = MIN_START_TIMEOUT_S, direct: bool = True):
        super().__init__(pending, timeout)
        self.num_episodes, self.seed = int(num_episodes), int(seed)
        ctx = torch.multiprocessing.get_context(torch.multiprocessing.get_start_method(allow_none=True) or "spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_evaluator_process, name="rlpipe-evaluator", daemon=True,
                                 args=(child, env_fn, _PolicyCopy(policy), self.seed + EVAL_SEED_OFFSET, direct))
        with stop_signals_blocked():
            self._proc.start()
        child.close()
        try:
            self._reply(start_timeout, "to start")  # its env made: a start that fails is a failure now
        except BaseException:
            self.close()
            raise

    @property
    def worker_pid(self) -> int | None:
        return self._proc.pid

    def _send(self, at: dict, weights: TensorDictBase) -> None:
        # As bytes (torch.save), not a pickled TensorDict: torch's pickler would hand the tensors over as
        # shared-memory file descriptors, served by a thread in this process that prints a traceback when
        # the evaluator is killed while fetching them (a restart, the run's end). Once per evaluation.
        request = io.BytesIO()
        torch.save({"weights": weights.to_dict(), "episodes": self.num_episodes,
                    "seed": eval_seed(self.seed, at["step"])}, request)
        try:
            self._conn.send_bytes(request.getvalue())
        except (BrokenPipeError, ConnectionError, OSError):
            pass  # the process is gone: check() and _take() say so

    def _take(self, timeout: float) -> dict | None:
        if not self._conn.poll(timeout):
            return None
        return self._reply(0, "")

    def _reply(self, timeout: float, what: str) -> dict:
        """The worker's next message (waiting up to ``timeout`` seconds for it): a result, or a failure."""
        try:
            if not self._conn.poll(timeout):
                raise WorkerFailure(self.role, f"the {self.role} did not start within {timeout:g} s")
            kind, payload = self._conn.recv()
        except (EOFError, ConnectionError, OSError):
            self._proc.join(timeout=5)
            raise dead_worker(self.role, [self._proc]) or WorkerFailure(
                self.role, f"the {self.role} closed its pipe {what}".rstrip()) from None
        if kind == "error":
            raise WorkerFailure(self.role, f"the {self.role} stopped on {payload}")
        return payload

    def check(self) -> None:
        """Raise ``WorkerFailure`` if the evaluator cannot answer: its process is gone, or the evaluation
        in flight is past ``timeout``."""
        failure = dead_worker(self.role, [self._proc]) or self._overdue()
        if failure is not None:
            raise failure

    def close(self, timeout: float = 30.0) -> None:
        """Kill the worker and reap it within ``timeout`` seconds; an evaluation in flight is dropped
        (the run's ``pending`` still lists it, so a checkpoint keeps it)."""
        self._in_flight = None
        kill_processes([self._proc], timeout=timeout)
        self._conn.close()


class EvalActor:
    """The eval env and a CPU copy of the policy, evaluating the weights sent to it, each evaluation on its
    own seed: what ``BackgroundEvaluator``'s process and ``ray_eval.RayEvaluator``'s Ray actor run."""

    def __init__(self, env_fn: Callable[[], EnvBase], policy_factory: Callable[[], nn.Module], seed: int,
                 direct: bool = True):
        # Deaf to the stop signals, as the learner's other workers are (runtime.stop_signals_blocked):
        # a Ctrl-C to the terminal's process group reaches the learner, which stops this worker itself.
        for signum in STOP_SIGNALS:
            with contextlib.suppress(ValueError, OSError):
                signal.signal(signum, signal.SIG_IGN)
        self.env = env_fn()
        self.env.set_seed(seed)
        self.policy = policy_factory()
        self.direct = direct  # ``evaluate``'s

    def pid(self) -> int:
        return os.getpid()

    def evaluate(self, weights: TensorDictBase, num_episodes: int, seed: int | None = None) -> dict:
        """``seed``: the evaluation's own (``config.eval_seed``), so it plays what the learner's would."""
        weights.to_module(self.policy)
        if seed is not None:
            self.env.set_seed(seed)
        return evaluate(self.env, self.policy, num_episodes, direct=self.direct)


def _evaluator_process(conn, env_fn: Callable[[], EnvBase], policy_factory: Callable[[], nn.Module],
                       seed: int, direct: bool) -> None:
    """``BackgroundEvaluator``'s process: an ``EvalActor``; "ready" once it is made, then one result (or
    "error" and the exception's first line, after which it ends) per request, until the pipe closes."""
    torch.set_num_threads(1)  # beside the learner's threads: episodes of one env, one step at a time
    try:
        worker = EvalActor(env_fn, policy_factory, seed, direct)
    except Exception as exc:
        conn.send(("error", f"{type(exc).__name__}: {first_line(exc)}"))
        return
    conn.send(("ready", None))
    while True:
        try:
            request = torch.load(io.BytesIO(conn.recv_bytes()), weights_only=True)
        except (EOFError, OSError):
            return
        try:
            result = worker.evaluate(TensorDict(request["weights"]), request["episodes"], request["seed"])
        except Exception as exc:
            conn.send(("error", f"{type(exc).__name__}: {first_line(exc)}"))
            return
        conn.send(("result", result))


class _PolicyCopy:
    """A picklable policy factory for an evaluator process: a CPU copy of the policy's structure."""

    def __init__(self, policy: nn.Module):
        self.policy = copy.deepcopy(policy).cpu()

    def __call__(self, env=None) -> nn.Module:
        return copy.deepcopy(self.policy)
