//! The ready-made surface model of `dvr` (`surface_model`, `SurfaceModel::loss`,
//! `SurfaceModel::shade`): every kind, encoding and IDR input set builds, trains and
//! shades in f32 and f64 with finite gradients; bad input is an error naming it.

#![cfg(feature = "dvr")]

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use neural_fields::camera::Rays;
use neural_fields::dvr::{
    surface_model, RenderInputs, SurfaceEncoding, SurfaceKind, SurfaceModel, SurfaceModelConfig,
};
use neural_fields::field::ImplicitSurface;
use neural_fields::nn::{build_seeded, FiniteGuard};
use neural_fields::texture::{TextureField, TextureInput};

/// Every model of `examples/dvr_multiview/` (kind, encoding, IDR's inputs).
fn configs() -> Vec<SurfaceModelConfig> {
    let hash = SurfaceEncoding::HashGrid {
        finest_resolution: 64.0,
    };
    [
        (
            SurfaceKind::Dvr,
            SurfaceEncoding::Frequency,
            RenderInputs::Full,
        ),
        (
            SurfaceKind::DvrJoint,
            SurfaceEncoding::Frequency,
            RenderInputs::Full,
        ),
        (
            SurfaceKind::Idr,
            SurfaceEncoding::Frequency,
            RenderInputs::Full,
        ),
        (
            SurfaceKind::Idr,
            SurfaceEncoding::Frequency,
            RenderInputs::NoView,
        ),
        (
            SurfaceKind::Idr,
            SurfaceEncoding::Frequency,
            RenderInputs::NoNormal,
        ),
        (SurfaceKind::Dvr, hash, RenderInputs::Full),
        (SurfaceKind::Idr, hash, RenderInputs::Full),
    ]
    .into_iter()
    .map(|(kind, encoding, render_inputs)| SurfaceModelConfig {
        kind,
        encoding,
        render_inputs,
        ..SurfaceModelConfig::default()
    })
    .collect()
}

fn build(config: &SurfaceModelConfig, dtype: DType) -> (SurfaceModel, VarMap) {
    let varmap = VarMap::new();
    let model = build_seeded(&varmap, dtype, &Device::Cpu, 3, |vb| {
        surface_model(config, vb)
    })
    .unwrap();
    (model, varmap)
}

/// Four 2 × 2 patches of rays along +z through `[-0.6, 0.6]²` (origins as a variable),
/// their colours (grey) and mask (inside the disc of radius ½).
fn batch(dtype: DType) -> (Var, Rays, Tensor, Tensor) {
    let dev = Device::Cpu;
    let mut origins = Vec::new();
    let mut mask = Vec::new();
    for patch in 0..4 {
        for k in 0..4 {
            let u = (patch % 2) * 2 + k % 2;
            let v = (patch / 2) * 2 + k / 2;
            let (x, y) = (-0.6 + 0.4 * u as f64, -0.6 + 0.4 * v as f64);
            origins.extend([x, y, -2.0]);
            mask.push(if x * x + y * y < 0.25 { 1.0 } else { 0.0 });
        }
    }
    let o = Var::from_tensor(
        &Tensor::from_vec(origins, (16, 3), &dev)
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
    )
    .unwrap();
    let d = Tensor::new(&[0.0f64, 0.0, 1.0], &dev)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
        .unsqueeze(0)
        .unwrap()
        .broadcast_as((16, 3))
        .unwrap()
        .contiguous()
        .unwrap();
    let rays = Rays::new(o.as_tensor().clone(), d).unwrap();
    let colors = Tensor::full(0.5f64, (16, 3), &dev)
        .unwrap()
        .to_dtype(dtype)
        .unwrap();
    let mask = Tensor::from_vec(mask, 16, &dev)
        .unwrap()
        .to_dtype(dtype)
        .unwrap();
    (o, rays, colors, mask)
}

fn scalar(t: &Tensor) -> f64 {
    t.to_dtype(DType::F64).unwrap().to_scalar::<f64>().unwrap()
}

fn values(t: &Tensor) -> Vec<f64> {
    t.flatten_all()
        .unwrap()
        .to_dtype(DType::F64)
        .unwrap()
        .to_vec1::<f64>()
        .unwrap()
}

/// Each model trains a step: a finite scalar loss in the rays' dtype whose gradients
/// w.r.t. every weight and the ray origins are finite; and shades rays with the
/// documented shapes and ranges.
#[test]
fn every_model_trains_a_step_and_shades_in_f32_and_f64() {
    for dtype in [DType::F32, DType::F64] {
        for config in configs() {
            let label = format!(
                "{:?} {:?} {:?} {dtype:?}",
                config.kind, config.encoding, config.render_inputs
            );
            let (model, varmap) = build(&config, dtype);
            let (origins, rays, colors, mask) = batch(dtype);
            let loss = model.loss(&rays, &colors, &mask, 0.3, 5).unwrap();
            assert_eq!(loss.total.rank(), 0, "{label}");
            assert_eq!(loss.total.dtype(), dtype, "{label}");
            assert!(scalar(&loss.total).is_finite(), "{label}");
            let photometric = scalar(&loss.photometric);
            assert!(photometric.is_finite() && photometric >= 0.0, "{label}");
            let grads = loss.total.backward().unwrap();
            FiniteGuard::new(&varmap)
                .check(0, &loss.total, Some(&grads))
                .unwrap();
            if let Some(g) = grads.get(&origins) {
                assert!(values(g).iter().all(|x| x.is_finite()), "{label}");
            }
            let seen = model.shade(&rays).unwrap();
            assert_eq!(seen.rgb.dims(), &[16, 3], "{label}");
            assert_eq!(seen.depth.dims(), &[16], "{label}");
            assert_eq!(seen.coverage.dims(), &[16], "{label}");
            assert_eq!(seen.normals.dims(), &[16, 3], "{label}");
            for t in [&seen.rgb, &seen.depth, &seen.coverage, &seen.normals] {
                assert_eq!(t.dtype(), dtype, "{label}");
                assert!(values(t).iter().all(|x| x.is_finite()), "{label}");
            }
            assert!(
                values(&seen.rgb).iter().all(|c| (0.0..=1.0).contains(c)),
                "{label}"
            );
            let coverage = values(&seen.coverage);
            assert!(coverage.iter().all(|&c| c == 0.0 || c == 1.0), "{label}");
            // Unit normals where a ray hits, zero elsewhere.
            let normals = values(&seen.normals);
            for (r, &c) in coverage.iter().enumerate() {
                let n = &normals[3 * r..3 * r + 3];
                let length = n.iter().map(|x| x * x).sum::<f64>().sqrt();
                let expected = if c == 1.0 { 1.0 } else { 0.0 };
                assert!(
                    (length - expected).abs() < 1e-3,
                    "{label}: ray {r}: |n| = {length}"
                );
            }
        }
    }
}

/// The loss through learnable origins: the surface points' implicit gradients reach the
/// rays (what camera refinement trains through); the shaded depth is on the surface.
#[test]
fn the_loss_reaches_the_ray_origins_and_the_depth_is_on_the_surface() {
    // An untrained IDR model is about a sphere of radius ½: the rays inside the disc hit.
    let config = SurfaceModelConfig {
        kind: SurfaceKind::Idr,
        ..SurfaceModelConfig::default()
    };
    let (model, _) = build(&config, DType::F64);
    let (origins, rays, _, mask) = batch(DType::F64);
    let colors = Tensor::full(0.9f64, (16, 3), &Device::Cpu).unwrap();
    let seen = model.shade(&rays).unwrap();
    let (coverage, mask) = (values(&seen.coverage), values(&mask));
    assert!(
        coverage.iter().zip(&mask).all(|(c, m)| c >= m),
        "{coverage:?}"
    );
    let loss = model
        .loss(
            &rays,
            &colors,
            &Tensor::new(mask.as_slice(), &Device::Cpu).unwrap(),
            0.0,
            1,
        )
        .unwrap();
    assert!(scalar(&loss.photometric) > 0.0);
    let grads = loss.total.backward().unwrap();
    let g = values(grads.get(&origins).unwrap());
    assert!(g.iter().all(|x| x.is_finite()));
    assert!(g.iter().any(|&x| x != 0.0));
    // The field is zero at o + t·w for every ray that hits.
    let points = rays
        .origins()
        .broadcast_add(
            &rays
                .directions()
                .broadcast_mul(&seen.depth.unsqueeze(1).unwrap())
                .unwrap(),
        )
        .unwrap();
    let f = values(&model.value(&points).unwrap());
    for (r, c) in coverage.iter().enumerate() {
        if *c == 1.0 {
            assert!(f[r].abs() < 1e-4, "ray {r}: f = {}", f[r]);
        }
    }
}

/// The variable names of each kind (so saved weights load into the same configuration),
/// and the coarse-to-fine windows, one per position encoding.
#[test]
fn variables_are_named_by_network_and_windows_listed() {
    let names = |m: &VarMap| -> Vec<String> { m.data().lock().unwrap().keys().cloned().collect() };
    for (config, prefixes, windows) in [
        (SurfaceKind::Dvr, &["geometry.", "texture."][..], 2),
        (SurfaceKind::DvrJoint, &["decoder."][..], 1),
        (SurfaceKind::Idr, &["geometry.", "render."][..], 1),
    ]
    .map(|(kind, p, w)| {
        let c = SurfaceModelConfig {
            kind,
            coarse_to_fine: true,
            ..SurfaceModelConfig::default()
        };
        (c, p, w)
    }) {
        let (model, varmap) = build(&config, DType::F32);
        let all = names(&varmap);
        assert!(
            all.iter()
                .all(|n| prefixes.iter().any(|p| n.starts_with(p))),
            "{all:?}"
        );
        for p in prefixes {
            assert!(all.iter().any(|n| n.starts_with(p)), "{p}: {all:?}");
        }
        assert_eq!(model.windows.len(), windows, "{:?}", config.kind);
        // Closed at first: the sin/cos bands (each pair adds 1 to the squared norm) are
        // off, so an encoded point is no longer than the point itself.
        let x = Tensor::new(&[[0.3f32, -0.2, 0.1]], &Device::Cpu).unwrap();
        for w in &model.windows {
            let y = neural_fields::encoding::Encoding::forward(w, &x).unwrap();
            let norm = |t: &Tensor| {
                t.sqr()
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap()
            };
            assert!(norm(&y) <= norm(&x) + 1e-6, "{} vs {}", norm(&y), norm(&x));
        }
        let (plain, _) = build(
            &SurfaceModelConfig {
                coarse_to_fine: false,
                ..config
            },
            DType::F32,
        );
        assert!(plain.windows.is_empty());
    }
    // Hash grids: a `grid` table beside the networks that read it.
    let config = SurfaceModelConfig {
        kind: SurfaceKind::Idr,
        encoding: SurfaceEncoding::HashGrid {
            finest_resolution: 32.0,
        },
        ..SurfaceModelConfig::default()
    };
    let (_, varmap) = build(&config, DType::F32);
    assert!(names(&varmap).iter().any(|n| n.starts_with("render.grid")));
}

/// The model is an implicit surface and a texture field: values `[N]`, gradients and
/// colours `[N, 3]`; IDR's colour needs the view directions.
#[test]
fn the_model_is_a_surface_and_a_texture() {
    let p = Tensor::new(&[[0.0f32, 0.0, 0.0], [0.9, 0.0, 0.0]], &Device::Cpu).unwrap();
    let dirs = Tensor::new(&[[0.0f32, 0.0, 1.0], [0.0, 0.0, 1.0]], &Device::Cpu).unwrap();
    let idr = SurfaceModelConfig {
        kind: SurfaceKind::Idr,
        ..SurfaceModelConfig::default()
    };
    let (model, _) = build(&idr, DType::F32);
    let v = values(&model.value(&p).unwrap());
    // The geometric initialisation: about the SDF of a sphere of radius ½.
    assert!(v[0] < -0.2 && v[1] > 0.2, "{v:?}");
    let (_, g) = model.value_and_grad(&p).unwrap();
    assert_eq!(g.dims(), &[2, 3]);
    let input = TextureInput {
        view_dirs: Some(&dirs),
        ..TextureInput::new(&p)
    };
    assert_eq!(model.rgb(&input).unwrap().dims(), &[2, 3]);
    let e = model.rgb(&TextureInput::new(&p)).unwrap_err().to_string();
    assert!(e.starts_with("view_dirs"), "{e}");
    let (dvr, _) = build(&SurfaceModelConfig::default(), DType::F32);
    assert_ne!(model.inside(), dvr.inside());
    assert_eq!(dvr.rgb(&TextureInput::new(&p)).unwrap().dims(), &[2, 3]);
}

/// Bad arguments are errors that name them.
#[test]
fn bad_input_is_an_error_naming_the_argument() {
    let dev = Device::Cpu;
    let err = |config: SurfaceModelConfig| {
        let vb = VarBuilder::zeros(DType::F32, &dev);
        surface_model(&config, vb).unwrap_err().to_string()
    };
    let e = err(SurfaceModelConfig {
        scene_box: [1.0, -1.0, -1.0, -1.0, 1.0, 1.0],
        ..SurfaceModelConfig::default()
    });
    assert!(e.starts_with("config.scene_box"), "{e}");
    let e = err(SurfaceModelConfig {
        scene_box: [f64::NAN, -1.0, -1.0, 1.0, 1.0, 1.0],
        ..SurfaceModelConfig::default()
    });
    assert!(e.starts_with("config.scene_box"), "{e}");
    let e = err(SurfaceModelConfig {
        patch: 0,
        ..SurfaceModelConfig::default()
    });
    assert!(e.starts_with("config.patch"), "{e}");
    let e = err(SurfaceModelConfig {
        encoding: SurfaceEncoding::HashGrid {
            finest_resolution: 4.0,
        },
        ..SurfaceModelConfig::default()
    });
    assert!(e.starts_with("config.encoding"), "{e}");
    let e = surface_model(
        &SurfaceModelConfig::default(),
        VarBuilder::zeros(DType::U8, &dev),
    )
    .unwrap_err()
    .to_string();
    assert!(e.starts_with("vb"), "{e}");

    let (model, _) = build(&SurfaceModelConfig::default(), DType::F32);
    let (_, rays, colors, mask) = batch(DType::F32);
    let e = |r: neural_fields::Result<neural_fields::dvr::SurfaceLoss>| r.unwrap_err().to_string();
    let e1 = e(model.loss(&rays, &colors.narrow(0, 0, 8).unwrap(), &mask, 0.0, 0));
    assert!(e1.starts_with("colors"), "{e1}");
    let e2 = e(model.loss(&rays, &colors.to_dtype(DType::F64).unwrap(), &mask, 0.0, 0));
    assert!(e2.starts_with("colors"), "{e2}");
    let e3 = e(model.loss(&rays, &colors, &mask.narrow(0, 0, 15).unwrap(), 0.0, 0));
    assert!(e3.starts_with("mask"), "{e3}");
    let e4 = e(model.loss(&rays, &colors, &mask.to_dtype(DType::U8).unwrap(), 0.0, 0));
    assert!(e4.starts_with("mask"), "{e4}");
    let e5 = e(model.loss(&rays, &colors, &mask, 1.5, 0));
    assert!(e5.starts_with("progress"), "{e5}");
    let e6 = e(model.loss(&rays, &colors, &mask, f64::NAN, 0));
    assert!(e6.starts_with("progress"), "{e6}");
    // Six rays are not whole 2 × 2 patches.
    let six = Rays::new(
        rays.origins().narrow(0, 0, 6).unwrap(),
        rays.directions().narrow(0, 0, 6).unwrap(),
    )
    .unwrap();
    let e7 = e(model.loss(
        &six,
        &colors.narrow(0, 0, 6).unwrap(),
        &mask.narrow(0, 0, 6).unwrap(),
        0.0,
        0,
    ));
    assert!(e7.starts_with("rays"), "{e7}");
    // Single rays (patch 1) need no patches.
    let single = SurfaceModelConfig {
        patch: 1,
        ..SurfaceModelConfig::default()
    };
    let (model, _) = build(&single, DType::F32);
    let loss = model
        .loss(
            &six,
            &colors.narrow(0, 0, 6).unwrap(),
            &mask.narrow(0, 0, 6).unwrap(),
            0.0,
            0,
        )
        .unwrap();
    assert!(scalar(&loss.total).is_finite());
}
