// instant-NGP's multiresolution hash encoding (kernels/hash_grid.rs), computed in double
// whatever the storage dtype, with the CPU kernel's operations in its order (products by
// __dmul_rn, never contracted into an fma), so that the forward pass and the position
// gradient are the CPU's values bit for bit.
//
// Inputs: x [N, D] (D = 1 to 4), table [R, F] (the levels' tables concatenated), the
// level table lv [L, 3] (u64: cells N_l, first row of the level, dense flag), the box
// bnd [2, D] (double: lo, then ext = hi - lo), the hash mask 2^T - 1 and R. Output
// [N, L*F], level-major columns.
//
// t_d = clamp((x_d - lo_d) / ext_d, 0, 1), dt_d/dx_d = 1/ext_d inside [0, 1] (faces
// included) and 0 outside. At level l: u = t*N_l, i = min(floor(u), N_l - 1), w = u - i.
// Corner c (bit k set: i_k + 1 on axis k) has the weight prod_k (w_k or 1 - w_k) (in axis
// order) and the row offset_l + (dense: sum_k v_k (N_l + 1)^k; hashed:
// (xor_k v_k * pi_k) & mask, pi = (1, 2654435761, 805459861, 3674653429), wrapping u32).
// y[p, l*F + j] = sum_c weight_c table[row_c, j].
//
// Backward (first order), given g [N, L*F]:
//   dL/dtable[row_c, j] += weight_c g[p, l*F + j]   (nf_hash_bwd_table: atomicAdd into a
//     double buffer [R, F] zeroed by the caller, then nf_hash_cast; elements with
//     g = 0 are skipped, as on the CPU);
//   dL/dx_a = sum_l sum_c (sum_j g[p, l*F + j] table[row_c, j]) dweight_c,a with
//     dweight_c,a = prod_k (k = a: +-N_l dt_a; else w_k or 1 - w_k)   (nf_hash_bwd_x).

__constant__ unsigned int NF_PRIMES[4] = {1u, 2654435761u, 805459861u, 3674653429u};

// One point at one level: per axis the cell i, the local coordinate w and dw = N_l dt/dx.
struct nf_axes {
    unsigned int i[4];
    double w[4];
    double dw[4];
};

// The normalised coordinates t and dt/dx of row x (HashPlan::unit).
__device__ __forceinline__ void nf_unit(const real* x, const double* bnd, int d, double* t, double* dt) {
    for (int k = 0; k < d; k++) {
        double ext = bnd[d + k];
        double v = ((double)x[k] - bnd[k]) / ext;
        bool inside = v >= 0.0 && v <= 1.0;
        t[k] = v < 0.0 ? 0.0 : (v > 1.0 ? 1.0 : v);  // NaN stays NaN, as f64::clamp
        dt[k] = inside ? 1.0 / ext : 0.0;
    }
}

// The cell and local coordinates of t at a level of `cells` cells per axis.
__device__ __forceinline__ void nf_level_axes(const double* t, const double* dt, int d, unsigned int cells, nf_axes* a) {
    double n = (double)cells;
    for (int k = 0; k < d; k++) {
        double u = __dmul_rn(t[k], n);
        double fu = floor(u);
        // Rust's saturating `as u32` (NaN: 0); u lies in [0, N] for t in [0, 1].
        unsigned int i = fu >= 0.0 ? (fu < 4294967295.0 ? (unsigned int)fu : 4294967295u) : 0u;
        if (i > cells - 1u) i = cells - 1u;
        a->i[k] = i;
        a->w[k] = u - (double)i;
        a->dw[k] = __dmul_rn(n, dt[k]);
    }
}

// Corner c's row in the concatenated table.
__device__ __forceinline__ u64 nf_corner_row(const nf_axes* a, int d, int c, unsigned int cells,
                                             u64 offset, int dense, unsigned int mask) {
    u64 side = (u64)cells + 1, stride = 1, index = 0;
    unsigned int hash = 0;
    for (int k = 0; k < d; k++) {
        unsigned int v = a->i[k] + ((c >> k) & 1);
        index += (u64)v * stride;
        hash ^= v * NF_PRIMES[k];
        stride *= side;
    }
    return offset + (dense ? index : (u64)(hash & mask));
}

// Corner c's weight, the product over the axes in order from 1.
__device__ __forceinline__ double nf_corner_weight(const nf_axes* a, int d, int c) {
    double wt = 1.0;
    for (int k = 0; k < d; k++) wt *= ((c >> k) & 1) ? a->w[k] : 1.0 - a->w[k];
    return wt;
}

// Corner c's weight derivative w.r.t. x_j, the product over the axes in order from 1.
__device__ __forceinline__ double nf_corner_dweight(const nf_axes* a, int d, int c, int j) {
    double g = 1.0;
    for (int k = 0; k < d; k++) {
        bool up = (c >> k) & 1;
        if (k == j) g *= up ? a->dw[k] : -a->dw[k];
        else g *= up ? a->w[k] : 1.0 - a->w[k];
    }
    return g;
}

// The rows and weights of point x at level l.
__device__ __forceinline__ int nf_level_corners(const double* t, const double* dt, int d, const u64* lv, u64 l,
                                                unsigned int mask, u64* rows, double* wts) {
    unsigned int cells = (unsigned int)lv[3 * l];
    u64 offset = lv[3 * l + 1];
    int dense = lv[3 * l + 2] != 0;
    nf_axes a;
    nf_level_axes(t, dt, d, cells, &a);
    int nc = 1 << d;
    for (int c = 0; c < nc; c++) {
        rows[c] = nf_corner_row(&a, d, c, cells, offset, dense, mask);
        wts[c] = nf_corner_weight(&a, d, c);
    }
    return nc;
}

// Forward: one thread per (level, point), points fastest.
extern "C" __global__ void nf_hash_fwd(const real* x, const real* table, const u64* lv, const double* bnd,
                                       u64 n, int d, u64 f, u64 levels, unsigned int mask, u64 table_rows,
                                       real* out) {
    if (d < 1 || d > 4) return;
    NF_GRID_STRIDE(i, n * levels) {
        u64 l = i / n, p = i % n;
        double t[4], dt[4];
        nf_unit(x + p * d, bnd, d, t, dt);
        u64 rows[16];
        double wts[16];
        int nc = nf_level_corners(t, dt, d, lv, l, mask, rows, wts);
        real* o = out + p * (levels * f) + l * f;
        for (u64 j = 0; j < f; j++) {
            double acc = 0.0;
            for (int c = 0; c < nc; c++) {
                if (rows[c] < table_rows) acc += __dmul_rn(wts[c], (double)table[rows[c] * f + j]);
            }
            o[j] = (real)acc;
        }
    }
}

// Table gradient: one thread per (level, point), atomicAdd into acc [R, F] (double).
extern "C" __global__ void nf_hash_bwd_table(const real* x, const u64* lv, const double* bnd, u64 n, int d,
                                             u64 f, u64 levels, unsigned int mask, u64 table_rows,
                                             const real* grad, double* acc) {
    if (d < 1 || d > 4) return;
    NF_GRID_STRIDE(i, n * levels) {
        u64 l = i / n, p = i % n;
        double t[4], dt[4];
        nf_unit(x + p * d, bnd, d, t, dt);
        u64 rows[16];
        double wts[16];
        int nc = nf_level_corners(t, dt, d, lv, l, mask, rows, wts);
        const real* g = grad + p * (levels * f) + l * f;
        for (u64 j = 0; j < f; j++) {
            double gj = (double)g[j];
            if (gj == 0.0) continue;
            for (int c = 0; c < nc; c++) {
                if (rows[c] < table_rows) atomicAdd(&acc[rows[c] * f + j], __dmul_rn(wts[c], gj));
            }
        }
    }
}

// The largest |g| over all m gradient values, as the bits of a non-negative double
// (atomicMax on the bits orders non-negative doubles; NaN, whose bits exceed +inf's,
// makes the result NaN). `mx` is zeroed by the caller.
extern "C" __global__ void nf_hash_grad_max(const real* g, u64 m, unsigned long long* mx) {
    NF_GRID_STRIDE(i, m) {
        double v = fabs((double)g[i]);
        if (v != 0.0 || v != v) atomicMax(mx, (unsigned long long)__double_as_longlong(v));
    }
}

// Table gradient in fixed point: as nf_hash_bwd_table, each contribution rounded to an
// integer multiple of 1/scale and added as a 64-bit two's-complement integer (wrapping
// addition is associative, and the final sums lie within +-2^62, so the result does not
// depend on the order of the additions).
extern "C" __global__ void nf_hash_bwd_table_fixed(const real* x, const u64* lv, const double* bnd, u64 n,
                                                   int d, u64 f, u64 levels, unsigned int mask,
                                                   u64 table_rows, const real* grad, double scale,
                                                   unsigned long long* acc) {
    if (d < 1 || d > 4) return;
    NF_GRID_STRIDE(i, n * levels) {
        u64 l = i / n, p = i % n;
        double t[4], dt[4];
        nf_unit(x + p * d, bnd, d, t, dt);
        u64 rows[16];
        double wts[16];
        int nc = nf_level_corners(t, dt, d, lv, l, mask, rows, wts);
        const real* g = grad + p * (levels * f) + l * f;
        for (u64 j = 0; j < f; j++) {
            double gj = (double)g[j];
            if (gj == 0.0) continue;
            for (int c = 0; c < nc; c++) {
                if (rows[c] < table_rows) {
                    long long q = llrint(__dmul_rn(__dmul_rn(wts[c], gj), scale));
                    atomicAdd(&acc[rows[c] * f + j], (unsigned long long)q);
                }
            }
        }
    }
}

// o = (real)(a / scale) for the fixed-point sums a, elementwise over m values.
extern "C" __global__ void nf_hash_cast_fixed(const unsigned long long* a, double scale, real* o, u64 m) {
    NF_GRID_STRIDE(i, m) o[i] = (real)((double)(long long)a[i] / scale);
}

// Position gradient: one thread per point, the levels, corners and features in the CPU's
// order.
extern "C" __global__ void nf_hash_bwd_x(const real* x, const real* table, const u64* lv, const double* bnd,
                                         u64 n, int d, u64 f, u64 levels, unsigned int mask, u64 table_rows,
                                         const real* grad, real* gx) {
    if (d < 1 || d > 4) return;
    NF_GRID_STRIDE(p, n) {
        double t[4], dt[4];
        nf_unit(x + p * d, bnd, d, t, dt);
        double acc[4] = {0.0, 0.0, 0.0, 0.0};
        const real* g = grad + p * (levels * f);
        int nc = 1 << d;
        for (u64 l = 0; l < levels; l++) {
            unsigned int cells = (unsigned int)lv[3 * l];
            u64 offset = lv[3 * l + 1];
            int dense = lv[3 * l + 2] != 0;
            nf_axes a;
            nf_level_axes(t, dt, d, cells, &a);
            for (int c = 0; c < nc; c++) {
                u64 row = nf_corner_row(&a, d, c, cells, offset, dense, mask);
                if (row >= table_rows) continue;
                double s = 0.0;
                for (u64 j = 0; j < f; j++)
                    s += __dmul_rn((double)g[l * f + j], (double)table[row * f + j]);
                for (int k = 0; k < d; k++) acc[k] += __dmul_rn(s, nf_corner_dweight(&a, d, c, k));
            }
        }
        for (int k = 0; k < d; k++) gx[p * d + k] = (real)acc[k];
    }
}

// o = (real)a, elementwise over m values.
extern "C" __global__ void nf_hash_cast(const double* a, real* o, u64 m) {
    NF_GRID_STRIDE(i, m) o[i] = (real)a[i];
}
