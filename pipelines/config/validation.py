"""The one place that validates a config: each key's declared rule, the rules between keys, and this machine's
checks (the device exists, thread and process counts fit its CPUs)."""

from __future__ import annotations

import importlib.util
import math
import os

from rlpipe.pipelines.config.schema import COLLECTOR_BACKENDS, LOGGERS, WORKERS_PER_CPU, _checks, _get, flat_keys
from rlpipe.pipelines.errors import InputError

__all__ = ["available_devices", "check_learning_rate_schedule", "check_machine", "validate"]


def validate(cfg, *, machine: bool = True) -> None:
    """Raise ``InputError`` naming the first key whose value cannot work, and what it must be.

    ``machine=True`` also checks what depends on this machine (the device exists, thread and
    process counts within its CPUs); a saved config (``config_from_dict``) skips those, so a run
    moved to another machine can be resumed with the keys changed there.
    """
    rules = _checks(type(cfg))
    for key in flat_keys(type(cfg)):
        value = _get(cfg, key)
        if value is None:
            continue
        if isinstance(value, float) and not math.isfinite(value):
            raise InputError(f"{key}={value}: expected a finite number")
        check = rules.get(key)
        if check is not None and not check.ok(value):
            shown = repr(value) if isinstance(value, str) else value
            raise InputError(f"{key}={shown}: expected {check.describe(value)}")
    # Rules between keys: here, or in an algorithm config's ``validate_extra`` for its own keys.
    if cfg.cudagraph and str(cfg.device).split(":")[0] != "cuda":
        raise InputError(f"cudagraph=true with device={cfg.device!r}: CUDA graphs need device=cuda; expected "
                         "cudagraph=false or null on this device")
    package = LOGGERS.get(cfg.logger)
    if package and importlib.util.find_spec(package) is None:
        raise InputError(f"logger={cfg.logger}: {package} is not installed; expected `pip install 'rlpipe[{cfg.logger}]'` "
                         "(or logger=tensorboard)")
    c = cfg.collector
    needs = COLLECTOR_BACKENDS[c.backend]  # a known name: its field's rule ran above
    if needs.package and importlib.util.find_spec(needs.package) is None:
        raise InputError(f"collector.backend={c.backend}: {needs.package} is not installed; expected "
                         f"`pip install 'rlpipe[{needs.package}]'` (or collector.backend=local)")
    if c.policy_device and c.backend != "local":
        raise InputError(f"collector.policy_device={c.policy_device!r} with collector.backend={c.backend}: a CPU copy "
                         "of the collect policy is made by the local backend's collectors; expected "
                         "collector.policy_device='' with this backend")
    per_block = c.envs_per_worker * (c.workers if c.sync else 1)
    if c.envs_per_worker > 1 and c.frames_per_batch % per_block:
        raise InputError(
            f"collector.frames_per_batch={c.frames_per_batch} does not split into whole steps of "
            f"{per_block} envs (collector.workers={c.workers} x collector.envs_per_worker={c.envs_per_worker}"
            f"{'' if c.sync else ', one worker per block'}): expected a multiple of {per_block}"
        )
    if needs.even_sync_blocks and c.sync and c.frames_per_batch % c.workers:
        raise InputError(f"collector.frames_per_batch={c.frames_per_batch} does not split evenly over "
                         f"collector.workers={c.workers} {needs.what} (collector.sync=true): expected a multiple of {c.workers}")
    if cfg.batch_size > cfg.replay_buffer_capacity:
        raise InputError(
            f"batch_size={cfg.batch_size} is larger than replay_buffer_capacity={cfg.replay_buffer_capacity}: "
            "expected batch_size <= replay_buffer_capacity"
        )
    cfg.validate_extra()
    if machine:
        check_machine(cfg)


def available_devices() -> list[str]:
    """The torch devices this machine can train on: 'cpu', then 'cuda:0', ... and 'mps' where present."""
    import torch

    devices = ["cpu"]
    if torch.cuda.is_available():
        devices += [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        devices.append("mps")
    return devices


def _cpus() -> int:
    return os.cpu_count() or 1


def check_machine(cfg) -> None:
    """What ``validate`` checks against this machine: the device exists, thread and worker counts fit its CPUs."""
    import torch

    try:
        device = torch.device(cfg.device)
    except (RuntimeError, TypeError) as exc:
        raise InputError(f"device={cfg.device!r}: expected a torch device such as 'cpu' or 'cuda:0'") from exc
    devices = available_devices()
    same_type = [d for d in devices if d.split(":")[0] == device.type]
    known = same_type if device.index is None or device.type == "cpu" else [f"{device.type}:{device.index}"]
    if not set(known) & set(same_type):
        why = "torch sees no CUDA device on this machine" if device.type == "cuda" else "not a device this machine trains on"
        raise InputError(f"device={cfg.device!r}: {why}; expected one of this machine's devices: {', '.join(devices)}")
    cpus = _cpus()
    if cfg.num_threads > cpus:
        raise InputError(f"num_threads={cfg.num_threads}: more threads than this machine's {cpus} CPUs only slow torch "
                         f"down; expected -1 (chosen at start), 0 (torch's default) or at most {cpus}")
    most = WORKERS_PER_CPU * cpus
    if cfg.collector.workers > most:
        raise InputError(f"collector.workers={cfg.collector.workers}: each is a process of its own; expected at most "
                         f"{most} on this machine's {cpus} CPUs")


def check_learning_rate_schedule(cfg) -> None:
    """``learning_rate_final_fraction`` moves the optimisers' learning rates, which a compiled or graphed
    update would keep at the values it was traced with: refused there, in one line."""
    if cfg.learning_rate_final_fraction is None:
        return
    for key in ("compile", "cudagraph"):
        if getattr(cfg, key):
            raise InputError(f"learning_rate_final_fraction={cfg.learning_rate_final_fraction} with {key}=true: a "
                             f"compiled or graphed update keeps the learning rates it was traced with; expected "
                             f"learning_rate_final_fraction=null or {key}=false")
