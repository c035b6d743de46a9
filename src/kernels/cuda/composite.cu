// Volume compositing of either sample layout (kernels/composite.rs), one thread per ray,
// accumulating in double whatever the storage dtype.
//
// Inputs: sigmas [M]; geometry g0, g1 [M] with mode 0: g0 = delta, g1 = t (sample
// depths), mode 1: g0 = interval starts, g1 = interval ends, delta = (e - s)*norm[r]
// (norm = 1 when `has_norms` is 0) and t = (s + e)/2; values [M, K]. Rays: `offsets`
// [R + 1] (packed) or, when `packed` is 0, R rays of `per_ray` samples. Output [R, K + 2]:
// sum w v_k for each k, sum w t, sum w.
//
// x_i = min(sigma_i delta_i, X_MAX), alpha_i = -expm1(-x_i), T_{i+1} = T_i e^{-x_i},
// w_i = T_i alpha_i; the scan stops once T < T_STOP (later weights are below 1e-300).
// With opaque_last, alpha = 1 for a ray's last sample. `bad` is set when a density is
// not finite and >= 0 or (mode 1) an interval length is not finite and >= 0.

#define X_MAX 1000.0
#define T_STOP 1e-300
#define MAXK 16

__device__ __forceinline__ void nf_range(const u64* offsets, int packed, u64 per_ray, u64 r, u64* a, u64* b) {
    if (packed) { *a = offsets[r]; *b = offsets[r + 1]; }
    else { *a = r * per_ray; *b = (r + 1) * per_ray; }
}

__device__ __forceinline__ bool nf_geometry(int mode, const real* g0, const real* g1, double norm,
                                            u64 i, double* del, double* t) {
    if (mode == 0) {
        *del = (double)g0[i];
        *t = (double)g1[i];
        return true;
    }
    double s = (double)g0[i], e = (double)g1[i];
    // delta in the storage dtype, as the CPU kernel forms it.
    real d = (real)(((real)e - (real)s) * (real)norm);
    *del = (double)d;
    *t = (double)(real)(((real)s + (real)e) * (real)0.5);
    return isfinite(*del) && *del >= 0.0;
}

extern "C" __global__ void nf_composite_fwd(
    const real* sig, const real* g0, const real* g1, const double* norms, int has_norms,
    int mode, const real* vals, const u64* offsets, int packed, u64 rays, u64 per_ray, u64 k,
    int opaque_last, real* out, int* bad) {
    u64 r = (u64)blockIdx.x * blockDim.x + threadIdx.x;
    if (r >= rays) return;
    u64 a, b;
    nf_range(offsets, packed, per_ray, r, &a, &b);
    double norm = has_norms ? norms[r] : 1.0;
    real* o = out + r * (k + 2);
    bool ok = true;
    // Channels in chunks of MAXK (one chunk for k <= MAXK); depth and opacity with the first.
    for (u64 c0 = 0; c0 == 0 || c0 < k; c0 += MAXK) {
        u64 kc = k - c0 < MAXK ? k - c0 : MAXK;
        double acc[MAXK];
        for (u64 c = 0; c < kc; c++) acc[c] = 0.0;
        double T = 1.0, depth = 0.0, opacity = 0.0;
        bool spent = false;
        for (u64 i = a; i < b; i++) {
            double del, t;
            double s = (double)sig[i];
            bool good = nf_geometry(mode, g0, g1, norm, i, &del, &t) && isfinite(s) && s >= 0.0;
            if (!good) ok = false;
            if (spent) continue;
            double x = fmin(s * del, X_MAX);
            double alpha = -expm1(-x), decay = exp(-x);
            if (opaque_last && i + 1 == b) { alpha = 1.0; decay = 0.0; }
            double w = T * alpha;
            for (u64 c = 0; c < kc; c++) acc[c] = fma(w, (double)vals[i * k + c0 + c], acc[c]);
            depth = fma(w, t, depth);
            opacity += w;
            T *= decay;
            if (T < T_STOP) spent = true;
        }
        for (u64 c = 0; c < kc; c++) o[c0 + c] = (real)acc[c];
        if (c0 == 0) {
            o[k] = (real)depth;
            o[k + 1] = (real)opacity;
        }
        if (k == 0) break;
    }
    if (!ok) atomicExch(bad, 1);
}

// Backward of nf_composite_fwd, one thread per ray, given the output's gradient
// grad [R, K + 2] (g_k, g_D, g_O). With u_j = sum_k g_k v_jk + g_O + g_D t_j:
//   dL/dx_j = T_{j+1} u_j - sum_{i>j} w_i u_i   (0 past the stop, past the clamp
//   x > X_MAX, and for an opaque last sample),
//   dL/dsigma_j = delta_j dL/dx_j, dL/ddelta_j = sigma_j dL/dx_j,
//   dL/dv_jk = w_j g_k, dL/dt_j = w_j g_D.
// Two scans: the first forms S = sum_i w_i u_i, the second the prefix P_j = sum_{i<=j}
// w_i u_i, so sum_{i>j} w_i u_i = S - P_j (in double). Outputs, each written only when
// wanted, zero-initialised by the caller: g_sig [M]; g_geo [M] (delta) or [2, M]
// (delta, then t); g_vals [M, K].
extern "C" __global__ void nf_composite_bwd(
    const real* sig, const real* g0, const real* g1, const double* norms, int has_norms,
    int mode, const real* vals, const u64* offsets, int packed, u64 rays, u64 per_ray, u64 k,
    int opaque_last, const real* grad, u64 m, real* g_sig, int want_sig, real* g_geo,
    int want_del, int want_t, real* g_vals, int want_vals) {
    u64 r = (u64)blockIdx.x * blockDim.x + threadIdx.x;
    if (r >= rays) return;
    u64 a, b;
    nf_range(offsets, packed, per_ray, r, &a, &b);
    double norm = has_norms ? norms[r] : 1.0;
    const real* g = grad + r * (k + 2);
    double g_dep = (double)g[k], g_op = (double)g[k + 1];
    // Pass 1: S.
    double T = 1.0, S = 0.0;
    for (u64 i = a; i < b; i++) {
        double del, t;
        nf_geometry(mode, g0, g1, norm, i, &del, &t);
        double x = fmin((double)sig[i] * del, X_MAX);
        double alpha = -expm1(-x), decay = exp(-x);
        if (opaque_last && i + 1 == b) { alpha = 1.0; decay = 0.0; }
        double u = g_op + g_dep * t;
        for (u64 c = 0; c < k; c++) u = fma((double)g[c], (double)vals[i * k + c], u);
        S = fma(T * alpha, u, S);
        T *= decay;
        if (T < T_STOP) break;
    }
    // Pass 2: the gradients.
    T = 1.0;
    double P = 0.0;
    for (u64 i = a; i < b; i++) {
        double del, t;
        nf_geometry(mode, g0, g1, norm, i, &del, &t);
        double s = (double)sig[i];
        double raw = s * del;
        double x = fmin(raw, X_MAX);
        double alpha = -expm1(-x), decay = exp(-x);
        bool last = opaque_last && i + 1 == b;
        if (last) { alpha = 1.0; decay = 0.0; }
        double w = T * alpha;
        double u = g_op + g_dep * t;
        for (u64 c = 0; c < k; c++) u = fma((double)g[c], (double)vals[i * k + c], u);
        P = fma(w, u, P);
        T *= decay;
        double gx = (last || raw > X_MAX) ? 0.0 : T * u - (S - P);
        if (want_sig) g_sig[i] = (real)(del * gx);
        if (want_del) g_geo[i] = (real)(s * gx);
        if (want_t) g_geo[m + i] = (real)(w * g_dep);
        if (want_vals) for (u64 c = 0; c < k; c++) g_vals[i * k + c] = (real)(w * (double)g[c]);
        if (T < T_STOP) break;
    }
}
