// Texturing kernels (NumPy references beside their callers in nodes/texture/views.py and bake.py).
//
//   face_views   per face, one view: visible? (depth test at 4 points, mask margin, depth-edge margin),
//                quality (projected area x cosine) and mean colour, into row ``view`` of (V, F) arrays
//   face_cost    per face: data cost of each view (1 - q / q_max, +1 where its colour disagrees with the
//                face's other views), the colour spread, the best view (NumPy: views.data_cost)
//   icm_step     per face: one round of iterated conditional modes on the Potts energy (views.select_views)
//   uv_raster    per face: the atlas texels whose centre lies in the face's UV triangle get its id (max id wins)
//   texel_bary   per texel: barycentrics of the texel centre in its face's UV triangle (clamped onto the
//                triangle: gutter texels borrow a neighbour face and extrapolate no further than its edge)
//   bake         per sample (face, barycentrics): 3-D point, projected into the face's blend views, sampled
//                bilinearly where the view's valid mask allows, gain-corrected, offsets added, blended
//
// Images arrive concatenated (RGB uchar, view after view at byte offsets ``img_off[view]``); valid masks
// likewise (uchar, at ``img_off[view] / 3``). Pixel centres are at integer coordinates (camera.h).
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL EXTENSION cl_khr_global_int32_base_atomics : enable
#include "camera.h"

#define NEAR_Z 1e-6f

inline float3 vertex3(__global const float *v, int i)
{
    return (float3)(v[3 * i], v[3 * i + 1], v[3 * i + 2]);
}

// The depth at pixel (x, y) of a z-buffer over ``box`` (x0, y0, width, height) alone (raster.cl's raster_depth):
// INFINITY where no face was drawn, inside the box or outside it.
inline float box_depth(__global const uint *zbuf, int4 box, int x, int y)
{
    x -= box.x;
    y -= box.y;
    if (x < 0 || y < 0 || x >= box.z || y >= box.w) return INFINITY;
    uint d = zbuf[y * box.z + x];
    return d == 0xFFFFFFFFu ? INFINITY : as_float(d);
}

// Bilinear RGB sample (0..255 floats) at pixel coordinates p (clamped to the image).
__attribute__((always_inline)) inline float3 sample_rgb(__global const uchar *img, int w, int h, float2 p)
{
    float x = clamp(p.x, 0.0f, (float)(w - 1)), y = clamp(p.y, 0.0f, (float)(h - 1));
    int x0 = (int)floor(x), y0 = (int)floor(y);
    int x1 = min(x0 + 1, w - 1), y1 = min(y0 + 1, h - 1);
    float fx = x - (float)x0, fy = y - (float)y0;
    __global const uchar *a = img + 3 * (y0 * w + x0), *b = img + 3 * (y0 * w + x1);
    __global const uchar *c = img + 3 * (y1 * w + x0), *d = img + 3 * (y1 * w + x1);
    float3 ca = (float3)(a[0], a[1], a[2]), cb = (float3)(b[0], b[1], b[2]);
    float3 cc = (float3)(c[0], c[1], c[2]), cd = (float3)(d[0], d[1], d[2]);
    return (1.0f - fy) * ((1.0f - fx) * ca + fx * cb) + fy * ((1.0f - fx) * cc + fx * cd);
}

// Whether pixel (round(p)) is inside the image and valid; writes its index.
inline int pixel_ok(__global const uchar *valid, int w, int h, float2 p, int *idx)
{
    if (!(p.x > -0.5f && p.y > -0.5f && p.x < (float)w - 0.5f && p.y < (float)h - 0.5f)) return 0;
    int x = (int)(p.x + 0.5f), y = (int)(p.y + 0.5f);
    *idx = y * w + x;
    return valid[*idx] != 0;
}

// One view (its image at byte img_off of the concatenated images): per face quality (0 = not usable) and mean
// colour of its four sample points. A face is usable when it faces the camera and each sample point
// (centroid, and the corners pulled a fifth of the way to it) projects onto a valid pixel (eroded mask),
// passes the depth test against the z-buffer (within depth_tol), and no pixel ``edge_px`` away along the axes
// differs from its depth by more than edge_tol (depth edges and the mesh's own outline: where registration
// errors show the wrong surface). ``relaxed`` is the quality under the weaker test used when no view passes
// the strict one: the centroid alone on a valid pixel and unoccluded (its colour is then the centroid's).
// quality, relaxed (V, F) and colour (V, F, 3) hold all views; this launch writes row ``view``.
__kernel void face_views(__global const float *verts, __global const int *faces, int nfaces,
                         __global const float *cams, int view, float4 centre,
                         __global const uint *zbuf, int4 box, __global const uchar *valid_all, __global const uchar *img_all,
                         long img_off, float depth_tol, float edge_tol, int edge_px,
                         __global float *quality, __global float *relaxed, __global float *colour)
{
    int f = get_global_id(0);
    if (f >= nfaces) return;
    __global const float *cam = cams + CAM_FLOATS * view;
    __global const uchar *img = img_all + img_off, *valid = valid_all + img_off / 3;
    quality += (long)view * nfaces;                 // row ``view`` of the (V, F) outputs
    relaxed += (long)view * nfaces;
    colour += (long)view * nfaces * 3;
    int w = (int)cam[22], h = (int)cam[23];
    float3 A = vertex3(verts, faces[3 * f]), B = vertex3(verts, faces[3 * f + 1]), C = vertex3(verts, faces[3 * f + 2]);
    float3 G = (A + B + C) / 3.0f;
    float3 n = cross(B - A, C - A);
    float3 to_cam = centre.xyz - G;
    float nl = length(n), cl = length(to_cam);
    float cosine = (nl > 0.0f && cl > 0.0f) ? dot(n, to_cam) / (nl * cl) : 0.0f;
    quality[f] = 0.0f;
    relaxed[f] = 0.0f;
    colour[3 * f] = colour[3 * f + 1] = colour[3 * f + 2] = 0.0f;
    if (cosine <= 0.0f) return;
    // the centroid first: where it is outside the valid pixels or occluded nothing is usable (quality, relaxed
    // and colour stay 0, as after the corners' tests), so the corners need not be projected
    float zg;
    float2 pg = project_point(cam, G, &zg);
    int ig;
    if (zg <= NEAR_Z || !pixel_ok(valid, w, h, pg, &ig) || zg > box_depth(zbuf, box, ig % w, ig / w) + depth_tol) return;
    float za, zb, zc;
    float2 pa = project_point(cam, A, &za), pb = project_point(cam, B, &zb), pc = project_point(cam, C, &zc);
    if (za <= NEAR_Z || zb <= NEAR_Z || zc <= NEAR_Z) return;
    float q = 0.5f * fabs((pb.x - pa.x) * (pc.y - pa.y) - (pb.y - pa.y) * (pc.x - pa.x)) * cosine;
    float3 sum = (float3)(0.0f), first = (float3)(0.0f);
    int strict = 1;
    for (int s = 0; s < 4; s++) {
        float z = zg;
        float2 p = pg;
        int idx = ig;
        if (s > 0) {
            float3 X = s == 1 ? G + 0.8f * (A - G) : (s == 2 ? G + 0.8f * (B - G) : G + 0.8f * (C - G));
            p = project_point(cam, X, &z);
        }
        if (s > 0 && (z <= NEAR_Z || !pixel_ok(valid, w, h, p, &idx) || z > box_depth(zbuf, box, idx % w, idx / w) + depth_tol)) {
            strict = 0;
            break;
        }
        float3 c = sample_rgb(img, w, h, p);
        if (s == 0) {
            relaxed[f] = q;
            first = c;
        }
        int x = idx % w, y = idx / w;
        for (int k = 0; k < 4 && strict; k++) {
            int xx = x + (k == 0 ? edge_px : (k == 1 ? -edge_px : 0));
            int yy = y + (k == 2 ? edge_px : (k == 3 ? -edge_px : 0));
            if (xx < 0 || yy < 0 || xx >= w || yy >= h || fabs(box_depth(zbuf, box, xx, yy) - z) > edge_tol)
                strict = 0;                                                // near a depth edge or the outline
        }
        if (!strict) break;
        sum += c;
    }
    float3 col = strict ? sum * 0.25f : first;
    if (strict) quality[f] = q;
    colour[3 * f] = col.x;
    colour[3 * f + 1] = col.y;
    colour[3 * f + 2] = col.z;
}

// Atlas texel (x, y) has its centre at (x + 0.5, y + 0.5) in texel units; ``uv`` holds per face corner
// texel coordinates (F, 3, 2). Texels covered by several faces (shared edges) keep the highest face id.
__kernel void uv_raster(__global const float *uv, int nfaces, int size, __global int *texel_face)
{
    int f = get_global_id(0);
    if (f >= nfaces) return;
    float2 a = vload2(3 * f, uv), b = vload2(3 * f + 1, uv), c = vload2(3 * f + 2, uv);
    float area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
    if (area == 0.0f) return;
    int x0 = max(0, (int)floor(fmin(a.x, fmin(b.x, c.x)) - 0.5f));
    int x1 = min(size - 1, (int)ceil(fmax(a.x, fmax(b.x, c.x)) - 0.5f));
    int y0 = max(0, (int)floor(fmin(a.y, fmin(b.y, c.y)) - 0.5f));
    int y1 = min(size - 1, (int)ceil(fmax(a.y, fmax(b.y, c.y)) - 0.5f));
    float inv = 1.0f / area;
    for (int y = y0; y <= y1; y++) {
        for (int x = x0; x <= x1; x++) {
            float px = (float)x + 0.5f, py = (float)y + 0.5f;
            float w0 = ((c.x - b.x) * (py - b.y) - (c.y - b.y) * (px - b.x)) * inv;
            float w1 = ((a.x - c.x) * (py - c.y) - (a.y - c.y) * (px - c.x)) * inv;
            float w2 = 1.0f - w0 - w1;
            if (w0 < 0.0f || w1 < 0.0f || w2 < 0.0f) continue;
            atomic_max(&texel_face[y * size + x], f);
        }
    }
}

// Barycentrics of each texel centre in its face's UV triangle, clamped to >= 0 and renormalised.
__kernel void texel_bary(__global const int *texel_face, int size, __global const float *uv, __global float *bary)
{
    int x = get_global_id(0), y = get_global_id(1);
    if (x >= size || y >= size) return;
    int i = y * size + x;
    int f = texel_face[i];
    float w0 = 0.0f, w1 = 0.0f, w2 = 0.0f;
    if (f >= 0) {
        float2 a = vload2(3 * f, uv), b = vload2(3 * f + 1, uv), c = vload2(3 * f + 2, uv);
        float area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
        float px = (float)x + 0.5f, py = (float)y + 0.5f;
        if (area != 0.0f) {
            w0 = ((c.x - b.x) * (py - b.y) - (c.y - b.y) * (px - b.x)) / area;
            w1 = ((a.x - c.x) * (py - c.y) - (a.y - c.y) * (px - c.x)) / area;
            w2 = 1.0f - w0 - w1;
        }
        w0 = fmax(w0, 0.0f); w1 = fmax(w1, 0.0f); w2 = fmax(w2, 0.0f);
        float s = w0 + w1 + w2;
        if (s > 0.0f) { w0 /= s; w1 /= s; w2 /= s; } else { w0 = w1 = w2 = 1.0f / 3.0f; }
    }
    bary[3 * i] = w0;
    bary[3 * i + 1] = w1;
    bary[3 * i + 2] = w2;
}

// Per sample i (face sample_face[i] >= 0, barycentrics sample_bary[i]): colour = sum_k wt_k c_k / sum_k wt_k
// over the face's K blend views, wt_k = sum_c b_c weight[f, c, k] (0 where the point projects onto an
// invalid pixel), c_k = gain[view] * image sample + sum_c b_c offset[f, c, k]; where face_blur[f] > 0 the
// image sample is mixed with a 5-tap cross of radius blur_px (views that disagree: geometry or calibration
// errors, where a sharp sample is sharply wrong from other viewpoints). out = (r, g, b, sum wt),
// 0..255 scale; sum wt = 0: no view could colour it (the caller fills it). With ``scatter`` sample i's result
// goes to row dest[i] (a BakeLayout's samples sorted by face, written back in layout order).
__kernel void bake(int nsamples, __global const int *sample_face, __global const float *sample_bary,
                   __global const float *verts, __global const int *faces, __global const float *cams,
                   __global const uchar *images, __global const uchar *valid, __global const long *img_off,
                   int K, __global const int *face_view, __global const float *weight,
                   __global const float *offset, __global const float *gain, __global const float *face_blur,
                   float blur_px, __global const int *dest, int scatter, __global float4 *out)
{
    int i = get_global_id(0);
    if (i >= nsamples) return;
    int o = scatter ? dest[i] : i;                // the sample's row of ``out`` (samples sorted by face, out not)
    int f = sample_face[i];
    if (f < 0) { out[o] = (float4)(0.0f); return; }
    float b0 = sample_bary[3 * i], b1 = sample_bary[3 * i + 1], b2 = sample_bary[3 * i + 2];
    float3 X = b0 * vertex3(verts, faces[3 * f]) + b1 * vertex3(verts, faces[3 * f + 1]) + b2 * vertex3(verts, faces[3 * f + 2]);
    float3 acc = (float3)(0.0f);
    float wsum = 0.0f;
    for (int k = 0; k < K; k++) {
        int v = face_view[f * K + k];
        if (v < 0) continue;
        float wt = b0 * weight[(f * 3) * K + k] + b1 * weight[(f * 3 + 1) * K + k] + b2 * weight[(f * 3 + 2) * K + k];
        if (wt <= 0.0f) continue;
        __global const float *cam = cams + CAM_FLOATS * v;
        int w = (int)cam[22], h = (int)cam[23];
        float z;
        float2 p = project_point(cam, X, &z);
        int idx;
        if (z <= NEAR_Z || !pixel_ok(valid + img_off[v] / 3, w, h, p, &idx)) continue;
        float3 c = sample_rgb(images + img_off[v], w, h, p);
        float bl = face_blur[f];
        if (bl > 0.0f) {                          // views disagree here: a blurred sample (5-tap cross)
            __global const uchar *im = images + img_off[v];
            float3 cross5 = c + sample_rgb(im, w, h, p + (float2)(blur_px, 0.0f)) + sample_rgb(im, w, h, p - (float2)(blur_px, 0.0f))
                          + sample_rgb(im, w, h, p + (float2)(0.0f, blur_px)) + sample_rgb(im, w, h, p - (float2)(0.0f, blur_px));
            c = (1.0f - bl) * c + bl * 0.2f * cross5;
        }
        c *= vload3(v, gain);
        int o0 = ((f * 3) * K + k) * 3, o1 = ((f * 3 + 1) * K + k) * 3, o2 = ((f * 3 + 2) * K + k) * 3;
        c += b0 * (float3)(offset[o0], offset[o0 + 1], offset[o0 + 2])
           + b1 * (float3)(offset[o1], offset[o1 + 1], offset[o1 + 2])
           + b2 * (float3)(offset[o2], offset[o2 + 1], offset[o2 + 2]);
        acc += wt * c;
        wsum += wt;
    }
    out[o] = wsum > 0.0f ? (float4)(acc / wsum, wsum) : (float4)(0.0f);
}

#define INVISIBLE 1e6f

// Per face f, over its views v (quality row-major (V, F), colour (V, F, 3)): q_v = sharp[v] * (quality > 0 ?
// quality : weak * relaxed) (views passing only the weaker test count little); cost (F, V) = 1 - q_v / max q
// where q_v > 0, else INVISIBLE; with two or more views: the mean of their gain-corrected colours, again
// without views further than 2 * consistency from it (when any stays), each view's distance d_v from it,
// spread[f] = mean d_v, and +1 on the cost of views with d_v > consistency when three or more see the face.
// best[f] = the cheapest view (lowest index on ties), -1 when none sees the face.
__kernel void face_cost(int nfaces, int nviews, __global const float *quality, __global const float *relaxed,
                        __global const float *colour, __global const float *sharp, __global const float *gain,
                        float weak, float consistency, __global float *cost, __global float *spread,
                        __global int *best)
{
    int f = get_global_id(0);
    if (f >= nfaces) return;
    __global float *c = cost + (long)f * nviews;
    float qmax = 0.0f;
    int n = 0;
    float3 centre = (float3)(0.0f);
    for (int v = 0; v < nviews; v++) {
        long i = (long)v * nfaces + f;
        float q = quality[i] > 0.0f ? quality[i] : weak * relaxed[i];
        q *= sharp[v];
        c[v] = q;
        if (q > 0.0f) {
            qmax = fmax(qmax, q);
            centre += vload3(i, colour) * vload3(v, gain);
            n++;
        }
    }
    float spr = 0.0f;
    if (n >= 2) {
        centre /= (float)n;
        if (consistency > 0.0f) {                  // the mean again without far outliers
            float3 kept = (float3)(0.0f);
            int kn = 0;
            for (int v = 0; v < nviews; v++) {
                if (c[v] <= 0.0f) continue;
                long i = (long)v * nfaces + f;
                float3 col = vload3(i, colour) * vload3(v, gain);
                if (length(col - centre) <= 2.0f * consistency) { kept += col; kn++; }
            }
            if (kn > 0) centre = kept / (float)kn;
        }
        for (int v = 0; v < nviews; v++) {
            if (c[v] <= 0.0f) continue;
            long i = (long)v * nfaces + f;
            float d = length(vload3(i, colour) * vload3(v, gain) - centre);
            spr += d;
            if (consistency > 0.0f && n >= 3 && d > consistency) c[v] = -c[v];     // marked: disagrees
        }
        spr /= (float)n;
    }
    spread[f] = spr;
    int b = -1;
    float bc = INVISIBLE;
    for (int v = 0; v < nviews; v++) {
        float q = c[v];
        float cv = q > 0.0f ? 1.0f - q / qmax : (q < 0.0f ? 2.0f + q / qmax : INVISIBLE);
        c[v] = cv;
        if (cv < bc) { bc = cv; b = v; }
    }
    best[f] = b;
}

// Integer hash (lowbias32), mirrored in views.hash32: which half of the faces moves in an ICM round.
inline uint hash32(uint x)
{
    x ^= x >> 16; x *= 0x7feb352dU; x ^= x >> 15; x *= 0x846ca68bU; x ^= x >> 16;
    return x;
}

// One round of iterated conditional modes on sum_f cost[f, l_f] + smoothness * #{neighbours with another
// label}: each face finds its best label given its neighbours' current labels (neighbours without a view,
// label -1, do not count); it moves when it is in this round's half (hash of face and round) and its best
// differs. ``moved`` counts the moves.
__kernel void icm_step(int nfaces, int nviews, __global const float *cost, __global const int *nbr,
                       __global const int *labels, __global int *out, float smoothness, uint round_key,
                       __global int *moved)
{
    int f = get_global_id(0);
    if (f >= nfaces) return;
    int own = labels[f];
    out[f] = own;
    if (own < 0) return;
    int l0 = -1, l1 = -1, l2 = -1;
    int g = nbr[3 * f];     if (g >= 0) l0 = labels[g];
    g = nbr[3 * f + 1];     if (g >= 0) l1 = labels[g];
    g = nbr[3 * f + 2];     if (g >= 0) l2 = labels[g];
    float total = (float)((l0 >= 0) + (l1 >= 0) + (l2 >= 0));
    __global const float *c = cost + (long)f * nviews;
    int b = 0;
    float be = INFINITY;
    for (int v = 0; v < nviews; v++) {
        float agree = (float)((l0 == v) + (l1 == v) + (l2 == v));
        float e = c[v] + smoothness * (total - agree);
        if (e < be) { be = e; b = v; }
    }
    if (b != own && (hash32((uint)f ^ round_key) & 1u)) {
        out[f] = b;
        atomic_inc(moved);
    }
}
