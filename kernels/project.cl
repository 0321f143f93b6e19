// Project points into every camera: uv[view, i] and depth[view, i] (see camera.h for the model).
// Points are relative to the origin the cameras were packed with (Cameras.pack(origin)).
#include "camera.h"

__kernel void project_points(__global const float* cams, __global const float* points, int n_points,
                             __global float2* uv, __global float* depth)
{
    int i = get_global_id(0), view = get_global_id(1);
    if (i >= n_points) return;
    float3 X = (float3)(points[3 * i], points[3 * i + 1], points[3 * i + 2]);
    float d;
    uv[view * n_points + i] = project_point(cams + CAM_FLOATS * view, X, &d);
    depth[view * n_points + i] = d;
}
