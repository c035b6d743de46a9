//! The chunked, supersampled image renderer: each pixel is the mean of its sub-pixel rays'
//! outputs, whatever the chunk size; outputs are detached; bad input errs naming the
//! argument.
#![cfg(feature = "volume")]

use candle_core::{DType, Device, Tensor, Var};
use neural_fields::camera::{Camera, Convention, Intrinsics, PixelFilter, Rays};
use neural_fields::glam::DVec3;
use neural_fields::volume::{render_image, ImageConfig};
use neural_fields::{Error, Result};

fn camera() -> Camera {
    let k = Intrinsics::from_fov_y(5, 3, 0.7).unwrap();
    Camera::look_at(
        k,
        DVec3::new(0.3, -0.2, 3.0),
        DVec3::ZERO,
        DVec3::Y,
        Convention::OpenGl,
    )
    .unwrap()
}

/// A per-ray "renderer": the directions `[n, 3]` and their first component `[n]`, each
/// row depending on its own ray only.
fn directions(rays: &Rays) -> Result<[Tensor; 2]> {
    let d = rays.directions().clone();
    Ok([d.clone(), d.narrow(1, 0, 1)?.squeeze(1)?])
}

fn arg_of(e: Error) -> &'static str {
    match e {
        Error::InvalidArgument { arg, .. } => arg,
        other => panic!("expected InvalidArgument, got {other}"),
    }
}

#[test]
fn one_ray_per_pixel_renders_the_pixel_centres_row_major() {
    let cam = camera();
    let [rgb, x] = render_image(
        &cam,
        &ImageConfig::default(),
        &Device::Cpu,
        DType::F64,
        directions,
    )
    .unwrap();
    assert_eq!(rgb.dims(), &[3, 5, 3]);
    assert_eq!(x.dims(), &[3, 5]);
    let want = cam.rays(&Device::Cpu, DType::F64).unwrap();
    let want = want.directions().reshape((3, 5, 3)).unwrap();
    let diff = (rgb - &want)
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f64>()
        .unwrap();
    assert_eq!(diff, 0.0);
    let want_x = want.narrow(2, 0, 1).unwrap().squeeze(2).unwrap();
    assert_eq!(
        x.to_vec2::<f64>().unwrap(),
        want_x.to_vec2::<f64>().unwrap()
    );
}

#[test]
fn each_pixel_is_the_mean_of_its_subpixel_rays_for_any_chunk() {
    let cam = camera();
    for filter in [PixelFilter::Box, PixelFilter::CYCLES] {
        let k = 3;
        // By hand: every sub-pixel ray, then the mean of each pixel's k² rows.
        let grid = cam
            .subpixel_grid(k, filter, &Device::Cpu, DType::F64)
            .unwrap();
        let all = cam.rays_for_pixels(&grid).unwrap();
        let want = all
            .directions()
            .reshape((15, k * k, 3))
            .unwrap()
            .mean(1)
            .unwrap()
            .reshape((3, 5, 3))
            .unwrap();
        // Chunks of one pixel (sizes below k² round up to it), of a few pixels that do not
        // divide the image, and of the whole image at once.
        for chunk in [1, 9, 20, 4 * 9, 10_000] {
            let config = ImageConfig {
                supersample: k,
                filter,
                chunk,
            };
            let mut calls = 0;
            let [rgb, _] = render_image(&cam, &config, &Device::Cpu, DType::F64, |rays| {
                calls += 1;
                assert_eq!(rays.len() % (k * k), 0, "whole pixels per chunk");
                assert!(rays.len() <= chunk.max(k * k));
                directions(rays)
            })
            .unwrap();
            let expected_calls = (15 * k * k).div_ceil((chunk / (k * k)).max(1) * k * k);
            assert_eq!(calls, expected_calls, "chunk {chunk}");
            let diff = (rgb - &want)
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f64>()
                .unwrap();
            assert!(diff < 1e-15, "{filter:?}, chunk {chunk}: {diff}");
        }
    }
}

#[test]
fn outputs_are_detached_and_keep_their_dtype() {
    let cam = camera();
    let w = Var::new(&[2.0f32, 1.0, 1.0], &Device::Cpu).unwrap();
    let [c] = render_image(
        &cam,
        &ImageConfig::default(),
        &Device::Cpu,
        DType::F32,
        |rays| Ok([rays.directions().broadcast_mul(w.as_tensor())?]),
    )
    .unwrap();
    assert_eq!(c.dtype(), DType::F32);
    assert!(!c.track_op(), "the image carries no graph");
}

#[test]
fn render_image_bad_input_errs_naming_the_argument() {
    let cam = camera();
    let dev = Device::Cpu;
    let run = |config: ImageConfig, dtype: DType| {
        render_image(&cam, &config, &dev, dtype, directions).map(|_| ())
    };
    for supersample in [0, 65] {
        let config = ImageConfig {
            supersample,
            ..ImageConfig::default()
        };
        assert_eq!(
            arg_of(run(config, DType::F32).unwrap_err()),
            "config.supersample"
        );
    }
    let config = ImageConfig {
        chunk: 0,
        ..ImageConfig::default()
    };
    assert_eq!(arg_of(run(config, DType::F32).unwrap_err()), "config.chunk");
    assert_eq!(
        arg_of(run(ImageConfig::default(), DType::U8).unwrap_err()),
        "dtype"
    );
    let config = ImageConfig {
        filter: PixelFilter::BlackmanHarris { half_width: -1.0 },
        ..ImageConfig::default()
    };
    assert_eq!(arg_of(run(config, DType::F32).unwrap_err()), "filter");
    // Outputs of the wrong length, rank or dtype.
    let wrong_rows = |rays: &Rays| Ok([rays.directions().narrow(0, 0, 1)?]);
    let wrong_rank = |rays: &Rays| Ok([rays.directions().unsqueeze(2)?]);
    let integers = |rays: &Rays| Ok([rays.directions().to_dtype(DType::U32)?]);
    for f in [
        &wrong_rows as &dyn Fn(&Rays) -> Result<[Tensor; 1]>,
        &wrong_rank,
        &integers,
    ] {
        let e = render_image(&cam, &ImageConfig::default(), &dev, DType::F32, f).unwrap_err();
        assert_eq!(arg_of(e), "render");
    }
    // The renderer's own error comes back as it is.
    let failing = |_: &Rays| -> Result<[Tensor; 1]> {
        Err(Error::InvalidArgument {
            arg: "mine",
            expected: "nothing".into(),
            got: "a test".into(),
        })
    };
    let e = render_image(&cam, &ImageConfig::default(), &dev, DType::F32, failing).unwrap_err();
    assert_eq!(arg_of(e), "mine");
}
