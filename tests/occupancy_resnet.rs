//! `occupancy::ResnetEncoder`: code shapes at 64² and 128², f32 and f64; gradients that
//! reach every weight, finite, and equal to finite differences in f64; the running
//! statistics (updated in training, the only statistics at inference, so an image's code
//! does not depend on its batch); a few Adam steps that learn a small task; argument
//! errors naming `images` or the configuration.
#![cfg(feature = "occupancy")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{Optimizer, VarBuilder, VarMap};
use common::{assert_parts_close, central_diff, normal_tensor, v64};
use neural_fields::nn::{adam, build_seeded};
use neural_fields::occupancy::{resnet_encoder, ResnetEncoder, ResnetEncoderConfig};
use neural_fields::rng::SplitMix64;

/// A tiny network: width 4, one block per stage (stage 1 identity shortcuts, stages
/// 2–4 projections).
fn tiny(c_dim: usize) -> ResnetEncoderConfig {
    ResnetEncoderConfig {
        width: 4,
        blocks: [1, 1, 1, 1],
        c_dim,
        ..ResnetEncoderConfig::default()
    }
}

fn build(config: &ResnetEncoderConfig, dtype: DType, seed: u64) -> (VarMap, ResnetEncoder) {
    let varmap = VarMap::new();
    let enc = build_seeded(&varmap, dtype, &Device::Cpu, seed, |vb| {
        resnet_encoder(config, vb)
    })
    .unwrap();
    (varmap, enc)
}

fn images(rng: &mut SplitMix64, b: usize, h: usize, w: usize, dtype: DType) -> Tensor {
    normal_tensor(rng, &[b, 3, h, w], 0.0, 1.0, dtype, &Device::Cpu).unwrap()
}

fn is_statistic(name: &str) -> bool {
    name.ends_with("running_mean") || name.ends_with("running_var")
}

#[test]
fn codes_are_b_by_c_dim_at_64_and_128_in_f32_and_f64() {
    let mut rng = SplitMix64::new(1);
    for dtype in [DType::F32, DType::F64] {
        let config = ResnetEncoderConfig {
            width: 8,
            c_dim: 32,
            ..ResnetEncoderConfig::default()
        };
        let (_vm, enc) = build(&config, dtype, 2);
        for (b, h, w) in [
            (1, 64, 64),
            (3, 64, 64),
            (1, 128, 128),
            (3, 128, 128),
            (2, 32, 96),
        ] {
            let x = images(&mut rng, b, h, w, dtype);
            for train in [false, true] {
                let c = enc.forward(&x, train).unwrap();
                assert_eq!(c.dims(), &[b, 32], "{dtype:?} {b}×{h}×{w} train {train}");
                assert_eq!(c.dtype(), dtype);
                assert!(v64(&c).iter().all(|v| v.is_finite()));
            }
        }
    }
    // The default network (ResNet-18's blocks at width 32, c_dim 256).
    let (_vm, enc) = build(&ResnetEncoderConfig::default(), DType::F32, 3);
    let x = images(&mut rng, 2, 64, 64, DType::F32);
    assert_eq!(enc.forward(&x, true).unwrap().dims(), &[2, 256]);
}

#[test]
fn the_default_has_resnet18s_variables_at_half_width() {
    let (varmap, _enc) = build(&ResnetEncoderConfig::default(), DType::F32, 0);
    let data = varmap.data().lock().unwrap();
    let dims = |name: &str| data[name].dims().to_vec();
    assert_eq!(dims("conv1.weight"), [32, 3, 7, 7]);
    assert_eq!(dims("layer1.1.conv2.weight"), [32, 32, 3, 3]);
    assert_eq!(dims("layer2.0.conv1.weight"), [64, 32, 3, 3]);
    assert_eq!(dims("layer2.0.downsample.0.weight"), [64, 32, 1, 1]);
    assert_eq!(dims("layer4.1.bn2.running_var"), [256]);
    assert_eq!(dims("fc.weight"), [256, 256]);
    assert!(!data.contains_key("layer1.0.downsample.0.weight"));
    let params: usize = data
        .iter()
        .filter(|(k, _)| !is_statistic(k))
        .map(|(_, v)| v.elem_count())
        .sum();
    // ResNet-18 has 11.2 M weights without its classifier; half the width, a quarter.
    assert!((2_700_000..2_900_000).contains(&params), "{params}");
}

#[test]
fn gradients_reach_every_weight_and_the_images_and_are_finite() {
    for dtype in [DType::F32, DType::F64] {
        let (varmap, enc) = build(&tiny(5), dtype, 4);
        let mut rng = SplitMix64::new(5);
        // 67 × 48: the height odd and the width even at every stride-2 convolution.
        let x = Var::from_tensor(&images(&mut rng, 3, 67, 48, dtype)).unwrap();
        let r = normal_tensor(&mut rng, &[3, 5], 0.0, 1.0, dtype, &Device::Cpu).unwrap();
        for train in [true, false] {
            let loss = (enc.forward(x.as_tensor(), train).unwrap() * &r)
                .unwrap()
                .sum_all()
                .unwrap();
            let grads = loss.backward().unwrap();
            let data = varmap.data().lock().unwrap();
            let mut weights = 0;
            for (name, var) in data.iter() {
                if is_statistic(name) {
                    assert!(grads.get(var).is_none(), "{name} is not trained");
                    continue;
                }
                weights += 1;
                let g = v64(grads
                    .get(var)
                    .unwrap_or_else(|| panic!("no gradient for {name}")));
                assert!(g.iter().all(|v| v.is_finite()), "{name}: {g:?}");
                assert!(
                    g.iter().any(|v| *v != 0.0),
                    "{name}: all zero ({dtype:?}, train {train})"
                );
            }
            // conv1 + bn1, 4 blocks × (2 convs + 2 BN), 3 projections × (conv + BN), fc.
            assert_eq!(weights, 3 + 4 * 6 + 3 * 3 + 2);
            let gx = v64(grads.get(&x).unwrap());
            assert!(gx.iter().all(|v| v.is_finite()) && gx.iter().any(|v| *v != 0.0));
        }
    }
}

/// The running statistics follow `r ← (1 − m)·r + m·stat` in training and are the only
/// statistics at inference: the same image in two different batches gets the same code,
/// which the batch statistics of training would not give it.
#[test]
fn inference_uses_the_running_statistics_so_codes_do_not_depend_on_the_batch() {
    let (varmap, enc) = build(&tiny(6), DType::F64, 6);
    let mut rng = SplitMix64::new(7);
    let x = images(&mut rng, 4, 64, 64, DType::F64);
    let stat = |name: &str| v64(varmap.data().lock().unwrap()[name].as_tensor());
    assert!(stat("bn1.running_mean").iter().all(|v| *v == 0.0));
    enc.forward(&x, true).unwrap();
    // bn1 sees conv1's output: its running mean moved to 0.1 × the batch's channel mean.
    let w = varmap.data().lock().unwrap()["conv1.weight"]
        .as_tensor()
        .clone();
    let y = x.conv2d(&w, 3, 2, 1, 1).unwrap();
    let mean = v64(&y.mean(3).unwrap().mean(2).unwrap().mean(0).unwrap());
    let n = (y.elem_count() / 4) as f64;
    let var = v64(&y
        .broadcast_sub(
            &Tensor::new(mean.as_slice(), &Device::Cpu)
                .unwrap()
                .reshape((1, 4, 1, 1))
                .unwrap(),
        )
        .unwrap()
        .sqr()
        .unwrap()
        .mean(3)
        .unwrap()
        .mean(2)
        .unwrap()
        .mean(0)
        .unwrap());
    for (k, (rm, rv)) in stat("bn1.running_mean")
        .iter()
        .zip(stat("bn1.running_var"))
        .enumerate()
    {
        assert!(
            (rm - 0.1 * mean[k]).abs() < 1e-12,
            "{rm} vs {}",
            0.1 * mean[k]
        );
        let unbiased = var[k] * n / (n - 1.0);
        assert!((rv - (0.9 + 0.1 * unbiased)).abs() < 1e-12, "{rv}");
    }
    for _ in 0..4 {
        enc.forward(&x, true).unwrap();
    }
    let before = stat("layer3.0.bn2.running_var");

    let other = (images(&mut rng, 3, 64, 64, DType::F64) * 5.0).unwrap();
    let a = Tensor::cat(&[&x.narrow(0, 0, 2).unwrap(), &other], 0).unwrap(); // image 0 first
    let b = Tensor::cat(
        &[&other.narrow(0, 0, 1).unwrap(), &x.narrow(0, 0, 1).unwrap()],
        0,
    )
    .unwrap(); // image 0 last
    let code =
        |t: &Tensor, i: usize, train: bool| v64(&enc.forward(t, train).unwrap().get(i).unwrap());
    let (ca, cb) = (code(&a, 0, false), code(&b, 1, false));
    for (p, q) in ca.iter().zip(&cb) {
        assert!((p - q).abs() <= 1e-12 * (1.0 + p.abs()), "{p} vs {q}");
    }
    assert_eq!(code(&a, 0, false), ca, "inference is deterministic");
    assert_eq!(
        stat("layer3.0.bn2.running_var"),
        before,
        "inference updates nothing"
    );
    // In training the batch's statistics change the same image's code.
    let (ta, tb) = (code(&a, 0, true), code(&b, 1, true));
    let gap = ta
        .iter()
        .zip(&tb)
        .map(|(p, q)| (p - q).abs())
        .fold(0.0, f64::max);
    assert!(gap > 1e-3, "training codes depend on the batch: {gap}");
}

/// Thirty Adam steps on a small task (the mean colour of noisy images of a random
/// colour; batch statistics in training) lower the training loss, and, once the running
/// statistics have caught up with the trained weights, bring the held-out error in
/// inference well below that of the untrained network and of predicting zero.
#[test]
fn adam_steps_learn_the_mean_colour_of_images() {
    let dtype = DType::F32;
    let config = ResnetEncoderConfig {
        width: 8,
        c_dim: 3,
        ..ResnetEncoderConfig::default()
    };
    let (varmap, enc) = build(&config, dtype, 8);
    let mut rng = SplitMix64::new(9);
    let mut batch = |b: usize| {
        let colour = normal_tensor(&mut rng, &[b, 3], 0.0, 1.0, dtype, &Device::Cpu).unwrap();
        let noise =
            normal_tensor(&mut rng, &[b, 3, 32, 32], 0.0, 0.5, dtype, &Device::Cpu).unwrap();
        let x = noise
            .broadcast_add(&colour.reshape((b, 3, 1, 1)).unwrap())
            .unwrap();
        let target = x.mean(3).unwrap().mean(2).unwrap();
        (x, target)
    };
    let mse = |c: &Tensor, t: &Tensor| (c - t).unwrap().sqr().unwrap().mean_all().unwrap();
    let (test_x, test_t) = batch(64);
    let error = || v64(&mse(&enc.forward(&test_x, false).unwrap(), &test_t))[0];
    let zero = v64(&test_t.sqr().unwrap().mean_all().unwrap())[0];
    // Training passes without a step move the running statistics to the weights' own.
    let calibrate = |batch: &mut dyn FnMut(usize) -> (Tensor, Tensor)| {
        for _ in 0..10 {
            enc.forward(&batch(16).0, true).unwrap();
        }
    };
    calibrate(&mut batch);
    let untrained = error();
    let mut opt = adam(&varmap, 1e-2).unwrap();
    let mut losses = Vec::new();
    for _ in 0..30 {
        let (x, t) = batch(16);
        let loss = mse(&enc.forward(&x, true).unwrap(), &t);
        losses.push(v64(&loss)[0]);
        opt.backward_step(&loss).unwrap();
    }
    calibrate(&mut batch);
    let trained = error();
    println!("held out: untrained {untrained:.4}, zero {zero:.4}, trained {trained:.4}");
    println!("training losses {losses:.3?}");
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(mean(&losses[25..]) < 0.5 * mean(&losses[..5]), "{losses:?}");
    assert!(
        trained < 0.5 * untrained.min(zero),
        "{trained} vs {untrained}, {zero}"
    );
}

#[test]
fn bad_images_are_refused_naming_images() {
    let (_vm, enc) = build(&tiny(2), DType::F32, 10);
    let d = Device::Cpu;
    let z = |shape: &[usize]| Tensor::zeros(shape, DType::F32, &d).unwrap();
    let nan = Tensor::cat(
        &[
            &z(&[1, 3, 32, 32]),
            &Tensor::full(f32::NAN, (1, 3, 32, 32), &d).unwrap(),
        ],
        0,
    )
    .unwrap();
    let inf = Tensor::full(f32::INFINITY, (2, 3, 32, 32), &d).unwrap();
    let cases: Vec<(Tensor, bool, &str)> = vec![
        (z(&[3, 32, 32]), false, "shape [B, 3, H, W]"),
        (z(&[2, 1, 32, 32]), false, "shape [B, 3, H, W]"),
        (z(&[2, 4, 64, 64]), false, "shape [B, 3, H, W]"),
        (z(&[0, 3, 64, 64]), false, "at least one image"),
        (z(&[2, 3, 31, 64]), false, "at least 32 pixels"),
        (z(&[2, 3, 64, 16]), false, "at least 32 pixels"),
        (nan, false, "finite values"),
        (inf, true, "finite values"),
        (
            z(&[2, 3, 32, 32]).to_dtype(DType::F64).unwrap(),
            false,
            "dtype F32",
        ),
        (
            z(&[2, 3, 32, 32]).to_dtype(DType::U32).unwrap(),
            false,
            "dtype f32 or f64",
        ),
        (z(&[1, 3, 32, 32]), true, "at least two values per channel"),
    ];
    for (x, train, msg) in cases {
        let e = enc.forward(&x, train).unwrap_err().to_string();
        assert!(e.starts_with("images: expected ") && e.contains(msg), "{e}");
    }
    // One 32 × 32 image in inference, or one 32 × 64 in training, is fine.
    assert!(enc.forward(&z(&[1, 3, 32, 32]), false).is_ok());
    assert!(enc.forward(&z(&[1, 3, 32, 64]), true).is_ok());
}

#[test]
fn bad_configurations_are_refused_naming_the_field() {
    let vb = || VarBuilder::zeros(DType::F32, &Device::Cpu);
    let cases = [
        (
            ResnetEncoderConfig {
                in_channels: 0,
                ..tiny(2)
            },
            "config.in_channels",
        ),
        (
            ResnetEncoderConfig {
                width: 0,
                ..tiny(2)
            },
            "config.width",
        ),
        (
            ResnetEncoderConfig {
                c_dim: 0,
                ..tiny(2)
            },
            "config.c_dim",
        ),
        (
            ResnetEncoderConfig {
                blocks: [2, 0, 2, 2],
                ..tiny(2)
            },
            "config.blocks",
        ),
        (
            ResnetEncoderConfig {
                momentum: 1.5,
                ..tiny(2)
            },
            "config.momentum",
        ),
        (
            ResnetEncoderConfig {
                eps: 0.0,
                ..tiny(2)
            },
            "config.eps",
        ),
        (
            ResnetEncoderConfig {
                eps: f64::NAN,
                ..tiny(2)
            },
            "config.eps",
        ),
        (
            ResnetEncoderConfig {
                width: 1 << 20,
                ..tiny(2)
            },
            "config.width",
        ),
        (
            ResnetEncoderConfig {
                width: usize::MAX,
                ..tiny(2)
            },
            "config.width",
        ),
        (
            ResnetEncoderConfig {
                blocks: [1, 1, 1, 1 << 30],
                ..tiny(2)
            },
            "config.blocks",
        ),
        (
            ResnetEncoderConfig {
                c_dim: 1 << 40,
                ..tiny(2)
            },
            "config.c_dim",
        ),
    ];
    for (config, name) in cases {
        let e = resnet_encoder(&config, vb()).unwrap_err().to_string();
        assert!(e.starts_with(&format!("{name}: expected")), "{e}");
    }
}

/// Backpropagated gradients of `Σ R ⊙ c` against central finite differences in f64, for
/// entries of the stem, a projection shortcut, a second-stage convolution, batch-norm
/// scales and shifts, `fc`, and the pixels, in training (batch statistics) and in
/// inference (running statistics, after a few training passes moved them).
#[test]
fn gradients_match_finite_differences_in_f64() {
    let (varmap, enc) = build(&tiny(3), DType::F64, 11);
    let mut rng = SplitMix64::new(12);
    let x = Var::from_tensor(&images(&mut rng, 2, 33, 40, DType::F64)).unwrap();
    let r = normal_tensor(&mut rng, &[2, 3], 0.0, 1.0, DType::F64, &Device::Cpu).unwrap();
    for _ in 0..3 {
        enc.forward(x.as_tensor(), true).unwrap();
    }
    let loss = |train: bool| -> f64 {
        let c = enc.forward(x.as_tensor(), train).unwrap();
        v64(&(c * &r).unwrap().sum_all().unwrap())[0]
    };
    let vars: Vec<(String, Var)> = {
        let data = varmap.data().lock().unwrap();
        [
            "conv1.weight",
            "bn1.weight",
            "layer1.0.conv2.weight",
            "layer2.0.conv1.weight",
            "layer2.0.downsample.0.weight",
            "layer3.0.bn1.bias",
            "layer4.0.bn2.weight",
            "fc.weight",
            "fc.bias",
        ]
        .iter()
        .map(|n| (n.to_string(), data[*n].clone()))
        .collect()
    };
    let mut tally = common::FdTally::default();
    for train in [true, false] {
        let grads = (enc.forward(x.as_tensor(), train).unwrap() * &r)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let mut targets: Vec<(String, Var)> = vars.clone();
        targets.push(("images".to_string(), x.clone()));
        for (name, var) in &targets {
            let g = v64(grads.get(var).unwrap());
            let values = v64(var.as_tensor());
            let scale = g.iter().fold(1e-3f64, |m, v| m.max(v.abs()));
            for k in 0..3 {
                let i = (k * 7919 + 13) % values.len();
                let x0 = values[i];
                let mut f = |t: f64| {
                    common::set_entry(var, i, t);
                    loss(train)
                };
                let fd = central_diff(&mut f, x0, 1e-6, scale);
                common::set_entry(var, i, x0);
                tally.check(g[i], fd, 1e-6 * scale, &|| {
                    format!("{name}[{i}] train {train}")
                });
            }
        }
    }
    let common::FdTally { checked, skipped } = tally;
    println!("{checked} entries checked, {skipped} skipped at kinks");
    assert!(
        checked >= 4 * skipped,
        "{checked} checked, {skipped} at kinks"
    );
}

/// The fused channels-last convolutions (the default on the CPU) and candle-nn's `Conv2d`
/// on `[B, C, H, W]` (`force_reference`) compute the same function: codes, the gradient of
/// every weight and of the images, and the running statistics after training passes, in
/// f64 to 1e-10 and in f32 relative to the largest entry; square and odd, unequal sides.
#[test]
fn fused_convolutions_match_the_reference_path() {
    for (dtype, tol) in [(DType::F64, 1e-10), (DType::F32, 2e-4)] {
        for (b, h, w) in [(3, 64, 64), (2, 33, 47)] {
            let config = ResnetEncoderConfig {
                width: 4,
                blocks: [2, 1, 1, 1],
                c_dim: 5,
                ..ResnetEncoderConfig::default()
            };
            let reference = ResnetEncoderConfig {
                force_reference: true,
                ..config.clone()
            };
            let (vm_f, fused) = build(&config, dtype, 21);
            let (vm_r, plain) = build(&reference, dtype, 21);
            let mut rng = SplitMix64::new(22);
            let x = Var::from_tensor(&images(&mut rng, b, h, w, dtype)).unwrap();
            let r = normal_tensor(&mut rng, &[b, 5], 0.0, 1.0, dtype, &Device::Cpu).unwrap();
            let close = |what: &str, a: &[f64], e: &[f64]| {
                let what = format!("{what} ({dtype:?}, {b}×{h}×{w})");
                assert_parts_close(&[a.to_vec()], &[e.to_vec()], tol, &what);
            };
            for train in [true, false] {
                let run = |enc: &ResnetEncoder| {
                    let codes = enc.forward(x.as_tensor(), train).unwrap();
                    let grads = (&codes * &r)
                        .unwrap()
                        .sum_all()
                        .unwrap()
                        .backward()
                        .unwrap();
                    (codes, grads)
                };
                let (cf, gf) = run(&fused);
                let (cr, gr) = run(&plain);
                close("codes", &v64(&cf), &v64(&cr));
                close(
                    "images' gradient",
                    &v64(gf.get(&x).unwrap()),
                    &v64(gr.get(&x).unwrap()),
                );
                let (df, dr) = (vm_f.data().lock().unwrap(), vm_r.data().lock().unwrap());
                for (name, var) in df.iter() {
                    let other = &dr[name];
                    if is_statistic(name) {
                        close(name, &v64(var.as_tensor()), &v64(other.as_tensor()));
                        continue;
                    }
                    let what = format!("{name}'s gradient, train {train}");
                    close(
                        &what,
                        &v64(gf.get(var).unwrap()),
                        &v64(gr.get(other).unwrap()),
                    );
                }
            }
        }
    }
}
