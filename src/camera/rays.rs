//! Rays and their intersections with boxes and spheres.

use crate::error::{check_finite, check_float, check_points, check_same, check_shape, Dim};
use crate::error::{Error, Result};
use candle_core::{DType, Tensor};

/// The smallest magnitude whose square is still a normal number in `dtype`: below it a
/// direction component is treated as exactly 0, so that no `x / d²` underflows to `0/0`.
fn tiny(dtype: DType) -> f64 {
    match dtype {
        DType::F32 => f64::from(f32::MIN_POSITIVE).sqrt(),
        _ => f64::MIN_POSITIVE.sqrt(),
    }
}

pub(crate) fn scalar_f64(t: &Tensor) -> Result<f64> {
    Ok(t.to_dtype(DType::F64)?.to_scalar::<f64>()?)
}

/// A `[1, 3]` constant in the dtype and device of `like`.
pub(crate) fn row3(v: [f64; 3], like: &Tensor) -> Result<Tensor> {
    Ok(Tensor::new(&[v], like.device())?.to_dtype(like.dtype())?)
}

fn full_like(like: &Tensor, v: f64) -> Result<Tensor> {
    Ok(Tensor::full(v, like.shape(), like.device())?.to_dtype(like.dtype())?)
}

/// A batch of rays `o + t·d`: origins `[N, 3]` and directions `[N, 3]`, one float dtype
/// and device, validated once when built ([`Rays::new`]): every function that takes
/// `&Rays` relies on that and checks nothing more of them. Directions are whatever the
/// producer made them (camera rays have unit camera-space z, see the module docs).
///
/// Rays may also carry a cone radius each ([`Rays::with_radii`]): the radius, per unit of
/// the ray parameter `t`, of the cone that the ray's pixel footprint sweeps (mip-NeRF's
/// `radii`), which cone casting ([`crate::volume::conical_frustums`]) reads. Camera rays
/// carry it ([`crate::camera::Camera::rays_for_pixels`]).
#[derive(Clone, Debug)]
pub struct Rays {
    origins: Tensor,
    directions: Tensor,
    radii: Option<Tensor>,
}

impl Rays {
    /// Bundles origins and directions, after checking them: `[N, 3]` each (`N = 0`
    /// allowed), f32 or f64, one dtype and device, finite, and no zero direction (one
    /// read-back of the `6N` values). Both may carry a graph (a learnable pose's rays).
    ///
    /// ```
    /// use candle_core::{Device, Tensor};
    /// use neural_fields::camera::Rays;
    ///
    /// let o = Tensor::new(&[[0.0f32, 0.0, 0.0]], &Device::Cpu)?;
    /// let rays = Rays::new(o.clone(), Tensor::new(&[[0.0f32, 0.0, 2.0]], &Device::Cpu)?)?;
    /// assert_eq!(rays.len(), 1);
    /// assert_eq!(rays.normalized()?.directions().to_vec2::<f32>()?, vec![vec![0.0, 0.0, 1.0]]);
    /// assert!(Rays::new(o, Tensor::zeros((1, 3), candle_core::DType::F32, &Device::Cpu)?).is_err());
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `origins` unless it is `[N, 3]` f32/f64 and
    /// finite, and `directions` unless it has the same shape, dtype and device, is finite
    /// and has no zero row.
    pub fn new(origins: Tensor, directions: Tensor) -> Result<Self> {
        let n = check_points(&origins, "origins")?;
        check_points(&directions, "directions")?;
        if directions.dim(0)? != n {
            return Err(Error::invalid(
                "directions",
                format!("shape [{n}, 3] (that of origins)"),
                format!("shape {:?}", directions.dims()),
            ));
        }
        check_same(&directions, "directions", &origins, "origins")?;
        check_finite(&origins, "origins")?;
        check_finite(&directions, "directions")?;
        let rays = Self {
            origins,
            directions,
            radii: None,
        };
        if n > 0 {
            let m = direction_scale(&rays)?;
            if scalar_f64(&m.min_all()?)?.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                return Err(Error::invalid(
                    "directions",
                    "non-zero rows",
                    "a zero direction",
                ));
            }
        }
        Ok(rays)
    }

    /// The same rays carrying cone radii `radii: [N]`: ray `i`'s cone has radius
    /// `radii[i]·t` at parameter `t` (world units, measured perpendicular to the direction,
    /// so for a pinhole camera whose directions have unit depth it is the pixel's footprint
    /// at depth 1 times `2/√12`, mip-NeRF's disc of the pixel's variance). `radii` must
    /// have the rays' dtype and device, be finite and `≥ 0` (one read-back); it may carry a
    /// graph.
    ///
    /// ```
    /// use candle_core::{Device, Tensor};
    /// use neural_fields::camera::Rays;
    ///
    /// let rays = Rays::new(
    ///     Tensor::new(&[[0.0f32, 0.0, 0.0]], &Device::Cpu)?,
    ///     Tensor::new(&[[0.0f32, 0.0, 2.0]], &Device::Cpu)?,
    /// )?
    /// .with_radii(Tensor::new(&[0.01f32], &Device::Cpu)?)?;
    /// // Unit directions halve t, so the radius per unit t doubles.
    /// let unit = rays.normalized()?;
    /// let radii = unit.radii().map(|r| r.to_vec1::<f32>()).transpose()?;
    /// assert_eq!(radii, Some(vec![0.005]));
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `radii` unless it is `[N]` with the rays' dtype and
    /// device, finite and non-negative.
    pub fn with_radii(self, radii: Tensor) -> Result<Rays> {
        check_float(&radii, "radii")?;
        check_shape(&radii, "radii", &[Dim::Is(self.len())])?;
        check_same(&radii, "radii", &self.origins, "rays")?;
        check_finite(&radii, "radii")?;
        if !self.is_empty() && scalar_f64(&radii.detach().min_all()?)? < 0.0 {
            return Err(Error::invalid(
                "radii",
                "non-negative cone radii",
                "a negative radius",
            ));
        }
        Ok(Rays {
            radii: Some(radii),
            ..self
        })
    }

    /// The cone radii `[N]` ([`Rays::with_radii`]), if the rays carry them.
    #[must_use]
    pub fn radii(&self) -> Option<&Tensor> {
        self.radii.as_ref()
    }

    /// Ray origins, `[N, 3]`.
    #[must_use]
    pub fn origins(&self) -> &Tensor {
        &self.origins
    }

    /// Ray directions, `[N, 3]` (not necessarily unit length).
    #[must_use]
    pub fn directions(&self) -> &Tensor {
        &self.directions
    }

    /// Number of rays `N`.
    #[must_use]
    pub fn len(&self) -> usize {
        self.origins.dims().first().copied().unwrap_or(0)
    }

    /// Whether there are no rays.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The same rays with unit directions `d / |d|` (origins shared; cone radii, if any,
    /// divided by `|d|`, since the parameter `t` is now distance). Computed as
    /// `d' / |d'|` with `d' = d / max|dᵢ|` (a detached per-ray scale, exact because
    /// `d/|d|` is scale-invariant), so tiny directions do not underflow. Differentiable
    /// w.r.t. the directions (and the radii).
    ///
    /// # Errors
    /// Only candle errors (the rays were checked when built: no direction is zero).
    pub fn normalized(&self) -> Result<Rays> {
        if self.is_empty() {
            return Ok(self.clone());
        }
        // m > 0 on every row: `Rays::new` rejects zero directions.
        let m = direction_scale(self)?;
        let dn = self.directions.broadcast_div(&m)?;
        let norm = dn.sqr()?.sum_keepdim(1)?.sqrt()?;
        let radii = match &self.radii {
            None => None,
            // |d| = m·|d'|.
            Some(r) => Some(r.div(&(norm.squeeze(1)? * m.squeeze(1)?)?)?),
        };
        Ok(Rays {
            origins: self.origins.clone(),
            directions: dn.broadcast_div(&norm)?,
            radii,
        })
    }

    /// Rays `start .. start + len` (a view, for processing in chunks).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `start` if `start > N` and `len` if
    /// `start + len > N`.
    pub fn narrow(&self, start: usize, len: usize) -> Result<Rays> {
        let n = self.len();
        if start > n {
            return Err(Error::invalid(
                "start",
                format!("≤ {n}"),
                format!("{start}"),
            ));
        }
        if len > n - start {
            return Err(Error::invalid(
                "len",
                format!("≤ {} (N − start)", n - start),
                format!("{len}"),
            ));
        }
        Ok(Rays {
            origins: self.origins.narrow(0, start, len)?,
            directions: self.directions.narrow(0, start, len)?,
            radii: match &self.radii {
                None => None,
                Some(r) => Some(r.narrow(0, start, len)?),
            },
        })
    }
}

/// The result of a ray–shape intersection, per ray.
///
/// `near = max(t_enter, 0)` (0 when the origin is inside), `far = t_exit`,
/// `hit = (far ≥ near) ∧ (far > 0)`; for a missed ray `near = far = 0`. Values are ray
/// parameters in units of the given directions. All outputs are finite.
#[derive(Clone, Debug)]
pub struct Intersection {
    /// Entry parameter `[N]`, clamped at 0; 0 for misses.
    pub near: Tensor,
    /// Exit parameter `[N]`; 0 for misses.
    pub far: Tensor,
    /// Hit mask `[N]`, u8 (1 = hit).
    pub hit: Tensor,
}

impl Intersection {
    /// The range `[near, far]` on every ray, all marked hit: the search range of
    /// [`crate::dvr::march()`] and [`crate::dvr::sphere_trace`] when it does not come from
    /// [`ray_aabb`] or [`ray_sphere`]. A ray with `near = far` has an empty range.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `near` unless it is an f32/f64 `[N]` tensor of
    /// finite values, `far` unless it matches `near`'s shape, dtype and device, is finite
    /// and `far ≥ near` on every ray.
    pub fn new(near: Tensor, far: Tensor) -> Result<Self> {
        check_float(&near, "near")?;
        let n = check_shape(&near, "near", &[Dim::Any("N")])?[0];
        check_same(&far, "far", &near, "near")?;
        check_shape(&far, "far", &[Dim::Is(n)])?;
        check_finite(&near, "near")?;
        check_finite(&far, "far")?;
        if n > 0 && scalar_f64(&(&far - &near)?.min_all()?)? < 0.0 {
            return Err(Error::invalid(
                "far",
                "far ≥ near on every ray",
                "far < near",
            ));
        }
        let hit = Tensor::ones(n, DType::U8, near.device())?;
        Ok(Intersection { near, far, hit })
    }
}

/// The detached per-ray scale `m = max|dᵢ|`, `[N, 1]` (> 0: [`Rays::new`] rejects zero
/// directions).
fn direction_scale(rays: &Rays) -> Result<Tensor> {
    Ok(rays.directions.detach().abs()?.max_keepdim(1)?)
}

/// Shared tail: clamp, mask, rescale by `1/m`, and check that nothing overflowed.
fn finish(
    t_enter: &Tensor,
    t_exit: &Tensor,
    valid: Option<&Tensor>,
    m: &Tensor,
) -> Result<Intersection> {
    let zero = t_enter.zeros_like()?;
    let near = t_enter.maximum(&zero)?;
    let mut hit = (near.le(t_exit)? * t_exit.gt(&zero)?)?;
    if let Some(v) = valid {
        hit = (hit * v)?;
    }
    let m = m.squeeze(1)?;
    let near = hit.where_cond(&near, &zero)?.div(&m)?;
    let far = hit.where_cond(t_exit, &zero)?.div(&m)?;
    check_finite(&near, "directions")?;
    check_finite(&far, "directions")?;
    Ok(Intersection { near, far, hit })
}

fn check_center(v: [f64; 3], arg: &'static str) -> Result<()> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(Error::invalid(arg, "finite coordinates", format!("{v:?}")))
    }
}

/// Ray–axis-aligned-box intersection by the slab method.
///
/// For each axis `i` with `dᵢ ≠ 0`, the slab `[minᵢ, maxᵢ]` is crossed for
/// `t ∈ [min(t₁, t₂), max(t₁, t₂)]`, `t₁ = (minᵢ − oᵢ)/dᵢ`, `t₂ = (maxᵢ − oᵢ)/dᵢ`;
/// `t_enter` is the largest entry and `t_exit` the smallest exit. An axis with `dᵢ = 0`
/// (in practice `|dᵢ| < √(smallest normal) · max|d|`; no `0·∞` is ever formed) gives no
/// constraint if `minᵢ ≤ oᵢ ≤ maxᵢ` and a miss otherwise. The box is **closed**: a ray
/// lying in a face plane (`oᵢ = minᵢ`, `dᵢ = 0`) and crossing the face hits, and a ray
/// grazing an edge or corner hits with `near = far`. See [`Intersection`] for
/// `near/far/hit`.
///
/// `rays`: `N` rays (f32 or f64); outputs `[N]` in their dtype and on their device.
/// Differentiable w.r.t. the rays' origins and directions (gradients are zero, never
/// NaN, for missed rays and where `near` is clamped at 0).
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::camera::{ray_aabb, Rays};
///
/// let rays = Rays::new(
///     Tensor::new(&[[0.0f32, 0.0, -3.0], [5.0, 0.0, -3.0]], &Device::Cpu)?,
///     Tensor::new(&[[0.0f32, 0.0, 1.0], [0.0, 0.0, 1.0]], &Device::Cpu)?,
/// )?;
/// let box_hit = ray_aabb(&rays, [-1.0; 3], [1.0; 3])?;
/// assert_eq!(box_hit.near.to_vec1::<f32>()?, vec![2.0, 0.0]);
/// assert_eq!(box_hit.far.to_vec1::<f32>()?, vec![4.0, 0.0]);
/// assert_eq!(box_hit.hit.to_vec1::<u8>()?, vec![1, 0]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `directions` for a direction so short that the
/// parameter overflows; `min` / `max` if not finite, `max` if `minᵢ > maxᵢ`.
pub fn ray_aabb(rays: &Rays, min: [f64; 3], max: [f64; 3]) -> Result<Intersection> {
    let m = direction_scale(rays)?;
    let (origins, directions) = (&rays.origins, &rays.directions);
    check_center(min, "min")?;
    check_center(max, "max")?;
    if min.iter().zip(&max).any(|(a, b)| a > b) {
        return Err(Error::invalid(
            "max",
            format!("≥ min = {min:?} componentwise"),
            format!("{max:?}"),
        ));
    }
    let dn = directions.broadcast_div(&m)?;
    let lo = row3(min, origins)?;
    let hi = row3(max, origins)?;
    let parallel = dn.detach().abs()?.lt(tiny(dn.dtype()))?;
    let d_safe = parallel.where_cond(&dn.ones_like()?, &dn)?;
    let t1 = lo.broadcast_sub(origins)?.div(&d_safe)?;
    let t2 = hi.broadcast_sub(origins)?.div(&d_safe)?;
    let t_lo = t1.minimum(&t2)?;
    let t_hi = t1.maximum(&t2)?;
    let o = origins.detach();
    let inside = (o.broadcast_ge(&lo)? * o.broadcast_le(&hi)?)?;
    let pos_inf = full_like(&dn, f64::INFINITY)?;
    let neg_inf = full_like(&dn, f64::NEG_INFINITY)?;
    let par_lo = inside.where_cond(&neg_inf, &pos_inf)?;
    let par_hi = inside.where_cond(&pos_inf, &neg_inf)?;
    let t_lo = parallel.where_cond(&par_lo, &t_lo)?;
    let t_hi = parallel.where_cond(&par_hi, &t_hi)?;
    let t_enter = t_lo.max_keepdim(1)?.squeeze(1)?;
    let t_exit = t_hi.min_keepdim(1)?.squeeze(1)?;
    finish(&t_enter, &t_exit, None, &m)
}

/// Ray–sphere intersection.
///
/// With `d' = d / max|dᵢ|` (a detached per-ray scale; the result is divided by it again,
/// which is exact since `t(o, d) = t(o, d/s)/s` for every `s > 0`), `oc = o − c`,
/// `a = d'·d'`, `b = d'·oc`, `c₀ = oc·oc − r²`, `l = oc − (b/a) d'` and the discriminant
/// `Δ = a (r² − l·l)` (the perpendicular form, accurate near tangency). For `Δ ≥ 0`, the
/// roots are `t₁ = q/a` and `t₂ = c₀/q` with `q = −(b + sign(b)√Δ)` (no cancellation).
/// A **tangent** ray (`Δ = 0`) hits with `near = far = −b/a`, and the `√Δ` term is given
/// zero gradient there (its true derivative is infinite). See [`Intersection`] for
/// `near/far/hit`; the origin inside gives `near = 0`.
///
/// `rays`: `N` rays (f32 or f64); outputs `[N]` in their dtype and on their device.
/// Differentiable w.r.t. the rays' origins and directions (zero, never NaN, for misses).
///
/// Range: the sphere must be resolvable in the dtype at the origin's distance
/// (`r ≫ ulp(|o − c|)`); in f32 keep `|o − c| ≤ 10⁶·r`. Beyond, `|o − c|² − r²` loses `r²`,
/// and intermediate partials of the backward overflow f32 even where the true gradient
/// is finite (`tests/stiff_cases_camera.rs` sweeps within this range).
///
/// # Errors
/// [`Error::InvalidArgument`] naming `center` if not finite; `radius` unless finite and
/// > 0; `directions` if the parameter overflows.
pub fn ray_sphere(rays: &Rays, center: [f64; 3], radius: f64) -> Result<Intersection> {
    let m = direction_scale(rays)?;
    let (origins, directions) = (&rays.origins, &rays.directions);
    check_center(center, "center")?;
    crate::error::check_scalar(radius, "radius", true)?;
    let r2 = radius * radius;
    let dn = directions.broadcast_div(&m)?;
    let oc = origins.broadcast_sub(&row3(center, origins)?)?;
    let a = dn.sqr()?.sum(1)?;
    let b = (&dn * &oc)?.sum(1)?;
    let c0 = (oc.sqr()?.sum(1)? - r2)?;
    let l = (&oc - dn.broadcast_mul(&(&b / &a)?.unsqueeze(1)?)?)?;
    let disc = ((l.sqr()?.sum(1)?.neg()? + r2)? * &a)?;
    let ones = a.ones_like()?;
    let zero = a.zeros_like()?;
    let pos = disc.gt(&zero)?;
    let sq = pos.where_cond(&pos.where_cond(&disc, &ones)?.sqrt()?, &zero)?;
    let sign = b.detach().ge(&zero)?.where_cond(&ones, &ones.neg()?)?;
    let s_sq = (&sign * &sq)?;
    let q = (&b + &s_sq)?.neg()?;
    let q_big = q.detach().abs()?.ge(tiny(q.dtype()))?;
    let q_safe = q_big.where_cond(&q, &ones)?;
    let t1 = (&q / &a)?;
    let t2_stable = (&c0 / &q_safe)?;
    let t2_direct = ((&s_sq - &b)? / &a)?;
    let t2 = pos.where_cond(&q_big.where_cond(&t2_stable, &t2_direct)?, &t1)?;
    let t_enter = t1.minimum(&t2)?;
    let t_exit = t1.maximum(&t2)?;
    let valid = disc.ge(&zero)?;
    finish(&t_enter, &t_exit, Some(&valid), &m)
}
