"""The version workarounds in ``pipelines/compat/`` still do their job on the installed versions: each
check fails when an upgrade changes what a workaround relies on (then delete or adapt that workaround)."""

import inspect
import os
import signal
import socket
from datetime import timedelta

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

from rlpipe.pipelines.artifacts.checkpoint import load_replay_buffer, replay_buffer_state
from rlpipe.pipelines.compat.ray import check_reachable, stop_signals_kept
from rlpipe.pipelines.compat.torch import stderr_kept_on_success
from rlpipe.pipelines.compat.torchrl import ray_weight_sync_deadline, write_cursor


def test_a_full_replay_buffer_saves_oldest_first_so_fifo_eviction_resumes_in_order():
    rb = ReplayBuffer(storage=LazyTensorStorage(5))
    rb.extend(TensorDict({"x": torch.arange(7)}, batch_size=[7]))  # 5 and 6 overwrote 0 and 1
    assert write_cursor(rb) == 2
    state = replay_buffer_state(rb)
    assert state["data"]["x"].tolist() == [2, 3, 4, 5, 6]
    again = ReplayBuffer(storage=LazyTensorStorage(5))
    load_replay_buffer(again, state)
    again.extend(TensorDict({"x": torch.tensor([7])}, batch_size=[1]))  # evicts the oldest, 2
    assert sorted(again[:]["x"].tolist()) == [3, 4, 5, 6, 7]


def test_stderr_is_passed_on_after_a_block_that_succeeds_and_held_back_after_one_that_fails(capfd):
    with stderr_kept_on_success():
        os.write(2, b"kept\n")
    with pytest.raises(RuntimeError), stderr_kept_on_success():
        os.write(2, b"the whole graph\n")
        raise RuntimeError("export failed")
    err = capfd.readouterr().err
    assert "kept" in err and "the whole graph" not in err


def test_the_stop_signal_handlers_come_back_after_a_block_that_replaced_them():
    def ours(signum, frame):
        pass

    before = signal.signal(signal.SIGTERM, ours)
    try:
        with stop_signals_kept([signal.SIGTERM]):
            signal.signal(signal.SIGTERM, signal.SIG_DFL)  # what ray.init does to the driver
        assert signal.getsignal(signal.SIGTERM) is ours
    finally:
        signal.signal(signal.SIGTERM, before)


def test_an_address_where_nothing_listens_is_refused_at_once():
    pytest.importorskip("ray")
    with socket.socket() as s:  # a port that was free a moment ago: nothing listens there now
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ConnectionError, match="nothing listens"):
        check_reachable(f"127.0.0.1:{port}")


def test_the_ray_weight_sync_waits_as_long_as_a_workers_start_up_may():
    """TorchRL 0.14's RayWeightSyncScheme gives the learner and each collector actor 60 s to join its Gloo group
    (``_DIST_TIMEOUT``, read when each side connects): an actor still importing TorchRL a minute in, on a machine
    whose cores another job holds, would end the run with ``DistStoreError``. ``ray_weight_sync_deadline`` (called
    by the Ray backend in the learner and by each actor with the run's start-up deadline, at least 300 s) sets
    it; this fails when an upgrade moves that deadline."""
    from torchrl.weight_update import _ray

    source = inspect.getsource(_ray)
    assert source.count("timeout=_DIST_TIMEOUT") >= 2  # the learner's store and each actor's, read at connect time
    assert source.count("ProcessGroupGloo(") == source.count("world_size, _DIST_TIMEOUT")  # and each Gloo group
    before = _ray._DIST_TIMEOUT
    try:
        ray_weight_sync_deadline(300)
        assert _ray._DIST_TIMEOUT == timedelta(seconds=300)
    finally:
        _ray._DIST_TIMEOUT = before
