//! Closed forms, stiff cases and bad input for volume compositing (reference and
//! dispatching paths).
#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::intervals::{batched_from_deltas, packed_from_deltas, starts_ends};
use common::v64;
use neural_fields::camera::Rays;
use neural_fields::volume::{
    accumulate, composite, render_weights, visible_mask, Composite, CompositeConfig, Intervals,
    Layout, Packed, DEFAULT_TERMINATION_EPS,
};
use neural_fields::Error;

/// The two compositing paths: the candle-op reference (`force_reference`) and the
/// dispatching entry point (the fused kernel on the CPU).
const IMPLS: [(&str, bool); 2] = [("reference", true), ("dispatch", false)];

/// `composite` on the path `force_reference` names, the rest of the configuration from
/// `config`.
fn comp(
    force_reference: bool,
    sigmas: &Tensor,
    colors: &Tensor,
    intervals: &Intervals,
    rays: Option<&Rays>,
    config: &CompositeConfig,
) -> neural_fields::Result<Composite> {
    composite(
        sigmas,
        colors,
        intervals,
        rays,
        &CompositeConfig {
            force_reference,
            ..config.clone()
        },
    )
}

fn dev() -> Device {
    Device::Cpu
}

fn t2(v: Vec<f64>, r: usize, s: usize, dt: DType) -> Tensor {
    Tensor::from_vec(v, (r, s), &dev())
        .unwrap()
        .to_dtype(dt)
        .unwrap()
}

/// Validated batched intervals from host starts and ends (`[r, s]`, row-major).
fn iv2(starts: Vec<f64>, ends: Vec<f64>, r: usize, s: usize, dt: DType) -> Intervals {
    Intervals::new(t2(starts, r, s, dt), t2(ends, r, s, dt), Layout::Batched).unwrap()
}

/// Intervals built without `Intervals::new`'s validation (the fields are public), to
/// reach the compositing functions' own checks.
fn raw_iv(starts: Tensor, ends: Tensor) -> Intervals {
    Intervals {
        starts,
        ends,
        layout: Layout::Batched,
    }
}

/// Uniform bins on [a, a + l]: (left ends, right ends, midpoints), each bin's right end
/// the next one's left end (the same f64).
fn bins(a: f64, l: f64, n: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let d = l / n as f64;
    let edge = |i: usize| a + i as f64 * d;
    let lefts: Vec<f64> = (0..n).map(edge).collect();
    let rights: Vec<f64> = (1..=n).map(edge).collect();
    let mids = lefts
        .iter()
        .zip(&rights)
        .map(|(s, e)| 0.5 * s + 0.5 * e)
        .collect();
    (lefts, rights, mids)
}

/// Composites one ray with intervals `[starts, ends]` and constant colour per sample
/// given as `cols` (C = 1).
fn one_ray(
    force_reference: bool,
    sig: &[f64],
    starts: &[f64],
    ends: &[f64],
    cols: &[f64],
    dt: DType,
) -> (f64, f64, f64) {
    let n = sig.len();
    let s = t2(sig.to_vec(), 1, n, dt);
    let c = t2(cols.to_vec(), 1, n, dt).reshape((1, n, 1)).unwrap();
    let iv = iv2(starts.to_vec(), ends.to_vec(), 1, n, dt);
    let out = comp(
        force_reference,
        &s,
        &c,
        &iv,
        None,
        &CompositeConfig::default(),
    )
    .unwrap();
    (v64(&out.color)[0], v64(&out.opacity)[0], v64(&out.depth)[0])
}

/// The dispatching path.
const DISPATCH: bool = false;

#[test]
fn one_slab_is_exact_for_aligned_bins() {
    for (name, f) in IMPLS {
        for dt in [DType::F32, DType::F64] {
            let tol = if dt == DType::F32 { 1e-6 } else { 1e-13 };
            for &(sigma, l, n) in &[
                (0.7, 2.0, 1usize),
                (3.0, 1.5, 7),
                (0.01, 1.0, 64),
                (50.0, 0.3, 192),
            ] {
                let (st, en, _) = bins(0.0, l, n);
                let c = 0.8;
                let (col, op, _) = one_ray(f, &vec![sigma; n], &st, &en, &vec![c; n], dt);
                let exact_op = 1.0 - (-sigma * l).exp();
                assert!(
                    (op - exact_op).abs() <= tol,
                    "{name} {dt:?}: opacity {op} vs {exact_op}"
                );
                assert!(
                    (col - c * exact_op).abs() <= tol,
                    "{name} {dt:?}: colour {col}"
                );
            }
        }
    }
}

#[test]
fn two_slabs_are_exact_for_aligned_bins() {
    for (name, f) in IMPLS {
        let (s1, s2, c1, c2, a, l) = (1.3, 4.0, 0.2, 0.9, 0.6, 1.0);
        let n = 10;
        let (st, en, mids) = bins(0.0, l, n);
        let sig: Vec<f64> = mids.iter().map(|&t| if t < a { s1 } else { s2 }).collect();
        let col: Vec<f64> = mids.iter().map(|&t| if t < a { c1 } else { c2 }).collect();
        let (c, o, _) = one_ray(f, &sig, &st, &en, &col, DType::F64);
        let t1 = (-s1 * a).exp();
        let exact = c1 * (1.0 - t1) + t1 * c2 * (1.0 - (-s2 * (l - a)).exp());
        let exact_o = 1.0 - t1 * (-s2 * (l - a)).exp();
        assert!((c - exact).abs() < 1e-14, "{name}: {c} vs {exact}");
        assert!((o - exact_o).abs() < 1e-14, "{name}: {o} vs {exact_o}");
    }
}

#[test]
fn opacity_equals_one_minus_exp_of_total_thickness() {
    let n = 50;
    let sig: Vec<f64> = (0..n).map(|i| ((i * 37 % 11) as f64) * 0.3).collect();
    let del: Vec<f64> = (0..n)
        .map(|i| 0.01 + ((i * 13 % 7) as f64) * 0.02)
        .collect();
    let (st, en) = starts_ends(&del, &[n]);
    // The lengths as the intervals hold them (ends − starts, in f64).
    let total: f64 = (0..n).map(|i| sig[i] * (en[i] - st[i])).sum();
    for (name, f) in IMPLS {
        let (_, o, _) = one_ray(f, &sig, &st, &en, &vec![0.0; n], DType::F64);
        assert!((o - (1.0 - (-total).exp())).abs() < 1e-14, "{name}");
    }
}

/// Least-squares slope of log(err) against log(n).
fn fitted_slope(ns: &[usize], errs: &[f64]) -> f64 {
    let xs: Vec<f64> = ns.iter().map(|&n| (n as f64).ln()).collect();
    let ys: Vec<f64> = errs.iter().map(|e| e.ln()).collect();
    let mx = xs.iter().sum::<f64>() / xs.len() as f64;
    let my = ys.iter().sum::<f64>() / ys.len() as f64;
    let num: f64 = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let den: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    num / den
}

const NS: [usize; 5] = [8, 16, 32, 64, 128];

#[test]
fn expected_depth_in_a_slab_converges_to_the_closed_form() {
    let (a, l, sigma) = (2.0, 1.5, 1.7f64);
    let el = (-sigma * l).exp();
    let exact = a + 1.0 / sigma - l * el / (1.0 - el);
    let mut errs = vec![];
    for &n in &NS {
        let (st, en, _) = bins(a, l, n);
        let (_, o, d) = one_ray(
            DISPATCH,
            &vec![sigma; n],
            &st,
            &en,
            &vec![0.0; n],
            DType::F64,
        );
        errs.push((d / o - exact).abs());
    }
    let slope = fitted_slope(&NS, &errs);
    println!("expected depth errors {errs:?}, slope {slope}");
    assert!(errs[4] < 1e-4, "{errs:?}");
    assert!((slope + 2.0).abs() < 0.1, "slope {slope}");
}

#[test]
fn linear_density_midpoint_is_exact_and_left_endpoint_is_first_order() {
    let (k, l) = (3.0, 1.2);
    let exact = 1.0 - (-k * l * l / 2.0f64).exp();
    let mut errs = vec![];
    for &n in &NS {
        let (st, en, mids) = bins(0.0, l, n);
        let sm: Vec<f64> = mids.iter().map(|t| k * t).collect();
        let (_, o_mid, _) = one_ray(DISPATCH, &sm, &st, &en, &vec![0.0; n], DType::F64);
        assert!(
            (o_mid - exact).abs() < 1e-14,
            "midpoint n={n}: {o_mid} vs {exact}"
        );
        let sl: Vec<f64> = st.iter().map(|t| k * t).collect();
        let (_, o_left, _) = one_ray(DISPATCH, &sl, &st, &en, &vec![0.0; n], DType::F64);
        errs.push((o_left - exact).abs());
    }
    let slope = fitted_slope(&NS, &errs);
    println!("left-endpoint opacity errors {errs:?}, slope {slope}");
    assert!((slope + 1.0).abs() < 0.05, "slope {slope}");
}

#[test]
fn colour_equal_to_depth_converges_second_order_with_midpoints() {
    let (sigma, l) = (2.5f64, 1.0);
    let exact = (1.0 - (-sigma * l).exp() * (1.0 + sigma * l)) / sigma;
    let mut errs = vec![];
    for &n in &NS {
        let (st, en, mids) = bins(0.0, l, n);
        let (c, _, _) = one_ray(DISPATCH, &vec![sigma; n], &st, &en, &mids, DType::F64);
        errs.push((c - exact).abs());
    }
    let slope = fitted_slope(&NS, &errs);
    println!("c(t)=t colour errors {errs:?}, slope {slope}");
    assert!((slope + 2.0).abs() < 0.05, "slope {slope}");
}

/// The depth is Σwᵢmᵢ with mᵢ the interval midpoints (not, say, the starts), on both
/// paths, batched and packed, with and without rays (which scale δ, not t).
#[test]
fn depth_is_the_weighted_sum_of_interval_midpoints() {
    let (r, s) = (3, 9);
    let del: Vec<f64> = (0..r * s).map(|i| 0.05 + 0.03 * (i % 5) as f64).collect();
    let sig: Vec<f64> = (0..r * s).map(|i| 0.5 + 0.7 * (i % 4) as f64).collect();
    let sig_t = t2(sig, r, s, DType::F64);
    let colors = Tensor::zeros((r, s, 1), DType::F64, &dev()).unwrap();
    // Shift every ray away from t = 0 so that midpoints and starts differ clearly.
    let base = batched_from_deltas(&del, r, s, DType::F64, &dev());
    let iv = Intervals::new(
        (&base.starts + 1.5).unwrap(),
        (&base.ends + 1.5).unwrap(),
        Layout::Batched,
    )
    .unwrap();
    let rays = Rays::new(
        Tensor::zeros((r, 3), DType::F64, &dev()).unwrap(),
        Tensor::new(
            &[[0.0f64, 0.0, 1.0], [0.0, 2.0, 0.0], [0.3, 0.4, 0.0]],
            &dev(),
        )
        .unwrap(),
    )
    .unwrap();
    let mids = v64(&iv.midpoints().unwrap());
    let starts = v64(&iv.starts);
    for rays in [None, Some(&rays)] {
        let w = v64(
            &render_weights(&sig_t, &iv, rays, &CompositeConfig::default())
                .unwrap()
                .weights,
        );
        for (name, f) in IMPLS {
            let out = comp(f, &sig_t, &colors, &iv, rays, &CompositeConfig::default()).unwrap();
            let depth = v64(&out.depth);
            for ray in 0..r {
                let want: f64 = (0..s).map(|i| w[ray * s + i] * mids[ray * s + i]).sum();
                let at_starts: f64 = (0..s).map(|i| w[ray * s + i] * starts[ray * s + i]).sum();
                assert!(
                    (depth[ray] - want).abs() <= 1e-13 * want.abs(),
                    "{name}, rays {}: ray {ray} depth {} vs {want}",
                    rays.is_some(),
                    depth[ray]
                );
                assert!(
                    (want - at_starts).abs() > 1e-3,
                    "the test must tell them apart"
                );
            }
        }
    }
}

#[test]
fn background_fills_the_transparent_remainder() {
    for (name, f) in IMPLS {
        let s = t2(vec![0.5, 1.0, 0.0, 0.0], 2, 2, DType::F64);
        let iv = iv2(
            vec![0.0, 1.0, 0.0, 1.0],
            vec![1.0, 2.0, 1.0, 2.0],
            2,
            2,
            DType::F64,
        );
        let c = Tensor::ones((2, 2, 3), DType::F64, &dev()).unwrap();
        let bg = Tensor::new(&[0.0f64, 0.5, 1.0], &dev()).unwrap();
        let opts = CompositeConfig {
            background: Some(bg),
            ..Default::default()
        };
        let out = comp(f, &s, &c, &iv, None, &opts).unwrap();
        let col = v64(&out.color);
        let o = 1.0 - (-1.5f64).exp();
        let want = [o, o + 0.5 * (1.0 - o), 1.0, 0.0, 0.5, 1.0];
        for (g, w) in col.iter().zip(want) {
            assert!((g - w).abs() < 1e-14, "{name}: {col:?}");
        }
    }
}

#[test]
fn opaque_last_makes_opacity_one_and_ignores_the_last_density() {
    for (name, f) in IMPLS {
        for dt in [DType::F32, DType::F64] {
            let s = t2(vec![0.1, 0.2, 0.0, 0.3, 0.0, 0.0], 2, 3, dt);
            let iv = batched_from_deltas(&[0.5, 0.5, 1e10, 0.5, 0.5, 0.0], 2, 3, dt, &dev());
            let c = Tensor::ones((2, 3, 1), dt, &dev()).unwrap();
            let opts = CompositeConfig {
                opaque_last: true,
                ..Default::default()
            };
            let out = comp(f, &s, &c, &iv, None, &opts).unwrap();
            for o in v64(&out.opacity) {
                assert!((o - 1.0).abs() < 1e-6, "{name}: {o}");
            }
        }
    }
    let w = render_weights(
        &t2(vec![0.0, 0.0, 0.0], 1, 3, DType::F32),
        &batched_from_deltas(&[1.0, 1.0, 0.0], 1, 3, DType::F32, &dev()),
        None,
        &CompositeConfig {
            opaque_last: true,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(v64(&w.weights), vec![0.0, 0.0, 1.0]);
}

#[test]
fn tiny_thickness_gives_alpha_equal_to_sigma_delta_in_f32() {
    for dt in [DType::F32, DType::F64] {
        for &x in &[1e-30, 1e-20, 1e-10, 1e-7, 1e-3, 0.29, 0.31, 0.5] {
            let w = render_weights(
                &t2(vec![x], 1, 1, dt),
                &iv2(vec![0.0], vec![1.0], 1, 1, dt),
                None,
                &CompositeConfig::default(),
            )
            .unwrap();
            let a = v64(&w.alphas)[0];
            let xr = v64(&t2(vec![x], 1, 1, dt))[0];
            let want = -(-xr).exp_m1();
            let tol = if dt == DType::F32 { 1e-6 } else { 1e-14 };
            assert!(
                ((a - want) / want).abs() < tol,
                "{dt:?} x={x}: alpha {a} vs {want}"
            );
        }
    }
}

#[test]
fn stiff_inputs_give_finite_outputs() {
    for (name, f) in IMPLS {
        for dt in [DType::F32, DType::F64] {
            // sigma*delta = 1e30, 1e40 (overflows f32), 1e-30, huge and tiny mixed. Ray 0
            // has them in this order (its δ = 1e-30 after t = 1e10 rounds to 0); ray 1
            // starts with the (σ = 1e10, δ = 1e-30) pair, where the length is exact.
            let s = t2(
                vec![
                    1e30, 1e30, 1e-30, 1e10, 0.0, 3.0e38, //
                    1e10, 1e30, 1e30, 1e-30, 0.0, 3.0e38,
                ],
                2,
                6,
                dt,
            );
            let iv = batched_from_deltas(
                &[
                    1.0, 1e10, 1.0, 1e-30, 1e10, 1.0, //
                    1e-30, 1.0, 1e10, 1.0, 1e10, 1.0,
                ],
                2,
                6,
                dt,
                &dev(),
            );
            let c = Tensor::ones((2, 6, 3), dt, &dev()).unwrap();
            let out = comp(f, &s, &c, &iv, None, &CompositeConfig::default()).unwrap();
            for v in v64(&out.color)
                .into_iter()
                .chain(v64(&out.opacity))
                .chain(v64(&out.depth))
            {
                assert!(v.is_finite(), "{name} {dt:?}: {v}");
            }
            assert!((v64(&out.opacity)[0] - 1.0).abs() < 1e-6);
            assert!((v64(&out.opacity)[1] - 1.0).abs() < 1e-6);
        }
    }
}

#[test]
fn one_dense_interval_gives_one_hot_weights() {
    for dt in [DType::F32, DType::F64] {
        let mut sig = vec![0.0; 64];
        sig[17] = 1e10;
        let w = render_weights(
            &t2(sig, 1, 64, dt),
            &batched_from_deltas(&[0.01; 64], 1, 64, dt, &dev()),
            None,
            &CompositeConfig::default(),
        )
        .unwrap();
        let w = v64(&w.weights);
        for (i, v) in w.iter().enumerate() {
            assert_eq!(*v, if i == 17 { 1.0 } else { 0.0 }, "{dt:?} at {i}");
        }
    }
}

#[test]
fn f32_transmittance_underflows_to_zero_without_nan_on_long_rays() {
    let n = 1024;
    let s = t2(vec![1.0; n], 1, n, DType::F32);
    let iv = batched_from_deltas(&vec![0.5; n], 1, n, DType::F32, &dev());
    let w = render_weights(&s, &iv, None, &CompositeConfig::default()).unwrap();
    let t = v64(&w.transmittance);
    assert!(t.iter().all(|v| v.is_finite()));
    assert_eq!(t[n - 1], 0.0, "exp(-511.5) underflows in f32");
    assert!(t[100] > 0.0 && t[300] == 0.0);
}

#[test]
fn packed_layout_matches_batched_and_handles_empty_rays() {
    let counts = [3usize, 0, 5, 1, 0];
    let packed = Packed::from_counts(&counts, &dev()).unwrap();
    assert_eq!(packed.ray_indices.dim(0).unwrap(), 9);
    assert_eq!(
        packed.offsets.to_vec1::<u32>().unwrap(),
        vec![0, 3, 3, 8, 9, 9]
    );
    assert_eq!(
        packed.ray_indices.to_vec1::<u32>().unwrap(),
        vec![0, 0, 0, 2, 2, 2, 2, 2, 3]
    );
    let sig: Vec<f64> = (0..9).map(|i| 0.3 * i as f64).collect();
    let del: Vec<f64> = (0..9).map(|i| 0.1 + 0.05 * i as f64).collect();
    let cols: Vec<f64> = (0..27).map(|i| (i % 5) as f64 * 0.2).collect();
    let s = Tensor::new(sig.as_slice(), &dev()).unwrap();
    let iv = packed_from_deltas(&del, &packed, DType::F64);
    let c = Tensor::from_vec(cols.clone(), (9, 3), &dev()).unwrap();
    let bg = Tensor::new(&[0.1f64, 0.2, 0.3], &dev()).unwrap();
    for opaque_last in [false, true] {
        let opts = CompositeConfig {
            opaque_last,
            background: Some(bg.clone()),
            force_reference: false,
        };
        let outs = [
            comp(true, &s, &c, &iv, None, &opts).unwrap(),
            comp(false, &s, &c, &iv, None, &opts).unwrap(),
        ];
        // Each non-empty ray on its own, batched.
        let mut start = 0;
        for (r, &n) in counts.iter().enumerate() {
            let (colour, op, dep) = if n == 0 {
                (vec![0.1, 0.2, 0.3], 0.0, 0.0)
            } else {
                let row = |t: &Tensor| t.narrow(0, start, n).unwrap().unsqueeze(0).unwrap();
                let one = comp(
                    true,
                    &row(&s),
                    &row(&c),
                    &Intervals::new(row(&iv.starts), row(&iv.ends), Layout::Batched).unwrap(),
                    None,
                    &opts,
                )
                .unwrap();
                (v64(&one.color), v64(&one.opacity)[0], v64(&one.depth)[0])
            };
            for out in &outs {
                let got = v64(&out.color);
                for k in 0..3 {
                    assert!((got[3 * r + k] - colour[k]).abs() < 1e-14, "ray {r}");
                }
                assert!((v64(&out.opacity)[r] - op).abs() < 1e-14);
                assert!((v64(&out.depth)[r] - dep).abs() < 1e-13);
            }
            start += n;
        }
        let w = render_weights(&s, &iv, None, &opts).unwrap();
        let acc = accumulate(&w.weights, &c, &iv.layout).unwrap();
        assert_eq!(acc.dims(), &[5, 3]);
    }
}

#[test]
fn accumulate_is_the_weighted_sum() {
    let w = t2(vec![0.5, 0.25], 1, 2, DType::F64);
    let v = Tensor::from_vec(vec![1.0f64, 2.0, 3.0, 4.0], (1, 2, 2), &dev()).unwrap();
    assert_eq!(
        v64(&accumulate(&w, &v, &Layout::Batched).unwrap()),
        vec![1.25, 2.0]
    );
}

fn arg_of(e: Error) -> &'static str {
    match e {
        Error::InvalidArgument { arg, .. } => arg,
        other => panic!("expected InvalidArgument, got {other}"),
    }
}

#[test]
fn bad_input_errors_name_the_argument() {
    let ok = t2(vec![1.0; 6], 2, 3, DType::F32);
    let ok_iv = batched_from_deltas(&[1.0; 6], 2, 3, DType::F32, &dev());
    let c = Tensor::ones((2, 3, 3), DType::F32, &dev()).unwrap();
    let o = CompositeConfig::default();
    let starts_of = |v: Vec<f64>, dt| t2(v, 2, 3, dt);
    for (name, f) in IMPLS {
        // Intervals of another shape than the densities: the densities do not fit them.
        let bad_shape = batched_from_deltas(&[1.0; 4], 2, 2, DType::F32, &dev());
        assert_eq!(
            arg_of(comp(f, &ok, &c, &bad_shape, None, &o).unwrap_err()),
            "sigmas",
            "{name}"
        );
        // Ends of another shape than the starts.
        let mismatched = raw_iv(ok_iv.starts.clone(), t2(vec![1.0; 4], 2, 2, DType::F32));
        assert_eq!(
            arg_of(comp(f, &ok, &c, &mismatched, None, &o).unwrap_err()),
            "intervals",
            "{name}"
        );
        let bad_c = Tensor::ones((2, 2, 3), DType::F32, &dev()).unwrap();
        assert_eq!(
            arg_of(comp(f, &ok, &bad_c, &ok_iv, None, &o).unwrap_err()),
            "colors",
            "{name}"
        );
        // A negative length: `Intervals::new` names the inverted end; intervals that skip
        // it (public fields) are named by compositing.
        let zeros = starts_of(vec![0.0; 6], DType::F32);
        let neg = starts_of(vec![1.0, 1.0, -1e-3, 1.0, 1.0, 1.0], DType::F32);
        assert_eq!(
            arg_of(
                Intervals::new(
                    starts_of(vec![0.0, 1.0, 2.0, 0.0, 1.0, 2.0], DType::F32),
                    starts_of(vec![1.0, 2.0, 2.0 - 1e-3, 1.0, 2.0, 3.0], DType::F32),
                    Layout::Batched
                )
                .unwrap_err()
            ),
            "ends"
        );
        assert_eq!(
            arg_of(comp(f, &ok, &c, &raw_iv(zeros.clone(), neg.clone()), None, &o).unwrap_err()),
            "intervals",
            "{name}"
        );
        assert_eq!(
            arg_of(comp(f, &neg, &c, &ok_iv, None, &o).unwrap_err()),
            "sigmas",
            "{name}"
        );
        for v in [f64::NAN, f64::INFINITY] {
            let bad = starts_of(vec![1.0, v, 1.0, 1.0, 1.0, 1.0], DType::F32);
            assert_eq!(
                arg_of(comp(f, &bad, &c, &ok_iv, None, &o).unwrap_err()),
                "sigmas",
                "{name} {v}"
            );
            assert_eq!(
                arg_of(
                    Intervals::new(
                        starts_of(vec![0.0, 1.0, 2.0, 0.0, 1.0, 2.0], DType::F32),
                        starts_of(vec![1.0, v, 3.0, 1.0, 2.0, 3.0], DType::F32),
                        Layout::Batched
                    )
                    .unwrap_err()
                ),
                "starts",
                "{name} {v}"
            );
            assert_eq!(
                arg_of(
                    comp(f, &ok, &c, &raw_iv(zeros.clone(), bad.clone()), None, &o).unwrap_err()
                ),
                "intervals",
                "{name} {v}"
            );
        }
        let f64s = batched_from_deltas(&[1.0; 6], 2, 3, DType::F64, &dev());
        assert_eq!(
            arg_of(comp(f, &ok, &c, &f64s, None, &o).unwrap_err()),
            "intervals",
            "{name}"
        );
        // Rays that do not match the intervals.
        let three = Rays::new(
            Tensor::zeros((3, 3), DType::F32, &dev()).unwrap(),
            Tensor::ones((3, 3), DType::F32, &dev()).unwrap(),
        )
        .unwrap();
        assert_eq!(
            arg_of(comp(f, &ok, &c, &ok_iv, Some(&three), &o).unwrap_err()),
            "rays",
            "{name}"
        );
        let bg = Tensor::ones(2, DType::F32, &dev()).unwrap();
        let ob = CompositeConfig {
            background: Some(bg),
            ..Default::default()
        };
        assert_eq!(
            arg_of(comp(f, &ok, &c, &ok_iv, None, &ob).unwrap_err()),
            "background",
            "{name}"
        );
    }
    let zeros = t2(vec![0.0; 6], 2, 3, DType::F64);
    let neg = t2(vec![1.0, 1.0, -1e-3, 1.0, 1.0, 1.0], 2, 3, DType::F64);
    let okd = t2(vec![1.0; 6], 2, 3, DType::F64);
    let w = CompositeConfig::default();
    let neg_iv = raw_iv(zeros, neg);
    assert_eq!(
        arg_of(render_weights(&okd, &neg_iv, None, &w).unwrap_err()),
        "intervals"
    );
    let e = render_weights(&okd, &neg_iv, None, &w)
        .unwrap_err()
        .to_string();
    assert!(e.contains("intervals") && e.contains("-0.001"), "{e}");
    let okd_iv = batched_from_deltas(&[1.0; 6], 2, 3, DType::F64, &dev());
    assert_eq!(
        arg_of(visible_mask(&okd, &okd_iv, None, 0.0).unwrap_err()),
        "eps"
    );
    let packed = Packed::from_counts(&[2, 2], &dev()).unwrap();
    let piv = packed_from_deltas(&[1.0; 4], &packed, DType::F64);
    let s5 = Tensor::ones(5, DType::F64, &dev()).unwrap();
    assert_eq!(
        arg_of(render_weights(&s5, &piv, None, &w).unwrap_err()),
        "sigmas"
    );
}

/// Inputs of 2^18 and more elements are checked in parallel chunks: a bad value in any
/// chunk (first, middle, last element) is still found, reported under the argument's
/// name with its flat index, by every compositing path and in f32 and f64. (The fused
/// kernel checks constant intervals in its own pass and names them without an index;
/// intervals that carry a graph are checked, with the index, on the dispatching path
/// too.)
#[test]
fn bad_values_in_large_inputs_are_found_in_every_chunk() {
    let (r, s) = (2048, 160);
    let n = r * s;
    for dt in [DType::F32, DType::F64] {
        let ok = Tensor::ones((r, s), dt, &dev()).unwrap();
        let ok_iv = batched_from_deltas(&vec![1.0; n], r, s, dt, &dev());
        let zeros = Tensor::zeros((r, s), dt, &dev()).unwrap();
        let c = Tensor::ones((r, s, 3), dt, &dev()).unwrap();
        let o = CompositeConfig::default();
        for (at, bad) in [(0, f64::NAN), (n / 2 + 17, -2.5), (n - 1, f64::INFINITY)] {
            let mut v = vec![0.5f64; n];
            v[at] = bad;
            let b = t2(v, r, s, dt);
            // Starts at 0 and ends `b`: the lengths are `b` exactly.
            let bad_iv = raw_iv(zeros.clone(), b.clone());
            let ends_var = Var::from_tensor(&b).unwrap();
            let tracked_iv = raw_iv(zeros.clone(), ends_var.as_tensor().clone());
            for (name, f) in IMPLS {
                let e = comp(f, &b, &c, &ok_iv, None, &o).unwrap_err().to_string();
                assert!(
                    e.contains("sigmas") && e.contains(&format!("flat index {at}")),
                    "{name}, {dt:?}, {bad} at {at}: {e}"
                );
                let e = comp(f, &ok, &c, &bad_iv, None, &o).unwrap_err();
                let msg = e.to_string();
                if f {
                    assert!(
                        msg.contains("intervals") && msg.contains(&format!("flat index {at}")),
                        "{name}, {dt:?}, {bad} at {at}: {msg}"
                    );
                } else {
                    assert_eq!(arg_of(e), "intervals", "{name}, {dt:?}, {bad} at {at}");
                }
                let e = comp(f, &ok, &c, &tracked_iv, None, &o)
                    .unwrap_err()
                    .to_string();
                assert!(
                    e.contains("intervals") && e.contains(&format!("flat index {at}")),
                    "{name}, {dt:?}, {bad} at {at}, tracked intervals: {e}"
                );
            }
        }
    }
}

#[test]
fn visible_mask_matches_transmittance_on_random_rays_in_f32_and_f64() {
    // Many rays with densities over ten decades: the mask is 1 exactly where the
    // transmittance of `render_weights` (f64, on the same intervals) is at least ε (ties
    // within rounding of the log-space sum skipped), for both dtypes and for ε at its
    // default and far from it.
    let (r, s) = (64, 100);
    let mut rng = neural_fields::rng::SplitMix64::new(9);
    let sig: Vec<f64> = (0..r * s)
        .map(|_| 10f64.powf(-6.0 + 10.0 * rng.uniform()) * rng.uniform())
        .collect();
    let del: Vec<f64> = (0..r * s).map(|_| 1e-3 + 0.05 * rng.uniform()).collect();
    let s64 = t2(sig.clone(), r, s, DType::F64);
    for dt in [DType::F32, DType::F64] {
        let iv = batched_from_deltas(&del, r, s, dt, &dev());
        // The same intervals (as the dtype holds them) in f64, for the reference
        // transmittance.
        let iv64 = Intervals::new(
            iv.starts.to_dtype(DType::F64).unwrap(),
            iv.ends.to_dtype(DType::F64).unwrap(),
            Layout::Batched,
        )
        .unwrap();
        let w = render_weights(&s64, &iv64, None, &CompositeConfig::default()).unwrap();
        let t = v64(&w.transmittance);
        for eps in [DEFAULT_TERMINATION_EPS, 1e-30, 0.5] {
            let mask = visible_mask(&s64.to_dtype(dt).unwrap(), &iv, None, eps).unwrap();
            assert_eq!(mask.dims(), &[r, s]);
            let mv = mask.flatten_all().unwrap().to_vec1::<u8>().unwrap();
            let mut checked = 0;
            for i in 0..r * s {
                if (t[i].ln() - eps.ln()).abs() < 1e-5 * eps.ln().abs().max(1.0) {
                    continue;
                }
                checked += 1;
                assert_eq!(
                    mv[i] == 1,
                    t[i] >= eps,
                    "{dt:?} eps {eps}: sample {i}, T = {}",
                    t[i]
                );
            }
            assert!(checked > r * s * 9 / 10, "{checked}");
            let kept = mv.iter().filter(|&&m| m == 1).count();
            if eps == DEFAULT_TERMINATION_EPS {
                assert!(
                    kept < r * s && kept > r,
                    "the scene must stop some rays: {kept}"
                );
            }
        }
    }
}

#[test]
fn visible_mask_drops_only_samples_after_transmittance_falls_below_eps() {
    let eps = 1e-4;
    let n = 200;
    let sig: Vec<f64> = (0..n)
        .map(|i| if i < 50 { 0.0 } else { 2.0 + (i % 3) as f64 })
        .collect();
    let del = vec![0.05; n];
    let cols: Vec<f64> = (0..n).map(|i| ((i * 7) % 10) as f64 / 10.0).collect();
    let s = t2(sig.clone(), 1, n, DType::F64);
    let iv = batched_from_deltas(&del, 1, n, DType::F64, &dev());
    let mask = visible_mask(&s, &iv, None, eps).unwrap();
    let mv = mask.flatten_all().unwrap().to_vec1::<u8>().unwrap();
    let w = render_weights(&s, &iv, None, &CompositeConfig::default()).unwrap();
    let t = v64(&w.transmittance);
    for i in 0..n {
        assert_eq!(mv[i] == 1, t[i] >= eps, "sample {i}: T = {}", t[i]);
    }
    let kept = mv.iter().filter(|&&m| m == 1).count();
    assert!(kept < n && kept > 50, "kept {kept}");
    // Composite with and without the dropped samples: error <= eps * max|c|.
    let (st, en) = (v64(&iv.starts), v64(&iv.ends));
    let full = one_ray(DISPATCH, &sig, &st, &en, &cols, DType::F64).0;
    let (kept_iv, idx) = iv.retain(&mask).unwrap();
    let pick = |v: &Vec<f64>| {
        Tensor::new(v.as_slice(), &dev())
            .unwrap()
            .index_select(&idx, 0)
            .unwrap()
    };
    assert_eq!(v64(&kept_iv.starts), v64(&pick(&st)));
    assert_eq!(v64(&kept_iv.ends), v64(&pick(&en)));
    let out = composite(
        &pick(&sig),
        &pick(&cols).unsqueeze(1).unwrap(),
        &kept_iv,
        None,
        &CompositeConfig::default(),
    )
    .unwrap();
    let err = (v64(&out.color)[0] - full).abs();
    let cmax = cols.iter().cloned().fold(0.0, f64::max);
    println!(
        "early termination: kept {kept}/{n}, colour error {err:e} (bound {:e})",
        eps * cmax
    );
    assert!(err <= eps * cmax, "{err}");
    assert!(err > 0.0, "the test must actually drop weight");
}

/// Pins a panic: the fused kernel's output for zero rays was a `[0, C + 2]` tensor whose
/// colour, depth and opacity views started past their (empty) storage, so reading them
/// (`to_vec1`) panicked inside candle. Every path and layout must return readable empty
/// results, and zero samples per ray must give the background.
#[test]
fn composite_of_zero_rays_returns_readable_empty_tensors() {
    for dtype in [DType::F32, DType::F64] {
        for force_reference in [false, true] {
            let config = CompositeConfig {
                force_reference,
                ..CompositeConfig::default()
            };
            let dev = Device::Cpu;
            // Batched, R = 0.
            let z = Tensor::zeros((0, 4), dtype, &dev).unwrap();
            let iv = Intervals::new(z.clone(), z.clone(), Layout::Batched).unwrap();
            let colors = Tensor::zeros((0, 4, 3), dtype, &dev).unwrap();
            let out = composite(&z, &colors, &iv, None, &config).unwrap();
            assert_eq!(out.color.dims(), &[0, 3]);
            assert_eq!(v64(&out.color).len(), 0);
            assert_eq!(v64(&out.depth).len(), 0);
            assert_eq!(v64(&out.opacity).len(), 0);
            // Packed, R = 0 and M = 0.
            let packed = Packed::from_counts(&[], &dev).unwrap();
            let e = Tensor::zeros(0, dtype, &dev).unwrap();
            let piv = Intervals::new(e.clone(), e.clone(), Layout::Packed(packed)).unwrap();
            let pcol = Tensor::zeros((0, 3), dtype, &dev).unwrap();
            let out = composite(&e, &pcol, &piv, None, &config).unwrap();
            assert_eq!(out.color.dims(), &[0, 3]);
            assert_eq!(v64(&out.depth).len() + v64(&out.opacity).len(), 0);
            // Batched, S = 0: every ray is background (black), opacity 0.
            let z = Tensor::zeros((2, 0), dtype, &dev).unwrap();
            let iv = Intervals::new(z.clone(), z.clone(), Layout::Batched).unwrap();
            let colors = Tensor::zeros((2, 0, 3), dtype, &dev).unwrap();
            let out = composite(&z, &colors, &iv, None, &config).unwrap();
            assert_eq!(v64(&out.color), vec![0.0; 6]);
            assert_eq!(v64(&out.opacity), vec![0.0; 2]);
            assert_eq!(v64(&out.depth), vec![0.0; 2]);
        }
    }
}
