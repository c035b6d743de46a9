//! Density activations for NeRF fields: trunc-exp and softplus.
//!
//! Both map a raw network output x ∈ ℝ to a density σ ≥ 0 whose value and gradient are
//! finite for every finite x, so that [`super::composite`] never sees ∞.
//!
//! - `trunc_exp(x) = exp(min(x, m))` with m = 88 in f32 (e⁸⁸ ≈ 1.65e38 < f32::MAX) and
//!   709 in f64; its *gradient* is defined as `exp(clamp(x, −15, 15))` (nerfstudio's
//!   trunc-exp, which removed NaNs that appeared after 50–80k training steps). The
//!   gradient is thus not the derivative of the forward value: it is bounded by
//!   e¹⁵ ≈ 3.3e6, and it is e⁻¹⁵ rather than ≈ 0 for very negative x, so empty space
//!   keeps a small gradient.
//! - `softplus(x) = log(1 + eˣ)` computed as `max(x, 0) + log1p(e^{−|x|})` (no overflow,
//!   no cancellation), with the exact derivative `sigmoid(x)` (1/2 at x = 0).
//!
//! On the CPU each is a candle [`CustomOp1`] with a `bwd`; on other devices the same
//! value and gradient are composed from candle ops with a detach trick
//! (`v.detach() + (x·s − (x·s).detach())` has value `v` and gradient `s`).

use crate::error::{check_float, Result};
use candle_core::{CpuStorage, CustomOp1, DType, Layout, Shape, Tensor};

/// Upper clamp of the trunc-exp argument in f32: e⁸⁸ ≈ 1.65e38 is finite.
pub const TRUNC_EXP_MAX_F32: f64 = 88.0;
/// Upper clamp of the trunc-exp argument in f64: e⁷⁰⁹ ≈ 8.2e307 is finite.
pub const TRUNC_EXP_MAX_F64: f64 = 709.0;
/// The trunc-exp gradient is `exp(clamp(x, −TRUNC_EXP_GRAD_CLAMP, TRUNC_EXP_GRAD_CLAMP))`.
pub const TRUNC_EXP_GRAD_CLAMP: f64 = 15.0;

fn unary<F32: Fn(f32) -> f32, F64: Fn(f64) -> f64>(
    name: &str,
    s: &CpuStorage,
    l: &Layout,
    f32op: F32,
    f64op: F64,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let Some((a, b)) = l.contiguous_offsets() else {
        candle_core::bail!("{name}: input must be contiguous")
    };
    let out = match s {
        CpuStorage::F32(v) => CpuStorage::F32(v[a..b].iter().map(|&x| f32op(x)).collect()),
        CpuStorage::F64(v) => CpuStorage::F64(v[a..b].iter().map(|&x| f64op(x)).collect()),
        _ => candle_core::bail!("{name}: f32 or f64 input expected"),
    };
    Ok((out, l.shape().clone()))
}

/// `x` if `x ≤ m`, else `m`; NaN stays NaN (unlike `f32::min`).
#[inline]
fn cap<T: PartialOrd>(x: T, m: T) -> T {
    if x > m {
        m
    } else {
        x
    }
}

struct TruncExp;

impl CustomOp1 for TruncExp {
    fn name(&self) -> &'static str {
        "nf-trunc-exp"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        unary(
            self.name(),
            s,
            l,
            |x| cap(x, TRUNC_EXP_MAX_F32 as f32).exp(),
            |x| cap(x, TRUNC_EXP_MAX_F64).exp(),
        )
    }

    fn bwd(
        &self,
        arg: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        let s = arg
            .clamp(-TRUNC_EXP_GRAD_CLAMP, TRUNC_EXP_GRAD_CLAMP)?
            .exp()?;
        Ok(Some(grad.mul(&s)?))
    }
}

struct Softplus;

/// Stable sigmoid from candle ops: 1/(1+e) for x ≥ 0, e/(1+e) otherwise, e = exp(−|x|).
fn sigmoid_ops(x: &Tensor) -> candle_core::Result<Tensor> {
    let e = x.abs()?.neg()?.exp()?;
    let den = (&e + 1.0)?;
    x.ge(0.0)?.where_cond(&den.recip()?, &(&e / &den)?)
}

impl CustomOp1 for Softplus {
    fn name(&self) -> &'static str {
        "nf-softplus"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        unary(
            self.name(),
            s,
            l,
            |x| x.max(0.0) + (-x.abs()).exp().ln_1p(),
            |x| x.max(0.0) + (-x.abs()).exp().ln_1p(),
        )
    }

    fn bwd(
        &self,
        arg: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        Ok(Some(grad.mul(&sigmoid_ops(arg)?)?))
    }
}

/// Value `value`, gradient `slope` with respect to `x` (any device): the detach trick.
fn with_slope(value: &Tensor, x: &Tensor, slope: &Tensor) -> Result<Tensor> {
    let xs = (x * slope.detach())?;
    let zero = (&xs - xs.detach())?;
    Ok((value.detach() + zero)?)
}

/// Truncated exponential density activation.
///
/// Value: `exp(min(x, m))`, m = [`TRUNC_EXP_MAX_F32`] (f32) or [`TRUNC_EXP_MAX_F64`]
/// (f64), so the value is finite for every finite x. Gradient (by definition, as in
/// nerfstudio): `∂/∂x = exp(clamp(x, −15, 15))` — not the derivative of the value; see
/// the module docs. NaN propagates.
///
/// Shapes: any; f32 or f64; any device (CustomOp on CPU, composed elsewhere).
/// Differentiable (first order) with respect to `x`.
///
/// # Errors
/// `x` when not f32/f64.
pub fn trunc_exp(x: &Tensor) -> Result<Tensor> {
    check_float(x, "x")?;
    if x.device().is_cpu() {
        return Ok(x.contiguous()?.apply_op1(TruncExp)?);
    }
    let m = if x.dtype() == DType::F32 {
        TRUNC_EXP_MAX_F32
    } else {
        TRUNC_EXP_MAX_F64
    };
    let value = x.minimum(m)?.exp()?;
    let slope = x
        .clamp(-TRUNC_EXP_GRAD_CLAMP, TRUNC_EXP_GRAD_CLAMP)?
        .exp()?;
    with_slope(&value, x, &slope)
}

/// Softplus density activation `log(1 + eˣ)`.
///
/// Value: `max(x, 0) + log1p(exp(−|x|))` (finite for all finite x, ≈ eˣ for very
/// negative x, ≈ x for large x). Gradient: `sigmoid(x)` exactly (1/2 at 0), computed
/// without overflow.
///
/// Shapes: any; f32 or f64; any device (CustomOp on CPU, composed elsewhere).
/// Differentiable (first order) with respect to `x`.
///
/// # Errors
/// `x` when not f32/f64.
pub fn softplus(x: &Tensor) -> Result<Tensor> {
    check_float(x, "x")?;
    if x.device().is_cpu() {
        return Ok(x.contiguous()?.apply_op1(Softplus)?);
    }
    let value = crate::numerics::softplus(x, 1.0)?;
    let slope = sigmoid_ops(x)?;
    with_slope(&value, x, &slope)
}
