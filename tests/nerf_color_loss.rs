//! `Nerf::color_loss`: the fused op (encodings, both networks, activations, compositing,
//! squared error and their backward pass in one CPU pass) against the same loss composed
//! of `Nerf::radiance`, `composite` and candle's ops, in f64 (1e-10) and f32 (1e-5);
//! batched and packed rays, rays longer than a tile and rays without samples, opaque last
//! intervals and backgrounds, both density activations, no direction encoding; gradients
//! against central differences; saturated densities; bad input.

#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use common::{central_diff_bound, close, reseed, v64};
use neural_fields::camera::Rays;
use neural_fields::encoding::{FrequencyEncoding, PointEncoding};
use neural_fields::nn::build_seeded;
use neural_fields::rng::SplitMix64;
use neural_fields::volume::Layout;
use neural_fields::volume::{nerf, DensityActivation, Nerf, NerfConfig};
use neural_fields::volume::{stratified, CompositeConfig, Intervals, Jitter, Packed};
use neural_fields::Error;
use proptest::prelude::*;

const DEV: Device = Device::Cpu;

fn small() -> NerfConfig {
    NerfConfig {
        width: 16,
        color_width: 8,
        ..NerfConfig::default()
    }
}

/// The network twice over one set of variables: the fused path and `force_reference`.
fn build(config: &NerfConfig, dtype: DType, seed: u64) -> (VarMap, Nerf, Nerf) {
    let varmap = VarMap::new();
    let fused = build_seeded(&varmap, dtype, &DEV, seed, |vb| nerf(config, vb)).unwrap();
    reseed(&varmap, seed ^ 7, 1.0);
    let reference = nerf(
        &NerfConfig {
            force_reference: true,
            ..config.clone()
        },
        VarBuilder::from_varmap(&varmap, dtype, &DEV),
    )
    .unwrap();
    (varmap, fused, reference)
}

/// `r` rays from distance 3 towards points near the origin, directions of length 0.5 to 2
/// (so that δ is scaled by the norm), and a target colour per ray.
fn rays(rng: &mut SplitMix64, r: usize, dtype: DType) -> (Rays, Tensor) {
    let (mut o, mut d) = (vec![], vec![]);
    for _ in 0..r {
        let a = [rng.normal(), rng.normal(), rng.normal()];
        let la = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        let aim = [
            rng.uniform() - 0.5,
            rng.uniform() - 0.5,
            rng.uniform() - 0.5,
        ];
        let len = 0.5 + 1.5 * rng.uniform();
        let origin: Vec<f64> = a.iter().map(|x| 3.0 * x / la).collect();
        let dir: Vec<f64> = (0..3).map(|k| aim[k] - origin[k]).collect();
        let ld = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
        o.extend(origin);
        d.extend(dir.iter().map(|x| len * x / ld));
    }
    let rays = Rays::new(
        Tensor::from_vec(o, (r, 3), &DEV)
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
        Tensor::from_vec(d, (r, 3), &DEV)
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
    )
    .unwrap();
    let target = rng.uniform_tensor(&[r, 3], 0.0, 1.0, dtype, &DEV).unwrap();
    (rays, target)
}

/// Packed intervals with `counts[r]` contiguous intervals on ray `r` in `[1, 5]`.
fn packed(counts: &[usize], dtype: DType) -> Intervals {
    let (mut s, mut e) = (vec![], vec![]);
    for &c in counts {
        for i in 0..c {
            s.push(1.0 + 4.0 * i as f64 / c as f64);
            e.push(1.0 + 4.0 * (i + 1) as f64 / c as f64);
        }
    }
    let m = s.len();
    let t = |v: Vec<f64>| {
        Tensor::from_vec(v, m, &DEV)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
    };
    Intervals::new(
        t(s),
        t(e),
        Layout::Packed(Packed::from_counts(counts, &DEV).unwrap()),
    )
    .unwrap()
}

fn batched(r: usize, s: usize, dtype: DType, seed: u64) -> Intervals {
    let near = Tensor::full(1.0, r, &DEV).unwrap().to_dtype(dtype).unwrap();
    let far = Tensor::full(5.0, r, &DEV).unwrap().to_dtype(dtype).unwrap();
    stratified(&near, &far, s, Jitter::PerSample, seed).unwrap()
}

/// The largest |entry| of `v`.
fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |m, x| m.max(x.abs()))
}

/// Loss and every variable's gradient of both paths agree to `tol` (relative to the
/// largest entry of each gradient); returns the fused loss.
fn assert_paths_agree(
    (varmap, fused, reference): &(VarMap, Nerf, Nerf),
    rays: &Rays,
    intervals: &Intervals,
    target: &Tensor,
    config: &CompositeConfig,
    tol: f64,
    case: &str,
) -> f64 {
    let (a_out, b_out) = (
        fused.color_loss(rays, intervals, target, config).unwrap(),
        reference
            .color_loss(rays, intervals, target, config)
            .unwrap(),
    );
    // Both paths report the same opacity (the composed one from `composite`).
    assert!(
        close(a_out.opacity_mean, b_out.opacity_mean, tol.max(1e-12), 0.0)
            && close(a_out.opacity_max, b_out.opacity_max, tol.max(1e-12), 0.0),
        "{case}: opacity {} / {} vs {} / {}",
        a_out.opacity_mean,
        a_out.opacity_max,
        b_out.opacity_mean,
        b_out.opacity_max
    );
    let (a, b) = (a_out.loss, b_out.loss);
    assert_eq!(a.dims(), &[] as &[usize], "{case}: a scalar loss");
    let (la, lb) = (v64(&a)[0], v64(&b)[0]);
    assert!(
        la.is_finite() && close(la, lb, tol, 0.0),
        "{case}: loss {la} vs {lb}"
    );
    let (ga, gb) = (a.backward().unwrap(), b.backward().unwrap());
    for v in varmap.all_vars() {
        let (x, y) = (v64(ga.get(&v).unwrap()), v64(gb.get(&v).unwrap()));
        let scale = max_abs(&y);
        assert!(scale > 0.0, "{case}: a variable without gradient");
        for (i, (p, q)) in x.iter().zip(&y).enumerate() {
            assert!(
                p.is_finite() && (p - q).abs() <= tol * scale,
                "{case}: gradient entry {i}: {p:e} vs {q:e} (scale {scale:e})"
            );
        }
    }
    la
}

#[test]
fn fused_loss_equals_the_composed_loss_in_f64_and_f32() {
    for (dtype, tol) in [(DType::F64, 1e-10), (DType::F32, 1e-5)] {
        let mut rng = SplitMix64::new(11);
        let nets = build(&small(), dtype, 3);
        let (rays8, target8) = rays(&mut rng, 8, dtype);
        // Two rays per tile, a ray longer than a tile (recomputed sub-tiles), and packed
        // rays of every length, some without samples.
        let bg = Tensor::new(&[0.2f64, 0.9, 0.4], &DEV)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let cases = [
            (
                "batched, 64 samples",
                batched(8, 64, dtype, 1),
                CompositeConfig::default(),
            ),
            (
                "batched, 300 samples",
                batched(8, 300, dtype, 2),
                CompositeConfig::default(),
            ),
            (
                "packed",
                packed(&[0, 1, 5, 130, 64, 0, 257, 3], dtype),
                CompositeConfig::default(),
            ),
            (
                "opaque last, background [3]",
                batched(8, 40, dtype, 3),
                CompositeConfig {
                    opaque_last: true,
                    background: Some(bg.clone()),
                    ..CompositeConfig::default()
                },
            ),
            (
                "background per ray",
                packed(&[7, 0, 100, 1, 2, 3, 4, 5], dtype),
                CompositeConfig {
                    background: Some(target8.affine(-0.5, 0.6).unwrap()),
                    ..CompositeConfig::default()
                },
            ),
        ];
        for (case, iv, config) in &cases {
            assert_paths_agree(&nets, &rays8, iv, &target8, config, tol, case);
        }
        // Softplus density, no direction encoding, identity position encoding.
        for (name, config) in [
            (
                "softplus",
                NerfConfig {
                    density: DensityActivation::Softplus { shift: -1.0 },
                    ..small()
                },
            ),
            (
                "no direction encoding",
                NerfConfig {
                    direction_encoding: None,
                    ..small()
                },
            ),
            (
                "identity encodings",
                NerfConfig {
                    position_encoding: PointEncoding::Identity,
                    direction_encoding: Some(PointEncoding::Identity),
                    ..small()
                },
            ),
        ] {
            let nets = build(&config, dtype, 5);
            let iv = batched(8, 50, dtype, 4);
            assert_paths_agree(
                &nets,
                &rays8,
                &iv,
                &target8,
                &CompositeConfig::default(),
                tol,
                name,
            );
        }
    }
}

#[test]
fn saturated_densities_keep_the_loss_and_gradients_finite() {
    // shift +40: σ ≈ e⁴⁰ for every sample, σδ far beyond the compositing clamp; and a
    // shift of −60: σ ≈ 0, the background alone.
    for dtype in [DType::F32, DType::F64] {
        let tol = if dtype == DType::F32 { 1e-5 } else { 1e-10 };
        for shift in [40.0, -60.0] {
            let config = NerfConfig {
                density: DensityActivation::TruncExp { shift },
                ..small()
            };
            let nets = build(&config, dtype, 9);
            let mut rng = SplitMix64::new(4);
            let (r, target) = rays(&mut rng, 4, dtype);
            let loss = assert_paths_agree(
                &nets,
                &r,
                &batched(4, 96, dtype, 6),
                &target,
                &CompositeConfig::default(),
                tol,
                &format!("shift {shift}"),
            );
            assert!(loss.is_finite());
        }
    }
}

#[test]
fn rays_or_targets_that_carry_gradients_take_the_composed_path() {
    let nets = build(&small(), DType::F64, 2);
    let mut rng = SplitMix64::new(8);
    let (r, target) = rays(&mut rng, 3, DType::F64);
    let tv = Var::from_tensor(&target).unwrap();
    let iv = batched(3, 20, DType::F64, 1);
    let loss = nets
        .1
        .color_loss(&r, &iv, tv.as_tensor(), &CompositeConfig::default())
        .unwrap()
        .loss;
    let g = v64(loss
        .backward()
        .unwrap()
        .get(&tv)
        .expect("a target gradient"));
    let reference = nets
        .2
        .color_loss(&r, &iv, &target, &CompositeConfig::default())
        .unwrap()
        .loss;
    assert_eq!(v64(&loss), v64(&reference));
    assert!(max_abs(&g) > 0.0);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(8))]

    /// ∂L/∂θ of the fused op against central differences of the fused loss, f64, for
    /// entries of every variable, at scene scales 1 and 30. Softplus density: trunc-exp's
    /// gradient is by definition not its value's derivative beyond |x| = 15.
    #[test]
    fn fused_loss_gradients_match_finite_differences(seed in any::<u64>(), scale in prop_oneof![Just(1.0), Just(30.0)]) {
        let config = NerfConfig {
            width: 8,
            color_width: 8,
            position_encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 3).unwrap()),
            direction_encoding: Some(PointEncoding::Frequency(FrequencyEncoding::new(3, 2).unwrap())),
            density: DensityActivation::Softplus { shift: -1.0 },
            ..NerfConfig::default()
        };
        let (varmap, net, _) = build(&config, DType::F64, seed);
        let mut rng = SplitMix64::new(seed ^ 1);
        let (r, target) = rays(&mut rng, 3, DType::F64);
        let r = Rays::new(r.origins().affine(scale, 0.0).unwrap(), r.directions().clone()).unwrap();
        let iv = packed(&[5, 9, 140], DType::F64);
        let iv = Intervals::new(
            iv.starts.affine(scale, 0.0).unwrap(),
            iv.ends.affine(scale, 0.0).unwrap(),
            Layout::Packed(Packed::from_counts(&[5, 9, 140], &DEV).unwrap()),
        ).unwrap();
        let cc = CompositeConfig::default();
        let loss = || net.color_loss(&r, &iv, &target, &cc).unwrap().loss.to_scalar::<f64>().unwrap();
        let grads = net.color_loss(&r, &iv, &target, &cc).unwrap().loss.backward().unwrap();
        let (mut checked, mut total) = (0, 0);
        // By name: the map's own order differs between processes, and with it the
        // entries a seed draws.
        for (n, v) in common::sorted_vars(&varmap).into_iter().enumerate() {
            let g = v64(grads.get(&v).unwrap());
            let x0 = v64(v.as_tensor());
            for _ in 0..3 {
                let i = rng.below(x0.len() as u64) as usize;
                total += 1;
                let mut f = |x: f64| {
                    let mut p = x0.clone();
                    p[i] = x;
                    v.set(&Tensor::from_vec(p, v.dims(), &DEV).unwrap()).unwrap();
                    loss()
                };
                let d = central_diff_bound(&mut f, x0[i], 1e-5, 1.0);
                v.set(&Tensor::from_vec(x0.clone(), v.dims(), &DEV).unwrap()).unwrap();
                if let Some((num, bar)) = d {
                    checked += 1;
                    let err = (g[i] - num).abs();
                    prop_assert!(close(g[i], num, 1e-6, 1e-4) || err <= bar, "variable {n} entry {i}: {} vs FD {num} ± {bar:e}", g[i]);
                }
            }
        }
        // ReLU kinks inside the stencil skip an entry; most must be checked.
        prop_assert!(2 * checked >= total, "only {checked} of {total} entries checked");
    }
}

#[test]
fn bad_input_names_the_argument() {
    let (_, net, _) = build(&small(), DType::F32, 1);
    let mut rng = SplitMix64::new(2);
    let (r, target) = rays(&mut rng, 4, DType::F32);
    let iv = batched(4, 8, DType::F32, 0);
    let cc = CompositeConfig::default();
    let arg = |e: neural_fields::Result<neural_fields::volume::ColorLoss>| match e {
        Err(Error::InvalidArgument { arg, .. }) => arg,
        other => panic!("expected InvalidArgument, got {other:?}"),
    };
    let wide = Tensor::zeros((4, 4), DType::F32, &DEV).unwrap();
    assert_eq!(arg(net.color_loss(&r, &iv, &wide, &cc)), "target");
    let nan = target.affine(0.0, f64::NAN).unwrap();
    assert_eq!(arg(net.color_loss(&r, &iv, &nan, &cc)), "target");
    let f64_target = target.to_dtype(DType::F64).unwrap();
    assert_eq!(arg(net.color_loss(&r, &iv, &f64_target, &cc)), "target");
    let bad_bg = CompositeConfig {
        background: Some(Tensor::zeros(2, DType::F32, &DEV).unwrap()),
        ..CompositeConfig::default()
    };
    assert_eq!(
        arg(net.color_loss(&r, &iv, &target, &bad_bg)),
        "config.background"
    );
    let five = batched(5, 8, DType::F32, 0);
    assert!(net.color_loss(&r, &five, &target, &cc).is_err());
    let none = batched(0, 8, DType::F32, 0);
    let empty = Tensor::zeros((0, 3), DType::F32, &DEV).unwrap();
    let r0 = Rays::new(empty.clone(), empty.clone()).unwrap();
    assert_eq!(arg(net.color_loss(&r0, &none, &empty, &cc)), "target");
}
