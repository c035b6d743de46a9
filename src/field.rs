//! Fields: functions of 3-D points, and the implicit surfaces they define.
//!
//! * [`Field`]: points `[N, 3]` → features `[N, C]` (colour, density, anything).
//! * [`ImplicitSurface`]: a scalar field `f` with a [`level`](ImplicitSurface::level) τ and
//!   an [`inside`](ImplicitSurface::inside) sign; the surface is `{p : f(p) = τ}`.
//!   Occupancy logits are level 0 with the inside positive; signed distances are level 0
//!   with the inside negative. [`ImplicitSurface::value_and_grad`] returns `f` and its
//!   spatial gradient `∇ₚf` in one pass, both differentiable w.r.t. the field's
//!   parameters (so normals `∇f/‖∇f‖` can be trained: eikonal loss, normal-conditioned
//!   rendering, DVR's implicit gradients).
//! * [`ConditionalField`] and [`Conditioned`]: a field `f(p, z)` of a latent code `z`, and
//!   the adapter that binds a code so that `f(·, z)` is a plain field.
//! * Analytic shapes ([`Sphere`], [`Cuboid`], [`RoundedBox`], [`Torus`], [`Plane`],
//!   [`Capsule`], [`Cylinder`]) implementing [`SignedDistance`], usable as SDFs
//!   ([`Sdf`]) or occupancy logits ([`Occupancy`]), with exact gradients and parameters
//!   held as tensors (wrap them in `Var`s to learn a radius or a centre). They are the
//!   fixtures of every test in this crate. [`Csg`] combines two of them (union,
//!   intersection, difference, smooth union) into another [`SignedDistance`].
//!
//! ```
//! use candle_core::{Device, DType, Tensor};
//! use neural_fields::field::{ImplicitSurface, Inside, SignedDistance, Sphere};
//!
//! let sphere = Sphere::new([0.0, 0.0, 0.0], 0.5, &Device::Cpu, DType::F64)?.occupancy(10.0);
//! let p = Tensor::new(&[[0.0f64, 0.0, 0.25], [1.0, 0.0, 0.0]], &Device::Cpu)?;
//! let (f, grad) = sphere.value_and_grad(&p)?;   // f: [2], grad: [2, 3]
//! assert_eq!(sphere.inside(), Inside::Positive);
//! let f = f.to_vec1::<f64>()?;
//! assert!(f[0] > 0.0 && f[1] < 0.0);            // inside positive, outside negative
//! assert_eq!(grad.dims(), &[2, 3]);
//! # Ok::<(), neural_fields::Error>(())
//! ```

use crate::error::{check_points, check_same, check_scalar, check_shape, Dim, Error, Result};
use candle_core::{DType, Device, Tensor, D};

/// A field over 3-D points: `points: [N, 3]` → `[N, C]` with `C = out_dim()`.
pub trait Field {
    /// The number of output channels `C`.
    fn out_dim(&self) -> usize;

    /// Evaluates the field at `points: [N, 3]`, returning `[N, C]` in the points' dtype.
    ///
    /// # Errors
    /// Wrong shape or dtype of `points`; errors of the underlying computation.
    fn forward(&self, points: &Tensor) -> Result<Tensor>;
}

/// Which side of the level set is the inside of the shape.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Inside {
    /// `f > τ` inside (occupancy logits and probabilities).
    Positive,
    /// `f < τ` inside (signed distance functions).
    Negative,
}

impl Inside {
    /// `+1` for [`Inside::Positive`], `−1` for [`Inside::Negative`].
    #[must_use]
    #[cfg_attr(not(any(feature = "dvr", feature = "occupancy")), allow(dead_code))]
    pub(crate) fn sign(self) -> f64 {
        match self {
            Inside::Positive => 1.0,
            Inside::Negative => -1.0,
        }
    }
}

/// A scalar field whose level set `{p : f(p) = τ}` is a surface.
pub trait ImplicitSurface {
    /// The scalar field `f(points)`: `points: [N, 3]` → `[N]`.
    ///
    /// # Errors
    /// Wrong shape or dtype of `points`.
    fn value(&self, points: &Tensor) -> Result<Tensor>;

    /// `f(points)` and its spatial gradient `∇ₚf`: `[N]` and `[N, 3]`.
    ///
    /// Both are differentiable w.r.t. the field's parameters (not obtained by a
    /// detaching `backward()`).
    ///
    /// # Errors
    /// Wrong shape or dtype of `points`.
    fn value_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)>;

    /// [`value`](Self::value) at points that lie on rays: `rays: [N]` (u32, on the
    /// device of `points`) is each point's ray index. A field that does not depend on
    /// the ray ignores it (this default); [`Conditioned`] with one code per ray
    /// (`[R, D]`) gives each point the code of its ray. The ray marchers of `dvr` call
    /// this form, so a batch of rays through different shapes can be marched at once.
    ///
    /// # Errors
    /// As [`value`](Self::value); an implementation that reads `rays` names it when it
    /// does not match.
    fn value_on_rays(&self, points: &Tensor, rays: &Tensor) -> Result<Tensor> {
        let _ = rays;
        self.value(points)
    }

    /// [`value_and_grad`](Self::value_and_grad) at points on rays; see
    /// [`value_on_rays`](Self::value_on_rays).
    ///
    /// # Errors
    /// As [`value_and_grad`](Self::value_and_grad) and
    /// [`value_on_rays`](Self::value_on_rays).
    fn value_and_grad_on_rays(&self, points: &Tensor, rays: &Tensor) -> Result<(Tensor, Tensor)> {
        let _ = rays;
        self.value_and_grad(points)
    }

    /// The level τ of the surface (0 for logits and SDFs).
    fn level(&self) -> f64 {
        0.0
    }

    /// Which side is inside.
    fn inside(&self) -> Inside;
}

/// A field `f(p, z)` that also takes a latent code `z: [N, D]` per point.
pub trait ConditionalField {
    /// The code dimension `D`.
    fn code_dim(&self) -> usize;

    /// The number of output channels `C`.
    fn out_dim(&self) -> usize;

    /// `f(points, codes)`: `[N, 3]`, `[N, D]` → `[N, C]`.
    ///
    /// # Errors
    /// Wrong shapes or dtypes.
    fn forward_with_code(&self, points: &Tensor, codes: &Tensor) -> Result<Tensor>;

    /// Channel 0 of `f(points, codes)` and its gradient w.r.t. the points: `[N]`, `[N, 3]`,
    /// differentiable w.r.t. the parameters and the codes.
    ///
    /// # Errors
    /// Wrong shapes or dtypes.
    fn value_and_grad_with_code(&self, points: &Tensor, codes: &Tensor)
        -> Result<(Tensor, Tensor)>;

    /// The level τ of channel 0's surface.
    fn level(&self) -> f64 {
        0.0
    }

    /// Which side of channel 0's surface is inside.
    fn inside(&self) -> Inside;
}

/// A [`ConditionalField`] with its latent code bound: `p ↦ f(p, z)`.
///
/// The code is `[D]` (shared by all points, broadcast to `[N, D]`) or `[N, D]` (one per
/// point; then every call must pass exactly `N` points). Given to the `dvr` ray marchers
/// (which call [`ImplicitSurface::value_on_rays`]), an `[R, D]` code is one per *ray*:
/// each sample takes the code of its ray, so rays through different shapes march in one
/// batch. Gradients flow to the code if it is a `Var` or depends on one (auto-decoding,
/// encoders).
#[derive(Clone, Debug)]
pub struct Conditioned<'a, F: ?Sized> {
    field: &'a F,
    code: Tensor,
}

impl<'a, F: ConditionalField + ?Sized> Conditioned<'a, F> {
    /// Binds `code: [D]` or `[N, D]` to `field`.
    ///
    /// # Errors
    /// `code` not of rank 1 or 2, or its last dimension not `field.code_dim()`.
    pub fn new(field: &'a F, code: Tensor) -> Result<Self> {
        let d = field.code_dim();
        match code.rank() {
            1 => check_shape(&code, "code", &[Dim::Is(d)])?,
            _ => check_shape(&code, "code", &[Dim::Any("N"), Dim::Is(d)])?,
        };
        Ok(Self { field, code })
    }

    fn codes_for(&self, points: &Tensor) -> Result<Tensor> {
        let n = check_points(points, "points")?;
        check_same(&self.code, "code", points, "points")?;
        let d = self.field.code_dim();
        if self.code.rank() == 1 {
            return Ok(self.code.unsqueeze(0)?.broadcast_as((n, d))?);
        }
        if self.code.dim(0)? != n {
            return Err(Error::invalid(
                "points",
                format!(
                    "{} points (one per row of the bound code)",
                    self.code.dim(0)?
                ),
                format!("{n}"),
            ));
        }
        Ok(self.code.clone())
    }

    /// Codes for points on rays: the shared `[D]` code broadcast, or row `rays[i]` of an
    /// `[R, D]` code (one per ray) for point i.
    fn codes_on_rays(&self, points: &Tensor, rays: &Tensor) -> Result<Tensor> {
        if self.code.rank() == 1 {
            return self.codes_for(points);
        }
        let n = check_points(points, "points")?;
        check_shape(rays, "rays", &[Dim::Is(n)])?;
        if rays.dtype() != DType::U32 || !rays.device().same_device(points.device()) {
            return Err(Error::invalid(
                "rays",
                "u32 ray indices on the device of points",
                format!("{:?} on {:?}", rays.dtype(), rays.device()),
            ));
        }
        let rows = self.code.dim(0)?;
        if n > 0 {
            let max = rays.max(0)?.to_scalar::<u32>()? as usize;
            if max >= rows {
                return Err(Error::invalid(
                    "code",
                    format!("one row per ray (at least {} rows)", max + 1),
                    format!("{rows} rows"),
                ));
            }
        }
        Ok(self.code.index_select(rays, 0)?)
    }
}

impl<F: ConditionalField + ?Sized> Field for Conditioned<'_, F> {
    fn out_dim(&self) -> usize {
        self.field.out_dim()
    }

    fn forward(&self, points: &Tensor) -> Result<Tensor> {
        let codes = self.codes_for(points)?;
        self.field.forward_with_code(points, &codes)
    }
}

impl<F: ConditionalField + ?Sized> ImplicitSurface for Conditioned<'_, F> {
    fn value(&self, points: &Tensor) -> Result<Tensor> {
        Ok(self.forward(points)?.narrow(1, 0, 1)?.squeeze(1)?)
    }

    fn value_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let codes = self.codes_for(points)?;
        self.field.value_and_grad_with_code(points, &codes)
    }

    fn value_on_rays(&self, points: &Tensor, rays: &Tensor) -> Result<Tensor> {
        let codes = self.codes_on_rays(points, rays)?;
        Ok(self
            .field
            .forward_with_code(points, &codes)?
            .narrow(1, 0, 1)?
            .squeeze(1)?)
    }

    fn value_and_grad_on_rays(&self, points: &Tensor, rays: &Tensor) -> Result<(Tensor, Tensor)> {
        let codes = self.codes_on_rays(points, rays)?;
        self.field.value_and_grad_with_code(points, &codes)
    }

    fn level(&self) -> f64 {
        self.field.level()
    }

    fn inside(&self) -> Inside {
        self.field.inside()
    }
}

/// An analytic signed distance function `d(p)`: negative inside, `‖∇d‖ = 1` almost
/// everywhere, with an exact gradient.
pub trait SignedDistance {
    /// `d(points)` and `∇ₚd`: `[N]` and `[N, 3]`, in the points' dtype, differentiable
    /// w.r.t. the shape's parameter tensors.
    ///
    /// # Errors
    /// Wrong shape, dtype or device of `points`.
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)>;

    /// The shape as an SDF surface (level 0, inside negative).
    fn sdf(self) -> Sdf<Self>
    where
        Self: Sized,
    {
        Sdf(self)
    }

    /// The shape as occupancy logits `−sharpness·d(p)` (level 0, inside positive), so
    /// `σ(logit)` is a soft occupancy whose transition has width ~`1/sharpness`.
    fn occupancy(self, sharpness: f64) -> Occupancy<Self>
    where
        Self: Sized,
    {
        Occupancy {
            shape: self,
            sharpness,
        }
    }
}

/// A [`SignedDistance`] used as an SDF surface: `f = d`, level 0, inside negative.
#[derive(Clone, Debug)]
pub struct Sdf<S>(pub S);

/// A [`SignedDistance`] used as occupancy logits: `f = −k·d`, level 0, inside positive.
#[derive(Clone, Debug)]
pub struct Occupancy<S> {
    /// The shape.
    pub shape: S,
    /// `k > 0`: logits per unit of distance.
    pub sharpness: f64,
}

impl<S: SignedDistance> ImplicitSurface for Sdf<S> {
    fn value(&self, points: &Tensor) -> Result<Tensor> {
        Ok(self.0.distance_and_grad(points)?.0)
    }
    fn value_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        self.0.distance_and_grad(points)
    }
    fn inside(&self) -> Inside {
        Inside::Negative
    }
}

impl<S: SignedDistance> ImplicitSurface for Occupancy<S> {
    fn value(&self, points: &Tensor) -> Result<Tensor> {
        Ok(self.value_and_grad(points)?.0)
    }
    fn value_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        check_scalar(self.sharpness, "sharpness", true)?;
        let (d, g) = self.shape.distance_and_grad(points)?;
        let k = -self.sharpness;
        Ok((d.affine(k, 0.0)?, g.affine(k, 0.0)?))
    }
    fn inside(&self) -> Inside {
        Inside::Positive
    }
}

impl<S: SignedDistance> Field for Sdf<S> {
    fn out_dim(&self) -> usize {
        1
    }
    fn forward(&self, points: &Tensor) -> Result<Tensor> {
        Ok(self.value(points)?.unsqueeze(1)?)
    }
}

impl<S: SignedDistance> Field for Occupancy<S> {
    fn out_dim(&self) -> usize {
        1
    }
    fn forward(&self, points: &Tensor) -> Result<Tensor> {
        Ok(self.value(points)?.unsqueeze(1)?)
    }
}

/// Row-wise unit vectors and norms of `x: [N, K]`: `(x/‖x‖ [N, K], ‖x‖ [N, 1])`, with
/// the unit vector 0 where `x = 0`.
///
/// Rows are first divided by their detached largest magnitude `m` (`u = x/m`,
/// `s = ‖u‖ ∈ [1, √K]`), so neither the value nor the backward ever forms `‖x‖²`: no
/// overflow for huge rows (f32 beyond 1.8e19), no underflow for tiny ones, and the
/// gradients of `u/s = x/‖x‖` and `m·s = ‖x‖` are the exact ones (both are functions of
/// `x` alone for any fixed `m`). Double where: no division ever sees a zero.
fn unit_and_norm(x: &Tensor) -> Result<(Tensor, Tensor)> {
    let n = x.dim(0)?;
    if x.elem_count() == 0 {
        // candle refuses to take the maximum of nothing.
        return Ok((x.clone(), Tensor::zeros((n, 1), x.dtype(), x.device())?));
    }
    let m = x.detach().abs()?.max_keepdim(1)?;
    let pos = m.gt(0.0)?;
    let m_safe = pos.where_cond(&m, &m.ones_like()?)?;
    let u = x.broadcast_div(&m_safe)?;
    let sq = u.sqr()?.sum_keepdim(1)?;
    let s = pos.where_cond(&sq, &sq.ones_like()?)?.sqrt()?;
    let unit = pos
        .broadcast_as(u.shape())?
        .where_cond(&u.broadcast_div(&s)?, &u.zeros_like()?)?;
    let norm = pos.where_cond(&(s * &m_safe)?, &sq.zeros_like()?)?;
    Ok((unit, norm))
}

/// A constant parameter tensor of the given shape; `arg` names the constructor argument
/// the values came from (in the error when one is not finite).
fn param(
    arg: &'static str,
    values: &[f64],
    shape: &[usize],
    device: &Device,
    dtype: DType,
) -> Result<Tensor> {
    for &v in values {
        check_scalar(v, arg, false)?;
    }
    Ok(Tensor::from_slice(values, shape, device)?.to_dtype(dtype)?)
}

fn offset(points: &Tensor, center: &Tensor) -> Result<Tensor> {
    check_points(points, "points")?;
    check_same(points, "points", center, "the shape's parameters")?;
    Ok(points.broadcast_sub(&center.unsqueeze(0)?)?)
}

/// A sphere: `d(p) = ‖p − c‖ − r`, `∇d = (p − c)/‖p − c‖` (0 at the centre).
#[derive(Clone, Debug)]
pub struct Sphere {
    /// Centre `c: [3]`.
    pub center: Tensor,
    /// Radius `r`: a scalar tensor (shape `[]`).
    pub radius: Tensor,
}

impl Sphere {
    /// A sphere with constant parameters in the given dtype and device.
    ///
    /// # Errors
    /// Non-finite parameters or `radius ≤ 0`.
    pub fn new(center: [f64; 3], radius: f64, device: &Device, dtype: DType) -> Result<Self> {
        check_scalar(radius, "radius", true)?;
        Ok(Self {
            center: param("center", &center, &[3], device, dtype)?,
            radius: param("radius", &[radius], &[], device, dtype)?,
        })
    }
}

impl SignedDistance for Sphere {
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let (unit, n) = unit_and_norm(&offset(points, &self.center)?)?;
        let dist = n.squeeze(1)?.broadcast_sub(&self.radius)?;
        Ok((dist, unit))
    }
}

/// An axis-aligned box with centre `c` and half-extents `h`:
/// `d(p) = ‖max(q, 0)‖ + min(maxᵢ qᵢ, 0)` with `q = |p − c| − h` (exact SDF).
///
/// Gradient: outside, `sgn(p − c) ⊙ max(q, 0)/‖max(q, 0)‖`; inside, `sgn(pⱼ − cⱼ)·eⱼ`
/// for the axis `j` of the largest `qⱼ` (on the medial planes, where two axes tie, the
/// ties are averaged).
#[derive(Clone, Debug)]
pub struct Cuboid {
    /// Centre `c: [3]`.
    pub center: Tensor,
    /// Half-extents `h: [3]`, all positive.
    pub half_extents: Tensor,
}

impl Cuboid {
    /// A box with constant parameters.
    ///
    /// # Errors
    /// Non-finite parameters or a half-extent ≤ 0.
    pub fn new(
        center: [f64; 3],
        half_extents: [f64; 3],
        device: &Device,
        dtype: DType,
    ) -> Result<Self> {
        for h in half_extents {
            check_scalar(h, "half_extents", true)?;
        }
        Ok(Self {
            center: param("center", &center, &[3], device, dtype)?,
            half_extents: param("half_extents", &half_extents, &[3], device, dtype)?,
        })
    }
}

/// `+1` where `x ≥ 0`, `−1` elsewhere (the side of a medial plane; `+1` on it).
fn side(x: &Tensor) -> Result<Tensor> {
    let ones = x.ones_like()?;
    Ok(x.ge(0.0)?.where_cond(&ones, &ones.neg()?)?)
}

/// The exact SDF of the box `{q ≤ 0}` in `K` dimensions, given each point's face
/// coordinates `q: [N, K]` (`qᵢ = |xᵢ| − hᵢ`): `d = ‖max(q, 0)‖ + min(maxᵢ qᵢ, 0)` as
/// `[N]`, and `∂d/∂q: [N, K]`: outside `max(q, 0)/‖max(q, 0)‖`, inside the one-hot of the
/// largest `qⱼ` (ties averaged). Shared by the boxes (`K = 3`) and the capped cylinder
/// (`K = 2`: radial and axial).
///
/// Inside (and on the surface, `max q = 0`) the value is computed as `Σⱼ wⱼqⱼ` with the
/// detached weights `w` of the gradient, so that its backward (to the shape's parameters)
/// is that same `w`: candle's `max` would give every tied `qⱼ` the full gradient, and a
/// `min(·, 0)` at `max q = 0` half of it.
fn box_distance(q: &Tensor) -> Result<(Tensor, Tensor)> {
    let n = q.dim(0)?;
    if q.elem_count() == 0 {
        return Ok((Tensor::zeros(n, q.dtype(), q.device())?, q.clone()));
    }
    let (q_unit, outside_norm) = unit_and_norm(&q.relu()?)?;
    let q_max = q.detach().max_keepdim(1)?;
    let onehot = q.detach().broadcast_eq(&q_max)?.to_dtype(q.dtype())?;
    let w_in = onehot.broadcast_div(&onehot.sum_keepdim(1)?)?;
    let inside = (q * &w_in)?.sum_keepdim(1)?;
    let is_out = outside_norm.gt(0.0)?;
    let dist = is_out.where_cond(&outside_norm, &inside)?.squeeze(1)?;
    let is_out = is_out.broadcast_as(q.shape())?;
    Ok((dist, is_out.where_cond(&q_unit, &w_in)?))
}

/// The box SDF with centre `center` and half-extents `half: [3]` at `points`, and its
/// spatial gradient `sgn(p − c) ⊙ ∂d/∂q`.
fn box_sdf(points: &Tensor, center: &Tensor, half: &Tensor) -> Result<(Tensor, Tensor)> {
    let d = offset(points, center)?;
    let q = d.abs()?.broadcast_sub(&half.unsqueeze(0)?)?;
    let (dist, w) = box_distance(&q)?;
    Ok((dist, (w * side(&d)?)?))
}

impl SignedDistance for Cuboid {
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        box_sdf(points, &self.center, &self.half_extents)
    }
}

/// A box with rounded edges and corners: the axis-aligned box with centre `c` and
/// half-extents `h` whose edges are rounded with radius `r` (`0 < r ≤ minᵢ hᵢ`), i.e. the
/// points within `r` of the inner box with half-extents `h − r`:
/// `d(p) = d_box(p; c, h − r) − r` (exact SDF, inside and out; [`Cuboid`]'s formula).
///
/// Gradient: that of the inner box, `sgn(p − c) ⊙ max(q, 0)/‖max(q, 0)‖` with
/// `q = |p − c| − (h − r)` outside the inner box (continuous across the rounded edges and
/// corners), and `sgn(pⱼ − cⱼ)·eⱼ` for the axis `j` of the largest `qⱼ` inside it (ties
/// averaged on its medial planes, where the distance has a crease). With `r = hⱼ` the
/// inner box is flat along axis `j` and its medial plane is its own face; with `r = h`
/// on every axis the shape is a sphere, whose centre gets the average `(1, 1, 1)/3`.
/// All finite; `d` and `∇d` are differentiable w.r.t. `center`, `half_extents` and
/// `radius`.
///
/// ```
/// use candle_core::{Device, DType, Tensor};
/// use neural_fields::field::{RoundedBox, SignedDistance};
///
/// let b = RoundedBox::new([0.0; 3], [1.0, 0.5, 0.5], 0.25, &Device::Cpu, DType::F64)?;
/// // Off a face, off the rounded edge along z at x = 1, y = 0.5, and the centre.
/// let p = Tensor::new(&[[1.5f64, 0.0, 0.0], [1.35, 1.05, 0.0], [0.0, 0.0, 0.0]], &Device::Cpu)?;
/// let (d, grad) = b.distance_and_grad(&p)?;
/// let d = d.to_vec1::<f64>()?;
/// // Off the edge, the nearest surface point is on the quarter circle of radius 0.25
/// // around the inner box's edge (0.75, 0.25, ·), 1 away: distance 1 − 0.25.
/// assert!((d[0] - 0.5).abs() < 1e-12 && (d[1] - 0.75).abs() < 1e-12);
/// assert!((d[2] + 0.5).abs() < 1e-12);
/// let g = &grad.to_vec2::<f64>()?[1];
/// assert!((g[0] - 0.6).abs() < 1e-12 && (g[1] - 0.8).abs() < 1e-12 && g[2] == 0.0);
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct RoundedBox {
    /// Centre `c: [3]`.
    pub center: Tensor,
    /// Half-extents `h: [3]` of the whole box (rounding included), all positive.
    pub half_extents: Tensor,
    /// Rounding radius `r` (scalar tensor), `0 < r ≤ minᵢ hᵢ`.
    pub radius: Tensor,
}

impl RoundedBox {
    /// A rounded box with constant parameters.
    ///
    /// # Errors
    /// Non-finite parameters, a half-extent ≤ 0, or `radius` not in `(0, minᵢ hᵢ]`.
    pub fn new(
        center: [f64; 3],
        half_extents: [f64; 3],
        radius: f64,
        device: &Device,
        dtype: DType,
    ) -> Result<Self> {
        for h in half_extents {
            check_scalar(h, "half_extents", true)?;
        }
        check_scalar(radius, "radius", true)?;
        let smallest = half_extents.iter().copied().fold(f64::INFINITY, f64::min);
        if radius > smallest {
            return Err(Error::invalid(
                "radius",
                format!("a rounding radius ≤ the smallest half-extent {smallest}"),
                format!("{radius}"),
            ));
        }
        Ok(Self {
            center: param("center", &center, &[3], device, dtype)?,
            half_extents: param("half_extents", &half_extents, &[3], device, dtype)?,
            radius: param("radius", &[radius], &[], device, dtype)?,
        })
    }
}

impl SignedDistance for RoundedBox {
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let inner = self.half_extents.broadcast_sub(&self.radius)?;
        let (dist, grad) = box_sdf(points, &self.center, &inner)?;
        Ok((dist.broadcast_sub(&self.radius)?, grad))
    }
}

/// A torus around the z axis through `c`: major radius `R`, minor radius `r`:
/// `d(p) = √((ρ − R)² + z²) − r` with `ρ = √(x² + y²)` in coordinates relative to `c`.
///
/// Gradient: `((ρ−R)/m · x/ρ, (ρ−R)/m · y/ρ, z/m)` with `m = √((ρ−R)² + z²)`, made
/// finite on the axis (`ρ = 0`) and on the core circle (`m = 0`).
#[derive(Clone, Debug)]
pub struct Torus {
    /// Centre `c: [3]`.
    pub center: Tensor,
    /// Major radius `R` (scalar tensor).
    pub major: Tensor,
    /// Minor radius `r` (scalar tensor).
    pub minor: Tensor,
}

impl Torus {
    /// A torus with constant parameters.
    ///
    /// # Errors
    /// Non-finite parameters, or a radius ≤ 0.
    pub fn new(
        center: [f64; 3],
        major: f64,
        minor: f64,
        device: &Device,
        dtype: DType,
    ) -> Result<Self> {
        check_scalar(major, "major", true)?;
        check_scalar(minor, "minor", true)?;
        Ok(Self {
            center: param("center", &center, &[3], device, dtype)?,
            major: param("major", &[major], &[], device, dtype)?,
            minor: param("minor", &[minor], &[], device, dtype)?,
        })
    }
}

impl SignedDistance for Torus {
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let d = offset(points, &self.center)?;
        let xy = d.narrow(1, 0, 2)?;
        let z = crate::narrow::narrow(&d, 1, 2, 1)?;
        let (radial, rho) = unit_and_norm(&xy)?; // (x/ρ, y/ρ), ρ
        let a = rho.broadcast_sub(&self.major)?;
        let q = Tensor::cat(&[&a, &z], 1)?;
        let (qn, m) = unit_and_norm(&q)?; // ((ρ−R)/m, z/m), m
        let dist = m.squeeze(1)?.broadcast_sub(&self.minor)?;
        let g_xy = radial.broadcast_mul(&qn.narrow(1, 0, 1)?)?;
        let grad = Tensor::cat(&[&g_xy, &crate::narrow::narrow(&qn, 1, 1, 1)?], 1)?;
        Ok((dist, grad))
    }
}

/// A plane `n̂·p = o` with `n̂ = n/‖n‖`: `d(p) = n̂·p − o`, `∇d = n̂`. The inside is the
/// half-space opposite to the normal.
#[derive(Clone, Debug)]
pub struct Plane {
    /// Normal `n: [3]` (normalised inside the computation, so it may be learned freely).
    pub normal: Tensor,
    /// Offset `o` (scalar tensor): the signed distance of the plane from the origin.
    pub offset: Tensor,
}

impl Plane {
    /// A plane with constant parameters.
    ///
    /// # Errors
    /// Non-finite parameters or a zero normal.
    pub fn new(normal: [f64; 3], offset: f64, device: &Device, dtype: DType) -> Result<Self> {
        let n2: f64 = normal.iter().map(|v| v * v).sum();
        if n2.is_nan() || n2 <= 0.0 || n2.is_infinite() {
            return Err(Error::invalid(
                "normal",
                "a finite non-zero vector",
                format!("{normal:?}"),
            ));
        }
        Ok(Self {
            normal: param("normal", &normal, &[3], device, dtype)?,
            offset: param("offset", &[offset], &[], device, dtype)?,
        })
    }
}

impl SignedDistance for Plane {
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let n = check_points(points, "points")?;
        check_same(points, "points", &self.normal, "the shape's parameters")?;
        let unit = self
            .normal
            .broadcast_div(&self.normal.sqr()?.sum_all()?.sqrt()?)?;
        let unit_col = unit.unsqueeze(1)?; // [3, 1]
        let dist = points
            .matmul(&unit_col)?
            .squeeze(D::Minus1)?
            .broadcast_sub(&self.offset)?;
        let grad = unit.unsqueeze(0)?.broadcast_as((n, 3))?.contiguous()?;
        Ok((dist, grad))
    }
}

/// Refuses end points `a`, `b` whose difference `b − a` overflows (the error names `b`);
/// with `distinct`, also coinciding ones. The points themselves are checked by `param`.
fn check_segment(a: [f64; 3], b: [f64; 3], distinct: bool) -> Result<()> {
    let ba: Vec<f64> = b.iter().zip(a).map(|(b, a)| b - a).collect();
    if ba.iter().all(|v| v.is_finite()) && !(distinct && ba.iter().all(|&v| v == 0.0)) {
        return Ok(());
    }
    let expected = if distinct {
        "an end centre other than a, with b − a finite"
    } else {
        "an end point with b − a finite"
    };
    Err(Error::invalid("b", expected, format!("{b:?} (a = {a:?})")))
}

/// The unit axis `(b − a)/‖b − a‖` (`[1, 3]`, 0 where `a = b`) and the length
/// `‖b − a‖` (`[1, 1]`) of a segment, after checking `points` against both ends.
fn axis(points: &Tensor, a: &Tensor, b: &Tensor) -> Result<(Tensor, Tensor)> {
    check_points(points, "points")?;
    check_same(points, "points", a, "the shape's parameters")?;
    check_same(points, "points", b, "the shape's parameters")?;
    unit_and_norm(&(b - a)?.unsqueeze(0)?)
}

/// A capsule: the points within `r` of the segment from `a` to `b`:
/// `d(p) = ‖p − a − t·(b − a)‖ − r` with `t = clamp((p − a)·(b − a)/‖b − a‖², 0, 1)` the
/// parameter of the nearest point of the segment (exact SDF).
///
/// The projection is computed as `clamp((p − a)·û, 0, L)·û` with `L = ‖b − a‖` and
/// `û = (b − a)/L` (no squared lengths, so huge shapes and points do not overflow).
/// Gradient: `v/‖v‖` with `v = p − a − t(b − a)` (the change of `t` is along `b − a`,
/// orthogonal to `v`, or zero where `t` is clamped): exact everywhere but on the segment
/// itself, where the distance has its crease and the gradient is 0 (as at a
/// [`Sphere`]'s centre). `a = b` is allowed and is the sphere of radius `r` around `a`
/// (`û = 0`, `t = 0`). All finite; `d` and `∇d` are differentiable w.r.t. `a`, `b` and
/// `radius`.
///
/// ```
/// use candle_core::{Device, DType, Tensor};
/// use neural_fields::field::{Capsule, SignedDistance};
///
/// let c = Capsule::new([0.0, 0.0, -1.0], [0.0, 0.0, 1.0], 0.5, &Device::Cpu, DType::F64)?;
/// // Beside the segment, beyond its end b, and on it.
/// let p = Tensor::new(&[[2.0f64, 0.0, 0.3], [0.0, 0.0, 3.0], [0.0, 0.0, 0.5]], &Device::Cpu)?;
/// let (d, grad) = c.distance_and_grad(&p)?;
/// assert_eq!(d.to_vec1::<f64>()?, vec![1.5, 1.5, -0.5]);
/// assert_eq!(grad.to_vec2::<f64>()?, vec![[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct Capsule {
    /// One end `a: [3]` of the segment.
    pub a: Tensor,
    /// The other end `b: [3]` (may equal `a`).
    pub b: Tensor,
    /// Radius `r` (scalar tensor).
    pub radius: Tensor,
}

impl Capsule {
    /// A capsule with constant parameters.
    ///
    /// # Errors
    /// Non-finite parameters, `b − a` not finite (named `b`), or `radius ≤ 0`.
    pub fn new(
        a: [f64; 3],
        b: [f64; 3],
        radius: f64,
        device: &Device,
        dtype: DType,
    ) -> Result<Self> {
        check_scalar(radius, "radius", true)?;
        let a_t = param("a", &a, &[3], device, dtype)?;
        let b_t = param("b", &b, &[3], device, dtype)?;
        check_segment(a, b, false)?;
        Ok(Self {
            a: a_t,
            b: b_t,
            radius: param("radius", &[radius], &[], device, dtype)?,
        })
    }
}

impl SignedDistance for Capsule {
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let (u, len) = axis(points, &self.a, &self.b)?;
        let pa = offset(points, &self.a)?;
        let along = pa.broadcast_mul(&u)?.sum_keepdim(1)?; // (p − a)·û: [N, 1]
        let t = along.maximum(0.0)?.broadcast_minimum(&len)?;
        let v = (pa - t.broadcast_mul(&u)?)?;
        let (unit, n) = unit_and_norm(&v)?;
        Ok((n.squeeze(1)?.broadcast_sub(&self.radius)?, unit))
    }
}

/// A capped cylinder of radius `r` whose axis runs from the centre `a` of one flat cap to
/// the centre `b` of the other. With `m = (a + b)/2`, `û = (b − a)/L`, `L = ‖b − a‖`, the
/// axial coordinate `y = (p − m)·û` and the distance from the axis
/// `ρ = ‖p − m − y·û‖`, it is the 2-D box `q = (ρ − r, |y| − L/2)`:
/// `d(p) = ‖max(q, 0)‖ + min(max(q₀, q₁), 0)` (exact SDF: outside, the distance to the
/// side (`q₀ > 0 ≥ q₁`), a cap (`q₁ > 0 ≥ q₀`) or the rim circle (both `> 0`); inside,
/// the nearer of side and caps).
///
/// Gradient, with `ê = (p − m − y·û)/ρ` (radial) and `s = sgn y`: outside
/// `(max(q₀, 0)·ê + max(q₁, 0)·s·û)/‖max(q, 0)‖`, exact up to the rim circle, where it
/// turns continuously from `ê` to `s·û`; inside `ê` where the side is nearer, `s·û` where
/// a cap is, and their average on the crease where both are equally near (the rim
/// circle itself included). On the axis `ê` is 0, so where the side is nearest (a long
/// thin cylinder's core) the gradient is 0; on the mid-plane `y = 0`, `s = +1`. All
/// finite; `d` and `∇d` are differentiable w.r.t. `a`, `b` and `radius`. [`Cylinder::new`]
/// refuses `a = b`; a cylinder whose ends are made to coincide through the fields is a
/// flat disk of undefined orientation and evaluates to finite values.
///
/// ```
/// use candle_core::{Device, DType, Tensor};
/// use neural_fields::field::{Cylinder, SignedDistance};
///
/// let c = Cylinder::new([0.0, 0.0, -1.0], [0.0, 0.0, 1.0], 0.5, &Device::Cpu, DType::F64)?;
/// // Beside the side, above a cap, off the rim, and inside nearer the side.
/// let p = Tensor::new(
///     &[[2.0f64, 0.0, 0.3], [0.0, 0.1, 3.0], [0.0, 3.5, 5.0], [0.0, 0.25, 0.0]],
///     &Device::Cpu,
/// )?;
/// let (d, grad) = c.distance_and_grad(&p)?;
/// assert_eq!(d.to_vec1::<f64>()?, vec![1.5, 2.0, 5.0, -0.25]);
/// let g = grad.to_vec2::<f64>()?;
/// assert_eq!((g[0][0], g[1][2], g[3][1]), (1.0, 1.0, 1.0));
/// assert!((g[2][1] - 0.6).abs() < 1e-12 && (g[2][2] - 0.8).abs() < 1e-12);
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct Cylinder {
    /// The centre `a: [3]` of one cap.
    pub a: Tensor,
    /// The centre `b: [3]` of the other cap (`≠ a`).
    pub b: Tensor,
    /// Radius `r` (scalar tensor).
    pub radius: Tensor,
}

impl Cylinder {
    /// A capped cylinder with constant parameters.
    ///
    /// # Errors
    /// Non-finite parameters, `b = a` or `b − a` not finite (named `b`), or
    /// `radius ≤ 0`.
    pub fn new(
        a: [f64; 3],
        b: [f64; 3],
        radius: f64,
        device: &Device,
        dtype: DType,
    ) -> Result<Self> {
        check_scalar(radius, "radius", true)?;
        let a_t = param("a", &a, &[3], device, dtype)?;
        let b_t = param("b", &b, &[3], device, dtype)?;
        check_segment(a, b, true)?;
        Ok(Self {
            a: a_t,
            b: b_t,
            radius: param("radius", &[radius], &[], device, dtype)?,
        })
    }
}

impl SignedDistance for Cylinder {
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let (u, len) = axis(points, &self.a, &self.b)?;
        let mid = (self.a.affine(0.5, 0.0)? + self.b.affine(0.5, 0.0)?)?;
        let pm = offset(points, &mid)?;
        let y = pm.broadcast_mul(&u)?.sum_keepdim(1)?; // [N, 1]
        let (radial, rho) = unit_and_norm(&(&pm - y.broadcast_mul(&u)?)?)?;
        let q = Tensor::cat(
            &[
                &rho.broadcast_sub(&self.radius)?,
                &y.abs()?.broadcast_sub(&len.affine(0.5, 0.0)?)?,
            ],
            1,
        )?;
        let (dist, w) = box_distance(&q)?;
        let w_side = crate::narrow::narrow(&w, 1, 0, 1)?;
        let w_cap = (crate::narrow::narrow(&w, 1, 1, 1)? * side(&y)?)?;
        let grad = (radial.broadcast_mul(&w_side)? + w_cap.broadcast_mul(&u)?)?;
        Ok((dist, grad))
    }
}

/// How [`Csg`] combines its two operands' distances `a` and `b`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CsgOp {
    /// `min(a, b)`: either shape. Gradient of the nearer operand (the average of both
    /// where they tie).
    Union,
    /// `max(a, b)`: both shapes. Gradient of the farther operand (ties averaged).
    Intersection,
    /// `max(a, −b)`: the first shape with the second cut away. Gradient `∇a` or `−∇b`
    /// (ties averaged).
    Difference,
    /// The polynomial smooth minimum (Inigo Quilez's quadratic `smin`) with blend width
    /// `k > 0`: `h = clamp(½ + ½(b − a)/k, 0, 1)`, `d = h·a + (1 − h)·b − k·h(1 − h)`.
    /// Equal to `min(a, b)` where `|a − b| ≥ k`, below it (by at most `k/4`, at
    /// `a = b`) in between, and continuously differentiable everywhere:
    /// `∂d/∂a = h`, `∂d/∂b = 1 − h` (the `h'` terms cancel), so `∇d = h·∇a + (1 − h)·∇b`,
    /// defined where the plain union has its crease.
    SmoothUnion {
        /// Blend width `k` (in units of distance), finite and `> 0` in the points' dtype;
        /// checked when the combination is evaluated.
        k: f64,
    },
}

/// Constructive solid geometry: two [`SignedDistance`] shapes combined by a [`CsgOp`],
/// itself a [`SignedDistance`] (so combinations nest, and [`SignedDistance::sdf`] and
/// [`SignedDistance::occupancy`] apply).
///
/// The result has the right sign for the combined shape, but it is a *bound*, not the
/// exact distance: `|d|` never exceeds the distance to the combined surface for
/// [`CsgOp::Union`], [`CsgOp::Intersection`] and [`CsgOp::Difference`] (exact outside
/// a union and inside an intersection, smaller elsewhere, e.g. inside a union where the
/// operands overlap), and `‖∇d‖ ≤ 1` everywhere when the operands' are (so sphere
/// tracing stays safe), with
/// `‖∇d‖ < 1` in a [`CsgOp::SmoothUnion`]'s blend region `|a − b| < k`, whose surface
/// is the blended one. Min and max have a crease where `a = b`: there the gradient is the
/// average of the operands' (not a unit vector); use the smooth union where a gradient
/// must stay defined. `d` and `∇d` are differentiable w.r.t. both operands' parameters.
///
/// ```
/// use std::sync::Arc;
/// use candle_core::{Device, DType, Tensor};
/// use neural_fields::field::{Csg, CsgOp, SignedDistance, Sphere};
///
/// let dev = Device::Cpu;
/// let left = Sphere::new([-0.5, 0.0, 0.0], 0.75, &dev, DType::F64)?;
/// let right = Sphere::new([0.5, 0.0, 0.0], 0.75, &dev, DType::F64)?;
/// let blend = Csg { op: CsgOp::SmoothUnion { k: 0.2 }, a: Arc::new(left), b: Arc::new(right) };
/// let cut = Csg { op: CsgOp::Difference, a: Arc::new(blend.clone()), b: blend.b.clone() };
/// let p = Tensor::new(&[[0.0f64, 0.0, 0.0], [-2.0, 0.0, 0.0]], &dev)?;
/// let (d, grad) = blend.distance_and_grad(&p)?;
/// let d = d.to_vec1::<f64>()?;
/// // Midway both spheres are 0.25 deep: h = ½, d = −0.25 − 0.2/4; far left, the left one.
/// assert!((d[0] + 0.3).abs() < 1e-12 && (d[1] - 0.75).abs() < 1e-12);
/// assert_eq!(grad.to_vec2::<f64>()?[0], vec![0.0, 0.0, 0.0]); // ½(1, 0, 0) + ½(−1, 0, 0)
/// let (d, _) = cut.distance_and_grad(&p)?; // the origin lies inside the cut-away sphere
/// assert!((d.to_vec1::<f64>()?[0] - 0.25).abs() < 1e-12);
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone)]
pub struct Csg {
    /// How the operands combine.
    pub op: CsgOp,
    /// The first operand.
    pub a: std::sync::Arc<dyn SignedDistance + Send + Sync>,
    /// The second operand (the one cut away by [`CsgOp::Difference`]).
    pub b: std::sync::Arc<dyn SignedDistance + Send + Sync>,
}

impl std::fmt::Debug for Csg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Csg")
            .field("op", &self.op)
            .finish_non_exhaustive()
    }
}

/// `max(a, b)` (`larger`) or `min(a, b)` with the chosen operand's gradient, ties
/// averaged (as candle's backward of `maximum`/`minimum` averages them).
fn pick(
    larger: bool,
    (da, ga): (Tensor, Tensor),
    (db, gb): (Tensor, Tensor),
) -> Result<(Tensor, Tensor)> {
    let (d, wa, wb) = if larger {
        (da.maximum(&db)?, da.ge(&db)?, db.ge(&da)?)
    } else {
        (da.minimum(&db)?, da.le(&db)?, db.le(&da)?)
    };
    let (wa, wb) = (wa.to_dtype(da.dtype())?, wb.to_dtype(da.dtype())?);
    let total = (&wa + &wb)?;
    let wa = (wa / &total)?.unsqueeze(1)?;
    let wb = (wb / &total)?.unsqueeze(1)?;
    let g = (ga.broadcast_mul(&wa)? + gb.broadcast_mul(&wb)?)?;
    Ok((d, g))
}

impl SignedDistance for Csg {
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        check_points(points, "points")?;
        if let CsgOp::SmoothUnion { k } = self.op {
            check_scalar(k, "k", true)?;
            // k must stay finite and non-zero in the points' dtype (f32 or f64).
            let k32 = k as f32;
            if points.dtype() != DType::F64 && !(k32.is_finite() && k32 > 0.0) {
                return Err(Error::invalid(
                    "k",
                    format!("a blend width representable in {:?}", points.dtype()),
                    format!("{k}"),
                ));
            }
        }
        let a = self.a.distance_and_grad(points)?;
        let b = self.b.distance_and_grad(points)?;
        match self.op {
            CsgOp::Union => pick(false, a, b),
            CsgOp::Intersection => pick(true, a, b),
            CsgOp::Difference => pick(true, a, (b.0.neg()?, b.1.neg()?)),
            CsgOp::SmoothUnion { k } => {
                let ((da, ga), (db, gb)) = (a, b);
                let kt = param("k", &[k], &[], points.device(), points.dtype())?;
                let h = (&db - &da)?
                    .broadcast_div(&kt)?
                    .affine(0.5, 0.5)?
                    .clamp(0.0, 1.0)?;
                let rest = h.affine(-1.0, 1.0)?; // 1 − h
                let bump = (&h * &rest)?.broadcast_mul(&kt)?;
                let d = ((&h * &da)? + (&rest * &db)? - bump)?;
                let g = (ga.broadcast_mul(&h.unsqueeze(1)?)?
                    + gb.broadcast_mul(&rest.unsqueeze(1)?)?)?;
                Ok((d, g))
            }
        }
    }
}
