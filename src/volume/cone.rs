//! Cone casting (mip-NeRF): the Gaussian moments of each interval's conical frustum.

use super::layout::{Intervals, Layout};
use crate::camera::Rays;
use crate::error::{Error, Result};
use candle_core::{Tensor, D};

/// Which covariance [`conical_frustums`] returns.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Covariance {
    /// The diagonal of each covariance, `[…, 3]`: what
    /// [`crate::encoding::integrated_pe`] reads.
    Diagonal,
    /// The full `3 × 3` covariance, `[…, 3, 3]`.
    Full,
}

/// The Gaussians of [`conical_frustums`]: one per interval, in the intervals' layout.
#[derive(Clone, Debug)]
pub struct Gaussians {
    /// Means `o + t̄·d`: `[R, S, 3]` (batched) or `[M, 3]` (packed).
    pub means: Tensor,
    /// Covariances: `[R, S, 3]` / `[M, 3]` ([`Covariance::Diagonal`]) or `[R, S, 3, 3]` /
    /// `[M, 3, 3]` ([`Covariance::Full`]).
    pub covariances: Tensor,
}

/// Cone casting (mip-NeRF): the mean and covariance of the conical frustum that each
/// interval `[t₀, t₁]` cuts from its ray's cone, the Gaussians that
/// [`crate::encoding::integrated_pe`] encodes.
///
/// Ray `r` (origin `o`, direction `d`, not necessarily unit: `t` is the ray parameter)
/// casts a cone whose cross-section at parameter `t` is a disc of radius `ρ_r·t`
/// (world units) perpendicular to `d`, with `ρ` the rays' cone radii
/// ([`Rays::with_radii`], mip-NeRF's `radii`: camera rays carry the pixel footprint at
/// depth 1 times `2/√12`). Each interval's
/// frustum is filled uniformly (density ∝ `t²` along the ray). With mip-NeRF's stable
/// parametrisation `t_μ = (t₀ + t₁)/2`, `t_δ = (t₁ − t₀)/2`:
///
/// - mean along the ray `t̄ = t_μ + 2t_μt_δ² / (3t_μ² + t_δ²)`;
/// - variance along the ray `σ_t² = t_δ²/3 − (4/15)·t_δ⁴(12t_μ² − t_δ²)/(3t_μ² + t_δ²)²`;
/// - radial variance `σ_r² = r²·(t_μ²/4 + (5/12)t_δ² − (4/15)·t_δ⁴/(3t_μ² + t_δ²))`;
///
/// lifted to 3-D (mip-NeRF's `lift_gaussian`): means `o + t̄·d`, covariances
/// `σ_t² d dᵀ + σ_r² (I − d dᵀ/‖d‖²)` ([`Covariance::Full`]) or their diagonal
/// `σ_t² d∘d + σ_r² (1 − d∘d/‖d‖²)` ([`Covariance::Diagonal`]).
///
/// The moments are evaluated with `t_μ`, `t_δ` scaled by `max(|t_μ|, t_δ)` (a detached
/// scale, exact because the formulas are homogeneous), so tiny depths do not underflow
/// to `0/0`, and
/// `d/‖d‖` comes from [`Rays::normalized`]; an interval at `t₀ = t₁ = 0` gives a point.
///
/// Shapes: `R` rays; batched intervals `[R, S]` give means `[R, S, 3]` and
/// covariances `[R, S, 3]` or `[R, S, 3, 3]`; packed ones `[M]` give `[M, 3]` and
/// `[M, 3]` or `[M, 3, 3]`. f32 or f64: the rays' dtype and device, which the intervals
/// must share. Differentiable w.r.t. the interval starts and ends, the origins, the
/// directions and the radii.
///
/// IPE end to end:
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::camera::Rays;
/// use neural_fields::encoding::integrated_pe;
/// use neural_fields::volume::{conical_frustums, stratified, Covariance, Jitter};
///
/// let dev = Device::Cpu;
/// let rays = Rays::new(
///     Tensor::new(&[[0.0f32, 0.0, -2.0], [0.3, 0.0, -2.0]], &dev)?,
///     Tensor::new(&[[0.0f32, 0.0, 1.0], [0.1, 0.0, 1.0]], &dev)?,
/// )?
/// .with_radii(Tensor::new(&[1e-3f32, 1e-3], &dev)?)?;
/// let (near, far) = (Tensor::new(&[1.0f32, 1.0], &dev)?, Tensor::new(&[3.0f32, 3.0], &dev)?);
/// let intervals = stratified(&near, &far, 8, Jitter::None, 0)?;           // [2, 8]
/// let g = conical_frustums(&rays, &intervals, Covariance::Diagonal)?;
/// assert_eq!(g.means.dims(), &[2, 8, 3]);
/// assert_eq!(g.covariances.dims(), &[2, 8, 3]);
/// let features = integrated_pe(
///     &g.means.reshape(((), 3))?,
///     &g.covariances.reshape(((), 3))?,
///     0,
///     10,
/// )?;
/// assert_eq!(features.dims(), &[16, 60]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Naming `rays` when they carry no cone radii ([`Rays::with_radii`]), or when their
/// count, dtype or device differs from the intervals'.
pub fn conical_frustums(
    rays: &Rays,
    intervals: &Intervals,
    covariance: Covariance,
) -> Result<Gaussians> {
    intervals.check_rays(rays)?;
    let radii = rays.radii().ok_or_else(|| {
        Error::invalid(
            "rays",
            "rays carrying cone radii (Rays::with_radii)",
            "rays without radii",
        )
    })?;

    // The moments along the ray, per sample.
    let mu = ((&intervals.starts + &intervals.ends)? * 0.5)?;
    let hw = ((&intervals.ends - &intervals.starts)? * 0.5)?;
    // Scale m = max(|t_μ|, t_δ) (1 where both vanish): a = t_μ/m, b = t_δ/m, so that
    // 3a² + b² ≥ 1 unless the interval is the point t = 0. The moments are homogeneous
    // in (t_μ, t_δ) (t̄ − t_μ of degree 1, the variances of degree 2), so m is a detached
    // constant: the gradients are exact, and none divides by m².
    let m = mu.abs()?.maximum(&hw)?.detach();
    let zero = m.eq(0.0)?.to_dtype(m.dtype())?.detach();
    let m_safe = (&m + &zero)?;
    let a = (&mu / &m_safe)?;
    let b = (&hw / &m_safe)?;
    let (a2, b2) = (a.sqr()?, b.sqr()?);
    let b4 = b2.sqr()?;
    let den = ((&a2 * 3.0)? + &b2 + &zero)?;
    let t_mean = (&mu + (&m * ((&a * &b2)? * 2.0)?.div(&den)?)?)?;
    let t_var_unit = ((&b2 / 3.0)?
        - ((&b4 * ((&a2 * 12.0)? - &b2)?)? / den.sqr()?)?.affine(4.0 / 15.0, 0.0)?)?;
    let m2 = m.sqr()?;
    let t_var = (&m2 * t_var_unit)?;
    let r_var_unit =
        ((&a2 * 0.25)? + (&b2 * (5.0 / 12.0))? - (&b4 / &den)?.affine(4.0 / 15.0, 0.0)?)?;
    let r2 = intervals.per_sample(&radii.sqr()?)?;
    let r_var = (&m2 * r_var_unit)?.broadcast_mul(&r2)?;

    // Lifted to 3-D.
    let d = intervals.directions(rays)?;
    let u = intervals.directions(&rays.normalized()?)?;
    let o = match &intervals.layout {
        Layout::Batched => rays.origins().unsqueeze(1)?,
        Layout::Packed(p) => rays.origins().index_select(&p.ray_indices, 0)?,
    };
    let means = o.broadcast_add(&d.broadcast_mul(&t_mean.unsqueeze(D::Minus1)?)?)?;
    let covariances = match covariance {
        Covariance::Diagonal => {
            let along = d.sqr()?.broadcast_mul(&t_var.unsqueeze(D::Minus1)?)?;
            let across = u.sqr()?.affine(-1.0, 1.0)?;
            (along + across.broadcast_mul(&r_var.unsqueeze(D::Minus1)?)?)?
        }
        Covariance::Full => {
            let outer = |v: &Tensor| -> Result<Tensor> {
                Ok(v.unsqueeze(D::Minus1)?
                    .broadcast_mul(&v.unsqueeze(D::Minus2)?)?)
            };
            let eye = Tensor::eye(3, d.dtype(), d.device())?;
            let along =
                outer(&d)?.broadcast_mul(&t_var.unsqueeze(D::Minus1)?.unsqueeze(D::Minus1)?)?;
            let across = outer(&u)?.neg()?.broadcast_add(&eye)?;
            (along + across.broadcast_mul(&r_var.unsqueeze(D::Minus1)?.unsqueeze(D::Minus1)?)?)?
        }
    };
    Ok(Gaussians { means, covariances })
}
