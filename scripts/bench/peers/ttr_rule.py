"""The stopping rule of ``rlpipe bench time-to-return``, for the peers' runners (``ttr_sb3.py``, ``ttr_cleanrl.py``).

The runners run inside the peers' own venvs, where rlpipe is not installed: this file is imported from
beside them (a script's folder is on ``sys.path``), and holds nothing but the standard library. It is
rlpipe's ``target_return`` rule (``pipelines/training/triggers.py`` ``TargetTrigger``) written again:
the mean return of the last ``window`` finished training episodes reaches ``target``, then a greedy
evaluation of ``eval_episodes`` episodes on an env of its own confirms it; one that does not is tried
again after ``recheck`` more finished episodes. Evaluation time is recorded to be left out.

The result is one line on stdout, ``TTR {json}``, with the fields of rlpipe's summary.json ``"target"``.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable

PREFIX = "TTR "


class Rule:
    def __init__(self, target: float, window: int = 5, eval_episodes: int = 10, recheck: int = 5):
        self.target, self.window, self.eval_episodes, self.recheck = float(target), int(window), int(eval_episodes), int(recheck)
        self.returns: list[float] = []
        self.next_check = self.window
        self.eval_seconds = 0.0
        self.confirm_seconds = 0.0
        self.confirmations = 0
        self.reached: dict | None = None
        self.train_mean: float | None = None
        self.eval_return: float | None = None
        self.eval_length: float | None = None
        self.first_step_unix: float | None = None
        self.last_step_unix: float | None = None

    @classmethod
    def from_spec(cls, spec: dict) -> Rule:
        """The rule a runner's JSON spec names (``time_to_return.peer_launch`` writes it)."""
        return cls(spec["target"], spec.get("window", 5), spec.get("eval_episodes", 10), spec.get("recheck", 5))

    def step(self) -> None:
        """Call after each env step (or batch of them)."""
        now = time.time()
        if self.first_step_unix is None:
            self.first_step_unix = now
        self.last_step_unix = now

    def episode(self, ret: float) -> None:
        """A finished training episode's undiscounted return (the peer's Monitor / RecordEpisodeStatistics)."""
        self.returns.append(float(ret))

    def check(self, evaluate: Callable[[int], list[float] | tuple[list[float], list[int]]], env_steps: int,
              updates: int) -> bool:
        """After a step's episodes: True once the target is reached and confirmed (the run should stop).

        ``evaluate(n)`` plays ``n`` greedy episodes and gives ``(returns, lengths)`` (a short episode that
        passes the target is a lunge, not a walk: the result says which), or only the returns where the
        peer's own evaluation gives no lengths (TF-Agents' tutorial's ``compute_avg_return``: its mean)."""
        if self.reached is not None:
            return True
        if len(self.returns) < self.window or len(self.returns) < self.next_check:
            return False
        mean = sum(self.returns[-self.window:]) / self.window
        self.train_mean = mean
        if mean < self.target:
            return False
        met = time.time()
        returns = evaluate(self.eval_episodes)
        seconds = time.time() - met
        returns, lengths = returns if isinstance(returns, tuple) else (returns, None)
        self.confirmations += 1
        self.eval_return = sum(returns) / len(returns)
        self.eval_length = sum(lengths) / len(lengths) if lengths else None
        if self.eval_return < self.target:
            self.eval_seconds += seconds
            self.next_check = len(self.returns) + self.recheck
            return False
        self.confirm_seconds = seconds
        self.reached = {"env_steps": int(env_steps), "updates": int(updates), "train_mean": mean,
                        "eval_return": self.eval_return, "eval_episode_length": self.eval_length, "time_unix": met}
        return True

    def result(self, env_steps: int, updates: int, **extra) -> dict:
        at = self.reached or {"env_steps": int(env_steps), "updates": int(updates), "train_mean": self.train_mean,
                              "eval_return": self.eval_return, "eval_episode_length": self.eval_length,
                              "time_unix": None}
        return {"return": self.target, "reached": self.reached is not None, **at, "window": self.window,
                "eval_episodes": self.eval_episodes, "confirmations": self.confirmations,
                "eval_seconds": self.eval_seconds, "confirm_seconds": self.confirm_seconds,
                "first_step_unix": self.first_step_unix, "last_block_unix": self.last_step_unix,
                "episodes": len(self.returns), **extra}

    def emit(self, env_steps: int, updates: int, **extra) -> None:
        print(PREFIX + json.dumps(self.result(env_steps, updates, **extra)), flush=True)
        sys.stderr.flush()


def versions(*names: str) -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    found = {"python": sys.version.split()[0]}
    for name in names:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            pass
    return found


def register_minitaur(path: str | None) -> None:
    """Register rlpipe's gymnasium Minitaur (``envs/minitaur.py``, standard packages only) as
    ``MinitaurBulletEnv-v0`` in this venv's gymnasium, loaded from its file."""
    if not path:
        return
    import importlib.util

    import gymnasium

    spec = importlib.util.spec_from_file_location("rlpipe_minitaur", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["rlpipe_minitaur"] = module
    spec.loader.exec_module(module)
    if "MinitaurBulletEnv-v0" not in gymnasium.registry:
        gymnasium.register(id="MinitaurBulletEnv-v0", entry_point="rlpipe_minitaur:MinitaurBulletEnv",
                           max_episode_steps=1000)


ANYTIME_PREFIX = "ANYTIME "
LAUNCH_ENV = "RLPIPE_BENCH_LAUNCH_UNIX"
"""the environment variable in which ``rlpipe bench anytime`` hands a runner the moment just before its launch"""


class Marks:
    """``rlpipe bench anytime``'s rule, for every side's runner: at each of ``marks`` (seconds of the run's own
    time since just before its command was launched, imports counted, the rule's evaluations left out) the policy
    is played greedily for ``eval_episodes`` episodes on an env of its own, seeded by the mark alone
    (``episode_seed``); the run stops after the last mark. The result is one line, ``ANYTIME {json}``."""

    def __init__(self, marks: list[float], eval_episodes: int = 10, launch_unix: float | None = None):
        import os

        self.marks = [float(m) for m in marks]
        self.eval_episodes = int(eval_episodes)
        self.launch = float(launch_unix if launch_unix is not None else os.environ.get(LAUNCH_ENV, time.time()))
        self.excluded = 0.0
        self.points: list[dict] = []

    @classmethod
    def from_spec(cls, spec: dict) -> Marks | None:
        return cls(spec["marks"], spec.get("eval_episodes", 10)) if spec.get("marks") else None

    def elapsed(self) -> float:
        """The run's own seconds so far: since just before the launch, less the rule's evaluations."""
        return time.time() - self.launch - self.excluded

    def due(self) -> bool:
        return len(self.points) < len(self.marks) and self.elapsed() >= self.marks[len(self.points)]

    def done(self) -> bool:
        return len(self.points) >= len(self.marks)

    def episode_seed(self, k: int) -> int:
        """The seed of the mark's ``k``-th evaluation episode: the same for every side and every run seed."""
        return 1_000_000 + 1_000 * len(self.points) + k

    def record(self, evaluate: Callable[[], dict[str, tuple[list[float], list[int]]]], env_steps: int,
               updates: int, **extra) -> None:
        """Evaluate now (``evaluate()``: ``{policy name: (returns, lengths)}``), the time it takes left out;
        ``extra``: more fields of the point (``ended``: the run had ended by itself, why)."""
        trained = self.elapsed()
        began = time.time()
        played = evaluate()
        self.excluded += time.time() - began
        point = {"mark_s": self.marks[len(self.points)], "trained_s": trained, "env_steps": int(env_steps),
                 "updates": int(updates), **extra}
        for name, (returns, lengths) in played.items():
            point[name] = {"return": sum(returns) / len(returns), "returns": list(map(float, returns)),
                           "episode_length": sum(lengths) / len(lengths) if lengths else None}
        self.points.append(point)

    def emit(self, **extra) -> None:
        print(ANYTIME_PREFIX + json.dumps({"points": self.points, "eval_episodes": self.eval_episodes,
                                           "excluded_s": self.excluded, **extra}), flush=True)
        sys.stderr.flush()
