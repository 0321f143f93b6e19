"""The environment a result is computed in: one component of every cache key (``environment``), so a cache
shared between machines or kept across an upgrade never hands out numbers another environment made.

It holds
  - the installed versions of the libraries whose upgrade can change numbers (read from the installed
    distributions' metadata, never by importing them; None when one is not installed);
  - the OpenCL device a worker of this process uses (platform name and version, device name, driver version:
    ``clrt.device_id`` of the device ``clrt`` chooses, as VOLCAP_CL_DEVICE asks), or None when there is none.
Both are read once per process (the device once per VOLCAP_CL_DEVICE value). Choosing the device builds no
kernel here: it reads the ranking ``clrt`` keeps per machine (on a machine never ranked, the ranking runs once,
as the first OpenCL node would run it).

``explain`` names what moved, e.g. ``environment.libraries.numpy``: after an upgrade, that is why everything
reruns.
"""
from __future__ import annotations

import os
from functools import lru_cache
from importlib import metadata

# name in the key -> the distributions that provide it (the first installed one counts)
LIBRARIES: dict[str, tuple[str, ...]] = {
    "numpy": ("numpy",),
    "scipy": ("scipy",),
    "pyopencl": ("pyopencl",),
    "opencv": ("opencv-python", "opencv-python-headless", "opencv-contrib-python", "opencv-contrib-python-headless"),
    "trimesh": ("trimesh",),
    "scikit-image": ("scikit-image",),
    "fast-simplification": ("fast-simplification",),
    "usd-core": ("usd-core",),
    "pygltflib": ("pygltflib",),
    "DracoPy": ("DracoPy",),
    "Pillow": ("Pillow",),
    "OpenEXR": ("OpenEXR",),
    "cvxopt": ("cvxopt",),          # CHOLMOD for track's normal equations, optional (nodes/common/cholesky.py)
}


def _version(distributions: tuple[str, ...]) -> str | None:
    for name in distributions:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return None


@lru_cache(maxsize=None)
def library_versions() -> dict[str, str | None]:
    """Name -> installed version (None when not installed) of every library in LIBRARIES."""
    return {name: _version(dists) for name, dists in LIBRARIES.items()}


@lru_cache(maxsize=None)
def _device(wanted: str) -> str | None:
    from . import clrt

    try:
        return clrt.device_id(clrt._choose_device())
    except Exception:  # no OpenCL here (OpenCLUnavailable, a broken driver): nodes that need it will say so
        return None


def opencl_device() -> str | None:
    """The OpenCL device this process's workers use (``clrt.device_id``), or None when there is none."""
    return _device(os.environ.get("VOLCAP_CL_DEVICE", "").strip().lower())


def environment() -> dict:
    """The key component: {"libraries": {name: version}, "opencl": device or None}."""
    return {"libraries": dict(library_versions()), "opencl": opencl_device()}


def forget():
    """Read the environment again on the next call (tests; a process that changed its libraries)."""
    library_versions.cache_clear()
    _device.cache_clear()
