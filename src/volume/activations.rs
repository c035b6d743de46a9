//! Density activations for NeRF fields: trunc-exp (softplus is
//! [`crate::numerics::softplus`]).
//!
//! Both (trunc-exp and softplus) map a raw network output x ∈ ℝ to a density σ ≥ 0 whose value and gradient are
//! finite for every finite x, so that [`super::composite()`] never sees ∞.
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
use crate::numerics::{map_cpu, with_slope};
use candle_core::{CpuStorage, CustomOp1, DType, Layout, Shape, Tensor};

/// Upper clamp of the trunc-exp argument in f32: e⁸⁸ ≈ 1.65e38 is finite.
pub const TRUNC_EXP_MAX_F32: f64 = 88.0;
/// Upper clamp of the trunc-exp argument in f64: e⁷⁰⁹ ≈ 8.2e307 is finite.
pub const TRUNC_EXP_MAX_F64: f64 = 709.0;
/// The trunc-exp gradient is `exp(clamp(x, −TRUNC_EXP_GRAD_CLAMP, TRUNC_EXP_GRAD_CLAMP))`.
pub const TRUNC_EXP_GRAD_CLAMP: f64 = 15.0;

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
        map_cpu(
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
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::trunc_exp;
///
/// let y = trunc_exp(&Tensor::new(&[0.0f32, 1e3], &Device::Cpu)?)?.to_vec1::<f32>()?;
/// assert_eq!(y[0], 1.0);
/// assert!(y[1].is_finite());                                           // e⁸⁸, not ∞
/// # Ok::<(), neural_fields::Error>(())
/// ```
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
