"""The update replayed as CUDA graphs (``device=cuda`` with ``compile=true``, or ``cudagraph=true``).

On a GPU, one SAC or TD3 update of the tutorials' networks is a few hundred small kernels, and
launching them from Python costs more than running them: the GPU waits on the CPU. A CUDA graph
records the kernels once and replays them with one launch. tensordict's ``CudaGraphModule`` does
the recording and replay (what LeanRL uses for CleanRL's scripts); this module adds what an
rlpipe update needs around it, and nothing else:

- an update branches on its index in Python (SAC's and DQN's target update every
  ``target_update_period`` updates, SAC's and TD3's delayed actor, TD3's targets), and a graph cannot
  branch: one graph per branch pattern, each recorded with a representative index
  (``canonical_index``), so a run of any length records at most a handful;
- the replay batch is handed to the graph as a flat tuple of tensors (keys fixed at the first
  call), and rebuilt as a TensorDict inside it, so the pipeline's own ``update`` runs unchanged.

CUDA graphs can give silently wrong results (an update whose Python reads a tensor's value, a
shape that changes): ``tests/test_update_graph.py`` checks, on a GPU, that the graphed updates
leave the same parameters as eager ones after N updates on the same batches.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import CudaGraphModule

__all__ = ["GraphedUpdate", "canonical_index"]


def canonical_index(update_index: int, periods: Sequence[int]) -> int:
    """The smallest index that takes the same branches as ``update_index``.

    ``periods`` are the intervals the update tests with ``update_index % p == 0`` (TD3's
    ``[policy_delay, policy_delay * target_update_period]``, SAC's ``[policy_delay,
    target_update_period]``): the least common multiple of those that divide ``update_index`` (1
    when none does), which every one of them divides and no other (a period dividing it would divide
    ``update_index``). Two indices with the same canonical index run the same code, so they can share
    one recorded graph.
    """
    return math.lcm(1, *(int(p) for p in periods if update_index % p == 0))


class GraphedUpdate:
    """``update(batch, update_index)`` as CUDA graphs, one per branch pattern.

    Args:
        update: the pipeline's update (``OffPolicyPipeline.update``), optionally compiled.
        periods: the index periods the update branches on (see ``canonical_index``).
        warmup: eager calls per graph before it is recorded (compiled code needs two or three
            before its compilation settles).
    """

    def __init__(self, update: Callable[[TensorDictBase, int], dict], periods: Sequence[int], warmup: int = 3):
        self.update = update
        self.periods = [int(p) for p in periods]
        self.warmup = warmup
        self.graphs: dict[int, CudaGraphModule] = {}
        self.keys: list | None = None
        self.batch_size: torch.Size | None = None

    def __call__(self, batch: TensorDictBase, update_index: int) -> dict[str, torch.Tensor]:
        if self.keys is None:
            self.keys = sorted(batch.keys(True, True), key=str)
            self.batch_size = batch.batch_size
        elif batch.batch_size != self.batch_size:
            raise ValueError(f"a CUDA-graph update needs one batch shape; got {tuple(batch.batch_size)} after "
                             f"{tuple(self.batch_size)}")
        index = canonical_index(update_index, self.periods)
        graph = self.graphs.get(index)
        if graph is None:
            graph = self.graphs[index] = CudaGraphModule(self._step_at(index), warmup=self.warmup)
        return graph(*(batch.get(k) for k in self.keys))

    def _step_at(self, index: int):
        keys, batch_size, update = self.keys, self.batch_size, self.update

        def step(*tensors: torch.Tensor) -> dict[str, torch.Tensor]:
            batch = TensorDict(dict(zip(keys, tensors)), batch_size=batch_size, device=tensors[0].device)
            return update(batch, index)

        return step
