//! Pinhole cameras and what is made from them: rays and their intersections with boxes
//! and spheres, differentiable poses and the rays they cast, the pose step and pose error
//! of camera refinement, similarity alignment of cameras and scenes, reprojection error,
//! and the photometric registration of cameras to a rendered scene.
//!
//! # Conventions
//!
//! **Pixels.** Pixel coordinates are continuous image coordinates `(x, y)` with `x` the
//! column and `y` the row, the origin at the top-left corner of the top-left pixel. The
//! integer pixel `(u, v)` covers `[u, u + 1) × [v, v + 1)`, so its **centre is
//! `(u + 0.5, v + 0.5)`**. Functions that take a `pixels: [N, 2]` tensor use these
//! coordinates as given (no half-pixel offset is added); [`Camera::rays`] goes through
//! pixel centres, and so do the batches of [`crate::data::RaySampler`] without jitter.
//!
//! **Camera axes** ([`Convention`]). With intrinsics `fx, fy, cx, cy`:
//!
//! | convention | axes | camera-space direction of pixel coordinate `(x, y)` |
//! |---|---|---|
//! | [`Convention::OpenCv`] (OpenCV, COLMAP) | x right, y down, z forward | `((x − cx)/fx, (y − cy)/fy, 1)` |
//! | [`Convention::OpenGl`] (OpenGL, Blender, NeRF synthetic) | x right, y up, looking down −z | `((x − cx)/fx, −(y − cy)/fy, −1)` |
//!
//! **Directions are not normalised.** Their camera-space z-component is ±1, so the ray
//! parameter `t` of a point `o + t·d` equals its z-depth in the camera frame (the
//! "depth" of DVR, whose issue #38 is users reading it as Euclidean distance). Call
//! [`Rays::normalized`] for unit directions, in which case `t` is the Euclidean distance.
//!
//! **Poses** are camera-to-world rigid transforms ([`glam::DAffine3`]): a camera-space
//! point `p_c` maps to `R p_c + t`; the ray origin is `t`, the camera centre.

mod align;
mod pose;
mod rays;
mod registration;

pub use align::{align_cameras, align_similarity, reprojection_error, Similarity, Transformable};
pub use pose::{pose_error, pose_rays, retract_pose, PoseParam};
pub use rays::{ray_aabb, ray_sphere, Intersection, Rays};
pub use registration::{register_poses, RegistrationConfig};

use crate::error::{check_dtype, check_finite, check_float, check_shape, Dim};
use crate::error::{Error, Result};
use candle_core::{DType, Device, Tensor};
use glam::{DAffine3, DMat3, DVec2, DVec3};
use rays::row3;

/// How a pixel integrates the image around its centre: a separable filter, the same along
/// both axes, whose density over offsets `x` (in pixels, from the centre) weighs the
/// radiance arriving through `centre + (x, y)`.
///
/// - [`PixelFilter::Box`]: uniform over the pixel's square, `x ∈ [−½, ½)`: the ideal
///   area sensor, and the filter of [`Camera::subpixel_grid`]'s box grid.
/// - [`PixelFilter::BlackmanHarris`]: the four-term Blackman–Harris window of support
///   `[−h, h]`, `w(x) ∝ a₀ − a₁ cos 2πs + a₂ cos 4πs − a₃ cos 6πs` with `s = (x + h)/(2h)`
///   and `(a₀, a₁, a₂, a₃) = (0.35875, 0.48829, 0.14128, 0.01168)`. Blender's Cycles uses
///   it by default with `filter_width` 1.5, which its table builder doubles, so the
///   support is ±1.5 px ([`PixelFilter::CYCLES`]; σ ≈ 0.42 px, against a box's 0.29 px).
///   Images rendered so are the mean of radiance samples at offsets drawn from it.
///
/// The filter's quantile `q(u)`, the inverse of its cumulative distribution (box:
/// `u − ½`; Blackman–Harris: `h(2s − 1)` where `s` solves `F(s) = u` for the window's
/// cumulative distribution `F(s) = s − (a₁/2πa₀) sin 2πs + (a₂/4πa₀) sin 4πs −
/// (a₃/6πa₀) sin 6πs`), maps a uniform number to an offset, so that `k` equal-mass strata of the filter have
/// their medians at `q((j + ½)/k)`: the plain mean of the `k × k` rays through those
/// points is a quadrature of the filtered pixel ([`Camera::subpixel_grid`]), and rays
/// through `q(U)` for uniform `U` sample it
/// ([`crate::data::RaySampler::with_pixel_filter`]).
///
/// ```
/// use candle_core::{DType, Device};
/// use neural_fields::camera::{Camera, Convention, Intrinsics, PixelFilter};
/// use neural_fields::glam::DVec3;
///
/// let k = Intrinsics::from_fov_y(1, 1, 0.8)?;
/// let cam = Camera::look_at(k, DVec3::new(0.0, -3.0, 0.0), DVec3::ZERO, DVec3::Z, Convention::OpenGl)?;
/// // Offsets from the pixel's centre (½, ½) of the medians of 4 equal-mass strata.
/// let offsets = |f: PixelFilter| -> neural_fields::Result<Vec<f64>> {
///     let g = cam.subpixel_grid(4, f, &Device::Cpu, DType::F64)?.to_vec2::<f64>()?;
///     Ok(g[..4].iter().map(|p| p[0] - 0.5).collect())
/// };
/// assert_eq!(offsets(PixelFilter::Box)?, [-0.375, -0.125, 0.125, 0.375]);
/// let bh = offsets(PixelFilter::CYCLES)?;
/// assert!((bh[0] + bh[3]).abs() < 1e-12 && (bh[1] + bh[2]).abs() < 1e-12); // symmetric
/// assert!(bh[0] < -0.375 && bh[0] > -1.5); // wider than the box, within ±1.5 px
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum PixelFilter {
    /// Uniform over the pixel: offsets in `[−½, ½)`.
    #[default]
    Box,
    /// Blackman–Harris window of support `[−half_width, half_width]` pixels.
    BlackmanHarris {
        /// Half the support in pixels (Cycles: its `filter_width`, default 1.5); in
        /// `(0, 64]`.
        half_width: f64,
    },
}

const BLACKMAN_HARRIS: [f64; 4] = [0.35875, 0.48829, 0.14128, 0.01168];

impl PixelFilter {
    /// Blender Cycles' default pixel filter: Blackman–Harris, support ±1.5 px.
    pub const CYCLES: PixelFilter = PixelFilter::BlackmanHarris { half_width: 1.5 };

    /// Checks the filter's parameters.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `filter` unless `half_width` is finite and in
    /// `(0, 64]`.
    pub(crate) fn validate(&self) -> Result<()> {
        match *self {
            PixelFilter::Box => Ok(()),
            PixelFilter::BlackmanHarris { half_width } => {
                if half_width > 0.0 && half_width <= 64.0 {
                    Ok(())
                } else {
                    Err(Error::invalid(
                        "filter",
                        "a Blackman-Harris half width in (0, 64] pixels",
                        half_width.to_string(),
                    ))
                }
            }
        }
    }

    /// The offset `x` from the pixel centre (pixels, one axis) below which the filter has
    /// mass `u`: the inverse of its cumulative distribution. Box: `u − ½`. Blackman–Harris:
    /// `x = h(2s − 1)` where `s` solves `F(s) = u` for the window's cumulative distribution
    /// `F(s) = s − (a₁/2πa₀) sin 2πs + (a₂/4πa₀) sin 4πs − (a₃/6πa₀) sin 6πs` (increasing;
    /// Newton's method inside a bisection bracket, to f64 resolution in a few iterations).
    /// Not differentiable (a sampling rule).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `u` unless in `[0, 1]`, or `filter` unless a
    /// Blackman–Harris `half_width` is finite and in `(0, 64]`.
    #[cfg(test)]
    fn quantile(&self, u: f64) -> Result<f64> {
        self.validate()?;
        if !(0.0..=1.0).contains(&u) {
            return Err(Error::invalid(
                "u",
                "a probability in [0, 1]",
                u.to_string(),
            ));
        }
        Ok(self.offset_unchecked(u))
    }

    /// The filter's quantile (see [`PixelFilter`]) plus ½: the offset from the pixel's top-left corner, for
    /// checked inputs. The box returns `u` itself, so box offsets are bit for bit those of
    /// a plain sub-pixel grid.
    pub(crate) fn corner_offset(&self, u: f64) -> f64 {
        match self {
            PixelFilter::Box => u,
            PixelFilter::BlackmanHarris { .. } => 0.5 + self.offset_unchecked(u),
        }
    }

    fn offset_unchecked(&self, u: f64) -> f64 {
        match *self {
            PixelFilter::Box => u - 0.5,
            PixelFilter::BlackmanHarris { half_width } => {
                let [a0, a1, a2, a3] = BLACKMAN_HARRIS;
                let tau = std::f64::consts::TAU;
                // F(s) − u and F'(s) (the window over a₀), from one sin_cos per harmonic.
                let residual_and_slope = |s: f64| {
                    let ((s1, c1), (s2, c2), (s3, c3)) = (
                        (tau * s).sin_cos(),
                        (2.0 * tau * s).sin_cos(),
                        (3.0 * tau * s).sin_cos(),
                    );
                    let f = s - a1 / (tau * a0) * s1 + a2 / (2.0 * tau * a0) * s2
                        - a3 / (3.0 * tau * a0) * s3;
                    (f - u, (a0 - a1 * c1 + a2 * c2 - a3 * c3) / a0)
                };
                // Newton's method kept inside a shrinking bracket of the root (bisection
                // where a step would leave it): F is increasing, so a handful of
                // iterations reach f64 resolution; 200 bound the loop in every case.
                let (mut lo, mut hi, mut s) = (0.0f64, 1.0f64, u);
                for _ in 0..200 {
                    let (r, slope) = residual_and_slope(s);
                    if r == 0.0 {
                        break;
                    }
                    if r < 0.0 {
                        lo = s;
                    } else {
                        hi = s;
                    }
                    let newton = s - r / slope;
                    let next = if slope > 0.0 && newton > lo && newton < hi {
                        newton
                    } else {
                        0.5 * (lo + hi)
                    };
                    let done = (next - s).abs() <= f64::EPSILON * next.abs().max(f64::MIN_POSITIVE);
                    s = next;
                    if done || hi - lo <= f64::EPSILON {
                        break;
                    }
                }
                half_width * (2.0 * s - 1.0)
            }
        }
    }
}

/// Camera axis convention; see the [module docs](self) for the pixel → direction formulas.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Convention {
    /// OpenCV / COLMAP: x right, y down, z forward; the image plane is at z = +1.
    /// Direction of pixel coordinate `(x, y)`: `((x − cx)/fx, (y − cy)/fy, 1)`.
    #[default]
    OpenCv,
    /// OpenGL / Blender: x right, y up, the camera looks down −z; the image plane is at
    /// z = −1. Direction of pixel coordinate `(x, y)`: `((x − cx)/fx, −(y − cy)/fy, −1)`.
    OpenGl,
}

/// Pinhole intrinsics: focal lengths and principal point in pixels, image size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x (columns), in pixels; > 0.
    pub fx: f64,
    /// Focal length along y (rows), in pixels; > 0.
    pub fy: f64,
    /// Principal point x (column coordinate; the image centre is `width / 2`).
    pub cx: f64,
    /// Principal point y (row coordinate; the image centre is `height / 2`).
    pub cy: f64,
    /// Image width in pixels; > 0.
    pub width: usize,
    /// Image height in pixels; > 0.
    pub height: usize,
}

impl Intrinsics {
    /// mip-NeRF's cone radius of one pixel per unit depth, `2 / (√12·√(fx·fy))`.
    pub(crate) fn cone_radius(&self) -> f64 {
        2.0 / (12f64.sqrt() * (self.fx * self.fy).sqrt())
    }

    /// Pinhole intrinsics from focal lengths `fx, fy` and principal point `cx, cy` (all in
    /// pixels) and the image size.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `fx` / `fy` unless finite and > 0, `cx` / `cy`
    /// unless finite, `width` / `height` if 0, and `width` if `width · height` exceeds
    /// `u32::MAX` (pixel indices are returned as u32).
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64, width: usize, height: usize) -> Result<Self> {
        crate::error::check_scalar(fx, "fx", true)?;
        crate::error::check_scalar(fy, "fy", true)?;
        crate::error::check_scalar(cx, "cx", false)?;
        crate::error::check_scalar(cy, "cy", false)?;
        if width == 0 {
            return Err(Error::invalid("width", "> 0", "0"));
        }
        if height == 0 {
            return Err(Error::invalid("height", "> 0", "0"));
        }
        match width.checked_mul(height) {
            Some(n) if n <= u32::MAX as usize => {}
            _ => {
                return Err(Error::invalid(
                    "width",
                    "width · height ≤ u32::MAX",
                    format!("{width} × {height}"),
                ))
            }
        }
        Ok(Self {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        })
    }

    /// Square-pixel intrinsics from a vertical field of view: `fy = fx = (height / 2) /
    /// tan(fov_y / 2)`, principal point at the image centre `(width / 2, height / 2)`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `fov_y` unless `0 < fov_y < π`, and those of
    /// [`Intrinsics::new`].
    pub fn from_fov_y(width: usize, height: usize, fov_y: f64) -> Result<Self> {
        if !(fov_y > 0.0 && fov_y < std::f64::consts::PI) {
            return Err(Error::invalid(
                "fov_y",
                "radians in (0, π)",
                format!("{fov_y}"),
            ));
        }
        let f = 0.5 * height as f64 / (0.5 * fov_y).tan();
        Self::new(f, f, 0.5 * width as f64, 0.5 * height as f64, width, height)
    }

    /// Camera-space ray directions for pixel coordinates.
    ///
    /// `pixels: [N, 2]` (f32 or f64) holds continuous coordinates `(x, y)` = (column, row);
    /// no half-pixel offset is added, so the centre of integer pixel `(u, v)` is
    /// `(u + 0.5, v + 0.5)`. Coordinates outside the image are allowed. Returns `[N, 3]` in
    /// the dtype and on the device of `pixels`:
    /// OpenCV `((x − cx)/fx, (y − cy)/fy, 1)`, OpenGL `((x − cx)/fx, −(y − cy)/fy, −1)`.
    /// Not normalised (see the module docs). Differentiable with respect to `pixels`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `pixels` for a wrong shape or dtype, or non-finite
    /// values.
    pub(crate) fn camera_directions(
        &self,
        pixels: &Tensor,
        convention: Convention,
    ) -> Result<Tensor> {
        check_float(pixels, "pixels")?;
        let n = check_shape(pixels, "pixels", &[Dim::Any("N"), Dim::Is(2)])?[0];
        check_finite(pixels, "pixels")?;
        let (sy, sz) = match convention {
            Convention::OpenCv => (1.0, 1.0),
            Convention::OpenGl => (-1.0, -1.0),
        };
        let x = ((pixels.narrow(1, 0, 1)? - self.cx)? / self.fx)?;
        let y = ((crate::narrow::narrow(pixels, 1, 1, 1)? - self.cy)? / (sy * self.fy))?;
        let z = Tensor::full(sz, (n, 1), pixels.device())?.to_dtype(pixels.dtype())?;
        Ok(Tensor::cat(&[&x, &y, &z], 1)?)
    }
}

/// How far `m` is from orthonormal: `max |mᵀm − I|` over the entries.
pub(crate) fn orthonormality(m: &DMat3) -> f64 {
    (m.transpose() * *m - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |a, &b| a.max(b.abs()))
}

/// Checks that `pose` is a finite rigid transform: `RᵀR = I` within 1e-6 (max abs entry)
/// and `det R = +1` within 1e-6.
pub(crate) fn check_pose(pose: &DAffine3, arg: &'static str) -> Result<()> {
    let m = pose.matrix3;
    if !m.is_finite() || !pose.translation.is_finite() {
        return Err(Error::invalid(arg, "finite entries", format!("{pose:?}")));
    }
    let dev = orthonormality(&m);
    if dev > 1e-6 {
        return Err(Error::invalid(
            arg,
            "an orthonormal rotation part (|RᵀR − I| ≤ 1e-6)",
            format!("max |RᵀR − I| = {dev:e}"),
        ));
    }
    let det = m.determinant();
    if (det - 1.0).abs() > 1e-6 {
        return Err(Error::invalid(
            arg,
            "a proper rotation (det R = +1)",
            format!("det R = {det}"),
        ));
    }
    Ok(())
}

/// `R` as a `[3, 3]` tensor transposed (`Rᵀ`, rows = columns of `R`), so that world
/// directions are `d_cam · Rᵀ` for row vectors.
fn rotation_t(m: &DMat3, like: &Tensor) -> Result<Tensor> {
    let rows = [
        m.x_axis.to_array(),
        m.y_axis.to_array(),
        m.z_axis.to_array(),
    ];
    Ok(Tensor::new(&rows, like.device())?.to_dtype(like.dtype())?)
}

/// A pinhole camera: intrinsics, a camera-to-world rigid pose, and an axis convention.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    intrinsics: Intrinsics,
    cam_to_world: DAffine3,
    /// `cam_to_world`'s inverse, made once for [`Camera::project`].
    world_to_cam: DAffine3,
    convention: Convention,
}

impl Camera {
    /// The unit viewing (optical) axis in world space: `+z` of the camera frame (OpenCV)
    /// or `−z` (OpenGL).
    pub(crate) fn forward(&self) -> DVec3 {
        let m = self.cam_to_world.matrix3;
        match self.convention {
            Convention::OpenCv => m.z_axis,
            Convention::OpenGl => -m.z_axis,
        }
        .normalize()
    }

    /// A camera from intrinsics and a camera-to-world pose `x_world = R x_cam + t`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `cam_to_world` if it has non-finite entries, if
    /// its rotation part is not orthonormal (max |RᵀR − I| > 1e-6) or if `det R ≠ +1`
    /// (a reflection).
    pub fn new(
        intrinsics: Intrinsics,
        cam_to_world: DAffine3,
        convention: Convention,
    ) -> Result<Self> {
        check_pose(&cam_to_world, "cam_to_world")?;
        Ok(Self {
            intrinsics,
            cam_to_world,
            world_to_cam: cam_to_world.inverse(),
            convention,
        })
    }

    /// A camera at `eye` looking at `target`, with `up` giving the world's up direction
    /// (it need not be orthogonal to the view direction). The principal-point ray passes
    /// through `target`; image "up" is the projection of `up`.
    ///
    /// With `f = (target − eye)/|target − eye|`, `r = (f × up)/|f × up|` and `u = r × f`,
    /// the camera-to-world rotation has columns `[r, −u, f]` (OpenCV) or `[r, u, −f]`
    /// (OpenGL); the translation is `eye`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `eye` / `target` / `up` if not finite, `target` if
    /// it equals `eye`, `up` if it is zero or parallel to `target − eye`.
    pub fn look_at(
        intrinsics: Intrinsics,
        eye: DVec3,
        target: DVec3,
        up: DVec3,
        convention: Convention,
    ) -> Result<Self> {
        for (v, name) in [(eye, "eye"), (target, "target"), (up, "up")] {
            if !v.is_finite() {
                return Err(Error::invalid(name, "a finite vector", format!("{v:?}")));
            }
        }
        let view = target - eye;
        let len = view.length();
        if !(len > 0.0 && len.is_finite()) {
            return Err(Error::invalid(
                "target",
                "a point different from eye",
                format!("target = eye = {eye:?}"),
            ));
        }
        let f = view / len;
        let up_len = up.length();
        if !(up_len > 0.0 && up_len.is_finite()) {
            return Err(Error::invalid("up", "a non-zero vector", format!("{up:?}")));
        }
        let r = f.cross(up / up_len);
        let r_len = r.length();
        if r_len < 1e-9 {
            return Err(Error::invalid(
                "up",
                "a vector not parallel to target − eye",
                format!("up = {up:?}, target − eye = {view:?}"),
            ));
        }
        let r = r / r_len;
        let u = r.cross(f);
        let m = match convention {
            Convention::OpenCv => DMat3::from_cols(r, -u, f),
            Convention::OpenGl => DMat3::from_cols(r, u, -f),
        };
        Self::new(
            intrinsics,
            DAffine3::from_mat3_translation(m, eye),
            convention,
        )
    }

    /// The intrinsics.
    #[must_use]
    pub fn intrinsics(&self) -> &Intrinsics {
        &self.intrinsics
    }

    /// The camera-to-world pose.
    #[must_use]
    pub fn cam_to_world(&self) -> DAffine3 {
        self.cam_to_world
    }

    /// The axis convention.
    #[must_use]
    pub fn convention(&self) -> Convention {
        self.convention
    }

    /// `k × k` sub-pixel points in every pixel, pixel-major, that sample `filter`: rows
    /// `(v · width + u) · k² + i · k + j` are `(u + ½ + q((j + ½)/k), v + ½ + q((i + ½)/k))`
    /// for `i, j < k`, with `q` the filter's quantile (see [`PixelFilter`]): the medians of
    /// `k × k` equal-mass strata of the filter. Averaging each run of `k²` consecutive
    /// rows (rendered colours, say) gives the pixel's filtered value by quadrature. With
    /// [`PixelFilter::Box`] the points are the sub-pixel centres
    /// `(u + (j + ½)/k, v + (i + ½)/k)` (box-filtered supersampling); with
    /// [`PixelFilter::CYCLES`] they reach into the neighbouring pixels, as the images
    /// Blender renders do. Shape `[height · width · k², 2]`, in `dtype` on `device`; feed it
    /// to [`Camera::rays_for_pixels`].
    ///
    /// ```
    /// use neural_fields::camera::{Camera, Convention, Intrinsics, PixelFilter};
    /// use neural_fields::glam::DVec3;
    /// use candle_core::{DType, Device};
    ///
    /// let k = Intrinsics::from_fov_y(3, 2, 0.8)?;
    /// let cam = Camera::look_at(k, DVec3::new(0.0, -3.0, 0.0), DVec3::ZERO, DVec3::Z, Convention::OpenGl)?;
    /// let grid = cam.subpixel_grid(2, PixelFilter::Box, &Device::Cpu, DType::F64)?.to_vec2::<f64>()?;
    /// assert_eq!(grid.len(), 3 * 2 * 4);
    /// assert_eq!(grid[..4], [vec![0.25, 0.25], vec![0.75, 0.25], vec![0.25, 0.75], vec![0.75, 0.75]]);
    /// assert_eq!(grid[4], [1.25, 0.25]); // pixel (1, 0)
    /// let cycles = cam.subpixel_grid(2, PixelFilter::CYCLES, &Device::Cpu, DType::F64)?.to_vec2::<f64>()?;
    /// assert!(cycles[0][0] < 0.25 && cycles[3][0] > 0.75); // wider than the box
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `dtype` unless f32 or f64, `k` unless between
    /// 1 and 64 (and at most 2²⁸ rows in all, naming `k`), or `filter` unless a
    /// Blackman–Harris `half_width` is finite and in `(0, 64]`.
    pub fn subpixel_grid(
        &self,
        k: usize,
        filter: PixelFilter,
        device: &Device,
        dtype: DType,
    ) -> Result<Tensor> {
        check_dtype(dtype)?;
        filter.validate()?;
        let (w, h) = (self.intrinsics.width, self.intrinsics.height);
        let n = (w * h).checked_mul(k * k).filter(|&n| n <= 1 << 28);
        let n = match n {
            Some(n) if (1..=64).contains(&k) => n,
            _ => {
                return Err(Error::invalid(
                    "k",
                    "1 to 64 sub-pixels per side, at most 2^28 in all",
                    format!("{k} for a {w} × {h} image"),
                ))
            }
        };
        let mut data = Vec::with_capacity(2 * n);
        let side = k as f64;
        let at: Vec<f64> = (0..k)
            .map(|j| filter.corner_offset((j as f64 + 0.5) / side))
            .collect();
        for v in 0..h {
            for u in 0..w {
                for &di in &at {
                    for &dj in &at {
                        data.push(u as f64 + dj);
                        data.push(v as f64 + di);
                    }
                }
            }
        }
        Ok(Tensor::from_vec(data, (n, 2), device)?.to_dtype(dtype)?)
    }

    /// Rays through all pixel centres, row-major (ray `v · width + u` passes through
    /// pixel `(u, v)`), `N = width · height`. See [`Camera::rays_for_pixels`].
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `dtype` unless f32 or f64; naming
    /// `self.intrinsics` when the `width · height` rays (a pixel, an origin and a direction,
    /// 8 values of `dtype` each) pass the allocation limit of 2³³ bytes (8 GiB), checked
    /// before anything is allocated.
    pub fn rays(&self, device: &Device, dtype: DType) -> Result<Rays> {
        check_dtype(dtype)?;
        let (w, h) = (self.intrinsics.width, self.intrinsics.height);
        crate::limits::check_bytes("self.intrinsics", &[w, h, 8], dtype.size_in_bytes())?;
        let pixels = self.subpixel_grid(1, PixelFilter::Box, device, dtype)?;
        self.rays_for_pixels(&pixels)
    }

    /// World-space rays for pixel coordinates `pixels: [N, 2]` (column, row; the centre of
    /// pixel `(u, v)` is `(u + 0.5, v + 0.5)`): origin `t` (the camera centre), direction
    /// `R · d_cam` with the camera-space direction `d_cam` of the pixel: OpenCV
    /// `((x − cx)/fx, (y − cy)/fy, 1)`, OpenGL `((x − cx)/fx, −(y − cy)/fy, −1)` (not
    /// normalised; no half-pixel offset is added to `pixels`).
    /// Dtype and device follow `pixels`; directions are differentiable w.r.t. `pixels`.
    ///
    /// The rays carry mip-NeRF's cone radius ([`Rays::with_radii`]) of a whole pixel,
    /// `2 / (√12·√(fx·fy))` per unit depth: the disc whose variance is the pixel's (a
    /// pixel is `1/fx × 1/fy` at depth 1). Rays through a `k × k` sub-pixel grid cover
    /// `1/k` of that: scale the radii by `1/k` ([`crate::volume::render_image`] does).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `pixels` for a wrong shape or dtype, or
    /// non-finite values.
    pub fn rays_for_pixels(&self, pixels: &Tensor) -> Result<Rays> {
        let d_cam = self.intrinsics.camera_directions(pixels, self.convention)?;
        let n = d_cam.dim(0)?;
        let directions = d_cam.matmul(&rotation_t(&self.cam_to_world.matrix3, pixels)?)?;
        let origins = row3(self.cam_to_world.translation.to_array(), pixels)?
            .broadcast_as((n, 3))?
            .contiguous()?;
        let radii = Tensor::full(self.intrinsics.cone_radius(), n, pixels.device())?
            .to_dtype(pixels.dtype())?;
        Rays::new(origins, directions)?.with_radii(radii)
    }

    /// The world-space ray of one continuous pixel coordinate `pixel = (x, y)` (column,
    /// row; the centre of pixel `(u, v)` is `(u + 0.5, v + 0.5)`), on the host in f64:
    /// `(origin, direction)` with the same formulas as [`Camera::rays_for_pixels`] (the
    /// direction is not normalised; its camera-space depth component is 1).
    #[must_use]
    pub(crate) fn ray(&self, pixel: DVec2) -> (DVec3, DVec3) {
        let k = &self.intrinsics;
        let x = (pixel.x - k.cx) / k.fx;
        let y = (pixel.y - k.cy) / k.fy;
        let d_cam = match self.convention {
            Convention::OpenCv => DVec3::new(x, y, 1.0),
            Convention::OpenGl => DVec3::new(x, -y, -1.0),
        };
        (
            self.cam_to_world.translation,
            self.cam_to_world.matrix3 * d_cam,
        )
    }

    /// Projects a world point into the image: `(x, y, depth)` with `(x, y)` the continuous
    /// pixel coordinate (column, row) and `depth` the camera-space depth along the viewing
    /// axis (the ray parameter `t` of [`Camera::rays_for_pixels`], so the ray through
    /// `(x, y)` at `t = depth` is `point`). `None` if the point is not in front of the camera
    /// (depth ≤ 0), not finite, or so close to the camera's plane that its pixel coordinates
    /// overflow f64. The inverse of the rays for points in front of the camera.
    #[must_use]
    pub fn project(&self, point: DVec3) -> Option<DVec3> {
        let p = self.world_to_cam.transform_point3(point);
        let depth = match self.convention {
            Convention::OpenCv => p.z,
            Convention::OpenGl => -p.z,
        };
        if !(depth > 0.0 && p.is_finite()) {
            return None;
        }
        let k = &self.intrinsics;
        let y_cam = match self.convention {
            Convention::OpenCv => p.y,
            Convention::OpenGl => -p.y,
        };
        let projected = DVec3::new(
            k.fx * p.x / depth + k.cx,
            k.fy * y_cam / depth + k.cy,
            depth,
        );
        // A point almost in the camera's plane projects beyond f64's range.
        projected.is_finite().then_some(projected)
    }
}

/// The point closest, in least squares, to every camera's optical axis:
/// `Σ (I − f fᵀ)(c − o) = 0` over the cameras' centres `o` and unit viewing axes `f`.
/// `Err(det)` with the system's determinant when the axes are (nearly) all parallel
/// (`|det| ≤ 1e-9·n³`, or NaN).
pub(crate) fn axes_centre(cameras: &[Camera]) -> std::result::Result<DVec3, f64> {
    let (mut a, mut b) = (DMat3::ZERO, DVec3::ZERO);
    for cam in cameras {
        let f = cam.forward();
        let p = DMat3::IDENTITY - DMat3::from_cols(f * f.x, f * f.y, f * f.z);
        a += p;
        b += p * cam.cam_to_world.translation;
    }
    let det = a.determinant();
    if det.is_nan() || det.abs() <= 1e-9 * cameras.len().pow(3) as f64 {
        return Err(det);
    }
    Ok(a.inverse() * b)
}

/// Random cameras around a set of cameras, for regularising unobserved viewpoints
/// (RegNeRF's sampled poses): the scene centre `c` is the point closest, in least squares,
/// to every camera's optical axis; each new camera sits at the mean distance `r` of the
/// cameras from `c` (scaled by `1 + N(0, 0.05²)`), in the direction from `c` of a random
/// input camera perturbed by `N(0, 0.25²)` per axis (renormalised), looks at `c` plus
/// `N(0, (0.05·r)²)` per axis, and takes the mean "up" of the input cameras, the convention
/// and the intrinsics of the first. Reproducible from `seed`.
///
/// ```
/// use neural_fields::camera::{cameras_around, Camera, Convention, Intrinsics};
/// use neural_fields::glam::DVec3;
///
/// let k = Intrinsics::from_fov_y(8, 8, 0.7)?;
/// let eyes = [DVec3::new(4.0, 0.0, 1.0), DVec3::new(0.0, 4.0, 1.0), DVec3::new(-4.0, 0.0, 1.0)];
/// let cams: Vec<Camera> = eyes
///     .iter()
///     .map(|&e| Camera::look_at(k, e, DVec3::ZERO, DVec3::Z, Convention::OpenGl))
///     .collect::<Result<_, _>>()?;
/// let new = cameras_around(&cams, 16, 0)?;
/// assert!(new.iter().all(|c| (c.cam_to_world().translation.length() - 4.12).abs() < 1.0));
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `cameras` if fewer than two are given, their axes
/// are (nearly) parallel so that no centre is defined, or their up directions cancel;
/// `count` if 0 or above 2²⁴ (checked before anything is allocated).
pub fn cameras_around(cameras: &[Camera], count: usize, seed: u64) -> Result<Vec<Camera>> {
    if cameras.len() < 2 {
        return Err(Error::invalid(
            "cameras",
            "at least two cameras",
            cameras.len().to_string(),
        ));
    }
    if count == 0 || count > 1 << 24 {
        return Err(Error::invalid(
            "count",
            "between 1 and 2^24 cameras",
            count.to_string(),
        ));
    }
    // Up axis of a camera in world space.
    let up_of = |c: &Camera| {
        let m = c.cam_to_world.matrix3;
        match c.convention {
            Convention::OpenCv => -m.y_axis,
            Convention::OpenGl => m.y_axis,
        }
    };
    let centre = axes_centre(cameras).map_err(|det| {
        Error::invalid(
            "cameras",
            "cameras whose optical axes are not all parallel",
            format!("det = {det:e}"),
        )
    })?;
    let radius = cameras
        .iter()
        .map(|c| (c.cam_to_world.translation - centre).length())
        .sum::<f64>()
        / cameras.len() as f64;
    let up = cameras
        .iter()
        .map(up_of)
        .fold(DVec3::ZERO, |s, u| s + u)
        .normalize_or_zero();
    if up == DVec3::ZERO || !centre.is_finite() || !(radius > 0.0 && radius.is_finite()) {
        return Err(Error::invalid(
            "cameras",
            "cameras around a centre, with a common up direction",
            format!("centre {centre:?}, radius {radius}, mean up {up:?}"),
        ));
    }
    crate::limits::check_bytes("count", &[count], std::mem::size_of::<Camera>())?;
    let mut rng = crate::rng::SplitMix64::new(seed);
    let mut out = Vec::with_capacity(count);
    let first = &cameras[0];
    // Draws along `up` are redrawn; a bounded number of tries keeps a degenerate input
    // from looping.
    for _ in 0..count.saturating_mul(64) {
        if out.len() == count {
            break;
        }
        let base = cameras[rng.below(cameras.len() as u64) as usize]
            .cam_to_world
            .translation
            - centre;
        let jitter = DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.25;
        let dir = (base.normalize_or_zero() + jitter).normalize_or_zero();
        let eye = centre + dir * radius * (1.0 + 0.05 * rng.normal());
        let target = centre + DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.05 * radius;
        // A direction (almost) along `up` has no defined roll: draw again.
        if let Ok(cam) = Camera::look_at(first.intrinsics, eye, target, up, first.convention) {
            out.push(cam);
        }
    }
    if out.len() < count {
        return Err(Error::invalid(
            "cameras",
            "cameras not all looking along their up direction",
            format!("{} of {count} poses drawn", out.len()),
        ));
    }
    Ok(out)
}

/// Rays through one random `k × k` block of pixel centres of each camera (RegNeRF's
/// patches, rendered from unobserved viewpoints such as [`cameras_around`]'s): for camera
/// `c`, the block's corner `(u₀, v₀)` is drawn uniformly from
/// `0..=width − k` × `0..=height − k` (0 where the image is smaller than the block), and
/// ray `c·k² + j·k + i` passes through pixel `(u₀ + i + ½, v₀ + j + ½)`. Reproducible from
/// `seed` (the corners are the draws of [`SplitMix64`](crate::rng::SplitMix64) seeded
/// with it, `u₀` then `v₀` per camera). Returns `C·k²` rays in `dtype` on `device`,
/// laid out so that `reshape((C, k, k))` of a per-ray quantity gives each patch as an
/// image; not differentiable (the pixels are constants).
///
/// ```
/// use candle_core::{DType, Device};
/// use neural_fields::camera::{patch_rays, Camera, Convention, Intrinsics};
/// use neural_fields::glam::DVec3;
///
/// let k = Intrinsics::from_fov_y(32, 24, 0.7)?;
/// let cam = Camera::look_at(k, DVec3::new(0.0, -4.0, 1.0), DVec3::ZERO, DVec3::Z, Convention::OpenGl)?;
/// let rays = patch_rays(&[cam, cam], 8, 0, &Device::Cpu, DType::F32)?;
/// assert_eq!(rays.len(), 2 * 8 * 8);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `cameras` if empty, `k` unless between 1 and 2¹² and
/// the `C·k²` rays (8 values of 8 bytes each) within the allocation limit of 2³³ bytes
/// (8 GiB), checked before anything is allocated; `dtype` unless f32 or f64.
pub fn patch_rays(
    cameras: &[Camera],
    k: usize,
    seed: u64,
    device: &Device,
    dtype: DType,
) -> Result<Rays> {
    if cameras.is_empty() {
        return Err(Error::invalid("cameras", "at least one camera", "none"));
    }
    if !(1..=1 << 12).contains(&k) {
        return Err(Error::invalid(
            "k",
            "a patch side in 1..=4096",
            k.to_string(),
        ));
    }
    check_dtype(dtype)?;
    // Per ray: a pixel, an origin and a direction (8 values, counted at 8 bytes).
    crate::limits::check_bytes("k", &[cameras.len(), k, k, 8], 8)?;
    let mut rng = crate::rng::SplitMix64::new(seed);
    let (mut origins, mut directions) = (Vec::new(), Vec::new());
    for cam in cameras {
        let size = &cam.intrinsics;
        let u0 = rng.below((size.width.saturating_sub(k) + 1) as u64) as f64;
        let v0 = rng.below((size.height.saturating_sub(k) + 1) as u64) as f64;
        let pixels: Vec<f64> = (0..k * k)
            .flat_map(|p| [u0 + (p % k) as f64 + 0.5, v0 + (p / k) as f64 + 0.5])
            .collect();
        let pixels = Tensor::from_vec(pixels, (k * k, 2), device)?.to_dtype(dtype)?;
        let rays = cam.rays_for_pixels(&pixels)?;
        origins.push(rays.origins().clone());
        directions.push(rays.directions().clone());
    }
    Rays::new(Tensor::cat(&origins, 0)?, Tensor::cat(&directions, 0)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Blackman–Harris window's cumulative distribution by the trapezoid rule on its
    /// density (independent of the closed form the library inverts), at offset `x` in pixels.
    fn blackman_harris_cdf(x: f64, h: f64) -> f64 {
        let density = |t: f64| {
            let v = std::f64::consts::TAU * (t / (2.0 * h) + 0.5);
            0.35875 - 0.48829 * v.cos() + 0.14128 * (2.0 * v).cos() - 0.01168 * (3.0 * v).cos()
        };
        let steps = 20_000;
        let integral = |to: f64| {
            let dt = (to + h) / steps as f64;
            (0..steps)
                .map(|i| {
                    0.5 * (density(-h + i as f64 * dt) + density(-h + (i + 1) as f64 * dt)) * dt
                })
                .sum::<f64>()
        };
        integral(x.clamp(-h, h)) / integral(h)
    }

    /// `PixelFilter::quantile` inverts each filter's cumulative distribution: the box's is
    /// `u − ½`; the Blackman–Harris window's (Cycles' default, ±1.5 px) is checked against a
    /// numerical integral of the window, with its symmetry, its ends at ±h, its standard
    /// deviation (0.4155 px at h = 1.5, against the box's 0.2887) and its refusals.
    #[test]
    fn pixel_filter_quantiles_invert_the_filters_distributions() {
        for u in [0.0, 0.1, 0.25, 0.5, 0.9, 1.0] {
            assert_eq!(PixelFilter::Box.quantile(u).unwrap(), u - 0.5);
        }
        for h in [0.5, 1.5, 4.0] {
            let f = PixelFilter::BlackmanHarris { half_width: h };
            assert!((f.quantile(0.0).unwrap() + h).abs() < 1e-12 * h);
            assert!((f.quantile(1.0).unwrap() - h).abs() < 1e-12 * h);
            let mut last = -h;
            for i in 1..100 {
                let u = i as f64 / 100.0;
                let x = f.quantile(u).unwrap();
                assert!(x > last, "quantile not increasing at u = {u}");
                last = x;
                assert!(
                    (f.quantile(1.0 - u).unwrap() + x).abs() < 1e-12 * h,
                    "not symmetric at u = {u}"
                );
                let back = blackman_harris_cdf(x, h);
                assert!(
                    (back - u).abs() < 1e-6,
                    "h = {h}, u = {u}: F(q(u)) = {back}"
                );
                // And to rounding against the closed form of the distribution.
                let [a0, a1, a2, a3] = [0.35875, 0.48829, 0.14128, 0.01168];
                let (t, z) = (std::f64::consts::TAU, (x + h) / (2.0 * h));
                let closed = z - a1 / (t * a0) * (t * z).sin()
                    + a2 / (2.0 * t * a0) * (2.0 * t * z).sin()
                    - a3 / (3.0 * t * a0) * (3.0 * t * z).sin();
                assert!(
                    (closed - u).abs() < 1e-14,
                    "h = {h}, u = {u}: closed-form F(q(u)) = {closed}"
                );
            }
        }
        // The standard deviation of the offsets, by the midpoint rule in u.
        let sd = |f: PixelFilter| {
            let n = 20_000;
            let m2: f64 = (0..n)
                .map(|i| f.quantile((i as f64 + 0.5) / n as f64).unwrap().powi(2))
                .sum();
            (m2 / n as f64).sqrt()
        };
        assert!((sd(PixelFilter::CYCLES) - 0.4155).abs() < 1e-3);
        assert!((sd(PixelFilter::Box) - 12f64.sqrt().recip()).abs() < 1e-4);
        let arg = |r: Result<f64>| match r {
            Err(Error::InvalidArgument { arg, .. }) => arg,
            other => panic!("expected an argument error, got {other:?}"),
        };
        assert_eq!(arg(PixelFilter::CYCLES.quantile(1.5)), "u");
        assert_eq!(arg(PixelFilter::CYCLES.quantile(f64::NAN)), "u");
        for half_width in [0.0, -1.0, 65.0, f64::NAN, f64::INFINITY] {
            let f = PixelFilter::BlackmanHarris { half_width };
            assert_eq!(arg(f.quantile(0.5)), "filter");
        }
    }

    /// At extreme probabilities the quantile is finite (or refused naming `u`/`filter`).
    #[test]
    fn quantiles_stay_finite_at_extreme_probabilities() {
        let filters = [
            PixelFilter::Box,
            PixelFilter::CYCLES,
            PixelFilter::BlackmanHarris { half_width: 64.0 },
            PixelFilter::BlackmanHarris { half_width: 1e-300 },
            PixelFilter::BlackmanHarris {
                half_width: f64::NAN,
            },
            PixelFilter::BlackmanHarris { half_width: 0.0 },
        ];
        for filter in filters {
            for u in [0.0, 1e-300, 0.5, 1.0 - f64::EPSILON, 1.0, -1e-300, f64::NAN] {
                match filter.quantile(u) {
                    Ok(x) => assert!(x.is_finite(), "{filter:?}, u = {u:e}: {x}"),
                    Err(e) => assert!(
                        !((0.0..=1.0).contains(&u) && filter.validate().is_ok()),
                        "{filter:?}, u = {u:e}: {e}"
                    ),
                }
            }
        }
    }
}
