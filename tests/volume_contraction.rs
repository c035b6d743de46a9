//! mip-NeRF 360's scene contraction: the identity inside the unit ball, C¹ across its
//! boundary, radius → 2 at infinity, monotone; the Gaussians' linearised push-forward
//! against J Σ Jᵀ with J by central differences; gradients against central differences
//! in f64 over extreme radii; f32 and f64; bad inputs.
#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::{central_diff_bound, close, v64};
use neural_fields::Error;
use proptest::prelude::*;

type M3 = [[f64; 3]; 3];

fn pts(p: &[[f64; 3]], dtype: DType) -> Tensor {
    let flat: Vec<f64> = p.iter().flatten().copied().collect();
    Tensor::from_vec(flat, (p.len(), 3), &Device::Cpu)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

/// `contract` of one f64 point, on the host.
fn c1(p: [f64; 3]) -> [f64; 3] {
    let v = v64(&contract_points(&pts(&[p], DType::F64)).unwrap());
    [v[0], v[1], v[2]]
}

fn norm(p: [f64; 3]) -> f64 {
    let m = p.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if m == 0.0 {
        return 0.0;
    }
    m * p.iter().map(|v| (v / m) * (v / m)).sum::<f64>().sqrt()
}

fn scaled(dir: [f64; 3], r: f64) -> [f64; 3] {
    let n = norm(dir);
    [dir[0] / n * r, dir[1] / n * r, dir[2] / n * r]
}

/// The Jacobian of `contract` at `p` by autograd, row `i` = ∂ out_i / ∂ x.
fn jac_autograd(p: [f64; 3], dtype: DType) -> M3 {
    let mut j = [[0.0; 3]; 3];
    for (i, row) in j.iter_mut().enumerate() {
        let x = Var::from_tensor(&pts(&[p], dtype)).unwrap();
        let out = contract_points(x.as_tensor()).unwrap();
        let g = out
            .narrow(1, i, 1)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let g = v64(g.get(x.as_tensor()).unwrap());
        row.copy_from_slice(&g);
    }
    j
}

/// The Jacobian of `contract` at `p` by central differences with step `h`.
fn jac_fd(p: [f64; 3], h: f64) -> M3 {
    let mut j = [[0.0; 3]; 3];
    for (i, row) in j.iter_mut().enumerate() {
        for (k, e) in row.iter_mut().enumerate() {
            let mut f = |t: f64| {
                let mut q = p;
                q[k] = t;
                c1(q)[i]
            };
            *e = central_diff_bound(&mut f, p[k], h, 1.0)
                .unwrap_or_else(|| panic!("no clean difference at {p:?}"))
                .0;
        }
    }
    j
}

fn mul(a: &M3, b: &M3) -> M3 {
    let mut c = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    c
}

fn transpose(a: &M3) -> M3 {
    let mut t = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            t[i][j] = a[j][i];
        }
    }
    t
}

fn arg_of(e: Error) -> &'static str {
    match e {
        Error::InvalidArgument { arg, .. } => arg,
        other => panic!("expected InvalidArgument, got {other}"),
    }
}

#[test]
fn identity_inside_the_unit_ball_exactly() {
    let inside = [
        [0.0, 0.0, 0.0],
        [1e-300, -1e-300, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.3, -0.4, 0.5],
        [0.57, 0.57, -0.57],
        [-0.999_999, 0.0, 1e-6],
    ];
    for dtype in [DType::F32, DType::F64] {
        let x = pts(&inside, dtype);
        let y = contract_points(&x).unwrap();
        assert_eq!(v64(&y), v64(&x), "{dtype:?}");
        let (m, v) = contract_both(&x, &x.abs().unwrap()).unwrap();
        assert_eq!(v64(&m), v64(&x), "{dtype:?}");
        assert_eq!(v64(&v), v64(&x.abs().unwrap()), "{dtype:?}");
        for p in inside {
            let j = jac_autograd(p, dtype);
            for (i, row) in j.iter().enumerate() {
                for (k, &e) in row.iter().enumerate() {
                    assert_eq!(e, f64::from(u8::from(i == k)), "{dtype:?} {p:?}");
                }
            }
        }
    }
}

#[test]
fn value_and_jacobian_are_continuous_across_the_unit_sphere() {
    let dirs = [
        [1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0],
        [1.0, 2.0, 3.0],
        [-0.3, 0.7, -0.1],
        [1.0, 1.0, 1.0],
    ];
    for dir in dirs {
        for eps in [1e-9, 1e-12] {
            let (a, b) = (scaled(dir, 1.0 - eps), scaled(dir, 1.0 + eps));
            let (ca, cb) = (c1(a), c1(b));
            let (ja, jb) = (jac_autograd(a, DType::F64), jac_autograd(b, DType::F64));
            for i in 0..3 {
                assert!((ca[i] - cb[i]).abs() < 1e-6, "{dir:?}: {ca:?} vs {cb:?}");
                for k in 0..3 {
                    assert!(
                        (ja[i][k] - jb[i][k]).abs() < 1e-6,
                        "{dir:?} ±{eps:e}: {ja:?} vs {jb:?}"
                    );
                }
            }
        }
        // Just outside, the Jacobian from the formula agrees with central differences
        // taken entirely outside the ball.
        let p = scaled(dir, 1.0 + 1e-3);
        let (ja, jf) = (jac_autograd(p, DType::F64), jac_fd(p, 1e-5));
        for i in 0..3 {
            for k in 0..3 {
                assert!((ja[i][k] - jf[i][k]).abs() < 1e-7, "{ja:?} vs {jf:?}");
            }
        }
    }
}

#[test]
fn far_points_approach_radius_two_from_inside() {
    let dir = [0.2, -0.9, 0.4];
    for k in 1..=300 {
        let r = 10f64.powi(k);
        let p = scaled(dir, r);
        let c = c1(p);
        let rc = norm(c);
        assert!(
            rc.is_finite() && rc <= 2.0 * (1.0 + 4.0 * f64::EPSILON),
            "r {r:e}: {rc}"
        );
        assert!(
            ((2.0 - rc) - 1.0 / r).abs() <= 1e-3 / r + 8.0 * f64::EPSILON,
            "r {r:e}: {rc}"
        );
        if r < 1e14 {
            assert!(rc < 2.0, "r {r:e}: {rc}");
        }
        // Same direction.
        for i in 0..3 {
            assert!(
                close(c[i] / rc, p[i] / norm(p), 1e-12, 1e-12),
                "{c:?} vs {p:?}"
            );
        }
        for row in jac_autograd(p, DType::F64) {
            assert!(row.iter().all(|v| v.is_finite()), "r {r:e}");
        }
    }
    // f32 up to 1e30.
    for k in 1..=30 {
        let r = 10f64.powi(k);
        let x = pts(&[scaled(dir, r)], DType::F32);
        let rc = norm({
            let v = v64(&contract_points(&x).unwrap());
            [v[0], v[1], v[2]]
        });
        assert!(rc <= 2.0 * (1.0 + 4.0 * f64::from(f32::EPSILON)), "{rc}");
        assert!(
            ((2.0 - rc) - 1.0 / r).abs() <= 1e-3 / r + 8.0 * f64::from(f32::EPSILON),
            "r {r:e}: {rc}"
        );
        for row in jac_autograd(scaled(dir, r), DType::F32) {
            assert!(row.iter().all(|v| v.is_finite()), "r {r:e}");
        }
    }
}

#[test]
fn contracted_radius_is_monotone_in_the_radius() {
    let dir = [-0.5, 0.1, 0.8];
    let mut radii: Vec<f64> = (0..=400).map(|i| i as f64 * 0.01).collect();
    radii.extend((7..=300).map(|k| 10f64.powf(k as f64 / 10.0)));
    let mut last = -1.0;
    for r in radii {
        let rc = norm(c1(scaled(dir, r)));
        assert!(rc >= last, "r {r}: {rc} < {last}");
        if r < 1e6 {
            assert!(rc > last, "r {r}: {rc} not above {last}");
        }
        last = rc;
    }
}

#[test]
fn gradient_at_the_origin_is_the_identity_and_finite_everywhere_stiff() {
    let j = jac_autograd([0.0; 3], DType::F64);
    assert_eq!(j, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
    for (dtype, huge) in [
        (DType::F64, 1e300),
        (DType::F64, f64::MAX),
        (DType::F32, 1e30),
    ] {
        for p in [[huge, 0.0, 0.0], [huge, -huge, huge], [0.0, 1.0, 0.0]] {
            let p = if dtype == DType::F32 {
                p.map(|v| v.min(f64::from(f32::MAX)).max(-f64::from(f32::MAX)))
            } else {
                p
            };
            let c = v64(&contract_points(&pts(&[p], dtype)).unwrap());
            assert!(c.iter().all(|v| v.is_finite()), "{dtype:?} {p:?}: {c:?}");
            for row in jac_autograd(p, dtype) {
                assert!(row.iter().all(|v| v.is_finite()), "{dtype:?} {p:?}");
            }
        }
    }
}

#[test]
fn f32_agrees_with_f64() {
    let p = [
        [0.1, 0.2, -0.3],
        [1.5, -0.2, 0.0],
        [-30.0, 4.0, 7.0],
        [1e6, 2e6, -3e6],
    ];
    let a = v64(&contract_points(&pts(&p, DType::F32)).unwrap());
    let b = v64(&contract_points(&pts(&p, DType::F64)).unwrap());
    for (a, b) in a.iter().zip(&b) {
        assert!(close(*a, *b, 1e-6, 1e-6), "{a} vs {b}");
    }
    let cov = Tensor::ones((4, 3), DType::F64, &Device::Cpu).unwrap();
    let (_, va) = contract_both(&pts(&p, DType::F32), &cov.to_dtype(DType::F32).unwrap()).unwrap();
    let (_, vb) = contract_both(&pts(&p, DType::F64), &cov).unwrap();
    for (a, b) in v64(&va).iter().zip(&v64(&vb)) {
        assert!(close(*a, *b, 1e-5, 1e-30), "{a} vs {b}");
    }
}

#[test]
fn gaussians_means_are_contracted_and_covariances_are_j_sigma_jt() {
    let means = [
        [0.3, 0.1, -0.2],
        [0.6, 0.6, 0.5],
        [1.2, -0.3, 0.4],
        [-3.0, 2.0, 1.0],
        [40.0, -70.0, 10.0],
        [1e3, 2e3, -5e2],
    ];
    // Symmetric positive definite Σ = A Aᵀ + 0.1 I, different per mean.
    let mut covs = Vec::new();
    for (n, _) in means.iter().enumerate() {
        let a: M3 = std::array::from_fn(|i| {
            std::array::from_fn(|k| ((n * 9 + i * 3 + k) as f64 * 0.37).sin())
        });
        let mut s = mul(&a, &transpose(&a));
        for (i, row) in s.iter_mut().enumerate() {
            row[i] += 0.1;
        }
        covs.push(s);
    }
    for dtype in [DType::F64, DType::F32] {
        let tol = if dtype == DType::F64 { 1e-7 } else { 1e-4 };
        let m = pts(&means, dtype);
        let flat: Vec<f64> = covs.iter().flatten().flatten().copied().collect();
        let full = Tensor::from_vec(flat, (covs.len(), 3, 3), &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let diag_in: Vec<[f64; 3]> = covs.iter().map(|s| [s[0][0], s[1][1], s[2][2]]).collect();
        let diag = pts(&diag_in, dtype);
        let (cm, cf) = contract_both(&m, &full).unwrap();
        let (cm2, cd) = contract_both(&m, &diag).unwrap();
        assert_eq!(v64(&cm), v64(&contract_points(&m).unwrap()));
        assert_eq!(v64(&cm2), v64(&cm));
        assert_eq!(cf.dims(), &[6, 3, 3]);
        assert_eq!(cd.dims(), &[6, 3]);
        let (cf, cd) = (v64(&cf), v64(&cd));
        for (n, &p) in means.iter().enumerate() {
            let j = jac_fd(p, 1e-4 * norm(p).max(1e-2));
            let want = mul(&mul(&j, &covs[n]), &transpose(&j));
            let d: M3 = std::array::from_fn(|i| {
                std::array::from_fn(|k| if i == k { covs[n][i][i] } else { 0.0 })
            });
            let want_diag = mul(&mul(&j, &d), &transpose(&j));
            let scale = want.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
            for i in 0..3 {
                for k in 0..3 {
                    let got = cf[n * 9 + i * 3 + k];
                    assert!(
                        close(got, want[i][k], tol, scale),
                        "{dtype:?} mean {p:?} [{i}][{k}]: {got} vs {}",
                        want[i][k]
                    );
                }
                let got = cd[n * 3 + i];
                assert!(
                    close(got, want_diag[i][i], tol, scale),
                    "{dtype:?} mean {p:?} diag {i}: {got} vs {}",
                    want_diag[i][i]
                );
            }
        }
    }
}

#[test]
fn bad_inputs_name_the_argument() {
    let d = Device::Cpu;
    let ok = pts(&[[0.5, 2.0, 0.0], [1.0, 1.0, 1.0]], DType::F64);
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let x = pts(&[[0.5, 2.0, 0.0], [1.0, bad, 1.0]], DType::F64);
        assert_eq!(arg_of(contract_points(&x).unwrap_err()), "points", "{bad}");
        assert_eq!(
            arg_of(contract_points(&x.to_dtype(DType::F32).unwrap()).unwrap_err()),
            "points"
        );
        assert_eq!(arg_of(contract_both(&x, &ok).unwrap_err()), "points");
        assert_eq!(arg_of(contract_both(&ok, &x).unwrap_err()), "covariances");
    }
    let two_cols = Tensor::zeros((4, 2), DType::F64, &d).unwrap();
    assert_eq!(arg_of(contract_points(&two_cols).unwrap_err()), "points");
    let ints = Tensor::zeros((4, 3), DType::U32, &d).unwrap();
    assert_eq!(arg_of(contract_points(&ints).unwrap_err()), "points");
    assert_eq!(arg_of(contract_both(&two_cols, &ok).unwrap_err()), "points");
    for cov in [
        Tensor::zeros((2, 2, 2), DType::F64, &d).unwrap(),
        Tensor::zeros((3, 3, 3), DType::F64, &d).unwrap(),
        Tensor::zeros((3, 3), DType::F64, &d).unwrap(),
        Tensor::zeros(2, DType::F64, &d).unwrap(),
        Tensor::zeros((2, 3), DType::F32, &d).unwrap(),
    ] {
        assert_eq!(
            arg_of(contract_both(&ok, &cov).unwrap_err()),
            "covariances",
            "{cov:?}"
        );
    }
    // Empty batches pass through.
    let empty = Tensor::zeros((0, 3), DType::F32, &d).unwrap();
    assert_eq!(contract_points(&empty).unwrap().dims(), &[0, 3]);
    let (m, v) = contract_both(&empty, &Tensor::zeros((0, 3, 3), DType::F32, &d).unwrap()).unwrap();
    assert_eq!(
        (m.dims(), v.dims()),
        (&[0usize, 3][..], &[0usize, 3, 3][..])
    );
}

/// A random point: a direction and a log-radius in the extreme range, or near 1.
fn point() -> impl Strategy<Value = [f64; 3]> {
    let dir = prop::array::uniform3(-1.0f64..1.0).prop_filter("nonzero", |d| norm(*d) > 0.1);
    let radius = prop_oneof![
        (-300.0f64..300.0).prop_map(|e| 10f64.powf(e)),
        (-1.0f64..3.0).prop_map(|e| 10f64.powf(e)),
        0.9f64..1.1,
    ];
    (dir, radius).prop_map(|(d, r)| scaled(d, r))
}

/// Checks the gradient `got` of a scalar loss `f` at `x` against central differences,
/// per coordinate; a stencil across the unit sphere (no clean difference) is skipped.
/// Returns how many coordinates were compared.
fn check_grad(
    what: &str,
    f: &mut dyn FnMut(&[f64]) -> f64,
    x: &[f64],
    got: &[f64],
    h: &dyn Fn(usize) -> f64,
) -> Result<usize, TestCaseError> {
    let mut compared = 0;
    // The stencil's scale: the gradient's size, and at least the loss's own (a gradient
    // of 4e-4 on a loss of 1.75 at r = 42 has differences only a few hundred ulps of the
    // loss wide, which the bound's 1e-8 agreement check must not read as a kink).
    let mag = got.iter().fold(f(x).abs(), |m, v| m.max(v.abs()));
    for k in 0..x.len() {
        let mut g = |t: f64| {
            let mut y = x.to_vec();
            y[k] = t;
            f(&y)
        };
        let Some((fd, bar)) = central_diff_bound(&mut g, x[k], h(k), mag) else {
            continue;
        };
        compared += 1;
        prop_assert!(
            // + 1e-300: far out, J's entries (1/r, 1/r²) multiply into the subnormal
            // range, where a product keeps only a few digits.
            (got[k] - fd).abs() <= 1e-6 * got[k].abs().max(fd.abs()).max(1e-3 * mag) + bar + 1e-300,
            "{what} [{k}] at {x:?}: autograd {} vs fd {fd} (±{bar})",
            got[k]
        );
    }
    Ok(compared)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]
    #[test]
    fn gradients_match_central_differences(
        p in point(),
        w in prop::array::uniform3(-1.0f64..1.0),
        cov_w in prop::array::uniform9(-1.0f64..1.0),
        a in prop::array::uniform9(-1.0f64..1.0),
        full in any::<bool>(),
    ) {
        let d = Device::Cpu;
        let r = norm(p);
        let hx = 1e-4 * r.max(1e-3);
        let wt = Tensor::new(&[w], &d).unwrap();

        // contract: L = Σ w · contract_points(x).
        let x = Var::from_tensor(&pts(&[p], DType::F64)).unwrap();
        let loss = (contract_points(x.as_tensor()).unwrap() * &wt).unwrap().sum_all().unwrap();
        let g = v64(loss.backward().unwrap().get(x.as_tensor()).unwrap());
        let mut f = |y: &[f64]| {
            let c = c1([y[0], y[1], y[2]]);
            (0..3).map(|i| w[i] * c[i]).sum::<f64>()
        };
        let compared = check_grad("contract", &mut f, &p, &g, &|_| hx)?;
        // Only a stencil across the unit sphere may have no clean difference.
        prop_assert!(compared == 3 || (r - 1.0).abs() < 1e-3, "{compared} compared at r {r}");

        // contract of Gaussians: L = Σ W ⊙ cov′ (+ Σ w · mean′), full Σ = A Aᵀ or its diagonal.
        let sigma: Vec<f64> = if full {
            (0..9)
                .map(|ik| (0..3).map(|j| a[ik / 3 * 3 + j] * a[ik % 3 * 3 + j]).sum::<f64>())
                .collect()
        } else {
            (0..3).map(|i| a[i] * a[i] + 0.1).collect()
        };
        let shape: Vec<usize> = if full { vec![1, 3, 3] } else { vec![1, 3] };
        let wc_vals: Vec<f64> = cov_w[..sigma.len()].to_vec();
        let wc = Tensor::from_vec(wc_vals.clone(), shape.clone(), &d).unwrap();
        let gaussian_loss = |m: &Tensor, s: &Tensor| {
            let (cm, cs) = contract_both(m, s).unwrap();
            ((cs * &wc).unwrap().sum_all().unwrap() + (cm * &wt).unwrap().sum_all().unwrap())
                .unwrap()
        };
        let m = Var::from_tensor(&pts(&[p], DType::F64)).unwrap();
        let s = Var::from_tensor(&Tensor::from_vec(sigma.clone(), shape.clone(), &d).unwrap())
            .unwrap();
        let grads = gaussian_loss(m.as_tensor(), s.as_tensor()).backward().unwrap();
        let gm = v64(grads.get(m.as_tensor()).unwrap());
        let gs = v64(grads.get(s.as_tensor()).unwrap());
        let eval = |y: &[f64], s: &[f64]| {
            let l = gaussian_loss(
                &pts(&[[y[0], y[1], y[2]]], DType::F64),
                &Tensor::from_vec(s.to_vec(), shape.clone(), &d).unwrap(),
            );
            l.to_scalar::<f64>().unwrap()
        };
        // The covariance term alone, for the gradient w.r.t. Σ (the means' term would
        // swamp its differences far away).
        let cov_only = |y: &[f64], s: &[f64]| {
            let (_, cs) = contract_both(
                &pts(&[[y[0], y[1], y[2]]], DType::F64),
                &Tensor::from_vec(s.to_vec(), shape.clone(), &d).unwrap(),
            )
            .unwrap();
            (cs * &wc).unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap()
        };
        check_grad("means", &mut |y| eval(y, &sigma), &p, &gm, &|_| hx)?;
        check_grad("covariances", &mut |s| cov_only(&p, s), &sigma, &gs, &|_| 1e-3)?;
        // The means' gradient of the covariance term alone (1/r³ far away).
        let m2 = Var::from_tensor(&pts(&[p], DType::F64)).unwrap();
        let (_, cs) = contract_both(m2.as_tensor(), s.as_tensor()).unwrap();
        let gm2 = v64(
            (cs * &wc).unwrap().sum_all().unwrap().backward().unwrap()
                .get(m2.as_tensor()).unwrap(),
        );
        check_grad("means (covariance term)", &mut |y| cov_only(y, &sigma), &p, &gm2, &|_| hx)?;
        prop_assert!(gm.iter().chain(&gs).chain(&gm2).all(|v| v.is_finite()));
    }
}

/// [`contract`](neural_fields::volume::contract) of points.
fn contract_points(points: &Tensor) -> neural_fields::Result<Tensor> {
    Ok(neural_fields::volume::contract(points, None)?.0)
}

/// [`contract`](neural_fields::volume::contract) of Gaussians.
fn contract_both(means: &Tensor, cov: &Tensor) -> neural_fields::Result<(Tensor, Tensor)> {
    let (m, c) = neural_fields::volume::contract(means, Some(cov))?;
    Ok((m, c.expect("covariances in, covariances out")))
}
