//! Volume compositing: one entry point per operation, for both sample layouts.
//!
//! Notation (per ray, samples i = 0..S): σᵢ ≥ 0 density, δᵢ = (endsᵢ − startsᵢ)·‖d‖ ≥ 0
//! interval length, tᵢ = (startsᵢ + endsᵢ)/2 sample depth, xᵢ = σᵢδᵢ optical thickness,
//! αᵢ = 1 − e^{−xᵢ}, Tᵢ = exp(−Σ_{j<i} xⱼ) the transmittance *before* sample i (T₀ = 1),
//! wᵢ = Tᵢαᵢ.
//!
//! | operation | function |
//! |---|---|
//! | colour, opacity, expected depth | [`composite`] |
//! | per-sample weights, transmittance, alphas | [`render_weights`] |
//! | Σ wᵢ·valuesᵢ along rays | [`accumulate`] |
//! | early termination (T ≥ ε) | [`visible_mask`] |
//!
//! Each takes the samples as [`Intervals`] in either [`Layout`] and, optionally, the
//! [`Rays`] whose direction norms scale δ. On the CPU, [`composite`] runs the fused
//! kernel (one O(S) pass per ray, analytic O(S) backward); elsewhere, or with
//! [`CompositeConfig::force_reference`], the reference path made of candle ops. The two
//! agree to rounding (tested).
//!
//! Numerics:
//! - αᵢ = −expm1(−xᵢ) is evaluated stably (α = x to rounding at x = 1e-30, where
//!   `1 − exp(−x)` is exactly 0 in f32).
//! - Tᵢ comes from one exclusive sum of xⱼ followed by one `exp`: no cumulative product,
//!   no division by α or T.
//! - xᵢ is clamped to [`X_MAX`](super::X_MAX) before the sum: e^{−X_MAX} is exactly 0 in f32 and f64, so
//!   the clamp changes no value and no gradient, but it keeps σδ overflowing to +∞ (e.g.
//!   σ = 1e30, δ = 1e10 in f32) from producing ∞·0 = NaN inside the sum.
//! - The opaque last interval ([`CompositeConfig::opaque_last`], as in multinerf) sets
//!   α = 1 for the last sample of each ray by selection; it never multiplies by a huge δ.
//!
//! Validation: σ must be finite and ≥ 0 (NaN, negative and **+∞ are rejected** with an
//! error naming `sigmas`: activations such as trunc-exp ([`crate::numerics::trunc_exp`]) never
//! produce ∞, so an infinite density is an upstream bug; a huge finite density such as
//! 1e30 is fine and acts as an opaque wall). Every δ must be finite and ≥ 0 (an error
//! names `intervals`).
//!
//! Passing loose tensors where intervals belong does not compile:
//!
//! ```compile_fail
//! use candle_core::{DType, Device, Tensor};
//! use neural_fields::volume::{composite, CompositeConfig};
//! let z = Tensor::zeros((2, 4), DType::F32, &Device::Cpu)?;
//! let colors = Tensor::zeros((2, 4, 3), DType::F32, &Device::Cpu)?;
//! // The 0.1 signature `composite(sigmas, colors, deltas, t_mids, opts)`:
//! let _ = composite(&z, &colors, &z, &z, &CompositeConfig::default())?;
//! # Ok::<(), neural_fields::Error>(())
//! ```

use super::fused::{self, FusedGeometry, KernelBuild};
use super::layout::{
    check_all_finite, check_nonneg_finite, check_samples, host_f64, Intervals, Layout, Weights,
};
use super::reference;
use crate::camera::Rays;
use crate::error::{check_float, check_same, check_scalar, check_shape, Dim, Result};
use candle_core::Tensor;

/// The default transmittance threshold ε of early termination ([`visible_mask`]): the
/// value of Instant-NGP and nerfacc. Samples behind `T < ε` carry less than ε of the
/// ray's weight in total.
pub const DEFAULT_TERMINATION_EPS: f64 = 1e-4;

/// Configuration of [`composite`] and [`render_weights`].
#[derive(Clone, Debug, Default)]
pub struct CompositeConfig {
    /// Treat the last interval of every ray as opaque: α = 1 there, so Σw = 1 − T_end
    /// becomes exactly 1 (unless T already underflowed). The last sample's σ and δ then
    /// receive zero gradient. This replaces NeRF's "last δ = 1e10" (which overflows and
    /// multiplies 0 by ∞) by a selection, as multinerf does.
    pub opaque_last: bool,
    /// Background colour c_bg, `[C]` or `[R, C]`; `None` means black (zero). The
    /// background enters as C = Σwᵢcᵢ + (1 − Σwᵢ)·c_bg and is differentiable.
    pub background: Option<Tensor>,
    /// Run the reference path (candle ops) even on the CPU, where [`composite`] would
    /// run the fused kernel: for second-order derivatives (the fused backward is first
    /// order only) and for comparing the two. Default `false`.
    pub force_reference: bool,
}

/// Per-ray compositing results.
#[derive(Clone, Debug)]
#[non_exhaustive]
pub struct Composite {
    /// `[R, C]`: C = Σwᵢcᵢ + (1 − Σwᵢ)·c_bg.
    pub color: Tensor,
    /// `[R]`: Σwᵢ = 1 − T_end (exactly 1 − exp(−Σxᵢ) without `opaque_last`).
    pub opacity: Tensor,
    /// `[R]`: the unnormalised expected depth Σwᵢtᵢ (tᵢ the interval midpoints, in ray
    /// parameter units); it treats the background as depth 0. See
    /// [`Composite::normalized_depth`] for Σwᵢtᵢ / Σwᵢ.
    pub depth: Tensor,
}

impl Composite {
    /// Normalised expected depth Σwᵢtᵢ / max(Σwᵢ, eps): the expected depth conditioned
    /// on the ray terminating inside the samples. `[R]`, the dtype of the composite
    /// (f32 or f64), differentiable through `depth` and `opacity`. Rays with opacity
    /// below `eps` get Σwᵢtᵢ / eps (close to 0).
    ///
    /// # Errors
    /// `eps` when not finite and > 0.
    pub fn normalized_depth(&self, eps: f64) -> Result<Tensor> {
        check_scalar(eps, "eps", true)?;
        Ok((&self.depth / self.opacity.maximum(eps)?)?)
    }
}

/// A compositing background checked against `like: [R, C]` (dtype, device, channels):
/// `[1, C]` for one colour shared by every ray, `[R, C]` for one per ray. Errors name the
/// background `name` (and `like_name` for a dtype or device unlike `like`'s).
pub(crate) fn background_rows(
    bg: &Tensor,
    name: &'static str,
    like: &Tensor,
    like_name: &'static str,
) -> Result<Tensor> {
    let (r, c) = like.dims2()?;
    check_same(bg, name, like, like_name)?;
    Ok(match bg.rank() {
        1 => {
            check_shape(bg, name, &[Dim::Is(c)])?;
            bg.unsqueeze(0)?
        }
        _ => {
            check_shape(bg, name, &[Dim::Is(r), Dim::Is(c)])?;
            bg.clone()
        }
    })
}

/// Adds the background term and packages the results.
fn finish(
    acc_color: Tensor,
    opacity: Tensor,
    depth: Tensor,
    config: &CompositeConfig,
) -> Result<Composite> {
    let color = match &config.background {
        None => acc_color,
        Some(bg) => {
            let bg = background_rows(bg, "background", &acc_color, "colors")?;
            let rest = opacity.neg()?.affine(1.0, 1.0)?.unsqueeze(1)?;
            (acc_color + rest.broadcast_mul(&bg)?)?
        }
    };
    Ok(Composite {
        color,
        opacity,
        depth,
    })
}

/// δ = span·‖d‖ of the samples as a tensor, checked finite and ≥ 0 (the reference path,
/// and the fused path when the intervals or the rays carry a graph).
fn checked_deltas(intervals: &Intervals, span: Tensor, norms: Option<&Tensor>) -> Result<Tensor> {
    let deltas = intervals.deltas_of(span, norms)?;
    check_nonneg_finite(&deltas, "intervals")?;
    Ok(deltas)
}

/// Composites the samples of a batch of rays into colour, opacity and expected depth.
///
/// Math: wᵢ as in [`render_weights`]; colour = Σwᵢcᵢ + (1 − Σwᵢ)·c_bg, opacity = Σwᵢ,
/// depth = Σwᵢtᵢ with tᵢ = (startsᵢ + endsᵢ)/2 and δᵢ = (endsᵢ − startsᵢ)·‖d_r‖ (‖d_r‖ = 1
/// when `rays` is `None`).
///
/// Shapes, batched layout: `sigmas: [R, S]`, `colors: [R, S, C]`, intervals `[R, S]`;
/// packed: `sigmas: [M]`, `colors: [M, C]`, intervals `[M]` (rays without samples get
/// opacity 0, depth 0 and the background colour). Returns [`Composite`] with
/// `color: [R, C]`, `opacity: [R]`, `depth: [R]`. f32 or f64, any device: the fused CPU
/// kernel on the CPU, the reference path elsewhere or with `config.force_reference`.
///
/// Differentiable with respect to `sigmas`, `colors`, the intervals, the rays'
/// directions and the background (first order on the fused path; the reference path
/// to any order).
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use neural_fields::volume::{composite, stratified, CompositeConfig, Jitter};
///
/// let dev = Device::Cpu;
/// let (near, far) = (Tensor::new(&[2.0f32; 4], &dev)?, Tensor::new(&[6.0f32; 4], &dev)?);
/// let intervals = stratified(&near, &far, 64, Jitter::None, 0)?;       // [R = 4, S = 64]
/// let sigmas = Tensor::full(10.0f32, (4, 64), &dev)?;                 // an opaque medium
/// let colors = Tensor::full(0.5f32, (4, 64, 3), &dev)?;
/// let out = composite(&sigmas, &colors, &intervals, None, &CompositeConfig::default())?;
/// assert_eq!(out.color.dims(), &[4, 3]);
/// let opacity = out.opacity.to_vec1::<f32>()?;
/// assert!(opacity.iter().all(|&o| (o - 1.0).abs() < 1e-6));
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Named after the offending argument: `sigmas` (shape, dtype, NaN, negative or
/// infinite values), `colors` (shape, dtype, device, NaN or infinite values),
/// `intervals` (dtype, device,
/// layout, a non-finite or inverted interval), `rays` (count, dtype, device), a
/// `background` not `[C]` or `[R, C]`.
pub fn composite(
    sigmas: &Tensor,
    colors: &Tensor,
    intervals: &Intervals,
    rays: Option<&Rays>,
    config: &CompositeConfig,
) -> Result<Composite> {
    check_samples(sigmas, Some((colors, "colors")), intervals)?;
    // A NaN colour would composite to a NaN pixel and NaN density gradients.
    check_all_finite(colors, "colors")?;
    let (color, opacity, depth) =
        composite_with(sigmas, colors, intervals, rays, config, KernelBuild::Avx512)?;
    finish(color, opacity, depth, config)
}

/// [`composite`] without the checks and the background, with the best kernel build the
/// fused path may use (tests pass each build).
pub(crate) fn composite_with(
    sigmas: &Tensor,
    colors: &Tensor,
    intervals: &Intervals,
    rays: Option<&Rays>,
    config: &CompositeConfig,
    build: KernelBuild,
) -> Result<(Tensor, Tensor, Tensor)> {
    let layout = &intervals.layout;
    if intervals.n_rays() == 0 {
        // No rays, hence no samples: empty results, still on the inputs' graph. (Both
        // paths split a `[0, K]` result with `narrow`, whose views would start past their
        // empty storage and panic when read.)
        return Ok(match layout {
            Layout::Batched => (colors.sum(1)?, sigmas.sum(1)?, sigmas.sum(1)?),
            Layout::Packed(_) => (colors.clone(), sigmas.clone(), sigmas.clone()),
        });
    }
    let norms = intervals.direction_norms(rays)?;
    let constant = !intervals.starts.track_op()
        && !intervals.ends.track_op()
        && norms.as_ref().is_none_or(|n| !n.track_op());
    let reference = !crate::kernels::fused_on(sigmas.device()) || config.force_reference;
    if constant && !reference {
        let geometry = FusedGeometry::Intervals {
            starts: &intervals.starts,
            ends: &intervals.ends,
            norms: norms.as_ref(),
        };
        return fused::composite(sigmas, colors, geometry, layout, config.opaque_last, build);
    }
    // δ and t as tensors, formed from one span.
    let span = intervals.span()?;
    let t_mids = intervals.midpoints_of(&span)?;
    let deltas = checked_deltas(intervals, span, norms.as_ref())?;
    if reference {
        check_nonneg_finite(sigmas, "sigmas")?;
        return reference::composite(sigmas, colors, &deltas, &t_mids, layout, config.opaque_last);
    }
    let geometry = FusedGeometry::Tensors {
        deltas: &deltas,
        t_mids: &t_mids,
    };
    fused::composite(sigmas, colors, geometry, layout, config.opaque_last, build)
}

/// Per-sample compositing weights, transmittance and alphas (the reference path, on any
/// device).
///
/// Math: xᵢ = σᵢδᵢ, αᵢ = −expm1(−xᵢ), Tᵢ = exp(−Σ_{j<i} xⱼ), wᵢ = Tᵢαᵢ, with
/// δᵢ = (endsᵢ − startsᵢ)·‖d_r‖ (‖d_r‖ = 1 when `rays` is `None`); with
/// `config.opaque_last`, α = 1 for the last sample of each ray. `config.background` is
/// not used.
///
/// Shapes: `sigmas: [R, S]` (batched) or `[M]` (packed), like the intervals → each field
/// of [`Weights`] has that shape. f32 or f64, any device. Differentiable (to any order)
/// with respect to `sigmas`, the intervals and the rays' directions.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::{render_weights, CompositeConfig, Intervals, Layout};
///
/// let dev = Device::Cpu;
/// let iv = Intervals::new(Tensor::new(&[[0.0f64, 1.0]], &dev)?, Tensor::new(&[[1.0f64, 2.0]], &dev)?, Layout::Batched)?;
/// let sigmas = Tensor::new(&[[1.0f64, 1.0]], &dev)?;
/// let w = render_weights(&sigmas, &iv, None, &CompositeConfig::default())?;
/// let (e1, w) = ((-1.0f64).exp(), w.weights.to_vec2::<f64>()?);
/// assert!((w[0][0] - (1.0 - e1)).abs() < 1e-15 && (w[0][1] - e1 * (1.0 - e1)).abs() < 1e-15);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// As [`composite`] for `sigmas`, `intervals` and `rays`.
pub fn render_weights(
    sigmas: &Tensor,
    intervals: &Intervals,
    rays: Option<&Rays>,
    config: &CompositeConfig,
) -> Result<Weights> {
    check_samples(sigmas, None, intervals)?;
    check_nonneg_finite(sigmas, "sigmas")?;
    let norms = intervals.direction_norms(rays)?;
    let deltas = checked_deltas(intervals, intervals.span()?, norms.as_ref())?;
    reference::weights(sigmas, &deltas, &intervals.layout, config.opaque_last)
}

/// Accumulates per-sample values along rays: `out[r, c] = Σ_{i in ray r} wᵢ·valuesᵢ,c`.
///
/// Shapes: batched `weights: [R, S]`, `values: [R, S, C]`; packed `weights: [M]`,
/// `values: [M, C]` (zero rows for rays with no samples) → `[R, C]`. Any device, f32 or
/// f64 (one dtype). Differentiable with respect to both.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::{accumulate, Layout, Packed};
///
/// let dev = Device::Cpu;
/// let packed = Packed::from_counts(&[2, 0, 1], &dev)?;
/// let w = Tensor::new(&[0.5f32, 0.25, 1.0], &dev)?;                  // [M = 3]
/// let v = Tensor::new(&[[2.0f32], [4.0], [3.0]], &dev)?;              // [M, C = 1]
/// let out = accumulate(&w, &v, &Layout::Packed(packed))?;
/// assert_eq!(out.to_vec2::<f32>()?, vec![vec![2.0], vec![0.0], vec![3.0]]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// `weights` when not float or not of the layout's sample shape; `values` when its shape
/// is not the weights' shape plus a channel axis, or its dtype or device differs.
pub fn accumulate(weights: &Tensor, values: &Tensor, layout: &Layout) -> Result<Tensor> {
    check_float(weights, "weights")?;
    let mut pattern = match layout {
        Layout::Batched => {
            let d = check_shape(weights, "weights", &[Dim::Any("R"), Dim::Any("S")])?;
            vec![Dim::Is(d[0]), Dim::Is(d[1])]
        }
        Layout::Packed(p) => {
            check_shape(weights, "weights", &[Dim::Is(p.n_samples())])?;
            vec![Dim::Is(p.n_samples())]
        }
    };
    check_same(values, "values", weights, "weights")?;
    pattern.push(Dim::Any("C"));
    check_shape(values, "values", &pattern)?;
    reference::accumulate(weights, values, layout)
}

/// Early termination: marks the samples that still matter, before the field's colour
/// (or any expensive per-sample quantity) is evaluated. Detached (no gradient).
///
/// Sample i is visible iff Tᵢ = exp(−Σ_{j<i} σⱼδⱼ) ≥ `eps` (Instant-NGP and nerfacc use
/// ε = 1e-4: [`DEFAULT_TERMINATION_EPS`]). Since T is non-increasing, the dropped samples
/// of a ray are a suffix i ≥ k with T_k < ε, and their total weight is
/// Σ_{i≥k} wᵢ = T_k − T_end < ε. Dropping them changes the composited colour by
/// Σ_{i≥k} wᵢ(cᵢ − c_bg), so the error is at most ε·max|cᵢ − c_bg| per channel; the
/// opacity changes by less than ε and the depth by less than ε·max tᵢ.
///
/// Shapes: `sigmas` of the intervals' sample shape (`[R, S]` or `[M]`) → u8 of that shape
/// (1 = keep). Use [`super::Intervals::retain`] to keep the marked samples in the packed
/// layout. The exclusive sums are one O(S) scan per ray in f64 on the host (the mask is
/// read back by its users anyway), so every device gives the same mask.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::{stratified, visible_mask, Jitter};
///
/// let dev = Device::Cpu;
/// let iv = stratified(&Tensor::new(&[0.0f32], &dev)?, &Tensor::new(&[4.0f32], &dev)?, 4, Jitter::None, 0)?;
/// let sigmas = Tensor::new(&[[0.0f32, 20.0, 1.0, 1.0]], &dev)?;      // a wall in sample 1
/// let mask = visible_mask(&sigmas, &iv, None, 1e-4)?;
/// assert_eq!(mask.to_vec2::<u8>()?, vec![vec![1, 1, 0, 0]]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// As [`render_weights`]; `eps` when not finite and > 0.
pub fn visible_mask(
    sigmas: &Tensor,
    intervals: &Intervals,
    rays: Option<&Rays>,
    eps: f64,
) -> Result<Tensor> {
    check_scalar(eps, "eps", true)?;
    check_samples(sigmas, None, intervals)?;
    check_nonneg_finite(sigmas, "sigmas")?;
    let norms = intervals.direction_norms(rays)?;
    let deltas = checked_deltas(intervals, intervals.span()?, norms.as_ref())?;
    let x = host_f64(&reference::thickness(&sigmas.detach(), &deltas.detach())?)?;
    // Compare in log space: T ≥ ε  ⇔  Σ_{j<i} x_j ≤ −ln ε.
    let limit = -eps.ln();
    let scan = |m: &mut [u8], row: &[f64]| {
        let mut excl = 0.0;
        for (mi, &xi) in m.iter_mut().zip(row) {
            *mi = u8::from(excl <= limit);
            excl += xi;
        }
    };
    let mut mask = vec![0u8; x.len()];
    match &intervals.layout {
        Layout::Batched => {
            use rayon::prelude::*;
            let s = sigmas.dim(1)?.max(1);
            mask.par_chunks_mut(s)
                .zip(x.par_chunks(s))
                .for_each(|(m, row)| scan(m, row));
        }
        Layout::Packed(p) => {
            for w in p.offsets_host().windows(2) {
                scan(&mut mask[w[0]..w[1]], &x[w[0]..w[1]]);
            }
        }
    }
    Ok(crate::narrow::from_vec(
        mask,
        sigmas.shape(),
        sigmas.device(),
    )?)
}
