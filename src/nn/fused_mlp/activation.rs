//! The hidden activation on slices, for the fused MLP: ReLU, and softplus with its slope
//! computed in f64 from branch-free polynomials that the compiler vectorises (compiled for
//! AVX-512 and AVX2 where the CPU has them). Scalar `exp` and `log1p` calls took four
//! fifths of a softplus network's forward pass.
//!
//! `softplus_β(h) = max(h, 0) + log1p(e^{−β|h|})/β` and `σ(z) = 1/(1 + e^{−z})` (as
//! `e/(1 + e)` with `e = e^{−|z|}` for `z < 0`), the same stable forms as
//! [`crate::numerics::softplus`]; `e^x` for `x ≤ 0` by `2ᵏ·e^r` (`|r| ≤ ln2/2`, Taylor to
//! degree 12) and `log1p(u)` for `u ∈ [0, 1]` by `2·atanh(s)` series, to a few ulps of
//! f64 (tested against the standard library).

use super::{Act, Real};
use crate::numerics::round_to_integer;

/// `e^x` for `x ≤ 0` (0 below −708, where f64 leaves the normal range).
#[inline(always)]
fn exp_nonpos(x: f64) -> f64 {
    const LN2_HI: f64 = 0.693_147_180_369_123_8;
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    let xc = x.max(-708.0);
    let k = round_to_integer(xc * std::f64::consts::LOG2_E);
    let r = (xc - k * LN2_HI) - k * LN2_LO;
    // e^r, |r| ≤ 0.35: Taylor to degree 12 (remainder below 2e-16 relative).
    let mut p = 1.0 / 479_001_600.0;
    for d in [
        39_916_800.0,
        3_628_800.0,
        362_880.0,
        40_320.0,
        5_040.0,
        720.0,
        120.0,
        24.0,
        6.0,
        2.0,
        1.0,
        1.0,
    ] {
        p = p * r + 1.0 / d;
    }
    let scale = f64::from_bits(((k as i64 + 1023) as u64) << 52);
    if x < -708.0 {
        0.0
    } else {
        p * scale
    }
}

/// `log(1 + u)` for `u ∈ [0, 1]`, with full relative precision for tiny `u`.
#[inline(always)]
fn log1p_unit(u: f64) -> f64 {
    // Below √2 − 1: 2·atanh(s) with s = u/(2 + u) ∈ [0, 0.172]; above: ln 2 + 2·atanh(s)
    // with s = (u − 1)/(u + 3) ∈ [−0.172, 0] (log((1 + u)/2)).
    let high = u > std::f64::consts::SQRT_2 - 1.0;
    let s = if high {
        (u - 1.0) / (u + 3.0)
    } else {
        u / (2.0 + u)
    };
    let z = s * s;
    // Σ z^j/(2j + 1), j ≤ 11: the remainder is below 1e-18 for |s| ≤ 0.172.
    let mut p = 1.0 / 23.0;
    for d in [21.0, 19.0, 17.0, 15.0, 13.0, 11.0, 9.0, 7.0, 5.0, 3.0, 1.0] {
        p = p * z + 1.0 / d;
    }
    let v = 2.0 * s * p;
    if high {
        v + std::f64::consts::LN_2
    } else {
        v
    }
}

/// `softplus_β(h)`; NaN propagates.
#[inline(always)]
pub(super) fn softplus(h: f64, beta: f64) -> f64 {
    let relu = if h > 0.0 { h } else { h * 0.0 };
    relu + log1p_unit(exp_nonpos(-(beta * h).abs())) / beta
}

/// `σ(z)`.
#[inline(always)]
pub(super) fn sigmoid(z: f64) -> f64 {
    let e = exp_nonpos(-z.abs());
    if z >= 0.0 {
        1.0 / (1.0 + e)
    } else {
        e / (1.0 + e)
    }
}

/// `φ''(h) = β σ(βh)(1 − σ(βh))` of softplus.
pub(super) fn softplus_curvature(h: f64, beta: f64) -> f64 {
    let s = sigmoid(beta * h);
    beta * s * (1.0 - s)
}

#[inline(always)]
fn activate_body<T: Real>(act: Act, h: &[T], a: &mut [T]) {
    let zero = T::from_f64(0.0);
    match act {
        Act::Relu => {
            // max(h, 0) as candle's relu (NaN propagates).
            for (a, &h) in a.iter_mut().zip(h) {
                *a = if h < zero { zero } else { h };
            }
        }
        Act::Softplus(beta) => {
            for (a, &h) in a.iter_mut().zip(h) {
                *a = T::from_f64(softplus(h.to_f64(), beta));
            }
        }
    }
}

#[inline(always)]
fn slope_times_body<T: Real>(act: Act, h: &[T], x: &[T], out: &mut [T]) {
    match act {
        Act::Relu => {
            // 𝟙[h ≥ 0], candle's own ReLU derivative, so both paths agree at the kink.
            let (zero, one) = (T::from_f64(0.0), T::from_f64(1.0));
            for ((o, &h), &x) in out.iter_mut().zip(h).zip(x) {
                *o = if h >= zero { one } else { zero } * x;
            }
        }
        Act::Softplus(beta) => {
            for ((o, &h), &x) in out.iter_mut().zip(h).zip(x) {
                *o = T::from_f64(sigmoid(beta * h.to_f64()) * x.to_f64());
            }
        }
    }
}

/// Runs `$body` compiled for AVX-512 or AVX2 when the CPU has them.
macro_rules! dispatch {
    ($body:ident, $($arg:expr),*) => {{
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx512f,avx512dq,avx512vl,fma")]
            fn avx512<T: Real>(act: Act, h: &[T], x: &[T], out: &mut [T]) {
                $body(act, h, x, out)
            }
            #[target_feature(enable = "avx2,fma")]
            fn avx2<T: Real>(act: Act, h: &[T], x: &[T], out: &mut [T]) {
                $body(act, h, x, out)
            }
            use std::arch::is_x86_feature_detected as has;
            if has!("avx512f") && has!("avx512dq") && has!("avx512vl") && has!("fma") {
                // SAFETY: the CPU has the features the function was compiled for.
                return unsafe { avx512($($arg),*) };
            }
            if has!("avx2") && has!("fma") {
                // SAFETY: as above.
                return unsafe { avx2($($arg),*) };
            }
        }
        $body($($arg),*)
    }};
}

#[inline(always)]
fn activate_with_unused<T: Real>(act: Act, h: &[T], _x: &[T], a: &mut [T]) {
    activate_body(act, h, a)
}

/// `a[i] = φ(h[i])`.
pub(super) fn activate<T: Real>(act: Act, h: &[T], a: &mut [T]) {
    dispatch!(activate_with_unused, act, h, h, a)
}

/// `out[i] = φ'(h[i]) · x[i]`.
pub(super) fn slope_times<T: Real>(act: Act, h: &[T], x: &[T], out: &mut [T]) {
    dispatch!(slope_times_body, act, h, x, out)
}

#[cfg(test)]
mod tests {
    use super::{exp_nonpos, log1p_unit, sigmoid, softplus};

    #[test]
    fn polynomial_exp_log1p_softplus_and_sigmoid_match_the_standard_library() {
        for i in 0..=20_000 {
            let x = -750.0 * (i as f64 / 20_000.0).powi(3);
            let want = x.exp();
            let got = exp_nonpos(x);
            if x >= -708.0 {
                assert!(
                    (got - want).abs() <= 4e-16 * want,
                    "exp({x}): {got} vs {want}"
                );
            } else {
                assert_eq!(got, 0.0);
            }
            let u = i as f64 / 20_000.0;
            for u in [u, u * 1e-12] {
                let (got, want) = (log1p_unit(u), u.ln_1p());
                assert!(
                    (got - want).abs() <= 1e-15 * want.max(f64::MIN_POSITIVE),
                    "log1p({u}): {got} vs {want}"
                );
            }
        }
        for h in [-1e4f64, -30.0, -1.0, -1e-9, 0.0, 1e-9, 0.5, 3.0, 1e4] {
            for beta in [1.0f64, 100.0] {
                let want = h.max(0.0) + (-(beta * h).abs()).exp().ln_1p() / beta;
                assert!((softplus(h, beta) - want).abs() <= 1e-15 * want.abs().max(1e-300));
                let z: f64 = beta * h;
                let want = 1.0 / (1.0 + (-z).exp());
                assert!((sigmoid(z) - want).abs() <= 1e-15);
            }
        }
        assert!(softplus(f64::NAN, 1.0).is_nan());
    }
}
