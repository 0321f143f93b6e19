"""Pictures of the stages' port types for the run report (each type's ``preview`` calls one of these).

Masks are overlaid on the images of the same frame, a skeleton is drawn over its mesh, cameras with their
bounds, and 3-D views are oriented by the cameras (world up = the cameras' mean image-up direction, first
view from camera 0). 3-D surfaces are rendered with VTK (pyvista, off-screen via EGL); when VTK cannot render
here, or ``VOLCAP_PREVIEW_NO_VTK=1``, they fall back to matplotlib orthographic projections so a report
still works.
"""
from __future__ import annotations

__fingerprint__ = False  # drawing only: nothing here changes what a node computes (nodegraph/fingerprint.py)

import math
import os

import numpy as np

from nodegraph.preview import figure as _figure, load_companion as _load_companion, render_figure as _render_figure
from nodegraph.preview import text_image as _text_image

_vtk_state: dict = {}


def vtk_available() -> bool:
    """Whether VTK can render off-screen here (checked once per process)."""
    if os.environ.get("VOLCAP_PREVIEW_NO_VTK") == "1":
        return False
    if "ok" not in _vtk_state:
        try:
            pv = _pyvista()
            p = pv.Plotter(off_screen=True, window_size=(32, 32))
            p.add_mesh(pv.Sphere())
            ok = p.screenshot(return_img=True).shape[:2] == (32, 32)
            p.close()
        except Exception:  # no OpenGL/EGL/OSMesa: fall back to matplotlib
            ok = False
        _vtk_state["ok"] = ok
    return _vtk_state["ok"]



# ---------------------------------------------------------------- 2-D: images and masks
def draw_images(value, size, companions):
    return contact_sheet(value.images, value.names, size)


def draw_masks(value, size, companions):
    images = _load_companion("Images", companions)
    if images is not None and len(images) == len(value):
        return contact_sheet([_overlay(im, m) for im, m in zip(images.images, value.masks)], value.names, size)
    return contact_sheet([np.repeat(m[:, :, None], 3, axis=2) for m in value.masks], value.names, size)


def contact_sheet(tiles: list[np.ndarray], names: list[str], width: int) -> np.ndarray:
    """RGB uint8 tiles on a grid (ceil(sqrt(n)) columns) with their names, ``width`` pixels wide."""
    import cv2

    n = max(len(tiles), 1)
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    tw = max(width // cols, 8)
    aspect = max((t.shape[0] / t.shape[1] for t in tiles), default=0.75)
    th = max(int(round(tw * aspect)), 8)
    sheet = np.full((rows * th, cols * tw, 3), 32, np.uint8)
    for i, (tile, name) in enumerate(zip(tiles, names)):
        r, c = divmod(i, cols)
        scale = min(tw / tile.shape[1], th / tile.shape[0])
        w, h = max(int(tile.shape[1] * scale), 1), max(int(tile.shape[0] * scale), 1)
        small = cv2.resize(tile, (w, h), interpolation=cv2.INTER_AREA)
        sheet[r * th:r * th + h, c * tw:c * tw + w] = small
        if tw >= 48:
            cv2.putText(sheet, str(name), (c * tw + 3, r * th + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 0), 1, cv2.LINE_AA)
    return sheet


def _overlay(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The image with its background darkened and the silhouette outline in red."""
    import cv2

    if mask.shape[:2] != img.shape[:2]:
        mask = cv2.resize(mask, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_NEAREST)
    fg = mask > 127
    out = img.copy()
    out[~fg] = (out[~fg] * 0.35).astype(np.uint8)
    contours, _ = cv2.findContours(fg.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, (255, 40, 40), max(1, img.shape[1] // 200))
    return out


# ---------------------------------------------------------------- 3-D: volumes, meshes, skeletons
def draw_volume(value, size, companions):
    occ = np.asarray(value.occupancy, dtype=np.float32)
    if not np.any(occ > 0.5):
        return _text_image([f"empty volume {occ.shape}"], size)
    up, front = _orientation(companions)
    if vtk_available():
        pv = _pyvista()
        grid = pv.ImageData(dimensions=np.array(occ.shape) + 2, spacing=value.voxel_size,
                            origin=value.bbox_min - 0.5 * value.voxel_size)
        grid.point_data["occ"] = np.pad(occ, 1).ravel(order="F")
        surf = grid.contour([0.5], scalars="occ", method="flying_edges")
        return _render_vtk([(surf, {"color": "#d9b38c"})], size, up, front)
    return _projections(value.centers()[occ > 0.5], size, up)


def draw_mesh(value, size, companions):
    if len(value.faces) == 0:
        return None
    up, front = _orientation(companions)
    if vtk_available():
        return _render_vtk([_vtk_mesh(value)], size, up, front)
    return _projections(np.asarray(value.vertices), size, up)


def draw_textured_mesh(value, size, companions):
    """Photos (top) over the textured mesh rendered into the same cameras (bottom), for three cameras spread
    over the rig; without Images and Cameras companions, the 3-D view of ``draw_mesh``."""
    if len(value.faces) == 0:
        return None
    images = _load_companion("Images", companions)
    cams = _load_companion("Cameras", companions)
    if images is None or cams is None or len(images) != len(cams):
        return draw_mesh(value, size, companions)
    from .raster import render_texture

    picks = sorted(set(np.linspace(0, len(cams) - 1, min(3, len(cams)) + 1)[:-1].round().astype(int).tolist()))
    faces = np.asarray(value.faces)
    visual = value.visual
    face_uv = face_colours = texture = None
    if getattr(visual, "kind", None) == "texture" and visual.uv is not None:
        texture = np.asarray((getattr(visual.material, "baseColorTexture", None) or visual.material.image).convert("RGB"))
        face_uv = np.asarray(visual.uv, np.float32)[faces]
    elif getattr(visual, "kind", None) == "vertex":
        face_colours = np.asarray(visual.vertex_colors, np.float32)[:, :3][faces]
    else:
        return draw_mesh(value, size, companions)
    tiles, names = [], []
    for i in picks:
        rgb, hit = render_texture(value.vertices, faces, face_uv, texture, cams, i, face_colours=face_colours,
                                  background=(32, 32, 32))
        ys, xs = np.nonzero(hit)
        H, W = hit.shape
        if len(ys):  # crop both to the rendered object, in a 3:4 (w:h) box with a margin
            cy, cx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2
            hh = 0.55 * max(ys.max() - ys.min() + 1, (xs.max() - xs.min() + 1) / 0.75)
            hh = min(hh, H / 2, W / 2 / 0.75)
            hw = 0.75 * hh
            y0, x0 = int(np.clip(cy - hh, 0, H - 2 * hh)), int(np.clip(cx - hw, 0, W - 2 * hw))
            y1, x1 = y0 + max(int(2 * hh), 1), x0 + max(int(2 * hw), 1)
        else:
            y0, y1, x0, x1 = 0, H, 0, W
        tiles += [images.images[i][y0:y1, x0:x1], rgb[y0:y1, x0:x1]]
        names += [f"photo {cams[i].name}", "textured"]
    order = [tiles[k] for k in range(0, len(tiles), 2)] + [tiles[k] for k in range(1, len(tiles), 2)]
    labels = [names[k] for k in range(0, len(names), 2)] + [names[k] for k in range(1, len(names), 2)]
    return _rows_sheet(order, labels, len(picks), size)


def _rows_sheet(tiles, names, cols, width):
    """Tiles in rows of ``cols``, each scaled into a cell of ``width / cols`` pixels."""
    import cv2

    tw = max(width // cols, 8)
    th = max(int(round(tw * max(t.shape[0] / t.shape[1] for t in tiles))), 8)
    rows = -(-len(tiles) // cols)
    sheet = np.full((rows * th, cols * tw, 3), 32, np.uint8)
    for k, (tile, name) in enumerate(zip(tiles, names)):
        r, c = divmod(k, cols)
        scale = min(tw / tile.shape[1], th / tile.shape[0])
        w, h = max(int(tile.shape[1] * scale), 1), max(int(tile.shape[0] * scale), 1)
        sheet[r * th:r * th + h, c * tw:c * tw + w] = cv2.resize(tile, (w, h), interpolation=cv2.INTER_AREA)
        cv2.putText(sheet, name, (c * tw + 3, r * th + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0), 1, cv2.LINE_AA)
    return sheet


def draw_mesh_sequence(value, size, companions):
    if not value:
        return None
    picks = sorted(set(np.linspace(0, len(value) - 1, min(4, len(value))).round().astype(int)))
    up, front = _orientation(companions)
    if not vtk_available():
        return _projections(np.concatenate([np.asarray(value[i].vertices) for i in picks]), size, up)
    pv = _pyvista()
    p = pv.Plotter(off_screen=True, window_size=(size, max(size // len(picks), 96)), shape=(1, len(picks)), border=False)
    for col, i in enumerate(picks):
        p.subplot(0, col)
        mesh, kw = _vtk_mesh(value[i])
        p.add_mesh(mesh, **kw)
        p.add_text(f"#{i}", font_size=8, color="white")
        _place_camera(p, value[i].bounds, up, front)
    return _screenshot(p)


def draw_skeleton(value, size, companions):
    joints = np.asarray(value.joints, dtype=np.float64).reshape(-1, 3)
    bones = [(j, int(pj)) for j, pj in enumerate(value.parents) if pj >= 0]
    mesh = _load_companion("Mesh", companions) or _load_companion("TexturedMesh", companions)
    up, front = _orientation(companions)
    if not vtk_available():
        return _projections(joints, size, up, segments=bones)
    pv = _pyvista()
    extent = np.ptp(np.vstack([joints, mesh.vertices]) if mesh is not None else joints, axis=0).max() or 1.0
    items = []
    if mesh is not None:
        items.append((_vtk_mesh(mesh)[0], {"color": "#aaaaaa", "opacity": 0.12}))
    items.append((pv.PolyData(joints).glyph(geom=pv.Sphere(radius=0.03 * extent), scale=False, orient=False), {"color": "#e03030"}))
    if bones:
        lines = np.hstack([[2, a, b] for a, b in bones])
        items.append((pv.PolyData(joints, lines=lines).tube(radius=0.01 * extent), {"color": "#3070e0"}))
    return _render_vtk(items, size, up, front)


def _vtk_mesh(mesh):
    """(pyvista PolyData, add_mesh kwargs): textured when the mesh has UVs and an image, else vertex colours."""
    pv = _pyvista()
    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).astype(np.int64).ravel()
    poly = pv.PolyData(np.asarray(mesh.vertices, dtype=np.float64), faces)
    visual = mesh.visual
    if getattr(visual, "kind", None) == "texture" and visual.uv is not None:
        mat = visual.material
        image = getattr(mat, "baseColorTexture", None) or getattr(mat, "image", None)
        if image is not None:
            poly.active_texture_coordinates = np.asarray(visual.uv, dtype=np.float32)
            return poly, {"texture": pv.Texture(np.asarray(image.convert("RGB"))), "smooth_shading": True}
    if getattr(visual, "kind", None) == "vertex":
        poly.point_data["rgb"] = np.asarray(visual.vertex_colors)[:, :3]
        return poly, {"scalars": "rgb", "rgb": True, "smooth_shading": True}
    return poly, {"color": "#d9b38c", "smooth_shading": True}


def _render_vtk(items, size, up, front) -> np.ndarray:
    """Two views side by side: from ``front`` and rotated 90 degrees about ``up``."""
    pv = _pyvista()
    p = pv.Plotter(off_screen=True, window_size=(size, size // 2), shape=(1, 2), border=False)
    side = np.cross(up, front)
    bounds = _bounds_of([mesh for mesh, _ in items])
    for col, direction in enumerate((front, side)):
        p.subplot(0, col)
        for mesh, kw in items:
            p.add_mesh(mesh, **kw)
        _place_camera(p, bounds, up, direction)
    return _screenshot(p)


def _bounds_of(meshes) -> np.ndarray:
    """[min, max] of pyvista meshes (VTK bounds are xmin xmax ymin ymax zmin zmax)."""
    b = np.array([m.bounds for m in meshes if m.n_points], dtype=np.float64).reshape(-1, 6)
    return np.array([b[:, 0::2].min(axis=0), b[:, 1::2].max(axis=0)])


def _place_camera(p, bounds, up, direction):
    """Look at the box ``bounds`` ((2, 3) [min, max]) from ``direction`` (slightly above), ``up`` vertical."""
    lo, hi = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    centre, radius = (lo + hi) / 2, max(np.linalg.norm(hi - lo) / 2, 1e-9)
    view = direction / np.linalg.norm(direction) + 0.25 * up
    view /= np.linalg.norm(view)
    p.camera_position = [tuple(centre + view * radius * 3.2), tuple(centre), tuple(up)]
    p.camera.view_angle = 36.0
    p.set_background("#202020")


def _screenshot(p) -> np.ndarray:
    try:
        return np.asarray(p.screenshot(return_img=True))[:, :, :3].copy()
    finally:
        p.close()


def _orientation(companions) -> tuple[np.ndarray, np.ndarray]:
    """(world up, view direction from the object towards the viewer), from companion cameras if any."""
    cams = _load_companion("Cameras", companions)
    if cams is None or len(cams) == 0:
        return np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0])
    ups = []
    for cam in cams:
        m1, m3 = cam.P[1, :3], cam.P[2, :3]
        image_down = m1 - (m1 @ m3) / (m3 @ m3) * m3  # the image y axis in world terms (works for bare P too)
        ups.append(-image_down / np.linalg.norm(image_down))
    up = np.mean(ups, axis=0)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else ups[0]
    centres = cams.centers
    front = centres[0] - centres.mean(axis=0) if len(cams) > 1 else centres[0]
    front = front - (front @ up) * up
    if np.linalg.norm(front) < 1e-9:
        front = np.cross(up, [1.0, 0, 0]) if abs(up[0]) < 0.9 else np.cross(up, [0, 1.0, 0])
    return up, front / np.linalg.norm(front)


def _projections(points: np.ndarray, size: int, up: np.ndarray, segments=()) -> np.ndarray:
    """Fallback without VTK: orthographic point-density projections onto the three axis planes."""
    fig, canvas = _figure(size, size // 3)
    names = "xyz"
    for k, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        ax = fig.add_subplot(1, 3, k + 1)
        if len(points):
            bins = [min(64, len(np.unique(points[:, a]))), min(64, len(np.unique(points[:, b])))]
            ax.hist2d(points[:, a], points[:, b], bins=bins, cmap="magma", cmin=1)
            for i, j in segments:
                ax.plot(points[[i, j], a], points[[i, j], b], color="#3070e0", lw=1)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(names[a], fontsize=7)
        ax.set_ylabel(names[b], fontsize=7)
        ax.tick_params(labelsize=6)
        if up[b] < -0.5:  # keep world up pointing up on the page
            ax.invert_yaxis()
    fig.tight_layout()
    return _render_figure(fig, canvas)


# ---------------------------------------------------------------- cameras and bounds
def draw_cameras(value, size, companions):
    bounds = _load_companion("Bounds", companions)
    return _cameras_figure(value, bounds, size)


def draw_bounds(value, size, companions):
    return _cameras_figure(_load_companion("Cameras", companions), value, size)


def _cameras_figure(cams, bounds, size) -> np.ndarray:
    """Camera centres, frusta (image corners back-projected) and the box, in a matplotlib 3-D view."""
    fig, canvas = _figure(size, int(size * 0.75))
    ax = fig.add_subplot(1, 1, 1, projection="3d")
    pts = []
    if bounds is not None:
        lo, hi = np.asarray(bounds)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        for i in range(8):
            for j in range(i + 1, 8):
                if np.sum(corners[i] != corners[j]) == 1:
                    ax.plot(*corners[[i, j]].T, color="#2a9d2a", lw=1)
        pts.append(corners)
    if cams is not None and len(cams):
        centres = cams.centers
        target = (np.asarray(bounds).mean(axis=0) if bounds is not None else centres.mean(axis=0))
        depth = 0.35 * max(np.median(np.linalg.norm(centres - target, axis=1)), 1e-9)
        for cam, c in zip(cams, centres):
            M = cam.P[:, :3]
            uv = np.array([[0, 0, 1], [cam.width, 0, 1], [cam.width, cam.height, 1], [0, cam.height, 1]], float)
            rays = np.linalg.solve(M, uv.T).T
            rays *= depth / np.linalg.norm(rays, axis=1, keepdims=True)
            if np.dot(rays.mean(axis=0), target - c) < 0:  # sign-ambiguous bare P: point the frustum at the scene
                rays = -rays
            far = c + rays
            for k in range(4):
                ax.plot(*np.array([c, far[k]]).T, color="#4060c0", lw=0.6)
                ax.plot(*np.array([far[k], far[(k + 1) % 4]]).T, color="#4060c0", lw=0.6)
            pts.append(far)
        ax.scatter(*centres.T, color="#c03030", s=6)
        for cam, c in zip(cams, centres):
            ax.text(*c, cam.name, fontsize=5, color="#603030")
        pts.append(centres)
    if pts:
        allp = np.vstack(pts)
        mid, half = (allp.max(0) + allp.min(0)) / 2, np.ptp(allp, axis=0).max() / 2 or 1.0
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.tick_params(labelsize=5)
    ax.set_xlabel("x", fontsize=7)
    ax.set_ylabel("y", fontsize=7)
    ax.set_zlabel("z", fontsize=7)
    return _render_figure(fig, canvas)


def _pyvista():
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista

    return pyvista
