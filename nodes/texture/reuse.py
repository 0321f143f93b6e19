"""What a texturing run can reuse from frame to frame: everything that depends only on the mesh's connectivity
(face neighbours, edges, vertex adjacency) or on the atlas (which texel bakes which face point, the fill
pyramid's cells, the device buffers holding them). A tracked segment has one connectivity and one atlas, so
these are made on its first frame and found again on every later one (also when the atlas arrives as a new
object, loaded from the cache: the memo is keyed by content).

    topo = Topology.of(faces, n_vertices)        # .nbr .edges .adjacency .incidence (lazily, once)
    layout = BakeLayout.of(atlas, gutter=2)      # .texel .face .bary .inner (compact: covered texels only)
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from functools import cached_property

import numpy as np

_MEMO: "OrderedDict[tuple, object]" = OrderedDict()
_MEMO_SIZE = 4


def _digest(*arrays) -> str:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def _memo(key, make):
    hit = _MEMO.get(key)
    if hit is None:
        hit = _MEMO[key] = make()
        while len(_MEMO) > _MEMO_SIZE:
            _MEMO.popitem(last=False)
    else:
        _MEMO.move_to_end(key)
    return hit


class Topology:
    """Connectivity of one mesh, each piece made on first use."""

    def __init__(self, faces, n_vertices: int):
        self.faces = np.ascontiguousarray(faces, np.int64).reshape(-1, 3)
        self.n_vertices = int(n_vertices)

    @classmethod
    def of(cls, faces, n_vertices: int) -> "Topology":
        faces = np.asarray(faces)
        return _memo(("topology", _digest(np.asarray(faces, np.int64)), int(n_vertices)), lambda: cls(faces, n_vertices))

    @cached_property
    def nbr(self) -> np.ndarray:
        from nodes.common.meshops import face_neighbours

        return face_neighbours(self.faces)

    @cached_property
    def edges(self) -> np.ndarray:
        from nodes.common.meshops import unique_edges

        return unique_edges(self.faces)[0]

    @cached_property
    def closed_parts(self) -> np.ndarray | None:
        """Per face the index of its part (faces joined across edges), where the faces form closed, consistently
        oriented surfaces (every directed edge once and its reverse once: a marching-cubes or tracked mesh); None
        where they do not (an open or non-manifold mesh, or one with a flipped face). Parts are joined by edges, not
        vertices: two surfaces touching at a vertex are two parts, each oriented in itself."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        f, n = self.faces, self.n_vertices
        if len(f) == 0:
            return None
        a, b = f.ravel(), f[:, [1, 2, 0]].ravel()
        fwd, rev = np.sort(a * n + b), np.sort(b * n + a)
        if np.any(fwd[1:] == fwd[:-1]) or not np.array_equal(fwd, rev):
            return None
        nb = self.nbr.ravel()
        own = np.repeat(np.arange(len(f)), 3)
        ok = nb >= 0
        _, label = connected_components(coo_matrix((np.ones(int(ok.sum()), np.int8), (own[ok], nb[ok])),
                                                   shape=(len(f), len(f))), directed=False)
        return label

    @cached_property
    def adjacency(self):
        """Row-normalised sparse (V, V) averaging over each vertex and its umbrella neighbours."""
        from nodes.common.meshops import ring_average

        return ring_average(self.faces, self.n_vertices)

    @cached_property
    def incidence(self):
        """Sparse (V, F) with a 1 where the vertex is a corner of the face."""
        from scipy.sparse import csr_matrix

        nf = len(self.faces)
        return csr_matrix((np.ones(3 * nf), (self.faces.ravel(), np.repeat(np.arange(nf), 3))),
                          shape=(self.n_vertices, nf))

    @cached_property
    def corner_count(self) -> np.ndarray:
        """(V,) faces per vertex."""
        return np.bincount(self.faces.ravel(), minlength=self.n_vertices).astype(np.float64)


class BakeLayout:
    """The texels an atlas bakes, compact: ``texel`` (N,) flat indices into the size x size texture of every
    texel with a face (inside a chart or in its gutter), ``face`` (N,) and ``bary`` (N, 3) the surface point
    it shows, ``inner`` (N,) whether its centre lies inside the face (not the gutter). ``texel_face`` is the
    full (S, S) map (-1 = empty). The fill pyramid's coarsest cells per texel are kept too (``cell``, their
    texel counts, and ``cell_channel``: the bin of each of a texel's three colour values; ``texel_channel``
    their bytes in the (S, S, 3) texture)."""

    COARSE = 16

    def __init__(self, atlas, gutter: int):
        from .bake import add_gutter, texel_bary, uv_raster

        self.size = int(atlas.size)
        inner = uv_raster(atlas.face_uv, self.size)
        tf = add_gutter(inner, max(1, gutter))
        flat = tf.reshape(-1)
        self.texel = np.flatnonzero(flat >= 0)
        self.face = flat[self.texel].astype(np.int32)
        self.bary = texel_bary(tf, atlas.face_uv).reshape(-1, 3)[self.texel]
        self.inner = inner.reshape(-1)[self.texel] >= 0
        self.texel_face = tf
        s, c = self.size, self.COARSE
        self.coarse_shape = (-(-s // c), -(-s // c))
        y, x = np.divmod(self.texel, s)
        self.cell = (y // c) * self.coarse_shape[1] + x // c
        n_cells = self.coarse_shape[0] * self.coarse_shape[1]
        self.cell_count = np.bincount(self.cell, minlength=n_cells)
        self.cell_channel = (self.cell[:, None] * 3 + np.arange(3)).reshape(-1).astype(np.intp)    # bin of each value
        self.texel_channel = (self.texel[:, None] * 3 + np.arange(3)).reshape(-1)  # its byte in the texture
        self.cell_area = np.full(self.coarse_shape, float(c * c))
        if s % c:                                             # edge cells are partly outside the square
            ys = np.minimum(np.arange(self.coarse_shape[0]) * c + c, s) - np.arange(self.coarse_shape[0]) * c
            self.cell_area = np.outer(ys, ys).astype(np.float64)
        self._device = None

    @classmethod
    def of(cls, atlas, gutter: int = 2) -> "BakeLayout":
        cached = getattr(atlas, "_layout", None)
        if cached is not None and cached[0] == gutter:
            return cached[1]
        lay = _memo(("layout", _digest(atlas.face_uv, atlas.faces), int(atlas.size), int(gutter)),
                    lambda: cls(atlas, gutter))
        try:
            atlas._layout = (gutter, lay)
        except AttributeError:
            pass
        return lay

    def device(self):
        """(face, bary, dest) on the OpenCL device, uploaded once: the texels sorted by face (``dest``, the
        layout's index of each device sample), so that neighbouring work items bake the same face from the
        same views (the bake kernel ran 12 % faster than in atlas order); the kernel writes each result to
        row ``dest`` (layout order)."""
        if self._device is None:
            from nodegraph import clrt

            order = np.argsort(self.face, kind="stable")
            self._device = (clrt.to_device(np.ascontiguousarray(self.face[order], np.int32)),
                            clrt.to_device(np.ascontiguousarray(self.bary[order], np.float32).reshape(-1)),
                            clrt.to_device(order.astype(np.int32)))
        return self._device

    def __len__(self):
        return len(self.texel)


def clear():
    """Forget every memoised topology and layout (tests)."""
    _MEMO.clear()


def reference_atlas(vertices, faces, size: int, directions: int):
    """The atlas charted on a segment's reference (keyframe) mesh, made once per segment and found again by
    content on its other frames."""
    from .atlas import make_atlas

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    return _memo(("atlas", _digest(v, f), int(size), int(directions)),
                 lambda: make_atlas(v, f, Topology.of(f, len(v)).nbr, size, directions=directions))
