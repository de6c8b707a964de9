"""The divergence check: a loss or parameter that turned NaN or infinite stops the run, unsaved (the tests make a
run diverge at an exact update through ``training.faults``)."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from rlpipe.pipelines.artifacts import checkpoint as ckpt
from rlpipe.pipelines.artifacts.rundir import RunDir
from rlpipe.pipelines.errors import InputError, TrainingDiverged
from rlpipe.pipelines.training.state import RunState

__all__ = ["check_finite"]


def check_finite(loss_sums: Mapping[str, torch.Tensor], module: nn.Module, state: RunState, run: RunDir) -> None:
    """Raise ``TrainingDiverged`` if a loss in ``loss_sums`` (those since the last log row) or a
    parameter of ``module`` is NaN or infinite.

    Nothing is saved then: every checkpoint passed this check, so the last one on disk is the
    run's last finite state, and ``--resume`` (with, say, a lower learning rate) continues from it.
    """
    # one device-to-host read for all of them: a few scalars per collected block
    tensors = [torch.as_tensor(v).reshape(-1) for v in loss_sums.values()]
    tensors += [p.detach().reshape(-1).isfinite().all().reshape(1) for p in module.parameters()]
    if not tensors or bool(torch.cat([t.float() for t in tensors]).isfinite().all()):
        return
    bad = [f"loss_{k}={float(v)}" for k, v in loss_sums.items() if not torch.as_tensor(v).isfinite().all()]
    try:
        last = f"the checkpoint {ckpt.latest_checkpoint(run.checkpoints)}"
    except InputError:
        last = "not saved (no checkpoint yet)"
    raise TrainingDiverged(
        f"training diverged by iteration {state.iteration} ({state.updates} updates): "
        f"{', '.join(bad) or 'a parameter'} is not finite; stopped without saving: the last finite state is "
        f"{last}; expected finite losses: lower the learning rates, then continue with --resume {run.path}"
    )
