// Silhouette keys, one work item per pixel. NumPy references: nodes/key.py (*_reference functions).
// Images are packed uint8 RGB, row-major; alpha outputs are uint8 0..255 (foreground = 255).

// BT.601 full-range YCbCr, chroma centred on 0.
inline float3 rgb_to_ycc(float3 c)
{
    float y = 0.299f * c.x + 0.587f * c.y + 0.114f * c.z;
    return (float3)(y, 0.564f * (c.z - y), 0.713f * (c.x - y));
}

inline float3 ycc_to_rgb(float3 v)
{
    float r = v.x + v.z / 0.713f;
    float b = v.x + v.y / 0.564f;
    float g = (v.x - 0.299f * r - 0.114f * b) / 0.587f;
    return (float3)(r, g, b);
}

inline uchar3 to_u8(float3 c)
{
    return convert_uchar3_sat_rte(c);
}

// Garbage matte: inside when a*x + b*y + c >= 0 for every edge (a, b) unit normal, pixels from the edge.
inline int inside_matte(__global const float4 *edges, int nedges, float x, float y)
{
    for (int e = 0; e < nedges; ++e) {
        float4 p = edges[e];
        if (p.x * x + p.y * y + p.z < 0.0f)
            return 0;
    }
    return 1;
}

// Chroma key. key = (u_cb, u_cr) unit direction of the key colour in the CbCr plane.
// strength s = (c.u - side * |c x u|) / max(Y, luma_floor): how strongly the pixel's chroma points at the
// key hue, relative to its brightness. Foreground alpha = 1 - smoothstep-free ramp of s over [inner, outer],
// times a ramp of luma over [black, black + 4] (pixels darker than the screen's black level are background).
// Spill: the chroma component along the key direction is removed (times spill) and RGB rebuilt at equal luma.
__kernel void chroma_key(__global const uchar *rgb, int npix, float2 key, float side, float luma_floor,
                         float inner, float outer, float black, float spill, int width,
                         __global const float4 *edges, int nedges,
                         __global uchar *alpha_out, __global uchar *despilled)
{
    int i = get_global_id(0);
    if (i >= npix)
        return;
    float3 c = convert_float3(vload3(i, rgb));
    float3 v = rgb_to_ycc(c);
    float along = v.y * key.x + v.z * key.y;
    float across = fabs(v.y * key.y - v.z * key.x);
    float s = (along - side * across) / fmax(v.x, luma_floor);
    float a = 1.0f - clamp((s - inner) / (outer - inner), 0.0f, 1.0f);
    a *= clamp((v.x - black) * 0.25f, 0.0f, 1.0f);
    if (nedges > 0 && !inside_matte(edges, nedges, (float)(i % width), (float)(i / width)))
        a = 0.0f;
    alpha_out[i] = convert_uchar_sat_rte(a * 255.0f);
    float remove = spill * fmax(along, 0.0f);
    v.y -= remove * key.x;
    v.z -= remove * key.y;
    vstore3(to_u8(ycc_to_rgb(v)), i, despilled);
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
