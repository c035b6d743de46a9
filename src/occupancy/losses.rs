//! Training losses of occupancy networks.
//!
//! * [`bce_with_logits`] (in [`crate::numerics`]): elementwise, finite for logits of
//!   ±10⁴, gradient `σ(x) − y`.
//! * [`reconstruction_loss`]: ONet's reduction, BCE summed over the `K` points of a shape and
//!   averaged over the `B` shapes of the batch.
//! * [`kl_standard_normal`] and [`reparameterize`]: the variational ONet's
//!   `KL[N(μ, diag σ²) ‖ N(0, I)]` and the sample `z = μ + σ ⊙ ε`.

use crate::numerics::bce_with_logits;

use crate::error::{check_float, check_same, check_same_shape, check_shape, Dim, Error, Result};
use crate::rng::SplitMix64;
use candle_core::Tensor;

/// `L = (1/B) Σ_b Σ_k BCE(logits[b, k], targets[b, k])` with the stable
/// [`bce_with_logits`].
///
/// * `logits`, `targets`: `[B, K]`, same f32/f64 dtype and device; targets in `[0, 1]`.
/// * Returns a scalar tensor (shape `[]`), differentiable w.r.t. both; `∂L/∂logits =
///   (σ(x) − y)/B`.
///
/// # Errors
/// Not rank 2, mismatched shapes, dtypes or devices.
pub fn reconstruction_loss(logits: &Tensor, targets: &Tensor) -> Result<Tensor> {
    check_float(logits, "logits")?;
    let dims = check_shape(logits, "logits", &[Dim::Any("B"), Dim::Any("K")])?;
    if dims[0] == 0 {
        return Err(Error::invalid("logits", "a non-empty batch", "B = 0"));
    }
    let l = bce_with_logits(logits, targets)?;
    Ok((l.sum_all()? / dims[0] as f64)?)
}

/// `KL[N(μ, diag exp(ℓ)) ‖ N(0, I)] = ½ Σ_d (exp(ℓ_d) + μ_d² − 1 − ℓ_d)` per row.
///
/// * `mean`, `logvar`: `[B, D]`, same dtype and device. Returns `[B]`.
/// * Differentiable: `∂/∂μ = μ`, `∂/∂ℓ = ½(exp(ℓ) − 1)`.
/// * Finite while `exp(ℓ)` is: `ℓ < 88` in f32, `ℓ < 709` in f64 (encoders usually
///   clamp ℓ far below that).
///
/// # Errors
/// Not rank 2, mismatched shapes, dtypes or devices.
pub fn kl_standard_normal(mean: &Tensor, logvar: &Tensor) -> Result<Tensor> {
    check_float(mean, "mean")?;
    check_shape(mean, "mean", &[Dim::Any("B"), Dim::Any("D")])?;
    check_same(logvar, "logvar", mean, "mean")?;
    check_same_shape(logvar, "logvar", mean, "mean")?;
    let t = ((logvar.exp()? + mean.sqr()?)? - logvar)?;
    Ok(((t - 1.0)?.sum(1)? * 0.5)?)
}

/// The reparameterised sample `z = μ + exp(½ℓ) ⊙ ε`, `ε ~ N(0, I)` drawn from `seed`
/// on the host (same seed, same `ε`), in the dtype and device of `mean`.
///
/// * `mean`, `logvar`: same shape (any rank), same dtype and device.
/// * Differentiable w.r.t. `mean` (`∂z/∂μ = 1`) and `logvar` (`∂z/∂ℓ = ½ exp(½ℓ) ε`).
///
/// # Errors
/// Mismatched shapes, dtypes or devices.
pub fn reparameterize(mean: &Tensor, logvar: &Tensor, seed: u64) -> Result<Tensor> {
    check_float(mean, "mean")?;
    check_same(logvar, "logvar", mean, "mean")?;
    check_same_shape(logvar, "logvar", mean, "mean")?;
    let eps =
        SplitMix64::new(seed).normal_tensor(mean.dims(), 0.0, 1.0, mean.dtype(), mean.device())?;
    Ok((mean + ((logvar * 0.5)?.exp()? * eps)?)?)
}
