// Silhouettes on the device and the visual hull's vote rule: the one definition every kernel uses that asks
// whether a point is inside the silhouettes (hull.cl, refine.cl, carve.cl, ...). Mirrored bit for bit by
// nodes/common/silhouettes.py (centre_states, vote).
//
// Layout (nodes.common.silhouettes.SilhouetteBits): per view one bit per pixel, rows of ceil(W/8) bytes, pixel x
// in bit x % 8 of byte x / 8 (written by silhouette.cl:pack_block_rows from uint8 masks, or straight from the
// images by key.cl:chroma_key_bits), and an (Hb+1) x (Wb+1) int summed-area table of 8x8 pixel block counts.
// Include after `#pragma OPENCL FP_CONTRACT OFF` so the projection matches the NumPy mirror.
#ifndef VOLCAP_SILHOUETTE_H
#define VOLCAP_SILHOUETTE_H

#include "camera.h"

// What one view says about one point.
#define SIL_IN 1          // its projection is inside the silhouette
#define SIL_BACKGROUND 2  // seen, on background
#define SIL_UNSEEN 3      // behind the camera or outside the image

// Pixel (px, py) of a point projected to (u, v) (pixel centres at integers); 0 when outside the image.
inline int seen_pixel(float u, float v, float W, float H, int* px, int* py)
{
    float fu = u + 0.5f, fv = v + 0.5f;
    if (!(fu >= 0.0f && fu < W && fv >= 0.0f && fv < H)) return 0;
    *px = (int)fu;
    *py = (int)fv;
    return 1;
}

inline int silhouette_bit(__global const uchar* bits, int W, int px, int py)
{
    return (bits[py * ((W + 7) >> 3) + (px >> 3)] >> (px & 7)) & 1;
}

// The centre test: what view `c` (packed camera) with silhouette `bits` says about point X (nearest pixel).
__attribute__((always_inline)) inline int centre_state(__global const float* c, __global const uchar* bits, float3 X)
{
    float3 xc = camera_point(c, X);
    if (!(xc.z * c[24] > 0.0f)) return SIL_UNSEEN;
    float2 uv = pixel_point(c, distort_point(c, xc.xy / xc.z));
    int px, py;
    if (!seen_pixel(uv.x, uv.y, c[22], c[23], &px, &py)) return SIL_UNSEEN;
    return silhouette_bit(bits, (int)c[22], px, py) ? SIL_IN : SIL_BACKGROUND;
}

// The vote over nviews views, n_in of which say SIL_IN and n_bg SIL_BACKGROUND (the others: SIL_UNSEEN).
// min_views > 0 tolerates t = nviews - min_views background votes (t = 0 when min_views is 0); the policy holds
// either way: policy 0 ("carve"): every view sees the point and at most t say BACKGROUND; policy 1 ("ignore"):
// at most t say BACKGROUND and at least one says IN.
inline int hull_vote(int n_in, int n_bg, int nviews, int min_views, int policy)
{
    int tol = min_views > 0 ? nviews - min_views : 0;
    if (policy == 0) return n_in + n_bg == nviews && n_bg <= tol;
    return n_bg <= tol && n_in > 0;
}

// Whether the vote is decided once views 0..v have answered (the last one answered s): a loop over the views
// may stop there and call hull_vote. carve: an unseen view decides (outside); until then every view was seen,
// so the background votes are v + 1 - n_in. ignore: one background vote decides when nothing is tolerated
// (with a tolerance the loop runs to the end: the background count is not passed in).
inline int vote_decided(int s, int n_in, int v, int nviews, int min_views, int policy)
{
    int tol = min_views > 0 ? nviews - min_views : 0;
    if (policy == 0) return s == SIL_UNSEEN || v + 1 - n_in > tol;
    return tol == 0 && s == SIL_BACKGROUND;
}

#endif
