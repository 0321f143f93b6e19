"""Taubin lambda|mu smoothing that keeps the silhouettes (kernels/relax.cl, kernels/refine.cl).

Taubin, "A signal processing approach to fair surface design" (SIGGRAPH 95): alternate a shrinking step
(lambda > 0) and an inflating step (mu < -lambda) of the umbrella Laplacian, which removes the marching-cubes
staircase without the shrinkage of plain Laplacian smoothing. With ``keep_silhouettes`` the smoothed mesh
is then fitted to the visual hull in two moves along the smoothed normals, so silhouettes neither grow nor
shrink: a vertex that ends outside goes back to the hull boundary (refine's point test, bisected from one
mean edge length inside, else along its move); a vertex that smoothing moved inwards (thin limbs, convex
rims) goes back out by as much, stopping at the boundary. Binary masks are read through their signed
distance outline blurred by ``outline_sigma`` pixels, so the fit follows a smooth curve through the pixel
staircase. (Clamping after every half-step instead was tried: it ratchets thin parts inwards.)

    offsets, neighbours = vertex_neighbours(faces, len(vertices))
    v = taubin_cl(vertices, offsets, neighbours, iterations=10)      # taubin_reference: the NumPy version
    v = relax_vertices(mesh, 10, views=views)                         # smoothing, then the fit to the hull
"""
from __future__ import annotations

import numpy as np
import trimesh

from kernels import source
from nodegraph import Input, Node, NodeError, Param
from nodes.common.meshops import carried_vertex_colors, vertex_neighbours
from nodes.common.silhouettes import POLICIES, Silhouettes, hull_test
from nodes.common.types import CameraSet, Masks, Mesh

from .refine import push_out

LAMBDA, MU = 0.6307, -0.6732


def taubin_step_reference(v: np.ndarray, offsets: np.ndarray, neighbours: np.ndarray, factor: float) -> np.ndarray:
    """One half-step: v + factor * (mean of neighbours - v), float32 in the kernel's order."""
    v = np.asarray(v, np.float32)
    counts = np.diff(offsets)
    has = counts > 0
    sums = np.zeros_like(v)
    gathered = v[neighbours]
    for j in range(int(counts.max(initial=0))):  # neighbour by neighbour, like the kernel's loop
        rows = np.flatnonzero(counts > j)
        sums[rows] += gathered[offsets[rows] + j]
    out = v.copy()
    mean = sums[has] / counts[has, None].astype(np.float32)
    out[has] = v[has] + np.float32(factor) * (mean - v[has])
    return out


def taubin_reference(vertices, offsets, neighbours, iterations: int, lam: float = LAMBDA, mu: float = MU) -> np.ndarray:
    """``iterations`` lambda|mu pairs of umbrella smoothing (NumPy, float32)."""
    v = np.asarray(vertices, np.float32)
    for _ in range(iterations):
        for factor in (lam, mu):
            v = taubin_step_reference(v, offsets, neighbours, factor)
    return v


def taubin_cl(vertices, offsets, neighbours, iterations: int, lam: float = LAMBDA, mu: float = MU) -> np.ndarray:
    """OpenCL version of ``taubin_reference`` (vertices stay on the device between half-steps)."""
    import pyopencl as cl

    from nodegraph import clrt

    v = np.ascontiguousarray(vertices, np.float32).reshape(-1, 3)
    n = len(v)
    if n == 0 or iterations == 0:
        return v.copy()
    ctx, queue = clrt.context()
    rw = cl.mem_flags.READ_WRITE
    d_v, d_p = clrt.to_device(v, rw), cl.Buffer(ctx, rw, v.nbytes)
    d_off, d_nb = clrt.to_device(np.asarray(offsets, np.int32)), clrt.to_device(np.asarray(neighbours, np.int32))
    k = clrt.kernel(source("relax.cl"), "taubin_step")
    size = (-(-n // 64) * 64,)
    for _ in range(iterations):
        for factor in (lam, mu):
            k.set_args(d_v, d_off, d_nb, np.int32(n), np.float32(factor), d_p)
            cl.enqueue_nd_range_kernel(queue, k, size, None)
            d_v, d_p = d_p, d_v
    out = np.empty_like(v)
    cl.enqueue_copy(queue, out, d_v, is_blocking=True)
    return out


def relax_vertices(mesh, iterations: int, lam: float = LAMBDA, mu: float = MU, views: Silhouettes | None = None,
                   steps: int = 10, method: str = "opencl") -> np.ndarray:
    """Taubin-smoothed vertices of ``mesh``; with ``views`` fitted to the visual hull along the smoothed
    normals: outside vertices back to the boundary (searched from one mean edge length inside, else along
    their move), vertices that moved inwards back out by their inward move, at most to the boundary."""
    vertices = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.faces)
    offsets, neighbours = vertex_neighbours(faces, len(vertices))
    smooth = taubin_cl if method == "opencl" else taubin_reference
    out = smooth(vertices, offsets, neighbours, iterations, lam, mu)
    if views is None or len(vertices) == 0:
        return out
    reach = float(mesh.edges_unique_length.mean()) if len(faces) else 0.0
    test = hull_test(views, method)
    normals = trimesh.Trimesh(out, faces, process=False).vertex_normals
    out = test.clamp(vertices, out, steps, normals, reach)
    inwards = np.einsum("ij,ij->i", vertices - out, normals)
    return push_out(out, normals, np.maximum(inwards, 0), test, steps)


# ---------------------------------------------------------------- node
class Relax(Node):
    """Taubin lambda|mu smoothing of a mesh (OpenCL). With keep_silhouettes (default) the result is fitted to the
    visual hull of the masks (no vertex outside; inward moves undone up to the boundary), so silhouettes hold
    while the staircase goes. Same topology."""

    type_name = "relax"
    version = 2
    inputs = {"mesh": Mesh,
              "masks": Input(Masks, optional=True, doc="silhouettes to stay inside (keep_silhouettes)"),
              "cameras": Input(CameraSet, optional=True, doc="cameras of the masks (keep_silhouettes)")}
    outputs = {"mesh": Mesh}
    params = {
        "iterations": Param(int, 10, range=(0, 1000), doc="lambda|mu pairs"),
        "lam": Param(float, LAMBDA, range=(0.0, 1.0), doc="shrinking factor lambda"),
        "mu": Param(float, MU, range=(-1.0, 0.0), doc="inflating factor mu (|mu| > lambda)"),
        "keep_silhouettes": Param(bool, True, doc="fit the result to the visual hull of masks + cameras"),
        "steps": Param(int, 10, range=(1, 30), doc="bisection steps of the clamp"),
        "outline_sigma": Param(float, 0.7, range=(0.0, 5.0), doc="binary masks: Gaussian blur (pixels) of the signed "
                               "distance outline, a smooth curve through the pixel staircase"),
        "min_views": Param(int, 0, range=(0, None), doc="hull vote: 0 = all views; k = at least k silhouettes"),
        "outside": Param(str, "carve", choices=POLICIES, doc="points projecting outside an image: carve, or ignore that view"),
        "use_alpha": Param(bool, True, doc="test against soft alpha when the masks carry it"),
        "method": Param(str, "opencl", choices=("opencl", "numpy"), doc="OpenCL kernels or the NumPy reference"),
    }
    kernels = [source("relax.cl"), source("refine.cl")]

    def run(self, mesh, masks=None, cameras=None, *, iterations, lam, mu, keep_silhouettes, steps, outline_sigma, min_views,
            outside, use_alpha, method):
        views = None
        if keep_silhouettes:
            if masks is None or cameras is None:
                raise NodeError("relax: keep_silhouettes needs the 'masks' and 'cameras' inputs connected "
                                "(or set keep_silhouettes: false)")
            views = Silhouettes.from_inputs(masks, cameras, min_views, outside, use_alpha, node="relax")
            views = views.distance_outline(outline_sigma)
        out = relax_vertices(mesh, iterations, lam, mu, views, steps, method)
        return {"mesh": trimesh.Trimesh(out.astype(np.float64), np.asarray(mesh.faces),
                                        vertex_colors=carried_vertex_colors(mesh, out), process=False)}
