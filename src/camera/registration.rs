//! Photometric registration of cameras to a rendered scene: direct image alignment of
//! each camera's pose by Levenberg–Marquardt, coarse to fine.

use super::pose::{pose_error, retract_pose};
use super::rays::Rays;
use super::Camera;
use crate::error::{Error, Result};
use crate::numerics::{levenberg_marquardt, robust_cost, LmConfig};
use candle_core::{DType, Tensor};
use glam::{DAffine3, DVec2, DVec3};

/// The settings of [`register_poses`]. The defaults are those that registered the
/// committed DVR dataset's cameras best (`docs/benchmarks.md`).
#[derive(Clone, Debug, PartialEq)]
pub struct RegistrationConfig {
    /// The Gaussian blurs (σ, pixels) of the coarse-to-fine levels, coarsest first;
    /// `[2, 1, 0]`.
    pub blurs: Vec<f64>,
    /// The solver at each level: 10 trial steps, `tolerance` 0, Huber's threshold 0.1 per
    /// channel, and [`LmConfig::default`]'s damping schedule.
    pub solver: LmConfig,
    /// σ (pixels) of the images' pixel filter, which the point-sampled render gets as an
    /// extra blur: 0.4155, a Gaussian like Cycles' Blackman–Harris window
    /// ([`crate::camera::PixelFilter::CYCLES`]).
    pub filter_sigma: f64,
    /// Pixels added around the bounding box of the image's coverage (alpha > 0) that is
    /// rendered; 4.
    pub margin: usize,
    /// The most one registration may move a camera: degrees of rotation and fraction of
    /// its distance to the origin; `(5, 0.05)`. A camera the alignment would move further
    /// (a scene that is not yet right can draw it anywhere) keeps its pose.
    pub max_move: (f64, f64),
    /// The images' background colour, given to the pixels outside the rendered box;
    /// white.
    pub background: [f64; 3],
    /// Rays per call of the renderer; 8192.
    pub chunk: usize,
}

impl Default for RegistrationConfig {
    fn default() -> Self {
        Self {
            blurs: vec![2.0, 1.0, 0.0],
            solver: LmConfig {
                iterations: 10,
                tolerance: 0.0,
                huber: Some(0.1),
                ..LmConfig::default()
            },
            filter_sigma: 0.4155,
            margin: 4,
            max_move: (5.0, 0.05),
            background: [1.0; 3],
            chunk: 8192,
        }
    }
}

/// Registers each camera to a scene held fixed by direct image alignment: the scene is
/// rendered from the camera (`render` on the rays through the pixel centres of the
/// bounding box of the image's coverage, grown by `config.margin`), and the pose moves
/// until the true image, seen where the rendered surface points project, matches the
/// render. Returns the cameras at their registered poses (intrinsics and convention
/// kept). One call is one render per camera; call it again from the returned cameras to
/// register against a fresh render.
///
/// **Residuals.** For each rendered pixel `x` with a surface point `X` (its ray's point at
/// the rendered depth where the opacity is at least ½; for a pixel that misses, the point
/// on its ray at the camera-space depth of the nearest hit pixel, so that the background
/// around the silhouette moves with it), four residuals `I(π_pose(X)) − R(x)`: the true
/// image `I` (bilinear, colour and alpha) at the projection of `X` under the pose, minus
/// the render `R` at `x`, both blurred alike. Their Jacobian w.r.t. the pose step of
/// [`retract_pose`] is the image gradient times the projection's derivative (central
/// differences, 10⁻⁶ per parameter).
///
/// **Solve.** [`levenberg_marquardt`] with `config.solver` (Huber's loss), at each blur of
/// `config.blurs` in turn (the render additionally blurred by `config.filter_sigma`,
/// since it is point-sampled where the images integrate over each pixel); if the camera's
/// own pose has a lower cost at the finest level than where the levels ended, it stays.
/// A camera that would move further than `config.max_move`, or whose render has no
/// surface point, keeps its pose. The Gauss–Newton step solves for the direction in which
/// a camera's centre and rotation compensate each other, along which per-parameter
/// gradient steps crawl; it needs a scene that is nearly right.
///
/// Shapes: `images[i]` is `[H, W, 4]` (f32 or f64), camera `i`'s view: colour composited
/// on `config.background` and alpha (coverage). `render(rays)` returns, for `N` rays in
/// the images' dtype and device, `(rgb: [N, 3], depth: [N], opacity: [N])`: the colour
/// composited on the background, the ray parameter `t` of the surface point `o + t·d`,
/// and the opacity. Plain f64 on the host apart from the renders; nothing is
/// differentiable. Cost per camera: one render of the box and, per level, at most
/// `solver.iterations + 1` passes over its pixels with 12 projections each.
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use neural_fields::camera::{
///     pose_error, ray_sphere, register_poses, retract_pose, Camera, Convention, Intrinsics,
///     PixelFilter, Rays, RegistrationConfig,
/// };
/// use neural_fields::glam::DVec3;
///
/// // A ball of radius ½ coloured by its point, on white: colour, depth, opacity per ray.
/// let ball = |rays: &Rays| -> neural_fields::Result<(Tensor, Tensor, Tensor)> {
///     let hit = ray_sphere(rays, [0.0; 3], 0.5)?;
///     let opacity = hit.hit.to_dtype(DType::F64)?;
///     let p = (rays.origins() + rays.directions().broadcast_mul(&hit.near.unsqueeze(1)?)?)?;
///     let red = ((p.narrow(1, 0, 1)? * 7.0)?.sin()? * 0.4)? + 0.5;
///     let green = ((p.narrow(1, 1, 1)? * 5.0)?.cos()? * 0.4)? + 0.5;
///     let blue = ((p.narrow(1, 2, 1)? * 9.0)?.sin()? * 0.3)? + 0.5;
///     let rgb = Tensor::cat(&[red?, green?, blue?], 1)?;
///     let on_white = ((rgb - 1.0)?.broadcast_mul(&opacity.unsqueeze(1)?)? + 1.0)?;
///     Ok((on_white, hit.near, opacity))
/// };
/// let k = Intrinsics::from_fov_y(64, 64, 0.6)?;
/// let truth = Camera::look_at(k, DVec3::new(2.0, -2.0, 1.0), DVec3::ZERO, DVec3::Z, Convention::OpenGl)?;
/// // Its image, 4 × 4 rays per pixel averaged: colour and alpha, [64, 64, 4].
/// let grid = truth.subpixel_grid(4, PixelFilter::Box, &Device::Cpu, DType::F64)?;
/// let (rgb, _, alpha) = ball(&truth.rays_for_pixels(&grid)?)?;
/// let rgba = Tensor::cat(&[rgb, alpha.unsqueeze(1)?], 1)?;
/// let image = rgba.reshape((64, 64, 16, 4))?.mean(2)?;
/// // The camera turned by about 1.6° and moved by about 1.5 % of its distance.
/// let start = retract_pose(&truth.cam_to_world(), [0.02, -0.02, 0.0, 0.03, 0.0, -0.03]);
/// let mut cameras = vec![Camera::new(k, start, Convention::OpenGl)?];
/// for _ in 0..3 {
///     cameras = register_poses(&cameras, &[image.clone()], ball, &RegistrationConfig::default())?;
/// }
/// let before = pose_error(&[start], &[truth.cam_to_world()])?;
/// let after = pose_error(&[cameras[0].cam_to_world()], &[truth.cam_to_world()])?;
/// // Both errors fall; the centre's by more than half (on a ball the rotation and the
/// // centre nearly compensate each other, so the rotation converges more slowly).
/// assert!(after.0 < before.0 && after.1 < before.1 / 2.0, "{before:?} → {after:?}");
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `images` unless there is one per camera, each a
/// float `[H, W, 4]` tensor of its camera's image size; `render` if it returns tensors
/// of other shapes; `config` if `blurs` is empty or has a negative or non-finite entry,
/// `filter_sigma` is negative or not finite, `chunk` is 0, or `solver` is refused by
/// [`levenberg_marquardt`]; and whatever `render` returns.
pub fn register_poses(
    cameras: &[Camera],
    images: &[Tensor],
    mut render: impl FnMut(&Rays) -> Result<(Tensor, Tensor, Tensor)>,
    config: &RegistrationConfig,
) -> Result<Vec<Camera>> {
    let sane = |s: &f64| *s >= 0.0 && s.is_finite();
    if config.blurs.is_empty()
        || !config.blurs.iter().all(sane)
        || !sane(&config.filter_sigma)
        || config.chunk == 0
    {
        return Err(Error::invalid(
            "config",
            "blurs ≥ 0 (at least one), filter_sigma ≥ 0, chunk > 0",
            format!(
                "blurs {:?}, filter_sigma {}, chunk {}",
                config.blurs, config.filter_sigma, config.chunk
            ),
        ));
    }
    if images.len() != cameras.len() {
        return Err(Error::invalid(
            "images",
            format!("{} images (one per camera)", cameras.len()),
            images.len().to_string(),
        ));
    }
    let mut registered = Vec::with_capacity(cameras.len());
    for (camera, image) in cameras.iter().zip(images) {
        let truth = Planes::of_image(image, camera)?;
        let (rendered, points) = render_box(camera, &truth, image, &mut render, config)?;
        if points.is_empty() {
            registered.push(*camera);
            continue;
        }
        let levels: Vec<Planes> = config.blurs.iter().map(|&s| truth.blurred(s)).collect();
        let aligned = align_view(camera, &levels, &rendered, &points, config)?;
        let before = camera.cam_to_world();
        let (turn, shift) = pose_error(&[aligned], &[before])?;
        registered.push(if turn <= config.max_move.0 && shift <= config.max_move.1 {
            Camera::new(*camera.intrinsics(), aligned, camera.convention())?
        } else {
            *camera
        });
    }
    Ok(registered)
}

/// An image as bilinearly sampled planes: red, green, blue and alpha.
#[derive(Clone, Debug)]
struct Planes {
    w: usize,
    h: usize,
    px: Vec<[f64; 4]>,
}

impl Planes {
    /// `image` (`[H, W, 4]`, float) on the host, checked against `camera`'s image size.
    fn of_image(image: &Tensor, camera: &Camera) -> Result<Self> {
        let k = camera.intrinsics();
        let (h, w) = (k.height, k.width);
        if !matches!(image.dtype(), DType::F32 | DType::F64) || image.dims() != [h, w, 4] {
            return Err(Error::invalid(
                "images",
                format!("float [{h}, {w}, 4] images (colour and alpha) of the cameras' size"),
                format!("{:?} {:?}", image.dtype(), image.dims()),
            ));
        }
        let values = image
            .to_dtype(DType::F64)?
            .flatten_all()?
            .to_vec1::<f64>()?;
        let px = values
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect();
        Ok(Self { w, h, px })
    }

    /// Blurred by a Gaussian of `sigma` pixels (separable, truncated at 3σ, edges
    /// clamped); itself for `sigma = 0`.
    fn blurred(&self, sigma: f64) -> Self {
        if sigma <= 0.0 {
            return self.clone();
        }
        let r = (3.0 * sigma).ceil() as isize;
        let k: Vec<f64> = (-r..=r)
            .map(|i| (-0.5 * (i as f64 / sigma).powi(2)).exp())
            .collect();
        let total: f64 = k.iter().sum();
        let pass = |src: &[[f64; 4]], horizontal: bool| -> Vec<[f64; 4]> {
            let mut out = vec![[0.0; 4]; src.len()];
            for y in 0..self.h {
                for x in 0..self.w {
                    let mut acc = [0.0; 4];
                    for (j, &kj) in k.iter().enumerate() {
                        let o = j as isize - r;
                        let (sx, sy) = if horizontal {
                            ((x as isize + o).clamp(0, self.w as isize - 1) as usize, y)
                        } else {
                            (x, (y as isize + o).clamp(0, self.h as isize - 1) as usize)
                        };
                        let p = src[sy * self.w + sx];
                        for c in 0..4 {
                            acc[c] += kj * p[c];
                        }
                    }
                    out[y * self.w + x] = acc.map(|a| a / total);
                }
            }
            out
        };
        let px = pass(&pass(&self.px, true), false);
        Self { px, ..*self }
    }

    /// The bilinear interpolation at the continuous pixel coordinate `u` (pixel `(i, j)`
    /// has its centre at `(i + ½, j + ½)`; edges clamped) and its derivatives along x
    /// and y.
    fn sample(&self, u: DVec2) -> ([f64; 4], [[f64; 4]; 2]) {
        let fx = (u.x - 0.5).clamp(0.0, (self.w - 1) as f64);
        let fy = (u.y - 0.5).clamp(0.0, (self.h - 1) as f64);
        let (x0, y0) = (
            (fx.floor() as usize).min(self.w.saturating_sub(2)),
            (fy.floor() as usize).min(self.h.saturating_sub(2)),
        );
        let (x1, y1) = ((x0 + 1).min(self.w - 1), (y0 + 1).min(self.h - 1));
        let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
        let at = |x: usize, y: usize| self.px[y * self.w + x];
        let (a, b, c, d) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
        let mut value = [0.0; 4];
        let mut grad = [[0.0; 4]; 2];
        for k in 0..4 {
            value[k] =
                (1.0 - ty) * ((1.0 - tx) * a[k] + tx * b[k]) + ty * ((1.0 - tx) * c[k] + tx * d[k]);
            grad[0][k] = (1.0 - ty) * (b[k] - a[k]) + ty * (d[k] - c[k]);
            grad[1][k] = (1.0 - tx) * (c[k] - a[k]) + tx * (d[k] - b[k]);
        }
        (value, grad)
    }
}

/// The pixels of the bounding box of `truth`'s coverage (alpha > 0) grown by `margin`
/// pixels, as indices `y·w + x`; none for an empty image.
fn box_pixels(truth: &Planes, margin: usize) -> Vec<usize> {
    let (w, h) = (truth.w, truth.h);
    let covered = |x: usize, y: usize| truth.px[y * w + x][3] > 0.0;
    let ys: Vec<usize> = (0..h).filter(|&y| (0..w).any(|x| covered(x, y))).collect();
    let xs: Vec<usize> = (0..w).filter(|&x| (0..h).any(|y| covered(x, y))).collect();
    let (Some(&y0), Some(&y1), Some(&x0), Some(&x1)) =
        (ys.first(), ys.last(), xs.first(), xs.last())
    else {
        return Vec::new();
    };
    let grow = |lo: usize, hi: usize, n: usize| lo.saturating_sub(margin)..(hi + margin + 1).min(n);
    grow(y0, y1, h)
        .flat_map(|y| grow(x0, x1, w).map(move |x| y * w + x))
        .collect()
}

/// The scene as `camera` sees it on the box of [`box_pixels`]: the planes of the render
/// (`render`'s colour and opacity on the box, the background elsewhere) and, for every
/// pixel of the box, a 3-D point: its surface point where the opacity is at least ½, or
/// for a miss the point on its ray at the camera-space depth of its nearest hit
/// (4-neighbour breadth-first within the box). Pixels with no hit within reach get none.
fn render_box(
    camera: &Camera,
    truth: &Planes,
    like: &Tensor,
    render: &mut impl FnMut(&Rays) -> Result<(Tensor, Tensor, Tensor)>,
    config: &RegistrationConfig,
) -> Result<(Planes, Vec<(usize, DVec3)>)> {
    let (w, h) = (truth.w, truth.h);
    let pixels = box_pixels(truth, config.margin);
    let [r, g, b] = config.background;
    let mut planes = Planes {
        w,
        h,
        px: vec![[r, g, b, 0.0]; w * h],
    };
    let mut depth: Vec<Option<f64>> = vec![None; w * h];
    let centre = |i: usize| DVec2::new((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
    for part in pixels.chunks(config.chunk) {
        let n = part.len();
        let coords: Vec<f64> = part.iter().flat_map(|&i| centre(i).to_array()).collect();
        let coords = Tensor::from_vec(coords, (n, 2), like.device())?.to_dtype(like.dtype())?;
        let (rgb, t, opacity) = render(&camera.rays_for_pixels(&coords)?)?;
        if rgb.dims() != [n, 3] || t.dims() != [n] || opacity.dims() != [n] {
            return Err(Error::invalid(
                "render",
                format!("rgb [{n}, 3], depth [{n}] and opacity [{n}]"),
                format!("{:?}, {:?}, {:?}", rgb.dims(), t.dims(), opacity.dims()),
            ));
        }
        let host = |x: &Tensor| x.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>();
        let (rgb, t, opacity) = (host(&rgb)?, host(&t)?, host(&opacity)?);
        for (k, &i) in part.iter().enumerate() {
            planes.px[i] = [rgb[3 * k], rgb[3 * k + 1], rgb[3 * k + 2], opacity[k]];
            if opacity[k] >= 0.5 && t[k].is_finite() {
                let (o, d) = camera.ray(centre(i));
                depth[i] = camera.project(o + t[k] * d).map(|u| u.z);
            }
        }
    }
    let mut inside = vec![false; w * h];
    for &i in &pixels {
        inside[i] = true;
    }
    let mut queue: std::collections::VecDeque<usize> = pixels
        .iter()
        .copied()
        .filter(|&i| depth[i].is_some())
        .collect();
    while let Some(i) = queue.pop_front() {
        let (x, y) = (i % w, i / w);
        let neighbours = [
            (x > 0).then(|| i - 1),
            (x + 1 < w).then(|| i + 1),
            (y > 0).then(|| i - w),
            (y + 1 < h).then(|| i + w),
        ];
        for j in neighbours.into_iter().flatten() {
            if inside[j] && depth[j].is_none() {
                depth[j] = depth[i];
                queue.push_back(j);
            }
        }
    }
    let points = pixels
        .iter()
        .filter_map(|&i| {
            let z = depth[i]?;
            let (o, d) = camera.ray(centre(i));
            Some((i, o + z * d))
        })
        .collect();
    Ok((planes, points))
}

/// The residuals of registering `pose` by direct image alignment and their Jacobian
/// w.r.t. the step of [`retract_pose`] (see [`register_poses`]): four per rendered point
/// that projects under `pose` and its twelve central-difference neighbours.
fn alignment_residuals(
    camera: &Camera,
    pose: &DAffine3,
    truth: &Planes,
    render: &Planes,
    points: &[(usize, DVec3)],
) -> Result<(Vec<f64>, Vec<[f64; 6]>)> {
    let at = |p: DAffine3| Camera::new(*camera.intrinsics(), p, camera.convention());
    let cam = at(*pose)?;
    const H: f64 = 1e-6;
    let mut moved = Vec::with_capacity(12);
    for k in 0..6 {
        for sign in [1.0, -1.0] {
            let mut step = [0.0; 6];
            step[k] = sign * H;
            moved.push(at(retract_pose(pose, step))?);
        }
    }
    let (mut residuals, mut jacobian) = (Vec::new(), Vec::new());
    for &(i, x) in points {
        let Some(u) = cam.project(x) else { continue };
        let mut du = [[0.0; 6]; 2];
        let mut ok = true;
        for k in 0..6 {
            match (moved[2 * k].project(x), moved[2 * k + 1].project(x)) {
                (Some(a), Some(b)) => {
                    du[0][k] = (a.x - b.x) / (2.0 * H);
                    du[1][k] = (a.y - b.y) / (2.0 * H);
                }
                _ => ok = false,
            }
        }
        if !ok {
            continue;
        }
        let (value, grad) = truth.sample(u.truncate());
        let rendered = render.px[i];
        for c in 0..4 {
            residuals.push(value[c] - rendered[c]);
            jacobian.push(std::array::from_fn(|k| {
                grad[0][c] * du[0][k] + grad[1][c] * du[1][k]
            }));
        }
    }
    Ok((residuals, jacobian))
}

/// `camera`'s pose aligned to its true image (`truth`: one blur per `config.blurs`)
/// against the render `render` with its points `points` ([`render_box`]), coarse to
/// fine (see [`register_poses`]).
fn align_view(
    camera: &Camera,
    truth: &[Planes],
    render: &Planes,
    points: &[(usize, DVec3)],
    config: &RegistrationConfig,
) -> Result<DAffine3> {
    let start = camera.cam_to_world();
    let mut pose = start;
    for (level, &sigma) in config.blurs.iter().enumerate() {
        let s = config.filter_sigma;
        let blurred = render.blurred((sigma * sigma + s * s).sqrt());
        let truth = &truth[level];
        let linearize =
            |p: &DAffine3| alignment_residuals(camera, p, truth, &blurred, points).map(Some);
        let (aligned, cost) = levenberg_marquardt(pose, &config.solver, linearize, |p, step| {
            retract_pose(p, *step)
        })?;
        pose = aligned;
        // A registration never raises the finest level's cost: if the camera's own pose
        // has a lower one than where the levels ended, it stays.
        if level + 1 == config.blurs.len() {
            let (r, _) = alignment_residuals(camera, &start, truth, &blurred, points)?;
            if robust_cost(&r, config.solver.huber) < cost {
                pose = start;
            }
        }
    }
    Ok(pose)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    /// Bilinear sampling: exact at pixel centres, its derivative that of the
    /// interpolation (central differences inside a cell); blurring keeps a constant image.
    #[test]
    fn planes_sample_bilinearly_with_their_gradient() {
        let mut rng = SplitMix64::new(5);
        let (w, h) = (7, 5);
        let px: Vec<[f64; 4]> = (0..w * h)
            .map(|_| std::array::from_fn(|_| rng.uniform()))
            .collect();
        let planes = Planes {
            w,
            h,
            px: px.clone(),
        };
        assert_eq!(planes.sample(DVec2::new(3.5, 2.5)).0, px[2 * w + 3]);
        for _ in 0..50 {
            let u = DVec2::new(0.5 + rng.uniform() * 6.0, 0.5 + rng.uniform() * 4.0);
            let (_, grad) = planes.sample(u);
            let e = 1e-7;
            for (axis, step) in [DVec2::X, DVec2::Y].into_iter().enumerate() {
                let (a, _) = planes.sample(u + step * e);
                let (b, _) = planes.sample(u - step * e);
                for c in 0..4 {
                    let fd = (a[c] - b[c]) / (2.0 * e);
                    // Within a cell; a sample on a cell edge has one-sided slopes.
                    if ((u[axis] - 0.5).fract() - 0.5).abs() < 0.49 {
                        assert!(
                            (grad[axis][c] - fd).abs() < 1e-6,
                            "{} vs {fd}",
                            grad[axis][c]
                        );
                    }
                }
            }
        }
        let flat = Planes {
            w,
            h,
            px: vec![[0.25, 0.5, 0.75, 1.0]; w * h],
        };
        for p in flat.blurred(1.5).px {
            assert!(p
                .iter()
                .zip([0.25, 0.5, 0.75, 1.0])
                .all(|(a, b)| (a - b).abs() < 1e-12));
        }
        assert_eq!(planes.blurred(0.0).px, px);
    }
}
