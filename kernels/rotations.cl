// The rotation nearest to each of a batch of 3x3 matrices, float64 (nodes/track/deform.py nearest_rotations; its
// reference is nearest_rotations_reference, LAPACK's SVD): for S = U diag(s) V^T the rotation R = V D U^T that
// maximises trace(R S) (D = diag(1, 1, det(V U^T)): the Procrustes rotation of the ARAP local step, which maps
// the edges e onto the edges f when S = sum e f^T).
//
// One-sided Jacobi SVD (Hestenes 1958; Demmel & Veselic 1992): the columns of A = S are turned in pairs until
// every two are orthogonal (A V = U diag(s), V the product of the turns), at most MAX_SWEEPS sweeps of the three
// pairs. The columns sorted by length give u1, u2 (u2 made orthogonal to u1) and v1, v2; the third columns
// u1 x u2 and v1 x v2 make both U and V rotations, so R = V U^T is the same as V D U^T from any SVD of S
// (when s2 > s3 the rotation is unique; the sign the third column of U and V take does not matter).
#pragma OPENCL EXTENSION cl_khr_fp64 : enable

#define MAX_SWEEPS 12

inline double3 column(const double* m, int c)
{
    return (double3)(m[c], m[3 + c], m[6 + c]);
}

inline void set_column(double* m, int c, double3 x)
{
    m[c] = x.x; m[3 + c] = x.y; m[6 + c] = x.z;
}

inline void jacobi_pair(double* a, double* v, int p, int q, int* turned)
{
    double3 ap = column(a, p), aq = column(a, q);
    double alpha = dot(ap, ap), beta = dot(aq, aq), gamma = dot(ap, aq);
    if (fabs(gamma) <= 1e-15 * sqrt(alpha * beta) || gamma == 0.0)
        return;
    double zeta = (beta - alpha) / (2.0 * gamma);
    double t = (zeta >= 0.0 ? 1.0 : -1.0) / (fabs(zeta) + sqrt(1.0 + zeta * zeta));
    double c = 1.0 / sqrt(1.0 + t * t), s = c * t;
    set_column(a, p, c * ap - s * aq);
    set_column(a, q, s * ap + c * aq);
    double3 vp = column(v, p), vq = column(v, q);
    set_column(v, p, c * vp - s * vq);
    set_column(v, q, s * vp + c * vq);
    *turned = 1;
}

// R[9 i ..] (row-major) the rotation nearest to S[9 i ..] (row-major), i < n.
__kernel void nearest_rotations(__global const double* S, int n, __global double* R)
{
    int i = get_global_id(0);
    if (i >= n) return;
    double a[9], v[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    for (int k = 0; k < 9; k++)
        a[k] = S[9 * i + k];
    for (int sweep = 0; sweep < MAX_SWEEPS; sweep++) {
        int turned = 0;
        jacobi_pair(a, v, 0, 1, &turned);
        jacobi_pair(a, v, 0, 2, &turned);
        jacobi_pair(a, v, 1, 2, &turned);
        if (!turned) break;
    }
    double s0 = length(column(a, 0)), s1 = length(column(a, 1)), s2 = length(column(a, 2));
    int first = 0, second = 1;                           // the two longest columns, longest first
    if (s1 > s0) { first = 1; second = 0; }
    double sf = first == 0 ? s0 : s1, ss = first == 0 ? s1 : s0;
    if (s2 > sf) { second = first; first = 2; }
    else if (s2 > ss) { second = 2; }
    double3 u1 = column(a, first), u2 = column(a, second);
    double3 v1 = column(v, first), v2 = column(v, second);
    double l1 = length(u1);
    u1 = l1 > 0.0 ? u1 / l1 : (double3)(1.0, 0.0, 0.0);
    u2 -= dot(u1, u2) * u1;
    double l2 = length(u2);
    if (l2 > 0.0) {
        u2 /= l2;
    } else {                                             // rank one: any direction across u1
        double3 e = fabs(u1.x) < 0.9 ? (double3)(1.0, 0.0, 0.0) : (double3)(0.0, 1.0, 0.0);
        u2 = normalize(e - dot(e, u1) * u1);
    }
    double3 u3 = cross(u1, u2), v3 = cross(v1, v2);
    // R = v1 u1^T + v2 u2^T + v3 u3^T
    double3 r0 = v1.x * u1 + v2.x * u2 + v3.x * u3;
    double3 r1 = v1.y * u1 + v2.y * u2 + v3.y * u3;
    double3 r2 = v1.z * u1 + v2.z * u2 + v3.z * u3;
    vstore3(r0, 3 * i, R);
    vstore3(r1, 3 * i + 1, R);
    vstore3(r2, 3 * i + 2, R);
}
