"""A skinned, animated rig as files production tools read: USD (UsdSkel: Skeleton, Animation, a Mesh with
joint indices and weights) and glTF 2.0 (a skin with inverse bind matrices, joint nodes, and one animation
with a translation and a rotation channel per joint). Both can be read back here (read_usd, read_gltf) and
re-skinned, which the tests do: the file's joint transforms at frame k must reproduce our skinned mesh.

Conventions: the rig's bone j takes rest points x to R_tj x + t_tj at frame t (the skinning matrix M_tj).
Each joint's bind (rest) transform is a pure translation to its rest pivot c_j; its world transform at frame
t is W_tj = M_tj B_j (rotation R_tj, origin at the moved pivot), its local transform W_t,parent^-1 W_tj. So
inverse(bind) * world = M_tj, which is what both formats skin with. USD matrices are row-vector (the
transpose of ours), glTF's are column-major arrays; time codes are the frame numbers (USD) or frame / fps
seconds from the first frame (glTF).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from nodes.common.types import FPS


def _names(names: list[str], count: int) -> list[str]:
    """Valid, unique USD/glTF joint names."""
    out, seen = [], set()
    for j in range(count):
        n = re.sub(r"[^A-Za-z0-9_]", "_", names[j] if j < len(names) and names[j] else f"joint_{j}")
        if not n or n[0].isdigit():
            n = "j_" + n
        base, k = n, 1
        while n in seen:
            n, k = f"{base}_{k}", k + 1
        seen.add(n)
        out.append(n)
    return out


def world_transforms(joints, rotations, translations) -> np.ndarray:
    """(F, J, 4, 4) joint world transforms W_tj = M_tj B_j (column-vector convention)."""
    f, j = rotations.shape[:2]
    w = np.zeros((f, j, 4, 4))
    w[..., :3, :3] = rotations
    w[..., :3, 3] = np.einsum("fjab,jb->fja", rotations, joints) + translations
    w[..., 3, 3] = 1.0
    return w


def local_transforms(world: np.ndarray, parents: list[int]) -> np.ndarray:
    """(F, J, 4, 4) joint transforms relative to their parents (the root's is its world transform)."""
    out = world.copy()
    for j, p in enumerate(parents):
        if p >= 0:
            out[:, j] = np.linalg.inv(world[:, p]) @ world[:, j]
    return out


def quaternions(rot: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (x, y, z, w) of rotation matrices (..., 3, 3)."""
    from scipy.spatial.transform import Rotation

    shape = rot.shape[:-2]
    return Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat().reshape(*shape, 4)


def key_quaternions(rot: np.ndarray) -> np.ndarray:
    """(F, J, 4) ``quaternions`` of (F, J, 3, 3) rotations keyed over frames, each key on the side of its
    predecessor (q and -q are the same rotation; q . q_prev >= 0), so that a player interpolating the four numbers
    turns the short way between keys instead of through a near-zero quaternion. The conversion alone picked the
    other sign at 102 of child_rope's 3743 character keys. Blender 4.5's glTF importer, USD's slerp (GfSlerp) and
    three.js take the short way by themselves (a bone spinning 10 degrees a frame: Blender's half frames within 2.1
    degrees of the slerp either way); a naive interpolator did not."""
    q = quaternions(rot)
    if len(q) > 1:
        side = np.where(np.einsum("fjc,fjc->fj", q[1:], q[:-1]) < 0, -1.0, 1.0)
        q[1:] *= np.cumprod(side, axis=0)[..., None]
    return q


def sparse_influences(weights: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(indices (V, k) int, weights (V, k) float) of the k largest weights per vertex, renormalised."""
    idx = np.argsort(-weights, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(weights, idx, axis=1)
    s = w.sum(1, keepdims=True)
    w = np.where(s > 0, w / np.where(s > 0, s, 1), np.eye(k)[0])
    idx = np.where(w > 0, idx, 0)
    return idx.astype(np.int64), w


# ---------------------------------------------------------------- USD
def write_usd(path: Path, vertices, faces, joints, parents, names, weights, rotations, translations, frames,
              fps: float = FPS, influences: int = 4):
    """Write a UsdSkel rig: /Rig (SkelRoot) with Skeleton, its Animation and the bound Mesh."""
    Path(path).write_bytes(usd_bytes(vertices=vertices, faces=faces, joints=joints, parents=parents, names=names,
                                     weights=weights, rotations=rotations, translations=translations, frames=frames,
                                     fps=fps, influences=influences))


def usd_bytes(vertices, faces, joints, parents, names, weights, rotations, translations, frames, fps: float = FPS,
              influences: int = 4, correctives=None) -> bytes:
    """The UsdSkel rig of ``write_usd`` as the bytes of a binary .usd layer; the SkelRoot's ``extent`` per frame
    bounds the skinned mesh (the mesh's own extent bounds its rest points). ``correctives`` (correctives.py,
    fitted with these ``influences``): UsdSkel BlendShape prims under the mesh (``skel:blendShapes`` /
    ``skel:blendShapeTargets``) and the Animation's ``blendShapes`` and per-frame ``blendShapeWeights``."""
    from nodes.common.usd import UsdStage

    names = _names(names, len(parents))
    paths = []
    for j, p in enumerate(parents):
        paths.append(names[j] if p < 0 else f"{paths[p]}/{names[j]}")
    joints = np.asarray(joints, np.float64)
    bind = np.tile(np.eye(4), (len(parents), 1, 1))
    bind[:, :3, 3] = joints
    local = local_transforms(world_transforms(joints, rotations, translations), parents)
    k = max(1, min(influences, len(parents)))
    idx, w = sparse_influences(np.asarray(weights, np.float64), k)

    stage = UsdStage(fps=fps, frames=(frames[0], frames[-1]))
    root = stage.group("/Rig", skel_root=True)
    skel = stage.skeleton("/Rig/Skeleton", paths, names, bind, local_transforms(bind[None], parents)[0])
    anim = stage.skeleton_animation(skel, "/Rig/Skeleton/Animation", frames, local[..., :3, 3],
                                    key_quaternions(local[..., :3, :3]))
    mesh = stage.mesh("/Rig/Mesh", faces, vertices)
    stage.bind_skin(mesh, skel, idx, w)
    rest = np.zeros((len(frames),) + np.shape(vertices))
    if correctives is not None and len(correctives.shapes):
        stage.blend_shapes(mesh, anim, [f"corrective_{i}" for i in range(len(correctives.shapes))],
                           correctives.shapes, frames, correctives.weights)
        rest = np.einsum("fk,kva->fva", correctives.weights, correctives.shapes)
    for k, frame in enumerate(frames):        # the SkelRoot's bounds: the mesh as UsdSkel skins it, per frame
        stage.extent_at(root, skinned_points(vertices + rest[k], idx, w, rotations[k], translations[k]), frame)
    return stage.save("rig.usd")


def skinned_points(vertices, indices, weights, rotations, translations) -> np.ndarray:
    """(V, 3) rest points skinned with sparse influences (``sparse_influences``) and one frame's (J, 3, 3)
    rotations and (J, 3) translations: sum_k w_vk (R_j x_v + t_j), j = indices[v, k]."""
    x = np.asarray(vertices, np.float64)
    r, t = np.asarray(rotations, np.float64)[indices], np.asarray(translations, np.float64)[indices]     # (V, k, ...)
    return np.einsum("vk,vkab,vb->va", weights, r, x) + np.einsum("vk,vka->va", weights, t)


def read_usd(path: Path) -> dict:
    """What a UsdSkel reader gets: rest points, faces, joint paths, frames (time samples), and per frame the
    points skinned by UsdSkel itself (blend shapes first: AnimQuery weights, the SkinningQuery's mapper,
    BlendShapeQuery; then SkeletonQuery skinning transforms + SkinningQuery LBS)."""
    from pxr import Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(path))
    root = UsdSkel.Root(stage.GetPrimAtPath("/Rig"))
    mesh_prim = stage.GetPrimAtPath("/Rig/Mesh")
    mesh = UsdGeom.Mesh(mesh_prim)
    cache = UsdSkel.Cache()
    cache.Populate(root, Usd.TraverseInstanceProxies())
    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Rig/Skeleton"))
    sq = cache.GetSkelQuery(skel)
    skin = cache.GetSkinningQuery(mesh_prim)
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Rig/Skeleton/Animation"))
    times = anim.GetRotationsAttr().GetTimeSamples()
    rest = np.array(mesh.GetPointsAttr().Get(), np.float64)
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
    faces = np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3) if np.all(counts == 3) else None
    shapes = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(mesh_prim)) if skin.HasBlendShapes() else None
    skinned, morph = [], []
    for t in times:
        xf = sq.ComputeSkinningTransforms(Usd.TimeCode(t))
        pts = mesh.GetPointsAttr().Get(Usd.TimeCode(t))
        if shapes is not None:
            w = skin.GetBlendShapeMapper().Remap(sq.GetAnimQuery().ComputeBlendShapeWeights(Usd.TimeCode(t)))
            morph.append(np.array(w, np.float64))
            sub, shape_idx, sub_idx = shapes.ComputeSubShapeWeights(w)
            if not shapes.ComputeDeformedPoints(sub, shape_idx, sub_idx, shapes.ComputeBlendShapePointIndices(),
                                                shapes.ComputeSubShapePointOffsets(), pts):
                raise ValueError(f"{path}: UsdSkel could not apply the blend shapes at time {t}")
        ok = skin.ComputeSkinnedPoints(xf, pts, Usd.TimeCode(t))
        if not ok:
            raise ValueError(f"{path}: UsdSkel could not skin the mesh at time {t}")
        skinned.append(np.array(pts, np.float64))
    return {"rest": rest, "faces": faces, "joints": list(skel.GetJointsAttr().Get()), "times": list(times),
            "skinned": np.array(skinned), "up": UsdGeom.GetStageUpAxis(stage), "fps": stage.GetTimeCodesPerSecond(),
            "blend_shapes": list(skin.GetBlendShapeOrder() or []) if shapes is not None else [],
            "blend_shape_weights": np.array(morph)}


# ---------------------------------------------------------------- glTF
def gltf_bytes(vertices, faces, joints, parents, names, weights, rotations, translations, frames, fps: float = FPS,
               influences: int = 4, correctives=None) -> bytes:
    """A binary glTF (GLB): one skinned mesh (rest POSITION and smooth NORMAL, which the skin moves too), its
    joint nodes, one animation (LINEAR) of n / fps seconds: a key per frame and a last key at n / fps repeating
    the last pose (held for one frame period, so a looping viewer shows the last frame like the others).
    ``correctives`` (correctives.py, fitted with 4 influences): its shapes as the mesh's morph targets (POSITION
    displacements, added before skinning as glTF does) and a ``weights`` channel on the same keys (LINEAR)."""
    from nodes.common.gltf import GltfBuilder
    from nodes.common.meshops import smooth_vertex_normals

    from .skinning import topological

    names = _names(names, len(parents))
    k = 4
    idx, w = sparse_influences(np.asarray(weights, np.float64), min(k, len(parents)))
    if idx.shape[1] < k:  # glTF's JOINTS_0 / WEIGHTS_0 hold four per vertex
        idx = np.pad(idx, ((0, 0), (0, k - idx.shape[1])))
        w = np.pad(w, ((0, 0), (0, k - w.shape[1])))
    joints = np.asarray(joints, np.float64)
    bind = np.tile(np.eye(4), (len(parents), 1, 1))
    bind[:, :3, 3] = joints
    rest_local = local_transforms(bind[None], parents)[0]
    local = local_transforms(world_transforms(joints, rotations, translations), parents)
    # key k at frame k's time; one more key at the clip's end (n / fps) holds the last pose for one frame period
    times = np.append((np.asarray(frames, np.float64) - frames[0]) / fps, (frames[-1] - frames[0] + 1) / fps)
    quats = key_quaternions(local[..., :3, :3])                           # (F, J, 4) xyzw, sign-continuous
    quats = np.concatenate([quats, quats[-1:]]).astype(np.float32)
    trans = np.concatenate([local[..., :3, 3], local[-1:, :, :3, 3]]).astype(np.float32)

    b = GltfBuilder("volcap skeleton")
    shapes = [] if correctives is None else list(correctives.shapes)
    body = b.node("mesh", mesh=b.mesh(vertices, faces, normals=smooth_vertex_normals(vertices, faces), joints=idx,
                                      weights=w, targets=shapes))
    nodes = {}
    for j in topological(parents):                                        # a joint's parent node exists before it
        nodes[j] = b.node(names[j], parent=nodes[parents[j]] if parents[j] >= 0 else None,
                          translation=rest_local[j, :3, 3], rotation=[0.0, 0.0, 0.0, 1.0])
    nodes = [nodes[j] for j in range(len(parents))]
    roots = [nodes[j] for j, p in enumerate(parents) if p < 0]
    b.skin(nodes, np.linalg.inv(bind), skeleton=roots[0], node=body)
    for j in range(len(parents)):
        b.animate(nodes[j], "translation", times, trans[:, j], animation="motion")
        b.animate(nodes[j], "rotation", times, quats[:, j], animation="motion")
    if shapes:
        mw = np.concatenate([correctives.weights, correctives.weights[-1:]])          # the last key held, too
        b.animate(body, "weights", times, mw, animation="motion")
    return b.glb()


def read_gltf(data: bytes) -> dict:
    """Load a GLB with pygltflib and skin its mesh the way a glTF viewer does at every key (the frames', then
    the clip's end, which holds the last pose): morph targets first (POSITION + sum of the key's weights x
    target displacements, the weights channel of the mesh's node, else the mesh's default weights), then joint
    matrices = global joint transform (from the animated node TRS) x inverse bind matrix; positions back in the
    world frame (nodes.common.gltf.world_points)."""
    import pygltflib as G
    from scipy.spatial.transform import Rotation

    from nodes.common.gltf import read_accessor as _accessor
    from nodes.common.gltf import world_points

    gltf = G.GLTF2.load_from_bytes(data)
    blob = gltf.binary_blob()
    prim = gltf.meshes[0].primitives[0]
    pos = _accessor(gltf, blob, prim.attributes.POSITION).astype(np.float64)
    faces = _accessor(gltf, blob, prim.indices).reshape(-1, 3)
    jidx = _accessor(gltf, blob, prim.attributes.JOINTS_0).astype(np.int64)
    wts = _accessor(gltf, blob, prim.attributes.WEIGHTS_0).astype(np.float64)
    skin = gltf.skins[0]
    ibm = _accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1).astype(np.float64)
    n = len(gltf.nodes)
    parent = np.full(n, -1)
    for i, node in enumerate(gltf.nodes):
        for c in node.children or []:
            parent[c] = i
    anim = gltf.animations[0]
    tracks = {}
    times = None
    for ch in anim.channels:
        s = anim.samplers[ch.sampler]
        times = _accessor(gltf, blob, s.input).astype(np.float64)
        tracks[(ch.target.node, ch.target.path)] = _accessor(gltf, blob, s.output).astype(np.float64)
    targets = np.array([_accessor(gltf, blob, t["POSITION"] if isinstance(t, dict) else t.POSITION)
                        for t in prim.targets or []], np.float64).reshape(-1, len(pos), 3)
    body = next(i for i, node in enumerate(gltf.nodes) if node.mesh == 0)
    morph = tracks.get((body, "weights"))
    morph = (np.tile(gltf.meshes[0].weights or [0.0] * len(targets), (len(times), 1)) if morph is None
             else morph.reshape(len(times), len(targets)))
    skinned = []
    for k in range(len(times)):
        moved = pos + np.einsum("t,tva->va", morph[k], targets)
        local = np.tile(np.eye(4), (n, 1, 1))
        for i, node in enumerate(gltf.nodes):
            t = tracks.get((i, "translation"), [node.translation or [0, 0, 0]] * len(times))[k]
            q = tracks.get((i, "rotation"), [node.rotation or [0, 0, 0, 1]] * len(times))[k]
            local[i, :3, :3] = Rotation.from_quat(q).as_matrix()
            local[i, :3, 3] = t
        world = np.empty_like(local)
        done = np.zeros(n, bool)

        def glob(i):
            if not done[i]:
                world[i] = local[i] if parent[i] < 0 else glob(parent[i]) @ local[i]
                done[i] = True
            return world[i]

        mats = np.array([glob(j) @ ibm[a] for a, j in enumerate(skin.joints)])        # (J, 4, 4)
        per = np.einsum("jab,vb->vja", mats[:, :3, :3], moved) + mats[:, :3, 3][None]
        skinned.append(np.einsum("vk,vka->va", wts, per[np.arange(len(pos))[:, None], jidx]))
    return {"rest": world_points(pos), "faces": faces, "joints": [gltf.nodes[j].name for j in skin.joints],
            "times": times, "skinned": world_points(np.array(skinned)), "weights": wts, "indices": jidx,
            "targets": world_points(targets), "morph_weights": morph}


# ---------------------------------------------------------------- BVH
BVH_FROM_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])   # +Z up -> BVH's +Y up


def bvh_text(joints, parents, names, rotations, translations, frames, fps: float = FPS, **_) -> str:
    """The motion as BVH (Biovision hierarchy): +Y up and metres (the world frame turned as for glTF), offsets
    from the rest joints, the root with 6 channels (position, then Z X Y rotation), every other joint 3 (Z X Y),
    an End Site under each leaf half its bone's length on along it (a zero one makes Blender's importer warn and
    guess the leaf bone); one line per frame at 1 / ``fps``. Joint rotations are the rig's local ones. Blender's
    BVH importer with its defaults (forward -Z, up Y) puts every bone head where our joints are (+Z up)."""
    from scipy.spatial.transform import Rotation

    from .skinning import topological

    B = BVH_FROM_WORLD
    world = world_transforms(np.asarray(joints, np.float64), np.asarray(rotations), np.asarray(translations))
    joints = np.asarray(joints, np.float64) @ B.T                                         # rest joints, BVH axes
    names = _names(names, len(parents))
    b4 = np.eye(4)
    b4[:3, :3] = B
    local = b4 @ local_transforms(world, parents) @ b4.T                                   # (F, J, 4, 4), BVH axes
    order = topological(parents)
    children = {j: [c for c in order if parents[c] == j] for j in range(len(parents))}
    lines = ["HIERARCHY"]

    def emit(j, depth):
        pad = "  " * depth
        off = joints[j] if parents[j] < 0 else joints[j] - joints[parents[j]]
        lines.append(f"{pad}{'ROOT' if parents[j] < 0 else 'JOINT'} {names[j]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {off[0]:.6f} {off[1]:.6f} {off[2]:.6f}")
        if parents[j] < 0:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation")
        else:
            lines.append(f"{pad}  CHANNELS 3 Zrotation Xrotation Yrotation")
        for c in children[j]:
            emit(c, depth + 1)
        if not children[j]:                       # half the leaf's own bone on: importers give the leaf a length
            end = 0.5 * off if parents[j] >= 0 and np.linalg.norm(off) > 1e-9 else np.array([0.0, 0.1, 0.0])
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {end[0]:.6f} {end[1]:.6f} {end[2]:.6f}",
                          f"{pad}  }}"])
        lines.append(f"{pad}}}")

    roots = [j for j in order if parents[j] < 0]
    if len(roots) != 1:
        raise ValueError(f"BVH holds one root; the rig has {len(roots)}")
    emit(roots[0], 0)
    lines += ["MOTION", f"Frames: {len(frames)}", f"Frame Time: {1.0 / fps:.8f}"]
    channel_order = []

    def walk(j):
        channel_order.append(j)
        for c in children[j]:
            walk(c)

    walk(roots[0])
    r = roots[0]
    euler = continuous_euler(Rotation.from_matrix(local[:, channel_order, :3, :3].reshape(-1, 3, 3)).as_euler(
        "ZXY", degrees=True).reshape(len(frames), len(channel_order), 3))
    for f in range(len(frames)):
        vals = list(local[f, r, :3, 3])                                   # the root's position (replaces its offset)
        for k in range(len(channel_order)):
            vals += list(euler[f, k])
        lines.append(" ".join(f"{v:.6f}" for v in vals))
    return "\n".join(lines) + "\n"


def continuous_euler(e: np.ndarray) -> np.ndarray:
    """(F, J, 3) Tait-Bryan angles in degrees, each frame's the same rotations written nearest the frame before:
    of the two equivalent triples (a, b, c) and (a + 180, 180 - b, c + 180), each angle shifted by whole turns, the
    one closest to the last frame's. Written frame by frame in (-180, 180], a joint turning past 180 degrees jumps
    by 360 between two keys, and an importer that interpolates the channels spins it once round in between
    (Blender's BVH importer makes them continuous by itself; not every tool does)."""
    out = np.array(e, np.float64)
    for f in range(1, len(out)):
        prev = out[f - 1]
        alt = out[f] + np.array([180.0, 0.0, 180.0])
        alt[:, 1] = 180.0 - out[f, :, 1]
        best, cost = None, None
        for cand in (out[f], alt):
            cand = cand + 360.0 * np.round((prev - cand) / 360.0)
            c = np.abs(cand - prev).sum(axis=1)
            best = cand if best is None else np.where((c < cost)[:, None], cand, best)
            cost = c if cost is None else np.minimum(c, cost)
        out[f] = best
    return out


def read_bvh(text: str) -> dict:
    """Parse a BVH from ``bvh_text`` (any BVH with ZXY rotations and one root): {"names", "parents",
    "positions": (F, J, 3) world joint positions by forward kinematics, "rest": (J, 3) the hierarchy's offsets
    alone, both in the world frame (+Z up)}."""
    from scipy.spatial.transform import Rotation

    tok = text.split()
    names, parents, offsets, channels, stack = [], [], [], [], []
    i = 1 if tok and tok[0] == "HIERARCHY" else 0
    while tok[i] != "MOTION":
        t = tok[i]
        if t in ("ROOT", "JOINT"):
            names.append(tok[i + 1])
            parents.append(stack[-1] if stack else -1)
            i += 2
        elif t == "End":                          # End Site
            names.append(None)
            parents.append(stack[-1])
            i += 2
        elif t == "{":
            stack.append(len(names) - 1)
            i += 1
        elif t == "}":
            stack.pop()
            i += 1
        elif t == "OFFSET":
            offsets.append([float(x) for x in tok[i + 1:i + 4]])
            i += 4
        elif t == "CHANNELS":
            n = int(tok[i + 1])
            channels.append((len(names) - 1, tok[i + 2:i + 2 + n]))
            i += 2 + n
        else:
            raise ValueError(f"BVH: unexpected token {t!r}")
    nframes = int(tok[i + 2])
    values = np.array([float(x) for x in tok[i + 6:]]).reshape(nframes, -1)
    keep = [j for j, n in enumerate(names) if n is not None]
    offsets = np.array(offsets)
    pos = np.zeros((nframes, len(names), 3))
    for f in range(nframes):
        k = 0
        local = {}
        for j, ch in channels:
            v = values[f, k:k + len(ch)]
            k += len(ch)
            t = offsets[j].copy()
            rot_ch = [c for c in ch if c.endswith("rotation")]
            if len(ch) == 6:
                t = v[:3]
                v = v[3:]
            local[j] = (t, Rotation.from_euler("".join(c[0] for c in rot_ch), v, degrees=True).as_matrix())
        world = {}
        for j in range(len(names)):
            t, r = local.get(j, (offsets[j], np.eye(3)))
            if parents[j] < 0:
                world[j] = (r, t)
            else:
                pr, pt = world[parents[j]]
                world[j] = (pr @ r, pr @ t + pt)
            pos[f, j] = world[j][1]
    rest = np.zeros((len(names), 3))          # the hierarchy's own pose: offsets alone, no rotation
    for j in range(len(names)):
        rest[j] = offsets[j] + (rest[parents[j]] if parents[j] >= 0 else 0.0)
    return {"names": [names[j] for j in keep], "parents": [keep.index(parents[j]) if parents[j] >= 0 else -1
                                                            for j in keep],
            "positions": pos[:, keep] @ BVH_FROM_WORLD, "rest": rest[keep] @ BVH_FROM_WORLD}
