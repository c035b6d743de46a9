//! mip-NeRF's integrated positional encoding as one CPU op (`FusedIntegrated`, what
//! [`crate::encoding::integrated_pe`] and `PointEncoding::Integrated` run on the CPU).

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::frequency::sin_cos_pi_slices;
use super::parallel::for_each_init;
use candle_core::{Shape, WithDType};

/// The integrated positional encoding of rows `[μ, σ²]: [rows, 2D]` as one CPU op:
/// `[sin(2ᵏμ)·e^{−4ᵏσ²/2}, cos(2ᵏμ)·e^{−4ᵏσ²/2}]` for `min_deg ≤ k < max_deg`, each output
/// row `[rows, 2DL]` written in one pass (per octave the `D` damped sines, then the `D`
/// damped cosines), and the backward pass
/// `∂L/∂μ_d = Σ_k 2ᵏ e_k (ḡ_{sin} cos − ḡ_{cos} sin)`,
/// `∂L/∂σ²_d = −Σ_k (4ᵏ/2) e_k (ḡ_{sin} sin + ḡ_{cos} cos)`, recomputing the sines.
///
/// All in f64: the sine and cosine of `2ᵏμ` come from the vectorised `sin(πy)` of the
/// frequency kernel at `y = 2ᵏμ/π` (one rounding of the argument, an absolute error of
/// about `|2ᵏμ|·2⁻⁵²`: the conditioning of `sin(2ᵏμ)` itself), the damping from `exp`.
#[derive(Clone)]
pub(crate) struct FusedIntegrated {
    /// The Gaussians' dimension `D`.
    pub(crate) dim: usize,
    /// The lowest octave.
    pub(crate) min_deg: usize,
    /// One past the highest octave.
    pub(crate) max_deg: usize,
}

/// Rows per work item (the f64 scratch stays in L2).
const ROWS: usize = 256;

/// Per-worker scratch: arguments, sines, cosines, dampings, each `[row][k][d]`.
type Scratch = [Vec<f64>; 4];

impl FusedIntegrated {
    fn octaves(&self) -> usize {
        self.max_deg - self.min_deg
    }

    /// Output columns `2DL`.
    fn width(&self) -> usize {
        2 * self.dim * self.octaves()
    }

    /// The octaves' frequencies `2ᵏ`, `min_deg ≤ k < max_deg`.
    fn scales(&self) -> Vec<f64> {
        (self.min_deg..self.max_deg)
            .map(|k| (k as f64).exp2())
            .collect()
    }

    fn scratch(&self) -> Scratch {
        let m = ROWS * self.dim * self.octaves();
        std::array::from_fn(|_| vec![0.0; m])
    }

    /// Sines, cosines and dampings of the rows `x: [rows, 2D]` into `t[1..4]`, laid out
    /// `[row][k][d]`; returns their count.
    fn trig<T: WithDType>(&self, x: &[T], scales: &[f64], t: &mut Scratch) -> usize {
        let (d, l) = (self.dim, self.octaves());
        let rows = x.len() / (2 * d).max(1);
        let m = rows * l * d;
        let [args, sin, cos, damp] = t;
        for (r, row) in x.chunks(2 * d).enumerate() {
            for (k, &scale) in scales.iter().enumerate() {
                let at = (r * l + k) * d;
                for j in 0..d {
                    args[at + j] = row[j].to_f64() * scale * std::f64::consts::FRAC_1_PI;
                    damp[at + j] = (-0.5 * scale * scale * row[d + j].to_f64()).exp();
                }
            }
        }
        sin_cos_pi_slices(&args[..m], &mut sin[..m], &mut cos[..m]);
        m
    }

    fn run<T: WithDType>(&self, x: &[T]) -> Vec<T> {
        let (d2, w) = ((2 * self.dim).max(1), self.width());
        let rows = x.len() / d2;
        let mut out = vec![T::from_f64(0.0); rows * w];
        if w == 0 {
            return out;
        }
        let scales = self.scales();
        let items: Vec<_> = out.chunks_mut(ROWS * w).zip(x.chunks(ROWS * d2)).collect();
        for_each_init(
            items,
            || self.scratch(),
            |t, (out, x)| {
                let (d, l) = (self.dim, self.octaves());
                self.trig(x, &scales, t);
                for (r, o) in out.chunks_mut(w).enumerate() {
                    for k in 0..l {
                        let src = (r * l + k) * d;
                        for j in 0..d {
                            let e = t[3][src + j];
                            o[2 * d * k + j] = T::from_f64(t[1][src + j] * e);
                            o[2 * d * k + d + j] = T::from_f64(t[2][src + j] * e);
                        }
                    }
                }
            },
        );
        out
    }

    fn grad<T: WithDType>(&self, x: &[T], g: &[T]) -> Vec<T> {
        let (d, l, w) = (self.dim, self.octaves(), self.width());
        let d2 = (2 * d).max(1);
        let mut gx = vec![T::from_f64(0.0); x.len()];
        if w == 0 {
            return gx;
        }
        let scales = self.scales();
        let items: Vec<_> = gx
            .chunks_mut(ROWS * d2)
            .zip(x.chunks(ROWS * d2))
            .zip(g.chunks(ROWS * w))
            .collect();
        for_each_init(
            items,
            || self.scratch(),
            |t, ((gx, x), g)| {
                self.trig(x, &scales, t);
                for (r, (gr, gi)) in gx.chunks_mut(2 * d).zip(g.chunks(w)).enumerate() {
                    for j in 0..d {
                        let (mut gm, mut gv) = (0.0, 0.0);
                        for (k, &scale) in scales.iter().enumerate() {
                            let src = (r * l + k) * d + j;
                            let (s, c, e) = (t[1][src], t[2][src], t[3][src]);
                            let (gs, gc) =
                                (gi[2 * d * k + j].to_f64(), gi[2 * d * k + d + j].to_f64());
                            gm += scale * e * (gs * c - gc * s);
                            gv -= 0.5 * scale * scale * e * (gs * s + gc * c);
                        }
                        gr[j] = T::from_f64(gm);
                        gr[d + j] = T::from_f64(gv);
                    }
                }
            },
        );
        gx
    }
}

impl CpuKernel<1> for FusedIntegrated {
    const NAME: &'static str = "integrated positional encoding";

    fn forward<T: Real>(&self, [x]: [&[T]; 1]) -> candle_core::Result<(Vec<T>, Shape)> {
        let rows = x.len() / (2 * self.dim).max(1);
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

cpu_op!(FusedIntegrated, 1, "nf-integrated-encoding", cuda);

#[cfg(feature = "cuda")]
#[path = "cuda/integrated.rs"]
mod cuda;
