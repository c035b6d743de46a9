//! Camera poses: learnable pose parameters and the rays they cast (one pose per view, in
//! one batch), the pose step of a Levenberg–Marquardt solver, and BARF's pose error.

use super::rays::{scalar_f64, Rays};
use super::{check_pose, Camera, Convention};
use crate::error::{check_dtype, check_finite, check_float, check_same, check_shape, Dim};
use crate::error::{Error, Result};
use candle_core::{DType, Device, Tensor, Var};
use glam::{DAffine3, DMat3, DQuat, DVec3};

/// A differentiable camera-to-world pose: a quaternion `q = (w, x, y, z)` (any non-zero
/// scale; the rotation is that of `q/|q|`) and a translation `t`, as candle variables for
/// an optimiser.
///
/// `R(q) = M(q) / |q|²` with `M` the homogeneous quaternion matrix (see
/// `docs/math.md`), so unconstrained steps on `q` always give a valid rotation.
/// Unconstrained optimisers let `|q|` drift up slowly, and the effective step size falls
/// as `1/|q|²`; setting `rotation` now and then from
/// `PoseParam::from_affine(&pose.to_affine()?, ..)` (a unit quaternion of the same
/// rotation) undoes that. [`pose_rays`] casts rays from a batch of them.
#[derive(Clone, Debug)]
pub struct PoseParam {
    /// Quaternion `[4]`, order `(w, x, y, z)`; need not be unit length, must be non-zero.
    pub rotation: Var,
    /// Translation (camera centre) `[3]`.
    pub translation: Var,
}

impl PoseParam {
    /// Variables initialised to the rigid transform `pose` (unit quaternion, translation).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `pose` unless it is a finite rigid transform
    /// (as in [`Camera::new`]), `dtype` unless f32 or f64.
    pub fn from_affine(pose: &DAffine3, device: &Device, dtype: DType) -> Result<Self> {
        check_pose(pose, "pose")?;
        check_dtype(dtype)?;
        let q = DQuat::from_mat3(&pose.matrix3).normalize();
        let t = pose.translation;
        let rotation =
            Var::from_tensor(&Tensor::new(&[q.w, q.x, q.y, q.z], device)?.to_dtype(dtype)?)?;
        let translation =
            Var::from_tensor(&Tensor::new(&[t.x, t.y, t.z], device)?.to_dtype(dtype)?)?;
        Ok(Self {
            rotation,
            translation,
        })
    }

    fn check(&self) -> Result<()> {
        check_float(&self.rotation, "rotation")?;
        check_shape(&self.rotation, "rotation", &[Dim::Is(4)])?;
        check_float(&self.translation, "translation")?;
        check_shape(&self.translation, "translation", &[Dim::Is(3)])?;
        check_same(&self.translation, "translation", &self.rotation, "rotation")?;
        check_finite(&self.rotation, "rotation")?;
        check_finite(&self.translation, "translation")
    }

    /// The rotation `R(q/|q|)` as a `[3, 3]` tensor (dtype and device of the variables),
    /// computed as `M(q')/|q'|²` with `q' = q / max|qᵢ|` (a detached scale; `R` is
    /// invariant to it) and
    ///
    /// ```text
    /// M = [[w²+x²−y²−z², 2(xy−wz),    2(xz+wy)   ],
    ///      [2(xy+wz),    w²−x²+y²−z², 2(yz−wx)   ],
    ///      [2(xz−wy),    2(yz+wx),    w²−x²−y²+z²]]
    /// ```
    ///
    /// Differentiable w.r.t. `rotation`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `rotation` if it is zero, non-finite or not a
    /// float `[4]`, or `translation` if it is not a float `[3]` of the same dtype/device.
    pub(crate) fn rotation_matrix(&self) -> Result<Tensor> {
        self.check()?;
        let q = self.rotation.as_tensor();
        let m = q.detach().abs()?.max_keepdim(0)?;
        if scalar_f64(&m.squeeze(0)?)?.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return Err(Error::invalid("rotation", "a non-zero quaternion", "0"));
        }
        let q = q.broadcast_div(&m)?;
        let c = |i: usize| q.narrow(0, i, 1);
        let (w, x, y, z) = (c(0)?, c(1)?, c(2)?, c(3)?);
        let (ww, xx, yy, zz) = (w.sqr()?, x.sqr()?, y.sqr()?, z.sqr()?);
        let two = |a: &Tensor, b: &Tensor| -> Result<Tensor> { Ok((a * b)?.affine(2.0, 0.0)?) };
        let entries = [
            ((&ww + &xx)? - (&yy + &zz)?)?,
            (two(&x, &y)? - two(&w, &z)?)?,
            (two(&x, &z)? + two(&w, &y)?)?,
            (two(&x, &y)? + two(&w, &z)?)?,
            ((&ww + &yy)? - (&xx + &zz)?)?,
            (two(&y, &z)? - two(&w, &x)?)?,
            (two(&x, &z)? - two(&w, &y)?)?,
            (two(&y, &z)? + two(&w, &x)?)?,
            ((&ww + &zz)? - (&xx + &yy)?)?,
        ];
        let s = (((&ww + &xx)? + &yy)? + &zz)?;
        let mat = Tensor::cat(&entries, 0)?.broadcast_div(&s)?;
        Ok(mat.reshape((3, 3))?)
    }

    /// The current value as a rigid transform (rotation of the normalised quaternion, at
    /// any scale of `q` that f64 holds).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `rotation` if it is zero or non-finite, or
    /// `translation` if non-finite (or either has a wrong shape/dtype).
    pub fn to_affine(&self) -> Result<DAffine3> {
        self.check()?;
        let q = self
            .rotation
            .as_tensor()
            .to_dtype(DType::F64)?
            .to_vec1::<f64>()?;
        let t = self
            .translation
            .as_tensor()
            .to_dtype(DType::F64)?
            .to_vec1::<f64>()?;
        // Scaled by max|qᵢ| first, so that a tiny or huge quaternion's length does not
        // under- or overflow.
        let m = q.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
        let quat = DQuat::from_xyzw(q[1], q[2], q[3], q[0]) / m;
        let len = quat.length();
        if !(len > 0.0 && len.is_finite()) {
            return Err(Error::invalid(
                "rotation",
                "a non-zero quaternion",
                format!("{q:?}"),
            ));
        }
        Ok(DAffine3::from_rotation_translation(
            quat / len,
            DVec3::new(t[0], t[1], t[2]),
        ))
    }
}

/// `pose` (camera-to-world) moved by the rigid step `step = (ω, v)`: rotation
/// `exp([ω]×)·R` (a turn by `|ω|` radians about the world axis `ω` through the camera
/// centre), centre `c + v`.
///
/// The retraction of a Gauss–Newton or Levenberg–Marquardt step on a camera: the six
/// parameters are a local chart at `pose` with no singularity near zero, unlike Euler
/// angles, and no normalisation constraint, unlike a quaternion. Differentiate a
/// residual w.r.t. `step` at zero (analytically or by differences of this map), solve
/// for the step ([`crate::numerics::levenberg_marquardt`] does both) and apply it here.
///
/// ```
/// use glam::{DAffine3, DVec3};
/// use neural_fields::camera::retract_pose;
///
/// let pose = DAffine3::from_translation(DVec3::new(0.0, 0.0, 4.0));
/// let moved = retract_pose(&pose, [0.0, 0.0, std::f64::consts::FRAC_PI_2, 1.0, 0.0, 0.0]);
/// assert!((moved.transform_vector3(DVec3::X) - DVec3::Y).length() < 1e-15);
/// assert_eq!(moved.translation, DVec3::new(1.0, 0.0, 4.0));
/// ```
#[must_use]
pub fn retract_pose(pose: &DAffine3, step: [f64; 6]) -> DAffine3 {
    let omega = DVec3::new(step[0], step[1], step[2]);
    let angle = omega.length();
    let turn = if angle > 0.0 {
        DMat3::from_axis_angle(omega / angle, angle)
    } else {
        DMat3::IDENTITY
    };
    DAffine3::from_mat3_translation(
        turn * pose.matrix3,
        pose.translation + DVec3::new(step[3], step[4], step[5]),
    )
}

/// World rays cast from learnable poses, one pose per view, in one batch: ray `i` leaves
/// the centre `t_v` of pose `v = views[i]` along `R(q_v/|q_v|) · d_cam`, where `d_cam` is
/// the camera-space direction of the pixel coordinate `pixels[i]` under the intrinsics and
/// convention of `cameras[v]` (OpenCV `((x − cx)/fx, (y − cy)/fy, 1)`, OpenGL
/// `((x − cx)/fx, −(y − cy)/fy, −1)`, as [`Camera::rays_for_pixels`]; the cameras' own
/// poses are not read). With every pose at its camera's pose, these are the cameras' rays.
///
/// Shapes: `views: [N]` u32 (indices into `poses`), `pixels: [N, 2]` continuous pixel
/// coordinates (the centre of pixel `(u, v)` is `(u + ½, v + ½)`), both on the poses'
/// device, `pixels` in their dtype (f32 or f64). Returns `N` rays in that dtype.
/// Differentiable w.r.t. every pose's `rotation` and `translation` and w.r.t. `pixels`.
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use neural_fields::camera::{pose_rays, Camera, Convention, Intrinsics, PoseParam};
/// use neural_fields::glam::DVec3;
///
/// let k = Intrinsics::from_fov_y(4, 4, 0.8)?;
/// let cam = Camera::look_at(k, DVec3::new(0.0, -3.0, 0.0), DVec3::ZERO, DVec3::Z, Convention::OpenGl)?;
/// let pose = PoseParam::from_affine(&cam.cam_to_world(), &Device::Cpu, DType::F64)?;
/// let pixels = Tensor::new(&[[0.5f64, 0.5], [2.0, 2.0]], &Device::Cpu)?;
/// let views = Tensor::new(&[0u32, 0], &Device::Cpu)?;
/// let rays = pose_rays(&[pose], &[cam], &views, &pixels)?;
/// let same = cam.rays_for_pixels(&pixels)?;
/// let d = (rays.directions() - same.directions())?.abs()?.max_all()?.to_scalar::<f64>()?;
/// assert!(d < 1e-12);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `poses` if there are none (or as
/// [`PoseParam::from_affine`]'s variables: a zero or non-finite quaternion, wrong shapes),
/// `cameras` unless there is one per pose, `views` unless it is a u32 `[N]` tensor on the
/// poses' device with every entry below `poses.len()`, and `pixels` unless it is a finite
/// `[N, 2]` tensor of the poses' dtype and device.
pub fn pose_rays(
    poses: &[PoseParam],
    cameras: &[Camera],
    views: &Tensor,
    pixels: &Tensor,
) -> Result<Rays> {
    let Some(first) = poses.first() else {
        return Err(Error::invalid("poses", "at least one pose", "none"));
    };
    if cameras.len() != poses.len() {
        return Err(Error::invalid(
            "cameras",
            format!("{} cameras (one per pose)", poses.len()),
            cameras.len().to_string(),
        ));
    }
    let rotations = poses
        .iter()
        .map(PoseParam::rotation_matrix)
        .collect::<Result<Vec<_>>>()?;
    let like = first.translation.as_tensor();
    check_float(pixels, "pixels")?;
    check_same(pixels, "pixels", like, "poses")?;
    let n = check_shape(pixels, "pixels", &[Dim::Any("N"), Dim::Is(2)])?[0];
    check_finite(pixels, "pixels")?;
    if views.dtype() != DType::U32
        || views.dims() != [n]
        || !views.device().same_device(like.device())
    {
        return Err(Error::invalid(
            "views",
            format!("a u32 [{n}] tensor on the poses' device"),
            format!("{:?} {:?}", views.dtype(), views.dims()),
        ));
    }
    if let Some(&v) = views
        .to_vec1::<u32>()?
        .iter()
        .find(|&&v| v as usize >= poses.len())
    {
        return Err(Error::invalid(
            "views",
            format!("indices below {}", poses.len()),
            v.to_string(),
        ));
    }
    let (device, dtype) = (like.device(), like.dtype());
    // Per-ray intrinsics, gathered from one row per view.
    let per_ray = |f: &dyn Fn(&Camera) -> f64| -> Result<Tensor> {
        let values: Vec<f64> = cameras.iter().map(f).collect();
        Ok(Tensor::new(values, device)?
            .to_dtype(dtype)?
            .index_select(views, 0)?
            .unsqueeze(1)?)
    };
    let flip = |c: &Camera| match c.convention() {
        Convention::OpenCv => 1.0,
        Convention::OpenGl => -1.0,
    };
    let (fx, fy) = (
        per_ray(&|c| c.intrinsics().fx)?,
        per_ray(&|c| c.intrinsics().fy)?,
    );
    let (cx, cy) = (
        per_ray(&|c| c.intrinsics().cx)?,
        per_ray(&|c| c.intrinsics().cy)?,
    );
    let sign = per_ray(&flip)?;
    let x = pixels
        .narrow(1, 0, 1)?
        .broadcast_sub(&cx)?
        .broadcast_div(&fx)?;
    let y = crate::narrow::narrow(pixels, 1, 1, 1)?
        .broadcast_sub(&cy)?
        .broadcast_div(&fy)?
        .broadcast_mul(&sign)?;
    let d_cam = Tensor::cat(&[&x, &y, &sign], 1)?.unsqueeze(2)?;
    let r = Tensor::stack(&rotations, 0)?.index_select(views, 0)?;
    let centres: Vec<&Tensor> = poses.iter().map(|p| p.translation.as_tensor()).collect();
    let origins = Tensor::stack(&centres, 0)?.index_select(views, 0)?;
    Rays::new(origins, r.matmul(&d_cam)?.squeeze(2)?)
}

/// BARF's pose error: the mean rotation error in degrees and the mean centre error, as a
/// fraction of the true camera's distance to the world origin, of `poses` against `truth`
/// (camera-to-world, pose `i` against pose `i`):
///
/// `(1/n) Σ ∠(R_iᵀ R̂_i)` and `(1/n) Σ |c_i − ĉ_i| / |ĉ_i|`,
///
/// the angle taken from the relative rotation's quaternion `(w, v)` as `2·atan2(|v|, |w|)`,
/// which stays accurate near 0 where `acos((tr R − 1)/2)` does not. Poses refined jointly
/// with a scene are compared after the similarity that maps their centres onto the true
/// ones ([`crate::camera::align_similarity`]). Plain f64 geometry, not differentiable.
///
/// ```
/// use neural_fields::camera::{pose_error, retract_pose};
/// use neural_fields::glam::{DAffine3, DVec3};
///
/// let truth = DAffine3::from_translation(DVec3::new(0.0, 0.0, 4.0));
/// let turned = retract_pose(&truth, [0.0, 0.0, 2f64.to_radians(), 0.04, 0.0, 0.0]);
/// let (degrees, fraction) = pose_error(&[turned], &[truth])?;
/// assert!((degrees - 2.0).abs() < 1e-9 && (fraction - 0.01).abs() < 1e-12);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `poses` if there are none or one is not finite, and
/// `truth` if its length differs or one of its poses is not finite.
pub fn pose_error(poses: &[DAffine3], truth: &[DAffine3]) -> Result<(f64, f64)> {
    if poses.is_empty() {
        return Err(Error::invalid("poses", "at least one pose", "none"));
    }
    if truth.len() != poses.len() {
        return Err(Error::invalid(
            "truth",
            format!("{} poses (as many as poses)", poses.len()),
            truth.len().to_string(),
        ));
    }
    for (set, name) in [(poses, "poses"), (truth, "truth")] {
        if let Some(p) = set
            .iter()
            .find(|p| !(p.matrix3.is_finite() && p.translation.is_finite()))
        {
            return Err(Error::invalid(name, "finite poses", format!("{p:?}")));
        }
    }
    let (mut rotation, mut centre) = (0.0, 0.0);
    for (p, t) in poses.iter().zip(truth) {
        let q = DQuat::from_mat3(&(p.matrix3.transpose() * t.matrix3)).normalize();
        rotation += (2.0 * q.xyz().length().atan2(q.w.abs())).to_degrees();
        centre += (p.translation - t.translation).length() / t.translation.length().max(1e-12);
    }
    let n = poses.len() as f64;
    Ok((rotation / n, centre / n))
}
