// Scatter-max pooling of point features into cells (kernels/scatter.rs).
//
// Inputs: values v [B, N, C], the cell of every point idx [B, N] (u32, each below
// `cells`). Output [B, cells, C]: y[b, q, j] = v[b, a, j] with a = the argmax point of
// cell q and channel j: the lowest point index among the cell's maxima, or the first NaN
// if the cell holds one (NaN ranks above every number; -0 and +0 are equal); empty cells
// hold 0. Backward (first order, w.r.t. v): dL/dv[b, a, j] = g[b, q, j] for each argmax a,
// 0 for every other element.
//
// Two passes find the argmax without ordering the points:
//   nf_scatter_key: key[b, q, j] = atomicMax over the cell's points of an order-preserving
//     unsigned key of v (sign-magnitude to two's order, -0 mapped to +0, every NaN to
//     the largest key); 0 (below every value's key) marks an empty cell;
//   nf_scatter_arg: arg[b, q, j] = atomicMax of ~a over the points whose key equals the
//     cell's, i.e. the lowest such a (0: empty; a < N < 2^32 - 1, so ~a != 0).
// Then nf_scatter_out (forward, one thread per output element) or nf_scatter_grad
// (backward, one thread per value element). `key` (u32 for f32, u64 for f64) and `arg`
// are zeroed by the caller.

template <int S> struct nf_key_of;
template <> struct nf_key_of<4> { typedef unsigned int type; };
template <> struct nf_key_of<8> { typedef unsigned long long type; };
typedef nf_key_of<sizeof(real)>::type nf_key;

__device__ __forceinline__ unsigned int nf_order_key(float v) {
    if (isnan(v)) return 0xffffffffu;
    unsigned int b = __float_as_uint(v);
    if (b == 0x80000000u) b = 0u;
    return (b & 0x80000000u) ? ~b : (b | 0x80000000u);
}

__device__ __forceinline__ unsigned long long nf_order_key(double v) {
    if (isnan(v)) return 0xffffffffffffffffull;
    unsigned long long b = (unsigned long long)__double_as_longlong(v);
    if (b == 0x8000000000000000ull) b = 0ull;
    return (b & 0x8000000000000000ull) ? ~b : (b | 0x8000000000000000ull);
}

// The flat (batch, cell, channel) slot of value element e, or false for a bad cell id.
__device__ __forceinline__ bool nf_slot(const unsigned int* idx, u64 e, u64 n, u64 c, u64 cells, u64* slot, u64* local) {
    u64 p = e / c, ch = e % c, bi = p / n;
    u64 q = (u64)idx[p];
    if (q >= cells) return false;
    *slot = (bi * cells + q) * c + ch;
    *local = p - bi * n;
    return true;
}

extern "C" __global__ void nf_scatter_key(const real* v, const unsigned int* idx, u64 b, u64 n, u64 c, u64 cells,
                                          nf_key* key) {
    NF_GRID_STRIDE(e, b * n * c) {
        u64 slot, local;
        if (!nf_slot(idx, e, n, c, cells, &slot, &local)) continue;
        atomicMax(&key[slot], nf_order_key(v[e]));
    }
}

extern "C" __global__ void nf_scatter_arg(const real* v, const unsigned int* idx, u64 b, u64 n, u64 c, u64 cells,
                                          const nf_key* key, unsigned int* arg) {
    NF_GRID_STRIDE(e, b * n * c) {
        u64 slot, local;
        if (!nf_slot(idx, e, n, c, cells, &slot, &local)) continue;
        if (nf_order_key(v[e]) == key[slot]) atomicMax(&arg[slot], ~(unsigned int)local);
    }
}

// Forward: out [B, cells, C], one thread per element.
extern "C" __global__ void nf_scatter_out(const real* v, const unsigned int* arg, u64 b, u64 n, u64 c, u64 cells,
                                          real* out) {
    NF_GRID_STRIDE(e, b * cells * c) {
        unsigned int a = arg[e];
        u64 bi = e / (cells * c), ch = e % c;
        u64 winner = (u64)(~a);
        out[e] = (a != 0u && winner < n) ? v[(bi * n + winner) * c + ch] : (real)0;
    }
}

// Backward: gv [B, N, C] given g [B, cells, C], one thread per element.
extern "C" __global__ void nf_scatter_grad(const unsigned int* idx, const unsigned int* arg, const real* g, u64 b,
                                           u64 n, u64 c, u64 cells, real* gv) {
    NF_GRID_STRIDE(e, b * n * c) {
        u64 slot, local;
        bool won = nf_slot(idx, e, n, c, cells, &slot, &local) && arg[slot] == ~(unsigned int)local;
        gv[e] = won ? g[slot] : (real)0;
    }
}
