// The tracker's silhouette term (nodes/track/deform.py silhouette_rows; its NumPy reference is
// silhouette_rows_reference, mirrored bit for bit): per (point, view) the signed distance outline (alpha = 0.5 +
// pixels inside, nodes.common.silhouettes.Silhouettes.distance_outline) sampled bilinearly at the point's
// projection; where the point is seen and outside (alpha < 0.5), the outline's gradient through the projection by
// central differences of `step` voxels (each point moved by h metres along one axis, projected again) and the
// distance to move in along it.
//
// The projection is camera.h's float32 arithmetic on the point rounded to float32 (the reference's astype); the
// sampling is float64, in the reference's order: clamp of the pixel coordinates to [0, size - 1.001] (NaN to 0,
// as np.nan_to_num then np.clip give), bilinear weights (1 - fx)(1 - fy), fx(1 - fy), (1 - fx)fy, fx fy summed
// left to right.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF
#include "camera.h"

// The outline at X's projection into view `cam` (field W x H, row-major); 0 where X is behind the camera or
// projects outside [0, W - 1] x [0, H - 1] (the value is then still written, from the clamped place).
inline int outline_sample(__global const float* cam, __global const float* field, int W, int H, double3 X,
                          double* value)
{
    float depth;
    float2 uv = project_point(cam, convert_float3(X), &depth);
    double u = (double)uv.x, w = (double)uv.y;
    int ok = depth > 0.0f && u >= 0.0 && u <= (double)(W - 1) && w >= 0.0 && w <= (double)(H - 1);
    double uc = fmin(fmax(u, 0.0), (double)W - 1.001);     // fmax(NaN, 0) = 0: np.nan_to_num's 0
    double wc = fmin(fmax(w, 0.0), (double)H - 1.001);
    long x0 = (long)uc, y0 = (long)wc;
    double fx = uc - (double)x0, fy = wc - (double)y0;
    __global const float* row0 = field + y0 * W;
    __global const float* row1 = row0 + W;
    *value = (1.0 - fx) * (1.0 - fy) * (double)row0[x0] + fx * (1.0 - fy) * (double)row0[x0 + 1]
             + (1.0 - fx) * fy * (double)row1[x0] + fx * fy * (double)row1[x0 + 1];
    return ok;
}

// One work-item per (point i, view v): keep[v * n + i] = 1 where the point is pulled in by view v, with the unit
// direction g[(v * n + i) * 3 ..] and the distance d[v * n + i] (voxels) to move along it.
__kernel void outline_pull(__global const double* X, int n, __global const float* cams,
                           __global const float* fields, __global const long* field_off, __global const int* field_w,
                           __global const int* field_h, double h, double step,
                           __global uchar* keep, __global double* g, __global double* d)
{
    int i = get_global_id(0), v = get_global_id(1);
    if (i >= n) return;
    size_t o = (size_t)v * n + i;
    __global const float* cam = cams + v * CAM_FLOATS;
    __global const float* field = fields + field_off[v];
    int W = field_w[v], H = field_h[v];
    keep[o] = 0;
    if (W < 2 || H < 2) return;                 // a view that sees nothing (track.crop keeps 1 x 1 of an empty mask)
    double3 x = (double3)(X[3 * i], X[3 * i + 1], X[3 * i + 2]);
    double a0;
    int ok = outline_sample(cam, field, W, H, x, &a0);
    if (!(ok && a0 < 0.5)) return;
    double gr[3];
    for (int axis = 0; axis < 3; axis++) {
        double3 e = (double3)(axis == 0 ? h : 0.0, axis == 1 ? h : 0.0, axis == 2 ? h : 0.0);
        double ap, am;
        int okp = outline_sample(cam, field, W, H, x + e, &ap);
        int okm = outline_sample(cam, field, W, H, x - e, &am);
        gr[axis] = okp && okm ? (ap - am) / (2.0 * step) : 0.0;
    }
    double norm = sqrt(gr[0] * gr[0] + gr[1] * gr[1] + gr[2] * gr[2]);
    if (!(norm > 1e-6)) return;
    keep[o] = 1;
    g[3 * o] = gr[0] / norm;
    g[3 * o + 1] = gr[1] / norm;
    g[3 * o + 2] = gr[2] / norm;
    d[o] = (0.5 - a0) / norm;
}
