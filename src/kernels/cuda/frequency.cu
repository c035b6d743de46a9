// NeRF's frequency encoding with frequencies 2^k pi (kernels/frequency.rs), one thread
// per (row, coordinate). x [N, D] -> out [N, E], E = D (1 + 2L) with the input, 2DL
// without; row layout: [x (when included)], then for k = 0..L: sin(pi 2^k x_d) for each
// d, cos(pi 2^k x_d) for each d. sincospi reduces the argument exactly (in double for
// both dtypes: an f32 input widens exactly, and the result is rounded once).
//
// Backward: dL/dx_d = g_{x_d} + sum_k pi 2^k (g_{sin,k,d} cos(pi 2^k x_d)
//                                              - g_{cos,k,d} sin(pi 2^k x_d)).

extern "C" __global__ void nf_frequency_fwd(const real* x, real* out, u64 rows, u64 d, u64 l,
                                            int include_input) {
    u64 head = include_input ? d : 0, w = head + 2 * d * l;
    NF_GRID_STRIDE(i, rows * d) {
        u64 r = i / d, j = i % d;
        double v = (double)x[i];
        real* o = out + r * w;
        if (include_input) o[j] = x[i];
        double scale = 1.0;
        for (u64 k = 0; k < l; k++) {
            double s, c;
            sincospi(v * scale, &s, &c);
            o[head + 2 * d * k + j] = (real)s;
            o[head + 2 * d * k + d + j] = (real)c;
            scale *= 2.0;
        }
    }
}

extern "C" __global__ void nf_frequency_bwd(const real* x, const real* g, real* gx, u64 rows,
                                            u64 d, u64 l, int include_input) {
    u64 head = include_input ? d : 0, w = head + 2 * d * l;
    const double pi = 3.141592653589793;
    NF_GRID_STRIDE(i, rows * d) {
        u64 r = i / d, j = i % d;
        double v = (double)x[i];
        const real* gi = g + r * w;
        double acc = include_input ? (double)gi[j] : 0.0;
        double scale = 1.0;
        for (u64 k = 0; k < l; k++) {
            double s, c;
            sincospi(v * scale, &s, &c);
            acc += pi * scale * ((double)gi[head + 2 * d * k + j] * c
                                 - (double)gi[head + 2 * d * k + d + j] * s);
            scale *= 2.0;
        }
        gx[i] = (real)acc;
    }
}
