//! The reference compositing path: plain candle ops on any device and dtype (f32, f64),
//! differentiable (to any order) with respect to σ, δ, the values and the sample depths.
//!
//! Candle's `cumsum` is a matmul with an n×n triangle, so this path costs O(R·S²); the
//! fused CPU op (`crate::kernels`' compositing kernel) is O(R·S). The entry points in [`super::composite`]
//! pick between the two; tests compare them.

use super::layout::{Layout, Weights};
use crate::error::Result;
use crate::kernels::X_MAX;
use candle_core::{DType, Tensor};

/// α = −expm1(−x) for x ≥ 0 from candle ops, accurate to a few ulps in f32 and f64.
///
/// Below a dtype-dependent threshold (0.3 in f32, 0.02 in f64) the Taylor series to x⁶
/// is used (truncation below the rounding error there); above it `1 − exp(−x)`, whose
/// cancellation error ε/x is then also at rounding level. Each branch is fed a clamped
/// input (the "double where" trick), so neither branch can produce NaN in the backward.
fn alpha_from_x(x: &Tensor) -> Result<Tensor> {
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

/// `[S, S]` strictly upper-triangular ones (`U[j, i] = 1` iff `j < i`) on `like`'s
/// device and dtype: `x.matmul(U)` is the exclusive prefix sum along the last axis.
pub(crate) fn exclusive_triangle(s: usize, like: &Tensor) -> Result<Tensor> {
    let i = Tensor::arange(0u32, s as u32, like.device())?;
    let m = i
        .unsqueeze(1)?
        .broadcast_lt(&i.unsqueeze(0)?)?
        .to_dtype(like.dtype())?;
    Ok(m)
}

/// xᵢ = min(σᵢδᵢ, X_MAX).
pub(crate) fn thickness(sigmas: &Tensor, deltas: &Tensor) -> Result<Tensor> {
    Ok((sigmas * deltas)?.minimum(X_MAX)?)
}

/// Compositing weights in either layout, from validated `sigmas` and `deltas` of the
/// layout's sample shape (`[R, S]` or `[M]`).
///
/// Math: xᵢ = min(σᵢδᵢ, X_MAX), αᵢ = −expm1(−xᵢ), Tᵢ = exp(−Σ_{j<i} xⱼ), wᵢ = Tᵢαᵢ; with
/// `opaque_last`, α = 1 for the last sample of each ray. The packed layout is gathered
/// into a zero-padded `[R, S_max]` block (padding has x = 0 and changes no sum),
/// processed like the batched one, and gathered back.
pub(crate) fn weights(
    sigmas: &Tensor,
    deltas: &Tensor,
    layout: &Layout,
    opaque_last: bool,
) -> Result<Weights> {
    let x = thickness(sigmas, deltas)?;
    let mut alpha = alpha_from_x(&x)?;
    let dev = sigmas.device();
    match layout {
        Layout::Batched => {
            let (r, s) = sigmas.dims2()?;
            if opaque_last && s > 0 {
                let last = Tensor::arange(0u32, s as u32, dev)?
                    .eq(s as u32 - 1)?
                    .unsqueeze(0)?
                    .broadcast_as((r, s))?;
                alpha = last.where_cond(&alpha.ones_like()?, &alpha)?;
            }
            let excl = x.matmul(&exclusive_triangle(s, &x)?)?;
            let transmittance = excl.neg()?.exp()?;
            let weights = (&transmittance * &alpha)?;
            Ok(Weights::new(weights, transmittance, alpha))
        }
        Layout::Packed(packed) => {
            let m = packed.n_samples();
            if m == 0 {
                return Ok(Weights::new(x.clone(), x, alpha));
            }
            let off = packed.offsets_host();
            let r = packed.n_rays;
            let smax = packed.max_count();
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
            let gather = crate::narrow::from_vec(gather, r * smax, dev)?;
            let scatter = crate::narrow::from_vec(scatter, m, dev)?;
            if opaque_last {
                let last = crate::narrow::from_vec(last, m, dev)?;
                alpha = last.where_cond(&alpha.ones_like()?, &alpha)?;
            }
            let x_ext = Tensor::cat(&[&x, &Tensor::zeros(1, x.dtype(), dev)?], 0)?;
            let x_pad = x_ext.index_select(&gather, 0)?.reshape((r, smax))?;
            let excl = x_pad.matmul(&exclusive_triangle(smax, &x_pad)?)?;
            let excl = excl.flatten_all()?.index_select(&scatter, 0)?;
            let transmittance = excl.neg()?.exp()?;
            let weights = (&transmittance * &alpha)?;
            Ok(Weights::new(weights, transmittance, alpha))
        }
    }
}

/// `out[r, c] = Σ_{i in ray r} wᵢ·valuesᵢ,c` for validated inputs: `[R, S]` weights with
/// `[R, S, C]` values, or `[M]` with `[M, C]` (zero rows for rays without samples).
pub(crate) fn accumulate(weights: &Tensor, values: &Tensor, layout: &Layout) -> Result<Tensor> {
    match layout {
        Layout::Batched => Ok(weights.unsqueeze(2)?.broadcast_mul(values)?.sum(1)?),
        Layout::Packed(packed) => {
            let c = values.dim(1)?;
            let zeros = Tensor::zeros((packed.n_rays, c), weights.dtype(), weights.device())?;
            if packed.n_samples() == 0 {
                return Ok(zeros);
            }
            let wv = weights.unsqueeze(1)?.broadcast_mul(values)?;
            Ok(zeros.index_add(&packed.ray_indices, &wv, 0)?)
        }
    }
}

/// Colour Σwᵢcᵢ `[R, C]`, opacity Σwᵢ `[R]` and depth Σwᵢtᵢ `[R]` of validated inputs in
/// either layout (no background).
pub(crate) fn composite(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    layout: &Layout,
    opaque_last: bool,
) -> Result<(Tensor, Tensor, Tensor)> {
    let w = weights(sigmas, deltas, layout, opaque_last)?.weights;
    let color = accumulate(&w, colors, layout)?;
    let wt = (&w * t_mids)?;
    match layout {
        Layout::Batched => Ok((color, w.sum(1)?, wt.sum(1)?)),
        Layout::Packed(_) => {
            let od = accumulate(&w.ones_like()?, &Tensor::stack(&[&w, &wt], 1)?, layout)?;
            let opacity = od.narrow(1, 0, 1)?.squeeze(1)?;
            let depth = crate::narrow::narrow(&od, 1, 1, 1)?.squeeze(1)?;
            Ok((color, opacity, depth))
        }
    }
}
