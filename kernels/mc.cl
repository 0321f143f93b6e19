// Marching cubes, row by row (Flying Edges, Schroeder et al. 2015). See nodes/mc.py for the case table and
// the NumPy twin.
//
// The volume V (nx, ny, nz), index (a * ny + b) * nz + c, is read in place. The kernels work on the padded
// point grid P (Nx, Ny, Nz) = (nx + 2, ny + 2, nz + 2): P(i, j, k) = V(i - 1, j - 1, k - 1), and the one-point
// border is 0 (closes shapes that touch the box) without a padded copy being made. Rows run along k, the
// contiguous axis. Point row (i, j) owns the vertices on the edges leaving its points along +i, +j, +k; cell
// row (i, j) is the cells whose lowest corner is on it.
//   mc_spans  per row of V: first and last k whose sample is not in the border's state (inside or not)
//   mc_count  per cell row: vertices owned, triangles, first k where the row owns a vertex
//             (the host turns these into exclusive prefix sums: first vertex id, first triangle)
//   mc_emit   per cell row: walks the same span, writes its vertices and triangles into one buffer
// Build options: VOXEL (uchar or float), MAX_TRIS (triangles per case, from the table).
#pragma OPENCL FP_CONTRACT OFF

#define BIG 0x7fffffff
#define GVOXEL __global const VOXEL

// V row of point row (i, j), or 0 for a border row
inline GVOXEL* vrow(GVOXEL* V, int nx, int ny, int nz, int i, int j)
{
    return (i >= 1 && i <= nx && j >= 1 && j <= ny) ? V + ((size_t)(i - 1) * ny + (j - 1)) * nz : 0;
}

inline float value(GVOXEL* row, int nz, int k)
{
    return (row && k >= 1 && k <= nz) ? (float)row[k - 1] : 0.0f;
}

inline int state(GVOXEL* row, int nz, int k, float level, int border)
{
    return (row && k >= 1 && k <= nz) ? (float)row[k - 1] > level : border;
}

// span of point row (i, j) in P's k, (BIG, -1) when the whole row is in the border's state
inline int2 span(__global const int2* spans, int nx, int ny, int i, int j)
{
    return (i >= 1 && i <= nx && j >= 1 && j <= ny) ? spans[(i - 1) * ny + (j - 1)] : (int2)(BIG, -1);
}

// One work-item per row of V. For uchar volumes the host guarantees 0 <= level < 255 (border outside) and
// v > level is v > floor(level); rows are skipped 16 samples at a time from both ends.
__kernel void mc_spans(GVOXEL* V, int nx, int ny, int nz, float level, int border, __global int2* spans)
{
    int b = get_global_id(0), a = get_global_id(1);
    if (b >= ny || a >= nx) return;
    GVOXEL* row = V + ((size_t)a * ny + b) * nz;
    int first = BIG, last = -1;
#ifdef VOXEL_UCHAR
    uchar t = (uchar)level;
    int c = 0;
    while (c + 16 <= nz && !any(vload16(0, row + c) > (uchar16)t)) c += 16;
    for (; c < nz; c++)
        if (row[c] > t) { first = c; break; }
    if (first != BIG) {
        int e = nz;
        while (e - 16 > first && !any(vload16(0, row + e - 16) > (uchar16)t)) e -= 16;
        for (c = e - 1; c >= first; c--)
            if (row[c] > t) { last = c; break; }
    }
#else
    for (int c = 0; c < nz; c++)
        if (((float)row[c] > level) != border) { first = c; break; }
    for (int c = nz - 1; c >= first && first != BIG; c--)
        if (((float)row[c] > level) != border) { last = c; break; }
#endif
    spans[(size_t)a * ny + b] = first == BIG ? (int2)(BIG, -1) : (int2)(first + 1, last + 1);
}

// states of the four point rows r = di + 2 dj of cell row (i, j) at k: bit r
inline int quad(GVOXEL* const* p, int nz, int k, float level, int border)
{
    return state(p[0], nz, k, level, border) | (state(p[1], nz, k, level, border) << 1)
         | (state(p[2], nz, k, level, border) << 2) | (state(p[3], nz, k, level, border) << 3);
}

// counts[0][row]: vertices owned, [1]: triangles, [2]: first k with an owned vertex (BIG if none)
__kernel void mc_count(GVOXEL* V, int nx, int ny, int nz, float level, int border, __global const int2* spans,
                       __global const int* ntri, __global int* counts)
{
    int j = get_global_id(0), i = get_global_id(1);
    int Nx = nx + 2, Ny = ny + 2;
    if (j >= Ny - 1 || i >= Nx - 1) return;
    int rows = (Nx - 1) * (Ny - 1), row = i * (Ny - 1) + j;
    int2 s0 = span(spans, nx, ny, i, j), s1 = span(spans, nx, ny, i + 1, j);
    int2 s2 = span(spans, nx, ny, i, j + 1), s3 = span(spans, nx, ny, i + 1, j + 1);
    int lo = min(min(s0.x, s1.x), min(s2.x, s3.x)), hi = max(max(s0.y, s1.y), max(s2.y, s3.y));
    int nv = 0, nt = 0, vstart = BIG;
    if (hi >= 0) {
        GVOXEL* p[4] = {vrow(V, nx, ny, nz, i, j), vrow(V, nx, ny, nz, i + 1, j),
                        vrow(V, nx, ny, nz, i, j + 1), vrow(V, nx, ny, nz, i + 1, j + 1)};
        int a = quad(p, nz, lo - 1, level, border);
        for (int k = lo - 1; k <= hi; k++) {
            int b = quad(p, nz, k + 1, level, border);
            int s = a & 1;
            int v = (s != ((a >> 1) & 1)) + (s != ((a >> 2) & 1)) + (s != (b & 1));
            if (v && vstart == BIG) vstart = k;
            nv += v;
            nt += ntri[a | (b << 4)];  // corner c = di + 2 dj + 4 dk
            a = b;
        }
    }
    counts[row] = nv;
    counts[rows + row] = nt;
    counts[2 * rows + row] = vstart;
}

// id of the vertex on axis a of a point whose row has `base` vertices before it and crossing bits `f`
inline int vertex_id(int base, int f, int a)
{
    return base + (a > 0 ? (f & 1) : 0) + (a > 1 ? ((f >> 1) & 1) : 0);
}

// crossing bits (+i, +j, +k) of point row n = di + 3 dj from the 9-row states S at k and T at k + 1
inline int crossing(int S, int T, int n)
{
    return (((S ^ (S >> 1)) >> n) & 1) | ((((S ^ (S >> 3)) >> n) & 1) << 1) | ((((S ^ T) >> n) & 1) << 2);
}

// offsets (3, rows + 1): [0] first vertex id of each cell row (total last), [1] first triangle, [2] first k
// with an owned vertex. out: vertices (3 floats each) then, from 3 * nverts, triangles (3 int bit patterns).
__kernel void mc_emit(GVOXEL* V, int nx, int ny, int nz, float level, int border, __global const int2* spans,
                      __global const int* ntri, __global const char* table, __global const int* offsets,
                      float4 bmin, float4 vs, __global float* out)
{
    int j = get_global_id(0), i = get_global_id(1);
    int Nx = nx + 2, Ny = ny + 2;
    if (j >= Ny - 1 || i >= Nx - 1) return;
    int rows = (Nx - 1) * (Ny - 1), R = rows + 1, own = i * (Ny - 1) + j;
    int nverts = offsets[rows], tri = offsets[R + own];
    int nv = offsets[own + 1] - offsets[own], nt = offsets[R + own + 1] - tri;
    if (nv == 0 && nt == 0) return;
    int2 s0 = span(spans, nx, ny, i, j), s1 = span(spans, nx, ny, i + 1, j);
    int2 s2 = span(spans, nx, ny, i, j + 1), s3 = span(spans, nx, ny, i + 1, j + 1);
    int lo = min(min(s0.x, s1.x), min(s2.x, s3.x)), hi = max(max(s0.y, s1.y), max(s2.y, s3.y));
    // the four point rows r = di + 2 dj whose vertices the cells use: running vertex counters
    int counter[4], start = offsets[2 * R + own];
    for (int r = 0; r < 4; r++) {
        int ri = i + (r & 1), rj = j + (r >> 1), valid = ri < Nx - 1 && rj < Ny - 1, idx = ri * (Ny - 1) + rj;
        counter[r] = valid ? offsets[idx] : 0;
        if (nt > 0) start = min(start, valid ? offsets[2 * R + idx] : BIG);
    }
    if (nt > 0) start = min(start, lo - 1);
    // the nine point rows n = di + 3 dj (di, dj < 3) whose samples give those crossings; (2, 2) unused
    GVOXEL* p[8];
    for (int n = 0; n < 8; n++) p[n] = vrow(V, nx, ny, nz, i + n % 3, j + n / 3);
    int S = 0;
    for (int n = 0; n < 8; n++) S |= state(p[n], nz, start, level, border) << n;
    for (int k = start; k <= hi; k++) {
        int T = 0;
        for (int n = 0; n < 8; n++) T |= state(p[n], nz, k + 1, level, border) << n;
        // vertices of point (i, j, k)
        int f = crossing(S, T, 0);
        for (int a = 0; a < 3; a++) {
            if (!((f >> a) & 1)) continue;
            int id = vertex_id(counter[0], f, a);
            float v0 = value(p[0], nz, k);
            float v1 = value(p[a == 0 ? 1 : (a == 1 ? 3 : 0)], nz, k + (a == 2));
            float t = (level - v0) / (v1 - v0);
            float x = bmin.x + ((float)i - 0.5f) * vs.x;
            float y = bmin.y + ((float)j - 0.5f) * vs.y;
            float z = bmin.z + ((float)k - 0.5f) * vs.z;
            if (a == 0) x = x + t * vs.x;
            if (a == 1) y = y + t * vs.y;
            if (a == 2) z = z + t * vs.z;
            out[3 * id] = x;
            out[3 * id + 1] = y;
            out[3 * id + 2] = z;
        }
        // triangles of cell (i, j, k); corner c = di + 2 dj + 4 dk
        int c = (S & 3) | ((S >> 1) & 12) | ((T & 3) << 4) | ((T & 24) << 3);
        int n = nt > 0 ? ntri[c] : 0;
        for (int q = 0; q < 3 * n; q++) {
            int e = table[c * 3 * MAX_TRIS + q];
            // edge e: from corner (dx, dy, dz) along axis a (same numbering as nodes/mc.py EDGES)
            int a = e >> 2, b0 = e & 1, b1 = (e >> 1) & 1;  // the two other corner bits, low axis first
            int dx = a == 0 ? 0 : b0;
            int dy = a == 1 ? 0 : (a == 0 ? b0 : b1);
            int dz = a == 2 ? 0 : b1;
            int r = dx + 2 * dy, m = dx + 3 * dy;
            int cur = crossing(S, T, m);
            int id = dz ? vertex_id(counter[r] + popcount(cur), crossing(T, T, m), a) : vertex_id(counter[r], cur, a);
            out[3 * nverts + 3 * tri + q] = as_float(id);
        }
        tri += n;
        for (int r = 0; r < 4; r++) counter[r] += popcount(crossing(S, T, (r & 1) + 3 * (r >> 1)));
        S = T;
    }
}
