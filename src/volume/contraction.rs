//! mip-NeRF 360's scene contraction of unbounded space into the ball of radius 2, for
//! points and (linearised) for Gaussians.

use super::layout::check_all_finite;
use crate::error::{check_float, check_points, check_same, Error, Result};
use candle_core::Tensor;

/// The parts of the contraction shared by the points and the Gaussians of [`contract`], for
/// validated finite points `x` of shape `[N, 3]`, `N > 0`.
struct Parts {
    /// `[N, 1]` mask (u8): 1 where `‖x‖ ≤ 1`.
    inside: Tensor,
    /// `[N, 3]` unit direction `x/‖x‖` (a placeholder where `inside`).
    u: Tensor,
    /// `[N, 1]` reciprocal radius `1/‖x‖` (a placeholder where `inside`).
    ir: Tensor,
}

/// Splits `x` into the mask of the unit ball and, outside it, the direction and the
/// reciprocal radius, without overflow or underflow of `‖x‖²` at any finite `x`.
///
/// Inside the unit ball `x` is replaced by a constant point of radius √3 before the
/// outside quantities are computed, so that neither their values nor their (masked)
/// gradients meet `0/0` at the origin.
fn parts(x: &Tensor) -> Result<Parts> {
    let n = x.dim(0)?;
    // ‖x‖² overflows to +∞ for huge x, which is correctly "outside"; tiny x underflow to
    // 0, correctly "inside".
    let inside = x.detach().sqr()?.sum_keepdim(1)?.le(1.0)?;
    let inside3 = inside.broadcast_as((n, 3))?.contiguous()?;
    let safe = inside3.where_cond(&x.ones_like()?, x)?;
    // Scale by the largest |component| (a constant: ‖x‖ = m·‖x/m‖ for any m > 0), so
    // that the squares neither overflow nor underflow; m ≥ 1/√3 on `safe`.
    let m = safe.detach().abs()?.max_keepdim(1)?;
    let y = safe.broadcast_div(&m)?;
    let ny = y.sqr()?.sum_keepdim(1)?.sqrt()?; // in [1, √3]
    let u = y.broadcast_div(&ny)?;
    let ir = ny.recip()?.broadcast_mul(&m.recip()?)?;
    Ok(Parts { inside, u, ir })
}

/// mip-NeRF 360's scene contraction (Barron et al. 2022, eq. 10), of points or of
/// Gaussians: maps all of space into the ball of radius 2,
///
/// ```text
/// contract(x) = x                         if ‖x‖ ≤ 1,
///               (2 − 1/‖x‖) · x/‖x‖       otherwise,
/// ```
///
/// and, given covariances, pushes each Gaussian through it linearised (mip-NeRF 360, §2):
/// the mean is contracted and the covariance `Σ` becomes `J Σ Jᵀ`, with `J` the
/// contraction's Jacobian at the mean.
///
/// The contraction is the identity inside the unit ball, continuous with a continuous
/// first derivative across the unit sphere (the Jacobian is the identity on both sides),
/// and maps a point at radius `r > 1` to radius `2 − 1/r < 2` along the same direction, so
/// the radius is strictly increasing and tends to 2 as `r → ∞`. Sampling the contracted
/// space uniformly therefore spends as much of it on the far field `r ∈ (1, ∞)` as on the
/// unit ball; pair it with sampling in disparity along unbounded rays. With `r = ‖x‖`,
/// `u = x/r` and `g(r) = 2 − 1/r`, outside the unit ball
/// `d(g·u) = g′(r)·u uᵀ dx + g(r)/r·(I − u uᵀ) dx`, so
///
/// ```text
/// J = a·I + b·u uᵀ,   a = (2 − 1/r)/r,   b = 1/r² − a = 2·(1/r)·(1/r − 1),
/// ```
///
/// symmetric, with eigenvalue `1/r²` along `u` and `a` across it; inside the unit ball
/// `J = I` (`a = 1`, `b = 0`, which is also the limit at `r = 1`).
///
/// - `points`: `[N, 3]` (the Gaussians' means), f32 or f64, any device; the contracted
///   points have the same shape, dtype and device.
/// - `covariances`: `None` for points; full `[N, 3, 3]` or diagonal `[N, 3]` (the
///   variances), same dtype and device as `points`. They come back in the input's form:
///   full `J Σ Jᵀ`, or for diagonal input the diagonal of `J diag(σ²) Jᵀ`, i.e.
///   `Σₖ J_ik² σ_k²` — an approximation: the contraction correlates the axes (outside the
///   unit ball, unless `u` is along an axis), and the off-diagonal terms are dropped, as
///   an integrated encoding of diagonal Gaussians needs.
///
/// Differentiable w.r.t. `points` (also through `J`) and `covariances` (candle ops; the
/// branch is a mask). The radius is computed after scaling each point by its largest
/// component, so any finite input — `1e300` in f64, `1e30` in f32 — gives a finite output
/// of radius `2 − 1/r` (which rounds to 2 once `1/r` is below the dtype's precision,
/// never above 2 beyond rounding) and finite gradients; at the origin the gradient is the
/// identity's. `J` falls off as `1/r` across and `1/r²` along `u`, and its eigenvalues are
/// at most 1, so the covariances only shrink (a covariance within a factor 3 of the
/// dtype's largest value may still overflow in the sums of the product).
///
/// # Errors
/// [`Error::InvalidArgument`] naming `points` for a shape other than `[N, 3]`, a dtype
/// other than f32/f64, or any non-finite element: NaN, and also ±∞ (whose direction is
/// undefined when several components are infinite), are refused rather than mapped;
/// naming `covariances` for a shape other than `[N, 3, 3]` or `[N, 3]` with the same `N`,
/// another dtype or device than `points`, or a non-finite element.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::contract;
///
/// let dev = Device::Cpu;
/// let x = Tensor::new(&[[0.5f64, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, -1e300]], &dev)?;
/// let (y, _) = contract(&x, None)?;
/// let y = y.to_vec2::<f64>()?;
/// assert_eq!(y[0], [0.5, 0.0, 0.0]);              // the identity inside the unit ball
/// assert_eq!(y[1], [0.0, 1.75, 0.0]);             // 2 − 1/4 along +y
/// assert_eq!(y[2], [0.0, 0.0, -2.0]);            // 2 − 1e-300 rounds to 2
///
/// let means = Tensor::new(&[[0.0f64, 0.0, 0.5], [0.0, 0.0, 2.0]], &dev)?;
/// let variances = Tensor::new(&[[1.0f64, 1.0, 1.0], [1.0, 1.0, 1.0]], &dev)?;
/// let (m, v) = contract(&means, Some(&variances))?;
/// assert_eq!(m.to_vec2::<f64>()?[1], [0.0, 0.0, 1.5]);
/// let v = v.map(|v| v.to_vec2::<f64>()).transpose()?.unwrap_or_default(); // covariances in, out
/// assert_eq!(v[0], [1.0, 1.0, 1.0]);        // unchanged inside the unit ball
/// // at r = 2: a = 0.75 across, 1/r² = 0.25 along the mean's direction
/// assert!((v[1][0] - 0.5625).abs() < 1e-12 && (v[1][2] - 0.0625).abs() < 1e-12);
/// # Ok::<(), neural_fields::Error>(())
/// ```
pub fn contract(points: &Tensor, covariances: Option<&Tensor>) -> Result<(Tensor, Option<Tensor>)> {
    let n = check_points(points, "points")?;
    let full = match covariances {
        None => None,
        Some(cov) => {
            check_float(cov, "covariances")?;
            check_same(cov, "covariances", points, "points")?;
            match cov.dims() {
                [m, 3, 3] if *m == n => Some(true),
                [m, 3] if *m == n => Some(false),
                dims => {
                    return Err(Error::invalid(
                        "covariances",
                        format!("shape [{n}, 3, 3] or [{n}, 3] (N of points)"),
                        format!("shape {dims:?}"),
                    ))
                }
            }
        }
    };
    check_all_finite(points, "points")?;
    if let Some(cov) = covariances {
        check_all_finite(cov, "covariances")?;
    }
    if n == 0 {
        return Ok((points.clone(), covariances.cloned()));
    }
    let Parts { inside, u, ir } = parts(points)?;
    let g = ir.affine(-1.0, 2.0)?;
    let inside3 = inside.broadcast_as((n, 3))?.contiguous()?;
    let contracted = inside3.where_cond(points, &u.broadcast_mul(&g)?)?;
    let (Some(cov), Some(full)) = (covariances, full) else {
        return Ok((contracted, None));
    };
    let a_out = (&g * &ir)?;
    let b_out = ((&ir * 2.0)? * (&ir - 1.0)?)?;
    let a = inside.where_cond(&ir.ones_like()?, &a_out)?;
    let b = inside.where_cond(&ir.zeros_like()?, &b_out)?;
    let uut = u.unsqueeze(2)?.broadcast_mul(&u.unsqueeze(1)?)?; // [N, 3, 3]
    let eye = Tensor::eye(3, points.dtype(), points.device())?;
    let jac = (eye.broadcast_mul(&a.unsqueeze(2)?)? + uut.broadcast_mul(&b.unsqueeze(2)?)?)?;
    let cov = cov.contiguous()?;
    let pushed = if full {
        // J is symmetric: J Σ Jᵀ = J Σ J.
        jac.matmul(&cov)?.matmul(&jac)?
    } else {
        jac.sqr()?.matmul(&cov.unsqueeze(2)?)?.squeeze(2)?
    };
    Ok((contracted, Some(pushed)))
}
