//! Pictures of shapes: the crate's ray march on an implicit surface, shaded by its normal.

use candle_core::{DType, Device, Tensor};
use neural_fields::camera::{ray_aabb, Camera, Convention, Intrinsics};
use neural_fields::dvr::{march, sphere_trace, MarchConfig, SphereTraceConfig};
use neural_fields::field::{ImplicitSurface, Inside};
use neural_fields::glam::DVec3;
use neural_fields::rng::SplitMix64;
use neural_fields::Result;

/// Half-side of the box the march searches: the normalised shapes' cube with a margin.
const BOX: f64 = 0.55;

/// A camera at distance 2 looking at the origin, up `+y`, from a random azimuth and an
/// elevation of 10°–40°, 0.7 rad vertical field of view (the cube `[−½, ½]³` fills most
/// of the frame from any side).
pub fn random_camera(rng: &mut SplitMix64, size: usize) -> Result<Camera> {
    let azimuth = std::f64::consts::TAU * rng.uniform();
    let elevation = (10.0 + 30.0 * rng.uniform()).to_radians();
    let eye = 2.0
        * DVec3::new(
            elevation.cos() * azimuth.sin(),
            elevation.sin(),
            elevation.cos() * azimuth.cos(),
        );
    Camera::look_at(
        Intrinsics::from_fov_y(size, size, 0.7)?,
        eye,
        DVec3::ZERO,
        DVec3::Y,
        Convention::OpenCv,
    )
}

/// The light of a view: from the camera's side and above, jittered per view.
pub fn random_light(rng: &mut SplitMix64, camera: &Camera) -> DVec3 {
    let eye = camera.cam_to_world().translation;
    let jitter = DVec3::new(rng.uniform(), rng.uniform(), rng.uniform()) - 0.5;
    (eye.normalize() + DVec3::Y * 0.8 + jitter).normalize()
}

/// `surface` seen from `camera`: `[H, W, 3]` f32 in `[0, 1]`, white background, grey
/// Lambertian shading `0.25 + 0.7·max(0, n·l)` with the outward normal `n` from central
/// differences of the field (step 1e-3) at the march's surface points.
pub fn shade(
    surface: &dyn ImplicitSurface,
    camera: &Camera,
    light: DVec3,
    dev: &Device,
) -> Result<Tensor> {
    let (w, h) = (camera.intrinsics().width, camera.intrinsics().height);
    let rays = camera.rays(dev, DType::F32)?;
    let bounds = ray_aabb(&rays, [-BOX; 3], [BOX; 3])?;
    // Sphere tracing where the field bounds the distance (the analytic shapes), else a
    // march of 96 steps with secant refinement (the networks' logits).
    let hits = match surface.inside() {
        Inside::Negative => {
            let config = SphereTraceConfig {
                max_iters: 24,
                threshold: 1e-3,
                fallback: MarchConfig {
                    steps: 32,
                    ..MarchConfig::default()
                },
                ..SphereTraceConfig::default()
            };
            sphere_trace(surface, &rays, &bounds, &config)?
        }
        Inside::Positive => {
            let config = MarchConfig {
                steps: 96,
                ..MarchConfig::default()
            };
            march(surface, &rays, &bounds, &config)?
        }
    };
    let p = hits.points.to_dtype(DType::F32)?;
    let step = 1e-3;
    let mut grad = Vec::new();
    for axis in 0..3 {
        let mut e = [0f32; 3];
        e[axis] = step as f32;
        let e = Tensor::new(&e, dev)?.unsqueeze(0)?;
        let up = surface.value(&p.broadcast_add(&e)?)?;
        let down = surface.value(&p.broadcast_sub(&e)?)?;
        grad.push(((up - down)? * (0.5 / step))?);
    }
    let g = Tensor::stack(&grad, 1)?;
    // Outward: up the distance of an inside-negative field, down the logits otherwise.
    let g = match surface.inside() {
        Inside::Negative => g,
        Inside::Positive => g.neg()?,
    };
    let norm = g
        .sqr()?
        .sum_keepdim(1)?
        .sqrt()?
        .clamp(1e-12, f64::INFINITY)?;
    let n = g.broadcast_div(&norm)?;
    let l = Tensor::new(&[light.x as f32, light.y as f32, light.z as f32], dev)?;
    let lambert = n.broadcast_mul(&l.unsqueeze(0)?)?.sum(1)?.relu()?;
    let grey = lambert.affine(0.7, 0.25)?;
    let mask = hits.mask.to_dtype(DType::F32)?;
    let grey = ((grey * &mask)? + (mask.affine(-1.0, 1.0))?)?;
    Ok(grey
        .unsqueeze(1)?
        .broadcast_as((w * h, 3))?
        .contiguous()?
        .reshape((h, w, 3))?)
}

/// The points `[N, 3]` projected by `camera` as dark dots on white, `[H, W, 3]`.
pub fn dots(points: &[f32], camera: &Camera) -> Result<Tensor> {
    let (w, h) = (camera.intrinsics().width, camera.intrinsics().height);
    let mut img = vec![1f32; w * h * 3];
    for p in points.chunks_exact(3) {
        let x = DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        if let Some(q) = camera.project(x) {
            let (u, v) = (q.x.floor(), q.y.floor());
            if u >= 0.0 && v >= 0.0 && (u as usize) < w && (v as usize) < h {
                let i = 3 * (v as usize * w + u as usize);
                img[i..i + 3].copy_from_slice(&[0.1, 0.1, 0.1]);
            }
        }
    }
    Ok(Tensor::from_vec(img, (h, w, 3), &Device::Cpu)?)
}
