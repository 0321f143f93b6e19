// Silhouette keys (chroma: 16 pixels per work item; the others one pixel). NumPy references: nodes/key.py (*_reference functions).
// Images are packed uint8 RGB, row-major; alpha outputs are uint8 0..255 (foreground = 255).

// ---- chroma key: 16 pixels per work item, as float16 vectors (PoCL vectorises these; per-pixel uchar3
// loads and rint() calls were what made the first version slow).
#define PIX 16

// Round half to even (as NumPy's rint) and saturate to 0..255; the 1.5 * 2^23 trick is exact in float32
// and needs no rounding-mode call. (Do not build this file with -cl-fast-relaxed-math: it would fold it.)
inline uchar16 to_u8x16(float16 v)
{
    return convert_uchar16(convert_int16((clamp(v, 0.0f, 255.0f) + 12582912.0f) - 12582912.0f));
}

// n (<= 48) bytes from src into three uchar16; the missing tail is zero.
inline void load_bytes48(__global const uchar *src, int n, uchar16 *a0, uchar16 *a1, uchar16 *a2)
{
    if (n == 3 * PIX) {
        *a0 = vload16(0, src);
        *a1 = vload16(1, src);
        *a2 = vload16(2, src);
        return;
    }
    uchar t[3 * PIX];
    for (int k = 0; k < 3 * PIX; ++k)
        t[k] = k < n ? src[k] : 0;
    *a0 = vload16(0, t);
    *a1 = vload16(1, t);
    *a2 = vload16(2, t);
}

// The first n (<= 48) of the 48 bytes a0 a1 a2 to dst.
inline void store_bytes48(__global uchar *dst, int n, uchar16 a0, uchar16 a1, uchar16 a2)
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

// Chroma key. key = (u_cb, u_cr) unit direction of the key colour in the CbCr plane.
// strength s = (c.u - side * |c x u|) / max(Y, luma_floor): how strongly the pixel's chroma points at the
// key hue, relative to its brightness. Foreground alpha = 1 - ramp of s over [inner, outer] (inv_ramp =
// 1 / (outer - inner)), times a ramp of luma over [black, black + 4] (darker than the screen's black level =
// background), and 0 outside the garbage matte (a*x + b*y + c < 0 for an edge (a, b, c)).
// Spill (when despill is set): the chroma component along the key direction is removed (times spill) and RGB
// rebuilt at equal luma. One work item = pixels 16 i .. 16 i + 15 (fewer in the last one).
__kernel void chroma_key(__global const uchar *rgb, int npix, float2 key, float side, float luma_floor,
                         float inner, float inv_ramp, float black, float spill, int width,
                         __global const float4 *edges, int nedges,
                         __global uchar *alpha_out, int despill, __global uchar *despilled)
{
    int i0 = get_global_id(0) * PIX;
    if (i0 >= npix)
        return;
    int n = min(PIX, npix - i0);
    uchar16 a0, a1, a2;
    load_bytes48(rgb + 3 * i0, 3 * n, &a0, &a1, &a2);
    // de-interleave packed RGB
    float16 r = convert_float16((uchar16)(a0.s0, a0.s3, a0.s6, a0.s9, a0.sc, a0.sf, a1.s2, a1.s5,
                                          a1.s8, a1.sb, a1.se, a2.s1, a2.s4, a2.s7, a2.sa, a2.sd));
    float16 g = convert_float16((uchar16)(a0.s1, a0.s4, a0.s7, a0.sa, a0.sd, a1.s0, a1.s3, a1.s6,
                                          a1.s9, a1.sc, a1.sf, a2.s2, a2.s5, a2.s8, a2.sb, a2.se));
    float16 b = convert_float16((uchar16)(a0.s2, a0.s5, a0.s8, a0.sb, a0.se, a1.s1, a1.s4, a1.s7,
                                          a1.sa, a1.sd, a2.s0, a2.s3, a2.s6, a2.s9, a2.sc, a2.sf));
    float16 y = 0.299f * r + 0.587f * g + 0.114f * b;  // BT.601 full-range YCbCr, chroma centred on 0
    float16 cb = 0.564f * (b - y), cr = 0.713f * (r - y);
    float16 along = cb * key.x + cr * key.y;
    float16 across = fabs(cb * key.y - cr * key.x);
    float16 s = (along - side * across) / fmax(y, luma_floor);
    float16 a = 1.0f - clamp((s - inner) * inv_ramp, 0.0f, 1.0f);
    a *= clamp((y - black) * 0.25f, 0.0f, 1.0f);
    if (nedges > 0) {  // pixel coordinates of the 16 lanes; they wrap onto the next row at most once
        int row = i0 / width;
        float16 x = (float16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15) + (float)(i0 - row * width);
        int16 wrap = x >= (float)width;
        x = select(x, x - (float)width, wrap);
        float16 yy = select((float16)(float)row, (float16)(float)(row + 1), wrap);
        for (int e = 0; e < nedges; ++e) {
            float4 p = edges[e];
            a = select(a, (float16)0.0f, p.x * x + p.y * yy + p.z < 0.0f);
        }
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
    store_bytes48(despilled + 3 * i0, 3 * n, to_u8x16(o0), to_u8x16(o1), to_u8x16(o2));
}

// Difference key against a clean plate (Horprasert et al. 1999 brightness/chromaticity distortion).
// mean: plate RGB (float); inv_var: 1 / sigma^2 per channel. Brightness distortion b = sum(I E / s^2) /
// sum(E^2 / s^2); chromaticity distortion cd = |(I - b E) / s|. A pixel is background when cd is small and
// b lies in [shadow, highlight] (a shadow is darker with the plate's chromaticity, Prati et al. 2003), or when
// it is within `still` sigmas of the plate. Output: alpha 0..255 and a class (0 bg, 1 shadow, 2 fg).
__kernel void difference_key(__global const uchar *rgb, __global const float *mean, __global const float *inv_var,
                             int npix, float cd_inner, float cd_outer, float shadow, float highlight, float still,
                             __global uchar *alpha_out, __global uchar *label)
{
    int i = get_global_id(0);
    if (i >= npix)
        return;
    float3 I = convert_float3(vload3(i, rgb));
    float3 E = vload3(i, mean);
    float3 w = vload3(i, inv_var);
    float b = dot(I * E, w) / fmax(dot(E * E, w), 1e-6f);
    float3 d = I - b * E;
    float cd = sqrt(dot(d * d, w));
    float3 diff = I - E;
    float dist = sqrt(dot(diff * diff, w));
    float a = clamp((cd - cd_inner) / (cd_outer - cd_inner), 0.0f, 1.0f);
    int out_of_range = (b < shadow || b > highlight) && dist > still;
    if (out_of_range)
        a = 1.0f;
    if (dist <= still)
        a = 0.0f;
    alpha_out[i] = convert_uchar_sat_rte(a * 255.0f);
    label[i] = a >= 0.5f ? 2 : (b < 1.0f && dist > still ? 1 : 0);
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
