// Elementwise activations, the values the CPU kernels compute (numerics.rs), each in
// the storage dtype `real`. NaN propagates.

extern "C" __global__ void nf_softplus(const real* x, real* y, u64 n, real beta) {
    NF_GRID_STRIDE(i, n) {
        real v = x[i];
        real relu = v > (real)0 ? v : v * (real)0;
        y[i] = relu + log1p(exp(-fabs(beta * v))) / beta;
    }
}

// sigma(beta x), the slope of softplus_beta, without overflow.
extern "C" __global__ void nf_sigmoid_scaled(const real* x, real* y, u64 n, real beta) {
    NF_GRID_STRIDE(i, n) {
        real z = beta * x[i];
        real e = exp(-fabs(z));
        y[i] = z >= (real)0 ? (real)1 / ((real)1 + e) : e / ((real)1 + e);
    }
}

// exp(min(x, cap)), cap = 88 (f32) or 709 (f64).
extern "C" __global__ void nf_trunc_exp(const real* x, real* y, u64 n) {
    const real cap = sizeof(real) == 4 ? (real)88 : (real)709;
    NF_GRID_STRIDE(i, n) {
        real v = x[i];
        y[i] = v > cap ? exp(cap) : exp(v);
    }
}
