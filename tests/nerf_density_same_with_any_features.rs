//! Regression: `Nerf`'s trunc-exp density once depended on a Cargo feature (without
//! `volume` it fell back to `exp(min(x, 88))` with no gradient clamp, and the f32 cap in
//! f64). The density and its gradient are now `numerics::trunc_exp` of the shifted raw
//! output and its one gradient rule `exp(clamp(x, −15, 15))`, on the fused and the
//! reference path, in f32 and f64, including raw values far above the cap; the fused
//! colour loss evaluates the same rule as the loss composed from `Nerf::radiance`.

#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use common::{assert_parts_close, sorted_vars, v64};
use neural_fields::camera::Rays;
use neural_fields::field::Field;
use neural_fields::nn::{build_seeded, mlp, Activation, MlpConfig};
use neural_fields::numerics::{
    trunc_exp, TRUNC_EXP_GRAD_CLAMP, TRUNC_EXP_MAX_F32, TRUNC_EXP_MAX_F64,
};
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{
    nerf, stratified, CompositeConfig, DensityActivation, Jitter, Nerf, NerfConfig,
};

const DEV: Device = Device::Cpu;

fn config(shift: f64, force_reference: bool) -> NerfConfig {
    NerfConfig {
        width: 16,
        color_width: 8,
        depth: 2,
        density: DensityActivation::TruncExp { shift },
        force_reference,
        ..NerfConfig::default()
    }
}

/// The network and, on its variables, its trunk alone (the reference path), whose first
/// output column is the raw density (the trunk's variables are under `trunk.`).
fn build(config: &NerfConfig, dtype: DType) -> (VarMap, Nerf, neural_fields::nn::Mlp) {
    let varmap = VarMap::new();
    let net = build_seeded(&varmap, dtype, &DEV, 5, |vb| nerf(config, vb)).unwrap();
    let trunk = mlp(
        &MlpConfig {
            out_dim: 1 + config.width,
            hidden: config.width,
            depth: config.depth,
            activation: Activation::Relu,
            skips: config.skips.clone(),
            encoding: config.position_encoding.clone(),
            force_reference: true,
            ..MlpConfig::default()
        },
        VarBuilder::from_varmap(&varmap, dtype, &DEV).pp("trunk"),
    )
    .unwrap();
    (varmap, net, trunk)
}

/// The documented rule at one shifted raw value `z` (already rounded to the dtype):
/// value `exp(min(z, cap))` in the dtype, slope `exp(clamp(z, −15, 15))`.
fn rule(z: f64, dtype: DType) -> (f64, f64) {
    let c = TRUNC_EXP_GRAD_CLAMP;
    if dtype == DType::F32 {
        let z = z as f32;
        let v = z.min(TRUNC_EXP_MAX_F32 as f32).exp();
        (f64::from(v), f64::from(z.clamp(-c as f32, c as f32).exp()))
    } else {
        (z.min(TRUNC_EXP_MAX_F64).exp(), z.clamp(-c, c).exp())
    }
}

#[test]
fn density_and_its_gradient_follow_the_one_trunc_exp_rule() {
    // Shifts that put the argument below the gradient clamp, inside it, above it, above
    // the f32 cap (88) and above the f64 cap (709).
    for dtype in [DType::F32, DType::F64] {
        let tol = if dtype == DType::F64 { 1e-10 } else { 2e-5 };
        for force_reference in [false, true] {
            for shift in [-30.0, -1.0, 0.0, 14.0, 20.0, 100.0, 1000.0] {
                let what = format!("{dtype:?} reference={force_reference} shift={shift}");
                let (_varmap, net, trunk) = build(&config(shift, force_reference), dtype);
                let mut rng = SplitMix64::new(9);
                let p = Var::from_tensor(
                    &rng.uniform_tensor(&[40, 3], -1.0, 1.0, dtype, &DEV)
                        .unwrap(),
                )
                .unwrap();
                let d = rng
                    .uniform_tensor(&[40, 3], -1.0, 1.0, dtype, &DEV)
                    .unwrap();
                let c = rng.uniform_tensor(&[40], 0.5, 1.5, dtype, &DEV).unwrap();
                let raw = Field::forward(&trunk, p.as_tensor())
                    .unwrap()
                    .narrow(1, 0, 1)
                    .unwrap()
                    .squeeze(1)
                    .unwrap();
                let z = (&raw + shift).unwrap();
                let (want, slope): (Vec<f64>, Vec<f64>) =
                    v64(&z).iter().map(|&z| rule(z, dtype)).unzip();
                // The tensor op of `numerics` gives the same values as the rule.
                let op = v64(&trunc_exp(&z).unwrap());
                for (i, (a, b)) in op.iter().zip(&want).enumerate() {
                    assert_eq!(a, b, "{what}: numerics::trunc_exp[{i}]");
                }
                // ∂(Σ c·σ)/∂p by the rule: Σ c·slope·∂raw/∂p with the slope held fixed.
                let slope_t = Tensor::new(slope.as_slice(), &DEV)
                    .unwrap()
                    .to_dtype(dtype)
                    .unwrap();
                let weight = (&c * &slope_t).unwrap();
                let g_rule = (&raw * &weight)
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .backward()
                    .unwrap();
                let g_rule = v64(g_rule.get(p.as_tensor()).unwrap());
                let density = net.density(p.as_tensor()).unwrap();
                let (radiance, _) = net.radiance(p.as_tensor(), &d).unwrap();
                for (name, sigma) in [("density", density), ("radiance", radiance)] {
                    let got = v64(&sigma);
                    assert!(got.iter().all(|v| v.is_finite()), "{what} {name}: {got:?}");
                    for (i, (a, b)) in got.iter().zip(&want).enumerate() {
                        assert!(
                            (a - b).abs() <= tol * b.abs(),
                            "{what} {name}[{i}]: {a} vs the rule's {b}"
                        );
                    }
                    let g = (&sigma * &c)
                        .unwrap()
                        .sum_all()
                        .unwrap()
                        .backward()
                        .unwrap();
                    let g = v64(g.get(p.as_tensor()).unwrap());
                    let scale = g_rule.iter().fold(1e-3f64, |m, v| m.max(v.abs()));
                    for (i, (a, b)) in g.iter().zip(&g_rule).enumerate() {
                        assert!(
                            a.is_finite() && (a - b).abs() <= tol * scale,
                            "{what} {name}: ∂/∂p[{i}] {a} vs the rule's {b}"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn fused_colour_loss_uses_the_same_rule_as_the_composed_loss() {
    // Short intervals (δ = 1e-5) keep σδ below compositing's clamp for densities up to
    // e²⁰, so the clamped slope (e¹⁵ where the argument exceeds 15) reaches the gradient;
    // shift 100 saturates σ (value checked, no gradient through σ).
    for dtype in [DType::F32, DType::F64] {
        let tol = if dtype == DType::F64 { 1e-10 } else { 1e-4 };
        for shift in [-20.0, 0.0, 12.0, 17.0, 100.0] {
            let varmap = VarMap::new();
            let fused = build_seeded(&varmap, dtype, &DEV, 3, |vb| {
                nerf(&config(shift, false), vb)
            })
            .unwrap();
            let reference = nerf(
                &config(shift, true),
                VarBuilder::from_varmap(&varmap, dtype, &DEV),
            )
            .unwrap();
            let dev_t = |v: &[f64], shape: (usize, usize)| {
                Tensor::from_vec(v.to_vec(), shape, &DEV)
                    .unwrap()
                    .to_dtype(dtype)
                    .unwrap()
            };
            let r = 6;
            let mut rng = SplitMix64::new(4);
            let origins: Vec<f64> = (0..3 * r).map(|_| rng.uniform() - 0.5).collect();
            let dirs: Vec<f64> = (0..r).flat_map(|_| [0.0, 0.0, 1.0]).collect();
            let rays = Rays::new(dev_t(&origins, (r, 3)), dev_t(&dirs, (r, 3))).unwrap();
            let near = Tensor::full(0.0f64, r, &DEV)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let far = Tensor::full(16e-5f64, r, &DEV)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let intervals = stratified(&near, &far, 16, Jitter::None, 0).unwrap();
            let target = rng.uniform_tensor(&[r, 3], 0.0, 1.0, dtype, &DEV).unwrap();
            let cfg = CompositeConfig::default();
            let mut parts = Vec::new();
            for net in [&fused, &reference] {
                let loss = net
                    .color_loss(&rays, &intervals, &target, &cfg)
                    .unwrap()
                    .loss;
                let grads = loss.backward().unwrap();
                let mut p = vec![v64(&loss)];
                for var in sorted_vars(&varmap) {
                    p.push(v64(grads.get(var.as_tensor()).unwrap()));
                }
                assert!(
                    p.iter().flatten().all(|v| v.is_finite()),
                    "{dtype:?} {shift}"
                );
                parts.push(p);
            }
            assert_parts_close(
                &parts[0],
                &parts[1],
                tol,
                &format!("colour loss {dtype:?} shift={shift}"),
            );
        }
    }
}
