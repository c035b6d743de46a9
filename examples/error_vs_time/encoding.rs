//! Positional-encoding error against frequency count, f32 (exact reduction and naive)
//! and f64, against an f64 evaluation of the same f32 inputs.

use crate::report::{median_seconds, v64, Row, Table, TIME_PER_CALL};
use candle_core::{DType, Device, Tensor};
use neural_fields::encoding::{Encoding, FrequencyEncoding};
use neural_fields::rng::SplitMix64;
use std::f64::consts::PI;

fn max_err(got: &[f64], x: &[f64], l: usize) -> f64 {
    let width = 3 * (2 * l + 1);
    let mut worst: f64 = 0.0;
    for (n, row) in x.chunks(3).enumerate() {
        let mut reference = row.to_vec();
        for k in 0..l {
            let w = (k as f64).exp2() * PI;
            reference.extend(row.iter().map(|v| (w * v).sin()));
            reference.extend(row.iter().map(|v| (w * v).cos()));
        }
        for (a, b) in got[n * width..(n + 1) * width].iter().zip(reference) {
            worst = worst.max((a - b).abs());
        }
    }
    worst
}

/// Naive f32 encoding: sin(f32(2ᵏπ)·x), the product rounded in f32.
fn naive(x: &Tensor, l: usize) -> Tensor {
    let mut parts = vec![x.clone()];
    for k in 0..l {
        let w = ((k as f64).exp2() * PI) as f32;
        let y = x.affine(f64::from(w), 0.0).unwrap();
        parts.push(y.sin().unwrap());
        parts.push(y.cos().unwrap());
    }
    Tensor::cat(&parts, 1).unwrap()
}

pub fn run(quick: bool) -> Vec<Table> {
    let n = if quick { 2_000 } else { 100_000 };
    let reps = if quick { 1 } else { 5 };
    let mut rng = SplitMix64::new(42);
    let x32 = rng
        .uniform_tensor(&[n, 3], -PI, PI, DType::F32, &Device::Cpu)
        .unwrap();
    let x64 = x32.to_dtype(DType::F64).unwrap();
    let xs = v64(&x64);
    let mut rows = Vec::new();
    for l in [1usize, 2, 5, 8, 10, 12, 15, 20] {
        let enc = FrequencyEncoding::new(3, l).unwrap();
        for (series, x) in [
            ("f32, exact reduction", &x32),
            ("f64, exact reduction", &x64),
        ] {
            let out = enc.forward(x).unwrap();
            let seconds = median_seconds(reps, || drop(enc.forward(x).unwrap()));
            rows.push(Row {
                series: series.into(),
                knob: l as f64,
                error: max_err(&v64(&out), &xs, l),
                seconds,
                work: n as f64,
            });
        }
        // The naive layout interleaves per frequency like the crate's, so it compares directly.
        let out = naive(&x32, l);
        let seconds = median_seconds(reps, || drop(naive(&x32, l)));
        rows.push(Row {
            series: "f32, naive sin(f32(2ᵏπ)·x)".into(),
            knob: l as f64,
            error: max_err(&v64(&out), &xs, l),
            seconds,
            work: n as f64,
        });
    }
    vec![Table {
        title: "Positional encoding error vs frequencies".into(),
        description: format!(
            "NeRF frequency encoding [x, sin(2ᵏπx), cos(2ᵏπx)]ₖ<L of {n} points uniform in [−π, π]³ (f32 values); error = max |γ(x) − γ_f64(x)| against an f64 evaluation of the same inputs; time = median of {reps} calls of `FrequencyEncoding::forward` on CPU. The naive series rounds 2ᵏπ·x in f32 before sin. The f64 rows are limited by the reference itself, which rounds 2ᵏπ·x in f64 (≈ 2ᵏ·1e-15)."
        ),
        knob: "L".into(),
        error_name: "max abs error".into(),
        work_unit: "points".into(),
        time_name: TIME_PER_CALL.into(),
        rows,
    }]
}
