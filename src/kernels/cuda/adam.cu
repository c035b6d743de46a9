// Adam's two in-place passes (kernels/adam.rs), in the storage dtype `real`, in the
// order of the CPU kernel. NaN propagates.

// mv = [m; v] (2n elements): m = b1 m + c1 g, v = b2 v + c2 g^2.
extern "C" __global__ void nf_adam_moments(real* mv, const real* g, u64 n, real b1, real c1,
                                           real b2, real c2) {
    NF_GRID_STRIDE(i, n) {
        real gi = g[i];
        mv[i] = mv[i] * b1 + gi * c1;
        mv[n + i] = mv[n + i] * b2 + gi * gi * c2;
    }
}

// theta = theta keep - lr (m sm) / (sqrt(v sv) + eps).
extern "C" __global__ void nf_adam_update(real* theta, const real* mv, u64 n, real keep, real lr,
                                          real eps, real sm, real sv) {
    NF_GRID_STRIDE(i, n) {
        real step = (mv[i] * sm) / (sqrt(mv[n + i] * sv) + eps);
        theta[i] = theta[i] * keep - step * lr;
    }
}
