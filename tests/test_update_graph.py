"""The update as CUDA graphs (pipelines/training/update_graph.py): one graph per branch pattern, same numbers.

TorchRL warns that CUDA graphs can give silently wrong results. The GPU tests check that SAC, TD3
(delayed actor, so several graphs) and DQN, graphed (and compiled and graphed), leave the same
parameters as eager updates on the same batches. They run where a GPU is (skipped on CPU); on CPU,
``CudaGraphModule`` passes calls through, so the CPU test checks the branch mapping and the batch
round trip of the wrapper itself.
"""

from __future__ import annotations

import pytest
import torch

from rlpipe.pipelines import dqn, sac, td3
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.training.update_graph import GraphedUpdate, canonical_index

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

SMALL = {
    "sac": (sac.SAC, "sac", ["env=Pendulum-v1", "actor_fc_layer_params=[32,32]",
                             "critic_joint_fc_layer_params=[32,32]", "batch_size=32"]),
    "td3": (td3.TD3, "td3", ["actor_fc_layer_params=[32]", "critic_fc_layer_params=[32]", "batch_size=32",
                             "target_update_period=2"]),
    "dqn": (dqn.DQN, "dqn", ["fc_layer_params=[32]", "batch_size=32", "target_update_period=3"]),
}


@pytest.fixture
def td_pytree_restored():
    """CudaGraphModule takes TensorDicts out of torch's pytree registry for the whole process; put
    them back after a test so the rest of the suite runs as it would alone."""
    from tensordict.nn.functional_modules import PYTREE_REGISTERED_LAZY_TDS, PYTREE_REGISTERED_TDS
    from torch.utils._pytree import SUPPORTED_NODES

    saved = {t: SUPPORTED_NODES[t] for t in PYTREE_REGISTERED_TDS + PYTREE_REGISTERED_LAZY_TDS if t in SUPPORTED_NODES}
    yield
    SUPPORTED_NODES.update(saved)


def _build(algo: str, *overrides: str):
    cls, preset, small = SMALL[algo]
    return cls(apply_overrides(cls.preset(preset), [*small, "num_threads=1", *overrides]))


def _batches(pipeline, n: int, device: str) -> list:
    """``n`` replay samples of real env transitions (random actions), drawn once."""
    torch.manual_seed(0)
    pipeline.replay_buffer.extend(pipeline.env.rollout(200, break_when_any_done=False).to(pipeline.device))
    keys = pipeline.replay_keys
    return [(b.select(*keys) if keys else b).to(device) for b in (pipeline.replay_buffer.sample() for _ in range(n))]


def _params(pipeline) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in pipeline.loss_module.state_dict().items()}


def _run(pipeline, batches) -> dict[str, torch.Tensor]:
    torch.manual_seed(1)
    if pipeline.device.type == "cuda":
        torch.cuda.manual_seed(1)
    for index, batch in enumerate(batches, start=1):
        pipeline.update_step(batch.clone(), index)
    return _params(pipeline)


@pytest.mark.unit
def test_canonical_index_takes_the_same_branches():
    periods = [2, 4]  # TD3: actor every 2nd update, targets every 2nd actor update
    for index in range(1, 50):
        c = canonical_index(index, periods)
        assert [index % p == 0 for p in periods] == [c % p == 0 for p in periods]
    assert {canonical_index(i, periods) for i in range(1, 50)} == {1, 2, 4}
    assert {canonical_index(i, [1]) for i in range(1, 10)} == {1}
    periods = [2, 3]  # SAC: actor every 2nd update, targets every 3rd: neither divides the other
    for index in range(1, 50):
        c = canonical_index(index, periods)
        assert c <= index and [index % p == 0 for p in periods] == [c % p == 0 for p in periods]
    assert {canonical_index(i, periods) for i in range(1, 50)} == {1, 2, 3, 6}


@pytest.mark.skipif(torch.cuda.is_available(), reason="CPU pass-through; on a GPU the tests below record real graphs")
@pytest.mark.parametrize("algo", ["td3", "dqn"])
@pytest.mark.filterwarnings("ignore:This module is instantiated on a machine without CUDA")
@pytest.mark.filterwarnings("ignore:Tensordict is registered in PyTree")
def test_the_wrapper_runs_the_update_as_the_pipeline_would_on_cpu(algo, td_pytree_restored):
    # Without CUDA, CudaGraphModule passes calls through: the wrapper's own work (one call per
    # branch pattern with a representative index, the batch rebuilt from its tensors) must not
    # change a single number.
    eager, wrapped = _build(algo), _build(algo)
    wrapped.update_step = GraphedUpdate(wrapped.update, wrapped.update_periods())
    batches = _batches(eager, 12, "cpu")
    before = _params(eager)
    a, b = _run(eager, batches), _run(wrapped, batches)
    for name in a:
        torch.testing.assert_close(a[name], b[name], rtol=0, atol=0, msg=name)
    assert any(not torch.equal(before[k], v) for k, v in a.items())  # it learned
    assert len(wrapped.update_step.graphs) == len(set(canonical_index(i, wrapped.update_periods()) for i in range(1, 13)))


@CUDA
@pytest.mark.parametrize("algo", ["sac", "td3", "dqn"])
@pytest.mark.parametrize("compiled", [False, True])
def test_cuda_graphed_updates_leave_the_eager_parameters(algo, compiled, td_pytree_restored):
    # graphed against not graphed, each compiled or not (compiled kernels round differently from
    # eager ones, and Adam turns rounding into visible steps: that is not what is checked here)
    flag = f"compile={str(compiled).lower()}"
    eager, graphed = _build(algo, "device=cuda", flag, "cudagraph=false"), _build(algo, "device=cuda", flag, "cudagraph=true")
    assert isinstance(graphed.update_step, GraphedUpdate)
    graphed.loss_module.load_state_dict(eager.loss_module.state_dict())
    batches = _batches(eager, 20, "cuda")
    a, b = _run(eager, batches), _run(graphed, batches)
    assert len(graphed.update_step.graphs) == len(set(canonical_index(i, graphed.update_periods()) for i in range(1, 21)))
    for name in a:
        torch.testing.assert_close(a[name], b[name], rtol=1e-4, atol=1e-5, msg=name)


@CUDA
def test_a_short_run_trains_with_graphed_updates(tmp_path, td_pytree_restored):
    pipeline = _build("td3", "device=cuda", "cudagraph=true", "num_iterations=60", "initial_collect_steps=64", "learning_starts=64",
                      "eval_interval=30", "num_eval_episodes=1", "collector.sync=true")
    result = pipeline.train(tmp_path / "run", progress=False)
    assert result.summary["updates"] == 60
    assert len(pipeline.update_step.graphs) == 3


@pytest.mark.unit
def test_cudagraph_on_a_cpu_device_is_one_clear_line():
    from rlpipe.pipelines.errors import InputError

    with pytest.raises(InputError) as info:
        apply_overrides(td3.preset("td3"), ["cudagraph=true", "device=cpu"])
    assert str(info.value).startswith("cudagraph=true with device='cpu'") and "\n" not in str(info.value)
    assert apply_overrides(td3.preset("td3"), ["compile=true"]).cudagraph is None  # follows compile, on CUDA only
