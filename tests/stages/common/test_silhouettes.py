"""silhouettes.distance_outline: the signed distance field the tracker's silhouette term reads."""
import numpy as np

from nodes.common.silhouettes import Silhouettes


def outline(*masks):
    return Silhouettes(np.zeros((len(masks), 32), np.float32), list(masks), None).distance_outline().alpha


def test_distance_outline_values_symmetry_and_repeats():
    m = np.zeros((60, 80), np.uint8)
    m[10:50, 20:60] = 255                                     # a square, mirror-symmetric left/right and up/down
    m[25:35, 5:75] = 255                                      # and a bar across it
    a = outline(m)[0]
    # alpha = 0.5 + (distance to the other class between pixel centres - half a pixel), inside positive
    assert a[30, 5] == 1.0 and a[30, 4] == 0.0               # the bar's end: first pixel in / first out
    assert a[12, 40] == 3.0 and a[8, 40] == -1.0             # 3 px from the top edge inside, 2 px above outside
    assert abs(a[10, 20] - 1.0) < 1e-6 and abs(a[9, 19] - (1.0 - np.sqrt(2.0))) < 1e-6   # diagonal: Euclidean
    assert np.array_equal(a, a[:, ::-1]) and np.array_equal(a, a[::-1, :])               # exact mirror images
    for _ in range(3):                                        # the same field on every call (cv2's was not)
        assert np.array_equal(outline(m)[0], a)
    bilinear = 0.5 * (a[30, 4] + a[30, 5])
    assert bilinear == 0.5                                    # >= 0.5 from the pixel edge on


def test_outline_kernel_matches_scipy_bit_for_bit():
    # kernels/silhouette.cl (Meijster's transform in integers) against scipy's exact transform on random masks:
    # speckle of every density, discs, noise, single rows and columns, one-pixel and one-row images
    from nodes.common.silhouettes import outline_field, outline_field_reference

    rng = np.random.default_rng(0)
    for trial in range(160):
        h, w = (1, int(rng.integers(1, 90))) if trial % 16 == 0 else (int(rng.integers(1, 90)), int(rng.integers(1, 90)))
        kind = trial % 4
        if kind == 0:
            m = (rng.random((h, w)) < rng.choice([0.001, 0.01, 0.3, 0.9, 0.999])) * 255
        elif kind == 1:
            yy, xx = np.mgrid[:h, :w]
            m = ((yy - h / 2) ** 2 + (xx - w / 3) ** 2 < (min(h, w) * rng.uniform(0.1, 0.6)) ** 2) * 200
        elif kind == 2:
            m = rng.integers(0, 256, (h, w))
        else:
            m = np.zeros((h, w))
            m[rng.integers(0, h), :] = 255
            m[:, rng.integers(0, w)] = 128
        m = m.astype(np.uint8)
        assert np.array_equal(outline_field(m), outline_field_reference(m)), (trial, h, w)
    for h, w, y, x in ((200, 210, 0, 0), (180, 230, 179, 229), (7, 300, 3, 0)):      # one pixel far from the rest:
        for value in (255, 0):                                                       # columns without the other class
            m = np.full((h, w), 255 - value, np.uint8)
            m[y, x] = value
            assert np.array_equal(outline_field(m), outline_field_reference(m)), (h, w, value)


def test_distance_outline_empty_and_full_masks():
    empty, full = outline(np.zeros((8, 9), np.uint8), np.full((8, 9), 255, np.uint8))
    assert np.all(np.isfinite(empty)) and empty.max() < 0.5   # nothing inside
    assert np.all(np.isfinite(full)) and full.min() >= 0.5    # everything inside


def test_border_views_of_device_silhouettes_match_their_block_windows_and_the_host_masks():
    """border_views on SilhouetteBits reads four border strips of each block table; it names the same views as
    the block windows touching a border (silhouette_windows) and as the host masks' border rows and columns,
    also for image sizes that are no multiple of 8 and for empty silhouettes."""
    from nodes.common.silhouettes import SilhouetteBits, border_views, silhouette_windows

    rng = np.random.default_rng(7)
    masks = []
    for w, h in [(37, 29), (64, 48), (41, 8), (8, 33), (50, 50), (23, 17), (64, 48), (9, 9)] * 3:
        m = np.zeros((h, w), np.uint8)
        case = len(masks) % 6
        y, x = int(rng.integers(1, h - 1)), int(rng.integers(1, w - 1))
        if case == 1:
            m[y, x] = 255                                         # inside only
        elif case == 2:
            m[y, 0 if rng.random() < 0.5 else w - 1] = 200        # left or right column
        elif case == 3:
            m[0 if rng.random() < 0.5 else h - 1, x] = 128        # top or bottom row
        elif case == 4:
            m[1:-1, 1:-1] = 255                                   # one pixel from every border
        elif case == 5:
            m[:] = 255
        masks.append(m)                                           # case 0: empty
    bits = SilhouetteBits.from_masks(masks)
    by_windows = [v for v, ((x0, y0, w, h), (W, H)) in enumerate(zip(silhouette_windows(bits), bits.sizes))
                  if w > 0 and (x0 == 0 or y0 == 0 or x0 + w == W or y0 + h == H)]
    assert border_views(bits) == by_windows
    views = border_views(bits)
    assert not any(v % 6 == 0 for v in views)                      # empty: never
    assert all(v in views for v in range(len(masks)) if v % 6 in (2, 3, 4, 5))   # a pixel in a border block


def test_border_views_of_device_silhouettes_on_random_masks():
    """The corner reads of border_views against the former per-view differencing of the whole block table
    (silhouette_windows) and against a host reference (block_table_reference: a border block holding an inside
    pixel), on random masks of random sizes and densities, a few pixels to most of the image, touching any of the four borders or none."""
    from nodes.common.silhouettes import (SilhouetteBits, block_table_reference, border_views,
                                          silhouette_windows)

    rng = np.random.default_rng(11)
    for trial in range(8):
        masks = []
        for _ in range(16):
            w, h = int(rng.integers(1, 90)), int(rng.integers(1, 70))
            density = float(rng.choice([0.0, 0.0005, 0.003, 0.02, 0.3]))
            m = np.where(rng.random((h, w)) < density, rng.integers(128, 256, (h, w)), rng.integers(0, 128, (h, w)))
            if rng.random() < 0.7:   # clear random margins (1-17 pixels, or none, a side): off the border too
                t, b, l, r = np.where(rng.random(4) < 0.25, 0, rng.integers(1, 18, 4))
                m[:t], m[h - b:], m[:, :l], m[:, w - r:] = 0, 0, 0, 0
            masks.append(m.astype(np.uint8))
        bits = SilhouetteBits.from_masks(masks)
        by_windows = [v for v, ((x0, y0, w, h), (W, H)) in enumerate(zip(silhouette_windows(bits), bits.sizes))
                      if w > 0 and (x0 == 0 or y0 == 0 or x0 + w == W or y0 + h == H)]
        reference = []
        for v, m in enumerate(masks):
            c = np.diff(np.diff(block_table_reference(m), axis=0), axis=1)
            if c[0].any() or c[-1].any() or c[:, 0].any() or c[:, -1].any():
                reference.append(v)
        assert border_views(bits) == by_windows == reference, trial
