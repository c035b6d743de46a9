//! The multiresolution hash grid: the fused op against the reference path (candle ops),
//! table and position gradients against finite differences in f64 on dense and hashed
//! levels (with collisions), points on cell faces, edges and outside the box, an
//! anisotropic box against the cube, tangents, determinism, and the configurations and
//! inputs it refuses.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use common::v64;
use neural_fields::encoding::{hash_grid, Encoding, HashGrid, HashGridConfig, PointEncoding};
use neural_fields::field::Field;
use neural_fields::nn::{mlp, MlpConfig};
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;

/// A small grid: 4 levels of 2 features, resolutions 2 to 16 in `[−1, 1]³`, tables of
/// `2^log2` rows (6: every level past the first is hashed and collides).
fn small(log2: u32) -> HashGridConfig {
    HashGridConfig {
        levels: 4,
        features: 2,
        log2_table_size: log2,
        base_resolution: 2.0,
        finest_resolution: 16.0,
        ..HashGridConfig::default()
    }
}

/// A grid whose table holds seeded values of order 1 (the default 1e-4 would hide
/// errors in sums).
fn grid(config: &HashGridConfig, dtype: DType, seed: u64) -> (VarMap, HashGrid) {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, dtype, &Device::Cpu);
    let g = hash_grid(config, vb).unwrap();
    let mut rng = SplitMix64::new(seed);
    let t = table_var(&varmap);
    let fresh = rng
        .uniform_tensor(t.dims(), -1.0, 1.0, dtype, &Device::Cpu)
        .unwrap();
    for (_, var) in varmap.data().lock().unwrap().iter() {
        var.set(&fresh).unwrap();
    }
    (varmap, g)
}

/// The twin on the reference path (`force_reference`) of the grid built from `config` in
/// `varmap`: built from the same map, so it reads the same table.
fn reference_twin(config: &HashGridConfig, varmap: &VarMap) -> HashGrid {
    let config = HashGridConfig {
        force_reference: true,
        ..config.clone()
    };
    let table = table_var(varmap);
    let vb = VarBuilder::from_varmap(varmap, table.dtype(), table.device());
    hash_grid(&config, vb).unwrap()
}

fn table_var(varmap: &VarMap) -> Var {
    varmap.all_vars().into_iter().next().unwrap()
}

/// Points: random inside, on cell faces and edges of the finest level (coordinates that
/// are multiples of 2/16), on the box's faces, and outside it.
fn points(rng: &mut SplitMix64, n: usize) -> Vec<f64> {
    let mut v = Vec::with_capacity(n * 3);
    for i in 0..n {
        for k in 0..3 {
            let u = rng.uniform();
            let x = match (i + k) % 5 {
                0 => -1.0 + 2.0 * (rng.below(17) as f64) / 16.0, // a face of every level
                1 => {
                    if u < 0.5 {
                        -1.0
                    } else {
                        1.0
                    }
                } // the box's faces
                2 => 3.0 * u - 1.5,                              // partly outside
                _ => 2.0 * u - 1.0,
            };
            v.push(x);
        }
    }
    v
}

fn tensor(v: &[f64], dtype: DType) -> Tensor {
    Tensor::from_vec(v.to_vec(), (v.len() / 3, 3), &Device::Cpu)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

/// A fixed weighting of the outputs, so that `loss = Σ c ⊙ y` has a gradient with
/// every component.
fn weights(n: usize, e: usize, dtype: DType) -> Tensor {
    let v: Vec<f64> = (0..n * e)
        .map(|i| ((i * 7919) % 101) as f64 / 50.0 - 1.0)
        .collect();
    Tensor::from_vec(v, (n, e), &Device::Cpu)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// Values and gradients (table, positions) of `Σ c ⊙ γ(x)` on one path: `g`'s, or with
/// `reference = Some(config)` (`g`'s configuration) its twin on the reference path.
fn run(
    g: &HashGrid,
    varmap: &VarMap,
    x: &[f64],
    reference: Option<&HashGridConfig>,
    dtype: DType,
) -> [Vec<f64>; 3] {
    let xv = Var::from_tensor(&tensor(x, dtype)).unwrap();
    let y = if let Some(config) = reference {
        reference_twin(config, varmap)
            .forward(xv.as_tensor())
            .unwrap()
    } else {
        g.forward(xv.as_tensor()).unwrap()
    };
    let c = weights(y.dims()[0], y.dims()[1], dtype);
    let grads = (&y * &c).unwrap().sum_all().unwrap().backward().unwrap();
    let table = table_var(varmap);
    [
        v64(&y),
        v64(grads.get(table.as_tensor()).unwrap()),
        v64(grads.get(xv.as_tensor()).unwrap()),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Fused equals reference to 1e-10 in f64 (values, table and position gradients),
    /// on dense (log2 = 12) and hashed, colliding (log2 = 6) tables.
    #[test]
    fn fused_equals_reference(seed in 0u64..1000, log2 in prop::sample::select(vec![6u32, 12])) {
        let (varmap, g) = grid(&small(log2), DType::F64, seed);
        let x = points(&mut SplitMix64::new(seed + 1), 37);
        let fused = run(&g, &varmap, &x, None, DType::F64);
        let reference = run(&g, &varmap, &x, Some(&small(log2)), DType::F64);
        for (k, (a, b)) in fused.iter().zip(&reference).enumerate() {
            let worst = (0..a.len()).max_by(|&i, &j| (a[i] - b[i]).abs().total_cmp(&(a[j] - b[j]).abs())).unwrap_or(0);
            prop_assert!(max_diff(a, b) < 1e-10, "output {k}: {} at {worst}: {} vs {} (x = {:?})", max_diff(a, b), a[worst], b[worst], &x[worst / 3 * 3..worst / 3 * 3 + 3]);
        }
    }

    /// The table gradient against central differences (the output is linear in the
    /// table, so differences are exact up to rounding), f64.
    #[test]
    fn table_gradient_matches_finite_differences(seed in 0u64..1000) {
        let (varmap, g) = grid(&small(6), DType::F64, seed);
        let x = points(&mut SplitMix64::new(seed + 2), 9);
        let [_, gt, _] = run(&g, &varmap, &x, None, DType::F64);
        let table = table_var(&varmap);
        let base = v64(table.as_tensor());
        let xt = tensor(&x, DType::F64);
        let loss = |v: &[f64]| {
            table.set(&Tensor::from_vec(v.to_vec(), table.dims(), &Device::Cpu).unwrap()).unwrap();
            let y = g.forward(&xt).unwrap();
            let c = weights(y.dims()[0], y.dims()[1], DType::F64);
            (&y * &c).unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap()
        };
        let mut rng = SplitMix64::new(seed);
        for _ in 0..12 {
            let i = rng.below(base.len() as u64) as usize;
            let h = 1e-3;
            let (mut up, mut down) = (base.clone(), base.clone());
            up[i] += h;
            down[i] -= h;
            let fd = (loss(&up) - loss(&down)) / (2.0 * h);
            prop_assert!((fd - gt[i]).abs() < 1e-9, "row {i}: fd {fd} vs {}", gt[i]);
        }
        loss(&base);
    }

    /// The position gradient against one-sided differences from above (a point on a
    /// face belongs to the cell above, where the encoding is linear along each axis),
    /// and zero outside the box, f64.
    #[test]
    fn position_gradient_matches_finite_differences(seed in 0u64..1000) {
        let (varmap, g) = grid(&small(6), DType::F64, seed);
        let x = points(&mut SplitMix64::new(seed + 3), 11);
        let [_, _, gx] = run(&g, &varmap, &x, None, DType::F64);
        let loss = |v: &[f64]| {
            let y = g.forward(&tensor(v, DType::F64)).unwrap();
            let c = weights(y.dims()[0], y.dims()[1], DType::F64);
            (&y * &c).unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap()
        };
        for i in 0..x.len() {
            let h = 1e-7;
            // On the box's upper face the point belongs to the last cell: step down.
            let step = if x[i] >= 1.0 { -h } else { h };
            let mut moved = x.clone();
            moved[i] += step;
            let fd = (loss(&moved) - loss(&x)) / step;
            let outside = x[i] < -1.0 || x[i] > 1.0;
            if outside {
                prop_assert_eq!(gx[i], 0.0);
            } else {
                prop_assert!((fd - gx[i]).abs() < 1e-5 * (1.0 + gx[i].abs()), "coordinate {i} = {}: fd {fd} vs {}", x[i], gx[i]);
            }
        }
    }
}

#[test]
fn fused_equals_reference_in_f32() {
    let (varmap, g) = grid(&small(6), DType::F32, 5);
    let x = points(&mut SplitMix64::new(6), 50);
    let fused = run(&g, &varmap, &x, None, DType::F32);
    let reference = run(&g, &varmap, &x, Some(&small(6)), DType::F32);
    for (a, b) in fused.iter().zip(&reference) {
        assert!(max_diff(a, b) < 1e-4, "{}", max_diff(a, b));
    }
}

/// Tangents (the reference path's Jacobian) agree with the fused position gradient and
/// stay differentiable w.r.t. the table (normals, the eikonal loss).
#[test]
fn tangents_match_the_position_gradient_and_reach_the_table() {
    let (varmap, g) = grid(&small(6), DType::F64, 8);
    let x = points(&mut SplitMix64::new(9), 13);
    let xt = tensor(&x, DType::F64);
    let n = x.len() / 3;
    let eye = Tensor::eye(3, DType::F64, &Device::Cpu)
        .unwrap()
        .unsqueeze(0)
        .unwrap()
        .broadcast_as((n, 3, 3))
        .unwrap()
        .contiguous()
        .unwrap();
    let (y, jac) = g.forward_jvp(&xt, &eye).unwrap(); // [N, 3, E]
    let c = weights(n, g.out_dim(), DType::F64);
    assert!(max_diff(&v64(&y), &v64(&g.forward(&xt).unwrap())) < 1e-12);
    // Σ_e c_e ∂y_e/∂x_d from the tangents, against the fused backward.
    let from_jac = jac
        .broadcast_mul(&c.unsqueeze(1).unwrap())
        .unwrap()
        .sum(2)
        .unwrap();
    let [_, _, gx] = run(&g, &varmap, &x, None, DType::F64);
    assert!(max_diff(&v64(&from_jac), &gx) < 1e-9);
    let grads = jac.sqr().unwrap().sum_all().unwrap().backward().unwrap();
    let gt = v64(grads.get(table_var(&varmap).as_tensor()).unwrap());
    assert!(gt.iter().any(|&v| v != 0.0) && gt.iter().all(|v| v.is_finite()));
}

#[test]
fn table_gradient_is_the_same_bit_for_bit_every_run() {
    let (varmap, g) = grid(&HashGridConfig::default(), DType::F32, 1);
    let x = points(&mut SplitMix64::new(2), 20_000);
    let first = run(&g, &varmap, &x, None, DType::F32);
    for _ in 0..3 {
        let again = run(&g, &varmap, &x, None, DType::F32);
        for (a, b) in first.iter().zip(&again) {
            assert!(a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits()));
        }
    }
}

/// A grid over an anisotropic, off-centre box (the suite plate's hull box) is the grid
/// over `[−1, 1]³` with the same table, read at the points mapped affinely between the
/// boxes: values and table gradients, fused and reference paths, f32 and f64.
#[test]
fn an_anisotropic_box_is_the_cube_grid_at_the_mapped_points() {
    let (lo, hi) = ([-1.344, -0.761, -0.643], [1.344, 0.761, 0.351]);
    let mut rng = SplitMix64::new(11);
    let unit: Vec<f64> = (0..300 * 3).map(|_| rng.uniform()).collect();
    let in_box: Vec<f64> = unit
        .iter()
        .enumerate()
        .map(|(i, u)| lo[i % 3] + u * (hi[i % 3] - lo[i % 3]))
        .collect();
    let in_cube: Vec<f64> = unit.iter().map(|u| 2.0 * u - 1.0).collect();
    for (dtype, tol) in [(DType::F64, 1e-12), (DType::F32, 1e-4)] {
        for force_reference in [false, true] {
            let cube = HashGridConfig {
                force_reference,
                ..small(6)
            };
            let boxed = HashGridConfig {
                lo: lo.to_vec(),
                hi: hi.to_vec(),
                ..cube.clone()
            };
            let (varmap, g) = grid(&cube, dtype, 5);
            let table = table_var(&varmap);
            let vb = VarBuilder::from_varmap(&varmap, table.dtype(), table.device());
            let b = hash_grid(&boxed, vb).unwrap();
            let [y_cube, t_cube, _] = run(&g, &varmap, &in_cube, None, dtype);
            let [y_box, t_box, _] = run(&b, &varmap, &in_box, None, dtype);
            let (dy, dt) = (max_diff(&y_cube, &y_box), max_diff(&t_cube, &t_box));
            assert!(
                dy < tol && dt < tol,
                "{dtype:?}, reference {force_reference}: values differ by {dy:e}, table gradients by {dt:e}"
            );
        }
    }
}

#[test]
fn points_outside_the_box_are_clamped_and_nan_or_inf_is_an_error() {
    let (varmap, g) = grid(&small(6), DType::F64, 3);
    let inside = tensor(&[1.0, -1.0, 0.25], DType::F64);
    let outside = tensor(&[7.0, -1e300, 0.25], DType::F64);
    assert_eq!(
        v64(&g.forward(&inside).unwrap()),
        v64(&g.forward(&outside).unwrap())
    );
    // ±∞ is refused as NaN is (it used to be clamped to the box's face).
    let inf = tensor(&[f64::INFINITY, -1.0, 0.25], DType::F64);
    let nan = tensor(&[f64::NAN, 0.0, 0.0], DType::F64);
    for bad in [&nan, &inf] {
        for e in [
            g.forward(bad).unwrap_err(),
            reference_twin(&small(6), &varmap).forward(bad).unwrap_err(),
        ] {
            assert!(
                e.to_string().starts_with("x:") && e.to_string().contains("NaN"),
                "{e}"
            );
        }
    }
    let wrong = Tensor::zeros((2, 2), DType::F64, &Device::Cpu).unwrap();
    assert!(g.forward(&wrong).unwrap_err().to_string().starts_with("x:"));
    let f32_points = tensor(&[0.0, 0.0, 0.0], DType::F32);
    assert!(g
        .forward(&f32_points)
        .unwrap_err()
        .to_string()
        .starts_with("x:"));
    let empty = Tensor::zeros((0, 3), DType::F64, &Device::Cpu).unwrap();
    assert_eq!(g.forward(&empty).unwrap().dims(), &[0, 8]);
}

#[test]
fn configurations_that_cannot_work_are_errors_naming_the_field() {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    for (config, field) in [
        (
            HashGridConfig {
                finest_resolution: 5e9,
                ..HashGridConfig::default()
            },
            "finest_resolution",
        ),
        (
            HashGridConfig {
                in_dim: 5,
                ..HashGridConfig::default()
            },
            "in_dim",
        ),
        (
            HashGridConfig {
                log2_table_size: 40,
                ..HashGridConfig::default()
            },
            "log2_table_size",
        ),
        (
            HashGridConfig {
                levels: 0,
                ..HashGridConfig::default()
            },
            "levels",
        ),
        (
            HashGridConfig {
                base_resolution: f64::NAN,
                ..HashGridConfig::default()
            },
            "base_resolution",
        ),
        (
            HashGridConfig {
                lo: vec![0.0; 3],
                hi: vec![0.0, 1.0, 1.0],
                ..HashGridConfig::default()
            },
            "lo",
        ),
        (
            HashGridConfig {
                lo: vec![0.0; 2],
                ..HashGridConfig::default()
            },
            "lo",
        ),
    ] {
        let e = hash_grid(&config, vb.clone()).unwrap_err().to_string();
        assert!(e.contains(field), "{field}: {e}");
    }
}

/// An `Mlp` on a hash grid: values, normals through `forward_with_jacobian`, and
/// gradients that reach the table.
#[test]
fn mlp_on_a_hash_grid_gives_normals_and_trains_the_table() {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    let g = hash_grid(&small(10), vb.pp("grid")).unwrap();
    let config = MlpConfig {
        depth: 2,
        hidden: 16,
        encoding: PointEncoding::HashGrid(g.clone()),
        ..MlpConfig::default()
    };
    let net = mlp(&config, vb.pp("mlp")).unwrap();
    let x = tensor(&points(&mut SplitMix64::new(4), 10), DType::F32);
    let y = Field::forward(&net, &x).unwrap();
    assert_eq!(y.dims(), &[10, 1]);
    let (_, jac) = net.forward_with_jacobian(&x, None).unwrap();
    assert_eq!(jac.dims(), &[10, 3, 1]);
    let loss = (y.sum_all().unwrap() + jac.sqr().unwrap().sum_all().unwrap()).unwrap();
    let grads = loss.backward().unwrap();
    let table = varmap
        .data()
        .lock()
        .unwrap()
        .get("grid.table")
        .expect("the grid's table is a variable of the map")
        .clone();
    assert!(grads.get(table.as_tensor()).is_some());
}

/// A digest of the fused table gradient's bits for a fixed problem (FNV-1a over the f32
/// bits of the gradient).
fn table_gradient_digest() -> u64 {
    let (varmap, g) = grid(&HashGridConfig::default(), DType::F32, 11);
    let x = points(&mut SplitMix64::new(12), 30_000);
    let [_, gt, _] = run(&g, &varmap, &x, None, DType::F32);
    gt.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, v| {
        (h ^ u64::from((*v as f32).to_bits())).wrapping_mul(0x0100_0000_01b3)
    })
}

/// The table gradient's bits do not depend on the number of threads: this test runs
/// itself in child processes with 1, 2 and 5 threads (`CANDLE_NUM_THREADS`, which sizes
/// candle's CPU pool) and compares the digests they print.
#[test]
fn table_gradient_bits_do_not_depend_on_the_thread_count() {
    const NAME: &str = "table_gradient_bits_do_not_depend_on_the_thread_count";
    if std::env::var_os("NF_DIGEST_CHILD").is_some() {
        println!("digest={:016x}", table_gradient_digest());
        return;
    }
    let exe = std::env::current_exe().unwrap();
    let digests: Vec<String> = ["1", "2", "5"]
        .iter()
        .map(|threads| {
            let out = std::process::Command::new(&exe)
                .args([NAME, "--exact", "--nocapture", "--test-threads=1"])
                .env("NF_DIGEST_CHILD", "1")
                .env("RAYON_NUM_THREADS", threads)
                .env("CANDLE_NUM_THREADS", threads)
                .output()
                .unwrap();
            let text = String::from_utf8_lossy(&out.stdout).into_owned();
            text.lines()
                .find_map(|l| l.split_once("digest=").map(|(_, d)| d.trim()))
                .unwrap_or_else(|| {
                    panic!("no digest from the child with {threads} threads: {text}")
                })
                .to_string()
        })
        .collect();
    assert!(digests.iter().all(|d| d == &digests[0]), "{digests:?}");
}
