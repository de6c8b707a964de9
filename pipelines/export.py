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
import os
import tempfile
from pathlib import Path

import torch
from torch import nn

from rlpipe.pipelines.rundir import replace_readable

__all__ = ["export_policy", "load_exported_policy", "load_policy"]


def export_policy(module: nn.Module, observation_dim: int, folder: Path, info: dict) -> Path:
    """Export ``module`` (observations ``[B, observation_dim]`` -> actions ``[B, ...]``) atomically."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    module = module.eval()
    example = torch.zeros(2, observation_dim)
    batch = torch.export.Dim("batch", min=1, max=1 << 20)
    program = torch.export.export(module, (example,), dynamic_shapes=({0: batch},), strict=False)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".policy.", suffix=".pt2")
    os.close(fd)
    torch.export.save(program, tmp)
    replace_readable(tmp, folder / "policy.pt2")
    (folder / "policy.json").write_text(json.dumps({"observation_dim": observation_dim, **info}, indent=2) + "\n")
    return folder / "policy.pt2"


def load_exported_policy(folder: Path) -> nn.Module:
    return torch.export.load(Path(folder) / "policy.pt2").module()


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
    import logging

    logging.disable(logging.WARNING)  # torch.export logs a traceback of its own for a damaged file
    try:
        program = torch.export.load(path).module()
        info = json.loads((folder / "policy.json").read_text())
    except Exception as exc:  # torch.export raises many kinds on a damaged file
        raise InputError(f"{path}: corrupt or not an exported policy ({type(exc).__name__})") from exc
    finally:
        logging.disable(logging.NOTSET)
    return _AnyBatch(program), info
