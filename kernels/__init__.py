"""OpenCL sources of the built-in stages: plain OpenCL C, one file per stage, shared headers (camera.h,
silhouette.h) included with ``#include "NAME"``. Shipped as package data; ``source(NAME)`` is the path the
OpenCL runtime (nodegraph.clrt) builds and the cache fingerprints."""
from __future__ import annotations

from pathlib import Path

KERNEL_DIR = Path(__file__).resolve().parent


def source(name: str) -> Path:
    """Path of the OpenCL source ``kernels/NAME``."""
    p = KERNEL_DIR / name
    if not p.is_file():
        raise FileNotFoundError(f"OpenCL source '{name}' not found in {KERNEL_DIR}")
    return p
