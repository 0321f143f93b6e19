"""OpenCL runtime: one context and queue per process, programs built once per source file and options,
``cl.Kernel`` objects kept, device buffers kept between calls, and ``Runner``: the one shape of the stages'
OpenCL code. Sources are given by path (the stage packages know where theirs are); ``#include "NAME"``
is searched beside the source.

``VOLCAP_CL_PROFILE=1`` creates the queue with profiling enabled (events then carry kernel times).
Compiler output (the build log's warnings, pyopencl's ``CompilerWarning``, and the "N warnings generated."
line PoCL's clang writes straight to file descriptor 2) is held back while a program builds and shown only
with ``VOLCAP_CL_VERBOSE=1`` (or ``volcap run --verbose``); a failed build always carries the whole log in its
error. Anything else written to stderr during a build is passed on.
Device choice: ``VOLCAP_CL_DEVICE`` (or ``volcap run --device``) is either ``cpu``, ``gpu``, or
``PLATFORM:DEVICE`` indices (as printed by ``volcap devices``). Default: the fastest device that builds
kernels correctly, by the stages' probes measured once per machine in child processes (``ranking``; kept in
~/.cache/volcap/opencl-devices.json; ``python -m nodegraph.clrt --rank [--refresh]``). The runtime matters:
on a 2-core EPYC the pip PoCL 3.0 hangs in its compiler or crashes on the key kernels, Intel's CPU runtime
is 2-12x slower than Debian's PoCL 3.1 on most of them (README, Benchmarks).
Never fork after this module has created a context (PoCL hangs); the process pools use spawn.
"""
from __future__ import annotations

import os
import re
import sys
import tempfile
import threading
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np

from .errors import VolcapError


class OpenCLUnavailable(VolcapError):
    pass


NO_DEVICE_HELP = ("install a working OpenCL device: on Debian/Ubuntu `apt-get install pocl-opencl-icd` (./setup.sh does "
                  "this), or your GPU vendor's OpenCL driver; `volcap devices` lists what works (`--refresh`: probe them again)")


# ---------------------------------------------------------------- device ranking
# The stage packages register probes (``register_probe``): functions that run a few of their real kernels on
# realistic data on the current device, check one against its NumPy reference (raising if it disagrees), and
# return milliseconds. A device is ranked by the sum of the probes, each device measured in a child process with
# a time limit (a broken runtime may hang in its compiler or crash), once per machine. Without registered probes
# (the engine alone) a generic kernel stands in.
_PROBES: list = []
PROBE_TIMEOUT_S = 120.0
GENERIC_PROBE = """
__kernel void probe(__global const float4* a, __global float4* b, int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    float4 x = a[i], y = a[(i * 7) % n];
    for (int k = 0; k < 24; k++) x = fma(x, (float4)(1.0001f), y / (fabs(x) + (float4)(1.5f)));
    b[i] = x;
}
"""


def register_probe(fn):
    """Register ``fn() -> milliseconds`` (see above); returns ``fn``."""
    _PROBES.append(fn)
    return fn


def _generic_probe() -> float:
    import time

    import pyopencl as cl

    ctx, q = context()
    n = 1 << 20
    prg = cl.Program(ctx, GENERIC_PROBE).build()
    k = cl.Kernel(prg, "probe")
    host = np.random.default_rng(0).random(4 * n, dtype=np.float32)
    a = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=host)
    b = cl.Buffer(ctx, cl.mem_flags.WRITE_ONLY, host.nbytes)
    k.set_args(a, b, np.int32(n))
    best = float("inf")
    for i in range(6):
        t = time.perf_counter()
        cl.enqueue_nd_range_kernel(q, k, (n,), (64,))
        q.finish()
        if i:
            best = min(best, time.perf_counter() - t)
    return best * 1e3


def probe_here() -> float:
    """The probes' milliseconds on this process's device (the child's side of ``probe_ms``)."""
    from .node import registry

    registry()  # the node packages register their probes when imported
    return sum(fn() for fn in _PROBES) if _PROBES else _generic_probe()


def device_id(dev) -> str:
    p = dev.platform
    return f"{p.name} {p.version} | {dev.name} | {dev.driver_version}"


PROBE_FAILED = 3     # the probe child's exit status when the device failed the probes (anything else: the child's fault)
_NOT_RANKED: dict[str, str] = {}   # device id -> why its probe gave no verdict in this process (not kept on disk)


class ProbeNotRun(OpenCLUnavailable):
    """The probe child failed before it could judge the device (no module to run, other probes than ours)."""


def probe_ms(pi: int, di: int) -> float | None:
    """The probes' milliseconds on device PLATFORM:DEVICE, measured in a child process; None when it cannot
    build or run them, gives wrong results, crashes or takes longer than PROBE_TIMEOUT_S. The child runs from the
    project's folder with it first on the path, so a run started from anywhere probes the same code; a child
    that fails before it reaches the device (no Python module to run, a broken install) or that ran other probes
    than this process has raises ProbeNotRun: no verdict (one would be kept for the machine: a run from another
    folder once marked this machine's only device unusable for every later run)."""
    import json
    import subprocess
    import sys

    from .node import registry

    registry()
    root = Path(__file__).resolve().parents[1]
    path = os.pathsep.join(p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p)
    env = dict(os.environ, VOLCAP_CL_DEVICE=f"{pi}:{di}", PYTHONPATH=path)
    try:
        res = subprocess.run([sys.executable, "-m", "nodegraph.clrt", "--probe"], env=env, capture_output=True,
                             text=True, timeout=PROBE_TIMEOUT_S, cwd=root)
    except subprocess.TimeoutExpired:
        return None
    if res.returncode == 0:
        try:
            out = json.loads(res.stdout.strip().splitlines()[-1])
            ms, ran = float(out["ms"]), out.get("probes")
        except (ValueError, KeyError, IndexError, TypeError):
            return None
        if ran != len(_PROBES):
            raise ProbeNotRun(f"the OpenCL probe of device {pi}:{di} ran {ran} probes, this process has "
                              f"{len(_PROBES)} (another installation?); nothing was ranked")
        return ms
    if res.returncode == PROBE_FAILED or res.returncode < 0:      # the probes failed, or the device crashed the child
        return None
    tail = (res.stderr or res.stdout).strip().splitlines()[-1:] or [f"exit status {res.returncode}"]
    raise ProbeNotRun(f"the OpenCL probe of device {pi}:{di} could not start ({tail[0]}); nothing was ranked")


def _probes_version() -> str:
    """A digest of the probes' sources (their modules, this one and the generic kernel): new probes rank anew."""
    import hashlib
    import inspect

    from .node import registry

    registry()
    h = hashlib.sha256(GENERIC_PROBE.encode())
    h.update(Path(__file__).read_bytes())       # how probes run and are judged: a change ranks anew
    for fn in _PROBES:
        try:
            h.update(Path(inspect.getsourcefile(fn)).read_bytes())
        except (OSError, TypeError):
            h.update(fn.__qualname__.encode())
    return h.hexdigest()[:12]


def _ranking_file() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "volcap" / "opencl-devices.json"


def ranking(refresh: bool = False) -> list[tuple[float | None, int, int, object]]:
    """Every OpenCL device with its probe time (ms; None = unusable), fastest first. Measured once per machine
    (a device is known by platform, device and driver version, the probes by the version of the project's
    sources) and kept in ~/.cache/volcap/opencl-devices.json; ``refresh`` measures again."""
    import json

    import pyopencl as cl

    path = _ranking_file()
    if refresh:
        _NOT_RANKED.clear()
    try:
        known = {} if refresh else json.loads(path.read_text())
    except (OSError, ValueError):
        known = {}
    version = _probes_version()
    rows, changed = [], False
    for pi, p in enumerate(cl.get_platforms()):
        for di, d in enumerate(p.get_devices()):
            did = f"{device_id(d)} | probes {version}"
            if did not in known:
                if device_id(d) not in _NOT_RANKED:
                    try:
                        known[did] = probe_ms(pi, di)
                        changed = True
                    except ProbeNotRun as exc:   # no verdict: unusable in this process, probed again by the next
                        _NOT_RANKED[device_id(d)] = str(exc)
                if did not in known:
                    rows.append((None, pi, di, d))
                    continue
            rows.append((known[did], pi, di, d))
    if changed:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(json.dumps(known, indent=1))
            os.replace(tmp, path)
        except OSError:
            pass
    return sorted(rows, key=lambda r: (r[0] is None, r[0] if r[0] is not None else 0.0, r[1], r[2]))


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
    if want and want not in ("cpu", "gpu"):
        try:
            pi, di = (int(x) for x in want.split(":"))
            return platforms[pi].get_devices()[di]
        except (ValueError, IndexError):
            raise OpenCLUnavailable(f"VOLCAP_CL_DEVICE={want!r}: expected cpu, gpu or PLATFORM:DEVICE (see `volcap devices`)") from None
    rows = ranking()
    if want in ("cpu", "gpu"):
        kind = cl.device_type.CPU if want == "cpu" else cl.device_type.GPU
        rows = [r for r in rows if r[3].type & kind]
        if not rows:
            raise OpenCLUnavailable(f"VOLCAP_CL_DEVICE={want}: no such OpenCL device; have: " + ", ".join(d.name for *_, d in devices))
    working = [r for r in rows if r[0] is not None]
    if not working:
        scope = f"no {want} device" if want else "no OpenCL device"
        reasons = [_NOT_RANKED[device_id(r[3])] for r in rows if device_id(r[3]) in _NOT_RANKED]
        why = f" ({'; '.join(reasons)})" if reasons else ""
        raise OpenCLUnavailable(f"{scope} can build kernels (" + ", ".join(d.name for *_, d in devices) + f"){why}; "
                                f"{NO_DEVICE_HELP}")
    return pick(working)[3]


def preference(dev) -> tuple:
    """The documented order among devices that work (README, Benchmarks): GPUs, then PoCL 3.1 or newer, then
    Intel's CPU runtime, then older PoCL (the pip PoCL 3.0 hangs or crashes on some of the key kernels)."""
    import re

    import pyopencl as cl

    gpu = 0 if dev.type & cl.device_type.GPU else 1
    version = dev.platform.version
    m = re.search(r"PoCL (\d+)\.(\d+)", version)
    if m:
        runtime = 0 if (int(m.group(1)), int(m.group(2))) >= (3, 1) else 2
    else:
        runtime = 1
    return gpu, runtime


def pick(working: list) -> tuple:
    """The device to use among ranked working ones: the documented first choice, unless the probes measured
    another at least a quarter faster (so that the noise of a busy machine does not flip between two runtimes
    of similar speed, while a much faster device, e.g. a GPU, always wins)."""
    first = min(working, key=lambda r: (preference(r[3]), r[1], r[2]))
    fastest = min(working, key=lambda r: r[0])
    return fastest if fastest[0] < 0.75 * first[0] else first


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


# ---------------------------------------------------------------- building programs, quietly
# A build's diagnostics reach the user three ways: the build log (clang's warnings, kept by the OpenCL runtime),
# pyopencl's CompilerWarning (raised whenever that log is not empty), and PoCL's clang printing its summary
# ("58 warnings generated.") from C straight to file descriptor 2, on every run (PoCL preprocesses each source
# again to look up its own kernel cache). ``program`` builds with the warning filtered and fd 2 redirected to a
# file, then: verbose -> prints the log and everything captured; otherwise passes on what was captured except
# clang's summary lines (so POCL_DEBUG output or another thread's progress bar is not lost); on failure -> the
# error carries pyopencl's message (which holds the full build log) and the captured lines.
_BUILD_LOCK = threading.Lock()  # fd 2 is the process's: one build at a time redirects it
_CLANG_SUMMARY = re.compile(r"^\d+ (warnings?|errors?)( and \d+ errors?)? generated\.$")


def verbose() -> bool:
    """Whether compiler output is shown (``VOLCAP_CL_VERBOSE=1``; ``volcap run --verbose`` sets it)."""
    return os.environ.get("VOLCAP_CL_VERBOSE", "").strip().lower() not in ("", "0", "false", "no")


class _Fd2Capture:
    """Everything written to file descriptor 2 inside the block (by Python or by C code), as ``.text``."""

    def __enter__(self):
        self.text, self._saved = "", None
        sys.stderr.flush()
        try:
            self._saved = os.dup(2)
        except OSError:  # no fd 2 at all: nothing to capture
            return self
        self._file = tempfile.TemporaryFile()
        os.dup2(self._file.fileno(), 2)
        return self

    def __exit__(self, *exc):
        if self._saved is None:
            return False
        try:
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        os.dup2(self._saved, 2)
        os.close(self._saved)
        self._file.seek(0)
        self.text = self._file.read().decode(errors="replace")
        self._file.close()
        if exc[0] is not None and self.text:  # an unexpected exception (Ctrl-C, ...): show what was held back
            sys.stderr.write(self.text)
        return False


def _build_log(prg) -> str:
    import pyopencl as cl

    logs = []
    for dev in prg.get_info(cl.program_info.DEVICES):
        try:
            log = prg.get_build_info(dev, cl.program_build_info.LOG)
        except cl.Error:
            continue
        if log and log.strip():
            logs.append(f"{dev.name}:\n{log.strip()}")
    return "\n".join(logs)


@lru_cache(maxsize=None)
def program(source: Path, options: tuple[str, ...] = ()):
    """Compiled program of the OpenCL file ``source`` (built once per process and option set). Compiler output is
    printed only when ``verbose()``; a failed build raises VolcapError with the whole build log."""
    import pyopencl as cl

    source = Path(source)
    ctx, _ = context()
    try:
        src = source.read_text()
    except OSError as exc:
        raise VolcapError(f"OpenCL source {source} cannot be read: {exc}") from None
    prg = failure = None
    with _BUILD_LOCK, warnings.catch_warnings(), _Fd2Capture() as said:
        warnings.simplefilter("ignore", cl.CompilerWarning)
        try:
            prg = cl.Program(ctx, src).build(options=[*options, f"-I{source.parent}"])
        except cl.Error as exc:  # a build failure (RuntimeError, with the log) or e.g. invalid options (LogicError)
            failure = exc
    other = "".join(line for line in said.text.splitlines(keepends=True) if not _CLANG_SUMMARY.match(line.strip()))
    if failure is not None:
        extra = f"\n(compiler's stderr:)\n{said.text.strip()}" if said.text.strip() else ""
        raise VolcapError(f"OpenCL build of {source.name} failed:\n{failure}{extra}") from None
    if verbose():
        log = _build_log(prg)
        head = f"OpenCL build of {source}" + (f" ({' '.join(options)})" if options else "")
        sys.stderr.write(f"{head}: {'log:' if log else 'empty log'}\n" + (f"{log}\n" if log else "") + said.text)
    elif other:
        sys.stderr.write(other)
    return prg


@lru_cache(maxsize=None)
def kernel(source: Path, name: str, options: tuple[str, ...] = ()):
    """A ``cl.Kernel`` object, kept (cheaper than ``prg.name`` look-ups, which build a new one each time)."""
    import pyopencl as cl

    return cl.Kernel(program(Path(source), options), name)


class DeviceBuffers:
    """Read-write OpenCL buffers by name, kept between calls and replaced (a quarter larger) when too small."""

    def __init__(self, ctx):
        self.ctx = ctx
        self._bufs: dict[str, object] = {}

    def get(self, name: str, nbytes: int):
        """The buffer called ``name``, at least ``nbytes`` long."""
        import pyopencl as cl

        buf = self._bufs.get(name)
        if buf is None or buf.size < nbytes:
            buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, max(int(nbytes * 1.25), 64))
            self._bufs[name] = buf
        return buf


def round_up(n: int, group: int) -> int:
    """``n`` rounded up to a whole number of work-groups of ``group`` items (at least one group)."""
    return max(group, -(-int(n) // group) * group)


class Runner:
    """The one shape of the stages' OpenCL code. A subclass names its OpenCL ``source`` (a path) and its build
    ``options``; ``Runner.get()`` is the process's instance of it (created on first use, kept, so kernels are
    built once and buffers are reused from frame to frame):

        class HullCL(Runner):
            source = kernels.source("hull.cl")

        hull = HullCL.get()
        cams = hull.upload("cams", packed)                  # named device buffer, grow-only, reused
        hull.launch("hull_dense", (nz, ny, nx), None, cams, ...)
        out = hull.read(vol, dims, np.uint8)

    ``launch`` rounds the global size up to whole work-groups (kernels check their bounds) and keeps the
    ``cl.Kernel`` objects. A kernel that cannot build raises VolcapError naming the source: no silent
    fallback."""

    source: Path | None = None
    options: tuple[str, ...] = ()
    _instances: dict = {}

    def __init__(self):
        self.ctx, self.queue = context()
        self.buffers = DeviceBuffers(self.ctx)

    @classmethod
    def get(cls):
        inst = Runner._instances.get(cls)
        if inst is None:
            inst = Runner._instances[cls] = cls()
        return inst

    def kernel(self, name: str, options: tuple[str, ...] = ()):
        return kernel(Path(self.source), name, (*self.options, *options))

    def buffer(self, role: str, nbytes: int):
        """The read-write device buffer called ``role``, at least ``nbytes`` long (kept between calls)."""
        return self.buffers.get(role, nbytes)

    def upload(self, role: str, arr: np.ndarray):
        """``arr`` copied into the buffer called ``role`` (non-blocking; pyopencl keeps ``arr`` alive until the
        copy is done)."""
        import pyopencl as cl

        arr = np.ascontiguousarray(arr)
        buf = self.buffer(role, arr.nbytes)
        cl.enqueue_copy(self.queue, buf, arr, is_blocking=False)
        return buf

    def host(self, arr: np.ndarray, writable: bool = False):
        """A device buffer over ``arr``'s own memory (no copy on a CPU device). Keep ``arr`` alive, and do not
        change it, until the queue has finished with the buffer."""
        import pyopencl as cl

        mf = cl.mem_flags
        flags = (mf.READ_WRITE if writable else mf.READ_ONLY) | mf.USE_HOST_PTR
        return cl.Buffer(self.ctx, flags, hostbuf=np.ascontiguousarray(arr))

    def launch(self, name: str, global_size, local_size, *args, options: tuple[str, ...] = ()):
        """Enqueue kernel ``name`` over ``global_size`` (rounded up to whole ``local_size`` groups when given)."""
        import pyopencl as cl

        k = self.kernel(name, options)
        k.set_args(*args)
        gs = tuple(int(g) for g in (global_size if isinstance(global_size, (tuple, list)) else (global_size,)))
        ls = None
        if local_size is not None:
            ls = tuple(int(v) for v in (local_size if isinstance(local_size, (tuple, list)) else (local_size,)))
            gs = tuple(round_up(g, v) for g, v in zip(gs, ls))
        return cl.enqueue_nd_range_kernel(self.queue, k, gs, ls)

    def read(self, buf, shape, dtype=np.uint8, out: np.ndarray | None = None) -> np.ndarray:
        """The first prod(shape) items of ``buf`` as a new host array (waits for the copy)."""
        import pyopencl as cl

        out = np.empty(shape, dtype) if out is None else out
        cl.enqueue_copy(self.queue, out, buf, is_blocking=True)
        return out

    def finish(self):
        self.queue.finish()


def devices_table(refresh: bool = False) -> list[str]:
    """One line per OpenCL device, fastest first by the probe, the one runs use marked with '*'."""
    import pyopencl as cl

    chosen = None
    ranked = ranking(refresh)
    try:
        chosen = device_id(_choose_device())
    except OpenCLUnavailable:
        pass
    rows = []
    for ms, pi, di, d in ranked:
        speed = (f"{ms:8.1f} ms" if ms is not None else f"not probed: {_NOT_RANKED[device_id(d)]}"
                 if device_id(d) in _NOT_RANKED else "unusable (fails, hangs or disagrees)")
        mark = "*" if device_id(d) == chosen else " "
        rows.append(f"{mark} {pi}:{di}  {cl.device_type.to_string(d.type):4s}  {speed}  {d.name}  "
                    f"({d.platform.name} {d.platform.version}, {d.max_compute_units} units)")
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


if __name__ == "__main__":  # python -m nodegraph.clrt [--rank | --probe]
    import json

    # this file runs as __main__: the stages register their probes in the module nodegraph.clrt, not here, so
    # both branches use that module (until stop 46 the child ran this file's own empty list: the generic kernel
    # alone ranked every device, and --rank kept its verdicts under a version no run looks up)
    from nodegraph import clrt as module

    if "--probe" in sys.argv:  # the child of probe_ms: run the probes on the device VOLCAP_CL_DEVICE names
        from nodegraph.node import registry

        registry()  # the probes register on import: a failure here is the code's, not the device's (exit 1)
        try:
            print(json.dumps({"ms": module.probe_here(), "probes": len(module._PROBES)}))
        except Exception as exc:  # noqa: BLE001 - any failure means: not this device
            print(f"probe failed: {type(exc).__name__}: {exc}", file=sys.stderr)
            sys.exit(PROBE_FAILED)
        sys.exit(0)
    try:
        if "--rank" in sys.argv:
            for row in module.devices_table(refresh="--refresh" in sys.argv):
                print(row)
        print("OpenCL device:", module.device_name())
    except module.OpenCLUnavailable as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(1)
