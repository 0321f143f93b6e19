// Per-pixel Gaussian mixture of a camera's background from several frames: one work item per pixel runs both
// passes of nodes/common/background.py (background_mixture_reference, the NumPy reference) over the frames, then
// pools the halves of one background and sorts the components by weight. The same float32 operations in the same
// order, without contraction to fused multiply-adds, so it agrees with NumPy to the last bit wherever no
// decision falls on a tie. Frames: (N, H*W, 3) uint8; outputs: mu, var (K, H*W, 3) and n (K, H*W) float32.
#pragma OPENCL FP_CONTRACT OFF

#define KMAX 5
#ifndef K
#define K 3
#endif

inline float variance(float n, float m2, float prior, float floor2)
{
    return fmax((m2 + 2.0f * prior) / (n + 1.0f), floor2);
}

// K: the component count, a build option (-DK=3): the loops unroll and the statistics stay in registers
__kernel void background_mixture(__global const uchar *frames, const int nframes, const int npix,
                                 const float floor2, const float limit, const float prior,
                                 __global float *mu_out, __global float *var_out, __global float *n_out)
{
    const int p = get_global_id(0);
    if (p >= npix)
        return;
    float n[KMAX], mu[KMAX][3], m2[KMAX][3];
    float mn[KMAX], mm[KMAX][3], mv[KMAX][3];
    for (int k = 0; k < K; k++) {
        n[k] = 0.0f;
        for (int c = 0; c < 3; c++) { mu[k][c] = 0.0f; m2[k][c] = 0.0f; }
    }
    for (int pass = 0; pass < 2; pass++) {
        if (pass == 1) {                     // the model to match against: pass 1's components, fixed
            for (int k = 0; k < K; k++) {
                mn[k] = n[k];
                for (int c = 0; c < 3; c++) {
                    mm[k][c] = mu[k][c];
                    mv[k][c] = variance(n[k], m2[k][c], prior, floor2);
                    m2[k][c] = 0.0f;
                }
                n[k] = 0.0f;
            }
        }
        for (int t = 0; t < nframes; t++) {
            __global const uchar *px = frames + ((size_t)t * npix + p) * 3;
            float x[3] = {(float)px[0], (float)px[1], (float)px[2]};
            int best = 0, weakest = 0;
            float dbest = INFINITY;
            for (int k = 0; k < K; k++) {
                float d2 = INFINITY;
                const float cn = pass == 0 ? n[k] : mn[k];
                if (cn > 0.0f) {
                    float s[3];
                    for (int c = 0; c < 3; c++) {
                        const float mk = pass == 0 ? mu[k][c] : mm[k][c];
                        const float v = pass == 0 ? variance(n[k], m2[k][c], prior, floor2) : mv[k][c];
                        const float dx = x[c] - mk;
                        s[c] = dx * dx / v;
                    }
                    d2 = (s[0] + s[1]) + s[2];
                }
                if (d2 < dbest) { dbest = d2; best = k; }
                if (n[k] < n[weakest]) weakest = k;
            }
            if (dbest <= limit) {
                n[best] += 1.0f;
                for (int c = 0; c < 3; c++) {
                    const float delta = x[c] - mu[best][c];
                    mu[best][c] += delta / fmax(n[best], 1.0f);
                    m2[best][c] += delta * (x[c] - mu[best][c]);
                }
            } else if (pass == 0) {
                n[weakest] = 1.0f;
                for (int c = 0; c < 3; c++) { mu[weakest][c] = x[c]; m2[weakest][c] = 0.0f; }
            }
        }
    }
    for (int k = 0; k < K; k++) {            // pool two components within the match distance of each other
        for (int j = k + 1; j < K; j++) {
            if (!(n[k] > 0.0f && n[j] > 0.0f))
                continue;
            float s[3];
            for (int c = 0; c < 3; c++) {
                const float dm = mu[k][c] - mu[j][c];
                s[c] = dm * dm / fmax(variance(n[k], m2[k][c], prior, floor2), variance(n[j], m2[j][c], prior, floor2));
            }
            if ((s[0] + s[1]) + s[2] > limit)
                continue;
            const float nk = n[k], nj = n[j], tot = nk + nj;
            for (int c = 0; c < 3; c++) {
                const float dm = mu[j][c] - mu[k][c];
                m2[k][c] += m2[j][c] + dm * dm * nk * nj / tot;
                mu[k][c] += dm * nj / tot;
                m2[j][c] = 0.0f;
            }
            n[k] = tot;
            n[j] = 0.0f;
        }
    }
    int order[KMAX];                         // by count, descending; ties keep their order (a stable sort)
    for (int k = 0; k < K; k++) {
        int i = k;
        while (i > 0 && n[order[i - 1]] < n[k]) { order[i] = order[i - 1]; i--; }
        order[i] = k;
    }
    for (int r = 0; r < K; r++) {
        const int k = order[r];
        n_out[(size_t)r * npix + p] = n[k];
        for (int c = 0; c < 3; c++) {
            mu_out[((size_t)r * npix + p) * 3 + c] = mu[k][c];
            var_out[((size_t)r * npix + p) * 3 + c] = variance(n[k], m2[k][c], prior, floor2);
        }
    }
}
