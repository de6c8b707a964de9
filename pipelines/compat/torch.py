"""Workarounds for torch 2.13 (the pinned range: ``torch>=2.13,<2.14``).

Each says what 2.13 does and when it can go; check it at each upgrade of the pin.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator

__all__ = ["stderr_kept_on_success"]


@contextlib.contextmanager
def stderr_kept_on_success() -> Iterator[None]:
    """Hold back what is written to fd 2 in the block; pass it on unless the block raises.

    torch 2.13's TorchScript ONNX exporter turns its C++ log on for every export
    (``setup_onnx_logging`` tests the function ``_jit_is_onnx_log_enabled`` instead of calling it)
    and so prints the whole graph to stderr when an export fails; the caller's warning says why
    instead. Delete this when torch's check calls the function (still so in 2.13).
    """
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        ok = False
        try:
            yield
            ok = True
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            if ok:
                held.seek(0)
                if text := held.read():
                    os.write(2, text)
