"""``rlpipe bench time-to-return``: its task table, its arithmetic, the peers' rule, and one tiny real run
(rlpipe's side only: the peers' venvs download gigabytes)."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from rlpipe.pipelines import presets, resolve_preset
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.errors import InputError
from rlpipe.scripts.bench import time_to_return as ttr

PEERS_DIR = Path(ttr.__file__).with_name("peers")


@pytest.mark.parametrize("name", list(ttr.TASKS))
def test_each_task_runs_a_preset_of_its_algorithm_on_its_env(name):
    task = ttr.TASKS[name]
    known = presets.names()
    if task.preset in known:  # the preset sized for the task, once it exists
        algo, cfg = resolve_preset(task.preset)
        assert (algo, cfg.env) == (task.algo, task.env)
    fallback, extra = task.fallback  # until then: the tutorial preset pointed at the task
    algo, cfg = resolve_preset(fallback)
    assert algo == task.algo
    assert apply_overrides(cfg, list(extra)).env == task.env
    if task.crossq in known:
        assert resolve_preset(task.crossq)[1].env == task.env
    assert set(task.peers) <= set(ttr.PEERS)
    assert task.cap > 0 and math.isfinite(task.target)


def test_the_issues_targets():
    targets = {name: (t.env, t.algo, t.target) for name, t in ttr.TASKS.items()}
    assert targets["pendulum-sac"] == ("Pendulum-v1", "sac", -200)
    assert targets["cartpole-v1-dqn"] == ("CartPole-v1", "dqn", 475)
    assert targets["cartpole-v0-dqn"] == ("CartPole-v0", "dqn", 195)
    assert targets["invpendulum-td3"] == ("InvertedPendulum-v5", "td3", 950)
    assert {targets["minitaur-sac-1"][2], targets["minitaur-sac-5"][2]} == {1.0, 5.0}


def _run(side, seconds=None, steps=100):
    reached = seconds is not None
    return {"task": "t", "side": side, "seed": 0, "reached": reached, "seconds": seconds, "env_steps": steps,
            "updates": steps, "start_s": 1.0, "tail_s": 0.5, "failed": False}


def test_a_run_not_reached_counts_as_never_in_the_median_and_is_never_dropped():
    runs = [_run("a", 10.0), _run("a", 30.0), _run("a"), _run("b", 5.0), _run("b"), _run("b")]
    s = ttr.summarise(runs)["t"]
    assert s["a"]["median_s"] == 30.0 and (s["a"]["min_s"], s["a"]["max_s"]) == (10.0, 30.0)
    assert (s["a"]["reached"], s["a"]["runs"]) == (2, 3)
    assert s["b"]["median_s"] is None and (s["b"]["reached"], s["b"]["runs"]) == (1, 3)


def test_no_crossq_leaves_out_only_the_crossq_side():
    task = ttr.TASKS["minitaur-sac-1"]
    assert ttr.task_sides(task, ["sbx", "cleanrl"]) == ["rlpipe", "crossq", "sbx"]  # CleanRL has no Minitaur
    assert ttr.task_sides(task, ["sbx"], crossq=False) == ["rlpipe", "sbx"]



def test_also_preset_plays_a_second_rlpipe_side_beside_the_default_against_the_same_peers(tmp_path, capsys):
    """`--also-preset FILE` (the file `rlpipe tune` wrote): the sized default and the file, seed by seed, in the
    one command that times SBX, so both ratios come from the same peer runs."""
    from rlpipe.scripts.cli import main

    task = ttr.TASKS["reacher-sac"]
    plan = list(ttr._plan({"reacher-sac": task}, ["sbx"], True, 2, first=100, also=True))
    assert plan == [("reacher-sac", 100, "rlpipe"), ("reacher-sac", 100, "preset"), ("reacher-sac", 100, "sbx"),
                    ("reacher-sac", 101, "rlpipe"), ("reacher-sac", 101, "preset"), ("reacher-sac", 101, "sbx")]
    mine = tmp_path / "mine.yaml"
    mine.write_text((Path(ttr.__file__).resolve().parents[2] / "presets" / "sac-pendulum.yaml").read_text())
    default = ttr.rlpipe_launch(task, "rlpipe", 100, -5.0, 2000, tmp_path / "a" / "run", None, [])
    also = ttr.rlpipe_launch(task, "preset", 100, -5.0, 2000, tmp_path / "b" / "run", None, [], str(mine))
    assert default.cmd[default.cmd.index("train") + 1] != str(mine)
    assert also.cmd[also.cmd.index("train") + 1] == str(mine) and f"env={task.env}" in also.cmd
    # a file that does not exist: one line, exit 2, before any run
    code = main(["bench", "time-to-return", "--tasks", "reacher-sac", "--peers", "none", "--also-preset",
                 str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "nope.yaml" in err[0]
    assert not (tmp_path / "out").exists()

def test_a_side_with_its_own_seed_count_runs_its_first_seeds_and_the_others_every_seed():
    # --side-seeds tfagents=1: the Minitaur tutorial's ~35-minute run timed once, rlpipe and SBX on every seed
    plan = list(ttr._plan({"minitaur-sac-1": ttr.TASKS["minitaur-sac-1"]}, ["sbx", "tfagents"], False, 3, {"tfagents": 1}))
    assert plan == [("minitaur-sac-1", 0, "rlpipe"), ("minitaur-sac-1", 0, "sbx"), ("minitaur-sac-1", 0, "tfagents"),
                    ("minitaur-sac-1", 1, "rlpipe"), ("minitaur-sac-1", 1, "sbx"),
                    ("minitaur-sac-1", 2, "rlpipe"), ("minitaur-sac-1", 2, "sbx")]
    # --seed 100: seeds the presets were not tuned on, 100 to 102; "its first seed" is then seed 100
    plan = list(ttr._plan({"minitaur-sac-1": ttr.TASKS["minitaur-sac-1"]}, ["tfagents"], False, 3, {"tfagents": 1}, first=100))
    assert plan == [("minitaur-sac-1", 100, "rlpipe"), ("minitaur-sac-1", 100, "tfagents"),
                    ("minitaur-sac-1", 101, "rlpipe"), ("minitaur-sac-1", 102, "rlpipe")]


def test_the_peers_rule_is_rlpipes_rule():
    spec = importlib.util.spec_from_file_location("ttr_rule", PEERS_DIR / "ttr_rule.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    rule = module.Rule(target=10, window=2, eval_episodes=3, recheck=2)
    evaluations = []

    def evaluate(n, value):
        evaluations.append(n)
        return [value] * n

    for ret in (0, 12):
        rule.episode(ret)
    assert not rule.check(lambda n: evaluate(n, 20), 50, 10)  # mean 6: no evaluation
    rule.episode(12)
    assert not rule.check(lambda n: evaluate(n, 5), 60, 20)  # mean 12, greedy 5: not confirmed
    rule.episode(12)
    assert not rule.check(lambda n: evaluate(n, 20), 70, 30)  # one episode since: no new evaluation yet
    rule.episode(12)
    assert rule.check(lambda n: (evaluate(n, 20), [7] * n), 80, 40)  # (returns, lengths) too
    assert evaluations == [3, 3]
    result = rule.result(80, 40)
    assert result["reached"] and (result["env_steps"], result["updates"], result["eval_return"]) == (80, 40, 20)
    assert result["eval_episode_length"] == 7
    assert result["confirmations"] == 2 and result["eval_seconds"] >= 0


def test_the_peers_load_minitaur_from_its_file_without_torch_or_rlpipe(tmp_path):
    # SBX's and TF-Agents' venvs have neither torch nor rlpipe: ttr_rule.register_minitaur loads
    # envs/minitaur.py as a file there (a torch import in it once made every peer's Minitaur run fail).
    script = tmp_path / "peer.py"
    script.write_text(
        "import sys\n"
        "sys.modules['torch'] = None; sys.modules['rlpipe'] = None  # an import of either raises\n"
        f"sys.path.insert(0, {str(PEERS_DIR)!r})\n"
        "import gymnasium, ttr_rule\n"
        f"ttr_rule.register_minitaur({ttr._minitaur_module()!r})\n"
        "env = gymnasium.make('MinitaurBulletEnv-v0')\n"
        "obs, _ = env.reset(seed=0)\n"
        "obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())\n"
        "print('stepped', obs.shape, type(reward).__name__)\n")
    import subprocess
    import sys

    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "stepped (28,) float" in done.stdout


@pytest.mark.slow
def test_a_tiny_run_of_the_harness_times_rlpipe_to_a_low_target(tmp_path, capsys):
    from rlpipe.scripts.cli import main

    out, figures = tmp_path / "bench", tmp_path / "ttr.json"
    code = main(["bench", "time-to-return", "eval_interval=0", "baseline_episodes=0", "num_eval_episodes=2",
                 "--tasks", "cartpole-v0-dqn", "--seeds", "1", "--peers", "none", "--target-return", "30",
                 "--out", str(out), "--json", str(figures)])
    assert code == 0
    printed = capsys.readouterr().out
    data = json.loads(figures.read_text())
    (run,) = data["runs"]
    assert run["side"] == "rlpipe" and run["reached"] and run["rc"] == 0
    assert 0 < run["start_s"] < run["seconds"] < run["wall_s"]  # launch -> first step -> target -> exit
    assert 0 < run["env_steps"] < data["tasks"]["cartpole-v0-dqn"]["cap"]
    summary = json.loads((out / "cartpole-v0-dqn" / "rlpipe-seed0" / "run" / "summary.json").read_text())
    assert summary["target"]["return"] == 30 and summary["frames"] == run["env_steps"]
    assert "[1/1] cartpole-v0-dqn seed 0 rlpipe: " in printed
    assert "| rlpipe | `rlpipe train dqn" in printed and "| 1/1 |" in printed
    assert Path(data["png"]).stat().st_size > 0


@pytest.mark.slow
def test_a_stopped_bench_ends_the_run_under_way_and_keeps_the_runs_it_finished(tmp_path):
    # Ctrl-C (the fault hook's SIGINT to the bench's process group) while the second run is under way
    out, figures = tmp_path / "bench", tmp_path / "ttr.json"
    done = subprocess.run(
        [sys.executable, "-m", "rlpipe.scripts.cli", "bench", "time-to-return", "eval_interval=0", "baseline_episodes=0",
         "num_eval_episodes=2", "--tasks", "cartpole-v0-dqn", "--seeds", "2", "--peers", "none", "--target-return", "30",
         "--out", str(out), "--json", str(figures)],
        capture_output=True, text=True, timeout=600, start_new_session=True, env={**os.environ, "RLPIPE_FAULT": "bench_run@2"})
    assert done.returncode == 130, done.stderr[-2000:]
    assert "interrupted by SIGINT" in done.stderr
    data = json.loads(figures.read_text())
    assert data["interrupted"] == {"signal": "SIGINT", "during": "cartpole-v0-dqn seed 1 rlpipe", "runs_done": 1,
                                   "runs_planned": 2}
    (run,) = data["runs"]  # the first seed's, whole
    assert run["seed"] == 0 and run["reached"] and run["rc"] == 0
    assert "| 1/1 |" in done.stdout and "Interrupted by SIGINT during cartpole-v0-dqn seed 1 rlpipe" in done.stdout
    # the second run was launched and ended with the bench: no process of it is left
    second = out / "cartpole-v0-dqn" / "rlpipe-seed1"
    assert (second / "output.log").exists()
    left = [pid for pid in os.listdir("/proc") if pid.isdigit() and _cmdline(pid).find(str(second)) >= 0]
    assert left == []


def _cmdline(pid: str) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:  # gone meanwhile
        return ""


# --- the torchrl peer: TorchRL's sota-implementations scripts from a checkout of pytorch/rl -------------------------

# Stands in for the checkout's dqn/config_cartpole.yaml (not in TorchRL's wheel, nor copied here): every key the
# script reads, sized for a test.
TINY_DQN_CONFIG = """\
device: null
env: {env_name: CartPole-v1}
collector: {total_frames: 500_100, frames_per_batch: 100, eps_start: 1.0, eps_end: 0.05, annealing_frames: 1000,
            init_random_frames: 100}
buffer: {buffer_size: 1000, batch_size: 32}
logger: {backend: wandb, project_name: p, group_name: null, exp_name: DQN, test_interval: 50_000,
         num_test_episodes: 1, video: False}
checkpoint: {path: null, interval: 0, format: archive, strict: error, resume: false, include_replay_buffer: true}
optim: {lr: 2.5e-4, max_grad_norm: 10}
loss: {gamma: 0.99, hard_update_freq: 50, num_updates: 3}
compile: {compile: False, compile_mode: null, cudagraphs: False}
hydra: {job: {chdir: true}}
"""


@pytest.fixture
def dqn_checkout(tmp_path):
    """A pytorch/rl checkout holding TorchRL's DQN CartPole recipe: the scripts the installed wheel ships, its version."""
    from importlib.metadata import files, version

    shipped = {str(f): f for f in files("torchrl") or () if str(f).startswith("sota-implementations/dqn/")}
    if "sota-implementations/dqn/dqn_cartpole.py" not in shipped:
        pytest.skip("this torchrl wheel ships no sota-implementations scripts to build a checkout from")
    folder = tmp_path / "rl" / "sota-implementations" / "dqn"
    folder.mkdir(parents=True)
    for name in ("dqn_cartpole.py", "utils_cartpole.py"):
        (folder / name).write_bytes(shipped[f"sota-implementations/dqn/{name}"].locate().read_bytes())
    (folder / "config_cartpole.yaml").write_text(TINY_DQN_CONFIG)
    (tmp_path / "rl" / "version.txt").write_text(version("torchrl") + "\n")
    return tmp_path / "rl"


def test_the_torchrl_peer_needs_a_checkout_of_the_installed_release(dqn_checkout, tmp_path, capsys):
    from importlib.metadata import version

    from rlpipe.scripts.cli import main

    def error(*extra):
        code = main(["bench", "time-to-return", "--tasks", "cartpole-v0-dqn", "--peers", "torchrl", *extra,
                     "--out", str(tmp_path / "out")])
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1, lines
        return lines[0]

    release = f"a checkout of pytorch/rl at tag v{version('torchrl')}"
    line = error()
    assert "--peers torchrl: needs --torchrl-sota DIR" in line and release in line
    assert "no sota-implementations folder" in error("--torchrl-sota", str(tmp_path))
    (dqn_checkout / "version.txt").write_text("0.13.3\n")
    assert "version.txt says 0.13.3" in error("--torchrl-sota", str(dqn_checkout))
    (dqn_checkout / "version.txt").write_text(version("torchrl") + "\n")
    script = dqn_checkout / "sota-implementations" / "dqn" / "dqn_cartpole.py"
    script.write_text(script.read_text() + "# changed\n")
    line = error("--torchrl-sota", str(dqn_checkout))
    assert f"sota-implementations/dqn/dqn_cartpole.py is not the one torchrl {version('torchrl')} ships" in line
    assert not (tmp_path / "out").exists()  # refused before anything is written
    # the recipes of the tasks chosen: a checkout without SAC's is enough for a DQN task, not for a SAC one
    script.write_text(script.read_text().removesuffix("# changed\n"))
    args = SimpleNamespace(tasks=["cartpole-v0-dqn"], peers=["torchrl"], torchrl_sota=dqn_checkout, threads=None,
                           cap=None, side_seeds=None, seeds=1, seed=0, cap_scale=None, preset=None, overrides=[])
    ttr.check_args(args)
    assert ttr.chosen_peers(SimpleNamespace(peers=None, torchrl_sota=dqn_checkout)) == ["cleanrl", "sb3", "sbx",
                                                                                       "torchrl"]
    with pytest.raises(InputError, match="sota-implementations/sac/sac.py missing"):
        ttr.check_args(SimpleNamespace(**{**vars(args), "tasks": ["pendulum-sac"]}))


@pytest.mark.slow
def test_the_torchrl_peer_runs_torchrls_script_and_is_timed_by_the_rule(dqn_checkout, tmp_path):
    from importlib.metadata import version

    # the script unchanged, on its config, to a target any CartPole episode passes (no episode ends before 5 steps)
    work = tmp_path / "torchrl-seed0"
    launch = ttr.peer_launch(ttr.TASKS["cartpole-v0-dqn"], "torchrl", 0, 5.0, 3000, work, 1, dqn_checkout)
    assert "dqn_cartpole.py" in launch.settings and "num_updates=3" in launch.settings
    result = ttr.run_one(launch, work / "output.log")
    assert result["rc"] == 0 and result["reached"] and not result["failed"], result
    assert 0 < result["start_s"] < result["seconds"] < result["wall_s"]  # launch -> first step -> target -> exit
    # checked as each batch of 100 frames arrives, before its updates; 3 updates a batch from the first one
    assert 5 * 5 <= result["env_steps"] <= 3000
    assert result["updates"] == 3 * (math.ceil(result["env_steps"] / 100) - 1)
    assert result["eval_return"] >= 5 and result["eval_episode_length"] == result["eval_return"]
    assert result["versions"]["torchrl"] == version("torchrl") and result["versions"]["hydra-core"] == "1.3.8"
    assert not (work / ".hydra").exists()  # Hydra's run folder is the run's own, its config copy not written
    row = {**result, "task": "cartpole-v0-dqn", "side": "torchrl", "seed": 0}
    assert ttr.summarise([row])["cartpole-v0-dqn"]["torchrl"]["reached"] == 1


def test_a_run_started_in_its_own_folder_finds_the_users_modules_on_a_relative_pythonpath(monkeypatch, tmp_path):
    """`PYTHONPATH=. rlpipe tune sac env=my_package:MyArm`: each trial's run starts in its own folder, where `.`
    would name another place."""
    from rlpipe.scripts.bench.time_to_return import _here_environ

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([".", "", "/opt/abs"]))
    assert _here_environ()["PYTHONPATH"].split(os.pathsep) == [str(tmp_path.resolve())] * 2 + ["/opt/abs"]


def test_a_preset_file_named_from_here_is_found_by_the_run_in_its_own_folder(tmp_path, monkeypatch):
    """`--preset my.yaml` (a path relative to where the bench was started): each run starts in a folder of its own,
    so the command it gets names the file absolutely."""
    mine = tmp_path / "my.yaml"
    mine.write_text((Path(ttr.__file__).resolve().parents[2] / "presets" / "sac-pendulum.yaml").read_text())
    monkeypatch.chdir(tmp_path)
    launch = ttr.rlpipe_launch(ttr.TASKS["pendulum-sac"], "rlpipe", 0, -200.0, 2000, tmp_path / "out" / "run", None, [],
                               "my.yaml")
    assert launch.cmd[launch.cmd.index("train") + 1] == str(mine)
