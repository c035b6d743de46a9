//! Distortion loss (O(S) form against the O(S²) double sum, gradients against the
//! hand-derived formula and central differences) and RegNeRF depth smoothness.
#![cfg(feature = "volume")]

use candle_core::{DType, Device, Tensor, Var};
use neural_fields::volume::{
    depth_smoothness, distortion_loss, log_linear_schedule, Intervals, Layout,
};
use neural_fields::Error;
use proptest::prelude::*;

fn t2(v: &[f64], r: usize, c: usize) -> Tensor {
    Tensor::from_vec(v.to_vec(), (r, c), &Device::Cpu).unwrap()
}

/// Validated batched intervals.
fn iv(starts: &Tensor, ends: &Tensor) -> Intervals {
    Intervals::new(starts.clone(), ends.clone(), Layout::Batched).unwrap()
}

/// Batched intervals built without `Intervals::new`'s validation, so that
/// `distortion_loss`'s own checks are exercised.
fn raw_iv(starts: &Tensor, ends: &Tensor) -> Intervals {
    Intervals {
        starts: starts.clone(),
        ends: ends.clone(),
        layout: Layout::Batched,
    }
}

/// RegNeRF's depth-smoothness weight: 400 → 0.1 log-linearly over 512 steps.
fn depth_smoothness_weight(step: usize) -> f64 {
    log_linear_schedule(step, 400.0, 0.1, 512)
}

fn arg_of(e: Error) -> &'static str {
    match e {
        Error::InvalidArgument { arg, .. } => arg,
        other => panic!("expected InvalidArgument, got {other}"),
    }
}

/// The definition, as a double sum per ray.
fn direct(w: &[f64], s: &[f64], e: &[f64]) -> f64 {
    let n = w.len();
    let m: Vec<f64> = (0..n).map(|i| 0.5 * (s[i] + e[i])).collect();
    let mut l = 0.0;
    for i in 0..n {
        for j in 0..n {
            l += w[i] * w[j] * (m[i] - m[j]).abs();
        }
        l += w[i] * w[i] * (e[i] - s[i]) / 3.0;
    }
    l
}

/// Sorted intervals with gaps, from positive lengths and gaps.
fn intervals(lengths: &[f64], gaps: &[f64], origin: f64) -> (Vec<f64>, Vec<f64>) {
    let mut t = origin;
    let mut s = vec![];
    let mut e = vec![];
    for (l, g) in lengths.iter().zip(gaps) {
        t += g;
        s.push(t);
        t += l;
        e.push(t);
    }
    (s, e)
}

fn loss_host(w: &[f64], s: &[f64], e: &[f64], r: usize, n: usize) -> f64 {
    (0..r)
        .map(|k| {
            direct(
                &w[k * n..(k + 1) * n],
                &s[k * n..(k + 1) * n],
                &e[k * n..(k + 1) * n],
            )
        })
        .sum()
}

fn case() -> impl Strategy<Value = (usize, usize, Vec<f64>, Vec<f64>, Vec<f64>, f64)> {
    (1usize..4, 1usize..24, -3.0f64..3.0).prop_flat_map(|(r, n, scale_exp)| {
        let m = r * n;
        (
            Just(r),
            Just(n),
            prop::collection::vec(prop_oneof![0.0f64..1.0, 1e-12f64..1e-6, Just(0.0)], m),
            prop::collection::vec(0.01f64..1.0, m),
            prop::collection::vec(0.01f64..1.0, m),
            Just(10f64.powf(scale_exp)),
        )
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn prefix_sum_form_equals_the_double_sum((r, n, w, len, gap, scale) in case()) {
        let len: Vec<f64> = len.iter().map(|x| x * scale).collect();
        let gap: Vec<f64> = gap.iter().map(|x| x * scale).collect();
        let mut s = vec![];
        let mut e = vec![];
        for k in 0..r {
            let (a, b) = intervals(&len[k * n..(k + 1) * n], &gap[k * n..(k + 1) * n], -scale);
            s.extend(a);
            e.extend(b);
        }
        let got = distortion_loss(&t2(&w, r, n), &iv(&t2(&s, r, n), &t2(&e, r, n)))
            .unwrap()
            .to_vec1::<f64>()
            .unwrap();
        for k in 0..r {
            let want = direct(&w[k * n..(k + 1) * n], &s[k * n..(k + 1) * n], &e[k * n..(k + 1) * n]);
            prop_assert!((got[k] - want).abs() <= 1e-12 * (1.0 + want.abs()) + 1e-12 * scale,
                "ray {}: {} vs {}", k, got[k], want);
        }
        // f32 agrees to its precision.
        let got32 = distortion_loss(
            &t2(&w, r, n).to_dtype(DType::F32).unwrap(),
            &iv(
                &t2(&s, r, n).to_dtype(DType::F32).unwrap(),
                &t2(&e, r, n).to_dtype(DType::F32).unwrap(),
            ),
        ).unwrap().to_dtype(DType::F64).unwrap().to_vec1::<f64>().unwrap();
        for k in 0..r {
            let wsum: f64 = w[k * n..(k + 1) * n].iter().sum();
            let bound = 1e-4 * (wsum * wsum + 1.0) * (e[k * n + n - 1] - s[k * n]).abs().max(scale);
            prop_assert!((got32[k] - got[k]).abs() <= bound, "f32 {} vs {}", got32[k], got[k]);
        }
    }

    #[test]
    fn gradients_match_the_hand_derived_formula_and_central_differences(
        (r, n, w, len, gap, scale) in case()
    ) {
        let len: Vec<f64> = len.iter().map(|x| x * scale).collect();
        let gap: Vec<f64> = gap.iter().map(|x| x * scale).collect();
        let mut s = vec![];
        let mut e = vec![];
        for k in 0..r {
            let (a, b) = intervals(&len[k * n..(k + 1) * n], &gap[k * n..(k + 1) * n], 0.3 * scale);
            s.extend(a);
            e.extend(b);
        }
        let wv = Var::from_tensor(&t2(&w, r, n)).unwrap();
        let sv = Var::from_tensor(&t2(&s, r, n)).unwrap();
        let ev = Var::from_tensor(&t2(&e, r, n)).unwrap();
        let l = distortion_loss(wv.as_tensor(), &iv(sv.as_tensor(), ev.as_tensor())).unwrap();
        let g = l.sum_all().unwrap().backward().unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f64>().unwrap();
        let gw = flat(g.get(wv.as_tensor()).unwrap());
        let gs = flat(g.get(sv.as_tensor()).unwrap());
        let ge = flat(g.get(ev.as_tensor()).unwrap());
        for k in 0..r {
            let o = k * n;
            let m: Vec<f64> = (0..n).map(|i| 0.5 * (s[o + i] + e[o + i])).collect();
            for i in 0..n {
                // Hand-derived (docs/math.md, "Distortion loss").
                let dw = 2.0 * (0..n).map(|j| w[o + j] * (m[i] - m[j]).abs()).sum::<f64>()
                    + 2.0 / 3.0 * w[o + i] * (e[o + i] - s[o + i]);
                let before: f64 = (0..i).map(|j| w[o + j]).sum();
                let after: f64 = (i + 1..n).map(|j| w[o + j]).sum();
                let dm = 2.0 * w[o + i] * (before - after);
                let dd = w[o + i] * w[o + i] / 3.0;
                let tol = |x: f64| 1e-10 * (1.0 + x.abs());
                prop_assert!((gw[o + i] - dw).abs() <= tol(dw) * scale.max(1.0), "dw {} vs {}", gw[o + i], dw);
                prop_assert!((gs[o + i] - (0.5 * dm - dd)).abs() <= tol(dm), "ds");
                prop_assert!((ge[o + i] - (0.5 * dm + dd)).abs() <= tol(dm), "de");
            }
        }
        // Central differences on the host double sum, every coordinate.
        let fd = |which: usize, idx: usize, h: f64| {
            let (mut w2, mut s2, mut e2) = (w.clone(), s.clone(), e.clone());
            let v = [&mut w2, &mut s2, &mut e2];
            v[which][idx] += h;
            let lp = loss_host(&w2, &s2, &e2, r, n);
            let (mut w2, mut s2, mut e2) = (w.clone(), s.clone(), e.clone());
            let v = [&mut w2, &mut s2, &mut e2];
            v[which][idx] -= h;
            let lm = loss_host(&w2, &s2, &e2, r, n);
            (lp - lm) / (2.0 * h)
        };
        for idx in 0..r * n {
            let h = 1e-6;
            let want = fd(0, idx, h);
            prop_assert!((gw[idx] - want).abs() <= 1e-6 * (1.0 + want.abs()) * scale.max(1.0), "w fd {} vs {}", gw[idx], want);
            // Intervals: step well inside the smallest gap so that order is kept.
            let hs = 1e-3 * 0.01 * scale;
            let want = fd(1, idx, hs);
            prop_assert!((gs[idx] - want).abs() <= 1e-6 * (1.0 + want.abs()), "s fd {} vs {}", gs[idx], want);
            let want = fd(2, idx, hs);
            prop_assert!((ge[idx] - want).abs() <= 1e-6 * (1.0 + want.abs()), "e fd {} vs {}", ge[idx], want);
        }
    }
}

#[test]
fn extreme_weights_and_lengths_give_finite_values_and_gradients() {
    for (wscale, lscale) in [
        (1e-30, 1e-30),
        (1e-30, 1e10),
        (1.0, 1e-30),
        (1e10, 1e-10),
        (1.0, 1e10),
    ] {
        for dt in [DType::F32, DType::F64] {
            let n = 64;
            let w: Vec<f64> = (0..n)
                .map(|i| wscale * ((i % 7) as f64 + 0.5) / 64.0)
                .collect();
            let s: Vec<f64> = (0..n).map(|i| lscale * i as f64).collect();
            let e: Vec<f64> = (0..n).map(|i| lscale * (i as f64 + 0.9)).collect();
            let wv = Var::from_tensor(&t2(&w, 1, n).to_dtype(dt).unwrap()).unwrap();
            let sv = Var::from_tensor(&t2(&s, 1, n).to_dtype(dt).unwrap()).unwrap();
            let ev = Var::from_tensor(&t2(&e, 1, n).to_dtype(dt).unwrap()).unwrap();
            let l = distortion_loss(wv.as_tensor(), &iv(sv.as_tensor(), ev.as_tensor())).unwrap();
            let g = l.sum_all().unwrap().backward().unwrap();
            let all_finite = |t: &Tensor| {
                t.to_dtype(DType::F64)
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f64>()
                    .unwrap()
                    .iter()
                    .all(|x| x.is_finite())
            };
            if dt == DType::F64 || wscale * wscale * lscale < 1e30 {
                assert!(all_finite(&l), "{dt:?} {wscale} {lscale}");
                for v in [&wv, &sv, &ev] {
                    assert!(
                        all_finite(g.get(v.as_tensor()).unwrap()),
                        "{dt:?} {wscale} {lscale}"
                    );
                }
            }
        }
    }
}

#[test]
fn distortion_of_a_single_interval_and_of_two_point_masses() {
    // One interval: only the intra term, w²δ/3.
    let l = distortion_loss(&t2(&[0.6], 1, 1), &iv(&t2(&[0.2], 1, 1), &t2(&[0.5], 1, 1))).unwrap();
    assert!((l.to_vec1::<f64>().unwrap()[0] - 0.36 * 0.3 / 3.0).abs() < 1e-15);
    // Two zero-length intervals at 0 and 1 with weights a, b: 2ab.
    let l = distortion_loss(
        &t2(&[0.3, 0.5], 1, 2),
        &iv(&t2(&[0.0, 1.0], 1, 2), &t2(&[0.0, 1.0], 1, 2)),
    )
    .unwrap();
    assert!((l.to_vec1::<f64>().unwrap()[0] - 0.3).abs() < 1e-15);
}

#[test]
fn distortion_bad_input_errs_naming_the_argument() {
    let w = t2(&[0.1, 0.2], 1, 2);
    let s = t2(&[0.0, 0.5], 1, 2);
    let e = t2(&[0.4, 0.9], 1, 2);
    assert!(distortion_loss(&w, &iv(&s, &e)).is_ok());
    assert_eq!(
        arg_of(distortion_loss(&t2(&[0.1, 0.2, 0.3], 1, 3), &iv(&s, &e)).unwrap_err()),
        "starts"
    );
    // Intervals that `Intervals::new` would reject are still rejected by the loss
    // itself (the fields are public), naming the same argument.
    assert_eq!(
        arg_of(distortion_loss(&w, &raw_iv(&s, &t2(&[0.4], 1, 1))).unwrap_err()),
        "ends"
    );
    assert_eq!(
        arg_of(Intervals::new(s.clone(), t2(&[0.4], 1, 1), Layout::Batched).unwrap_err()),
        "ends"
    );
    assert_eq!(
        arg_of(distortion_loss(&w, &raw_iv(&t2(&[0.5, 0.0], 1, 2), &e)).unwrap_err()),
        "starts"
    );
    assert_eq!(
        arg_of(distortion_loss(&w, &raw_iv(&e, &s)).unwrap_err()),
        "starts"
    );
    assert_eq!(
        arg_of(distortion_loss(&w, &raw_iv(&s.to_dtype(DType::F32).unwrap(), &e)).unwrap_err()),
        "starts"
    );
    assert_eq!(
        arg_of(distortion_loss(&w.to_dtype(DType::F32).unwrap(), &iv(&s, &e)).unwrap_err()),
        "starts"
    );
}

/// RegNeRF's opacity weighting: each top-left pixel's two differences scaled by its weight
/// (hand-computed), the last row and column of the weights unused, and a weight of the
/// wrong shape an error naming `weights`.
#[test]
fn weighted_depth_smoothness_scales_each_pixel_by_its_weight() {
    #[rustfmt::skip]
    let d = [1.0, 2.0, 4.0,
             0.0, 3.0, 3.0,
             5.0, 5.0, 5.0];
    #[rustfmt::skip]
    let m = [1.0, 0.0, 9.0,
             0.5, 0.25, 9.0,
             9.0, 9.0, 9.0];
    let t = |v: &[f64]| Tensor::from_vec(v.to_vec(), (1, 3, 3), &Device::Cpu).unwrap();
    // Pixel terms 2, 5, 34, 4 (see below) weighted 1, 0, 0.5, 0.25: (2 + 17 + 1)/4 = 5.
    let l = depth_smoothness(&t(&d), Some(&t(&m)))
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    assert_eq!(l, vec![5.0]);
    let bad = Tensor::ones((1, 2, 3), DType::F64, &Device::Cpu).unwrap();
    assert_eq!(
        arg_of(depth_smoothness(&t(&d), Some(&bad)).unwrap_err()),
        "weights"
    );
}

#[test]
fn depth_smoothness_matches_a_hand_computed_patch() {
    #[rustfmt::skip]
    let d = [
        1.0, 2.0, 4.0,
        0.0, 3.0, 3.0,
        5.0, 5.0, 5.0,
        // A constant patch costs nothing.
        7.0, 7.0, 7.0,
        7.0, 7.0, 7.0,
        7.0, 7.0, 7.0,
    ];
    // Pixel (0,0): (1−2)² + (1−0)² = 2; (0,1): (2−4)² + (2−3)² = 5;
    // (1,0): (0−3)² + (0−5)² = 34; (1,1): (3−3)² + (3−5)² = 4. Mean 45/4.
    for dt in [DType::F32, DType::F64] {
        let t = Tensor::from_vec(d.to_vec(), (2, 3, 3), &Device::Cpu)
            .unwrap()
            .to_dtype(dt)
            .unwrap();
        let l = depth_smoothness(&t, None)
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap()
            .to_vec1::<f64>()
            .unwrap();
        assert_eq!(l, vec![11.25, 0.0]);
    }
    // Gradient of the first patch at pixel (1,1): from its own term 2(3−3) + 2(3−5) = −4,
    // from (0,1)'s vertical term −2(2−3) = 2 and (1,0)'s horizontal term −2(0−3) = 6: 4,
    // over the 4 positions of the mean: 1.
    let v =
        Var::from_tensor(&Tensor::from_vec(d.to_vec(), (2, 3, 3), &Device::Cpu).unwrap()).unwrap();
    let g = depth_smoothness(v.as_tensor(), None)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let gv = g
        .get(v.as_tensor())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    assert_eq!(gv[4], 1.0);
    // Central differences everywhere (the loss is quadratic: exact up to rounding).
    for idx in 0..18 {
        let f = |h: f64| {
            let mut d2 = d.to_vec();
            d2[idx] += h;
            let t = Tensor::from_vec(d2, (2, 3, 3), &Device::Cpu).unwrap();
            depth_smoothness(&t, None)
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar::<f64>()
                .unwrap()
        };
        let want = (f(1e-3) - f(-1e-3)) / 2e-3;
        assert!(
            (gv[idx] - want).abs() < 1e-8,
            "{idx}: {} vs {want}",
            gv[idx]
        );
    }
    let bad = Tensor::zeros((2, 1, 1), DType::F32, &Device::Cpu).unwrap();
    assert_eq!(arg_of(depth_smoothness(&bad, None).unwrap_err()), "depth");
    let bad = Tensor::zeros((3, 3), DType::F32, &Device::Cpu).unwrap();
    assert_eq!(arg_of(depth_smoothness(&bad, None).unwrap_err()), "depth");
}

#[test]
fn depth_smoothness_weight_decays_log_linearly_from_400_to_0_1_over_512_steps() {
    assert!((depth_smoothness_weight(0) - 400.0).abs() < 1e-12);
    assert!((depth_smoothness_weight(256) - 40f64.sqrt()).abs() < 1e-12);
    assert!((depth_smoothness_weight(128) - 400.0 * (0.1f64 / 400.0).powf(0.25)).abs() < 1e-10);
    assert_eq!(depth_smoothness_weight(512), 0.1);
    assert_eq!(depth_smoothness_weight(100_000), 0.1);
    assert_eq!(log_linear_schedule(5, 2.0, 8.0, 0), 8.0);
    assert!((log_linear_schedule(1, 2.0, 8.0, 2) - 4.0).abs() < 1e-12);
}

/// A learning rate of 0 (`start = end = 0`) made the schedule NaN at step 0 (0·ln 0), and
/// a training run that decayed it stopped on a NaN camera rotation.
#[test]
fn a_zero_rate_made_the_log_linear_schedule_nan() {
    for step in [0, 1, 50, 99, 100, 1000] {
        assert_eq!(log_linear_schedule(step, 0.0, 0.0, 100), 0.0, "step {step}");
    }
    // Decaying to 0: the start, then the limit 0.
    assert_eq!(log_linear_schedule(0, 1e-3, 0.0, 100), 1e-3);
    for step in [1, 50, 100, 1000] {
        assert_eq!(
            log_linear_schedule(step, 1e-3, 0.0, 100),
            0.0,
            "step {step}"
        );
    }
    // Rising from 0: 0 until the end.
    assert_eq!(log_linear_schedule(99, 0.0, 1.0, 100), 0.0);
    assert_eq!(log_linear_schedule(100, 0.0, 1.0, 100), 1.0);
    // Extreme positive endpoints stay finite and monotone.
    let mut last = f64::INFINITY;
    for step in 0..=64 {
        let v = log_linear_schedule(step, 1e300, 1e-300, 64);
        assert!(v.is_finite() && v > 0.0 && v <= last, "step {step}: {v}");
        last = v;
    }
    assert!(log_linear_schedule(3, -1.0, 1.0, 10).is_nan());
}
