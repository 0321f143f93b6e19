// Exact visual-hull points on segments (Liang & Wong, VISAPP 2008): a point is inside the hull when enough
// silhouettes contain its projection; a segment from an inside point to an outside point is bisected to the
// place where it leaves the hull.
//
// Silhouettes: binary (silhouette.h bits: the nearest pixel, as the hull's centre test) or, when soft != 0, soft
// alpha sampled bilinearly (inside when alpha >= 0.5), which puts the boundary between pixels.
// Camera layout and projection: kernels/camera.h (Cameras.pack(), 32 floats per camera). Pixel centres are
// integers. The vote is silhouette.h's (as the hull node).
// Arithmetic order here is mirrored by nodes/common/silhouettes.py (view_states, exit_reference, clamp_reference).
#pragma OPENCL FP_CONTRACT OFF
#include "silhouette.h"

// What view c says about point X: SIL_IN, SIL_BACKGROUND or SIL_UNSEEN.
inline int view_state(__global const float* c, float3 X, __global const uchar* bits, __global const float* alpha,
                      int soft)
{
    float3 xc = camera_point(c, X);
    if (!(xc.z * c[24] > 0.0f)) return SIL_UNSEEN;
    float2 uv = pixel_point(c, distort_point(c, xc.xy / xc.z));
    float u = uv.x, v = uv.y;
    int px, py, W = (int)c[22], H = (int)c[23];
    if (!seen_pixel(u, v, c[22], c[23], &px, &py)) return SIL_UNSEEN;
    if (soft) {
        float fx0 = floor(u), fy0 = floor(v);
        float fx = u - fx0, fy = v - fy0;
        int x0 = clamp((int)fx0, 0, W - 1), x1 = clamp((int)fx0 + 1, 0, W - 1);
        int y0 = clamp((int)fy0, 0, H - 1), y1 = clamp((int)fy0 + 1, 0, H - 1);
        float top = (1.0f - fx) * alpha[y0 * W + x0] + fx * alpha[y0 * W + x1];
        float bottom = (1.0f - fx) * alpha[y1 * W + x0] + fx * alpha[y1 * W + x1];
        float a = (1.0f - fy) * top + fy * bottom;
        return a >= 0.5f ? SIL_IN : SIL_BACKGROUND;
    }
    return silhouette_bit(bits, W, px, py) ? SIL_IN : SIL_BACKGROUND;
}

#define HULL_ARGS __global const float* cams, int nviews, __global const uchar* bits, __global const int* bit_off, \
                  __global const float* alpha, __global const int* alpha_off, int soft, int min_views, int policy
#define HULL_PASS cams, nviews, bits, bit_off, alpha, alpha_off, soft, min_views, policy

inline int inside_hull(float3 X, HULL_ARGS)
{
    int n_in = 0, n_bg = 0;
    for (int v = 0; v < nviews; v++) {
        int s = view_state(cams + v * CAM_FLOATS, X, bits + bit_off[v], alpha + alpha_off[v], soft);
        n_in += s == SIL_IN;
        n_bg += s == SIL_BACKGROUND;
        if (vote_decided(s, n_in, v, nviews, min_views, policy)) break;
    }
    return hull_vote(n_in, n_bg, nviews, min_views, policy);
}

// Parameter t in [lo, hi] of the segment A + t (B - A) after `steps` bisections, A taken as inside.
inline float2 bisect(float3 A, float3 B, int steps, HULL_ARGS)
{
    float lo = 0.0f, hi = 1.0f;
    float3 d = B - A;
    for (int s = 0; s < steps; s++) {
        float t = 0.5f * (lo + hi);
        float3 X = A + t * d;
        if (inside_hull(X, HULL_PASS)) lo = t; else hi = t;
    }
    return (float2)(lo, hi);
}

// Refine: each segment runs from its inside end a[i] to its outside end b[i]; out[i] = the middle of the
// last bisection interval.
__kernel void hull_exit(__global const float* a, __global const float* b, int n, int steps, HULL_ARGS,
                        __global float* out)
{
    int i = get_global_id(0);
    if (i >= n) return;
    float3 A = vload3(i, a), B = vload3(i, b);
    float2 r = bisect(A, B, steps, HULL_PASS);
    float t = 0.5f * (r.x + r.y);
    vstore3(A + t * (B - A), i, out);
}

// Clamp: a vertex moves from a[i] (kept as inside) to b[i]. When b[i] is outside the hull it goes back to the
// boundary: along -dirs[i] (from c = b[i] - reach * dirs[i], when c is inside and reach > 0), otherwise along
// its move; the result is the last point found inside.
__kernel void hull_clamp(__global const float* a, __global const float* b, __global const float* dirs, float reach,
                         int n, int steps, HULL_ARGS, __global float* out)
{
    int i = get_global_id(0);
    if (i >= n) return;
    float3 B = vload3(i, b);
    if (inside_hull(B, HULL_PASS)) {
        vstore3(B, i, out);
        return;
    }
    float3 A = vload3(i, a);
    if (reach > 0.0f) {
        float3 C = B - reach * vload3(i, dirs);
        if (inside_hull(C, HULL_PASS)) A = C;
    }
    float2 r = bisect(A, B, steps, HULL_PASS);
    vstore3(A + r.x * (B - A), i, out);
}

// Point test: inside[i] = 1 when p[i] is inside the hull.
__kernel void hull_inside(__global const float* p, int n, HULL_ARGS, __global uchar* inside)
{
    int i = get_global_id(0);
    if (i >= n) return;
    inside[i] = (uchar)inside_hull(vload3(i, p), HULL_PASS);
}
