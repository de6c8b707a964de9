"""Typed configs, presets and ``key=value`` overrides: what `rlpipe train PRESET key=value` relies on.

Everything here is in-process and fast: no env is stepped, nothing is trained.
"""

from __future__ import annotations

import dataclasses
import json
import typing

import pytest

from rlpipe.pipelines import InputError, presets, resolve_preset
from rlpipe.pipelines.config import (
    CollectorConfig,
    TrainConfig,
    apply_overrides,
    config_from_dict,
    config_to_dict,
    field_docs,
    flat_keys,
    validate,
)
from rlpipe.pipelines.dqn import DQNConfig, preset

COLLECTOR_KEYS = {"collector.workers", "collector.sync", "collector.frames_per_batch", "collector.weight_sync_interval"}


def _leaf_keys(cls: type, prefix: str = "") -> set[str]:
    """Every settable dotted key of a config dataclass, computed independently of rlpipe's helper."""
    hints = typing.get_type_hints(cls)
    keys: set[str] = set()
    for f in dataclasses.fields(cls):
        ftype = hints[f.name]
        if dataclasses.is_dataclass(ftype):
            keys |= _leaf_keys(ftype, prefix + f.name + ".")
        else:
            keys.add(prefix + f.name)
    return keys


# --- presets -------------------------------------------------------------------------------------


def test_dqn_preset_is_the_tf_agents_tutorial():
    algo, cfg = resolve_preset("dqn")
    assert algo == "dqn"
    assert isinstance(cfg, DQNConfig)
    assert cfg.env == "CartPole-v0"
    assert cfg.fc_layer_params == [100]
    assert cfg.learning_rate == pytest.approx(1e-3)
    assert cfg.batch_size == 64
    assert cfg.replay_buffer_capacity == 100_000
    assert cfg.collect_steps_per_iteration == 1
    assert cfg.initial_collect_steps == 1000
    assert cfg.num_iterations == 20_000
    assert cfg.eval_interval == 1000
    assert cfg.num_eval_episodes == 10
    assert cfg.epsilon_greedy == pytest.approx(0.1)
    assert cfg.epsilon_greedy_end is None  # constant epsilon, as DqnAgent
    assert cfg.gamma == 1.0
    assert cfg.target_update_tau == 1.0
    assert cfg.target_update_period == 1
    assert cfg.td_errors_loss == "l2"  # element-wise squared TD error
    assert cfg.double_dqn is False
    assert cfg.compile is False
    assert cfg.total_frames == 1000 + 20_000
    validate(cfg)


def test_dqn_cartpole_v1_preset_is_valid_and_on_cartpole_v1():
    algo, cfg = resolve_preset("dqn-cartpole-v1")
    assert algo == "dqn"
    assert isinstance(cfg, DQNConfig)
    assert cfg.env == "CartPole-v1"
    validate(cfg)
    assert {"dqn", "dqn-cartpole-v1"} <= set(presets.names())
    assert presets.names()["dqn"] == presets.names()["dqn-cartpole-v1"] == "dqn"


def test_presets_are_fresh_copies():
    _, a = resolve_preset("dqn")
    a.fc_layer_params.append(7)
    a.batch_size = 1
    _, b = resolve_preset("dqn")
    assert b.fc_layer_params == [100] and b.batch_size == 64
    assert preset("dqn") == b


def test_unknown_preset_names_the_closest():
    with pytest.raises(InputError, match="dqn-cartpole-v1"):
        resolve_preset("dqn-cartpole")


# --- overrides -----------------------------------------------------------------------------------


def test_overrides_are_typed_and_return_a_copy():
    base = preset("dqn")
    cfg = apply_overrides(base, [
        "batch_size=128", "learning_rate=5e-4", "fc_layer_params=[64,32]", "compile=false",
        "double_dqn=true", "epsilon_greedy_end=0.01", "learning_starts=null", "env=CartPole-v1",
        "gamma=0.99",
    ])
    assert cfg.batch_size == 128 and type(cfg.batch_size) is int
    assert cfg.learning_rate == pytest.approx(5e-4) and isinstance(cfg.learning_rate, float)
    assert cfg.fc_layer_params == [64, 32]
    assert cfg.double_dqn is True and cfg.compile is False
    assert cfg.epsilon_greedy_end == pytest.approx(0.01)
    assert cfg.learning_starts is None
    assert cfg.env == "CartPole-v1"
    assert cfg.gamma == pytest.approx(0.99)
    assert isinstance(cfg, DQNConfig)
    assert base == preset("dqn"), "apply_overrides must not modify the config it is given"


def test_zero_is_accepted_where_it_means_something():
    cfg = apply_overrides(preset("dqn"), ["eval_interval=0", "initial_collect_steps=0", "learning_starts=0"])
    assert (cfg.eval_interval, cfg.initial_collect_steps, cfg.learning_starts) == (0, 0, 0)


def test_dotted_overrides_on_the_base_config():
    cfg = apply_overrides(TrainConfig(), ["collector.workers=2", "collector.sync=false", "collector.frames_per_batch=10"])
    assert cfg.collector == CollectorConfig(workers=2, sync=False, frames_per_batch=10)


def test_dotted_overrides_on_the_dqn_config():
    cfg = apply_overrides(preset("dqn"), ["collector.workers=2", "collector.sync=false"])
    assert cfg.collector.workers == 2 and cfg.collector.sync is False
    with pytest.raises(InputError, match=r"collector\.frames_per_batch"):
        apply_overrides(preset("dqn"), ["collector.frames_per_batch=0"])


def test_flat_keys_of_dqn_config_are_every_settable_key():
    assert set(flat_keys(DQNConfig)) == _leaf_keys(DQNConfig)


@pytest.mark.parametrize(
    "override, closest",
    [("batchsize=3", "batch_size"), ("learning_rat=0.1", "learning_rate"), ("num_iteration=5", "num_iterations"),
     ("fc_layers=[3]", "fc_layer_params")],
)
def test_unknown_key_names_the_closest_valid_key(override, closest):
    with pytest.raises(InputError) as info:
        apply_overrides(preset("dqn"), [override])
    message = str(info.value)
    assert override.split("=")[0] in message
    assert closest in message


@pytest.mark.parametrize(
    "override, expected",
    [("batch_size=abc", "integer"), ("batch_size=1.5", "integer"), ("seed=x", "integer"),
     ("gamma=abc", "number"), ("compile=maybe", "true or false"), ("fc_layer_params=abc", "list"),
     ("fc_layer_params=[a,b]", "list")],
)
def test_ill_typed_value_names_key_and_expected_type(override, expected):
    key = override.split("=")[0]
    with pytest.raises(InputError) as info:
        apply_overrides(preset("dqn"), [override])
    message = str(info.value)
    assert key in message and expected in message
    assert "\n" not in message


@pytest.mark.parametrize(
    "override, key",
    [("batch_size=0", "batch_size"), ("num_iterations=-1", "num_iterations"), ("num_iterations=0", "num_iterations"),
     ("replay_buffer_capacity=0", "replay_buffer_capacity"), ("num_eval_episodes=0", "num_eval_episodes"),
     ("collect_steps_per_iteration=0", "collect_steps_per_iteration"), ("target_update_period=0", "target_update_period"),
     ("checkpoint_interval=-5", "checkpoint_interval"), ("log_interval=0", "log_interval"),
     ("policy_save_interval=0", "policy_save_interval"), ("initial_collect_steps=-1", "initial_collect_steps"),
     ("eval_interval=-1", "eval_interval"), ("learning_rate=0", "learning_rate"), ("learning_rate=-1e-3", "learning_rate"),
     ("fc_layer_params=[]", "fc_layer_params"), ("fc_layer_params=[64,0]", "fc_layer_params"),
     ("gamma=0", "gamma"), ("gamma=1.5", "gamma"), ("target_update_tau=0", "target_update_tau"),
     ("epsilon_greedy=1.5", "epsilon_greedy"), ("epsilon_decay_steps=0", "epsilon_decay_steps"),
     ("td_errors_loss=l3", "td_errors_loss"), ("collector.policy_device=cuda", "collector.policy_device"),
     ("collector.policy_device=cpu collector.backend=ray", "collector.policy_device")],
)
def test_values_that_cannot_work_are_rejected_naming_the_key(override, key):
    with pytest.raises(InputError) as info:
        apply_overrides(preset("dqn"), override.split())
    message = str(info.value)
    assert message.startswith(key + "="), message
    assert "expected" in message


def test_batch_larger_than_replay_is_rejected():
    with pytest.raises(InputError, match="batch_size"):
        apply_overrides(preset("dqn"), ["replay_buffer_capacity=32"])


@pytest.mark.parametrize("item", ["batch_size", "=3", ""])
def test_override_without_key_value_form_is_rejected(item):
    with pytest.raises(InputError, match="key=value"):
        apply_overrides(preset("dqn"), [item])


def test_input_error_is_a_value_error():
    assert issubclass(InputError, ValueError)


def test_validate_checks_a_config_built_in_python():
    validate(DQNConfig())
    with pytest.raises(InputError, match="batch_size"):
        validate(DQNConfig(batch_size=0))
    with pytest.raises(InputError, match="num_eval_episodes"):
        validate(DQNConfig(num_eval_episodes=-2))


# --- to and from plain data (config.json) --------------------------------------------------------


def test_config_round_trips_through_json():
    cfg = apply_overrides(preset("dqn-cartpole-v1"), ["batch_size=32", "fc_layer_params=[8,8]", "learning_starts=500"])
    data = json.loads(json.dumps(config_to_dict(cfg)))
    back = config_from_dict(DQNConfig, data)
    assert back == cfg
    assert isinstance(back, DQNConfig) and isinstance(back.collector, CollectorConfig)


@pytest.mark.parametrize(
    "change, key",
    [({"no_such_key": 1}, "no_such_key"), ({"batch_size": 0}, "batch_size"), ({"batch_size": "abc"}, None)],
)
def test_config_from_dict_rejects_bad_data(change, key):
    data = config_to_dict(preset("dqn"))
    data.update(change)
    with pytest.raises(InputError, match=key):
        config_from_dict(DQNConfig, data)


@pytest.mark.parametrize("change, key", [({"batch_size": "abc"}, "batch_size"), ({"fc_layer_params": "x"}, "fc_layer_params")])
def test_config_from_dict_names_the_ill_typed_key(change, key):
    data = config_to_dict(preset("dqn"))
    data.update(change)
    with pytest.raises(InputError, match=key):
        config_from_dict(DQNConfig, data)


def test_config_from_dict_validates_the_collector_group():
    data = config_to_dict(preset("dqn"))
    data["collector"]["frames_per_batch"] = 0
    with pytest.raises(InputError, match="frames_per_batch"):
        config_from_dict(DQNConfig, data)


# --- help text -----------------------------------------------------------------------------------


def test_field_docs_cover_every_dqn_and_shared_key():
    docs = field_docs(DQNConfig)
    own = _leaf_keys(DQNConfig) - COLLECTOR_KEYS
    missing = [k for k in sorted(own) if not docs.get(k, "").strip()]
    assert not missing, f"keys without a docstring: {missing}"
    # an algorithm's default for a key declared in the base says why, with its value
    assert "default 1.0 here: DqnAgent's default" in docs["gamma"]
    assert docs["fc_layer_params"] and docs["epsilon_greedy"]


def test_field_docs_cover_every_key_including_groups():
    docs = field_docs(DQNConfig)
    missing = [k for k in sorted(_leaf_keys(DQNConfig)) if not docs.get(k, "").strip()]
    assert not missing, f"keys without a docstring: {missing}"


def test_field_docs_of_the_base_config_cover_the_collector_group():
    docs = field_docs(TrainConfig)
    for key in COLLECTOR_KEYS:
        assert docs.get(key, "").strip(), key


def test_frames_per_batch_must_split_into_whole_vector_steps():
    with pytest.raises(InputError) as info:
        apply_overrides(preset("dqn"), ["collector.envs_per_worker=16", "collector.frames_per_batch=50"])
    assert str(info.value).startswith("collector.frames_per_batch=50") and "multiple of 16" in str(info.value)
    apply_overrides(preset("dqn"), ["collector.envs_per_worker=16", "collector.frames_per_batch=160"])


def test_cuda_without_a_gpu_is_one_clear_line():
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(InputError) as info:
        apply_overrides(preset("dqn"), ["device=cuda"])
    assert str(info.value).startswith("device='cuda': torch sees no CUDA device") and "\n" not in str(info.value)


# --- issue 11: NaN and inf, seeds, this machine's limits ---------------------------------------------


def _float_keys(cls: type) -> list[str]:
    cfg = cls()
    keys = []
    for key in flat_keys(cls):
        owner, *rest = key.split(".")
        value = getattr(getattr(cfg, owner), rest[0]) if rest else getattr(cfg, owner)
        hint = str(typing.get_type_hints(type(cfg) if not rest else type(getattr(cfg, owner)))[rest[0] if rest else owner])
        if isinstance(value, float) or "float" in hint:
            keys.append(key)
    return keys


def _all_configs():
    from rlpipe.pipelines.sac import SACConfig
    from rlpipe.pipelines.td3 import TD3Config

    return [DQNConfig, TD3Config, SACConfig]


@pytest.mark.unit
@pytest.mark.parametrize("cls", _all_configs(), ids=lambda c: c.__name__)
def test_nan_and_inf_are_refused_for_every_float_key(cls):
    keys = _float_keys(cls)
    assert "learning_rate" in keys or "actor_learning_rate" in keys
    for key in keys:
        for bad in ("nan", "inf", "-inf"):
            with pytest.raises(InputError) as info:
                apply_overrides(cls(), [f"{key}={bad}"])
            message = str(info.value)
            assert message.startswith(f"{key}=") and "expected a finite number" in message, (key, bad, message)
            assert "\n" not in message


@pytest.mark.unit
@pytest.mark.parametrize("seed, ok", [(0, True), (2**31 - 1, True), (-1, False), (2**31, False), (10**30, False)])
def test_seeds_torch_numpy_and_gymnasium_all_take(seed, ok):
    if ok:
        assert apply_overrides(preset("dqn"), [f"seed={seed}"]).seed == seed
    else:
        with pytest.raises(InputError, match=r"^seed=.*expected an integer from 0 to 2147483647"):
            apply_overrides(preset("dqn"), [f"seed={seed}"])


@pytest.mark.unit
def test_devices_this_machine_lacks_are_refused_naming_those_it_has():
    from rlpipe.pipelines.config import available_devices

    devices = available_devices()
    assert devices[0] == "cpu"
    for device in ("meta", "cuda:99", "mps" if "mps" not in devices else "xpu"):
        with pytest.raises(InputError) as info:
            apply_overrides(preset("dqn"), [f"device={device}"])
        assert str(info.value).startswith(f"device='{device}': ") and f"devices: {', '.join(devices)}" in str(info.value)
    apply_overrides(preset("dqn"), ["device=cpu:0"])


@pytest.mark.unit
def test_thread_and_worker_counts_beyond_this_machine_are_refused(monkeypatch):
    import os

    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    apply_overrides(preset("dqn"), ["num_threads=4", "collector.workers=32"])
    with pytest.raises(InputError, match=r"^num_threads=5: .*at most 4"):
        apply_overrides(preset("dqn"), ["num_threads=5"])
    with pytest.raises(InputError, match=r"^collector.workers=33: .*at most 32"):
        apply_overrides(preset("dqn"), ["collector.workers=33"])


@pytest.mark.unit
def test_a_saved_config_from_a_bigger_machine_loads_and_the_overrides_fix_it():
    data = config_to_dict(preset("dqn"))
    data["num_threads"] = 10_000
    cfg = config_from_dict(DQNConfig, data)  # a run saved elsewhere can be resumed here ...
    with pytest.raises(InputError, match="num_threads"):
        apply_overrides(cfg, [])
    assert apply_overrides(cfg, ["num_threads=-1"]).num_threads == -1  # ... with the key changed


@pytest.mark.unit
def test_initial_collect_policy_is_random_or_collect():
    assert preset("dqn").initial_collect_policy == "random"
    assert apply_overrides(preset("dqn"), ["initial_collect_policy=collect"]).initial_collect_policy == "collect"
    with pytest.raises(InputError, match=r"^initial_collect_policy='greedy': expected one of 'random', 'collect'"):
        apply_overrides(preset("dqn"), ["initial_collect_policy=greedy"])


# --- issue 12: the tutorials' remaining pieces -------------------------------------------------------


def test_sac_002_preset_is_the_older_tutorial():
    from rlpipe.pipelines.sac import SACConfig

    algo, cfg = resolve_preset("sac-002")
    assert algo == "sac" and isinstance(cfg, SACConfig)
    assert cfg.env == "MinitaurBulletEnv-v0"
    assert (cfg.num_iterations, cfg.initial_collect_steps, cfg.collect_steps_per_iteration) == (100_000, 10_000, 1)
    assert cfg.initial_collect_policy == "collect"  # its DynamicStepDriver runs tf_agent.collect_policy
    assert cfg.replay_buffer_capacity == 1_000_000 and cfg.batch_size == 256
    assert (cfg.num_eval_episodes, cfg.eval_interval, cfg.log_interval) == (30, 10_000, 5000)
    assert cfg.gradient_clipping is None and "gradient_clipping" in flat_keys(SACConfig)
    assert (cfg.actor_learning_rate, cfg.critic_learning_rate, cfg.alpha_learning_rate) == (3e-4, 3e-4, 3e-4)
    assert (cfg.target_update_tau, cfg.target_update_period, cfg.gamma, cfg.reward_scale_factor) == (0.005, 1, 0.99, 1.0)
    assert cfg.actor_fc_layer_params == [256, 256] and cfg.critic_joint_fc_layer_params == [256, 256]
    validate(cfg)
    assert resolve_preset("sac")[1].initial_collect_policy == "random"


@pytest.mark.parametrize("override, key", [("gradient_clipping=0", "gradient_clipping"),
                                           ("critic_kernel_initializer=he", "critic_kernel_initializer")])
def test_sac_clipping_and_initialiser_keys_are_checked(override, key):
    with pytest.raises(InputError, match=rf"^{key}="):
        apply_overrides(resolve_preset("sac")[1], [override])


def test_glorot_uniform_critics_as_tf_agents_initialises_them():
    import math

    import torch

    from rlpipe.modules.critics import make_qvalue_critic
    from rlpipe.pipelines.sac import SAC

    torch.manual_seed(0)
    critic = make_qvalue_critic(28, 8, [256, 256], init="glorot_uniform")
    linears = [m for m in critic.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(36, 256), (256, 256), (256, 1)]
    for m in linears:
        bound = math.sqrt(6 / (m.in_features + m.out_features))
        assert m.weight.abs().max() <= bound and m.weight.abs().max() > 0.9 * bound
        assert m.weight.std().item() == pytest.approx(bound / math.sqrt(3), rel=0.1 if m.out_features > 1 else 0.5)
        assert torch.count_nonzero(m.bias) == 0
    torch_default = make_qvalue_critic(28, 8, [256, 256])
    assert next(torch_default.parameters()).abs().max() <= 1 / math.sqrt(36)  # nn.Linear's default bound
    # in the pipeline: both twin critics of the loss (redrawn by TorchRL within the first one's range)
    cfg = apply_overrides(resolve_preset("sac")[1], ["env=Pendulum-v1", "critic_kernel_initializer=glorot_uniform"])
    pipeline = SAC(cfg)
    first = pipeline.loss_module.qvalue_network_params.flatten_keys().values()
    weights = [p for p in first if p.dim() == 3]  # [twin, out, in]
    out_, in_ = weights[1].shape[1:]
    bound = math.sqrt(6 / (in_ + out_))
    for twin in weights[1]:
        assert twin.abs().max() <= bound * 1.001 and twin.std() > 0.8 * bound / math.sqrt(3)
    assert not torch.equal(weights[1][0], weights[1][1])


def test_gradient_clipping_clips_each_tensor_as_tf_agents_does():
    import torch

    from rlpipe.modules.fast.optim import clip_gradient_norms

    a, b = torch.nn.Parameter(torch.zeros(2, 3)), torch.nn.Parameter(torch.zeros(4))
    a.grad, b.grad = torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 0.1]]), torch.full((4,), 10.0)
    clip_gradient_norms([a], 1.0, stacked=True)  # each stacked network's tensor on its own
    clip_gradient_norms([b], 1.0)
    torch.testing.assert_close(a.grad, torch.tensor([[0.6, 0.8, 0.0], [0.0, 0.0, 0.1]]))
    torch.testing.assert_close(b.grad, torch.full((4,), 0.5))


def test_sac_trains_with_clipping_glorot_critics_and_the_collect_policy_first(tmp_path):
    from rlpipe.pipelines.sac import SAC

    cfg = apply_overrides(resolve_preset("sac-002")[1], [
        "env=Pendulum-v1", "num_iterations=60", "initial_collect_steps=50", "replay_buffer_capacity=1000",
        "batch_size=16", "eval_interval=0", "num_eval_episodes=1", "log_interval=30", "actor_fc_layer_params=[16]",
        "critic_joint_fc_layer_params=[16]", "gradient_clipping=0.5", "critic_kernel_initializer=glorot_uniform",
        "num_threads=1", "collector.frames_per_batch=10"])
    pipeline = SAC(cfg)
    collector = pipeline.make_collector(100, 50)
    assert collector.init_random_frames == 0, "sac-002's initial steps come from the collect policy"
    collector.shutdown()
    random_first = SAC(apply_overrides(cfg, ["initial_collect_policy=random"])).make_collector(100, 50)
    assert random_first.init_random_frames == 50
    random_first.shutdown()
    result = pipeline.train(tmp_path / "run", progress=False)
    assert result.summary["updates"] == 60 and result.summary["final_average_return"] is not None


# --- issue 20: one base, each algorithm its own keys and defaults ---------------------------------------


def test_each_algorithm_config_holds_only_its_own_keys_beside_the_shared_ones():
    from rlpipe.pipelines import pipeline_class

    shared = set(flat_keys(TrainConfig))
    keys = {algo: set(flat_keys(pipeline_class(algo).Config)) for algo in ("dqn", "td3", "sac")}
    own = {algo: k - shared for algo, k in keys.items()}
    assert all(shared < k for k in keys.values())
    assert {"epsilon_greedy", "td_errors_loss", "double_dqn", "fc_layer_params"} <= own["dqn"]
    assert {"initial_alpha", "reward_scale_factor", "alpha_learning_rate", "target_entropy"} <= own["sac"]
    assert {"policy_delay", "policy_noise", "clipped_double_q", "exploration_noise"} <= own["td3"]
    sac_only, dqn_only = own["sac"] - own["dqn"] - own["td3"], own["dqn"] - own["sac"] - own["td3"]
    assert not sac_only & keys["dqn"] and not sac_only & keys["td3"]
    assert not dqn_only & keys["sac"] and not dqn_only & keys["td3"]
    # what one algorithm's tutorial needs is not the base's: DqnAgent's gamma and tau, SAC's temperature
    base = TrainConfig()
    assert (base.gamma, base.target_update_tau) != (1.0, 1.0) and not hasattr(base, "initial_alpha")
    assert (DQNConfig().gamma, DQNConfig().target_update_tau) == (1.0, 1.0)


@pytest.mark.parametrize("algo, override", [("dqn", "batch_size=0"), ("td3", "learning_starts=-1"),
                                            ("sac", "replay_buffer_capacity=0"), ("dqn", "gamma=1.5")])
def test_a_key_whose_default_an_algorithm_changes_keeps_its_rule(algo, override):
    from rlpipe.pipelines import pipeline_class

    with pytest.raises(InputError, match=rf"^{override.split('=')[0]}="):
        apply_overrides(pipeline_class(algo).preset(), [override])


def test_every_key_is_declared_once_and_an_algorithms_default_says_why_in_its_help():
    """One home per key: no config class declares a key another declares (an algorithm's own default for it is a
    ``config_class`` value, whose why reaches the key's help); declaring one again is refused at import."""
    import ast
    import inspect

    from rlpipe.pipelines import pipeline_class
    from rlpipe.pipelines.config import ActorKeys, ClippedGradientKeys, CriticKeys, OneRateKeys, RayConfig, config_class
    from rlpipe.pipelines.sac import SACFamilyConfig

    classes = [TrainConfig, CollectorConfig, RayConfig, ActorKeys, CriticKeys, OneRateKeys, ClippedGradientKeys,
               SACFamilyConfig, *(pipeline_class(algo).Config for algo in ("sac", "crossq", "td3", "dqn"))]
    declared: dict[str, list[str]] = {}
    for cls in classes:
        body = ast.parse(inspect.getsource(cls)).body[0].body
        for node in body:
            if isinstance(node, ast.AnnAssign):
                declared.setdefault(node.target.id, []).append(cls.__name__)
    assert {key: homes for key, homes in declared.items() if len(homes) > 1} == {}
    td3 = pipeline_class("td3").Config
    assert td3().policy_delay == 2 and "policy_freq" in field_docs(td3)["policy_delay"]
    assert "policy_freq" not in field_docs(pipeline_class("crossq").Config)["policy_delay"]
    with pytest.raises(TypeError, match="declared in the class"):
        @config_class(gamma=0.9)
        class Again(TrainConfig):
            gamma: float = 0.5
    with pytest.raises(TypeError, match="no base class declares"):
        config_class(nonsense=1)(type("Stray", (TrainConfig,), {}))
