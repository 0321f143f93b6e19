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


def test_distance_outline_empty_and_full_masks():
    empty, full = outline(np.zeros((8, 9), np.uint8), np.full((8, 9), 255, np.uint8))
    assert np.all(np.isfinite(empty)) and empty.max() < 0.5   # nothing inside
    assert np.all(np.isfinite(full)) and full.min() >= 0.5    # everything inside
