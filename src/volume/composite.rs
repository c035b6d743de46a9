//! Volume compositing: weights, transmittance, colour, opacity and expected depth.
//!
//! Notation (per ray, samples i = 0..S): σᵢ ≥ 0 density, δᵢ ≥ 0 interval length,
//! xᵢ = σᵢδᵢ optical thickness, αᵢ = 1 − e^{−xᵢ}, Tᵢ = exp(−Σ_{j<i} xⱼ) the transmittance
//! *before* sample i (T₀ = 1), wᵢ = Tᵢαᵢ.
//!
//! Numerics:
//! - αᵢ = −expm1(−xᵢ) is evaluated stably: a degree-6 series for small xᵢ (so α = x to
//!   rounding at x = 1e-30, where `1 − exp(−x)` is exactly 0 in f32), `1 − exp(−x)` above.
//! - Tᵢ comes from one exclusive sum of xⱼ followed by one `exp`: no cumulative product,
//!   no division by α or T.
//! - xᵢ is clamped to [`X_MAX`] before the sum: e^{−X_MAX} is exactly 0 in f32 and f64, so
//!   the clamp changes no value and no gradient, but it keeps σδ overflowing to +∞ (e.g.
//!   σ = 1e30, δ = 1e10 in f32) from producing ∞·0 = NaN inside the sum.
//! - The opaque last interval ([`WeightOptions::opaque_last`], as in multinerf) sets
//!   α = 1 for the last sample of each ray by selection; it never multiplies by a huge δ.
//!
//! Validation: σ must be finite and ≥ 0 (NaN, negative and **+∞ are rejected** with an
//! error naming `sigmas`: activations such as trunc-exp ([`super::activations`]) never
//! produce ∞, so an infinite density is an upstream bug; a huge finite density such as
//! 1e30 is fine and acts as an opaque wall). δ must be finite and ≥ 0 (error names
//! `deltas`).
//!
//! The reference path here is built from candle ops and runs on any device and dtype
//! (f32, f64). It is differentiable with respect to σ, δ, the values and the sample
//! depths. Candle's `cumsum` is a matmul with an n×n triangle, so the reference costs
//! O(R·S²); the fused CPU op in [`super::fused`] is O(R·S).

use crate::error::{
    check_float, check_same, check_same_shape, check_scalar, check_shape, Dim, Error, Result,
};
use crate::parallel::for_each_init;
use candle_core::{DType, Device, Storage, Tensor};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// Optical thickness above which xᵢ = σᵢδᵢ is clamped. `exp(−1000)` is exactly zero in
/// f32 and f64, so clamping changes no weight or gradient; it only keeps `+∞` (from
/// overflow of σδ) out of the exclusive sum.
pub const X_MAX: f64 = 1000.0;

/// The default transmittance threshold ε of early termination ([`visible_mask`]): the
/// value of Instant-NGP and nerfacc. Samples behind `T < ε` carry less than ε of the
/// ray's weight in total.
pub const DEFAULT_TERMINATION_EPS: f64 = 1e-4;

/// Options for [`render_weights`] and the compositing functions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WeightOptions {
    /// Treat the last interval of every ray as opaque: α = 1 there, so Σw = 1 − T_end
    /// becomes exactly 1 (unless T already underflowed). The last sample's σ and δ then
    /// receive zero gradient. This replaces NeRF's "last δ = 1e10" (which overflows and
    /// multiplies 0 by ∞) by a selection, as multinerf does.
    pub opaque_last: bool,
}

/// Per-sample compositing quantities returned by [`render_weights`] and
/// [`render_weights_packed`]. All have the shape of the input densities (`[R, S]` or
/// `[M]`) and its dtype.
#[derive(Clone, Debug)]
pub struct Weights {
    /// wᵢ = Tᵢαᵢ.
    pub weights: Tensor,
    /// Tᵢ = exp(−Σ_{j<i} σⱼδⱼ), the transmittance before sample i (T₀ = 1).
    pub transmittance: Tensor,
    /// αᵢ = 1 − exp(−σᵢδᵢ) (1 for the last sample under `opaque_last`).
    pub alphas: Tensor,
}

/// Packed layout: `M` samples stored flat, ray by ray, with per-ray counts.
///
/// Ray r owns samples `offsets[r] .. offsets[r + 1]`; rays may have zero samples.
/// The host copy of the offsets is kept alongside the device tensors so that the fused
/// CPU op and the padding used by the reference path need no device read-back.
#[derive(Clone, Debug)]
pub struct Packed {
    /// `[M]` u32: the ray of each sample (non-decreasing).
    pub ray_indices: Tensor,
    /// `[R + 1]` u32: `offsets[r]` is the first sample of ray r, `offsets[R] = M`.
    pub offsets: Tensor,
    /// Number of rays `R`.
    pub n_rays: usize,
    offsets_host: Arc<[usize]>,
}

impl Packed {
    /// Builds the layout from per-ray sample counts (`counts[r]` samples for ray r, zero
    /// allowed), with its index tensors on `device`.
    ///
    /// # Errors
    /// `counts` when the total does not fit in u32; candle errors on allocation.
    pub fn from_counts(counts: &[usize], device: &Device) -> Result<Self> {
        let mut offsets_host = Vec::with_capacity(counts.len() + 1);
        let mut acc = 0usize;
        offsets_host.push(0);
        for &c in counts {
            acc += c;
            offsets_host.push(acc);
        }
        if acc > u32::MAX as usize {
            return Err(Error::invalid(
                "counts",
                "a total sample count that fits in u32",
                format!("{acc}"),
            ));
        }
        let mut ray_idx = Vec::with_capacity(acc);
        for (r, &c) in counts.iter().enumerate() {
            ray_idx.extend(std::iter::repeat_n(r as u32, c));
        }
        let off_u32: Vec<u32> = offsets_host.iter().map(|&o| o as u32).collect();
        Ok(Self {
            ray_indices: Tensor::from_vec(ray_idx, acc, device)?,
            offsets: Tensor::from_vec(off_u32, counts.len() + 1, device)?,
            n_rays: counts.len(),
            offsets_host: offsets_host.into(),
        })
    }

    /// Builds the layout from a `[R, S]` visibility mask (u8, nonzero = keep), e.g. from
    /// [`visible_mask`]. Returns the layout and the `[M]` u32 flat indices (into the
    /// `R·S` samples, row-major) of the kept samples, for `index_select` on flattened
    /// per-sample tensors.
    ///
    /// # Errors
    /// `mask` when it is not a 2-D u8 tensor.
    pub fn from_mask(mask: &Tensor) -> Result<(Self, Tensor)> {
        let dims = check_shape(mask, "mask", &[Dim::Any("R"), Dim::Any("S")])?;
        if mask.dtype() != DType::U8 {
            return Err(Error::invalid(
                "mask",
                "dtype u8",
                format!("{:?}", mask.dtype()),
            ));
        }
        let (r, s) = (dims[0], dims[1]);
        let host = mask.flatten_all()?.to_vec1::<u8>()?;
        let mut counts = vec![0usize; r];
        let mut keep = Vec::new();
        for (i, &m) in host.iter().enumerate() {
            if m != 0 {
                counts[i / s.max(1)] += 1;
                keep.push(i as u32);
            }
        }
        let n = keep.len();
        let packed = Self::from_counts(&counts, mask.device())?;
        Ok((packed, Tensor::from_vec(keep, n, mask.device())?))
    }

    /// Total number of samples `M`.
    #[must_use]
    pub fn n_samples(&self) -> usize {
        self.offsets_host.last().copied().unwrap_or(0)
    }

    /// Host copy of the offsets (`R + 1` entries).
    #[must_use]
    pub fn offsets_host(&self) -> &[usize] {
        &self.offsets_host
    }

    /// Shared host copy of the offsets (cheap to clone).
    pub(crate) fn offsets_arc(&self) -> Arc<[usize]> {
        self.offsets_host.clone()
    }

    /// Largest per-ray sample count.
    #[must_use]
    pub fn max_count(&self) -> usize {
        self.offsets_host
            .windows(2)
            .map(|w| w[1] - w[0])
            .max()
            .unwrap_or(0)
    }
}

/// Index and value of the first element outside [`zero`, `max`] (NaN included), or
/// `None`. A branch-free (vectorisable) pass finds whether one exists; only then is it
/// located. This check runs on every compositing call, so slices of at least
/// 2·[`PARALLEL_CHECK_LEN`] elements are checked in chunks of that length on candle's
/// CPU pool.
fn first_bad<T>(xs: &[T], zero: T, max: T) -> Option<(usize, f64)>
where
    T: Copy + PartialOrd + Into<f64> + Sync,
{
    let ok = |v: T| (v >= zero) & (v <= max);
    let all_ok = |c: &[T]| {
        c.chunks(1024)
            .all(|c| c.iter().fold(true, |acc, &v| acc & ok(v)))
    };
    let fine = if xs.len() < 2 * PARALLEL_CHECK_LEN {
        all_ok(xs)
    } else {
        let failed = AtomicBool::new(false);
        let chunks = xs.chunks(PARALLEL_CHECK_LEN).collect();
        for_each_init(
            chunks,
            || (),
            |_, c| {
                if !all_ok(c) {
                    failed.store(true, Ordering::Relaxed);
                }
            },
        );
        !failed.load(Ordering::Relaxed)
    };
    if fine {
        return None;
    }
    xs.iter().position(|&v| !ok(v)).map(|i| (i, xs[i].into()))
}

/// Chunk length of the parallel input check in [`first_bad`].
const PARALLEL_CHECK_LEN: usize = 1 << 16;

/// Checks that every element is finite and ≥ 0 (rejects NaN, −x, +∞).
///
/// On CPU this is one pass over the data; elsewhere a few reductions and one read-back.
pub(crate) fn check_nonneg_finite(t: &Tensor, arg: &'static str) -> Result<()> {
    if t.elem_count() == 0 {
        return Ok(());
    }
    {
        let (st, layout) = t.storage_and_layout();
        if let (Storage::Cpu(cpu), Some((a, b))) = (&*st, layout.contiguous_offsets()) {
            let bad = match t.dtype() {
                DType::F32 => first_bad(&cpu.as_slice::<f32>()?[a..b], 0.0, f32::MAX),
                DType::F64 => first_bad(&cpu.as_slice::<f64>()?[a..b], 0.0, f64::MAX),
                other => {
                    return Err(Error::invalid(
                        arg,
                        "dtype f32 or f64",
                        format!("{other:?}"),
                    ))
                }
            };
            return match bad {
                None => Ok(()),
                Some((i, v)) => Err(Error::invalid(
                    arg,
                    "finite values >= 0",
                    format!("{v} at flat index {i}"),
                )),
            };
        }
    }
    let x = t.detach().to_dtype(DType::F64)?.flatten_all()?;
    // x − x is NaN exactly for NaN and ±∞.
    let probe = x.sub(&x)?.sum_all()?.to_scalar::<f64>()?;
    if !probe.is_finite() {
        return Err(Error::invalid(arg, "finite values >= 0", "NaN or infinity"));
    }
    let min = x.min(0)?.to_scalar::<f64>()?;
    if min < 0.0 {
        return Err(Error::invalid(
            arg,
            "finite values >= 0",
            format!("minimum {min}"),
        ));
    }
    Ok(())
}

/// α = −expm1(−x) for x ≥ 0 from candle ops, accurate to a few ulps in f32 and f64.
///
/// Below a dtype-dependent threshold (0.3 in f32, 0.02 in f64) the Taylor series to x⁶
/// is used (truncation below the rounding error there); above it `1 − exp(−x)`, whose
/// cancellation error ε/x is then also at rounding level. Each branch is fed a clamped
/// input (the "double where" trick), so neither branch can produce NaN in the backward.
pub(crate) fn alpha_from_x(x: &Tensor) -> Result<Tensor> {
    let thr = if x.dtype() == DType::F32 { 0.3 } else { 0.02 };
    let xs = x.minimum(thr)?;
    let xb = x.maximum(thr)?;
    // x(1 − x/2(1 − x/3(1 − x/4(1 − x/5(1 − x/6))))) by Horner.
    let mut p = ((&xs * (-1.0 / 6.0))? + 1.0)?;
    for k in [5.0, 4.0, 3.0, 2.0] {
        p = ((&xs * (-1.0 / k))?.mul(&p)? + 1.0)?;
    }
    let series = (&xs * p)?;
    let big = ((xb.neg()?.exp()?.neg()?) + 1.0)?;
    let small = x.lt(thr)?;
    Ok(small.where_cond(&series, &big)?)
}

/// `[S, S]` strictly upper-triangular ones (`U[j, i] = 1` iff `j < i`) on `x`'s device
/// and dtype: `x.matmul(U)` is the exclusive prefix sum along the last axis.
fn exclusive_triangle(s: usize, like: &Tensor) -> Result<Tensor> {
    let i = Tensor::arange(0u32, s as u32, like.device())?;
    let m = i
        .unsqueeze(1)?
        .broadcast_lt(&i.unsqueeze(0)?)?
        .to_dtype(like.dtype())?;
    Ok(m)
}

/// Core of the reference path on a padded `[R, S]` thickness tensor `x` (already
/// clamped, padding = 0) and alphas `alpha` (already opaque where requested).
fn weights_from_padded(x: &Tensor, alpha: Tensor) -> Result<Weights> {
    let s = x.dim(1)?;
    let excl = x.matmul(&exclusive_triangle(s, x)?)?;
    let transmittance = excl.neg()?.exp()?;
    let weights = (&transmittance * &alpha)?;
    Ok(Weights {
        weights,
        transmittance,
        alphas: alpha,
    })
}

/// xᵢ = min(σᵢδᵢ, X_MAX).
fn thickness(sigmas: &Tensor, deltas: &Tensor) -> Result<Tensor> {
    Ok((sigmas * deltas)?.minimum(X_MAX)?)
}

/// Validates densities and deltas of the same shape, dtype and device.
pub(crate) fn check_sigmas_deltas(sigmas: &Tensor, deltas: &Tensor) -> Result<()> {
    check_float(sigmas, "sigmas")?;
    check_same(deltas, "deltas", sigmas, "sigmas")?;
    check_same_shape(deltas, "deltas", sigmas, "sigmas")?;
    check_nonneg_finite(sigmas, "sigmas")?;
    check_nonneg_finite(deltas, "deltas")?;
    Ok(())
}

/// Compositing weights for the batched layout (reference path, candle ops).
///
/// Math: xᵢ = σᵢδᵢ, αᵢ = −expm1(−xᵢ), Tᵢ = exp(−Σ_{j<i} xⱼ), wᵢ = Tᵢαᵢ; with
/// `opts.opaque_last`, α_{S−1} = 1.
///
/// Shapes: `sigmas: [R, S]`, `deltas: [R, S]` → each field of [`Weights`] is `[R, S]`.
/// Dtype f32 or f64, any device. Differentiable with respect to `sigmas` and `deltas`.
///
/// # Errors
/// `sigmas` when not a 2-D f32/f64 tensor or containing NaN, negative values or +∞;
/// `deltas` when its shape, dtype or device differs from `sigmas` or it contains NaN,
/// negative values or +∞.
pub fn render_weights(sigmas: &Tensor, deltas: &Tensor, opts: &WeightOptions) -> Result<Weights> {
    check_shape(sigmas, "sigmas", &[Dim::Any("R"), Dim::Any("S")])?;
    check_sigmas_deltas(sigmas, deltas)?;
    let (r, s) = sigmas.dims2()?;
    let x = thickness(sigmas, deltas)?;
    let mut alpha = alpha_from_x(&x)?;
    if opts.opaque_last && s > 0 {
        let last = Tensor::arange(0u32, s as u32, sigmas.device())?
            .eq(s as u32 - 1)?
            .unsqueeze(0)?
            .broadcast_as((r, s))?;
        alpha = last.where_cond(&alpha.ones_like()?, &alpha)?;
    }
    weights_from_padded(&x, alpha)
}

/// Compositing weights for the packed layout (reference path, candle ops).
///
/// Same math as [`render_weights`] per ray; ray r's samples are
/// `offsets[r]..offsets[r + 1]` of `packed`. Internally the samples are gathered into a
/// zero-padded `[R, S_max]` block (padding has x = 0 and does not change any sum),
/// processed like the batched layout, and gathered back.
///
/// Shapes: `sigmas: [M]`, `deltas: [M]` with `M = packed.n_samples()` → fields `[M]`.
/// f32 or f64, any device. Differentiable with respect to `sigmas` and `deltas`.
///
/// # Errors
/// As [`render_weights`]; `sigmas` also when its length differs from the packed count.
pub fn render_weights_packed(
    sigmas: &Tensor,
    deltas: &Tensor,
    packed: &Packed,
    opts: &WeightOptions,
) -> Result<Weights> {
    let m = packed.n_samples();
    check_shape(sigmas, "sigmas", &[Dim::Is(m)])?;
    check_sigmas_deltas(sigmas, deltas)?;
    let x = thickness(sigmas, deltas)?;
    let mut alpha = alpha_from_x(&x)?;
    if m == 0 {
        return Ok(Weights {
            weights: x.clone(),
            transmittance: x.clone(),
            alphas: alpha,
        });
    }
    let off = packed.offsets_host();
    let r = packed.n_rays;
    let smax = packed.max_count();
    let dev = sigmas.device();
    // gather[r*smax + k] = sample index, or m (a zero appended) for padding;
    // scatter[m] = r*smax + k; last[m] = 1 for the last sample of its ray.
    let mut gather = vec![m as u32; r * smax];
    let mut scatter = vec![0u32; m];
    let mut last = vec![0u8; m];
    for ray in 0..r {
        let (a, b) = (off[ray], off[ray + 1]);
        for (k, idx) in (a..b).enumerate() {
            gather[ray * smax + k] = idx as u32;
            scatter[idx] = (ray * smax + k) as u32;
        }
        if b > a {
            last[b - 1] = 1;
        }
    }
    let gather = Tensor::from_vec(gather, r * smax, dev)?;
    let scatter = Tensor::from_vec(scatter, m, dev)?;
    if opts.opaque_last {
        let last = Tensor::from_vec(last, m, dev)?;
        alpha = last.where_cond(&alpha.ones_like()?, &alpha)?;
    }
    let x_ext = Tensor::cat(&[&x, &Tensor::zeros(1, x.dtype(), dev)?], 0)?;
    let x_pad = x_ext.index_select(&gather, 0)?.reshape((r, smax))?;
    let excl = x_pad.matmul(&exclusive_triangle(smax, &x_pad)?)?;
    let excl = excl.flatten_all()?.index_select(&scatter, 0)?;
    let transmittance = excl.neg()?.exp()?;
    let weights = (&transmittance * &alpha)?;
    Ok(Weights {
        weights,
        transmittance,
        alphas: alpha,
    })
}

/// Accumulates per-sample values along rays: `out[r, c] = Σᵢ w[r, i]·values[r, i, c]`.
///
/// Shapes: `weights: [R, S]`, `values: [R, S, C]` → `[R, C]`. Any device, f32/f64 (same
/// dtype). Differentiable with respect to both.
///
/// # Errors
/// `values` when its shape is not `[R, S, C]` for the weights' `R, S` or its dtype or
/// device differs; `weights` when not 2-D float.
pub fn accumulate(weights: &Tensor, values: &Tensor) -> Result<Tensor> {
    check_float(weights, "weights")?;
    let d = check_shape(weights, "weights", &[Dim::Any("R"), Dim::Any("S")])?;
    check_same(values, "values", weights, "weights")?;
    check_shape(
        values,
        "values",
        &[Dim::Is(d[0]), Dim::Is(d[1]), Dim::Any("C")],
    )?;
    Ok(weights.unsqueeze(2)?.broadcast_mul(values)?.sum(1)?)
}

/// Packed form of [`accumulate`]: `out[r, c] = Σ_{i in ray r} w[i]·values[i, c]`.
///
/// Shapes: `weights: [M]`, `values: [M, C]` → `[R, C]` (zero rows for rays with no
/// samples). f32 or f64, any device. Differentiable with respect to both.
///
/// # Errors
/// `weights` / `values` on shape, dtype or device mismatch with `packed`.
pub fn accumulate_packed(weights: &Tensor, values: &Tensor, packed: &Packed) -> Result<Tensor> {
    check_float(weights, "weights")?;
    let m = packed.n_samples();
    check_shape(weights, "weights", &[Dim::Is(m)])?;
    check_same(values, "values", weights, "weights")?;
    let d = check_shape(values, "values", &[Dim::Is(m), Dim::Any("C")])?;
    let zeros = Tensor::zeros((packed.n_rays, d[1]), weights.dtype(), weights.device())?;
    if m == 0 {
        return Ok(zeros);
    }
    let wv = weights.unsqueeze(1)?.broadcast_mul(values)?;
    Ok(zeros.index_add(&packed.ray_indices, &wv, 0)?)
}

/// Options for [`composite`] and its variants.
#[derive(Clone, Debug, Default)]
pub struct CompositeOptions {
    /// See [`WeightOptions::opaque_last`].
    pub opaque_last: bool,
    /// Background colour c_bg, `[C]` or `[R, C]`; `None` means black (zero). The
    /// background enters as C = Σwᵢcᵢ + (1 − Σwᵢ)·c_bg and is differentiable.
    pub background: Option<Tensor>,
}

impl CompositeOptions {
    /// The [`WeightOptions`] part.
    #[must_use]
    pub fn weight_options(&self) -> WeightOptions {
        WeightOptions {
            opaque_last: self.opaque_last,
        }
    }
}

/// Per-ray compositing results.
#[derive(Clone, Debug)]
pub struct Composite {
    /// `[R, C]`: C = Σwᵢcᵢ + (1 − Σwᵢ)·c_bg.
    pub color: Tensor,
    /// `[R]`: Σwᵢ = 1 − T_end (exactly 1 − exp(−Σxᵢ) without `opaque_last`).
    pub opacity: Tensor,
    /// `[R]`: the unnormalised expected depth Σwᵢtᵢ (tᵢ the sample depths, usually
    /// interval midpoints); it treats the background as depth 0. See
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

/// Adds the background term and packages the results.
pub(crate) fn finish(
    acc_color: Tensor,
    opacity: Tensor,
    depth: Tensor,
    opts: &CompositeOptions,
) -> Result<Composite> {
    let color = match &opts.background {
        None => acc_color,
        Some(bg) => {
            let (r, c) = acc_color.dims2()?;
            check_same(bg, "background", &acc_color, "colors")?;
            let bg = match bg.rank() {
                1 => {
                    check_shape(bg, "background", &[Dim::Is(c)])?;
                    bg.unsqueeze(0)?
                }
                _ => {
                    check_shape(bg, "background", &[Dim::Is(r), Dim::Is(c)])?;
                    bg.clone()
                }
            };
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

pub(crate) fn check_composite_inputs(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
) -> Result<()> {
    let d = check_shape(sigmas, "sigmas", &[Dim::Any("R"), Dim::Any("S")])?;
    check_float(sigmas, "sigmas")?;
    check_same(colors, "colors", sigmas, "sigmas")?;
    check_shape(
        colors,
        "colors",
        &[Dim::Is(d[0]), Dim::Is(d[1]), Dim::Any("C")],
    )?;
    check_same(t_mids, "t_mids", sigmas, "sigmas")?;
    check_shape(t_mids, "t_mids", &[Dim::Is(d[0]), Dim::Is(d[1])])?;
    check_sigmas_deltas(sigmas, deltas)
}

pub(crate) fn check_composite_inputs_packed(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    packed: &Packed,
) -> Result<()> {
    let m = packed.n_samples();
    check_shape(sigmas, "sigmas", &[Dim::Is(m)])?;
    check_float(sigmas, "sigmas")?;
    check_same(colors, "colors", sigmas, "sigmas")?;
    check_shape(colors, "colors", &[Dim::Is(m), Dim::Any("C")])?;
    check_same(t_mids, "t_mids", sigmas, "sigmas")?;
    check_shape(t_mids, "t_mids", &[Dim::Is(m)])?;
    check_sigmas_deltas(sigmas, deltas)
}

/// Composites a batch of rays: colour, opacity and expected depth (reference path).
///
/// Math: wᵢ from [`render_weights`]; colour = Σwᵢcᵢ + (1 − Σwᵢ)·c_bg, opacity = Σwᵢ,
/// depth = Σwᵢtᵢ.
///
/// Shapes: `sigmas: [R, S]`, `colors: [R, S, C]`, `deltas: [R, S]`, `t_mids: [R, S]`
/// (the depth assigned to each sample, usually the interval midpoint) → [`Composite`]
/// with `color: [R, C]`, `opacity: [R]`, `depth: [R]`. f32 or f64, any device.
/// Differentiable with respect to `sigmas`, `colors`, `deltas`, `t_mids` and the
/// background.
///
/// # Errors
/// Named after the offending argument: shape/dtype/device mismatches, NaN, negative or
/// infinite `sigmas` or `deltas`, a `background` not `[C]` or `[R, C]`.
pub fn composite_reference(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    opts: &CompositeOptions,
) -> Result<Composite> {
    check_composite_inputs(sigmas, colors, deltas, t_mids)?;
    let w = render_weights(sigmas, deltas, &opts.weight_options())?;
    let acc = accumulate(&w.weights, colors)?;
    let opacity = w.weights.sum(1)?;
    let depth = (&w.weights * t_mids)?.sum(1)?;
    finish(acc, opacity, depth, opts)
}

/// Packed-layout [`composite_reference`]: `sigmas, deltas, t_mids: [M]`,
/// `colors: [M, C]` → `color: [R, C]`, `opacity: [R]`, `depth: [R]`; rays without
/// samples get opacity 0, depth 0 and the background colour.
///
/// Math per ray r (its samples `offsets[r]..offsets[r + 1]` of `packed`): wᵢ from
/// [`render_weights_packed`]; colour = Σwᵢcᵢ + (1 − Σwᵢ)·c_bg, opacity = Σwᵢ, depth =
/// Σwᵢtᵢ. f32 or f64, any device. Differentiable with respect to `sigmas`, `colors`,
/// `deltas`, `t_mids` and the background.
///
/// # Errors
/// As [`composite_reference`], with shapes checked against `packed`.
pub fn composite_packed_reference(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    packed: &Packed,
    opts: &CompositeOptions,
) -> Result<Composite> {
    check_composite_inputs_packed(sigmas, colors, deltas, t_mids, packed)?;
    let w = render_weights_packed(sigmas, deltas, packed, &opts.weight_options())?;
    let acc = accumulate_packed(&w.weights, colors, packed)?;
    let wt = Tensor::stack(&[&w.weights, &(&w.weights * t_mids)?], 1)?;
    let od = accumulate_packed(&w.weights.ones_like()?, &wt, packed)?;
    let opacity = od.narrow(1, 0, 1)?.squeeze(1)?;
    let depth = od.narrow(1, 1, 1)?.squeeze(1)?;
    finish(acc, opacity, depth, opts)
}

/// Composites a batch of rays, picking the implementation: the fused CPU op
/// ([`super::fused::composite_fused`]) on CPU, [`composite_reference`] elsewhere. Same
/// math, shapes, gradients and errors as [`composite_reference`], except that on the CPU
/// only first-order gradients are available (call [`composite_reference`] for
/// higher-order derivatives).
///
/// # Errors
/// As [`composite_reference`].
pub fn composite(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    opts: &CompositeOptions,
) -> Result<Composite> {
    if sigmas.device().is_cpu() {
        super::fused::composite_fused(sigmas, colors, deltas, t_mids, opts)
    } else {
        composite_reference(sigmas, colors, deltas, t_mids, opts)
    }
}

/// Packed-layout [`composite`]: fused on CPU, [`composite_packed_reference`] elsewhere.
/// Same math, shapes (`sigmas, deltas, t_mids: [M]`, `colors: [M, C]` → `[R, C]`, `[R]`,
/// `[R]`), dtypes (f32, f64) and gradients as [`composite_packed_reference`], first
/// order only on the CPU.
///
/// # Errors
/// As [`composite_packed_reference`].
pub fn composite_packed(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    packed: &Packed,
    opts: &CompositeOptions,
) -> Result<Composite> {
    if sigmas.device().is_cpu() {
        super::fused::composite_packed_fused(sigmas, colors, deltas, t_mids, packed, opts)
    } else {
        composite_packed_reference(sigmas, colors, deltas, t_mids, packed, opts)
    }
}

/// Early termination: marks the samples that still matter, before the field's colour
/// (or any expensive per-sample quantity) is evaluated. Detached (no gradient).
///
/// Sample i is visible iff Tᵢ = exp(−Σ_{j<i} σⱼδⱼ) ≥ `eps` (Instant-NGP and nerfacc use
/// ε = 1e-4: [`DEFAULT_TERMINATION_EPS`]). Since T is non-increasing, the dropped samples of a ray are a suffix
/// i ≥ k with T_k < ε, and their total weight is Σ_{i≥k} wᵢ = T_k − T_end < ε.
/// Dropping them changes the composited colour by Σ_{i≥k} wᵢ(cᵢ − c_bg), so the error is
/// at most ε·max|cᵢ − c_bg| per channel (≤ ε·max|cᵢ| on a black background); the
/// opacity changes by less than ε and the depth by less than ε·max tᵢ.
///
/// Shapes: `sigmas, deltas: [R, S]` → `[R, S]` u8 (1 = keep). Use [`Packed::from_mask`]
/// to turn it into a packed layout. On the CPU the exclusive sums are one O(S) scan per
/// ray in f64 (parallel over rays); elsewhere one matmul with the S × S triangle in the
/// inputs' dtype (the two agree except for sums within rounding of −ln ε).
///
/// # Errors
/// As [`render_weights`]; `eps` when not finite and > 0.
pub fn visible_mask(sigmas: &Tensor, deltas: &Tensor, eps: f64) -> Result<Tensor> {
    check_scalar(eps, "eps", true)?;
    check_shape(sigmas, "sigmas", &[Dim::Any("R"), Dim::Any("S")])?;
    check_sigmas_deltas(sigmas, deltas)?;
    let x = thickness(&sigmas.detach(), &deltas.detach())?;
    let (r, s) = x.dims2()?;
    // Compare in log space: T ≥ ε  ⇔  Σ_{j<i} x_j ≤ −ln ε.
    let limit = -eps.ln();
    if x.device().is_cpu() {
        use rayon::prelude::*;
        let xs: Vec<f64> = x.to_dtype(DType::F64)?.flatten_all()?.to_vec1()?;
        let mut mask = vec![0u8; r * s];
        mask.par_chunks_mut(s.max(1))
            .zip(xs.par_chunks(s.max(1)))
            .for_each(|(m, row)| {
                let mut excl = 0.0;
                for (mi, &xi) in m.iter_mut().zip(row) {
                    *mi = u8::from(excl <= limit);
                    excl += xi;
                }
            });
        return Ok(Tensor::from_vec(mask, (r, s), x.device())?);
    }
    let excl = x.matmul(&exclusive_triangle(s, &x)?)?;
    Ok(excl.le(limit)?)
}
