//! Differentiable surface points from detached hits, by the implicit function theorem.

use super::marching::Hits;
use crate::camera::Rays;
use crate::error::{check_scalar, Error, Result};
use crate::field::ImplicitSurface;
use crate::numerics::guard_denominator;
use candle_core::{DType, Tensor};

/// Configuration of [`implicit_surface`].
#[derive(Clone, Copy, Debug)]
pub struct ImplicitConfig {
    /// Guard `ε` on the cosine `|∇f·w|/(‖∇f‖‖w‖)` (1e-3, DVR's constant, applied
    /// relative to the gradient and direction lengths).
    pub grazing_eps: f64,
    /// Floor on `‖∇f‖` (1e-12, field units per unit length) so that a vanishing spatial
    /// gradient cannot divide by 0. The guard scales with `‖w‖`, so it does not depend
    /// on how the directions are scaled.
    pub min_gradient: f64,
}

impl Default for ImplicitConfig {
    fn default() -> Self {
        Self {
            grazing_eps: 1e-3,
            min_gradient: 1e-12,
        }
    }
}

/// Differentiable surface points for the `H` rays of a [`Hits`] with a surface.
#[derive(Clone, Debug)]
pub struct SurfacePoints {
    /// Indices of those rays in the march's batch, `[H]` u32, ascending.
    pub indices: Tensor,
    /// `t̂`, `[H]`: value = the march's depth, gradient = the implicit derivative w.r.t.
    /// the field's parameters (and codes), the ray origins and the directions.
    pub depth: Tensor,
    /// `p̂ = o + t̂·w`, `[H, 3]`, differentiable like `depth`.
    pub points: Tensor,
    /// `f(x₀)`, `[H]`, with graph (≈ τ).
    pub value: Tensor,
    /// `∇ₚf(x₀)`, `[H, 3]`, with graph w.r.t. parameters and `x₀` (not through `t̂`):
    /// unnormalised surface normals for shading and eikonal terms.
    pub gradient: Tensor,
    /// `[H]` u8: 1 where the denominator was guarded (grazing ray or `∇f ≈ 0`).
    pub guarded: Tensor,
}

/// Makes the surface points of `hits` differentiable (IDR's implicit form; the math
/// below).
///
/// * `field`: the field that was marched (possibly [`crate::field::Conditioned`] with a
///   shared `[D]` code or one `[R, D]` code per ray; gradients then reach the code).
/// * `rays`: the `R` rays that were marched, *with* their graph (e.g. from
///   [`crate::camera::pose_rays`]) so that gradients reach the camera.
/// * `hits`: the march's result for these rays; only its detached depths and statuses
///   are read.
///
/// Evaluates `field.value_and_grad` once, at the `H` rays with a surface. Output dtype
/// and device are those of the rays. Everything is finite whenever the inputs are: the
/// guarded denominator bounds `|∂t̂/∂f|` by `1/(grazing_eps·max(‖∇f‖, min_gradient)·‖w‖)`.
/// (In f32 the true `∂t/∂w ∝ t/‖w‖` itself overflows where `t/‖w‖` exceeds ~1e38.)
///
/// # Math (see docs/math.md, "DVR: implicit gradients")
/// The depth `t(θ, o, w)` of the first surface point is defined by `f_θ(o + t·w) = τ`.
/// Differentiating, `∇f·(δo + t·δw + w·δt) + ∂f/∂θ·δθ = 0`, so with `D = ∇f·w ≠ 0`:
///
/// ```text
/// ∂t/∂θ = −(∂f/∂θ)/D,    ∂t/∂o = −∇f/D,    ∂t/∂w = −t·∇f/D.
/// ```
///
/// IDR's form produces all three with ordinary autograd and one field evaluation: with
/// `t₀` the detached depth of the march and `x₀ = o + t₀·w` built from `o`, `w` *with
/// their graph*,
///
/// ```text
/// t̂ = t₀ − (f(x₀) − sg[f(x₀)]) / sg[D],      p̂ = o + t̂·w,
/// ```
///
/// where `sg` stops gradients: the value is exactly `t₀`, and the derivative of
/// `f(x₀)` w.r.t. `θ`, `o` (via `∂x₀/∂o = I`) and `w` (via `∂x₀/∂w = t₀·I`) divided by
/// `−D` is exactly the implicit derivative above. The denominator is guarded in a
/// sign-preserving way on the cosine `c = D/(‖∇f‖‖w‖)`: `D̃ = s·guard(c, ε)` with
/// `s = max(‖∇f‖, min_gradient)·‖w‖` and `guard(c, ε) = c` where `|c| ≥ ε`, else
/// `ε·sgn(c)` (`sgn(0) = +1`), so `|∂t/∂f| ≤ 1/(ε·s)` and grazing rays keep the sign of
/// their gradient.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `hits` if it has a different number of rays or dtype
/// than `rays`, `config.grazing_eps` / `config.min_gradient` unless finite and > 0; field
/// errors.
pub fn implicit_surface<F: ImplicitSurface + ?Sized>(
    field: &F,
    rays: &Rays,
    hits: &Hits,
    config: &ImplicitConfig,
) -> Result<SurfacePoints> {
    check_scalar(config.grazing_eps, "config.grazing_eps", true)?;
    check_scalar(config.min_gradient, "config.min_gradient", true)?;
    let r = rays.len();
    let (origins, directions) = (rays.origins(), rays.directions());
    if hits.status.len() != r || hits.depth.dims() != [r] {
        return Err(Error::invalid(
            "hits",
            format!("the march result for these {r} rays"),
            format!("{} rays", hits.status.len()),
        ));
    }
    crate::error::check_same(&hits.depth, "hits", origins, "origins")?;
    let idx = hits.surface_indices();
    let h = idx.len();
    let device = origins.device();
    let indices = Tensor::from_vec(idx, h, device)?;
    if h == 0 {
        let z1 = Tensor::zeros(0, origins.dtype(), device)?;
        let z3 = Tensor::zeros((0, 3), origins.dtype(), device)?;
        return Ok(SurfacePoints {
            indices,
            depth: z1.clone(),
            points: z3.clone(),
            value: z1,
            gradient: z3,
            guarded: Tensor::zeros(0, DType::U8, device)?,
        });
    }
    let o = origins.index_select(&indices, 0)?;
    let w = directions.index_select(&indices, 0)?;
    let t0 = hits.depth.detach().index_select(&indices, 0)?;
    let x0 = (&o + w.broadcast_mul(&t0.unsqueeze(1)?)?)?;
    let (f, g) = field.value_and_grad_on_rays(&x0, &indices)?;
    let gd = g.detach();
    let wd = w.detach();
    let d = (&gd * &wd)?.sum(1)?;
    let grad_norm = gd.sqr()?.sum(1)?.sqrt()?;
    let floored = grad_norm.clamp(config.min_gradient, f64::INFINITY)?;
    let scale = (floored * wd.sqr()?.sum(1)?.sqrt()?)?;
    let cos = (&d / &scale)?;
    let guarded = (cos.abs()?.lt(config.grazing_eps)? + grad_norm.lt(config.min_gradient)?)?
        .clamp(0u8, 1u8)?;
    let denom = (guard_denominator(&cos, config.grazing_eps)? * &scale)?.detach();
    let delta = (&f - f.detach())?;
    let depth = (&t0 - (delta / denom)?)?;
    let points = (&o + w.broadcast_mul(&depth.unsqueeze(1)?)?)?;
    Ok(SurfacePoints {
        indices,
        depth,
        points,
        value: f,
        gradient: g,
        guarded,
    })
}
