// nodes/common/silhouettes.py outline_field (NumPy reference: outline_field_reference, scipy's exact Euclidean
// distance transform, bit for bit): alpha = 0.5 + (distance between pixel centres to the nearest pixel of the
// other class - half a pixel), positive inside (value > 127). Meijster, Roerdink & Hesselink 2000 ("A general
// algorithm for computing distance transforms in linear time"), in integers: a pass down each column (the
// distance to the nearest pixel of each class in that column), then one along each row (the lower envelope of
// the columns' parabolas); the squared distances are exact integers, so sqrt in double is scipy's value. Both
// classes at once. A class absent from a column: W + H (larger than any distance in the image).
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

// One work-item per column x: g_in / g_out[y * W + x] = rows to the nearest inside / outside pixel of column x.
__kernel void edt_columns(__global const uchar* mask, int W, int H, __global int* g_in, __global int* g_out)
{
    int x = get_global_id(0);
    if (x >= W) return;
    int far = W + H, din = far, dout = far;
    for (int y = 0; y < H; y++) {
        int inside = mask[(size_t)y * W + x] > 127;
        din = inside ? 0 : (din == far ? far : din + 1);
        dout = inside ? (dout == far ? far : dout + 1) : 0;
        g_in[(size_t)y * W + x] = din;
        g_out[(size_t)y * W + x] = dout;
    }
    din = far;
    dout = far;
    for (int y = H - 1; y >= 0; y--) {
        size_t o = (size_t)y * W + x;
        int inside = mask[o] > 127;
        din = inside ? 0 : (din == far ? far : din + 1);
        dout = inside ? (dout == far ? far : dout + 1) : 0;
        g_in[o] = min(g_in[o], din);
        g_out[o] = min(g_out[o], dout);
    }
}

inline long edt_f(int x, int i, int gi)
{
    return (long)(x - i) * (x - i) + (long)gi * gi;
}

// floor((u^2 - i^2 + g_u^2 - g_i^2) / (2 (u - i))), u > i: where column u's parabola starts to lie below i's
inline int edt_sep(int i, int u, int gi, int gu)
{
    long num = (long)u * u - (long)i * i + (long)gu * gu - (long)gi * gi, den = 2L * (u - i);
    long q = num / den;
    if (num % den != 0 && num < 0) q -= 1;
    return (int)q;
}

// The squared distances along one row of W pixels from its columns' distances g (Meijster's second phase);
// s, t: W ints of scratch each.
inline void edt_row(__global const int* g, int W, __global int* s, __global int* t, __global long* d2)
{
    int q = 0;
    s[0] = 0;
    t[0] = 0;
    for (int u = 1; u < W; u++) {
        while (q >= 0 && edt_f(t[q], s[q], g[s[q]]) > edt_f(t[q], u, g[u])) q--;
        if (q < 0) {
            q = 0;
            s[0] = u;
        } else {
            int w = 1 + edt_sep(s[q], u, g[s[q]], g[u]);
            if (w < W) {
                q++;
                s[q] = u;
                t[q] = w;
            }
        }
    }
    for (int u = W - 1; u >= 0; u--) {
        d2[u] = edt_f(u, s[q], g[s[q]]);
        if (u == t[q]) q--;
    }
}

// One work-item per row y: the field (float32, as the reference rounds it) from both classes' squared distances.
__kernel void edt_rows(__global const uchar* mask, int W, int H, __global const int* g_in, __global const int* g_out,
                       __global int* scratch, __global long* d2, __global float* field)
{
    int y = get_global_id(0);
    if (y >= H) return;
    size_t o = (size_t)y * W;
    __global int* s = scratch + 2 * o;
    __global int* t = s + W;
    __global long* to_in = d2 + 2 * o;
    __global long* to_out = to_in + W;
    edt_row(g_in + o, W, s, t, to_in);
    edt_row(g_out + o, W, s, t, to_out);
    for (int x = 0; x < W; x++) {
        double d = mask[o + x] > 127 ? sqrt((double)to_out[x]) - 0.5 : 0.5 - sqrt((double)to_in[x]);
        field[o + x] = (float)d + 0.5f;
    }
}
