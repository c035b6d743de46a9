//! Cone casting (`volume::conical_frustums`): the closed-form moments against a direct
//! numerical integral over the frustum, the thin-interval limit, full vs diagonal, both
//! layouts, f32 vs f64, gradients against finite differences, bad input.

#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::{central_diff_bound, close, v64};
use neural_fields::camera::Rays;
use neural_fields::volume::{conical_frustums, Covariance, Intervals, Layout, Packed};
use proptest::prelude::*;

const DEV: Device = Device::Cpu;

fn rays(o: &[[f64; 3]], d: &[[f64; 3]], dtype: DType) -> Rays {
    let n = o.len();
    let flat = |v: &[[f64; 3]]| v.iter().flatten().copied().collect::<Vec<f64>>();
    Rays::new(
        Tensor::from_vec(flat(o), (n, 3), &DEV)
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
        Tensor::from_vec(flat(d), (n, 3), &DEV)
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
    )
    .unwrap()
}

fn t(values: &[f64], shape: &[usize], dtype: DType) -> Tensor {
    Tensor::from_vec(values.to_vec(), shape, &DEV)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

fn batched(starts: &[f64], ends: &[f64], r: usize, dtype: DType) -> Intervals {
    let s = starts.len() / r;
    Intervals::new(
        t(starts, &[r, s], dtype),
        t(ends, &[r, s], dtype),
        Layout::Batched,
    )
    .unwrap()
}

fn packed(starts: &[f64], ends: &[f64], counts: &[usize], dtype: DType) -> Intervals {
    let p = Packed::from_counts(counts, &DEV).unwrap();
    let m = starts.len();
    Intervals::new(
        t(starts, &[m], dtype),
        t(ends, &[m], dtype),
        Layout::Packed(p),
    )
    .unwrap()
}

/// Mean and full covariance of the uniform conical frustum of `[t0, t1]` along the ray
/// `o + t·d` whose cross-section at `t` is a disc of radius `r·t` perpendicular to `d`,
/// by a midpoint rule over (t, ρ, θ) with the volume element `t²·ρ`.
fn frustum_moments(
    o: [f64; 3],
    d: [f64; 3],
    r: f64,
    t0: f64,
    t1: f64,
) -> ([f64; 3], [[f64; 3]; 3]) {
    let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let u = [d[0] / norm, d[1] / norm, d[2] / norm];
    // e1 ⊥ u, e2 = u × e1.
    let a = if u[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let dot = a[0] * u[0] + a[1] * u[1] + a[2] * u[2];
    let mut e1 = [a[0] - dot * u[0], a[1] - dot * u[1], a[2] - dot * u[2]];
    let n1 = (e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]).sqrt();
    e1.iter_mut().for_each(|x| *x /= n1);
    let e2 = [
        u[1] * e1[2] - u[2] * e1[1],
        u[2] * e1[0] - u[0] * e1[2],
        u[0] * e1[1] - u[1] * e1[0],
    ];
    let (nt, nr, na) = (400usize, 64usize, 32usize);
    let mut pts = Vec::with_capacity(nt * nr * na);
    for i in 0..nt {
        let tt = t0 + (t1 - t0) * (i as f64 + 0.5) / nt as f64;
        for j in 0..nr {
            let rho = (j as f64 + 0.5) / nr as f64;
            for k in 0..na {
                let th = std::f64::consts::TAU * (k as f64 + 0.5) / na as f64;
                let (c, s) = (th.cos(), th.sin());
                let w = tt * tt * rho;
                let x: [f64; 3] = std::array::from_fn(|q| {
                    o[q] + tt * d[q] + tt * r * rho * (c * e1[q] + s * e2[q])
                });
                pts.push((w, x));
            }
        }
    }
    let wsum: f64 = pts.iter().map(|p| p.0).sum();
    let mean: [f64; 3] =
        std::array::from_fn(|q| pts.iter().map(|(w, x)| w * x[q]).sum::<f64>() / wsum);
    let cov: [[f64; 3]; 3] = std::array::from_fn(|p| {
        std::array::from_fn(|q| {
            pts.iter()
                .map(|(w, x)| w * (x[p] - mean[p]) * (x[q] - mean[q]))
                .sum::<f64>()
                / wsum
        })
    });
    (mean, cov)
}

#[test]
fn moments_match_a_numerical_integral_over_the_frustum() {
    let o = [0.1, -0.2, 0.3];
    let d = [0.3, -0.5, 1.2];
    let norm2 = 0.09 + 0.25 + 1.44;
    let u: Vec<f64> = d.iter().map(|x| x / f64::sqrt(norm2)).collect();
    for (t0, t1, r) in [
        (1.0, 1.5, 0.3),
        (0.0, 1.0, 0.5),
        (2.0, 2.001, 0.05),
        (0.5, 4.0, 0.1),
        (10.0, 11.0, 0.02),
    ] {
        let ry = rays(&[o], &[d], DType::F64);
        let iv = batched(&[t0], &[t1], 1, DType::F64);
        let radii = t(&[r], &[1], DType::F64);
        let g = conical_frustums(
            &ry.clone().with_radii(radii.clone()).unwrap(),
            &iv,
            Covariance::Full,
        )
        .unwrap();
        let (mean, cov) = frustum_moments(o, d, r, t0, t1);
        let got_mean = v64(&g.means);
        let got_cov = v64(&g.covariances);
        for q in 0..3 {
            assert!(
                close(got_mean[q], mean[q], 1e-4, 1.0),
                "[{t0}, {t1}] mean {q}: {} vs {}",
                got_mean[q],
                mean[q]
            );
        }
        let scale = cov.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
        for p in 0..3 {
            for q in 0..3 {
                assert!(
                    close(got_cov[3 * p + q], cov[p][q], 1e-3, scale),
                    "[{t0}, {t1}] cov {p}{q}: {} vs {}",
                    got_cov[3 * p + q],
                    cov[p][q]
                );
            }
        }
        // Along the ray and across it separately (the thin interval's variance along
        // the ray is swamped by the radial one in the entries).
        let quad = |c: &dyn Fn(usize, usize) -> f64| -> f64 {
            (0..3)
                .flat_map(|p| (0..3).map(move |q| (p, q)))
                .map(|(p, q)| u[p] * c(p, q) * u[q])
                .sum()
        };
        let along_got = quad(&|p, q| got_cov[3 * p + q]);
        let along_num = quad(&|p, q| cov[p][q]);
        assert!(
            close(along_got, along_num, 1e-3, 0.0),
            "[{t0}, {t1}] variance along the ray: {along_got} vs {along_num}"
        );
        let trace_got = got_cov[0] + got_cov[4] + got_cov[8] - along_got;
        let trace_num = cov[0][0] + cov[1][1] + cov[2][2] - along_num;
        assert!(
            close(trace_got, trace_num, 1e-3, 0.0),
            "[{t0}, {t1}] radial variance: {trace_got} vs {trace_num}"
        );
    }
}

#[test]
fn a_thin_interval_is_a_disc() {
    let o = [0.5, 0.0, -1.0];
    let d = [0.0, 0.6, 0.8]; // unit
    let (tm, r) = (3.0, 0.01);
    let ry = rays(&[o], &[d], DType::F64);
    let iv = batched(&[tm - 1e-7], &[tm + 1e-7], 1, DType::F64);
    let g = conical_frustums(
        &ry.clone().with_radii(t(&[r], &[1], DType::F64)).unwrap(),
        &iv,
        Covariance::Full,
    )
    .unwrap();
    let mean = v64(&g.means);
    for q in 0..3 {
        assert!(close(mean[q], o[q] + tm * d[q], 1e-12, 1.0), "{mean:?}");
    }
    let c = v64(&g.covariances);
    let along: f64 = (0..3)
        .flat_map(|p| (0..3).map(move |q| (p, q)))
        .map(|(p, q)| d[p] * c[3 * p + q] * d[q])
        .sum();
    assert!(along.abs() < 1e-13, "variance along the ray {along}");
    let radial = (c[0] + c[4] + c[8] - along) / 2.0;
    assert!(close(radial, r * r * tm * tm / 4.0, 1e-9, 0.0), "{radial}");
}

/// Origins, directions, radii, starts and ends of three rays with three intervals each.
type Sample = (Vec<[f64; 3]>, Vec<[f64; 3]>, Vec<f64>, Vec<f64>, Vec<f64>);

fn sample_inputs() -> Sample {
    let o = vec![[0.1, -0.2, 0.3], [-1.0, 2.0, 0.5], [0.0, 0.0, -4.0]];
    let d = vec![[0.3, -0.5, 1.2], [1e-3, 2e-3, 1e-3], [0.0, 0.0, 1.0]];
    let radii = vec![0.01, 0.3, 0.0];
    let starts = vec![0.0, 1.0, 2.5, 100.0, 101.0, 1e4, 1e-3, 2.0, 2.0];
    let ends = vec![1.0, 2.5, 2.6, 101.0, 200.0, 1e4 + 1e-3, 2.0, 2.0, 3.0];
    (o, d, radii, starts, ends)
}

#[test]
fn diagonal_is_the_diagonal_of_full_in_both_layouts_and_dtypes() {
    let (o, d, radii, starts, ends) = sample_inputs();
    let mut per_dtype = Vec::new();
    for dtype in [DType::F32, DType::F64] {
        let ry = rays(&o, &d, dtype);
        let rad = t(&radii, &[3], dtype);
        let b = batched(&starts, &ends, 3, dtype);
        let p = packed(&starts, &ends, &[3, 3, 3], dtype);
        let gb = conical_frustums(
            &ry.clone().with_radii(rad.clone()).unwrap(),
            &b,
            Covariance::Diagonal,
        )
        .unwrap();
        let gf = conical_frustums(
            &ry.clone().with_radii(rad.clone()).unwrap(),
            &b,
            Covariance::Full,
        )
        .unwrap();
        let pd = conical_frustums(
            &ry.clone().with_radii(rad.clone()).unwrap(),
            &p,
            Covariance::Diagonal,
        )
        .unwrap();
        let pf = conical_frustums(
            &ry.clone().with_radii(rad.clone()).unwrap(),
            &p,
            Covariance::Full,
        )
        .unwrap();
        assert_eq!(gb.means.dims(), &[3, 3, 3]);
        assert_eq!(gb.covariances.dims(), &[3, 3, 3]);
        assert_eq!(gf.covariances.dims(), &[3, 3, 3, 3]);
        assert_eq!(pd.means.dims(), &[9, 3]);
        assert_eq!(pd.covariances.dims(), &[9, 3]);
        assert_eq!(pf.covariances.dims(), &[9, 3, 3]);
        assert_eq!(gb.means.dtype(), dtype);
        let diag = v64(&gb.covariances);
        let full = v64(&gf.covariances);
        for i in 0..9 {
            for q in 0..3 {
                assert_eq!(diag[3 * i + q], full[9 * i + 4 * q], "sample {i} axis {q}");
            }
        }
        // Full covariances are symmetric.
        for i in 0..9 {
            for p in 0..3 {
                for q in 0..3 {
                    assert_eq!(full[9 * i + 3 * p + q], full[9 * i + 3 * q + p]);
                }
            }
        }
        assert_eq!(v64(&gb.means), v64(&pd.means));
        assert_eq!(diag, v64(&pd.covariances));
        assert_eq!(full, v64(&pf.covariances));
        per_dtype.push((v64(&gb.means), full));
    }
    let ((m32, c32), (m64, c64)) = (&per_dtype[0], &per_dtype[1]);
    for (a, b) in m32.iter().zip(m64) {
        assert!(close(*a, *b, 1e-5, 1.0), "mean f32 {a} vs f64 {b}");
    }
    let scale = c64.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    for (a, b) in c32.iter().zip(c64) {
        assert!(close(*a, *b, 1e-4, 1e-6 * scale), "cov f32 {a} vs f64 {b}");
    }
}

#[test]
fn packed_rays_may_have_no_samples() {
    let (o, d, radii, starts, ends) = sample_inputs();
    let ry = rays(&o, &d, DType::F64);
    let rad = t(&radii, &[3], DType::F64);
    let b = batched(&starts, &ends, 3, DType::F64);
    let p = packed(&starts[..3], &ends[..3], &[3, 0, 0], DType::F64);
    let gb = conical_frustums(
        &ry.clone().with_radii(rad.clone()).unwrap(),
        &b,
        Covariance::Full,
    )
    .unwrap();
    let gp = conical_frustums(
        &ry.clone().with_radii(rad.clone()).unwrap(),
        &p,
        Covariance::Full,
    )
    .unwrap();
    assert_eq!(v64(&gp.covariances), v64(&gb.covariances)[..27].to_vec());
    let empty = packed(&[], &[], &[0, 0, 0], DType::F64);
    let ge = conical_frustums(
        &ry.clone().with_radii(rad.clone()).unwrap(),
        &empty,
        Covariance::Diagonal,
    )
    .unwrap();
    assert_eq!(ge.means.dims(), &[0, 3]);
}

#[test]
fn bad_input_names_the_argument() {
    let (o, d, radii, starts, ends) = sample_inputs();
    let ry = rays(&o, &d, DType::F32);
    let iv = batched(&starts, &ends, 3, DType::F32);
    let err = |radii: &Tensor, iv: &Intervals, ry: &Rays| {
        ry.clone()
            .with_radii(radii.clone())
            .and_then(|ry| conical_frustums(&ry, iv, Covariance::Diagonal))
            .unwrap_err()
            .to_string()
    };
    let e = err(&t(&[0.1, 0.1], &[2], DType::F32), &iv, &ry);
    assert!(e.starts_with("radii"), "{e}");
    let e = err(&t(&radii, &[3, 1], DType::F32), &iv, &ry);
    assert!(e.starts_with("radii"), "{e}");
    let e = err(&t(&radii, &[3], DType::F64), &iv, &ry);
    assert!(e.starts_with("radii"), "{e}");
    let e = err(&t(&[0.1, -0.1, 0.0], &[3], DType::F32), &iv, &ry);
    assert!(e.starts_with("radii"), "{e}");
    let e = err(&t(&[0.1, f64::NAN, 0.0], &[3], DType::F32), &iv, &ry);
    assert!(e.starts_with("radii"), "{e}");
    let e = err(&t(&[0.1, f64::INFINITY, 0.0], &[3], DType::F32), &iv, &ry);
    assert!(e.starts_with("radii"), "{e}");
    let two = rays(&o[..2], &d[..2], DType::F32);
    let e = err(&t(&radii[..2], &[2], DType::F32), &iv, &two);
    assert!(e.starts_with("rays"), "{e}");
    // Rays without cone radii cannot be cast.
    let e = conical_frustums(&ry, &iv, Covariance::Diagonal)
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("rays") && e.contains("radii"), "{e}");
    let iv64 = batched(&starts, &ends, 3, DType::F64);
    let e = err(&t(&radii, &[3], DType::F32), &iv64, &ry);
    assert!(e.starts_with("rays"), "{e}");
}

/// Inputs of the gradient check: one ray per row, two separated intervals per ray.
#[derive(Clone, Debug)]
struct Inputs {
    o: Vec<f64>,
    d: Vec<f64>,
    radii: Vec<f64>,
    starts: Vec<f64>,
    ends: Vec<f64>,
}

/// `Σ wm·means` (`part` 0) or `Σ wc·covariances` (`part` 1), with the inputs as
/// variables when `vars` is given.
fn loss(
    x: &Inputs,
    cov: Covariance,
    packed_layout: bool,
    part: usize,
    vars: Option<&[Var; 5]>,
) -> Tensor {
    let r = x.radii.len();
    let tensors: Vec<Tensor> = match vars {
        Some(v) => v.iter().map(|v| v.as_tensor().clone()).collect(),
        None => vec![
            t(&x.o, &[r, 3], DType::F64),
            t(&x.d, &[r, 3], DType::F64),
            t(&x.radii, &[r], DType::F64),
            t(&x.starts, &[r, 2], DType::F64),
            t(&x.ends, &[r, 2], DType::F64),
        ],
    };
    let ry = Rays::new(tensors[0].clone(), tensors[1].clone())
        .unwrap()
        .with_radii(tensors[2].clone())
        .unwrap();
    let iv = if packed_layout {
        let p = Packed::from_counts(&vec![2; r], &DEV).unwrap();
        Intervals::new(
            tensors[3].flatten_all().unwrap(),
            tensors[4].flatten_all().unwrap(),
            Layout::Packed(p),
        )
        .unwrap()
    } else {
        Intervals::new(tensors[3].clone(), tensors[4].clone(), Layout::Batched).unwrap()
    };
    let g = conical_frustums(&ry, &iv, cov).unwrap();
    let weights = |n: usize, seed: f64| -> Tensor {
        let w: Vec<f64> = (0..n).map(|i| ((i as f64 + 1.0) * seed).sin()).collect();
        t(&w, &[n], DType::F64)
    };
    let m = g.means.flatten_all().unwrap();
    let c = g.covariances.flatten_all().unwrap();
    let lm = (&m * weights(m.elem_count(), 0.7))
        .unwrap()
        .sum_all()
        .unwrap();
    let lc = (&c * weights(c.elem_count(), 1.3))
        .unwrap()
        .sum_all()
        .unwrap();
    if part == 0 {
        lm
    } else {
        lc
    }
}

fn check_gradients(
    x: &Inputs,
    cov: Covariance,
    packed_layout: bool,
    part: usize,
) -> Result<(), TestCaseError> {
    let r = x.radii.len();
    let vars = [
        Var::from_tensor(&t(&x.o, &[r, 3], DType::F64)).unwrap(),
        Var::from_tensor(&t(&x.d, &[r, 3], DType::F64)).unwrap(),
        Var::from_tensor(&t(&x.radii, &[r], DType::F64)).unwrap(),
        Var::from_tensor(&t(&x.starts, &[r, 2], DType::F64)).unwrap(),
        Var::from_tensor(&t(&x.ends, &[r, 2], DType::F64)).unwrap(),
    ];
    let l = loss(x, cov, packed_layout, part, Some(&vars));
    let scale = l.to_scalar::<f64>().unwrap().abs().max(1e-300);
    let grads = l.backward().unwrap();
    let names = ["origins", "directions", "radii", "starts", "ends"];
    let (mut checked, mut total) = (0usize, 0usize);
    for (k, v) in vars.iter().enumerate() {
        // No gradient: the loss does not depend on it (the radii of the means).
        let ad = grads.get(v).map_or_else(|| vec![0.0; v.elem_count()], v64);
        let host = match k {
            0 => &x.o,
            1 => &x.d,
            2 => &x.radii,
            3 => &x.starts,
            _ => &x.ends,
        };
        for (i, &x0) in host.iter().enumerate() {
            // Steps small beside what each input may move by: the interval's own
            // length for t (the intervals stay valid), the radius itself.
            let h = match k {
                3 | 4 => {
                    let j = i;
                    1e-3 * (x.ends[j] - x.starts[j])
                        .max(1e-6 * x.ends[j].abs())
                        .max(1e-9)
                }
                2 => 1e-3 * x0.max(1e-6),
                1 => {
                    let row = &x.d[3 * (i / 3)..3 * (i / 3) + 3];
                    1e-3 * row.iter().fold(0.0f64, |m, v| m.max(v.abs()))
                }
                _ => 1e-3 * (x0.abs() + 1.0),
            };
            let mut f = |val: f64| {
                let mut y = x.clone();
                match k {
                    0 => y.o[i] = val,
                    1 => y.d[i] = val,
                    2 => y.radii[i] = val,
                    3 => y.starts[i] = val,
                    _ => y.ends[i] = val,
                }
                loss(&y, cov, packed_layout, part, None)
                    .to_scalar::<f64>()
                    .unwrap()
            };
            total += 1;
            let Some((fd, bar)) = central_diff_bound(&mut f, x0, h, scale) else {
                continue;
            };
            checked += 1;
            prop_assert!(
                (ad[i] - fd).abs() <= 1e-5 * ad[i].abs().max(fd.abs()) + 2.0 * bar,
                "{cov:?} packed {packed_layout} part {part}: d/d{}[{i}] AD {} vs FD {fd} (h {h})\n{x:?}",
                names[k],
                ad[i]
            );
        }
    }
    prop_assert!(
        2 * checked >= total,
        "only {checked} of {total} finite differences were resolved\n{x:?}"
    );
    Ok(())
}

fn inputs() -> impl Strategy<Value = Inputs> {
    let ray = (
        prop::array::uniform3(-2.0f64..2.0),
        prop::array::uniform3(-1.0f64..1.0),
        -3.0f64..0.0, // log10 |d| scale
        -4.0f64..0.0, // log10 radius
        -3.0f64..4.0, // log10 first start
        -5.0f64..0.5, // log10 relative length of each interval
        -5.0f64..0.5,
    );
    prop::collection::vec(ray, 1..3).prop_map(|rows| {
        let mut x = Inputs {
            o: vec![],
            d: vec![],
            radii: vec![],
            starts: vec![],
            ends: vec![],
        };
        for (o, d, ds, lr, lt, l1, l2) in rows {
            x.o.extend(o);
            let mut d = d;
            if d.iter().all(|v| v.abs() < 0.1) {
                d[2] = 1.0;
            }
            x.d.extend(d.map(|v| v * 10f64.powf(ds)));
            x.radii.push(10f64.powf(lr));
            let t0 = 10f64.powf(lt);
            let t1 = t0 * (1.0 + 10f64.powf(l1));
            let t2 = t1 * 1.5;
            let t3 = t2 * (1.0 + 10f64.powf(l2));
            x.starts.extend([t0, t2]);
            x.ends.extend([t1, t3]);
        }
        x
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn gradients_match_finite_differences(
        x in inputs(),
        full in proptest::bool::ANY,
        packed_layout in proptest::bool::ANY,
    ) {
        let cov = if full { Covariance::Full } else { Covariance::Diagonal };
        check_gradients(&x, cov, packed_layout, 0)?;
        check_gradients(&x, cov, packed_layout, 1)?;
    }
}
