"""``rlpipe bench profile``'s classification of py-spy samples into parts, on real samples.

tests/data/pyspy_raw_sample.txt holds lines of py-spy 0.4.3's ``record --format raw --idle --threads
--subprocesses --full-filenames --nolineno`` output, taken from two real runs in their steady state:
``rlpipe train dqn`` (pid 20926: the env stepped by TorchRL's in-process Collector; pid 15882: with
``collector.sync=false``) and the ``td3`` preset with CleanRL's sizes (pid 21414, its collector
process 21497). No timing is asserted.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from rlpipe.scripts.bench import profile as bp

pytestmark = pytest.mark.unit

SAMPLE = Path(__file__).parent / "data" / "pyspy_raw_sample.txt"

# (pid, thread, part) of each line of SAMPLE, in order
EXPECTED = [
    (21497, "MainThread", "collection policy"),
    (21497, "MainThread", "collector bookkeeping (trajectory ids, stacking, copies)"),
    (21497, "MainThread", "env step"),
    (21497, "MainThread", "waiting for the learner to take the block / weights"),
    (20926, "MainThread", "collection policy (in-process collector)"),
    (20926, "MainThread", "collector bookkeeping (in-process: trajectory ids, stacking, copies)"),
    (20926, "MainThread", "env step (in-process collector)"),
    (20926, "MainThread", "insert a block into the replay buffer"),
    (21414, "MainThread", "insert a block into the replay buffer"),
    (20926, "MainThread", "replay sample"),
    (21414, "MainThread", "replay sample"),
    (20926, "MainThread", "triggers (log rows, checkpoints), loop bookkeeping, other"),
    (21414, "MainThread", "triggers (log rows, checkpoints), loop bookkeeping, other"),
    (20926, "MainThread", "update: backward (autograd engine)"),
    (21414, "MainThread", "update: backward (autograd engine)"),
    (20926, "MainThread", "update: forward (losses)"),
    (21414, "MainThread", "update: forward (losses)"),
    (20926, "MainThread", "update: optimiser step"),
    (21414, "MainThread", "update: optimiser step"),
    (21414, "MainThread", "update: target update"),
    (21414, "MainThread", "waiting for a collected block"),
    (21414, "MainThread", "weight push to collectors"),
    (20926, "rlpipe-watchdog", None),
    # the dqn preset with collector.sync=false (pid 15882): the async collector's iterator, no rollout here
    (15882, "MainThread", "waiting for a collected block"),
]


def test_each_real_stack_lands_in_its_part():
    lines = SAMPLE.read_text().splitlines()
    assert len(lines) == len(EXPECTED)
    for line, (pid, thread, part) in zip(lines, EXPECTED, strict=True):
        processes = bp.parse_raw([line])
        assert list(processes) == [pid]
        proc = processes[pid]
        (name, stacks), = proc["threads"].items()
        assert name == thread
        if part is None:
            continue
        (stack, _), = stacks.items()
        classify = bp.classify_learner if bp.role(proc) == "learner" else bp.classify_worker
        assert classify(stack) == part, line[:200]


def test_gym_collectors_steps_land_in_the_same_parts():
    # GymCollector (collector.direct=true) steps the env under its own _rollout, below TorchRL's iterator
    gc = "/work/rlpipe/pipelines/workers/gym_collector.py"
    worker = (("_main_async_collector", "/site-packages/torchrl/collectors/_runner.py"),
              ("Collector.iterator", "/site-packages/torchrl/collectors/_single.py"),
              ("GymCollector.rollout", gc), ("GymCollector._rollout", gc))
    steps = ("GymCollector._steps", gc)  # its per-step loop
    policy = (("_egreedy_step.<locals>.act", "/work/rlpipe/modules/fast/tensor_policy.py"),
              ("EGreedyQPolicy.act", "/work/rlpipe/modules/fast/exploration.py"))
    assert bp.classify_worker((*worker, *policy)) == "collection policy"
    assert bp.classify_worker((*worker, steps, *policy)) == "collection policy"
    assert bp.classify_worker((*worker, ("CartPoleEnv.step", "/site-packages/gymnasium/envs/classic_control/cartpole.py"))
                              ) == "env step"
    assert bp.classify_worker((*worker, steps, ("TimeLimit.step", "/site-packages/gymnasium/wrappers/common.py"))
                              ) == "env step"
    assert bp.classify_worker((*worker, ("GymCollector._block", gc))) == \
        "collector bookkeeping (trajectory ids, stacking, copies)"
    learner = (("Loop.run", "/work/rlpipe/pipelines/training/loop.py"),
               ("Loop.collect", "/work/rlpipe/pipelines/training/loop.py"), *worker[1:])
    assert bp.classify_learner((*learner, ("TimeLimit.step", "/site-packages/gymnasium/wrappers/common.py"))) == \
        "env step (in-process collector)"
    assert bp.classify_learner((*learner, steps, *policy)) == "collection policy (in-process collector)"
    # rlpipe's own replay sample (modules/fast/sampling.py), not ReplayBuffer.sample
    updates = (("Loop.run", "/work/rlpipe/pipelines/training/loop.py"),
               ("Loop.pay_updates", "/work/rlpipe/pipelines/training/loop.py"))
    assert bp.classify_learner((*updates, ("sample", "/work/rlpipe/modules/fast/sampling.py"),
                                ("_gather", "/work/rlpipe/modules/fast/sampling.py"))) == "replay sample"


def test_processes_roles_and_shares():
    processes = bp.parse_raw(SAMPLE.read_text().splitlines())
    # the collector process's command line holds ';' (multiprocessing's -c string): still one process
    assert set(processes) == {20926, 21414, 21497, 15882}
    assert processes[21497]["parent"] == 21414
    assert {pid: bp.role(p) for pid, p in processes.items()} == {20926: "learner", 21414: "learner", 21497: "collector",
                                                                 15882: "learner"}
    figures = {f["pid"]: f for f in bp.shares(processes)}
    # main threads only: the watchdog thread's 799 idle samples are not the learner's
    assert figures[20926]["samples"] == 1 + 3 + 20 + 1 + 2 + 4 + 9 + 1 + 29
    # a learner that steps its env in-process files its collector's iterator as bookkeeping, one with
    # collector processes as waiting
    assert "collector bookkeeping (in-process: trajectory ids, stacking, copies)" in figures[20926]["shares"]
    assert figures[15882]["shares"] == {"waiting for a collected block": 1.0}
    for f in figures.values():
        assert sum(f["shares"].values()) == pytest.approx(1.0)
    assert figures[21497]["shares"]["waiting for the learner to take the block / weights"] == pytest.approx(644 / 652)
    table = bp.table(list(figures.values()))
    assert "| update: target update |" in table and "collector process (pid 21497" in table


@pytest.mark.parametrize("argv, words", [
    (["bench", "profile", "dqm", "--out", "new"], ["dqm", "dqn"]),
    (["bench", "profile", "env=CartPole-v1", "--out", "new"], ["PRESET"]),
    (["bench", "profile", "dqn", "batchsize=3", "--out", "new"], ["batchsize"]),
    (["bench", "profile", "dqn", "--duration", "0", "--out", "new"], ["--duration=0"]),
])
def test_bad_profile_arguments_are_one_line_and_write_nothing(argv, words, tmp_path, monkeypatch, capsys):
    from rlpipe.scripts.cli import main

    monkeypatch.chdir(tmp_path)
    code = main(argv)
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("rlpipe: error:"), lines
    for word in words:
        assert word in lines[0]
    assert list(tmp_path.iterdir()) == []
