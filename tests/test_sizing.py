"""The sized default (pipelines/sizing.py): the rule as a function of an env's facts, the facts measured the same
way every time, `rlpipe train env=ID` choosing the algorithm and saying what it chose, and the development suite
in `rlpipe bench time-to-return`."""

from __future__ import annotations

import dataclasses
import json

import pytest

from rlpipe.pipelines import resolve_preset
from rlpipe.pipelines.config import TrainConfig, apply_overrides, validate
from rlpipe.pipelines.sizing import EnvFacts, measure, resolve_for_env, run_length, sized_config
from rlpipe.scripts.bench import time_to_return as ttr

REACHER = EnvFacts("Reacher-v5", False, 10, 2, (-1.0, -1.0), (1.0, 1.0), 50, -42.7, 50.0, 2)
CHEETAH = EnvFacts("HalfCheetah-v5", False, 17, 6, (-1.0,) * 6, (1.0,) * 6, 1000, -300.0, 1000.0, 2)
IDP = EnvFacts("InvertedDoublePendulum-v5", False, 9, 1, (-1.0,), (1.0,), 1000, 70.0, 7.0, 2)
ACROBOT = EnvFacts("Acrobot-v1", True, 6, 3, (), (), 500, -500.0, 500.0, 2)
# what `rlpipe train` runs in these tests: a few updates, nothing else
TINY = ["num_iterations=20", "initial_collect_steps=50", "num_eval_episodes=1", "eval_interval=0", "log_interval=10",
        "batch_size=16", "--no-progress"]


@pytest.mark.unit
def test_the_rule_sizes_a_small_body_in_the_learners_process_with_the_pendulum_presets_rates_for_one_actuator():
    pendulum, _ = sized_config("sac", IDP)
    assert (pendulum.actor_learning_rate, pendulum.target_update_tau, pendulum.policy_delay) == (2e-3, 0.02, 2)
    assert (sized_config("td3", IDP)[0].learning_rate, sized_config("td3", REACHER)[0].learning_rate) == (2e-3, 1e-3)
    cfg, line = sized_config("sac", REACHER)
    assert cfg.actor_fc_layer_params == cfg.critic_joint_fc_layer_params == [64, 64]
    # two actuators: HalfCheetah's learning settings, in the learner's process
    assert (cfg.actor_learning_rate, cfg.target_update_tau, cfg.policy_delay, cfg.target_entropy) == (1e-3, 0.005, 1, -2.0)
    assert cfg.initial_collect_steps == 1000  # five random episodes are 250 steps: at least 1,000
    assert cfg.initial_collect_steps + 2 * cfg.num_iterations == cfg.replay_buffer_capacity == 50_000
    assert (cfg.collector.workers, cfg.collector.sync, cfg.num_threads) == (1, True, 1)
    validate(cfg)
    for said in ("Reacher-v5", "obs 10", "act 2 in [-1, 1]", "50-step episodes", "-42.7", "64x64",
                 "1,000 random steps", "env in the learner's process"):
        assert said in line, (said, line)


@pytest.mark.unit
def test_the_rule_puts_a_many_jointed_body_in_a_collector_process_only_where_there_is_a_second_cpu():
    cfg, line = sized_config("sac", CHEETAH)
    assert (cfg.collector.workers, cfg.collector.sync) == (1, False) and "collector process" in line
    assert (cfg.actor_learning_rate, cfg.target_update_tau, cfg.target_entropy) == (1e-3, 0.005, -6.0)
    assert cfg.initial_collect_steps == 5000  # five 1,000-step random episodes
    one_cpu, line = sized_config("sac", dataclasses.replace(CHEETAH, cpus=1))
    assert one_cpu.collector.sync and "learner's process" in line
    td3, _ = sized_config("td3", CHEETAH)
    assert (td3.learning_rate, td3.target_update_tau, td3.learning_starts) == (1e-3, 0.005, 5000)


@pytest.mark.unit
def test_the_rule_discounts_by_0999_only_where_the_random_agent_plays_long_episodes_to_their_limit():
    swimmer = EnvFacts("Swimmer-v5", False, 8, 2, (-1.0, -1.0), (1.0, 1.0), 1000, -3.4, 1000.0, 2)
    for algo in ("sac", "td3"):
        cfg, line = sized_config(algo, swimmer)
        assert cfg.gamma == 0.999 and "gamma 0.999 (random episodes run to the 1,000-step limit)" in line
        # an episode the random agent ends early (it falls), a short time limit: the usual 0.99, not said
        for facts in (IDP, REACHER, dataclasses.replace(swimmer, random_episode_length=950.0)):
            cfg, line = sized_config(algo, facts)
            assert cfg.gamma == 0.99 and "gamma" not in line, facts.env
    assert sized_config("dqn", dataclasses.replace(ACROBOT, time_limit=1000, random_episode_length=1000.0))[0].gamma == 0.99


@pytest.mark.unit
def test_sac_updates_every_second_env_step_unless_the_random_agent_plays_long_episodes_to_their_limit():
    swimmer = EnvFacts("Swimmer-v5", False, 8, 2, (-1.0, -1.0), (1.0, 1.0), 1000, -3.4, 1000.0, 2)
    for facts, per_update in ((IDP, 2), (REACHER, 2), (swimmer, 1), (CHEETAH, 1)):
        cfg, line = sized_config("sac", facts)
        assert cfg.collect_steps_per_iteration == per_update, facts.env
        said = "an update every 2 env steps" if per_update == 2 else "an update every env step"
        assert said in line, (said, line)
        # the random steps and the budget are in env steps, whatever the ratio
        assert cfg.initial_collect_steps + cfg.num_iterations * per_update <= cfg.replay_buffer_capacity
        assert cfg.initial_collect_steps + (cfg.num_iterations + 1) * per_update > cfg.replay_buffer_capacity
    assert sized_config("td3", IDP)[0].collect_steps_per_iteration == 1


@pytest.mark.unit
def test_sac_learns_from_3_step_returns_where_random_episodes_last_a_tenth_of_a_long_limit():
    swimmer = EnvFacts("Swimmer-v5", False, 8, 2, (-1.0, -1.0), (1.0, 1.0), 1000, -3.4, 1000.0, 2)
    lander = EnvFacts("LunarLanderContinuous-v3", False, 8, 2, (-1.0, -1.0), (1.0, 1.0), 1000, -208.6, 113.0, 2)
    hopper = EnvFacts("Hopper-v5", False, 11, 3, (-1.0,) * 3, (1.0,) * 3, 1000, 14.6, 22.0, 2)
    cases = ((swimmer, 3), (CHEETAH, 3), (lander, 3), (dataclasses.replace(swimmer, random_episode_length=950.0), 3),
             (dataclasses.replace(lander, random_episode_length=99.0), 1), (IDP, 1), (hopper, 1), (REACHER, 1),
             (dataclasses.replace(lander, time_limit=999), 1))
    for facts, n_step in cases:
        cfg, line = sized_config("sac", facts)
        assert cfg.n_step == n_step, facts
        assert ("3-step returns" in line) == (n_step == 3), line
    # the lander keeps what its short random episodes give it otherwise: gamma 0.99, an update every 2 env steps
    cfg, _ = sized_config("sac", lander)
    assert (cfg.gamma, cfg.collect_steps_per_iteration) == (0.99, 2)
    assert sized_config("td3", swimmer)[0].n_step == 1 and sized_config("dqn", ACROBOT)[0].n_step == 1
    assert sized_config("td3", lander)[0].n_step == 1


@pytest.mark.unit
def test_the_rule_is_a_function_of_the_facts_alone():
    for algo, facts in (("sac", REACHER), ("td3", REACHER), ("sac", CHEETAH), ("dqn", ACROBOT)):
        assert sized_config(algo, facts) == sized_config(algo, facts)
    dqn, line = sized_config("dqn", ACROBOT)
    assert (dqn.fc_layer_params, dqn.learning_rate, dqn.epsilon_greedy_end, dqn.target_update_period) == (
        [64, 64], 2.3e-3, 0.04, 20)
    assert dqn.initial_collect_steps == 2500 and "3 actions" in line
    assert dqn.collect_steps_per_iteration == 4 and dqn.num_iterations * 4 + 2500 <= 500_000
    assert dqn.epsilon_decay_steps == 5000  # a tenth of 100 episodes, not of the ceiling


@pytest.mark.unit
def test_the_run_goes_on_past_100_episodes_to_a_plateau_or_a_ceiling_of_1000_episodes_and_exports_its_best():
    hopper = EnvFacts("Hopper-v5", False, 11, 3, (-1.0,) * 3, (1.0,) * 3, 1000, 14.6, 22.0, 2)
    for facts, ceiling in ((CHEETAH, 1_000_000), (hopper, 1_000_000), (REACHER, 50_000), (IDP, 1_000_000),
                           (dataclasses.replace(REACHER, time_limit=200), 200_000)):
        cfg, line = sized_config("sac", facts)
        per_update = cfg.collect_steps_per_iteration
        assert cfg.replay_buffer_capacity == ceiling, facts
        assert cfg.initial_collect_steps + cfg.num_iterations * per_update <= ceiling
        assert (cfg.plateau, cfg.keep_best) == (0.5, True)
        # a plateau ends it only after the 100 episodes the schedules are sized to (no sooner than before)
        horizon = min(1_000_000, max(50_000, 100 * facts.time_limit))
        assert cfg.plateau_min_iterations * per_update + cfg.initial_collect_steps == horizon
        assert 1000 <= cfg.eval_interval and cfg.eval_interval * per_update <= 10_000
        assert f"until a plateau (no better greedy evaluation over the last 50% of the run) or {ceiling:,} env steps" in line
    validate(sized_config("sac", CHEETAH)[0])


def test_a_time_budget_is_the_runs_length_no_plateau_ends_it_sooner():
    resolved = resolve_for_env("env=Reacher-v5", ["time_budget=10m"])
    cfg = apply_overrides(resolved.config, resolved.overrides)
    assert (cfg.plateau, cfg.keep_best, cfg.time_budget) == (0.0, True, "10m")
    assert "until the time budget 10m or 50,000 env steps (no plateau stop" in resolved.lines[-1]
    # the user's own plateau= still wins; no budget (or time_budget=null): the plateau rule
    resolved = resolve_for_env("env=Reacher-v5", ["time_budget=10m", "plateau=0.3"])
    assert apply_overrides(resolved.config, resolved.overrides).plateau == 0.3
    for off in ([], ["time_budget=null"]):
        assert resolve_for_env("env=Reacher-v5", off).config.plateau == 0.5


def test_the_facts_are_measured_the_same_way_every_time():
    cfg = apply_overrides(TrainConfig(), ["env=Reacher-v5"])
    first, second = measure(cfg), measure(cfg)
    assert first == second  # the random agent is seeded apart from any run
    assert (first.observation_size, first.action_size, first.time_limit, first.discrete) == (10, 2, 50, False)
    assert first.random_episode_length == 50 and first.random_return < 0


def test_a_tutorial_preset_on_its_own_env_stays_the_tutorial():
    assert resolve_for_env("sac", ["seed=3"]) is None
    assert resolve_for_env("sac", ["env=MinitaurBulletEnv-v0"]) is None
    assert resolve_for_env("sac", ["env=rlpipe/MinitaurBullet-v0"]) is None  # the same env by its registered id
    assert resolve_for_env("sac-pendulum", ["env=Reacher-v5"]) is None  # a sized preset named: as named
    assert resolve_for_env("td3", ["env=Pendulum-v1"]) is None  # the TD3 tutorial's own env
    cartpole = resolve_for_env("dqn", ["env=CartPole-v1"])  # the env's sized preset of that algorithm: its settings,
    preset = resolve_preset("dqn-cartpole-v1-fast")[1]  # for the sized default's length (sizing.run_length)
    length, _ = run_length(measure(preset, play=False), preset.initial_collect_steps, preset.collect_steps_per_iteration)
    assert cartpole.config == dataclasses.replace(preset, **length) and "dqn-cartpole-v1-fast" in cartpole.lines[0]
    assert cartpole.config.num_iterations > preset.num_iterations and cartpole.config.keep_best


def _train(tmp_path, capfd, *argv):
    from rlpipe.scripts.cli import main

    capfd.readouterr()
    code = main(["train", *argv, *TINY, "--out", str(tmp_path / "run")])
    out, err = capfd.readouterr()
    assert code == 0, err
    algo, saved = (lambda d: (d["algo"], d["config"]))(json.loads((tmp_path / "run" / "config.json").read_text()))
    return out.splitlines(), algo, saved


def test_train_env_with_discrete_actions_picks_dqn_and_says_so_first(tmp_path, monkeypatch, capfd):
    monkeypatch.chdir(tmp_path)
    lines, algo, saved = _train(tmp_path, capfd, "env=Acrobot-v1")
    assert algo == "dqn"
    assert lines[0].startswith("rlpipe: training DQN: Acrobot-v1 has a Discrete(3) action space"), lines[:2]
    assert lines[1].startswith("rlpipe: sized for Acrobot-v1: obs 6, 3 actions, 500-step episodes"), lines[:2]
    sized, _ = sized_config("dqn", measure(apply_overrides(TrainConfig(), ["env=Acrobot-v1"])))
    assert saved["learning_rate"] == sized.learning_rate and saved["fc_layer_params"] == sized.fc_layer_params
    assert saved["num_iterations"] == 20  # the command's keys over the sized ones


def test_train_env_with_box_actions_picks_sac_sized_for_the_env(tmp_path, monkeypatch, capfd):
    monkeypatch.chdir(tmp_path)
    lines, algo, saved = _train(tmp_path, capfd, "env=InvertedDoublePendulum-v5")
    assert algo == "sac"
    assert lines[0].startswith("rlpipe: training SAC: InvertedDoublePendulum-v5 has a Box(1) action space"), lines[:2]
    assert "sized for InvertedDoublePendulum-v5: obs 9, act 1" in lines[1], lines[:2]
    assert (saved["actor_fc_layer_params"], saved["target_update_tau"], saved["policy_delay"]) == ([64, 64], 0.02, 2)


@pytest.mark.unit
def test_the_bench_takes_the_development_suite_and_plays_the_sized_default_there():
    assert set(ttr.DEV_SUITE) <= set(ttr.TASKS)
    for name in ttr.DEV_SUITE:
        task = ttr.TASKS[name]
        assert not task.preset and task.fallback == (task.algo, (f"env={task.env}",)), name
        assert set(task.peers) == {"sb3", "sbx", "torchrl"}
    assert {ttr.TASKS[n].env for n in ttr.DEV_SUITE} == {"Reacher-v5", "Swimmer-v5", "InvertedDoublePendulum-v5",
                                                         "LunarLanderContinuous-v3", "Acrobot-v1"}


def test_the_bench_launches_the_sized_default_with_a_cap_from_its_random_steps(tmp_path):
    from rlpipe.scripts.cli import _parser

    args = _parser().parse_args(["bench", "time-to-return", "--tasks", "reacher-sac", "acrobot-dqn", "--seeds", "2", "--seed", "100",
                                 "--peers", "sbx"])
    ttr.check_args(args)  # the rlpipe side's config for each task resolves before any run
    task = ttr.TASKS["reacher-sac"]
    launch = ttr.rlpipe_launch(task, "rlpipe", 100, task.target, 10_000, tmp_path / "run", None, [])
    assert launch.cmd[launch.cmd.index("train") + 1:][:2] == ["sac", "env=Reacher-v5"]
    assert "num_iterations=4500" in launch.cmd  # 10,000 less the sized default's 1,000 random steps, two env steps an update
    assert "sized from the env" in launch.settings


@pytest.mark.unit
def test_a_goal_env_is_normalised_as_rl_zoos_fetch_unless_an_image_is_among_its_entries():
    fetch = EnvFacts("FetchReach-v4", False, 16, 4, (-1.0,) * 4, (1.0,) * 4, 50, -48.6, 50.0, 2, (16,), True)
    cfg, line = sized_config("sac", fetch)
    assert cfg.normalize_observations and "observations normalised" in line and "HER" in line
    camera = dataclasses.replace(fetch, observation_size=16 + 3 * 40 * 40, observation_shape=(16 + 3 * 40 * 40,),
                                 entry_images=(("camera", (3, 40, 40)),))
    cfg, line = sized_config("sac", camera)
    assert not cfg.normalize_observations and "observations normalised" not in line
    assert "image 'camera' 3x40x40 through a CNN" in line and "HER" in line
    validate(cfg)
