// Z-buffer triangle rasterizer (NumPy reference: nodes/raster.py).
//
// Pipeline for one view:  project_vertices -> raster_triangles -> resolve | coverage | shade
//                     or  project_bounds -> raster_depth (depths alone, on the mesh's box)
//                     or  project_bounds -> raster_cover (coverage alone, on the mesh's box)
// Conventions: pixel (u, v) has its centre at integer coordinates (as Cameras.project); a pixel is covered
// when its centre lies inside or on the edge of the projected triangle. Lens distortion is applied per
// vertex, so triangle edges stay straight in the distorted image (fine for small triangles).
// Depth is camera z, interpolated perspective-correctly (1/z is linear in screen space). The z-buffer holds
// 64-bit keys (float bits of depth << 32 | face id), so atom_min keeps the nearest face and breaks exact depth
// ties by the lower face id: the result does not depend on execution order.
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
#pragma OPENCL EXTENSION cl_khr_int64_extended_atomics : enable
#pragma OPENCL EXTENSION cl_khr_global_int32_base_atomics : enable
#pragma OPENCL EXTENSION cl_khr_global_int32_extended_atomics : enable
#include "camera.h"

#define EMPTY 0xFFFFFFFFFFFFFFFFUL

// Camera layout and projection: kernels/camera.h (Cameras.pack()). (u, v, depth, 1 if imaged else 0)
__attribute__((always_inline)) inline float4 project_one(__global const float *cam, float3 x, float near)
{
    float3 xc = camera_point(cam, x);
    float2 n = xc.xy / xc.z;
    float2 uv = pixel_point(cam, distort_point(cam, n));
    float depth = xc.z * cam[24];
    // radial distortion folds back beyond the radius where d(r_d)/dr = 0: such points are not imaged
    float k1 = cam[17], k2 = cam[18], k3 = cam[21];
    float r2 = n.x * n.x + n.y * n.y;
    float slope = 1.0f + r2 * (3.0f * k1 + r2 * (5.0f * k2 + r2 * 7.0f * k3));
    return (float4)(uv.x, uv.y, depth, (depth > near && slope > 0.0f) ? 1.0f : 0.0f);
}

__kernel void project_vertices(__global const float *verts, __global const float *cams, int view, int nverts,
                               float near, __global float4 *out)
{
    int i = get_global_id(0);
    if (i >= nverts) return;
    out[i] = project_one(cams + CAM_FLOATS * view, (float3)(verts[3 * i], verts[3 * i + 1], verts[3 * i + 2]), near);
}

// project_vertices, and the pixel box the projections span as raster_triangles clips a face's box (ceil / floor
// of the coordinates clamped to the image), over the imaged vertices with finite coordinates: every pixel a
// face can cover lies in it. ``bounds`` (x0, y0, x1, y1) must hold (INT_MAX, INT_MAX, INT_MIN, INT_MIN); a
// vertex widens it with an atomic only where it lies beyond what it reads there (the bounds only grow, so a
// stale read costs an atomic, never a pixel).
__kernel void project_bounds(__global const float *verts, __global const float *cams, int view, int nverts,
                             float near, __global float4 *out, __global int *bounds)
{
    int i = get_global_id(0);
    if (i >= nverts) return;
    __global const float *cam = cams + CAM_FLOATS * view;
    float4 p = project_one(cam, (float3)(verts[3 * i], verts[3 * i + 1], verts[3 * i + 2]), near);
    out[i] = p;
    if (p.w == 0.0f || !isfinite(p.x) || !isfinite(p.y)) return;
    int width = (int)cam[22], height = (int)cam[23];
    int x0 = (int)ceil(clamp(p.x, 0.0f, (float)width)), x1 = (int)floor(clamp(p.x, -1.0f, (float)(width - 1)));
    int y0 = (int)ceil(clamp(p.y, 0.0f, (float)height)), y1 = (int)floor(clamp(p.y, -1.0f, (float)(height - 1)));
    if (x0 < bounds[0]) atomic_min(&bounds[0], x0);
    if (y0 < bounds[1]) atomic_min(&bounds[1], y0);
    if (x1 > bounds[2]) atomic_max(&bounds[2], x1);
    if (y1 > bounds[3]) atomic_max(&bounds[3], y1);
}

inline float edge(float2 a, float2 b, float2 p)
{
    return (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x);
}

// A face on the screen: its corners, 1 / area, its corners' inverse depths and the pixel centres of its clipped box.
typedef struct {
    float2 p0, p1, p2;
    float inv_area, iz0, iz1, iz2;
    int x0, x1, y0, y1;
} FaceScreen;

// Face f's screen setup: 0 when it is not drawn (a corner behind the near plane, no area, or, with ``cull``,
// turned clockwise on the screen: x right, y down, so away from a camera with positive focal lengths and a proper
// rotation).
__attribute__((always_inline)) inline int face_screen(__global const int *faces, __global const float4 *proj, int f, int width, int height,
                       int cull, FaceScreen *s)
{
    float4 a = proj[faces[3 * f]], b = proj[faces[3 * f + 1]], c = proj[faces[3 * f + 2]];
    if (a.w == 0.0f || b.w == 0.0f || c.w == 0.0f) return 0;        // behind the near plane: dropped
    s->p0 = a.xy;
    s->p1 = b.xy;
    s->p2 = c.xy;
    float area = edge(s->p0, s->p1, s->p2);
    if (area == 0.0f || !isfinite(area) || (cull && area > 0.0f)) return 0;
    s->inv_area = 1.0f / area;
    // clamp in float first: vertices close to the camera plane project very far away
    s->x0 = (int)ceil(clamp(fmin(s->p0.x, fmin(s->p1.x, s->p2.x)), 0.0f, (float)width));
    s->x1 = (int)floor(clamp(fmax(s->p0.x, fmax(s->p1.x, s->p2.x)), -1.0f, (float)(width - 1)));
    s->y0 = (int)ceil(clamp(fmin(s->p0.y, fmin(s->p1.y, s->p2.y)), 0.0f, (float)height));
    s->y1 = (int)floor(clamp(fmax(s->p0.y, fmax(s->p1.y, s->p2.y)), -1.0f, (float)(height - 1)));
    s->iz0 = 1.0f / a.z;
    s->iz1 = 1.0f / b.z;
    s->iz2 = 1.0f / c.z;
    return 1;
}

// Whether the centre of pixel (x, y) lies in the face (edges included), and its perspective-correct depth there.
inline int face_depth(const FaceScreen *s, int x, int y, float *z)
{
    float2 p = (float2)((float)x, (float)y);
    float w0 = edge(s->p1, s->p2, p) * s->inv_area;
    float w1 = edge(s->p2, s->p0, p) * s->inv_area;
    float w2 = edge(s->p0, s->p1, p) * s->inv_area;
    if (w0 < 0.0f || w1 < 0.0f || w2 < 0.0f) return 0;
    *z = 1.0f / (w0 * s->iz0 + w1 * s->iz1 + w2 * s->iz2);
    return 1;
}

// The pixel centres (x, y) of face screen s's clipped box that its inside test holds for, with the depth z there:
// the one walk of the three raster kernels below (each a work item per face).
#define EACH_COVERED_PIXEL(s, x, y, z) \
    for (int y = (s).y0; y <= (s).y1; y++) \
        for (int x = (s).x0; x <= (s).x1; x++) \
            if (face_depth(&(s), x, y, &(z)))

// One work item per face: walk the pixel centres of its clipped bounding box.
__kernel void raster_triangles(__global const int *faces, __global const float4 *proj, int nfaces,
                               int width, int height, __global ulong *zbuf)
{
    int f = get_global_id(0);
    FaceScreen s;
    float z;
    if (f >= nfaces || !face_screen(faces, proj, f, width, height, 0, &s)) return;
    EACH_COVERED_PIXEL(s, x, y, z)
        atom_min(&zbuf[y * width + x], ((ulong)as_uint(z) << 32) | (ulong)(uint)f);
}

// raster_triangles' depths alone, for readers of depth that never need the face: camera z as its float bits
// (positive floats order as their bits, so a 32-bit atomic_min keeps the nearest; the same depths as the keys'
// upper halves), into a z-buffer of the pixels of ``box`` (x0, y0, width, height; project_bounds': every covered
// pixel lies in it) only, row after row. Empty pixels keep 0xFFFFFFFF. ``cull``: the faces turned away
// (face_screen) are skipped; for a closed, outward-oriented surface seen from outside, the nearest face at every
// pixel faces the camera, so the depths are the same at half the work (the caller decides: MeshRaster.culls).
__kernel void raster_depth(__global const int *faces, __global const float4 *proj, int nfaces,
                           int width, int height, int4 box, int cull, __global uint *zbuf)
{
    int f = get_global_id(0);
    FaceScreen s;
    float z;
    if (f >= nfaces || !face_screen(faces, proj, f, width, height, cull, &s)) return;
    EACH_COVERED_PIXEL(s, x, y, z)
        atomic_min(&zbuf[(y - box.y) * box.z + (x - box.x)], as_uint(z));
}

// raster_triangles' coverage alone (what kernel coverage reads from its z-buffer: some face's inside test held
// there), into the pixels of ``box`` (as raster_depth's, cleared to 0 by the caller): 255 where a face covers the
// pixel centre. No depth and no atomics: every writer of a pixel writes the same byte.
__kernel void raster_cover(__global const int *faces, __global const float4 *proj, int nfaces,
                           int width, int height, int4 box, __global uchar *mask)
{
    int f = get_global_id(0);
    FaceScreen s;
    float z;
    if (f >= nfaces || !face_screen(faces, proj, f, width, height, 0, &s)) return;
    EACH_COVERED_PIXEL(s, x, y, z)
        mask[(y - box.y) * box.z + (x - box.x)] = 255;
}

// Per pixel: face id (-1 = empty), depth (INFINITY = empty), perspective-correct barycentrics.
__kernel void resolve(__global const ulong *zbuf, __global const int *faces, __global const float4 *proj,
                      int width, int height, __global int *tri_id, __global float *depth, __global float *bary)
{
    int x = get_global_id(0), y = get_global_id(1);
    if (x >= width || y >= height) return;
    int i = y * width + x;
    ulong key = zbuf[i];
    if (key == EMPTY) {
        tri_id[i] = -1;
        depth[i] = INFINITY;
        bary[3 * i] = bary[3 * i + 1] = bary[3 * i + 2] = 0.0f;
        return;
    }
    int f = (int)(uint)(key & 0xFFFFFFFFUL);
    float4 a = proj[faces[3 * f]], b = proj[faces[3 * f + 1]], c = proj[faces[3 * f + 2]];
    float2 p = (float2)((float)x, (float)y);
    float inv_area = 1.0f / edge(a.xy, b.xy, c.xy);
    float w0 = edge(b.xy, c.xy, p) * inv_area / a.z;
    float w1 = edge(c.xy, a.xy, p) * inv_area / b.z;
    float w2 = edge(a.xy, b.xy, p) * inv_area / c.z;
    float s = 1.0f / (w0 + w1 + w2);
    tri_id[i] = f;
    depth[i] = as_float((uint)(key >> 32));
    bary[3 * i] = w0 * s;
    bary[3 * i + 1] = w1 * s;
    bary[3 * i + 2] = w2 * s;
}

// Per pixel: 255 where any face was drawn.
__kernel void coverage(__global const ulong *zbuf, int npixels, __global uchar *mask)
{
    int i = get_global_id(0);
    if (i >= npixels) return;
    mask[i] = zbuf[i] == EMPTY ? 0 : 255;
}

// Material layout (12 floats): colour A rgb, colour B rgb, pattern (0 plain, 1 checker, 2 stripes), period,
// lit (1 Lambert, 0 unlit), receives shadow (0/1), pad, pad.
// shadow = (centre x, centre y, sigma, strength) on the z = 0 floor, read from the texture coordinate.
__kernel void shade(__global const int *tri_id, __global const float *bary, __global const int *faces,
                    __global const float *normals, __global const float *texcoords,
                    __global const int *face_material, __global const float *materials,
                    float4 light, float ambient, float4 shadow, float4 empty_rgb, int n_object,
                    int npixels, __global uchar *rgb, __global uchar *mask)
{
    int i = get_global_id(0);
    if (i >= npixels) return;
    int f = tri_id[i];
    mask[i] = (f >= 0 && f < n_object) ? 255 : 0;
    float3 col;
    if (f < 0) {
        col = empty_rgb.xyz;
    } else {
        float b0 = bary[3 * i], b1 = bary[3 * i + 1], b2 = bary[3 * i + 2];
        int ia = faces[3 * f], ib = faces[3 * f + 1], ic = faces[3 * f + 2];
        float3 t = b0 * vload3(ia, texcoords) + b1 * vload3(ib, texcoords) + b2 * vload3(ic, texcoords);
        __global const float *m = materials + 12 * face_material[f];
        float period = m[7];
        float sel = 0.0f;
        if (m[6] == 1.0f) {
            float k = floor(t.x / period) + floor(t.y / period) + floor(t.z / period);
            sel = k - 2.0f * floor(k * 0.5f);
        } else if (m[6] == 2.0f) {
            float k = floor(t.z / period);
            sel = k - 2.0f * floor(k * 0.5f);
        }
        col = (1.0f - sel) * vload3(0, m) + sel * vload3(1, m);
        if (m[8] != 0.0f) {
            float3 n = b0 * vload3(ia, normals) + b1 * vload3(ib, normals) + b2 * vload3(ic, normals);
            float len = length(n);
            float lambert = len > 0.0f ? fmax(0.0f, dot(n / len, light.xyz)) : 0.0f;
            col *= ambient + (1.0f - ambient) * lambert;
        }
        if (m[9] != 0.0f) {
            float dx = t.x - shadow.x, dy = t.y - shadow.y;
            col *= 1.0f - shadow.w * exp(-(dx * dx + dy * dy) / (2.0f * shadow.z * shadow.z));
        }
    }
    col = clamp(col * 255.0f + 0.5f, 0.0f, 255.0f);
    rgb[3 * i] = (uchar)col.x;
    rgb[3 * i + 1] = (uchar)col.y;
    rgb[3 * i + 2] = (uchar)col.z;
}
