//! Photometric registration of cameras to a rendered scene ([`register_poses`]).

use candle_core::{DType, Device, Tensor};
use neural_fields::camera::{
    pose_error, ray_sphere, register_poses, retract_pose, Camera, Convention, Intrinsics,
    PixelFilter, Rays, RegistrationConfig,
};
use neural_fields::glam::DVec3;
use neural_fields::rng::SplitMix64;
use neural_fields::{Error, Result};

/// The ball of radius ½ at the origin, coloured by its point, on white: colour, depth and
/// opacity of each ray.
fn textured_ball(rays: &Rays) -> Result<(Tensor, Tensor, Tensor)> {
    let hit = ray_sphere(rays, [0.0; 3], 0.5)?;
    let opacity = hit.hit.to_dtype(rays.origins().dtype())?;
    let p = (rays.origins() + rays.directions().broadcast_mul(&hit.near.unsqueeze(1)?)?)?;
    let axis = |i: usize| p.narrow(1, i, 1);
    let (x, y, z) = (axis(0)?, axis(1)?, axis(2)?);
    let red = ((x * 7.0)?.sin()? * 0.4)? + 0.5;
    let green = ((((y * 5.0)? + (z.clone() * 2.0)?)?.cos()? * 0.4)? + 0.5)?;
    let blue = ((z * 9.0)?.sin()? * 0.3)? + 0.5;
    let rgb = Tensor::cat(&[red?, green, blue?], 1)?;
    let on_white = ((rgb - 1.0)?.broadcast_mul(&opacity.unsqueeze(1)?)? + 1.0)?;
    Ok((on_white, hit.near, opacity))
}

/// Direct image alignment registers a camera to an analytic textured ball: from 2° and
/// 2 % of the distance off, four registrations bring both errors below a quarter (a ball
/// is the hardest case: its points lie at nearly one depth, so the centre and the
/// rotation compensate each other almost exactly).
#[test]
fn registration_aligns_a_camera_to_a_textured_ball() {
    let k = Intrinsics::from_fov_y(64, 64, 0.6).unwrap();
    let gl = Convention::OpenGl;
    let truth = Camera::look_at(k, DVec3::new(2.0, -2.0, 1.0), DVec3::ZERO, DVec3::Z, gl).unwrap();
    // The true image, 4 × 4 rays per pixel averaged (a filtered image): colour and alpha.
    let grid = truth
        .subpixel_grid(4, PixelFilter::Box, &Device::Cpu, DType::F64)
        .unwrap();
    let (rgb, _, alpha) = textured_ball(&truth.rays_for_pixels(&grid).unwrap()).unwrap();
    let rgba = Tensor::cat(&[rgb, alpha.unsqueeze(1).unwrap()], 1).unwrap();
    let image = rgba.reshape((64, 64, 16, 4)).unwrap().mean(2).unwrap();
    // The camera turned by 2° about a random axis through its centre, its centre moved by
    // 2 % of its distance to the origin.
    let mut rng = SplitMix64::new(11);
    let mut unit = || DVec3::new(rng.normal(), rng.normal(), rng.normal()).normalize();
    let pose = truth.cam_to_world();
    let (turn, shift) = (
        unit() * 2f64.to_radians(),
        unit() * 0.02 * pose.translation.length(),
    );
    let start = retract_pose(&pose, [turn.x, turn.y, turn.z, shift.x, shift.y, shift.z]);
    let before = pose_error(&[start], &[pose]).unwrap();
    assert!((before.0 - 2.0).abs() < 1e-6 && (before.1 - 0.02).abs() < 1e-9);
    let mut cameras = vec![Camera::new(k, start, gl).unwrap()];
    let config = RegistrationConfig::default();
    for _ in 0..4 {
        cameras = register_poses(
            &cameras,
            std::slice::from_ref(&image),
            textured_ball,
            &config,
        )
        .unwrap();
    }
    let after = pose_error(&[cameras[0].cam_to_world()], &[pose]).unwrap();
    assert!(
        after.0 < before.0 / 4.0 && after.1 < before.1 / 4.0,
        "{before:?} -> {after:?}"
    );
    assert_eq!(cameras[0].intrinsics(), &k);
    assert_eq!(cameras[0].convention(), gl);
}

/// A camera whose image shows nothing (alpha 0 everywhere) keeps its pose; so does one
/// the alignment would move further than `max_move`.
#[test]
fn registration_keeps_cameras_it_cannot_or_may_not_move() {
    let k = Intrinsics::from_fov_y(16, 16, 0.6).unwrap();
    let cam = Camera::look_at(
        k,
        DVec3::new(0.0, -3.0, 0.0),
        DVec3::ZERO,
        DVec3::Z,
        Convention::OpenGl,
    )
    .unwrap();
    let empty = Tensor::cat(
        &[
            Tensor::ones((16, 16, 3), DType::F32, &Device::Cpu).unwrap(),
            Tensor::zeros((16, 16, 1), DType::F32, &Device::Cpu).unwrap(),
        ],
        2,
    )
    .unwrap();
    let same = register_poses(
        &[cam],
        &[empty],
        textured_ball,
        &RegistrationConfig::default(),
    );
    assert_eq!(same.unwrap(), vec![cam]);
    let grid = cam
        .subpixel_grid(1, PixelFilter::Box, &Device::Cpu, DType::F64)
        .unwrap();
    let (rgb, _, alpha) = textured_ball(&cam.rays_for_pixels(&grid).unwrap()).unwrap();
    let image = Tensor::cat(&[rgb, alpha.unsqueeze(1).unwrap()], 1)
        .unwrap()
        .reshape((16, 16, 4))
        .unwrap();
    let moved = retract_pose(&cam.cam_to_world(), [0.0, 0.0, 0.02, 0.05, 0.0, 0.0]);
    let start = Camera::new(k, moved, Convention::OpenGl).unwrap();
    let frozen = RegistrationConfig {
        max_move: (0.0, 0.0),
        ..RegistrationConfig::default()
    };
    assert_eq!(
        register_poses(&[start], &[image], textured_ball, &frozen).unwrap(),
        vec![start]
    );
}

/// Bad images, renders and settings are refused, naming themselves.
#[test]
fn registration_refuses_bad_arguments() {
    let arg = |r: Result<Vec<Camera>>| match r {
        Err(Error::InvalidArgument { arg, .. }) => arg,
        other => panic!("expected an argument error, got {other:?}"),
    };
    let k = Intrinsics::from_fov_y(8, 8, 0.6).unwrap();
    let cam = Camera::look_at(
        k,
        DVec3::new(0.0, -3.0, 0.0),
        DVec3::ZERO,
        DVec3::Z,
        Convention::OpenGl,
    )
    .unwrap();
    let image = Tensor::ones((8, 8, 4), DType::F32, &Device::Cpu).unwrap();
    let config = RegistrationConfig::default();
    assert_eq!(
        arg(register_poses(&[cam], &[], textured_ball, &config)),
        "images"
    );
    let three = Tensor::ones((8, 8, 3), DType::F32, &Device::Cpu).unwrap();
    assert_eq!(
        arg(register_poses(&[cam], &[three], textured_ball, &config)),
        "images"
    );
    let small = Tensor::ones((4, 8, 4), DType::F32, &Device::Cpu).unwrap();
    assert_eq!(
        arg(register_poses(&[cam], &[small], textured_ball, &config)),
        "images"
    );
    let short = |r: &Rays| -> Result<(Tensor, Tensor, Tensor)> {
        let (rgb, depth, opacity) = textured_ball(r)?;
        Ok((rgb.narrow(1, 0, 2)?, depth, opacity))
    };
    assert_eq!(
        arg(register_poses(
            &[cam],
            std::slice::from_ref(&image),
            short,
            &config
        )),
        "render"
    );
    for bad in [
        RegistrationConfig {
            blurs: vec![],
            ..config.clone()
        },
        RegistrationConfig {
            blurs: vec![-1.0],
            ..config.clone()
        },
        RegistrationConfig {
            filter_sigma: f64::NAN,
            ..config.clone()
        },
        RegistrationConfig {
            chunk: 0,
            ..config.clone()
        },
    ] {
        assert_eq!(
            arg(register_poses(
                &[cam],
                std::slice::from_ref(&image),
                textured_ball,
                &bad
            )),
            "config"
        );
    }
}
