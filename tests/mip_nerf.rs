//! mip-NeRF end to end: cone radii on rays (camera rays, sub-pixel rays, unit directions,
//! chunks), the integrated encoding as a `PointEncoding` (its JVP against finite
//! differences in f64), the NeRF trunk on Gaussians, and the sampler's pixel-area
//! weighting of a multiscale dataset.

#![cfg(all(feature = "volume", feature = "data"))]

mod common;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use common::{central_diff_bound, close, v64};
use neural_fields::camera::{Camera, Convention, Intrinsics, Rays};
use neural_fields::data::{Background, Dataset, Image, RaySampler, View};
use neural_fields::encoding::{integrated_pe, PointEncoding};
use neural_fields::glam::DVec3;
use neural_fields::nn::build_seeded;
use neural_fields::volume::{
    nerf, render_image, stratified, CompositeConfig, ImageConfig, Jitter, NerfConfig,
};
use proptest::prelude::*;

const DEV: Device = Device::Cpu;

fn camera(width: usize, height: usize) -> Camera {
    let k = Intrinsics::from_fov_y(width, height, 0.7).unwrap();
    Camera::look_at(
        k,
        DVec3::new(0.0, -3.0, 0.5),
        DVec3::ZERO,
        DVec3::Z,
        Convention::OpenGl,
    )
    .unwrap()
}

fn t(values: &[f64], shape: &[usize], dtype: DType) -> Tensor {
    Tensor::from_vec(values.to_vec(), shape, &DEV)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

#[test]
fn camera_rays_carry_the_pixel_cone_radius() {
    for dtype in [DType::F32, DType::F64] {
        let cam = camera(8, 6);
        let k = cam.intrinsics();
        let want = 2.0 / (12f64.sqrt() * (k.fx * k.fy).sqrt());
        let rays = cam.rays(&DEV, dtype).unwrap();
        let radii = v64(rays.radii().expect("camera rays carry radii"));
        assert_eq!(radii.len(), 48);
        assert!(
            radii.iter().all(|&r| close(r, want, 1e-6, 0.0)),
            "{radii:?}"
        );
        // Unit directions: t becomes distance, so the radius per unit t shrinks by |d|.
        let norms: Vec<f64> = v64(&rays.directions().sqr().unwrap().sum(1).unwrap())
            .iter()
            .map(|s| s.sqrt())
            .collect();
        let unit = v64(rays.normalized().unwrap().radii().unwrap());
        for (i, (&r, &n)) in unit.iter().zip(&norms).enumerate() {
            assert!(
                close(r, want / n, 1e-6, 0.0),
                "ray {i}: {r} vs {}",
                want / n
            );
        }
        // Chunks keep their rays' radii.
        let part = rays.narrow(10, 5).unwrap();
        assert_eq!(v64(part.radii().unwrap()), radii[10..15].to_vec());
    }
}

#[test]
fn sub_pixel_rays_cover_a_kth_of_the_pixel() {
    let cam = camera(4, 3);
    let want = cam.rays(&DEV, DType::F64).unwrap().radii().unwrap().clone();
    let want = v64(&want)[0];
    for k in [1usize, 2, 3] {
        let config = ImageConfig {
            supersample: k,
            ..ImageConfig::default()
        };
        let [radius] = render_image(&cam, &config, &DEV, DType::F64, |rays| {
            Ok([rays.radii().expect("radii").clone()])
        })
        .unwrap();
        // The pixel mean of k² equal radii is the radius itself.
        for r in v64(&radius.flatten_all().unwrap()) {
            assert!(close(r, want / k as f64, 1e-12, 0.0), "k = {k}: {r}");
        }
    }
}

#[test]
fn with_radii_refuses_bad_radii() {
    let rays = Rays::new(
        t(&[0.0; 6], &[2, 3], DType::F32),
        t(&[0.0, 0.0, 1.0, 0.0, 1.0, 0.0], &[2, 3], DType::F32),
    )
    .unwrap();
    let cases: Vec<Tensor> = vec![
        t(&[0.1], &[1], DType::F32),
        t(&[0.1, 0.1], &[2], DType::F64),
        t(&[0.1, -0.1], &[2], DType::F32),
        t(&[0.1, f64::NAN], &[2], DType::F32),
        t(&[0.1, f64::INFINITY], &[2], DType::F32),
        t(&[0.1, 0.2], &[1, 2], DType::F32),
    ];
    for radii in cases {
        let e = rays.clone().with_radii(radii).unwrap_err().to_string();
        assert!(e.starts_with("radii"), "{e}");
    }
    assert!(rays
        .clone()
        .with_radii(t(&[0.0, 1e30], &[2], DType::F32))
        .is_ok());
}

#[test]
fn integrated_encoding_is_integrated_pe_of_the_split_rows() {
    let enc = PointEncoding::Integrated {
        dim: 3,
        min_deg: 1,
        max_deg: 5,
    };
    let mu = [0.3, -1.2, 2.0, 1e3, 0.0, -0.5];
    let var = [0.01, 0.0, 1.0, 1e-6, 4.0, 0.2];
    let x = Tensor::cat(
        &[t(&mu, &[2, 3], DType::F64), t(&var, &[2, 3], DType::F64)],
        1,
    )
    .unwrap();
    let got = v64(&enc.forward(&x).unwrap());
    let want = v64(&integrated_pe(
        &t(&mu, &[2, 3], DType::F64),
        &t(&var, &[2, 3], DType::F64),
        1,
        5,
    )
    .unwrap());
    assert_eq!(got, want);
    assert_eq!(got.len(), 2 * 2 * 3 * 4);
    // Rows of another width name x.
    let e = enc
        .forward(&t(&mu, &[2, 3], DType::F64))
        .unwrap_err()
        .to_string();
    assert!(e.starts_with('x'), "{e}");
}

/// `Σ w·γ(x)` and `Σ w·J_γ(x)dx` of the integrated encoding, in f64.
fn ipe_and_jvp(x: &[f64], dx: &[f64], n: usize) -> (f64, f64) {
    let enc = PointEncoding::Integrated {
        dim: 3,
        min_deg: 0,
        max_deg: 6,
    };
    let (y, j) = enc
        .forward_jvp(&t(x, &[n, 6], DType::F64), &t(dx, &[n, 1, 6], DType::F64))
        .unwrap();
    let w: Vec<f64> = (0..y.elem_count())
        .map(|i| (0.37 * i as f64 + 0.1).sin())
        .collect();
    let dot = |a: Vec<f64>| a.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>();
    (
        dot(v64(&y.flatten_all().unwrap())),
        dot(v64(&j.flatten_all().unwrap())),
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// The JVP of the integrated encoding against central differences along `dx`, over
    /// means up to 1e3 and variances from 0 to 10 (where the damping underflows).
    #[test]
    fn integrated_encoding_jvp_matches_finite_differences(
        mu in prop::collection::vec(-1e3f64..1e3, 6),
        scale in prop::sample::select(vec![1e-3f64, 1.0]),
        var in prop::collection::vec(0.0f64..10.0, 6),
        dx in prop::collection::vec(-1.0f64..1.0, 12),
    ) {
        let n = 2;
        let mut x = Vec::new();
        for r in 0..n {
            x.extend(mu[3 * r..3 * r + 3].iter().map(|m| m * scale));
            x.extend(var[3 * r..3 * r + 3].iter().map(|v| v * scale));
        }
        // Variances must stay ≥ 0 along the stencil: move them only where they are not 0.
        let dx: Vec<f64> = dx
            .iter()
            .enumerate()
            .map(|(i, &d)| if i % 6 >= 3 && x[i] < 1e-2 { 0.0 } else { d })
            .collect();
        let (y0, jvp) = ipe_and_jvp(&x, &dx, n);
        let mut f = |h: f64| {
            let xs: Vec<f64> = x.iter().zip(&dx).map(|(a, b)| a + h * b).collect();
            ipe_and_jvp(&xs, &dx, n).0
        };
        let h = 1e-3 * 1e-2f64.min(1.0 / (1.0 + mu.iter().fold(0f64, |m, v| m.max(v.abs())) * scale));
        if let Some((fd, bar)) = central_diff_bound(&mut f, 0.0, h, y0.abs() + 1.0) {
            prop_assert!(
                (fd - jvp).abs() <= 1e-6 * (jvp.abs() + 1.0) + 2.0 * bar,
                "jvp {jvp} vs finite differences {fd} ± {bar}"
            );
        }
    }
}

fn mip_config() -> NerfConfig {
    NerfConfig {
        position_encoding: PointEncoding::Integrated {
            dim: 3,
            min_deg: 0,
            max_deg: 8,
        },
        ..NerfConfig::default()
    }
}

#[test]
fn nerf_on_gaussians_reads_points_as_zero_variance() {
    for dtype in [DType::F32, DType::F64] {
        let varmap = VarMap::new();
        let net = build_seeded(&varmap, dtype, &DEV, 3, |vb| nerf(&mip_config(), vb)).unwrap();
        let p = t(&[0.1, 0.2, -0.3, 0.5, -0.4, 0.0], &[2, 3], dtype);
        let wide = Tensor::cat(&[&p, &p.zeros_like().unwrap()], 1).unwrap();
        assert_eq!(
            v64(&net.density(&p).unwrap()),
            v64(&net.density(&wide).unwrap())
        );
        let blurred = Tensor::cat(&[&p, &(p.ones_like().unwrap() * 0.5).unwrap()], 1).unwrap();
        assert_ne!(
            v64(&net.density(&p).unwrap()),
            v64(&net.density(&blurred).unwrap())
        );
        let e = net
            .density(&t(&[0.0; 8], &[2, 4], dtype))
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("points"), "{e}");
    }
}

#[test]
fn nerf_color_loss_casts_cones_when_rays_carry_radii() {
    for dtype in [DType::F32, DType::F64] {
        let varmap = VarMap::new();
        let net = build_seeded(&varmap, dtype, &DEV, 5, |vb| nerf(&mip_config(), vb)).unwrap();
        let cam = camera(6, 4);
        let rays = cam.rays(&DEV, dtype).unwrap();
        let n = rays.len();
        let near = Tensor::full(2.0, n, &DEV).unwrap().to_dtype(dtype).unwrap();
        let far = Tensor::full(4.0, n, &DEV).unwrap().to_dtype(dtype).unwrap();
        let iv = stratified(&near, &far, 16, Jitter::None, 0).unwrap();
        let inputs = net.sample_inputs(&rays, &iv).unwrap();
        assert_eq!(inputs.dims(), &[n * 16, 6]);
        let target = Tensor::full(0.5, (n, 3), &DEV)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let config = CompositeConfig::default();
        let cones = net.color_loss(&rays, &iv, &target, &config).unwrap();
        let points_only = Rays::new(rays.origins().clone(), rays.directions().clone()).unwrap();
        assert_eq!(
            net.sample_inputs(&points_only, &iv).unwrap().dims(),
            &[n * 16, 3]
        );
        let points = net.color_loss(&points_only, &iv, &target, &config).unwrap();
        let (a, b) = (
            v64(&cones.loss.reshape(1).unwrap())[0],
            v64(&points.loss.reshape(1).unwrap())[0],
        );
        assert!(a.is_finite() && b.is_finite() && a != b, "{a} {b}");
        let grads = cones.loss.backward().unwrap();
        for var in varmap.all_vars() {
            let g = v64(&grads
                .get(&var)
                .expect("every weight has a gradient")
                .flatten_all()
                .unwrap());
            assert!(g.iter().all(|x| x.is_finite()));
        }
    }
}

fn grey_view(width: usize, height: usize, value: u8) -> View {
    let image = Image::new(width, height, 3, vec![value; width * height * 3]).unwrap();
    View::new(camera(width, height), image, None, format!("{width}")).unwrap()
}

#[test]
fn sampler_weighs_every_scale_of_a_view_the_same() {
    // One view at full and at half resolution: the half-resolution image has a quarter
    // of the pixels, each 4 times the area, so each image gets half the rays.
    let data = Dataset::new(
        vec![grey_view(16, 12, 10), grey_view(8, 6, 200)],
        Background::Color([1.0; 3]),
        None,
    )
    .unwrap();
    let mut sampler = RaySampler::new(&data, 7, &DEV, DType::F64).unwrap();
    let batch = sampler.pixels(20_000).unwrap();
    let views = batch.views.to_vec1::<u32>().unwrap();
    let half = views.iter().filter(|&&v| v == 1).count() as f64 / views.len() as f64;
    assert!((half - 0.5).abs() < 0.02, "{half}");
    // Every pixel of the half-resolution view is drawn: its pixel index is unbiased.
    let px = batch.pixels.to_vec2::<u32>().unwrap();
    let mut seen = [false; 48];
    for (v, p) in views.iter().zip(&px) {
        if *v == 1 {
            seen[(p[1] * 8 + p[0]) as usize] = true;
        }
    }
    assert!(seen.iter().all(|&s| s));
    // The rays carry their view's cone radius, sub-pixel footprints a k-th of it.
    let radii = v64(batch.rays.radii().unwrap());
    let r = |v: usize| data.views()[v].camera().intrinsics().fx;
    for (i, &v) in views.iter().enumerate().take(200) {
        let k = data.views()[v as usize].camera().intrinsics();
        assert!(close(
            radii[i],
            2.0 / (12f64.sqrt() * (k.fx * k.fy).sqrt()),
            1e-12,
            0.0
        ));
    }
    assert!(close(r(0), 2.0 * r(1), 1e-12, 0.0));
    let feet = sampler.pixel_footprints(10, 2).unwrap();
    let fv = feet.views.to_vec1::<u32>().unwrap();
    for (i, &rad) in v64(feet.rays.radii().unwrap()).iter().enumerate() {
        let k = data.views()[fv[i] as usize].camera().intrinsics();
        assert!(close(
            rad,
            1.0 / (12f64.sqrt() * (k.fx * k.fy).sqrt()),
            1e-12,
            0.0
        ));
    }
}

#[test]
fn sampler_is_uniform_over_pixels_when_focal_lengths_agree() {
    // Two views of one camera: the same stream of pixels as a plain uniform draw, so the
    // area weighting changes nothing for single-scale datasets.
    let data = Dataset::new(
        vec![grey_view(16, 12, 10), grey_view(16, 12, 200)],
        Background::Color([1.0; 3]),
        None,
    )
    .unwrap();
    let mut sampler = RaySampler::new(&data, 11, &DEV, DType::F32).unwrap();
    let views = sampler
        .pixels(20_000)
        .unwrap()
        .views
        .to_vec1::<u32>()
        .unwrap();
    let second = views.iter().filter(|&&v| v == 1).count() as f64 / views.len() as f64;
    assert!((second - 0.5).abs() < 0.02, "{second}");
}
