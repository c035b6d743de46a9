//! Stiff cases of `numerics`, `rng` and `error`: the defended scalar maths at every
//! magnitude in f32 and f64, the Levenberg–Marquardt solver, and the seeded tensor makers.

mod common;

use candle_core::{DType, Device, Tensor};

use common::stiff::{magnitudes, var, Expect, Suite, DTYPES};

use neural_fields::numerics::{
    bce_with_logits, safe_sin_cos, sigmoid, sin_cos_pi, softplus, trunc_exp,
};
use neural_fields::rng::SplitMix64;

#[test]
fn numerics_stay_finite_at_every_magnitude() {
    let mut s = Suite::default();
    sweep_numerics(&mut s);
    s.finish("numerics", NUMERICS);
}

#[test]
fn levenberg_marquardt_stays_finite_or_refuses() {
    let mut s = Suite::default();
    sweep_levenberg_marquardt(&mut s);
    s.finish("Levenberg–Marquardt", LEVENBERG_MARQUARDT);
}

#[test]
fn every_source_file_has_a_stiff_case_file() {
    common::stiff::check_owners();
}

#[test]
fn rng_tensor_makers_stay_finite() {
    let mut s = Suite::default();
    sweep_rng(&mut s);
    s.finish("rng", RNG);
}

#[test]
fn every_public_numerics_function_is_swept_or_exempt() {
    common::stiff::check_coverage(
        "stiff_cases_numerics",
        &[NUMERICS, LEVENBERG_MARQUARDT, RNG],
        EXEMPT,
        &[],
        &[],
    );
}

/// Items swept by `sweep_numerics`.
const NUMERICS: &[&str] = &[
    "numerics::bce_with_logits",
    "numerics::safe_sin_cos",
    "numerics::sigmoid",
    "numerics::sin_cos_pi",
    "numerics::softplus",
    "numerics::trunc_exp",
];

/// Items swept by `sweep_levenberg_marquardt`.
const LEVENBERG_MARQUARDT: &[&str] = &["numerics::levenberg_marquardt"];

/// Items swept by `sweep_rng`.
const RNG: &[&str] = &["rng::SplitMix64::uniform_tensor"];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    ("numerics::LmConfig::default", "constant"),
    (
        "error::",
        "validation helpers: their job is to return Err for bad input (unit-tested)",
    ),
    ("rng::SplitMix64::", "integer state; tensor makers swept"),
    (
        "numerics::SoftplusOp::",
        "CustomOp internals, swept via numerics::softplus",
    ),
    (
        "numerics::SigmoidOfScaled::",
        "CustomOp internals (softplus backward), swept via numerics::softplus",
    ),
    (
        "numerics::TruncExpOp::",
        "CustomOp internals, swept via numerics::trunc_exp",
    ),
    (
        "numerics::f32::",
        "trunc-exp's scalar rule per element type, swept via numerics::trunc_exp",
    ),
    (
        "numerics::f64::",
        "trunc-exp's scalar rule per element type, swept via numerics::trunc_exp",
    ),
];

fn sweep_numerics(s: &mut Suite) {
    for dtype in DTYPES {
        let xs = magnitudes(dtype);
        let n = xs.len();
        let x = var(&xs, &[n], dtype);
        let t = x.as_tensor();
        let half = Tensor::full(0.5f64, n, &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let tag = format!("{dtype:?}, |x| up to max");
        // The sine and the cosine each on their own, so that each gradient is checked.
        let sin = format!("{tag}, sin");
        s.case(
            "numerics::safe_sin_cos",
            &sin,
            Expect::Finite,
            &[&x],
            || Ok(vec![safe_sin_cos(t)?.0]),
        );
        let cos = format!("{tag}, cos");
        s.case(
            "numerics::safe_sin_cos",
            &cos,
            Expect::Finite,
            &[&x],
            || Ok(vec![safe_sin_cos(t)?.1]),
        );
        s.case("numerics::sin_cos_pi", &sin, Expect::Finite, &[&x], || {
            Ok(vec![sin_cos_pi(t)?.0])
        });
        s.case("numerics::sin_cos_pi", &cos, Expect::Finite, &[&x], || {
            Ok(vec![sin_cos_pi(t)?.1])
        });
        s.case("numerics::sigmoid", &tag, Expect::Finite, &[&x], || {
            Ok(vec![sigmoid(t)?])
        });
        s.case("numerics::trunc_exp", &tag, Expect::Finite, &[&x], || {
            Ok(vec![trunc_exp(t)?])
        });
        for beta in [1e-3, 1.0, 100.0, 1e6] {
            // softplus_β(x) ≈ x for large x: finite as long as x is.
            s.case(
                "numerics::softplus",
                format!("{tag}, β = {beta}"),
                Expect::Finite,
                &[&x],
                || Ok(vec![softplus(t, beta)?]),
            );
        }
        s.case(
            "numerics::bce_with_logits",
            &tag,
            Expect::Finite,
            &[&x],
            || Ok(vec![bce_with_logits(t, &half)?]),
        );
    }
}

fn sweep_rng(s: &mut Suite) {
    let d = Device::Cpu;
    for dtype in DTYPES {
        let tag = format!("{dtype:?}");
        for (a, b) in [(0.0f64, 1e-30f64), (-1e30, 1e30), (1e10, 1e10)] {
            s.case(
                "rng::SplitMix64::uniform_tensor",
                format!("{tag}, [{a}, {b})"),
                Expect::Finite,
                &[],
                || {
                    Ok(vec![SplitMix64::new(1).uniform_tensor(
                        &[64],
                        a,
                        b,
                        dtype,
                        &d,
                    )?])
                },
            );
        }
    }
}

/// Levenberg–Marquardt on least-squares problems scaled to every magnitude, from every
/// damping: a finite fit and cost, or a refusal.
fn sweep_levenberg_marquardt(s: &mut Suite) {
    for &x in &magnitudes(DType::F64) {
        let x = x.clamp(-1e150, 1e150);
        for lambda in [1e-300, 1e-3, 1e300] {
            s.case(
                "numerics::levenberg_marquardt",
                format!("residuals scaled by {x:e}, λ = {lambda:e}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let config = neural_fields::numerics::LmConfig {
                        lambda,
                        lambda_min: lambda.min(1e-9),
                        lambda_max: lambda.max(1e12),
                        ..Default::default()
                    };
                    let (p, cost) = neural_fields::numerics::levenberg_marquardt(
                        [0.0, 0.0],
                        &config,
                        |p: &[f64; 2]| {
                            let r = vec![x * p[0] - 1.0, 2.0 * x * p[1] + x];
                            Ok(Some((r, vec![[x, 0.0], [0.0, 2.0 * x]])))
                        },
                        |p, d| [p[0] + d[0], p[1] + d[1]],
                    )?;
                    Ok(vec![Tensor::new(&[p[0], p[1], cost], &Device::Cpu)?])
                },
            );
        }
    }
}
