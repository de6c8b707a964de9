"""One replay batch: TorchRL's ``ReplayBuffer.sample`` with the batch gathered leaf by leaf.

The loop samples once per update. For the replay buffer every built-in pipeline makes (a plain
``ReplayBuffer`` over a ``LazyTensorStorage``, ``RandomSampler``, no transforms), the stock call
spends most of its time around the indexing: ``ReplayBuffer.sample`` ~88 us for a batch of 128 of
DQN's 6 stored keys on this 2-core CPU, of which ``LazyTensorStorage.get`` ~70 and a TensorDict
index ~40, for ~15 us of tensor indexing (8 leaves). ``sample`` takes the index from the buffer's
own sampler (same random numbers, same locks) and indexes each stored tensor into a TensorDict of the
same keys, shapes, dtypes and device: ~34 us (BENCHMARKS.md, "Where TorchRL's ~700 us a step go"). TorchRL
has no cheaper entry point for it. Any other
buffer (another sampler, storage or writer, transforms, prefetching, a collate function,
a storage that is not one level of nested plain tensors) goes through ``ReplayBuffer.sample``
unchanged; ``tests/test_sampling.py`` checks that both give the same batches.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.data.replay_buffers.storages.utils import _collate_id
from torchrl.data.replay_buffers.writers import RoundRobinWriter

__all__ = ["sample"]


def _plain(rb) -> bool:
    transform = rb._transform
    return (type(rb) is ReplayBuffer and type(rb._sampler) is RandomSampler
            and type(rb._storage) is LazyTensorStorage and type(rb._writer) is RoundRobinWriter
            and rb._collate_fn is _collate_id and rb._batch_size is not None and not rb._prefetch and rb._sample_unit is None
            and not (transform is not None and len(transform)) and not rb._service_shutdown
            and rb._sample_dependency is None and not (rb._delayed_init and not rb.initialized)
            and rb._storage.initialized and rb._storage.ndim == 1 and type(rb._storage._storage) is TensorDict)


def _gather(td: TensorDict, index: torch.Tensor, depth: int = 0) -> TensorDict | None:
    out = {}
    for key, value in td._tensordict.items():
        if type(value) is torch.Tensor or type(value) is torch.nn.Parameter:
            out[key] = value[index]
        elif type(value) is TensorDict and depth == 0 and value.batch_size == td.batch_size and value.device == td.device:
            inner = _gather(value, index, 1)
            if inner is None:
                return None
            out[key] = inner
        else:
            return None
    return TensorDict._new_unsafe(out, batch_size=index.shape, device=td.device)


def sample(rb):
    """``rb.sample()``: the same batch, gathered directly where ``rb`` is a plain one (see the module docstring)."""
    if not _plain(rb):
        return rb.sample()
    with rb._replay_lock, rb._write_lock:
        index, _ = rb._sampler.sample(rb._storage, rb._batch_size)
        stored = rb._storage._storage
        data = None
        if type(index) is torch.Tensor and index.ndim == 1 and stored.device is not None:
            data = _gather(stored, index.to(stored.device))  # as TorchRL's _storage_index moves it
        if data is None:  # the index is drawn: the stock lookup from here on
            data = rb._storage.get(index)  # LazyTensorStorage's own collate is the identity
    return data
