//! DVR and IDR training losses, all finite for any finite input (BCE terms use
//! [`crate::numerics::bce_with_logits`]; norms have a floored square root so their
//! gradients stay finite at 0).
//!
//! Logits of an implicit surface are `s = σ·(f − τ)` (inside positive for both
//! occupancy logits and SDFs, see [`crate::dvr::march`]).

use crate::camera::{Intersection, Rays};
use crate::error::{
    check_float, check_points, check_same, check_same_shape, check_scalar, check_shape,
};
use crate::error::{Dim, Error, Result};
use crate::field::{ImplicitSurface, Inside};
use crate::numerics::bce_with_logits;
use crate::rng::SplitMix64;
use candle_core::Tensor;

/// `‖x‖` per row of `x: [N, K]` as `√max(Σx², 1e-30)`: finite gradient everywhere.
fn safe_norm(x: &Tensor) -> Result<Tensor> {
    Ok(x.sqr()?.sum(1)?.clamp(1e-30, f64::INFINITY)?.sqrt()?)
}

/// A `[N]` mask of any dtype as `pred`'s float dtype, checked.
fn mask_weights(mask: Option<&Tensor>, like: &Tensor, n: usize) -> Result<Tensor> {
    match mask {
        None => Ok(Tensor::ones(n, like.dtype(), like.device())?),
        Some(m) => {
            check_shape(m, "mask", &[Dim::Is(n)])?;
            if !m.device().same_device(like.device()) {
                return Err(Error::invalid(
                    "mask",
                    "the device of pred",
                    format!("{:?}", m.device()),
                ));
            }
            Ok(m.to_dtype(like.dtype())?)
        }
    }
}

/// `Σ mᵢ ℓᵢ / max(Σ mᵢ, 1)`.
fn masked_mean(per_row: &Tensor, m: &Tensor) -> Result<Tensor> {
    let count = m.sum_all()?.clamp(1.0, f64::INFINITY)?;
    Ok((per_row * m)?.sum_all()?.div(&count)?)
}

fn check_pair(pred: &Tensor, target: &Tensor) -> Result<()> {
    check_float(pred, "pred")?;
    check_same(target, "target", pred, "pred")?;
    check_same_shape(target, "target", pred, "pred")?;
    Ok(())
}

/// The norm of a photometric loss.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Photometric {
    /// `Σ_c |Δ_c|` per pixel (DVR, IDR).
    L1,
    /// `Σ_c Δ_c²` per pixel.
    L2,
}

/// Photometric loss on the masked pixels: `Σᵢ mᵢ ℓᵢ / max(Σᵢ mᵢ, 1)` with
/// `ℓᵢ = Σ_c |predᵢc − targetᵢc|` (L1) or `Σ_c (predᵢc − targetᵢc)²` (L2).
///
/// * `pred, target: [N, C]`, same float dtype and device; `mask: [N]` (any dtype,
///   nonzero = used; e.g. hit ∧ inside the object mask), or `None` for all pixels.
/// * Returns a scalar, differentiable w.r.t. `pred` and `target`.
///
/// # Errors
/// `pred` not float `[N, C]`; `target` of another shape/dtype/device; `mask` not `[N]`.
pub fn photometric_loss(
    pred: &Tensor,
    target: &Tensor,
    mask: Option<&Tensor>,
    norm: Photometric,
) -> Result<Tensor> {
    check_pair(pred, target)?;
    let n = check_shape(pred, "pred", &[Dim::Any("N"), Dim::Any("C")])?[0];
    let diff = (pred - target)?;
    let per = match norm {
        Photometric::L1 => diff.abs()?.sum(1)?,
        Photometric::L2 => diff.sqr()?.sum(1)?,
    };
    masked_mean(&per, &mask_weights(mask, pred, n)?)
}

/// Depth L1 loss on the masked rays: `Σᵢ mᵢ |predᵢ − targetᵢ| / max(Σ mᵢ, 1)`.
///
/// * `pred, target: [N]` (e.g. [`crate::dvr::SurfacePoints::depth`] and ground-truth
///   depths of the same rays); `mask: [N]` or `None`. Scalar output, differentiable
///   w.r.t. `pred` and `target`.
///
/// # Errors
/// As [`photometric_loss`], with `pred` required to be `[N]`.
pub fn depth_loss(pred: &Tensor, target: &Tensor, mask: Option<&Tensor>) -> Result<Tensor> {
    check_pair(pred, target)?;
    let n = check_shape(pred, "pred", &[Dim::Any("N")])?[0];
    let per = (pred - target)?.abs()?;
    masked_mean(&per, &mask_weights(mask, pred, n)?)
}

/// `s = σ(f − τ)` at `points`, with graph.
fn logits<F: ImplicitSurface + ?Sized>(field: &F, points: &Tensor) -> Result<Tensor> {
    check_points(points, "points")?;
    let f = field.value(points)?;
    Ok(f.affine(
        field.inside().sign(),
        -field.inside().sign() * field.level(),
    )?)
}

/// DVR's occupancy losses: the mean BCE of the logits `s = σ(f − τ)` at
/// `points: [M, 3]` towards a label, `mean BCE(s(p), y)` with `y = 1` when `inside`,
/// else `0`:
/// - the **freespace loss** (`inside = false`), at the predicted surface points of rays
///   outside the object mask, or at [`random_points_on_rays`] of rays without a hit;
/// - the **occupancy loss** of foreground rays that found no surface (`inside = true`),
///   e.g. at [`random_points_on_rays`] or [`most_inside_along_rays`] of those rays.
///
/// Differentiable w.r.t. the field (and `points`). 0 for `M = 0`.
///
/// # Errors
/// `points` not float `[M, 3]`; field errors.
pub fn occupancy_bce<F: ImplicitSurface + ?Sized>(
    field: &F,
    points: &Tensor,
    inside: bool,
) -> Result<Tensor> {
    if check_points(points, "points")? == 0 {
        return Ok(Tensor::zeros((), points.dtype(), points.device())?);
    }
    let s = logits(field, points)?;
    let target = if inside { 1.0 } else { 0.0 };
    let y = Tensor::full(target, s.shape(), s.device())?.to_dtype(s.dtype())?;
    Ok(bce_with_logits(&s, &y)?.mean_all()?)
}

/// One uniformly random point per ray, `o + u·w` with `u ~ U(near, far)` drawn from
/// `seed`: `[R, 3]`, differentiable w.r.t. the rays' origins and directions (`u` is
/// constant).
///
/// * `rays`: `R` rays; `range`: `near, far: [R]` in their dtype and on their device (the
///   hit mask is not used).
///
/// # Errors
/// Naming `near` / `far` for shapes, dtypes or devices that differ from the rays'.
pub fn random_points_on_rays(rays: &Rays, range: &Intersection, seed: u64) -> Result<Tensor> {
    let r = rays.len();
    let (origins, directions) = (rays.origins(), rays.directions());
    let (near, far) = (&range.near, &range.far);
    for (t, name) in [(near, "near"), (far, "far")] {
        check_float(t, name)?;
        check_shape(t, name, &[Dim::Is(r)])?;
        check_same(t, name, origins, "origins")?;
    }
    let u =
        SplitMix64::new(seed).uniform_tensor(&[r], 0.0, 1.0, origins.dtype(), origins.device())?;
    let t = (near + ((far - near)? * u)?)?.detach();
    Ok((origins + directions.broadcast_mul(&t.unsqueeze(1)?)?)?)
}

/// Normal smoothness (DVR): `mean ‖n(p) − n(p + δ)‖` with `n = ∇f/‖∇f‖` and
/// `δ ~ U(−ε, ε)³` drawn from `seed` (DVR: ε = 5e-4, weight 0.05).
///
/// * `points: [M, 3]` (e.g. [`crate::dvr::SurfacePoints::points`]). Scalar output,
///   differentiable w.r.t. the field's parameters and `points` (needs a field whose
///   `value_and_grad` is differentiable, such as [`crate::nn::Mlp`]).
///
/// # Errors
/// `points` not float `[M, 3]`; `eps` not finite and > 0; field errors.
pub fn normal_smoothness_loss<F: ImplicitSurface + ?Sized>(
    field: &F,
    points: &Tensor,
    eps: f64,
    seed: u64,
) -> Result<Tensor> {
    let m = check_points(points, "points")?;
    check_scalar(eps, "eps", true)?;
    if m == 0 {
        return Ok(Tensor::zeros((), points.dtype(), points.device())?);
    }
    let jitter = SplitMix64::new(seed).uniform_tensor(
        &[m, 3],
        -eps,
        eps,
        points.dtype(),
        points.device(),
    )?;
    let both = Tensor::cat(&[points, &(points + jitter)?], 0)?;
    let (_, g) = field.value_and_grad(&both)?;
    let n = g.broadcast_div(&safe_norm(&g)?.unsqueeze(1)?)?;
    let diff = (n.narrow(0, 0, m)? - n.narrow(0, m, m)?)?;
    Ok(safe_norm(&diff)?.mean_all()?)
}

/// Eikonal loss (IDR, weight 0.1): `mean (‖g‖ − 1)²` for spatial gradients `g: [M, 3]`
/// (e.g. [`crate::dvr::SurfacePoints::gradient`] or `value_and_grad` at random points).
/// Differentiable w.r.t. `g` (finite at `g = 0`). 0 for `M = 0`.
///
/// # Errors
/// `gradient` not float `[M, 3]`.
pub fn eikonal_loss(gradient: &Tensor) -> Result<Tensor> {
    let m = check_points(gradient, "gradient")?;
    if m == 0 {
        return Ok(Tensor::zeros((), gradient.dtype(), gradient.device())?);
    }
    Ok((safe_norm(gradient)? - 1.0)?.sqr()?.mean_all()?)
}

/// IDR's mask loss: `(1/α)·Σᵢ BCE(α·sᵢ, maskᵢ) / normalizer` with `sᵢ = σ(fᵢ − τ)`
/// (for an SDF, `BCE(−α·fᵢ, maskᵢ)`; IDR: α = 50 doubled at fixed epochs, weight 100,
/// summed over the rays that missed or are outside the object mask and divided by the
/// total number of rays).
///
/// * `values: [M]`: field values per ray, with graph — IDR uses the minimum SDF along
///   the ray ([`most_inside_along_rays`]); `mask: [M]` targets in `[0, 1]`, same dtype.
/// * `inside`: the field's inside sign; `alpha > 0`; `normalizer ≥ 1`.
/// * Scalar output, differentiable w.r.t. `values`.
///
/// # Errors
/// `values` not float `[M]`; `mask` of another shape/dtype; `alpha` not finite and > 0;
/// `normalizer` 0.
pub fn idr_mask_loss(
    values: &Tensor,
    mask: &Tensor,
    inside: Inside,
    alpha: f64,
    normalizer: usize,
) -> Result<Tensor> {
    check_float(values, "values")?;
    check_shape(values, "values", &[Dim::Any("M")])?;
    check_scalar(alpha, "alpha", true)?;
    if normalizer == 0 {
        return Err(Error::invalid("normalizer", "at least 1", "0"));
    }
    check_same_shape(mask, "mask", values, "values")?;
    check_same(mask, "mask", values, "values")?;
    let logits = values.affine(alpha * inside.sign(), 0.0)?;
    let sum = bce_with_logits(&logits, mask)?.sum_all()?;
    Ok(sum.affine(1.0 / (alpha * normalizer as f64), 0.0)?)
}

/// IDR's α schedule for [`idr_mask_loss`]: `α = initial · factor^k` where `k` is the
/// number of milestones `≤ epoch`.
#[derive(Clone, Debug, PartialEq)]
pub struct AlphaSchedule {
    /// α at epoch 0 (IDR: 50).
    pub initial: f64,
    /// Multiplier at each milestone (IDR: 2).
    pub factor: f64,
    /// Epochs at which α is multiplied (IDR: 250, 500, 750, 1000, 1250).
    pub milestones: Vec<usize>,
}

impl Default for AlphaSchedule {
    /// IDR's: 50, doubled at epochs 250, 500, 750, 1000 and 1250.
    fn default() -> Self {
        Self {
            initial: 50.0,
            factor: 2.0,
            milestones: vec![250, 500, 750, 1000, 1250],
        }
    }
}

impl AlphaSchedule {
    /// α at `epoch`.
    #[must_use]
    pub fn alpha_at(&self, epoch: usize) -> f64 {
        let k = self.milestones.iter().filter(|&&m| m <= epoch).count();
        self.initial * self.factor.powi(i32::try_from(k).unwrap_or(i32::MAX))
    }
}

/// For each ray, the field value at the most-inside of `steps` evenly spaced samples on
/// `[near, far]` (largest `s = σ(f − τ)`; for an SDF the minimum distance), re-evaluated
/// with graph at that point: `[R]`, differentiable w.r.t. the field's parameters and the
/// rays (the sample parameter is detached). IDR's input to [`idr_mask_loss`].
///
/// The search is detached and chunked (`steps·R` evaluations in calls of at most
/// 65 536 points), plus one evaluation with graph per ray.
///
/// # Errors
/// As [`crate::dvr::march`] for the rays and bounds; `steps` below 1 or whose samples of
/// one ray (32 bytes each) pass the allocation limit of 2³³ bytes (8 GiB), checked before
/// anything is allocated.
pub fn most_inside_along_rays<F: ImplicitSurface + ?Sized>(
    field: &F,
    rays: &Rays,
    range: &Intersection,
    steps: usize,
) -> Result<Tensor> {
    if steps == 0 {
        return Err(Error::invalid("steps", "at least 1", "0"));
    }
    // One ray's samples (a point and its ray, 32 bytes each) are held together.
    crate::limits::check_bytes("steps", &[steps], 32)?;
    let (origins, directions) = (rays.origins(), rays.directions());
    let rays = super::marching::read_problem(rays, range)?;
    let r = rays.o.len();
    let mut ev = super::marching::Evaluator::new(field, &rays, 65_536);
    let per_chunk = (65_536 / steps).max(1);
    let mut best_t = vec![0.0; r];
    let idx: Vec<usize> = (0..r).collect();
    let frac = |j: usize| {
        if steps == 1 {
            0.5
        } else {
            j as f64 / (steps - 1) as f64
        }
    };
    for chunk in idx.chunks(per_chunk) {
        let mut pts = super::marching::RayPoints::with_capacity(steps * chunk.len());
        for &i in chunk {
            for j in 0..steps {
                let t = rays.near[i] + (rays.far[i] - rays.near[i]) * frac(j);
                pts.push(i, &rays.o[i], &rays.w[i], t);
            }
        }
        let s = ev.values(&pts)?;
        for (ci, &i) in chunk.iter().enumerate() {
            let row = &s[ci * steps..(ci + 1) * steps];
            let mut jb = 0;
            for j in 1..steps {
                if row[j] > row[jb] {
                    jb = j;
                }
            }
            best_t[i] = rays.near[i] + (rays.far[i] - rays.near[i]) * frac(jb);
        }
    }
    let t = Tensor::from_vec(best_t, r, &candle_core::Device::Cpu)?
        .to_dtype(origins.dtype())?
        .to_device(origins.device())?;
    let p = (origins + directions.broadcast_mul(&t.unsqueeze(1)?)?)?;
    field.value_on_rays(&p, &ray_indices(r, origins.device())?)
}

/// `[0, 1, …, r − 1]` as u32 ray indices on `device`.
pub(crate) fn ray_indices(r: usize, device: &candle_core::Device) -> Result<Tensor> {
    // Ray counts are far below 2³² (the host copies alone would not fit otherwise).
    Ok(Tensor::arange(0u32, r as u32, device)?)
}
