// Visual hull: dense centre test and sparse coarse-to-fine classification (Loop, Zhang & Zhang, HPG 2013).
//
// Silhouettes (silhouette.h: bits + 8x8 block tables, nodes.common.silhouettes.SilhouetteBits) are prepared once
// per frame from masks (silhouette.cl) or straight from the images by a key (key.cl:chroma_key_bits).
// The centre test and the vote are silhouette.h's; the coarse test reads the block table over the blocks
// covering a cell's projected footprint, which is conservative: a cell is only called inside/outside when that
// is certain. Camera layout and projection: kernels/camera.h (Cameras.pack(), 32 floats per camera).
// Arithmetic order here is mirrored by nodes/hull/hull.py:hull_reference so both give identical voxels.
#pragma OPENCL FP_CONTRACT OFF
#include "silhouette.h"

// what one view says about a whole box of voxel centres (flags; 0 = unsure)
#define BOX_IN 1      // every centre projects inside the silhouette
#define BOX_NOTIN 2   // no centre is inside
#define BOX_OUT 4     // every centre is seen on background
#define BOX_OFF 8     // every centre is unseen (behind the camera or outside the image)
#define BOX_SEEN 16   // every centre is seen (in front, inside the image)

// ------------------------------------------------------------------ projection
inline float3 voxel_centre(float3 bmin, float3 vs, int i, int j, int k)
{
    return (float3)(bmin.x + ((float)i + 0.5f) * vs.x, bmin.y + ((float)j + 0.5f) * vs.y, bmin.z + ((float)k + 0.5f) * vs.z);
}

// The vote of silhouette.h, and at least min_seen views see X (in front, inside the image): hull_reference's
// vote(..., min_seen). An early stop of the loop (vote_decided) is a carved voxel either way.
inline int voxel_test(__global const float* cams, __global const uchar* bits, __global const int* bit_off,
                      int nviews, int min_views, int policy, int min_seen, float3 X)
{
    int n_in = 0, n_bg = 0;
    for (int v = 0; v < nviews; v++) {
        int s = centre_state(cams + v * CAM_FLOATS, bits + bit_off[v], X);
        n_in += (s == SIL_IN);
        n_bg += (s == SIL_BACKGROUND);
        if (vote_decided(s, n_in, v, nviews, min_views, policy)) break;
    }
    return hull_vote(n_in, n_bg, nviews, min_views, policy) && n_in + n_bg >= min_seen;
}

__kernel void hull_dense(__global const float* cams, int nviews, __global const uchar* bits,
                         __global const int* bit_off, float4 bmin, float4 vs, int nx, int ny, int nz,
                         int min_views, int policy, int min_seen, __global uchar* vol)
{
    int k = get_global_id(0), j = get_global_id(1), i = get_global_id(2);
    if (k >= nz || j >= ny || i >= nx) return;
    float3 X = voxel_centre(bmin.xyz, vs.xyz, i, j, k);
    vol[((size_t)i * ny + j) * nz + k] = (uchar)voxel_test(cams, bits, bit_off, nviews, min_views, policy, min_seen, X);
}

// ------------------------------------------------------------------ conservative footprint test
inline float2 imul(float2 a, float2 b)
{
    float p = a.x * b.x, q = a.x * b.y, r = a.y * b.x, s = a.y * b.y;
    return (float2)(fmin(fmin(p, q), fmin(r, s)), fmax(fmax(p, q), fmax(r, s)));
}
inline float2 iscale(float c, float2 a) { return c >= 0.0f ? (float2)(c * a.x, c * a.y) : (float2)(c * a.y, c * a.x); }
inline float2 isq(float2 a)
{
    float lo = fmin(fabs(a.x), fabs(a.y)), hi = fmax(fabs(a.x), fabs(a.y));
    if (a.x <= 0.0f && a.y >= 0.0f) lo = 0.0f;
    return (float2)(lo * lo, hi * hi);
}
inline float2 widen(float2 a, float abs_pad, float rel_pad)
{
    float m = fmax(fabs(a.x), fabs(a.y));
    return (float2)(a.x - (abs_pad + rel_pad * m), a.y + (abs_pad + rel_pad * m));
}

// Flags (BOX_IN / BOX_NOTIN / BOX_OUT / BOX_OFF, or 0 when unsure) holding for every voxel centre of the box whose extreme
// voxel centres are lo and hi, in one view. The centres' projections lie in the convex hull of the 8 corner
// projections (pinhole part), distortion is bounded by interval arithmetic, and the pixel rectangle is
// widened a little so float rounding can never make the test claim something false.
__attribute__((always_inline)) inline int box_state(__global const float* c, __global const int* sat, float3 lo, float3 hi)
{
    float2 xr = (float2)(INFINITY, -INFINITY), yr = xr;
    int front = 0, behind = 0;
    for (int n = 0; n < 8; n++) {
        float3 X = (float3)((n & 1) ? hi.x : lo.x, (n & 2) ? hi.y : lo.y, (n & 4) ? hi.z : lo.z);
        float3 xc = camera_point(c, X);
        float z = xc.z * c[24];
        front += z > 0.0f;
        behind += z < 0.0f;
        float x = xc.x / xc.z, y = xc.y / xc.z;
        xr = (float2)(fmin(xr.x, x), fmax(xr.y, x));
        yr = (float2)(fmin(yr.x, y), fmax(yr.y, y));
    }
    if (behind == 8) return BOX_NOTIN | BOX_OFF;
    if (front != 8) return 0;
    xr = widen(xr, 1e-7f, 1e-5f);
    yr = widen(yr, 1e-7f, 1e-5f);
    if (has_distortion(c)) {
        float k1 = c[17], k2 = c[18], p1 = c[19], p2 = c[20], k3 = c[21];
        float2 r2 = isq(xr) + isq(yr);
        float2 poly = iscale(k2, (float2)(1.0f, 1.0f)) + imul(r2, iscale(k3, (float2)(1.0f, 1.0f)));
        poly = iscale(k1, (float2)(1.0f, 1.0f)) + imul(r2, poly);
        float2 radial = (float2)(1.0f, 1.0f) + imul(r2, poly);
        float2 xy = imul(xr, yr);
        float2 xd = imul(xr, radial) + iscale(2.0f * p1, xy) + iscale(p2, r2 + iscale(2.0f, isq(xr)));
        float2 yd = imul(yr, radial) + iscale(p1, r2 + iscale(2.0f, isq(yr))) + iscale(2.0f * p2, xy);
        xr = widen(xd, 1e-7f, 1e-5f);
        yr = widen(yd, 1e-7f, 1e-5f);
    }
    float2 ur = widen(iscale(c[12], xr) + iscale(c[13], yr) + (float2)(c[14], c[14]), 0.01f, 1e-5f) + 0.5f;
    float2 vr = widen(iscale(c[15], yr) + (float2)(c[16], c[16]), 0.01f, 1e-5f) + 0.5f;
    float W = c[22], H = c[23];
    if (!(isfinite(ur.x) && isfinite(ur.y) && isfinite(vr.x) && isfinite(vr.y))) return 0;
    if (ur.y < 0.0f || ur.x >= W || vr.y < 0.0f || vr.x >= H) return BOX_NOTIN | BOX_OFF;
    int inside_image = ur.x >= 0.0f && ur.y < W && vr.x >= 0.0f && vr.y < H;
    int x0 = (int)fmax(ur.x, 0.0f), x1 = (int)fmin(ur.y, W - 1.0f);
    int y0 = (int)fmax(vr.x, 0.0f), y1 = (int)fmin(vr.y, H - 1.0f);
    int Wi = (int)W, Hi = (int)H, Wb = (Wi + 7) >> 3;
    int bx0 = x0 >> 3, bx1 = x1 >> 3, by0 = y0 >> 3, by1 = y1 >> 3;
    int sum = sat[(by1 + 1) * (Wb + 1) + bx1 + 1] - sat[by0 * (Wb + 1) + bx1 + 1]
            - sat[(by1 + 1) * (Wb + 1) + bx0] + sat[by0 * (Wb + 1) + bx0];
    if (sum == 0) return inside_image ? (BOX_NOTIN | BOX_OUT | BOX_SEEN) : BOX_NOTIN;
    int area = (min((bx1 + 1) << 3, Wi) - (bx0 << 3)) * (min((by1 + 1) << 3, Hi) - (by0 << 3));
    if (!inside_image) return 0;
    return sum == area ? (BOX_IN | BOX_SEEN) : BOX_SEEN;
}

// Cells of 2^level voxels, coded i | j << 10 | k << 20. Each cell is inside (filled), outside (left
// empty) or mixed: mixed cells of level > 1 append their children to `next` (stream compaction through an
// atomic counter); cells of level 1 decide their 8 voxels with the centre test right here.
__kernel void hull_cells(__global const float* cams, int nviews, __global const uchar* bits,
                         __global const int* bit_off, __global const int* sat, __global const int* sat_off,
                         float4 bmin, float4 vs, int nx, int ny, int nz, int min_views, int policy,
                         int min_seen, int level, __global const uint* cells, int ncells, __global uint* next,
                         volatile __global int* counter, __global uchar* vol)
{
    int gid = get_global_id(0);
    if (gid >= ncells) return;
    uint code = cells[gid];
    int ci = code & 1023, cj = (code >> 10) & 1023, ck = code >> 20;
    int size = 1 << level;
    int i0 = ci << level, j0 = cj << level, k0 = ck << level;
    int i1 = min(i0 + size, nx) - 1, j1 = min(j0 + size, ny) - 1, k1 = min(k0 + size, nz) - 1;
    float3 lo = voxel_centre(bmin.xyz, vs.xyz, i0, j0, k0), hi = voxel_centre(bmin.xyz, vs.xyz, i1, j1, k1);

    int n_in = 0, n_notin = 0, n_out = 0, n_off = 0, n_seen = 0, inside = 0, outside = 0;
    int tol = min_views > 0 ? nviews - min_views : 0;  // background votes tolerated (silhouette.h hull_vote)
    // at level 1 the box corners are the 8 voxel centres themselves: test those directly
    for (int v = 0; v < nviews && level > 1; v++) {
        int s = box_state(cams + v * CAM_FLOATS, sat + sat_off[v], lo, hi);
        n_in += (s & BOX_IN) != 0;
        n_notin += (s & BOX_NOTIN) != 0;
        n_out += (s & BOX_OUT) != 0;
        n_off += (s & BOX_OFF) != 0;
        n_seen += (s & BOX_SEEN) != 0;
        // bounds on every voxel's votes, views not yet asked counted either way: IN <= in_max,
        // BACKGROUND in [n_out, out_max], some view unseen for sure when n_off > 0, and the views that see
        // it in [n_seen, nviews - n_off] (min_seen)
        int in_max = nviews - n_notin, out_max = nviews - n_in - n_off;
        if (policy == 0) {
            inside = n_seen == nviews && n_in >= nviews - tol;
            outside = n_off > 0 || n_out > tol || in_max < nviews - tol;
        } else {
            inside = out_max <= tol && n_in > 0 && n_seen >= min_seen;
            outside = n_out > tol || in_max == 0 || nviews - n_off < min_seen;
        }
        if (inside || outside) break;
    }
    if (outside) return;
    if (inside) {
        for (int i = i0; i <= i1; i++)
            for (int j = j0; j <= j1; j++)
                for (int k = k0; k <= k1; k++) vol[((size_t)i * ny + j) * nz + k] = 1;
        return;
    }
    if (level == 1) {
        for (int i = i0; i <= i1; i++)
            for (int j = j0; j <= j1; j++)
                for (int k = k0; k <= k1; k++) {
                    float3 X = voxel_centre(bmin.xyz, vs.xyz, i, j, k);
                    vol[((size_t)i * ny + j) * nz + k] = (uchar)voxel_test(cams, bits, bit_off, nviews, min_views, policy,
                                                                           min_seen, X);
                }
        return;
    }
    int hs = size >> 1;
    int ni = 1 + (i0 + hs <= i1), nj = 1 + (j0 + hs <= j1), nk = 1 + (k0 + hs <= k1);
    int at = atomic_add(counter, ni * nj * nk);
    for (int a = 0; a < ni; a++)
        for (int b = 0; b < nj; b++)
            for (int d = 0; d < nk; d++)
                next[at++] = (uint)(2 * ci + a) | ((uint)(2 * cj + b) << 10) | ((uint)(2 * ck + d) << 20);
}
