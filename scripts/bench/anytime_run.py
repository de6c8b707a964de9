"""``rlpipe bench anytime``'s rlpipe side: one run, evaluated at marks of wall-clock time (``peers/ttr_rule.Marks``).

    python -m rlpipe.scripts.bench.anytime_run '{"env": "Hopper-v5", "algo": "sac", "seed": 100,
                                                 "overrides": ["time_budget=10m"], "marks": [60, ...], "out": DIR}'

The run is the one ``rlpipe train env=ID KEY=VALUE ...`` makes (the sized default, or ``preset``), trained with one
trigger more, ``MarkTrigger``: after each collected block it checks the clock, and at each mark plays two policies
greedily on an env of its own, the time this takes left out of the run's time: ``last`` (the learner's policy as
it is) and ``exported`` (what ``policy/`` would hold if the run ended there: the best evaluation's weights where
``keep_best`` kept them, else the last). After the last mark the run ends (``stopped_because`` ``anytime``); a run
that ends by itself before it (a plateau, its ceiling) is evaluated at the marks left as it ended. A ``time_budget=``
given sizes the run as it does for ``rlpipe train``, and the marks end it (its own clock would count the rule's
evaluations).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import sys
from pathlib import Path


def main(spec: dict) -> None:
    from rlpipe.scripts.bench.peers.ttr_rule import Marks, versions

    marks = Marks(spec["marks"], spec.get("eval_episodes", 10))
    import torch

    from rlpipe.pipelines import pipeline_class
    from rlpipe.pipelines.training.triggers import Trigger
    from rlpipe.pipelines.workers.evaluation import evaluate
    from rlpipe.scripts.bench.time_to_return import Task, rlpipe_config

    env, algo = spec["env"], spec["algo"]
    task = Task(env, algo, 0.0, 1, "", (algo, (f"env={env}",)))
    _, extra, _, cfg = rlpipe_config(task, [*spec.get("overrides", ()), f"seed={spec['seed']}"], spec.get("preset"))
    # the marks end the run: a time_budget= the user gave has sized it (pipelines/sizing.py), but on the run's own
    # clock it would count the rule's evaluations, which the bench leaves out
    cfg = dataclasses.replace(cfg, time_budget=None)
    pipeline = pipeline_class(algo)(cfg)
    eval_env = pipeline.eval_env_fn()
    shadow = copy.deepcopy(pipeline.policy)  # the kept best's weights are played in a copy: the learner's stay

    def play(policy) -> tuple[list[float], list[int]]:
        returns, lengths = [], []
        for k in range(marks.eval_episodes):
            eval_env.set_seed(marks.episode_seed(k))
            result = evaluate(eval_env, policy, 1)
            returns.append(float(result["returns"][0]))
            lengths.append(int(result["average_episode_length"]))
        return returns, lengths

    class MarkTrigger(Trigger):
        name = "anytime"

        def __init__(self):
            super().__init__(0)

        best = None

        def play_both(self) -> dict:
            played = {"last": play(pipeline.policy)}
            if self.best is not None and self.best.get("weights") is not None:
                with torch.no_grad():
                    self.best["weights"].to_module(shadow)
                played["exported"] = play(shadow)
            else:
                played["exported"] = played["last"]
            return played

        def final(self, loop) -> None:  # after the last evaluation (the built-in triggers' final firings come first)
            self.best = loop.state.best

        def poll(self, loop) -> None:
            self.best = loop.state.best
            if loop.finished_early is not None or not marks.due():
                return
            marks.record(self.play_both, loop.state.frames, loop.state.updates)
            if marks.done():
                loop.finish_early("anytime")

    trigger = MarkTrigger()
    result = pipeline.train(spec["out"], progress=False, triggers=[trigger])
    while not marks.done():  # the run ended by itself (a plateau, its ceiling): what it made is what a user has then
        marks.record(trigger.play_both, result.summary["frames"], result.summary["updates"],
                     ended=result.summary["stopped_because"])
    marks.emit(versions={**versions("torch", "torchrl", "tensordict", "gymnasium", "mujoco", "numpy"),
                         "rlpipe": _version()}, lib="rlpipe", settings=list(extra) + list(spec.get("overrides", ())),
               threads=cfg.num_threads)
    sys.stdout.flush()
    os._exit(0)  # the benchmark's figures are out; the run directory is complete


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rlpipe")
    except PackageNotFoundError:
        return "unknown"


if __name__ == "__main__":
    spec = json.loads(sys.argv[1])
    Path(spec["out"]).parent.mkdir(parents=True, exist_ok=True)
    main(spec)
