//! `occupancy::VoxelEncoder`: code shapes for both input layouts, f32 and f64; ONet's
//! variables at the default; gradients that reach every variable and the voxels, finite,
//! and equal to finite differences in f64; codes that see where a shape is; a few Adam
//! steps that learn a small task; argument errors naming `voxels` or the configuration.
#![cfg(feature = "occupancy")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{Optimizer, VarBuilder, VarMap};
use common::{assert_parts_close, central_diff, normal_tensor, v64};
use neural_fields::nn::{adam, build_seeded};
use neural_fields::occupancy::{voxel_encoder, VoxelEncoder, VoxelEncoderConfig};
use neural_fields::rng::SplitMix64;

/// A tiny network: 8³ grids, 4 → 8 → 16 channels at 8³ → 4³ → 2³.
fn tiny(c_dim: usize) -> VoxelEncoderConfig {
    VoxelEncoderConfig {
        base_channels: 4,
        stages: 2,
        c_dim,
        resolution: 8,
        force_reference: false,
    }
}

fn build(config: &VoxelEncoderConfig, dtype: DType, seed: u64) -> (VarMap, VoxelEncoder) {
    let varmap = VarMap::new();
    let enc = build_seeded(&varmap, dtype, &Device::Cpu, seed, |vb| {
        voxel_encoder(config, vb)
    })
    .unwrap();
    (varmap, enc)
}

/// `B` random binary grids of side `r` (each voxel filled with probability ½).
fn binary(rng: &mut SplitMix64, b: usize, r: usize, dtype: DType) -> Tensor {
    let v: Vec<f64> = (0..b * r * r * r)
        .map(|_| if rng.uniform() < 0.5 { 1.0 } else { 0.0 })
        .collect();
    Tensor::from_vec(v, (b, r, r, r), &Device::Cpu)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

/// A grid of side `r` filled on the box `lo ≤ (i, j, k) < hi`.
fn boxed(r: usize, lo: [usize; 3], hi: [usize; 3]) -> Vec<f64> {
    let mut v = vec![0.0; r * r * r];
    for i in lo[0]..hi[0] {
        for j in lo[1]..hi[1] {
            for k in lo[2]..hi[2] {
                v[(i * r + j) * r + k] = 1.0;
            }
        }
    }
    v
}

#[test]
fn codes_are_b_by_c_dim_for_both_layouts_in_f32_and_f64() {
    let mut rng = SplitMix64::new(1);
    for dtype in [DType::F32, DType::F64] {
        // ONet's 32³ and four stages, at a small width.
        let config = VoxelEncoderConfig {
            base_channels: 4,
            c_dim: 8,
            ..VoxelEncoderConfig::default()
        };
        let (_vm, enc) = build(&config, dtype, 2);
        for b in [1, 3] {
            let x = binary(&mut rng, b, 32, dtype);
            let c = enc.forward(&x).unwrap();
            assert_eq!(c.dims(), &[b, 8], "{dtype:?} B = {b}");
            assert_eq!(c.dtype(), dtype);
            assert!(v64(&c).iter().all(|v| v.is_finite()));
            // [B, 1, R, R, R] is the same grid.
            let c5 = enc.forward(&x.unsqueeze(1).unwrap()).unwrap();
            assert_eq!(v64(&c5), v64(&c));
        }
        // Other resolutions and stage counts: 16³ with 0 to 4 stages.
        for stages in 0..=4 {
            let config = VoxelEncoderConfig {
                base_channels: 2,
                stages,
                c_dim: 5,
                resolution: 16,
                force_reference: false,
            };
            let (_vm, enc) = build(&config, dtype, 3);
            let c = enc.forward(&binary(&mut rng, 2, 16, dtype)).unwrap();
            assert_eq!(c.dims(), &[2, 5], "{stages} stages");
        }
    }
    // The default network (ONet's at half width, c_dim 256).
    let (_vm, enc) = build(&VoxelEncoderConfig::default(), DType::F32, 4);
    let c = enc.forward(&binary(&mut rng, 2, 32, DType::F32)).unwrap();
    assert_eq!(c.dims(), &[2, 256]);
}

/// ONet's layout at `base_channels: 32`; the default halves every width.
#[test]
fn onets_variables_at_32_base_channels_and_half_of_them_by_default() {
    for (base, convs) in [(32, 174_112), (16, 43_536)] {
        let config = VoxelEncoderConfig {
            base_channels: base,
            ..VoxelEncoderConfig::default()
        };
        let (varmap, _enc) = build(&config, DType::F32, 0);
        let data = varmap.data().lock().unwrap();
        let dims = |name: &str| data[name].dims().to_vec();
        assert_eq!(dims("conv_in.weight"), [base, 1, 3, 3, 3]);
        assert_eq!(dims("conv_0.weight"), [2 * base, base, 3, 3, 3]);
        assert_eq!(dims("conv_3.weight"), [16 * base, 8 * base, 3, 3, 3]);
        assert_eq!(dims("conv_3.bias"), [16 * base]);
        assert_eq!(dims("fc.weight"), [256, 16 * base * 8]);
        assert_eq!(data.len(), 2 * 6);
        let params: usize = data.values().map(|v| v.elem_count()).sum();
        // 27·(w + w·2w + 2w·4w + 4w·8w + 8w·16w) weights, 31·w biases, fc.
        assert_eq!(params, 27 * convs + 31 * base + 128 * base * 256 + 256);
    }
    assert_eq!(VoxelEncoderConfig::default().base_channels, 16);
}

#[test]
fn gradients_reach_every_variable_and_the_voxels_and_are_finite() {
    for dtype in [DType::F32, DType::F64] {
        let (varmap, enc) = build(&tiny(5), dtype, 5);
        let mut rng = SplitMix64::new(6);
        let x = Var::from_tensor(&binary(&mut rng, 3, 8, dtype)).unwrap();
        let r = normal_tensor(&mut rng, &[3, 5], 0.0, 1.0, dtype, &Device::Cpu).unwrap();
        let loss = (enc.forward(x.as_tensor()).unwrap() * &r)
            .unwrap()
            .sum_all()
            .unwrap();
        let grads = loss.backward().unwrap();
        let data = varmap.data().lock().unwrap();
        assert_eq!(data.len(), 2 * 4); // conv_in, conv_0, conv_1, fc
        for (name, var) in data.iter() {
            let g = v64(grads
                .get(var)
                .unwrap_or_else(|| panic!("no gradient for {name}")));
            assert!(g.iter().all(|v| v.is_finite()), "{name}: {g:?}");
            assert!(g.iter().any(|v| *v != 0.0), "{name}: all zero ({dtype:?})");
        }
        let gx = v64(grads.get(&x).unwrap());
        assert_eq!(gx.len(), 3 * 512);
        assert!(gx.iter().all(|v| v.is_finite()) && gx.iter().any(|v| *v != 0.0));
    }
}

/// Backpropagated gradients of `Σ R ⊙ c` against central finite differences in f64, for
/// entries of every convolution's weight and bias, `fc`, and voxels (occupancies in
/// `(0.1, 0.9)`, so that the stencil stays in `[0, 1]`), including voxels on the grid's
/// faces, where the convolutions read the padding.
#[test]
fn gradients_match_finite_differences_in_f64() {
    let (varmap, enc) = build(&tiny(3), DType::F64, 7);
    let mut rng = SplitMix64::new(8);
    let v: Vec<f64> = (0..2 * 512).map(|_| 0.1 + 0.8 * rng.uniform()).collect();
    let x = Var::from_vec(v, (2, 8, 8, 8), &Device::Cpu).unwrap();
    let r = normal_tensor(&mut rng, &[2, 3], 0.0, 1.0, DType::F64, &Device::Cpu).unwrap();
    let loss = || -> f64 {
        let c = enc.forward(x.as_tensor()).unwrap();
        v64(&(c * &r).unwrap().sum_all().unwrap())[0]
    };
    let grads = (enc.forward(x.as_tensor()).unwrap() * &r)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let mut targets: Vec<(String, Var)> = {
        let data = varmap.data().lock().unwrap();
        let mut names: Vec<&String> = data.keys().collect();
        names.sort();
        names
            .into_iter()
            .map(|n| (n.clone(), data[n].clone()))
            .collect()
    };
    assert_eq!(targets.len(), 8);
    targets.push(("voxels".to_string(), x.clone()));
    let mut tally = common::FdTally::default();
    for (name, var) in &targets {
        let g = v64(grads.get(var).unwrap());
        let values = v64(var.as_tensor());
        let scale = g.iter().fold(1e-3f64, |m, v| m.max(v.abs()));
        // Four entries each; for the voxels a corner, a face and two inside.
        let picks: Vec<usize> = if name == "voxels" {
            vec![
                0,
                7 * 64 + 3 * 8 + 5,
                512 + 3 * 64 + 4 * 8 + 2,
                512 + 4 * 64 + 4 * 8 + 4,
            ]
        } else {
            (0..4).map(|k| (k * 7919 + 13) % values.len()).collect()
        };
        for i in picks {
            let x0 = values[i];
            let mut f = |t: f64| {
                common::set_entry(var, i, t);
                loss()
            };
            let fd = central_diff(&mut f, x0, 1e-6, scale);
            common::set_entry(var, i, x0);
            tally.check(g[i], fd, 1e-6 * scale, &|| format!("{name}[{i}]"));
        }
    }
    let common::FdTally { checked, skipped } = tally;
    println!("{checked} entries checked, {skipped} skipped at kinks");
    assert!(checked >= 30, "{checked} checked, {skipped} at kinks");
}

/// The same 4³ cube at eight places in a 16³ grid gets eight different codes, and none
/// is the empty grid's: the flattened last feature grid keeps where a shape is (a
/// globally pooled encoder would give a translation a nearly equal code).
#[test]
fn translating_a_blob_changes_the_code() {
    let config = VoxelEncoderConfig {
        base_channels: 4,
        stages: 3,
        c_dim: 16,
        resolution: 16,
        force_reference: false,
    };
    let (_vm, enc) = build(&config, DType::F64, 9);
    let mut grids = vec![vec![0.0; 16 * 16 * 16]];
    for lo in [
        [2, 2, 2],
        [3, 2, 2],
        [2, 3, 2],
        [2, 2, 3],
        [6, 6, 6],
        [10, 2, 7],
        [11, 11, 11],
        [12, 0, 12],
    ] {
        grids.push(boxed(16, lo, [lo[0] + 4, lo[1] + 4, lo[2] + 4]));
    }
    let n = grids.len();
    let x = Tensor::from_vec(grids.concat(), (n, 16, 16, 16), &Device::Cpu).unwrap();
    let codes: Vec<Vec<f64>> = (0..n)
        .map(|i| v64(&enc.forward(&x).unwrap().get(i).unwrap()))
        .collect();
    let norm = codes.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    for i in 0..n {
        for j in 0..i {
            let gap = codes[i]
                .iter()
                .zip(&codes[j])
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(gap > 1e-3 * norm, "grids {i} and {j}: codes {gap:e} apart");
        }
    }
}

/// A hundred Adam steps on a small task (the cube root of the filled fraction of random
/// boxes voxelised in 16³) bring the held-out error below half that of the untrained
/// network and of predicting the training targets' mean (about a quarter of it here).
#[test]
fn adam_steps_learn_the_filled_fraction_of_boxes() {
    let dtype = DType::F32;
    let config = VoxelEncoderConfig {
        base_channels: 4,
        stages: 3,
        c_dim: 1,
        resolution: 16,
        force_reference: false,
    };
    let (varmap, enc) = build(&config, dtype, 10);
    let mut rng = SplitMix64::new(11);
    let mut batch = |b: usize| {
        let mut grids = Vec::with_capacity(b);
        let mut targets = Vec::with_capacity(b);
        for _ in 0..b {
            let mut lo = [0; 3];
            let mut hi = [0; 3];
            for a in 0..3 {
                let (p, q) = (
                    (rng.uniform() * 16.0) as usize,
                    (rng.uniform() * 16.0) as usize,
                );
                lo[a] = p.min(q);
                hi[a] = p.max(q) + 1;
            }
            let g = boxed(16, lo, hi);
            // The fraction's cube root spreads the targets over [0, 1].
            targets.push((g.iter().sum::<f64>() / 4096.0).cbrt());
            grids.push(g);
        }
        let x = Tensor::from_vec(grids.concat(), (b, 16, 16, 16), &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let t = Tensor::from_vec(targets, (b, 1), &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        (x, t)
    };
    let mse = |c: &Tensor, t: &Tensor| (c - t).unwrap().sqr().unwrap().mean_all().unwrap();
    let (test_x, test_t) = batch(64);
    let error = || v64(&mse(&enc.forward(&test_x).unwrap(), &test_t))[0];
    let (train_x, train_t) = batch(256);
    let mean = v64(&train_t.mean_all().unwrap())[0];
    let mean_error = v64(&test_t
        .affine(1.0, -mean)
        .unwrap()
        .sqr()
        .unwrap()
        .mean_all()
        .unwrap())[0];
    let untrained = error();
    let mut opt = adam(&varmap, 3e-3).unwrap();
    let mut losses = Vec::new();
    for step in 0..100 {
        let at = (step * 16) % 256;
        let (x, t) = (
            train_x.narrow(0, at, 16).unwrap(),
            train_t.narrow(0, at, 16).unwrap(),
        );
        let loss = mse(&enc.forward(&x).unwrap(), &t);
        losses.push(v64(&loss)[0]);
        opt.backward_step(&loss).unwrap();
    }
    let trained = error();
    println!("held out: untrained {untrained:.4}, mean {mean_error:.4}, trained {trained:.4}");
    println!("training losses {losses:.4?}");
    assert!(
        trained < 0.5 * untrained.min(mean_error),
        "{trained} vs untrained {untrained}, mean {mean_error}"
    );
}

#[test]
fn bad_voxels_are_refused_naming_voxels() {
    let (_vm, enc) = build(&tiny(2), DType::F32, 12);
    let d = Device::Cpu;
    let z = |shape: &[usize]| Tensor::zeros(shape, DType::F32, &d).unwrap();
    let with = |x: f32| {
        Tensor::cat(
            &[
                &z(&[1, 8, 8, 8]),
                &Tensor::full(x, (1, 8, 8, 8), &d).unwrap(),
            ],
            0,
        )
        .unwrap()
    };
    let shape = "shape [B, 8, 8, 8] or [B, 1, 8, 8, 8]";
    let cases: Vec<(Tensor, &str)> = vec![
        (z(&[8, 8, 8]), shape),
        (z(&[2, 16, 16, 16]), shape),
        (z(&[2, 8, 8, 4]), shape),
        (z(&[2, 2, 8, 8, 8]), shape),
        (z(&[2, 1, 1, 8, 8, 8]), shape),
        (z(&[0, 8, 8, 8]), "at least one grid"),
        (z(&[0, 1, 8, 8, 8]), "at least one grid"),
        (with(f32::NAN), "finite values"),
        (with(f32::INFINITY), "finite values"),
        (with(1.5), "occupancies in [0, 1]"),
        (with(-1e-6), "occupancies in [0, 1]"),
        (z(&[2, 8, 8, 8]).to_dtype(DType::F64).unwrap(), "dtype F32"),
        (
            z(&[2, 8, 8, 8]).to_dtype(DType::U32).unwrap(),
            "dtype f32 or f64",
        ),
    ];
    for (x, msg) in cases {
        let e = enc.forward(&x).unwrap_err().to_string();
        assert!(e.starts_with("voxels: expected ") && e.contains(msg), "{e}");
    }
    // The bounds themselves, and fractional occupancies, are fine.
    assert!(enc.forward(&with(1.0)).is_ok());
    assert!(enc.forward(&with(0.25)).is_ok());
}

#[test]
fn bad_configurations_are_refused_naming_the_field() {
    let vb = || VarBuilder::zeros(DType::F32, &Device::Cpu);
    let cases = [
        (
            VoxelEncoderConfig {
                base_channels: 0,
                ..tiny(2)
            },
            "config.base_channels",
        ),
        (
            VoxelEncoderConfig {
                c_dim: 0,
                ..tiny(2)
            },
            "config.c_dim",
        ),
        (
            VoxelEncoderConfig {
                resolution: 0,
                ..tiny(2)
            },
            "config.resolution",
        ),
        (
            VoxelEncoderConfig {
                resolution: 24,
                ..tiny(2)
            },
            "config.resolution",
        ),
        (
            VoxelEncoderConfig {
                stages: 4,
                ..tiny(2)
            },
            "config.stages",
        ),
        (
            VoxelEncoderConfig {
                stages: 100,
                ..tiny(2)
            },
            "config.stages",
        ),
        (
            VoxelEncoderConfig {
                base_channels: 1 << 20,
                ..tiny(2)
            },
            "config.base_channels",
        ),
        (
            VoxelEncoderConfig {
                base_channels: usize::MAX,
                ..tiny(2)
            },
            "config.base_channels",
        ),
        (
            VoxelEncoderConfig {
                c_dim: 1 << 40,
                ..tiny(2)
            },
            "config.c_dim",
        ),
        (
            // The first convolution's gather index: 27·512³ u32.
            VoxelEncoderConfig {
                resolution: 512,
                ..tiny(2)
            },
            "config.resolution",
        ),
        (
            // 4 channels at 2^14³ after no stage.
            VoxelEncoderConfig {
                stages: 0,
                resolution: 1 << 14,
                ..tiny(2)
            },
            "config.resolution",
        ),
    ];
    for (config, name) in cases {
        let e = voxel_encoder(&config, vb()).unwrap_err().to_string();
        assert!(e.starts_with(&format!("{name}: expected")), "{e}");
    }
    // The edge cases that are allowed: as many stages as halvings, a 1³ grid.
    for config in [
        VoxelEncoderConfig {
            stages: 3,
            ..tiny(2)
        },
        VoxelEncoderConfig {
            stages: 0,
            resolution: 1,
            ..tiny(2)
        },
    ] {
        let enc = voxel_encoder(&config, vb()).unwrap();
        let r = config.resolution;
        let x = Tensor::ones((2, r, r, r), DType::F32, &Device::Cpu).unwrap();
        assert_eq!(enc.forward(&x).unwrap().dims(), &[2, 2]);
    }
}

/// The fused chain of convolutions (the default on the CPU: one op whose grids and their
/// gradients live in buffers kept between calls) and candle's ops (`force_reference`)
/// compute the same codes and the same gradients of every variable and of the voxels, in
/// f64 to 1e-10 and in f32 relative to the largest entry; the second of two calls, whose
/// kept buffers still hold the first call's values, as well.
#[test]
fn fused_convolution_chain_matches_the_reference_encoder() {
    for (dtype, tol) in [(DType::F64, 1e-10), (DType::F32, 1e-4)] {
        let config = tiny(5);
        let reference = VoxelEncoderConfig {
            force_reference: true,
            ..config.clone()
        };
        let (vm_f, fused) = build(&config, dtype, 31);
        let (vm_r, plain) = build(&reference, dtype, 31);
        let mut rng = SplitMix64::new(32);
        for b in [3, 2] {
            let x = Var::from_tensor(&binary(&mut rng, b, config.resolution, dtype)).unwrap();
            let r = normal_tensor(&mut rng, &[b, 5], 0.0, 1.0, dtype, &Device::Cpu).unwrap();
            let run = |enc: &VoxelEncoder| {
                let codes = enc.forward(x.as_tensor()).unwrap();
                let grads = (&codes * &r)
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .backward()
                    .unwrap();
                (v64(&codes), grads)
            };
            let (cf, gf) = run(&fused);
            let (cr, gr) = run(&plain);
            let close = |what: &str, a: &[f64], e: &[f64]| {
                let what = format!("{what} ({dtype:?}, B = {b})");
                assert_parts_close(&[a.to_vec()], &[e.to_vec()], tol, &what);
            };
            close("codes", &cf, &cr);
            close(
                "voxels' gradient",
                &v64(gf.get(&x).unwrap()),
                &v64(gr.get(&x).unwrap()),
            );
            let (df, dr) = (vm_f.data().lock().unwrap(), vm_r.data().lock().unwrap());
            for (name, var) in df.iter() {
                let what = format!("{name}'s gradient");
                close(
                    &what,
                    &v64(gf.get(var).unwrap()),
                    &v64(gr.get(&dr[name]).unwrap()),
                );
            }
        }
    }
}
