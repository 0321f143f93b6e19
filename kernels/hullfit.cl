// The smooth silhouette field and the visual hull's searches at a level (nodes/mesh/hullfit.py mirrors every
// function here in NumPy float32, in the same order of operations).
//
// Each view's mask is read as f(u, v) = sum over the 3x3 nearest pixels of value * B(u - x) B(v - y), B the
// quadratic B-spline, pixel centres at integers, pixels off the image 0; where the nine values are equal f is
// that value exactly. Binary masks are bits (rows of ceil(W/8) bytes, pixel x in bit x % 8 of byte x / 8);
// soft masks one byte per pixel (alpha * 255). A view sees a point inside at level tau when it is in front of
// the camera, on the image and f >= tau; otherwise on background, or unseen (behind / off the image).
// Vote (silhouette.h hull_vote, nodes.common.silhouettes.vote): at most t = nviews - min_views views on background
// (t = 0 when min_views is 0); policy 0 (carve): every view sees the point; policy 1 (ignore): at least one inside.
//
// Searches run along segments A -> B with A inside. Under "carve" (every view must see the point inside) the
// hull's exit is the first exit over the views, found view by view: a view that sees the current best exit
// point inside is skipped (its own exit lies beyond, on a short segment), the others are bisected alone on
// [0, best]. Other vote rules bisect the vote itself.
//
// View culling: a search may be given, per point, a ball (centre, radius) and the views that are not known to see
// the whole ball inside (active_views: field exactly 1 on it, from the 8x8 block tables of SilhouetteBits). When
// the segment lies in the ball, only those views are visited; the others cannot cut it (their field is 1 >= tau
// there), so the result is the same bit for bit, and otherwise every view is visited.
#pragma OPENCL FP_CONTRACT OFF
#include "silhouette.h"  // the projection (camera.h) and the visual hull's vote rule (hull_vote)

#define IN SIL_IN
#define BACKGROUND SIL_BACKGROUND
#define UNSEEN SIL_UNSEEN

#define FIELD_ARGS __global const float* cams, int nviews, __global const uchar* pix, __global const int* pix_off, \
                   int soft, int min_views, int policy
#define FIELD_PASS cams, nviews, pix, pix_off, soft, min_views, policy
// The views to visit: all when `use` is 0, else those whose bit is set in words w.
#define VISIT(v) (!use || ((w[(v) >> 5] >> ((v) & 31)) & 1u))
#define CULL_ARGS __global const float* cull, __global const uint* act, int nwords, int use_cull

// Three horizontally adjacent pixel values starting at (x, y), off-image pixels 0.
__attribute__((always_inline)) inline float3 pixel_triple(__global const uchar* p, int soft, int W, int H, int x, int y)
{
    if (y < 0 || y >= H) return (float3)(0.0f);
    float3 r;
    if (soft) {
        __global const uchar* row = p + y * W;
        r.x = x >= 0 && x < W ? (float)row[x] * (1.0f / 255.0f) : 0.0f;
        r.y = x + 1 >= 0 && x + 1 < W ? (float)row[x + 1] * (1.0f / 255.0f) : 0.0f;
        r.z = x + 2 >= 0 && x + 2 < W ? (float)row[x + 2] * (1.0f / 255.0f) : 0.0f;
        return r;
    }
    int wb = (W + 7) >> 3;
    __global const uchar* row = p + y * wb;
    int bits;
    if (x >= 0 && x + 2 < W) {
        int b = x >> 3;
        int word = row[b] | (b + 1 < wb ? row[b + 1] << 8 : 0);
        bits = (word >> (x & 7)) & 7;
    } else {
        bits = 0;
        for (int k = 0; k < 3; k++) {
            int xx = x + k;
            if (xx >= 0 && xx < W) bits |= ((row[xx >> 3] >> (xx & 7)) & 1) << k;
        }
    }
    return (float3)((float)(bits & 1), (float)((bits >> 1) & 1), (float)((bits >> 2) & 1));
}

// f at pixel coordinates (u, v) of a view whose pixels start at p (u, v on the image).
__attribute__((always_inline)) inline float field_value(__global const uchar* p, int soft, int W, int H, float u, float v)
{
    float px = floor(u + 0.5f), py = floor(v + 0.5f);
    int x = (int)px - 1, y = (int)py - 1;
    float3 r0 = pixel_triple(p, soft, W, H, x, y);
    float3 r1 = pixel_triple(p, soft, W, H, x, y + 1);
    float3 r2 = pixel_triple(p, soft, W, H, x, y + 2);
    float lo = fmin(fmin(fmin(r0.x, r0.y), fmin(r0.z, r1.x)), fmin(fmin(r1.y, r1.z), fmin(fmin(r2.x, r2.y), r2.z)));
    float hi = fmax(fmax(fmax(r0.x, r0.y), fmax(r0.z, r1.x)), fmax(fmax(r1.y, r1.z), fmax(fmax(r2.x, r2.y), r2.z)));
    if (lo == hi) return lo;
    float tx = u - px, ty = v - py;
    float ax = 0.5f - tx, bx = 0.5f + tx, ay = 0.5f - ty, by = 0.5f + ty;
    float wx0 = 0.5f * (ax * ax), wx1 = 0.75f - tx * tx, wx2 = 0.5f * (bx * bx);
    float wy0 = 0.5f * (ay * ay), wy1 = 0.75f - ty * ty, wy2 = 0.5f * (by * by);
    float acc = 0.0f;
    acc = acc + wy0 * ((r0.x * wx0 + r0.y * wx1) + r0.z * wx2);
    acc = acc + wy1 * ((r1.x * wx0 + r1.y * wx1) + r1.z * wx2);
    acc = acc + wy2 * ((r2.x * wx0 + r2.y * wx1) + r2.z * wx2);
    return acc;
}

// Field of view c at X: f when X is in front of the camera and on the image, else -1 (unseen).
inline float view_value(__global const float* c, __global const uchar* p, int soft, float3 X)
{
    float depth;
    float2 uv = project_point(c, X, &depth);
    if (!(depth > 0.0f)) return -1.0f;
    int W = (int)c[22], H = (int)c[23];
    if (!(uv.x >= -0.5f && uv.x < (float)W - 0.5f && uv.y >= -0.5f && uv.y < (float)H - 0.5f)) return -1.0f;
    return field_value(p, soft, W, H, uv.x, uv.y);
}

inline int view_state(__global const float* c, __global const uchar* p, int soft, float3 X, float tau)
{
    float f = view_value(c, p, soft, X);
    return f < 0.0f ? UNSEEN : (f >= tau ? IN : BACKGROUND);
}

// One view's crossing of level tau on [0, hi] of A + t d, A inside (ga = f(A) - tau >= 0) and the point at hi
// outside (gb < 0): Illinois regula falsi, at most `steps` iterations, stopping when the bracket is shorter
// than 2^-12 or at a point whose field is within ROOT_TOL of tau ((t, t) then). Returns the bracket (last
// inside, first outside).
#define ROOT_TOL 1e-4f
inline float2 view_crossing(__global const float* c, __global const uchar* p, int soft, float3 A, float3 d,
                            float tau, float ga, float hi, float gb, int steps)
{
    float a = 0.0f, b = hi;
    int side = 0;
    for (int k = 0; k < steps && b - a > 2.4414062e-04f; k++) {
        float t = b - gb * ((b - a) / (gb - ga));
        if (!(t > a && t < b)) t = 0.5f * (a + b);
        float g = view_value(c, p, soft, A + t * d) - tau;
        if (fabs(g) < ROOT_TOL) return (float2)(t, t);  // on the level (within 1e-4 pixel on a straight edge)
        if (g >= 0.0f) {
            a = t;
            ga = g;
            if (side == 1) gb = 0.5f * gb;
            side = 1;
        } else {
            b = t;
            gb = g;
            if (side == -1) ga = 0.5f * ga;
            side = -1;
        }
    }
    return (float2)(a, b);
}

inline int inside_at(float3 X, float tau, FIELD_ARGS, int use, __global const uint* w)
{
    int n_in = 0, n_bg = 0;
    for (int v = 0; v < nviews; v++) {
        if (!VISIT(v)) {  // a culled view sees the point inside
            n_in++;
            continue;
        }
        int s = view_state(cams + v * CAM_FLOATS, pix + pix_off[v], soft, X, tau);
        n_in += s == IN;
        n_bg += s == BACKGROUND;
        if (min_views == 0 && policy == 0 && s != IN) return 0;
    }
    return hull_vote(n_in, n_bg, nviews, min_views, policy);
}

// Exit of the segment A -> B at level tau: the parameter bracket (lo, hi) of the first exit; (1, 1) when the
// segment does not leave the hull; (0, 0) when A is not inside.
__attribute__((always_inline)) inline float2 exit_interval(float3 A, float3 B, float tau, int steps, FIELD_ARGS, int use, __global const uint* w)
{
    float3 d = B - A;
    float lo = 1.0f, hi = 1.0f;
    if (min_views == 0 && policy == 0) {
        for (int v = 0; v < nviews; v++) {
            if (!VISIT(v)) continue;
            __global const float* c = cams + v * CAM_FLOATS;
            __global const uchar* p = pix + pix_off[v];
            float gb = view_value(c, p, soft, A + hi * d) - tau;
            if (gb >= 0.0f) continue;
            float ga = view_value(c, p, soft, A) - tau;
            if (ga < 0.0f) return (float2)(0.0f, 0.0f);
            float2 r = view_crossing(c, p, soft, A, d, tau, ga, hi, gb, steps);
            lo = r.x;
            hi = r.y;
        }
        return (float2)(lo, hi);
    }
    if (!inside_at(A, tau, FIELD_PASS, use, w)) return (float2)(0.0f, 0.0f);
    if (inside_at(B, tau, FIELD_PASS, use, w)) return (float2)(1.0f, 1.0f);
    float a = 0.0f, b = 1.0f;
    for (int s = 0; s < steps + 8; s++) {  // bisection of the vote: slower to converge than regula falsi
        float t = 0.5f * (a + b);
        if (inside_at(A + t * d, tau, FIELD_PASS, use, w)) a = t; else b = t;
    }
    return (float2)(a, b);
}

// Exits at two levels tau_hi > tau_lo on one segment in one pass over the views (carve): a view that sees the
// point at the far level's best exit (hi2 >= hi1) inside at tau_hi is skipped for both levels (one lookup: along
// the segment outwards the field falls, so both its own exits lie beyond); otherwise it is looked up at hi1 too. Writes (lo, hi) of the tau_hi exit to *r_hi and of the tau_lo exit to *r_lo, as
// exit_interval would for each.
__attribute__((always_inline)) inline void exit_two_levels(float3 A, float3 B, float tau_hi, float tau_lo, int steps, FIELD_ARGS, int use,
                            __global const uint* w, float2* r_hi, float2* r_lo)
{
    float3 d = B - A;
    float lo1 = 1.0f, hi1 = 1.0f, lo2 = 1.0f, hi2 = 1.0f;
    int dead1 = 0, dead2 = 0;
    for (int v = 0; v < nviews; v++) {
        if (!VISIT(v)) continue;
        __global const float* c = cams + v * CAM_FLOATS;
        __global const uchar* p = pix + pix_off[v];
        float f2 = view_value(c, p, soft, A + hi2 * d);
        if (f2 >= tau_hi) continue;  // inside at both levels at the far best exit: its own exits lie beyond
        float f1 = hi2 == hi1 ? f2 : view_value(c, p, soft, A + hi1 * d);
        int cut1 = !dead1 && f1 < tau_hi, cut2 = !dead2 && f2 < tau_lo;
        if (!cut1 && !cut2) continue;
        float fa = view_value(c, p, soft, A);
        if (cut1) {
            if (fa < tau_hi) { dead1 = 1; lo1 = hi1 = 0.0f; }
            else {
                float2 r = view_crossing(c, p, soft, A, d, tau_hi, fa - tau_hi, hi1, f1 - tau_hi, steps);
                lo1 = r.x;
                hi1 = r.y;
            }
        }
        if (cut2) {
            if (fa < tau_lo) { dead2 = 1; lo2 = hi2 = 0.0f; }
            else {
                float2 r = view_crossing(c, p, soft, A, d, tau_lo, fa - tau_lo, hi2, f2 - tau_lo, steps);
                lo2 = r.x;
                hi2 = r.y;
            }
        }
    }
    *r_hi = (float2)(lo1, hi1);
    *r_lo = (float2)(lo2, hi2);
}

// ---------------------------------------------------------------- view culling

// Whether view c sees every point of the ball (X, R) exactly inside (field 1): the ball is in front of the camera,
// its projection (bounded through the Jacobian of the projection, lens distortion included) and the 3x3 pixels
// around it are on the image, and every 8x8 block those pixels touch is full in the view's block table `sat`
// ((Hb+1) x (Wb+1) summed-area table of the blocks' counts of pixels whose value is 1).
__attribute__((always_inline)) inline int ball_all_in(__global const float* c, __global const int* sat, float3 X, float R)
{
    float3 xc = camera_point(c, X);
    float3 r0 = (float3)(c[0], c[1], c[2]), r1 = (float3)(c[4], c[5], c[6]), r2 = (float3)(c[8], c[9], c[10]);
    float zr = R * length(r2);  // how far the ball reaches along the camera's z
    if (!(xc.z * c[24] > 1.001f * zr)) return 0;
    float nx = xc.x / xc.z, ny = xc.y / xc.z;
    float k = R / (fabs(xc.z) - zr);
    // bounds of the normalised offsets: x/z - nx = ((r0 - nx r2) . delta) / (z + r2 . delta)
    float dx = k * length(r0 - nx * r2), dy = k * length(r1 - ny * r2);
    if (has_distortion(c)) {  // the distortion's derivatives over the ball, bounded (both axes by the larger offset)
        float r = sqrt(nx * nx + ny * ny) + dx + dy;
        float rr = r * r;
        float g = 1.0f + 2.0f * ((3.0f * fabs(c[17]) + (5.0f * fabs(c[18]) + 7.0f * fabs(c[21]) * rr) * rr) * rr)
                  + 12.0f * (fabs(c[19]) + fabs(c[20])) * r;
        dx = dy = g * fmax(dx, dy);
    }
    float2 uv = pixel_point(c, distort_point(c, (float2)(nx, ny)));
    float ru = 1.01f * (fabs(c[12]) * dx + fabs(c[13]) * dy) + 0.01f;
    float rv = 1.01f * fabs(c[15]) * dy + 0.01f;
    int W = (int)c[22], H = (int)c[23];
    if (!(uv.x - ru >= -0.5f && uv.x + ru < (float)W - 0.5f && uv.y - rv >= -0.5f && uv.y + rv < (float)H - 0.5f))
        return 0;
    int x0 = (int)floor(uv.x - ru + 0.5f) - 1, x1 = (int)floor(uv.x + ru + 0.5f) + 1;
    int y0 = (int)floor(uv.y - rv + 0.5f) - 1, y1 = (int)floor(uv.y + rv + 0.5f) + 1;
    if (x0 < 0 || y0 < 0 || x1 >= W || y1 >= H) return 0;
    int bx0 = x0 >> 3, bx1 = x1 >> 3, by0 = y0 >> 3, by1 = y1 >> 3;
    int stride = ((W + 7) >> 3) + 1;
    int count = (sat[(by1 + 1) * stride + bx1 + 1] - sat[by0 * stride + bx1 + 1])
                - (sat[(by1 + 1) * stride + bx0] - sat[by0 * stride + bx0]);
    int full = (min((bx1 + 1) << 3, W) - (bx0 << 3)) * (min((by1 + 1) << 3, H) - (by0 << 3));
    return count == full;
}

// Whether point i's search of the segment A -> B may visit only its active views: culling is on and the segment
// lies in the point's ball (cull[i] = centre, radius). Sets *w to the point's words.
inline int use_cull_for(int i, float3 A, float3 B, CULL_ARGS, __global const uint** w)
{
    *w = act + i * nwords;
    if (!use_cull) return 0;
    float4 c = vload4(i, cull);
    float r2 = c.w * c.w;
    float3 a = A - c.xyz, b = B - c.xyz;
    return dot(a, a) <= r2 && dot(b, b) <= r2;
}

// ---------------------------------------------------------------- kernels

// Active views of each ball cull[i] = (centre, radius): bit v of words act[i * nwords ..] is 0 when view v sees
// the whole ball inside (ball_all_in), 1 otherwise. sat / sat_off: the views' block tables.
__kernel void active_views(__global const float* cull, int n, __global const float* cams, int nviews,
                           __global const int* sat, __global const int* sat_off, int nwords, __global uint* act)
{
    int i = get_global_id(0);
    if (i >= n) return;
    float4 b = vload4(i, cull);
    for (int k = 0; k < nwords; k++) {
        uint bits = 0;
        for (int v = k * 32; v < min(nviews, k * 32 + 32); v++)
            if (!ball_all_in(cams + v * CAM_FLOATS, sat + sat_off[v], b.xyz, b.w)) bits |= 1u << (v & 31);
        act[i * nwords + k] = bits;
    }
}

// Point test at level tau: inside[i] = 1 when p[i] is inside the hull.
__kernel void inside_level(__global const float* p, int n, float tau, FIELD_ARGS, __global uchar* inside)
{
    int i = get_global_id(0);
    if (i >= n) return;
    inside[i] = (uchar)inside_at(vload3(i, p), tau, FIELD_PASS, 0, (__global const uint*)0);
}

// Segment search: when a[i] is inside at tau and b[i] is not, out[i] = A + t (B - A) with t the middle of the
// exit bracket and found[i] = 1; otherwise out[i] = keep[i], found[i] = 0.
__kernel void cross_level(__global const float* a, __global const float* b, __global const float* keep, int n,
                          float tau, int steps, FIELD_ARGS, CULL_ARGS, __global float* out, __global uchar* found)
{
    int i = get_global_id(0);
    if (i >= n) return;
    float3 A = vload3(i, a), B = vload3(i, b);
    __global const uint* w;
    int use = use_cull_for(i, A, B, cull, act, nwords, use_cull, &w);
    float2 r = exit_interval(A, B, tau, steps, FIELD_PASS, use, w);
    if (r.y > 0.0f && r.x < 1.0f) {
        float t = 0.5f * (r.x + r.y);
        vstore3(A + t * (B - A), i, out);
        found[i] = 1;
    } else {
        vstore3(vload3(i, keep), i, out);
        found[i] = 0;
    }
}

// Onto the level along a direction: the segment p[i] - reach d[i] -> p[i] + reach d[i] (d unit). When its
// start is inside at tau and it leaves the hull, out[i] = the middle of the exit bracket and found[i] = 1;
// otherwise out[i] = p[i], found[i] = 0.
__kernel void onto_level(__global const float* p, __global const float* d, float reach, int n, float tau,
                         int steps, FIELD_ARGS, CULL_ARGS, __global float* out, __global uchar* found)
{
    int i = get_global_id(0);
    if (i >= n) return;
    float3 P = vload3(i, p), D = reach * vload3(i, d);
    float3 A = P - D;
    __global const uint* w;
    int use = use_cull_for(i, A, P + D, cull, act, nwords, use_cull, &w);
    float2 r = exit_interval(A, P + D, tau, steps, FIELD_PASS, use, w);
    if (r.y > 0.0f && r.x < 1.0f) {
        vstore3(A + (0.5f * (r.x + r.y)) * (2.0f * D), i, out);
        found[i] = 1;
    } else {
        vstore3(P, i, out);
        found[i] = 0;
    }
}

// The shell along a line: on the segment A = p[i] - reach d[i] -> B = p[i] + reach d[i], the exit brackets at
// level tau_in (the deep side of the shell) and at tau_out (its far side): out[i] = (in_lo, in_hi, out_lo,
// out_hi), parameters in [0, 1] from A to B ((0, 0): A is not inside at that level; (1, 1): no exit).
__kernel void shell_interval(__global const float* p, __global const float* d, float reach, int n, float tau_in,
                             float tau_out, int steps, FIELD_ARGS, CULL_ARGS, __global float* out)
{
    int i = get_global_id(0);
    if (i >= n) return;
    float3 P = vload3(i, p), D = reach * vload3(i, d);
    float3 A = P - D, B = P + D;
    __global const uint* w;
    int use = use_cull_for(i, A, B, cull, act, nwords, use_cull, &w);
    float2 r_in, r_out;
    if (tau_out == tau_in) r_out = r_in = exit_interval(A, B, tau_in, steps, FIELD_PASS, use, w);
    else if (min_views == 0 && policy == 0 && tau_in > tau_out)
        exit_two_levels(A, B, tau_in, tau_out, steps, FIELD_PASS, use, w, &r_in, &r_out);
    else {
        r_in = exit_interval(A, B, tau_in, steps, FIELD_PASS, use, w);
        r_out = exit_interval(A, B, tau_out, steps, FIELD_PASS, use, w);
    }
    vstore4((float4)(r_in.x, r_in.y, r_out.x, r_out.y), i, out);
}
