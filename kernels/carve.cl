// Photo-consistency carving: voxel colouring (Seitz & Dyer 1999) and space carving (Kutulakos & Seitz 2000),
// with exact visibility from item buffers (Culbertson et al. 1999) and a strict silhouette guard.
// NumPy reference: nodes/carve/reference.py (same float32 operations in the same order, so the two give the
// same voxels; nodes/carve/carving.py drives both through the same steps).
//
// Grid: occ[(i * ny + j) * nz + k], bit 0 = occupied, bit 1 = protected (a candidate the guard kept: never tested
// again). Voxel centres are in local coordinates ((i, j, k) + 0.5) * vs; the cameras are packed for that origin.
// Silhouettes: kernels/silhouette.h's bits (nodes.common.silhouettes.SilhouetteBits), per view at bit_off[c].
// Pixel buffers cover a window per view (win[c] = x0, y0, width, height: the silhouette's bounding box; no
// mask pixel lies outside it), pixel (x, y) of view c at pix_off[c] + (y - y0) * width + (x - x0):
//   images  uchar4: r g b -
//   marks   uchar: 1 = occupied by a voxel already kept in this sweep / layer (one buffer per sweep)
//   items   ulong: (depth bits << 32) | voxel index of the nearest surface voxel (item buffer)
//   cover   int: how many counted voxels cover the pixel (their cube's inner outline holds its centre)
//   keeper  uint: the nearest depth (float bits) of the candidates covering the pixel in a guard step (else ~0)
//
// The photo-consistency test (photo): a surface voxel's mean colour per view over the footprint pixels it is
// seen in, in the views that take part (in a sweep: cameras behind the plane and within the cone; facing the
// voxel within max_angle); inconsistent when seen in >= min_views views and the colour deviation over the views
// exceeds thr + adaptive * (RMS spread of the pixels within a view) and, when contrast > 0, the views' colours
// differ by more than `contrast` times what their own texture explains (see carve_params).
//
// The silhouette guard (strict): a voxel is never removed when that would leave a silhouette pixel of any view
// that some voxel covered (its centre inside the projected cube) without a voxel covering it. Per pixel `cover`
// counts the surface voxels whose cube covers it for sure (the projected cube's outline eroded by its error
// bound); a step's candidates take themselves out of the count and bid for the pixels they cover (keeper =
// nearest depth); a candidate stays (and is protected for good) when a silhouette pixel its cube may cover (the
// outline dilated by the bound) is left with cover 0 and it is that pixel's keeper or the pixel has none.
// Before deciding, the candidates' face neighbours that stay join the count (they will be surface voxels). Every
// decision reads counts no other decision of the step changes, so the result does not depend on the order in
// which work items run.
//
// Steps (kernels): a space-carving round sweeps +x -x +y -y +z -z, plane by plane: carve_sweep_test, the
// guard's kernels, carve_sweep_mark. An item pass: carve_compact lists the surface voxels, carve_splat writes
// the item buffers, carve_test tests them, carve_expose, carve_decide and carve_apply carry out the guard. Voxel
// colouring: per layer carve_test (marks), the guard's three, carve_mark.
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL EXTENSION cl_khr_int64_extended_atomics : enable
#include "silhouette.h"

#define SAMPLES 8             // at most SAMPLES x SAMPLES pixels sampled per voxel and view (strided when larger)
#define PROTECTED 2           // occ bit 1: the guard kept this candidate (it is never tested again)
#define BACK_FACING -0.5f     // item buffers skip views more than 120 degrees from a voxel's normal
#define COVER_EPS 0.01f       // pixels: added to the outline's error bound (rounding, other rasterizers)
#define NO_KEEPER 0xFFFFFFFFu
#define EMPTY_ITEM 0xFFFFFFFFFFFFFFFFUL
#define ST_CAND 1             // stamp[v] = (step << 2) | state
#define ST_KEEP 2
#define ST_GO 3
#define SPACE_RGB 0
#define SPACE_LAB 1

#define VIEW_ARGS __global const float* cams, __global const float4* centres, __global const int4* win, \
    __global const int* pix_off, __global const uchar* bits, __global const int* bit_off, int nviews
#define VIEW_PASS cams, centres, win, pix_off, bits, bit_off, nviews
#define GRID_ARGS int nx, int ny, int nz, float4 vs
// voxels flagged for the next incremental pass: a bit per voxel and the list of the flagged ones
#define FRESH_ARGS __global uint* fresh, __global uint* flist, __global int* nflist
#define FRESH_PASS fresh, flist, nflist
#define GRID_PASS nx, ny, nz, vs
// the photo-consistency parameters: footprint scale, cos(cone), cos(max_angle), min_views, threshold,
// adaptive, colour space, contrast
#define TEST_ARGS __global const float4* gains, __global const uchar4* images, float scale, float cos_cone, \
    float cos_min, int min_views, float thr, float adaptive, int space, float contrast
#define TEST_PASS gains, images, scale, cos_cone, cos_min, min_views, thr, adaptive, space, contrast

inline float dot3(float3 a)
{
    return (a.x * a.x + a.y * a.y) + a.z * a.z;
}

inline float3 voxel_centre(int i, int j, int k, float4 vs)
{
    return (float3)(((float)i + 0.5f) * vs.x, ((float)j + 0.5f) * vs.y, ((float)k + 0.5f) * vs.z);
}

inline int inside_grid(int i, int j, int k, int nx, int ny, int nz)
{
    return i >= 0 && j >= 0 && k >= 0 && i < nx && j < ny && k < nz;
}

inline int occupied(__global const uchar* occ, int i, int j, int k, int nx, int ny, int nz)
{
    if (!inside_grid(i, j, k, nx, ny, nz)) return 0;
    return occ[((size_t)i * ny + j) * nz + k] & 1;
}

// A surface voxel has an empty face neighbour (outside the grid counts as empty).
inline int surface(__global const uchar* occ, int i, int j, int k, int nx, int ny, int nz)
{
    return !(occupied(occ, i - 1, j, k, nx, ny, nz) && occupied(occ, i + 1, j, k, nx, ny, nz) &&
             occupied(occ, i, j - 1, k, nx, ny, nz) && occupied(occ, i, j + 1, k, nx, ny, nz) &&
             occupied(occ, i, j, k - 1, nx, ny, nz) && occupied(occ, i, j, k + 1, nx, ny, nz));
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

inline float cross2(float2 a, float2 b)
{
    return a.x * b.y - a.y * b.x;
}

// The pixel loops of view c (after `cam` and `w`): its silhouette (silhouette.h) and the offset of its window in
// the pixel buffers.
#define VIEW_ROWS(c) \
    __global const uchar* mrow = bits + bit_off[c]; \
    int mwidth = (int)cam[22]; \
    int pbase = pix_off[c] - w.y * w.z - w.x
#define MASK(x, y) silhouette_bit(mrow, mwidth, x, y)
#define PIX(x, y) (pbase + (y) * w.z + (x))

// ---------------------------------------------------------------- footprints
// Pixel of a point given in camera coordinates xc (camera.h's projection after camera_point); writes its depth.
inline float2 project_camera(__global const float* cam, float3 xc, float* depth)
{
    *depth = xc.z * cam[24];
    return pixel_point(cam, distort_point(cam, xc.xy / xc.z));
}

// Half an edge of the voxel along axis a (0, 1, 2) in camera coordinates: R[:, a] * vs[a] / 2.
inline float3 half_edge(__global const float* cam, int a, float4 vs)
{
    float h = 0.5f * (a == 0 ? vs.x : (a == 1 ? vs.y : vs.z));
    return (float3)(cam[a] * h, cam[4 + a] * h, cam[8 + a] * h);
}

// Footprint of the voxel at X in a view (photo test, item buffers, marks): its cube projected through the local
// affine approximation of the camera, i.e. the hexagon {p + a e0 + b e1 + c e2 : |a|, |b|, |c| <= 1} spanned by
// the projected half-edges e0 e1 e2 (times `scale`) around the projected centre p. Pixels inside are those whose
// centre q satisfies |e_k x (q - p)| <= lim_k for k = 0, 1, 2 (x: 2-D cross product, lim_k = sum_j |e_k x e_j|);
// the rectangle r = (x0, x1, y0, y1) bounds it, clipped to the view's window. When no pixel centre lies inside
// the rectangle, the footprint is the pixel nearest to p (single). Returns 0 when a projected point is behind
// the camera or not finite.
typedef struct {
    float2 p, e0, e1, e2;
    float l0, l1, l2;
    int4 r;
    int single;
    float depth;
} footprint_t;

inline int footprint(__global const float* cam, int4 w, float3 X, float4 vs, float scale, footprint_t* f)
{
    float d0, d1, d2, d3;
    float3 xc = camera_point(cam, X);
    float2 p = project_camera(cam, xc, &d0);
    float2 px = project_camera(cam, xc + half_edge(cam, 0, vs), &d1);
    float2 py = project_camera(cam, xc + half_edge(cam, 1, vs), &d2);
    float2 pz = project_camera(cam, xc + half_edge(cam, 2, vs), &d3);
    if (!(d0 > 0.0f && d1 > 0.0f && d2 > 0.0f && d3 > 0.0f)) return 0;
    float2 e0 = scale * (px - p), e1 = scale * (py - p), e2 = scale * (pz - p);
    float hu = (fabs(e0.x) + fabs(e1.x)) + fabs(e2.x);
    float hv = (fabs(e0.y) + fabs(e1.y)) + fabs(e2.y);
    if (!(isfinite(hu) && isfinite(hv) && isfinite(p.x) && isfinite(p.y))) return 0;
    float fx0 = ceil(p.x - hu), fx1 = floor(p.x + hu), fy0 = ceil(p.y - hv), fy1 = floor(p.y + hv);
    f->single = fx0 > fx1 || fy0 > fy1;
    if (f->single) {
        fx0 = fx1 = floor(p.x + 0.5f);
        fy0 = fy1 = floor(p.y + 0.5f);
    }
    float wx0 = (float)w.x, wy0 = (float)w.y, wx1 = (float)(w.x + w.z - 1), wy1 = (float)(w.y + w.w - 1);
    fx0 = fmax(fx0, wx0); fy0 = fmax(fy0, wy0);
    fx1 = fmin(fx1, wx1); fy1 = fmin(fy1, wy1);
    f->r = (int4)((int)fmin(fx0, wx1 + 1.0f), (int)fmax(fx1, wx0 - 1.0f), (int)fmin(fy0, wy1 + 1.0f),
                  (int)fmax(fy1, wy0 - 1.0f));
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

// The silhouette guard's outline of the voxel's cube in a view, with an error bound. The eight corners are
// projected exactly (camera.h, lens distortion included; their camera coordinates from the centre's and the
// half edges); the hexagon Z = {c + a e0 + b e1 + d e2 : |a|, |b|,
// |d| <= 1} is their affine fit (c their mean, e_k half the mean edge along axis k), and delta the largest
// distance of a projected corner from its corner of Z. The true outline (the convex hull of the projected
// corners) then contains Z eroded by delta and lies inside Z dilated by delta. With d = delta + COVER_EPS:
//   inner (covers for sure)  |e_k x q| <= lim_k - d |e_k|   for k = 0, 1, 2
//   outer (may cover)        |e_k x q| <= lim_k + d |e_k|
// (q = pixel centre - c). The rectangle r bounds the projected corners grown by COVER_EPS, clipped to the
// window. Returns 0 when a corner (or the centre) is behind the camera or not finite.
typedef struct {
    float2 c, e0, e1, e2;
    float l0, l1, l2, m0, m1, m2;   // lim_k and d |e_k|
    int4 r;
    uint key;                        // the guard's bid: the bits of the voxel centre's depth (> 0)
} outline_t;

inline int cube_outline(__global const float* cam, int4 w, float3 X, float4 vs, outline_t* o)
{
    float2 P[8];
    float3 xc = camera_point(cam, X);
    float3 hx = half_edge(cam, 0, vs), hy = half_edge(cam, 1, vs), hz = half_edge(cam, 2, vs);
    for (int s = 0; s < 8; s++) {
        float d;
        float3 Y = (((s & 1) ? xc + hx : xc - hx) + ((s & 2) ? hy : -hy)) + ((s & 4) ? hz : -hz);
        P[s] = project_camera(cam, Y, &d);
        if (!(d > 0.0f && isfinite(P[s].x) && isfinite(P[s].y))) return 0;
    }
    float2 c = (((((((P[0] + P[1]) + P[2]) + P[3]) + P[4]) + P[5]) + P[6]) + P[7]) * 0.125f;
    float2 e0 = (((P[1] - P[0]) + (P[3] - P[2])) + ((P[5] - P[4]) + (P[7] - P[6]))) * 0.125f;
    float2 e1 = (((P[2] - P[0]) + (P[3] - P[1])) + ((P[6] - P[4]) + (P[7] - P[5]))) * 0.125f;
    float2 e2 = (((P[4] - P[0]) + (P[5] - P[1])) + ((P[6] - P[2]) + (P[7] - P[3]))) * 0.125f;
    float dd = 0.0f;
    float2 lo = P[0], hi = P[0];
    for (int s = 0; s < 8; s++) {
        float2 m = (((s & 1) ? c + e0 : c - e0) + ((s & 2) ? e1 : -e1)) + ((s & 4) ? e2 : -e2);
        float2 q = P[s] - m;
        dd = fmax(dd, q.x * q.x + q.y * q.y);
        lo = fmin(lo, P[s]);
        hi = fmax(hi, P[s]);
    }
    float d = sqrt(dd) + COVER_EPS;
    float depth = xc.z * cam[24];
    if (!(depth > 0.0f)) return 0;
    o->key = as_uint(depth);
    o->c = c; o->e0 = e0; o->e1 = e1; o->e2 = e2;
    o->l0 = fabs(cross2(e0, e1)) + fabs(cross2(e0, e2));
    o->l1 = fabs(cross2(e1, e0)) + fabs(cross2(e1, e2));
    o->l2 = fabs(cross2(e2, e0)) + fabs(cross2(e2, e1));
    o->m0 = d * sqrt(e0.x * e0.x + e0.y * e0.y);
    o->m1 = d * sqrt(e1.x * e1.x + e1.y * e1.y);
    o->m2 = d * sqrt(e2.x * e2.x + e2.y * e2.y);
    float wx0 = (float)w.x, wy0 = (float)w.y, wx1 = (float)(w.x + w.z - 1), wy1 = (float)(w.y + w.w - 1);
    float x0 = fmax(ceil(lo.x - COVER_EPS), wx0), x1 = fmin(floor(hi.x + COVER_EPS), wx1);
    float y0 = fmax(ceil(lo.y - COVER_EPS), wy0), y1 = fmin(floor(hi.y + COVER_EPS), wy1);
    o->r = (int4)((int)fmin(x0, wx1 + 1.0f), (int)fmax(x1, wx0 - 1.0f), (int)fmin(y0, wy1 + 1.0f),
                  (int)fmax(y1, wy0 - 1.0f));
    return 1;
}

// outer = 1: the dilated outline (may cover); 0: the eroded one (covers for sure).
inline int in_outline(const outline_t* o, int x, int y, int outer)
{
    float2 q = (float2)((float)x - o->c.x, (float)y - o->c.y);
    float a = fabs(cross2(o->e0, q)), b = fabs(cross2(o->e1, q)), d = fabs(cross2(o->e2, q));
    if (outer) return a <= o->l0 + o->m0 && b <= o->l1 + o->m1 && d <= o->l2 + o->m2;
    return a <= o->l0 - o->m0 && b <= o->l1 - o->m1 && d <= o->l2 - o->m2;
}

// ---------------------------------------------------------------- colour
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

// The photo-consistency test of the surface voxel v at X (normal direction g). Visibility: use_items: a pixel
// is seen when the item buffer holds v; else when it is not marked. Writes the mean colour over views (r g b),
// the colour variance over views (-1 when seen in < 2 views); returns 1 when v is inconsistent.
inline int photo(uint v, float3 X, float3 g, int axis, float plane, float sign, __global const uchar* marks,
                 int use_items, __global const ulong* items, VIEW_ARGS, GRID_ARGS, TEST_ARGS, float3* rgb_out, float* var_out,
                 int* views_out)
{
    float3 s1 = (float3)(0.0f), rgb = (float3)(0.0f);
    float s2 = 0.0f, w2 = 0.0f;
    int views = 0;
    for (int c = 0; c < nviews; c++) {
        if (!active(centres[c], axis, plane, sign) || !in_cone(centres[c], X, axis, sign, cos_cone) ||
            !facing(g, X, centres[c], cos_min))
            continue;
        __global const float* cam = cams + CAM_FLOATS * c;
        int4 w = win[c];
        VIEW_ROWS(c);
        footprint_t f;
        if (!footprint(cam, w, X, vs, scale, &f)) continue;
        int4 r = f.r;
        int stride = max(1, (max(r.y - r.x + 1, r.w - r.z + 1) + SAMPLES - 1) / SAMPLES);
        float3 sum = (float3)(0.0f), sq = (float3)(0.0f);
        int n = 0, total = 0;
        for (int y = r.z; y <= r.w; y += stride)
            for (int x = r.x; x <= r.y; x += stride) {
                if (!MASK(x, y) || !in_footprint(&f, x, y)) continue;
                total++;
                int p = PIX(x, y);
                if (use_items ? (uint)(items[p] & 0xFFFFFFFFUL) != v : marks[p] != 0) continue;
                uchar4 px = images[p];
                float3 col = (float3)((float)px.x, (float)px.y, (float)px.z);
                sum += col;
                sq += col * col;
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
    int bad = 0;
    if (views >= 2) {
        float3 mean = s1 / (float)views;
        var = s2 / (float)views - dot3(mean);
        float within = w2 / (float)views;
        float limit = thr + adaptive * sqrt(within);
        // contrast: the spread between views must also exceed `contrast` times the spread within them (a voxel
        // over fine texture, whose footprints differ between views by a fraction of the pattern, is not carved)
        bad = views >= min_views && var > limit * limit && var > (contrast * contrast) * within;
    }
    *rgb_out = views ? rgb / (float)views : (float3)(0.0f);
    *var_out = var;
    *views_out = views;
    return bad;
}

// ---------------------------------------------------------------- the guard
inline void cover_add(uint v, float3 X, int delta, VIEW_ARGS, float4 vs, __global int* cover)
{
    for (int c = 0; c < nviews; c++) {
        __global const float* cam = cams + CAM_FLOATS * c;
        int4 w = win[c];
        VIEW_ROWS(c);
        outline_t o;
        if (!cube_outline(cam, w, X, vs, &o)) continue;
        for (int y = o.r.z; y <= o.r.w; y++)
            for (int x = o.r.x; x <= o.r.y; x++)
                if (MASK(x, y) && in_outline(&o, x, y, 0))
                    atomic_add(&cover[PIX(x, y)], delta);
    }
}

inline int is_counted(__global const uint* counted, uint v)
{
    return (counted[v >> 5] >> (v & 31)) & 1;
}

// A new candidate: out of the cover counts (when counted), bidding for the pixels it covers for sure (the nearest
// candidate wins a pixel: on a ray that only candidates cover, the one in front stays).
inline void claim(uint v, float3 X, VIEW_ARGS, float4 vs, __global const uint* counted, __global int* cover,
                  __global uint* keeper)
{
    int was = is_counted(counted, v);
    for (int c = 0; c < nviews; c++) {
        __global const float* cam = cams + CAM_FLOATS * c;
        int4 w = win[c];
        VIEW_ROWS(c);
        outline_t o;
        if (!cube_outline(cam, w, X, vs, &o)) continue;
        for (int y = o.r.z; y <= o.r.w; y++)
            for (int x = o.r.x; x <= o.r.y; x++)
                if (MASK(x, y) && in_outline(&o, x, y, 0)) {
                    int p = PIX(x, y);
                    if (was) atomic_dec(&cover[p]);
                    atomic_min(&keeper[p], o.key);
                }
    }
}

inline void candidate(uint v, float3 X, int step, __global int* stamp, __global uint* cands, __global int* ncands,
                      VIEW_ARGS, float4 vs, __global const uint* counted, __global int* cover, __global uint* keeper)
{
    stamp[v] = (step << 2) | ST_CAND;
    cands[atomic_inc(ncands)] = v;
    claim(v, X, VIEW_PASS, vs, counted, cover, keeper);
}

// Initial cover counts: every listed (surface) voxel counted once.
__kernel void carve_count(__global const uint* list, int count, VIEW_ARGS, GRID_ARGS, __global uint* counted,
                          __global int* cover)
{
    int t = get_global_id(0);
    if (t >= count) return;
    uint v = list[t];
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    atomic_or(&counted[v >> 5], 1u << (v & 31));
    cover_add(v, voxel_centre(i, j, k, vs), 1, VIEW_PASS, vs, cover);
}

// Before the decisions: a candidate's face neighbours that stay (occupied, not candidates of the step) join the
// cover counts when they are not counted yet (they cover the rays that pass the candidate; counting any voxel that
// stays is safe, and these are surface voxels once the candidate goes).
inline void expose(uint v, __global const int* stamp, VIEW_ARGS, GRID_ARGS, __global const uchar* occ,
                   __global uint* counted, __global int* cover)
{
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny), step = stamp[v] >> 2;
    for (int q = 0; q < 6; q++) {
        int a = i + (q == 0) - (q == 1), b = j + (q == 2) - (q == 3), e = k + (q == 4) - (q == 5);
        if (!inside_grid(a, b, e, nx, ny, nz)) continue;
        uint u = ((uint)a * ny + b) * nz + e;
        if (!(occ[u] & 1) || (stamp[u] >> 2) == step || is_counted(counted, u)) continue;
        uint old = atomic_or(&counted[u >> 5], 1u << (u & 31));
        if (!((old >> (u & 31)) & 1)) cover_add(u, voxel_centre(a, b, e, vs), 1, VIEW_PASS, vs, cover);
    }
}

// Per candidate: stays when a silhouette pixel its cube may cover is left with cover 0 and it is that pixel's
// keeper (its depth won the bids; equal depths all stay) or the pixel has none.
inline void decide(uint v, __global int* stamp, VIEW_ARGS, GRID_ARGS, __global const int* cover,
                   __global const uint* keeper)
{
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny), step = stamp[v] >> 2;
    float3 X = voxel_centre(i, j, k, vs);
    int needed = 0;
    for (int c = 0; c < nviews && !needed; c++) {
        __global const float* cam = cams + CAM_FLOATS * c;
        int4 w = win[c];
        VIEW_ROWS(c);
        outline_t o;
        if (!cube_outline(cam, w, X, vs, &o)) continue;
        for (int y = o.r.z; y <= o.r.w && !needed; y++)
            for (int x = o.r.x; x <= o.r.y; x++) {
                if (!MASK(x, y) || !in_outline(&o, x, y, 1)) continue;
                int p = PIX(x, y);
                if (cover[p] == 0 && (keeper[p] == o.key || keeper[p] == NO_KEEPER)) {
                    needed = 1;
                    break;
                }
            }
    }
    stamp[v] = (step << 2) | (needed ? ST_KEEP : ST_GO);
}

// Flag the occupied voxels of the 3x3x3 block around (i, j, k) for the next incremental pass (once each).
inline void flag_around(uint v, int i, int j, int k, GRID_ARGS, __global const uchar* occ, FRESH_ARGS)
{
    for (int a = max(i - 1, 0); a <= min(i + 1, nx - 1); a++)
        for (int b = max(j - 1, 0); b <= min(j + 1, ny - 1); b++)
            for (int e = max(k - 1, 0); e <= min(k + 1, nz - 1); e++) {
                uint u = ((uint)a * ny + b) * nz + e;
                if (!(occ[u] & 1)) continue;
                uint old = atomic_or(&fresh[u >> 5], 1u << (u & 31));
                if (!((old >> (u & 31)) & 1)) flist[atomic_inc(nflist)] = u;
            }
}

// A removed voxel gave back pixels of a view: the voxel that now shows there is found along the ray from the
// camera through the removed voxel's centre (steps of half a voxel beyond it, until a voxel that stays this step),
// and it and its neighbours are flagged, so the next incremental pass splats and tests them.
inline void reveal(uint v, int i, int j, int k, float3 X, float4 C, int step, __global const int* stamp, GRID_ARGS,
                   __global const uchar* occ, FRESH_ARGS)
{
    float3 d = X - C.xyz;
    float dt = (0.5f * fmin(fmin(vs.x, vs.y), vs.z)) / fmax(fmax(fabs(d.x), fabs(d.y)), fabs(d.z));
    if (!isfinite(dt)) return;
    int limit = 2 * (nx + ny + nz) + 4;
    for (int n = 1; n <= limit; n++) {
        float tn = (float)n * dt;
        float3 P = X + tn * d;
        int a = (int)floor(P.x / vs.x), b = (int)floor(P.y / vs.y), e = (int)floor(P.z / vs.z);
        if (!inside_grid(a, b, e, nx, ny, nz)) return;
        uint u = ((uint)a * ny + b) * nz + e;
        if (u == v || !(occ[u] & 1) || stamp[u] == ((step << 2) | ST_GO)) continue;
        flag_around(u, a, b, e, GRID_PASS, occ, FRESH_PASS);
        return;
    }
}

// Carry out a decision: bids withdrawn; a kept candidate counts again and is protected; a removed one leaves the
// volume, flags its occupied 26 neighbours for the next incremental pass and, in an item pass, gives back its
// pixels in the item buffers, flagging in each view where it held pixels the voxels that now show there.
inline void apply(uint v, __global const int* stamp, VIEW_ARGS, GRID_ARGS, __global uchar* occ,
                  __global int* cover, __global uint* keeper, __global uint* counted, int use_items,
                  __global ulong* items, FRESH_ARGS, __global int* removed)
{
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny), step = stamp[v] >> 2;
    float3 X = voxel_centre(i, j, k, vs);
    int keep = (stamp[v] & 3) == ST_KEEP;
    for (int c = 0; c < nviews; c++) {
        __global const float* cam = cams + CAM_FLOATS * c;
        int4 w = win[c];
        VIEW_ROWS(c);
        outline_t o;
        if (!cube_outline(cam, w, X, vs, &o)) continue;
        for (int y = o.r.z; y <= o.r.w; y++)
            for (int x = o.r.x; x <= o.r.y; x++)
                if (MASK(x, y) && in_outline(&o, x, y, 0)) {
                    int p = PIX(x, y);
                    keeper[p] = NO_KEEPER;
                    if (keep) atomic_inc(&cover[p]);
                }
    }
    if (keep) {
        occ[v] = 1 | PROTECTED;
        atomic_or(&counted[v >> 5], 1u << (v & 31));
        return;
    }
    occ[v] = 0;
    atomic_inc(removed);
    flag_around(v, i, j, k, GRID_PASS, occ, FRESH_PASS);
    if (!use_items) return;
    for (int c = 0; c < nviews; c++) {
        __global const float* cam = cams + CAM_FLOATS * c;
        int4 w = win[c];
        VIEW_ROWS(c);
        footprint_t f;
        if (!footprint(cam, w, X, vs, 1.0f, &f)) continue;
        int given = 0;
        for (int y = f.r.z; y <= f.r.w; y++)
            for (int x = f.r.x; x <= f.r.y; x++) {
                int p = PIX(x, y);
                if ((uint)(items[p] & 0xFFFFFFFFUL) == v) {
                    items[p] = EMPTY_ITEM;
                    given = 1;
                }
            }
        if (given) reveal(v, i, j, k, X, centres[c], step, stamp, GRID_PASS, occ, FRESH_PASS);
    }
}

// The guard's kernels, over the step's candidates (each knows its step from its stamp, so a step sets no argument).
__kernel void carve_expose(__global const uint* cands, __global const int* ncands, __global const int* stamp, VIEW_ARGS,
                           GRID_ARGS, __global const uchar* occ, __global uint* counted, __global int* cover)
{
    int t = get_global_id(0);
    if (t >= *ncands) return;
    expose(cands[t], stamp, VIEW_PASS, GRID_PASS, occ, counted, cover);
}

__kernel void carve_decide(__global const uint* cands, __global const int* ncands, __global int* stamp, VIEW_ARGS,
                           GRID_ARGS, __global const int* cover, __global const uint* keeper)
{
    int t = get_global_id(0);
    if (t >= *ncands) return;
    decide(cands[t], stamp, VIEW_PASS, GRID_PASS, cover, keeper);
}

__kernel void carve_apply(__global const uint* cands, __global const int* ncands, __global const int* stamp, VIEW_ARGS,
                          GRID_ARGS, __global uchar* occ, __global int* cover, __global uint* keeper,
                          __global uint* counted, int use_items, __global ulong* items, FRESH_ARGS,
                          __global int* removed)
{
    int t = get_global_id(0);
    if (t >= *ncands) return;
    apply(cands[t], stamp, VIEW_PASS, GRID_PASS, occ, cover, keeper, counted, use_items, items, FRESH_PASS,
          removed);
}

// ---------------------------------------------------------------- item passes
// List the occupied surface voxels of `list` (all of them, or the flagged ones: flags cleared). Appended to `out`
// in no particular order (what follows does not depend on it).
__kernel void carve_compact(__global const uint* list, int count, int flagged, __global const uchar* occ,
                            __global uint* fresh, int nx, int ny, int nz, __global uint* out, __global int* counter)
{
    int t = get_global_id(0);
    if (t >= count) return;
    uint v = list[t];
    if (flagged) atomic_and(&fresh[v >> 5], ~(1u << (v & 31)));
    if (!(occ[v] & 1)) return;
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    if (surface(occ, i, j, k, nx, ny, nz)) out[atomic_inc(counter)] = v;
}

// Item buffers: every listed surface voxel writes (depth, index) into the silhouette pixels of its whole
// footprint in every view it does not clearly turn away from; the nearest wins (exact depth ties: lower index).
__kernel void carve_splat(__global const uint* list, int count, __global const uchar* occ, VIEW_ARGS, GRID_ARGS,
                          __global ulong* items)
{
    int t = get_global_id(0);
    if (t >= count) return;
    uint v = list[t];
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    float3 X = voxel_centre(i, j, k, vs);
    float3 g = voxel_normal(occ, i, j, k, nx, ny, nz);
    for (int c = 0; c < nviews; c++) {
        if (!facing(g, X, centres[c], BACK_FACING)) continue;   // clearly turned away: hidden anyway
        __global const float* cam = cams + CAM_FLOATS * c;
        int4 w = win[c];
        VIEW_ROWS(c);
        footprint_t f;
        if (!footprint(cam, w, X, vs, 1.0f, &f)) continue;
        ulong key = ((ulong)as_uint(f.depth) << 32) | (ulong)v;
        for (int y = f.r.z; y <= f.r.w; y++)
            for (int x = f.r.x; x <= f.r.y; x++)
                if (in_footprint(&f, x, y) && MASK(x, y))
                    atom_min(&items[PIX(x, y)], key);
    }
}

// The photo-consistency test of listed surface voxels (item passes: use_items; voxel colouring's layers: marks),
// every camera. Inconsistent ones become candidates of the step (stamp, list, claim). write_colors: instead,
// write the mean colour (r g b, number of views) and the colour variance over views (-1 when seen in < 2 views)
// of each list entry, protected voxels included (indexed by position in the list).
__kernel void carve_test(__global const uint* list, int first, int count, __global const uchar* occ, __global int* stamp,
                         int step, __global const uchar* marks, int use_items, __global const ulong* items, VIEW_ARGS,
                         GRID_ARGS, TEST_ARGS, __global uint* cands, __global int* ncands, __global const uint* counted,
                         __global int* cover, __global uint* keeper, int write_colors, __global uchar4* colors,
                         __global float* variance)
{
    int t = get_global_id(0);
    if (t >= count) return;
    uint v = list[first + t];
    if (!(occ[v] & 1) || ((occ[v] & PROTECTED) && !write_colors)) return;
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    if (!surface(occ, i, j, k, nx, ny, nz)) return;
    float3 X = voxel_centre(i, j, k, vs);
    float3 g = voxel_normal(occ, i, j, k, nx, ny, nz);
    float3 rgb;
    float var;
    int views;
    int bad = photo(v, X, g, -1, 0.0f, 0.0f, marks, use_items, items, VIEW_PASS, GRID_PASS, TEST_PASS, &rgb, &var, &views);
    if (write_colors) {
        colors[t] = (uchar4)(convert_uchar3_sat_rte(rgb), (uchar)min(views, 255));
        variance[t] = var;
    } else if (bad) {
        candidate(v, X, step, stamp, cands, ncands, VIEW_PASS, vs, counted, cover, keeper);
    }
}

// Voxel colouring, after a layer's decisions: its kept surface voxels mark their footprints in every view.
__kernel void carve_mark(__global const uint* list, int first, int count, __global const uchar* occ, VIEW_ARGS,
                         GRID_ARGS, __global uchar* marks)
{
    int t = get_global_id(0);
    if (t >= count) return;
    uint v = list[first + t];
    if (!(occ[v] & 1)) return;
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    if (!surface(occ, i, j, k, nx, ny, nz)) return;
    float3 X = voxel_centre(i, j, k, vs);
    for (int c = 0; c < nviews; c++) {
        __global const float* cam = cams + CAM_FLOATS * c;
        int4 w = win[c];
        VIEW_ROWS(c);
        footprint_t f;
        if (!footprint(cam, w, X, vs, 1.0f, &f)) continue;
        for (int y = f.r.z; y <= f.r.w; y++)
            for (int x = f.r.x; x <= f.r.y; x++)
                if (in_footprint(&f, x, y)) marks[PIX(x, y)] = 1;
    }
}

// ---------------------------------------------------------------- plane sweeps
inline void mark_footprint(float3 X, int axis, float plane, float sign, VIEW_ARGS, float4 vs, __global uchar* marks)
{
    for (int c = 0; c < nviews; c++) {
        if (!active(centres[c], axis, plane, sign)) continue;
        __global const float* cam = cams + CAM_FLOATS * c;
        int4 w = win[c];
        VIEW_ROWS(c);
        footprint_t f;
        if (!footprint(cam, w, X, vs, 1.0f, &f)) continue;
        for (int y = f.r.z; y <= f.r.w; y++)
            for (int x = f.r.x; x <= f.r.y; x++)
                if (in_footprint(&f, x, y)) marks[PIX(x, y)] = 1;
    }
}

// A round's planes (nodes/carve/carving.py, sweep_planes), in sweep order: the plane's occupied voxels are
// list[first .. first + count); axis, plane position, sign (+1: the sweep runs towards +axis); the plane's step.
typedef struct {
    int first, count, axis, step;
    float plane, sign;
} sweep_plane_t;

// A plane of a sweep, one step: its surface voxels are tested in the cameras behind the plane (visibility: marks
// of the voxels kept in earlier planes of the sweep); inconsistent ones become candidates (then the guard's three
// kernels); carve_sweep_mark: the plane's surface voxels that stay mark their footprints, and the candidate count
// goes back to 0 for the next plane. The plane is found on the device, so a plane sets no kernel argument:
// at[0] is the next plane (carve_sweep_test reads it and copies it to at[1]), at[1] the plane under way
// (carve_sweep_mark reads it and moves at[0] on). No kernel writes what its own work items read.
__kernel void carve_sweep_test(__global const uint* list, __global const sweep_plane_t* planes, __global int* at,
                               __global int* stamp, __global const uchar* marks, __global const uchar* occ,
                               VIEW_ARGS, GRID_ARGS, TEST_ARGS, __global uint* cands, __global int* ncands,
                               __global const uint* counted, __global int* cover, __global uint* keeper)
{
    int t = get_global_id(0);
    int r = at[0];
    if (t == 0) at[1] = r;
    sweep_plane_t pl = planes[r];
    if (t >= pl.count) return;
    uint v = list[pl.first + t];
    if ((occ[v] & (1 | PROTECTED)) != 1) return;
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    if (!surface(occ, i, j, k, nx, ny, nz)) return;
    float3 X = voxel_centre(i, j, k, vs);
    float3 g = voxel_normal(occ, i, j, k, nx, ny, nz);
    float3 rgb;
    float var;
    int views;
    if (photo(v, X, g, pl.axis, pl.plane, pl.sign, marks, 0, 0, VIEW_PASS, GRID_PASS, TEST_PASS, &rgb, &var, &views))
        candidate(v, X, pl.step, stamp, cands, ncands, VIEW_PASS, vs, counted, cover, keeper);
}

__kernel void carve_sweep_mark(__global const uint* list, __global const sweep_plane_t* planes, __global int* at,
                               __global const uchar* occ, VIEW_ARGS, GRID_ARGS, __global uchar* marks,
                               __global int* ncands)
{
    int t = get_global_id(0);
    int r = at[1];
    if (t == 0) {
        at[0] = r + 1;
        *ncands = 0;
    }
    sweep_plane_t pl = planes[r];
    if (t >= pl.count) return;
    uint v = list[pl.first + t];
    if (!(occ[v] & 1)) return;
    int k = v % nz, j = (v / nz) % ny, i = v / (nz * ny);
    if (surface(occ, i, j, k, nx, ny, nz))
        mark_footprint(voxel_centre(i, j, k, vs), pl.axis, pl.plane, pl.sign, VIEW_PASS, vs, marks);
}
