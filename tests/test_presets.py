"""Presets sized for a task: each builds on its env, `rlpipe presets` lists it with its task and measured
time, a tutorial preset pointed at another env prints one hint line and trains on, and a sized preset
skips the start-up work it does not want (untrained evaluation, random baseline, thread timing)."""

from __future__ import annotations

import csv
import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

import rlpipe.envs  # noqa: F401  (registers MinitaurBulletEnv-v0)
from rlpipe.pipelines import device_hint, pipeline_class, preset_info, presets, resolve_preset, size_hint, sized_presets
from rlpipe.pipelines.config import PresetInfo, apply_overrides
from rlpipe.pipelines.errors import InputError

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

SIZED = {
    "sac-pendulum": ("Pendulum-v1", (-200.0,)),
    "td3-pendulum": ("Pendulum-v1", (-200.0,)),
    "dqn-cartpole-v0": ("CartPole-v0", (195.0,)),
    "dqn-cartpole-v1-fast": ("CartPole-v1", (475.0,)),
    "sac-invpendulum": ("InvertedPendulum-v5", (950.0,)),
    "td3-invpendulum": ("InvertedPendulum-v5", (950.0,)),
    "sac-halfcheetah-100k": ("HalfCheetah-v5", (3000.0,)),
    "sac-minitaur": ("MinitaurBulletEnv-v0", (1.0,)),
    "sac-minitaur-5": ("MinitaurBulletEnv-v0", (5.0,)),
}


@pytest.mark.parametrize("name", list(SIZED))
def test_each_sized_preset_builds_on_its_task(name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo writes MUJOCO_LOG.TXT into the cwd
    env, targets = SIZED[name]
    info = preset_info(name)
    assert (info.env, info.targets, info.sized) == (env, targets, True)
    algo, cfg = resolve_preset(name)
    assert cfg.env == env
    # what a preset sized for time skips: the thread timing (a count named), the untrained
    # evaluation and the random baseline
    assert cfg.num_threads > 0 and not cfg.initial_eval and cfg.baseline_episodes == 0
    pipeline = pipeline_class(algo)(cfg)
    assert pipeline.env.fake_tensordict() is not None


def test_the_tutorial_presets_keep_their_start_up():
    for name in ("sac", "td3", "dqn"):
        cfg = resolve_preset(name)[1]
        assert cfg.initial_eval and cfg.num_threads == -1 and not preset_info(name).sized


def test_every_preset_has_its_task_and_the_sized_ones_are_found_by_env():
    for name in presets.names():
        assert preset_info(name) is not None, name
        assert preset_info(name).env == resolve_preset(name)[1].env, name
    assert sized_presets("Pendulum-v1") == ["td3-pendulum", "sac-pendulum", "crossq-pendulum"]
    assert sized_presets("MinitaurBulletEnv-v0") == ["sac-minitaur", "sac-minitaur-5", "crossq-minitaur", "crossq-minitaur-5"]
    assert sized_presets("Acrobot-v1") == []


def test_rlpipe_presets_lists_each_with_its_task_and_measured_time(capsys):
    """Each preset file's ``info``: its task, and its measured time where ``info.measured`` records one."""
    from rlpipe.scripts import cli

    assert cli.main(["presets"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()[1:]}
    assert set(lines) == set(presets.names())
    for name, (env, targets) in SIZED.items():
        assert env in lines[name] and f"{targets[0]:g}" in lines[name], lines[name]
    for name in presets.names():
        measured = dict(preset_info(name).measured)
        if measured:
            assert f"{measured['seconds']:.1f} s" in lines[name] and measured["commit"] in lines[name], lines[name]
    assert "1 then 5" in lines["crossq-minitaur"] and "not measured yet" in lines["crossq-minitaur"]
    assert "to 1" in lines["sac-minitaur"]  # a measured time says which target it is to, where it has one


def test_a_preset_file_that_records_its_measured_time_reads_back_and_a_bad_one_is_one_line(tmp_path):
    algo, cfg = resolve_preset("sac-pendulum")
    info = dataclasses.replace(preset_info("sac-pendulum"), measured=(("seconds", 9.5), ("date", "2026-12-07"),
                                                                      ("commit", "e8e6153")))
    path = presets.save(tmp_path / "mine.yaml", algo, cfg, info)
    assert preset_info(str(path)).measured == info.measured
    assert "measured: {seconds: 9.5, date: '2026-12-07', commit: e8e6153}" in path.read_text()
    path.write_text(path.read_text().replace("seconds: 9.5", "seconds: soon"))
    with pytest.raises(InputError, match=r"info\.measured\.seconds='soon': expected a mapping such as") as bad:
        resolve_preset(str(path))
    assert len(str(bad.value).splitlines()) == 1


def test_a_tutorial_preset_on_a_sized_env_trains_that_envs_sized_preset_and_says_so(tmp_path, monkeypatch, capfd):
    from rlpipe.scripts.cli import main

    monkeypatch.chdir(tmp_path)
    capfd.readouterr()
    code = main(["train", "sac", "env=Pendulum-v1", "num_iterations=20", "initial_collect_steps=50",
                 "num_eval_episodes=1", "actor_fc_layer_params=[16]", "critic_joint_fc_layer_params=[16]",
                 "--out", str(tmp_path / "run"), "--no-progress"])
    out, err = capfd.readouterr()
    assert code == 0, err
    assert "sac-pendulum" in out.splitlines()[0], out  # the run's first line names the settings it took
    assert not [line for line in err.splitlines() if line.startswith("rlpipe: hint:")], err
    saved = json.loads((tmp_path / "run" / "config.json").read_text())["config"]
    pendulum = resolve_preset("sac-pendulum")[1]
    assert (saved["policy_delay"], saved["target_update_tau"]) == (pendulum.policy_delay, pendulum.target_update_tau)
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["iterations"] == 20



def test_an_env_with_a_sized_preset_trains_its_settings_until_the_users_stop_not_the_presets_length(capfd):
    """`rlpipe train env=HalfCheetah-v5`: sac-halfcheetah-100k's learning settings, but not its 100,000 env steps (a
    benchmark's length, to its target): the sized default's ceiling of 1,000,000, ended sooner by a plateau or by the
    user's time budget, the best evaluation's policy exported. The preset by name stays as written."""
    from rlpipe.scripts.cli import main

    def keys(*args: str) -> tuple[dict[str, str], str]:
        capfd.readouterr()
        assert main(["train", *args, "--keys"]) == 0
        out, err = capfd.readouterr()
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line and not line.startswith(" ")), err

    preset = resolve_preset("sac-halfcheetah-100k")[1]
    got, err = keys("env=HalfCheetah-v5")
    steps = preset.initial_collect_steps + int(got["num_iterations"]) * preset.collect_steps_per_iteration
    assert 999_000 <= steps <= 1_000_000 and got["replay_buffer_capacity"] == "1000000"
    assert (got["plateau"], got["keep_best"], got["actor_learning_rate"]) == ("0.5", "true", json.dumps(
        preset.actor_learning_rate))
    assert "'sac-halfcheetah-100k'" in err and "until a plateau" in err and "1,000,000 env steps" in err
    budgeted, err = keys("env=HalfCheetah-v5", "time_budget=10m")
    assert budgeted["plateau"] == "0.0" and budgeted["num_iterations"] == got["num_iterations"]
    assert "until the time budget 10m" in err
    as_named, _ = keys("sac-halfcheetah-100k")
    assert int(as_named["num_iterations"]) == preset.num_iterations

def test_a_sized_preset_on_an_env_no_preset_knows_gets_the_keys_that_size_a_run(capfd):
    from rlpipe.scripts.cli import main

    capfd.readouterr()
    assert main(["train", "sac-pendulum", "env=MountainCarContinuous-v0", "--keys"]) == 0
    out, err = capfd.readouterr()
    assert 'env="MountainCarContinuous-v0"\n    [command line] ' in out
    assert "\n    [preset sac-pendulum] " in out  # where the values came from: the preset as written, not sized
    hints = [line for line in err.splitlines() if line.startswith("rlpipe: hint:")]
    assert len(hints) == 1, hints
    for key in ("actor_fc_layer_params", "critic_joint_fc_layer_params", "initial_collect_steps", "collector.sync",
                "rlpipe train sac env=MountainCarContinuous-v0"):
        assert key in hints[0]
    # the command the hint names: sized for the env, and --keys says so beside each value the rule set
    assert main(["train", "sac", "env=MountainCarContinuous-v0", "seed=3", "--keys"]) == 0
    out = capfd.readouterr().out
    assert "\nseed=3\n    [command line] " in out and "\ngamma=0.99\n    [default] " in out
    assert "\n    [sized for MountainCarContinuous-v0 (pipelines/sizing.py)] " in out


def test_no_hint_on_the_presets_own_env():
    for name in presets.names():
        assert size_hint(name, resolve_preset(name)[1]) is None, name
    cfg = apply_overrides(resolve_preset("dqn")[1], ["env=CartPole-v1"])
    assert "rlpipe train dqn-cartpole-v1-fast" in size_hint("dqn", cfg)


def test_a_gpu_run_whose_policy_acts_on_the_gpu_is_told_the_faster_collector_keys():
    cfg = resolve_preset("sac-halfcheetah")[1]
    assert device_hint(cfg) is None  # on the CPU: nothing to say
    on_gpu = dataclasses.replace(cfg, device="cuda")
    hint = device_hint(on_gpu)
    for key in ("collector.policy_device=cpu", "collector.sync=false", "collector.frames_per_batch=32"):
        assert key in hint
    cpu_copy = dataclasses.replace(on_gpu, collector=dataclasses.replace(cfg.collector, policy_device="cpu"))
    assert device_hint(cpu_copy) is None  # already acting from a CPU copy


def test_a_sized_preset_starts_training_without_the_untrained_evaluation(tmp_path):
    algo, cfg = resolve_preset("sac-pendulum")
    cfg = apply_overrides(cfg, ["num_iterations=20", "initial_collect_steps=50", "eval_interval=20",
                                "num_eval_episodes=1", "log_interval=10"])
    pipeline_class(algo)(cfg).train(tmp_path / "run", progress=False)
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    evaluated = [int(r["step"]) for r in rows if r["average_return"]]
    assert evaluated == [20], evaluated  # the tutorials' step-0 evaluation is skipped, the last one kept
    assert not (tmp_path / "run" / "baseline.json").exists()


@pytest.mark.slow
def test_sac_pendulum_learns_within_a_few_thousand_steps(tmp_path, play):
    # ~3,400-4,200 env steps reach -200 in the tries (BENCHMARKS.md); -400 on a 10-episode greedy
    # evaluation at 4,000 updates (9,000 env steps: 2 a update) leaves room for seeds that are slower.
    # Also SAC's own checks: the temperature is learned, and the exported (deterministic) policy acts as well
    # in gymnasium's own env.
    algo, cfg = resolve_preset("sac-pendulum")
    cfg = apply_overrides(cfg, ["num_iterations=4000", "eval_interval=4000"])
    result = pipeline_class(algo)(cfg).train(tmp_path / "run", progress=False)
    assert result.summary["final_average_return"] > -400, result.summary
    alphas = [float(r["loss_alpha_value"]) for r in result.metrics if r.get("loss_alpha_value")]
    assert alphas and abs(alphas[-1] - cfg.initial_alpha) > 0.1 * cfg.initial_alpha, (cfg.initial_alpha, alphas[-3:])
    returns = play(tmp_path / "run" / "policy" / "policy.pt2", "Pendulum-v1", 3, seed=200)  # actions within [-2, 2]
    assert sum(returns) / 3 > -600, returns


# --- presets as files: presets/NAME.yaml, a user's own file, `rlpipe presets --show`, `rlpipe train my.yaml` ---

SNAPSHOT = Path(__file__).parent / "data" / "presets_resolved.json"
"""every preset's algo, config (``dataclasses.asdict``) and info as the Python preset functions made them, taken
before the presets became files"""
BENCHMARKS = Path(__file__).resolve().parents[1] / "BENCHMARKS.md"


def _with_defaults(defaults, snapshot):
    """``snapshot`` with a key added to the config since it was taken at its default (a group's keys too)."""
    if not (isinstance(defaults, dict) and isinstance(snapshot, dict)):
        return snapshot
    return {**{key: _with_defaults(value, snapshot[key]) if key in snapshot else value for key, value in defaults.items()},
            **{key: value for key, value in snapshot.items() if key not in defaults}}


def test_each_preset_file_resolves_to_the_settings_it_had_as_python():
    snapshot = json.loads(SNAPSHOT.read_text())
    assert set(snapshot) <= set(presets.names())  # none lost (a preset added since has no snapshot)
    for name, before in snapshot.items():
        algo, cfg = resolve_preset(name)
        as_data = json.loads(json.dumps(dataclasses.asdict(cfg)))
        defaults = json.loads(json.dumps(dataclasses.asdict(type(cfg)())))
        assert algo == before["algo"], name
        assert as_data == _with_defaults(defaults, before["config"]), name
        info = {k: v for k, v in dataclasses.asdict(preset_info(name)).items() if k != "measured"}  # a record, no setting
        assert json.loads(json.dumps(info)) == before["info"], name
        assert pipeline_class(algo).preset(name) == cfg and name in pipeline_class(algo).presets


def test_each_preset_file_says_what_it_is_for_and_where_its_figures_are():
    lines = BENCHMARKS.read_text().splitlines()
    headings = [line.lstrip("#").strip() for line in lines if line.startswith("#")]
    notes = lines[lines.index("## Preset tuning notes"):]
    noted = " ".join(line for line in notes if line.startswith("### "))
    before = json.loads(SNAPSHOT.read_text())
    for name in presets.names():
        first = presets.text(name).splitlines()[0]
        assert first.startswith(f"# {name}: "), first
        figures = re.search(r'figures: BENCHMARKS\.md, "(.+)"$', first)
        assert figures or first.endswith("not timed here"), first
        if figures:
            assert any(h.startswith(figures.group(1)) for h in headings), f"{name}: no heading {figures.group(1)!r}"
        if name in before:  # the presets whose tuning notes moved from the code
            assert re.search(rf"(### |and ){re.escape(name)}( |$)", noted), f"no tuning notes for {name}"


def test_a_preset_of_your_own_round_trips_through_save_and_load(tmp_path):
    algo, cfg = resolve_preset("sac-pendulum")
    mine = apply_overrides(cfg, ["env=InvertedPendulum-v5", "actor_fc_layer_params=[32,32]", "target_entropy=-0.5",
                                 "actor_learning_rate=1e-05", "collector.frames_per_batch=8"])
    info = PresetInfo("InvertedPendulum-v5", (900.0,), "sized for time to 900", sized=True)
    path = presets.save(tmp_path / "runs" / "mine.yaml", algo, mine, info=info, comment="mine: my tries\nseed 3")
    assert presets.load(path) == (algo, mine) and presets.load(str(path)) == (algo, mine)
    assert presets.info(path) == info and preset_info(str(path)) == info
    text = path.read_text()
    assert text.startswith("# mine: my tries\n# seed 3\nalgo: sac\n"), text
    written = yaml.safe_load(text)["config"]  # only what differs from SACConfig's defaults, a group as a mapping
    assert written["collector"] == {"frames_per_batch": 8} and written["actor_fc_layer_params"] == [32, 32]
    assert written["actor_learning_rate"] == 1e-05 and "batch_size" not in written and "seed" not in written
    plain = presets.save(tmp_path / "plain.yaml", "td3", pipeline_class("td3").Config())
    assert yaml.safe_load(plain.read_text()) == {"algo": "td3", "config": {}}
    assert presets.load(plain) == ("td3", pipeline_class("td3").Config()) and presets.info(plain) is None


def test_rlpipe_presets_show_prints_the_file_and_a_copy_of_it_is_the_preset(tmp_path, capsys):
    from rlpipe.scripts.cli import main

    assert main(["presets", "--show", "td3-pendulum"]) == 0
    shown = capsys.readouterr().out
    assert shown == presets.text("td3-pendulum") and shown.startswith("# td3-pendulum: ")
    (tmp_path / "copy.yaml").write_text(shown)
    assert presets.load(tmp_path / "copy.yaml") == resolve_preset("td3-pendulum")


BAD_FILES = {
    # name: (the file's text (None: no file), words its one line names besides the file)
    "missing": (None, ["no such preset file"]),
    "not-yaml": ("algo: sac\nconfig: [1, 2\n", ["not valid YAML", "line 3"]),
    "a-list": ("- algo: sac\n", ["list", "mapping"]),
    "unknown-algo": ("algo: ppo\n", ["ppo", "sac"]),
    "no-algo": ("config: {batch_size: 3}\n", ["algo", "sac"]),
    "top-level-config-key": ("algo: sac\nbatch_size: 3\n", ["'batch_size'", "config:"]),
    "unknown-key": ("algo: dqn\nconfig:\n  batchsize: 3\n", ["batchsize", "batch_size"]),
    "unknown-group-key": ("algo: td3\nconfig:\n  collector: {workerz: 2}\n", ["collector.workerz", "collector.workers"]),
    "group-not-a-mapping": ("algo: td3\nconfig:\n  collector: 2\n", ["collector=2", "mapping"]),
    "ill-typed": ("algo: dqn\nconfig:\n  batch_size: abc\n", ["batch_size", "integer"]),
    "zero-batch": ("algo: dqn\nconfig:\n  batch_size: 0\n", ["batch_size=0", "positive"]),
    "key-twice": ("algo: dqn\nconfig:\n  batch_size: 3\n  batch_size: 4\n", ["batch_size", "twice"]),
    "bad-info": ("algo: dqn\ninfo: {env: CartPole-v0, targets: high}\n", ["info.targets", "list"]),
}
SAME_AS_OVERRIDE = {"unknown-key": "batchsize=3", "ill-typed": "batch_size=abc", "zero-batch": "batch_size=0"}


@pytest.mark.parametrize("name", list(BAD_FILES))
def test_a_bad_preset_file_is_one_line_naming_it_and_exit_2(name, tmp_path, monkeypatch, capfd):
    from rlpipe.scripts.cli import main

    monkeypatch.chdir(tmp_path)
    text, words = BAD_FILES[name]
    if text is not None:
        (tmp_path / "mine.yaml").write_text(text)
    capfd.readouterr()
    for argv in (["train", "mine.yaml", "--out", "new"], ["train", "mine.yaml", "--keys"], ["presets", "--show", "mine.yaml"]):
        code = main(argv)
        lines = capfd.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1, (argv, lines)
        assert lines[0].startswith("rlpipe: error: mine.yaml: "), lines[0]
        for word in words:
            assert word in lines[0], (word, lines[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ([] if text is None else ["mine.yaml"])  # nothing written
    if name in SAME_AS_OVERRIDE:  # the line the same key=value on the command line gets
        assert main(["train", "dqn", SAME_AS_OVERRIDE[name], "--out", "new"]) == 2
        assert lines[0].replace("mine.yaml: ", "") == capfd.readouterr().err.strip()


def test_rlpipe_train_a_preset_file_with_overrides_on_top(tmp_path, monkeypatch, capfd):
    from rlpipe.scripts.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "tiny.yaml").write_text(
        "# tiny: Pendulum-v1 in a few iterations\n"
        "algo: sac\n"
        "config:\n"
        "  env: Pendulum-v1\n"
        "  num_iterations: 20\n"
        "  initial_collect_steps: 50\n"
        "  actor_fc_layer_params: [16]\n"
        "  critic_joint_fc_layer_params: [16]\n"
        "  actor_learning_rate: 2e-3\n"
        "  num_eval_episodes: 1\n"
        "  initial_eval: false\n"
        "  baseline_episodes: 0\n"
        "  eval_in_background: false\n"
        "  live_report: false\n"
        "  num_threads: 1\n"
        "  collector: {workers: 1, sync: true}\n")
    capfd.readouterr()
    assert main(["train", "tiny.yaml", "num_iterations=30", "--keys"]) == 0
    keys = capfd.readouterr().out
    assert "num_iterations=30\n" in keys and "actor_fc_layer_params=[16]\n" in keys and "actor_learning_rate=0.002\n" in keys
    code = main(["train", "tiny.yaml", "num_iterations=30", "--out", "run", "--no-progress"])
    err = capfd.readouterr().err
    assert code == 0, err
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["algo"] == "sac" and saved["config"]["critic_joint_fc_layer_params"] == [16], saved
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["iterations"] == 30


def test_rlpipe_train_a_bad_preset_file_as_a_process_exits_2_with_one_line(tmp_path):
    (tmp_path / "mine.yaml").write_text("algo: td3\nconfig:\n  collector: {workerz: 2}\n")
    rlpipe = Path(sys.executable).parent / "rlpipe"
    proc = subprocess.run([str(rlpipe), "train", "mine.yaml", "--out", "new"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        "rlpipe: error: mine.yaml: unknown config key 'collector.workerz'; closest valid keys: collector.workers, "
        "collector.envs_per_worker, collector.direct"], proc.stderr
    assert not (tmp_path / "new").exists()
