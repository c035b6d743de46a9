//! Proposal sampling and the interlevel loss: closed forms, a brute-force overlap check,
//! finite-difference gradients in f64 over extreme weights, and bad input.
#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::{central_diff, close, v64};
use neural_fields::camera::Rays;
use neural_fields::rng::SplitMix64;
use neural_fields::volume::Layout;
use neural_fields::volume::{
    interlevel_loss, proposal_sample, stratified, Intervals, Jitter, ProposalConfig,
};
use neural_fields::Error;
use proptest::prelude::*;

/// Random batched intervals on `[0, 1]` (stratified, jittered) and random weights.
fn level(r: usize, s: usize, seed: u64, scale: f64) -> (Intervals, Tensor) {
    let dev = Device::Cpu;
    let near = Tensor::zeros(r, DType::F64, &dev).unwrap();
    let far = Tensor::ones(r, DType::F64, &dev).unwrap();
    let iv = stratified(&near, &far, s, Jitter::PerSample, seed).unwrap();
    let mut rng = SplitMix64::new(seed);
    let w = rng
        .uniform_tensor(&[r, s], 0.0, scale, DType::F64, &dev)
        .unwrap();
    (iv, w)
}

/// The loss with the bound by brute force over all pairs.
fn brute(coarse: &(Intervals, Tensor), fine: &Intervals, w: &Tensor) -> f64 {
    let (cs, ce, cw) = (v64(&coarse.0.starts), v64(&coarse.0.ends), v64(&coarse.1));
    let (fs, fe, fw) = (v64(&fine.starts), v64(&fine.ends), v64(w));
    let (r, s) = fine.starts.dims2().unwrap();
    let sc = coarse.0.starts.dims2().unwrap().1;
    let mut total = 0.0;
    for ray in 0..r {
        for i in 0..s {
            let bound: f64 = (0..sc)
                .filter(|&j| {
                    cs[ray * sc + j] < fe[ray * s + i] && ce[ray * sc + j] > fs[ray * s + i]
                })
                .map(|j| cw[ray * sc + j])
                .sum();
            let wi = fw[ray * s + i];
            total += (wi - bound).max(0.0).powi(2) / (wi + 1e-7);
        }
    }
    total / r as f64
}

#[test]
fn loss_matches_the_brute_force_bound_and_its_closed_forms() {
    let coarse = level(5, 7, 1, 0.3);
    let (fine, w) = level(5, 19, 2, 0.2);
    let got = interlevel_loss(&coarse, &fine, &w)
        .unwrap()
        .to_scalar::<f64>()
        .unwrap();
    assert!(close(got, brute(&coarse, &fine, &w), 1e-12, 1e-12), "{got}");
    // A proposal of weight 1 everywhere bounds any weights in [0, 1]: loss 0.
    let ones = (
        coarse.0.clone(),
        Tensor::ones((5, 7), DType::F64, &Device::Cpu).unwrap(),
    );
    assert_eq!(
        interlevel_loss(&ones, &fine, &w)
            .unwrap()
            .to_scalar::<f64>()
            .unwrap(),
        0.0
    );
    // A zero proposal: Σ w² / (w + ε) per ray.
    let zeros = (
        coarse.0.clone(),
        Tensor::zeros((5, 7), DType::F64, &Device::Cpu).unwrap(),
    );
    let want: f64 = v64(&w).iter().map(|x| x * x / (x + 1e-7)).sum::<f64>() / 5.0;
    let got = interlevel_loss(&zeros, &fine, &w)
        .unwrap()
        .to_scalar::<f64>()
        .unwrap();
    assert!(close(got, want, 1e-12, 1e-12));
    // f32 works and agrees.
    let f32s = |t: &Tensor| t.to_dtype(DType::F32).unwrap();
    let c32 = (
        Intervals::new(
            f32s(&coarse.0.starts),
            f32s(&coarse.0.ends),
            Layout::Batched,
        )
        .unwrap(),
        f32s(&coarse.1),
    );
    let f32_iv = Intervals::new(f32s(&fine.starts), f32s(&fine.ends), Layout::Batched).unwrap();
    let l32 = interlevel_loss(&c32, &f32_iv, &f32s(&w))
        .unwrap()
        .to_dtype(DType::F64)
        .unwrap();
    assert!(close(
        l32.to_scalar::<f64>().unwrap(),
        brute(&coarse, &fine, &w),
        1e-4,
        1e-6
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// ∂L/∂ŵ by autograd against central differences (f64), proposal weights from 1e-9 to
    /// 1e3; the final weights get no gradient (detached).
    #[test]
    fn gradient_wrt_proposal_weights_matches_finite_differences(seed in 0u64..10_000, scale in prop::sample::select(vec![1e-9, 1e-3, 1.0, 1e3])) {
        let (civ, cw) = level(3, 6, seed, scale);
        let (fine, w) = level(3, 11, seed + 7, scale);
        let cw0 = v64(&cw);
        let var = Var::from_tensor(&cw).unwrap();
        let wv = Var::from_tensor(&w).unwrap();
        let loss = interlevel_loss(&(civ.clone(), var.as_tensor().clone()), &fine, wv.as_tensor()).unwrap();
        let grads = loss.backward().unwrap();
        let g = v64(grads.get(&var).unwrap());
        prop_assert!(grads.get(&wv).is_none_or(|g| v64(g).iter().all(|&x| x == 0.0)));
        let mut checked = 0;
        for k in 0..cw0.len() {
            let mut f = |x: f64| {
                let mut c = cw0.clone();
                c[k] = x;
                let t = Tensor::from_vec(c, (3, 6), &Device::Cpu).unwrap();
                interlevel_loss(&(civ.clone(), t), &fine, &w).unwrap().to_scalar::<f64>().unwrap()
            };
            if let Some(fd) = central_diff(&mut f, cw0[k], 1e-6 * scale, 1.0) {
                prop_assert!(close(g[k], fd, 1e-5, 1e-6), "ŵ[{k}]: {} vs {fd}", g[k]);
                checked += 1;
            }
        }
        prop_assert!(checked > 0);
    }
}

fn rays(r: usize) -> Rays {
    let dev = Device::Cpu;
    let o: Vec<f64> = (0..r).flat_map(|i| [0.1 * i as f64, 0.0, -3.0]).collect();
    let d: Vec<f64> = (0..r).flat_map(|_| [0.0, 0.0, 2.0]).collect(); // not unit length
    Rays::new(
        Tensor::from_vec(o, (r, 3), &dev).unwrap(),
        Tensor::from_vec(d, (r, 3), &dev).unwrap(),
    )
    .unwrap()
}

#[test]
fn proposals_concentrate_the_final_samples_on_the_density() {
    let dev = Device::Cpu;
    let r = 4;
    let (near, far) = (
        Tensor::full(0.5f64, r, &dev).unwrap(),
        Tensor::full(2.5f64, r, &dev).unwrap(),
    );
    // A slab |z| < 0.1 (t ∈ [1.45, 1.55] with |d| = 2).
    let slab = |p: &Tensor| -> neural_fields::Result<Tensor> {
        let z = p.narrow(1, 2, 1)?.squeeze(1)?.abs()?;
        Ok((z.lt(0.1)?.to_dtype(DType::F64)? * 100.0)?)
    };
    let (mut a, mut b) = (slab, slab);
    let config = ProposalConfig {
        samples: vec![128, 32],
        final_samples: 16,
        padding: 0.0,
        ..ProposalConfig::default()
    };
    let out = proposal_sample(
        &rays(r),
        &near,
        &far,
        &mut [&mut a, &mut b],
        &config,
        None,
        None,
    )
    .unwrap();
    assert_eq!(out.intervals.starts.dims(), &[r, 16]);
    assert_eq!(out.levels.len(), 2);
    assert_eq!(out.levels[0].1.dims(), &[r, 128]);
    assert_eq!(out.levels[1].1.dims(), &[r, 32]);
    for t in v64(&out.intervals.midpoints().unwrap()) {
        assert!((1.4..1.6).contains(&t), "{t}");
    }
    // Deterministic without a seed; seeded draws differ between seeds.
    let again = proposal_sample(
        &rays(r),
        &near,
        &far,
        &mut [&mut a, &mut b],
        &config,
        None,
        None,
    )
    .unwrap();
    assert_eq!(v64(&again.intervals.starts), v64(&out.intervals.starts));
    let s1 = proposal_sample(
        &rays(r),
        &near,
        &far,
        &mut [&mut a, &mut b],
        &config,
        Some(1),
        None,
    )
    .unwrap();
    let s2 = proposal_sample(
        &rays(r),
        &near,
        &far,
        &mut [&mut a, &mut b],
        &config,
        Some(2),
        None,
    )
    .unwrap();
    assert_ne!(v64(&s1.intervals.starts), v64(&s2.intervals.starts));
    // The interlevel loss of a level against itself is zero.
    let own = interlevel_loss(&out.levels[1], &out.levels[1].0, &out.levels[1].1).unwrap();
    assert_eq!(own.to_scalar::<f64>().unwrap(), 0.0);
}

#[test]
fn bad_input_is_an_error_naming_the_argument() {
    let dev = Device::Cpu;
    let (near, far) = (
        Tensor::zeros(2, DType::F64, &dev).unwrap(),
        Tensor::ones(2, DType::F64, &dev).unwrap(),
    );
    let mut f =
        |p: &Tensor| -> neural_fields::Result<Tensor> { Ok(p.narrow(1, 0, 1)?.squeeze(1)?.abs()?) };
    let arg = |e: Error| match e {
        Error::InvalidArgument { arg, .. } => arg,
        other => panic!("{other}"),
    };
    let two = ProposalConfig {
        samples: vec![8, 8],
        ..ProposalConfig::default()
    };
    assert_eq!(
        arg(proposal_sample(&rays(2), &near, &far, &mut [&mut f], &two, None, None).unwrap_err()),
        "proposals"
    );
    let zero = ProposalConfig {
        samples: vec![0],
        ..ProposalConfig::default()
    };
    assert_eq!(
        arg(proposal_sample(&rays(2), &near, &far, &mut [&mut f], &zero, None, None).unwrap_err()),
        "config"
    );
    let coarse = level(2, 4, 0, 1.0);
    let (fine, w) = level(2, 5, 1, 1.0);
    assert_eq!(
        arg(interlevel_loss(&coarse, &fine, &w.narrow(1, 0, 4).unwrap()).unwrap_err()),
        "weights"
    );
    assert_eq!(
        arg(interlevel_loss(&coarse, &fine, &w.to_dtype(DType::F32).unwrap()).unwrap_err()),
        "weights"
    );
    let other_rays = level(3, 5, 1, 1.0);
    assert_eq!(
        arg(interlevel_loss(&coarse, &other_rays.0, &other_rays.1).unwrap_err()),
        "proposal"
    );
}

/// Given the field's density, the sampler keeps exactly the final samples that are visible
/// (T ≥ early_stop_eps) and not faint (α ≥ alpha_threshold), packed, and its interlevel
/// loss is the sum over levels against the field's weights on all final samples.
#[test]
fn the_fields_density_culls_the_samples_and_gives_the_interlevel_target() {
    use neural_fields::volume::{render_weights, CompositeConfig};
    let dev = Device::Cpu;
    let r = 3;
    let (near, far) = (
        Tensor::full(0.5f64, r, &dev).unwrap(),
        Tensor::full(2.5f64, r, &dev).unwrap(),
    );
    let proposal = |p: &Tensor| -> neural_fields::Result<Tensor> {
        Ok((p
            .narrow(1, 2, 1)?
            .squeeze(1)?
            .abs()?
            .affine(-4.0, 1.0)?
            .relu()?
            * 20.0)?)
    };
    // The field: an opaque half-space z > 0, empty elsewhere.
    let field = |p: &Tensor| -> neural_fields::Result<Tensor> {
        Ok((p
            .narrow(1, 2, 1)?
            .squeeze(1)?
            .gt(0.0)?
            .to_dtype(DType::F64)?
            * 50.0)?)
    };
    let config = ProposalConfig {
        samples: vec![32, 16],
        final_samples: 24,
        alpha_threshold: 1e-2,
        ..ProposalConfig::default()
    };
    let (mut a, mut b, mut f) = (proposal, proposal, field);
    let plain = proposal_sample(
        &rays(r),
        &near,
        &far,
        &mut [&mut a, &mut b],
        &config,
        Some(5),
        None,
    )
    .unwrap();
    assert!(plain.interlevel.is_none());
    let culled = proposal_sample(
        &rays(r),
        &near,
        &far,
        &mut [&mut a, &mut b],
        &config,
        Some(5),
        Some(&mut f),
    )
    .unwrap();
    // The same draws; the kept ones are those the weights say are worth evaluating.
    let iv = &plain.intervals;
    let (rr, s) = iv.starts.dims2().unwrap();
    let sigma = field(
        &iv.positions(&rays(r))
            .unwrap()
            .reshape((rr * s, 3))
            .unwrap(),
    )
    .unwrap()
    .reshape((rr, s))
    .unwrap();
    let w = render_weights(&sigma, iv, Some(&rays(r)), &CompositeConfig::default()).unwrap();
    let keep = (w.transmittance.ge(1e-4).unwrap() * w.alphas.ge(1e-2).unwrap()).unwrap();
    let (expected, _) = iv.retain(&keep).unwrap();
    assert_eq!(v64(&culled.intervals.starts), v64(&expected.starts));
    let kept = culled.intervals.starts.dim(0).unwrap();
    assert!(kept > 0 && kept < rr * s, "{kept} of {}", rr * s);
    let mut sum = 0.0;
    for level in &plain.levels {
        sum += interlevel_loss(level, iv, &w.weights)
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
    }
    let got = culled.interlevel.unwrap().to_scalar::<f64>().unwrap();
    assert!(close(got, sum, 1e-12, 1e-12), "{got} vs {sum}");
    // A density of the wrong shape is refused, naming the closure.
    let mut wrong = |p: &Tensor| -> neural_fields::Result<Tensor> {
        Ok(Tensor::zeros(p.dim(0)? + 1, DType::F64, p.device())?)
    };
    let e = proposal_sample(
        &rays(r),
        &near,
        &far,
        &mut [&mut a, &mut b],
        &config,
        None,
        Some(&mut wrong),
    )
    .unwrap_err();
    assert!(
        matches!(
            e,
            Error::InvalidArgument {
                arg: "sigma_fn",
                ..
            }
        ),
        "{e}"
    );
}

fn rays_as(r: usize, dtype: DType) -> Rays {
    let base = rays(r);
    Rays::new(
        base.origins().to_dtype(dtype).unwrap(),
        base.directions().to_dtype(dtype).unwrap(),
    )
    .unwrap()
}

/// The linear-then-disparity spacing: level 0 is uniform in s (edges k/n without jitter),
/// linear to t = 1 and in disparity beyond, reaching a far plane at 1e10 with finite
/// intervals, in f32 and f64.
#[test]
fn linear_disparity_spacing_is_uniform_in_s_out_to_a_far_plane() {
    use neural_fields::volume::Spacing;
    let dev = Device::Cpu;
    for dtype in [DType::F32, DType::F64] {
        let r = 3;
        let near = Tensor::new(&[0.0f64, 0.05, 0.5], &dev)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let far = Tensor::new(&[1e10f64, 1e3, 2.0], &dev)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let mut flat = |p: &Tensor| -> neural_fields::Result<Tensor> {
            Ok(Tensor::ones(p.dim(0)?, p.dtype(), p.device())?)
        };
        let config = ProposalConfig {
            spacing: Spacing::LinearDisparity,
            samples: vec![16],
            final_samples: 8,
            ..ProposalConfig::default()
        };
        let out = proposal_sample(
            &rays_as(r, dtype),
            &near,
            &far,
            &mut [&mut flat],
            &config,
            None,
            None,
        )
        .unwrap();
        let level0 = &out.levels[0].0;
        let s = Spacing::LinearDisparity
            .normalize(&level0.starts, &near, &far)
            .unwrap();
        let s = v64(&s);
        let tol = if dtype == DType::F32 { 1e-5 } else { 1e-12 };
        for ray in 0..r {
            for k in 0..16 {
                let got = s[ray * 16 + k];
                assert!(
                    (got - k as f64 / 16.0).abs() < tol,
                    "{dtype:?} ray {ray}: s = {got}"
                );
            }
        }
        // Linear below t = 1: on ray 0 (near 0), the first half of the edges are 2s.
        let t = v64(&level0.starts);
        for (k, &tk) in t.iter().enumerate().take(8) {
            assert!(close(tk, 2.0 * k as f64 / 16.0, 1e-5, 1e-6), "t = {tk}");
        }
        // Disparity beyond: the edge at s = ¾ is t = 2.
        assert!(close(t[12], 2.0, 1e-5, 0.0), "{}", t[12]);
        for x in v64(&out.intervals.ends)
            .iter()
            .chain(&v64(&out.intervals.starts))
        {
            assert!(x.is_finite());
        }
        // Linear spacing normalises by (t − near)/(far − near).
        let lin = Spacing::Linear
            .normalize(&level0.starts, &near, &far)
            .unwrap();
        assert!(v64(&lin).iter().all(|s| (0.0..=1.0).contains(s)));
        // A negative near is refused for the disparity spacing, naming it.
        let neg = Tensor::new(&[-1.0f64, 0.05, 0.5], &dev)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let e = proposal_sample(
            &rays_as(r, dtype),
            &neg,
            &far,
            &mut [&mut flat],
            &config,
            None,
            None,
        )
        .unwrap_err()
        .to_string();
        assert!(e.starts_with("near"), "{e}");
        // normalize names t for a wrong shape.
        let e = Spacing::Linear
            .normalize(&near, &near, &far)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with('t'), "{e}");
    }
}

/// `Spacing::normalize`'s gradient w.r.t. t against central differences (f64), across
/// the linear and disparity pieces.
#[test]
fn spacing_normalize_gradient_matches_finite_differences() {
    use neural_fields::volume::Spacing;
    let dev = Device::Cpu;
    let near = Tensor::new(&[0.05f64], &dev).unwrap();
    let far = Tensor::new(&[1e4f64], &dev).unwrap();
    let ts = [0.1, 0.7, 1.5, 30.0, 900.0];
    let t = Var::from_tensor(&Tensor::new(&[ts], &dev).unwrap()).unwrap();
    let s = Spacing::LinearDisparity
        .normalize(t.as_tensor(), &near, &far)
        .unwrap();
    let g = v64(s
        .sum_all()
        .unwrap()
        .backward()
        .unwrap()
        .get(t.as_tensor())
        .unwrap());
    for (k, &t0) in ts.iter().enumerate() {
        let mut f = |x: f64| {
            let mut v = ts;
            v[k] = x;
            let t = Tensor::new(&[v], &dev).unwrap();
            v64(&Spacing::LinearDisparity.normalize(&t, &near, &far).unwrap())[k]
        };
        let fd = central_diff(&mut f, t0, 1e-4 * t0, 1.0).expect("smooth away from t = 1");
        assert!(close(g[k], fd, 1e-6, 1e-12), "t = {t0}: {} vs {fd}", g[k]);
    }
}
