//! ONet decoder: batch-independent inference (bit-identical alone or among 10 000
//! points), spatial gradients against finite differences, training-mode statistics.
#![cfg(feature = "occupancy")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
use neural_fields::field::ConditionalField;
use neural_fields::nn::build_seeded;
use neural_fields::occupancy::{onet_decoder, NormMode, OnetConfig};
use neural_fields::rng::SplitMix64;

fn config() -> OnetConfig {
    OnetConfig {
        hidden: 32,
        blocks: 2,
        code_dim: 8,
        ..OnetConfig::default()
    }
}

#[test]
fn inference_is_bit_identical_alone_or_among_ten_thousand_points() {
    for dtype in [DType::F32, DType::F64] {
        let vm = VarMap::new();
        let net = build_seeded(&vm, dtype, &Device::Cpu, 1, |vb| {
            onet_decoder(&config(), vb)
        })
        .unwrap();
        let mut rng = SplitMix64::new(2);
        // Move the running statistics away from (0, 1) with a few training-mode calls.
        net.set_mode(NormMode::Train);
        for _ in 0..3 {
            let p = common::uniform(&mut rng, 512, 3, -0.5, 0.5, dtype);
            let c = common::uniform(&mut rng, 512, 8, -1.0, 1.0, dtype);
            let _ = net.logits(&p, &c).unwrap();
        }
        net.set_mode(NormMode::Eval);
        let n = 10_001;
        let p = common::uniform(&mut rng, n, 3, -0.5, 0.5, dtype);
        let code = common::uniform(&mut rng, 1, 8, -1.0, 1.0, dtype);
        let codes = code.broadcast_as((n, 8)).unwrap().contiguous().unwrap();
        let all = common::v64(&net.logits(&p, &codes).unwrap());
        for &i in &[0usize, 255, 256, 5000, 10_000] {
            let one = common::v64(&net.logits(&p.narrow(0, i, 1).unwrap(), &code).unwrap());
            assert_eq!(one[0].to_bits(), all[i].to_bits(), "{dtype:?} point {i}");
        }
        // A different neighbourhood: the same point in a batch of 300 others.
        let mid = Tensor::cat(
            &[
                &p.narrow(0, 100, 300).unwrap(),
                &p.narrow(0, 5000, 1).unwrap(),
            ],
            0,
        )
        .unwrap();
        let c301 = code.broadcast_as((301, 8)).unwrap().contiguous().unwrap();
        let some = common::v64(&net.logits(&mid, &c301).unwrap());
        assert_eq!(some[300].to_bits(), all[5000].to_bits());
        // In training mode the batch statistics make outputs depend on the batch.
        net.set_mode(NormMode::Train);
        let a = common::v64(
            &net.logits(
                &p.narrow(0, 0, 64).unwrap(),
                &codes.narrow(0, 0, 64).unwrap(),
            )
            .unwrap(),
        );
        let b = common::v64(
            &net.logits(
                &p.narrow(0, 0, 128).unwrap(),
                &codes.narrow(0, 0, 128).unwrap(),
            )
            .unwrap(),
        );
        assert_ne!(a[0], b[0]);
    }
}

#[test]
fn spatial_gradient_matches_finite_differences_and_reaches_the_code() {
    let vm = VarMap::new();
    let net = build_seeded(&vm, DType::F64, &Device::Cpu, 4, |vb| {
        onet_decoder(&config(), vb)
    })
    .unwrap();
    let mut rng = SplitMix64::new(9);
    // Non-trivial fc1 and γ/β: perturb every variable.
    for v in common::sorted_vars(&vm) {
        let noise =
            common::normal_tensor(&mut rng, v.dims(), 0.0, 0.3, DType::F64, &Device::Cpu).unwrap();
        v.set(&(v.as_tensor() + noise).unwrap()).unwrap();
    }
    let p = common::uniform(&mut rng, 20, 3, -0.5, 0.5, DType::F64);
    let c = common::uniform(&mut rng, 20, 8, -1.0, 1.0, DType::F64);
    let (v, g) = net.value_and_grad_with_code(&p, &c).unwrap();
    assert_eq!(common::v64(&v), common::v64(&net.logits(&p, &c).unwrap()));
    let g = common::v64(&g);
    let pv = common::v64(&p);
    let h = 1e-6;
    for i in 0..20 {
        for k in 0..3 {
            let mut a = pv.clone();
            let mut b = pv.clone();
            a[3 * i + k] += h;
            b[3 * i + k] -= h;
            let fa = common::v64(
                &net.logits(&Tensor::from_vec(a, (20, 3), &Device::Cpu).unwrap(), &c)
                    .unwrap(),
            )[i];
            let fb = common::v64(
                &net.logits(&Tensor::from_vec(b, (20, 3), &Device::Cpu).unwrap(), &c)
                    .unwrap(),
            )[i];
            let num = (fa - fb) / (2.0 * h);
            // ReLU kinks: skip points where a unit switches within ±h (rare).
            if (g[3 * i + k] - num).abs() > 1e-5 * (1.0 + num.abs()) {
                assert!(
                    (g[3 * i + k] - num).abs() < 0.05 * (1.0 + num.abs()),
                    "{i},{k}: {} vs {num}",
                    g[3 * i + k]
                );
            }
        }
    }
    assert_eq!(net.code_dim(), 8);
    assert!(onet_decoder(
        &OnetConfig {
            hidden: 0,
            ..config()
        },
        candle_nn::VarBuilder::from_varmap(&VarMap::new(), DType::F32, &Device::Cpu)
    )
    .is_err());
    let e = net
        .logits(&p, &c.narrow(0, 0, 3).unwrap())
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("codes"), "{e}");
}

/// `logits` with one code per shape (`[B, Q, 3]`, `[B, D]`) is `logits` with the code
/// repeated per point: values, parameter, code and point gradients, in both
/// normalisation modes (f64).
#[test]
fn grouped_codes_match_codes_repeated_per_point() {
    let vm = VarMap::new();
    let net = build_seeded(&vm, DType::F64, &Device::Cpu, 2, |vb| {
        onet_decoder(&config(), vb)
    })
    .unwrap();
    let mut rng = SplitMix64::new(5);
    let (b, q) = (3, 7);
    let pts = candle_core::Var::from_tensor(
        &rng.uniform_tensor(&[b, q, 3], -0.5, 0.5, DType::F64, &Device::Cpu)
            .unwrap(),
    )
    .unwrap();
    let codes = candle_core::Var::from_tensor(
        &rng.uniform_tensor(&[b, 8], -1.0, 1.0, DType::F64, &Device::Cpu)
            .unwrap(),
    )
    .unwrap();
    let w = rng
        .uniform_tensor(&[b, q], -1.0, 1.0, DType::F64, &Device::Cpu)
        .unwrap();
    for mode in [NormMode::Train, NormMode::Eval] {
        net.set_mode(mode);
        let grouped = net.logits(&pts, &codes).unwrap();
        let repeated = codes
            .unsqueeze(1)
            .unwrap()
            .broadcast_as((b, q, 8))
            .unwrap()
            .reshape((b * q, 8))
            .unwrap();
        let flat = net
            .logits(&pts.reshape((b * q, 3)).unwrap(), &repeated)
            .unwrap()
            .reshape((b, q))
            .unwrap();
        let diff = |a: &Tensor, c: &Tensor| -> f64 {
            (a - c)
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f64>()
                .unwrap()
        };
        assert!(diff(&grouped, &flat) < 1e-12, "{mode:?}: values differ");
        let ga = (&grouped * &w)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let gb = (&flat * &w).unwrap().sum_all().unwrap().backward().unwrap();
        let vars: Vec<candle_core::Var> = vm.all_vars();
        for v in vars.iter().chain([&pts, &codes]) {
            let (a, c) = (ga.get(v).unwrap(), gb.get(v).unwrap());
            assert!(diff(a, c) < 1e-10, "{mode:?}: gradients differ");
        }
    }
    // A batch that does not split into the codes' shapes is refused naming it.
    let bad = Tensor::zeros((2, 0, 3), DType::F64, &Device::Cpu).unwrap();
    assert!(net.logits(&bad, &codes).is_err());
    assert!(net.logits(&pts, &codes.narrow(0, 0, 2).unwrap()).is_err());
}

/// A `[D]` code bound by `Conditioned` (a stride-0 broadcast over the points) enters the
/// decoder once; its logits, spatial gradients and parameter and code gradients equal
/// those of the same code copied into every row (f32 and f64, both modes).
#[test]
fn shared_code_once_equals_code_copied_per_point() {
    use neural_fields::field::{Conditioned, ImplicitSurface};
    for dtype in [DType::F32, DType::F64] {
        let vm = VarMap::new();
        let net = build_seeded(&vm, dtype, &Device::Cpu, 3, |vb| {
            onet_decoder(&config(), vb)
        })
        .unwrap();
        let mut rng = SplitMix64::new(9);
        let n = 33;
        let pts = rng
            .uniform_tensor(&[n, 3], -0.5, 0.5, dtype, &Device::Cpu)
            .unwrap();
        let code = candle_core::Var::from_tensor(
            &rng.uniform_tensor(&[8], -1.0, 1.0, dtype, &Device::Cpu)
                .unwrap(),
        )
        .unwrap();
        let tol = if dtype == DType::F64 { 1e-12 } else { 1e-5 };
        let diff = |a: &Tensor, c: &Tensor| -> f64 {
            (a - c)
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_dtype(DType::F64)
                .unwrap()
                .to_scalar::<f64>()
                .unwrap()
        };
        for mode in [NormMode::Train, NormMode::Eval] {
            net.set_mode(mode);
            let copied = code
                .unsqueeze(0)
                .unwrap()
                .broadcast_as((n, 8))
                .unwrap()
                .contiguous()
                .unwrap();
            let surface = Conditioned::new(&net, code.as_tensor().clone()).unwrap();
            let (v_shared, g_shared) = surface.value_and_grad(&pts).unwrap();
            let (v_copied, g_copied) = net.value_and_grad_with_code(&pts, &copied).unwrap();
            assert!(diff(&v_shared, &v_copied) < tol, "{mode:?}: values differ");
            assert!(diff(&g_shared, &g_copied) < tol, "{mode:?}: ∇p differs");
            let ga = surface
                .value(&pts)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            let gb = net
                .logits(&pts, &copied)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            for v in vm.all_vars().iter().chain([&code]) {
                let (a, c) = (ga.get(v).unwrap(), gb.get(v).unwrap());
                assert!(diff(a, c) < 100.0 * tol, "{mode:?}: gradients differ");
            }
        }
    }
}

/// The decoder's `[B, Q]` logits in training mode, its variables and the inputs, for
/// the fused-against-reference comparison (`force_reference` picks the path).
fn training_pass(
    dtype: DType,
    force_reference: bool,
    (b, q): (usize, usize),
) -> (VarMap, neural_fields::occupancy::OnetDecoder, Var, Var) {
    let config = OnetConfig {
        force_reference,
        ..config()
    };
    let vm = VarMap::new();
    let net = build_seeded(&vm, dtype, &Device::Cpu, 3, |vb| onet_decoder(&config, vb)).unwrap();
    // Scales and shifts away from their (1, 0) start, so every code moves them.
    common::reseed(&vm, 4, 1.0);
    let mut rng = SplitMix64::new(6);
    let p = Var::from_tensor(
        &rng.uniform_tensor(&[b, q, 3], -0.5, 0.5, dtype, &Device::Cpu)
            .unwrap(),
    )
    .unwrap();
    let c = Var::from_tensor(
        &rng.uniform_tensor(&[b, 8], -1.0, 1.0, dtype, &Device::Cpu)
            .unwrap(),
    )
    .unwrap();
    net.set_mode(NormMode::Train);
    (vm, net, p, c)
}

/// The fused training pass (the whole decoder as one CPU op) gives the reference candle
/// ops' logits, gradients of every variable, the points and the codes, and running
/// statistics, in f32 and f64, with one code per shape (groups that straddle the kernel's
/// row tiles, and batches of more than one gradient chunk of rows) and one code per point,
/// after a first pass on a larger batch (whose row buffers the compared pass reuses,
/// holding that pass's values).
#[test]
fn fused_training_pass_matches_the_reference_ops() {
    for dtype in [DType::F64, DType::F32] {
        let tol = if dtype == DType::F64 { 1e-10 } else { 2e-4 };
        for (b, q, grouped) in [(3, 301, true), (2, 200, false), (2, 1100, true)] {
            let mut parts: Vec<Vec<Vec<f64>>> = Vec::new();
            for force_reference in [false, true] {
                let (vm, net, p, c) = training_pass(dtype, force_reference, (b, q));
                let (pw, cw) = (
                    SplitMix64::new(9)
                        .uniform_tensor(&[b + 1, q + 7, 3], -0.5, 0.5, dtype, &Device::Cpu)
                        .unwrap(),
                    SplitMix64::new(10)
                        .uniform_tensor(&[b + 1, 8], -1.0, 1.0, dtype, &Device::Cpu)
                        .unwrap(),
                );
                let warm = net.logits(&pw, &cw).unwrap();
                warm.sqr().unwrap().sum_all().unwrap().backward().unwrap();
                let logits = if grouped {
                    net.logits(&p, &c).unwrap()
                } else {
                    let codes = c.unsqueeze(1).unwrap().broadcast_as((b, q, 8)).unwrap();
                    let codes = codes.reshape((b * q, 8)).unwrap();
                    net.logits(&p.reshape((b * q, 3)).unwrap(), &codes).unwrap()
                };
                let w = SplitMix64::new(7)
                    .uniform_tensor(logits.dims(), -1.0, 1.0, dtype, &Device::Cpu)
                    .unwrap();
                let grads = (&logits * &w)
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .backward()
                    .unwrap();
                let mut part = vec![common::v64(&logits)];
                for v in common::sorted_vars(&vm).iter().chain([&p, &c]) {
                    part.push(common::v64(grads.get(v).unwrap()));
                }
                // The running statistics, through inference-mode logits.
                net.set_mode(NormMode::Eval);
                part.push(common::v64(&net.logits(&p, &c).unwrap()));
                parts.push(part);
            }
            let what = format!("{dtype:?}, {b} × {q}, grouped {grouped}");
            if dtype == DType::F64 {
                common::assert_parts_close(&parts[0], &parts[1], tol, &what);
                continue;
            }
            // In f32, against the largest entry of all: a bias that feeds a normalisation
            // has a zero gradient, which f32 round-off leaves at ~1e-6 in either path.
            let all = parts[1]
                .iter()
                .flatten()
                .fold(0.0f64, |m, v| m.max(v.abs()));
            for (k, (x, y)) in parts[0].iter().zip(&parts[1]).enumerate() {
                for (i, (u, v)) in x.iter().zip(y).enumerate() {
                    assert!(
                        (u - v).abs() <= tol * all,
                        "{what}: part {k}[{i}]: {u} vs {v}"
                    );
                }
            }
        }
    }
}

/// The fused training pass's gradients of `Σ w ⊙ logits` against central finite
/// differences in f64 (entries of every variable, the points and the codes), with the
/// points at scales from 1e-4 (a batch variance far below `ε`, where the normalisation
/// divides by about `√ε`) to 1e3.
#[test]
fn fused_training_pass_gradients_match_finite_differences_in_f64() {
    let mut tally = common::FdTally::default();
    for (k, scale) in [1e-4, 1.0, 1e3].into_iter().enumerate() {
        let (vm, net, p, c) = training_pass(DType::F64, false, (2, 150));
        p.set(&(p.as_tensor() * scale).unwrap()).unwrap();
        let w = SplitMix64::new(8 + k as u64)
            .uniform_tensor(&[2, 150], -1.0, 1.0, DType::F64, &Device::Cpu)
            .unwrap();
        let loss = || -> f64 {
            let l = net.logits(&p, &c).unwrap();
            common::v64(&(l * &w).unwrap().sum_all().unwrap())[0]
        };
        let grads = (net.logits(&p, &c).unwrap() * &w)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let mut targets = common::sorted_vars(&vm);
        targets.extend([p.clone(), c.clone()]);
        for (t, var) in targets.iter().enumerate() {
            let g = common::v64(grads.get(var).unwrap());
            let values = common::v64(var.as_tensor());
            let gscale = g.iter().fold(1e-3f64, |m, v| m.max(v.abs()));
            let i = (t * 7919 + 13 * k) % values.len();
            let x0 = values[i];
            let h = 1e-6
                * x0.abs()
                    .max(if var.dims() == p.dims() { scale } else { 1.0 });
            let mut f = |x: f64| {
                common::set_entry(var, i, x);
                loss()
            };
            let fd = common::central_diff_bound(&mut f, x0, h, gscale);
            common::set_entry(var, i, x0);
            // The tolerance grows by the estimate's own error bar.
            let bar = fd.map_or(0.0, |(_, bar)| bar);
            tally.check(g[i], fd.map(|(d, _)| d), 1e-5 * gscale + bar, &|| {
                format!("scale {scale}, target {t}[{i}]")
            });
        }
    }
    let common::FdTally { checked, skipped } = tally;
    println!("{checked} entries checked, {skipped} skipped at kinks");
    assert!(
        checked >= 4 * skipped,
        "{checked} checked, {skipped} at kinks"
    );
}
