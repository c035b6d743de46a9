//! A sample count a caller passes is checked against the allocation limit (2³³ bytes)
//! before anything is allocated: a count above 2⁶³ used to panic on an overflowing product
//! in `stratified`, and one of 2⁴⁰ to abort the process in the allocator (`stratified`,
//! `sample_pdf`, `proposal_sample`); the surface and point-cloud samplers and the torus of
//! `flow` reserved or allocated whatever was asked. Each is now an `Err` naming the count.

use candle_core::{Device, Tensor};
use neural_fields::camera::{patch_rays, Camera, Convention, Intrinsics, Rays};
use neural_fields::flow::DeformingTorus;
use neural_fields::glam::DVec3;
use neural_fields::mesh::{Mesh, PointCloud};
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{
    proposal_sample, render_image, sample_pdf, stratified, ImageConfig, Jitter, ProposalConfig,
};

fn names(e: neural_fields::Error, arg: &str) {
    let msg = e.to_string();
    assert!(msg.starts_with(&format!("{arg}: ")), "{msg}");
    assert!(msg.contains("8589934592"), "the limit is stated: {msg}");
}

fn near_far(r: usize) -> (Tensor, Tensor) {
    let dev = Device::Cpu;
    (
        Tensor::zeros(r, candle_core::DType::F32, &dev).unwrap(),
        Tensor::ones(r, candle_core::DType::F32, &dev).unwrap(),
    )
}

#[test]
fn stratified_refuses_counts_past_the_limit_without_panicking() {
    let (near, far) = near_far(2);
    for n in [usize::MAX, (1 << 63) + 1, 1 << 40, 1 << 30] {
        names(
            stratified(&near, &far, n, Jitter::None, 0).unwrap_err(),
            "n",
        );
    }
    // Within the limit it still samples.
    assert_eq!(
        stratified(&near, &far, 4, Jitter::None, 0)
            .unwrap()
            .starts
            .dims(),
        &[2, 4]
    );
}

#[test]
fn sample_pdf_refuses_counts_past_the_limit() {
    let (near, far) = near_far(2);
    let iv = stratified(&near, &far, 4, Jitter::None, 0).unwrap();
    let w = Tensor::ones((2, 4), candle_core::DType::F32, &Device::Cpu).unwrap();
    for n in [usize::MAX, 1 << 40, 1 << 30] {
        names(sample_pdf(&iv, &w, n, true, 0, 0.0).unwrap_err(), "n");
    }
    assert_eq!(
        sample_pdf(&iv, &w, 3, true, 0, 0.0).unwrap().dims(),
        &[2, 3]
    );
}

#[test]
fn proposal_sample_refuses_counts_past_the_limit() {
    let dev = Device::Cpu;
    let (near, far) = near_far(1);
    let rays = Rays::new(
        Tensor::new(&[[0.0f32, 0.0, 0.0]], &dev).unwrap(),
        Tensor::new(&[[0.0f32, 0.0, 1.0]], &dev).unwrap(),
    )
    .unwrap();
    let mut flat = |p: &Tensor| -> neural_fields::Result<Tensor> {
        Ok(Tensor::ones(p.dim(0)?, p.dtype(), p.device())?)
    };
    for (samples, last, arg) in [
        (vec![1 << 40], 8, "config.samples"),
        (vec![64], usize::MAX, "config.final_samples"),
    ] {
        let config = ProposalConfig {
            samples,
            final_samples: last,
            ..ProposalConfig::default()
        };
        let e = proposal_sample(&rays, &near, &far, &mut [&mut flat], &config, None, None);
        names(e.unwrap_err(), arg);
    }
}

#[test]
fn surface_and_cloud_samplers_refuse_counts_past_the_limit() {
    let tri = Mesh::new(
        vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        vec![[0, 1, 2]],
    )
    .unwrap();
    names(tri.sample_surface(1 << 40, 0).unwrap_err(), "n");
    names(tri.sample_surface(usize::MAX, 0).unwrap_err(), "n");
    let cloud = PointCloud::new(vec![[0.0; 3], [1.0, 0.0, 0.0]], None, None).unwrap();
    names(cloud.sample(1 << 40, 0).unwrap_err(), "n");
    let torus = DeformingTorus::default();
    names(
        torus.surface(1 << 40, &mut SplitMix64::new(0)).unwrap_err(),
        "n",
    );
    assert_eq!(torus.surface(5, &mut SplitMix64::new(0)).unwrap().len(), 5);
}

#[test]
fn the_torus_refuses_radii_its_rejection_loop_would_not_end_on() {
    for (major, minor) in [
        (f64::NAN, 0.1),
        (0.25, f64::INFINITY),
        (0.1, 0.2),
        (0.25, 0.0),
    ] {
        let torus = DeformingTorus {
            major,
            minor,
            ..DeformingTorus::default()
        };
        let e = torus
            .surface(3, &mut SplitMix64::new(0))
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("self: "), "{e}");
    }
}

#[test]
fn image_sizes_past_the_limit_are_refused_before_the_rays_exist() {
    // 65 535 × 65 535 pixels: under u32::MAX pixels, 137 GB of f32 rays.
    let k = Intrinsics::new(1e4, 1e4, 0.0, 0.0, 65_535, 65_535).unwrap();
    let cam = Camera::look_at(
        k,
        DVec3::new(0.0, 0.0, 3.0),
        DVec3::ZERO,
        DVec3::Y,
        Convention::OpenGl,
    )
    .unwrap();
    let e = cam.rays(&Device::Cpu, candle_core::DType::F32).unwrap_err();
    names(e, "self.intrinsics");
    let config = ImageConfig::default();
    let e = render_image(&cam, &config, &Device::Cpu, candle_core::DType::F32, |r| {
        Ok([r.origins().clone()])
    });
    names(e.unwrap_err(), "camera");
    // Nine patches of 4096² rays: 9.7 GB of rays from nine cameras.
    let e = patch_rays(&[cam; 9], 4096, 0, &Device::Cpu, candle_core::DType::F32);
    names(e.unwrap_err(), "k");
}
