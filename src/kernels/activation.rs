//! The hidden activation on slices, for the fused MLP: ReLU, and softplus with its slope
//! computed at the data's precision from branch-free polynomials that the compiler
//! vectorises (compiled for AVX-512 and AVX2 where the CPU has them). Scalar `exp` and
//! `log1p` calls took four fifths of a softplus network's forward pass; computing f32 data
//! in f64 polynomials still took three fifths of a DVR step.
//!
//! `softplus_β(h) = max(h, 0) + log1p(e^{−β|h|})/β` and `σ(z) = 1/(1 + e^{−z})` (as
//! `e/(1 + e)` with `e = e^{−|z|}` for `z < 0`), the same stable forms as
//! [`crate::numerics::softplus`]; `e^x` for `x ≤ 0` by `2ᵏ·e^r` (`|r| ≤ ln2/2`, Taylor to
//! degree 12) and `log1p(u)` for `u ∈ [0, 1]` by `2·atanh(s)` series, to a few ulps of
//! f64 (tested against the standard library); for f32 the same forms with degree 7 and
//! five series terms, to a few ulps of f32.

use candle_core::WithDType;

/// The hidden activation.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Act {
    Relu,
    Softplus(f64),
}

/// `e^x` for `x ≤ 0` (0 below −708, where f64 leaves the normal range).
#[inline(always)]
fn exp_nonpos(x: f64) -> f64 {
    const LN2_HI: f64 = 0.693_147_180_369_123_8;
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    const ROUND: f64 = 6_755_399_441_055_744.0; // 1.5·2⁵²: adding and subtracting it rounds
    let xc = x.max(-708.0);
    let shifted = xc * std::f64::consts::LOG2_E + ROUND;
    let k = shifted - ROUND;
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
    // 2ᵏ from the integer in `shifted`'s low bits (its ulp is 1): integer lane ops, where
    // a float-to-int cast does not vectorise as well.
    let ki = shifted.to_bits().wrapping_sub(ROUND.to_bits());
    let scale = f64::from_bits(ki.wrapping_add(1023) << 52);
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
    // One division of the selected numerator and denominator (not two and a blend).
    let (num, den) = if high {
        (u - 1.0, u + 3.0)
    } else {
        (u, 2.0 + u)
    };
    let s = num / den;
    // Where s² would be subnormal the series is 1: squaring 0 instead avoids the slow
    // subnormal arithmetic.
    let sq = if s.abs() < 1e-150 { 0.0 } else { s };
    let z = sq * sq;
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
    (if z >= 0.0 { 1.0 } else { e }) / (1.0 + e)
}

/// `e^x` for `x ≤ 0` at f32 precision (0 below −87, where f32 leaves the normal range):
/// `2ᵏ·e^r`, `|r| ≤ ln2/2`, Taylor to degree 7 (remainder below 5e-9 relative).
#[inline(always)]
fn exp_nonpos_f32(x: f32) -> f32 {
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    const ROUND: f32 = 12_582_912.0; // 1.5·2²³: adding and subtracting it rounds to an integer
    let xc = x.max(-87.0);
    let shifted = xc * std::f32::consts::LOG2_E + ROUND;
    let k = shifted - ROUND;
    let r = (xc - k * LN2_HI) - k * LN2_LO;
    let mut p = 1.0 / 5_040.0;
    for d in [720.0, 120.0, 24.0, 6.0, 2.0, 1.0, 1.0] {
        p = p * r + 1.0 / d;
    }
    // 2ᵏ from the integer in `shifted`'s low bits (its ulp is 1): integer lane ops, where
    // a float-to-int cast would not vectorise as well.
    let ki = shifted.to_bits().wrapping_sub(ROUND.to_bits());
    let scale = f32::from_bits(ki.wrapping_add(127) << 23);
    if x < -87.0 {
        0.0
    } else {
        p * scale
    }
}

/// `log(1 + u)` for `u ∈ [0, 1]` at f32 precision, with full relative precision for tiny
/// `u` (the series of [`log1p_unit`] to `j ≤ 5`: remainder below 1e-10 relative).
#[inline(always)]
fn log1p_unit_f32(u: f32) -> f32 {
    let high = u > std::f32::consts::SQRT_2 - 1.0;
    // One division of the selected numerator and denominator (not two and a blend).
    let (num, den) = if high {
        (u - 1.0, u + 3.0)
    } else {
        (u, 2.0 + u)
    };
    let s = num / den;
    let sq = if s.abs() < 1e-18 { 0.0 } else { s }; // as in `log1p_unit`
    let z = sq * sq;
    let mut p = 1.0 / 11.0;
    for d in [9.0, 7.0, 5.0, 3.0, 1.0] {
        p = p * z + 1.0 / d;
    }
    let v = 2.0 * s * p;
    if high {
        v + std::f32::consts::LN_2
    } else {
        v
    }
}

/// `softplus_β(h)` at f32 precision, given `1/β`; NaN propagates. Where `β|h| > 80` the
/// log term (below 2e-35/β) is flushed to 0, so that no lane computes with subnormals
/// (which cost a microcode assist per operation).
#[inline(always)]
fn softplus_f32(h: f32, beta: f32, inv_beta: f32) -> f32 {
    let relu = if h > 0.0 { h } else { h * 0.0 };
    let a = (beta * h).abs();
    let e = exp_nonpos_f32(-a.min(80.0));
    let e = if a > 80.0 { 0.0 } else { e };
    relu + log1p_unit_f32(e) * inv_beta
}

/// `σ(z)` at f32 precision.
#[inline(always)]
fn sigmoid_f32(z: f32) -> f32 {
    let e = exp_nonpos_f32(-z.abs());
    (if z >= 0.0 { 1.0 } else { e }) / (1.0 + e)
}

/// Softplus and its slope at the precision of the data: f64 data through the f64
/// polynomials above, f32 data through f32 ones (16 lanes per AVX-512 register instead of
/// 8, and fewer terms), a few f32 ulps from the correctly rounded value.
pub(crate) trait Precision: Copy {
    /// `a[i] = softplus_β(h[i])`.
    fn softplus_slice(h: &[Self], beta: f64, a: &mut [Self]);
    /// `out[i] = σ(β·h[i])·x[i]`, softplus's slope times `x`.
    fn sigmoid_times_slice(h: &[Self], beta: f64, x: &[Self], out: &mut [Self]);
}

impl Precision for f64 {
    #[inline(always)]
    fn softplus_slice(h: &[f64], beta: f64, a: &mut [f64]) {
        for (a, &h) in a.iter_mut().zip(h) {
            *a = softplus(h, beta);
        }
    }

    #[inline(always)]
    fn sigmoid_times_slice(h: &[f64], beta: f64, x: &[f64], out: &mut [f64]) {
        for ((o, &h), &x) in out.iter_mut().zip(h).zip(x) {
            *o = sigmoid(beta * h) * x;
        }
    }
}

impl Precision for f32 {
    #[inline(always)]
    fn softplus_slice(h: &[f32], beta: f64, a: &mut [f32]) {
        let (beta, inv_beta) = (beta as f32, (1.0 / beta) as f32);
        for (a, &h) in a.iter_mut().zip(h) {
            *a = softplus_f32(h, beta, inv_beta);
        }
    }

    #[inline(always)]
    fn sigmoid_times_slice(h: &[f32], beta: f64, x: &[f32], out: &mut [f32]) {
        let beta = beta as f32;
        for ((o, &h), &x) in out.iter_mut().zip(h).zip(x) {
            *o = sigmoid_f32(beta * h) * x;
        }
    }
}

/// `φ''(h) = β σ(βh)(1 − σ(βh))` of softplus.
pub(super) fn softplus_curvature(h: f64, beta: f64) -> f64 {
    let s = sigmoid(beta * h);
    beta * s * (1.0 - s)
}

#[inline(always)]
fn activate_body<T: WithDType + Precision>(act: Act, h: &[T], a: &mut [T]) {
    let zero = T::from_f64(0.0);
    match act {
        Act::Relu => {
            // max(h, 0) as candle's relu (NaN propagates).
            for (a, &h) in a.iter_mut().zip(h) {
                *a = if h < zero { zero } else { h };
            }
        }
        Act::Softplus(beta) => T::softplus_slice(h, beta, a),
    }
}

#[inline(always)]
fn slope_times_body<T: WithDType + Precision>(act: Act, h: &[T], x: &[T], out: &mut [T]) {
    match act {
        Act::Relu => {
            // 𝟙[h ≥ 0], candle's own ReLU derivative, so both paths agree at the kink.
            let (zero, one) = (T::from_f64(0.0), T::from_f64(1.0));
            for ((o, &h), &x) in out.iter_mut().zip(h).zip(x) {
                *o = if h >= zero { one } else { zero } * x;
            }
        }
        Act::Softplus(beta) => T::sigmoid_times_slice(h, beta, x, out),
    }
}

/// Runs `$body` compiled for AVX-512 or AVX2 when the CPU has them.
macro_rules! dispatch {
    ($body:ident, $($arg:expr),*) => {{
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx512f,avx512dq,avx512vl,fma")]
            fn avx512<T: WithDType + Precision>(act: Act, h: &[T], x: &[T], out: &mut [T]) {
                $body(act, h, x, out)
            }
            #[target_feature(enable = "avx2,fma")]
            fn avx2<T: WithDType + Precision>(act: Act, h: &[T], x: &[T], out: &mut [T]) {
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
fn activate_with_unused<T: WithDType + Precision>(act: Act, h: &[T], _x: &[T], a: &mut [T]) {
    activate_body(act, h, a)
}

/// `a[i] = φ(h[i])`.
pub(super) fn activate<T: WithDType + Precision>(act: Act, h: &[T], a: &mut [T]) {
    dispatch!(activate_with_unused, act, h, h, a)
}

/// `out[i] = φ'(h[i]) · x[i]`.
pub(super) fn slope_times<T: WithDType + Precision>(act: Act, h: &[T], x: &[T], out: &mut [T]) {
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

    /// The f32 polynomials against the f64 ones rounded to f32: within 4 f32 ulps
    /// (relative 5e-7), over the whole range and at tiny arguments.
    #[test]
    fn f32_polynomials_are_within_a_few_ulps_of_the_f64_ones() {
        use super::{exp_nonpos_f32, log1p_unit_f32, sigmoid_f32, softplus_f32};
        let ulps = |got: f32, want: f64| {
            let w = want as f32;
            (f64::from(got) - f64::from(w)).abs() <= 4.0 * f64::from(f32::EPSILON) * want.abs()
        };
        for i in 0..=20_000 {
            let x = -90.0 * (i as f64 / 20_000.0).powi(3);
            let got = exp_nonpos_f32(x as f32);
            if x >= -87.0 {
                assert!(ulps(got, (x as f32 as f64).exp()), "exp({x}): {got}");
            } else {
                assert_eq!(got, 0.0);
            }
            let u = i as f64 / 20_000.0;
            for u in [u, u * 1e-30] {
                let u = u as f32;
                let got = log1p_unit_f32(u);
                assert!(ulps(got, f64::from(u).ln_1p()), "log1p({u}): {got}");
            }
        }
        for h in [-1e4f32, -30.0, -1.0, -1e-9, 0.0, 1e-9, 0.5, 3.0, 1e4] {
            for beta in [1.0f32, 100.0] {
                let want = softplus(f64::from(h), f64::from(beta));
                let got = softplus_f32(h, beta, 1.0 / beta);
                assert!(
                    (f64::from(got) - want).abs() <= 1e-6 * want.abs().max(1e-30),
                    "softplus({h}, {beta}): {got} vs {want}"
                );
                let z = beta * h;
                let (got, want) = (sigmoid_f32(z), sigmoid(f64::from(z)));
                assert!(
                    (f64::from(got) - want).abs() <= 2e-7,
                    "σ({z}): {got} vs {want}"
                );
            }
        }
        assert!(softplus_f32(f32::NAN, 1.0, 1.0).is_nan());
    }
}
