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
use crate::kernels::{FusedFrequency, FusedIntegrated, Trig};
use crate::numerics::{safe_sin_cos, sin_cos_pi};
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

    /// The fused CPU op of this encoding with `2ᵏπ` (the kernel layer's
    /// `FusedFrequency`: each output row written in one pass, the argument reduced
    /// exactly as [`sin_cos_pi`] does).
    fn kernel(&self) -> FusedFrequency {
        FusedFrequency {
            in_dim: self.in_dim,
            n_freqs: self.n_freqs,
            include_input: self.include_input,
        }
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
        if self.use_pi && crate::kernels::fused_for(x) {
            return Ok(x.contiguous()?.apply_op1(self.kernel())?);
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
    /// mip-NeRF's integrated positional encoding ([`integrated_pe`]) of Gaussians in
    /// `dim` dimensions, each input row the mean and the diagonal variance side by side,
    /// `x = [μ, σ²]: [N, 2·dim]` (from [`crate::volume::conical_frustums`]); output
    /// `[N, 2·dim·(max_deg − min_deg)]`. Zero variances give the frequency encoding
    /// `sin(2ᵏμ), cos(2ᵏμ)` (without π) of the means. `min_deg ≤ max_deg ≤ 60`, checked
    /// where it encodes.
    Integrated {
        /// The Gaussians' dimension (3 for points in space).
        dim: usize,
        /// The lowest octave `k` (mip-NeRF: 0).
        min_deg: usize,
        /// One past the highest octave (mip-NeRF: 16 for positions).
        max_deg: usize,
    },
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
            PointEncoding::Integrated {
                dim,
                min_deg,
                max_deg,
            } => 2 * dim * max_deg.saturating_sub(*min_deg),
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
            PointEncoding::Integrated { dim, .. } => Some(2 * dim),
        }
    }

    /// Whether the raw input forms the first `in_dim` output columns (needed by the
    /// geometric initialisation, which keeps only those columns at initialisation).
    pub(crate) fn leads_with_input(&self) -> bool {
        match self {
            PointEncoding::Identity => true,
            PointEncoding::Frequency(e) => e.include_input,
            PointEncoding::Fourier(_)
            | PointEncoding::HashGrid(_)
            | PointEncoding::Integrated { .. } => false,
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
            PointEncoding::Integrated {
                dim,
                min_deg,
                max_deg,
            } => {
                check_input(x, 2 * dim)?;
                integrated_rows(x, *dim, *min_deg, *max_deg)
            }
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
            PointEncoding::Integrated {
                dim,
                min_deg,
                max_deg,
            } => {
                let n = check_input(x, 2 * dim)?;
                check_tangents(x, dx, n, 2 * dim)?;
                integrated_pe_jvp(x, dx, *dim, *min_deg, *max_deg)
            }
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
            PointEncoding::Frequency(e) if e.use_pi && e.in_dim == in_dim => Some(e.kernel()),
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
        match &self.frequency {
            None => out[..x.len()].copy_from_slice(x),
            Some(f) => f.encode(x, out, &mut self.trig),
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

    fn frequency_spec(&self) -> (usize, bool) {
        self.frequency
            .as_ref()
            .map_or((0, true), |f| (f.n_freqs, f.include_input))
    }
}

/// [`integrated_pe`] of `x = [μ, σ²]: [N, 2D]` and its JVPs along `dx: [N, K, 2D]`:
/// with `a = 2ᵏμ`, `b = 4ᵏσ²/2`, `∂(sin a·e⁻ᵇ) = (cos a·2ᵏdμ − sin a·4ᵏdσ²/2)·e⁻ᵇ` and
/// `∂(cos a·e⁻ᵇ) = (−sin a·2ᵏdμ − cos a·4ᵏdσ²/2)·e⁻ᵇ`.
fn integrated_pe_jvp(
    x: &Tensor,
    dx: &Tensor,
    d: usize,
    min_deg: usize,
    max_deg: usize,
) -> Result<(Tensor, Tensor)> {
    let out = integrated_rows(x, d, min_deg, max_deg)?;
    let (n, k) = (dx.dim(0)?, dx.dim(1)?);
    let l = max_deg - min_deg;
    let powers = |p: f64| -> Result<Tensor> {
        let v: Vec<f64> = (min_deg..max_deg).map(|j| (p * j as f64).exp2()).collect();
        Ok(Tensor::from_vec(v, (1, 1, l, 1), x.device())?.to_dtype(x.dtype())?)
    };
    let (s, s2) = (powers(1.0)?, powers(2.0)?);
    // [N, 1, L, D] arguments and damping; [N, K, L, D] tangents.
    let a = x
        .narrow(1, 0, d)?
        .reshape((n, 1, 1, d))?
        .broadcast_mul(&s)?;
    let damp = x
        .narrow(1, d, d)?
        .reshape((n, 1, 1, d))?
        .broadcast_mul(&s2)?
        .affine(-0.5, 0.0)?
        .exp()?;
    let (sin, cos) = safe_sin_cos(&a)?;
    let (sin, cos) = ((sin * &damp)?, (cos * &damp)?);
    let dmu = dx.narrow(2, 0, d)?.unsqueeze(2)?.broadcast_mul(&s)?;
    let dvar = dx
        .narrow(2, d, d)?
        .unsqueeze(2)?
        .broadcast_mul(&s2)?
        .affine(0.5, 0.0)?;
    let ds = (dmu.broadcast_mul(&cos)? - dvar.broadcast_mul(&sin)?)?;
    let dc = (dmu.broadcast_mul(&sin)?.neg()? - dvar.broadcast_mul(&cos)?)?;
    let jvp = Tensor::cat(&[ds, dc], 3)?.reshape((n, k, 2 * l * d))?;
    Ok((out, jvp))
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
/// f32 or f64 (the output takes `means`' dtype and device). On the CPU it runs as one
/// fused op (the kernel layer's `FusedIntegrated`: sines from a vectorised polynomial in
/// f64, forward and backward without intermediate tensors; 1e-6 relative to the candle-op
/// reference path in f32, which runs on any other device, and within `|2ᵏμ|·2⁻⁵⁰` in f64).
///
/// # Errors
/// [`Error::InvalidArgument`] naming `means` when it is not an f32/f64 `[N, D]` tensor,
/// `variances` when its shape, dtype or device differs from `means`', and
/// `min_deg, max_deg` unless `min_deg ≤ max_deg ≤ 60`; `means` when the output's
/// `N·2D·(max_deg − min_deg)` values pass the allocation limit of 2³³ bytes (checked
/// before anything is allocated). The values of `variances` are
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
    integrated_rows(
        &Tensor::cat(&[means, variances], 1)?,
        dims[1],
        min_deg,
        max_deg,
    )
}

/// [`integrated_pe`] of the rows `x = [μ, σ²]: [N, 2D]` (checked by the caller): the
/// fused CPU op (the kernel layer's `FusedIntegrated`) on the CPU, else
/// [`integrated_pe_reference`].
fn integrated_rows(x: &Tensor, d: usize, min_deg: usize, max_deg: usize) -> Result<Tensor> {
    if min_deg > max_deg || max_deg > 60 {
        return Err(Error::invalid(
            "min_deg, max_deg",
            "min_deg ≤ max_deg ≤ 60",
            format!("{min_deg}, {max_deg}"),
        ));
    }
    // The output, [N, 2·D·L], up to 60 times the input's size.
    let rows = x.dims().first().copied().unwrap_or(0);
    crate::limits::check_bytes(
        "means",
        &[rows, 2 * d, max_deg - min_deg],
        x.dtype().size_in_bytes(),
    )?;
    if crate::kernels::fused_for(x) {
        let op = FusedIntegrated {
            dim: d,
            min_deg,
            max_deg,
        };
        return Ok(x.contiguous()?.apply_op1(op)?);
    }
    integrated_pe_reference(&x.narrow(1, 0, d)?, &x.narrow(1, d, d)?, min_deg, max_deg)
}

/// [`integrated_pe`] from candle ops (any device; degrees checked by the caller).
fn integrated_pe_reference(
    means: &Tensor,
    variances: &Tensor,
    min_deg: usize,
    max_deg: usize,
) -> Result<Tensor> {
    let l = max_deg - min_deg;
    let (n, d) = means.dims2()?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    /// The fused integrated encoding against its candle-op reference, values and both
    /// gradients, in f32 and f64, over zero, tiny and wide variances and means to 1e3.
    #[test]
    fn fused_integrated_encoding_matches_the_reference_path() -> Result<()> {
        let mut rng = SplitMix64::new(9);
        let n = 300;
        let mu: Vec<f64> = (0..3 * n)
            .map(|i| (rng.uniform() - 0.5) * [2.0, 20.0, 2e3][i % 3])
            .collect();
        let var: Vec<f64> = (0..3 * n)
            .map(|i| [0.0, 1e-6 * rng.uniform(), 1e-3 * rng.uniform(), 5.0][i % 4])
            .collect();
        for dtype in [DType::F32, DType::F64] {
            let m = Var::from_tensor(
                &Tensor::from_vec(mu.clone(), (n, 3), &Device::Cpu)?.to_dtype(dtype)?,
            )?;
            let v = Var::from_tensor(
                &Tensor::from_vec(var.clone(), (n, 3), &Device::Cpu)?.to_dtype(dtype)?,
            )?;
            let w = Tensor::from_vec(
                (0..n * 3 * 2 * 9)
                    .map(|i| (0.1 * i as f64).sin())
                    .collect::<Vec<f64>>(),
                (n, 54),
                &Device::Cpu,
            )?
            .to_dtype(dtype)?;
            let mut parts = Vec::new();
            for fused in [true, false] {
                let y = if fused {
                    integrated_pe(m.as_tensor(), v.as_tensor(), 1, 10)?
                } else {
                    integrated_pe_reference(m.as_tensor(), v.as_tensor(), 1, 10)?
                };
                let g = (&y * &w)?.sum_all()?.backward()?;
                let host = |t: &Tensor| -> Result<Vec<f64>> {
                    Ok(t.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?)
                };
                let missing = |arg| Error::invalid(arg, "a gradient", "none");
                let gm = g.get(m.as_tensor()).ok_or_else(|| missing("means"))?;
                let gv = g.get(v.as_tensor()).ok_or_else(|| missing("variances"))?;
                parts.push([host(&y)?, host(gm)?, host(gv)?]);
            }
            // Arguments up to 2⁹·1e3: the reference's f32 sin is accurate to an ulp of
            // the argument (≈ 0.03 at 5e5), so f32 compares the low-frequency columns
            // tightly and the rest loosely.
            let tol = if dtype == DType::F32 { 2e-2 } else { 1e-9 };
            for (what, (a, b)) in ["value", "d/dmeans", "d/dvariances"]
                .iter()
                .zip(parts[0].iter().zip(&parts[1]))
            {
                let scale = b.iter().fold(1.0f64, |s, x| s.max(x.abs()));
                for (i, (x, y)) in a.iter().zip(b).enumerate() {
                    assert!(
                        (x - y).abs() <= tol * scale,
                        "{dtype:?} {what}[{i}]: fused {x} vs reference {y}"
                    );
                }
            }
        }
        Ok(())
    }

    #[test]
    fn fused_integrated_encoding_keeps_empty_batches_and_no_octaves() -> Result<()> {
        let z = Tensor::zeros((0, 3), DType::F32, &Device::Cpu)?;
        assert_eq!(integrated_pe(&z, &z, 0, 4)?.dims(), &[0, 24]);
        let x = Tensor::ones((2, 3), DType::F64, &Device::Cpu)?;
        assert_eq!(integrated_pe(&x, &x, 3, 3)?.dims(), &[2, 0]);
        Ok(())
    }
}
