// mip-NeRF's integrated positional encoding (kernels/integrated.rs), one thread per
// (row, coordinate), in double. Rows [mu, var] : [N, 2D] -> [N, 2DL], L = max_deg -
// min_deg; per octave k (scale s = 2^k): the D values sin(s mu_d) e_k, then the D values
// cos(s mu_d) e_k, with e_k = exp(-s^2 var_d / 2); sin(s mu) as sinpi(s mu / pi), as the
// CPU kernel does.
//
// Backward: dL/dmu_d = sum_k s e_k (g_sin cos - g_cos sin),
//           dL/dvar_d = -sum_k (s^2/2) e_k (g_sin sin + g_cos cos).

extern "C" __global__ void nf_integrated_fwd(const real* x, real* out, u64 rows, u64 d,
                                             u64 min_deg, u64 max_deg) {
    const double inv_pi = 0.3183098861837907;
    u64 l = max_deg - min_deg, w = 2 * d * l;
    NF_GRID_STRIDE(i, rows * d) {
        u64 r = i / d, j = i % d;
        double mu = (double)x[r * 2 * d + j], var = (double)x[r * 2 * d + d + j];
        real* o = out + r * w;
        for (u64 k = 0; k < l; k++) {
            double scale = ldexp(1.0, (int)(min_deg + k));
            double s, c;
            sincospi(mu * scale * inv_pi, &s, &c);
            double e = exp(-0.5 * scale * scale * var);
            o[2 * d * k + j] = (real)(s * e);
            o[2 * d * k + d + j] = (real)(c * e);
        }
    }
}

extern "C" __global__ void nf_integrated_bwd(const real* x, const real* g, real* gx, u64 rows,
                                             u64 d, u64 min_deg, u64 max_deg) {
    const double inv_pi = 0.3183098861837907;
    u64 l = max_deg - min_deg, w = 2 * d * l;
    NF_GRID_STRIDE(i, rows * d) {
        u64 r = i / d, j = i % d;
        double mu = (double)x[r * 2 * d + j], var = (double)x[r * 2 * d + d + j];
        const real* gi = g + r * w;
        double gm = 0.0, gv = 0.0;
        for (u64 k = 0; k < l; k++) {
            double scale = ldexp(1.0, (int)(min_deg + k));
            double s, c;
            sincospi(mu * scale * inv_pi, &s, &c);
            double e = exp(-0.5 * scale * scale * var);
            double gs = (double)gi[2 * d * k + j], gc = (double)gi[2 * d * k + d + j];
            gm += scale * e * (gs * c - gc * s);
            gv -= 0.5 * scale * scale * e * (gs * s + gc * c);
        }
        gx[r * 2 * d + j] = (real)gm;
        gx[r * 2 * d + d + j] = (real)gv;
    }
}
