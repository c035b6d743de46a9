//! The fused compositing op (the CPU default of `composite`) against the reference path
//! (`force_reference`) and central finite differences, on extreme inputs, and its stiff
//! cases. The comparisons of kernel builds live inside the crate
//! (`src/volume/fused_tests.rs`): the build is crate-private.
#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::host::extreme_inputs as inputs;
use common::intervals::{batched_from_deltas, packed_from_deltas};
use common::v64;
use neural_fields::camera::Rays;
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{
    accumulate, composite, render_weights, Composite, CompositeConfig, Intervals, Layout, Packed,
};
use proptest::prelude::*;

fn dev() -> Device {
    Device::Cpu
}

/// Loss weights: one per colour channel, one for opacity, one for depth.
fn loss_weights(seed: u64, c: usize) -> Vec<f64> {
    let mut rng = SplitMix64::new(seed ^ 0x5eed);
    (0..c + 2).map(|_| rng.normal()).collect()
}

fn loss(out: &Composite, lw: &[f64]) -> Tensor {
    let c = lw.len() - 2;
    let a = Tensor::new(&lw[..c], out.color.device())
        .unwrap()
        .to_dtype(out.color.dtype())
        .unwrap();
    let lc = out
        .color
        .broadcast_mul(&a.unsqueeze(0).unwrap())
        .unwrap()
        .sum_all()
        .unwrap();
    let lo = (out.opacity.sum_all().unwrap() * lw[c]).unwrap();
    let ld = (out.depth.sum_all().unwrap() * lw[c + 1]).unwrap();
    ((lc + lo).unwrap() + ld).unwrap()
}

/// Gradients of the loss; `starts`/`ends` are empty when the intervals were constant.
struct Grads {
    loss: f64,
    sig: Vec<f64>,
    col: Vec<f64>,
    starts: Vec<f64>,
    ends: Vec<f64>,
}

/// `composite` on the fused path (`fused = true`, the CPU default) or the reference.
fn run(
    fused: bool,
    sig: &Tensor,
    col: &Tensor,
    iv: &Intervals,
    rays: Option<&Rays>,
    config: &CompositeConfig,
) -> Composite {
    composite(
        sig,
        col,
        iv,
        rays,
        &CompositeConfig {
            force_reference: !fused,
            ..config.clone()
        },
    )
    .unwrap()
}

/// Gradients of `loss` through the path `fused` names. With `geo_var` the interval
/// bounds are variables (the fused op then takes δ and t as tensors and differentiates
/// them); without, they are constants of the graph (the fused op forms δ and t from the
/// bounds in place) and `rays` may scale δ.
#[allow(clippy::too_many_arguments)]
fn grads(
    fused: bool,
    sig: &Tensor,
    col: &Tensor,
    iv: &Intervals,
    rays: Option<&Rays>,
    config: &CompositeConfig,
    lw: &[f64],
    geo_var: bool,
) -> Grads {
    let (s, c) = (
        Var::from_tensor(sig).unwrap(),
        Var::from_tensor(col).unwrap(),
    );
    let (sv, ev) = (
        Var::from_tensor(&iv.starts).unwrap(),
        Var::from_tensor(&iv.ends).unwrap(),
    );
    let iv_in = if geo_var {
        Intervals {
            starts: sv.as_tensor().clone(),
            ends: ev.as_tensor().clone(),
            layout: iv.layout.clone(),
        }
    } else {
        iv.clone()
    };
    let out = run(fused, s.as_tensor(), c.as_tensor(), &iv_in, rays, config);
    let l = loss(&out, lw);
    let g = l.backward().unwrap();
    let get = |v: &Var| v64(g.get(v.as_tensor()).expect("gradient present"));
    Grads {
        loss: v64(&l)[0],
        sig: get(&s),
        col: get(&c),
        starts: if geo_var { get(&sv) } else { Vec::new() },
        ends: if geo_var { get(&ev) } else { Vec::new() },
    }
}

fn all_finite(g: &Grads) -> bool {
    g.loss.is_finite()
        && g.sig
            .iter()
            .chain(&g.col)
            .chain(&g.starts)
            .chain(&g.ends)
            .all(|v| v.is_finite())
}

/// Per-sample magnitude scale of ∂L/∂xⱼ: |∂L/∂xⱼ| ≤ Tⱼ·max|u| with
/// uᵢ = Σₖ gₖcᵢₖ + g_O + g_D·tᵢ (tᵢ the midpoints); values below 1e-290 count as zero (the kernel stops a
/// ray once T < 1e-300). Also returns T.
fn x_scale(
    sig: &Tensor,
    iv: &Intervals,
    rays: Option<&Rays>,
    col: &[f64],
    lw: &[f64],
    opaque_last: bool,
) -> (Vec<f64>, Vec<f64>) {
    let cfg = CompositeConfig {
        opaque_last,
        ..Default::default()
    };
    let w = render_weights(sig, iv, rays, &cfg).unwrap();
    let t = v64(&w.transmittance);
    let tm = v64(&iv.midpoints().unwrap());
    let c = lw.len() - 2;
    let umax = (0..t.len())
        .map(|i| {
            let mut u = lw[c] + lw[c + 1] * tm[i];
            for k in 0..c {
                u += lw[k] * col[i * c + k];
            }
            u.abs()
        })
        .fold(0.0, f64::max);
    (t.iter().map(|ti| (ti.max(1e-290)) * umax).collect(), t)
}

/// Scale of ∂L/∂starts and ∂L/∂ends = ∓∂L/∂δ + ½·∂L/∂t (unit directions): the δ part
/// is at most xⱼ-scale·σⱼ, the t part (wⱼ·g_D) at most Tⱼ·|g_D|.
fn geo_scale(xs: &[f64], t: &[f64], sig: &[f64], g_d: f64) -> Vec<f64> {
    (0..xs.len())
        .map(|i| xs[i] * sig[i] + t[i].max(1e-290) * g_d.abs())
        .collect()
}

/// Scale floor for gradients of the form w·g (colours, depths) under `check_close` at
/// rel 1e-10: the kernel drops the weights after T < 1e-300 (its documented stop), an
/// absolute error below 1e-300·max|g|, which is 1e-10 × this floor (regression:
/// `a_sample_behind_transmittance_below_1e_300_gets_zero_weight`).
fn stop_floor(lw: &[f64], len: usize) -> Vec<f64> {
    let gmax = lw.iter().fold(0.0f64, |m, w| m.max(w.abs()));
    vec![1e-290 * gmax; len]
}

fn check_close(
    name: &str,
    a: &[f64],
    b: &[f64],
    scale: &[f64],
    rel: f64,
) -> Result<(), TestCaseError> {
    prop_assert_eq!(a.len(), b.len(), "{}: lengths", name);
    for i in 0..a.len() {
        let tol = rel * (a[i].abs().max(b[i].abs()) + scale[i]);
        prop_assert!(
            (a[i] - b[i]).abs() <= tol,
            "{name}[{i}]: {} vs {} (tol {tol:e})",
            a[i],
            b[i]
        );
    }
    Ok(())
}

/// `r` rays of `s` samples from [`inputs`]: densities, colours and contiguous intervals
/// with those lengths (each ray from t = 0; a tiny δ after a large t rounds, as it would
/// in any interval of that t), all f64.
fn batched(r: usize, s: usize, c: usize, seed: u64) -> (Tensor, Tensor, Intervals) {
    let (sig, del, col) = inputs(seed, r * s, c);
    (
        Tensor::from_vec(sig, (r, s), &dev()).unwrap(),
        Tensor::from_vec(col, (r, s, c), &dev()).unwrap(),
        batched_from_deltas(&del, r, s, DType::F64, &dev()),
    )
}

/// `r` constant rays with directions of norms between 0.5 and 2 (which scale δ).
fn scaled_rays(r: usize, seed: u64) -> Rays {
    let mut rng = SplitMix64::new(seed ^ 0xd1);
    let mut d = Vec::with_capacity(3 * r);
    for _ in 0..r {
        let v = [rng.normal(), rng.normal(), rng.normal()];
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
        let want = 0.5 + 1.5 * rng.uniform();
        d.extend(v.iter().map(|x| x / n * want));
    }
    Rays::new(
        Tensor::zeros((r, 3), DType::F64, &dev()).unwrap(),
        Tensor::from_vec(d, (r, 3), &dev()).unwrap(),
    )
    .unwrap()
}

fn sample_count() -> impl Strategy<Value = usize> {
    prop_oneof![1usize..=8, 9usize..=200, Just(1024usize)]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// Fused and reference gradients agree to 1e-10 relative (f64), measured against the
    /// magnitude of the terms each gradient is made of; 1–8 channels cover the kernels
    /// specialised for 1–4 channels and the general one, and the intervals are either
    /// differentiated (δ and t as tensors) or constant (formed in the kernel, with rays
    /// whose direction norms scale δ).
    #[test]
    fn fused_gradients_equal_reference_gradients(
        seed in any::<u64>(), r in 1usize..4, s in sample_count(), c in 1usize..9, opaque_last in any::<bool>(),
        geo_var in any::<bool>(),
    ) {
        let (sig, col, iv) = batched(r, s, c, seed);
        let lw = loss_weights(seed, c);
        let cfg = CompositeConfig { opaque_last, ..Default::default() };
        let rays = scaled_rays(r, seed);
        let rays = if geo_var { None } else { Some(&rays) };
        let gf = grads(true, &sig, &col, &iv, rays, &cfg, &lw, geo_var);
        let gr = grads(false, &sig, &col, &iv, rays, &cfg, &lw, geo_var);
        prop_assert!(all_finite(&gf) && all_finite(&gr));
        prop_assert!((gf.loss - gr.loss).abs() <= 1e-12 * (1.0 + gr.loss.abs()));
        let (xs, t) = x_scale(&sig, &iv, rays, &v64(&col), &lw, opaque_last);
        let (sv, dv) = (v64(&sig), v64(&iv.deltas(rays).unwrap()));
        let ss: Vec<f64> = xs.iter().zip(&dv).map(|(x, d)| x * d).collect();
        check_close("sigmas", &gf.sig, &gr.sig, &ss, 1e-10)?;
        let zero_c = stop_floor(&lw, gf.col.len());
        check_close("colors", &gf.col, &gr.col, &zero_c, 1e-10)?;
        prop_assert_eq!(gf.starts.len(), if geo_var { r * s } else { 0 });
        let geo = geo_scale(&xs, &t, &sv, lw[c + 1]);
        check_close("starts", &gf.starts, &gr.starts, &geo, 1e-10)?;
        check_close("ends", &gf.ends, &gr.ends, &geo, 1e-10)?;
    }

    /// Fused gradients against central finite differences (relative steps; one-sided
    /// second-order differences at the domain's edge), to 1e-6 relative plus the
    /// difference quotient's rounding floor. Every interval starts at t = 0 here (the
    /// compositing functions do not need sorted intervals), so that its length δ = end is
    /// exact down to 1e-30 and can be stepped relatively.
    #[test]
    fn fused_gradients_match_finite_differences(
        seed in any::<u64>(), s in sample_count(), opaque_last in any::<bool>()
    ) {
        let (r, c) = (2, 3);
        let (sv, dv, cv) = inputs(seed, r * s, c);
        let st0 = vec![0.0; r * s];
        let geo = |st: &[f64], en: &[f64]| Intervals {
            starts: Tensor::from_slice(st, (r, s), &dev()).unwrap(),
            ends: Tensor::from_slice(en, (r, s), &dev()).unwrap(),
            layout: Layout::Batched,
        };
        let iv = geo(&st0, &dv);
        let sig = Tensor::from_slice(&sv, (r, s), &dev()).unwrap();
        let col = Tensor::from_slice(&cv, (r, s, c), &dev()).unwrap();
        let lw = loss_weights(seed, c);
        let cfg = CompositeConfig { opaque_last, ..Default::default() };
        let g = grads(true, &sig, &col, &iv, None, &cfg, &lw, true);
        let (xs, t) = x_scale(&sig, &iv, None, &cv, &lw, opaque_last);
        let eval = |sv: &[f64], st: &[f64], en: &[f64], cv: &[f64]| -> f64 {
            let out = run(
                true,
                &Tensor::from_slice(sv, (r, s), &dev()).unwrap(),
                &Tensor::from_slice(cv, (r, s, c), &dev()).unwrap(),
                &geo(st, en),
                None,
                &cfg,
            );
            v64(&loss(&out, &lw))[0]
        };
        let mut rng = SplitMix64::new(seed ^ 77);
        let picks: Vec<usize> = if r * s <= 24 { (0..r * s).collect() } else { (0..24).map(|_| rng.below((r * s) as u64) as usize).collect() };
        let l0 = g.loss.abs().max(1.0);
        let g_d = lw[c + 1].abs();
        for &i in &picks {
            // d/dσ_i, d/dend_i and d/dstart_i: the step moves x = σδ by at least 1e-8 (a
            // relative step alone is meaningless at σ = 1e-30); one-sided second-order
            // differences where the central one would leave the domain (σ ≥ 0, δ ≥ 0).
            let fd_at = |f: &dyn Fn(f64) -> f64, x0: f64, h: f64, room: f64| {
                if room >= 2.0 * h {
                    (f(x0 + h) - f(x0 - h)) / (2.0 * h)
                } else {
                    (-3.0 * f(x0) + 4.0 * f(x0 + h) - f(x0 + 2.0 * h)) / (2.0 * h)
                }
            };
            let (s0, d0) = (sv[i], dv[i]);
            let h = 1e-5 * s0.max(1e-3 / d0);
            let fd = fd_at(&|x: f64| { let mut v = sv.clone(); v[i] = x; eval(&v, &st0, &dv, &cv) }, s0, h, s0);
            let tol = 1e-6 * (g.sig[i].abs() + xs[i] * d0) + 20.0 * f64::EPSILON * l0 / h;
            prop_assert!((fd - g.sig[i]).abs() <= tol, "dσ[{i}] σ={s0:e} δ={d0:e}: fd {fd:e} vs {:e} (tol {tol:e})", g.sig[i]);
            // The end moves δ and the midpoint: ∂L/∂end = ∂L/∂δ + ½∂L/∂t.
            let h = if s0 > 0.0 { 1e-5 * d0.max(1e-3 / s0) } else { 1e-5 * d0 };
            let geo_tol = |gi: f64| 1e-6 * (gi.abs() + xs[i] * s0 + t[i] * g_d);
            let fd = fd_at(&|x: f64| { let mut v = dv.clone(); v[i] = x; eval(&sv, &st0, &v, &cv) }, d0, h, d0);
            let tol = geo_tol(g.ends[i]) + 20.0 * f64::EPSILON * l0 / h;
            prop_assert!((fd - g.ends[i]).abs() <= tol, "dend[{i}] σ={s0:e} δ={d0:e}: fd {fd:e} vs {:e} (tol {tol:e})", g.ends[i]);
            // The start (at 0) moves δ the other way: ∂L/∂start = −∂L/∂δ + ½∂L/∂t; stepped
            // downwards, where δ = end − start grows, when δ leaves no room above.
            let f = |x: f64| { let mut v = st0.clone(); v[i] = x; eval(&sv, &v, &dv, &cv) };
            let fd = if d0 >= 2.0 * h {
                (f(h) - f(-h)) / (2.0 * h)
            } else {
                (3.0 * f(0.0) - 4.0 * f(-h) + f(-2.0 * h)) / (2.0 * h)
            };
            let tol = geo_tol(g.starts[i]) + 20.0 * f64::EPSILON * l0 / h;
            prop_assert!((fd - g.starts[i]).abs() <= tol, "dstart[{i}] σ={s0:e} δ={d0:e}: fd {fd:e} vs {:e} (tol {tol:e})", g.starts[i]);
            // d/dc_i0 (linear: differences are exact up to rounding)
            let f = |x: f64| { let mut v = cv.clone(); v[i * c] = x; eval(&sv, &st0, &dv, &v) };
            let fd = (f(cv[i * c] + 1e-3) - f(cv[i * c] - 1e-3)) / 2e-3;
            prop_assert!((fd - g.col[i * c]).abs() <= 1e-6 * g.col[i * c].abs() + 1e-11 * l0, "dc[{i}]");
        }
    }

    /// Packed layout with empty rays: fused equals reference, values and gradients, with
    /// the intervals differentiated or constant (then with rays that scale δ).
    #[test]
    fn packed_fused_equals_packed_reference_with_empty_rays(
        seed in any::<u64>(), counts in prop::collection::vec(prop_oneof![Just(0usize), 1usize..40], 1..8), opaque_last in any::<bool>(),
        geo_var in any::<bool>(),
    ) {
        let c = 3;
        let packed = Packed::from_counts(&counts, &dev()).unwrap();
        let m = packed.ray_indices.dim(0).unwrap();
        prop_assume!(m > 0);
        let (sig, del, col) = inputs(seed, m, c);
        let sig = Tensor::from_vec(sig, m, &dev()).unwrap();
        let iv = packed_from_deltas(&del, &packed, DType::F64);
        let col = Tensor::from_vec(col, (m, c), &dev()).unwrap();
        let lw = loss_weights(seed, c);
        let bg = Tensor::new(&[0.3f64, 0.6, 0.9], &dev()).unwrap();
        let cfg = CompositeConfig { opaque_last, background: Some(bg), force_reference: false };
        let rays = scaled_rays(counts.len(), seed);
        let rays = if geo_var { None } else { Some(&rays) };
        let gf = grads(true, &sig, &col, &iv, rays, &cfg, &lw, geo_var);
        let gr = grads(false, &sig, &col, &iv, rays, &cfg, &lw, geo_var);
        prop_assert!(all_finite(&gf) && all_finite(&gr));
        prop_assert!((gf.loss - gr.loss).abs() <= 1e-12 * (1.0 + gr.loss.abs()));
        // Scale per sample from the packed reference weights.
        let tr = v64(&render_weights(&sig, &iv, rays, &cfg).unwrap().transmittance);
        // |u| ≤ Σ|colour and opacity weights| + |g_D|·max t (colours in [0, 1)); the
        // midpoints t grow with the lengths (up to 1e10 each).
        let tmax = v64(&iv.midpoints().unwrap()).into_iter().fold(1.0, f64::max);
        let umax = 10.0 * (lw[..=c].iter().map(|x| x.abs()).sum::<f64>() + lw[c + 1].abs() * tmax);
        let (sv, dv) = (v64(&sig), v64(&iv.deltas(rays).unwrap()));
        let ss: Vec<f64> = (0..m).map(|i| tr[i].max(1e-290) * umax * dv[i]).collect();
        let sd: Vec<f64> = (0..m).map(|i| tr[i].max(1e-290) * (umax * sv[i] + lw[c + 1].abs())).collect();
        check_close("sigmas", &gf.sig, &gr.sig, &ss, 1e-10)?;
        let floor = stop_floor(&lw, 3 * m);
        check_close("colors", &gf.col, &gr.col, &floor, 1e-10)?;
        check_close("starts", &gf.starts, &gr.starts, &sd, 1e-10)?;
        check_close("ends", &gf.ends, &gr.ends, &sd, 1e-10)?;
    }
}

#[test]
fn fused_equals_reference_in_f32() {
    let (sig, col, iv) = batched(64, 192, 3, 7);
    let (sig, col) = (
        sig.to_dtype(DType::F32).unwrap(),
        col.to_dtype(DType::F32).unwrap(),
    );
    // Rounding sorted f64 bounds to f32 keeps them sorted.
    let iv = Intervals::new(
        iv.starts.to_dtype(DType::F32).unwrap(),
        iv.ends.to_dtype(DType::F32).unwrap(),
        Layout::Batched,
    )
    .unwrap();
    let lw = loss_weights(7, 3);
    let cfg = CompositeConfig::default();
    let gf = grads(true, &sig, &col, &iv, None, &cfg, &lw, true);
    let gr = grads(false, &sig, &col, &iv, None, &cfg, &lw, true);
    assert!(all_finite(&gf) && all_finite(&gr));
    assert!(
        (gf.loss - gr.loss).abs() < 1e-4 * (1.0 + gr.loss.abs()),
        "{} vs {}",
        gf.loss,
        gr.loss
    );
    let max_c = gr.col.iter().map(|x| x.abs()).fold(0.0, f64::max);
    for (a, b) in gf.col.iter().zip(&gr.col) {
        assert!((a - b).abs() < 1e-5 * max_c);
    }
    // σ and interval gradients, measured against the size of the terms they are formed
    // from (as in the f64 proptest): f32 rounding of the reference's exclusive sum (a
    // matmul) and exponentials sets the tolerance.
    let (xs, t) = x_scale(&sig, &iv, None, &v64(&col), &lw, false);
    let (sv, dv) = (v64(&sig), v64(&iv.deltas(None).unwrap()));
    let ss: Vec<f64> = xs.iter().zip(&dv).map(|(x, d)| x * d).collect();
    let sd = geo_scale(&xs, &t, &sv, lw[4]);
    let worst = |a: &[f64], b: &[f64], scale: &[f64]| {
        a.iter()
            .zip(b)
            .zip(scale)
            .map(|((a, b), s)| (a - b).abs() / (a.abs().max(b.abs()) + s))
            .fold(0.0, f64::max)
    };
    let (ws, wst, we) = (
        worst(&gf.sig, &gr.sig, &ss),
        worst(&gf.starts, &gr.starts, &sd),
        worst(&gf.ends, &gr.ends, &sd),
    );
    eprintln!(
        "f32 fused vs reference: worst relative deviation d/dsigma {ws:e}, d/dstarts {wst:e}, d/dends {we:e}"
    );
    check_close("sigmas", &gf.sig, &gr.sig, &ss, F32_GRAD_TOL).unwrap();
    check_close("starts", &gf.starts, &gr.starts, &sd, F32_GRAD_TOL).unwrap();
    check_close("ends", &gf.ends, &gr.ends, &sd, F32_GRAD_TOL).unwrap();
}

/// Tolerance of f32 σ and interval gradients, fused against reference, relative to the
/// size of their terms.
const F32_GRAD_TOL: f64 = 1e-5;

/// Stiff inputs in f32 and f64, both paths: outputs and gradients finite, and the
/// documented values.
#[test]
fn stiff_cases_have_finite_outputs_and_gradients() {
    let cases: Vec<(&str, Vec<f64>, Vec<f64>)> = vec![
        (
            "sigma*delta = 1e30",
            vec![1e30, 0.5, 0.1],
            vec![1.0, 0.1, 0.1],
        ),
        (
            "sigma*delta = 1e40 overflows f32",
            vec![1e30, 1e30, 1.0],
            vec![1e10, 1e10, 0.1],
        ),
        (
            "sigma*delta = 1e-30",
            vec![1e-30, 1e-30, 1e-30],
            vec![1.0, 1.0, 1.0],
        ),
        (
            "density 1e10 in one interval",
            vec![0.0, 1e10, 0.0],
            vec![0.01, 0.01, 0.01],
        ),
        (
            "max f32 density",
            vec![3.0e38, 0.0, 1.0],
            vec![1.0, 1e-30, 1.0],
        ),
        (
            "max f32 density, tiny first interval",
            vec![0.0, 3.0e38, 1.0],
            vec![1e-30, 1.0, 1.0],
        ),
        ("zero deltas", vec![1e30, 5.0, 0.0], vec![0.0, 0.0, 0.0]),
    ];
    for dt in [DType::F32, DType::F64] {
        for (name, s, d) in &cases {
            for opaque_last in [false, true] {
                let sig = Tensor::new(s.as_slice(), &dev())
                    .unwrap()
                    .unsqueeze(0)
                    .unwrap()
                    .to_dtype(dt)
                    .unwrap();
                let iv = batched_from_deltas(d, 1, 3, dt, &dev());
                let col = Tensor::ones((1, 3, 3), dt, &dev()).unwrap();
                let lw = [1.0, -1.0, 0.5, 2.0, 0.1];
                let cfg = CompositeConfig {
                    opaque_last,
                    ..Default::default()
                };
                for (pname, fused) in [("fused", true), ("reference", false)] {
                    for geo_var in [true, false] {
                        let g = grads(fused, &sig, &col, &iv, None, &cfg, &lw, geo_var);
                        assert!(
                            all_finite(&g),
                            "{name} {dt:?} {pname} opaque_last={opaque_last} geo_var={geo_var}: {:?} {:?} {:?}",
                            g.sig,
                            g.starts,
                            g.ends
                        );
                    }
                }
            }
        }
    }
    // 1e-30 thickness: opacity = 3e-30 to 1e-6 relative in f32, fused and reference.
    for dt in [DType::F32, DType::F64] {
        let sig = Tensor::new(&[[1e-30f64, 1e-30, 1e-30]], &dev())
            .unwrap()
            .to_dtype(dt)
            .unwrap();
        let iv = batched_from_deltas(&[1.0; 3], 1, 3, dt, &dev());
        let col = Tensor::ones((1, 3, 1), dt, &dev()).unwrap();
        for fused in [true, false] {
            let out = run(fused, &sig, &col, &iv, None, &CompositeConfig::default());
            let o = v64(&out.opacity)[0];
            assert!((o / 3e-30 - 1.0).abs() < 1e-6, "{dt:?}: {o:e}");
        }
    }
}

#[test]
fn one_dense_interval_gives_one_hot_weights_and_gradient_only_up_to_it() {
    let n = 32;
    let mut s = vec![0.0; n];
    s[9] = 1e10;
    let sig = Tensor::from_vec(s, (1, n), &dev()).unwrap();
    let iv = batched_from_deltas(&vec![0.01; n], 1, n, DType::F64, &dev());
    let col = Tensor::arange(0.0f64, n as f64, &dev())
        .unwrap()
        .reshape((1, n, 1))
        .unwrap();
    let cfg = CompositeConfig::default();
    let out = run(true, &sig, &col, &iv, None, &cfg);
    assert_eq!(v64(&out.color)[0], 9.0, "colour of the one-hot sample");
    assert_eq!(v64(&out.opacity)[0], 1.0);
    let g = grads(true, &sig, &col, &iv, None, &cfg, &[1.0, 0.0, 0.0], true);
    assert_eq!(g.col[9], 1.0);
    assert!(g.col.iter().enumerate().all(|(i, v)| i == 9 || *v == 0.0));
    assert!(
        g.sig[10..].iter().all(|v| *v == 0.0),
        "nothing behind the wall matters"
    );
}

#[test]
fn f32_long_rays_underflow_without_nan_in_fused_gradients() {
    let (r, n) = (4, 1024);
    let sig = Tensor::full(2.0f32, (r, n), &dev()).unwrap();
    let iv = batched_from_deltas(&vec![0.5; r * n], r, n, DType::F32, &dev());
    let col = Tensor::full(0.5f32, (r, n, 3), &dev()).unwrap();
    let g = grads(
        true,
        &sig,
        &col,
        &iv,
        None,
        &CompositeConfig::default(),
        &[1.0, 1.0, 1.0, 1.0, 1.0],
        true,
    );
    assert!(all_finite(&g));
    assert!(g.sig[n - 1] == 0.0 && g.sig[0] != 0.0);
}

#[test]
fn packed_with_only_empty_rays_gives_background() {
    let packed = Packed::from_counts(&[0, 0], &dev()).unwrap();
    let z = Tensor::zeros(0, DType::F32, &dev()).unwrap();
    let zc = Tensor::zeros((0, 3), DType::F32, &dev()).unwrap();
    let iv = Intervals::new(z.clone(), z.clone(), Layout::Packed(packed)).unwrap();
    let bg = Tensor::new(&[0.25f32, 0.5, 1.0], &dev()).unwrap();
    let cfg = CompositeConfig {
        opaque_last: false,
        background: Some(bg),
        force_reference: false,
    };
    for fused in [true, false] {
        let out = run(fused, &z, &zc, &iv, None, &cfg);
        assert_eq!(v64(&out.color), vec![0.25, 0.5, 1.0, 0.25, 0.5, 1.0]);
        assert_eq!(v64(&out.opacity), vec![0.0, 0.0]);
    }
}

/// `composite` with values as colours (0.1's `accumulate_fused`): `.color` is Σwv and
/// `.opacity` is Σw of the reference weights.
#[test]
fn composite_of_values_equals_weights_times_values() {
    let (sig, col, iv) = batched(3, 17, 2, 99);
    let out = run(true, &sig, &col, &iv, None, &CompositeConfig::default());
    let w = render_weights(&sig, &iv, None, &CompositeConfig::default()).unwrap();
    let want = accumulate(&w.weights, &col, &Layout::Batched).unwrap();
    let got = v64(&out.color);
    for (a, b) in got.iter().zip(v64(&want)) {
        assert!((a - b).abs() < 1e-13);
    }
    let op = v64(&out.opacity);
    for (a, b) in op.iter().zip(v64(&w.weights.sum(1).unwrap())) {
        assert!((a - b).abs() < 1e-13);
    }
}

#[test]
fn fused_rejects_non_contiguous_nothing_and_bad_input_with_names() {
    // Non-contiguous inputs are fine (copied); bad values are named.
    let (sig, col, iv) = batched(3, 5, 3, 1);
    let sig_t = sig.t().unwrap().contiguous().unwrap().t().unwrap();
    let cfg = CompositeConfig::default();
    let a = run(true, &sig_t, &col, &iv, None, &cfg);
    let b = run(false, &sig, &col, &iv, None, &cfg);
    for (x, y) in v64(&a.color).iter().zip(v64(&b.color)) {
        assert!((x - y).abs() < 1e-13);
    }
    // Inverted intervals (built without `Intervals::new`, which would reject them).
    let neg = Intervals {
        starts: iv.ends.clone(),
        ends: iv.starts.clone(),
        layout: Layout::Batched,
    };
    match composite(&sig, &col, &neg, None, &cfg) {
        Err(neural_fields::Error::InvalidArgument { arg, .. }) => assert_eq!(arg, "intervals"),
        other => panic!("{other:?}"),
    }
}

mod activations {
    use super::*;
    use neural_fields::numerics;
    use neural_fields::numerics::trunc_exp;

    /// Softplus with β = 1.
    fn softplus(x: &Tensor) -> neural_fields::Result<Tensor> {
        numerics::softplus(x, 1.0)
    }

    fn value_and_grad(
        f: fn(&Tensor) -> neural_fields::Result<Tensor>,
        xs: &[f64],
        dt: DType,
    ) -> (Vec<f64>, Vec<f64>) {
        let x = Var::from_tensor(&Tensor::new(xs, &dev()).unwrap().to_dtype(dt).unwrap()).unwrap();
        let y = f(x.as_tensor()).unwrap();
        let g = y.sum_all().unwrap().backward().unwrap();
        (v64(&y), v64(g.get(x.as_tensor()).unwrap()))
    }

    #[test]
    fn trunc_exp_value_is_clamped_and_gradient_is_exp_of_clamped_input() {
        let xs = [-1000.0, -20.0, -1.0, 0.0, 3.0, 20.0, 88.0, 100.0, 800.0];
        for (dt, m, tol) in [(DType::F32, 88.0f64, 1e-6), (DType::F64, 709.0, 1e-15)] {
            let (y, g) = value_and_grad(trunc_exp, &xs, dt);
            for i in 0..xs.len() {
                let want = if dt == DType::F32 {
                    f64::from((xs[i].min(m) as f32).exp())
                } else {
                    xs[i].min(m).exp()
                };
                let rel = if want == 0.0 {
                    y[i].abs()
                } else {
                    ((y[i] - want) / want).abs()
                };
                assert!(
                    y[i].is_finite() && rel < tol,
                    "{dt:?} value at {}: {} vs {want}",
                    xs[i],
                    y[i]
                );
                let gw = xs[i].clamp(-15.0, 15.0).exp();
                assert!(
                    ((g[i] - gw) / gw).abs() < tol,
                    "{dt:?} grad at {}: {}",
                    xs[i],
                    g[i]
                );
            }
        }
        let (y, _) = value_and_grad(trunc_exp, &[f64::NAN], DType::F32);
        assert!(y[0].is_nan(), "NaN propagates");
    }

    #[test]
    fn softplus_is_stable_with_sigmoid_gradient() {
        let xs = [-800.0, -100.0, -30.0, -1.0, 0.0, 1e-8, 2.0, 40.0, 1e6];
        for (dt, tol) in [(DType::F32, 1e-6), (DType::F64, 1e-14)] {
            let (y, g) = value_and_grad(softplus, &xs, dt);
            for i in 0..xs.len() {
                let x = xs[i];
                let want = x.max(0.0) + (-x.abs()).exp().ln_1p();
                let xr = v64(&Tensor::new(&[x], &dev()).unwrap().to_dtype(dt).unwrap())[0];
                let want = if dt == DType::F32 {
                    want as f32 as f64
                } else {
                    want
                };
                let scale = want.abs().max(f64::MIN_POSITIVE);
                assert!(
                    ((y[i] - want) / scale).abs() < tol || (want < 1e-38 && dt == DType::F32),
                    "{dt:?} value at {x}: {} vs {want}",
                    y[i]
                );
                let sig = 1.0 / (1.0 + (-xr).exp());
                assert!(
                    (g[i] - sig).abs() <= tol * sig.max(1e-300)
                        || (sig < 1e-38 && dt == DType::F32),
                    "{dt:?} grad at {x}: {} vs {sig}",
                    g[i]
                );
            }
            assert_eq!(g[4], 0.5, "derivative at 0 is exactly 1/2");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]
        #[test]
        fn softplus_gradient_matches_finite_differences(x in -40.0f64..40.0) {
            let (_, g) = value_and_grad(softplus, &[x], DType::F64);
            let f = |x: f64| v64(&softplus(&Tensor::new(&[x], &dev()).unwrap()).unwrap())[0];
            let h = 1e-5;
            let fd = (f(x + h) - f(x - h)) / (2.0 * h);
            prop_assert!((fd - g[0]).abs() <= 1e-6 * g[0].abs() + 1e-10, "{fd} vs {}", g[0]);
        }
    }

    #[test]
    fn activations_feed_compositing_without_nan_for_huge_raw_outputs() {
        for dt in [DType::F32, DType::F64] {
            for act in [
                trunc_exp as fn(&Tensor) -> neural_fields::Result<Tensor>,
                softplus,
            ] {
                let raw = Var::from_tensor(
                    &Tensor::new(&[[-1e4f64, 1e3, 87.0, 0.0, 1e30]], &dev())
                        .unwrap()
                        .to_dtype(dt)
                        .unwrap(),
                )
                .unwrap();
                let sig = act(raw.as_tensor()).unwrap();
                let iv = batched_from_deltas(&[0.1; 5], 1, 5, dt, &dev());
                let col = Tensor::ones((1, 5, 3), dt, &dev()).unwrap();
                let out = run(true, &sig, &col, &iv, None, &CompositeConfig::default());
                let g = out.color.sum_all().unwrap().backward().unwrap();
                let gr = v64(g.get(raw.as_tensor()).unwrap());
                assert!(gr.iter().all(|v| v.is_finite()), "{dt:?}: {gr:?}");
                assert!(v64(&out.color).iter().all(|v| v.is_finite()));
            }
        }
    }
}

/// When the intervals are plain tensors (no gradient), the fused op forms δ and t in
/// place and skips their gradients; the gradients it does produce are the reference's,
/// with unit directions and with rays whose norms scale δ.
#[test]
fn gradients_with_constant_intervals_match_reference() {
    let (sig, col, iv) = batched(5, 33, 3, 4242);
    let rays = scaled_rays(5, 4242);
    for rays in [None, Some(&rays)] {
        let grads_of = |fused: bool| {
            let s = Var::from_tensor(&sig).unwrap();
            let c = Var::from_tensor(&col).unwrap();
            let out = run(
                fused,
                s.as_tensor(),
                c.as_tensor(),
                &iv,
                rays,
                &CompositeConfig::default(),
            );
            let l = loss(&out, &[0.3, -1.0, 2.0, 0.7, -0.2]);
            let g = l.backward().unwrap();
            (
                v64(g.get(s.as_tensor()).unwrap()),
                v64(g.get(c.as_tensor()).unwrap()),
            )
        };
        let (gs_f, gc_f) = grads_of(true);
        let (gs_r, gc_r) = grads_of(false);
        // Measured against the size of the terms each gradient is made of (as in the
        // proptests): ∂L/∂σ = δ·∂L/∂x with |∂L/∂x| ≤ T·max|u|, and |u| grows with the
        // midpoints t, which grow with δ (up to 1e10 here).
        let lw = [0.3, -1.0, 2.0, 0.7, -0.2];
        let (xs, _) = x_scale(&sig, &iv, rays, &v64(&col), &lw, false);
        let dv = v64(&iv.deltas(rays).unwrap());
        let ss: Vec<f64> = xs.iter().zip(&dv).map(|(x, d)| x * d + 1.0).collect();
        let sc: Vec<f64> = vec![1.0; gc_r.len()];
        let what = format!("rays {}", rays.is_some());
        check_close(&format!("{what}: sigmas"), &gs_f, &gs_r, &ss, 1e-10).unwrap();
        check_close(&format!("{what}: colors"), &gc_f, &gc_r, &sc, 1e-10).unwrap();
    }
}

/// Found as a proptest failure (seed 6506839704322377247): a ray whose transmittance
/// fell to 9.5e-301 before an opaque sample. The reference gives that sample weight
/// T (here 5.0e-301); the kernel stops once T < 1e-300 and gives it 0. The colour
/// gradients differ by that weight, below the documented 1e-300 bound, and everything is
/// finite.
#[test]
fn a_sample_behind_transmittance_below_1e_300_gets_zero_weight() {
    // x = σδ: 691.5 takes T to e^{-691.5} ≈ 5.0e-301, then an opaque sample. Intervals
    // [0, 1], [1, 2], [2, 3]: δ = 1, midpoints 0.5, 1.5, 2.5.
    let sig = Tensor::new(&[[691.5f64, 1e18, 1.0]], &dev()).unwrap();
    let iv = batched_from_deltas(&[1.0; 3], 1, 3, DType::F64, &dev());
    let col = Tensor::ones((1, 3, 1), DType::F64, &dev()).unwrap();
    let grads_of = |fused: bool| {
        let c = Var::from_tensor(&col).unwrap();
        let out = run(
            fused,
            &sig,
            c.as_tensor(),
            &iv,
            None,
            &CompositeConfig::default(),
        );
        let g = out.color.sum_all().unwrap().backward().unwrap();
        v64(g.get(c.as_tensor()).unwrap())
    };
    let (f, r) = (grads_of(true), grads_of(false));
    assert!(
        r[1] > 0.0 && r[1] < 1e-300,
        "reference keeps the tiny weight: {r:?}"
    );
    assert_eq!(f[1], 0.0, "the kernel stops before it: {f:?}");
    for (a, b) in f.iter().zip(&r) {
        assert!(a.is_finite() && (a - b).abs() <= 1e-300, "{a} vs {b}");
    }
}
