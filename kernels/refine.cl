// Exact visual-hull points on segments (Liang & Wong, VISAPP 2008): a point is inside the hull when enough
// silhouettes contain its projection; a segment from an inside point to an outside point is bisected to the
// place where it leaves the hull.
//
// Silhouettes: binary masks (inside when value > 127 at the nearest pixel) or, when soft != 0, soft alpha
// sampled bilinearly (inside when alpha >= 0.5), which puts the boundary between pixels.
// Camera layout and projection: kernels/camera.h (Cameras.pack(), 32 floats per camera). Pixel centres are
// integers.
// Vote (as the hull node): min_views > 0: at least min_views views inside; else policy 0 (carve): every
// view inside; policy 1 (ignore): no view on background and at least one inside.
// Arithmetic order here is mirrored by nodes/refine.py (view_states, exit_reference, clamp_reference).
#pragma OPENCL FP_CONTRACT OFF
#include "camera.h"

#define IN 1
#define BACKGROUND 2
#define UNSEEN 3

// 1 = inside the silhouette, 2 = on background, 3 = behind the camera or outside the image.
inline int view_state(__global const float* c, float3 X, __global const uchar* mask,
                      __global const float* alpha, int soft)
{
    float3 xc = camera_point(c, X);
    if (!(xc.z * c[24] > 0.0f)) return UNSEEN;
    float2 uv = pixel_point(c, distort_point(c, xc.xy / xc.z));
    float u = uv.x, v = uv.y;
    int W = (int)c[22], H = (int)c[23];
    if (!(u >= -0.5f && u < (float)W - 0.5f && v >= -0.5f && v < (float)H - 0.5f)) return UNSEEN;
    if (soft) {
        float fx0 = floor(u), fy0 = floor(v);
        float fx = u - fx0, fy = v - fy0;
        int x0 = clamp((int)fx0, 0, W - 1), x1 = clamp((int)fx0 + 1, 0, W - 1);
        int y0 = clamp((int)fy0, 0, H - 1), y1 = clamp((int)fy0 + 1, 0, H - 1);
        float top = (1.0f - fx) * alpha[y0 * W + x0] + fx * alpha[y0 * W + x1];
        float bottom = (1.0f - fx) * alpha[y1 * W + x0] + fx * alpha[y1 * W + x1];
        float a = (1.0f - fy) * top + fy * bottom;
        return a >= 0.5f ? IN : BACKGROUND;
    }
    int px = (int)(u + 0.5f), py = (int)(v + 0.5f);
    return mask[py * W + px] > 127 ? IN : BACKGROUND;
}

#define HULL_ARGS __global const float* cams, int nviews, __global const uchar* masks, __global const int* mask_off, \
                  __global const float* alpha, __global const int* alpha_off, int soft, int min_views, int policy
#define HULL_PASS cams, nviews, masks, mask_off, alpha, alpha_off, soft, min_views, policy

inline int inside_hull(float3 X, HULL_ARGS)
{
    int n_in = 0, n_bg = 0;
    for (int v = 0; v < nviews; v++) {
        int s = view_state(cams + v * CAM_FLOATS, X, masks + mask_off[v], alpha + alpha_off[v], soft);
        n_in += s == IN;
        n_bg += s == BACKGROUND;
        // stop as soon as the vote is decided
        if (min_views > 0) {
            if (n_in >= min_views) return 1;
            if (n_in + (nviews - 1 - v) < min_views) return 0;
        } else if (policy == 0) {
            if (s != IN) return 0;
        } else if (s == BACKGROUND) {
            return 0;
        }
    }
    if (min_views > 0) return n_in >= min_views;
    if (policy == 0) return n_in == nviews;
    return n_bg == 0 && n_in > 0;
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
