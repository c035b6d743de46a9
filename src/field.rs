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
//! * Analytic shapes ([`Sphere`], [`Cuboid`], [`Torus`], [`Plane`]) implementing
//!   [`SignedDistance`], usable as SDFs ([`Sdf`]) or occupancy logits ([`Occupancy`]),
//!   with exact gradients and parameters held as tensors (wrap them in `Var`s to learn
//!   a radius or a centre). They are the fixtures of every test in this crate.
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

impl SignedDistance for Cuboid {
    fn distance_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let d = offset(points, &self.center)?;
        let sign = d
            .ge(0.0)?
            .where_cond(&d.ones_like()?, &d.ones_like()?.neg()?)?;
        let q = d.abs()?.broadcast_sub(&self.half_extents.unsqueeze(0)?)?;
        let q_pos = q.relu()?;
        let (q_unit, outside_norm) = unit_and_norm(&q_pos)?;
        let q_max = q.max_keepdim(1)?;
        let inside_part = q_max.clamp(f64::NEG_INFINITY, 0.0)?;
        let dist = (&outside_norm + inside_part)?.squeeze(1)?;

        let grad_out = (q_unit * &sign)?;
        let onehot = q.broadcast_eq(&q_max)?.to_dtype(q.dtype())?;
        let grad_in = (onehot.broadcast_div(&onehot.sum_keepdim(1)?)? * &sign)?;
        let is_out = outside_norm.gt(0.0)?.broadcast_as(q.shape())?;
        Ok((dist, is_out.where_cond(&grad_out, &grad_in)?))
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
