"""Runs that survive lost workers and stop signals: a collector or evaluator process killed (kill -9)
or frozen (SIGSTOP) at an exact iteration is replaced and the run goes on; past
``collector.max_restarts`` the run saves a checkpoint and stops with one line (exit 75); SIGTERM and
SIGHUP, to the learner alone or to its process group, save a checkpoint like Ctrl-C (exit 128 + the
signal). Every run is a real ``rlpipe train`` process; faults come from the test hook
(``RLPIPE_FAULT``, ``pipelines/system/faults.py``) at exact points, and what outlives a run is read with psutil.
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import psutil
import pytest
import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer

from rlpipe.pipelines import td3
from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.config import apply_overrides, eval_seed
from rlpipe.pipelines.workers.evaluation import BackgroundEvaluator, evaluate
from rlpipe.pipelines.workers.supervision import NoRestartLeft, Supervisor, Watchdog, WorkerFailure

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

CLI = [sys.executable, "-m", "rlpipe.scripts.cli"]
SMALL_TD3 = ["actor_fc_layer_params=[32]", "critic_fc_layer_params=[32]", "batch_size=32"]
# 100 random frames, then 300 iterations of one frame each: blocks of 50 frames end at iterations 50, 100, ...
TD3_RUN = [
    "train", "td3", *SMALL_TD3, "collector.workers=2", "num_iterations=300", "initial_collect_steps=100",
    "learning_starts=100", "log_interval=50", "eval_interval=150", "num_eval_episodes=1", "checkpoint_interval=50",
    "policy_save_interval=1000", "--no-progress",
]
TOTAL_FRAMES = 400


@dataclass
class Finished:
    exit: int
    stdout: str
    stderr: str
    left: list[str]  # processes of the run's session still alive after it exited

    def lines(self) -> list[str]:
        return [line for line in self.stderr.splitlines() if line.startswith("rlpipe:")]


def session_members(sid: int) -> list[psutil.Process]:
    members = []
    for proc in psutil.process_iter():
        with contextlib.suppress(psutil.Error, ProcessLookupError, PermissionError):
            if os.getsid(proc.pid) == sid and proc.status() != psutil.STATUS_ZOMBIE:
                members.append(proc)
    return members


def train(args: list[str], run: Path, fault: str = "", timeout: float = 400) -> Finished:
    """``rlpipe ARGS --out RUN`` (or ``--resume RUN``) in a session of its own, with ``RLPIPE_FAULT=fault``;
    a run still going after ``timeout`` s is a hang: it is dumped (faulthandler) and killed."""
    env = {**os.environ, "PYTHONFAULTHANDLER": "1", "RLPIPE_FAULT": fault}
    where = [] if "--resume" in args else ["--out", str(run)]
    proc = subprocess.Popen([*CLI, *args, *where], cwd=run.parent, env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGABRT)  # faulthandler prints where it waits, then the process ends
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=30)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate(timeout=30)
        pytest.fail(f"the run hung (killed after {timeout} s):\n{err[-5000:]}")
    deadline = time.monotonic() + 15  # a collector's worker may take a moment to see its learner gone
    while session_members(proc.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = [" ".join(p.cmdline()) for p in session_members(proc.pid)]
    for p in session_members(proc.pid):
        with contextlib.suppress(psutil.Error):
            p.kill()
    return Finished(proc.returncode, out, err, left)


def rows(run: Path) -> list[dict]:
    with (run / "metrics.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


def log_rows(run: Path) -> list[dict]:
    return [r for r in rows(run) if r["steps_per_s"]]


def eval_steps(run: Path) -> list[int]:
    return [int(r["step"]) for r in rows(run) if r["average_return"]]


def checkpoint(run: Path, step: int | None = None) -> dict:
    folder = run / "checkpoints"
    path = ckpt.latest_checkpoint(folder) if step is None else folder / f"step_{step:010d}"
    return ckpt.load_checkpoint(path, "td3", "Pendulum-v1")


def replay_data(state: dict):
    rb = ReplayBuffer(storage=LazyTensorStorage(100_000))
    ckpt.load_replay_buffer(rb, state["replay_buffer"])
    return rb[:]


# --- a worker killed, or frozen, is replaced and the run finishes ---------------------------------------


@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    """Two MultiAsyncCollector workers and the background evaluator: worker 0 kill -9'd after the block
    of iteration 100, the evaluator's process kill -9'd right after the evaluation at 150 was asked."""
    run = tmp_path_factory.mktemp("killed") / "run"
    done = train([*TD3_RUN, "collector.sync=false", "eval_in_background=true", "replay_all_keys=true"], run,
                 fault="collector_worker@100:SIGKILL;evaluator_worker@150:SIGKILL")
    return run, done


@pytest.mark.slow
def test_a_killed_collector_worker_is_replaced_and_the_run_finishes(killed):
    run, done = killed
    assert done.exit == 0, done.stderr[-3000:]
    restarts = [line for line in done.lines() if "restarting the collector" in line]
    assert len(restarts) == 1 and "collector worker 0" in restarts[0] and "killed by SIGKILL" in restarts[0], done.lines()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == 300 and summary["frames"] == TOTAL_FRAMES
    logged = log_rows(run)  # metrics say how many workers are alive and how many restarts were made
    restart_counts = [int(r["collector_restarts"]) for r in logged]  # at 50, 100, ..., 300
    # none before the kill at 100; the one restart from the next block or so on
    assert restart_counts[:2] == [0, 0] and restart_counts[-2:] == [1, 1] and sorted(restart_counts) == restart_counts
    assert {r["workers_alive"] for r in logged} == {"2"}
    assert done.left == [], done.left  # no worker, evaluator or tracker outlives the run


@pytest.mark.slow
def test_a_killed_evaluator_is_replaced_and_asked_again(killed):
    run, done = killed
    assert done.exit == 0, done.stderr[-3000:]
    restarts = [line for line in done.lines() if "restarting the evaluator" in line]
    assert len(restarts) == 1 and "killed by SIGKILL" in restarts[0], done.lines()
    assert eval_steps(run) == [0, 150, 300]  # the evaluation the killed process had is made by the next one
    assert log_rows(run)[-1]["evaluator_restarts"] == "1"


@pytest.mark.slow
def test_a_restart_loses_no_replay_data(killed):
    run, _ = killed
    data = replay_data(checkpoint(run))
    assert data.numel() == TOTAL_FRAMES
    assert checkpoint(run)["counters"]["frames"] == TOTAL_FRAMES
    # the new workers number their trajectories after the stored ones: each id is one episode, its steps
    # counting up one by one (the new pool starts at 0 again; a SliceSampler on the ids would join two episodes)
    traj, steps = data["collector", "traj_ids"].flatten(), data["step_count"].flatten()
    for i in traj.unique().tolist():
        episode = steps[traj == i]
        assert torch.equal(episode, torch.arange(int(episode[0]), int(episode[0]) + len(episode))), (i, traj, steps)


@pytest.fixture(scope="module")
def frozen(tmp_path_factory):
    """A collector worker and the evaluator's process stopped (SIGSTOP: alive, never answering): the
    weight push and the evaluation wait at most their timeouts."""
    run = tmp_path_factory.mktemp("frozen") / "run"
    done = train([*TD3_RUN, "collector.sync=false", "eval_in_background=true", "collector.timeout=10",
                  "eval_timeout=12"], run, fault="collector_worker@100:SIGSTOP;evaluator_worker@150:SIGSTOP")
    return run, done


@pytest.mark.slow
def test_a_wait_that_times_out_is_a_failed_worker(frozen):
    run, done = frozen
    assert done.exit == 0, done.stderr[-3000:]
    lines = done.lines()
    assert any("restarting the collector" in line and "within 10 s" in line for line in lines), lines
    # frozen right after it was asked: the weights it is sent, or else the evaluation, time out
    assert any("restarting the evaluator" in line and ("within 10 s" in line or "eval_timeout=12" in line)
               for line in lines), lines
    assert eval_steps(run) == [0, 150, 300]
    assert json.loads((run / "summary.json").read_text())["frames"] == TOTAL_FRAMES
    assert done.left == [], done.left  # the frozen processes were killed, not left behind


# --- no restart left: checkpoint, one line, resume ----------------------------------------------------


@pytest.fixture(scope="module")
def lost(tmp_path_factory):
    """MultiSyncCollector workers, one restart allowed, a worker killed at 100 and again at 150; then
    --resume."""
    run = tmp_path_factory.mktemp("lost") / "run"
    stopped = train([*TD3_RUN, "collector.sync=true", "collector.max_restarts=1"], run,
                    fault="collector_worker@100,150:SIGKILL")
    state = {"latest": checkpoint(run), "before": checkpoint(run, 100)}
    resumed = train(["train", "td3", "--resume", str(run), "--no-progress"], run)
    return run, stopped, state, resumed


@pytest.mark.slow
def test_past_max_restarts_the_run_saves_and_stops_with_one_line(lost):
    run, stopped, state, _ = lost
    assert stopped.exit == 75, stopped.stderr[-3000:]
    assert "Traceback" not in stopped.stderr, stopped.stderr[-3000:]
    last = stopped.lines()[-1]
    assert last.startswith("rlpipe: error: collector worker 0") and "killed by SIGKILL" in last, last
    assert "no restart left" in last and "collector.max_restarts=1" in last, last
    assert "checkpoint saved at iteration 150" in last and f"--resume {run}" in last, last
    assert state["latest"]["counters"]["iteration"] == 150 and state["latest"]["counters"]["frames"] == 250
    assert stopped.left == [], stopped.left


@pytest.mark.slow
def test_the_replay_buffer_keeps_what_it_had_across_a_restart(lost):
    _, _, state, _ = lost
    before, after = replay_data(state["before"]), replay_data(state["latest"])
    assert before.numel() == 200 and after.numel() == 250
    for key in ("observation", "action", ("next", "reward")):  # the frames from before the kill at 100, as they were
        assert torch.equal(after[:200][key], before[key]), key


@pytest.mark.slow
def test_a_run_stopped_for_lost_workers_resumes_to_the_end(lost):
    run, _, _, resumed = lost
    assert resumed.exit == 0, resumed.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["iterations"] == 300 and summary["frames"] == TOTAL_FRAMES
    assert eval_steps(run) == [0, 150, 300]
    assert resumed.left == []


# --- SIGTERM and SIGHUP stop like Ctrl-C ---------------------------------------------------------------


@pytest.mark.parametrize("fault, status", [
    ("collected@100:SIGTERM:self", 143),  # the learner alone (`kill PID`, `timeout`, Kubernetes)
    # the whole process group, as a terminal closing sends it (and SLURM or job control send SIGTERM so: the
    # same path; tests/test_resume_exact.py stops runs with SIGTERM to the group)
    ("collected@100:SIGHUP", 129),
])
@pytest.mark.slow
def test_a_stop_signal_saves_a_checkpoint_and_resume_finishes(fault, status, tmp_path):
    run = tmp_path / "run"
    stopped = train([*TD3_RUN, "collector.sync=false", "num_iterations=400"], run, fault=fault)
    signame = fault.split(":")[1]
    assert stopped.exit == status, stopped.stderr[-3000:]
    assert "died" not in stopped.stderr  # the workers never saw the signal: the learner stopped them
    last = stopped.lines()[-1]
    assert last.startswith(f"rlpipe: interrupted by {signame}") and "--resume" in last, stopped.stderr[-3000:]
    counters = checkpoint(run)["counters"]
    assert 100 <= counters["iteration"] < 400, counters  # saved where it stopped, not only at 0
    assert stopped.left == [], stopped.left
    if fault.endswith(":self"):  # resumed once (the three stop the same way)
        resumed = train(["train", "td3", "--resume", str(run), "--no-progress"], run)
        assert resumed.exit == 0, resumed.stderr[-3000:]
        assert json.loads((run / "summary.json").read_text())["iterations"] == 400


# --- the parts, in this process --------------------------------------------------------------------------


def test_closing_an_evaluator_with_an_evaluation_in_flight_ends_its_process_and_keeps_the_evaluation_owed():
    """close() with an evaluation in flight ends the worker at once (the run stops without waiting for the
    episodes), and the evaluation stays in ``pending``, which a checkpoint keeps."""
    cfg = apply_overrides(td3.preset("td3"), [*SMALL_TD3])
    pipeline = td3.TD3(cfg)
    pending = deque()
    evaluator = BackgroundEvaluator(pipeline.eval_env_fn, pipeline.policy, 1000, pending)  # 1,000 episodes: busy
    try:
        worker = psutil.Process(evaluator.worker_pid)
        evaluator.ask({"step": 1, "frames": 1, "updates": 1}, evaluator.snapshot(pipeline.policy))
        assert list(evaluator.results()) == []  # not back yet
    finally:
        evaluator.close()
    assert not worker.is_running() or worker.status() == psutil.STATUS_ZOMBIE
    assert len(pending) == 1


def test_the_background_evaluator_plays_the_episodes_the_learner_would_at_that_step():
    """An evaluation in the background process is seeded from the run's seed and its step
    (``config.eval_seed``): the same weights at the same step give the learner's own evaluation's
    episodes, return for return, so a resumed run evaluates as the uninterrupted one did."""
    cfg = apply_overrides(td3.preset("td3"), [*SMALL_TD3, "seed=7"])
    pipeline = td3.TD3(cfg)
    evaluator = BackgroundEvaluator(pipeline.eval_env_fn, pipeline.policy, 3, deque(), seed=7)
    try:
        results = {}
        for step in (100, 200, 100):
            evaluator.ask({"step": step, "frames": step, "updates": step}, evaluator.snapshot(pipeline.policy))
            results.setdefault(step, []).append(next(evaluator.results(block=True))[1]["returns"])
    finally:
        evaluator.close()
    here = {}
    for step in (100, 200):
        pipeline.eval_env.set_seed(eval_seed(7, step))
        here[step] = evaluate(pipeline.eval_env, pipeline.policy, 3)["returns"]
    assert results[100] == [here[100], here[100]]  # the same step twice: the same episodes
    assert results[200] == [here[200]] and here[200] != here[100]


@pytest.mark.unit
def test_supervisor_counts_restarts_per_role_and_gives_up_past_the_budget():
    lines = []
    supervisor = Supervisor(max_restarts=1, timeout=5, log=lines.append)
    assert supervisor.columns() == {}  # nothing watched: blank columns
    supervisor.report("collector", 2, 2)
    supervisor.failed("collector", WorkerFailure("collector", "collector worker 1 (pid 7) died: killed by SIGKILL"))
    supervisor.report("evaluator", 1, 1)
    supervisor.failed("evaluator", WorkerFailure("evaluator", "evaluator worker 0 (pid 8) died: exited with status 1"))
    assert supervisor.columns() == {"workers_alive": 2, "collector_restarts": 1, "evaluator_restarts": 1}
    assert lines == ["rlpipe: collector worker 1 (pid 7) died: killed by SIGKILL; restarting the collector (restart 1 of 1)",
                     "rlpipe: evaluator worker 0 (pid 8) died: exited with status 1; restarting the evaluator "
                     "(restart 1 of 1)"]
    with pytest.raises(NoRestartLeft, match=r"no restart left \(1 restart made, collector.max_restarts=1\)"):
        supervisor.failed("collector", WorkerFailure("collector", "collector worker 0 (pid 9) died"))


@pytest.mark.unit
def test_watchdog_acts_once_a_wait_passes_its_deadline_and_never_before():
    watchdog = Watchdog()
    fired = threading.Event()
    try:
        with watchdog.limit(0.2, fired.set):
            assert fired.wait(30)  # a wait that outlives its deadline gets the action
        for _ in range(50):  # waits that end in time get nothing
            with watchdog.limit(30, lambda: pytest.fail("fired before its deadline")):
                pass
        assert watchdog.expired == 1
    finally:
        watchdog.close()
    assert not watchdog._thread.is_alive()


def test_ablate_kills_a_run_that_does_not_stop_in_time():
    from rlpipe.scripts.ablate import stop_runs

    ignores = "import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); print('ready', flush=True); time.sleep(600)"
    stops = "import time; print('ready', flush=True); time.sleep(600)"
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True) for code in (ignores, stops)]
    try:
        for proc in procs:
            assert proc.stdout.readline().strip() == "ready"
        stopping = threading.Thread(target=stop_runs, args=(procs, signal.SIGINT), kwargs={"timeout": 3.0})
        stopping.start()
        stopping.join(300)  # generous: what is checked is that it returns, having stopped both
        assert not stopping.is_alive(), "stop_runs did not return"
        assert procs[0].returncode == -signal.SIGKILL  # ignored the signal: killed at the timeout
        assert procs[1].returncode == -signal.SIGINT  # stopped when passed the signal
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
