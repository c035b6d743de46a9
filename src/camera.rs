//! Pinhole cameras, rays, ray–box and ray–sphere intersection, and a differentiable pose.
//!
//! # Conventions
//!
//! **Pixels.** Pixel coordinates are continuous image coordinates `(x, y)` with `x` the
//! column and `y` the row, the origin at the top-left corner of the top-left pixel. The
//! integer pixel `(u, v)` covers `[u, u + 1) × [v, v + 1)`, so its **centre is
//! `(u + 0.5, v + 0.5)`**. Functions that take a `pixels: [N, 2]` tensor use these
//! coordinates as given (no half-pixel offset is added); [`Camera::pixel_grid`] and
//! [`Camera::random_rays`] produce pixel centres.
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

use crate::error::{
    check_dtype, check_finite, check_float, check_points, check_same, check_shape, Dim,
};
use crate::error::{Error, Result};
use candle_core::{DType, Device, Tensor, Var};
use glam::{DAffine3, DMat3, DQuat, DVec2, DVec3};

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
/// [`PixelFilter::quantile`] maps a uniform number to an offset (the inverse of the
/// filter's cumulative distribution), so that `k` equal-mass strata of the filter have
/// their medians at `quantile((j + ½)/k)`: the plain mean of the `k × k` rays through
/// those points is a quadrature of the filtered pixel ([`Camera::subpixel_grid`]), and
/// rays through `quantile(U)` for uniform `U` sample it
/// ([`crate::data::RaySampler::with_pixel_filter`]).
///
/// ```
/// use neural_fields::camera::PixelFilter;
///
/// assert_eq!(PixelFilter::Box.quantile(0.75)?, 0.25);
/// let bh = PixelFilter::CYCLES;
/// assert!(bh.quantile(0.5)?.abs() < 1e-12);                  // symmetric
/// assert!((bh.quantile(0.25)? + bh.quantile(0.75)?).abs() < 1e-12);
/// assert!(bh.quantile(1.0)? <= 1.5 && bh.quantile(0.99)? > 0.7); // tails to ±1.5 px
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
    pub fn validate(&self) -> Result<()> {
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
    /// [`Error::InvalidArgument`] naming `u` unless in `[0, 1]`, or `filter` as
    /// [`PixelFilter::validate`].
    pub fn quantile(&self, u: f64) -> Result<f64> {
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

    /// [`PixelFilter::quantile`] plus ½: the offset from the pixel's top-left corner, for
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

/// The smallest magnitude whose square is still a normal number in `dtype`: below it a
/// direction component is treated as exactly 0, so that no `x / d²` underflows to `0/0`.
fn tiny(dtype: DType) -> f64 {
    match dtype {
        DType::F32 => f64::from(f32::MIN_POSITIVE).sqrt(),
        _ => f64::MIN_POSITIVE.sqrt(),
    }
}

fn scalar_f64(t: &Tensor) -> Result<f64> {
    Ok(t.to_dtype(DType::F64)?.to_scalar::<f64>()?)
}

/// A `[1, 3]` constant in the dtype and device of `like`.
fn row3(v: [f64; 3], like: &Tensor) -> Result<Tensor> {
    Ok(Tensor::new(&[v], like.device())?.to_dtype(like.dtype())?)
}

fn full_like(like: &Tensor, v: f64) -> Result<Tensor> {
    Ok(Tensor::full(v, like.shape(), like.device())?.to_dtype(like.dtype())?)
}

impl Intrinsics {
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
fn check_pose(pose: &DAffine3, arg: &'static str) -> Result<()> {
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

    /// The camera centre in world space (the translation of the pose; every ray's origin).
    #[must_use]
    pub fn center(&self) -> DVec3 {
        self.cam_to_world.translation
    }

    /// Centres of all pixels, row-major: row `i = v · width + u` is `(u + 0.5, v + 0.5)`.
    /// Shape `[height · width, 2]`, in `dtype` on `device`. The same as
    /// [`Camera::subpixel_grid`] with `k = 1`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `dtype` unless f32 or f64.
    pub fn pixel_grid(&self, device: &Device, dtype: DType) -> Result<Tensor> {
        self.subpixel_grid(1, PixelFilter::Box, device, dtype)
    }

    /// `k × k` sub-pixel points in every pixel, pixel-major, that sample `filter`: rows
    /// `(v · width + u) · k² + i · k + j` are `(u + ½ + q((j + ½)/k), v + ½ + q((i + ½)/k))`
    /// for `i, j < k`, with `q` the filter's [`PixelFilter::quantile`]: the medians of
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
    /// 1 and 64 (and at most 2²⁸ rows in all, naming `k`), or `filter` as
    /// [`PixelFilter::validate`].
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
    /// [`Error::InvalidArgument`] naming `dtype` unless f32 or f64.
    pub fn rays(&self, device: &Device, dtype: DType) -> Result<Rays> {
        let pixels = self.pixel_grid(device, dtype)?;
        self.rays_for_pixels(&pixels)
    }

    /// World-space rays for pixel coordinates `pixels: [N, 2]` (column, row; the centre of
    /// pixel `(u, v)` is `(u + 0.5, v + 0.5)`): origin `t` (the camera centre), direction
    /// `R · d_cam` with the camera-space direction `d_cam` of the pixel: OpenCV
    /// `((x − cx)/fx, (y − cy)/fy, 1)`, OpenGL `((x − cx)/fx, −(y − cy)/fy, −1)` (not
    /// normalised; no half-pixel offset is added to `pixels`).
    /// Dtype and device follow `pixels`; directions are differentiable w.r.t. `pixels`.
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
        Rays::new(origins, directions)
    }

    /// `n` rays through pixel centres drawn uniformly with replacement, reproducibly from
    /// `seed` by [`SplitMix64::below`](crate::rng::SplitMix64::below): an index is
    /// `⌊s · W·H / 2⁶⁴⌋` for a 64-bit draw `s`, whose bias is below `W·H / 2⁶⁴`. Returns
    /// the rays and the linear pixel indices
    /// `v · width + u` as a `[n]` u32 tensor on `device`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `n` if 0 and `dtype` unless f32 or f64.
    pub fn random_rays(
        &self,
        n: usize,
        seed: u64,
        device: &Device,
        dtype: DType,
    ) -> Result<(Rays, Tensor)> {
        check_dtype(dtype)?;
        if n == 0 {
            return Err(Error::invalid("n", "at least one ray", "0"));
        }
        let w = self.intrinsics.width;
        let total = (self.intrinsics.width * self.intrinsics.height) as u64;
        let mut rng = crate::rng::SplitMix64::new(seed);
        let mut idx = Vec::with_capacity(n);
        let mut pix = Vec::with_capacity(2 * n);
        for _ in 0..n {
            let i = rng.below(total) as usize;
            idx.push(i as u32); // invariant: total ≤ u32::MAX (checked in Intrinsics::new)
            pix.push((i % w) as f64 + 0.5);
            pix.push((i / w) as f64 + 0.5);
        }
        let pixels = Tensor::from_vec(pix, (n, 2), device)?.to_dtype(dtype)?;
        let rays = self.rays_for_pixels(&pixels)?;
        Ok((rays, Tensor::from_vec(idx, n, device)?))
    }

    /// The world-space ray of one continuous pixel coordinate `pixel = (x, y)` (column,
    /// row; the centre of pixel `(u, v)` is `(u + 0.5, v + 0.5)`), on the host in f64:
    /// `(origin, direction)` with the same formulas as [`Camera::rays_for_pixels`] (the
    /// direction is not normalised; its camera-space depth component is 1).
    #[must_use]
    pub fn ray(&self, pixel: DVec2) -> (DVec3, DVec3) {
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
    /// axis (the ray parameter `t` of [`Camera::ray`], so `ray(x, y)` at `t = depth` is
    /// `point`). `None` if the point is not in front of the camera (depth ≤ 0), not finite,
    /// or so close to the camera's plane that its pixel coordinates overflow f64.
    /// The inverse of [`Camera::ray`] for points in front of the camera.
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

    /// A differentiable copy of this camera's pose ([`PoseParam::from_affine`]).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `dtype` unless f32 or f64.
    pub fn pose_param(&self, device: &Device, dtype: DType) -> Result<PoseParam> {
        PoseParam::from_affine(&self.cam_to_world, device, dtype)
    }
}

/// A batch of rays `o + t·d`: origins `[N, 3]` and directions `[N, 3]`, one float dtype
/// and device, validated once when built ([`Rays::new`]): every function that takes
/// `&Rays` relies on that and checks nothing more of them. Directions are whatever the
/// producer made them (camera rays have unit camera-space z, see the module docs).
#[derive(Clone, Debug)]
pub struct Rays {
    origins: Tensor,
    directions: Tensor,
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
    /// assert_eq!(rays.at(&Tensor::new(&[1.5f32], &Device::Cpu)?)?.to_vec2::<f32>()?, vec![vec![0.0, 0.0, 3.0]]);
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

    /// Points `o + t·d` for `t: [N]` (same dtype and device): `[N, 3]`. Differentiable
    /// w.r.t. `t`, origins and directions.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `t` for a wrong shape, dtype or device.
    pub fn at(&self, t: &Tensor) -> Result<Tensor> {
        check_float(t, "t")?;
        check_shape(t, "t", &[Dim::Is(self.len())])?;
        check_same(t, "t", &self.origins, "origins")?;
        Ok((&self.origins + t.unsqueeze(1)?.broadcast_mul(&self.directions)?)?)
    }

    /// The same rays with unit directions `d / |d|` (origins shared). Computed as
    /// `d' / |d'|` with `d' = d / max|dᵢ|` (a detached per-ray scale, exact because
    /// `d/|d|` is scale-invariant), so tiny directions do not underflow. Differentiable
    /// w.r.t. the directions.
    ///
    /// # Errors
    /// Only candle errors (the rays were checked when built: no direction is zero).
    pub fn normalized(&self) -> Result<Rays> {
        if self.is_empty() {
            return Ok(self.clone());
        }
        // m > 0 on every row: `Rays::new` rejects zero directions.
        let dn = self.directions.broadcast_div(&direction_scale(self)?)?;
        let norm = dn.sqr()?.sum_keepdim(1)?.sqrt()?;
        Ok(Rays {
            origins: self.origins.clone(),
            directions: dn.broadcast_div(&norm)?,
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
/// is finite (`tests/stiff_cases.rs` sweeps within this range).
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
/// assert!(new.iter().all(|c| (c.center().length() - 4.12).abs() < 1.0));
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `cameras` if fewer than two are given, their axes
/// are (nearly) parallel so that no centre is defined, or their up directions cancel;
/// `count` if 0 or too large to allocate.
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
    // Forward (viewing) axis and up axis of a camera in world space.
    let axes = |c: &Camera| {
        let m = c.cam_to_world.matrix3;
        match c.convention {
            Convention::OpenCv => (m.z_axis, -m.y_axis),
            Convention::OpenGl => (-m.z_axis, m.y_axis),
        }
    };
    // Least squares: Σ (I − f fᵀ) (c − o) = 0.
    let (mut a, mut b) = (DMat3::ZERO, DVec3::ZERO);
    for cam in cameras {
        let (f, _) = axes(cam);
        let f = f.normalize();
        let p = DMat3::IDENTITY - DMat3::from_cols(f * f.x, f * f.y, f * f.z);
        a += p;
        b += p * cam.center();
    }
    let det = a.determinant();
    if det.is_nan() || det.abs() <= 1e-9 * cameras.len().pow(3) as f64 {
        return Err(Error::invalid(
            "cameras",
            "cameras whose optical axes are not all parallel",
            format!("det = {det:e}"),
        ));
    }
    let centre = a.inverse() * b;
    let radius = cameras
        .iter()
        .map(|c| (c.center() - centre).length())
        .sum::<f64>()
        / cameras.len() as f64;
    let up = cameras
        .iter()
        .map(|c| axes(c).1)
        .fold(DVec3::ZERO, |s, u| s + u)
        .normalize_or_zero();
    if up == DVec3::ZERO || !centre.is_finite() || !(radius > 0.0 && radius.is_finite()) {
        return Err(Error::invalid(
            "cameras",
            "cameras around a centre, with a common up direction",
            format!("centre {centre:?}, radius {radius}, mean up {up:?}"),
        ));
    }
    let mut rng = crate::rng::SplitMix64::new(seed);
    let mut out = Vec::with_capacity(count.min(1 << 20));
    let first = &cameras[0];
    // Draws along `up` are redrawn; a bounded number of tries keeps a degenerate input
    // from looping.
    for _ in 0..count.saturating_mul(64) {
        if out.len() == count {
            break;
        }
        let base = cameras[rng.below(cameras.len() as u64) as usize].center() - centre;
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

/// A differentiable camera-to-world pose: a quaternion `q = (w, x, y, z)` (any non-zero
/// scale; the rotation is that of `q/|q|`) and a translation `t`, as candle variables for
/// an optimiser.
///
/// `R(q) = M(q) / |q|²` with `M` the homogeneous quaternion matrix (see
/// `docs/math.md`), so unconstrained steps on `q` always give a valid rotation.
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
    pub fn rotation_matrix(&self) -> Result<Tensor> {
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

    /// The current value as a rigid transform (rotation of the normalised quaternion).
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
        let quat = DQuat::from_xyzw(q[1], q[2], q[3], q[0]);
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

    /// Rescales `rotation` in place to unit length, `q ← q/|q|`, which leaves the
    /// rotation unchanged. Unconstrained optimisers let `|q|` drift up slowly, and the
    /// effective step size falls as `1/|q|²` (see `docs/math.md`); calling this now and
    /// then undoes that.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `rotation` if it is zero or non-finite, or
    /// either variable has a wrong shape or dtype.
    pub fn renormalize(&self) -> Result<()> {
        self.check()?;
        let q = self.rotation.as_tensor().detach();
        let m = q.abs()?.max_keepdim(0)?;
        if scalar_f64(&m.squeeze(0)?)?.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return Err(Error::invalid("rotation", "a non-zero quaternion", "0"));
        }
        let q = q.broadcast_div(&m)?;
        let norm = q.sqr()?.sum_keepdim(0)?.sqrt()?;
        self.rotation.set(&q.broadcast_div(&norm)?)?;
        Ok(())
    }

    /// World rays for `pixels: [N, 2]` (as in [`Camera::rays_for_pixels`]): origins `t`
    /// (broadcast to `[N, 3]`), directions `R(q/|q|) · d_cam`. Differentiable w.r.t.
    /// `rotation`, `translation` and `pixels`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `pixels` for a wrong shape, dtype or device
    /// (it must match the variables'), and those of [`PoseParam::rotation_matrix`].
    pub fn rays(
        &self,
        intrinsics: &Intrinsics,
        convention: Convention,
        pixels: &Tensor,
    ) -> Result<Rays> {
        let rot = self.rotation_matrix()?;
        check_float(pixels, "pixels")?;
        check_same(pixels, "pixels", &self.translation, "translation")?;
        let d_cam = intrinsics.camera_directions(pixels, convention)?;
        let n = d_cam.dim(0)?;
        let directions = d_cam.matmul(&rot.t()?)?;
        let origins = self
            .translation
            .as_tensor()
            .unsqueeze(0)?
            .broadcast_as((n, 3))?
            .contiguous()?;
        Rays::new(origins, directions)
    }
}

/// A similarity transform `y = s·R·x + t` (scale `s > 0`, rotation `R`, translation `t`),
/// the map between two reconstructions of the same scene that agree up to gauge: a
/// jointly refined set of cameras is determined only up to one (BARF, §4.1, aligns its
/// poses to the truth this way before measuring them).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity {
    /// Scale `s > 0`.
    pub scale: f64,
    /// Rotation `R` (a unit quaternion).
    pub rotation: DQuat,
    /// Translation `t`.
    pub translation: DVec3,
}

impl Similarity {
    /// The identity: `s = 1`, `R = I`, `t = 0`.
    pub const IDENTITY: Self = Self {
        scale: 1.0,
        rotation: DQuat::IDENTITY,
        translation: DVec3::ZERO,
    };

    /// `s·R·x + t`.
    #[must_use]
    pub fn transform_point(&self, x: DVec3) -> DVec3 {
        self.scale * (self.rotation * x) + self.translation
    }

    /// The camera-to-world pose of a camera moved with the scene: rotation `R·R_p`,
    /// centre `s·R·c + t` (the camera's intrinsics are unchanged; its world-space depth
    /// scales by `s`).
    #[must_use]
    pub fn transform_pose(&self, pose: &DAffine3) -> DAffine3 {
        DAffine3::from_mat3_translation(
            DMat3::from_quat(self.rotation) * pose.matrix3,
            self.transform_point(pose.translation),
        )
    }

    /// The inverse map `x = R⁻¹(y − t)/s`.
    #[must_use]
    pub fn inverse(&self) -> Self {
        let r = self.rotation.inverse();
        Self {
            scale: 1.0 / self.scale,
            rotation: r,
            translation: -(r * self.translation) / self.scale,
        }
    }
}

/// The similarity `y ≈ s·R·x + t` that best maps the points `from` onto `to` in least
/// squares, `min Σᵢ |s·R·fromᵢ + t − toᵢ|²` over proper rotations `R` (Horn 1987: `R` is
/// the quaternion of the largest eigenvalue of a symmetric 4 × 4 matrix of the centred
/// cross-covariance; `s = Σ yᵢ·R xᵢ / Σ |xᵢ|²` on centred points; `t` from the centroids).
/// Used to align cameras refined jointly with a scene to the true cameras (their
/// centres as the points) before comparing poses or the scene.
///
/// The eigenvector is found by cyclic Jacobi rotations (at most 64 sweeps), so the cost
/// is `O(n)` for `n` points and there is no SVD.
///
/// ```
/// use glam::{DQuat, DVec3};
/// use neural_fields::camera::{align_similarity, Similarity};
///
/// let truth = Similarity {
///     scale: 2.0,
///     rotation: DQuat::from_rotation_z(0.3),
///     translation: DVec3::new(1.0, -2.0, 0.5),
/// };
/// let from = [DVec3::X, DVec3::Y, DVec3::Z, DVec3::ONE];
/// let to: Vec<DVec3> = from.iter().map(|&p| truth.transform_point(p)).collect();
/// let s = align_similarity(&from, &to)?;
/// assert!((s.scale - 2.0).abs() < 1e-12);
/// assert!(s.rotation.angle_between(truth.rotation) < 1e-9);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `to` if its length differs from `from`'s; `from` if
/// it has fewer than 3 points, a non-finite coordinate, or points that do not span a
/// plane (the rotation about their line is then undetermined); `to` for a non-finite
/// coordinate or if all its points coincide (no scale).
pub fn align_similarity(from: &[DVec3], to: &[DVec3]) -> Result<Similarity> {
    if to.len() != from.len() {
        return Err(Error::invalid(
            "to",
            format!("{} points (as many as from)", from.len()),
            to.len().to_string(),
        ));
    }
    if from.len() < 3 {
        return Err(Error::invalid(
            "from",
            "at least 3 points",
            from.len().to_string(),
        ));
    }
    for (pts, name) in [(from, "from"), (to, "to")] {
        if let Some(p) = pts.iter().find(|p| !p.is_finite()) {
            return Err(Error::invalid(name, "finite points", format!("{p:?}")));
        }
    }
    let n = from.len() as f64;
    let mean = |p: &[DVec3]| p.iter().fold(DVec3::ZERO, |s, &q| s + q) / n;
    let (mx, my) = (mean(from), mean(to));
    // Centre and scale each set to unit RMS radius so the tests below are relative.
    let rms = |p: &[DVec3], m: DVec3| {
        (p.iter().map(|&q| (q - m).length_squared()).sum::<f64>() / n).sqrt()
    };
    let (rx, ry) = (rms(from, mx), rms(to, my));
    if !(rx > 0.0 && rx.is_finite()) {
        return Err(Error::invalid(
            "from",
            "points that do not all coincide",
            format!("RMS spread {rx}"),
        ));
    }
    if !(ry > 0.0 && ry.is_finite()) {
        return Err(Error::invalid(
            "to",
            "points that do not all coincide",
            format!("RMS spread {ry}"),
        ));
    }
    // Cross-covariance S_ab = Σ x_a y_b of the normalised, centred points.
    let mut s = [[0.0f64; 3]; 3];
    for (&x, &y) in from.iter().zip(to) {
        let (x, y) = (((x - mx) / rx).to_array(), ((y - my) / ry).to_array());
        for a in 0..3 {
            for b in 0..3 {
                s[a][b] += x[a] * y[b] / n;
            }
        }
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let mut m = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (values, vectors) = symmetric_eigen4(&mut m);
    let mut order = [0usize, 1, 2, 3];
    order.sort_by(|&i, &j| values[j].total_cmp(&values[i]));
    // The two largest eigenvalues coincide exactly when the points lie on a line (or
    // the cross-covariance is otherwise rank-deficient in a way that leaves R free).
    if values[order[0]] - values[order[1]] <= 1e-9 {
        return Err(Error::invalid(
            "from",
            "points spanning a plane (a unique rotation)",
            format!("eigenvalue gap {:e}", values[order[0]] - values[order[1]]),
        ));
    }
    let q = vectors[order[0]];
    let rotation = DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize();
    let (mut num, mut den) = (0.0, 0.0);
    for (&x, &y) in from.iter().zip(to) {
        num += (y - my).dot(rotation * (x - mx));
        den += (x - mx).length_squared();
    }
    let scale = num / den;
    if !(scale > 0.0 && scale.is_finite()) {
        return Err(Error::invalid(
            "to",
            "points related to from by a positive scale",
            format!("least-squares scale {scale}"),
        ));
    }
    Ok(Similarity {
        scale,
        rotation,
        translation: my - scale * (rotation * mx),
    })
}

/// The similarity `S` from the frame of the cameras `from` (a reconstruction's, with its
/// scene) to the frame of the cameras `to` (the reference) under which the cameras agree
/// best in **what they see**: the least-squares fit of the reprojections of the scene
/// `points` (in `from`'s frame),
///
/// `min_S Σᵢ Σₖ |π_toᵢ(S·yₖ) − π_fromᵢ(yₖ)|²` (pixels),
///
/// over every pair of camera `i` and point `yₖ` that `fromᵢ` sees in front of it and
/// inside its image ([`Camera::project`]). A pinhole projection is unchanged when its
/// camera and the point move by one similarity, so each residual is the disagreement of
/// the reference camera `toᵢ` and the reconstruction's camera moved by `S` on the moved
/// point: a point of the scene lands on the same pixel in both.
///
/// Why not the centres ([`align_similarity`], BARF's protocol for comparing poses): a
/// camera refined from images is determined worst along the direction in which a shift
/// of its centre across the line of sight and the matching turn leave the scene's image
/// in place. A fit of the centres gives that direction full weight, so each camera's
/// error along it moves the whole fitted scene; this fit gives it the little weight the
/// images give it, and places the scene where the cameras' views put it. For a scene
/// learnt with refined cameras, compare the scene after this alignment and the poses
/// after the centres' one.
///
/// Solved by Levenberg–Marquardt ([`crate::numerics::damped_solve`]) on a local chart
/// `x ↦ e^σ·exp([ω]×)·(S(x) − m) + m + v` about the moved points' centroid `m`, with
/// central-difference Jacobians in f64 (7 parameters), from the centres' fit, for at
/// most 100 iterations. The pairs are chosen once, at `S`'s start; a step that takes
/// one of them behind its reference camera is refused. Cost per iteration: `O(15·P)`
/// projections for `P` pairs. The cameras' intrinsics may differ between `from` and
/// `to`.
///
/// ```
/// use glam::{DQuat, DVec3};
/// use neural_fields::camera::{align_cameras, Camera, Convention, Intrinsics, Similarity};
///
/// let k = Intrinsics::from_fov_y(64, 64, 0.7)?;
/// let truth = Similarity {
///     scale: 1.5,
///     rotation: DQuat::from_rotation_y(0.4),
///     translation: DVec3::new(0.2, -0.1, 0.3),
/// };
/// let eyes = [(3.0, 0.0, 0.5), (0.0, 3.0, -0.5), (-3.0, 0.5, 0.0), (0.5, -3.0, 1.0)];
/// let mut from = Vec::new();
/// let mut to = Vec::new();
/// for (x, y, z) in eyes {
///     let c = Camera::look_at(k, DVec3::new(x, y, z), DVec3::ZERO, DVec3::Z, Convention::OpenCv)?;
///     to.push(Camera::new(k, truth.transform_pose(&c.cam_to_world()), Convention::OpenCv)?);
///     from.push(c);
/// }
/// let points = [DVec3::ZERO, DVec3::X * 0.3, DVec3::Y * 0.3, DVec3::Z * 0.3];
/// let s = align_cameras(&from, &to, &points)?;
/// assert!((s.scale - 1.5).abs() < 1e-9);
/// assert!(s.rotation.angle_between(truth.rotation) < 1e-9);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `to` if its length differs from `from`'s; `from` if
/// the centres' fit that starts the solve fails (fewer than 3 cameras, or centres on one
/// line: [`align_similarity`]); `points` if it is empty, has a non-finite coordinate, or
/// no camera of `from` sees any of its points.
pub fn align_cameras(from: &[Camera], to: &[Camera], points: &[DVec3]) -> Result<Similarity> {
    check_views(from, to, points)?;
    let centres = |cams: &[Camera]| cams.iter().map(Camera::center).collect::<Vec<_>>();
    let start = align_similarity(&centres(from), &centres(to))?;
    let pairs = seen_pairs(from, to, points, &start)?;
    // The residuals of `s`, or `None` when a pair's point falls behind its camera.
    let residuals = |s: &Similarity| -> Option<Vec<f64>> {
        let moved: Vec<DVec3> = points.iter().map(|&y| s.transform_point(y)).collect();
        let mut r = Vec::with_capacity(2 * pairs.len());
        for &(i, j, seen, _) in &pairs {
            let p = to[i].project(moved[j])?;
            r.push(p.x - seen.x);
            r.push(p.y - seen.y);
        }
        Some(r)
    };
    let cost = |r: &[f64]| r.iter().map(|x| x * x).sum::<f64>();
    // The chart at `s`: 7 parameters (ω, v, σ) about the moved points' centroid.
    let centroid = |s: &Similarity| {
        points
            .iter()
            .fold(DVec3::ZERO, |a, &y| a + s.transform_point(y))
            / points.len() as f64
    };
    let chart = |s: &Similarity, m: DVec3, p: &[f64; 7]| -> Similarity {
        let turn = DQuat::from_scaled_axis(DVec3::new(p[0], p[1], p[2]));
        let grow = p[6].exp();
        Similarity {
            scale: grow * s.scale,
            rotation: (turn * s.rotation).normalize(),
            translation: grow * (turn * (s.translation - m)) + m + DVec3::new(p[3], p[4], p[5]),
        }
    };
    let mut s = start;
    let Some(mut r) = residuals(&s) else {
        // invariant: every pair was kept only where `to` projects it at `start`.
        return Ok(start);
    };
    let mut lambda = 1e-3;
    for _ in 0..100 {
        let m = centroid(&s);
        let spread = (points
            .iter()
            .map(|&y| (s.transform_point(y) - m).length_squared())
            .sum::<f64>()
            / points.len() as f64)
            .sqrt()
            .max(1e-300);
        // Central differences: unit-free steps for ω and σ, a fraction of the points'
        // spread for v.
        let mut jac: Vec<Vec<f64>> = Vec::with_capacity(7);
        for a in 0..7 {
            let h = if (3..6).contains(&a) {
                1e-6 * spread
            } else {
                1e-6
            };
            let mut p = [0.0; 7];
            p[a] = h;
            let plus = residuals(&chart(&s, m, &p));
            p[a] = -h;
            let minus = residuals(&chart(&s, m, &p));
            let (Some(plus), Some(minus)) = (plus, minus) else {
                return Ok(s);
            };
            jac.push(
                plus.iter()
                    .zip(&minus)
                    .map(|(a, b)| (a - b) / (2.0 * h))
                    .collect(),
            );
        }
        let mut h = [[0.0f64; 7]; 7];
        let mut g = [0.0f64; 7];
        for a in 0..7 {
            g[a] = jac[a].iter().zip(&r).map(|(x, y)| x * y).sum();
            for b in 0..=a {
                h[a][b] = jac[a].iter().zip(&jac[b]).map(|(x, y)| x * y).sum();
                h[b][a] = h[a][b];
            }
        }
        let current = cost(&r);
        let mut accepted = false;
        while lambda < 1e12 {
            let Some(step) = crate::numerics::damped_solve(&h, &g, lambda) else {
                lambda *= 10.0;
                continue;
            };
            let trial = chart(&s, m, &step);
            match residuals(&trial) {
                Some(next) if cost(&next) < current => {
                    s = trial;
                    r = next;
                    lambda = (lambda / 10.0).max(1e-12);
                    accepted = true;
                    break;
                }
                _ => lambda *= 10.0,
            }
        }
        if !accepted || current - cost(&r) <= 1e-12 * current {
            break;
        }
    }
    Ok(s)
}

/// The argument checks that [`align_cameras`] and [`reprojection_error`] share.
fn check_views(from: &[Camera], to: &[Camera], points: &[DVec3]) -> Result<()> {
    if to.len() != from.len() {
        return Err(Error::invalid(
            "to",
            format!("{} cameras (as many as from)", from.len()),
            to.len().to_string(),
        ));
    }
    if points.is_empty() {
        return Err(Error::invalid("points", "at least one point", "none"));
    }
    if let Some(p) = points.iter().find(|p| !p.is_finite()) {
        return Err(Error::invalid("points", "finite points", format!("{p:?}")));
    }
    Ok(())
}

/// The pairs of [`align_cameras`] and [`reprojection_error`]: camera `i` and point `k`
/// where `from[i]` sees `points[k]` in front of it and inside its image (edges
/// included) and `to[i]` sees `frame·points[k]` in front of it, with the pixels `from[i]`
/// and `to[i]` see them at.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `points` when there is no such pair.
fn seen_pairs(
    from: &[Camera],
    to: &[Camera],
    points: &[DVec3],
    frame: &Similarity,
) -> Result<Vec<(usize, usize, DVec2, DVec2)>> {
    let moved: Vec<DVec3> = points.iter().map(|&y| frame.transform_point(y)).collect();
    let mut pairs = Vec::new();
    for (i, (f, t)) in from.iter().zip(to).enumerate() {
        let k = f.intrinsics();
        let inside = |p: DVec3| {
            (0.0..=k.width as f64).contains(&p.x) && (0.0..=k.height as f64).contains(&p.y)
        };
        for (j, (&y, &m)) in points.iter().zip(&moved).enumerate() {
            if let (Some(p), Some(q)) = (f.project(y).filter(|&p| inside(p)), t.project(m)) {
                pairs.push((i, j, p.truncate(), q.truncate()));
            }
        }
    }
    if pairs.is_empty() {
        return Err(Error::invalid(
            "points",
            "points that some camera of from sees (in front of it, inside its image)",
            format!("none of {} points", points.len()),
        ));
    }
    Ok(pairs)
}

/// The mean distance in pixels between where `from` sees `points` and where `to` sees
/// them moved by `frame`:
///
/// `(1/|P|) Σ_{(i,k)∈P} |π_toᵢ(S·yₖ) − π_fromᵢ(yₖ)|`,
///
/// over the pairs `P` of camera `i` and point `yₖ` that `fromᵢ` sees in front of it and
/// inside its image and `toᵢ` sees in front of it. [`align_cameras`] selects its pairs
/// the same way (at its starting similarity) and minimises their squared residuals, so
/// with `frame` its result this is that fit's residual, as a mean distance.
///
/// It measures a camera's error as a scene learnt with that camera feels it. Unlike the
/// rotation and centre errors after [`align_similarity`], it leaves out what the images do not show: a camera
/// orbited a little about the scene and turned to match sees nearly the same image and
/// scores nearly zero here. `points` are in `from`'s frame (for a reconstruction: points
/// of its surface), `frame` maps them into `to`'s (the identity when both are in one).
/// Plain f64 geometry, not differentiable. Cost: `O(|from|·|points|)` projections.
///
/// ```
/// use glam::DVec3;
/// use neural_fields::camera::{reprojection_error, Camera, Convention, Intrinsics, Similarity};
///
/// let k = Intrinsics::from_fov_y(64, 64, 0.7)?;
/// let eye = DVec3::new(0.0, -3.0, 0.0);
/// let cam = Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenCv)?;
/// // The same camera shifted sideways by 0.03 (a hundredth of its distance).
/// let side = DVec3::X * 0.03;
/// let shifted = Camera::look_at(k, eye + side, side, DVec3::Z, Convention::OpenCv)?;
/// let points = [DVec3::ZERO, DVec3::new(0.2, 0.0, 0.1)];
/// let none = reprojection_error(&[cam], &[cam], &points, &Similarity::IDENTITY)?;
/// let some = reprojection_error(&[cam], &[shifted], &points, &Similarity::IDENTITY)?;
/// assert!(none < 1e-12);
/// // Every point seen a hundredth of the focal length (fy ≈ 87.7 px) off: about 0.88 px.
/// assert!((some - 0.01 * k.fy).abs() < 1e-9);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `to` if its length differs from `from`'s; `points` if
/// it is empty, has a non-finite coordinate, or no pair is seen; `frame` if it is not
/// finite.
pub fn reprojection_error(
    from: &[Camera],
    to: &[Camera],
    points: &[DVec3],
    frame: &Similarity,
) -> Result<f64> {
    check_views(from, to, points)?;
    if !(frame.scale.is_finite() && frame.rotation.is_finite() && frame.translation.is_finite()) {
        return Err(Error::invalid(
            "frame",
            "a finite similarity",
            format!("{frame:?}"),
        ));
    }
    let pairs = seen_pairs(from, to, points, frame)?;
    let sum: f64 = pairs.iter().map(|(_, _, p, q)| (*q - *p).length()).sum();
    Ok(sum / pairs.len() as f64)
}

/// `pose` (camera-to-world) moved by the rigid step `step = (ω, v)`: rotation
/// `exp([ω]×)·R` (a turn by `|ω|` radians about the world axis `ω` through the camera
/// centre), centre `c + v`.
///
/// The retraction of a Gauss–Newton or Levenberg–Marquardt step on a camera: the six
/// parameters are a local chart at `pose` with no singularity near zero, unlike Euler
/// angles, and no normalisation constraint, unlike a quaternion. Differentiate a
/// residual w.r.t. `step` at zero (analytically or by differences of this map), solve
/// for the step ([`crate::numerics::damped_solve`]) and apply it here.
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

/// Eigenvalues and unit eigenvectors of the symmetric 4 × 4 matrix `m` (destroyed) by
/// cyclic Jacobi rotations; `vectors[k]` belongs to `values[k]`.
fn symmetric_eigen4(m: &mut [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0f64; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    let scale: f64 = m.iter().flatten().map(|x| x * x).sum::<f64>().sqrt();
    for _sweep in 0..64 {
        let off: f64 = (0..4)
            .flat_map(|i| (0..4).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| m[i][j] * m[i][j])
            .sum::<f64>()
            .sqrt();
        if off <= 1e-15 * scale || off == 0.0 {
            break;
        }
        for p in 0..3 {
            for q in p + 1..4 {
                if m[p][q] == 0.0 {
                    continue;
                }
                // The rotation in the (p, q) plane that zeroes m[p][q].
                let theta = (m[q][q] - m[p][p]) / (2.0 * m[p][q]);
                // (signum(0) = 1: a rotation by π/4 when the diagonal entries are equal.)
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for row in m.iter_mut() {
                    let (mkp, mkq) = (row[p], row[q]);
                    row[p] = c * mkp - s * mkq;
                    row[q] = s * mkp + c * mkq;
                }
                let (row_p, row_q) = (m[p], m[q]);
                for k in 0..4 {
                    m[p][k] = c * row_p[k] - s * row_q[k];
                    m[q][k] = s * row_p[k] + c * row_q[k];
                }
                for row in v.iter_mut() {
                    let (vp, vq) = (row[p], row[q]);
                    row[p] = c * vp - s * vq;
                    row[q] = s * vp + c * vq;
                }
            }
        }
    }
    let values = [m[0][0], m[1][1], m[2][2], m[3][3]];
    // Column k of v is the eigenvector of values[k].
    let mut vectors = [[0.0f64; 4]; 4];
    for (k, vec) in vectors.iter_mut().enumerate() {
        for (i, x) in vec.iter_mut().enumerate() {
            *x = v[i][k];
        }
    }
    (values, vectors)
}
