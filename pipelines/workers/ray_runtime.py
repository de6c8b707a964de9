"""A run's hold on Ray, shared by the Ray collector backend (``ray``) and the Ray evaluator (``ray_eval``):
joining a cluster or starting a local instance, and the checks made before anything is placed on it
(an address nothing answers at, a cluster short of the CPUs the actors ask for)."""

from __future__ import annotations

import math
import os

from rlpipe.pipelines.compat.ray import check_reachable, stop_signals_kept
from rlpipe.pipelines.config import TrainConfig
from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.system.runtime import STOP_SIGNALS
from rlpipe.pipelines.workers.supervision import first_line

__all__ = ["RayRuntime", "check_address", "check_cpus"]


class RayRuntime:
    """This run's hold on Ray: joins ``address`` or starts a local instance; ``close`` leaves a joined cluster up.

    A Ray already initialised in this process (a user's own program) is used as it is and left as it was.
    """

    def __init__(self, address: str, cpus_needed: float):
        import ray

        self.address = address
        self.started = False
        if ray.is_initialized():
            return
        # log_to_driver=False: Ray would print each actor's multi-line repr into the run's output; an
        # actor's failure still reaches the learner, as the exception of the block it owed.
        common = dict(include_dashboard=False, logging_level="error", configure_logging=True, log_to_driver=False)
        try:
            with stop_signals_kept(STOP_SIGNALS):
                if address:
                    check_reachable(address)
                    ray.init(address=address, **common)
                else:
                    # "local" rather than None: None would join whichever cluster was started last on this
                    # machine. Ray's CPUs are logical: as many as the workers ask for, at least the cores.
                    ray.init(address="local", num_cpus=max(os.cpu_count() or 1, math.ceil(cpus_needed)), **common)
        except ConnectionError as exc:
            raise _address_error(address, exc) from exc
        self.started = True

    def close(self) -> None:
        """Disconnect; a local instance this run started is shut down with its processes."""
        import ray

        if self.started and ray.is_initialized():
            ray.shutdown()
        self.started = False


def check_cpus(ray, config: TrainConfig, *, evaluator: bool = False) -> None:
    """``InputError`` unless the cluster has the CPUs the collector actors ask for (and, with
    ``evaluator``, the background evaluator's actor as well): short of them, an actor would wait for
    Ray to place it for good."""
    c, r = config.collector, config.ray
    needed = (c.workers + evaluator) * r.num_cpus_per_worker
    total = ray.cluster_resources().get("CPU", 0.0)
    if total >= needed:
        return
    where = f"the Ray cluster at {r.address!r}" if r.address else "the local Ray instance"
    if evaluator:
        raise InputError(f"collector.workers={c.workers} collector actors and the background evaluator's, "
                         f"x ray.num_cpus_per_worker={r.num_cpus_per_worker:g}, need {needed:g} CPUs; {where} has "
                         f"{total:g}: expected fewer workers, a smaller ray.num_cpus_per_worker, more nodes, "
                         "or eval_in_background=false")
    raise InputError(f"collector.workers={c.workers} x ray.num_cpus_per_worker={r.num_cpus_per_worker:g} needs "
                     f"{needed:g} CPUs; {where} has {total:g}: expected fewer workers, a smaller "
                     "ray.num_cpus_per_worker, or more nodes")


def check_address(address: str) -> None:
    """``InputError`` at once if nothing answers at ``address`` (empty: a local instance, nothing to
    check); the run calls it before it writes anything, so such a command leaves nothing behind."""
    if not address:
        return
    try:
        check_reachable(address)
    except ConnectionError as exc:
        raise _address_error(address, exc) from exc


def _address_error(address: str, exc: BaseException) -> InputError:
    return InputError(f"ray.address={address!r}: no Ray cluster answers there ({first_line(exc)}); "
                      "expected the address `ray start --head` printed, 'auto' on one of its nodes, "
                      "or empty to start a local Ray instance")
