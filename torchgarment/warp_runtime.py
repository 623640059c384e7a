"""NVIDIA Warp, initialized once and quietly (a dependency: anny uses it, and torchgarment runs its mesh
proximity queries, :mod:`torchgarment.sdf.proximity`, on Warp's CPU BVH).

Warp prints a version banner (stdout) when it initializes and, on machines without a CUDA driver, a "Warp
CUDA warning: Could not find or load the NVIDIA CUDA driver" line from native code (stderr, issue 17). The
banner is silenced through Warp's settings, the native line by pointing file descriptor 2 at /dev/null for the
duration of the init only.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from types import ModuleType


@contextmanager
def muted_stderr() -> Iterator[None]:
    """Point file descriptor 2 (native code's stderr included) at /dev/null inside the block; exceptions
    propagate unchanged."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def import_warp() -> ModuleType:
    """The ``warp`` module, initialized (once per process) without its banner and CUDA-driver line."""
    import warp

    if not getattr(warp, "_torchgarment_initialized", False):
        warp.config.log_level = logging.ERROR
        warp.config.quiet = True
        with muted_stderr():
            warp.init()
        warp._torchgarment_initialized = True
    return warp
