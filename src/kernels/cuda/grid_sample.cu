// Bilinear/trilinear sampling of feature planes and grids (kernels/grid_sample.rs),
// computed in double whatever the storage dtype, with the CPU kernel's operations in its
// order (products by __dmul_rn, never contracted into an fma), so that the forward pass
// and the coordinate gradient are the CPU's values bit for bit.
//
// Inputs: features [B, C, P] (P = prod of the spatial sizes, flattened with W fastest),
// coords [B, N, k] (k = 2 or 3; coordinate a runs along W, H, D for a = 0, 1, 2). The
// geometry: size_a (samples along coordinate axis a, 1 past k) and stride_a (of axis a in
// the flat spatial index). Output [B, N, C].
//
// Per axis of S samples: S < 2: i = 0, w = 0, dw = 0; otherwise u = clamp(c, 0, 1)(S - 1),
// i = min(floor(u), S - 2), w = u - i, dw = dw/dc = S - 1 for c in [0, 1] and 0 outside
// (clamped). Corner q (bit a set: i_a + 1 on axis a, or i_a again on an axis of one
// sample) has the flat offset sum_a (i_a + q_a [S_a > 1]) stride_a and the weight
// prod_a (w_a or 1 - w_a) (in axis order). y[b, n, ch] = sum_q weight_q F[b, ch, off_q].
//
// Backward (first order), given g [B, N, C]:
//   dL/dF[b, ch, off_q] += weight_q g[b, n, ch]   (nf_gs_bwd_features: atomicAdd into a
//     double buffer [B, C, P] zeroed by the caller, then nf_gs_cast; g = 0 skipped, as
//     on the CPU);
//   dL/dc_a = sum_q (sum_ch g[b, n, ch] F[b, ch, off_q]) dweight_q,a with
//     dweight_q,a = prod_a' (a' = a: +-dw_a; else w_a' or 1 - w_a')   (nf_gs_bwd_coords).

struct nf_gs_geo {
    u64 size[3];
    u64 stride[3];
};

// One axis of one point (GridGeometry::axis).
__device__ __forceinline__ void nf_gs_axis(u64 n, double c, u64* i, double* w, double* dw) {
    if (n < 2) {
        *i = 0;
        *w = 0.0;
        *dw = 0.0;
        return;
    }
    double s = (double)(n - 1);
    bool inside = c >= 0.0 && c <= 1.0;
    double cl = c < 0.0 ? 0.0 : (c > 1.0 ? 1.0 : c);  // NaN stays NaN, as f64::clamp
    double u = __dmul_rn(cl, s);
    double fu = floor(u);
    // Rust's saturating `as usize` (NaN: 0); u lies in [0, S - 1].
    u64 ii = fu >= 0.0 ? (fu < 18446744073709551615.0 ? (u64)fu : 18446744073709551615ull) : 0ull;
    if (ii > n - 2) ii = n - 2;
    *i = ii;
    *w = u - (double)ii;
    *dw = inside ? s : 0.0;
}

// The per-axis cells, local coordinates and rates of point c (k coordinates).
__device__ __forceinline__ void nf_gs_axes(const nf_gs_geo* g, int k, const real* c, u64* i, double* w, double* dw) {
    for (int a = 0; a < k; a++) nf_gs_axis(g->size[a], (double)c[a], &i[a], &w[a], &dw[a]);
}

__device__ __forceinline__ u64 nf_gs_offset(const nf_gs_geo* g, int k, const u64* i, int q) {
    u64 off = 0;
    for (int a = 0; a < k; a++) {
        u64 step = ((q >> a) & 1) && g->size[a] > 1 ? g->stride[a] : 0;
        off += i[a] * g->stride[a] + step;
    }
    return off;
}

__device__ __forceinline__ double nf_gs_weight(int k, const double* w, int q) {
    double wt = 1.0;
    for (int a = 0; a < k; a++) wt *= ((q >> a) & 1) ? w[a] : 1.0 - w[a];
    return wt;
}

__device__ __forceinline__ double nf_gs_dweight(int k, const double* w, const double* dw, int q, int j) {
    double g = 1.0;
    for (int a = 0; a < k; a++) {
        bool up = (q >> a) & 1;
        if (a == j) g *= up ? dw[a] : -dw[a];
        else g *= up ? w[a] : 1.0 - w[a];
    }
    return g;
}

#define NF_GS_GEO                                              \
    nf_gs_geo geo;                                             \
    geo.size[0] = s0; geo.size[1] = s1; geo.size[2] = s2;      \
    geo.stride[0] = st0; geo.stride[1] = st1; geo.stride[2] = st2;

// Forward: one thread per (point, channel), channels fastest.
extern "C" __global__ void nf_gs_fwd(const real* feat, const real* coords, u64 b, u64 n, u64 c, int k,
                                     u64 s0, u64 s1, u64 s2, u64 st0, u64 st1, u64 st2, u64 cells,
                                     real* out) {
    if (k < 1 || k > 3) return;
    NF_GS_GEO
    NF_GRID_STRIDE(e, b * n * c) {
        u64 p = e / c, ch = e % c, bi = p / n;
        u64 i[3];
        double w[3], dw[3];
        nf_gs_axes(&geo, k, coords + p * k, i, w, dw);
        const real* plane = feat + (bi * c + ch) * cells;
        double acc = 0.0;
        for (int q = 0; q < (1 << k); q++) {
            u64 off = nf_gs_offset(&geo, k, i, q);
            if (off < cells) acc += __dmul_rn(nf_gs_weight(k, w, q), (double)plane[off]);
        }
        out[e] = (real)acc;
    }
}

// Feature gradient: one thread per (point, channel), atomicAdd into acc [B, C, P] (double).
extern "C" __global__ void nf_gs_bwd_features(const real* coords, const real* grad, u64 b, u64 n, u64 c, int k,
                                              u64 s0, u64 s1, u64 s2, u64 st0, u64 st1, u64 st2, u64 cells,
                                              double* acc) {
    if (k < 1 || k > 3) return;
    NF_GS_GEO
    NF_GRID_STRIDE(e, b * n * c) {
        double gj = (double)grad[e];
        if (gj == 0.0) continue;
        u64 p = e / c, ch = e % c, bi = p / n;
        u64 i[3];
        double w[3], dw[3];
        nf_gs_axes(&geo, k, coords + p * k, i, w, dw);
        double* a = acc + (bi * c + ch) * cells;
        for (int q = 0; q < (1 << k); q++) {
            u64 off = nf_gs_offset(&geo, k, i, q);
            if (off < cells) atomicAdd(&a[off], __dmul_rn(nf_gs_weight(k, w, q), gj));
        }
    }
}

// Coordinate gradient: one thread per point, the corners and channels in the CPU's order.
extern "C" __global__ void nf_gs_bwd_coords(const real* feat, const real* coords, const real* grad, u64 b, u64 n,
                                            u64 c, int k, u64 s0, u64 s1, u64 s2, u64 st0, u64 st1, u64 st2,
                                            u64 cells, real* gc) {
    if (k < 1 || k > 3) return;
    NF_GS_GEO
    NF_GRID_STRIDE(p, b * n) {
        u64 bi = p / n;
        u64 i[3];
        double w[3], dw[3];
        nf_gs_axes(&geo, k, coords + p * k, i, w, dw);
        const real* fb = feat + bi * c * cells;
        const real* g = grad + p * c;
        double acc[3] = {0.0, 0.0, 0.0};
        for (int q = 0; q < (1 << k); q++) {
            u64 off = nf_gs_offset(&geo, k, i, q);
            if (off >= cells) continue;
            double s = 0.0;
            for (u64 ch = 0; ch < c; ch++) s += __dmul_rn((double)g[ch], (double)fb[ch * cells + off]);
            for (int a = 0; a < k; a++) acc[a] += __dmul_rn(s, nf_gs_dweight(k, w, dw, q, a));
        }
        for (int a = 0; a < k; a++) gc[p * k + a] = (real)acc[a];
    }
}

// o = (real)a, elementwise over m values.
extern "C" __global__ void nf_gs_cast(const double* a, real* o, u64 m) {
    NF_GRID_STRIDE(i, m) o[i] = (real)a[i];
}
