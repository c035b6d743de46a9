//! Test helpers that the crate's own unit tests share with the integration tests (they
//! include this file with `#[path]`): they use only candle and the including module's
//! `SplitMix64` (`crate::rng::SplitMix64` inside the crate,
//! `neural_fields::rng::SplitMix64` outside).

use super::SplitMix64;
use candle_core::{DType, Tensor};

/// Flattens any float tensor into a `Vec<f64>`.
pub fn v64(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

/// Random extreme compositing inputs for `n` samples with `c` channels: σ in
/// {0, 10^[−30, 30], moderate optical thickness}, δ in {10^[−30, 10], moderate},
/// colours in [0, 1). Returns `(σ, δ, colours)`.
pub fn extreme_inputs(seed: u64, n: usize, c: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut rng = SplitMix64::new(seed);
    let mut sig = Vec::with_capacity(n);
    let mut del = Vec::with_capacity(n);
    for _ in 0..n {
        let d = if rng.uniform() < 0.4 {
            10f64.powf(-30.0 + 40.0 * rng.uniform())
        } else {
            0.001 + 0.1 * rng.uniform()
        };
        let s = match rng.below(10) {
            0 | 1 => 0.0,
            2 | 3 => 10f64.powf(-30.0 + 60.0 * rng.uniform()),
            4..=6 => 2.0 * rng.uniform() / d,
            _ => 0.05 * rng.uniform() / d,
        };
        sig.push(s);
        del.push(d);
    }
    let col = (0..n * c).map(|_| rng.uniform()).collect();
    (sig, del, col)
}
