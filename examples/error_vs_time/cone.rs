//! mip-NeRF's Gaussians: cone casting's closed-form frustum moments against a numerical
//! integral over the frustum with more and more quadrature points, and scene
//! contraction's linearised push-forward of Gaussians against Monte Carlo estimates of
//! the true push-forward covariance.

use crate::report::{median_seconds, v64, Row, Table, TIME_PER_CALL};
use candle_core::{DType, Device, Tensor};
use neural_fields::camera::Rays;
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{conical_frustums, contract, Covariance, Intervals, Layout};

pub fn run(quick: bool) -> Vec<Table> {
    vec![cone_table(quick), contraction_table(quick)]
}

/// One frustum: origin, direction, radius per unit t, interval.
#[derive(Clone, Copy)]
struct Frustum {
    o: [f64; 3],
    d: [f64; 3],
    r: f64,
    t0: f64,
    t1: f64,
}

fn frustums(n: usize) -> Vec<Frustum> {
    let mut rng = SplitMix64::new(5);
    (0..n)
        .map(|_| {
            let t0 = 0.5 + 5.0 * rng.uniform();
            Frustum {
                o: std::array::from_fn(|_| rng.uniform() - 0.5),
                d: [rng.uniform() - 0.5, rng.uniform() - 0.5, 1.0],
                r: 0.002 + 0.02 * rng.uniform(),
                t0,
                t1: t0 + 0.02 + 0.5 * rng.uniform(),
            }
        })
        .collect()
}

/// The mean and full covariance of one uniform frustum by the midpoint rule with `n`
/// points in `t` and in the radius and 4 in the angle (exact for the angular part of
/// moments up to order 2), volume element `t²ρ`.
fn quadrature(f: &Frustum, n: usize) -> [f64; 12] {
    let norm = f.d.iter().map(|x| x * x).sum::<f64>().sqrt();
    let u = f.d.map(|x| x / norm);
    let a = if u[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let dot: f64 = (0..3).map(|i| a[i] * u[i]).sum();
    let e1 = {
        let v: [f64; 3] = std::array::from_fn(|i| a[i] - dot * u[i]);
        let l = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        v.map(|x| x / l)
    };
    let e2 = [
        u[1] * e1[2] - u[2] * e1[1],
        u[2] * e1[0] - u[0] * e1[2],
        u[0] * e1[1] - u[1] * e1[0],
    ];
    let (mut w_sum, mut m, mut c) = (0.0, [0.0f64; 3], [[0.0f64; 3]; 3]);
    let mut pts = Vec::with_capacity(n * n * 4);
    for i in 0..n {
        let t = f.t0 + (f.t1 - f.t0) * (i as f64 + 0.5) / n as f64;
        for j in 0..n {
            let rho = (j as f64 + 0.5) / n as f64;
            for k in 0..4 {
                let th = std::f64::consts::TAU * (k as f64 + 0.5) / 4.0;
                let (s, co) = th.sin_cos();
                let w = t * t * rho;
                let x: [f64; 3] = std::array::from_fn(|q| {
                    f.o[q] + t * f.d[q] + t * f.r * rho * (co * e1[q] + s * e2[q])
                });
                w_sum += w;
                (0..3).for_each(|q| m[q] += w * x[q]);
                pts.push((w, x));
            }
        }
    }
    m = m.map(|x| x / w_sum);
    for (w, x) in &pts {
        for p in 0..3 {
            for q in 0..3 {
                c[p][q] += w * (x[p] - m[p]) * (x[q] - m[q]);
            }
        }
    }
    let mut out = [0.0; 12];
    out[..3].copy_from_slice(&m);
    for p in 0..3 {
        for q in 0..3 {
            out[3 + 3 * p + q] = c[p][q] / w_sum;
        }
    }
    out
}

/// The closed form in `dtype`: `[n, 12]` rows of mean and covariance.
fn closed_form(fs: &[Frustum], dtype: DType) -> Tensor {
    let n = fs.len();
    let dev = Device::Cpu;
    let t = |v: Vec<f64>, shape: &[usize]| {
        Tensor::from_vec(v, shape, &dev)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
    };
    let rays = Rays::new(
        t(fs.iter().flat_map(|f| f.o).collect(), &[n, 3]),
        t(fs.iter().flat_map(|f| f.d).collect(), &[n, 3]),
    )
    .unwrap()
    .with_radii(t(fs.iter().map(|f| f.r).collect(), &[n]))
    .unwrap();
    let iv = Intervals::new(
        t(fs.iter().map(|f| f.t0).collect(), &[n, 1]),
        t(fs.iter().map(|f| f.t1).collect(), &[n, 1]),
        Layout::Batched,
    )
    .unwrap();
    let g = conical_frustums(&rays, &iv, Covariance::Full).unwrap();
    Tensor::cat(
        &[
            g.means.reshape((n, 3)).unwrap(),
            g.covariances.reshape((n, 9)).unwrap(),
        ],
        1,
    )
    .unwrap()
}

/// The largest error of the means (relative to the distance from the origin of the ray)
/// and of the covariances (relative to each frustum's largest covariance entry).
fn moment_error(got: &[f64], reference: &[f64]) -> f64 {
    let mut worst: f64 = 0.0;
    for (a, b) in got.chunks(12).zip(reference.chunks(12)) {
        let mscale = b[..3].iter().fold(1.0f64, |s, x| s.max(x.abs()));
        let cscale = b[3..].iter().fold(0.0f64, |s, x| s.max(x.abs()));
        for q in 0..3 {
            worst = worst.max((a[q] - b[q]).abs() / mscale);
        }
        for q in 3..12 {
            worst = worst.max((a[q] - b[q]).abs() / cscale);
        }
    }
    worst
}

fn cone_table(quick: bool) -> Table {
    let n = if quick { 32 } else { 1024 };
    let reps = if quick { 1 } else { 5 };
    let fs = frustums(n);
    let reference = v64(&closed_form(&fs, DType::F64));
    let mut rows = Vec::new();
    for (series, dtype) in [
        ("closed form, f64", DType::F64),
        ("closed form, f32", DType::F32),
    ] {
        let got = v64(&closed_form(&fs, dtype));
        // The f64 row's error is its disagreement with the finest quadrature below.
        let error = if dtype == DType::F64 {
            let fine: Vec<f64> = fs.iter().flat_map(|f| quadrature(f, 256)).collect();
            moment_error(&got, &fine)
        } else {
            moment_error(&got, &reference)
        };
        rows.push(Row {
            series: series.into(),
            knob: 1.0,
            error,
            seconds: median_seconds(reps, || drop(closed_form(&fs, dtype))),
            work: n as f64,
        });
    }
    let sides: &[usize] = if quick {
        &[2, 8]
    } else {
        &[2, 4, 8, 16, 32, 64]
    };
    for &side in sides {
        let got: Vec<f64> = fs.iter().flat_map(|f| quadrature(f, side)).collect();
        let seconds = median_seconds(reps, || {
            drop(fs.iter().map(|f| quadrature(f, side)).collect::<Vec<_>>())
        });
        rows.push(Row {
            series: "midpoint quadrature (f64)".into(),
            knob: (4 * side * side) as f64,
            error: moment_error(&got, &reference),
            seconds,
            work: n as f64,
        });
    }
    Table {
        title: "Cone casting: frustum moments vs quadrature points".into(),
        description: format!(
            "Mean and full covariance of {n} conical frustums (radius 0.002–0.022 per unit t, intervals of length 0.02–0.52 at t = 0.5–6) by `volume::conical_frustums` (mip-NeRF's closed form, one point per frustum) and by the midpoint rule over (t, ρ, θ) with the knob's points per frustum (n in t and in ρ, 4 in θ; weight t²ρ); error = the largest difference of a mean (relative to its largest coordinate, at least 1) or covariance entry (relative to the frustum's largest entry) against the closed form in f64; the f64 closed form's own row is its difference from the 256 × 256 × 4 quadrature. Time = median of {reps} calls for all frustums on the CPU (the quadrature in plain f64 loops)."
        ),
        knob: "points per frustum".into(),
        error_name: "max relative error".into(),
        work_unit: "frustums".into(),
        time_name: TIME_PER_CALL.into(),
        rows,
    }
}

/// `contract(x)` on the host, f64.
fn contract_host(x: [f64; 3]) -> [f64; 3] {
    let r = x.iter().map(|v| v * v).sum::<f64>().sqrt();
    if r <= 1.0 {
        x
    } else {
        let s = (2.0 - 1.0 / r) / r;
        x.map(|v| v * s)
    }
}

fn contraction_table(quick: bool) -> Table {
    let reps = if quick { 1 } else { 5 };
    // Gaussians at radii 0.5 to 50 (inside the ball, across its boundary, far out),
    // isotropic with a standard deviation of 5 % of the distance (a cone's frustum).
    let mut rng = SplitMix64::new(23);
    let count = if quick { 8 } else { 64 };
    let gaussians: Vec<([f64; 3], f64)> = (0..count)
        .map(|i| {
            let radius = [0.5, 1.2, 5.0, 50.0][i % 4];
            let dir = {
                let v: [f64; 3] = std::array::from_fn(|_| rng.normal());
                let l = v.iter().map(|x| x * x).sum::<f64>().sqrt();
                v.map(|x| x / l)
            };
            (dir.map(|x| x * radius), 0.05 * radius)
        })
        .collect();
    // The true push-forward covariance, by Monte Carlo with many samples.
    let mc = |samples: usize, seed: u64| -> Vec<[f64; 9]> {
        let mut rng = SplitMix64::new(seed);
        gaussians
            .iter()
            .map(|(mu, sd)| {
                let ys: Vec<[f64; 3]> = (0..samples)
                    .map(|_| contract_host(std::array::from_fn(|q| mu[q] + sd * rng.normal())))
                    .collect();
                let m: [f64; 3] =
                    std::array::from_fn(|q| ys.iter().map(|y| y[q]).sum::<f64>() / samples as f64);
                std::array::from_fn(|k| {
                    let (p, q) = (k / 3, k % 3);
                    ys.iter()
                        .map(|y| (y[p] - m[p]) * (y[q] - m[q]))
                        .sum::<f64>()
                        / (samples - 1) as f64
                })
            })
            .collect()
    };
    let reference = mc(if quick { 1 << 14 } else { 1 << 20 }, 99);
    let error = |got: &[[f64; 9]]| -> f64 {
        got.iter()
            .zip(&reference)
            .map(|(a, b)| {
                let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
                let den: f64 = b.iter().map(|y| y * y).sum();
                (num / den).sqrt()
            })
            .fold(0.0, f64::max)
    };
    let mut rows = Vec::new();
    let dev = Device::Cpu;
    let n = gaussians.len();
    let means = Tensor::from_vec(
        gaussians.iter().flat_map(|g| g.0).collect::<Vec<f64>>(),
        (n, 3),
        &dev,
    )
    .unwrap();
    let covs = Tensor::from_vec(
        gaussians
            .iter()
            .flat_map(|g| {
                let v = g.1 * g.1;
                [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v]
            })
            .collect::<Vec<f64>>(),
        (n, 3, 3),
        &dev,
    )
    .unwrap();
    let linear = || contract(&means, Some(&covs)).unwrap().1.unwrap();
    let got: Vec<[f64; 9]> = v64(&linear())
        .chunks(9)
        .map(|c| std::array::from_fn(|k| c[k]))
        .collect();
    rows.push(Row {
        series: "linearised (volume::contract)".into(),
        knob: 1.0,
        error: error(&got),
        seconds: median_seconds(reps, || drop(linear())),
        work: n as f64,
    });
    let counts: &[usize] = if quick {
        &[16, 256]
    } else {
        &[16, 64, 256, 1024, 4096, 16384]
    };
    for &samples in counts {
        let got = mc(samples, 7);
        rows.push(Row {
            series: "Monte Carlo".into(),
            knob: samples as f64,
            error: error(&got),
            seconds: median_seconds(reps, || drop(mc(samples, 7))),
            work: n as f64,
        });
    }
    Table {
        title: "Scene contraction of Gaussians: linearised vs Monte Carlo".into(),
        description: format!(
            "Covariance of contract(X) for {n} isotropic Gaussians X at distances 0.5, 1.2, 5 and 50 from the origin with a standard deviation of 5 % of the distance (mip-NeRF 360's contraction). `volume::contract` pushes the covariance through the Jacobian at the mean (one evaluation, the knob 1); Monte Carlo estimates it from the knob's samples; error = the largest relative Frobenius error of a covariance against a Monte Carlo estimate with {} samples (its own noise ≈ 0.3 %·√(2¹⁴/N) sets the floor). Time = median of {reps} calls for all Gaussians on the CPU (f64).",
            if quick { 1 << 14 } else { 1 << 20 }
        ),
        knob: "evaluations per Gaussian".into(),
        error_name: "max relative error".into(),
        work_unit: "Gaussians".into(),
        time_name: TIME_PER_CALL.into(),
        rows,
    }
}
