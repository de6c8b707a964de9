"""The exported policy: TF-Agents' saved policy, as a ``torch.export`` program.

``policy/policy.pt2`` loads with torch alone — no rlpipe, no config — and maps a batch of
observations to actions::

    import torch
    policy = torch.export.load("RUN/policy/policy.pt2").module()
    action = policy(torch.as_tensor(obs, dtype=torch.float32)[None])[0]

``policy/policy.json`` says what goes in and comes out.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import torch
from torch import nn

from rlpipe.pipelines.files import atomic_path, write_json_atomic

__all__ = ["export_policy", "load_policy"]


def export_policy(module: nn.Module, observation_dim: int, folder: Path, info: dict) -> Path:
    """Export ``module`` (observations ``[B, observation_dim]`` -> actions ``[B, ...]``) atomically."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    module = module.eval()
    example = torch.zeros(2, observation_dim)
    batch = torch.export.Dim("batch", min=1, max=1 << 20)
    program = torch.export.export(module, (example,), dynamic_shapes=({0: batch},), strict=False)
    with atomic_path(folder / "policy.pt2", suffix=".pt2") as tmp:
        torch.export.save(program, tmp)
    write_json_atomic(folder / "policy.json", {"observation_dim": observation_dim, **info})
    return folder / "policy.pt2"


class _AnyBatch(nn.Module):
    """Lets the exported program (batched input) also take a single observation."""

    def __init__(self, program: nn.Module):
        super().__init__()
        self.program = program

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        if observation.dim() == 1:
            return self.program(observation.unsqueeze(0)).squeeze(0)
        return self.program(observation)


def load_policy(folder: Path) -> tuple[nn.Module, dict]:
    """The exported policy of a run (``RUN/policy``) and its description; ``InputError`` if unusable."""
    from rlpipe.pipelines.errors import InputError

    folder = Path(folder)
    path = folder / "policy.pt2"
    if not path.exists():
        raise InputError(f"{path}: no exported policy; expected a run that finished or saved its policy")
    # torch.export logs a traceback of its own for a damaged file; the caller's own
    # logging.disable level is kept while loading and restored after.
    disabled = logging.root.manager.disable
    logging.disable(max(disabled, logging.WARNING))
    try:
        program = torch.export.load(path).module()
        info = json.loads((folder / "policy.json").read_text())
    except Exception as exc:  # torch.export raises many kinds on a damaged file
        raise InputError(f"{path}: corrupt or not an exported policy ({type(exc).__name__})") from exc
    finally:
        logging.disable(disabled)
    return _AnyBatch(program), info
