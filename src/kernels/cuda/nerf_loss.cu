// NeRF's photometric loss on CUDA (kernels/nerf_loss.rs has the math): the encodings,
// the per-layer bias and activation passes around cuBLAS's matrix products, and one
// thread per ray for the density and colour activations, compositing, the squared error
// and their backward pass to the networks' raw outputs.
//
// Layouts (row-major): samples [M, 4] = position, delta; rays [R, 9] = unit direction,
// target colour, background colour; ray r owns samples offsets[r]..offsets[r + 1].

#define X_MAX 1000.0

// Frequency encoding of the 3 columns `x[row * stride + col]`: [x (when included),
// sin(pi 2^k x_d) for each d, cos(pi 2^k x_d) for each d, k = 0..l-1] (l = 0 with the
// input: the identity).
__device__ __forceinline__ void nf_nl_encode3(const real* x, u64 stride, u64 row, u64 j, u64 l,
                                              int include, real* out, u64 w) {
    u64 head = include ? 3 : 0;
    double v = (double)x[row * stride + j];
    real* o = out + row * w;
    if (include) o[j] = x[row * stride + j];
    double scale = 1.0;
    for (u64 k = 0; k < l; k++) {
        double s, c;
        sincospi(v * scale, &s, &c);
        o[head + 6 * k + j] = (real)s;
        o[head + 6 * k + 3 + j] = (real)c;
        scale *= 2.0;
    }
}

// The trunk's input: the encoded positions [M, wp].
extern "C" __global__ void nf_nl_encode_positions(const real* samples, real* out, u64 m, u64 l,
                                                  int include, u64 wp) {
    NF_GRID_STRIDE(i, m * 3) nf_nl_encode3(samples, 4, i / 3, i % 3, l, include, out, wp);
}

// The rays' encoded directions [R, wd].
extern "C" __global__ void nf_nl_encode_directions(const real* rays, real* out, u64 r, u64 l,
                                                   int include, u64 wd) {
    NF_GRID_STRIDE(i, r * 3) nf_nl_encode3(rays, 9, i / 3, i % 3, l, include, out, wd);
}

// The head's input [M, wd + f]: the sample's ray's encoded direction, then the trunk's
// feature (columns 1.. of its output yt [M, 1 + f]). One block per ray.
extern "C" __global__ void nf_nl_head_input(const real* ed, const real* yt, const u64* offsets,
                                            u64 wd, u64 f, real* out) {
    u64 r = blockIdx.x, a = offsets[r], b = offsets[r + 1], w = wd + f;
    for (u64 e = threadIdx.x; e < (b - a) * w; e += blockDim.x) {
        u64 i = a + e / w, c = e % w;
        out[i * w + c] = c < wd ? ed[r * wd + c] : yt[i * (1 + f) + 1 + (c - wd)];
    }
}

// z += bias (per column); a = act(z) unless `last` (act 0: ReLU max(z, 0); 1: softplus
// with slope beta). z, a: [m, out].
extern "C" __global__ void nf_nl_bias_act(real* z, real* a, const real* bias, u64 m, u64 out,
                                          int act, double beta, int last) {
    NF_GRID_STRIDE(i, m * out) {
        real v = z[i] + bias[i % out];
        z[i] = v;
        if (!last) {
            if (act == 0) {
                a[i] = v > (real)0 ? v : (real)0;
            } else {
                real b = (real)beta;
                real relu = v > (real)0 ? v : v * (real)0;
                a[i] = relu + log1p(exp(-fabs(b * v))) / b;
            }
        }
    }
}

// dz = act'(z) * da (ReLU: 1[z >= 0]; softplus: sigma(beta z)), in place in da.
extern "C" __global__ void nf_nl_act_bwd(real* da, const real* z, u64 n, int act, double beta) {
    NF_GRID_STRIDE(i, n) {
        real v = z[i];
        if (act == 0) {
            if (!(v >= (real)0)) da[i] = (real)0;
        } else {
            real s = (real)beta * v;
            real e = exp(-fabs(s));
            real sig = s >= (real)0 ? (real)1 / ((real)1 + e) : e / ((real)1 + e);
            da[i] = da[i] * sig;
        }
    }
}

// The trunk output's gradient columns 1.. (the feature) from the head input's gradient
// columns wd..: gyt[i, 1 + c] = gha0[i, wd + c].
extern "C" __global__ void nf_nl_feature_grad(const real* gha0, real* gyt, u64 m, u64 wd, u64 f) {
    NF_GRID_STRIDE(e, m * f) {
        u64 i = e / f, c = e % f;
        gyt[i * (1 + f) + 1 + c] = gha0[i * (wd + f) + wd + c];
    }
}

// (sigma, dsigma/drho) at raw density rho: z = rho + shift rounded to the storage dtype;
// density 0: trunc-exp (value exp(min(z, cap)), slope exp(clamp(z, -15, 15)), in the
// storage dtype); 1: softplus (beta 1; value rounded to the storage dtype, slope sigma(z)).
__device__ __forceinline__ void nf_nl_density(double raw, int density, double shift,
                                              double* sigma, double* slope) {
    real z = (real)(raw + (double)(real)shift);
    if (density == 0) {
        const real cap = sizeof(real) == 4 ? (real)88 : (real)709;
        real c = z > (real)15 ? (real)15 : (z < (real)-15 ? (real)-15 : z);
        *sigma = (double)(z > cap ? exp(cap) : exp(z));
        *slope = (double)exp(c);
    } else {
        double zd = (double)z;
        double relu = zd > 0.0 ? zd : zd * 0.0;
        *sigma = (double)(real)(relu + log1p(exp(-fabs(zd))));
        double e = exp(-fabs(zd));
        *slope = zd >= 0.0 ? 1.0 / (1.0 + e) : e / (1.0 + e);
    }
}

// One thread per ray: sigma_i, c_i from the raw outputs (yt[:, 0], yh [M, 3]),
// compositing in double, C = sum w c + (1 - sum w) c_bg, the ray's squared error
// (atomically added to stats[0]), its opacity (stats[1] += , stats[2] = max via the bits
// of a non-negative double), and the gradients of inv * |C - C*|^2 w.r.t. the raw
// outputs: gyt[:, 0] and gyh [M, 3]. stats[3] = 1 when a raw output is not finite.
extern "C" __global__ void nf_nl_rays(const real* yt, u64 t_out, const real* yh,
                                      const real* samples, const real* rays,
                                      const u64* offsets, u64 n_rays, int density,
                                      double shift, int opaque_last, double inv, real* gyt,
                                      real* gyh, double* stats) {
    u64 r = (u64)blockIdx.x * blockDim.x + threadIdx.x;
    if (r >= n_rays) return;
    u64 a = offsets[r], b = offsets[r + 1];
    const real* d = rays + r * 9;
    double target[3], bg[3], colour[3] = {0.0, 0.0, 0.0};
    for (int k = 0; k < 3; k++) { target[k] = (double)d[3 + k]; bg[k] = (double)d[6 + k]; }
    double optical = 0.0, opacity = 0.0;
    bool finite = true;
    for (u64 i = a; i < b; i++) {
        double raw = (double)yt[i * t_out];
        finite = finite && isfinite(raw);
        double sigma, slope;
        nf_nl_density(raw, density, shift, &sigma, &slope);
        double x = fmin(sigma * (double)samples[i * 4 + 3], X_MAX);
        bool last = opaque_last && i + 1 == b;
        double alpha = last ? 1.0 : -expm1(-x);
        double w = exp(-optical) * alpha;
        optical += x;
        opacity += w;
        for (int k = 0; k < 3; k++) {
            double rc = (double)yh[i * 3 + k];
            finite = finite && isfinite(rc);
            colour[k] += w / (1.0 + exp(-rc));
        }
    }
    double g[3], loss = 0.0;
    for (int k = 0; k < 3; k++) {
        double dk = colour[k] + (1.0 - opacity) * bg[k] - target[k];
        loss += dk * dk;
        g[k] = 2.0 * dk * inv;
    }
    // The suffix sums sum_{i>j} u_i w_i, as the total minus the running prefix.
    double total = 0.0;
    optical = 0.0;
    for (u64 i = a; i < b; i++) {
        double sigma, slope;
        nf_nl_density((double)yt[i * t_out], density, shift, &sigma, &slope);
        double x = fmin(sigma * (double)samples[i * 4 + 3], X_MAX);
        bool last = opaque_last && i + 1 == b;
        double w = exp(-optical) * (last ? 1.0 : -expm1(-x));
        optical += x;
        double u = 0.0;
        for (int k = 0; k < 3; k++) {
            double c = 1.0 / (1.0 + exp(-(double)yh[i * 3 + k]));
            u += g[k] * (c - bg[k]);
        }
        total += u * w;
    }
    double prefix = 0.0;
    optical = 0.0;
    for (u64 i = a; i < b; i++) {
        double sigma, slope;
        nf_nl_density((double)yt[i * t_out], density, shift, &sigma, &slope);
        double delta = (double)samples[i * 4 + 3];
        double x = fmin(sigma * delta, X_MAX);
        bool last = opaque_last && i + 1 == b;
        double t = exp(-optical);
        double w = t * (last ? 1.0 : -expm1(-x));
        double decay = last ? 0.0 : exp(-x);
        optical += x;
        double u = 0.0, c[3];
        for (int k = 0; k < 3; k++) {
            c[k] = 1.0 / (1.0 + exp(-(double)yh[i * 3 + k]));
            u += g[k] * (c[k] - bg[k]);
        }
        prefix += u * w;
        double gx = u * t * decay - (total - prefix);
        double g_sigma = sigma * delta < X_MAX ? gx * delta : 0.0;
        gyt[i * t_out] = (real)(g_sigma * slope);
        for (int k = 0; k < 3; k++) gyh[i * 3 + k] = (real)(w * g[k] * c[k] * (1.0 - c[k]));
    }
    atomicAdd(&stats[0], loss);
    atomicAdd(&stats[1], opacity);
    atomicMax((unsigned long long*)&stats[2], (unsigned long long)__double_as_longlong(opacity));
    if (!finite) stats[3] = 1.0;  // every writer stores the same value
}

// A column of ones [n] (the right-hand side of the bias gradients' products).
extern "C" __global__ void nf_nl_ones(real* o, u64 n) {
    NF_GRID_STRIDE(i, n) o[i] = (real)1;
}
