"""What every benchmark prints first: the OpenCL platform and device, the CPU model and core count, the load."""
from __future__ import annotations

import os


def cpu_model() -> str:
    try:
        return next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        import platform

        return platform.processor() or "unknown"


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far (a load-independent figure on a shared machine)."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def load_average() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def describe() -> str:
    cpu = cpu_model()
    try:
        from nodegraph import clrt

        device = clrt.device_name()
    except Exception as exc:  # noqa: BLE001 - a benchmark without OpenCL still says why
        device = f"none ({exc})"
    return f"OpenCL platform/device: {device}\nCPU: {cpu}, {os.cpu_count()} cores; load average {load_average()}"
