//! The NeRF network: shapes, ranges, view dependence, the density as a `Field`, weights
//! through safetensors, gradients against finite differences, the fused path (both
//! networks in one CPU op) against the reference path of candle ops, and bad input.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use common::{assert_parts_close, central_diff, close, reseed, sorted_vars, uniform, v64};
use neural_fields::field::Field;
use neural_fields::nn::build_seeded;
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{nerf, DensityActivation, Nerf, NerfConfig};
use neural_fields::Error;
use proptest::prelude::*;

fn small() -> NerfConfig {
    NerfConfig {
        width: 16,
        color_width: 8,
        ..NerfConfig::default()
    }
}

fn build(config: &NerfConfig, dtype: DType, seed: u64) -> (VarMap, Nerf) {
    let varmap = VarMap::new();
    let net = build_seeded(&varmap, dtype, &Device::Cpu, seed, |vb| nerf(config, vb)).unwrap();
    (varmap, net)
}

fn points(rng: &mut SplitMix64, n: usize, scale: f64, dtype: DType) -> Tensor {
    rng.uniform_tensor(&[n, 3], -scale, scale, dtype, &Device::Cpu)
        .unwrap()
}

#[test]
fn outputs_have_their_shapes_ranges_and_the_density_is_the_field() {
    for dtype in [DType::F32, DType::F64] {
        for density in [
            DensityActivation::TruncExp { shift: -1.0 },
            DensityActivation::Softplus { shift: -1.0 },
        ] {
            let (_, net) = build(&NerfConfig { density, ..small() }, dtype, 1);
            let mut rng = SplitMix64::new(2);
            let p = points(&mut rng, 50, 1.5, dtype);
            let d = points(&mut rng, 50, 1.0, dtype);
            let (sigma, rgb) = net.radiance(&p, &d).unwrap();
            assert_eq!((sigma.dims(), rgb.dims()), (&[50][..], &[50, 3][..]));
            assert_eq!((sigma.dtype(), rgb.dtype()), (dtype, dtype));
            assert!(v64(&sigma).iter().all(|&s| s >= 0.0 && s.is_finite()));
            assert!(v64(&rgb).iter().all(|&c| c > 0.0 && c < 1.0));
            // The density does not depend on the direction; the Field is the density.
            assert_eq!(v64(&net.density(&p).unwrap()), v64(&sigma));
            assert_eq!(
                v64(&Field::forward(&net, &p).unwrap().squeeze(1).unwrap()),
                v64(&sigma)
            );
            assert_eq!(Field::out_dim(&net), 1);
        }
    }
}

#[test]
fn colour_depends_on_the_direction_but_not_its_length() {
    let (_, net) = build(&small(), DType::F64, 3);
    let mut rng = SplitMix64::new(4);
    let p = points(&mut rng, 20, 1.0, DType::F64);
    let d = points(&mut rng, 20, 1.0, DType::F64);
    let (_, a) = net.radiance(&p, &d).unwrap();
    let (_, b) = net.radiance(&p, &(&d * 7.5).unwrap()).unwrap();
    for (x, y) in v64(&a).iter().zip(v64(&b)) {
        assert!((x - y).abs() < 1e-12);
    }
    let (_, c) = net.radiance(&p, &d.neg().unwrap()).unwrap();
    let diff: f64 = v64(&a)
        .iter()
        .zip(v64(&c))
        .map(|(x, y)| (x - y).abs())
        .sum();
    assert!(diff > 1e-6, "{diff}");
    // Without a direction encoding the colour is view-independent.
    let (_, flat) = build(
        &NerfConfig {
            direction_encoding: None,
            ..small()
        },
        DType::F64,
        3,
    );
    let (_, e) = flat.radiance(&p, &d).unwrap();
    let (_, f) = flat.radiance(&p, &d.neg().unwrap()).unwrap();
    assert_eq!(v64(&e), v64(&f));
}

#[test]
fn weights_round_trip_through_safetensors() {
    let (varmap, net) = build(&small(), DType::F32, 5);
    let path =
        std::env::temp_dir().join(format!("nerf-weights-{}.safetensors", std::process::id()));
    varmap.save(&path).unwrap();
    let (mut other, net2) = build(&small(), DType::F32, 6);
    let mut rng = SplitMix64::new(7);
    let p = points(&mut rng, 10, 1.0, DType::F32);
    let d = points(&mut rng, 10, 1.0, DType::F32);
    assert_ne!(
        v64(&net.radiance(&p, &d).unwrap().1),
        v64(&net2.radiance(&p, &d).unwrap().1)
    );
    other.load(&path).unwrap();
    assert_eq!(
        v64(&net.radiance(&p, &d).unwrap().1),
        v64(&net2.radiance(&p, &d).unwrap().1)
    );
    let _ = std::fs::remove_file(path);
}

#[test]
fn bad_input_is_an_error_naming_the_argument() {
    let (_, net) = build(&small(), DType::F32, 1);
    let p = Tensor::zeros((4, 3), DType::F32, &Device::Cpu).unwrap();
    let arg = |r: neural_fields::Result<(Tensor, Tensor)>| match r {
        Err(Error::InvalidArgument { arg, .. }) => arg,
        other => panic!("{other:?}"),
    };
    assert_eq!(
        arg(net.radiance(
            &p,
            &Tensor::zeros((3, 3), DType::F32, &Device::Cpu).unwrap()
        )),
        "directions"
    );
    assert_eq!(
        arg(net.radiance(
            &p,
            &Tensor::zeros((4, 3), DType::F64, &Device::Cpu).unwrap()
        )),
        "directions"
    );
    assert_eq!(
        arg(net.radiance(
            &Tensor::zeros((4, 2), DType::F32, &Device::Cpu).unwrap(),
            &p
        )),
        "points"
    );
    let e = build_seeded(&VarMap::new(), DType::F32, &Device::Cpu, 0, |vb| {
        nerf(
            &NerfConfig {
                width: 0,
                ..small()
            },
            vb,
        )
    });
    assert!(matches!(
        e,
        Err(Error::InvalidArgument {
            arg: "config.width",
            ..
        })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]

    /// ∂(Σ w·rgb + Σ u·σ)/∂(points, directions) by autograd against central differences,
    /// in f64, over positions up to ±100 and direction lengths from 1e-3 to 1e3.
    #[test]
    fn gradients_match_finite_differences(seed in 0u64..1000, scale in prop::sample::select(vec![1.0, 10.0, 100.0]), len in prop::sample::select(vec![1e-3, 1.0, 1e3])) {
        let config = NerfConfig { density: DensityActivation::Softplus { shift: -1.0 }, ..small() };
        let (_, net) = build(&config, DType::F64, seed);
        let mut rng = SplitMix64::new(seed + 1);
        let p0 = v64(&points(&mut rng, 2, scale, DType::F64));
        let d0: Vec<f64> = v64(&points(&mut rng, 2, 1.0, DType::F64)).iter().map(|x| x * len).collect();
        let w = v64(&points(&mut rng, 2, 1.0, DType::F64));
        let u = [0.7, -0.3];
        let objective = |p: &[f64], d: &[f64]| -> neural_fields::Result<Tensor> {
            let dev = Device::Cpu;
            let (sigma, rgb) = net.radiance(&Tensor::from_slice(p, (2, 3), &dev)?, &Tensor::from_slice(d, (2, 3), &dev)?)?;
            let wt = Tensor::from_slice(&w, (2, 3), &dev)?;
            Ok(((rgb * wt)?.sum_all()? + (sigma * Tensor::new(&u, &dev)?)?.sum_all()?)?)
        };
        let pv = Var::from_slice(&p0, (2, 3), &Device::Cpu).unwrap();
        let dv = Var::from_slice(&d0, (2, 3), &Device::Cpu).unwrap();
        let (sigma, rgb) = net.radiance(pv.as_tensor(), dv.as_tensor()).unwrap();
        let total = ((rgb * Tensor::from_slice(&w, (2, 3), &Device::Cpu).unwrap()).unwrap().sum_all().unwrap()
            + (sigma * Tensor::new(&u, &Device::Cpu).unwrap()).unwrap().sum_all().unwrap()).unwrap();
        let grads = total.backward().unwrap();
        let (gp, gd) = (v64(grads.get(&pv).unwrap()), v64(grads.get(&dv).unwrap()));
        let mut checked = 0;
        for i in 0..6 {
            let mut f = |x: f64| { let mut p = p0.clone(); p[i] = x; objective(&p, &d0).unwrap().to_scalar::<f64>().unwrap() };
            // h well below the period of the top frequency (2⁹π) of the position encoding.
            // The encoding's curvature can look like a kink to the stencil: retry smaller.
            let fd = central_diff(&mut f, p0[i], 1e-6, 1.0).or_else(|| central_diff(&mut f, p0[i], 1e-8, 1.0));
            if let Some(fd) = fd {
                prop_assert!(close(gp[i], fd, 1e-5, 1e-3), "points[{i}]: {} vs {fd}", gp[i]);
                checked += 1;
            }
            let mut g = |x: f64| { let mut d = d0.clone(); d[i] = x; objective(&p0, &d).unwrap().to_scalar::<f64>().unwrap() };
            let fd = central_diff(&mut g, d0[i], 1e-4 * len, 1.0 / len)
                .or_else(|| central_diff(&mut g, d0[i], 1e-6 * len, 1.0 / len));
            if let Some(fd) = fd {
                prop_assert!(close(gd[i], fd, 1e-5, 1e-3 / len), "directions[{i}]: {} vs {fd}", gd[i]);
                checked += 1;
            }
        }
        // Kinks (ReLU boundaries) inside a stencil skip a coordinate; most must be checked.
        prop_assert!(checked >= 6, "only {checked} of 12 derivatives checked");
    }
}

/// Both networks in one CPU op: outputs and gradients equal the reference path of candle
/// ops (f64 to 1e-10, f32 to 1e-5).
#[test]
fn fused_nerf_equals_reference() {
    for dtype in [DType::F64, DType::F32] {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, dtype, &Device::Cpu);
        let base = NerfConfig {
            width: 16,
            color_width: 8,
            depth: 3,
            skips: vec![2],
            ..NerfConfig::default()
        };
        let fused = nerf(&base, vb.clone()).unwrap();
        let reference = nerf(
            &NerfConfig {
                force_reference: true,
                ..base
            },
            vb,
        )
        .unwrap();
        reseed(&varmap, 3, 0.5);
        let mut rng = SplitMix64::new(2);
        let points = uniform(&mut rng, 300, 3, -1.0, 1.0, dtype);
        let dirs = uniform(&mut rng, 300, 3, -1.0, 1.0, dtype);
        let tol = if dtype == DType::F64 { 1e-10 } else { 1e-5 };
        let mut outs = Vec::new();
        for net in [&fused, &reference] {
            let (sigma, rgb) = net.radiance(&points, &dirs).unwrap();
            let loss = (sigma.sum_all().unwrap() + rgb.sqr().unwrap().sum_all().unwrap()).unwrap();
            let grads = loss.backward().unwrap();
            let mut parts = vec![v64(&sigma), v64(&rgb)];
            for var in sorted_vars(&varmap) {
                parts.push(v64(grads.get(var.as_tensor()).unwrap()));
            }
            outs.push(parts);
        }
        assert_parts_close(&outs[0], &outs[1], tol, &format!("NeRF {dtype:?}"));
    }
}
