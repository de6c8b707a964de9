"""The plug-in story: a TorchRL user's own parts in each pipeline, written as a user would write them.

Every case runs for DQN (CartPole-v1), TD3, SAC and CrossQ (Pendulum-v1) with small networks: foreign and
plain TorchRL envs (no ``RewardSum``), an observation under another key, env instances, batched
envs, the user's networks and losses, a TorchRL logger, callbacks, a custom trigger, rlpipe's
parts in a hand-written loop, the exported policy in a fresh process, and resume from Python.
"""

from __future__ import annotations

import csv
import functools
import json
import os
import signal
import subprocess
import sys

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import CatTensors, GymEnv, SerialEnv, TransformedEnv
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import CrossQLoss, DQNLoss, SACLoss, TD3Loss
from torchrl.record.loggers import CSVLogger

from rlpipe import pipelines
from rlpipe.modules import make_qvalue_actor
from rlpipe.pipelines import crossq, dqn, sac, td3
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.training.triggers import EVAL, IntervalTrigger, Trigger

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

ALGOS = ["dqn", "td3", "sac", "crossq"]
# The env, trigger, logger and thread plumbing: crossq's is sac's (CrossQ subclasses SAC); what crossq
# has of its own (networks, loss, update, export) is checked with ALGOS.
PLUMBING = ["dqn", "td3", "sac"]
ENV = {"dqn": "CartPole-v1", "td3": "Pendulum-v1", "sac": "Pendulum-v1", "crossq": "Pendulum-v1"}
PIPELINE = {"dqn": dqn.DQN, "td3": td3.TD3, "sac": sac.SAC, "crossq": crossq.CrossQ}
SMALL = {
    "dqn": ["fc_layer_params=[16]"],
    "td3": ["actor_fc_layer_params=[16]", "critic_fc_layer_params=[16]"],
    "sac": ["actor_fc_layer_params=[16]", "critic_joint_fc_layer_params=[16]"],
    "crossq": ["actor_fc_layer_params=[16]", "critic_fc_layer_params=[16]"],
}
SHORT = [
    "batch_size=16", "num_iterations=100", "initial_collect_steps=50", "learning_starts=50", "eval_interval=0",
    "num_eval_episodes=1", "log_interval=50", "checkpoint_interval=1000", "policy_save_interval=1000",
    "collector.sync=true", "collector.workers=1", "eval_in_background=false",
]


def config(algo: str, *overrides: str):
    return apply_overrides(PIPELINE[algo].preset(), [f"env={ENV[algo]}", *SMALL[algo], *SHORT, *overrides])


def plain_env(algo: str):
    """A TorchRL env with no transforms at all: no RewardSum, no StepCounter, no InitTracker."""
    return GymEnv(ENV[algo])


def make_plain(algo: str):
    """The same, with integer-index actions for CartPole (the users' networks below are built for them)."""
    return GymEnv(ENV[algo], categorical_action_encoding=True) if algo == "dqn" else GymEnv(ENV[algo])


def obs_dim(algo: str) -> int:
    return {"dqn": 4, "td3": 3, "sac": 3, "crossq": 3}[algo]


def changed(before: dict, module: nn.Module) -> bool:
    return any(not torch.equal(before[k], v) for k, v in module.state_dict().items())


def snapshot(module: nn.Module) -> dict:
    return {k: v.clone() for k, v in module.state_dict().items()}


# --- envs ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("algo", PLUMBING)
def test_a_plain_torchrl_env_without_reward_sum_trains_and_labels_the_run(algo, tmp_path):
    cfg = config(algo, "num_iterations=200")  # 250 steps: a Pendulum episode (200 steps) ends too
    result = PIPELINE[algo](cfg, env=functools.partial(plain_env, algo)).train(tmp_path / "run", progress=False)
    assert result.summary["updates"] == 200
    # the training episodes' returns are logged though the env has no RewardSum
    assert any(row["train_episode_return"] for row in result.metrics)
    # the run is labelled with the env used, not the config's default env
    assert result.summary["env"] == ENV[algo]
    assert json.loads((result.run_dir / "config.json").read_text())["config"]["env"] == ENV[algo]


@pytest.mark.parametrize("algo", PLUMBING)
def test_env_instances_train_with_an_eval_env_and_are_refused_without_one(algo, tmp_path):
    with pytest.raises(InputError, match="eval_env"):
        PIPELINE[algo](config(algo), env=plain_env(algo))
    pipeline = PIPELINE[algo](config(algo), env=plain_env(algo), eval_env=plain_env(algo))
    assert pipeline.train(tmp_path / "run", progress=False).summary["updates"] == 100


def vector_env(algo: str):
    """The observation under another key, as after ``CatTensors``: ``"observation_vector"``."""
    return TransformedEnv(make_plain(algo), CatTensors(in_keys=["observation"], out_key="observation_vector"))


@pytest.mark.parametrize("algo", PLUMBING)
def test_an_observation_under_another_key_is_read_where_the_user_says(algo, tmp_path):
    make = functools.partial(vector_env, algo)
    with pytest.raises(InputError, match="observation_key"):
        PIPELINE[algo](config(algo), env=make, observation_key="pixels")
    pipeline = PIPELINE[algo](config(algo), env=make, observation_key="observation_vector")
    assert pipeline.policy.in_keys == ["observation_vector"]
    result = pipeline.train(tmp_path / "run", progress=False)
    info = json.loads((result.run_dir / "policy" / "policy.json").read_text())
    assert info["observation_key"] == "observation_vector" and info["observation_dim"] == obs_dim(algo)


@pytest.mark.parametrize("algo", PLUMBING)
def test_the_observation_key_is_taken_from_the_users_actor(algo, tmp_path):
    actor = users_actor(algo, key="observation_vector")
    pipeline = PIPELINE[algo](config(algo), env=functools.partial(vector_env, algo), actor=actor)
    assert pipeline.observation_key == "observation_vector" and pipeline.policy is actor
    assert pipeline.train(tmp_path / "run", progress=False).summary["updates"] == 100


@pytest.mark.parametrize("algo", PLUMBING)
def test_a_batched_env_trains_and_evaluates_every_sub_env(algo, tmp_path):
    make = functools.partial(SerialEnv, 2, functools.partial(GymEnv, ENV[algo]))
    cfg = config(algo, "num_eval_episodes=3", "eval_interval=50")
    result = PIPELINE[algo](cfg, env=make).train(tmp_path / "run", progress=False)
    assert result.summary["updates"] == 100 and result.summary["frames"] == 150
    assert result.summary["env"] == ENV[algo]
    assert [e["step"] for e in result.evaluations] == [0, 50, 100]
    assert all(len(e["returns"]) == 3 for e in result.evaluations)


# --- the user's networks and losses -------------------------------------------------------------------


def users_actor(algo: str, key: str = "observation") -> nn.Module:
    """An actor built from TorchRL parts by hand, as a user would (not with rlpipe's factories)."""
    spec = make_plain(algo).action_spec
    n_in = obs_dim(algo)
    if algo == "dqn":
        return make_qvalue_actor(n_in, spec, hidden_sizes=[8], observation_key=key)
    if algo == "td3":
        net = nn.Sequential(nn.Linear(n_in, 8), nn.ReLU(), nn.Linear(8, 1), nn.Tanh())
        scale = float(spec.space.high)

        class Scaled(nn.Module):
            def __init__(self):
                super().__init__()
                self.net = net

            def forward(self, x):
                return scale * self.net(x)

        return TensorDictModule(Scaled(), in_keys=[key], out_keys=["action"])
    net = TensorDictModule(nn.Sequential(MLP(in_features=n_in, out_features=2, num_cells=[8]),
                                         _LocScale()), in_keys=[key], out_keys=["loc", "scale"])
    return ProbabilisticActor(net, in_keys=["loc", "scale"], spec=spec, distribution_class=TanhNormal,
                              distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
                              return_log_prob=True)


class _LocScale(nn.Module):
    def forward(self, x):
        loc, scale = x.chunk(2, -1)
        return loc, nn.functional.softplus(scale) + 1e-3


def users_critic(algo: str) -> nn.Module:
    return ValueOperator(MLP(in_features=obs_dim(algo) + 1, out_features=1, num_cells=[8]),
                         in_keys=["observation", "action"])


@pytest.mark.parametrize("algo", ALGOS)
def test_the_users_networks_are_trained_evaluated_and_exported(algo, tmp_path):
    actor = users_actor(algo)
    kwargs = {"actor": actor} if algo == "dqn" else {"actor": actor, "qvalue": users_critic(algo)}
    before = snapshot(actor)
    pipeline = PIPELINE[algo](config(algo), env=functools.partial(make_plain, algo), **kwargs)
    result = pipeline.train(tmp_path / "run", progress=False)
    assert result.policy is actor and changed(before, actor), "the user's actor was not trained"
    if algo != "dqn":
        assert pipeline.loss_module.qvalue_network_params["module", "0", "weight"].shape == (2, 8, obs_dim(algo) + 1)
    # the exported policy acts as the user's actor does (deterministically)
    exported = torch.export.load(str(result.run_dir / "policy" / "policy.pt2")).module()
    obs = torch.randn(5, obs_dim(algo))
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = actor(TensorDict(observation=obs, batch_size=[5]))["action"]
    torch.testing.assert_close(exported(obs), expected)


def test_dqn_takes_a_bare_q_network(tmp_path):
    qnet = MLP(in_features=4, out_features=2, num_cells=[8])
    before = snapshot(qnet)
    pipeline = dqn.DQN(config("dqn"), env=functools.partial(make_plain, "dqn"), qvalue=qnet)
    pipeline.train(tmp_path / "run", progress=False)
    assert changed(before, qnet)


def users_loss(algo: str):
    spec = make_plain(algo).action_spec
    if algo == "dqn":
        loss = DQNLoss(make_qvalue_actor(4, spec, [8]), action_space=spec, delay_value=True)
        loss.make_value_estimator(gamma=0.5)
        return loss
    if algo == "td3":
        actor = users_actor("td3")
        return TD3Loss(actor, users_critic("td3"), action_spec=spec)
    if algo == "crossq":
        return CrossQLoss(users_actor("crossq"), users_critic("crossq"), num_qvalue_nets=2)
    return SACLoss(users_actor("sac"), users_critic("sac"), num_qvalue_nets=2)


@pytest.mark.parametrize("algo", ALGOS)
def test_the_users_loss_module_is_trained_as_handed_in(algo, tmp_path):
    loss = users_loss(algo)
    gamma = loss.value_estimator.gamma if algo == "dqn" else None
    before = snapshot(loss)
    pipeline = PIPELINE[algo](config(algo), env=functools.partial(make_plain, algo), loss_module=loss)
    result = pipeline.train(tmp_path / "run", progress=False)
    assert pipeline.loss_module is loss and changed(before, loss)
    network = loss.value_network if algo == "dqn" else loss.actor_network
    assert result.policy is network  # the policy evaluated and exported is the one the loss trains
    if algo == "dqn":  # its own value estimator is kept (the config's gamma would be 0.99)
        assert loss.value_estimator.gamma == gamma == 0.5


# --- logger, callbacks, triggers, resume ---------------------------------------------------------------


@pytest.mark.parametrize("algo", PLUMBING)
def test_a_torchrl_logger_and_callbacks_see_every_row(algo, tmp_path):
    logger = CSVLogger(exp_name="mine", log_dir=str(tmp_path / "logs"))
    rows = []
    result = PIPELINE[algo](config(algo)).train(tmp_path / "run", progress=False, logger=logger, callbacks=[rows.append])
    assert [r["step"] for r in rows] == [int(r["step"]) for r in result.metrics]
    scalars = {p.stem for p in (tmp_path / "logs" / "mine" / "scalars").glob("*.csv")}
    assert {"average_return", "steps_per_s"} <= scalars
    assert not (result.run_dir / "tb").exists()  # the given logger replaces the default one


class _CtrlCAt:
    """A trigger function that records the iterations it ran at and presses Ctrl-C at one of them."""

    def __init__(self, at: int | None):
        self.at, self.seen = at, []

    def __call__(self, loop):
        self.seen.append(loop.state.iteration)
        if loop.state.iteration == self.at:
            os.kill(os.getpid(), signal.SIGINT)


@pytest.mark.parametrize("algo", PLUMBING)
def test_custom_triggers_run_on_schedule_and_what_a_ctrl_c_left_owed_runs_on_resume(algo, tmp_path):
    # two triggers due at iteration 50; the first presses Ctrl-C there: the second is still owed
    press, record = _CtrlCAt(50), _CtrlCAt(None)
    with pytest.raises(KeyboardInterrupt):
        PIPELINE[algo](config(algo)).train(tmp_path / "run", progress=False, triggers=[
            IntervalTrigger(50, press, name="press"), IntervalTrigger(50, record, name="record")])
    assert press.seen == [50] and record.seen == []
    press_again, record_again = _CtrlCAt(None), _CtrlCAt(None)
    result = PIPELINE[algo](config(algo)).train(tmp_path / "run", resume=True, progress=False, triggers=[
        IntervalTrigger(50, press_again, name="press"), IntervalTrigger(50, record_again, name="record")])
    assert press_again.seen == [100] and record_again.seen == [50, 100]  # each iteration once, in all
    assert result.summary["updates"] == 100
    assert [int(r["step"]) for r in result.metrics if r["steps_per_s"]] == [50, 100]


def test_a_key_a_users_trigger_logs_lands_in_metrics_csv_and_stays_there_on_resume(tmp_path):
    def doubled(loop):
        loop.log({"my_metric": 2 * loop.state.iteration})

    press = _CtrlCAt(50)
    with pytest.raises(KeyboardInterrupt):
        dqn.DQN(config("dqn")).train(tmp_path / "run", progress=False, triggers=[
            IntervalTrigger(50, doubled, name="doubled"), IntervalTrigger(50, press, name="press")])
    result = dqn.DQN(config("dqn")).train(tmp_path / "run", resume=True, progress=False, triggers=[
        IntervalTrigger(50, doubled, name="doubled"), IntervalTrigger(50, _CtrlCAt(None), name="press")])
    with (result.run_dir / "metrics.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["step"], r["my_metric"]) for r in rows if r["my_metric"]] == [("50", "100"), ("100", "200")]
    assert any(r["average_return"] and not r["my_metric"] for r in rows)  # the rows before it: blank there
    assert [r["my_metric"] for r in result.metrics if r["my_metric"]] == ["100", "200"]


@pytest.mark.parametrize("eval_interval", [50, 30])
def test_a_users_trigger_at_the_last_iteration_sees_that_iterations_evaluation(eval_interval, tmp_path):
    """README: user triggers run after the built-in ones; at the last iteration one once saw the evaluation before."""
    seen = []

    def note(loop):
        seen.append((loop.state.iteration, loop.evaluations[-1]["step"], loop.last_return))

    result = dqn.DQN(config("dqn", f"eval_interval={eval_interval}")).train(
        tmp_path / "run", progress=False, triggers=[IntervalTrigger(50, note, name="note")])
    last = result.evaluations[-1]
    assert last["step"] == 100 and [e["step"] for e in result.evaluations].count(100) == 1
    assert seen[-1] == (100, 100, last["average_return"])
    assert seen[0][:2] == (50, 50)  # blocks of 50 steps: an interval of 30 evaluates at 50 too


class _Moments(Trigger):
    """A user's trigger that records every moment of the run it is fired at."""

    name = "moments"

    def __init__(self):
        super().__init__(50)
        self.seen = []

    def __call__(self, loop):
        self.seen.append(("interval", loop.state.iteration))

    def start(self, loop):
        self.seen.append(("start", loop.state.iteration))

    def final(self, loop):  # after the built-in ones' final firing: the last evaluation is in
        self.seen.append(("final", loop.state.iteration, loop.evaluations[-1]["step"]))

    def close(self, loop):
        self.seen.append(("close",))


def test_a_users_trigger_is_fired_at_the_start_on_schedule_and_once_more_at_the_end(tmp_path):
    moments = _Moments()
    dqn.DQN(config("dqn")).train(tmp_path / "run", progress=False, triggers=[moments])
    assert moments.seen == [("start", 0), ("interval", 50), ("interval", 100), ("final", 100, 100), ("close",)]


def test_the_pipelines_thread_choice_answers():
    pipeline = dqn.DQN(config("dqn"))
    assert pipeline.choose_threads() >= 1


@pytest.mark.parametrize("omp, cap", [("1", 1), ("2", 2), ("0", None), ("many", None), (None, None)])
def test_omp_num_threads_caps_the_threads_a_run_chooses(monkeypatch, omp, cap):
    from rlpipe.pipelines.training.threads import omp_threads

    if omp is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", omp)
    assert omp_threads() == cap
    if cap == 1:  # a user's one thread is kept, whatever a timing would have picked
        assert td3.TD3(config("td3")).choose_threads() == 1


def test_trigger_names_must_be_unique_and_a_refused_run_writes_nothing(tmp_path):
    with pytest.raises(InputError, match="unique"):
        dqn.DQN(config("dqn")).train(tmp_path / "run", progress=False,
                                    triggers=[IntervalTrigger(5, lambda loop: None, name=EVAL)])
    assert not (tmp_path / "run").exists()


# --- rlpipe's parts in the user's own loop; the exported policy on its own ----------------------------


@pytest.mark.parametrize("algo", ALGOS)
def test_rlpipes_parts_in_a_hand_written_loop(algo):
    pipeline = PIPELINE[algo](config(algo))
    collector = pipeline.make_collector(total_frames=200, init_random_frames=50)
    buffer = pipeline.make_replay_buffer()
    updates = 0
    for batch in collector:
        buffer.extend(batch.reshape(-1))
        if len(buffer) > 50:  # the first block is the random initial collect
            for _ in range(batch.numel()):
                updates += 1
                losses = pipeline.update(buffer.sample(), updates)
                assert all(torch.isfinite(v) for v in losses.values())
    collector.shutdown()
    assert len(buffer) == 200 and updates == 150


def test_the_exported_policies_act_in_a_fresh_process_with_torch_alone(tmp_path):
    policies = {algo: PIPELINE[algo](config(algo)).train(tmp_path / algo, progress=False).run_dir / "policy" / "policy.pt2"
                for algo in ALGOS}
    script = "import sys, torch\n" + "".join(
        f"print(list(torch.export.load({str(path)!r}).module()(torch.zeros(7, {obs_dim(algo)})).shape))\n"
        for algo, path in policies.items()) + "print('rlpipe' in sys.modules, 'torchrl' in sys.modules)\n"
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split("\n")[:5] == ["[7]", "[7, 1]", "[7, 1]", "[7, 1]", "False False"]  # dqn, td3, sac, crossq


# --- a pipeline leaves the process as it found it -------------------------------------------------------


@pytest.mark.parametrize("algo", PLUMBING)
def test_building_and_training_leave_threads_and_the_callers_random_state_alone(algo, tmp_path):
    torch.set_num_threads(2)
    try:
        torch.manual_seed(123)
        expected = torch.rand(3)
        torch.manual_seed(123)
        a = PIPELINE[algo](config(algo))
        assert torch.equal(torch.rand(3), expected)  # building drew nothing from the caller's generator
        assert torch.get_num_threads() == 2
        b = PIPELINE[algo](config(algo))  # the same seed: the same networks
        for (name, x), y in zip(a.loss_module.state_dict().items(), b.loss_module.state_dict().values()):
            assert torch.equal(x, y), name
        a.train(tmp_path / "run", progress=False)  # trains with config.num_threads=1 ...
        assert torch.get_num_threads() == 2  # ... and gives the caller's setting back
    finally:
        torch.set_num_threads(1)


def test_a_broken_pipeline_module_is_an_import_error_not_an_unknown_preset(monkeypatch, tmp_path):
    monkeypatch.setitem(pipelines.ALGOS, "broken", "rlpipe.pipelines.no_such_module:Broken")
    (tmp_path / "broken.yaml").write_text("algo: broken\n")
    with pytest.raises(ModuleNotFoundError):
        pipelines.resolve_preset(str(tmp_path / "broken.yaml"))
