//! Samplers along rays: stratified intervals, importance sampling from a step-function
//! PDF, merging, annealed near/far, and the errors they return on bad input.
#![cfg(feature = "volume")]

use candle_core::{DType, Device, Tensor, Var};
use neural_fields::camera::Rays;
use neural_fields::volume::Layout;
use neural_fields::volume::{
    anneal_near_far, merge_sorted, sample_pdf, stratified, Intervals, Jitter,
};
use neural_fields::Error;
use proptest::prelude::*;

fn dev() -> Device {
    Device::Cpu
}

fn t1(v: &[f64], dt: DType) -> Tensor {
    Tensor::new(v, &dev()).unwrap().to_dtype(dt).unwrap()
}

fn t2(v: &[f64], r: usize, c: usize, dt: DType) -> Tensor {
    Tensor::from_vec(v.to_vec(), (r, c), &dev())
        .unwrap()
        .to_dtype(dt)
        .unwrap()
}

/// The intervals whose bins are `bins` (`[R, S + 1]` edges): starts `bins[.., ..S]`,
/// ends `bins[.., 1..]`.
fn bins_iv(bins: &Tensor) -> Intervals {
    let s = bins.dim(1).unwrap() - 1;
    Intervals::new(
        bins.narrow(1, 0, s).unwrap(),
        bins.narrow(1, 1, s).unwrap(),
        Layout::Batched,
    )
    .unwrap()
}

fn rows(t: &Tensor) -> Vec<Vec<f64>> {
    t.to_dtype(DType::F64).unwrap().to_vec2::<f64>().unwrap()
}

fn arg_of(e: Error) -> &'static str {
    match e {
        Error::InvalidArgument { arg, .. } => arg,
        other => panic!("expected InvalidArgument, got {other}"),
    }
}

const DTYPES: [DType; 2] = [DType::F32, DType::F64];

#[test]
fn stratified_deterministic_equals_the_linspace_formula() {
    for dt in DTYPES {
        let near = [0.0, 2.0, -1.5, 3.0];
        let far = [1.0, 6.0, 0.25, 3.0];
        let n = 7;
        let iv = stratified(&t1(&near, dt), &t1(&far, dt), n, Jitter::None, 0).unwrap();
        assert_eq!(iv.starts.dtype(), dt);
        let (s, e, m) = (
            rows(&iv.starts),
            rows(&iv.ends),
            rows(&iv.midpoints().unwrap()),
        );
        let tol = if dt == DType::F32 { 1e-6 } else { 1e-14 };
        for r in 0..near.len() {
            let span = far[r] - near[r];
            for k in 0..n {
                let want_s = near[r] + span * k as f64 / n as f64;
                let want_e = near[r] + span * (k + 1) as f64 / n as f64;
                let want_m = near[r] + span * (k as f64 + 0.5) / n as f64;
                assert!(
                    (s[r][k] - want_s).abs() <= tol * (1.0 + want_s.abs()),
                    "{dt:?} start"
                );
                assert!(
                    (e[r][k] - want_e).abs() <= tol * (1.0 + want_e.abs()),
                    "{dt:?} end"
                );
                assert!(
                    (m[r][k] - want_m).abs() <= tol * (1.0 + want_m.abs()),
                    "{dt:?} mid"
                );
            }
            // Endpoints are exact, not merely close.
            assert_eq!(
                s[r][0],
                t1(&[near[r]], dt)
                    .to_dtype(DType::F64)
                    .unwrap()
                    .to_vec1::<f64>()
                    .unwrap()[0]
            );
            assert_eq!(
                e[r][n - 1],
                t1(&[far[r]], dt)
                    .to_dtype(DType::F64)
                    .unwrap()
                    .to_vec1::<f64>()
                    .unwrap()[0]
            );
        }
    }
}

fn jitter_strategy() -> impl Strategy<Value = Jitter> {
    prop_oneof![
        Just(Jitter::None),
        Just(Jitter::PerSample),
        Just(Jitter::SingleJitter)
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn stratified_samples_lie_in_near_far_are_sorted_and_contiguous(
        near in prop::collection::vec(-1e6f64..1e6, 1..6),
        span_exp in prop::collection::vec(-20f64..6.0, 6),
        n in 1usize..40,
        jitter in jitter_strategy(),
        seed in any::<u64>(),
        f32_mode in any::<bool>(),
    ) {
        let dt = if f32_mode { DType::F32 } else { DType::F64 };
        let far: Vec<f64> = near.iter().zip(&span_exp).map(|(a, e)| a + 10f64.powf(*e)).collect();
        // Round the inputs to the dtype first so that `near ≤ far` holds there too.
        let nt = t1(&near, dt);
        let ft = t1(&far, dt);
        let nh = nt.to_dtype(DType::F64).unwrap().to_vec1::<f64>().unwrap();
        let fh = ft.to_dtype(DType::F64).unwrap().to_vec1::<f64>().unwrap();
        let iv = stratified(&nt, &ft, n, jitter, seed).unwrap();
        let (s, e) = (rows(&iv.starts), rows(&iv.ends));
        for r in 0..near.len() {
            prop_assert_eq!(s[r][0], nh[r]);
            prop_assert_eq!(e[r][n - 1], fh[r]);
            for k in 0..n {
                prop_assert!(s[r][k] >= nh[r] && e[r][k] <= fh[r]);
                prop_assert!(s[r][k] <= e[r][k]);
                if k + 1 < n {
                    prop_assert_eq!(e[r][k], s[r][k + 1]);
                }
            }
        }
    }
}

#[test]
fn single_jitter_shifts_all_interior_edges_by_one_draw() {
    let near = t1(&[0.0, 0.0, 0.0], DType::F64);
    let far = t1(&[1.0, 1.0, 1.0], DType::F64);
    let n = 10;
    let iv = stratified(&near, &far, n, Jitter::SingleJitter, 7).unwrap();
    let s = rows(&iv.starts);
    for row in &s {
        let shift = row[1] - 1.0 / n as f64;
        assert!(shift.abs() <= 0.5 / n as f64 + 1e-15);
        for (k, x) in row.iter().enumerate().skip(1) {
            assert!((x - k as f64 / n as f64 - shift).abs() < 1e-12);
        }
    }
    // Different rays draw differently; the per-sample mode varies along the ray.
    assert_ne!(s[0][1], s[1][1]);
    let p = rows(
        &stratified(&near, &far, n, Jitter::PerSample, 7)
            .unwrap()
            .starts,
    );
    let d1 = p[0][1] - 0.1;
    let d2 = p[0][2] - 0.2;
    assert!((d1 - d2).abs() > 1e-9);
}

#[test]
fn jittered_samples_are_reproducible_from_the_seed() {
    let near = t1(&[0.0, 1.0], DType::F32);
    let far = t1(&[1.0, 5.0], DType::F32);
    let a = rows(
        &stratified(&near, &far, 16, Jitter::PerSample, 42)
            .unwrap()
            .starts,
    );
    let b = rows(
        &stratified(&near, &far, 16, Jitter::PerSample, 42)
            .unwrap()
            .starts,
    );
    let c = rows(
        &stratified(&near, &far, 16, Jitter::PerSample, 43)
            .unwrap()
            .starts,
    );
    assert_eq!(a, b);
    assert_ne!(a, c);
}

#[test]
fn deltas_are_scaled_by_the_direction_norm() {
    for dt in DTYPES {
        let near = t1(&[0.0, 1.0], dt);
        let far = t1(&[1.0, 3.0], dt);
        let iv = stratified(&near, &far, 4, Jitter::None, 0).unwrap();
        let origins = t2(&[0.0; 6], 2, 3, dt);
        let dirs = t2(&[0.0, 0.0, 1.0, 3.0, 4.0, 1.0], 2, 3, dt);
        let rays = Rays::new(origins.clone(), dirs).unwrap();
        let d = rows(&iv.deltas(Some(&rays)).unwrap());
        let plain = rows(&iv.deltas(None).unwrap());
        let norm1 = (26.0f64).sqrt();
        for k in 0..4 {
            assert!((d[0][k] - 0.25).abs() < 1e-6);
            assert!((plain[1][k] - 0.5).abs() < 1e-6);
            assert!((d[1][k] - 0.5 * norm1).abs() < 1e-5);
        }
        // Zero and misshapen directions cannot make rays; rays that do not match the
        // intervals are named.
        let zero = t2(&[0.0; 6], 2, 3, dt);
        assert_eq!(
            arg_of(Rays::new(origins.clone(), zero).unwrap_err()),
            "directions"
        );
        let bad = t2(&[0.0; 4], 2, 2, dt);
        assert_eq!(
            arg_of(Rays::new(origins.clone(), bad).unwrap_err()),
            "directions"
        );
        let three = Rays::new(t2(&[0.0; 9], 3, 3, dt), t2(&[1.0; 9], 3, 3, dt)).unwrap();
        assert_eq!(arg_of(iv.deltas(Some(&three)).unwrap_err()), "rays");
    }
}

#[test]
fn samples_from_a_one_hot_step_function_land_exactly_in_that_bin() {
    // Bins with awkward edges, so that interpolation rounding would show.
    let edges = [0.1, 0.3, 0.7000001, 0.7000002, 1.3, 2.9];
    for dt in DTYPES {
        let eh = t1(&edges, dt)
            .to_dtype(DType::F64)
            .unwrap()
            .to_vec1::<f64>()
            .unwrap();
        for hot in 0..5 {
            let mut w = [0.0; 5];
            w[hot] = 1.0;
            let bins = t2(&edges, 1, 6, dt);
            let weights = t2(&w, 1, 5, dt);
            for det in [true, false] {
                let t = sample_pdf(&bins_iv(&bins), &weights, 257, det, 3, 0.0).unwrap();
                assert_eq!(t.dtype(), dt);
                for x in &rows(&t)[0] {
                    assert!(
                        *x >= eh[hot] && *x <= eh[hot + 1],
                        "{dt:?} bin {hot} det {det}: {x} outside [{}, {}]",
                        eh[hot],
                        eh[hot + 1]
                    );
                }
            }
            // NeRF's padding of 1e-5 with deterministic u still keeps every sample in
            // the hot bin: the padded mass outside is far below 1/(2n).
            let t = sample_pdf(&bins_iv(&bins), &weights, 64, true, 0, 1e-5).unwrap();
            for x in &rows(&t)[0] {
                assert!(*x >= eh[hot] && *x <= eh[hot + 1]);
            }
        }
    }
}

#[test]
fn histogram_of_a_million_importance_samples_matches_the_pdf() {
    // Uneven bins and weights; each bin is split into 4 equal sub-bins for the
    // histogram, so that the uniform density inside a bin is checked too.
    let edges = [0.0, 0.5, 0.75, 2.0, 2.5, 4.0, 4.1, 6.0];
    let w = [0.05, 0.2, 0.1, 0.0, 0.3, 0.25, 0.1];
    let total: f64 = w.iter().sum();
    let (rays, n) = (1000usize, 1000usize);
    let sub = 4usize;
    let s = w.len();
    let bins = Tensor::from_vec(edges.repeat(rays), (rays, s + 1), &dev()).unwrap();
    let weights = Tensor::from_vec(w.repeat(rays), (rays, s), &dev()).unwrap();
    for (dt, seed) in [(DType::F64, 11u64), (DType::F32, 12)] {
        let t = sample_pdf(
            &bins_iv(&bins.to_dtype(dt).unwrap()),
            &weights.to_dtype(dt).unwrap(),
            n,
            false,
            seed,
            0.0,
        )
        .unwrap();
        let samples = t
            .to_dtype(DType::F64)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f64>()
            .unwrap();
        assert_eq!(samples.len(), 1_000_000);
        let mut counts = vec![0usize; s * sub];
        for x in &samples {
            let b = edges
                .windows(2)
                .position(|e| *x >= e[0] && *x < e[1])
                .unwrap_or(s - 1);
            let frac = (x - edges[b]) / (edges[b + 1] - edges[b]);
            let k = ((frac * sub as f64) as usize).min(sub - 1);
            counts[b * sub + k] += 1;
        }
        let mut max_err = 0.0f64;
        for b in 0..s {
            for k in 0..sub {
                let got = counts[b * sub + k] as f64 / samples.len() as f64;
                let want = w[b] / total / sub as f64;
                max_err = max_err.max((got - want).abs());
            }
        }
        println!(
            "sample_pdf histogram ({dt:?}, 10^6 samples, {} sub-bins): max bin error {max_err:.3e}",
            s * sub
        );
        assert!(max_err < 5e-4, "{dt:?}: max bin error {max_err}");
    }
}

#[test]
fn importance_samples_are_sorted_and_detached() {
    let edges: Vec<f64> = (0..=16).map(|i| (i as f64).powf(1.3)).collect();
    let w: Vec<f64> = (0..16).map(|i| ((i * 7) % 5) as f64 * 0.1).collect();
    for dt in DTYPES {
        let bins = Var::from_tensor(&t2(&edges, 1, 17, dt)).unwrap();
        let weights = Var::from_tensor(&t2(&w, 1, 16, dt)).unwrap();
        for det in [true, false] {
            let t = sample_pdf(
                &bins_iv(bins.as_tensor()),
                weights.as_tensor(),
                100,
                det,
                5,
                1e-5,
            )
            .unwrap();
            let row = &rows(&t)[0];
            assert!(row.windows(2).all(|p| p[0] <= p[1]), "not sorted");
            assert!(row[0] >= edges[0] && row[99] <= edges[16]);
            // No graph: a loss built on the samples gives no gradient to the inputs.
            let loss = (t.sqr().unwrap().sum_all().unwrap()
                + weights.as_tensor().sum_all().unwrap())
            .unwrap();
            let grads = loss.backward().unwrap();
            assert!(
                grads.get(bins.as_tensor()).is_none(),
                "gradient reached bins"
            );
            let gw = grads.get(weights.as_tensor()).unwrap();
            // Only the direct term contributes: d(sum w)/dw = 1.
            for g in &rows(gw)[0] {
                assert_eq!(*g, 1.0);
            }
        }
    }
}

/// The CDF's own bounds are checked in src/volume/sampling.rs (`host_cdf`).
#[test]
fn deterministic_samples_of_a_uniform_pdf_are_the_bin_centred_linspace() {
    for dt in DTYPES {
        // Deterministic samples of a uniform PDF are the bin-centred linspace.
        let bins = t2(&[0.0, 1.0, 2.0, 3.0, 4.0], 1, 5, dt);
        let t = sample_pdf(&bins_iv(&bins), &t2(&[1.0; 4], 1, 4, dt), 4, true, 0, 0.0).unwrap();
        assert_eq!(rows(&t)[0], vec![0.5, 1.5, 2.5, 3.5]);
    }
}

#[test]
fn merged_samples_are_sorted_complete_and_carry_gradients_to_coarse() {
    let near = t1(&[0.0, 1.0], DType::F64);
    let far = t1(&[2.0, 5.0], DType::F64);
    let iv = stratified(&near, &far, 8, Jitter::PerSample, 1).unwrap();
    let coarse = Var::from_tensor(&iv.midpoints().unwrap()).unwrap();
    let w = Tensor::rand(0f64, 1.0, (2, 8), &dev()).unwrap();
    let fine = sample_pdf(&iv, &w, 16, false, 2, 1e-5).unwrap();
    let merged = merge_sorted(coarse.as_tensor(), &fine).unwrap();
    assert_eq!(merged.dims(), &[2, 24]);
    let m = rows(&merged);
    let mut want = rows(coarse.as_tensor());
    for (r, f) in rows(&fine).into_iter().enumerate() {
        want[r].extend(f);
        want[r].sort_by(|a, b| a.partial_cmp(b).unwrap());
    }
    assert_eq!(m, want);
    let g = merged.sum_all().unwrap().backward().unwrap();
    let gc = rows(g.get(coarse.as_tensor()).unwrap());
    assert!(gc.iter().flatten().all(|x| *x == 1.0));
    // Re-derived intervals: contiguous, from near to far, containing every sample.
    let iv2 = Intervals::from_samples(&merged, &near, &far).unwrap();
    let (s, e) = (rows(&iv2.starts), rows(&iv2.ends));
    for r in 0..2 {
        assert_eq!(s[r][0], [0.0, 1.0][r]);
        assert_eq!(e[r][23], [2.0, 5.0][r]);
        for k in 0..24 {
            assert!(s[r][k] <= m[r][k] && m[r][k] <= e[r][k]);
            if k < 23 {
                assert_eq!(e[r][k], s[r][k + 1]);
            }
        }
    }
}

#[test]
fn annealed_near_far_follows_regnerf_schedule() {
    let near = t1(&[2.0], DType::F64);
    let far = t1(&[6.0], DType::F64);
    let at = |step| {
        let (n, f) = anneal_near_far(&near, &far, step, 256, 0.5, 0.5).unwrap();
        (
            rows(&n.unsqueeze(0).unwrap())[0][0],
            rows(&f.unsqueeze(0).unwrap())[0][0],
        )
    };
    // mid = 4; start at [4 − 1, 4 + 1]; halfway s = 0.75 → [2.5, 5.5]; then [2, 6].
    assert_eq!(at(0), (3.0, 5.0));
    assert_eq!(at(128), (2.5, 5.5));
    assert_eq!(at(256), (2.0, 6.0));
    assert_eq!(at(10_000), (2.0, 6.0));
    let (n, f) = anneal_near_far(&near, &far, 0, 100, 0.2, 0.25).unwrap();
    // mid = 3; [3 + 0.2(2 − 3), 3 + 0.2(6 − 3)] = [2.8, 3.6]
    assert!((rows(&n.unsqueeze(0).unwrap())[0][0] - 2.8).abs() < 1e-12);
    assert!((rows(&f.unsqueeze(0).unwrap())[0][0] - 3.6).abs() < 1e-12);
    assert_eq!(
        arg_of(anneal_near_far(&near, &far, 0, 10, 1.5, 0.5).unwrap_err()),
        "p_start"
    );
    assert_eq!(
        arg_of(anneal_near_far(&near, &far, 0, 10, 0.5, -0.1).unwrap_err()),
        "mid_ratio"
    );
}

#[test]
fn bad_input_errs_naming_the_argument() {
    let dt = DType::F32;
    let near = t1(&[0.0, 3.0], dt);
    let far = t1(&[1.0, 2.0], dt);
    // near > far on ray 1.
    let e = stratified(&near, &far, 4, Jitter::None, 0).unwrap_err();
    assert!(e.to_string().contains("near 3 > far 2"), "{e}");
    assert_eq!(arg_of(e), "near");
    let far_ok = t1(&[1.0, 4.0], dt);
    assert_eq!(
        arg_of(stratified(&near, &far_ok, 0, Jitter::None, 0).unwrap_err()),
        "n"
    );
    assert_eq!(
        arg_of(stratified(&near, &t1(&[1.0], dt), 4, Jitter::None, 0).unwrap_err()),
        "far"
    );
    assert_eq!(
        arg_of(
            stratified(
                &near,
                &far_ok.to_dtype(DType::F64).unwrap(),
                4,
                Jitter::None,
                0
            )
            .unwrap_err()
        ),
        "far"
    );
    assert_eq!(
        arg_of(stratified(&t1(&[f64::NAN, 0.0], dt), &far_ok, 4, Jitter::None, 0).unwrap_err()),
        "near"
    );
    let i32near = Tensor::new(&[0u32, 1], &dev()).unwrap();
    assert_eq!(
        arg_of(stratified(&i32near, &far_ok, 4, Jitter::None, 0).unwrap_err()),
        "near"
    );

    let bins = bins_iv(&t2(&[0.0, 1.0, 2.0, 3.0], 1, 4, dt));
    let w = t2(&[0.2, 0.3, 0.5], 1, 3, dt);
    assert!(sample_pdf(&bins, &w, 8, true, 0, 1e-5).is_ok());
    assert_eq!(
        arg_of(sample_pdf(&bins, &w, 0, true, 0, 1e-5).unwrap_err()),
        "n"
    );
    let neg = t2(&[0.2, -0.3, 0.5], 1, 3, dt);
    assert_eq!(
        arg_of(sample_pdf(&bins, &neg, 8, true, 0, 1e-5).unwrap_err()),
        "weights"
    );
    // Unsorted bins no longer make intervals: edges [0, 2, 1, 3] give the inverted
    // interval [2, 1].
    let unsorted = t2(&[0.0, 2.0, 1.0, 3.0], 1, 4, dt);
    assert_eq!(
        arg_of(
            Intervals::new(
                unsorted.narrow(1, 0, 3).unwrap(),
                unsorted.narrow(1, 1, 3).unwrap(),
                Layout::Batched
            )
            .unwrap_err()
        ),
        "ends"
    );
    let short = bins_iv(&t2(&[0.0, 1.0, 2.0], 1, 3, dt));
    assert_eq!(
        arg_of(sample_pdf(&short, &w, 8, true, 0, 1e-5).unwrap_err()),
        "intervals"
    );
    let two_rays = bins_iv(&t2(&[0.0, 1.0, 2.0, 3.0, 0.0, 1.0, 2.0, 3.0], 2, 4, dt));
    assert_eq!(
        arg_of(sample_pdf(&two_rays, &w, 8, true, 0, 1e-5).unwrap_err()),
        "intervals"
    );
    assert_eq!(
        arg_of(sample_pdf(&bins, &w, 8, true, 0, -1.0).unwrap_err()),
        "padding"
    );
    assert_eq!(
        arg_of(sample_pdf(&bins, &w.to_dtype(DType::F64).unwrap(), 8, true, 0, 0.0).unwrap_err()),
        "intervals"
    );
    let nan_w = t2(&[0.2, f64::NAN, 0.5], 1, 3, dt);
    assert_eq!(
        arg_of(sample_pdf(&bins, &nan_w, 8, true, 0, 1e-5).unwrap_err()),
        "weights"
    );

    let a = t2(&[0.0, 1.0], 1, 2, dt);
    let b = t2(&[0.0, 1.0, 2.0, 3.0], 2, 2, dt);
    assert_eq!(arg_of(merge_sorted(&a, &b).unwrap_err()), "fine");

    let near1 = t1(&[0.0], dt);
    let far1 = t1(&[1.0], dt);
    let unsorted_samples = t2(&[0.5, 0.2], 1, 2, dt);
    assert_eq!(
        arg_of(Intervals::from_samples(&unsorted_samples, &near1, &far1).unwrap_err()),
        "samples"
    );
    let outside = t2(&[0.5, 1.2], 1, 2, dt);
    assert_eq!(
        arg_of(Intervals::from_samples(&outside, &near1, &far1).unwrap_err()),
        "samples"
    );
    let inverted = Intervals::new(
        t2(&[0.0, 0.7], 1, 2, dt),
        t2(&[0.6, 0.65], 1, 2, dt),
        Layout::Batched,
    );
    assert_eq!(arg_of(inverted.unwrap_err()), "ends");
    let overlapping = Intervals::new(
        t2(&[0.0, 0.5], 1, 2, dt),
        t2(&[0.6, 0.7], 1, 2, dt),
        Layout::Batched,
    );
    assert_eq!(arg_of(overlapping.unwrap_err()), "starts");
}

fn pdf_case() -> impl Strategy<Value = (Vec<f64>, Vec<f64>)> {
    (1usize..20).prop_flat_map(|s| {
        (
            // Bin widths, zero-width bins included, over scales 1e-6…1e6.
            prop::collection::vec(
                prop_oneof![Just(0.0), 1e-6f64..1e-3, 1e-3f64..1.0, 1.0f64..1e6],
                s,
            ),
            // Weights with exact zeros (zero-mass bins must never be drawn from).
            prop::collection::vec(
                prop_oneof![Just(0.0), Just(0.0), 1e-20f64..1e-10, 1e-3f64..10.0],
                s,
            ),
        )
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]
    #[test]
    fn importance_samples_stay_in_bins_of_positive_mass_and_are_sorted(
        (widths, w) in pdf_case(),
        origin in -1e3f64..1e3,
        n in 1usize..64,
        deterministic in any::<bool>(),
        f32_mode in any::<bool>(),
        seed in any::<u64>(),
    ) {
        let dt = if f32_mode { DType::F32 } else { DType::F64 };
        let s = w.len();
        let mut edges = vec![origin];
        for x in &widths {
            edges.push(edges.last().unwrap() + x);
        }
        // The edges as the dtype holds them (rounding keeps them sorted).
        let bins = t2(&edges, 1, s + 1, dt);
        let eh = rows(&bins)[0].clone();
        let t = sample_pdf(&bins_iv(&bins), &t2(&w, 1, s, dt), n, deterministic, seed, 0.0).unwrap();
        let row = &rows(&t)[0];
        let wh = rows(&t2(&w, 1, s, dt))[0].clone();
        let all_zero = wh.iter().all(|x| *x == 0.0);
        prop_assert!(row.windows(2).all(|p| p[0] <= p[1]), "not sorted");
        for x in row {
            let ok = (0..s).any(|i| eh[i] <= *x && *x <= eh[i + 1] && (all_zero || wh[i] > 0.0));
            prop_assert!(ok, "sample {} not in a bin of positive mass; edges {:?}, weights {:?}", x, eh, wh);
        }
    }
}

/// A smooth, thin bump of density: σ(t) = A·exp(−(t − 2)²/(2w²)) with A = 40, w = 0.05
/// (optical depth 5); colour c(t) = t.
fn bump_field(t: &Tensor) -> (Tensor, Tensor) {
    let z = (t - 2.0).unwrap() / 0.05;
    let sigma = (z.unwrap().sqr().unwrap() * -0.5).unwrap().exp().unwrap() * 40.0;
    (sigma.unwrap(), t.unsqueeze(2).unwrap())
}

/// The bump's colour by a host midpoint rule with 10⁶ steps on [1.5, 2.5] (the density
/// outside is below e^−50).
fn bump_exact() -> f64 {
    let n = 1_000_000;
    let h = 1.0 / n as f64;
    let (mut tau, mut c) = (0.0f64, 0.0f64);
    for i in 0..n {
        let t = 1.5 + (i as f64 + 0.5) * h;
        let x = 40.0 * (-0.5 * ((t - 2.0) / 0.05).powi(2)).exp() * h;
        c += (-tau).exp() * (-(-x).exp_m1()) * t;
        tau += x;
    }
    c
}

fn render_bump(iv: &Intervals) -> Vec<f64> {
    use neural_fields::volume::{composite, CompositeConfig};
    let mids = iv.midpoints().unwrap();
    let (sigma, rgb) = bump_field(&mids);
    composite(&sigma, &rgb, iv, None, &CompositeConfig::default())
        .unwrap()
        .color
        .flatten_all()
        .unwrap()
        .to_vec1::<f64>()
        .unwrap()
}

#[test]
fn coarse_to_fine_importance_sampling_beats_stratified_at_small_budgets() {
    use neural_fields::volume::{render_weights, CompositeConfig};
    let exact = bump_exact();
    let r = 256;
    let near = Tensor::zeros(r, DType::F64, &dev()).unwrap();
    let far = (near.ones_like().unwrap() * 4.0).unwrap();
    let mean_err = |c: &[f64]| c.iter().map(|x| (x - exact).abs()).sum::<f64>() / c.len() as f64;
    println!("thin bump (exact colour {exact:.6}), mean |colour error| over {r} rays:");
    for (nc, nf, gain) in [
        (16usize, 32usize, 4.0),
        (32, 64, 2.0),
        (64, 128, 1.0),
        (64, 256, 0.0),
    ] {
        let flat = stratified(&near, &far, nc + nf, Jitter::PerSample, 1).unwrap();
        let err_flat = mean_err(&render_bump(&flat));
        // nc coarse + nf importance samples from the coarse weights, merged.
        let coarse = stratified(&near, &far, nc, Jitter::PerSample, 2).unwrap();
        let cm = coarse.midpoints().unwrap();
        let (sigma, _) = bump_field(&cm);
        let w = render_weights(&sigma, &coarse, None, &CompositeConfig::default())
            .unwrap()
            .weights;
        let fine = sample_pdf(&coarse, &w, nf, false, 3, 1e-5).unwrap();
        let merged = merge_sorted(&cm, &fine).unwrap();
        let iv = Intervals::from_samples(&merged, &near, &far).unwrap();
        let err_imp = mean_err(&render_bump(&iv));
        println!(
            "  {:>3} samples: stratified {err_flat:.3e}, {nc} coarse + {nf} importance {err_imp:.3e}",
            nc + nf
        );
        // At small budgets the coarse pass finds the bump and the fine samples resolve
        // it; at large ones stratified sampling's O(1/N²) error catches up (importance
        // samples follow the weights, not the quadrature error in the bump's front tail).
        assert!(
            err_imp * gain <= err_flat,
            "{nc}+{nf}: importance {err_imp} vs stratified {err_flat}"
        );
    }
}
