//! Defended numerics shared by every module: range-reduced sine and cosine, a stable
//! sigmoid, softplus and BCE-with-logits, the trunc-exp density activation with its one
//! gradient rule, a sign-preserving guarded denominator, and
//! [`levenberg_marquardt`], the host-side solver of small nonlinear least-squares
//! problems (camera alignment and registration).
//!
//! The tensor functions are elementwise, follow their input's device and dtype (f32 or f64),
//! and are differentiable with respect to their tensor inputs through candle's autograd,
//! with finite gradients wherever the value is finite. `where_cond` in candle evaluates
//! the gradient of both branches, so each function feeds the untaken branch a safe input
//! instead of relying on the mask (the "double where" trick).

use crate::error::{check_float, check_same, check_same_shape, check_scalar, Result};
use candle_core::{CpuStorage, CustomOp1, DType, Layout, Shape, Tensor};
use rayon::prelude::*;

// 2π split into three parts whose first two have 22 significant bits, so that k·C1 and
// k·C2 are exact in f64 for |k| < 2³¹ (Cody–Waite reduction; see docs/math.md).
const TWO_PI_1: f64 = 6.283_184_051_513_672;
const TWO_PI_2: f64 = 1.255_665_665_667_038_4e-6;
const TWO_PI_3: f64 = 2.489_348_868_758_645_4e-13;

/// Reduces `x` to `r = x − 2πk ∈ [−π, π]` in f64, with `k = round(x / 2π)` detached.
///
/// `dr/dx = 1`, so `sin(r)` has the derivative `cos(x)` of `sin(x)`.
fn reduce_two_pi(x: &Tensor) -> Result<Tensor> {
    let x64 = x.to_dtype(DType::F64)?;
    let k = x64
        .detach()
        .affine(1.0 / std::f64::consts::TAU, 0.0)?
        .round()?;
    let r = ((x64 - k.affine(TWO_PI_1, 0.0)?)? - k.affine(TWO_PI_2, 0.0)?)?;
    Ok((r - k.affine(TWO_PI_3, 0.0)?)?)
}

/// Range-reduced sine and cosine: `(sin(x), cos(x))`, accurate for large `|x|`.
///
/// The argument is reduced once, in f64, by a three-part Cody–Waite reduction,
/// `r = x − k·C₁ − k·C₂ − k·C₃` with `k = round(x/2π)` and `C₁ + C₂ + C₃ = 2π`, before
/// `sin(r)` and `cos(r)` are taken, so both are accurate to about 1e-15 (absolute, before
/// rounding to the input dtype) for `|x| ≤ 10¹⁰`, on every backend — including GPUs whose
/// fast `sin` loses accuracy as the argument grows. An f32 input is reduced exactly as the
/// f32 number it is.
///
/// * `x`: any shape, f32 or f64. Outputs: same shape and dtype.
/// * Differentiable w.r.t. `x`: `d sin/dx = cos(x)`, `d cos/dx = −sin(x)`.
///
/// # Errors
/// `x` not f32/f64.
pub fn safe_sin_cos(x: &Tensor) -> Result<(Tensor, Tensor)> {
    let dtype = check_float(x, "x")?;
    let r = reduce_two_pi(x)?;
    Ok((r.sin()?.to_dtype(dtype)?, r.cos()?.to_dtype(dtype)?))
}

/// Exact reduction for `sin(πx)` and `cos(πx)`: `r = x − 2·round(x/2) ∈ [−1, 1]`.
///
/// The subtraction is exact in the input's own dtype (both operands are within a factor
/// two of each other or `r` is an integer), so no precision is lost however large `x` is.
fn reduce_two(x: &Tensor) -> Result<Tensor> {
    let k2 = x.detach().affine(0.5, 0.0)?.round()?.affine(2.0, 0.0)?;
    Ok((x - k2)?)
}

/// `(sin(πx), cos(πx))` with exact argument reduction in the input dtype.
///
/// Computing `sin(π·x)` naively rounds the product `π·x`, an absolute error of about
/// `|x|·ε` (0.25 rad for f32 at `x = 2²⁰`); here `x` is first reduced exactly, once, to
/// `r = x − 2·round(x/2) ∈ [−1, 1]` and only `π·r` is rounded, so the error stays at
/// a few ulps of 1 for every `x`. This is what makes positional encodings with
/// `2ᵏπx` accurate in f32 (see [`crate::encoding`]).
///
/// * `x`: any shape, f32 or f64. Outputs: same shape and dtype.
/// * Differentiable w.r.t. `x`: `d sin(πx)/dx = π·cos(πx)`, `d cos(πx)/dx = −π·sin(πx)`.
///
/// # Errors
/// `x` not f32/f64.
pub fn sin_cos_pi(x: &Tensor) -> Result<(Tensor, Tensor)> {
    check_float(x, "x")?;
    let r = reduce_two(x)?.affine(std::f64::consts::PI, 0.0)?;
    Ok((r.sin()?, r.cos()?))
}

/// Logistic sigmoid `σ(x) = 1 / (1 + e^{−x})`, computed without overflow.
///
/// With `e = exp(−|x|) ∈ (0, 1]`: `σ(x) = 1/(1+e)` for `x ≥ 0` and `e/(1+e)` otherwise,
/// so neither the value nor the gradient `σ(x)(1 − σ(x))` ever sees an infinity (the
/// naive form overflows `e^{−x}` for `x < −88` in f32 and turns the gradient into NaN).
///
/// * `x`: any shape, f32 or f64. Output: same shape and dtype, in `[0, 1]`.
/// * Differentiable w.r.t. `x`.
///
/// # Errors
/// `x` not f32/f64.
pub fn sigmoid(x: &Tensor) -> Result<Tensor> {
    check_float(x, "x")?;
    let e = x.abs()?.neg()?.exp()?;
    let denom = (&e + 1.0)?;
    let pos = denom.recip()?;
    let neg = (&e / &denom)?;
    Ok(x.ge(0.0)?.where_cond(&pos, &neg)?)
}

/// `log(1 + e^{−|x|})`, the smooth part shared by softplus and BCE; finite everywhere.
fn log1p_exp_neg_abs(x: &Tensor) -> Result<Tensor> {
    Ok((x.abs()?.neg()?.exp()? + 1.0)?.log()?)
}

/// Softplus with sharpness β: `softplus_β(x) = log(1 + e^{βx}) / β`.
///
/// Computed as `max(x, 0) + log1p(e^{−β|x|}) / β`, which neither overflows for large
/// `x` nor loses the tiny value `≈ e^{βx}/β` for very negative `x`. Its derivative is
/// `σ(βx)` (exactly 1/2 at 0). As β → ∞ it tends to ReLU; IDR uses β = 100.
///
/// On the CPU this is one fused pass forward and one backward (a candle `CustomOp1`,
/// several times faster than the composed form in an MLP); elsewhere the same value and
/// gradient are composed from candle ops (the reference the CPU kernel is tested
/// against).
///
/// * `x`: any shape, f32 or f64; `beta > 0` and finite. Output: same shape and dtype.
/// * Differentiable (first order) w.r.t. `x`.
///
/// # Errors
/// `x` not f32/f64; `beta` not finite or ≤ 0.
pub fn softplus(x: &Tensor, beta: f64) -> Result<Tensor> {
    check_float(x, "x")?;
    check_scalar(beta, "beta", true)?;
    if crate::kernels::fused_on(x.device()) {
        return Ok(x.contiguous()?.apply_op1(SoftplusOp { beta })?);
    }
    softplus_reference(x, beta)
}

/// [`softplus`] from candle ops only (any device): value
/// `max(x, 0) + log(1 + e^{−β|x|}) / β` (rounding `1 + e^{−β|x|}` costs an absolute
/// error up to ε/β, which the CPU kernel's `log1p` avoids), gradient the stable [`sigmoid`] of βx attached
/// with the detach trick (the same gradient formula as the CPU kernel, rather than
/// whatever candle's `relu`/`abs` derivatives compose to). What [`softplus`] runs off
/// the CPU; public so that the CPU kernel can be checked against it.
///
/// # Errors
/// As [`softplus`].
pub(crate) fn softplus_reference(x: &Tensor, beta: f64) -> Result<Tensor> {
    check_float(x, "x")?;
    check_scalar(beta, "beta", true)?;
    let value = (x.relu()? + log1p_exp_neg_abs(&x.affine(beta, 0.0)?)?.affine(1.0 / beta, 0.0)?)?;
    let slope = sigmoid(&x.affine(beta, 0.0)?)?;
    with_slope(&value, x, &slope)
}

/// A tensor with the value of `value` whose gradient with respect to `x` is `slope`
/// (elementwise), on any device: `value.detach() + (x·s − (x·s).detach())` with `s`
/// detached.
pub(crate) fn with_slope(value: &Tensor, x: &Tensor, slope: &Tensor) -> Result<Tensor> {
    let xs = (x * slope.detach())?;
    let zero = (&xs - xs.detach())?;
    Ok((value.detach() + zero)?)
}

/// `f` of every element, in parallel over blocks of 4096 (rayon).
fn par_map<T: Copy + Send + Sync, F: Fn(T) -> T + Sync>(v: &[T], f: F) -> Vec<T> {
    v.par_iter().with_min_len(4096).map(|&x| f(x)).collect()
}

/// Applies `f32op`/`f64op` to every element of a contiguous CPU f32/f64 storage.
pub(crate) fn map_cpu<F32: Fn(f32) -> f32 + Sync, F64: Fn(f64) -> f64 + Sync>(
    name: &str,
    s: &CpuStorage,
    l: &Layout,
    f32op: F32,
    f64op: F64,
) -> candle_core::Result<(CpuStorage, Shape)> {
    let Some((a, b)) = l.contiguous_offsets() else {
        candle_core::bail!("{name}: inputs must be contiguous")
    };
    let out = match s {
        CpuStorage::F32(v) => CpuStorage::F32(par_map(&v[a..b], f32op)),
        CpuStorage::F64(v) => CpuStorage::F64(par_map(&v[a..b], f64op)),
        _ => candle_core::bail!("{name}: f32 or f64 input expected"),
    };
    Ok((out, l.shape().clone()))
}

/// Rounds to the nearest integer (ties to even) without a call or a branch that stops
/// vectorisation: adding and subtracting `1.5·2⁵²` is exact below 2⁵¹ in magnitude, and
/// larger doubles are already integers and pass through unchanged; NaN stays NaN.
#[inline(always)]
pub(crate) fn round_to_integer(v: f64) -> f64 {
    const SHIFT: f64 = 6_755_399_441_055_744.0; // 1.5 · 2⁵²
    const BIG: f64 = 2_251_799_813_685_248.0; // 2⁵¹
    let r = (v + SHIFT) - SHIFT;
    if v.abs() < BIG {
        r
    } else {
        v
    }
}

/// Scalar stable sigmoid (as [`sigmoid`]).
macro_rules! scalar_sigmoid {
    ($z:expr) => {{
        let z = $z;
        let e = (-z.abs()).exp();
        if z >= 0.0 {
            1.0 / (1.0 + e)
        } else {
            e / (1.0 + e)
        }
    }};
}

/// Scalar softplus_β (as [`softplus`]); NaN propagates.
macro_rules! scalar_softplus {
    ($x:expr, $beta:expr) => {{
        let (x, beta) = ($x, $beta);
        let relu = if x > 0.0 { x } else { x * 0.0 };
        relu + (-(beta * x).abs()).exp().ln_1p() / beta
    }};
}
#[cfg_attr(not(feature = "volume"), allow(unused_imports))] // used by the fused NeRF loss
pub(crate) use {scalar_sigmoid, scalar_softplus};

/// CPU kernel of [`softplus`].
struct SoftplusOp {
    beta: f64,
}

impl CustomOp1 for SoftplusOp {
    fn name(&self) -> &'static str {
        "nf-softplus"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let (b32, b64) = (self.beta as f32, self.beta);
        map_cpu(
            self.name(),
            s,
            l,
            |x| scalar_softplus!(x, b32),
            |x| scalar_softplus!(x, b64),
        )
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        crate::kernels::cuda::map("nf_softplus", s, l, Some(self.beta))
    }

    fn bwd(
        &self,
        arg: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        let slope = arg.apply_op1_no_bwd(&SigmoidOfScaled { beta: self.beta })?;
        Ok(Some(grad.mul(&slope)?))
    }
}

/// `σ(βx)` on the CPU, the derivative of softplus_β (not itself differentiated).
struct SigmoidOfScaled {
    beta: f64,
}

impl CustomOp1 for SigmoidOfScaled {
    fn name(&self) -> &'static str {
        "nf-sigmoid-of-scaled"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let (b32, b64) = (self.beta as f32, self.beta);
        map_cpu(
            self.name(),
            s,
            l,
            |x| scalar_sigmoid!(b32 * x),
            |x| scalar_sigmoid!(b64 * x),
        )
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        crate::kernels::cuda::map("nf_sigmoid_scaled", s, l, Some(self.beta))
    }
}

/// Upper clamp of the trunc-exp argument in f32: e⁸⁸ ≈ 1.65e38 is finite.
pub const TRUNC_EXP_MAX_F32: f64 = 88.0;
/// Upper clamp of the trunc-exp argument in f64: e⁷⁰⁹ ≈ 8.2e307 is finite.
pub const TRUNC_EXP_MAX_F64: f64 = 709.0;
/// The trunc-exp gradient is `exp(clamp(x, −TRUNC_EXP_GRAD_CLAMP, TRUNC_EXP_GRAD_CLAMP))`.
pub const TRUNC_EXP_GRAD_CLAMP: f64 = 15.0;

/// The element types of [`trunc_exp`]'s scalar rule, each with its own cap.
pub(crate) trait TruncExpScalar: Copy + PartialOrd {
    /// [`TRUNC_EXP_MAX_F32`] or [`TRUNC_EXP_MAX_F64`] in this type.
    const CAP: Self;
    /// [`TRUNC_EXP_GRAD_CLAMP`] in this type.
    const GRAD_CLAMP: Self;
    fn exp(self) -> Self;
    fn neg(self) -> Self;
}

impl TruncExpScalar for f32 {
    const CAP: f32 = TRUNC_EXP_MAX_F32 as f32;
    const GRAD_CLAMP: f32 = TRUNC_EXP_GRAD_CLAMP as f32;
    #[inline(always)]
    fn exp(self) -> f32 {
        f32::exp(self)
    }
    #[inline(always)]
    fn neg(self) -> f32 {
        -self
    }
}

impl TruncExpScalar for f64 {
    const CAP: f64 = TRUNC_EXP_MAX_F64;
    const GRAD_CLAMP: f64 = TRUNC_EXP_GRAD_CLAMP;
    #[inline(always)]
    fn exp(self) -> f64 {
        f64::exp(self)
    }
    #[inline(always)]
    fn neg(self) -> f64 {
        -self
    }
}

/// [`trunc_exp`]'s value at one element: `exp(min(x, cap))` with the cap of `x`'s type,
/// computed in that type; NaN stays NaN (unlike `f32::min`).
#[inline(always)]
pub(crate) fn trunc_exp_value<T: TruncExpScalar>(x: T) -> T {
    if x > T::CAP {
        T::CAP.exp()
    } else {
        x.exp()
    }
}

/// [`trunc_exp`]'s gradient rule at one element: `exp(clamp(x, −15, 15))`, computed in
/// `x`'s type; NaN stays NaN.
#[inline(always)]
pub(crate) fn trunc_exp_slope<T: TruncExpScalar>(x: T) -> T {
    let c = if x > T::GRAD_CLAMP {
        T::GRAD_CLAMP
    } else if x < T::GRAD_CLAMP.neg() {
        T::GRAD_CLAMP.neg()
    } else {
        x
    };
    c.exp()
}

/// CPU kernel of [`trunc_exp`].
struct TruncExpOp;

impl CustomOp1 for TruncExpOp {
    fn name(&self) -> &'static str {
        "nf-trunc-exp"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        map_cpu(
            self.name(),
            s,
            l,
            trunc_exp_value::<f32>,
            trunc_exp_value::<f64>,
        )
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        crate::kernels::cuda::map("nf_trunc_exp", s, l, None)
    }

    fn bwd(
        &self,
        arg: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        // The gradient rule (`trunc_exp_slope`) in candle ops, which run on candle's own
        // CPU pool inside the backward pass.
        let slope = arg
            .clamp(-TRUNC_EXP_GRAD_CLAMP, TRUNC_EXP_GRAD_CLAMP)?
            .exp()?;
        Ok(Some(grad.mul(&slope)?))
    }
}

/// Truncated exponential, the density activation of instant-NGP and nerfacto.
///
/// Value: `exp(min(x, m))`, m = [`TRUNC_EXP_MAX_F32`] (f32) or [`TRUNC_EXP_MAX_F64`]
/// (f64), so the value is finite for every finite x (e⁸⁸ ≈ 1.65e38 < f32::MAX). Gradient,
/// by definition (nerfstudio's trunc-exp, which removed NaNs that appeared after 50–80k
/// training steps): `∂/∂x = exp(clamp(x, −15, 15))` ([`TRUNC_EXP_GRAD_CLAMP`]) — not the
/// derivative of the value: it is bounded by e¹⁵ ≈ 3.3e6, and it is e⁻¹⁵ rather than ≈ 0
/// for very negative x, so empty space keeps a small gradient. NaN propagates.
///
/// This is the one definition of the rule: the NeRF model and its fused colour loss
/// evaluate the same value and slope.
///
/// Shapes: any; f32 or f64, computed in the input's dtype; any device (one fused pass on
/// the CPU; elsewhere the same value and gradient composed from candle ops, with the
/// gradient attached by the detach trick `v.detach() + (x·s − (x·s).detach())`).
/// Differentiable (first order) with respect to `x`.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::numerics::trunc_exp;
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
    if crate::kernels::fused_on(x.device()) {
        return Ok(x.contiguous()?.apply_op1(TruncExpOp)?);
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

/// Binary cross-entropy on logits, elementwise, finite for any finite logit.
///
/// `ℓ(x, y) = −y·log σ(x) − (1 − y)·log(1 − σ(x)) = max(x, 0) − x·y + log(1 + e^{−|x|})`.
///
/// candle-nn's `binary_cross_entropy_with_logit` evaluates `log(σ(x))`, which is `−∞`
/// for logits below about −88 (f32) and makes the loss and its gradient non-finite; this
/// form stays finite for logits of ±10⁴ and beyond, with gradient `∂ℓ/∂x = σ(x) − y`.
///
/// * `logits`, `targets`: same shape, same f32/f64 dtype and device; targets in `[0, 1]`
///   (soft labels allowed). Output: elementwise loss, same shape. Reduce it yourself
///   (ONet sums over the points of a shape and averages over shapes).
/// * Differentiable w.r.t. `logits` and `targets`.
///
/// # Errors
/// Mismatched shapes, dtypes or devices (naming `targets`), non-float input.
pub fn bce_with_logits(logits: &Tensor, targets: &Tensor) -> Result<Tensor> {
    check_float(logits, "logits")?;
    check_same(targets, "targets", logits, "logits")?;
    check_same_shape(targets, "targets", logits, "logits")?;
    let linear = (logits.relu()? - (logits * targets)?)?;
    Ok((linear + log1p_exp_neg_abs(logits)?)?)
}

/// Sign-preserving guarded denominator: `x` where `|x| ≥ eps`, else `eps·sgn(x)` with
/// `sgn(0) = +1`.
///
/// DVR's reference replaces small `|∇f·w|` by `+eps`, which flips the sign of the
/// implicit gradient for rays that meet the surface from behind; this guard keeps the
/// sign, so `1/guard(x)` is bounded by `1/eps` and has the sign of `x`.
///
/// * `x`: any shape, f32 or f64; `eps > 0`. Output: same shape and dtype.
/// * Differentiable w.r.t. `x` where `|x| ≥ eps` (zero gradient inside the guard band).
///
/// # Errors
/// `x` not f32/f64; `eps` not finite or ≤ 0.
#[cfg_attr(not(feature = "dvr"), allow(dead_code))] // the implicit surface gradient
pub(crate) fn guard_denominator(x: &Tensor, eps: f64) -> Result<Tensor> {
    check_float(x, "x")?;
    check_scalar(eps, "eps", true)?;
    let sign = x
        .ge(0.0)?
        .where_cond(&x.ones_like()?, &x.ones_like()?.neg()?)?;
    let small = x.abs()?.lt(eps)?;
    Ok(small.where_cond(&sign.affine(eps, 0.0)?, x)?)
}

/// One Levenberg–Marquardt step: the `δ` that solves `(H + λ·D)·δ = −g`, with
/// `D = diag(H)` (Marquardt's scaling, each diagonal entry at least `10⁻¹²·max diag(H)`
/// so that a parameter without signal stays put instead of making the system singular),
/// by a Cholesky factorisation.
///
/// `H` is a Gauss–Newton matrix `Σ jⱼ jⱼᵀ` (symmetric, positive semi-definite; only its
/// lower triangle is read) and `g = Σ jⱼ rⱼ` the gradient of `½ Σ rⱼ²`; `λ ≥ 0` trades a
/// Gauss–Newton step (`λ → 0`) for a short scaled gradient step (`λ → ∞`). Plain `f64`
/// arrays: one small system per camera or per object, not a tensor op. The step of
/// [`levenberg_marquardt`].
///
/// Returns `None` when `H` has no positive diagonal entry, an entry or `λ` is not
/// finite, `λ < 0`, or the damped matrix is not positive definite.
#[must_use]
pub(crate) fn damped_solve<const N: usize>(
    h: &[[f64; N]; N],
    g: &[f64; N],
    lambda: f64,
) -> Option<[f64; N]> {
    if !(lambda >= 0.0 && lambda.is_finite()) {
        return None;
    }
    let finite = h.iter().flatten().chain(g).all(|x| x.is_finite());
    let top = (0..N).map(|i| h[i][i]).fold(0.0f64, f64::max);
    if !finite || top <= 0.0 {
        return None;
    }
    // Lower-triangular L with L Lᵀ = H + λ D.
    let mut l = [[0.0f64; N]; N];
    for i in 0..N {
        for j in 0..=i {
            let mut s = h[i][j];
            if i == j {
                s += lambda * h[i][i].max(1e-12 * top);
            }
            s -= (0..j).map(|k| l[i][k] * l[j][k]).sum::<f64>();
            if i == j {
                if s.is_nan() || s <= 0.0 {
                    return None;
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    // L y = −g, then Lᵀ δ = y.
    let mut y = [0.0f64; N];
    for i in 0..N {
        let s = (0..i).fold(-g[i], |s, k| s - l[i][k] * y[k]);
        y[i] = s / l[i][i];
    }
    let mut x = [0.0f64; N];
    for i in (0..N).rev() {
        let s = (i + 1..N).fold(y[i], |s, k| s - l[k][i] * x[k]);
        x[i] = s / l[i][i];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// The settings of [`levenberg_marquardt`]: the damping schedule, the iteration budget,
/// the stopping tolerance and an optional robust loss. The defaults suit a converging
/// fit of a few parameters (camera alignment); a registration that runs a fixed budget
/// sets `tolerance` to 0 and its own `iterations`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LmConfig {
    /// Trial steps at most, accepted or refused; 100.
    pub iterations: usize,
    /// The starting damping `λ₀`; 1e-3.
    pub lambda: f64,
    /// `λ` is multiplied by this after an accepted step, in `(0, 1)`; ⅓.
    pub shrink: f64,
    /// `λ` is multiplied by this after a refused step, > 1; 4.
    pub grow: f64,
    /// The floor of `λ`; 1e-9.
    pub lambda_min: f64,
    /// The solver stops once `λ` exceeds this (no step lowers the cost); 1e12.
    pub lambda_max: f64,
    /// The solver stops after an accepted step that lowers the cost by at most this
    /// fraction of it; 1e-12 (0: only the budget and `lambda_max` stop it).
    pub tolerance: f64,
    /// Huber's threshold `k` on each residual (`None`: least squares, the default).
    pub huber: Option<f64>,
}

impl Default for LmConfig {
    fn default() -> Self {
        Self {
            iterations: 100,
            lambda: 1e-3,
            shrink: 1.0 / 3.0,
            grow: 4.0,
            lambda_min: 1e-9,
            lambda_max: 1e12,
            tolerance: 1e-12,
            huber: None,
        }
    }
}

/// The normal equations `H = Σ wᵢ jᵢ jᵢᵀ`, `g = Σ wᵢ jᵢ rᵢ` of residuals `rᵢ` with
/// Jacobian rows `jᵢ` and their cost `Σ ρ(rᵢ)`: `ρ(r) = ½r²`, or under Huber's loss of
/// threshold `k`, `½r²` for `|r| ≤ k` and `k(|r| − ½k)` beyond, with the iteratively
/// reweighted least-squares weight `w = min(1, k/|r|)` (1 without a threshold).
pub(crate) struct NormalEquations<const N: usize> {
    pub(crate) h: [[f64; N]; N],
    pub(crate) g: [f64; N],
    pub(crate) cost: f64,
}

impl<const N: usize> NormalEquations<N> {
    /// The equations of `residuals` (one Jacobian row each) under `huber`.
    pub(crate) fn new(residuals: &[f64], jacobian: &[[f64; N]], huber: Option<f64>) -> Self {
        let mut e = Self {
            h: [[0.0; N]; N],
            g: [0.0; N],
            cost: 0.0,
        };
        for (&r, j) in residuals.iter().zip(jacobian) {
            let (w, rho) = robust(r, huber);
            e.cost += rho;
            for p in 0..N {
                e.g[p] += w * j[p] * r;
                for q in 0..=p {
                    e.h[p][q] += w * j[p] * j[q];
                }
            }
        }
        for p in 0..N {
            for q in p + 1..N {
                e.h[p][q] = e.h[q][p];
            }
        }
        e
    }
}

/// The weight and cost `(w, ρ(r))` of residual `r` (see [`NormalEquations`]).
fn robust(r: f64, huber: Option<f64>) -> (f64, f64) {
    match huber {
        Some(k) if r.abs() > k => (k / r.abs(), k * (r.abs() - 0.5 * k)),
        _ => (1.0, 0.5 * r * r),
    }
}

/// The cost `Σ ρ(rᵢ)` of `residuals` under `huber` (see [`NormalEquations`]).
pub(crate) fn robust_cost(residuals: &[f64], huber: Option<f64>) -> f64 {
    residuals.iter().map(|&r| robust(r, huber).1).sum()
}

/// Minimises `Σ ρ(rᵢ(x))` over a state `x` with `N` local parameters by Levenberg–Marquardt:
/// at the current state, the residuals `r` and their Jacobian `J` w.r.t. a step `δ` of the
/// state's local chart (`linearize`) give the normal equations `H = JᵀWJ`, `g = JᵀWr`
/// (`W` Huber's reweighting, the identity without `config.huber`); the trial step solves
/// `(H + λ·diag H)·δ = −g` (Marquardt's scaling, a Cholesky factorisation), and the trial
/// state `retract(x, δ)` is accepted if its cost is lower (`λ ← max(λ·shrink,
/// lambda_min)`), else refused (`λ ← λ·grow`). It stops after `config.iterations` trials,
/// when `λ` exceeds `lambda_max`, or after an accepted step that lowers the cost by at most
/// `tolerance` of it. Returns the last accepted state and its cost (the start, with an
/// infinite cost, if `linearize` returns `None` there).
///
/// `linearize(x)` returns `Ok(None)` for a state where the residuals are not defined (a
/// point behind a camera): a trial step there is refused. The number of residuals may
/// differ between states. Plain `f64` on the host: one small problem per camera or per
/// scene (`N` of 6 or 7), not a tensor op; nothing here is differentiable.
///
/// ```
/// use neural_fields::numerics::{levenberg_marquardt, LmConfig};
///
/// // Fit y = a·exp(b·t) to exact samples of a = 2, b = −1, from a = 1, b = 0.
/// let t: Vec<f64> = (0..10).map(|i| i as f64 / 3.0).collect();
/// let y: Vec<f64> = t.iter().map(|t| 2.0 * (-t).exp()).collect();
/// let (fit, cost) = levenberg_marquardt(
///     [1.0, 0.0],
///     &LmConfig::default(),
///     |p: &[f64; 2]| {
///         let r = t.iter().zip(&y).map(|(t, y)| p[0] * (p[1] * t).exp() - y).collect();
///         let j = t.iter().map(|t| [(p[1] * t).exp(), p[0] * t * (p[1] * t).exp()]).collect();
///         Ok(Some((r, j)))
///     },
///     |p, d| [p[0] + d[0], p[1] + d[1]],
/// )?;
/// assert!((fit[0] - 2.0).abs() < 1e-6 && (fit[1] + 1.0).abs() < 1e-6 && cost < 1e-12);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`crate::Error::InvalidArgument`] naming `config` unless `lambda` and `lambda_min` are
/// finite and > 0, `lambda_max ≥ lambda`, `shrink` in `(0, 1)`, `grow` finite and > 1,
/// `tolerance` finite and ≥ 0 and `huber`, if set, finite and > 0; `linearize` if it
/// returns a Jacobian with a row count other than the residuals'; and whatever
/// `linearize` returns.
pub fn levenberg_marquardt<S, const N: usize>(
    start: S,
    config: &LmConfig,
    mut linearize: impl FnMut(&S) -> Result<Option<(Vec<f64>, Vec<[f64; N]>)>>,
    mut retract: impl FnMut(&S, &[f64; N]) -> S,
) -> Result<(S, f64)> {
    let c = config;
    let positive = |x: f64| x > 0.0 && x.is_finite();
    if !(positive(c.lambda)
        && positive(c.lambda_min)
        && c.lambda_max >= c.lambda
        && c.shrink > 0.0
        && c.shrink < 1.0
        && c.grow > 1.0
        && c.grow.is_finite()
        && c.tolerance >= 0.0
        && c.tolerance.is_finite()
        && c.huber.is_none_or(positive))
    {
        return Err(crate::Error::invalid(
            "config",
            "λ, λ_min > 0, λ_max ≥ λ, shrink in (0, 1), grow > 1, tolerance ≥ 0, huber > 0",
            format!("{c:?}"),
        ));
    }
    let mut equations = |x: &S| -> Result<Option<NormalEquations<N>>> {
        let Some((r, j)) = linearize(x)? else {
            return Ok(None);
        };
        if r.len() != j.len() {
            return Err(crate::Error::invalid(
                "linearize",
                format!("a Jacobian row per residual ({})", r.len()),
                format!("{} rows", j.len()),
            ));
        }
        Ok(Some(NormalEquations::new(&r, &j, c.huber)))
    };
    let Some(mut current) = equations(&start)? else {
        return Ok((start, f64::INFINITY));
    };
    let mut state = start;
    let mut lambda = c.lambda;
    for _ in 0..c.iterations {
        if lambda > c.lambda_max {
            break;
        }
        if let Some(step) = damped_solve(&current.h, &current.g, lambda) {
            let trial = retract(&state, &step);
            if let Some(next) = equations(&trial)? {
                if next.cost < current.cost {
                    let decrease = current.cost - next.cost;
                    let before = current.cost;
                    (state, current) = (trial, next);
                    lambda = (lambda * c.shrink).max(c.lambda_min);
                    if decrease <= c.tolerance * before {
                        break;
                    }
                    continue;
                }
            }
        }
        lambda *= c.grow;
    }
    Ok((state, current.cost))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    use crate::test_host::v64 as vec64;

    /// The gradient of `v` in `g`, or an error naming it.
    fn grad<'a>(g: &'a candle_core::backprop::GradStore, v: &Var) -> Result<&'a Tensor> {
        g.get(v)
            .ok_or_else(|| crate::Error::invalid("v", "a variable of the graph", "no gradient"))
    }

    #[test]
    fn safe_sin_is_accurate_for_huge_f32_arguments() -> Result<()> {
        let xs: Vec<f32> = vec![0.0, 1.0, -3.5, 1e4, 3.3e7, -7.77e8, 1e10, -1e10, 123456.78];
        let t = Tensor::new(xs.as_slice(), &Device::Cpu)?;
        let (s, c) = safe_sin_cos(&t)?;
        let (s, c) = (vec64(&s), vec64(&c));
        for (i, &x) in xs.iter().enumerate() {
            let x = f64::from(x);
            assert!(
                (s[i] - x.sin()).abs() < 1e-6,
                "sin({x}): {} vs {}",
                s[i],
                x.sin()
            );
            assert!(
                (c[i] - x.cos()).abs() < 1e-6,
                "cos({x}): {} vs {}",
                c[i],
                x.cos()
            );
        }
        Ok(())
    }

    #[test]
    fn sin_pi_of_large_integers_is_zero() -> Result<()> {
        let t = Tensor::new(&[1e6f32, 2f32.powi(20) + 1.0, 3.0], &Device::Cpu)?;
        for v in vec64(&sin_cos_pi(&t)?.0) {
            assert!(v.abs() < 1e-6, "{v}");
        }
        Ok(())
    }

    #[test]
    fn bce_with_logits_is_finite_with_finite_gradients_for_extreme_logits() -> Result<()> {
        let x = Var::new(&[-1e4f32, -100.0, 0.0, 100.0, 1e4], &Device::Cpu)?;
        let y = Tensor::new(&[1f32, 1.0, 0.5, 0.0, 0.0], &Device::Cpu)?;
        let l = bce_with_logits(x.as_tensor(), &y)?;
        let lv = vec64(&l);
        assert!(
            (lv[0] - 1e4).abs() < 1e-2 && (lv[4] - 1e4).abs() < 1e-2,
            "{lv:?}"
        );
        assert!((lv[2] - std::f64::consts::LN_2).abs() < 1e-6);
        let g = vec64(grad(&l.sum_all()?.backward()?, &x)?);
        let expected = [-1.0, -1.0, 0.0, 1.0, 1.0];
        for (a, b) in g.iter().zip(expected) {
            assert!((a - b).abs() < 1e-6, "{g:?}");
        }
        Ok(())
    }

    #[test]
    fn sigmoid_gradient_is_finite_far_out() -> Result<()> {
        let x = Var::new(&[-1e3f32, -90.0, 0.0, 90.0, 1e3], &Device::Cpu)?;
        let s = sigmoid(x.as_tensor())?;
        let g = vec64(grad(&s.sum_all()?.backward()?, &x)?);
        assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
        assert!((g[2] - 0.25).abs() < 1e-7);
        Ok(())
    }

    /// `guard_denominator` at f32's extremes: finite values and gradients.
    #[test]
    fn guard_is_finite_with_finite_gradients_at_f32_extremes() -> Result<()> {
        let xs = [-1e30f32, -1e4, -88.7, -1e-30, 0.0, 1e-30, 88.7, 1e4, 1e30];
        let v = Var::new(&xs, &Device::Cpu)?;
        let y = guard_denominator(v.as_tensor(), 1e-3)?;
        assert!(vec64(&y).iter().all(|a| a.is_finite()), "{:?}", vec64(&y));
        let g = vec64(grad(&y.sum_all()?.backward()?, &v)?);
        assert!(g.iter().all(|a| a.is_finite()), "{g:?}");
        Ok(())
    }

    /// `guard_denominator` refuses integer input naming `x` and a NaN `eps` naming `eps`.
    #[test]
    fn guard_names_bad_arguments() {
        let d = Device::Cpu;
        let ints = Tensor::new(&[1u32, 2], &d).unwrap();
        let x = Tensor::new(&[1f32, 2.0], &d).unwrap();
        let e = guard_denominator(&ints, 1e-3).unwrap_err().to_string();
        assert!(e.starts_with("x: expected dtype f32 or f64"), "{e}");
        assert!(guard_denominator(&x, f64::NAN)
            .unwrap_err()
            .to_string()
            .starts_with("eps"));
    }

    /// The guard bounds `1/x` by `1/eps` and its derivative by `1/eps²`: both finite for
    /// values from 0 to the dtype's largest, in f32 and f64, while `1/eps²` is
    /// representable (≥ 5.4e-20 in f32, the caller's choice).
    #[test]
    fn guarded_reciprocals_stay_finite_at_every_magnitude() -> Result<()> {
        for dtype in [DType::F32, DType::F64] {
            let (big, tiny, tiny_eps) = if dtype == DType::F32 {
                (f64::from(f32::MAX), f64::from(f32::MIN_POSITIVE), 1e-19)
            } else {
                (f64::MAX, f64::MIN_POSITIVE, 1e-150)
            };
            let values = [
                0.0, tiny, -tiny, 1e-30, -1e-30, 1.0, -1.0, 1e30, -1e30, big, -big,
            ];
            let t = Tensor::new(&values, &Device::Cpu)?.to_dtype(dtype)?;
            let x = Var::from_tensor(&t)?;
            for eps in [tiny_eps, 1e-3, 1.0] {
                let y = guard_denominator(x.as_tensor(), eps)?.recip()?;
                assert!(
                    vec64(&y).iter().all(|a| a.is_finite()),
                    "{dtype:?}, eps = {eps}: {:?}",
                    vec64(&y)
                );
                let g = vec64(grad(&y.sum_all()?.backward()?, &x)?);
                assert!(
                    g.iter().all(|a| a.is_finite()),
                    "{dtype:?}, eps = {eps}: gradient {g:?}"
                );
            }
        }
        Ok(())
    }

    #[test]
    fn guard_keeps_the_sign() -> Result<()> {
        let x = Tensor::new(&[-1e-9f64, 0.0, 1e-9, -2.0, 3.0], &Device::Cpu)?;
        let g = vec64(&guard_denominator(&x, 1e-3)?);
        assert_eq!(g, vec![-1e-3, 1e-3, 1e-3, -2.0, 3.0]);
        Ok(())
    }

    /// The CPU softplus kernel and the candle-op reference both match the exact value
    /// (computed in f64) and the exact gradient σ(βx), f32 and f64, for β from 1e-3 to 1e6
    /// and x from −1e30 to 1e30, including x = 0 (gradient exactly 1/2). The kernel is
    /// accurate to a few ulps of the value; the reference's `log(1 + e^{−β|x|})` rounds
    /// `1 + tiny`, an absolute error of ε/β that the kernel's `log1p` does not have.
    #[test]
    fn softplus_kernel_matches_the_candle_op_reference() -> Result<()> {
        let xs = [
            -1e30, -1e4, -700.0, -88.0, -30.0, -1.0, -1e-3, -1e-30, 0.0, 1e-30, 1e-3, 0.5, 1.0,
            30.0, 88.0, 700.0, 1e4, 1e30,
        ];
        for dt in [DType::F32, DType::F64] {
            let (eps, floor) = if dt == DType::F32 {
                (f32::EPSILON as f64, 1e-37)
            } else {
                (f64::EPSILON, 1e-300)
            };
            for beta in [1e-3, 0.5, 1.0, 100.0, 1e6] {
                let run = |f: fn(&Tensor, f64) -> Result<Tensor>| -> Result<(Vec<f64>, Vec<f64>)> {
                    let x = Tensor::new(&xs, &Device::Cpu)?.to_dtype(dt)?;
                    let v = Var::from_tensor(&x)?;
                    let y = f(v.as_tensor(), beta)?;
                    let g = y.sum_all()?.backward()?;
                    Ok((vec64(&y), vec64(grad(&g, &v)?)))
                };
                let (yk, gk) = run(softplus)?;
                let (yr, gr) = run(softplus_reference)?;
                for (i, &x) in xs.iter().enumerate() {
                    let z = beta * x;
                    let exact = x.max(0.0) + (-z.abs()).exp().ln_1p() / beta;
                    let slope = if z >= 0.0 {
                        1.0 / (1.0 + (-z).exp())
                    } else {
                        z.exp() / (1.0 + z.exp())
                    };
                    let case = format!("{dt:?} β = {beta}, x = {x}");
                    let tol = 8.0 * eps * exact.abs() + floor;
                    assert!(
                        (yk[i] - exact).abs() <= tol,
                        "{case}: kernel {} vs {exact}",
                        yk[i]
                    );
                    assert!(
                        (yr[i] - exact).abs() <= tol + 2.0 * eps / beta,
                        "{case}: reference {} vs {exact}",
                        yr[i]
                    );
                    for (name, g) in [("kernel", gk[i]), ("reference", gr[i])] {
                        assert!(
                            (g - slope).abs() <= 8.0 * eps * slope + floor,
                            "{case}: {name} gradient {g} vs {slope}"
                        );
                    }
                }
            }
        }
        Ok(())
    }

    /// The reference softplus's (β = 100) autograd gradient at `x` and its central
    /// difference.
    fn reference_gradient_and_difference(x: f64) -> Result<(f64, f64)> {
        let v = Var::new(&[x], &Device::Cpu)?;
        let y = softplus_reference(v.as_tensor(), 100.0)?;
        let g = vec64(grad(&y.sum_all()?.backward()?, &v)?)[0];
        let f = |s: f64| -> Result<f64> {
            Ok(vec64(&softplus_reference(
                &Tensor::new(&[s], &Device::Cpu)?,
                100.0,
            )?)[0])
        };
        let h = 1e-6 * x.abs().max(1e-2);
        Ok((g, (f(x + h)? - f(x - h)?) / (2.0 * h)))
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]

        /// The reference path's gradient (candle's autograd through the composed ops)
        /// equals a central difference, over |x| up to 1e3 at β = 100.
        #[test]
        fn softplus_reference_gradient_matches_finite_differences(x in -1e3f64..1e3) {
            let (g, fd) = reference_gradient_and_difference(x)
                .map_err(|e| proptest::test_runner::TestCaseError::fail(e.to_string()))?;
            proptest::prop_assert!(g.is_finite());
            proptest::prop_assert!((g - fd).abs() <= 1e-5 * g.abs().max(fd.abs()).max(1e-3), "at {}: {} vs {}", x, g, fd);
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]

    /// With λ = 0 the step solves the normal equations; a larger λ gives a shorter step
    /// that tends to the scaled gradient step −g/(λ·diag H). Systems scaled by 1e±100.
    #[test]
    fn damped_solve_solves_the_damped_normal_equations(seed in 0u64..10_000, log_scale in -100.0f64..100.0) {
        let mut rng = crate::rng::SplitMix64::new(seed);
        let scale = 10f64.powf(log_scale);
        let rows: Vec<[f64; 6]> = (0..10).map(|_| std::array::from_fn(|_| rng.normal())).collect();
        let r: Vec<f64> = (0..10).map(|_| rng.normal()).collect();
        let mut h = [[0.0; 6]; 6];
        let mut g = [0.0; 6];
        for (j, &ri) in rows.iter().zip(&r) {
            for p in 0..6 {
                g[p] += j[p] * ri * scale;
                for q in 0..6 {
                    h[p][q] += j[p] * j[q] * scale;
                }
            }
        }
        let x = damped_solve(&h, &g, 0.0).unwrap();
        let gmax = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for p in 0..6 {
            let hx: f64 = (0..6).map(|q| h[p][q] * x[q]).sum();
            proptest::prop_assert!((hx + g[p]).abs() < 1e-9 * gmax, "row {}: {} vs {}", p, hx, -g[p]);
        }
        let norm = |v: &[f64; 6]| v.iter().map(|a| a * a).sum::<f64>().sqrt();
        let damped = damped_solve(&h, &g, 1.0).unwrap();
        proptest::prop_assert!(norm(&damped) < norm(&x));
        let lambda = 1e8;
        let far = damped_solve(&h, &g, lambda).unwrap();
        let gradient_step: [f64; 6] = std::array::from_fn(|p| -g[p] / (lambda * h[p][p]));
        for p in 0..6 {
            proptest::prop_assert!((far[p] - gradient_step[p]).abs() < 1e-6 * norm(&gradient_step));
        }
    }
    }

    /// ½|J x − b|² with J = diag(2, 4), b = (2, 4): the Gauss–Newton step from x = 0 is
    /// (1, 1), and λ = 1 doubles the diagonal: half the step.
    #[test]
    fn damped_solve_takes_the_gauss_newton_step_and_its_damped_half() {
        let h = [[4.0, 0.0], [0.0, 16.0]];
        let g = [-4.0, -16.0];
        assert_eq!(damped_solve(&h, &g, 0.0), Some([1.0, 1.0]));
        let half = damped_solve(&h, &g, 1.0);
        assert!(half.is_some_and(|x| x.iter().all(|x| (x - 0.5).abs() < 1e-15)));
        assert_eq!(damped_solve(&[[0.0; 2]; 2], &g, 1.0), None);
    }

    #[test]
    fn damped_solve_refuses_what_it_cannot_solve() {
        assert_eq!(damped_solve(&[[1.0]], &[1.0], -1.0), None);
        assert_eq!(damped_solve(&[[1.0]], &[1.0], f64::NAN), None);
        assert_eq!(damped_solve(&[[1.0]], &[f64::NAN], 1.0), None);
        assert_eq!(damped_solve(&[[0.0]], &[1.0], 1.0), None);
        // Indefinite: not a Gauss–Newton matrix.
        assert_eq!(
            damped_solve(&[[1.0, 2.0], [2.0, 1.0]], &[1.0, 1.0], 0.0),
            None
        );
        // A parameter without signal stays put instead of making the system singular.
        let step = damped_solve(&[[2.0, 0.0], [0.0, 0.0]], &[-2.0, 0.0], 1e-3).unwrap();
        assert!((step[0] - 1.0 / 1.001).abs() < 1e-12 && step[1] == 0.0);
    }

    /// The settings are checked, naming `config`; a Jacobian of the wrong length names
    /// `linearize`; a start without residuals is returned with an infinite cost; Huber's
    /// cost is ½r² inside the threshold and linear beyond.
    #[test]
    fn levenberg_marquardt_checks_its_settings_and_its_linearization() {
        let fit = |c: &LmConfig| {
            levenberg_marquardt(
                [0.0],
                c,
                |p: &[f64; 1]| Ok(Some((vec![p[0] - 1.0], vec![[1.0]]))),
                |p, d| [p[0] + d[0]],
            )
        };
        let (x, cost) = fit(&LmConfig::default()).unwrap();
        assert!((x[0] - 1.0).abs() < 1e-9 && cost < 1e-18);
        for bad in [
            LmConfig {
                lambda: 0.0,
                ..LmConfig::default()
            },
            LmConfig {
                shrink: 1.0,
                ..LmConfig::default()
            },
            LmConfig {
                grow: 1.0,
                ..LmConfig::default()
            },
            LmConfig {
                lambda_max: 1e-6,
                ..LmConfig::default()
            },
            LmConfig {
                tolerance: f64::NAN,
                ..LmConfig::default()
            },
            LmConfig {
                huber: Some(0.0),
                ..LmConfig::default()
            },
        ] {
            let e = fit(&bad).unwrap_err();
            assert!(
                matches!(e, crate::Error::InvalidArgument { arg: "config", .. }),
                "{bad:?}"
            );
        }
        let short = levenberg_marquardt(
            [0.0],
            &LmConfig::default(),
            |_: &[f64; 1]| Ok(Some((vec![1.0, 2.0], vec![[1.0]]))),
            |p, d| [p[0] + d[0]],
        );
        assert!(matches!(
            short,
            Err(crate::Error::InvalidArgument {
                arg: "linearize",
                ..
            })
        ));
        let (x, cost) = levenberg_marquardt(
            [3.0],
            &LmConfig::default(),
            |_: &[f64; 1]| Ok(None::<(Vec<f64>, Vec<[f64; 1]>)>),
            |p, d| [p[0] + d[0]],
        )
        .unwrap();
        assert_eq!((x, cost), ([3.0], f64::INFINITY));
        assert_eq!(robust_cost(&[0.5, -3.0], Some(1.0)), 0.125 + 2.5);
        assert_eq!(robust_cost(&[0.5, -3.0], None), 0.125 + 4.5);
    }
}
