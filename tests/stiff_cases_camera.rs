//! Stiff cases of `camera`: cameras, rays and intersections at extreme poses and
//! pixels; pose retraction, alignment and reprojection error at every magnitude.

mod common;

use candle_core::{DType, Device, Tensor};

use common::stiff::{magnitudes, var, Expect, Suite, DTYPES};

use neural_fields::camera::{
    align_cameras, align_similarity, pose_rays, ray_aabb, ray_sphere, reprojection_error, Camera,
    Convention, Intrinsics, PixelFilter, PoseParam, Rays, Similarity,
};
use neural_fields::glam::{DAffine3, DQuat, DVec3};

#[test]
fn cameras_and_rays_stay_finite() {
    let mut s = Suite::default();
    sweep_camera(&mut s);
    s.finish("cameras and rays", CAMERAS);
}

#[test]
fn pose_alignment_stays_finite() {
    let mut s = Suite::default();
    sweep_camera_host(&mut s);
    s.finish("poses and alignment", POSES);
}

#[test]
fn every_public_camera_function_is_swept_or_exempt() {
    common::stiff::check_coverage("stiff_cases_camera", &[CAMERAS, POSES], EXEMPT, &[], &[]);
}

/// Items swept by `sweep_camera`.
const CAMERAS: &[&str] = &[
    "camera::Camera::look_at",
    "camera::Camera::new",
    "camera::Camera::rays",
    "camera::Camera::rays_for_pixels",
    "camera::Camera::subpixel_grid",
    "camera::Intersection::new",
    "camera::Intrinsics::from_fov_y",
    "camera::Intrinsics::new",
    "camera::PoseParam::from_affine",
    "camera::PoseParam::to_affine",
    "camera::pose_rays",
    "camera::Rays::narrow",
    "camera::Rays::new",
    "camera::Rays::normalized",
    "camera::Rays::radii",
    "camera::Rays::with_radii",
    "camera::ray_aabb",
    "camera::ray_sphere",
];

/// Items swept by `sweep_camera_host`.
const POSES: &[&str] = &[
    "camera::Camera::project",
    "camera::align_cameras",
    "camera::align_similarity",
    "camera::cameras_around",
    "camera::patch_rays",
    "camera::reprojection_error",
    "camera::retract_pose",
    "camera::pose_error",
    "camera::Similarity::apply",
    "camera::DVec3::transformed",
    "camera::DAffine3::transformed",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    ("camera::Camera::cam_to_world", "getter"),
    ("camera::RegistrationConfig::default", "constant"),
    (
        "camera::register_poses",
        "a registration over renders: its numerics are levenberg_marquardt's and retract_pose's, swept",
    ),
    ("camera::Camera::convention", "getter"),
    ("camera::Camera::intrinsics", "getter"),
    ("camera::Convention::", "enum"),
    ("camera::Rays::directions", "getter"),
    ("camera::Rays::is_empty", "getter"),
    ("camera::Rays::len", "getter"),
    ("camera::Rays::origins", "getter"),
];

fn sweep_camera(s: &mut Suite) {
    let d = Device::Cpu;
    for dtype in DTYPES {
        let tag = format!("{dtype:?}");
        for (fx, w) in [(1e-6, 1usize), (500.0, 64), (1e8, 8)] {
            s.case(
                "camera::Intrinsics::new",
                format!("{tag}, fx = {fx}"),
                Expect::Finite,
                &[],
                || {
                    let k = Intrinsics::new(fx, fx, w as f64 / 2.0, w as f64 / 2.0, w, w)?;
                    let px =
                        Tensor::from_slice(&[0.0, 0.0, 1e6, -1e6], (2, 2), &d)?.to_dtype(dtype)?;
                    let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenCv)?;
                    Ok(vec![cam.rays_for_pixels(&px)?.directions().clone()])
                },
            );
        }
        // The camera-space directions of 0.1's `Intrinsics::camera_directions`: an
        // identity pose, a field of view near π.
        s.case(
            "camera::Camera::rays_for_pixels",
            format!("{tag}, identity pose, fov 3.1"),
            Expect::Finite,
            &[],
            || {
                let k = Intrinsics::from_fov_y(4, 4, 3.1)?;
                let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenGl)?;
                Ok(vec![cam
                    .rays_for_pixels(&Tensor::zeros((1, 2), dtype, &d)?)?
                    .directions()
                    .clone()])
            },
        );
        for fov in [1e-12, 1.0, std::f64::consts::PI - 1e-6] {
            s.case(
                "camera::Intrinsics::from_fov_y",
                format!("{tag}, fov = {fov}"),
                Expect::Finite,
                &[],
                || {
                    let k = Intrinsics::from_fov_y(8, 8, fov)?;
                    let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenCv)?;
                    Ok(vec![cam
                        .rays_for_pixels(&Tensor::zeros((1, 2), dtype, &d)?)?
                        .directions()
                        .clone()])
                },
            );
        }
        for eye in [
            DVec3::new(0.0, 0.0, 1e-8),
            DVec3::new(1e8, 1e8, 1e8),
            DVec3::new(0.0, 1e-3, 3.0),
        ] {
            let label = format!("{tag}, eye = {eye}");
            let k = Intrinsics::from_fov_y(4, 3, 0.8).unwrap();
            s.case(
                "camera::Camera::look_at",
                &label,
                Expect::Finite,
                &[],
                || {
                    Ok(vec![Camera::look_at(
                        k,
                        eye,
                        DVec3::ZERO,
                        DVec3::Y,
                        Convention::OpenGl,
                    )?
                    .rays(&d, dtype)?
                    .directions()
                    .clone()])
                },
            );
            let cam = Camera::look_at(k, eye, DVec3::ZERO, DVec3::Y, Convention::OpenGl).unwrap();
            s.case("camera::Camera::rays", &label, Expect::Finite, &[], || {
                let r = cam.rays(&d, dtype)?;
                Ok(vec![r.origins().clone(), r.directions().clone()])
            });
            let filters = [
                PixelFilter::Box,
                PixelFilter::CYCLES,
                PixelFilter::BlackmanHarris { half_width: 64.0 },
                PixelFilter::BlackmanHarris { half_width: 1e-300 },
                PixelFilter::BlackmanHarris {
                    half_width: f64::NAN,
                },
            ];
            for (k, filter) in [1, 3, 64, 65]
                .into_iter()
                .flat_map(|k| filters.map(|f| (k, f)))
            {
                s.case(
                    "camera::Camera::subpixel_grid",
                    format!("{label}, k = {k}, {filter:?}"),
                    if k <= 64 && valid(filter) {
                        Expect::Finite
                    } else {
                        Expect::FiniteOrErr
                    },
                    &[],
                    || {
                        let g = cam.subpixel_grid(k, filter, &d, dtype)?;
                        let r = cam.rays_for_pixels(&g)?;
                        Ok(vec![g, r.directions().clone()])
                    },
                );
            }
            s.case(
                "camera::Camera::rays_for_pixels",
                &label,
                Expect::Finite,
                &[],
                || {
                    let px = Tensor::from_slice(&[1e-30, 1e6], (1, 2), &d)?.to_dtype(dtype)?;
                    Ok(vec![cam.rays_for_pixels(&px)?.directions().clone()])
                },
            );
        }
        s.case(
            "camera::Camera::new",
            format!("{tag}, translation 1e12"),
            Expect::Finite,
            &[],
            || {
                let pose = DAffine3::from_rotation_translation(
                    DQuat::from_rotation_y(0.3),
                    DVec3::splat(1e12),
                );
                Ok(vec![Camera::new(
                    Intrinsics::from_fov_y(2, 2, 1.0)?,
                    pose,
                    Convention::OpenCv,
                )?
                .rays(&d, dtype)?
                .origins()
                .clone()])
            },
        );
        // Rays: huge and tiny origins and directions, exact zeros in direction components.
        // In f32 a unit sphere 1e15 away is below resolution (ulp(1e15) ≈ 7e7): r² is lost
        // in |o − c|² − r², and candle's division backward (grad·lhs/rhs²) overflows an
        // intermediate although the true gradient is finite. f32 sweeps stay within 1e6.
        let big = if dtype == DType::F32 { 1e6 } else { 1e100 };
        let o = var(
            &[
                0.0, 0.0, -3.0, 1e-30, 0.5, -big, 2.0, 2.0, 2.0, 0.0, 0.0, 0.0,
            ],
            &[4, 3],
            dtype,
        );
        // ∂t/∂d ≈ t/|d|: a direction of length 1e-20 from inside a unit box has a true
        // gradient of 1e40, beyond f32; f32 sweeps directions down to 1e-9.
        let short = if dtype == DType::F32 { 1e-9 } else { 1e-20 };
        let w = var(
            &[
                0.0, 0.0, 1.0, 0.0, 0.0, 1e-10, 1e10, 0.0, 0.0, short, short, short,
            ],
            &[4, 3],
            dtype,
        );
        let t = var(&[0.0, 1e-30, 1e10, 1.0], &[4], dtype);
        let label = format!("{tag}, origins up to {big:e}, directions {short:e}…1e10");
        s.case(
            "camera::Rays::new",
            &label,
            Expect::Finite,
            &[&o, &w, &t],
            || {
                let r = Rays::new(o.as_tensor().clone(), w.as_tensor().clone())?;
                let along = r.directions().broadcast_mul(&t.as_tensor().unsqueeze(1)?)?;
                Ok(vec![(r.origins() + along)?])
            },
        );
        s.case(
            "camera::Rays::normalized",
            &label,
            Expect::Finite,
            &[&w],
            || {
                Ok(vec![Rays::new(
                    o.as_tensor().clone(),
                    w.as_tensor().clone(),
                )?
                .normalized()?
                .directions()
                .clone()])
            },
        );
        // Cone radii 0, tiny, huge and ordinary through normalisation (divided by |d|,
        // which reaches `short`).
        let radii = var(&[0.0, 1e-30, 1e10, 1e-3], &[4], dtype);
        for item in ["camera::Rays::with_radii", "camera::Rays::radii"] {
            s.case(item, &label, Expect::FiniteOrErr, &[&w, &radii], || {
                let r = Rays::new(o.as_tensor().clone(), w.as_tensor().clone())?
                    .with_radii(radii.as_tensor().clone())?
                    .normalized()?;
                Ok(vec![r.radii().expect("radii kept").clone()])
            });
        }
        s.case(
            "camera::Rays::narrow",
            &label,
            Expect::Finite,
            &[&o],
            || {
                Ok(vec![Rays::new(
                    o.as_tensor().clone(),
                    w.as_tensor().clone(),
                )?
                .narrow(1, 2)?
                .origins()
                .clone()])
            },
        );
        s.case(
            "camera::ray_aabb",
            &label,
            Expect::FiniteOrErr,
            &[&o, &w],
            || {
                let rays = Rays::new(o.as_tensor().clone(), w.as_tensor().clone())?;
                let i = ray_aabb(&rays, [-1.0; 3], [1.0; 3])?;
                Ok(vec![i.near, i.far, i.hit])
            },
        );
        s.case(
            "camera::ray_sphere",
            &label,
            Expect::FiniteOrErr,
            &[&o, &w],
            || {
                let rays = Rays::new(o.as_tensor().clone(), w.as_tensor().clone())?;
                let i = ray_sphere(&rays, [0.0; 3], 1.0)?;
                Ok(vec![i.near, i.far, i.hit])
            },
        );
        // Explicit search ranges: empty, tiny, huge and negative bounds; and far < near,
        // which must be an Err.
        let nf_big = if dtype == DType::F32 { 1e30 } else { 1e300 };
        let near = var(&[0.0, 1e-30, 1e10, -nf_big], &[4], dtype);
        let far = var(&[0.0, 2e-30, 1e10, nf_big], &[4], dtype);
        s.case(
            "camera::Intersection::new",
            format!("{tag}, bounds ±{nf_big:e}"),
            Expect::Finite,
            &[&near, &far],
            || {
                let i = neural_fields::camera::Intersection::new(
                    near.as_tensor().clone(),
                    far.as_tensor().clone(),
                )?;
                Ok(vec![i.near, i.far, i.hit])
            },
        );
        s.case(
            "camera::Intersection::new",
            format!("{tag}, far < near"),
            Expect::FiniteOrErr,
            &[],
            || {
                let i = neural_fields::camera::Intersection::new(
                    far.as_tensor().clone(),
                    near.as_tensor().affine(1.0, -1.0)?,
                )?;
                Ok(vec![i.near, i.far, i.hit])
            },
        );
        // Learnable pose with a tiny and a huge quaternion.
        for qs in [1e-6, 1.0, 1e6] {
            let label = format!("{tag}, |q| = {qs}");
            let pose = DAffine3::from_rotation_translation(
                DQuat::from_rotation_x(0.7),
                DVec3::new(0.0, 1.0, 5.0),
            );
            let k = Intrinsics::from_fov_y(8, 8, 1.0).unwrap();
            let p = PoseParam::from_affine(&pose, &d, dtype).unwrap();
            p.rotation
                .set(&p.rotation.as_tensor().affine(qs, 0.0).unwrap())
                .unwrap();
            let px = Tensor::from_slice(&[0.5, 0.5, 7.5, 7.5], (2, 2), &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenCv).unwrap();
            let views = Tensor::zeros(2, DType::U32, &d).unwrap();
            s.case(
                "camera::pose_rays",
                &label,
                Expect::Finite,
                &[&p.rotation, &p.translation],
                || {
                    let r = pose_rays(std::slice::from_ref(&p), &[cam], &views, &px)?;
                    Ok(vec![r.origins().clone(), r.directions().clone()])
                },
            );
            s.case(
                "camera::PoseParam::from_affine",
                &label,
                Expect::Finite,
                &[],
                || Ok(vec![p.translation.as_tensor().clone()]),
            );
            s.case(
                "camera::PoseParam::to_affine",
                &label,
                Expect::Finite,
                &[],
                || {
                    let a = p.to_affine()?;
                    Ok(vec![Tensor::new(a.matrix3.to_cols_array().as_slice(), &d)?])
                },
            );
        }
    }
}

/// A host-side vector result as a `[3]` f64 tensor, so the suite checks it is finite.
fn host3(v: DVec3) -> neural_fields::Result<Tensor> {
    Ok(Tensor::new(&v.to_array(), &Device::Cpu)?)
}

fn sweep_camera_host(s: &mut Suite) {
    let k = Intrinsics::new(500.0, 400.0, 32.0, 24.0, 64, 48).unwrap();
    // Pose steps at every magnitude: finite poses.
    for &x in &magnitudes(DType::F64) {
        let x = x.clamp(-1e150, 1e150);
        s.case(
            "camera::retract_pose",
            format!("step of {x:e}"),
            Expect::Finite,
            &[],
            || {
                let pose = DAffine3::from_translation(DVec3::splat(x));
                let moved = neural_fields::camera::retract_pose(&pose, [x, -x, 0.5, x, 1.0, -x]);
                Ok(vec![
                    host3(moved.translation)?,
                    host3(moved.matrix3.x_axis)?,
                    host3(moved.matrix3.z_axis)?,
                ])
            },
        );
        s.case(
            "camera::pose_error",
            format!("poses at {x:e}"),
            Expect::FiniteOrErr,
            &[],
            || {
                let pose = DAffine3::from_translation(DVec3::splat(x));
                let moved =
                    neural_fields::camera::retract_pose(&pose, [0.1, 0.0, 0.0, x, 0.0, 0.0]);
                let (r, t) = neural_fields::camera::pose_error(&[moved], &[pose])?;
                Ok(vec![Tensor::new(&[r, t], &Device::Cpu)?])
            },
        );
    }
    for r in [1e-6, 1.0, 1e6, 1e150] {
        s.case(
            "camera::cameras_around",
            format!("cameras at distance {r:e}"),
            Expect::FiniteOrErr,
            &[],
            || {
                let cams: Vec<Camera> = [DVec3::X, DVec3::Y, -DVec3::X]
                    .iter()
                    .map(|&e| {
                        Camera::look_at(
                            k,
                            (e + DVec3::Z * 0.3) * r,
                            DVec3::ZERO,
                            DVec3::Z,
                            Convention::OpenGl,
                        )
                    })
                    .collect::<neural_fields::Result<_>>()?;
                let around = neural_fields::camera::cameras_around(&cams, 8, 1)?;
                around
                    .iter()
                    .map(|c| host3(c.cam_to_world().translation))
                    .collect()
            },
        );
        for dtype in [DType::F32, DType::F64] {
            s.case(
                "camera::patch_rays",
                format!("{dtype:?}, cameras at distance {r:e}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let cams: Vec<Camera> = [DVec3::X, -DVec3::Y]
                        .iter()
                        .map(|&e| {
                            Camera::look_at(k, e * r, DVec3::ZERO, DVec3::Z, Convention::OpenCv)
                        })
                        .collect::<neural_fields::Result<_>>()?;
                    let rays = neural_fields::camera::patch_rays(&cams, 4, 2, &Device::Cpu, dtype)?;
                    Ok(vec![rays.origins().clone(), rays.directions().clone()])
                },
            );
        }
    }
    // Alignment by the views of scenes at every magnitude (cameras 3·x from the scene,
    // points within 0.3·x), onto a copy scaled by up to 1e±150: finite maps, or `Err`
    // for scenes whose cameras or points over- or underflow.
    let cams = |x: f64, scale: f64| -> neural_fields::Result<Vec<Camera>> {
        let k = Intrinsics::from_fov_y(32, 32, 0.6)?;
        [DVec3::X, -DVec3::X, DVec3::Y, DVec3::Z]
            .iter()
            .map(|&e| {
                Camera::look_at(
                    k,
                    e * 3.0 * x * scale,
                    DVec3::ZERO,
                    DVec3::new(0.1, 0.2, 1.0),
                    Convention::OpenCv,
                )
            })
            .collect()
    };
    for &x in &magnitudes(DType::F64) {
        for ratio in [1e-150, 1.0, 1e150] {
            s.case(
                "camera::align_cameras",
                format!("scene at scale {x:e}, copy scaled by {ratio:e}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let points = [DVec3::ZERO, DVec3::X * 0.3 * x, DVec3::Y * 0.3 * x];
                    let sim = align_cameras(&cams(x, 1.0)?, &cams(x, ratio)?, &points)?;
                    Ok(vec![
                        host3(sim.apply(points[1]))?,
                        Tensor::new(&[sim.scale, sim.rotation.w], &Device::Cpu)?,
                    ])
                },
            );
            // The residual of that alignment: finite pixels, or `Err`.
            s.case(
                "camera::reprojection_error",
                format!("scene at scale {x:e}, copy scaled by {ratio:e}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let points = [DVec3::ZERO, DVec3::X * 0.3 * x, DVec3::Y * 0.3 * x];
                    let frame = Similarity {
                        scale: ratio,
                        ..Similarity::IDENTITY
                    };
                    let px = reprojection_error(&cams(x, 1.0)?, &cams(x, ratio)?, &points, &frame)?;
                    Ok(vec![Tensor::new(&[px], &Device::Cpu)?])
                },
            );
        }
    }
    // Similarity alignment of clouds at every magnitude (and onto a cloud scaled by up to
    // 1e±150): finite maps, or `Err` for clouds whose spread over- or underflows.
    for &x in &magnitudes(DType::F64) {
        for ratio in [1e-150, 1.0, 1e150] {
            s.case(
                "camera::align_similarity",
                format!("cloud at {x:e}, scaled by {ratio:e}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let from: Vec<DVec3> = [DVec3::X, DVec3::Y, DVec3::Z, DVec3::ONE]
                        .iter()
                        .map(|&p| p * x + DVec3::splat(x))
                        .collect();
                    let to: Vec<DVec3> = from
                        .iter()
                        .map(|&p| DVec3::new(p.y, -p.x, p.z) * ratio)
                        .collect();
                    let sim = align_similarity(&from, &to)?;
                    let pose = DAffine3::from_translation(DVec3::splat(x));
                    let moved = sim.apply(pose);
                    Ok(vec![
                        host3(sim.apply(from[0]))?,
                        host3(moved.translation)?,
                        Tensor::new(&[sim.scale, sim.rotation.w], &Device::Cpu)?,
                    ])
                },
            );
            for name in [
                "camera::Similarity::apply",
                "camera::DVec3::transformed",
                "camera::DAffine3::transformed",
            ] {
                s.case(
                    name,
                    format!("scale {ratio:e}, point {x:e}"),
                    Expect::Finite,
                    &[],
                    || {
                        let sim = Similarity {
                            scale: ratio,
                            rotation: DQuat::from_rotation_z(0.5),
                            translation: DVec3::splat(1.0),
                        };
                        let p = DVec3::splat(x.clamp(-1e100, 1e100));
                        let pose = sim.apply(DAffine3::from_translation(p));
                        Ok(vec![host3(sim.apply(p))?, host3(pose.translation)?])
                    },
                );
            }
        }
    }
    for convention in [Convention::OpenCv, Convention::OpenGl] {
        let cam = Camera::look_at(
            k,
            DVec3::new(1.0, -2.0, 0.5),
            DVec3::ZERO,
            DVec3::Z,
            convention,
        )
        .unwrap();
        for &x in &magnitudes(DType::F64) {
            // Points on and near the camera plane, behind it and far in front: `None` or a
            // finite pixel, never an infinite one.
            let c = cam.cam_to_world().translation;
            let axis = cam.cam_to_world().matrix3.z_axis;
            for p in [
                c + DVec3::splat(x),
                c + axis * x + DVec3::new(1.0, 0.0, 0.0),
                DVec3::splat(x),
            ] {
                s.case(
                    "camera::Camera::project",
                    format!("{convention:?}, point {p}"),
                    Expect::Finite,
                    &[],
                    || Ok(cam.project(p).map(host3).transpose()?.into_iter().collect()),
                );
            }
        }
    }
}

/// Whether `filter`'s parameters are valid: a Blackman–Harris half width in `(0, 64]`.
fn valid(filter: PixelFilter) -> bool {
    match filter {
        PixelFilter::Box => true,
        PixelFilter::BlackmanHarris { half_width } => half_width > 0.0 && half_width <= 64.0,
    }
}
