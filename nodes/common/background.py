"""Per-pixel statistics of a camera's background learnt from several frames of the empty stage: a Gaussian
mixture per pixel (capture.background learns it; key.difference keys against it, nodes/key/keying.py)."""
from __future__ import annotations

import numpy as np

from kernels import source
from nodegraph import NodeError, clrt

KERNELS = source("background.cl")

KMAX = 5  # components per pixel at most (kernels/background.cl holds them in private memory)
PRIOR_SIGMA = 2.5  # a new component's sigma before its frames say, in units of the noise floor


def background_mixture(frames, components: int = 3, noise: float = 4.0, match: float = 4.0, min_weight: float = 0.1,
                       shift: float = 0.0, method: str = "opencl"):
    """A per-pixel Gaussian mixture of one camera's background from several frames (Stauffer & Grimson 1999, in
    batch; the seed's "learning techniques" for the background). Pass 1: each frame's colour joins the nearest
    component within ``match`` sigmas (colour distance over the three channels, as ``still`` measures it) and
    updates its sample mean and variance (Welford; the variance shrunk towards 2.5x the noise floor by two
    pseudo-frames), or replaces the component that has seen fewest frames. Pass 2 assigns every frame again to
    the nearest of those components (within ``match``; farther frames count for none) with their final
    variances, and two components whose means lie within the match distance of each other (in the wider one's
    sigmas) are pooled: one background that nearest-assignment split in two halves. A component is background when it holds at least ``min_weight`` of
    the frames (the most frequent one always): a flickering light or a swaying leaf is two backgrounds, a subject
    passing once is none.

    ``shift`` (pixels): the footage may sit that far from the plate frames (a camera nudged between the two
    recordings, vibration): each component's sigma grows by shift x its mean's gradient, so edges of the background
    do not key as subject (Utrecht: the plate video and the footage are two recordings).

    ``method``: "opencl" (kernels/background.cl, one work item per pixel over all frames) or "numpy"
    (background_mixture_reference, the same float32 operations).

    Returns (mean (K, H, W, 3) uint8, sigma (K, H, W, 3) float16 per channel, at least ``noise``; weight (K, H, W)
    float32), components sorted by weight; the slots that are not background repeat the first component (so a
    minimum over the slots is unchanged by them) and have weight 0."""
    stack = _stack(frames)
    K = int(components)
    if not 1 <= K <= KMAX:
        raise NodeError(f"background mixture: {K} components (1..{KMAX})")
    floor = np.float32(noise) ** 2
    limit = np.float32(match) ** 2
    prior = np.float32(PRIOR_SIGMA * noise) ** 2
    if method == "opencl":
        n, mu, var = _mixture_cl(stack, K, floor, limit, prior)
    else:
        n, mu, var = background_mixture_reference(stack, K, floor, limit, prior)
    return _finish(n, mu, var, len(stack), min_weight, shift)


def _stack(frames) -> np.ndarray:
    frames = [np.asarray(f, np.uint8)[..., :3] for f in frames]
    if not frames:
        raise NodeError("background mixture: no frames")
    h, w = frames[0].shape[:2]
    for f in frames:
        if f.shape[:2] != (h, w):
            raise NodeError(f"background frames differ in size: {f.shape[1]}x{f.shape[0]} after {w}x{h}")
    return np.ascontiguousarray(np.stack(frames))


def background_mixture_reference(stack: np.ndarray, K: int, floor, limit, prior):
    """NumPy reference of kernels/background.cl: (n (K, H, W), mu, var (K, H, W, 3)) float32 after both passes
    and the pooling, components sorted by count (see background_mixture)."""
    frames = list(stack)
    h, w = frames[0].shape[:2]
    floor, limit, prior = np.float32(floor), np.float32(limit), np.float32(prior)

    def variance(n, m2):
        return np.maximum((m2 + 2 * prior) / (n[..., None] + 1), floor)

    def accumulate(n, mu, m2, create, model=None):
        """Every frame into (n, mu, m2) by nearest component, of ``model`` ((n, mu, var) to match against) or of
        the statistics themselves; ``create``: a frame that matches none starts a component."""
        for x in frames:
            x = x.astype(np.float32)
            mn, mm, var = model if model is not None else (n, mu, variance(n, m2))
            d2 = np.where(mn > 0, np.sum((x - mm) ** 2 / var, -1), np.inf)
            best = np.argmin(d2, 0)
            ok = np.take_along_axis(d2, best[None], 0)[0] <= limit
            weakest = np.argmin(n, 0)
            for k in range(K):
                hit = ok & (best == k)
                n[k] += hit
                delta = np.where(hit[..., None], x - mu[k], 0)
                mu[k] += delta / np.maximum(n[k], 1)[..., None]
                m2[k] += delta * (x - mu[k])
                if create:
                    new = ~ok & (weakest == k)
                    n[k][new], mu[k][new], m2[k][new] = 1, x[new], 0

    def empty():
        return np.zeros((K, h, w), np.float32), np.zeros((K, h, w, 3), np.float32), np.zeros((K, h, w, 3), np.float32)

    n, mu, m2 = empty()
    accumulate(n, mu, m2, create=True)
    model = (n, mu, variance(n, m2))
    n, mu, m2 = empty()
    mu[:] = model[1]
    accumulate(n, mu, m2, create=False, model=model)
    for k in range(K):
        for j in range(k + 1, K):
            var = variance(n, m2)
            close = (n[k] > 0) & (n[j] > 0) & (np.sum((mu[k] - mu[j]) ** 2 / np.maximum(var[k], var[j]), -1)
                                                 <= limit)
            nk, nj = n[k][close][:, None], n[j][close][:, None]
            dm = mu[j][close] - mu[k][close]
            tot = nk + nj
            m2[k][close] += m2[j][close] + dm * dm * nk * nj / tot
            mu[k][close] += dm * nj / tot
            n[k][close] = tot[:, 0]
            n[j][close], m2[j][close] = 0, 0
    var = variance(n, m2)
    order = np.argsort(-n, axis=0, kind="stable")
    n = np.take_along_axis(n, order, 0)
    mu = np.take_along_axis(mu, order[..., None], 0)
    var = np.take_along_axis(var, order[..., None], 0)
    return n, mu, var


def _finish(n, mu, var, count: int, min_weight: float, shift: float):
    """Weights, the slots that are no background replaced by the first, the shift allowance, rounding."""
    K = len(n)
    weight = n / np.float32(count)
    keep = weight >= np.float32(min_weight)
    keep[0] = True
    mu = np.where(keep[..., None], mu, mu[:1])
    var = np.where(keep[..., None], var, var[:1])
    weight = np.where(keep, weight, 0).astype(np.float32)
    if shift > 0:
        import cv2

        for k in range(K):
            for c in range(3):
                gx = cv2.Sobel(mu[k, ..., c], cv2.CV_32F, 1, 0, ksize=3) / 8
                gy = cv2.Sobel(mu[k, ..., c], cv2.CV_32F, 0, 1, ksize=3) / 8
                var[k, ..., c] += np.float32(shift) ** 2 * (gx * gx + gy * gy)
    mean = np.clip(np.rint(mu), 0, 255).astype(np.uint8)
    return mean, np.sqrt(var).astype(np.float16), weight


class BackgroundCL(clrt.Runner):
    source = KERNELS


def _mixture_cl(stack: np.ndarray, K: int, floor, limit, prior):
    run = BackgroundCL.get()
    N, h, w = stack.shape[:3]
    npix = h * w
    frames = run.host(stack)
    mu, var, n = run.buffer("mu", K * npix * 12), run.buffer("var", K * npix * 12), run.buffer("n", K * npix * 4)
    f = np.float32
    run.launch("background_mixture", npix, 64, frames, np.int32(N), np.int32(npix), f(floor), f(limit), f(prior),
               mu, var, n, options=(f"-DK={K}",))
    return (run.read(n, (K, h, w), np.float32), run.read(mu, (K, h, w, 3), np.float32),
            run.read(var, (K, h, w, 3), np.float32))
