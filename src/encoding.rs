//! Input encodings: frequency positional encoding, Gaussian Fourier features, the
//! integrated positional encoding of mip-NeRF, and instant-NGP's multiresolution hash
//! grid ([`HashGrid`], learned tables); BARF's coarse-to-fine window over an encoding's
//! bands ([`CoarseToFine`]); and bilinear/trilinear sampling of feature planes and grids
//! ([`grid_sample`]) with scatter pooling of point features into cells ([`scatter`]), the
//! pieces of Convolutional Occupancy Networks.
//!
//! Every encoding maps `x: [N, D]` to `γ(x): [N, E]` and can push tangents forward
//! ([`Encoding::forward_jvp`]), which is how [`crate::nn::Mlp`] obtains spatial
//! gradients that stay differentiable w.r.t. its weights.
//!
//! Accuracy: the arguments `2ᵏπx` grow with the frequency, and a naive `sin(π·2ᵏ·x)` in
//! f32 rounds the product to an absolute error of about `2ᵏ·|x|·6e-8` (3e-4 at
//! `k = 9`, `|x| = π`). Here `2ᵏx` is formed exactly (a power of two) and reduced
//! exactly before the multiplication by π ([`crate::numerics::sin_cos_pi`]), and encodings
//! without π use the Cody–Waite [`crate::numerics::safe_sin_cos`], so f32 encodings match an
//! f64 reference to about 1e-6 at every frequency.
//!
//! ```
//! use candle_core::{Device, Tensor};
//! use neural_fields::encoding::{Encoding, FrequencyEncoding};
//!
//! let pe = FrequencyEncoding::new(3, 10)?; // NeRF's 63-dimensional point encoding
//! let x = Tensor::new(&[[0.1f32, -0.2, 0.3]], &Device::Cpu)?;
//! assert_eq!(pe.forward(&x)?.dims(), &[1, 63]);
//! # Ok::<(), neural_fields::Error>(())
//! ```

mod coarse_to_fine;
mod feature_grid;
mod hash;

pub use coarse_to_fine::CoarseToFine;
pub use feature_grid::{
    cell_index, grid_sample, scatter, GridSampleConfig, Pooling, ScatterConfig,
};
pub use hash::{hash_grid, HashGrid, HashGridConfig};

use crate::error::{check_float, check_same, check_scalar, check_shape, Dim, Error, Result};
use crate::numerics::{round_to_integer, safe_sin_cos, sin_cos_pi};
use crate::rng::SplitMix64;
use candle_core::{DType, Device, Tensor};

/// An encoding `γ: ℝᴰ → ℝᴱ` applied row-wise.
pub trait Encoding {
    /// Input dimension `D`.
    fn in_dim(&self) -> usize;

    /// Output dimension `E`.
    fn out_dim(&self) -> usize;

    /// `γ(x)`: `x: [N, D]` → `[N, E]`, in `x`'s dtype and device, differentiable w.r.t. `x`.
    ///
    /// # Errors
    /// `x` not `[N, D]` f32/f64.
    fn forward(&self, x: &Tensor) -> Result<Tensor>;

    /// `γ(x)` and the Jacobian-vector products `J_γ(x)·dxₖ` for `K` tangents
    /// `dx: [N, K, D]` → (`[N, E]`, `[N, K, E]`), both differentiable w.r.t. `x` and `dx`.
    ///
    /// # Errors
    /// Shapes other than `[N, D]` and `[N, K, D]`, or mismatched dtypes.
    fn forward_jvp(&self, x: &Tensor, dx: &Tensor) -> Result<(Tensor, Tensor)>;
}

fn check_input(x: &Tensor, d: usize) -> Result<usize> {
    check_float(x, "x")?;
    Ok(check_shape(x, "x", &[Dim::Any("N"), Dim::Is(d)])?[0])
}

/// Checks the identity encoding's input: f32/f64 `[N, D]` for any `D`; returns `(N, D)`.
fn check_identity_input(x: &Tensor) -> Result<(usize, usize)> {
    check_float(x, "x")?;
    let dims = check_shape(x, "x", &[Dim::Any("N"), Dim::Any("D")])?;
    Ok((dims[0], dims[1]))
}

fn check_tangents(x: &Tensor, dx: &Tensor, n: usize, d: usize) -> Result<usize> {
    check_same(dx, "dx", x, "x")?;
    let dims = check_shape(dx, "dx", &[Dim::Any("N"), Dim::Any("K"), Dim::Is(d)])?;
    if dims[0] != n {
        return Err(Error::invalid(
            "dx",
            format!("{n} rows (those of x)"),
            format!("{}", dims[0]),
        ));
    }
    Ok(dims[1])
}

/// NeRF's frequency positional encoding
/// `γ(x) = [x, sin(2⁰ωx), cos(2⁰ωx), …, sin(2ᴸ⁻¹ωx), cos(2ᴸ⁻¹ωx)]` with `ω = π` (or
/// `ω = 1`, as NeRF's code does, with `use_pi = false`), each term
/// applied to all `D` coordinates; the leading `x` is optional.
///
/// Output dimension `E = D·(1 + 2L)` with the input, `2DL` without. Column layout: the
/// input (if included), then for each frequency `k` the `D` sines followed by the `D`
/// cosines.
#[derive(Clone, Debug, PartialEq)]
pub struct FrequencyEncoding {
    in_dim: usize,
    n_freqs: usize,
    /// Whether the raw input leads the output (default `true`; `false` leaves it out).
    pub include_input: bool,
    /// Frequencies `2ᵏπ` (default `true`) or `2ᵏ` (`false`, NeRF's released code).
    pub use_pi: bool,
}

impl FrequencyEncoding {
    /// `L = n_freqs` frequencies `2ᵏπ`, `k < L`, with the input included.
    ///
    /// # Errors
    /// `in_dim == 0`, or `n_freqs > 60` (beyond, `2ᵏ` overflows the f32 exponent range
    /// of useful inputs).
    pub fn new(in_dim: usize, n_freqs: usize) -> Result<Self> {
        if in_dim == 0 {
            return Err(Error::invalid("in_dim", "at least 1", "0"));
        }
        if n_freqs > 60 {
            return Err(Error::invalid(
                "n_freqs",
                "at most 60",
                format!("{n_freqs}"),
            ));
        }
        Ok(Self {
            in_dim,
            n_freqs,
            include_input: true,
            use_pi: true,
        })
    }

    /// The number of frequencies `L`.
    pub(crate) fn n_freqs(&self) -> usize {
        self.n_freqs
    }

    /// The scaled arguments `2ᵏx` as `[N, L, D]` (exact: multiplication by powers of 2).
    fn scaled(&self, x: &Tensor) -> Result<Tensor> {
        let n = x.dim(0)?;
        let scales: Vec<f64> = (0..self.n_freqs).map(|k| (k as f64).exp2()).collect();
        let s = Tensor::from_vec(scales, (1, self.n_freqs, 1), x.device())?.to_dtype(x.dtype())?;
        Ok(x.unsqueeze(1)?
            .broadcast_mul(&s)?
            .reshape((n, self.n_freqs, self.in_dim))?)
    }

    /// `sin(ωy)`, `cos(ωy)` for the scaled arguments `y`, accurately.
    fn sin_cos(&self, y: &Tensor) -> Result<(Tensor, Tensor)> {
        if self.use_pi {
            sin_cos_pi(y)
        } else {
            safe_sin_cos(y)
        }
    }

    /// [`Encoding::forward`] from candle ops (any device, any float dtype; `use_pi = false`
    /// on the CPU too).
    fn forward_reference(&self, x: &Tensor) -> Result<Tensor> {
        check_input(x, self.in_dim)?;
        let (s, c) = self.sin_cos(&self.scaled(x)?)?;
        self.assemble(x, &s, &c)
    }

    fn assemble(&self, head: &Tensor, sin: &Tensor, cos: &Tensor) -> Result<Tensor> {
        // sin, cos: [..., L, D] → [..., L, 2D] → [..., 2LD]
        let rank = sin.rank();
        let body = Tensor::cat(&[sin, cos], rank - 1)?.flatten_from(rank - 2)?;
        if self.include_input {
            Ok(Tensor::cat(&[head, &body], rank - 2)?)
        } else {
            Ok(body)
        }
    }
}

impl Encoding for FrequencyEncoding {
    fn in_dim(&self) -> usize {
        self.in_dim
    }

    fn out_dim(&self) -> usize {
        self.in_dim * (2 * self.n_freqs + usize::from(self.include_input))
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        check_input(x, self.in_dim)?;
        if self.use_pi && x.device().is_cpu() && matches!(x.dtype(), DType::F32 | DType::F64) {
            return Ok(x.contiguous()?.apply_op1(FusedFrequency(self.clone()))?);
        }
        self.forward_reference(x)
    }

    fn forward_jvp(&self, x: &Tensor, dx: &Tensor) -> Result<(Tensor, Tensor)> {
        let n = check_input(x, self.in_dim)?;
        let k = check_tangents(x, dx, n, self.in_dim)?;
        let (s, c) = self.sin_cos(&self.scaled(x)?)?;
        // The value is `forward`'s (the fused op on the CPU), bit for bit.
        let value = Encoding::forward(self, x)?;
        // d sin(ω2ᵏx) = ω2ᵏ cos(ω2ᵏx) dx,  d cos(ω2ᵏx) = −ω2ᵏ sin(ω2ᵏx) dx
        let omega = if self.use_pi {
            std::f64::consts::PI
        } else {
            1.0
        };
        let rates: Vec<f64> = (0..self.n_freqs)
            .map(|j| omega * (j as f64).exp2())
            .collect();
        let rates =
            Tensor::from_vec(rates, (1, 1, self.n_freqs, 1), x.device())?.to_dtype(x.dtype())?;
        let dy = dx.unsqueeze(2)?.broadcast_mul(&rates)?; // [N, K, L, D]
        let ds = dy.broadcast_mul(&c.unsqueeze(1)?)?;
        let dc = dy.broadcast_mul(&s.unsqueeze(1)?)?.neg()?;
        let tangent = self.assemble(dx, &ds, &dc)?;
        // invariant: check_tangents proved dx is [n, k, D]; assemble joins dx's D columns
        // (when the input is included) with the 2·L·D sine/cosine tangent columns of
        // ds, dc: [n, k, L, D], so the last dimension is out_dim().
        debug_assert_eq!(tangent.dims(), &[n, k, self.out_dim()]);
        Ok((value, tangent))
    }
}

/// The frequency encoding with `2ᵏπ` as one CPU op: each output row written in one pass
/// (no intermediate `[N, L, D]` tensors) and the backward pass
/// `∂L/∂x_d = ḡ_{x_d} + Σ_k π2ᵏ (ḡ_{sin,k,d} cos(π2ᵏx_d) − ḡ_{cos,k,d} sin(π2ᵏx_d))`,
/// recomputing the sines and cosines. The argument is reduced exactly, as
/// [`crate::numerics::sin_cos_pi`] does, and the sine and cosine come from one branch-free
/// polynomial pass in f64 ([`sin_cos_pi_slices`]), which the compiler vectorises; f32 inputs
/// are widened (exactly) and the results rounded once, so they are at least as accurate as
/// the reference path's f32 `sin(π·r)`.
#[derive(Clone)]
struct FusedFrequency(FrequencyEncoding);

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
fn sin_cos_pi_slices(y: &[f64], s: &mut [f64], c: &mut [f64]) {
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
type Trig = (Vec<f64>, Vec<f64>, Vec<f64>);

impl FusedFrequency {
    fn width(&self) -> usize {
        Encoding::out_dim(&self.0)
    }

    fn scratch(&self) -> Trig {
        let m = ENCODE_ROWS * self.0.in_dim * self.0.n_freqs;
        (vec![0.0; m], vec![0.0; m], vec![0.0; m])
    }

    /// Sines and cosines of `π2ᵏx` for the rows `x`, laid out `[row][k][d]` in `t.1`, `t.2`.
    fn trig<T: candle_core::WithDType>(&self, x: &[T], t: &mut Trig) -> usize {
        let (d, l) = (self.0.in_dim, self.0.n_freqs);
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

    fn forward<T: candle_core::WithDType>(&self, x: &[T]) -> Vec<T> {
        let (d, w) = (self.0.in_dim, self.width());
        let rows = x.len() / d;
        let mut out = vec![T::from_f64(0.0); rows * w];
        let items: Vec<_> = out
            .chunks_mut(ENCODE_ROWS * w.max(1))
            .zip(x.chunks(ENCODE_ROWS * d))
            .collect();
        crate::kernels::for_each_init(
            items,
            || self.scratch(),
            |t, (out, x)| self.write_rows(x, out, t),
        );
        out
    }

    /// Encodes at most [`ENCODE_ROWS`] rows `x: [rows, D]` into `out: [rows, E]`.
    fn write_rows<T: candle_core::WithDType>(&self, x: &[T], out: &mut [T], t: &mut Trig) {
        let (d, l, w) = (self.0.in_dim, self.0.n_freqs, self.width());
        let head = if self.0.include_input { d } else { 0 };
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

    fn backward<T: candle_core::WithDType>(&self, x: &[T], g: &[T]) -> Vec<T> {
        let (d, l, w) = (self.0.in_dim, self.0.n_freqs, self.width());
        let head = if self.0.include_input { d } else { 0 };
        let mut gx = vec![T::from_f64(0.0); x.len()];
        let items: Vec<_> = gx
            .chunks_mut(ENCODE_ROWS * d)
            .zip(x.chunks(ENCODE_ROWS * d))
            .zip(g.chunks(ENCODE_ROWS * w.max(1)))
            .collect();
        crate::kernels::for_each_init(
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

impl candle_core::CustomOp1 for FusedFrequency {
    fn name(&self) -> &'static str {
        "nf-frequency-encoding"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> candle_core::Result<(candle_core::CpuStorage, candle_core::Shape)> {
        use candle_core::CpuStorage;
        let [(a, b)] = crate::kernels::contiguous([l], "frequency encoding")?;
        let rows = l.dims().first().copied().unwrap_or(0);
        let out = match s {
            CpuStorage::F32(v) => CpuStorage::F32(self.forward(&v[a..b])),
            CpuStorage::F64(v) => CpuStorage::F64(self.forward(&v[a..b])),
            _ => candle_core::bail!("frequency encoding: f32 or f64 input expected"),
        };
        Ok((out, candle_core::Shape::from((rows, self.width()))))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> candle_core::Result<Option<Tensor>> {
        let grad = grad.contiguous()?;
        let (xs, xl) = x.storage_and_layout();
        let (gs, gl) = grad.storage_and_layout();
        let op = "frequency encoding";
        let gx = match x.dtype() {
            DType::F32 => {
                let v = crate::kernels::cpu_slice::<f32>(&xs, xl, op, "input")?;
                let g = crate::kernels::cpu_slice::<f32>(&gs, gl, op, "gradient")?;
                Tensor::from_vec(self.backward(v, g), x.shape(), x.device())?
            }
            DType::F64 => {
                let v = crate::kernels::cpu_slice::<f64>(&xs, xl, op, "input")?;
                let g = crate::kernels::cpu_slice::<f64>(&gs, gl, op, "gradient")?;
                Tensor::from_vec(self.backward(v, g), x.shape(), x.device())?
            }
            other => candle_core::bail!("frequency encoding: unsupported dtype {other:?}"),
        };
        Ok(Some(gx))
    }
}

/// Gaussian random Fourier features (Tancik et al. 2020):
/// `γ(x) = [sin(2πBx), cos(2πBx)]` with `B: [F, D]`, `Bᵢⱼ ~ N(0, s²)`.
///
/// Output dimension `E = 2F` (sines then cosines). `B` is drawn once from a seed and is
/// not trained. Typical: `F = 256`, `s ∈ {1, 10, 100}`.
#[derive(Clone, Debug)]
pub struct FourierFeatures {
    b: Tensor,
}

impl FourierFeatures {
    /// Draws `B: [n_features, in_dim]` with standard deviation `scale` from `seed`.
    ///
    /// # Errors
    /// `in_dim` or `n_features` zero, `scale` not finite and positive.
    pub fn new(
        in_dim: usize,
        n_features: usize,
        scale: f64,
        seed: u64,
        device: &Device,
        dtype: DType,
    ) -> Result<Self> {
        if in_dim == 0 || n_features == 0 {
            return Err(Error::invalid(
                "in_dim, n_features",
                "both at least 1",
                format!("{in_dim}, {n_features}"),
            ));
        }
        check_scalar(scale, "scale", true)?;
        let b = SplitMix64::new(seed).normal_tensor(
            &[n_features, in_dim],
            0.0,
            scale,
            dtype,
            device,
        )?;
        Ok(Self { b })
    }

    /// Uses a given matrix `b: [F, D]`.
    ///
    /// # Errors
    /// `b` not a rank-2 f32/f64 tensor.
    pub fn from_matrix(b: Tensor) -> Result<Self> {
        check_float(&b, "b")?;
        check_shape(&b, "b", &[Dim::Any("F"), Dim::Any("D")])?;
        Ok(Self { b })
    }

    /// `2·Bx` as `[N, F]` (so that `sin(π·2Bx) = sin(2πBx)` can be reduced exactly).
    fn twice_projection(&self, x: &Tensor) -> Result<Tensor> {
        let bt = self.b.to_device(x.device())?.to_dtype(x.dtype())?.t()?;
        Ok(x.matmul(&bt)?.affine(2.0, 0.0)?)
    }
}

impl Encoding for FourierFeatures {
    fn in_dim(&self) -> usize {
        self.b.dims()[1]
    }

    fn out_dim(&self) -> usize {
        2 * self.b.dims()[0]
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        check_input(x, self.in_dim())?;
        let v = self.twice_projection(x)?;
        let (s, c) = sin_cos_pi(&v)?;
        Ok(Tensor::cat(&[s, c], 1)?)
    }

    fn forward_jvp(&self, x: &Tensor, dx: &Tensor) -> Result<(Tensor, Tensor)> {
        let n = check_input(x, self.in_dim())?;
        let k = check_tangents(x, dx, n, self.in_dim())?;
        let v = self.twice_projection(x)?;
        let (s, c) = sin_cos_pi(&v)?;
        let bt = self.b.to_device(x.device())?.to_dtype(x.dtype())?.t()?;
        let f = bt.dim(1)?;
        // d(2Bx) = 2B dx; d sin(π·2Bx) = 2π cos(2πBx) B dx.
        let dv = dx
            .reshape((n * k, self.in_dim()))?
            .matmul(&bt)?
            .reshape((n, k, f))?
            .affine(std::f64::consts::TAU, 0.0)?;
        let ds = dv.broadcast_mul(&c.unsqueeze(1)?)?;
        let dc = dv.broadcast_mul(&s.unsqueeze(1)?)?.neg()?;
        Ok((Tensor::cat(&[s, c], 1)?, Tensor::cat(&[ds, dc], 2)?))
    }
}

/// The encodings an [`crate::nn::Mlp`] can put in front of its first layer.
#[derive(Clone, Debug, Default)]
pub enum PointEncoding {
    /// No encoding: `γ(x) = x`.
    #[default]
    Identity,
    /// [`FrequencyEncoding`].
    Frequency(FrequencyEncoding),
    /// [`FourierFeatures`].
    Fourier(FourierFeatures),
    /// [`HashGrid`] (its table is a parameter of the model, built from the same
    /// `VarBuilder`'s map).
    HashGrid(HashGrid),
    /// A frequency encoding or hash grid under BARF's coarse-to-fine window
    /// ([`CoarseToFine`]).
    CoarseToFine(CoarseToFine),
}

impl PointEncoding {
    /// Output dimension for inputs of dimension `in_dim`.
    #[must_use]
    pub(crate) fn out_dim_for(&self, in_dim: usize) -> usize {
        match self {
            PointEncoding::Identity => in_dim,
            PointEncoding::Frequency(e) => e.out_dim(),
            PointEncoding::Fourier(e) => e.out_dim(),
            PointEncoding::HashGrid(e) => e.out_dim(),
            PointEncoding::CoarseToFine(e) => e.out_dim(),
        }
    }

    /// The input dimension the encoding requires (`None` for the identity, which takes
    /// any).
    #[must_use]
    pub(crate) fn in_dim(&self) -> Option<usize> {
        match self {
            PointEncoding::Identity => None,
            PointEncoding::Frequency(e) => Some(e.in_dim()),
            PointEncoding::Fourier(e) => Some(e.in_dim()),
            PointEncoding::HashGrid(e) => Some(e.in_dim()),
            PointEncoding::CoarseToFine(e) => Some(e.in_dim()),
        }
    }

    /// Whether the raw input forms the first `in_dim` output columns (needed by the
    /// geometric initialisation, which keeps only those columns at initialisation).
    pub(crate) fn leads_with_input(&self) -> bool {
        match self {
            PointEncoding::Identity => true,
            PointEncoding::Frequency(e) => e.include_input,
            PointEncoding::Fourier(_) | PointEncoding::HashGrid(_) => false,
            PointEncoding::CoarseToFine(e) => e.inner().leads_with_input(),
        }
    }

    /// [`Encoding::forward`] of the wrapped encoding (identity: `γ(x) = x`, returned as
    /// is): `x: [N, D]` → `[N, E]` in `x`'s dtype (f32 or f64) and device,
    /// differentiable w.r.t. `x`.
    ///
    /// # Errors
    /// As the wrapped encoding's; for the identity, `x` not an f32/f64 tensor of rank 2
    /// (any `D`; [`crate::nn::Mlp`] checks `D` against its configuration).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        match self {
            PointEncoding::Identity => {
                check_identity_input(x)?;
                Ok(x.clone())
            }
            PointEncoding::Frequency(e) => e.forward(x),
            PointEncoding::Fourier(e) => e.forward(x),
            PointEncoding::HashGrid(e) => e.forward(x),
            PointEncoding::CoarseToFine(e) => e.forward(x),
        }
    }

    /// [`Encoding::forward_jvp`] of the wrapped encoding (identity: `J_γ = I`, so
    /// `(x, dx)` as is): `x: [N, D]`, `dx: [N, K, D]` → (`[N, E]`, `[N, K, E]`), f32 or
    /// f64, differentiable w.r.t. `x` and `dx`.
    ///
    /// # Errors
    /// As the wrapped encoding's; for the identity, `x` not an f32/f64 rank-2 tensor,
    /// or `dx` not `[N, K, D]` with `x`'s `N`, `D`, dtype and device.
    pub fn forward_jvp(&self, x: &Tensor, dx: &Tensor) -> Result<(Tensor, Tensor)> {
        match self {
            PointEncoding::Identity => {
                let (n, d) = check_identity_input(x)?;
                check_tangents(x, dx, n, d)?;
                Ok((x.clone(), dx.clone()))
            }
            PointEncoding::Frequency(e) => e.forward_jvp(x, dx),
            PointEncoding::Fourier(e) => e.forward_jvp(x, dx),
            PointEncoding::HashGrid(e) => e.forward_jvp(x, dx),
            PointEncoding::CoarseToFine(e) => e.forward_jvp(x, dx),
        }
    }
}

/// An encoding that fused CPU ops evaluate inside their own tiles
/// ([`RowEncoder::new`]): the identity, or frequencies `2ᵏπ` (the fused encoding's
/// rows, bit for bit those of [`PointEncoding::forward`] on the CPU).
#[derive(Clone)]
#[cfg_attr(not(feature = "volume"), allow(dead_code))]
pub(crate) struct RowEncoder {
    frequency: Option<FusedFrequency>,
    in_dim: usize,
    trig: Trig,
}

#[cfg_attr(not(feature = "volume"), allow(dead_code))]
impl RowEncoder {
    /// The encoder of `enc` on `in_dim`-wide rows, or `None` when `enc` is neither the
    /// identity nor a frequency encoding with `2ᵏπ`.
    pub(crate) fn new(enc: &PointEncoding, in_dim: usize) -> Option<Self> {
        let frequency = match enc {
            PointEncoding::Identity => None,
            PointEncoding::Frequency(e) if e.use_pi && e.in_dim == in_dim => {
                Some(FusedFrequency(e.clone()))
            }
            _ => return None,
        };
        let trig = frequency
            .as_ref()
            .map_or((vec![], vec![], vec![]), FusedFrequency::scratch);
        Some(Self {
            frequency,
            in_dim,
            trig,
        })
    }

    /// Output columns per row.
    pub(crate) fn out_dim(&self) -> usize {
        self.frequency
            .as_ref()
            .map_or(self.in_dim, FusedFrequency::width)
    }

    /// Encodes the rows `x: [rows, in_dim]` into `out: [rows, out_dim]`.
    pub(crate) fn encode<T: candle_core::WithDType>(&mut self, x: &[T], out: &mut [T]) {
        let (d, w) = (self.in_dim.max(1), self.out_dim().max(1));
        match &self.frequency {
            None => out[..x.len()].copy_from_slice(x),
            Some(f) => {
                for (x, out) in x
                    .chunks(ENCODE_ROWS * d)
                    .zip(out.chunks_mut(ENCODE_ROWS * w))
                {
                    f.write_rows(x, out, &mut self.trig);
                }
            }
        }
    }
}

#[cfg_attr(not(feature = "volume"), allow(dead_code))]
impl crate::kernels::RowEncode for RowEncoder {
    fn out_dim(&self) -> usize {
        RowEncoder::out_dim(self)
    }

    fn encode<T: candle_core::WithDType>(&mut self, x: &[T], out: &mut [T]) {
        RowEncoder::encode(self, x, out);
    }
}

/// Integrated positional encoding (mip-NeRF) of Gaussians with means `μ: [N, D]` and
/// diagonal variances `σ²: [N, D]`:
/// `IPE = [sin(2ᵏμ)·e^{−4ᵏσ²/2}, cos(2ᵏμ)·e^{−4ᵏσ²/2}]` for `min_deg ≤ k < max_deg`,
/// the expectation of the frequency encoding (without π) under the Gaussian.
///
/// Output `[N, 2·D·(max_deg − min_deg)]`, laid out like [`FrequencyEncoding`] without the
/// input. High frequencies whose period is far below the Gaussian's width fade to 0
/// instead of aliasing. Differentiable w.r.t. `means` and `variances`.
///
/// f32 or f64 (the output takes `means`' dtype and device).
///
/// # Errors
/// [`Error::InvalidArgument`] naming `means` when it is not an f32/f64 `[N, D]` tensor,
/// `variances` when its shape, dtype or device differs from `means`', and
/// `min_deg, max_deg` unless `min_deg ≤ max_deg ≤ 60`. The values of `variances` are
/// data and not checked (negative or NaN variances give non-finite or growing outputs).
pub fn integrated_pe(
    means: &Tensor,
    variances: &Tensor,
    min_deg: usize,
    max_deg: usize,
) -> Result<Tensor> {
    check_float(means, "means")?;
    let dims = check_shape(means, "means", &[Dim::Any("N"), Dim::Any("D")])?;
    check_same(variances, "variances", means, "means")?;
    check_shape(
        variances,
        "variances",
        &[Dim::Is(dims[0]), Dim::Is(dims[1])],
    )?;
    if min_deg > max_deg || max_deg > 60 {
        return Err(Error::invalid(
            "min_deg, max_deg",
            "min_deg ≤ max_deg ≤ 60",
            format!("{min_deg}, {max_deg}"),
        ));
    }
    let l = max_deg - min_deg;
    let (n, d) = (dims[0], dims[1]);
    let scales: Vec<f64> = (min_deg..max_deg).map(|k| (k as f64).exp2()).collect();
    let sq: Vec<f64> = scales.iter().map(|s| s * s).collect();
    let s = Tensor::from_vec(scales, (1, l, 1), means.device())?.to_dtype(means.dtype())?;
    let s2 = Tensor::from_vec(sq, (1, l, 1), means.device())?.to_dtype(means.dtype())?;
    let mu = means.unsqueeze(1)?.broadcast_mul(&s)?; // [N, L, D]
    let var = variances.unsqueeze(1)?.broadcast_mul(&s2)?;
    let damp = var.affine(-0.5, 0.0)?.exp()?;
    let (sin, cos) = safe_sin_cos(&mu)?;
    let (sin, cos) = ((sin * &damp)?, (cos * &damp)?);
    Ok(Tensor::cat(&[sin, cos], 2)?.reshape((n, 2 * l * d))?)
}
