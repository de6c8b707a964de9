"""``fast``: rlpipe's fast parts (``rlpipe.modules.fast``) against the stock TorchRL and torch parts they replace.

``fast=false`` puts every stock part back at once, and a run learns the same with either; a TorchRL or torch
whose private names the fast parts read have changed stops a ``fast=true`` run before it starts, in one line.
"""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictSequential
from torchrl.objectives import CrossQLoss, DQNLoss, SACLoss, SoftUpdate

from rlpipe.modules import fast
from rlpipe.modules.critics import BatchRenorm1d
from rlpipe.modules.fast.crossq_loss import LeanCrossQLoss
from rlpipe.modules.fast.dqn_loss import LeanDQNLoss
from rlpipe.modules.fast.exploration import EGreedyQPolicy
from rlpipe.modules.fast.optim import LeanAdam
from rlpipe.modules.fast.sac_loss import LeanSACLoss
from rlpipe.modules.fast.target_updates import ForeachSoftUpdate
from rlpipe.pipelines import pipeline_class, resolve_preset
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.workers.local import direct_collection

SMALL = {"sac": ["env=Pendulum-v1", "actor_fc_layer_params=[16]", "critic_joint_fc_layer_params=[16]"],
         "td3": ["actor_fc_layer_params=[16]", "critic_fc_layer_params=[16]", "learning_starts=100"],
         "dqn": ["fc_layer_params=[16]", "target_update_period=2"],
         "crossq": ["actor_fc_layer_params=[16]", "critic_fc_layer_params=[16]"]}
STOCK_LOSS = {"sac": SACLoss, "dqn": DQNLoss, "crossq": CrossQLoss}
LEAN_LOSS = {"sac": LeanSACLoss, "dqn": LeanDQNLoss, "crossq": LeanCrossQLoss}
# collection in the learner's process, a block at a time: a collector process acting on weights it got while the
# learner went on would make each run's data depend on timing
IN_PROCESS = ["eval_in_background=false", "collector.workers=1", "collector.sync=true"]


def pipeline(algo: str, *extra: str):
    name, cfg = resolve_preset(algo)
    return pipeline_class(name)(apply_overrides(cfg, [*SMALL[algo], *IN_PROCESS, *extra]))


@pytest.mark.parametrize("algo", ["sac", "td3", "dqn", "crossq"])
def test_fast_false_puts_every_stock_part_back(algo):
    stock, ours = pipeline(algo, "fast=false"), pipeline(algo)
    if algo in STOCK_LOSS:
        assert type(stock.loss_module) is STOCK_LOSS[algo] and type(ours.loss_module) is LEAN_LOSS[algo]
    else:  # TD3's loss is the tutorial's own (its ablation switches): its networks go through TensorDicts
        assert stock.loss_module._critic_layers is None and not stock.loss_module._actor_on_tensors
        assert ours.loss_module._critic_layers is not None and ours.loss_module._actor_on_tensors
    assert {type(o) for o in stock.optimizers.values()} == {torch.optim.Adam}
    assert {type(o) for o in ours.optimizers.values()} == {LeanAdam}
    if ours.target_updater is not None:
        assert type(stock.target_updater) is SoftUpdate and type(ours.target_updater) is ForeachSoftUpdate
    assert not direct_collection(stock.config, stock.env_fn, stock.env)
    assert direct_collection(ours.config, ours.env_fn, ours.env)
    if algo == "dqn":
        assert type(stock.collect_policy) is TensorDictSequential and type(ours.collect_policy) is EGreedyQPolicy
    if algo == "crossq":
        norms = [m for m in stock.loss_module.qvalue_network.modules() if isinstance(m, BatchRenorm1d)]
        assert norms and not any(m.fast for m in norms)


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_the_fast_parts_learn_what_the_stock_parts_learn(tmp_path, algo):
    """The same run with each (TorchRL's collector on both sides: ``GymCollector`` draws its own random numbers,
    ``tests/test_gym_collector.py``): the same losses at every log row, the same evaluations."""
    runs = {}
    for fast_parts in ("true", "false"):
        p = pipeline(algo, f"fast={fast_parts}", "collector.direct=false", "num_iterations=200",
                     "initial_collect_steps=100", "log_interval=50", "eval_interval=200", "baseline_episodes=0", "num_eval_episodes=1",
                     "batch_size=32", "num_threads=1", "target_return=null")
        runs[fast_parts] = p.train(tmp_path / fast_parts, progress=False)
    rows = {k: [r for r in run.metrics if any(c.startswith("loss_") and r[c] for c in r)] for k, run in runs.items()}
    assert len(rows["true"]) == len(rows["false"]) >= 2
    for ours, stock in zip(rows["true"], rows["false"]):
        for column in (c for c in ours if c.startswith("loss_") and ours[c]):
            assert float(ours[column]) == pytest.approx(float(stock[column]), rel=1e-3, abs=1e-6), column
    returns = {k: [e["average_return"] for e in run.evaluations] for k, run in runs.items()}
    assert returns["true"] == pytest.approx(returns["false"], rel=1e-3)


@pytest.mark.unit
def test_a_changed_version_or_private_name_is_named():
    found = fast.problems(names=(("torch", ("_foreach_lerp_", "_no_such_kernel"), "a part"),
                                 ("torchrl.objectives.NoSuchLoss", ("_alpha",), "another part")),
                          versions={"torch": (1, 0)})
    assert found[0].startswith("torch ") and "checked against torch 1.0.x" in found[0]
    assert found[1:] == ["torch has no _no_such_kernel (used by a part)",
                         "torchrl.objectives.NoSuchLoss is gone (used by another part)"]
    assert fast.problems() == []  # this install: the versions the parts were checked against, every name there


def test_a_fast_run_on_a_torchrl_the_parts_were_not_checked_against_stops_in_one_line(monkeypatch):
    monkeypatch.setitem(fast.CHECKED_VERSIONS, "torchrl", (0, 99))  # as if TorchRL had moved on under us
    with pytest.raises(InputError) as refused:
        pipeline("sac")
    message = str(refused.value)
    assert len(message.splitlines()) == 1 and "checked against torchrl 0.99.x" in message and "fast=false" in message
    assert type(pipeline("sac", "fast=false").loss_module) is SACLoss  # the stock parts still run
