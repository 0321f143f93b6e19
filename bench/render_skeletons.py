"""Pictures of the skeleton stage, written to docs/:

    python bench/render_skeletons.py [thu_wd_human inria_dancer figure]

- skeleton_<dataset>.png: graphs/skeleton/<dataset>.yaml run on the real data (frame 0); the joint tree
  of the relaxed mesh (skeletonize) projected onto three camera images, extremities labelled, beside the
  tree from the hull volume. Checks by eye that the five extremities are the head, the hands and the feet.
- skeleton_humanoid_<dataset>.jpg (argument humanoid:<dataset>, thu_wd_human / inria_dancer / pose2sim_single):
  the named template (skeleton.humanoid) of graphs/skeleton/<dataset>.yaml over the photos of frame 0, red right,
  blue left; where the graph triangulates MediaPipe's body landmarks (pose2sim_single, thu_wd_human) they are
  drawn too (white crosses) and each joint's distance to its landmark printed: an independent check of the joints
  where limbs meet for the shape's fit (not for joints placed at the landmarks: there it is the landmark's distance
  from the limb's centre line). Where the graph also fits with the landmarks (node `marked`, thu_wd_human), that
  fit is the second row.
- skeleton_humanoid_figure.jpg (argument humanoid:figure): skeleton.humanoid on the synth walking figure at 128^3
  (``hand: 0, foot: 0.08``), frames 0, 6, 12, 18, over a front and a side view of the rendered frame, red right,
  blue left, the figure's true joints as white crosses; each frame's median and worst joint error printed.
- skeleton_figure.png: the synth walking figure over 100 frames: skeletonize.sequence + skin (10 bones,
  fixed bone lengths) on its true meshes; the rig drawn over the mesh at four frames (front view), the
  part of each vertex in colour, and the LBS error per frame.
Uses a cache in /tmp/volcap-skeleton-docs (reruns are quick).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("VOLCAP_DATA", str(ROOT.parent / "shared" / "data"))

CACHE = Path("/tmp/volcap-skeleton-docs")
COLOURS = {"head": (255, 60, 60), "hand": (60, 200, 60), "foot": (60, 120, 255)}


def run_graph_outputs(path: Path, wanted: list[tuple[str, str]]):
    from nodegraph.cache import Cache
    from nodegraph.executors import LocalExecutor
    from nodegraph.graphfile import load_graph
    from nodegraph.node import node_class
    from nodegraph.run import run_graph

    g = load_graph(path).keep_all()
    res = run_graph(g, Cache(CACHE / "cache"), CACHE / "out", LocalExecutor(1), progress=False)
    assert res.ok, res.failures
    out = {}
    for node, port in wanted:
        [rec] = [r for r in res.records if r["node"] == node]
        cls = node_class(rec["type"])
        out[(node, port)] = Cache(CACHE / "cache").load(rec["key"], port, cls.outputs[port].type)
    return out


def draw_tree(img, uv, parents, names, colour=(255, 220, 0), thick=3):
    import cv2

    for j, p in enumerate(parents):
        if p >= 0:
            cv2.line(img, tuple(map(int, uv[j])), tuple(map(int, uv[p])), colour, thick, cv2.LINE_AA)
    for j, (x, y) in enumerate(uv):
        name = names[j] if j < len(names) else ""
        kind = name.split("_")[0]
        c = COLOURS.get(kind, (255, 255, 255) if name == "root" else colour)
        cv2.circle(img, (int(x), int(y)), thick + 3 if kind in COLOURS or name == "root" else thick + 1, c, -1, cv2.LINE_AA)
        if kind in COLOURS or name == "root":
            cv2.putText(img, name, (int(x) + 8, int(y) - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 4, cv2.LINE_AA)
            cv2.putText(img, name, (int(x) + 8, int(y) - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.6, c, 1, cv2.LINE_AA)


def dataset_picture(name: str):
    import cv2

    vals = run_graph_outputs(ROOT / "graphs" / "skeleton" / f"{name}.yaml",
                             [("capture", "images"), ("capture", "cameras"), ("skeleton", "skeleton"),
                              ("skeleton", "report"), ("from_hull", "skeleton"), ("relax", "mesh")])
    images, cams = vals[("capture", "images")], vals[("capture", "cameras")]
    sk, hull_sk, rep = vals[("skeleton", "skeleton")], vals[("from_hull", "skeleton")], vals[("skeleton", "report")]
    mesh = vals[("relax", "mesh")]
    centre = np.asarray(mesh.vertices).mean(0)
    # three views around the subject: the cameras facing it from the most different directions
    dirs = np.array([(c.center - centre) / np.linalg.norm(c.center - centre) for c in cams.cameras])
    views = [0]
    while len(views) < 3:
        views.append(int(np.argmin(np.max(dirs @ dirs[views].T, axis=1))))
    tiles = []
    for v in views:
        img = images.images[v].copy()
        pts_uv, _ = cams.project(np.asarray(mesh.vertices), v)
        uv, _ = cams.project(sk.joints, v)
        huv, _ = cams.project(hull_sk.joints, v)
        lo = np.maximum(np.minimum(pts_uv.min(0), uv.min(0)) - 40, 0).astype(int)
        hi = np.minimum(np.maximum(pts_uv.max(0), uv.max(0)) + 40, [img.shape[1], img.shape[0]]).astype(int)
        a = img.copy()
        draw_tree(a, uv, sk.parents, sk.names)
        b = img.copy()
        draw_tree(b, huv, hull_sk.parents, hull_sk.names, colour=(255, 140, 0))
        crop = lambda x: x[lo[1]:hi[1], lo[0]:hi[0]]  # noqa: E731
        pair = np.hstack([crop(a), crop(b)])
        scale = 520 / pair.shape[0]
        pair = cv2.resize(pair, (int(pair.shape[1] * scale), 520), interpolation=cv2.INTER_AREA)
        for text, x0 in ((f"{cams.names[v]}: from the relaxed mesh", 8), ("from the hull volume", crop(a).shape[1] * scale + 8)):
            cv2.putText(pair, text, (int(x0), 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 4, cv2.LINE_AA)
            cv2.putText(pair, text, (int(x0), 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(pair)
    width = max(t.shape[1] for t in tiles)
    sheet = np.vstack([np.pad(t, ((0, 4), (0, width - t.shape[1]), (0, 0))) for t in tiles])
    title = np.zeros((56, width, 3), np.uint8)
    cv2.putText(title, f"{name}: skeletonize (relaxed mesh at 128^3), {rep['joints']} joints", (8, 22),
                cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    cv2.putText(title, f"extremities {', '.join(sorted(rep['names']))}, {rep['seconds'] * 1000:.0f} ms; "
                f"hull volume: {len([p for p in range(len(hull_sk.parents)) if p not in hull_sk.parents])} extremities",
                (8, 46), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    sheet = np.vstack([title, sheet])
    out = ROOT / "docs" / f"skeleton_{name}.png"
    from PIL import Image   # a 256-colour palette at 0.7x keeps docs/ pictures well under 1 MB

    img = Image.fromarray(np.ascontiguousarray(sheet))
    img = img.resize((int(img.width * 0.7), int(img.height * 0.7)), Image.LANCZOS)
    img.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(out, optimize=True)
    print(out, rep)


def draw_sides(img, uv, parents, names, labelled=(), thick=3):
    """A named rig over an image: bones in yellow, joints red (right), blue (left) or white; the joints whose name
    starts with one of ``labelled`` (e.g. "elbow") get their name beside them."""
    import cv2

    for c, p in enumerate(parents):
        if p >= 0:
            cv2.line(img, tuple(map(int, uv[c])), tuple(map(int, uv[p])), (255, 220, 0), thick, cv2.LINE_AA)
    for k, (x, y) in enumerate(uv):
        n = names[k]
        col = (255, 60, 60) if n.endswith("_r") else (60, 120, 255) if n.endswith("_l") else (255, 255, 255)
        cv2.circle(img, (int(x), int(y)), thick + 3, col, -1, cv2.LINE_AA)
        if n.split("_")[0] in labelled:
            for colour, width in (((0, 0, 0), 3), (col, 1)):
                cv2.putText(img, n, (int(x) + 8, int(y) - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, width, cv2.LINE_AA)


LANDMARK_OF = {"shoulder_{s}": "{side}_shoulder", "elbow_{s}": "{side}_elbow", "wrist_{s}": "{side}_wrist",
               "hip_{s}": "{side}_hip", "knee_{s}": "{side}_knee", "ankle_{s}": "{side}_ankle"}


def humanoid_picture(name: str):
    import cv2

    graph = ROOT / "graphs" / "skeleton" / f"{name}.yaml"
    from nodegraph.graphfile import load_graph

    has_points = "points" in load_graph(graph).nodes
    wanted = [("capture", "images"), ("capture", "cameras"), ("humanoid", "skeleton"), ("humanoid", "report")]
    vals = run_graph_outputs(graph, wanted + ([("points", "points")] if has_points else []))
    images, cams = vals[("capture", "images")], vals[("capture", "cameras")]
    sk, rep = vals[("humanoid", "skeleton")], vals[("humanoid", "report")]
    j = dict(zip(sk.names, np.asarray(sk.joints)))
    marks = {}
    rows = [sk]           # one row of pictures per fit: the shape's, and the landmarks' where the graph has one
    if has_points:
        pts = vals[("points", "points")]
        marks = {n: np.asarray(p) for n, p in zip(pts["landmarks"], pts["points"]) if p is not None}
        dist = {}
        for ours, theirs in LANDMARK_OF.items():
            for s, side in (("l", "left"), ("r", "right")):
                if theirs.format(side=side) in marks:
                    dist[ours.format(s=s)] = 100 * float(np.linalg.norm(j[ours.format(s=s)] - marks[theirs.format(side=side)]))
        print(f"{name}: humanoid joint to landmark, cm: " + ", ".join(f"{k} {v:.1f}" for k, v in dist.items())
              + f"; median {np.median(list(dist.values())):.1f}, max {max(dist.values()):.1f}")
        if "marked" in load_graph(graph).nodes:      # the shape's fit above, the landmarks-named one beside it
            msk = run_graph_outputs(graph, [("marked", "skeleton"), ("marked", "report")])
            mrep = msk[("marked", "report")]
            msk = msk[("marked", "skeleton")]
            m = dict(zip(msk.names, np.asarray(msk.joints)))
            d2 = [100 * float(np.linalg.norm(m[o.format(s=s)] - marks[t.format(side=side)])) for o, t in LANDMARK_OF.items()
                  for s, side in (("l", "left"), ("r", "right")) if t.format(side=side) in marks]
            print(f"{name}: with the landmarks naming extremities and sides and placing "
                  f"{', '.join(mrep.get('joints_from_landmarks', [])) or 'no joint'}: median {np.median(d2):.1f}, "
                  f"max {max(d2):.1f} cm")
            rows.append(msk)
    n_views = min(4, len(cams.cameras))
    views = [int(v) for v in np.linspace(0, len(cams.cameras), n_views, endpoint=False)]
    tiles = []
    for v in views:
        img0 = images.images[v]
        uvs = [cams.project(np.asarray(k.joints), v)[0] for k in rows]
        allu = np.vstack(uvs)
        lo = np.maximum(allu.min(0) - 120, 0).astype(int)
        hi = np.minimum(allu.max(0) + 120, [img0.shape[1], img0.shape[0]]).astype(int)
        column = []
        for k, uv, label in zip(rows, uvs, ("shape", "landmarks")):
            img = img0.copy()
            draw_sides(img, uv, k.parents, k.names, thick=4)
            if marks:
                muv, _ = cams.project(np.array(list(marks.values())), v)
                for x, y in muv:
                    cv2.drawMarker(img, (int(x), int(y)), (255, 255, 255), cv2.MARKER_CROSS, 14, 2)
            tile = img[lo[1]:hi[1], lo[0]:hi[0]]
            tile = cv2.resize(tile, (int(tile.shape[1] * 520 / tile.shape[0]), 520), interpolation=cv2.INTER_AREA)
            text = cams.names[v] + (f" ({label})" if len(rows) > 1 else "")
            cv2.putText(tile, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 4, cv2.LINE_AA)
            cv2.putText(tile, text, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 1, cv2.LINE_AA)
            column.append(tile)
        tiles.append(np.vstack(column))
    sheet = np.hstack(tiles)
    out = ROOT / "docs" / f"skeleton_humanoid_{name}.jpg"
    cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 80])
    print(out, {k: rep[k] for k in ("sides_from", "legs", "height") if k in rep})


def humanoid_figure_picture(resolution: int = 128):
    import cv2

    from nodegraph.testing import run_node
    from nodes.synth import scenes

    truth_of = {"pelvis": "pelvis", "chest": "chest", "neck": "neck", "head": "head", "shoulder_{s}": "{s}_shoulder",
                "elbow_{s}": "{s}_elbow", "wrist_{s}": "{s}_wrist", "hip_{s}": "{s}_hip", "knee_{s}": "{s}_knee",
                "ankle_{s}": "{s}_ankle"}
    tiles = []
    for f in (0, 6, 12, 18):
        shot = run_node("synth", {}, {"scene": "figure", "cameras": 8, "width": 640, "height": 480}, frame=f)
        truth = scenes.build("figure", f)
        sk = run_node("skeleton.humanoid", {"mesh": shot["mesh"]}, {"hand": 0, "foot": 0.08,
                                                                   "resolution": resolution})["skeleton"]
        voxel = float(np.ptp(np.asarray(shot["mesh"].vertices), axis=0).max()) / resolution
        ours, theirs = [], []
        for o, t in truth_of.items():
            for s in ("l", "r") if "{s}" in o else (None,):
                ours.append(np.asarray(sk.joints)[sk.names.index(o.format(s=s) if s else o)])
                theirs.append(truth.skeleton.joints[truth.skeleton.names.index(t.format(s=s) if s else t)])
        err = np.linalg.norm(np.array(ours) - np.array(theirs), axis=1) / voxel
        print(f"figure frame {f}: joint error median {np.median(err):.2f}, max {err.max():.2f} voxels at {resolution}^3")
        cams = shot["cameras"]
        column = []
        for v in (0, 2):
            img = np.ascontiguousarray(shot["images"].images[v][..., :3]).copy()
            uv, _ = cams.project(np.asarray(sk.joints), v)
            draw_sides(img, uv, sk.parents, sk.names, thick=2)
            tuv, _ = cams.project(np.array(theirs), v)
            for x, y in tuv:
                cv2.drawMarker(img, (int(round(x)), int(round(y))), (255, 255, 255), cv2.MARKER_CROSS, 10, 1)
            lo = np.maximum(uv.min(0) - 40, 0).astype(int)
            hi = np.minimum(uv.max(0) + 40, [img.shape[1], img.shape[0]]).astype(int)
            tile = cv2.resize(img[lo[1]:hi[1], lo[0]:hi[0]], None, fx=1.5, fy=1.5, interpolation=cv2.INTER_CUBIC)
            cv2.putText(tile, f"frame {f}, {cams.names[v]}", (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 3,
                        cv2.LINE_AA)
            cv2.putText(tile, f"frame {f}, {cams.names[v]}", (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255),
                        1, cv2.LINE_AA)
            column.append(tile)
        width = max(t.shape[1] for t in column)
        column = [cv2.copyMakeBorder(t, 0, 0, 0, width - t.shape[1], cv2.BORDER_CONSTANT) for t in column]
        tiles.append(np.vstack(column))
    height = max(t.shape[0] for t in tiles)
    sheet = np.hstack([cv2.copyMakeBorder(t, 0, height - t.shape[0], 0, 0, cv2.BORDER_CONSTANT) for t in tiles])
    out = ROOT / "docs" / "skeleton_humanoid_figure.jpg"
    cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 80])
    print(out)


def figure_picture(frames: int = 100):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh

    from nodegraph.testing import run_node
    from nodes.skeleton.skinning import lbs
    from nodes.synth import scenes

    rest, w, _ = scenes.figure_rest()
    meshes = [trimesh.Trimesh(scenes.skin(rest.vertices, w, *scenes.figure_pose(f)), rest.faces, process=False)
              for f in range(frames)]
    a = run_node("skeletonize.sequence", {"meshes": meshes}, {"bones": 10}, frames=list(range(frames)))
    b = run_node("skin", {"meshes": meshes, "skeleton": a["skeleton"]}, {}, frames=list(range(frames)))
    sk, err = b["skeleton"], b["error"]
    skinned = lbs(np.asarray(b["rest"].vertices), sk.weights, sk.rotations, sk.translations)
    labels = np.argmax(sk.weights, axis=1)
    fig = plt.figure(figsize=(16, 6.5))
    show = [0, 6, 12, 18]   # a step is 24 frames
    cmap = plt.get_cmap("tab10")
    for i, f in enumerate(show):
        ax = fig.add_subplot(1, 5, i + 1)
        v = skinned[f]
        a0 = 0 if i % 2 == 0 else 1                     # front view (x, z) and side view (y, z) in turn
        ax.scatter(v[::3, a0], v[::3, 2], s=0.4, c=cmap(labels[::3] % 10), alpha=0.5)
        piv = np.einsum("jab,jb->ja", sk.rotations[f], sk.joints) + sk.translations[f]
        true = scenes.figure_pose(f)[1]
        for j, p in enumerate(sk.parents):
            if p >= 0:
                ax.plot(piv[[j, p], a0], piv[[j, p], 2], "k-", lw=2)
        ax.plot(piv[:, a0], piv[:, 2], "ko", ms=5)
        ax.plot(true[:, a0], true[:, 2], "r+", ms=8, mew=1.5)
        ax.set_title(f"frame {f} ({'front' if a0 == 0 else 'side'}): rms {err['timeline']['rmse'][f] * 1000:.2f} mm",
                     fontsize=10)
        ax.set_aspect("equal")
        ax.axis("off")
    ax = fig.add_subplot(1, 5, 5)
    t = err["timeline"]
    ax.plot(t["frame"], np.array(t["rmse"]) * 1000, label="rms")
    ax.plot(t["frame"], np.array(t["max"]) * 1000, label="max")
    ax.set_xlabel("frame")
    ax.set_ylabel("LBS error (mm)")
    ax.set_title(f"rms {err['rmse'] * 1000:.3f} mm = {err['rmse_percent']:.4f} % of diagonal", fontsize=10)
    ax.legend()
    fig.suptitle(f"synth figure, {frames} frames: skeletonize.sequence + skin, {err['bones']} bones, fixed bone lengths "
                 f"(spread {err['bone_length_spread']:.1e}); black: our joints, red +: true joints; colours: parts")
    fig.tight_layout()
    out = ROOT / "docs" / "skeleton_figure.png"
    fig.savefig(out, dpi=80)
    print(out, {k: v for k, v in err.items() if k not in ("timeline", "residual", "history")})


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from machine import describe, load_average

    print(describe())
    names = sys.argv[1:] or ["thu_wd_human", "inria_dancer", "figure"]
    for n in names:
        if n == "figure":
            figure_picture()
        elif n == "humanoid:figure":
            humanoid_figure_picture()
        elif n.startswith("humanoid:"):
            humanoid_picture(n.split(":", 1)[1])
        else:
            dataset_picture(n)
    print(f"load average at the end: {load_average()}")
