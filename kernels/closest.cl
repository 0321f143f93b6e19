// Nearest vertices and closest points on a triangle mesh, one work item per query point, float64
// (nodes/track/deform.py).
//
// nearest_in_grid (PointGrid.nearest; its reference is scipy's cKDTree, PointGrid.nearest_reference): the points
// sorted by the cell of a uniform grid (cell_start: CSR over the cells, x fastest), searched in shells of cells
// around the query's cell (Chebyshev ring r) until the best squared distance is below the shell's lower bound
// ((r - 1) h)^2 or the bound ``upper`` (strict, as cKDTree's distance_upper_bound): exact; -1 beyond ``upper``.
//
// closest_on_faces (SurfaceQuery.closest and its NumPy reference closest_reference, the same operations in the
// same order): the faces around
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

__attribute__((always_inline)) inline double3 closest_on_triangle(double3 p, double3 a, double3 b, double3 c)
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

// d[i], j[i]: distance and index (ids[k] of the sorted point k) of the nearest grid point to p[i] closer than
// ``upper`` (INFINITY: none), else INFINITY and -1.
__kernel void nearest_in_grid(__global const double* p, int n, __global const double* pts, __global const long* ids,
                              __global const int* cell_start, int nx, int ny, int nz, double lox, double loy,
                              double loz, double h, double upper, __global double* d, __global long* j)
{
    int i = get_global_id(0);
    if (i >= n) return;
    double3 x = vload3(i, p);
    // the query's cell (may lie outside the grid), clamped to a range that cannot overflow
    double gx = clamp(floor((x.x - lox) / h), -1.0e6, 1.0e6);
    double gy = clamp(floor((x.y - loy) / h), -1.0e6, 1.0e6);
    double gz = clamp(floor((x.z - loz) / h), -1.0e6, 1.0e6);
    int cx = (int)gx, cy = (int)gy, cz = (int)gz;
    // beyond this ring no cell of the grid is left
    int far = max(max(max(cx, nx - 1 - cx), max(cy, ny - 1 - cy)), max(cz, nz - 1 - cz));
    double best = upper * upper;
    long bj = -1;
    // rings nearer than this hold no cell of the grid (a query outside it)
    int near = max(max(max(0, -cx), cx - (nx - 1)), max(max(max(0, -cy), cy - (ny - 1)), max(max(0, -cz), cz - (nz - 1))));
    // ring r lies beyond the (2r - 1)^3 cells around the query's, (r - 1 + m) h away at least, m the query's least
    // distance to a face of its own cell (cells); less 1e-9 of a cell for rounding, and a ring is left out only when
    // that bound exceeds the best found by more than its rounding (so a point it holds could neither win nor tie)
    double fx = (x.x - lox) / h - gx, fy = (x.y - loy) / h - gy, fz = (x.z - loz) / h - gz;
    double m = fmax(fmin(fmin(fmin(fx, 1.0 - fx), fmin(fy, 1.0 - fy)), fmin(fz, 1.0 - fz)) - 1.0e-9, 0.0);
    for (int r = near; r <= far; r++) {
        double lb = (r - 1) * h, lbm = (r - 1 + m) * h;
        if (r > 0 && (lb * lb >= best || lbm * lbm > best * (1.0 + 1.0e-9))) break;
        for (int z = max(cz - r, 0); z <= min(cz + r, nz - 1); z++) {
            int az = abs(z - cz);
            for (int y = max(cy - r, 0); y <= min(cy + r, ny - 1); y++) {
                int ay = abs(y - cy);
                int inner = (az < r && ay < r);          // only the ring's two x ends
                int x0 = max(cx - r, 0), x1 = min(cx + r, nx - 1);
                for (int xx = x0; xx <= x1; xx++) {
                    if (inner && xx != cx - r && xx != cx + r) {
                        xx = cx + r - 1;                // jump to the far end
                        continue;
                    }
                    int c = (z * ny + y) * nx + xx;
                    for (int k = cell_start[c]; k < cell_start[c + 1]; k++) {
                        double3 e = vload3(k, pts) - x;
                        double dd = (e.x * e.x + e.y * e.y) + e.z * e.z;
                        if (dd < best) {
                            best = dd;
                            bj = ids[k];
                        }
                    }
                }
            }
        }
    }
    d[i] = bj >= 0 ? sqrt(best) : INFINITY;
    j[i] = bj;
}
