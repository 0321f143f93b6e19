"""OpenCL runtime: one context and queue per process, compiled programs cached, kernels from ``kernels/``.

``VOLCAP_CL_PROFILE=1`` creates the queue with profiling enabled (events then carry kernel times).
Device choice: ``VOLCAP_CL_DEVICE`` (or ``app.py run --device``) is either ``cpu``, ``gpu``, or
``PLATFORM:DEVICE`` indices (as printed by ``app.py devices``). Default: first GPU, else first CPU.
Never fork after this module has created a context (PoCL hangs); the process pools use spawn.
"""
from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

import numpy as np

from .errors import VolcapError

KERNEL_DIR = Path(__file__).resolve().parent.parent / "kernels"


class OpenCLUnavailable(VolcapError):
    pass


def kernel_path(name: str) -> Path:
    p = KERNEL_DIR / name
    if not p.is_file():
        raise VolcapError(f"OpenCL source '{name}' not found in {KERNEL_DIR}")
    return p


def _builds(dev) -> bool:
    """Whether a device can compile a kernel (the pip PoCL's LLVM 14 cannot on CPUs newer than it knows,
    failing with "unknown target CPU 'generic'")."""
    import pyopencl as cl

    try:
        cl.Program(cl.Context([dev]), "__kernel void probe(__global int *a) { a[0] = 1; }").build()
        return True
    except Exception:
        return False


NO_DEVICE_HELP = ("install a working OpenCL CPU device: `pip install pocl-binary-distribution`, or, when its LLVM "
                  "does not know this CPU, the distribution's PoCL (`apt-get install pocl-opencl-icd`); ./setup.sh does this")


def _choose_device():
    try:
        import pyopencl as cl
        platforms = cl.get_platforms()
    except Exception as exc:
        raise OpenCLUnavailable(f"no OpenCL platform found ({exc}); {NO_DEVICE_HELP}") from None
    devices = [(pi, di, d) for pi, p in enumerate(platforms) for di, d in enumerate(p.get_devices())]
    if not devices:
        raise OpenCLUnavailable(f"OpenCL platforms exist but expose no device; {NO_DEVICE_HELP}")
    want = os.environ.get("VOLCAP_CL_DEVICE", "").strip().lower()
    if want in ("cpu", "gpu"):
        kind = cl.device_type.CPU if want == "cpu" else cl.device_type.GPU
        match = [d for _, _, d in devices if d.type & kind]
        if not match:
            raise OpenCLUnavailable(f"VOLCAP_CL_DEVICE={want}: no such OpenCL device; have: " + ", ".join(d.name for *_, d in devices))
        working = [d for d in match if _builds(d)]
        if not working:
            raise OpenCLUnavailable(f"VOLCAP_CL_DEVICE={want}: no {want} device can build kernels; {NO_DEVICE_HELP}")
        return working[0]
    if want:
        try:
            pi, di = (int(x) for x in want.split(":"))
            return platforms[pi].get_devices()[di]
        except (ValueError, IndexError):
            raise OpenCLUnavailable(f"VOLCAP_CL_DEVICE={want!r}: expected cpu, gpu or PLATFORM:DEVICE (see `app.py devices`)") from None
    # default: the first GPU, else the first CPU device, that can actually build a kernel
    ordered = sorted(devices, key=lambda e: 0 if e[2].type & cl.device_type.GPU else 1)
    for *_, d in ordered:
        if _builds(d):
            return d
    raise OpenCLUnavailable("no OpenCL device can build kernels (" + ", ".join(d.name for *_, d in devices) + f"); {NO_DEVICE_HELP}")


@lru_cache(maxsize=None)
def context():
    """(context, queue) of this process, created on first use."""
    import pyopencl as cl

    dev = _choose_device()
    ctx = cl.Context([dev])
    props = cl.command_queue_properties.PROFILING_ENABLE if os.environ.get("VOLCAP_CL_PROFILE") == "1" else 0
    return ctx, cl.CommandQueue(ctx, properties=props)


def queue():
    return context()[1]


@lru_cache(maxsize=None)
def program(name: str, options: tuple[str, ...] = ()):
    """Compiled program for ``kernels/NAME`` (built once per process and option set)."""
    import pyopencl as cl

    ctx, _ = context()
    src = kernel_path(name).read_text()
    try:
        return cl.Program(ctx, src).build(options=[*options, f"-I{KERNEL_DIR}"])
    except cl.RuntimeError as exc:
        raise VolcapError(f"OpenCL build of kernels/{name} failed:\n{exc}") from None


@lru_cache(maxsize=None)
def kernel(file: str, name: str, options: tuple[str, ...] = ()):
    """A ``cl.Kernel`` object, kept (cheaper than ``prg.name`` look-ups, which build a new one each time)."""
    import pyopencl as cl

    return cl.Kernel(program(file, options), name)


def devices_table() -> list[str]:
    import pyopencl as cl

    rows = []
    for pi, p in enumerate(cl.get_platforms()):
        for di, d in enumerate(p.get_devices()):
            rows.append(f"{pi}:{di}  {cl.device_type.to_string(d.type):4s}  {d.name}  ({p.name}, {d.max_compute_units} units)")
    return rows


def to_device(arr: np.ndarray, flags=None):
    import pyopencl as cl

    ctx, _ = context()
    mf = cl.mem_flags
    return cl.Buffer(ctx, (flags or mf.READ_ONLY) | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(arr))


def device_name() -> str:
    ctx, _ = context()
    d = ctx.devices[0]
    return f"{d.name} ({d.platform.name} {d.platform.version.split()[2] if len(d.platform.version.split()) > 2 else ''})".strip()


if __name__ == "__main__":  # python -m nodegraph.clrt: is there a device that builds kernels?
    import sys

    try:
        print("OpenCL device:", device_name())
    except OpenCLUnavailable as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(1)
