// Taubin lambda|mu smoothing (Taubin, SIGGRAPH 95), one half-step: every vertex moves by `factor` times its
// umbrella Laplacian (mean of its neighbours minus itself). Neighbours in CSR form (offsets, indices).
// Arithmetic order here is mirrored by nodes/relax.py:taubin_step_reference.
#pragma OPENCL FP_CONTRACT OFF

__kernel void taubin_step(__global const float* v, __global const int* offsets, __global const int* neighbours,
                          int n, float factor, __global float* out)
{
    int i = get_global_id(0);
    if (i >= n) return;
    float3 p = vload3(i, v);
    int s = offsets[i], e = offsets[i + 1];
    if (e == s) {
        vstore3(p, i, out);
        return;
    }
    float3 sum = (float3)(0.0f);
    for (int j = s; j < e; j++) sum += vload3(neighbours[j], v);
    float3 mean = sum / (float)(e - s);
    vstore3(p + factor * (mean - p), i, out);
}
