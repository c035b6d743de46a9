//! Grid sampling and scatter pooling: the fused ops against the reference paths (candle
//! ops), gradients against finite differences in f64 (points inside cells, on cell
//! borders, exactly on the grid boundary and outside it), a closed form, determinism
//! across thread counts, empty inputs and the inputs they refuse.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::v64;
use neural_fields::encoding::{
    cell_index, grid_sample, scatter, GridSampleConfig, Pooling, ScatterConfig,
};
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;

/// `grid_sample` on the fused path (the default configuration).
fn fused_sample(features: &Tensor, coords: &Tensor) -> neural_fields::Result<Tensor> {
    grid_sample(features, coords, &GridSampleConfig::default())
}

/// `grid_sample` on the reference path (`force_reference`).
fn reference_sample(features: &Tensor, coords: &Tensor) -> neural_fields::Result<Tensor> {
    grid_sample(
        features,
        coords,
        &GridSampleConfig {
            force_reference: true,
        },
    )
}

/// `scatter` with the mean.
fn mean_pool(values: &Tensor, index: &Tensor, cells: usize) -> neural_fields::Result<Tensor> {
    scatter(values, index, cells, &ScatterConfig::default())
}

/// `scatter` with the maximum on the fused path.
fn max_pool(values: &Tensor, index: &Tensor, cells: usize) -> neural_fields::Result<Tensor> {
    let config = ScatterConfig {
        pooling: Pooling::Max,
        force_reference: false,
    };
    scatter(values, index, cells, &config)
}

/// `scatter` with the maximum on the reference path (`force_reference`).
fn max_pool_reference(
    values: &Tensor,
    index: &Tensor,
    cells: usize,
) -> neural_fields::Result<Tensor> {
    let config = ScatterConfig {
        pooling: Pooling::Max,
        force_reference: true,
    };
    scatter(values, index, cells, &config)
}

/// A problem: features `[B, C, spatial…]` and coordinates `[B, N, k]` as host values.
#[derive(Clone, Debug)]
struct Problem {
    fdims: Vec<usize>,
    f: Vec<f64>,
    n: usize,
    x: Vec<f64>,
}

impl Problem {
    fn k(&self) -> usize {
        self.fdims.len() - 2
    }

    /// Samples along coordinate axis `a` (0: W, the last axis).
    fn size(&self, a: usize) -> usize {
        self.fdims[self.fdims.len() - 1 - a]
    }

    fn features(&self, dtype: DType) -> Tensor {
        Tensor::from_vec(self.f.clone(), self.fdims.as_slice(), &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
    }

    fn coords(&self, dtype: DType) -> Tensor {
        Tensor::from_vec(
            self.x.clone(),
            (self.fdims[0], self.n, self.k()),
            &Device::Cpu,
        )
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
    }

    /// The fixed output weighting of `loss = Σ w ⊙ y`.
    fn weights(&self, dtype: DType) -> Tensor {
        let (b, c) = (self.fdims[0], self.fdims[1]);
        let v: Vec<f64> = (0..b * self.n * c)
            .map(|i| ((i * 7919) % 101) as f64 / 50.0 - 1.0)
            .collect();
        Tensor::from_vec(v, (b, self.n, c), &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
    }

    /// `Σ w ⊙ grid_sample(f, x)` on the fused path, in f64.
    fn loss(&self, f: &[f64], x: &[f64]) -> f64 {
        let p = Problem {
            f: f.to_vec(),
            x: x.to_vec(),
            ..self.clone()
        };
        let y = fused_sample(&p.features(DType::F64), &p.coords(DType::F64)).unwrap();
        (y * self.weights(DType::F64))
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap()
    }

    /// Values, feature gradient and coordinate gradient on one path.
    fn run(&self, reference: bool, dtype: DType) -> [Vec<f64>; 3] {
        let fv = Var::from_tensor(&self.features(dtype)).unwrap();
        let xv = Var::from_tensor(&self.coords(dtype)).unwrap();
        let y = if reference {
            reference_sample(fv.as_tensor(), xv.as_tensor()).unwrap()
        } else {
            fused_sample(fv.as_tensor(), xv.as_tensor()).unwrap()
        };
        let g = (&y * self.weights(dtype))
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        [
            v64(&y),
            v64(g.get(fv.as_tensor()).unwrap()),
            v64(g.get(xv.as_tensor()).unwrap()),
        ]
    }
}

/// Coordinates: inside cells, exactly on cell borders (`j/(S − 1)`), exactly on the grid
/// boundary (0 and 1), and outside (clamped).
fn coordinate(rng: &mut SplitMix64, size: usize, kind: u64) -> f64 {
    let u = rng.uniform();
    match kind {
        0 => (rng.below(size as u64) as f64) / ((size.max(2) - 1) as f64),
        1 => {
            if u < 0.5 {
                0.0
            } else {
                1.0
            }
        }
        2 => 3.0 * u - 1.0,
        _ => u,
    }
}

fn problem(seed: u64, three_d: bool) -> Problem {
    let mut rng = SplitMix64::new(seed);
    let b = 1 + rng.below(2) as usize;
    let c = 1 + rng.below(5) as usize;
    let k = if three_d { 3 } else { 2 };
    let mut fdims = vec![b, c];
    for _ in 0..k {
        // Sizes 1 (a degenerate axis) to 6.
        fdims.push(1 + rng.below(6) as usize);
    }
    let f: Vec<f64> = (0..fdims.iter().product::<usize>())
        .map(|_| 2.0 * rng.uniform() - 1.0)
        .collect();
    let n = 1 + rng.below(12) as usize;
    let mut p = Problem {
        fdims,
        f,
        n,
        x: Vec::new(),
    };
    for i in 0..b * n {
        for a in 0..k {
            let kind = rng.below(4);
            let size = p.size(a);
            let _ = i;
            p.x.push(coordinate(&mut rng, size, kind));
        }
    }
    p
}

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// The derivative the documented rule gives at coordinate `i`, by finite differences:
/// zero outside `[0, 1]` (clamped) and on a one-sample axis; otherwise the slope of the
/// cell `min(⌊u⌋, S − 2)` the rule picks (the cell above on an interior border, the first
/// at 0, the last at 1), measured by a one-sided difference that steps from the point
/// towards that cell's centre (the function is linear along the axis inside a cell, so
/// the difference is exact up to rounding).
fn expected_coord_derivative(p: &Problem, i: usize, size: usize) -> f64 {
    let c = p.x[i];
    if !(0.0..=1.0).contains(&c) || size < 2 {
        return 0.0;
    }
    let h = 1e-6;
    let at = |v: f64| {
        let mut x = p.x.clone();
        x[i] = v;
        p.loss(&p.f, &x)
    };
    let u = c * (size - 1) as f64;
    let cell = (u.floor() as usize).min(size - 2);
    if u - (cell as f64) < 0.5 {
        (at(c + h) - at(c)) / h
    } else {
        (at(c) - at(c - h)) / h
    }
}

fn check_gradients(p: &Problem) {
    let [_, gf, gx] = p.run(false, DType::F64);
    // Features: the loss is linear in them, so any difference is exact up to rounding.
    for i in (0..p.f.len()).step_by(1 + p.f.len() / 17) {
        let h = 1e-3;
        let mut up = p.f.clone();
        up[i] += h;
        let mut dn = p.f.clone();
        dn[i] -= h;
        let fd = (p.loss(&up, &p.x) - p.loss(&dn, &p.x)) / (2.0 * h);
        assert!(
            (fd - gf[i]).abs() <= 1e-8 * (1.0 + fd.abs()),
            "feature {i}: analytic {} fd {fd} ({p:?})",
            gf[i]
        );
    }
    // Coordinates: piecewise linear along each axis, so one-sided differences on the
    // documented side are exact up to rounding.
    let k = p.k();
    for (i, &g) in gx.iter().enumerate() {
        let size = p.size(i % k);
        let fd = expected_coord_derivative(p, i, size);
        assert!(
            (fd - g).abs() <= 1e-6 * (1.0 + fd.abs()),
            "coordinate {i} = {}, axis size {size}: analytic {g} fd {fd} ({p:?})",
            p.x[i]
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn gradients_match_finite_differences_2d(seed in any::<u64>()) {
        check_gradients(&problem(seed, false));
    }

    #[test]
    fn gradients_match_finite_differences_3d(seed in any::<u64>()) {
        check_gradients(&problem(seed, true));
    }

    #[test]
    fn fused_equals_reference(seed in any::<u64>(), three_d in any::<bool>()) {
        let p = problem(seed, three_d);
        let fused = p.run(false, DType::F64);
        let reference = p.run(true, DType::F64);
        for (a, b) in fused.iter().zip(&reference) {
            prop_assert!(max_diff(a, b) <= 1e-10, "{a:?} vs {b:?}");
        }
        let fused = p.run(false, DType::F32);
        let reference = p.run(true, DType::F32);
        for (a, b) in fused.iter().zip(&reference) {
            prop_assert!(max_diff(a, b) <= 2e-5, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn scatter_gradients_match_finite_differences(seed in any::<u64>()) {
        let mut rng = SplitMix64::new(seed);
        let (b, n, c, cells) = (2usize, 1 + rng.below(9) as usize, 1 + rng.below(3) as usize, 4usize);
        let v: Vec<f64> = (0..b * n * c).map(|_| 2.0 * rng.uniform() - 1.0).collect();
        let idx: Vec<u32> = (0..b * n).map(|_| rng.below(cells as u64) as u32).collect();
        let index = Tensor::from_vec(idx, (b, n), &Device::Cpu).unwrap();
        let w: Vec<f64> = (0..b * cells * c).map(|i| ((i * 37) % 11) as f64 - 5.0).collect();
        let w = Tensor::from_vec(w, (b, cells, c), &Device::Cpu).unwrap();
        type Op = fn(&Tensor, &Tensor, usize) -> neural_fields::Result<Tensor>;
        for op in [mean_pool as Op, max_pool as Op, max_pool_reference as Op] {
            let loss = |v: &[f64]| {
                let t = Tensor::from_vec(v.to_vec(), (b, n, c), &Device::Cpu).unwrap();
                (op(&t, &index, cells).unwrap() * &w).unwrap().sum_all().unwrap()
                    .to_scalar::<f64>().unwrap()
            };
            let var = Var::from_vec(v.clone(), (b, n, c), &Device::Cpu).unwrap();
            let y = op(var.as_tensor(), &index, cells).unwrap();
            let g = v64((y * &w).unwrap().sum_all().unwrap().backward().unwrap()
                .get(var.as_tensor()).unwrap());
            for i in 0..v.len() {
                let h = 1e-7;
                let (mut up, mut dn) = (v.clone(), v.clone());
                up[i] += h;
                dn[i] -= h;
                let fd = (loss(&up) - loss(&dn)) / (2.0 * h);
                prop_assert!((fd - g[i]).abs() <= 1e-6 * (1.0 + fd.abs()), "{i}: {} vs {fd}", g[i]);
            }
        }
    }
}

/// Sampling a function that is linear in the pixel position returns it exactly (the
/// coordinates clamped into `[0, 1]`), on both paths, in 2-D and 3-D.
#[test]
fn a_linear_function_is_sampled_exactly() {
    let mut rng = SplitMix64::new(3);
    for k in [2usize, 3] {
        let sizes = [5usize, 3, 4]; // per coordinate axis: W, H, D
        let slopes = [0.7, -1.3, 2.1];
        let (c, b) = (2usize, 2usize);
        let spatial: Vec<usize> = (0..k).rev().map(|a| sizes[a]).collect();
        let cells: usize = spatial.iter().product();
        let mut f = Vec::new();
        for _ in 0..b {
            for ch in 0..c {
                for flat in 0..cells {
                    let (mut rest, mut val) = (flat, 0.5 + ch as f64);
                    for a in 0..k {
                        let i = rest % sizes[a];
                        rest /= sizes[a];
                        val += slopes[a] * i as f64 / (sizes[a] - 1) as f64;
                    }
                    f.push(val);
                }
            }
        }
        let mut fdims = vec![b, c];
        fdims.extend(&spatial);
        let n = 40;
        let x: Vec<f64> = (0..b * n * k).map(|_| 1.6 * rng.uniform() - 0.3).collect();
        let p = Problem { fdims, f, n, x };
        for reference in [false, true] {
            let [y, _, _] = p.run(reference, DType::F64);
            for (q, row) in p.x.chunks(k).enumerate() {
                for ch in 0..c {
                    let want = 0.5
                        + ch as f64
                        + (0..k)
                            .map(|a| slopes[a] * row[a].clamp(0.0, 1.0))
                            .sum::<f64>();
                    let got = y[q * c + ch];
                    assert!(
                        (got - want).abs() < 1e-12,
                        "k {k} point {q}: {got} vs {want}"
                    );
                }
            }
        }
    }
}

/// The documented one-sided derivatives, asserted as values: on an interior border the
/// slope of the cell above, at 1 the slope of the last cell, at 0 the first cell's, and
/// zero outside.
#[test]
fn border_derivatives_are_the_documented_one_sided_values() {
    // One row of samples 0, 1, 3, 6 along W (slopes ×3: 3, 6, 9 per unit coordinate).
    let f = Tensor::new(&[0.0f64, 1.0, 3.0, 6.0], &Device::Cpu)
        .unwrap()
        .reshape((1, 1, 1, 4))
        .unwrap();
    let cases = [
        (0.0, 3.0),
        (1.0 / 3.0, 6.0),
        (2.0 / 3.0, 9.0),
        (1.0, 9.0),
        (1.5, 0.0),
        (-0.25, 0.0),
    ];
    for reference in [false, true] {
        for &(c, want) in &cases {
            let x =
                Var::from_tensor(&Tensor::new(&[[[c, 0.5f64]]], &Device::Cpu).unwrap()).unwrap();
            let y = if reference {
                reference_sample(&f, x.as_tensor()).unwrap()
            } else {
                fused_sample(&f, x.as_tensor()).unwrap()
            };
            let g = v64(y
                .sum_all()
                .unwrap()
                .backward()
                .unwrap()
                .get(x.as_tensor())
                .unwrap());
            assert!((g[0] - want).abs() < 1e-9, "c = {c}: {} vs {want}", g[0]);
            assert_eq!(g[1], 0.0, "a one-sample axis has no slope");
        }
    }
}

fn digest(v: &[f64]) -> u64 {
    v.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, x| {
        (h ^ (*x as f32).to_bits() as u64 ^ x.to_bits()).wrapping_mul(0x0100_0000_01b3)
    })
}

fn gradient_digest() -> u64 {
    let mut rng = SplitMix64::new(11);
    let (b, c, s, n) = (2usize, 9usize, 24usize, 6000usize);
    let f: Vec<f64> = (0..b * c * s * s * s)
        .map(|_| rng.uniform() - 0.5)
        .collect();
    let x: Vec<f64> = (0..b * n * 3).map(|_| rng.uniform()).collect();
    let p = Problem {
        fdims: vec![b, c, s, s, s],
        f,
        n,
        x,
    };
    let [y, gf, gx] = p.run(false, DType::F32);
    digest(&y) ^ digest(&gf).rotate_left(1) ^ digest(&gx).rotate_left(2)
}

/// The fused op's values and gradients do not depend on the number of threads: this test
/// runs itself in child processes with 1, 2 and 5 threads (`CANDLE_NUM_THREADS`, which
/// sizes candle's CPU pool) and compares the digests they print.
#[test]
fn gradient_bits_do_not_depend_on_the_thread_count() {
    const NAME: &str = "gradient_bits_do_not_depend_on_the_thread_count";
    if std::env::var_os("NF_DIGEST_CHILD").is_some() {
        println!("digest={:016x}", gradient_digest());
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

/// Brute-force scatter mean and max on the host, ties included: the max passes its
/// gradient to the lowest point index among equal values.
#[test]
fn scatters_match_brute_force_and_the_tie_rule() {
    let mut rng = SplitMix64::new(5);
    let (b, n, c, cells) = (2usize, 30usize, 3usize, 7usize);
    // Values on a coarse lattice so that ties are frequent.
    let v: Vec<f64> = (0..b * n * c).map(|_| rng.below(4) as f64 - 2.0).collect();
    let idx: Vec<u32> = (0..b * n)
        .map(|_| rng.below(cells as u64 - 2) as u32)
        .collect();
    let index = Tensor::from_vec(idx.clone(), (b, n), &Device::Cpu).unwrap();
    let (mut mean, mut max) = (vec![0.0; b * cells * c], vec![0.0; b * cells * c]);
    let mut arg = vec![usize::MAX; b * cells * c];
    let mut count = vec![0.0; b * cells];
    for bi in 0..b {
        for p in 0..n {
            let q = bi * cells + idx[bi * n + p] as usize;
            count[q] += 1.0;
            for j in 0..c {
                let x = v[(bi * n + p) * c + j];
                mean[q * c + j] += x;
                if arg[q * c + j] == usize::MAX || x > max[q * c + j] {
                    max[q * c + j] = x;
                    arg[q * c + j] = bi * n + p;
                }
            }
        }
    }
    for q in 0..b * cells {
        for j in 0..c {
            mean[q * c + j] /= f64::max(count[q], 1.0);
        }
    }
    let var = Var::from_vec(v.clone(), (b, n, c), &Device::Cpu).unwrap();
    let got = v64(&mean_pool(var.as_tensor(), &index, cells).unwrap());
    assert!(max_diff(&got, &mean) < 1e-12);
    for dtype in [DType::F64, DType::F32] {
        let var = Var::from_tensor(&var.as_tensor().to_dtype(dtype).unwrap()).unwrap();
        for reference in [false, true] {
            let y = if reference {
                max_pool_reference(var.as_tensor(), &index, cells).unwrap()
            } else {
                max_pool(var.as_tensor(), &index, cells).unwrap()
            };
            assert_eq!(v64(&y), max, "reference {reference}");
            let w: Vec<f64> = (0..b * cells * c).map(|i| 1.0 + i as f64).collect();
            let w = Tensor::from_vec(w.clone(), (b, cells, c), &Device::Cpu)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let g = v64((y * &w)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap()
                .get(var.as_tensor())
                .unwrap());
            let mut want = vec![0.0; b * n * c];
            for (qj, &a) in arg.iter().enumerate() {
                if a != usize::MAX {
                    want[a * c + qj % c] = 1.0 + qj as f64;
                }
            }
            assert_eq!(g, want, "reference {reference} {dtype:?}");
        }
    }
}

#[test]
fn cell_index_is_x_fastest_and_clamps() {
    let p = Tensor::new(
        &[[
            [0.0f64, 0.0, 0.0],
            [0.999_999_9, 0.5, 0.26],
            [1.0, 1.0, 1.0],
            [-3.0, 7.0, 0.0],
            [f64::INFINITY, f64::NEG_INFINITY, 0.75],
        ]],
        &Device::Cpu,
    )
    .unwrap();
    let ids = cell_index(&p, 4)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<u32>()
        .unwrap();
    assert_eq!(ids, [0, 3 + 4 * (2 + 4), 63, 4 * 3, 3 + 4 * 4 * 3]);
    let p2 = p.narrow(2, 0, 2).unwrap().to_dtype(DType::F32).unwrap();
    let ids = cell_index(&p2, 4)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<u32>()
        .unwrap();
    assert_eq!(ids, [0, 3 + 4 * 2, 15, 12, 3]);
}

#[test]
fn zero_points_give_empty_results() {
    let f =
        Var::from_tensor(&Tensor::ones((2, 3, 4, 5), DType::F64, &Device::Cpu).unwrap()).unwrap();
    let x = Tensor::zeros((2, 0, 2), DType::F64, &Device::Cpu).unwrap();
    for reference in [false, true] {
        let y = if reference {
            reference_sample(f.as_tensor(), &x).unwrap()
        } else {
            fused_sample(f.as_tensor(), &x).unwrap()
        };
        assert_eq!(y.dims(), &[2, 0, 3]);
        let g = y.sum_all().unwrap().backward().unwrap();
        if let Some(gf) = g.get(f.as_tensor()) {
            assert!(v64(gf).iter().all(|&v| v == 0.0));
        }
    }
    let v = Tensor::zeros((2, 0, 3), DType::F32, &Device::Cpu).unwrap();
    let i = Tensor::zeros((2, 0), DType::U32, &Device::Cpu).unwrap();
    for y in [
        mean_pool(&v, &i, 5).unwrap(),
        max_pool(&v, &i, 5).unwrap(),
        max_pool_reference(&v, &i, 5).unwrap(),
    ] {
        assert_eq!(y.dims(), &[2, 5, 3]);
        assert!(v64(&y).iter().all(|&x| x == 0.0));
    }
    let c = Tensor::zeros((1, 0, 3), DType::F32, &Device::Cpu).unwrap();
    assert_eq!(cell_index(&c, 8).unwrap().dims(), &[1, 0]);
}

fn arg_of(e: neural_fields::Error) -> String {
    match e {
        neural_fields::Error::InvalidArgument { arg, .. } => arg.to_string(),
        other => panic!("not an argument error: {other}"),
    }
}

#[test]
fn bad_inputs_are_errors_naming_the_argument() {
    let d = Device::Cpu;
    let f = Tensor::ones((1, 2, 3, 3), DType::F32, &d).unwrap();
    let x = Tensor::full(0.5f32, (1, 4, 2), &d).unwrap();
    let nan = Tensor::new(&[[[0.5f32, f32::NAN]]], &d).unwrap();
    let cases: Vec<(neural_fields::Result<Tensor>, &str)> = vec![
        (fused_sample(&f.flatten_all().unwrap(), &x), "features"),
        (
            fused_sample(&Tensor::ones((1, 2, 0, 3), DType::F32, &d).unwrap(), &x),
            "features",
        ),
        (
            fused_sample(&f, &Tensor::full(0.5f32, (1, 4, 3), &d).unwrap()),
            "coords",
        ),
        (
            fused_sample(&f, &Tensor::full(0.5f32, (2, 4, 2), &d).unwrap()),
            "coords",
        ),
        (fused_sample(&f, &x.to_dtype(DType::F64).unwrap()), "coords"),
        (fused_sample(&f, &nan), "coords"),
        (reference_sample(&f, &nan), "coords"),
        (
            fused_sample(&f.to_dtype(DType::U32).unwrap(), &x),
            "features",
        ),
        (cell_index(&nan, 4), "coords"),
        (cell_index(&x, 0), "resolution"),
        (cell_index(&x, 1 << 16), "resolution"),
        (
            cell_index(&Tensor::zeros((1, 4, 4), DType::F32, &d).unwrap(), 4),
            "coords",
        ),
    ];
    for (i, (r, arg)) in cases.into_iter().enumerate() {
        assert_eq!(arg_of(r.unwrap_err()), arg, "case {i}");
    }
    let v = Tensor::ones((1, 3, 2), DType::F32, &d).unwrap();
    let good = Tensor::new(&[[0u32, 1, 2]], &d).unwrap();
    let far = Tensor::new(&[[0u32, 3, 2]], &d).unwrap();
    let wrong_type = good.to_dtype(DType::F32).unwrap();
    let wrong_shape = Tensor::new(&[[0u32, 1]], &d).unwrap();
    type Op = fn(&Tensor, &Tensor, usize) -> neural_fields::Result<Tensor>;
    for op in [mean_pool as Op, max_pool as Op, max_pool_reference as Op] {
        assert!(op(&v, &good, 3).is_ok());
        for bad in [&far, &wrong_type, &wrong_shape] {
            assert_eq!(arg_of(op(&v, bad, 3).unwrap_err()), "index");
        }
        let msg = op(&v, &far, 3).unwrap_err().to_string();
        assert!(msg.contains("3 at [0, 1]"), "{msg}");
        assert_eq!(
            arg_of(op(&v.to_dtype(DType::U8).unwrap(), &good, 3).unwrap_err()),
            "values"
        );
    }
}
