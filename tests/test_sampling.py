"""The loop's replay sample (``modules/fast/sampling.sample``) gives what ``ReplayBuffer.sample`` gives."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.envs.transforms import Compose, RenameTransform

from rlpipe.modules.fast.sampling import sample


def _transitions(n: int) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    return TensorDict({
        "observation": torch.randn(n, 3, generator=g), "action": torch.randint(0, 2, (n,), generator=g),
        "next": {"observation": torch.randn(n, 3, generator=g), "reward": torch.randn(n, 1, generator=g),
                 "done": torch.rand(n, 1, generator=g) < 0.1, "terminated": torch.rand(n, 1, generator=g) < 0.1},
    }, batch_size=[n])


def _same(a: TensorDict, b: TensorDict) -> None:
    assert type(a) is type(b) and a.batch_size == b.batch_size and a.device == b.device
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert a[key].dtype == b[key].dtype and torch.equal(a[key], b[key]), key
    assert a["next"].batch_size == b["next"].batch_size


def _buffer(**kwargs) -> ReplayBuffer:
    rb = ReplayBuffer(storage=LazyTensorStorage(500), batch_size=32, **kwargs)
    rb.extend(_transitions(300))
    return rb


@pytest.mark.parametrize("kind", ["plain", "another sampler", "transform"])
def test_the_loop_samples_the_batches_torchrls_sample_gives(kind):
    extra = {"plain": dict, "another sampler": lambda: {"sampler": SamplerWithoutReplacement()},
             "transform": lambda: {"transform": Compose(RenameTransform(["action"], ["act"]))}}[kind]
    ours, stock = _buffer(**extra()), _buffer(**extra())
    torch.manual_seed(3)
    mine = [sample(ours) for _ in range(5)]
    ours.extend(_transitions(400))  # past the capacity: the writer wraps round
    mine += [sample(ours) for _ in range(5)]
    torch.manual_seed(3)
    theirs = [stock.sample() for _ in range(5)]
    stock.extend(_transitions(400))
    theirs += [stock.sample() for _ in range(5)]
    for a, b in zip(mine, theirs, strict=True):
        _same(a, b)
    # the batch is a copy: writing into it leaves the stored transitions alone
    before = ours._storage._storage["observation"].clone()
    mine[0]["observation"].add_(1.0)
    assert torch.equal(ours._storage._storage["observation"], before)
