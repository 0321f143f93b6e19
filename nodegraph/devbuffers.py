"""Device buffers kept between calls: a stage that runs every frame allocates once, not per frame."""
from __future__ import annotations


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
