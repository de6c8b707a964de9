"""The shared off-policy collect/learn loop with triggers (TF-Agents' Learner, on TorchRL parts).

A pipeline (``dqn``, ``td3``, ``sac``) subclasses ``OffPolicyPipeline`` and supplies only what is
its own: ``check_env`` (what action space it takes), ``build`` (policy, exploring policy, loss,
target updater, optimisers), ``update`` (one gradient step) and ``export_module`` (the policy as a
plain ``nn.Module``). Everything else is here, once:

* a TorchRL collector (``Collector``, ``MultiSyncCollector`` or ``MultiAsyncCollector``) whose first
  ``initial_collect_steps`` frames come from a random policy;
* a TorchRL replay buffer (``LazyTensorStorage``: FIFO eviction at capacity, uniform sampling);
* collection in blocks of ``collector.frames_per_batch`` env steps, each followed by the updates
  those steps pay for at ``1 / collect_steps_per_iteration`` updates per env step: the tutorials'
  update-to-data ratio, with far less per-step overhead than one step / one update;
* triggers at iteration counts: evaluate, log, checkpoint, export; a progress bar;
* a run directory (see ``rundir``) and resume from its last checkpoint.

Ctrl-C stops at the next safe point: between two updates, between two env steps of an evaluation,
or between two triggers. The checkpoint it saves then records what that iteration still owes (the
updates its frames paid for, the triggers not yet run, the background evaluations not yet back,
with the weights each was asked for), and ``--resume`` does exactly those first. Collector and
evaluator processes never see the Ctrl-C (they are started with SIGINT blocked): the learner stops
them, so none is killed in the middle of a message. A second Ctrl-C stops at once, without saving.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import math
import random
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.collectors import Collector, Evaluator, MultiAsyncCollector, MultiSyncCollector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.record.loggers import TensorboardLogger
from tqdm.auto import tqdm

from rlpipe.envs import EnvError, make_env
from rlpipe.pipelines import checkpoint as ckpt
from rlpipe.pipelines.config import TrainConfig, config_to_dict, validate
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.evaluation import evaluate
from rlpipe.pipelines.export import export_policy
from rlpipe.pipelines.rate_limiter import SampleToInsertRatio
from rlpipe.pipelines.rundir import MetricsCSV, RunDir, default_run_dir, write_json_atomic

__all__ = ["OffPolicyPipeline", "TrainResult", "seed_everything"]


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


@dataclass
class TrainResult:
    """What ``train`` hands back: the trained policy, the metrics rows and where the run lives."""

    policy: nn.Module
    run_dir: Path
    metrics: list[dict[str, str]]
    summary: dict[str, Any]
    evaluations: list[dict[str, Any]] = field(default_factory=list)


class OffPolicyPipeline:
    """Base of every pipeline. Subclasses set ``algo``, ``Config``, ``loss_names`` and the hooks."""

    algo: ClassVar[str]
    Config: ClassVar[type[TrainConfig]]
    loss_names: ClassVar[tuple[str, ...]] = ("loss",)

    # set by ``build``
    policy: nn.Module  # deterministic policy (evaluation, export)
    collect_policy: nn.Module  # exploring policy (collection)
    loss_module: nn.Module
    optimizers: dict[str, torch.optim.Optimizer]

    def __init__(
        self,
        config: TrainConfig | None = None,
        *,
        env: EnvBase | Callable[[], EnvBase] | None = None,
        eval_env: EnvBase | None = None,
    ):
        cfg = config if config is not None else self.Config()
        if not isinstance(cfg, self.Config):
            raise InputError(f"config is a {type(cfg).__name__}; expected {self.Config.__name__} for {self.algo}")
        validate(cfg)
        self.config = cfg
        self.device = torch.device(cfg.device)
        if cfg.num_threads:
            torch.set_num_threads(cfg.num_threads)
        seed_everything(cfg.seed)

        # An env factory lets collector processes and the evaluator make their own copies.
        if env is None:
            self.env_fn: Callable[[], EnvBase] | None = functools.partial(make_env, cfg.env, device="cpu")
        elif isinstance(env, EnvBase):
            self.env_fn = None
        elif callable(env):
            self.env_fn = env
        else:
            raise InputError(f"env is a {type(env).__name__}; expected a TorchRL EnvBase or a function returning one")
        try:
            self.env = env if isinstance(env, EnvBase) else self.env_fn()
        except EnvError as exc:
            raise InputError(str(exc)) from exc
        self.env.set_seed(cfg.seed)
        if eval_env is None and self.env_fn is None:
            raise InputError("env is an instance: pass eval_env as well, or pass a function that makes the env")
        self.eval_env = eval_env if eval_env is not None else self.env_fn()
        self.eval_env.set_seed(cfg.seed + 10_000)
        if self.env_fn is None and (cfg.collector.workers > 1 or not cfg.collector.sync):
            raise InputError("collector.workers>1 or collector.sync=false: pass env as a function that makes the env")

        self.check_env(self.env)
        self.observation_dim = int(self.env.observation_spec["observation"].shape[-1])
        self.build()
        self.replay_buffer = self.make_replay_buffer()
        # What the loop stores of each transition (None: everything the collector returns). The
        # loss's in_keys are 6 of the collector's 16: sampling them costs about a third less.
        self.replay_keys: list | None = None if cfg.replay_all_keys else list(self.loss_module.in_keys)
        # "triggers": what the current iteration still owes (log, eval, export, save), in order.
        self.counters: dict[str, Any] = {"frames": 0, "updates": 0, "iteration": 0, "triggers": []}
        # Background evaluations asked for and not back yet: (position, policy weights), oldest first.
        self.background_evals: deque[tuple[dict, TensorDictBase]] = deque()
        self.limiter = SampleToInsertRatio(1.0 / cfg.collect_steps_per_iteration, cfg.first_update_frame)
        self._update_fn = torch.compile(self.update) if cfg.compile else self.update

    # --- what a pipeline supplies -------------------------------------------------------------

    def check_env(self, env: EnvBase) -> None:
        """Raise ``InputError`` if this pipeline cannot act in ``env``."""

    def build(self) -> None:
        """Make ``policy``, ``collect_policy``, ``loss_module``, ``optimizers`` (and a target updater)."""
        raise NotImplementedError

    def update(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """One gradient step on ``batch``; returns detached losses named as in ``loss_names``."""
        raise NotImplementedError

    def after_update(self, updates: int) -> None:
        """Called after each update with the update count (target network updates go here)."""

    def on_frames(self, frames: int) -> None:
        """Called after each collected block with its frame count (exploration schedules go here)."""

    def export_module(self) -> nn.Module:
        """The deterministic policy as a plain module: observations [B, D] -> actions."""
        raise NotImplementedError

    def export_info(self) -> dict[str, Any]:
        spec = self.env.action_spec
        if hasattr(spec.space, "n"):
            return {"algo": self.algo, "env": self.config.env, "action": "discrete", "num_actions": int(spec.space.n)}
        return {"algo": self.algo, "env": self.config.env, "action": "continuous",
                "low": spec.space.low.flatten().tolist(), "high": spec.space.high.flatten().tolist()}

    # --- the parts, as plain TorchRL objects -------------------------------------------------------

    def make_replay_buffer(self) -> ReplayBuffer:
        cfg = self.config
        return ReplayBuffer(
            storage=LazyTensorStorage(cfg.replay_buffer_capacity, device=self.device),
            batch_size=cfg.batch_size,
        )

    def make_collector(self, total_frames: int, init_random_frames: int):
        c = self.config.collector
        common = dict(
            frames_per_batch=c.frames_per_batch,
            total_frames=total_frames,
            init_random_frames=init_random_frames,
        )
        if c.workers == 1 and c.sync:
            return Collector(self.env, self.collect_policy, **common)
        if not c.sync and init_random_frames > 0:
            # MultiAsyncCollector decides random-or-policy for a worker's next block when it hands
            # over that worker's last one, so the other workers' blocks in flight are random too:
            # ask for that many fewer, and exactly `init_random_frames` come out random (to a block).
            # (Each async worker's block is a whole `frames_per_batch`.)
            common["init_random_frames"] = max(1, init_random_frames - (c.workers - 1) * c.frames_per_batch)
        cls = MultiSyncCollector if c.sync else MultiAsyncCollector
        return cls([self.env_fn] * c.workers, self.collect_policy, **common)

    def make_evaluator(self):
        """TorchRL's ``Evaluator`` in a child process, fed snapshots of ``policy``'s weights."""
        if self.env_fn is None:
            raise InputError("eval_in_background=true: pass env as a function that makes the env")
        return Evaluator(
            self.env_fn,
            policy_factory=_PolicyCopy(self.policy),
            num_trajectories=self.config.num_eval_episodes,
            max_steps=None,  # our envs end episodes themselves (time limits); StepCounter is set
            backend="process",
            busy_policy="queue",
            collector_kwargs={"traj_format": "padded"},  # what 0.14 does by default, without its FutureWarning
        )

    # --- checkpoint state -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "algo": self.algo,
            "env": self.config.env,
            "loss": self.loss_module.state_dict(),
            "collect_policy": self.collect_policy.state_dict(),
            "optimizers": {k: opt.state_dict() for k, opt in self.optimizers.items()},
            "counters": dict(self.counters),
            "limiter": self.limiter.state_dict(),
            "background_evals": [{"at": dict(at), "weights": dict(w.flatten_keys("/").items())}
                                 for at, w in self.background_evals],
            "replay_buffer": ckpt.replay_buffer_state(self.replay_buffer),
            "rng": ckpt.rng_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from ``state_dict`` output; ``InputError`` if it does not fit this pipeline."""
        try:
            self.loss_module.load_state_dict(state["loss"])
            self.collect_policy.load_state_dict(state["collect_policy"])
            for k, opt in self.optimizers.items():
                opt.load_state_dict(state["optimizers"][k])
            self.counters = {**state["counters"], "triggers": list(state["counters"].get("triggers", []))}
            self.background_evals = deque((dict(e["at"]), TensorDict(e["weights"]).unflatten_keys("/"))
                                          for e in state.get("background_evals", []))
            self.limiter.load_state_dict(state["limiter"])
            self.replay_buffer.empty()
            ckpt.load_replay_buffer(self.replay_buffer, state["replay_buffer"], keys=self.replay_keys)
            ckpt.set_rng_state(state["rng"])
        except (KeyError, ValueError, RuntimeError, TypeError, IndexError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise InputError(f"checkpoint does not fit this {self.algo} pipeline and config: {first[:200]}") from exc

    # --- the loop ---------------------------------------------------------------------------------

    def train(self, out: str | Path | None = None, *, resume: bool = False, progress: bool = True) -> TrainResult:
        """Run (or, with ``resume=True``, continue) training; write everything into the run directory.

        Ctrl-C (SIGINT) saves a checkpoint at the next safe point and raises ``KeyboardInterrupt``;
        ``train(out, resume=True)`` then continues exactly from there.
        """
        cfg = self.config
        evaluations: list[dict] = []
        if resume:
            if out is None:
                raise InputError("resume needs the run directory to continue")
            run = RunDir.open(out)
            path = ckpt.latest_checkpoint(run.checkpoints)
            try:
                self.load_state_dict(ckpt.load_checkpoint(path, self.algo, cfg.env))
            except InputError as exc:
                changed = _changed_keys(run.read_config()[1], config_to_dict(cfg))
                hint = f" (keys changed since it was saved: {', '.join(changed)})" if changed else ""
                raise InputError(f"{path / 'state.pt'}: {exc}{hint}") from exc
            metrics = MetricsCSV(run.metrics_path, list(self.loss_names), resume_after_step=self.counters["iteration"])
            run.write_config(self.algo, config_to_dict(cfg))  # keys changed on resume are recorded
            evaluations = [_eval_from_row(r) for r in metrics.rows() if r.get("average_return") not in ("", None)]
            self._drop_done_work(metrics.rows())
        else:
            run = RunDir.create(out or default_run_dir(self.algo, cfg.env), self.algo, config_to_dict(cfg))
            metrics = MetricsCSV(run.metrics_path, list(self.loss_names))
            self.counters["triggers"] = ["eval"]  # the tutorials evaluate once before training
        self.run_dir = run
        logger = TensorboardLogger(exp_name="tb", log_dir=str(run.path))
        c = self.counters
        clock = _Clock()
        interval_stats = _IntervalStats()
        eval_return = evaluations[-1]["average_return"] if evaluations else math.nan
        bar = tqdm(total=cfg.num_iterations, initial=c["iteration"], unit="it", disable=not progress,
                   desc=f"{self.algo} {cfg.env}", dynamic_ncols=True)
        stop = _DeferredInterrupt()
        evaluator = None
        collector = None
        background = self.background_evals  # (position, weights) asked for and not back yet, oldest first
        in_flight: list = []  # the one of them the evaluator has (TorchRL's is fed one at a time)

        def position() -> dict:
            return {"step": c["iteration"], "frames": c["frames"], "updates": c["updates"]}

        def log_row(step_row: dict, at: dict | None = None) -> None:
            at = at or position()
            row = {**at, **step_row}
            metrics.append(row)
            for key, value in row.items():
                if key != "step" and isinstance(value, (int, float)) and not math.isnan(value):
                    logger.log_scalar(key, value, step=at["step"])

        def record_eval(result: dict, at: dict) -> None:
            nonlocal eval_return
            eval_return = result["average_return"]
            evaluations.append({**at, **result})
            log_row({"average_return": result["average_return"],
                     "average_episode_length": result["average_episode_length"],
                     "wall_time": clock.wall()}, at)
            with clock.paused():
                self._plot_returns(run, metrics)
            bar.set_postfix(avg_return=f"{eval_return:.1f}", refresh=False)

        def run_eval(weights: TensorDictBase | None = None, at: dict | None = None) -> None:
            """Evaluate the policy now (or ``weights``, taken at ``at``), in this process."""
            policy = self.policy
            if weights is not None:
                policy = copy.deepcopy(self.policy)
                weights.to_module(policy)
            with clock.paused():
                result = evaluate(self.eval_env, policy, cfg.num_eval_episodes, interrupt=stop.check)
            record_eval(result, at or position())

        def feed_evaluator() -> None:
            # TorchRL 0.14's Evaluator loses a request when a second one is queued while the first
            # finishes (its backend's poll clears the pending flag of the next request), and the run
            # then waits forever for that result: hand it one request at a time.
            if background and not in_flight:
                at, weights = background[0]
                with _sigint_blocked():  # the evaluator starts its worker (thread and process) lazily
                    evaluator.trigger_eval(weights, step=at["step"])
                in_flight.append(background[0])

        def collect_background_evals(block: bool = False, feed: bool = True) -> None:
            while background:
                if feed:
                    feed_evaluator()
                elif not in_flight:
                    return
                result = evaluator.poll(timeout=0.2 if block else 0)
                if result is None:
                    if not block:
                        return
                    stop.check()
                    continue
                at, _ = in_flight.pop()
                background.popleft()
                assert int(result["eval/step"]) == at["step"], (result["eval/step"], at)
                record_eval({"average_return": float(result["eval/reward"]),
                             "average_episode_length": float(result["eval/episode_length"]),
                             "returns": None}, at)

        def save() -> None:
            with clock.paused():
                ckpt.save_checkpoint(run.checkpoints, c["iteration"], self.state_dict())

        def export() -> None:
            with clock.paused():
                export_policy(self.export_module(), self.observation_dim, run.policy_dir, self.export_info())

        def run_triggers() -> None:
            """Run what the current iteration owes, in order; each is crossed off once done."""
            owed = c["triggers"]
            while owed:
                stop.check()
                name = owed[0]
                if name == "save":
                    owed.pop(0)  # the checkpoint it writes owes nothing more
                    save()
                    continue
                if name == "log":
                    log_row(interval_stats.flush(clock))
                elif name == "eval":
                    if evaluator is not None and c["iteration"] > 0:
                        background.append((position(), Evaluator.extract_weights(self.policy)))
                        collect_background_evals()
                    else:
                        run_eval()
                elif name == "export":
                    export()
                owed.pop(0)

        def pay_updates() -> None:
            n_updates = 0
            while self.limiter.owed:
                stop.check()
                losses = self._update_fn(self.replay_buffer.sample())
                c["updates"] += 1
                n_updates += 1
                self.limiter.made(1)
                self.after_update(c["updates"])
                interval_stats.add_losses(losses)
            if collector is not None and n_updates and c["updates"] % cfg.collector.weight_sync_interval < n_updates:
                self._sync_weights(collector)

        # The deferred Ctrl-C handler stays on through the checkpoint saved on an interrupt: a SIGINT
        # delivered twice (the terminal's and a parent's) must not cut that save short.
        with stop, _gc_frozen():
            try:
                if not resume:
                    save()  # iteration 0: a run stopped at any point from here on can be resumed
                if cfg.eval_in_background:
                    evaluator = self.make_evaluator()
                elif background:  # asked for in the background before a resume that turned it off
                    while background:
                        at, weights = background[0]
                        run_eval(weights, at)
                        background.popleft()
                clock.start()
                pay_updates()  # owed by a run stopped in the middle of a block ...
                run_triggers()  # ... and what its iteration still had to do
                frames_left = cfg.total_frames - c["frames"]
                if frames_left > 0:
                    with _sigint_blocked(), clock.paused():  # worker start-up is not training time
                        collector = self.make_collector(frames_left, max(0, cfg.initial_collect_steps - c["frames"]))
                    collector.set_seed(cfg.seed + c["frames"])
                for batch in collector or ():
                    batch = batch.reshape(-1)
                    # Collectors round their budget up to whole blocks; the run stops at its own.
                    batch = batch[: cfg.total_frames - c["frames"]]
                    self.replay_buffer.extend(batch if self.replay_keys is None else batch.select(*self.replay_keys))
                    c["frames"] += batch.numel()
                    interval_stats.add_frames(batch)
                    self.on_frames(batch.numel())
                    self.limiter.insert(batch.numel())
                    previous = c["iteration"]
                    now = c["iteration"] = max(0, c["frames"] - cfg.initial_collect_steps) // cfg.collect_steps_per_iteration
                    c["triggers"] = self._triggers_between(previous, now)
                    bar.update(now - previous)
                    pay_updates()
                    run_triggers()
                    if background:
                        collect_background_evals()
                    if c["frames"] >= cfg.total_frames:
                        break
                if collector is not None:
                    collector.shutdown()
                    collector = None
                if background:
                    with clock.paused():
                        collect_background_evals(block=True)
                if not evaluations or evaluations[-1]["step"] != c["iteration"]:
                    run_eval()
            except _Stopped:
                if in_flight:
                    collect_background_evals(feed=False)  # one already back is kept; the others are saved
                save()  # with what this iteration still owes: --resume does that first
                raise KeyboardInterrupt from None
            finally:
                if collector is not None:
                    collector.shutdown()
                if evaluator is not None:
                    evaluator.shutdown()
                bar.close()
            export()
            save()
            summary = self._summary(run, evaluations, clock)
            write_json_atomic(run.summary_path, summary)
        return TrainResult(policy=self.policy, run_dir=run.path, metrics=metrics.rows(), summary=summary,
                           evaluations=evaluations)

    def _triggers_between(self, previous: int, now: int) -> list[str]:
        """The triggers whose interval has a multiple in (previous, now], in the order they run."""
        cfg = self.config
        owed = []
        if _crossed(previous, now, cfg.log_interval):
            owed.append("log")
        if cfg.eval_interval and _crossed(previous, now, cfg.eval_interval) and now < cfg.num_iterations:
            owed.append("eval")  # the last iteration's evaluation runs after the loop, in the foreground
        if _crossed(previous, now, cfg.policy_save_interval):
            owed.append("export")
        if _crossed(previous, now, cfg.checkpoint_interval) and now < cfg.num_iterations:
            owed.append("save")
        return owed

    def _drop_done_work(self, rows: list[dict[str, str]]) -> None:
        """On resume, forget owed work whose rows were written after the checkpoint was saved."""
        step = self.counters["iteration"]
        logged = {int(r["step"]) for r in rows if r.get("steps_per_s") not in ("", None)}
        evaluated = {int(r["step"]) for r in rows if r.get("average_return") not in ("", None)}
        owed = self.counters["triggers"]
        if "log" in owed and step in logged:
            owed.remove("log")
        if "eval" in owed and step in evaluated:
            owed.remove("eval")
        self.background_evals = deque((at, w) for at, w in self.background_evals if at["step"] not in evaluated)

    # --- helpers ----------------------------------------------------------------------------------

    def _sync_weights(self, collector) -> None:
        # In-process collection shares the policy's parameters; processes get a push.
        if not isinstance(collector, Collector):
            collector.update_policy_weights_()

    def _plot_returns(self, run: RunDir, metrics: MetricsCSV) -> None:
        from rlpipe.pipelines.analysis import plot_training_returns

        rows = [r for r in metrics.rows() if r.get("average_return") not in ("", None)]
        plot_training_returns(rows, run.returns_png, title=f"{self.algo} on {self.config.env}")

    def _summary(self, run: RunDir, evaluations: list[dict], clock: "_Clock") -> dict[str, Any]:
        c = self.counters
        last = evaluations[-1] if evaluations else {}
        train_s = clock.train_seconds()
        return {
            "algo": self.algo,
            "env": self.config.env,
            "seed": self.config.seed,
            "iterations": c["iteration"],
            "frames": c["frames"],
            "updates": c["updates"],
            "final_average_return": last.get("average_return"),
            "final_average_episode_length": last.get("average_episode_length"),
            "wall_time_s": clock.wall(),
            "train_time_s": train_s,
            "env_steps_per_s": c["frames"] / train_s if train_s > 0 else None,
            "updates_per_s": c["updates"] / train_s if train_s > 0 else None,
        }


class _Stopped(Exception):
    """Ctrl-C reached a safe point (an ``Exception``, so cleanup code in libraries runs as usual)."""


class _DeferredInterrupt:
    """While active (main thread only), Ctrl-C sets a flag that ``check`` turns into ``_Stopped``.

    A ``KeyboardInterrupt`` raised wherever the learner happens to be can land inside an optimiser
    step or inside a library's context manager (tensordict's ``to_module`` turns it into an
    unrelated ``RuntimeError``), and the state it leaves is not one to checkpoint. The loop calls
    ``check`` where its state is whole. A second Ctrl-C raises ``KeyboardInterrupt`` at once.
    """

    def __init__(self):
        self.requested = False
        self._first = 0.0
        self._installed = False
        self._previous = None

    def __enter__(self) -> "_DeferredInterrupt":
        # A process started with SIGINT ignored (nohup, a background job) is meant to be immune to
        # Ctrl-C, as Python itself leaves it then: keep it so.
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN):
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def __exit__(self, *exc) -> None:
        if self._installed:
            # None: the handler was not set from Python; the default one is the closest to it
            signal.signal(signal.SIGINT, signal.default_int_handler if self._previous is None else self._previous)
            self._installed = False

    # A second SIGINT this soon after the first is the same Ctrl-C delivered twice (the terminal's to
    # the process group, and a parent's such as `rlpipe ablate` forwarding it), not a second press.
    SAME_PRESS_S = 2.0

    def _handle(self, signum, frame) -> None:
        if self.requested:
            if time.monotonic() - self._first < self.SAME_PRESS_S:
                return
            raise KeyboardInterrupt
        self.requested = True
        self._first = time.monotonic()
        print("\nrlpipe: stopping at the next safe point to save a checkpoint (Ctrl-C again: stop now, unsaved)",
              file=sys.stderr, flush=True)

    def check(self) -> None:
        if self.requested:
            raise _Stopped


@contextlib.contextmanager
def _gc_frozen():
    """Keep Python's cyclic garbage collector off the objects that exist before training.

    Each update makes many short-lived objects, so the collector runs often, and its full
    collections scan every object of torch, TorchRL and the env (~0.1 s each here; ~0.03 s with
    them frozen). Frozen objects are left out of those scans; they are handed back at the end, so
    garbage among them is collected as usual afterwards.
    """
    import gc

    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


@contextlib.contextmanager
def _sigint_blocked():
    """Start processes (and threads) with SIGINT blocked, so a Ctrl-C reaches the learner alone.

    The block is inherited by threads started here and by the processes they spawn (the signal
    mask survives fork and exec); the learner's own SIGINT, if one comes meanwhile, waits until
    the block is lifted. The learner then shuts the workers down itself.
    """
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class _PolicyCopy:
    """A picklable policy factory for an evaluator process: a CPU copy of the policy's structure."""

    def __init__(self, policy: nn.Module):
        self.policy = copy.deepcopy(policy).cpu()

    def __call__(self, env=None) -> nn.Module:
        return copy.deepcopy(self.policy)


def _changed_keys(saved: dict, current: dict, prefix: str = "") -> list[str]:
    changed = []
    for key, value in current.items():
        if isinstance(value, dict) and isinstance(saved.get(key), dict):
            changed += _changed_keys(saved[key], value, prefix + key + ".")
        elif saved.get(key) != value:
            changed.append(prefix + key)
    return changed


def _eval_from_row(row: dict[str, str]) -> dict[str, Any]:
    return {"step": int(row["step"]), "frames": int(row["frames"]), "updates": int(row["updates"]),
            "average_return": float(row["average_return"]),
            "average_episode_length": float(row["average_episode_length"]), "returns": None}


def _crossed(previous: int, now: int, interval: int) -> bool:
    """Whether a multiple of ``interval`` lies in (previous, now]."""
    return interval > 0 and now // interval > previous // interval


class _Clock:
    """Wall time, and training time with evaluations and saving taken out (for steps per second)."""

    def __init__(self):
        self._t0 = time.perf_counter()
        self._paused = 0.0
        self._train_start: float | None = None

    def start(self) -> None:
        self._train_start = time.perf_counter()
        self._paused = 0.0

    def wall(self) -> float:
        return time.perf_counter() - self._t0

    def train_seconds(self) -> float:
        if self._train_start is None:
            return 0.0
        return time.perf_counter() - self._train_start - self._paused

    class _Pause:
        def __init__(self, clock):
            self.clock = clock

        def __enter__(self):
            self.t = time.perf_counter()

        def __exit__(self, *exc):
            if self.clock._train_start is not None:
                self.clock._paused += time.perf_counter() - self.t

    def paused(self) -> "_Clock._Pause":
        return _Clock._Pause(self)


class _IntervalStats:
    """Means of losses, finished training episodes' returns, and speeds since the last log row."""

    def __init__(self):
        self._reset(0.0, 0, 0)

    def _reset(self, t: float, frames: int, updates: int) -> None:
        self.loss_sums: dict[str, torch.Tensor] = {}
        self.loss_counts: dict[str, int] = {}
        self.episode_returns: list[float] = []
        self.frames = 0
        self.updates = 0
        self.t = t

    def add_frames(self, batch: TensorDictBase) -> None:
        self.frames += batch.numel()
        done = batch["next", "done"]
        if done.any():
            self.episode_returns += batch["next", "episode_reward"][done].tolist()

    def add_losses(self, losses: dict[str, torch.Tensor]) -> None:
        self.updates += 1
        for k, v in losses.items():  # some losses are not made every update (TD3's delayed actor)
            self.loss_sums[k] = self.loss_sums.get(k, 0.0) + v
            self.loss_counts[k] = self.loss_counts.get(k, 0) + 1

    def flush(self, clock: _Clock) -> dict[str, Any]:
        now = clock.train_seconds()
        dt = max(now - self.t, 1e-9)
        row: dict[str, Any] = {f"loss_{k}": float(v) / self.loss_counts[k] for k, v in self.loss_sums.items()}
        if self.episode_returns:
            row["train_episode_return"] = sum(self.episode_returns) / len(self.episode_returns)
        row["steps_per_s"] = self.frames / dt
        row["updates_per_s"] = self.updates / dt
        row["wall_time"] = clock.wall()
        self._reset(now, 0, 0)
        return row
