// Marching cubes, row by row (Flying Edges style). See nodes/mc.py for the case table and the NumPy twin.
//
// The padded volume P (Nx, Ny, Nz), index (i * Ny + j) * Nz + k, is walked along i. Work-item (k, j) owns
// "point row" (j, k): the vertices on the grid edges leaving its points along +i, +j, +k, and "cell row"
// (j, k): the cells whose lowest corner is on it. A cell row reads the vertex ids of four point rows,
// (j, k), (j+1, k), (j, k+1), (j+1, k+1), numbered row by row from the prefix sums of mc_count.
// Build options: VOXEL (uchar or float), MAX_TRIS (triangles per case, from the table).
#pragma OPENCL FP_CONTRACT OFF

#define BIG 0x7fffffff

inline int inside(__global const VOXEL* P, int Nx, int Ny, int Nz, int i, int j, int k, float level)
{
    if (i >= Nx || j >= Ny || k >= Nz) return 0;
    return (float)P[((size_t)i * Ny + j) * Nz + k] > level;
}

// bits 0, 1, 2: the edges along i, j, k leaving point (i, j, k) cross the level
inline int crossings(__global const VOXEL* P, int Nx, int Ny, int Nz, int i, int j, int k, float level)
{
    if (i >= Nx || j >= Ny || k >= Nz) return 0;
    int s = inside(P, Nx, Ny, Nz, i, j, k, level);
    return (s != inside(P, Nx, Ny, Nz, i + 1, j, k, level))
         | ((s != inside(P, Nx, Ny, Nz, i, j + 1, k, level)) << 1)
         | ((s != inside(P, Nx, Ny, Nz, i, j, k + 1, level)) << 2);
}

inline int cell_case(__global const VOXEL* P, int Nx, int Ny, int Nz, int i, int j, int k, float level)
{
    int c = 0;
    for (int n = 0; n < 8; n++)
        c |= inside(P, Nx, Ny, Nz, i + (n & 1), j + ((n >> 1) & 1), k + ((n >> 2) & 1), level) << n;
    return c;
}

// occupied[j * Nz + k]: some sample of point row (j, k) is above the level
__kernel void mc_rows(__global const VOXEL* P, int Nx, int Ny, int Nz, float level, __global uchar* occupied)
{
    int k = get_global_id(0), j = get_global_id(1);
    if (k >= Nz || j >= Ny) return;
    size_t plane = (size_t)Ny * Nz, at = (size_t)j * Nz + k;
    int any = 0;
    for (int i = 0; i < Nx; i++) any |= (float)P[at + i * plane] > level;
    occupied[at] = (uchar)any;
}

// counts[0][row]: vertices owned, [1]: triangles, [2] / [3]: first / last position i where either is nonzero.
// Slides along i keeping the four samples (j, k), (j+1, k), (j, k+1), (j+1, k+1) of the current plane.
__kernel void mc_count(__global const VOXEL* P, int Nx, int Ny, int Nz, float level, __global const int* ntri,
                       __global const uchar* occupied, __global int* counts)
{
    int k = get_global_id(0), j = get_global_id(1);
    if (k >= Nz - 1 || j >= Ny - 1) return;
    int rows = (Ny - 1) * (Nz - 1), row = j * (Nz - 1) + k;
    size_t plane = (size_t)Ny * Nz, at = (size_t)j * Nz + k;
    int nv = 0, nt = 0, first = BIG, last = -1;
    if (!(occupied[at] | occupied[at + 1] | occupied[at + Nz] | occupied[at + Nz + 1])) {
        // nothing above the level around this row: no vertex, no triangle
        counts[row] = 0;
        counts[rows + row] = 0;
        counts[2 * rows + row] = BIG;
        counts[3 * rows + row] = -1;
        return;
    }
    // bit 0: (j, k), 1: (j+1, k), 2: (j, k+1), 3: (j+1, k+1) -- the cell case's corner order
    int a = ((float)P[at] > level) | (((float)P[at + Nz] > level) << 1) | (((float)P[at + 1] > level) << 2)
          | (((float)P[at + Nz + 1] > level) << 3);
    for (int i = 0; i < Nx - 1; i++) {
        size_t q = at + (size_t)(i + 1) * plane;
        int b = ((float)P[q] > level) | (((float)P[q + Nz] > level) << 1) | (((float)P[q + 1] > level) << 2)
              | (((float)P[q + Nz + 1] > level) << 3);
        int s = a & 1;
        int v = (s != (b & 1)) + (s != ((a >> 1) & 1)) + (s != ((a >> 2) & 1));
        int c = (a & 1) | ((a & 2) << 1) | ((a & 4) << 2) | ((a & 8) << 3)      // corners with i bit 0
              | ((b & 1) << 1) | ((b & 2) << 2) | ((b & 4) << 3) | ((b & 8) << 4); // and i bit 1
        int t = ntri[c];
        if (v + t) {
            first = min(first, i);
            last = i;
        }
        nv += v;
        nt += t;
        a = b;
    }
    // the last plane is padding: nothing crosses there
    counts[row] = nv;
    counts[rows + row] = nt;
    counts[2 * rows + row] = first;
    counts[3 * rows + row] = last;
}

// id of the vertex on axis a of a point whose row has `base` vertices before it and crossing bits `f`
inline int vertex_id(int base, int f, int a)
{
    return base + (a > 0 ? (f & 1) : 0) + (a > 1 ? ((f >> 1) & 1) : 0);
}

// offsets[0][row]: first vertex id of the row, [1]: first triangle, [2] / [3]: span (from mc_count)
__kernel void mc_emit(__global const VOXEL* P, int Nx, int Ny, int Nz, float level, __global const int* ntri,
                      __global const char* table, __global const int* offsets, int rows, float4 bmin, float4 vs,
                      __global float* verts, __global int* faces)
{
    int k = get_global_id(0), j = get_global_id(1);
    if (k >= Nz - 1 || j >= Ny - 1) return;
    int own = j * (Nz - 1) + k;
    int last = offsets[3 * rows + own];
    if (last < 0) return;
    // the four point rows: (j, k), (j+1, k), (j, k+1), (j+1, k+1); rows past the grid own nothing
    int rj[4] = {j, j + 1, j, j + 1}, rk[4] = {k, k, k + 1, k + 1};
    int counter[4], start = BIG;
    for (int r = 0; r < 4; r++) {
        int valid = rj[r] < Ny - 1 && rk[r] < Nz - 1;
        int idx = rj[r] * (Nz - 1) + rk[r];
        counter[r] = valid ? offsets[idx] : 0;
        if (valid) start = min(start, offsets[2 * rows + idx]);
    }
    int tri = offsets[rows + own];
    int cur[4], nxt[4];
    for (int r = 0; r < 4; r++) cur[r] = crossings(P, Nx, Ny, Nz, start, rj[r], rk[r], level);
    for (int i = start; i <= last; i++) {
        for (int r = 0; r < 4; r++) nxt[r] = crossings(P, Nx, Ny, Nz, i + 1, rj[r], rk[r], level);
        // vertices of this point row at i
        int f = cur[0];
        for (int a = 0; a < 3; a++) {
            if (!((f >> a) & 1)) continue;
            int id = vertex_id(counter[0], f, a);
            int ii = i + (a == 0), jj = j + (a == 1), kk = k + (a == 2);
            float v0 = (float)P[((size_t)i * Ny + j) * Nz + k];
            float v1 = (float)P[((size_t)ii * Ny + jj) * Nz + kk];
            float t = (level - v0) / (v1 - v0);
            float x = bmin.x + ((float)i - 0.5f) * vs.x;
            float y = bmin.y + ((float)j - 0.5f) * vs.y;
            float z = bmin.z + ((float)k - 0.5f) * vs.z;
            if (a == 0) x = x + t * vs.x;
            if (a == 1) y = y + t * vs.y;
            if (a == 2) z = z + t * vs.z;
            verts[3 * id] = x;
            verts[3 * id + 1] = y;
            verts[3 * id + 2] = z;
        }
        // triangles of cell i
        if (i < Nx - 1) {
            int c = cell_case(P, Nx, Ny, Nz, i, j, k, level);
            int n = ntri[c];
            for (int q = 0; q < 3 * n; q++) {
                int e = table[c * 3 * MAX_TRIS + q];
                // edge e: from corner c0 along axis a (same numbering as nodes/mc.py EDGES)
                int a = e >> 2, rest = e & 3;
                int b0 = rest & 1, b1 = rest >> 1;      // the two other corner bits, low axis first
                int dx = a == 0 ? 0 : b0;
                int dy = a == 1 ? 0 : (a == 0 ? b0 : b1);
                int dz = a == 2 ? 0 : b1;
                int r = dy + 2 * dz;
                int id = dx ? vertex_id(counter[r] + popcount(cur[r]), nxt[r], a) : vertex_id(counter[r], cur[r], a);
                faces[3 * tri + q] = id;
            }
            tri += n;
        }
        for (int r = 0; r < 4; r++) {
            counter[r] += popcount(cur[r]);
            cur[r] = nxt[r];
        }
    }
}
