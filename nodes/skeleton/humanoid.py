"""A named humanoid skeleton fitted to one body: the seed's "skeletal model provided at the start".

The template (``TEMPLATE``) is a joint tree with standard names and each joint's place along a path of the
body's curve skeleton, as a fraction of that path's arc length:

    spine   pelvis -> the head's tip:   spine, chest, neck, head; head_end at the tip
    arms    where the arm's path leaves the spine -> the hand's tip: shoulder, elbow, wrist; hand_end at the
            tip (the clavicle on the spine, ``CLAVICLE``)
    legs    pelvis -> the foot's tip: hip, knee, ankle; toe at the tip
Fitting (``fit_humanoid``): TEASAR centre lines of the solid (curve.py, not simplified); its extremities within
20 % of the height above the floor are the feet (two; one when the legs touch and make one column), of the others
the shortest branches are cut (stray spurs of the voxel skeleton) down to the head (the thickest right below its
tip: a raised hand may be higher, an arm along the body shorter) and two hands; the pelvis where the two feet's paths to the head meet
(moved across onto the hips' midpoint at the end; legs together: where the foot's path reaches 47 % of the height, and the column is split in halves along the
body's left-right axis, one leg in each), each arm's branch where its path reaches the spine
(the legs' joints are measured from the foot with the mean leg length: the legs' paths may meet off-centre);
then every joint at its fraction of its path (the spine's measured from where the legs meet), elbows and knees
moved to the path's sharpest bend within +-0.15 of their fraction when it bends by more than ``BEND_DEG``
(chords of a tenth of the path). A hip's place along its path is where the path has entered the thigh, below the
joint (the path leaves the crotch's branch point sideways and down): the hip is taken up the thigh's centre line
(knee -> that point, extended) to ``HIP_DROP`` of the leg below the branch point (synth walk at 128^3: hips median
5.3-6.0 -> 1.7 cm from the true joints; the branch point's own height gives 2.4), or higher, to the pelvis's widest
slice across the left-right axis, where that lies above (``HIP_BAND``: on a visual hull, whose filled crotch makes the
legs' paths meet low). Left and right: the feet point forwards
(the part of each foot below the ankle lies in front of it), right = forward x up; a joint's side is the
sign of its offset along right (measured at the upper arm and the thigh: hands and feet may cross the midline);
when the right arm and the right leg come out on opposite sides, the pair less aligned with right is flipped. Names map to the ones other tools retarget from (``RETARGET``: Mixamo, the
Unreal mannequin, SMPL). Fractions: the median place of each joint of the synth figure along its fitted path over a walk
cycle, checked against adult proportions; the wrists ``HAND`` of the height back from the arm's end (real people's
hands; ``hand`` 0 for a body without them, such as the synth figure, whose arms end at the wrists: the wrist at the
path's end, hand_end past it), the elbows ``FOREARM`` back from the wrists along the path, the ankles ``FOOT``
back from the leg's end (in a legs-together column at most ``ANKLE_RISE`` of the height above the floor it stands
on) and the knees halfway between the (raised) hips and the ankles (``foot``: the synth figure's feet are short,
0.08); the shoulders where the arm's path reaches ``SHOULDER_OUT`` of the height across from the
spine's axis, lifted onto the upper arm's centre line there (the path's corner into the body runs under the joint):
wrists, elbows, shoulders and the spine's joints are placed by proportion, not found. "The height" in these shares
is the body's stature where a sequence gives it (``bind_humanoid``), else the solid's own height. Given body
landmarks (``marks``, MediaPipe's), they name the extremities and the sides, and the shoulders, elbows, wrists,
knees and ankles go where their landmarks lie along the limb's centre line (``_place_at_marks``).
"""
from __future__ import annotations

import logging
import warnings

import numpy as np

from nodegraph import NodeError

LOG = logging.getLogger("volcap.skeleton")
SIDES = ("l", "r")
LOW_ARM = 0.3            # an arm whose path leaves the spine below this share of its arc meets the body at the hip
NEAR_SPINE = 0.12        # ... unless, coming from the hand, it passes this share of the height from the spine higher up:
                         # the curve skeleton has a second trunk there (the shoulders' bar joined low, not at the neck)
BEND_DEG = 25.0
FOOT_HEIGHT = 0.2        # extremities this share of the body's height above the floor are feet
CROTCH_HEIGHT = 0.47
HIP_DROP = 0.02          # the hips this share of the leg's path below where the legs' paths meet (on the thigh's line)
# ... or higher, at the pelvis's widest slice (the greater trochanters) when it lies above that and within HIP_BAND of
# the stature below / above it. On a visual hull the legs' paths meet low (the hull fills the crotch: the demo's rig
# over 24 frames had its hips 3.5-4.5 cm low at 128^3); the widest slice is the silhouettes' own (synth walk, relax
# meshes at 128^3: -0.7..+0.4 cm of the true hips' height). Only up: a person's widest slice lies at or below the
# joints (soft tissue; thu_wd_human's 2-3.6 cm below where the legs' paths put the hips)
HIP_BAND = (0.05, 0.09)
HIP_BREADTH = 0.3        # a slice wider than this share of the stature holds more than the pelvis (a hand against it)
# a slice wider than the one below it by more than 2.5 voxels, and by less than that one's 1 / MERGE times: something
# joined the pelvis there (legs joining at the crotch double the breadth; a hand adds a tenth or a fifth of it)
MERGE = 0.6
MIN_LEG = 0.15           # a leg's path from the pelvis shorter than this share of the height: no fit
HEAD_ARC = 0.12          # a head's thickness is measured this share of the height below its tip
# the shoulder joints this share of the height out from the spine's axis, on the upper arm's centre line:
# the arm's path leaves the spine low and its corner runs under the joint (synth walk at 128^3: shoulders 2.0-3.4
# voxels off along the path, 1.4-2.8 cm below the joint). Adults' shoulder joint centres lie about 0.2 of the height
# apart (the shoulders' breadth, ~0.23, less the acromions); the synth figure's 0.104
SHOULDER_OUT = 0.10
SIDEWAYS = 0.3           # ... lifted onto the upper arm's line only where that line runs at least this much sideways
# the clavicles' joint on the spine, this share of its arc (between chest 0.44 and neck 0.71: the synth figure's
# shoulders' height). Where the arm's path leaves the spine moves from fit to fit (synth walk: 1.32-1.39 m), and the
# clavicle-to-shoulder lengths measured from there made the rig's shoulders 2-4 cm too close to the spine
CLAVICLE = 0.62
# skeletonize.humanoid: a joint where the fits agree (the median distance of each fit's joint, carried by the surface to
# the kept fit's frame, from their median under this share of the stature) is placed at that median, not at the kept
# fit's (synth walk: spreads 0.3-2.1 cm, every joint; the kept fit, a stride frame's, had its hips 3-3.6 voxels low
# at 128^3. child_rope: spreads 2-22 cm, 0-3 joints a segment)
AGREE = 0.02
# the elbow this share of the height back from the wrist along the arm's path. The template's 0.60 of the path missed
# by up to 0.09 of it as the path's start at the spine moves (synth walk at 128^3: elbows up to 4.7 voxels off);
# MediaPipe's elbows on thu_wd_human, pose2sim_single and inria_dancer lie 0.149-0.182 of the height back from their
# wrists along the path (median 0.154; straight forearms 0.135-0.162), the synth figure's forearm 0.143
FOREARM = 0.15
# each limb bone's length: this quantile of the fits' lengths of it, by the joint it ends at. A crouch's bent legs' centre
# lines cut the corners and measure short: the legs' 75th percentile. The arms' median: a misplaced joint measures
# long as often (child_rope: the 75th percentile put the forearm at 20 cm, the wrist at 0.92 of the arm's path, and
# the crouched rest's wrists outside the arms; with the median 16 cm, posed joints > 2 cm outside 1.5 / 2.3 / 5.7 ->
# 0.9 / 1.2 / 3.2 % per segment, LBS and correctives no worse)
LIMB_QUANTILE = {"shoulder": 0.5, "elbow": 0.5, "wrist": 0.5, "hand_end": 0.5, "knee": 0.75, "ankle": 0.75, "toe": 0.75}
LIMB_BONES = tuple(LIMB_QUANTILE)  # the limbs' bones, by the joint they end at
# the wrist this share of the body's height back from the hand's end of the arm's centre line (the curve skeleton's
# extremity, inside the hand). Real people: MediaPipe's wrists lie 12.4-17.7 cm back from it on thu_wd_human,
# pose2sim_single and inria_dancer (0.075-0.107 of the height, median 0.085), where a fixed 0.92 of the arm's path put
# them 4-7.5 cm too far out, in the hand. 0: a body without hands (the synth figure: its arms end at the wrists)
HAND = 0.085
# the ankle this share of the height back from the foot's end of the leg's centre line (the toe's tip): MediaPipe's
# ankles lie 19-24.5 cm back on thu_wd_human, pose2sim_single and inria_dancer (0.113-0.148 of the height; one leg
# whose path ends off the foot 0.069; median of the six 0.123), where 0.88 of the leg's path put five of the six 8-12
# cm towards the toes. The synth figure's feet are short: 0.072-0.091 (``foot`` 0.08 in its graphs). The knee then
# lies halfway between hip and ankle along the path (MediaPipe's: 0.46-0.53 of the way; the synth figure's 0.48-0.50),
# or at the leg's sharpest bend near there
FOOT = 0.12
# ... but, in a legs-together column (one column split in halves: no foot stands out of it, its centre line comes
# straight down onto the floor under the ankles), no higher than this share of the stature above the floor where the
# column stands on it. FOOT alone put child_rope's fitted ankles 10-13 cm up (mid-shin; shins 8-20 cm for a 1.2 m
# child), and its rig's posed ankles a median 10.5-18.3 cm above the sole of a foot on the floor. MediaPipe's ankles
# stand 0.055-0.06 of the height above the floor on thu_wd_human and inria_dancer's planted foot, the synth figure's
# true ankles 0.053. (On legs apart, whose paths run out along the feet, FOOT alone: the rule there moved the synth
# figure's ankles and knees off the truth.) The knees of such a column stay halfway: its halves' bends are the
# column's outline, not knees (child_rope: bends 15-20 cm above the floor made 8 cm shins)
ANKLE_RISE = 0.055
MIN_BONE = 0.05          # no limb bone shorter than this share of the height (the stature) from a bend or a landmark
SIDES_ANKLE = 0.88       # left and right: the foot's cells below this share of the leg's path (the ankle's place before
                         # FOOT; the ankle's new place widened the foot's cells into the other leg of a legs-together
                         # column and turned child_rope's segment 0 round)
HEAD_THICKER = 1.5       # ... and must be this many times a hand's     # legs together: where the legs meet, this share of the height above the floor
# name: (parent, path, fraction of the path's arc); "{s}" is the side
TEMPLATE = {
    "pelvis": (None, "spine", 0.09), "spine": ("pelvis", "spine", 0.26), "chest": ("spine", "spine", 0.44),
    "neck": ("chest", "spine", 0.71), "head": ("neck", "spine", 0.90), "head_end": ("head", "spine", 1.0),
    "clavicle_{s}": ("chest", "arm", 0.0), "shoulder_{s}": ("clavicle_{s}", "arm", 0.26),
    "elbow_{s}": ("shoulder_{s}", "arm", None), "wrist_{s}": ("elbow_{s}", "arm", None),   # None: FOREARM, HAND
    "hand_end_{s}": ("wrist_{s}", "arm", 1.0),
    "hip_{s}": ("pelvis", "leg", 0.14), "knee_{s}": ("hip_{s}", "leg", None), "ankle_{s}": ("knee_{s}", "leg", None),
    "toe_{s}": ("ankle_{s}", "leg", 1.0),
}
BENDS = {"elbow_{s}", "knee_{s}"}
# our name -> (Mixamo, Unreal mannequin, SMPL); "{S}" Left/Right, "{s}" l/r, "{side}" left/right
RETARGET = {
    "pelvis": ("mixamorig:Hips", "pelvis", "pelvis"), "spine": ("mixamorig:Spine", "spine_01", "spine1"),
    "chest": ("mixamorig:Spine2", "spine_03", "spine3"), "neck": ("mixamorig:Neck", "neck_01", "neck"),
    "head": ("mixamorig:Head", "head", "head"), "head_end": ("mixamorig:HeadTop_End", "", ""),
    "clavicle_{s}": ("mixamorig:{S}Shoulder", "clavicle_{s}", "{side}_collar"),
    "shoulder_{s}": ("mixamorig:{S}Arm", "upperarm_{s}", "{side}_shoulder"),
    "elbow_{s}": ("mixamorig:{S}ForeArm", "lowerarm_{s}", "{side}_elbow"),
    "wrist_{s}": ("mixamorig:{S}Hand", "hand_{s}", "{side}_wrist"), "hand_end_{s}": ("", "", "{side}_hand"),
    "hip_{s}": ("mixamorig:{S}UpLeg", "thigh_{s}", "{side}_hip"), "knee_{s}": ("mixamorig:{S}Leg", "calf_{s}", "{side}_knee"),
    "ankle_{s}": ("mixamorig:{S}Foot", "foot_{s}", "{side}_ankle"), "toe_{s}": ("mixamorig:{S}ToeBase", "ball_{s}", "{side}_foot"),
}
TOOLS = ("mixamo", "unreal", "smpl")


def template_names() -> list[str]:
    """Every joint name of the template, parents first."""
    out = []
    for name in TEMPLATE:
        out.extend([name.format(s=s) for s in SIDES] if "{s}" in name else [name])
    return out


def retarget_names(tool: str) -> dict[str, str]:
    """Our joint name -> ``tool``'s (mixamo, unreal or smpl); joints the tool has no name for are left out."""
    k = TOOLS.index(tool)
    out = {}
    for ours, theirs in RETARGET.items():
        for s, S, side in (("l", "Left", "left"), ("r", "Right", "right")) if "{s}" in ours else ((None, None, None),):
            name = theirs[k].format(s=s, S=S, side=side) if s else theirs[k]
            if name:
                out[ours.format(s=s) if s else ours] = name
    return out


def _tree_paths(points: np.ndarray, parent: np.ndarray):
    """path(a, b): the node indices from a to b along the tree (parent pointers)."""
    depth = np.full(len(parent), -1, np.int64)
    for v in range(len(parent)):
        stack, u = [], v
        while u >= 0 and depth[u] < 0:
            stack.append(u)
            u = int(parent[u])
        d = -1 if u < 0 else int(depth[u])
        for w in reversed(stack):
            d += 1
            depth[w] = d

    def path(a: int, b: int) -> list[int]:
        up_a, up_b = [a], [b]
        while depth[up_a[-1]] > depth[up_b[-1]]:
            up_a.append(int(parent[up_a[-1]]))
        while depth[up_b[-1]] > depth[up_a[-1]]:
            up_b.append(int(parent[up_b[-1]]))
        while up_a[-1] != up_b[-1]:
            up_a.append(int(parent[up_a[-1]]))
            up_b.append(int(parent[up_b[-1]]))
        return up_a + up_b[-2::-1]

    return path


def _spine_share(pts, spine_path, v) -> float:
    """Where node ``v`` of the spine's path lies along it, as a share of its arc from the pelvis."""
    return _length(pts[spine_path[:spine_path.index(v) + 1]]) / max(_length(pts[spine_path]), 1e-12)


def _nearest_arc(points: np.ndarray, p: np.ndarray) -> tuple[float, float]:
    """(fraction of the arc, distance) of the point of a polyline nearest ``p``."""
    a, d = points[:-1], np.diff(points, axis=0)
    dd = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    gap = np.linalg.norm(a + t[:, None] * d - p, axis=1)
    i = int(np.argmin(gap))
    s = np.concatenate([[0.0], np.cumsum(np.sqrt(dd))])
    return float((s[i] + t[i] * np.sqrt(dd[i])) / max(s[-1], 1e-12)), float(gap[i])


def _line(poly: np.ndarray, span) -> tuple[np.ndarray, np.ndarray]:
    """(centre, unit direction towards the span's end) of the line fitted to a polyline between two fractions of
    its arc."""
    q = np.array([_at(poly, f) for f in np.linspace(span[0], span[1], 9)])
    c = q.mean(axis=0)
    d = np.linalg.svd(q - c)[2][0]
    return c, d if d @ (q[-1] - q[0]) >= 0 else -d


def _shoulder(arm: np.ndarray, frac: float, axis: np.ndarray, up: np.ndarray, right: np.ndarray,
              out: float) -> tuple[float, np.ndarray]:
    """(fraction of the arm's path, point) of the shoulder joint: where the path first reaches ``out`` from the
    spine's axis (the vertical line through ``axis``; ``frac`` if the path does not by ``frac`` + 0.1 of its arc: an
    arm close along the body), then on the upper arm's centre line (fitted to the path 0.12-0.3 of its arc further
    on, clear of the corner where the path turns into the body) at ``out`` from the axis, the crossing nearer the
    path's point. An upper arm that runs less than SIDEWAYS along ``right`` (forward, or down along the body) meets
    that distance far from the joint, if at all: there the path's point (also when the line never reaches it)."""
    flat = lambda x: x - (x @ up) * up
    grid = np.linspace(0.0, frac + 0.1, 41)
    reach = np.array([np.linalg.norm(flat(_at(arm, f) - axis)) for f in grid])
    if (reach >= out).any():
        frac = float(grid[int(np.argmax(reach >= out))])
    p = _at(arm, frac)
    c, d = _line(arm, (frac + 0.12, min(frac + 0.3, 1.0)))
    if abs(float(d @ right)) < SIDEWAYS:
        return frac, p
    w, dh = flat(c - axis), flat(d)
    t = float((p - c) @ d)
    a, b, k = dh @ dh, 2.0 * float(w @ dh), float(w @ w) - out * out
    disc = b * b - 4 * a * k
    if disc < 0:
        return frac, p
    t = min(((-b - np.sqrt(disc)) / (2 * a), (-b + np.sqrt(disc)) / (2 * a)), key=lambda x: abs(x - t))   # |w + t dh| = out
    return frac, c + t * d


def _solid(occ: np.ndarray, origin, spacing, point: np.ndarray) -> bool:
    ijk = np.floor((np.asarray(point) - origin) / spacing).astype(int)
    return bool(np.all(ijk >= 0) and np.all(ijk < occ.shape) and occ[tuple(ijk)])


def _hip_level(occ: np.ndarray, origin, spacing, u: np.ndarray, right: np.ndarray, centre: np.ndarray,
               guess: float, size: float) -> float | None:
    """The height (along ``u``) of the widest slice of the pelvis between ``HIP_BAND`` of ``size`` below and above
    ``guess``: per slice of the voxels across ``u`` (an axis of the grid) the 4-connected part nearest ``centre``,
    its extent along ``right``; the mean height of the run of slices around the widest that are within half a
    voxel of it. None when ``u`` is not an axis of the grid, or that run reaches the band's edge, an empty slice or
    one wider than ``HIP_BREADTH``, or something joined the pelvis below its top (``MERGE``): no peak of the
    pelvis's own inside the band."""
    from scipy import ndimage

    axis = int(np.argmax(np.abs(u)))
    if abs(u[axis]) < 1 - 1e-6:
        return None
    sign = float(np.sign(u[axis]))
    origin, spacing = np.asarray(origin, np.float64), np.broadcast_to(np.asarray(spacing, np.float64), (3,))
    step = float(spacing.min())
    heights = sign * (origin[axis] + (np.arange(occ.shape[axis]) + 0.5) * spacing[axis])
    pick = np.flatnonzero((heights >= guess - HIP_BAND[0] * size) & (heights <= guess + HIP_BAND[1] * size))
    pick = pick[np.argsort(heights[pick])]      # upwards
    if len(pick) < 3:
        return None
    across = [a for a in range(3) if a != axis]
    at = (np.asarray(centre, np.float64)[across] - origin[across]) / spacing[across] - 0.5
    width = np.full(len(pick), np.nan)          # NaN: an empty slice; inf: wider than a pelvis
    for n, k in enumerate(pick):
        labels, count = ndimage.label(np.take(occ, k, axis=axis))
        if count == 0:
            continue
        ij = np.argwhere(labels)
        part = ij[labels[tuple(ij.T)] == labels[tuple(ij[np.argmin(((ij - at) ** 2).sum(1))])]]
        flat = np.zeros((len(part), 3))
        flat[:, across] = origin[across] + (part + 0.5) * spacing[across]
        w = float(np.ptp(flat @ right)) + step
        width[n] = w if w <= HIP_BREADTH * size else np.inf
    finite = np.isfinite(width)
    if not finite.any():
        return None
    best = int(np.argmax(np.where(finite, width, -np.inf)))
    near = finite & (width >= width[best] - 0.5 * step)
    lo = hi = best
    while lo > 0 and near[lo - 1]:
        lo -= 1
    while hi < len(pick) - 1 and near[hi + 1]:
        hi += 1
    if lo == 0 or hi == len(pick) - 1 or not (finite[lo - 1] and finite[hi + 1]):
        return None
    below = width[:hi + 1]
    grew = below[1:] - below[:-1]
    if np.any(np.isfinite(grew) & (grew > 2.5 * step) & (below[:-1] > MERGE * below[1:])):
        return None   # something beside the pelvis joined it up to the peak (hands against the hips)
    return float(heights[pick[lo:hi + 1]].mean())


def _length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def _at(points: np.ndarray, frac: float) -> np.ndarray:
    """The point at ``frac`` of a polyline's arc length."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] == 0:
        return points[0].copy()
    return np.array([np.interp(frac * s[-1], s, points[:, a]) for a in range(3)])


def _planted_ankle(leg: np.ndarray, u: np.ndarray, floor: float, size: float) -> float | None:
    """The share of a leg's path (pelvis -> foot) at which it last rises ``ANKLE_RISE`` x ``size`` above the floor,
    coming back from the foot: where the ankle is at the highest on a foot standing on the floor. None when the
    path's end is not on the floor (within half that height: a raised foot) or never rises that high."""
    h = leg @ u - floor
    top = ANKLE_RISE * size
    if len(leg) < 2 or h[-1] > 0.5 * top:
        return None
    above = np.flatnonzero(h >= top)
    if not len(above):
        return None
    i = int(above[-1])                       # the last point at the height; the next is under it
    t = (h[i] - top) / max(h[i] - h[i + 1], 1e-12)
    seg = np.linalg.norm(np.diff(leg, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    return float((arc[i] + t * seg[i]) / max(arc[-1], 1e-12))


def _bend(points: np.ndarray, frac: float, window: float = 0.15, chord: float = 0.1) -> tuple[float, float]:
    """(fraction, degrees) of the sharpest bend of a polyline within frac +- window: the angle between the
    chords to the points ``chord`` of the arc before and after (long chords: the voxel path's stair steps
    are not bends)."""
    best = (frac, 0.0)
    for f in np.linspace(max(chord, frac - window), min(1 - chord, frac + window), 31):
        a, b, c = _at(points, f - chord), _at(points, f), _at(points, f + chord)
        u, v = b - a, c - b
        nu, nv = np.linalg.norm(u), np.linalg.norm(v)
        if nu and nv:
            ang = float(np.degrees(np.arccos(np.clip(u @ v / nu / nv, -1, 1))))
            if ang > best[1]:
                best = (float(f), ang)
    return best


def _cut(tree, leaf: int):
    """The tree without ``leaf``'s branch (up to the first joint with another child, or the root's child)."""
    from .curve import CurveSkeleton

    children = [0] * len(tree.parents)
    for p in tree.parents:
        if p >= 0:
            children[p] += 1
    chain, j = [leaf], leaf
    while tree.parents[j] >= 0 and children[tree.parents[j]] == 1 and tree.parents[tree.parents[j]] >= 0:
        j = tree.parents[j]
        chain.append(j)
    keep = [k for k in range(len(tree.parents)) if k not in set(chain)]
    remap = {k: i for i, k in enumerate(keep)}
    return CurveSkeleton(tree.joints[keep], [remap[tree.parents[k]] if tree.parents[k] >= 0 else -1 for k in keep], [],
                         None if tree.radius is None else tree.radius[keep], [tree.kind[k] for k in keep])


def _branch_length(tree, leaf: int) -> float:
    children = [0] * len(tree.parents)
    for p in tree.parents:
        if p >= 0:
            children[p] += 1
    j, length = leaf, 0.0
    while tree.parents[j] >= 0:
        length += float(np.linalg.norm(tree.joints[j] - tree.joints[tree.parents[j]]))
        j = tree.parents[j]
        if children[j] > 1 or tree.parents[j] < 0:
            break
    return length


def _reach(tree, j: int) -> float:
    length = 0.0
    while tree.parents[j] >= 0:
        length += float(np.linalg.norm(tree.joints[j] - tree.joints[tree.parents[j]]))
        j = tree.parents[j]
    return length


def _tip_thickness(raw, point: np.ndarray, arc: float) -> float:
    """The largest distance to the boundary along the raw skeleton within ``arc`` of an extremity's tip: a head is
    thick right below its top, a hand is not (the tip itself touches the boundary: its own radius says nothing)."""
    v = int(np.argmin(np.linalg.norm(raw.points - point, axis=1)))
    best, walked = float(raw.radius[v]), 0.0
    while raw.parent[v] >= 0 and walked < arc:
        walked += float(np.linalg.norm(raw.points[v] - raw.points[raw.parent[v]]))
        v = int(raw.parent[v])
        best = max(best, float(raw.radius[v]))
    return best


MARK_REACH = 0.3        # a landmark names the tree's extremity nearest it within this distance (metres)
# limb joints placed where their landmark lies along the limb's centre line (not the hips: MediaPipe's sit high, on
# thu_wd_human 8-10 cm above where the legs' paths meet), when the landmark is within JOINT_REACH of that line
MARKED_JOINTS = ("shoulder", "elbow", "wrist", "knee", "ankle")
JOINT_REACH = 0.08


def body_marks(points: dict) -> dict | None:
    """fit_humanoid's ``marks`` from named 3D body landmarks (MediaPipe's names, skeleton.keypoints: None where
    not triangulated): head = nose, hands = index finger (else wrist), feet = foot index (else ankle), right =
    from the left hip and shoulder to the right ones; None when one is missing."""
    def first(*names):
        return next((np.asarray(points[n], np.float64) for n in names if points.get(n) is not None), None)

    out = {"head": first("nose")}
    for s, side in (("l", "left"), ("r", "right")):
        out[f"hand_{s}"] = first(f"{side}_index", f"{side}_wrist")
        out[f"foot_{s}"] = first(f"{side}_foot_index", f"{side}_ankle")
    pairs = [(first(f"right_{k}"), first(f"left_{k}")) for k in ("hip", "shoulder")]
    if any(v is None for v in out.values()) or any(a is None or b is None for a, b in pairs):
        return None
    out["right"] = sum(a - b for a, b in pairs)
    out["joints"] = {f"{k}_{s}": first(f"{side}_{k}") for k in MARKED_JOINTS for s, side in (("l", "left"), ("r", "right"))
                     if first(f"{side}_{k}") is not None}
    return out


def _marked_extremities(tree, marks: dict):
    """(tree, named) with the extremities the landmarks name (head, hand_l, hand_r, foot_l, foot_r: the leaf
    nearest each, within MARK_REACH) and every other branch cut; None where a landmark has no leaf near it.
    Both feet on one leaf: the legs touch (one foot, as _extremities names it)."""
    roles = {"head": "head", "hand_l": "hand_0", "hand_r": "hand_1", "foot_l": "foot_0", "foot_r": "foot_1"}
    while True:
        leaves = tree.leaves
        pos = tree.joints[leaves]
        chosen = {}
        for role, name in roles.items():
            d = np.linalg.norm(pos - marks[role], axis=1)
            if d.min() > MARK_REACH:
                return None
            chosen[name] = leaves[int(np.argmin(d))]
        if len({chosen["head"], chosen["hand_0"], chosen["hand_1"], chosen["foot_0"]}) < 4 or chosen["foot_1"] in (
                chosen["head"], chosen["hand_0"], chosen["hand_1"]):
            return None
        rest = [j for j in leaves if j not in set(chosen.values())]
        if not rest:
            if chosen["foot_1"] == chosen["foot_0"]:
                del chosen["foot_1"]
            return tree, chosen
        tree = _cut(tree, min(rest, key=lambda j: _branch_length(tree, j)))


def _extremities(tree, u: np.ndarray, floor: float, height: float, node: str, raw=None):
    """(tree, {"head", "hand_0", "hand_1", "foot_0"[, "foot_1"]: joint}) of a person's curve skeleton: feet are
    extremities within FOOT_HEIGHT of the floor (one foot: the legs touch, one column), at most two; of the others
    the shortest branches are cut (a stray spur of the voxel skeleton) down to three: the head (the nearest to the
    root along the tree: arms are longer than the neck; given the raw skeleton, the thickest within HEAD_ARC of the
    height below its tip: a head is, a hand is not) and the hands."""
    while True:
        leaves = tree.leaves
        h = {j: float(tree.joints[j] @ u) - floor for j in leaves}
        feet = sorted((j for j in leaves if h[j] < FOOT_HEIGHT * height), key=lambda j: h[j])
        others = [j for j in leaves if j not in feet]
        if len(feet) > 2:
            tree = _cut(tree, min(feet, key=lambda j: _branch_length(tree, j)))
        elif len(others) > 3:
            tree = _cut(tree, min(others, key=lambda j: _branch_length(tree, j)))
        else:
            break
    if not feet:
        raise NodeError(f"{node}: no extremity of the body's curve skeleton is near the floor (within "
                        f"{FOOT_HEIGHT:.0%} of its height): no feet found (is the world frame upright?)")
    if len(others) < 3:
        raise NodeError(f"{node}: the body's curve skeleton has {len(others)} extremities above the feet, fewer than a "
                        "head and two hands: arms against the body? (try another frame)")
    if raw is not None:   # the thickest below its tip (a raised hand can be higher, an arm longer than a neck)
        thick = {j: _tip_thickness(raw, tree.joints[j], HEAD_ARC * height) for j in others}
        head = max(others, key=thick.get)
        if any(thick[head] < HEAD_THICKER * thick[j] for j in others if j != head):
            raise NodeError(f"{node}: no extremity is clearly thicker than the others below its tip (a head: "
                            f"{sorted(round(t, 3) for t in thick.values())} m): arms over the head? (try another frame)")
    else:
        head = min(others, key=lambda j: _reach(tree, j))
    hands = [j for j in others if j != head]
    named = {"head": head, "hand_0": hands[0], "hand_1": hands[1]}
    named.update({f"foot_{k}": j for k, j in enumerate(feet)})
    return tree, named


def _place_at_marks(joints, names, fracs, limbs, side, marked: dict, node: str, height: float) -> list[str]:
    """Limb joints moved (in place in ``joints``) to where their landmark lies along the limb's centre line, when
    the landmark is within JOINT_REACH of it and keeps the limb's joints in order, each bone at least MIN_BONE of
    the height (else that landmark is not taken, with a warning); the joints without a landmark keep their
    places; ``fracs`` follows the moved joints. The names moved."""
    moved = []
    for which, chain, start in (("arm", ("shoulder", "elbow", "wrist"), "clavicle"), ("leg", ("knee", "ankle"), "hip")):
        for s in SIDES:
            poly = limbs[(which, side[(which, s)])]
            gap = MIN_BONE * height / max(_length(poly), 1e-12)
            at = {}
            for k in chain:
                p = marked.get(f"{k}_{s}")
                if p is not None:
                    f, off = _nearest_arc(poly, np.asarray(p, np.float64))
                    if off <= JOINT_REACH:
                        at[k] = f
            last = fracs[f"{chain[-1]}_{s}"]       # the limb's end lies past its last joint (1.0: the path's end)
            end = 1.0 + gap if last >= 1.0 else 1.0
            while at:
                seq = [(None, fracs[f"{start}_{s}"])] + [(k, at.get(k, fracs[f"{k}_{s}"])) for k in chain] + [(None, end)]
                bad = next((i for i in range(len(seq) - 1) if seq[i + 1][1] - seq[i][1] < gap - 1e-9), None)
                if bad is None:
                    break
                drop = seq[bad + 1][0] if seq[bad + 1][0] in at else seq[bad][0]
                if drop not in at:        # the template's own joints too close: leave the limb as it is
                    at = {}
                    break
                LOG.warning("%s: the %s_%s landmark lies out of order along the limb (or too near a neighbour): "
                            "not taken", node, drop, s)
                del at[drop]
            for k, f in at.items():
                joints[names.index(f"{k}_{s}")] = _at(poly, f)
                fracs[f"{k}_{s}"] = f            # (a knee halfway to its ankle reads the landmark's)
                moved.append(f"{k}_{s}")
    return sorted(moved)


def _elbow_between(shoulder, wrist, up_len: float, fore_len: float, cells: np.ndarray, spine: np.ndarray,
                   step: float) -> np.ndarray:
    """An elbow ``up_len`` from the shoulder and ``fore_len`` from the wrist: of the circle where the two spheres
    meet, the point inside the body (within half a voxel of its cells) farthest from the spine (an arm hangs beside
    the torso, not in it); the spheres apart (a straight arm): on the line between, in the bones' ratio. Outside
    the body either way: the nearest body cell."""
    from scipy.spatial import cKDTree

    body = cKDTree(cells)
    d = wrist - shoulder
    dist = float(np.linalg.norm(d))
    if dist < 1e-9 or dist >= up_len + fore_len or dist <= abs(up_len - fore_len):   # a straight arm
        x = shoulder + d * (up_len / max(up_len + fore_len, 1e-12))
        gap, i = body.query(x)
        return x if gap <= 0.5 * step else cells[i]       # never outside the body
    axis = d / dist
    a = (up_len**2 - fore_len**2 + dist**2) / (2 * dist)
    r = np.sqrt(max(up_len**2 - a**2, 0.0))
    e1 = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    t = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    ring = shoulder + a * axis + r * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2))
    gap, idx = body.query(ring)
    inside = gap <= 0.5 * step
    lateral = cKDTree(spine).query(ring)[0]
    score = np.where(inside, lateral, -np.inf)
    return ring[int(np.argmax(score))] if inside.any() else cells[idx[int(np.argmin(gap))]]


def _split_leg(poly: np.ndarray, cells: np.ndarray, u, right, forward, step: float):
    """Two legs from one leg column (legs touching): at each point of its centre line, the column's extent along
    ``right`` in a slice one voxel thick; each leg at the middle of its half. Returns (leg on +right, leg on -right)."""
    out_r, out_l = [], []
    for p in poly:
        d = cells - p
        near = (np.abs(d @ u) < 1.5 * step) & (np.abs(d @ forward) < 0.15)
        if near.sum() < 2:
            out_r.append(p)
            out_l.append(p)
            continue
        side = d[near] @ right
        a, b = side.max(), side.min()
        mid, half = 0.5 * (a + b), 0.5 * (a - b)
        out_r.append(p + right * (mid + 0.5 * half))
        out_l.append(p + right * (mid - 0.5 * half))
    return np.array(out_r), np.array(out_l)


def fit_humanoid(occ: np.ndarray, origin, spacing, up=(0.0, 0.0, 1.0), node: str = "skeleton.humanoid",
                 marks: dict | None = None, hand: float = HAND, foot: float = FOOT, stature: float | None = None):
    """(joints (J, 3), parents, names, report) of the template fitted to a solid (module docstring). The
    proportions (hand, foot, forearm, shoulders, the shortest bone) are shares of ``stature``, the body's standing
    height, when given (a crouched frame of a sequence is lower than the body is tall), else of this solid's
    height. ``marks``
    (head, hand_l, hand_r, foot_l, foot_r: 3D points, e.g. triangulated body landmarks; right: the body's left
    to right direction): the extremities they
    name and their sides are taken from them instead of from the shape (a head on a short neck, spurs of a
    4-view hull, feet that point nowhere); when one has no extremity near it, the shape decides."""
    from .curve import joint_tree, teasar

    foot_share = float(foot)     # (``foot`` names a foot's tree node below)
    step = float(np.min(spacing))
    raw = teasar(occ, origin, spacing)
    u = np.asarray(up, np.float64) / (np.linalg.norm(up) or 1.0)
    cells = origin + (np.argwhere(occ) + 0.5) * spacing
    ch = cells @ u
    floor, height = float(ch.min()), float(np.ptp(ch))
    size = float(stature) if stature else height    # the body's proportions: of its standing height
    tree0 = joint_tree(raw, prune=2.0, prune_min=step, bend=2.0 * step, smooth=step, up=up)
    marked = _marked_extremities(tree0, marks) if marks else None
    if marks and marked is None:
        LOG.warning("%s: the body landmarks do not each have an extremity of the curve skeleton within %.0f cm: "
                    "extremities and sides from the shape", node, 100 * MARK_REACH)
    tree, named_j = marked or _extremities(tree0, u, floor, height, node, raw)
    named = {n: tree.joints[j] for n, j in named_j.items()}
    together = "foot_1" not in named
    pts, parent = raw.points, raw.parent
    end = {n: int(np.argmin(np.linalg.norm(pts - p, axis=1))) for n, p in named.items()}
    path = _tree_paths(pts, parent)
    to_head = {k: path(end[k], end["head"]) for k in named if k != "head"}
    if together:      # one leg column: the crotch where the path from the foot reaches CROTCH_HEIGHT
        hf = pts[to_head["foot_0"]] @ u - floor
        pelvis = to_head["foot_0"][int(np.argmax(hf >= CROTCH_HEIGHT * height))]
    else:
        on1 = set(to_head["foot_1"])
        pelvis = next(v for v in to_head["foot_0"] if v in on1)
    spine_path = path(pelvis, end["head"])
    on_spine = set(spine_path)
    polys = {"spine": pts[spine_path]}
    limbs = {}
    at_spine = {}     # where each arm's path leaves the spine, as a share of the spine's arc from the pelvis
    for k in (0, 1):
        branch = next((v for v in to_head[f"hand_{k}"] if v in on_spine), None)
        if branch is None:
            raise NodeError(f"{node}: a hand's path never reaches the spine (try another frame)")
        limbs[("arm", k)] = pts[path(branch, end[f"hand_{k}"])]
        at_spine[k] = _spine_share(pts, spine_path, branch)
        if at_spine[k] < LOW_ARM:   # a second trunk beside the spine? then the arm comes near the spine up high
            arm = to_head[f"hand_{k}"]
            sp = pts[spine_path]
            for v in arm:
                gap = np.linalg.norm(sp - pts[v], axis=1)
                if gap.min() < NEAR_SPINE * height:
                    break
            near = spine_path[int(np.argmin(gap))]
            if _spine_share(pts, spine_path, near) >= LOW_ARM:
                limbs[("arm", k)] = np.vstack([pts[near], pts[path(v, end[f"hand_{k}"])]])
                at_spine[k] = _spine_share(pts, spine_path, near)
    if all(at_spine[k] < LOW_ARM for k in (0, 1)):   # one such arm is repaired from the other (below); two cannot be
        raise NodeError(f"{node}: both hands' paths reach the body near the pelvis, not at the shoulders: arms "
                        "against the hips? (try another frame)")
    for k in (0, 1):
        foot = end["foot_0"] if together else end[f"foot_{k}"]
        limbs[("leg", k)] = pts[path(pelvis, foot)]
    # sides: the part of each foot below its ankle lies in front of the ankle
    forward = np.zeros(3)
    for k in ((0,) if together else (0, 1)):
        ankle = _at(limbs[("leg", k)], SIDES_ANKLE)
        h = (cells - ankle) @ u
        near = np.linalg.norm((cells - ankle) - h[:, None] * u, axis=1) < 0.5 * np.linalg.norm(limbs[("leg", k)][-1] - ankle) + 3 * step
        foot = cells[(h < 0) & near]
        if len(foot):
            d = foot.mean(0) - ankle
            forward += d - (d @ u) * u
    report = {}
    if marked:           # left and right named by the landmarks: right from their left hip and shoulder to the right ones
        right = np.asarray(marks["right"], np.float64)
        right = right - (right @ u) * u
        right /= np.linalg.norm(right)
        report["sides_from"] = "landmarks"
    elif np.linalg.norm(forward) < step:   # the hips are wider than deep: their slice's main horizontal axis
        hip = cells[np.abs(cells @ u - float(pts[pelvis] @ u)) < 0.05 * height]
        flat = hip - np.outer(hip @ u, u)
        axis = np.linalg.eigh(np.cov((flat - flat.mean(0)).T))[1][:, -1] if len(hip) > 3 else np.cross([1.0, 0, 0], u)
        right = axis - (axis @ u) * u
        right /= np.linalg.norm(right)
        report["sides_from"] = "unknown (no foot in front of an ankle): left-right axis from the hips, l/r arbitrary"
    else:
        right = np.cross(forward / np.linalg.norm(forward), u)
        report["sides_from"] = "feet"
    if together:          # the column split in halves along right: each leg in its half
        fwd = np.cross(u, right)
        limbs[("leg", 0)], limbs[("leg", 1)] = _split_leg(limbs[("leg", 0)], cells, u, right, fwd, step)
    report["legs"] = "together: one column split in halves" if together else "apart"
    short = min(_length(limbs[("leg", k)]) for k in (0, 1))
    if short < MIN_LEG * height:       # the feet's paths meet at a foot, not at a pelvis
        raise NodeError(f"{node}: a leg's path from the pelvis is {100 * short:.0f} cm, under {MIN_LEG:.0%} of the body's "
                        f"height ({100 * height:.0f} cm): a foot raised to the other leg? (try another frame)")
    centre = pts[pelvis]
    side = {}
    near = {}
    for limb, at in (("arm", 0.3), ("leg", 0.4)):   # near the body: hands and feet may cross the midline
        near[limb] = [_at(limbs[(limb, k)], at) for k in (0, 1)]
        r = int(np.argmax([(q - centre) @ right for q in near[limb]]))
        side[(limb, "r")], side[(limb, "l")] = r, 1 - r
    if marked:           # hand_0 / foot_0 are the left ones; one leg column split: its first half is on +right
        side[("arm", "l")], side[("arm", "r")] = 0, 1
        side[("leg", "r")], side[("leg", "l")] = (0, 1) if together else (1, 0)
    arms = near["arm"][side[("arm", "r")]] - near["arm"][side[("arm", "l")]]
    legs = near["leg"][side[("leg", "r")]] - near["leg"][side[("leg", "l")]]
    if arms @ legs < 0 and not marked:   # the right arm and the right leg on opposite sides: flip the pair less along right
        weak = min(("arm", arms), ("leg", legs), key=lambda x: abs(x[1] @ right) / (np.linalg.norm(x[1]) or 1.0))[0]
        side[(weak, "r")], side[(weak, "l")] = side[(weak, "l")], side[(weak, "r")]
        report["sides_flipped"] = weak
    leg_length = np.mean([_length(limbs[("leg", k)]) for k in (0, 1)])
    names = template_names()
    joints = np.zeros((len(names), 3))
    parents = []
    bends = {}
    fracs = {}
    bent = set()        # elbows and knees placed at their limb's bend
    for name in names:
        key = next(t for t in TEMPLATE if t == name or ("{s}" in t and any(t.format(s=s) == name for s in SIDES)))
        par, which, frac = TEMPLATE[key]
        s = name.rsplit("_", 1)[1] if "{s}" in key else None
        poly = polys["spine"] if which == "spine" else limbs[(which, side[(which, s)])]
        if key == "hip_{s}":   # measured from the foot with the mean leg length: the legs may meet off-centre
            frac = max(0.0, 1.0 - (1.0 - frac) * leg_length / _length(poly))
        arc = max(_length(poly), 1e-12)
        gap = MIN_BONE * size / arc            # the shortest bone, as a share of this path
        bounds = (0.0, 1.0)                      # where a bend may move the joint
        if key in ("knee_{s}", "ankle_{s}"):   # the ankle FOOT back from the toe's end, the knee halfway up from it
            ankle = float(np.clip(1.0 - foot_share * size / arc, fracs[f"hip_{s}"] + 0.2, 0.97))
            planted = _planted_ankle(poly, u, floor, size) if together else None
            if planted is not None:
                ankle = float(np.clip(max(ankle, planted), fracs[f"hip_{s}"] + 0.2, 0.97))
                if key == "ankle_{s}" and planted > 1.0 - foot_share * size / arc:
                    report.setdefault("ankles_from_the_floor", []).append(name)   # ANKLE_RISE, not FOOT, placed it
            frac = ankle if key == "ankle_{s}" else 0.5 * (fracs[f"hip_{s}"] + ankle)
            bounds = (fracs[f"hip_{s}"] + gap, ankle - gap)
        if key == "elbow_{s}":     # FOREARM back from the wrist along the path
            wrist = 1.0 if hand == 0 else float(np.clip(1.0 - hand * size / arc, fracs[f"shoulder_{s}"] + 0.1, 1.0))
            lo, hi = fracs[f"shoulder_{s}"] + gap, wrist - gap
            frac = float(np.clip(wrist - FOREARM * size / arc, lo, hi)) if lo <= hi else 0.5 * (lo - gap + wrist)
            bounds = (fracs[f"shoulder_{s}"] + gap, wrist - gap)
        if key == "wrist_{s}":     # HAND back from the arm's end, past its elbow
            top = 1.0 if hand == 0 else 1.0 - max(hand * size, 2 * step) / arc
            lo = fracs[f"elbow_{s}"] + 0.05           # past the elbow, however large ``hand`` is
            frac = float(np.clip(1.0 - hand * size / arc, lo, max(top, lo)))
        if key == "hand_end_{s}" and hand == 0:   # no hand: the wrist is the path's end, the end marker past it
            tip = end[f"hand_{side[('arm', s)]}"]
            back = _at(poly, max(0.0, 1.0 - 0.05 * size / max(_length(poly), 1e-12)))
            d = poly[-1] - back
            d = d / (np.linalg.norm(d) or 1.0)
            reach = 0.5 * float(raw.radius[tip])        # half the end's radius out, shortened while it leaves the body
            while reach > 0.5 * step and not _solid(occ, origin, spacing, poly[-1] + reach * d):
                reach *= 0.5
            joints[names.index(name)] = poly[-1] + max(reach, 0.5 * step) * d
            fracs[name] = 1.0
            parents.append(names.index(par.format(s=s)))
            continue
        if key in BENDS and not (together and key == "knee_{s}"):
            f, ang = _bend(poly, frac)
            bends[name] = round(ang, 1)
            if ang > BEND_DEG and bounds[0] < f < bounds[1]:     # (a knee's bend is not the hip's corner)
                frac = f
                bent.add(name)
        joints[names.index(name)] = _at(poly, frac)
        fracs[name] = frac
        if key == "clavicle_{s}":      # on the spine (its path's fraction stays the arm path's start)
            joints[names.index(name)] = _at(polys["spine"], CLAVICLE)
        if key == "shoulder_{s}":
            f, q = _shoulder(poly, frac, joints[names.index("neck")], u, right, SHOULDER_OUT * size)
            if np.linalg.norm(q - _at(poly, f)) < 0.06 * size and _solid(occ, origin, spacing, q):
                joints[names.index(name)] = q
                fracs[name] = f
        parents.append(-1 if par is None else names.index(par.format(s=s) if s else par))
    if marked and marks.get("joints"):
        report["joints_from_landmarks"] = _place_at_marks(joints, names, fracs, limbs, side, marks["joints"], node,
                                                          size)
    level = float(pts[pelvis] @ u) - HIP_DROP * leg_length
    widest = _hip_level(occ, origin, spacing, u, right, pts[pelvis], level, size)
    raised = widest is not None and widest > level
    report["hips_from"] = "the pelvis's widest slice" if raised else "where the legs' paths meet"
    for s in SIDES:     # the hip on its thigh's centre line, raised to about where the legs' paths meet, or to the
        j_h, j_k = names.index(f"hip_{s}"), names.index(f"knee_{s}")        # pelvis's widest slice when higher
        top, knee = joints[j_h].copy(), joints[j_k]
        d = top - knee
        du = float(d @ u)
        z = widest if raised else level
        if du > 1e-6 and z > float(top @ u):
            joints[j_h] = top + d * ((z - float(top @ u)) / du)
            name = f"knee_{s}"
            if name not in bent and name not in report.get("joints_from_landmarks", ()):
                # halfway between the raised hip and the ankle: the rise lengthens the thigh (synth walk at 128^3:
                # knees 1.5-3.1 voxels below the true ones, halfway from the hip's place on the path)
                leg = limbs[("leg", side[("leg", s)])]
                arc = max(_length(leg), 1e-12)
                lo, hi = fracs[f"hip_{s}"], fracs[f"ankle_{s}"]
                gap = MIN_BONE * size / arc
                mid = 0.5 * (lo - np.linalg.norm(joints[j_h] - top) / arc + hi)
                fracs[name] = float(np.clip(mid, lo + gap, hi - gap)) if lo + gap <= hi - gap else 0.5 * (lo + hi)
                joints[j_k] = _at(leg, fracs[name])
    j_p = names.index("pelvis")   # the pelvis on the midline between the hips (across; the legs' paths may meet off-centre)
    mid = 0.5 * (joints[names.index("hip_l")] + joints[names.index("hip_r")])
    joints[j_p] = joints[j_p] - float((joints[j_p] - mid) @ right) * right
    low = [k for k in (0, 1) if at_spine[k] < LOW_ARM]
    if len(low) == 1:   # a hand against the hip: that arm's path enters the body there, not at the shoulder
        bad = low[0]
        sb, sg = ("r", "l") if side[("arm", "r")] == bad else ("l", "r")
        J = {n: names.index(n) for n in names}
        joints[J[f"clavicle_{sb}"]] = joints[J[f"clavicle_{sg}"]]
        c = joints[J[f"clavicle_{sg}"]]
        g = joints[J[f"shoulder_{sg}"]]
        joints[J[f"shoulder_{sb}"]] = g - 2 * float((g - c) @ right) * right     # the good shoulder mirrored
        up_len = float(np.linalg.norm(joints[J[f"elbow_{sg}"]] - g))
        fore_len = float(np.linalg.norm(joints[J[f"wrist_{sg}"]] - joints[J[f"elbow_{sg}"]]))
        joints[J[f"elbow_{sb}"]] = _elbow_between(joints[J[f"shoulder_{sb}"]], joints[J[f"wrist_{sb}"]], up_len,
                                                  fore_len, cells, polys["spine"], step)
        report["arm_from_hip"] = sb
        if "joints_from_landmarks" in report:     # that arm's shoulder and elbow are the repair's now
            report["joints_from_landmarks"] = [n for n in report["joints_from_landmarks"]
                                               if n not in (f"shoulder_{sb}", f"elbow_{sb}")]
        LOG.warning("%s: arm '%s' meets the body at the hip (its hand against it): its shoulder mirrored from "
                    "the other, its elbow between shoulder and wrist at the other arm's bone lengths", node, sb)
    lengths = {n: round(float(np.linalg.norm(joints[j] - joints[p])), 4) for j, (n, p) in enumerate(zip(names, parents))
               if p >= 0}
    report.update(joints=len(names), bends_deg=bends, bone_lengths=lengths, height=round(height, 4),
                  forward=np.round(forward, 4).tolist())
    return joints, parents, names, report


def bind_humanoid(frames: np.ndarray, faces, resolution: int, up=(0.0, 0.0, 1.0), node: str = "skeletonize.humanoid",
                  tries: int = 40, lengths: dict | None = None, hand: float = HAND, foot: float = FOOT):
    """The template fitted to one frame of a dynamic mesh and set moving with it, ready for ``skin``:
    (joints, parents, names, one-hot weights (V, J), rotations (F, J, 3, 3), translations (F, J, 3), report),
    rest = the first frame. The fit is tried on up to ``tries`` frames spread over the segment (a child's arms
    lie against the body in some, its legs touch in others; 40: enough fits to measure the limbs); of the fits, the one whose parts move most rigidly
    over the whole segment is kept (the rms distance of the vertices from their part's rigid motion: a part
    that straddles a real joint, or a limb found in the wrong place, does not move rigidly). The end joints
    (head_end, hand_end_*, toe_*) mark where a limb ends and are left out: no part of the body moves with them.
    Each vertex goes to the nearest bone (the segment from a joint to one of its children, owned by the joint)
    in the fitted frame; each joint's part moves rigidly (Kabsch, first frame -> each frame), a part with fewer
    than 4 vertices as its parent does. The fitted joints (inside the body there) are carried to every frame by
    the surface around each (motion.carry_joints): the first frame's are the rest joints, and each joint's
    motion takes it where its carried one goes (``skin``'s ``hold`` keeps the posed joints near there). ``skin``
    (lengths: fixed) then makes the joints rotation-only with constant bone lengths. Bone lengths: as
    the fits measured them, left and right averaged (a body is symmetric; one child_rope fit measured the upper
    arms 12 and 18 cm), the limbs' bones (``LIMB_BONES``) each its ``LIMB_QUANTILE`` of the fits' lengths of it
    (the most rigid fits of child_rope are crouched frames, whose bent legs' centre lines cut the corners: shins
    7-16 cm against 19-26 upright; the segment's lengths 24/11 cm -> 25/22 thigh/shin: the legs' 75th percentile,
    the arms' median), the others the kept fit's;
    or ``lengths`` (joint name -> length of the bone ending at it) as given; each fit is given them
    (with_lengths), and the rest joints again once carried to the first frame. With three fits or more, each fit's
    joints are carried by the surface to the kept fit's frame, and a joint on which they agree (``AGREE``) takes
    their median (``joints_from_fits`` and ``fits_spread_cm`` in the report)."""
    from .curve import voxelize
    from .motion import Trajectories, carry_joints

    frames = np.asarray(frames, np.float64)
    order = sorted(set(np.linspace(0, len(frames) - 1, min(tries, len(frames))).round().astype(int).tolist()))
    u = np.asarray(up, np.float64) / (np.linalg.norm(up) or 1.0)
    stature = body_stature(frames, u)
    fits, errors, tried = [], [], {}
    for r in order:
        occ, origin, spacing = voxelize(frames[r], np.asarray(faces), resolution)
        try:
            fit = fit_humanoid(occ, origin, spacing, up, node, hand=hand, foot=foot, stature=stature)
        except NodeError as exc:
            errors.append(f"frame index {r}: {str(exc).split(': ', 1)[-1]}")
            continue
        own = lengths or symmetric(skeleton_lengths(*fit[:3]))
        raw = fit[0]
        fit = (with_lengths(fit[0], fit[1], fit[2], own), *fit[1:], own)
        bound = _bind(frames, r, *fit[:3])
        tried[r] = round(1000 * bound[-1], 2)
        fits.append((fit, bound, r, raw))
    if not fits:
        raise NodeError(f"{node}: the template fits none of the {len(order)} frames tried: " + "; ".join(errors[:3]))
    best = min(fits, key=lambda x: x[1][-1])
    if lengths is None:   # each limb as long as most fits measure it: a bent limb's centre line cuts the corners
        own, source = dict(best[0][4]), {}
        for b in LIMB_BONES:
            by = sorted(fits, key=lambda x: x[0][4][f"{b}_l"])
            src = by[int(round(LIMB_QUANTILE[b] * (len(by) - 1)))]
            source[b] = int(src[2])
            own.update({f"{b}_{s}": src[0][4][f"{b}_{s}"] for s in SIDES})
        if any(v != best[2] for v in source.values()):
            fit, r, raw = best[0], best[2], best[3]
            fit = (with_lengths(raw, fit[1], fit[2], own), *fit[1:4], own)
            best = (fit, _bind(frames, r, *fit[:3]), r, raw)
        best[0][3]["limb_lengths_from_index"] = source
    (_, _, names, report, own), (keep, rest_joints, sub_parents, weights, rot, tr, counts, _), r, raw = best
    if len(fits) >= 3:      # where the fits agree, their median joint (AGREE)
        carried_all = []
        for _, bound_i, r_i, raw_i in fits:
            keep_i, _, sub_i, w_i = bound_i[:4]
            pos, has_i = carry_joints(Trajectories(frames[r_i], frames[[r]]), raw_i[keep_i], sub_i, np.argmax(w_i, axis=1))
            carried_all.append(np.where(has_i[:, None], pos[0], np.nan))
        stack = np.stack(carried_all)
        with warnings.catch_warnings():      # a joint no fit's surface carries: all NaN, not taken
            warnings.simplefilter("ignore", RuntimeWarning)
            cons = np.nanmedian(stack, axis=0)
            spread = np.nanmedian(np.linalg.norm(stack - cons[None], axis=2), axis=0)
        ok = ~np.isnan(cons).any(axis=1) & ~np.isnan(spread) & (spread < AGREE * stature)
        raw = raw.copy()
        raw[np.asarray(keep)[ok]] = cons[ok]
        report["joints_from_fits"] = [names[j] for j, o in zip(keep, ok) if o]
        report["fits_spread_cm"] = {names[j]: (None if np.isnan(d) else round(100 * float(d), 1))
                                    for j, d in zip(keep, spread)}
    # the fitted joints (inside the body there, before any length was imposed) carried to every frame by the surface
    # around each (motion.carry_joints); a part's own motion carries its joint poorly where the part holds vertices
    # far from it (child_rope: an arm's part reaching into the torso it lies against put the wrists 8-14 cm outside
    # the body in the first frame)
    carried, has = carry_joints(Trajectories(frames[r], frames), raw[keep], sub_parents, np.argmax(weights, axis=1))
    rest_joints[has] = carried[0, has]
    rest_joints = with_lengths(rest_joints, sub_parents, [names[j] for j in keep], own)
    # each joint's motion takes it where the surface carries the fitted joint: skin's ``hold`` pulls towards there
    tr[:, has] = carried[:, has] - np.einsum("fjab,jb->fja", rot[:, has], rest_joints[has])
    report["vertices_per_joint"] = dict(zip([names[j] for j in keep], counts.tolist()))
    report["fitted_on_index"] = int(r)
    report["stature"] = round(stature, 4)
    report["frames_refused"] = errors
    report["rigid_rms_mm_by_index"] = tried
    report["bone_lengths_used"] = {n: round(v, 4) for n, v in own.items()}
    return rest_joints, sub_parents, [names[j] for j in keep], weights, rot, tr, report


def body_stature(frames: np.ndarray, up=(0.0, 0.0, 1.0)) -> float:
    """The subject's standing height over a sequence (F, V, 3): the 95th percentile over frames of its extent along
    ``up``: most frames stand lower (crouches); a body with its arms over its head in more than 5 % of the
    frames measures taller than it is."""
    u = np.asarray(up, np.float64) / (np.linalg.norm(up) or 1.0)
    h = np.asarray(frames, np.float64) @ u
    return float(np.percentile(h.max(axis=1) - h.min(axis=1), 95)) if h.size else 0.0


def with_lengths(joints: np.ndarray, parents: list[int], names: list[str], lengths: dict) -> np.ndarray:
    """The joints with the given bone lengths (joint name -> distance from its parent): parents first, each
    joint on the line from its parent's new place towards its own given place, at the given distance (the
    root and joints not named keep their offsets from their parents). Aimed from the new parent, a chain's
    joints each stay as near their given places as the lengths allow; along the given bones' directions a
    length changed near the root moved the whole limb below it (child_rope: the wrists 16-30 mm outside the
    body in the first frame went to 57-176 mm)."""
    new = np.array(joints, np.float64)
    for j in sorted(range(len(parents)), key=lambda j: _depth(parents, j)):
        p = parents[j]
        if p < 0:
            continue
        if names[j] not in lengths:
            new[j] = new[p] + (np.asarray(joints[j], np.float64) - joints[p])
            continue
        d = np.asarray(joints[j], np.float64) - new[p]
        n = float(np.linalg.norm(d))
        if n == 0:
            d = np.asarray(joints[j], np.float64) - joints[p]
            n = float(np.linalg.norm(d))
        new[j] = new[p] + (d / n * lengths[names[j]] if n > 0 else d)
    return new


def symmetric(lengths: dict) -> dict:
    """Bone lengths with each left/right pair replaced by the pair's mean."""
    out = dict(lengths)
    for n, v in lengths.items():
        if n.endswith("_l") and n[:-2] + "_r" in lengths:
            out[n] = out[n[:-2] + "_r"] = 0.5 * (v + lengths[n[:-2] + "_r"])
    return out


def skeleton_lengths(joints, parents, names) -> dict:
    """Joint name (our template's) -> length of the bone ending at it, from a skeleton's rest joints."""
    out = {}
    for j, p in enumerate(parents):
        ours = template_name(names[j]) if j < len(names) else None
        if p >= 0 and ours is not None:
            out[ours] = float(np.linalg.norm(np.asarray(joints[j], np.float64) - joints[p]))
    return out


def _bind(frames: np.ndarray, r: int, joints, parents, names):
    """The template fitted on frame index ``r`` bound to the segment (bind_humanoid): (kept joints, rest joints,
    parents, one-hot weights, rotations, translations, vertices per joint, rms distance of the vertices from
    their part's rigid motion over the segment)."""
    from .motion import fit_rigid

    keep = [j for j, n in enumerate(names) if not (n.endswith("_end") or n.startswith("toe_") or "_end_" in n)]
    remap = {j: k for k, j in enumerate(keep)}
    bones = [(j, c) for c, j in enumerate(parents) if j >= 0]            # (owner joint, child joint) segments
    a = joints[[j for j, _ in bones]]
    b = joints[[c for _, c in bones]]
    ab = b - a
    at = frames[r]
    t = np.clip(np.einsum("vbk,bk->vb", at[:, None] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    d = np.linalg.norm(at[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)
    owner = np.array([remap[j] for j, _ in bones])[np.argmin(d, axis=1)]
    J = len(keep)
    sub_parents = [remap[parents[j]] if parents[j] >= 0 else -1 for j in keep]
    rot = np.tile(np.eye(3), (len(frames), J, 1, 1))
    tr = np.zeros((len(frames), J, 3))
    counts = np.bincount(owner, minlength=J)
    for k in range(J):                                        # parents first (template order)
        if counts[k] >= 4:
            rot[:, k], tr[:, k] = fit_rigid(frames[0], frames, np.flatnonzero(owner == k))
        elif sub_parents[k] >= 0:
            rot[:, k], tr[:, k] = rot[:, sub_parents[k]], tr[:, sub_parents[k]]
    moved = np.einsum("fvab,vb->fva", rot[:, owner], frames[0]) + tr[:, owner]
    rms = float(np.sqrt(((moved - frames) ** 2).sum(2).mean()))
    rest_joints = np.array([rot[r, k].T @ (joints[j] - tr[r, k]) for k, j in enumerate(keep)])   # back to frame 0
    weights = np.zeros((len(frames[0]), J))
    weights[np.arange(len(frames[0])), owner] = 1.0
    return keep, rest_joints, sub_parents, weights, rot, tr, counts, rms


# ---------------------------------------------------------------- rest pose
REST_POSES = ("captured", "T", "A")
A_POSE_DEG = 45.0        # A pose: the arms this far below the horizontal
# the bone each joint aims in the T pose: (child joint, direction: "up", "down" or "out" = away from the midline)
AIM = {"pelvis": ("spine", "up"), "spine": ("chest", "up"), "chest": ("neck", "up"), "neck": ("head", "up"),
       "clavicle_{s}": ("shoulder_{s}", "out"), "shoulder_{s}": ("elbow_{s}", "arm"), "elbow_{s}": ("wrist_{s}", "arm"),
       "hip_{s}": ("knee_{s}", "down"), "knee_{s}": ("ankle_{s}", "down")}


def template_name(name: str) -> str | None:
    """Our template's name for a joint named ours or by a retargeting tool (None: not a template joint)."""
    if name in template_names():
        return name
    for tool in TOOLS:
        for ours, theirs in retarget_names(tool).items():
            if theirs == name:
                return ours
    return None


def _turn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking direction a to direction b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-9:                                   # opposite: half a turn about any axis normal to a
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1 + c)


def rest_pose(joints: np.ndarray, parents: list[int], names: list[str], pose: str, up=(0.0, 0.0, 1.0)):
    """Rotation-only joint turns that take a template rig from its captured rest pose to a T or A pose:
    (G (J, 3, 3) each joint's world rotation, new joint positions (J, 3)); bone j then maps x to
    G_j (x - p_j) + p'_j. The spine and the legs are straightened along ``up`` (down), clavicles point out
    horizontally, the arms out (T) or ``A_POSE_DEG`` below (A); hands, feet and head keep their turn relative
    to their parent bone; the pelvis keeps its heading. Left/right come from the names; the body's right
    from its hips and shoulders."""
    ours = [template_name(n) for n in names]
    if None in ours:
        bad = [n for n, o in zip(names, ours) if o is None]
        raise ValueError(f"joints {bad[:4]} are not the humanoid template's: a T or A rest pose needs the "
                         "template's rig (skeletonize.humanoid), not the free route's")
    index = {n: j for j, n in enumerate(ours)}
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    p = np.asarray(joints, np.float64)
    right = sum(p[index[f"{k}_r"]] - p[index[f"{k}_l"]] for k in ("hip", "shoulder") if f"{k}_r" in index)
    right = right - (right @ u) * u
    if not np.linalg.norm(right) > 0:
        raise ValueError("no left-right axis: the rig has neither hips nor shoulders on both sides")
    right /= np.linalg.norm(right)
    a = np.radians(A_POSE_DEG if pose == "A" else 0.0)
    aim = {}
    for key, (child, how) in AIM.items():
        for s in SIDES if "{s}" in key else (None,):
            n, c = (key.format(s=s), child.format(s=s)) if s else (key, child)
            if n in index and c in index:
                out = right if s == "r" else -right
                aim[index[n]] = (index[c], {"up": u, "down": -u, "out": out,
                                            "arm": np.cos(a) * out - np.sin(a) * u}[how])
    g = np.tile(np.eye(3), (len(parents), 1, 1))
    new = p.copy()
    for j in sorted(range(len(parents)), key=lambda j: _depth(parents, j)):
        q = parents[j]
        if q >= 0:
            g[j] = g[q]
            new[j] = new[q] + g[q] @ (p[j] - p[q])
        if j in aim:
            c, target = aim[j]
            g[j] = _turn(g[j] @ (p[c] - p[j]), target) @ g[j]
    return g, new


def _depth(parents, j):
    d = 0
    while parents[j] >= 0:
        j, d = parents[j], d + 1
    return d
