//! NeRF's frequency positional encoding with frequencies `2ᵏπ` as one CPU op
//! (`FusedFrequency`, what [`crate::encoding::FrequencyEncoding`] runs on the CPU), and
//! its rows, which the fused NeRF loss evaluates inside its tiles.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::parallel::for_each_init;
use crate::numerics::round_to_integer;
use candle_core::{Shape, WithDType};

/// The frequency encoding with `2ᵏπ` as one CPU op: each output row written in one pass
/// (no intermediate `[N, L, D]` tensors) and the backward pass
/// `∂L/∂x_d = ḡ_{x_d} + Σ_k π2ᵏ (ḡ_{sin,k,d} cos(π2ᵏx_d) − ḡ_{cos,k,d} sin(π2ᵏx_d))`,
/// recomputing the sines and cosines. The argument is reduced exactly, as
/// [`crate::numerics::sin_cos_pi`] does, and the sine and cosine come from one branch-free
/// polynomial pass in f64 ([`sin_cos_pi_slices`]), which the compiler vectorises; f32 inputs
/// are widened (exactly) and the results rounded once, so they are at least as accurate as
/// the reference path's f32 `sin(π·r)`.
#[derive(Clone)]
pub(crate) struct FusedFrequency {
    /// Input dimension `D`.
    pub(crate) in_dim: usize,
    /// Frequencies `L`.
    pub(crate) n_freqs: usize,
    /// Whether the raw input leads each output row.
    pub(crate) include_input: bool,
}

/// Rows per work item of the fused encoding (its f64 scratch stays in L2).
const ENCODE_ROWS: usize = 256;

/// The loop of [`sin_cos_pi_slices`], inlined into each instruction-set build.
// The coefficients are written with the decimals they were published with.
#[allow(clippy::excessive_precision)]
#[inline(always)]
fn sin_cos_pi_slices_body(y: &[f64], s: &mut [f64], c: &mut [f64]) {
    const S: [f64; 6] = [
        -1.666_666_666_666_663_243_48e-1,
        8.333_333_333_322_489_461_24e-3,
        -1.984_126_982_985_794_931_34e-4,
        2.755_731_370_707_006_767_89e-6,
        -2.505_076_025_340_686_341_95e-8,
        1.589_690_995_211_550_102_21e-10,
    ];
    const C: [f64; 6] = [
        4.166_666_666_666_660_190_37e-2,
        -1.388_888_888_887_410_957_49e-3,
        2.480_158_728_947_672_941_78e-5,
        -2.755_731_435_139_066_330_35e-7,
        2.087_572_321_298_174_827_90e-9,
        -1.135_964_755_778_819_482_65e-11,
    ];
    for ((&y, s), c) in y.iter().zip(s.iter_mut()).zip(c.iter_mut()) {
        let r = y - 2.0 * round_to_integer(0.5 * y);
        let q = round_to_integer(2.0 * r);
        let x = (r - 0.5 * q) * std::f64::consts::PI;
        let z = x * x;
        let ps = z * (S[0] + z * (S[1] + z * (S[2] + z * (S[3] + z * (S[4] + z * S[5])))));
        let sin = x + x * ps;
        let pc = C[0] + z * (C[1] + z * (C[2] + z * (C[3] + z * (C[4] + z * C[5]))));
        let cos = (1.0 - 0.5 * z) + z * z * pc;
        // q ∈ {−2, …, 2}: sin(πy) = (s, c, −s, −c)[q mod 4], cos(πy) = (c, −s, −c, s)[q mod 4],
        // written as comparisons so that the loop stays vectorisable.
        let odd = q.abs() == 1.0;
        let (a, b) = if odd { (cos, sin) } else { (sin, cos) };
        *s = if (-0.5..=1.5).contains(&q) { a } else { -a };
        *c = if (-1.5..=0.5).contains(&q) { b } else { -b };
    }
}

/// `sin(πy)` and `cos(πy)` for every `y`, to about 1 ulp of f64.
///
/// Reduction (exact): `r = y − 2·round(y/2) ∈ [−1, 1]`, then `q = round(2r)` and
/// `f = r − q/2 ∈ [−¼, ¼]`, so `πy ≡ πf + qπ/2`; the kernels are musl's minimax
/// polynomials for `sin` and `cos` on `[−π/4, π/4]`, and the quadrant `q mod 4` swaps
/// and negates them. Rounding to an integer is [`crate::numerics::round_to_integer`], so
/// the loop has no calls and no branches; it runs compiled for AVX-512 or AVX2 where
/// the CPU has them.
pub(super) fn sin_cos_pi_slices(y: &[f64], s: &mut [f64], c: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx512f,avx512dq,avx512vl,fma")]
        fn avx512(y: &[f64], s: &mut [f64], c: &mut [f64]) {
            sin_cos_pi_slices_body(y, s, c)
        }
        #[target_feature(enable = "avx2,fma")]
        fn avx2(y: &[f64], s: &mut [f64], c: &mut [f64]) {
            sin_cos_pi_slices_body(y, s, c)
        }
        use std::arch::is_x86_feature_detected as has;
        if has!("avx512f") && has!("avx512dq") && has!("avx512vl") && has!("fma") {
            // SAFETY: the CPU has the features the function was compiled for.
            return unsafe { avx512(y, s, c) };
        }
        if has!("avx2") && has!("fma") {
            // SAFETY: as above.
            return unsafe { avx2(y, s, c) };
        }
    }
    sin_cos_pi_slices_body(y, s, c)
}

/// Per-worker scratch of the fused encoding: arguments, sines, cosines.
pub(crate) type Trig = (Vec<f64>, Vec<f64>, Vec<f64>);

impl FusedFrequency {
    /// Output columns `E = D·(1 + 2L)` with the input, `2DL` without.
    pub(crate) fn width(&self) -> usize {
        self.in_dim * (2 * self.n_freqs + usize::from(self.include_input))
    }

    /// Per-worker scratch for [`ENCODE_ROWS`] rows.
    pub(crate) fn scratch(&self) -> Trig {
        let m = ENCODE_ROWS * self.in_dim * self.n_freqs;
        (vec![0.0; m], vec![0.0; m], vec![0.0; m])
    }

    /// Sines and cosines of `π2ᵏx` for the rows `x`, laid out `[row][k][d]` in `t.1`, `t.2`.
    fn trig<T: WithDType>(&self, x: &[T], t: &mut Trig) -> usize {
        let (d, l) = (self.in_dim, self.n_freqs);
        let m = x.len() * l;
        for (row, args) in x.chunks(d).zip(t.0.chunks_mut((d * l).max(1))) {
            let mut scale = 1.0;
            for k in 0..l {
                for (a, &v) in args[k * d..(k + 1) * d].iter_mut().zip(row) {
                    *a = v.to_f64() * scale;
                }
                scale *= 2.0;
            }
        }
        sin_cos_pi_slices(&t.0[..m], &mut t.1[..m], &mut t.2[..m]);
        m
    }

    fn run<T: WithDType>(&self, x: &[T]) -> Vec<T> {
        let (d, w) = (self.in_dim, self.width());
        let rows = x.len() / d;
        let mut out = vec![T::from_f64(0.0); rows * w];
        let items: Vec<_> = out
            .chunks_mut(ENCODE_ROWS * w.max(1))
            .zip(x.chunks(ENCODE_ROWS * d))
            .collect();
        for_each_init(
            items,
            || self.scratch(),
            |t, (out, x)| self.write_rows(x, out, t),
        );
        out
    }

    /// Encodes the rows `x: [rows, D]` into `out: [rows, E]`, [`ENCODE_ROWS`] at a time
    /// with the caller's scratch (the rows of [`CpuKernel::forward`], bit for bit).
    pub(crate) fn encode<T: WithDType>(&self, x: &[T], out: &mut [T], t: &mut Trig) {
        let (d, w) = (self.in_dim.max(1), self.width().max(1));
        for (x, out) in x
            .chunks(ENCODE_ROWS * d)
            .zip(out.chunks_mut(ENCODE_ROWS * w))
        {
            self.write_rows(x, out, t);
        }
    }

    /// Encodes at most [`ENCODE_ROWS`] rows `x: [rows, D]` into `out: [rows, E]`.
    fn write_rows<T: WithDType>(&self, x: &[T], out: &mut [T], t: &mut Trig) {
        let (d, l, w) = (self.in_dim, self.n_freqs, self.width());
        let head = if self.include_input { d } else { 0 };
        self.trig(x, t);
        for (r, (o, xr)) in out.chunks_mut(w).zip(x.chunks(d)).enumerate() {
            o[..head].copy_from_slice(&xr[..head]);
            for k in 0..l {
                let src = (r * l + k) * d;
                let base = head + 2 * d * k;
                for j in 0..d {
                    o[base + j] = T::from_f64(t.1[src + j]);
                    o[base + d + j] = T::from_f64(t.2[src + j]);
                }
            }
        }
    }

    fn grad<T: WithDType>(&self, x: &[T], g: &[T]) -> Vec<T> {
        let (d, l, w) = (self.in_dim, self.n_freqs, self.width());
        let head = if self.include_input { d } else { 0 };
        let mut gx = vec![T::from_f64(0.0); x.len()];
        let items: Vec<_> = gx
            .chunks_mut(ENCODE_ROWS * d)
            .zip(x.chunks(ENCODE_ROWS * d))
            .zip(g.chunks(ENCODE_ROWS * w.max(1)))
            .collect();
        for_each_init(
            items,
            || self.scratch(),
            |t, ((gx, x), g)| {
                self.trig(x, t);
                for (r, (gr, gi)) in gx.chunks_mut(d).zip(g.chunks(w)).enumerate() {
                    for j in 0..d {
                        let mut acc = if head > 0 { gi[j].to_f64() } else { 0.0 };
                        let mut rate = std::f64::consts::PI; // π2ᵏ
                        for k in 0..l {
                            let src = (r * l + k) * d + j;
                            let base = head + 2 * d * k;
                            acc += rate
                                * (gi[base + j].to_f64() * t.2[src]
                                    - gi[base + d + j].to_f64() * t.1[src]);
                            rate *= 2.0;
                        }
                        gr[j] = T::from_f64(acc);
                    }
                }
            },
        );
        gx
    }
}

impl CpuKernel<1> for FusedFrequency {
    const NAME: &'static str = "frequency encoding";

    fn forward<T: Real>(&self, [x]: [&[T]; 1]) -> candle_core::Result<(Vec<T>, Shape)> {
        let rows = x.len() / self.in_dim;
        Ok((self.run(x), Shape::from((rows, self.width()))))
    }

    fn backward<T: Real>(
        &self,
        [x]: [&[T]; 1],
        grad: &[T],
        _: [bool; 1],
    ) -> candle_core::Result<[Option<Vec<T>>; 1]> {
        Ok([Some(self.grad(x, grad))])
    }
}

cpu_op!(FusedFrequency, 1, "nf-frequency-encoding", cuda);

#[cfg(feature = "cuda")]
#[path = "cuda/frequency.rs"]
mod cuda;
