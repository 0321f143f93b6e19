// Photo-consistency carving: voxel colouring (Seitz & Dyer 1999) and space carving (Kutulakos & Seitz 2000).
// NumPy reference: nodes/carve/reference.py (same float32 operations in the same order, so the two give the
// same voxels; nodes/carve/carving.py drives both through the same steps).
//
// Grid: occ[(i * ny + j) * nz + k], bit 0 = occupied, bit 1 = protected (see carve_commit). Voxel centres are in local coordinates
// ((i, j, k) + 0.5) * vs; the cameras are packed for that origin (Cameras.pack(origin=bbox_min)).
// Views: one camera (camera.h layout), its centre, its gain and its pixel offset into the shared buffers:
//   images  uchar4 per pixel: r g b and the mask (> 127 = silhouette) in w
//   marks   uchar per pixel: 1 = occupied by a voxel already kept in this sweep (or background)
//   items   ulong per pixel: (depth bits << 32) | voxel index of the nearest surface voxel (item buffer)
//
// One step (a sweep plane, a voxel-colouring layer, or an item-buffer pass) is two launches over the step's
// voxels (a segment of a voxel list):
//   carve_test    surface voxels only: mean colour per view over the footprint pixels the voxel is seen
//                 in; views are the cameras behind the sweep plane (all cameras for layers and item
//                 passes); a voxel seen in >= min_views views whose colour deviation over the views exceeds
//                 thr + adaptive * (RMS spread of the pixels within a view) is stamped with the step number
//                 (a candidate; the adaptive threshold of Slabaugh et al. 2004);
//   carve_commit  a candidate is removed unless it is the last occupied voxel along its centre's ray in
//                 some view whose silhouette holds that centre (never carve through a silhouette); kept
//                 surface voxels then mark their footprints in the views of the step (sweeps and layers).
// Candidates of the same step never count as cover for each other, so the result does not depend on the
// order in which work items run. An item pass may be incremental: a voxel removed by an item pass gives back its
// pixels in the item buffers and flags its neighbours; carve_compact lists the flagged surface voxels, and the
// next pass splats and tests only those (a full pass, rebuilding the buffers, confirms convergence).
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL EXTENSION cl_khr_int64_extended_atomics : enable
#include "camera.h"

#define SAMPLES 8      // at most SAMPLES x SAMPLES pixels sampled per voxel and view (strided when larger)
#define PROTECTED 2     // occ bit 1: a silhouette needs this voxel (it is never tested again)
#define BACK_FACING -0.5f   // item buffers skip views more than 120 degrees from a voxel's normal
#define GUARD_OFFSET 0.4f  // the silhouette guard's rays pass the voxel centre and points this far off it (voxels)
#define SPACE_RGB 0
#define SPACE_LAB 1

inline float dot3(float3 a)
{
    return (a.x * a.x + a.y * a.y) + a.z * a.z;
}

inline float3 voxel_centre(int i, int j, int k, float4 vs)
{
    return (float3)(((float)i + 0.5f) * vs.x, ((float)j + 0.5f) * vs.y, ((float)k + 0.5f) * vs.z);
}

inline int occupied(__global const uchar* occ, int i, int j, int k, int nx, int ny, int nz)
{
    if (i < 0 || j < 0 || k < 0 || i >= nx || j >= ny || k >= nz) return 0;
    return occ[((size_t)i * ny + j) * nz + k] & 1;
}

// A surface voxel has an empty face neighbour (outside the grid counts as empty).
inline int surface(__global const uchar* occ, int i, int j, int k, int nx, int ny, int nz)
{
    return !(occupied(occ, i - 1, j, k, nx, ny, nz) && occupied(occ, i + 1, j, k, nx, ny, nz) &&
             occupied(occ, i, j - 1, k, nx, ny, nz) && occupied(occ, i, j + 1, k, nx, ny, nz) &&
             occupied(occ, i, j, k - 1, nx, ny, nz) && occupied(occ, i, j, k + 1, nx, ny, nz));
}

// Occupied and not a candidate of this step (candidates may be leaving while the commit runs).
inline int staying(__global const uchar* occ, __global const int* stamp, int step, int i, int j, int k, int nx,
                   int ny, int nz)
{
    if (i < 0 || j < 0 || k < 0 || i >= nx || j >= ny || k >= nz) return 0;
    size_t w = ((size_t)i * ny + j) * nz + k;
    return stamp[w] != step && (occ[w] & 1);
}

inline int surface_staying(__global const uchar* occ, __global const int* stamp, int step, int i, int j, int k,
                           int nx, int ny, int nz)
{
    return !(staying(occ, stamp, step, i - 1, j, k, nx, ny, nz) && staying(occ, stamp, step, i + 1, j, k, nx, ny, nz) &&
             staying(occ, stamp, step, i, j - 1, k, nx, ny, nz) && staying(occ, stamp, step, i, j + 1, k, nx, ny, nz) &&
             staying(occ, stamp, step, i, j, k - 1, nx, ny, nz) && staying(occ, stamp, step, i, j, k + 1, nx, ny, nz));
}

// Outward normal direction (not normalised) of a surface voxel: minus the sum of the offsets of its occupied
// 26-neighbours (integer valued, so exact in float).
inline float3 voxel_normal(__global const uchar* occ, int i, int j, int k, int nx, int ny, int nz)
{
    float3 g = (float3)(0.0f);
    for (int a = -1; a <= 1; a++)
        for (int b = -1; b <= 1; b++)
            for (int c = -1; c <= 1; c++)
                if (occupied(occ, i + a, j + b, k + c, nx, ny, nz)) g -= (float3)((float)a, (float)b, (float)c);
    return g;
}

// The view from centre C sees the voxel at X (normal direction g) within the grazing limit: the angle between
// g and C - X is at most acos(cos_min). A voxel without a normal direction (g = 0) passes.
inline int facing(float3 g, float3 X, float4 C, float cos_min)
{
    float3 d = C.xyz - X;
    float gg = dot3(g);
    if (gg == 0.0f) return 1;
    return (g.x * d.x + g.y * d.y) + g.z * d.z >= cos_min * sqrt(gg * dot3(d));
}

// Camera `c` takes part in a step: axis < 0 = every camera; else its centre lies behind the sweep plane
// (sign * (centre[axis] - plane) < 0: the side the sweep comes from).
inline int active(float4 centre, int axis, float plane, float sign)
{
    if (axis < 0) return 1;
    float x = axis == 0 ? centre.x : (axis == 1 ? centre.y : centre.z);
    return sign * (x - plane) < 0.0f;
}

// In a sweep, camera C tests the voxel at X only when the ray to X runs within the sweep cone: at most
// acos(cos_cone) from the sweep axis (rays crossing the voxel slab at a flatter angle see its neighbours in the
// same slab, which have not marked their pixels yet). Always true outside sweeps (axis < 0).
inline int in_cone(float4 C, float3 X, int axis, float sign, float cos_cone)
{
    if (axis < 0) return 1;
    float3 d = X - C.xyz;
    float along = sign * (axis == 0 ? d.x : (axis == 1 ? d.y : d.z));
    return along > 0.0f && along >= cos_cone * sqrt(dot3(d));
}

// Footprint of the voxel at X in a view: its cube projected through the local affine approximation of the
// camera, i.e. the hexagon {p + a e0 + b e1 + c e2 : |a|, |b|, |c| <= 1} spanned by the projected half-edges
// e0 e1 e2 (times `scale`) around the projected centre p. Pixels inside are those whose centre q satisfies
// |e_k x (q - p)| <= lim_k for k = 0, 1, 2 (x: 2-D cross product, lim_k = sum_j |e_k x e_j|); the
// rectangle r = (x0, x1, y0, y1) bounds it, clipped to the image. When no pixel centre lies inside the
// rectangle, the footprint is the pixel nearest to p (single). Returns 0 when a projected point is behind the
// camera or not finite.
typedef struct {
    float2 p, e0, e1, e2;
    float l0, l1, l2;
    int4 r;
    int single;
    float depth;
} footprint_t;

inline float cross2(float2 a, float2 b)
{
    return a.x * b.y - a.y * b.x;
}

inline int footprint(__global const float* cam, float3 X, float4 vs, float scale, footprint_t* f)
{
    float d0, d1, d2, d3;
    float2 p = project_point(cam, X, &d0);
    float2 px = project_point(cam, (float3)(X.x + 0.5f * vs.x, X.y, X.z), &d1);
    float2 py = project_point(cam, (float3)(X.x, X.y + 0.5f * vs.y, X.z), &d2);
    float2 pz = project_point(cam, (float3)(X.x, X.y, X.z + 0.5f * vs.z), &d3);
    if (!(d0 > 0.0f && d1 > 0.0f && d2 > 0.0f && d3 > 0.0f)) return 0;
    float2 e0 = scale * (px - p), e1 = scale * (py - p), e2 = scale * (pz - p);
    float hu = (fabs(e0.x) + fabs(e1.x)) + fabs(e2.x);
    float hv = (fabs(e0.y) + fabs(e1.y)) + fabs(e2.y);
    if (!(isfinite(hu) && isfinite(hv) && isfinite(p.x) && isfinite(p.y))) return 0;
    float W = cam[22], H = cam[23];
    float fx0 = ceil(p.x - hu), fx1 = floor(p.x + hu), fy0 = ceil(p.y - hv), fy1 = floor(p.y + hv);
    f->single = fx0 > fx1 || fy0 > fy1;
    if (f->single) {
        fx0 = fx1 = floor(p.x + 0.5f);
        fy0 = fy1 = floor(p.y + 0.5f);
    }
    fx0 = fmax(fx0, 0.0f); fy0 = fmax(fy0, 0.0f);
    fx1 = fmin(fx1, W - 1.0f); fy1 = fmin(fy1, H - 1.0f);
    f->r = (int4)((int)fmin(fx0, W), (int)fmax(fx1, -1.0f), (int)fmin(fy0, H), (int)fmax(fy1, -1.0f));
    f->p = p; f->e0 = e0; f->e1 = e1; f->e2 = e2;
    f->l0 = fabs(cross2(e0, e1)) + fabs(cross2(e0, e2));
    f->l1 = fabs(cross2(e1, e0)) + fabs(cross2(e1, e2));
    f->l2 = fabs(cross2(e2, e0)) + fabs(cross2(e2, e1));
    f->depth = d0;
    return 1;
}

inline int in_footprint(const footprint_t* f, int x, int y)
{
    if (f->single) return 1;
    float2 q = (float2)((float)x - f->p.x, (float)y - f->p.y);
    return fabs(cross2(f->e0, q)) <= f->l0 && fabs(cross2(f->e1, q)) <= f->l1 && fabs(cross2(f->e2, q)) <= f->l2;
}

inline float lab_f(float t)
{
    return t > 0.008856452f ? cbrt(t) : t / 0.12841855f + 0.13793103f;
}

inline float srgb_linear(float c)
{
    c = c / 255.0f;
    return c <= 0.04045f ? c / 12.92f : pow((c + 0.055f) / 1.055f, 2.4f);
}

// A mean colour (r g b, 0..255) in the colour space of the test: sRGB as is, or CIE L*a*b* (D65).
inline float3 colour_space(float3 rgb, int space)
{
    if (space == SPACE_RGB) return rgb;
    float r = srgb_linear(rgb.x), g = srgb_linear(rgb.y), b = srgb_linear(rgb.z);
    float X = ((0.4124564f * r + 0.3575761f * g) + 0.1804375f * b) / 0.95047f;
    float Y = (0.2126729f * r + 0.7151522f * g) + 0.0721750f * b;
    float Z = ((0.0193339f * r + 0.1191920f * g) + 0.9503041f * b) / 1.08883f;
    float fx = lab_f(X), fy = lab_f(Y), fz = lab_f(Z);
    return (float3)(116.0f * fy - 16.0f, 500.0f * (fx - fy), 200.0f * (fy - fz));
}

// Squared spread, in the colour space, of a view's pixels around their mean m (per-channel standard deviation
// sd): the sum over channels of |f(m + sd_a e_a) - f(m)|^2, first-order propagation (exact for rgb).
inline float spread(float3 m, float3 sd, float3 q, int space)
{
    if (space == SPACE_RGB) return dot3(sd);
    float3 a = colour_space((float3)(m.x + sd.x, m.y, m.z), space) - q;
    float3 b = colour_space((float3)(m.x, m.y + sd.y, m.z), space) - q;
    float3 c = colour_space((float3)(m.x, m.y, m.z + sd.z), space) - q;
    return (dot3(a) + dot3(b)) + dot3(c);
}

// Reset the marks of every view: background pixels are marked (never sampled), silhouette pixels free.
__kernel void carve_reset_marks(__global const uchar4* images, int npixels, __global uchar* marks)
{
    int p = get_global_id(0);
    if (p >= npixels) return;
    marks[p] = images[p].w > 127 ? 0 : 1;
}

// Item buffers: every surface voxel of the list writes (depth, index) into the pixels of its whole footprint
// in every view it does not clearly turn away from; the nearest wins (exact depth ties: the lower index).
__kernel void carve_splat(__global const uint* list, int first, int count, __global const uchar* occ, int nx, int ny,
                          int nz, float4 vs, __global const float* cams, __global const float4* centres, int nviews,
                          __global const int* pix_off,
                          __global const uchar4* images, __global ulong* items)
{
    int t = get_global_id(0);
    if (t >= count) return;
    uint v = list[first + t];
    if (!(occ[v] & 1)) return;
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    if (!surface(occ, i, j, k, nx, ny, nz)) return;
    float3 X = voxel_centre(i, j, k, vs);
    float3 g = voxel_normal(occ, i, j, k, nx, ny, nz);
    for (int c = 0; c < nviews; c++) {
        if (!facing(g, X, centres[c], BACK_FACING)) continue;   // clearly turned away: hidden anyway
        __global const float* cam = cams + CAM_FLOATS * c;
        footprint_t f;
        if (!footprint(cam, X, vs, 1.0f, &f)) continue;
        int W = (int)cam[22];
        ulong key = ((ulong)as_uint(f.depth) << 32) | (ulong)v;
        for (int y = f.r.z; y <= f.r.w; y++)
            for (int x = f.r.x; x <= f.r.y; x++) {
                int p = pix_off[c] + y * W + x;
                if (in_footprint(&f, x, y) && images[p].w > 127) atom_min(&items[p], key);
            }
    }
}

// The photo-consistency test of the surface voxels of one step. use_items: a pixel is seen when the item
// buffer holds this voxel; else when it is not marked. write_colors: instead of stamping candidates, write the
// mean colour (r g b, number of views) and the colour variance over views (-1 when seen in < 2 views) of each
// list entry (indexed by its position in the list).
__kernel void carve_test(__global const uint* list, int first, int count, int axis, float plane, float sign,
                         int use_items, __global const uchar* occ, __global int* stamp, int step, int nx, int ny,
                         int nz, float4 vs, __global const float* cams, __global const float4* centres,
                         __global const float4* gains, int nviews, __global const int* pix_off,
                         __global const uchar4* images, __global const uchar* marks, __global const ulong* items,
                         float scale, float cos_cone, float cos_min, int min_views, float thr, float adaptive, int space, int write_colors,
                         __global uchar4* colors, __global float* variance)
{
    int t = get_global_id(0);
    if (t >= count) return;
    uint v = list[first + t];
    if (!(occ[v] & 1) || ((occ[v] & PROTECTED) && !write_colors)) return;
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    if (!surface(occ, i, j, k, nx, ny, nz)) return;
    float3 X = voxel_centre(i, j, k, vs);
    float3 g = voxel_normal(occ, i, j, k, nx, ny, nz);
    float3 s1 = (float3)(0.0f), rgb = (float3)(0.0f);
    float s2 = 0.0f, w2 = 0.0f;
    int views = 0;
    for (int c = 0; c < nviews; c++) {
        if (!active(centres[c], axis, plane, sign) || !in_cone(centres[c], X, axis, sign, cos_cone) ||
            !facing(g, X, centres[c], cos_min))
            continue;
        __global const float* cam = cams + CAM_FLOATS * c;
        footprint_t f;
        if (!footprint(cam, X, vs, scale, &f)) continue;
        int4 r = f.r;
        int W = (int)cam[22];
        int stride = max(1, (max(r.y - r.x + 1, r.w - r.z + 1) + SAMPLES - 1) / SAMPLES);
        float3 sum = (float3)(0.0f), sq = (float3)(0.0f);
        int n = 0, total = 0;
        for (int y = r.z; y <= r.w; y += stride)
            for (int x = r.x; x <= r.y; x += stride) {
                int p = pix_off[c] + y * W + x;
                uchar4 px = images[p];
                if (px.w <= 127 || !in_footprint(&f, x, y)) continue;
                total++;
                if (use_items ? (uint)(items[p] & 0xFFFFFFFFUL) != v : marks[p] != 0) continue;
                float3 f = (float3)((float)px.x, (float)px.y, (float)px.z);
                sum += f;
                sq += f * f;
                n++;
            }
        if (n == 0 || 2 * n < total) continue;     // seen: at least half of the sampled silhouette pixels
        float3 m = sum / (float)n;
        float3 sd = sqrt(fmax(sq / (float)n - m * m, (float3)(0.0f)));
        m = m * gains[c].xyz;
        sd = sd * gains[c].xyz;
        rgb += m;
        float3 q = colour_space(m, space);
        s1 += q;
        s2 += dot3(q);
        w2 += spread(m, sd, q, space);
        views++;
    }
    float var = -1.0f;
    float limit = 0.0f;
    if (views >= 2) {
        float3 mean = s1 / (float)views;
        var = s2 / (float)views - dot3(mean);
        limit = thr + adaptive * sqrt(w2 / (float)views);
    }
    if (write_colors) {
        float3 c = views ? rgb / (float)views : (float3)(0.0f);
        colors[first + t] = (uchar4)(convert_uchar3_sat_rte(c), (uchar)min(views, 255));
        variance[first + t] = var;
    } else if (views >= min_views && views >= 2 && var > limit * limit) {
        stamp[v] = step;
    }
}

// The flagged voxels of the list that are occupied surface voxels, appended to `out` (in no particular order:
// what follows does not depend on it); flags cleared.
__kernel void carve_compact(__global const uint* list, int count, __global const uchar* occ, __global uchar* fresh,
                            int nx, int ny, int nz, __global uint* out, __global int* counter)
{
    int t = get_global_id(0);
    if (t >= count) return;
    uint v = list[t];
    if (!fresh[v]) return;
    fresh[v] = 0;
    if (!(occ[v] & 1)) return;
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    if (surface(occ, i, j, k, nx, ny, nz)) out[atomic_inc(counter)] = v;
}

// Whether removing voxel (i, j, k) would leave a viewing ray without an occupied voxel while that view's
// silhouette holds the ray's pixel: the rays through the centre and through the six points GUARD_OFFSET of a
// voxel from it along the axes (so rim voxels whose outer part alone covers the silhouette's edge stay). A ray
// is walked both ways from its point in steps of half a voxel along its major axis until it leaves the grid.
inline int ray_needs(__global const uchar* occ, __global const int* stamp, int step, int i, int j, int k, int nx,
                     int ny, int nz, float4 vs, float3 X, __global const float* cam, float4 C, int pix_off,
                     __global const uchar4* images, int limit)
{
    float depth;
    float2 p = project_point(cam, X, &depth);
    float fu = p.x + 0.5f, fv = p.y + 0.5f;
    if (!(depth > 0.0f && fu >= 0.0f && fu < cam[22] && fv >= 0.0f && fv < cam[23])) return 0;
    if (images[pix_off + (int)fv * (int)cam[22] + (int)fu].w <= 127) return 0;   // the vote's "inside" test
    float3 d = X - C.xyz;
    float dt = (0.5f * fmin(fmin(vs.x, vs.y), vs.z)) / fmax(fmax(fabs(d.x), fabs(d.y)), fabs(d.z));
    if (!isfinite(dt)) return 0;
    for (int dir = 1; dir >= -1; dir -= 2) {   // away from the camera first
        for (int n = 1; n <= limit; n++) {
            float tn = (float)(dir * n) * dt;
            float3 P = X + tn * d;
            int a = (int)floor(P.x / vs.x), b = (int)floor(P.y / vs.y), e = (int)floor(P.z / vs.z);
            if (a < 0 || b < 0 || e < 0 || a >= nx || b >= ny || e >= nz) break;
            if (a == i && b == j && e == k) continue;
            if (staying(occ, stamp, step, a, b, e, nx, ny, nz)) return 0;
        }
    }
    return 1;
}

inline int last_on_a_ray(__global const uchar* occ, __global const int* stamp, int step, int i, int j, int k, int nx,
                         int ny, int nz, float4 vs, float3 X, __global const float* cams, __global const float4* centres,
                         int nviews, __global const int* pix_off, __global const uchar4* images)
{
    int limit = 2 * (nx + ny + nz) + 4;
    for (int c = 0; c < nviews; c++) {
        __global const float* cam = cams + CAM_FLOATS * c;
        for (int q = 0; q < 7; q++) {
            float3 P = X;
            float o = (q & 1) ? -GUARD_OFFSET : GUARD_OFFSET;
            if (q == 1 || q == 2) P.x = X.x + o * vs.x;
            if (q == 3 || q == 4) P.y = X.y + o * vs.y;
            if (q == 5 || q == 6) P.z = X.z + o * vs.z;
            if (ray_needs(occ, stamp, step, i, j, k, nx, ny, nz, vs, P, cam, centres[c], pix_off[c], images, limit))
                return 1;
        }
    }
    return 0;
}

// Remove the candidates of this step that no silhouette needs; with do_marks, kept surface voxels (candidates
// of this step count as empty neighbours) mark their whole footprint in the views of the step.
__kernel void carve_commit(__global const uint* list, int first, int count, int axis, float plane, float sign,
                           int do_marks, __global uchar* occ, __global const int* stamp, int step, int nx, int ny,
                           int nz, float4 vs, __global const float* cams, __global const float4* centres, int nviews,
                           __global const int* pix_off, __global const uchar4* images, __global uchar* marks,
                           __global int* removed, __global ulong* items, __global uchar* fresh)
{
    int t = get_global_id(0);
    if (t >= count) return;
    uint v = list[first + t];
    if (!(occ[v] & 1)) return;
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    float3 X = voxel_centre(i, j, k, vs);
    if (stamp[v] == step) {
        if (last_on_a_ray(occ, stamp, step, i, j, k, nx, ny, nz, vs, X, cams, centres, nviews, pix_off, images)) {
            occ[v] = 1 | PROTECTED;     // removing voxels never uncovers a ray: protected for good
        } else {
            occ[v] = 0;
            atomic_inc(removed);
            if (axis < 0 && !do_marks) {
                // item pass: give back the pixels this voxel held in the item buffers, and flag its neighbours
                // (now possibly surface) for the next incremental pass
                for (int c = 0; c < nviews; c++) {
                    __global const float* cam = cams + CAM_FLOATS * c;
                    footprint_t f;
                    if (!footprint(cam, X, vs, 1.0f, &f)) continue;
                    int W = (int)cam[22];
                    for (int y = f.r.z; y <= f.r.w; y++)
                        for (int x = f.r.x; x <= f.r.y; x++) {
                            int p = pix_off[c] + y * W + x;
                            if ((uint)(items[p] & 0xFFFFFFFFUL) == v) items[p] = 0xFFFFFFFFFFFFFFFFUL;
                        }
                }
                for (int a = max(i - 1, 0); a <= min(i + 1, nx - 1); a++)
                    for (int b = max(j - 1, 0); b <= min(j + 1, ny - 1); b++)
                        for (int e = max(k - 1, 0); e <= min(k + 1, nz - 1); e++) fresh[((size_t)a * ny + b) * nz + e] = 1;
            }
            return;
        }
    }
    if (!do_marks || !surface_staying(occ, stamp, step, i, j, k, nx, ny, nz)) return;
    for (int c = 0; c < nviews; c++) {
        if (!active(centres[c], axis, plane, sign)) continue;
        __global const float* cam = cams + CAM_FLOATS * c;
        footprint_t f;
        if (!footprint(cam, X, vs, 1.0f, &f)) continue;
        int W = (int)cam[22];
        for (int y = f.r.z; y <= f.r.w; y++)
            for (int x = f.r.x; x <= f.r.y; x++)
                if (in_footprint(&f, x, y)) marks[pix_off[c] + y * W + x] = 1;
    }
}
