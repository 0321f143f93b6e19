"""Nodes of the key stage: chroma key, difference key, grey threshold, clean-up, multi-view consensus,
GrabCut at the boundary (the work is in keying.py)."""
from __future__ import annotations

import numpy as np

from nodegraph import Input, Node, NodeError, Output, Param, Table
from nodes.common.types import Bounds, CameraSet, Images, ImageSet, Masks, MaskSet, PlateModel, Volume
from nodes.common.views import map_views

from .keying import (KERNELS, check_views, chroma_key_bits, chroma_key_cl, chroma_key_windowed, clean_mask_box, cleaned_alpha, difference_key_cl,
                     difference_key_mixture_cl, estimate_key_direction,
                     grabcut_band, grey_threshold_cl, hull_footprint, key_direction_from_rgb, maskset, matte_edges,
                     plate_model, disc, surface_centres)


class ChromaKey(Node):
    """Chroma key (green/blue screen): foreground alpha from how strongly each pixel's chroma points at the
    screen hue relative to its brightness, with an optional garbage matte (pixels outside the projection of
    the capture box are background) and spill suppression of the screen colour in the kept pixels."""

    type_name = "key.chroma"
    version = 2
    inputs = {
        "images": Images,
        "cameras": Input(CameraSet, optional=True, doc="with bounds: garbage matte"),
        "bounds": Input(Bounds, optional=True, doc="capture volume; pixels outside its projection are background"),
    }
    outputs = {"masks": Masks, "images": Images}
    params = {
        "key_color": Param(list, None, item=int, length=3, doc="screen RGB; default: estimated from the image border"),
        "inner": Param(float, 0.05, doc="key strength below which a pixel is fully foreground"),
        "outer": Param(float, 0.2, doc="key strength above which a pixel is fully background"),
        "side": Param(float, 1.0, range=(0, None), doc="weight of chroma off the key hue (larger = narrower hue band)"),
        "luma_floor": Param(float, 16.0, range=(1, 255), doc="luma below which chroma is not normalised further"),
        "black": Param(float, 0.0, range=(0, 255), doc="pixels darker than this luma are background (dark studio walls)"),
        "spill": Param(float, 1.0, range=(0, 1), doc="fraction of the key-coloured chroma removed from kept pixels"),
        "matte_margin": Param(float, 8.0, range=(0, None), doc="garbage matte slack, pixels"),
        "window_margin": Param(int, 16, range=(-1, None), doc="the despilled images are black beyond this many "
                               "pixels around the box of the alpha (the cache then keeps that box only; a texture "
                               "or carve samples inside the masks); -1: the whole images"),
    }
    kernels = [KERNELS]

    def run(self, images, cameras=None, bounds=None, *, key_color, inner, outer, side, luma_floor, black, spill,
            matte_margin, window_margin):
        if outer <= inner:
            raise NodeError(f"key.chroma: param 'outer' ({outer}) must be larger than 'inner' ({inner})")
        if (cameras is None) != (bounds is None):
            raise NodeError("key.chroma: the garbage matte needs both inputs 'cameras' and 'bounds'")
        frames = images.images
        check_views("key.chroma", frames, cameras)
        keys = [key_direction_from_rgb(key_color)] * len(frames) if key_color else map_views(estimate_key_direction, frames)
        edges = [matte_edges(cameras, v, bounds, matte_margin) for v in range(len(frames))] if cameras is not None else None
        # The silhouettes go straight into the hull's device layout, the soft alpha, the host masks and the
        # despilled images are computed, each only if a reader (or the cache) asks for them: the demo's clean-up
        # reads the host masks only, bench/cli.py's hull the device's only.
        def bits():
            return chroma_key_bits(frames, keys, side=side, luma_floor=luma_floor, inner=inner, outer=outer,
                                   black=black, edges=edges)

        full: dict = {}

        def key_frames():
            if not full:
                alphas, despilled, windows = [], [], []
                kw = dict(side=side, luma_floor=luma_floor, inner=inner, outer=outer, black=black, spill=spill)
                windowed = spill > 0 and window_margin >= 0   # despilled inside the alpha's window only, black beyond
                for v, im in enumerate(frames):
                    e = None if edges is None else edges[v]
                    if windowed:   # the window's pixels alone: whole images only if a reader in the unit asks
                        a, d, win = chroma_key_windowed(im, keys[v], margin=window_margin, edges=e, crop=True, **kw)
                    else:
                        (a, d), win = chroma_key_cl(im, keys[v], edges=e, despill=spill > 0, **kw), None
                    alphas.append(a)
                    despilled.append(d if spill > 0 else im)
                    windows.append(win)
                full.update(masks=maskset(alphas, images.names, boxes=[tuple(b) for b in windows] if windowed else None),
                            images=despilled,
                            windows=windows if windowed else None)   # the alpha is 0 outside its window
            return full

        def despilled():
            k = key_frames()
            if k["windows"] is None:
                return k["images"], None
            return "crops", k["images"], [im.shape for im in frames], k["windows"]

        names = list(images.names)
        masks = MaskSet.lazy(lambda: (key_frames()["masks"].masks, None, key_frames()["masks"].alpha8,
                                      key_frames()["masks"].boxes), names, make_device=bits)
        return {"masks": masks, "images": ImageSet.lazy(despilled, names)}


class Plate(Node):
    """Clean plates from the footage where none was shot (a sequence node): per camera the per-pixel median over
    up to ``frames`` frames spread over the run, with a coverage report: the share of pixels that stayed one colour
    in at least ``min_share`` of those frames (the rest: a moving subject stood there most of the time, and the plate
    there is the subject's). Only motion reveals the background: a subject that never moves is stable too and ends
    up in the plate (Utrecht's seated person: the plate differs from the shipped one on 5-13 % of the pixels, 70-77
    % of them on the subject). Give its background to key.difference."""

    type_name = "key.plate"
    version = 1
    per = "sequence"
    inputs = {"images": Input(Images, doc="every frame's images (arrive as a list)")}
    outputs = {"background": Output(Images, "one plate per camera"),
               "report": Output(Table, "per camera the share of pixels seen as background, frames used")}
    params = {
        "frames": Param(int, 25, range=(3, 1000), doc="at most this many frames, spread over the run, make the median"),
        "tolerance": Param(float, 12.0, range=(0.0, 255.0), doc="grey levels within which a frame agrees with the median"),
        "min_share": Param(float, 0.5, range=(0.01, 1.0), doc="a pixel is background-seen when this share of frames agree"),
    }

    def run(self, images, *, frames, tolerance, min_share):
        from .keying import footage_plate

        sets = list(images)
        if len(sets) < 3:
            raise NodeError(f"key.plate: {len(sets)} frames: a plate from the footage needs at least 3 (the subject "
                            "must have moved away from each background pixel in most of them)")
        names = sets[0].names
        for k, s in enumerate(sets):
            if s.names != names:
                raise NodeError(f"key.plate: frame {self.frames[k] if k < len(self.frames) else k} has cameras "
                                f"{s.names}, the first frame {names}")
        pick = sorted(set(np.linspace(0, len(sets) - 1, min(frames, len(sets))).round().astype(int).tolist()))
        plates, report = [], {"frames_used": [int(self.frames[i]) if i < len(self.frames) else int(i) for i in pick],
                              "cameras": {}}
        for v, name in enumerate(names):
            plate, seen, share = footage_plate([sets[i].images[v] for i in pick], tolerance, min_share)
            plates.append(plate)
            report["cameras"][name] = {"stable": round(float(seen.mean()), 4), "unstable_pixels": int((~seen).sum()),
                                       "median_agreement": round(float(np.median(share)), 4)}
            if seen.mean() < 0.95:
                self.log.warning("key.plate: camera '%s': %.1f %% of the pixels never showed one background in %d "
                                 "of %d frames (the subject stood there): the plate there is the subject's",
                                 name, 100 * (1 - seen.mean()), int(np.ceil(min_share * len(pick))), len(pick))
        return {"background": ImageSet(plates, names), "report": report}


class DifferenceKey(Node):
    """Difference key against the background: one clean plate per camera (``background``: a per-pixel Gaussian of
    the plate with the plate's sensor noise as sigma), or a mixture learnt from several plate frames (``model``,
    from capture.background: a pixel is as foreground as the background component that explains it best). Pixels
    whose colour departs from it in chromaticity, or in brightness beyond the shadow/highlight range, are
    foreground. Shadows (darker, same chromaticity as the background) are background (Horprasert 1999); shadow 1
    turns that off."""

    type_name = "key.difference"
    version = 1
    inputs = {"images": Images,
              "background": Input(Images, optional=True, doc="clean plate per camera, same order"),
              "model": Input(PlateModel, optional=True, doc="background mixture per camera (capture.background), same order")}
    outputs = {"masks": Masks}
    params = {
        "noise": Param(float, 4.0, range=(0.5, None), doc="lowest plate noise sigma, grey levels (background plates)"),
        "cd_inner": Param(float, 0.0, range=(0, None), doc="chromaticity distortion (sigmas) below which it is "
                          "background; 0 = 4 against a plate (whose own noise the difference carries), 2 against a "
                          "learnt model (per-pixel sigmas)"),
        "cd_outer": Param(float, 0.0, range=(0, None), doc="chromaticity distortion (sigmas) above which it is "
                          "foreground; 0 = 8 against a plate, 4 against a learnt model"),
        "shadow": Param(float, 0.5, range=(0, 1), doc="lowest brightness ratio still taken as a shadow"),
        "highlight": Param(float, 1.2, range=(1, None), doc="highest brightness ratio still taken as background"),
        "still": Param(float, 3.0, range=(0, None), doc="colour distance (sigmas) within which a pixel is background"),
    }
    kernels = [KERNELS]

    def run(self, images, background, model, *, noise, cd_inner, cd_outer, shadow, highlight, still):
        # measured on the key stage (bench/key_quality.py): against a learnt model 2/4 sigmas keep 0.948 IoU with
        # 0.005 % of empty-stage pixels keyed; against one plate the same bounds key 1.9 % of them (its own noise)
        cd_inner = cd_inner or (2.0 if model is not None else 4.0)
        cd_outer = cd_outer or (4.0 if model is not None else 8.0)
        if cd_outer <= cd_inner:
            raise NodeError(f"key.difference: param 'cd_outer' ({cd_outer}) must be larger than 'cd_inner' ({cd_inner})")
        if (background is None) == (model is None):
            raise NodeError("key.difference: connect exactly one of 'background' (clean plates) and 'model' "
                            f"(capture.background's mixture); {'both are' if model is not None else 'neither is'} connected")
        plates = background if background is not None else model
        if len(plates) != len(images):
            raise NodeError(f"key.difference: {len(images)} images but {len(plates)} background "
                            f"{'plates' if background is not None else 'models'}")
        if model is not None and list(model.names) != list(images.names):
            raise NodeError(f"key.difference: the model's cameras {list(model.names)} are not the images' "
                            f"{list(images.names)}")
        kw = dict(cd_inner=cd_inner, cd_outer=cd_outer, shadow=shadow, highlight=highlight, still=still)
        alphas = []
        for v, (name, im) in enumerate(zip(images.names, images.images)):
            shape = background.images[v].shape if background is not None else model.mean[v].shape[1:]
            if tuple(shape) != im.shape:
                raise NodeError(f"key.difference: camera '{name}': {'plate' if background is not None else 'model'} "
                                f"{shape[1]}x{shape[0]} does not match image {im.shape[1]}x{im.shape[0]}")
            if background is not None:
                mean, inv_var = plate_model(background.images[v], noise)
                a, _ = difference_key_cl(im, mean, inv_var, **kw)
            else:
                a, _ = difference_key_mixture_cl(im, model, v, **kw)
            alphas.append(a)
        return {"masks": maskset(alphas, images.names)}


class Person(Node):
    """A learned person matte where there is neither a green screen nor a clean plate: MediaPipe Pose's body
    segmentation per view (its model ships in the mediapipe 0.10.14 wheel; nothing is downloaded), and the 33 body
    landmarks it fits on the way (pixels, visibility) for the skeleton stage. One person per view, the most
    prominent: follow with key.consensus where others stand around (see person.py)."""

    type_name = "key.person"
    version = 1
    inputs = {"images": Images}
    outputs = {"masks": Masks,
               "keypoints": Output(Table, "per camera: found, and the 33 landmarks [x px, y px, visibility] by name")}
    params = {
        "threshold": Param(float, 0.5, range=(0.01, 0.99), doc="segmentation score above which a pixel is the person"),
        "min_confidence": Param(float, 0.5, range=(0.05, 0.95), doc="person detector's confidence needed in a view"),
    }

    def run(self, images, *, threshold, min_confidence):
        from .person import LANDMARKS, person_matte

        masks, alphas, table = [], [], {"landmarks": list(LANDMARKS), "cameras": {}}
        for name, im in zip(images.names, images.images):
            alpha, lm = person_matte(im, min_confidence)
            if lm is None:
                self.log.warning("key.person: camera '%s': no person found (min_confidence %.2f): its mask is empty",
                                 name, min_confidence)
            masks.append((alpha > threshold).view(np.uint8) * np.uint8(255))   # np.where(.., 255, 0)'s bytes, 28x faster
            alphas.append(alpha)
            table["cameras"][name] = {"found": lm is not None,
                                      "points": None if lm is None else np.round(lm[:, :3], 2).tolist()}
        return {"masks": MaskSet(masks, alphas, images.names), "keypoints": table}


class Threshold(Node):
    """Grey threshold: foreground where the grey level exceeds ``threshold`` (masks shipped as images, or
    objects on a black background such as Middlebury's: threshold 0.19, dilate 10, erode 7)."""

    type_name = "key.threshold"
    version = 1
    inputs = {"images": Images}
    outputs = {"masks": Masks}
    params = {
        "threshold": Param(float, 0.5, range=(0, 1), doc="fraction of 255"),
        "channel": Param(str, "mean", choices=("mean", "max"), doc="grey = mean of R, G, B or their max"),
        "dilate": Param(int, 0, range=(0, 100), doc="then dilate by this radius, pixels"),
        "erode": Param(int, 0, range=(0, 100), doc="then erode by this radius, pixels"),
    }
    kernels = [KERNELS]

    def run(self, images, *, threshold, channel, dilate, erode):
        import cv2

        masks = []
        for im in images.images:
            m = grey_threshold_cl(im, threshold * 255, channel == "max")
            if dilate:
                m = cv2.dilate(m, disc(dilate))
            if erode:
                m = cv2.erode(m, disc(erode))
            masks.append(m)
        return {"masks": MaskSet(masks, None, list(images.names))}


class Cleanup(Node):
    """Mask clean-up: morphological opening and closing, keep the largest components, fill holes."""

    type_name = "key.cleanup"
    version = 1
    inputs = {"masks": Masks}
    outputs = {"masks": Masks}
    params = {
        "open": Param(int, 1, range=(0, 50), doc="opening radius, pixels (removes specks)"),
        "close": Param(int, 2, range=(0, 50), doc="closing radius, pixels (bridges cracks)"),
        "keep": Param(int, 1, range=(0, None), doc="keep the k largest components (0 = all)"),
        "fill_holes": Param(bool, True, doc="fill background regions not connected to the border"),
    }

    def run(self, masks, *, open, close, keep, fill_holes):
        soft = masks.alpha8 if masks.alpha8 is not None else masks.alpha

        def clean(m, a, hint):   # hint: where the key says the mask lies (its alpha window); the result's own box
            c, box = clean_mask_box(m, open_px=open, close_px=close, keep=keep, fill_holes=fill_holes, hint=hint)
            return c, (None if a is None else cleaned_alpha(c, m, a, hint=box)), box

        done = map_views(clean, masks.masks, soft if soft is not None else [None] * len(masks),
                         masks.boxes or [None] * len(masks))
        out, alphas, boxes = [c for c, _, _ in done], [a for _, a, _ in done], [b for _, _, b in done]
        if masks.alpha8 is not None:   # 8-bit alpha in, 8-bit out (the same float alpha)
            return {"masks": MaskSet(out, None, list(masks.names), alpha8=alphas, boxes=boxes)}
        return {"masks": MaskSet(out, alphas if soft is not None else None, list(masks.names), boxes=boxes)}


class Consensus(Node):
    """Multi-view consistency: each view's mask intersected with the projection of a visual hull computed from
    all views' masks (with a min_views tolerance), so what only one or two cameras believe is foreground is
    rejected."""

    type_name = "key.consensus"
    version = 1
    inputs = {"masks": Masks, "cameras": CameraSet, "volume": Input(Volume, doc="hull of all views' masks")}
    outputs = {"masks": Masks}
    params = {"dilate": Param(int, 2, range=(0, 100), doc="extra margin around the hull's projection, pixels")}

    def run(self, masks, cameras, volume, *, dilate):
        check_views("key.consensus", masks.masks, cameras, kind="mask")
        out, alphas = [], []
        centres = surface_centres(volume)     # the hull's surface voxels, projected into every view
        for v, m in enumerate(masks.masks):
            keep = hull_footprint(volume, cameras, v, dilate, centres) > 0
            out.append(_kept(m, keep, np.uint8))
            if masks.alpha is not None:
                alphas.append(_kept(masks.alpha[v], keep, np.float32))
        return {"masks": MaskSet(out, alphas if masks.alpha is not None else None, list(masks.names))}


def _kept(a, keep, dtype):
    """``a`` where ``keep``, 0 elsewhere, as ``dtype``: np.where(keep, a, 0).astype(dtype)'s values (a float's -0.0
    kept) in one pass instead of three (an HD view 8.5 -> 1.5 ms)."""
    out = np.zeros(np.shape(a), dtype)
    np.copyto(out, a, casting="unsafe", where=keep)
    return out


class GrabCut(Node):
    """Boundary refinement: each mask re-decided in a band around its edge by GrabCut (colour models of both
    sides + a graph cut that follows image edges), for what a colour key cannot separate, e.g. dark hair in
    front of a dark studio wall. Pixels well inside stay foreground, pixels far outside stay background."""

    type_name = "key.grabcut"
    version = 1
    inputs = {"images": Images, "masks": Masks}
    outputs = {"masks": Masks}
    params = {
        "inner": Param(int, 4, range=(0, 100), doc="pixels deeper than this inside the mask are certain foreground"),
        "outer": Param(int, 20, range=(1, 200), doc="pixels farther than this outside the mask are certain background"),
        "iterations": Param(int, 2, range=(1, 20), doc="GrabCut iterations (colour model re-fit + cut)"),
    }

    def run(self, images, masks, *, inner, outer, iterations):
        if len(masks) != len(images):
            raise NodeError(f"key.grabcut: {len(images)} images but {len(masks)} masks")
        from concurrent.futures import ThreadPoolExecutor

        for name, im, m in zip(images.names, images.images, masks.masks):
            if m.shape != im.shape[:2]:
                raise NodeError(f"key.grabcut: camera '{name}': mask {m.shape[1]}x{m.shape[0]} does not match image "
                                f"{im.shape[1]}x{im.shape[0]}")
        with ThreadPoolExecutor() as pool:  # OpenCV releases the GIL; views are independent
            out = list(pool.map(lambda im, m: grabcut_band(im, m, inner, outer, iterations), images.images, masks.masks))
        return {"masks": MaskSet(out, None, list(masks.names))}
