"""Workarounds for Ray 2.60 (the version the ``ray`` extra pins: ``ray[default]==2.60.0``).

Each says what 2.60 does and when it can go; check both at each upgrade of the pin.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import threading
from collections.abc import Iterable, Iterator

__all__ = ["check_reachable", "stop_signals_kept"]


@contextlib.contextmanager
def stop_signals_kept(signals: Iterable[int]) -> Iterator[None]:
    """The process's handlers of ``signals`` as they were, whatever ``ray.init`` does to them.

    Ray 2.60's ``ray.init`` sets a SIGTERM handler of its own (``sys.exit``), and the driver's core
    worker then installs a C++ one over it that prints a stack and aborts (exit -6): a run's SIGTERM
    would no longer save a checkpoint (``runtime.DeferredInterrupt``). Setting the Python handlers
    again puts them back in front (main thread only, where Python handles signals at all). Delete when
    ``ray.init`` leaves the driver's signal handlers alone (not in 2.60)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = {signum: signal.getsignal(signum) for signum in signals}
    try:
        yield
    finally:
        for signum, handler in before.items():
            if handler is not None:  # None: not set from Python; nothing of ours to put back
                signal.signal(signum, handler)


def check_reachable(address: str) -> None:
    """Raise ``ConnectionError`` at once if nothing listens at ``address``: ``ray.init`` would retry
    its connection to the cluster's GCS for minutes (Ray 2.60), with no message a user can act on.
    Uses Ray's private ``canonicalize_bootstrap_address`` (what ``ray.init`` resolves "auto" with).
    Delete when ``ray.init`` takes a connection timeout (not in 2.60)."""
    if address.startswith("ray://"):  # Ray Client: its own handshake, with its own timeout
        return
    from ray._private.services import canonicalize_bootstrap_address

    try:
        host_port = canonicalize_bootstrap_address(address)  # "auto": the cluster this machine last started
    except ValueError as exc:
        raise ConnectionError(str(exc)) from exc
    if host_port is None:
        return
    host, _, port = host_port.rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=5.0).close()
    except (OSError, ValueError) as exc:
        raise ConnectionError(f"nothing listens at {host_port}: {exc}") from exc
