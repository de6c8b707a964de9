"""The fast parts: where rlpipe re-implements a TorchRL or torch part for speed, and nowhere else.

Each part computes what the stock part computes (same parameters, state dicts, keys, random draws in the same
order) and is held equal to it by a test; it exists because the stock part spends several times its arithmetic
in per-call Python on the small networks and batches of a CPU run. ``fast=false`` (a config key of every
pipeline) puts every stock part back at once: the stock losses, ``torch.optim.Adam``, ``SoftUpdate``,
``ReplayBuffer.sample``, TorchRL's ``Collector`` over ``GymEnv``, ``env.rollout`` for evaluations, the stock
exploration modules and ``BatchRenorm1d``. ``tests/test_fast.py`` trains one run each way.

| stock part (TorchRL 0.14, torch 2.13) | ours | why (2-core CPU, one thread) | held equal by |
|---|---|---|---|
| `SACLoss` (v2) | `sac_loss.LeanSACLoss` | ~18 ms an update at batch 256, (256, 256) nets, for ~6 ms of matmuls | tests/test_sac_loss.py |
| `CrossQLoss` | `crossq_loss.LeanCrossQLoss` | TensorDict copies and vmap around each network call (BENCHMARKS.md, "CrossQ against SAC, per update") | tests/test_crossq.py |
| `DQNLoss` | `dqn_loss.LeanDQNLoss` | ~1.8 ms an update for ~0.01 ms of matmuls | tests/test_dqn_loss.py |
| `TD3Loss`'s network calls | `modules/td3_loss.py`'s `TD3AblationLoss` on tensors (`tensor_nets`); the loss itself is the tutorial's (its target noise in normalised action units, its ablation switches), with `fast=false` too | ~3 ms a forward at batch 256 for ~0.3 ms of matmuls | tests/test_td3_loss.py |
| `BatchRenorm1d`'s training forward | `modules/critics.py`'s `BatchRenorm1d` (its warm-up count held with `fast=false` too: a TorchRL 0.14 bug) | CrossQ's update 38.9 -> 13.6 ms | tests/test_crossq.py |
| `torch.optim.Adam(fused=True)` | `optim.LeanAdam` | a step of TD3's critics ~47 -> ~28 us | tests/test_optim.py (bitwise) |
| `SoftUpdate.step` | `target_updates.ForeachSoftUpdate` | one `_foreach_lerp_` for a loop of TensorDict ops | tests/test_td3_loss.py |
| `ReplayBuffer.sample` | `sampling.sample` | ~88 -> ~34 us a batch of 128 of DQN's keys | tests/test_sampling.py |
| `QValueActor` + `EGreedyModule`, `EGreedyModule.step` | `exploration.EGreedyQPolicy`, `anneal_epsilon` | ~0.3 ms a call for a few us of arithmetic: 18% of a `dqn` iteration; ~120 us a block of 10 | tests/test_dqn.py |
| collect and greedy policies through TensorDicts | `tensor_policy.tensor_step`, `greedy_step` | 150-300 us a call -> ~25 us | tests/test_gym_collector.py, tests/test_evaluation.py |
| `Collector` over `GymEnv` | `pipelines/workers/gym_collector.py` (a collector, so it lives with the workers) | BENCHMARKS.md, "Collection: env steps per second" | tests/test_gym_collector.py: TorchRL's keys, shapes, dtypes and episode bookkeeping; its own random draws (the same seed, the same blocks, not TorchRL's numbers) |
| `env.rollout` for evaluations | `pipelines/workers/evaluation.py` (`_evaluate_directly`) | the same episodes at a fraction of the cost (BENCHMARKS.md) | tests/test_evaluation.py |

The figures are those each module's docstring gives with how they were measured. Together, on a whole run: the
``sac-pendulum`` preset reaches -200 in 14.5 s (median of 5 seeds) with them and in 25.7 s with ``fast=false``, after
as many env steps (BENCHMARKS.md, "The fast parts against TorchRL's own"). ``tensor_nets`` holds what the losses share (TorchRL ``MLP``s run from flat parameter
dicts, one copy or stacked twins).

Private names: this room (and the two worker modules in the table) are the only code in rlpipe that reads
TorchRL's or torch's private names for speed. ``PRIVATE_NAMES`` lists them; ``problems()`` checks that each is
still there and that TorchRL and torch are the versions these parts were checked equal against, and a pipeline
with ``fast=true`` refuses to start with one line naming what changed (``fast=false`` runs on the stock parts).
A renamed attribute would otherwise be an ``AttributeError`` deep in an update, and a changed meaning a silently
different number. Private names read elsewhere, for other reasons than speed: ``pipelines/compat`` (workarounds
of TorchRL 0.14's bugs, each saying when it can go), ``modules/frames.py`` (the frame-stacking buffer calls its
``ReplayBuffer`` base's sampler and storage) and ``pipelines/workers/ray.py`` (TorchRL's ``_TrajectoryPool``).
"""

from __future__ import annotations

import importlib

import torch
import torchrl

__all__ = ["CHECKED_VERSIONS", "PRIVATE_NAMES", "problems"]

CHECKED_VERSIONS = {"torch": (2, 13), "torchrl": (0, 14)}
"""The (major, minor) versions the fast parts were checked equal against (the tests above)."""

def _adam() -> torch.optim.Adam:
    return torch.optim.Adam([torch.zeros(1, requires_grad=True)])


def _replay_buffer():
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    return ReplayBuffer(storage=LazyTensorStorage(1), batch_size=1)


def _tensordict():
    from tensordict import TensorDict

    return TensorDict({}, [])


# an owner that is an instance: private attributes set in ``__init__`` are not on the class
_INSTANCES = {"an Adam": _adam, "a ReplayBuffer": _replay_buffer, "a TensorDict": _tensordict}

PRIVATE_NAMES: tuple[tuple[str, tuple[str, ...], str], ...] = (
    ("torch", ("_fused_adam_", "_foreach_add_", "_foreach_norm", "_foreach_mul_", "_foreach_lerp_"),
     "optim, target_updates, SAC's policy averaging"),
    ("torch.optim.optimizer", ("_global_optimizer_pre_hooks", "_global_optimizer_post_hooks"), "optim.LeanAdam"),
    ("an Adam", ("_optimizer_step_pre_hooks", "_optimizer_step_post_hooks"), "optim.LeanAdam"),
    ("torch.nn.modules.module", ("_global_forward_hooks", "_global_forward_pre_hooks"), "tensor_nets.module_forward"),
    ("torchrl.objectives.SACLoss", ("_alpha", "_alpha_loss"), "sac_loss, crossq_loss"),
    ("torchrl.objectives.LossModule", ("_reduce_loss", "_maybe_get_priority_weight"), "the lean losses"),
    ("torchrl.modules.AdditiveGaussianModule", ("_add_noise",), "tensor_policy"),
    ("torchrl.data.replay_buffers.storages.utils", ("_collate_id",), "sampling.sample"),
    ("a ReplayBuffer", ("_replay_lock", "_write_lock", "_sampler", "_storage", "_writer", "_batch_size", "_transform",
                        "_collate_fn", "_prefetch", "_sample_unit", "_service_shutdown", "_sample_dependency",
                        "_delayed_init"), "sampling.sample"),
    ("a TensorDict", ("_tensordict", "_new_unsafe"), "sampling.sample"),
    ("torchrl._utils", ("seed_generator",), "pipelines/workers/gym_collector.py"),
)
"""``(module, class or instance, its private names, the parts that use them)``."""


def _resolve(owner: str):
    if owner in _INSTANCES:
        return _INSTANCES[owner]()
    try:
        return importlib.import_module(owner)
    except ImportError:
        module, _, attr = owner.rpartition(".")
        return getattr(importlib.import_module(module), attr)


def problems(names: tuple[tuple[str, tuple[str, ...], str], ...] | None = None,
             versions: dict[str, tuple[int, int]] | None = None) -> list[str]:
    """What keeps the fast parts from being the stock parts' equal here: a version other than the one they were
    checked against (``CHECKED_VERSIONS``), or a private name that is gone (``PRIVATE_NAMES``); each a short
    phrase, none where all is well."""
    names = PRIVATE_NAMES if names is None else names
    versions = CHECKED_VERSIONS if versions is None else versions
    found = []
    for name, module in (("torch", torch), ("torchrl", torchrl)):
        installed = tuple(int(part) for part in module.__version__.split("+")[0].split(".")[:2])
        if name in versions and installed != versions[name]:
            want = ".".join(map(str, versions[name]))
            found.append(f"{name} {module.__version__} (the fast parts were checked against {name} {want}.x)")
    for owner, attrs, user in names:
        try:
            resolved = _resolve(owner)
        except (ImportError, AttributeError):
            found.append(f"{owner} is gone (used by {user})")
            continue
        gone = [attr for attr in attrs if not hasattr(resolved, attr)]
        if gone:
            found.append(f"{owner} has no {', '.join(gone)} (used by {user})")
    return found
