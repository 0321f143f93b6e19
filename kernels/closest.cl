// Closest points on a triangle mesh, one work item per query point (nodes/track/deform.py: SurfaceQuery.closest
// and its NumPy reference closest_reference, the same operations in the same order, float64): the faces around
// the point's nearest vertex (a padded vertex -> faces table, -1 padding skipped) are each tested with Ericson's
// closest point on a triangle (Real-Time Collision Detection 5.1.5: region parameters v, w on scalars, the
// point a + v ab + w ac at the end; later region tests win: vertex a, b, c, then edges ab, ac, bc, else inside),
// and the first face of the smallest distance is kept.
#pragma OPENCL FP_CONTRACT OFF
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

inline double dot3d(double3 a, double3 b)
{
    return (a.x * b.x + a.y * b.y) + a.z * b.z;
}

inline double clamp01(double x)
{
    return x < 0.0 ? 0.0 : (x > 1.0 ? 1.0 : x);
}

inline double3 closest_on_triangle(double3 p, double3 a, double3 b, double3 c)
{
    double3 ab = b - a, ac = c - a, ap = p - a;
    double d1 = dot3d(ab, ap), d2 = dot3d(ac, ap);
    double3 bp = p - b;
    double d3 = dot3d(ab, bp), d4 = dot3d(ac, bp);
    double3 cp = p - c;
    double d5 = dot3d(ab, cp), d6 = dot3d(ac, cp);
    double va = d3 * d6 - d5 * d4, vb = d5 * d2 - d1 * d6, vc = d1 * d4 - d3 * d2;
    double v, w;
    if (d1 <= 0.0 && d2 <= 0.0) {                                       // vertex a
        v = 0.0; w = 0.0;
    } else if (d3 >= 0.0 && d4 <= d3) {                                 // vertex b
        v = 1.0; w = 0.0;
    } else if (d6 >= 0.0 && d5 <= d6) {                                 // vertex c
        v = 0.0; w = 1.0;
    } else if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {                   // edge ab
        v = clamp01(d1 - d3 != 0.0 ? d1 / (d1 - d3) : 0.0); w = 0.0;
    } else if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {                   // edge ac
        v = 0.0; w = clamp01(d2 - d6 != 0.0 ? d2 / (d2 - d6) : 0.0);
    } else if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {     // edge bc
        double den = (d4 - d3) + (d5 - d6);
        double t = clamp01(den != 0.0 ? (d4 - d3) / den : 0.0);
        v = 1.0 - t; w = t;
    } else {                                                            // inside the face
        double denom = va + vb + vc;
        v = denom != 0.0 ? vb / denom : 0.0;
        w = denom != 0.0 ? vc / denom : 0.0;
    }
    return a + v * ab + w * ac;
}

// q[i], d[i], face[i]: the closest point to p[i] on the faces vf[nearest[i], :] (corners: per face a, b, c).
__kernel void closest_on_faces(__global const double* p, __global const long* nearest, __global const long* vf,
                               int width, __global const double* corners, int n,
                               __global double* q, __global double* d, __global long* face)
{
    int i = get_global_id(0);
    if (i >= n) return;
    double3 x = vload3(i, p);
    long j = nearest[i];
    double best = INFINITY;
    double3 bq = x;
    long bf = -1;
    for (int m = 0; m < width; m++) {
        long f = vf[j * width + m];
        if (f < 0) continue;
        double3 r = closest_on_triangle(x, vload3(3 * f, corners), vload3(3 * f + 1, corners), vload3(3 * f + 2, corners));
        double3 e = r - x;
        double dist = sqrt(dot3d(e, e));
        if (dist < best) {
            best = dist; bq = r; bf = f;
        }
    }
    vstore3(bq, i, q);
    d[i] = best;
    face[i] = bf;
}
