// Camera model shared by the kernels: reads one camera of the packed (N, 32) float layout written by
// nodegraph.cameras.Cameras.pack() and projects a world point exactly like Cameras.project:
//   x_cam = Rt X;  x_n = x_cam.xy / x_cam.z;  x_d = distort(x_n);  u = K x_d
// cam[0..11] Rt row-major, cam[12..16] fx skew cx fy cy, cam[17..21] k1 k2 p1 p2 k3,
// cam[22..23] width height, cam[24] z sign (bare-P cameras).
#ifndef VOLCAP_CAMERA_H
#define VOLCAP_CAMERA_H

// Projects X; returns the pixel (u, v) and writes the depth (camera z, > 0 in front) to *depth.
inline float2 project_point(__global const float* cam, float3 X, float* depth)
{
    float xc = cam[0] * X.x + cam[1] * X.y + cam[2]  * X.z + cam[3];
    float yc = cam[4] * X.x + cam[5] * X.y + cam[6]  * X.z + cam[7];
    float zc = cam[8] * X.x + cam[9] * X.y + cam[10] * X.z + cam[11];
    float x = xc / zc, y = yc / zc;
    float k1 = cam[17], k2 = cam[18], p1 = cam[19], p2 = cam[20], k3 = cam[21];
    if (k1 != 0.0f || k2 != 0.0f || p1 != 0.0f || p2 != 0.0f || k3 != 0.0f) {
        float r2 = x * x + y * y;
        float radial = 1.0f + r2 * (k1 + r2 * (k2 + r2 * k3));
        float xd = x * radial + 2.0f * p1 * x * y + p2 * (r2 + 2.0f * x * x);
        float yd = y * radial + p1 * (r2 + 2.0f * y * y) + 2.0f * p2 * x * y;
        x = xd; y = yd;
    }
    *depth = zc * cam[24];
    return (float2)(cam[12] * x + cam[13] * y + cam[14], cam[15] * y + cam[16]);
}

#endif
