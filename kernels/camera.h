// Camera model shared by the kernels: reads one camera of the packed (N, 32) float layout written by
// nodegraph.cameras.Cameras.pack() and projects a world point exactly like Cameras.project:
//   x_cam = Rt X;  x_n = x_cam.xy / x_cam.z;  x_d = distort(x_n);  u = K x_d
// cam[0..11] Rt row-major, cam[12..16] fx skew cx fy cy, cam[17..21] k1 k2 p1 p2 k3,
// cam[22..23] width height, cam[24] z sign (bare-P cameras).
// The steps are separate functions for kernels that need one of them (the hull tests the depth before
// dividing, and bounds whole boxes in camera space). Every sum is written left to right, so a kernel
// compiled with `#pragma OPENCL FP_CONTRACT OFF` before the #include can be mirrored bit for bit in NumPy
// float32 (nodegraph/cameras.py:project_packed_f32).
#ifndef VOLCAP_CAMERA_H
#define VOLCAP_CAMERA_H

#define CAM_FLOATS 32   // floats per camera (nodegraph.cameras.PACK_FLOATS)

// Camera coordinates Rt X; z * cam[24] > 0 in front of the camera.
inline float3 camera_point(__global const float* cam, float3 X)
{
    return (float3)(((cam[0] * X.x + cam[1] * X.y) + cam[2] * X.z) + cam[3],
                    ((cam[4] * X.x + cam[5] * X.y) + cam[6] * X.z) + cam[7],
                    ((cam[8] * X.x + cam[9] * X.y) + cam[10] * X.z) + cam[11]);
}

inline int has_distortion(__global const float* cam)
{
    return cam[17] != 0.0f || cam[18] != 0.0f || cam[19] != 0.0f || cam[20] != 0.0f || cam[21] != 0.0f;
}

// OpenCV lens distortion (k1 k2 p1 p2 k3) of normalised coordinates (x_cam.xy / x_cam.z).
inline float2 distort_point(__global const float* cam, float2 n)
{
    if (!has_distortion(cam)) return n;
    float x = n.x, y = n.y;
    float k1 = cam[17], k2 = cam[18], p1 = cam[19], p2 = cam[20], k3 = cam[21];
    float r2 = x * x + y * y;
    float radial = 1.0f + r2 * (k1 + r2 * (k2 + r2 * k3));
    float xd = (x * radial + ((2.0f * p1) * x) * y) + p2 * (r2 + (2.0f * x) * x);
    float yd = (y * radial + p1 * (r2 + (2.0f * y) * y)) + ((2.0f * p2) * x) * y;
    return (float2)(xd, yd);
}

// Pixel coordinates K x_d (pixel centres at integers).
inline float2 pixel_point(__global const float* cam, float2 d)
{
    return (float2)((cam[12] * d.x + cam[13] * d.y) + cam[14], cam[15] * d.y + cam[16]);
}

// Projects X; returns the pixel (u, v) and writes the depth (camera z, > 0 in front) to *depth.
__attribute__((always_inline)) inline float2 project_point(__global const float* cam, float3 X, float* depth)
{
    float3 xc = camera_point(cam, X);
    *depth = xc.z * cam[24];
    return pixel_point(cam, distort_point(cam, xc.xy / xc.z));
}

#endif
