// Silhouette keys (chroma and difference: 16 pixels per work item; threshold one pixel). NumPy references:
// nodes/key.py (*_reference functions). Images are packed uint8 RGB, row-major; alpha outputs are uint8 0..255
// (foreground = 255). No contraction to fused multiply-adds: every float operation rounds as NumPy's does, so
// the chroma key and its silhouette-bits variant give the very same alpha, and the garbage matte's row spans
// (bisection) agree with its per-pixel test.
#pragma OPENCL FP_CONTRACT OFF

// ---- chroma key: 16 pixels per work item, as float16 vectors (PoCL vectorises these; per-pixel uchar3
// loads and rint() calls were what made the first version slow).
#define PIX 16

// Round half to even (as NumPy's rint) and saturate to 0..255; the 1.5 * 2^23 trick is exact in float32
// and needs no rounding-mode call. (Do not build this file with -cl-fast-relaxed-math: it would fold it.)
inline uchar16 to_u8x16(float16 v)
{
    return convert_uchar16(convert_int16((clamp(v, 0.0f, 255.0f) + 12582912.0f) - 12582912.0f));
}

// LOAD48(name, T): name(src, n, a0, a1, a2) loads n (<= 48) values of type T from src as three T16 vectors;
// the missing tail is zero.
#define LOAD48(NAME, T)                                                               \
    inline void NAME(__global const T *src, int n, T##16 *a0, T##16 *a1, T##16 *a2)  \
    {                                                                                 \
        if (n == 3 * PIX) {                                                           \
            *a0 = vload16(0, src);                                                    \
            *a1 = vload16(1, src);                                                    \
            *a2 = vload16(2, src);                                                    \
            return;                                                                   \
        }                                                                             \
        T t[3 * PIX];                                                                 \
        for (int k = 0; k < 3 * PIX; ++k)                                             \
            t[k] = k < n ? src[k] : (T)0;                                             \
        *a0 = vload16(0, t);                                                          \
        *a1 = vload16(1, t);                                                          \
        *a2 = vload16(2, t);                                                          \
    }
LOAD48(load_bytes48, uchar)
LOAD48(load_floats48, float)

// The first n (<= 48) of the 48 bytes a0 a1 a2 to dst.
__attribute__((always_inline)) inline void store_bytes48(__global uchar *dst, int n, uchar16 a0, uchar16 a1, uchar16 a2)
{
    if (n == 3 * PIX) {
        vstore16(a0, 0, dst);
        vstore16(a1, 1, dst);
        vstore16(a2, 2, dst);
        return;
    }
    uchar t[3 * PIX];
    vstore16(a0, 0, t);
    vstore16(a1, 1, t);
    vstore16(a2, 2, t);
    for (int k = 0; k < n; ++k)
        dst[k] = t[k];
}


// de-interleave 16 packed RGB pixels given as three float16 (48 values r g b r g b ...) into channels, with
// two-source float shuffles (one permute instruction each on AVX-512)
inline void planes16(float16 f0, float16 f1, float16 f2, float16 *r, float16 *g, float16 *b)
{
    // lanes 0..15 of f0, 16..31 of f1: the pixels' channels found in f0 and f1 (lanes past them are don't-care)
    float16 r01 = shuffle2(f0, f1, (uint16)(0, 3, 6, 9, 12, 15, 18, 21, 24, 27, 30, 0, 0, 0, 0, 0));
    float16 g01 = shuffle2(f0, f1, (uint16)(1, 4, 7, 10, 13, 16, 19, 22, 25, 28, 31, 0, 0, 0, 0, 0));
    float16 b01 = shuffle2(f0, f1, (uint16)(2, 5, 8, 11, 14, 17, 20, 23, 26, 29, 0, 0, 0, 0, 0, 0));
    // then lanes 16..31 are f2's
    *r = shuffle2(r01, f2, (uint16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 17, 20, 23, 26, 29));
    *g = shuffle2(g01, f2, (uint16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 18, 21, 24, 27, 30));
    *b = shuffle2(b01, f2, (uint16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 19, 22, 25, 28, 31));
}

// the same for 16 packed uint8 RGB pixels (three uchar16), converted to float as they lie
inline void rgb_planes16(uchar16 a0, uchar16 a1, uchar16 a2, float16 *r, float16 *g, float16 *b)
{
    planes16(convert_float16(a0), convert_float16(a1), convert_float16(a2), r, g, b);
}

// the first n (<= 16) of 16 bytes to dst
inline void store_bytes16(__global uchar *dst, int n, uchar16 v)
{
    if (n == PIX) {
        vstore16(v, 0, dst);
        return;
    }
    uchar t[PIX];
    vstore16(v, 0, t);
    for (int k = 0; k < n; ++k)
        dst[k] = t[k];
}

// Chroma key alpha (0..1, before the garbage matte) of 16 pixels; writes the luma, chroma and the chroma
// along the key direction that despill needs. See chroma_key below for the formula.
inline float16 chroma_alpha16(float16 r, float16 g, float16 b, float2 key, float side, float luma_floor, float inner,
                              float inv_ramp, float black, float16 *y, float16 *cb, float16 *cr, float16 *along)
{
    *y = 0.299f * r + 0.587f * g + 0.114f * b;  // BT.601 full-range YCbCr, chroma centred on 0
    *cb = 0.564f * (b - *y);
    *cr = 0.713f * (r - *y);
    *along = *cb * key.x + *cr * key.y;
    float16 across = fabs(*cb * key.y - *cr * key.x);
    float16 s = (*along - side * across) / fmax(*y, luma_floor);
    float16 a = 1.0f - clamp((s - inner) * inv_ramp, 0.0f, 1.0f);
    return a * clamp((*y - black) * 0.25f, 0.0f, 1.0f);
}

// Garbage matte edge p = (a, b, c): pixel (x, y) is on its inside when a x + b y + c >= 0.
inline int matte_inside(float4 p, float x, float y)
{
    return p.x * x + p.y * y + p.z >= 0.0f;
}

// First x in [0, width] where the edge test reads `want` (width when nowhere), for a test that is monotone in
// x: false..false true..true read as (test == want). Tried first at the analytic crossing, then bisection.
__attribute__((always_inline)) inline int matte_flip(float4 p, float y, int width, int want)
{
    int lo = 0, hi = width;  // the answer lies in [lo, hi]
    float xs = floor(-(p.y * y + p.z) / p.x);
    if (xs < 0.0f && matte_inside(p, 0.0f, y) == want)
        return 0;
    if (xs >= (float)width && matte_inside(p, (float)(width - 1), y) != want)
        return width;
    if (xs >= 0.0f && xs < (float)width) {
        int t = (int)xs;
        if (matte_inside(p, (float)t, y) == want) {
            if (t == 0 || matte_inside(p, (float)(t - 1), y) != want)
                return t;
            hi = t - 1;
        } else {
            if (t + 1 == width || matte_inside(p, (float)(t + 1), y) == want)
                return t + 1;
            lo = t + 2;
        }
    }
    while (lo < hi) {
        int mid = (lo + hi) >> 1;
        if (matte_inside(p, (float)mid, y) == want)
            hi = mid;
        else
            lo = mid + 1;
    }
    return lo;
}

// The pixels [x0, x1) of row y inside every matte edge (x0 >= x1: none). Each edge's test is monotone in x
// (every rounding step is), so it holds on a prefix or a suffix of the row: where it flips is found with the
// very same arithmetic as the per-pixel test, so the span and the per-pixel test agree exactly.
inline int2 matte_span(__global const float4 *edges, int nedges, int width, float y)
{
    int x0 = 0, x1 = width;
    for (int e = 0; e < nedges && x0 < x1; ++e) {
        float4 p = edges[e];
        if (p.x == 0.0f) {  // horizontal edge: the whole row or nothing
            if (!matte_inside(p, 0.0f, y))
                x1 = 0;
        } else if (p.x > 0.0f) {  // inside from some x on
            x0 = max(x0, matte_flip(p, y, width, 1));
        } else {  // inside up to some x
            x1 = min(x1, matte_flip(p, y, width, 0));
        }
    }
    return (int2)(x0, x1);
}

// n zero bytes at p
inline void zero_bytes(__global uchar *p, int n)
{
    for (; n >= 16; n -= 16, p += 16)
        vstore16((uchar16)0, 0, p);
    for (; n > 0; --n, ++p)
        *p = 0;
}

// The garbage matte as one inside span [x0, x1) per image row (one work item per row).
__kernel void matte_rows(__global const float4 *edges, int nedges, int width, int height, __global int2 *spans)
{
    int y = get_global_id(0);
    if (y < height)
        spans[y] = matte_span(edges, nedges, width, (float)y);
}

// Spill suppression of 16 pixels given as luma, chroma and chroma along the key (chroma_alpha16's): the key-
// coloured chroma times `spill` removed, back to packed RGB; the first `nbytes` bytes written to dst.
__attribute__((always_inline)) inline void despill_store48(float16 y, float16 cb, float16 cr, float16 along, float2 key, float spill,
                            __global uchar *dst, int nbytes)
{
    float16 remove = spill * fmax(along, 0.0f);
    cb -= remove * key.x;
    cr -= remove * key.y;
    // back to interleaved RGB as three 16-byte chunks: byte q of chunk j is pixel (16 j + q) / 3, channel
    // (16 j + q) % 3; R = Y + Cr / 0.713, B = Y + Cb / 0.564, G = (Y - 0.299 R - 0.114 B) / 0.587.
    const float kr_g = -0.299f / (0.587f * 0.713f), kb_g = -0.114f / (0.587f * 0.564f);
    const float kr_r = 1.0f / 0.713f, kb_b = 1.0f / 0.564f;
    uint16 p0 = (uint16)(0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3, 4, 4, 4, 5);
    uint16 p1 = (uint16)(5, 5, 6, 6, 6, 7, 7, 7, 8, 8, 8, 9, 9, 9, 10, 10);
    uint16 p2 = (uint16)(10, 11, 11, 11, 12, 12, 12, 13, 13, 13, 14, 14, 14, 15, 15, 15);
    float16 kr0 = (float16)(kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r);
    float16 kb0 = (float16)(0, kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b, 0);
    float16 kr1 = (float16)(kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g);
    float16 kb1 = (float16)(kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g);
    float16 kr2 = (float16)(0, kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g, 0, kr_r, kr_g, 0);
    float16 kb2 = (float16)(kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b, 0, kb_g, kb_b);
    float16 o0 = shuffle(y, p0) + shuffle(cr, p0) * kr0 + shuffle(cb, p0) * kb0;
    float16 o1 = shuffle(y, p1) + shuffle(cr, p1) * kr1 + shuffle(cb, p1) * kb1;
    float16 o2 = shuffle(y, p2) + shuffle(cr, p2) * kr2 + shuffle(cb, p2) * kb2;
    store_bytes48(dst, nbytes, to_u8x16(o0), to_u8x16(o1), to_u8x16(o2));
}

// Chroma key. key = (u_cb, u_cr) unit direction of the key colour in the CbCr plane.
// strength s = (c.u - side * |c x u|) / max(Y, luma_floor): how strongly the pixel's chroma points at the
// key hue, relative to its brightness. Foreground alpha = 1 - ramp of s over [inner, outer] (inv_ramp =
// 1 / (outer - inner)), times a ramp of luma over [black, black + 4] (darker than the screen's black level =
// background), and 0 outside the garbage matte (a*x + b*y + c < 0 for an edge (a, b, c)), given as the
// inside span of each row (matte_rows) when `matte` is set.
// Spill (when despill is set): the chroma component along the key direction is removed (times spill) and RGB
// rebuilt at equal luma. One work item = pixels 16 i .. 16 i + 15 (fewer in the last one).
__kernel void chroma_key(__global const uchar *rgb, int npix, float2 key, float side, float luma_floor,
                         float inner, float inv_ramp, float black, float spill, int width,
                         __global const int2 *spans, int matte,
                         __global uchar *alpha_out, int despill, __global uchar *despilled)
{
    int i0 = get_global_id(0) * PIX;
    if (i0 >= npix)
        return;
    int n = min(PIX, npix - i0);
    uchar16 a0, a1, a2;
    load_bytes48(rgb + 3 * i0, 3 * n, &a0, &a1, &a2);
    float16 r, g, b, y, cb, cr, along;
    rgb_planes16(a0, a1, a2, &r, &g, &b);
    float16 a = chroma_alpha16(r, g, b, key, side, luma_floor, inner, inv_ramp, black, &y, &cb, &cr, &along);
    if (matte && width < PIX) {  // narrow images: lane by lane
        float t[PIX];
        vstore16(a, 0, t);
        for (int k = 0; k < n; ++k) {
            int row = (i0 + k) / width, x = i0 + k - row * width;
            if (x < spans[row].x || x >= spans[row].y)
                t[k] = 0.0f;
        }
        a = vload16(0, t);
    } else if (matte) {  // pixel columns of the 16 lanes and their rows' spans; lanes wrap to the next row at most once
        int row = i0 / width;
        int16 x = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15) + (i0 - row * width);
        int16 wrap = x >= width;
        x = select(x, x - width, wrap);
        int2 s0 = spans[row], s1 = spans[min(row + 1, npix / width - 1)];
        int16 lo = select((int16)s0.x, (int16)s1.x, wrap), hi = select((int16)s0.y, (int16)s1.y, wrap);
        a = select((float16)0.0f, a, (x >= lo) & (x < hi));
    }
    uchar16 au = to_u8x16(a * 255.0f);
    if (n == PIX) {
        vstore16(au, 0, alpha_out + i0);
    } else {
        uchar t[PIX];
        vstore16(au, 0, t);
        for (int k = 0; k < n; ++k)
            alpha_out[i0 + k] = t[k];
    }
    if (!despill)
        return;
    despill_store48(y, cb, cr, along, key, spill, despilled + 3 * i0, 3 * n);
}

// The RGB planes of pixels c0 .. c0 + n - 1 of row r of a box whose corner is pixel (x0, y0) of an image ``width`` wide.
__attribute__((always_inline)) inline void box_planes16(__global const uchar *rgb, int width, int x0, int y0, int c0, int r, int n, float16 *rf,
                         float16 *gf, float16 *bf)
{
    uchar16 a0, a1, a2;
    load_bytes48(rgb + 3 * ((size_t)(y0 + r) * width + x0 + c0), 3 * n, &a0, &a1, &a2);
    rgb_planes16(a0, a1, a2, rf, gf, bf);
}

// The despilled RGB of the box [x0, x0 + bw) x [y0, y0 + rows) of a packed RGB image `width` pixels wide, written
// packed as (rows, bw, 3): chroma_key's despill, bit for bit, for the pixels a reader keeps (key.chroma's window
// around the alpha; the rest of the image is black). Work item (i, r): PIX pixels of the box's row r from column 16 i.
__kernel void despill_box(__global const uchar *rgb, int width, int x0, int y0, int bw, float2 key, float spill,
                          __global uchar *out)
{
    int c0 = get_global_id(0) * PIX, r = get_global_id(1);
    if (c0 >= bw)
        return;
    int n = min(PIX, bw - c0);
    float16 rf, gf, bf, y, cb, cr, along;
    box_planes16(rgb, width, x0, y0, c0, r, n, &rf, &gf, &bf);
    chroma_alpha16(rf, gf, bf, key, 0.0f, 1.0f, 0.0f, 1.0f, 0.0f, &y, &cb, &cr, &along);
    despill_store48(y, cb, cr, along, key, spill, out + 3 * ((size_t)r * bw + c0), 3 * n);
}

// chroma_key's alpha (no despill) on the box (x0, y0, bw, rows) of the garbage matte's spans alone, into a
// box-sized alpha (row after row): the pixels of the image outside the box are outside the matte (alpha 0).
// The same operations as chroma_key, so the same bytes. Work item (i, r): pixels 16 i .. 16 i + 15 of box row r.
__kernel void chroma_key_box(__global const uchar *rgb, int width, int x0, int y0, int bw, float2 key, float side,
                             float luma_floor, float inner, float inv_ramp, float black,
                             __global const int2 *spans, __global uchar *alpha_out)
{
    int c0 = get_global_id(0) * PIX, r = get_global_id(1);
    if (c0 >= bw)
        return;
    int n = min(PIX, bw - c0);
    float16 rf, gf, bf, y, cb, cr, along;
    box_planes16(rgb, width, x0, y0, c0, r, n, &rf, &gf, &bf);
    float16 a = chroma_alpha16(rf, gf, bf, key, side, luma_floor, inner, inv_ramp, black, &y, &cb, &cr, &along);
    int2 s = spans[y0 + r];
    int16 x = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15) + (x0 + c0);
    a = select((float16)0.0f, a, (x >= (int16)s.x) & (x < (int16)s.y));
    uchar16 au = to_u8x16(a * 255.0f);
    __global uchar *dst = alpha_out + (size_t)r * bw + c0;
    if (n == PIX) {
        vstore16(au, 0, dst);
    } else {
        uchar t[PIX];
        vstore16(au, 0, t);
        for (int k = 0; k < n; ++k)
            dst[k] = t[k];
    }
}

// 16 lanes of -1 / 0 (a comparison's result) to a 16-bit mask, lane i in bit i
inline uint lanes_to_bits16(int16 m)
{
    uint16 w = as_uint16(m) & (uint16)(1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192, 16384, 32768);
    uint8 w8 = w.lo | w.hi;
    uint4 w4 = w8.lo | w8.hi;
    uint2 w2 = w4.lo | w4.hi;
    return w2.x | w2.y;
}

// Chroma key straight into the visual hull's silhouette layout (kernels/hull.cl, nodes/hull.py:SilhouetteBits):
// bit (alpha >= 128) per pixel, rows of Wb = ceil(W/8) bytes, pixel x in bit x % 8 of byte x / 8, and the
// 8x8-pixel block counts prefixed along each block row of the (Hb+1) x (Wb+1) table (zero first row and
// column; the hull's block_cols adds the column prefix). Same alpha as chroma_key (same operations), and
// alpha >= 128 is exactly a * 255 >= 127.5, as chroma_key rounds half to even.
// One work item = table row by (block row by - 1: 8 image rows). Pixels outside the garbage matte's row span
// are not read at all.
__kernel void chroma_key_bits(__global const uchar *rgb, int width, int height, float2 key, float side,
                              float luma_floor, float inner, float inv_ramp, float black,
                              __global const float4 *edges, int edge0, int nedges,
                              __global uchar *bits, int bit_off, __global int *sat, int sat_off)
{
    int by = get_global_id(0);
    int Wb = (width + 7) >> 3, Hb = (height + 7) >> 3;
    if (by > Hb)
        return;
    __global int *counts = sat + sat_off + by * (Wb + 1);
    for (int bx = 0; bx <= Wb; ++bx)
        counts[bx] = 0;
    if (by == 0)
        return;
    int y0 = (by - 1) << 3, y1 = min(y0 + 8, height);
    for (int y = y0; y < y1; ++y) {
        __global uchar *row = bits + bit_off + (size_t)y * Wb;
        int2 span = matte_span(edges + edge0, nedges, width, (float)y);
        int c0 = 0, c1 = 0;  // chunks of 16 pixels that overlap the span
        if (span.x < span.y) {
            c0 = span.x >> 4;
            c1 = (span.y + 15) >> 4;
        }
        zero_bytes(row, min(2 * c0, Wb));
        zero_bytes(row + min(2 * c1, Wb), Wb - min(2 * c1, Wb));
        for (int c = c0; c < c1; ++c) {
            int x = c * PIX, n = min(PIX, width - x);
            uchar16 a0, a1, a2;
            load_bytes48(rgb + 3 * ((size_t)y * width + x), 3 * n, &a0, &a1, &a2);
            float16 r, g, b, yl, cb, cr, along;
            rgb_planes16(a0, a1, a2, &r, &g, &b);
            float16 a = chroma_alpha16(r, g, b, key, side, luma_floor, inner, inv_ramp, black, &yl, &cb, &cr, &along);
            int16 lane = (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15) + x;
            uint m = lanes_to_bits16((a * 255.0f >= 127.5f) & (lane >= span.x) & (lane < span.y));
            row[2 * c] = (uchar)m;
            counts[2 * c + 1] += popcount(m & 255u);
            if (2 * c + 1 < Wb) {
                row[2 * c + 1] = (uchar)(m >> 8);
                counts[2 * c + 2] += popcount(m >> 8);
            }
        }
    }
    int acc = 0;
    for (int bx = 1; bx <= Wb; ++bx) {
        acc += counts[bx];
        counts[bx] = acc;
    }
}

// Difference key against a clean plate (Horprasert et al. 1999 brightness/chromaticity distortion).
// mean: plate RGB (float); inv_var: 1 / sigma^2 per channel. Brightness distortion b = sum(I E / s^2) /
// sum(E^2 / s^2); chromaticity distortion cd = |(I - b E) / s|. A pixel is background when cd is small and
// b lies in [shadow, highlight] (a shadow is darker with the plate's chromaticity, Prati et al. 2003), or when
// it is within `still` sigmas of the plate. Output: alpha 0..255 and a class (0 bg, 1 shadow, 2 fg).
// One work item = pixels 16 i .. 16 i + 15 (fewer in the last one), as float16 vectors like chroma_key.
__kernel void difference_key(__global const uchar *rgb, __global const float *mean, __global const float *inv_var,
                             int npix, float cd_inner, float cd_outer, float shadow, float highlight, float still,
                             __global uchar *alpha_out, __global uchar *label)
{
    int i0 = get_global_id(0) * PIX;
    if (i0 >= npix)
        return;
    int n = min(PIX, npix - i0);
    uchar16 a0, a1, a2;
    float16 f0, f1, f2, Ir, Ig, Ib, Er, Eg, Eb, wr, wg, wb;
    load_bytes48(rgb + 3 * i0, 3 * n, &a0, &a1, &a2);
    rgb_planes16(a0, a1, a2, &Ir, &Ig, &Ib);
    load_floats48(mean + 3 * i0, 3 * n, &f0, &f1, &f2);
    planes16(f0, f1, f2, &Er, &Eg, &Eb);
    load_floats48(inv_var + 3 * i0, 3 * n, &f0, &f1, &f2);
    planes16(f0, f1, f2, &wr, &wg, &wb);
    float16 b = ((Ir * Er) * wr + (Ig * Eg) * wg + (Ib * Eb) * wb)
              / fmax((Er * Er) * wr + (Eg * Eg) * wg + (Eb * Eb) * wb, 1e-6f);
    float16 dr = Ir - b * Er, dg = Ig - b * Eg, db = Ib - b * Eb;
    float16 cd = sqrt((dr * dr) * wr + (dg * dg) * wg + (db * db) * wb);
    dr = Ir - Er;
    dg = Ig - Eg;
    db = Ib - Eb;
    float16 dist = sqrt((dr * dr) * wr + (dg * dg) * wg + (db * db) * wb);
    float16 a = clamp((cd - cd_inner) / (cd_outer - cd_inner), 0.0f, 1.0f);
    int16 moving = dist > still;
    a = select(a, (float16)1.0f, ((b < shadow) | (b > highlight)) & moving);
    a = select(a, (float16)0.0f, dist <= still);
    int16 cls = select(select((int16)0, (int16)1, (b < 1.0f) & moving), (int16)2, a >= 0.5f);
    store_bytes16(alpha_out + i0, n, to_u8x16(a * 255.0f));
    store_bytes16(label + i0, n, convert_uchar16(cls));
}

// Difference key against a background mixture, read as it is stored (PlateMixture: mean uint8 (K, H*W, 3), sigma
// half (K, H*W, 3)): per pixel the difference_key test against each of the K components (the shadow and
// highlight allowance on the first only), and the component that explains the pixel best decides (the lowest
// alpha, on a tie the lowest class). One pixel per work item. NumPy reference: difference_key_mixture_reference.
__kernel void difference_key_mixture(__global const uchar *rgb, __global const uchar *mean, __global const half *sigma,
                                     int npix, int K, float cd_inner, float cd_outer, float shadow, float highlight,
                                     float still, __global uchar *alpha_out, __global uchar *label)
{
    const int i = get_global_id(0);
    if (i >= npix)
        return;
    const float I[3] = {(float)rgb[3 * i], (float)rgb[3 * i + 1], (float)rgb[3 * i + 2]};
    int best = 1 << 30;
    for (int k = 0; k < K; k++) {
        const size_t o = ((size_t)k * npix + i) * 3;
        float E[3], w[3];
        for (int c = 0; c < 3; c++) {
            const float s = vload_half(o + c, sigma);
            E[c] = (float)mean[o + c];
            w[c] = 1.0f / (s * s);
        }
        const float sh = k == 0 ? shadow : 1.0f, hi = k == 0 ? highlight : 1.0f;
        const float b = ((I[0] * E[0]) * w[0] + (I[1] * E[1]) * w[1] + (I[2] * E[2]) * w[2])
                      / fmax((E[0] * E[0]) * w[0] + (E[1] * E[1]) * w[1] + (E[2] * E[2]) * w[2], 1e-6f);
        float d0 = I[0] - b * E[0], d1 = I[1] - b * E[1], d2 = I[2] - b * E[2];
        const float cd = sqrt((d0 * d0) * w[0] + (d1 * d1) * w[1] + (d2 * d2) * w[2]);
        d0 = I[0] - E[0];
        d1 = I[1] - E[1];
        d2 = I[2] - E[2];
        const float dist = sqrt((d0 * d0) * w[0] + (d1 * d1) * w[1] + (d2 * d2) * w[2]);
        float a = clamp((cd - cd_inner) / (cd_outer - cd_inner), 0.0f, 1.0f);
        const int moving = dist > still;
        if ((b < sh || b > hi) && moving)
            a = 1.0f;
        if (dist <= still)
            a = 0.0f;
        const int cls = a >= 0.5f ? 2 : ((b < 1.0f && moving) ? 1 : 0);
        const int code = (int)((clamp(a * 255.0f, 0.0f, 255.0f) + 12582912.0f) - 12582912.0f) * 4 + cls;
        best = min(best, code);
    }
    alpha_out[i] = (uchar)(best >> 2);
    label[i] = (uchar)(best & 3);
}

// Grey threshold: foreground where the mean of R, G, B (or their max) exceeds t (0..255).
__kernel void grey_threshold(__global const uchar *rgb, int npix, float t, int use_max, __global uchar *mask)
{
    int i = get_global_id(0);
    if (i >= npix)
        return;
    float3 c = convert_float3(vload3(i, rgb));
    float g = use_max ? fmax(c.x, fmax(c.y, c.z)) : (c.x + c.y + c.z) * (1.0f / 3.0f);
    mask[i] = g > t ? 255 : 0;
}
