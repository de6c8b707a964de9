"""``GymCollector``: the in-process collector that steps a gymnasium env directly (issue 22).

Its blocks must be what TorchRL's ``Collector`` gives for the same env and policy (a user's replay buffer
and loss take them), its episodes bookkept as TorchRL's transforms do, and the same seed must give the
same blocks.
"""

from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import GymEnv
from torchrl.objectives import DQNLoss

from rlpipe.envs import make_env
from rlpipe.modules.fast.tensor_policy import tensor_step
from rlpipe.pipelines import pipeline_class, resolve_preset
from rlpipe.pipelines.compat.torchrl import COLLECTOR_KWARGS
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.workers.gym_collector import GymCollector
from rlpipe.pipelines.workers.local import direct_collection
from rlpipe.pipelines.workers.snapshot_collector import SNAPSHOT

SMALL = {"dqn": ["fc_layer_params=[16]"], "td3": ["actor_fc_layer_params=[16]", "critic_fc_layer_params=[16]"],
         "sac": ["env=Pendulum-v1", "actor_fc_layer_params=[16]", "critic_joint_fc_layer_params=[16]"]}
IN_PROCESS = ["eval_in_background=false", "collector.workers=1", "collector.sync=true"]


def pipeline(algo: str, *extra: str):
    algo_name, cfg = resolve_preset(algo)
    return pipeline_class(algo_name)(apply_overrides(cfg, [*SMALL[algo], *IN_PROCESS, *extra]))


def layout(block) -> dict:
    return {k: (tuple(v.shape), v.dtype) for k, v in block.items(include_nested=True, leaves_only=True)}


def blocks(collector, n: int) -> list:
    out = []
    for block in collector:
        out.append(block)
        if len(out) == n:
            break
    collector.shutdown()
    return out


@pytest.mark.parametrize("algo", ["dqn", "td3", "sac"])  # CartPole (discrete), Pendulum (noisy actor, TanhNormal)
def test_blocks_have_torchrls_keys_shapes_and_dtypes(algo):
    p = pipeline(algo)
    ours = p.make_collector(total_frames=200, init_random_frames=50)
    assert isinstance(ours, GymCollector)
    theirs = Collector(p.env, p.collect_policy, frames_per_batch=50, total_frames=200, init_random_frames=50,
                       **COLLECTOR_KWARGS)
    (our_random, our_policy), (their_random, their_policy) = blocks(ours, 2), blocks(theirs, 2)
    assert layout(our_policy) == layout(their_policy)
    assert layout(our_random) == layout(their_random) == layout(their_policy)  # random rows: the policy's keys too


def test_a_collector_process_steps_its_env_directly_too():
    p = pipeline("td3", "collector.sync=false")
    collector = p.make_collector(total_frames=150, init_random_frames=50)
    try:
        assert issubclass(collector.collector_class, GymCollector)
        first, second = blocks(collector, 2)
    finally:
        collector.shutdown()
    theirs = Collector(p.env, p.collect_policy, frames_per_batch=50, total_frames=50, **COLLECTOR_KWARGS)
    assert layout(first) == layout(second) == layout(blocks(theirs, 1)[0])
    assert not torch.equal(first["observation"], second["observation"])  # the shared block was refilled, not resent


def test_episodes_are_bookkept_as_torchrls_transforms_do():
    p = pipeline("dqn", "env=CartPole-v1")
    collector = GymCollector(p.env, p.collect_policy, frames_per_batch=100, total_frames=300, **COLLECTOR_KWARGS)
    collector.set_seed(0)
    batch = torch.cat(blocks(collector, 3))
    done = batch["next", "done"].squeeze(-1)
    assert done.sum() >= 3  # CartPole's episodes under a fresh network last ~10-50 steps
    assert torch.equal(batch["next", "done"], batch["next", "terminated"] | batch["next", "truncated"])
    assert not batch["done"].any() and not batch["next", "is_init"].any()
    ends = done.nonzero().squeeze(-1).tolist()
    start = 0
    for end in ends:
        episode = batch[start:end + 1]
        assert episode["step_count"].squeeze(-1).tolist() == list(range(end + 1 - start))
        assert torch.equal(episode["next", "step_count"], episode["step_count"] + 1)
        assert episode["next", "episode_reward"][-1].item() == pytest.approx(
            episode["episode_reward"][0].item() + episode["next", "reward"].sum().item(), rel=1e-5)
        assert (episode["collector", "traj_ids"] == episode["collector", "traj_ids"][0]).all()
        if end + 1 < batch.numel():  # the next row starts a new episode and trajectory
            after = batch[end + 1]
            assert after["is_init"].item() and after["step_count"].item() == 0 and after["episode_reward"].item() == 0
            assert after["collector", "traj_ids"].item() == episode["collector", "traj_ids"][0].item() + 1
        start = end + 1
    # each transition's next observation is the following row's observation within an episode
    same_episode = ~done[:-1]
    assert torch.equal(batch["next", "observation"][:-1][same_episode], batch["observation"][1:][same_episode])


def test_the_same_seed_gives_the_same_blocks():
    def run():
        p = pipeline("td3")
        torch.manual_seed(5)
        collector = p.make_backend().start(150, 50, seed=11).collector
        return torch.cat(blocks(collector, 3))

    first, second = run(), run()
    assert (first == second).all()
    assert first["observation"][0].tolist() == pytest.approx(
        make_env("Pendulum-v1").base_env._env.reset(seed=11)[0].tolist())  # set_seed seeds the first episode


def test_a_torchrl_replay_buffer_and_loss_take_its_blocks():
    p = pipeline("dqn", "replay_all_keys=true")
    collector = p.make_collector(total_frames=150, init_random_frames=50)
    buffer = ReplayBuffer(storage=LazyTensorStorage(1000), batch_size=32)
    for block in collector:
        buffer.extend(block)
    assert len(buffer) == 150
    loss = DQNLoss(p.policy, action_space=p.env.action_spec_unbatched, delay_value=False)
    sample = buffer.sample()
    losses = loss(sample)
    losses["loss"].backward()
    assert torch.isfinite(losses["loss"])


def test_the_fast_policy_paths_act_as_the_modules_themselves():
    observation = torch.tensor([0.3, -0.2, 0.5])
    for algo in ("td3", "sac"):
        policy = pipeline(algo).collect_policy
        step = tensor_step(policy)
        assert step.__name__ == "act" and "_tensordict_step" not in step.__qualname__
        torch.manual_seed(0)
        ours = step(observation)
        torch.manual_seed(0)
        theirs = policy(pipeline(algo).env.reset().set("observation", observation))
        for key, value in ours.items():
            assert torch.allclose(value, theirs[key], atol=1e-4), (algo, key)


def test_user_envs_and_direct_false_keep_torchrls_collector():
    p = pipeline("dqn", "env=CartPole-v1")
    assert direct_collection(p.config, p.env_fn, p.env)
    rescaled = pipeline("td3", "rescale_observations=true")  # the rescale is a gymnasium wrapper: still direct
    assert direct_collection(rescaled.config, rescaled.env_fn, rescaled.env)
    collector = rescaled.make_collector(total_frames=50, init_random_frames=0)
    assert isinstance(collector, GymCollector)
    collector.shutdown()
    off = apply_overrides(p.config, ["collector.direct=false"])
    assert not direct_collection(off, p.env_fn, p.env)
    vector = pipeline("dqn", "env=CartPole-v1", "collector.envs_per_worker=2", "collector.frames_per_batch=50")
    assert not direct_collection(vector.config, vector.env_fn, vector.env)
    user_env = GymEnv("CartPole-v1")  # a user's own TorchRL env: its transforms are its own
    algo, cfg = resolve_preset("dqn")
    user = pipeline_class(algo)(apply_overrides(cfg, [*SMALL["dqn"], *IN_PROCESS]), env=lambda: user_env,
                                eval_env=lambda: make_env("CartPole-v1"))
    collector = user.make_collector(total_frames=50, init_random_frames=0)
    assert isinstance(collector, Collector)
    collector.shutdown()


def test_a_restored_collector_goes_on_with_the_episode_under_way_as_if_never_stopped():
    # issue 23: its snapshot (env state, episode under way, trajectory counter) travels in state_dict, and a
    # new collector loaded with it gives the block the first one gives next, bit for bit
    def collector():
        p = pipeline("dqn", "env=CartPole-v1")
        return p, GymCollector(p.env, p.collect_policy, frames_per_batch=30, total_frames=-1, **COLLECTOR_KWARGS)

    torch.manual_seed(0)
    _, first = collector()
    first.set_seed(0)
    iterator = iter(first)
    seen = torch.cat([next(iterator), next(iterator)])
    state = first.state_dict()
    assert bool(state[SNAPSHOT]["capturable"]) and state[SNAPSHOT]["episode/observation"].shape == (4,)
    rng = torch.get_rng_state()
    expected = next(iterator)
    torch.set_rng_state(rng)
    with torch.random.fork_rng():
        _, other = collector()
    other.load_state_dict(state)
    block = next(iter(other))
    assert (block == expected).all(), "the restored collector's next block differs from the uninterrupted one"
    assert not block["is_init"][0].item() or seen["next", "done"][-1].item()


def test_a_collector_whose_env_cannot_be_restored_starts_a_new_trajectory():
    p = pipeline("dqn", "env=CartPole-v1")
    collector = GymCollector(p.env, p.collect_policy, frames_per_batch=30, total_frames=-1, **COLLECTOR_KWARGS)
    collector.set_seed(0)
    iterator = iter(collector)
    seen = torch.cat([next(iterator), next(iterator)])
    state = {k: v for k, v in collector.snapshot().items() if not k.startswith(("env/", "episode/"))}
    state["capturable"] = torch.tensor(False)
    other = GymCollector(p.env, p.collect_policy, frames_per_batch=30, total_frames=-1, **COLLECTOR_KWARGS)
    assert not other.load_snapshot(state)
    block = next(iter(other))
    # the episode under way cannot go on: a new trajectory starts, numbered after the ones collected before
    assert block["is_init"][0].item() and block["step_count"][0].item() == 0
    assert block["collector", "traj_ids"][0].item() > seen["collector", "traj_ids"].max().item()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (checked on the GPU machine)")
@pytest.mark.parametrize("algo", ["td3", "sac"])
def test_a_cpu_copy_of_the_collect_policy_acts_and_follows_the_learners_weights(algo):
    from rlpipe.pipelines.workers.local import push_weights

    p = pipeline(algo, "device=cuda", "collector.policy_device=cpu", "collector.frames_per_batch=16")
    collector = p.make_collector(total_frames=64, init_random_frames=0)
    try:
        copy = dict(collector.policy.named_parameters())
        assert {t.device.type for t in copy.values()} == {"cpu"}  # the learner's stay on the GPU
        assert {t.device.type for t in p.collect_policy.parameters()} == {"cuda"}
        block = next(iter(collector))
        bound = float(p.env.action_spec_unbatched.space.high.max())
        assert block.device.type == "cuda" and block["action"].abs().max() <= bound + 1e-6
        with torch.no_grad():
            for param in p.collect_policy.parameters():
                param.add_(1.0)
        push_weights(collector)
        for name, param in p.collect_policy.named_parameters():
            torch.testing.assert_close(copy[name], param.cpu(), rtol=0, atol=0)
    finally:
        collector.shutdown()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (checked on the GPU machine)")
@pytest.mark.parametrize("algo", ["td3", "sac"])  # Pendulum: bounds of 2, read from the env's spec on the CPU
def test_the_fast_policy_paths_act_on_a_gpu(algo):
    p = pipeline(algo, "device=cuda", "collector.frames_per_batch=16")
    collector = p.make_collector(total_frames=32, init_random_frames=0)
    try:
        block = next(iter(collector))
    finally:
        collector.shutdown()
    bound = float(p.env.action_spec_unbatched.space.high.max())
    assert block.device.type == "cuda" and block["action"].abs().max() <= bound + 1e-6


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (checked on the GPU machine)")
def test_a_collector_process_acting_from_a_cpu_copy_hands_its_blocks_to_a_gpu_learner():
    from rlpipe.pipelines.workers.local import LocalBackend

    p = pipeline("sac", "device=cuda", "collector.policy_device=cpu", "collector.sync=false",
                 "collector.frames_per_batch=16")
    backend = p.make_backend().start(total_frames=64, init_random_frames=0, seed=0)
    try:
        assert isinstance(backend, LocalBackend) and len(backend.health().pids) == 1  # one worker process
        bound = float(p.env.action_spec_unbatched.space.high.max())
        seen = []
        for block in backend:  # stored on the CPU by the worker, on the learner's GPU once handed out
            assert block.device.type == "cuda" and block["action"].abs().max() <= bound + 1e-6
            seen.append(block["action"].cpu())
            with torch.no_grad():  # new weights on the GPU: the push copies them into the worker's CPU copy
                for param in p.collect_policy.parameters():
                    param.mul_(0.5)
            backend.push_weights()  # a push across devices that failed, or a dead worker, raises here
        assert len(seen) == 4
    finally:
        backend.close()
