// Mesh fairing on the device (nodes/mesh/fairing.py mirrors each kernel in NumPy float32, same order of
// operations): face normals, vertex normals over each vertex's faces (CSR: off, idx), filtered face normals
// (the mean of their corners' normals: normals are smoothed before positions), the fairing step (each vertex
// moves along the filtered normals of its faces towards their planes, and tangentially towards the mean of its
// neighbours), and the clamp of every vertex to its shell interval along a fixed line.
#pragma OPENCL FP_CONTRACT OFF

inline float3 cross3(float3 a, float3 b)
{
    return (float3)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}

inline float dot3(float3 a, float3 b)
{
    return (a.x * b.x + a.y * b.y) + a.z * b.z;
}

inline float3 unit3(float3 x)
{
    float l = sqrt(dot3(x, x));
    return l > 0.0f ? x / l : x;
}

// fn[i] = (b - a) x (c - a): the face normal times twice its area.
__kernel void face_normals(__global const float* v, __global const int* f, int nf, __global float* fn)
{
    int i = get_global_id(0);
    if (i >= nf) return;
    float3 a = vload3(f[3 * i], v), b = vload3(f[3 * i + 1], v), c = vload3(f[3 * i + 2], v);
    vstore3(cross3(b - a, c - a), i, fn);
}

// vn[i] = unit(sum of face vectors fv over vertex i's faces).
__kernel void vertex_normals(__global const float* fv, __global const int* off, __global const int* idx, int nv,
                             __global float* vn)
{
    int i = get_global_id(0);
    if (i >= nv) return;
    float3 s = (float3)(0.0f);
    for (int j = off[i]; j < off[i + 1]; j++) s = s + vload3(idx[j], fv);
    vstore3(unit3(s), i, vn);
}

// m[i] = unit(vn[a] + vn[b] + vn[c]) of face i.
__kernel void face_filter(__global const float* vn, __global const int* f, int nf, __global float* m)
{
    int i = get_global_id(0);
    if (i >= nf) return;
    float3 s = (vload3(f[3 * i], vn) + vload3(f[3 * i + 1], vn)) + vload3(f[3 * i + 2], vn);
    vstore3(unit3(s), i, m);
}

// One fairing step: out = p + (mean over the faces of m (m . (centroid - p))) + lam_t * (the neighbours' mean
// minus p, projected onto the tangent plane of vn[i]). Each neighbour of a closed mesh's vertex is in two of
// its faces, so the neighbours' mean is (sum of the faces' corners - count p) / (2 count). A vertex with a
// face turned against its filtered normal (a fold) takes half an umbrella step instead, which opens the fold.
__kernel void fair_step(__global const float* v, __global const int* f, __global const int* off,
                        __global const int* idx, __global const float* m, __global const float* vn, float lam_t,
                        int nv, __global float* out)
{
    int i = get_global_id(0);
    if (i >= nv) return;
    float3 p = vload3(i, v);
    int s = off[i], e = off[i + 1];
    if (e == s) {
        vstore3(p, i, out);
        return;
    }
    float3 dn = (float3)(0.0f), ring = (float3)(0.0f);
    int folded = 0;
    for (int j = s; j < e; j++) {
        int k = idx[j];
        float3 a = vload3(f[3 * k], v), b = vload3(f[3 * k + 1], v), c = vload3(f[3 * k + 2], v);
        float3 corners = (a + b) + c;
        float3 mf = vload3(k, m);
        dn = dn + mf * dot3(mf, corners / 3.0f - p);
        ring = ring + corners;
        folded |= dot3(cross3(b - a, c - a), mf) < 0.0f;
    }
    float cnt = (float)(e - s);
    float3 t = (ring - cnt * p) / (2.0f * cnt) - p;
    if (folded) {
        vstore3(p + 0.5f * t, i, out);
        return;
    }
    dn = dn / cnt;
    float3 n = vload3(i, vn);
    t = t - dot3(t, n) * n;
    vstore3((p + dn) + lam_t * t, i, out);
}

// The shell clamp along fixed lines: vertex i's line runs from base = centre[i] - reach axis[i] along the unit
// axis[i] over 2 reach;
// its shell interval (from kernel shell_interval, parameters along the line) is shell[i] = (in_lo, in_hi,
// out_lo, out_hi). The vertex's offset along the line is clamped to [in_hi, out_lo] (the deep side: the first
// point outside level tau_in, 0 when base is not that deep; the far side: the last point inside level tau_out),
// its offset across the line to at most `across`. A line whose base is not inside even at tau_out has no
// shell: only the offsets' limits apply ([0, 1] along, `across` across). With `onto` the vertex goes onto the
// deep level instead: the middle of (in_lo, in_hi) (no shell when in_hi is 0).
__kernel void shell_clamp(__global const float* v, __global const float* centre, __global const float* axis,
                          __global const float* shell, float reach, float across, int onto, int nv,
                          __global float* out)
{
    int i = get_global_id(0);
    if (i >= nv) return;
    float3 n = vload3(i, axis), p = vload3(i, v);
    float3 A = vload3(i, centre) - reach * n;
    float4 sh = vload4(i, shell);
    float lo = sh.y, hi = onto ? sh.x : sh.z;
    if ((onto ? sh.y : sh.w) == 0.0f) {  // base outside at that level: no shell on this line
        lo = 0.0f;
        hi = 1.0f;
    }
    if (lo > hi) lo = hi = 0.5f * (lo + hi);
    float3 d = p - A;
    float len = 2.0f * reach;
    float s = dot3(d, n) / len;
    float3 t = d - (s * len) * n;
    float tl = sqrt(dot3(t, t));
    if (tl > across) t = t * (across / tl);
    s = fmin(fmax(s, lo), hi);
    vstore3((A + (s * len) * n) + t, i, out);
}

// Fold repair: a vertex two of whose faces that share an edge have unit normals more than 150 degrees apart
// (cos < -0.8660254: FOLD_COS of nodes.common.meshops, the fold of eval.mesh) takes half an umbrella step
// (towards the mean of its neighbours); the others stay.
inline int other_shared(int4 a, int4 b, int i)
{
    // whether faces a and b (corners xyz), both holding vertex i, share another corner: an edge
    int s = 0;
    if (a.x != i) s |= a.x == b.x || a.x == b.y || a.x == b.z;
    if (a.y != i) s |= a.y == b.x || a.y == b.y || a.y == b.z;
    if (a.z != i) s |= a.z == b.x || a.z == b.y || a.z == b.z;
    return s;
}

__kernel void unfold_step(__global const float* v, __global const int* f, __global const int* off,
                          __global const int* idx, int nv, __global float* out, __global int* count)
{
    int i = get_global_id(0);
    if (i >= nv) return;
    float3 p = vload3(i, v);
    int s = off[i], e = off[i + 1];
    int folded = 0;
    float3 ring = (float3)(0.0f);
    for (int j = s; j < e; j++) {
        int k = idx[j];
        int4 fk = (int4)(f[3 * k], f[3 * k + 1], f[3 * k + 2], 0);
        float3 a = vload3(fk.x, v), b = vload3(fk.y, v), c = vload3(fk.z, v);
        ring = ring + ((a + b) + c);
        float3 nj = unit3(cross3(b - a, c - a));
        for (int l = s; l < j; l++) {
            int q = idx[l];
            int4 fq = (int4)(f[3 * q], f[3 * q + 1], f[3 * q + 2], 0);
            if (!other_shared(fk, fq, i)) continue;
            float3 a2 = vload3(fq.x, v), b2 = vload3(fq.y, v), c2 = vload3(fq.z, v);
            folded |= dot3(nj, unit3(cross3(b2 - a2, c2 - a2))) < -0.8660254f;
        }
    }
    if (folded) {
        float cnt = (float)(e - s);
        p = p + 0.5f * ((ring - cnt * p) / (2.0f * cnt) - p);
        atomic_inc(count);
    }
    vstore3(p, i, out);
}
