"""What every benchmark prints first: the OpenCL platform and device, the CPU model and core count, the load."""
from __future__ import annotations

import os


def describe() -> str:
    cpu = "?"
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    try:
        from nodegraph import clrt

        device = clrt.device_name()
    except Exception as exc:  # noqa: BLE001 - a benchmark without OpenCL still says why
        device = f"none ({exc})"
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    return f"OpenCL device: {device}\nCPU: {cpu}, {os.cpu_count()} cores; load average {load}"
