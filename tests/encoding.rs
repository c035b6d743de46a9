//! Encodings: accuracy against f64 references in f32, range-reduced sin/cos for huge
//! arguments, forward-mode JVPs against finite differences, IPE limits, validation.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::{central_diff, uniform, v64};
use neural_fields::encoding::{integrated_pe, Encoding, FourierFeatures, FrequencyEncoding};
use neural_fields::numerics::safe_sin_cos;
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;
use std::f64::consts::PI;

/// f64 reference of the π-frequency encoding of one f32 coordinate row.
fn reference(x: &[f64], l: usize) -> Vec<f64> {
    let mut out = x.to_vec();
    for k in 0..l {
        let w = (k as f64).exp2() * PI;
        out.extend(x.iter().map(|v| (w * v).sin()));
        out.extend(x.iter().map(|v| (w * v).cos()));
    }
    out
}

fn max_error_f32(l: usize) -> f64 {
    let mut rng = SplitMix64::new(l as u64);
    let x = uniform(&mut rng, 2000, 3, -PI, PI, DType::F32);
    let xs = v64(&x); // the exact f32 values
    let enc = v64(&FrequencyEncoding::new(3, l).unwrap().forward(&x).unwrap());
    let width = 3 * (2 * l + 1);
    let mut worst: f64 = 0.0;
    for n in 0..2000 {
        let r = reference(&xs[3 * n..3 * n + 3], l);
        for (a, b) in enc[width * n..width * (n + 1)].iter().zip(r) {
            worst = worst.max((a - b).abs());
        }
    }
    worst
}

#[test]
fn f32_frequency_encoding_matches_f64_reference() {
    let e5 = max_error_f32(5);
    let e10 = max_error_f32(10);
    let e16 = max_error_f32(16);
    println!("f32 positional encoding max error on |x| ≤ π: L=5 {e5:.2e}, L=10 {e10:.2e}, L=16 {e16:.2e}");
    assert!(e5 <= 1e-5, "L = 5: {e5}");
    assert!(e10 <= 1e-4, "L = 10: {e10}");
    // Exact reduction keeps even L = 16 (arguments up to 2¹⁵π²) at rounding level.
    assert!(e16 <= 1e-4, "L = 16: {e16}");
}

#[test]
fn safe_sin_cos_are_finite_and_accurate_up_to_1e10_in_f32_and_f64() {
    let mut rng = SplitMix64::new(9);
    let mut xs: Vec<f64> = (0..4000)
        .map(|_| {
            let mag = 10f64.powf(rng.uniform() * 10.0);
            if rng.uniform() < 0.5 {
                -mag
            } else {
                mag
            }
        })
        .collect();
    xs.extend([0.0, 1e10, -1e10, 2f64.powi(33), PI * 1e9]);
    for dtype in [DType::F32, DType::F64] {
        let t = Tensor::new(xs.as_slice(), &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let exact = v64(&t); // the values as represented in this dtype
        let (s, c) = safe_sin_cos(&t).unwrap();
        let (s, c) = (v64(&s), v64(&c));
        let mut worst: f64 = 0.0;
        for i in 0..exact.len() {
            assert!(s[i].is_finite() && c[i].is_finite());
            worst = worst
                .max((s[i] - exact[i].sin()).abs())
                .max((c[i] - exact[i].cos()).abs());
        }
        println!("{dtype:?}: safe sin/cos max error for |x| ≤ 1e10: {worst:.2e}");
        assert!(worst <= 1e-4, "{dtype:?}: {worst}");
    }
}

fn jvp_check(enc: &dyn Encoding, seed: u64) -> Result<(), TestCaseError> {
    let mut rng = SplitMix64::new(seed);
    let d = enc.in_dim();
    let x = uniform(&mut rng, 3, d, -1.0, 1.0, DType::F64);
    let dx = rng
        .uniform_tensor(&[3, 2, d], -1.0, 1.0, DType::F64, &Device::Cpu)
        .unwrap();
    let (value, tangent) = enc.forward_jvp(&x, &dx).unwrap();
    prop_assert_eq!(v64(&value), v64(&enc.forward(&x).unwrap()));
    let (xs, dxs, t) = (v64(&x), v64(&dx), v64(&tangent));
    let e = enc.out_dim();
    for n in 0..3 {
        for k in 0..2 {
            for col in 0..e {
                // Directional derivative along dx[n, k].
                let mut f = |s: f64| {
                    let row: Vec<f64> = (0..d)
                        .map(|j| xs[n * d + j] + s * dxs[(n * 2 + k) * d + j])
                        .collect();
                    v64(&enc
                        .forward(&Tensor::from_vec(row, (1, d), &Device::Cpu).unwrap())
                        .unwrap())[col]
                };
                if let Some(fd) = central_diff(&mut f, 0.0, 1e-5, 1.0) {
                    let a = t[(n * 2 + k) * e + col];
                    prop_assert!(
                        (a - fd).abs() < 1e-6 * (1.0 + a.abs()),
                        "col {}: {} vs {}",
                        col,
                        a,
                        fd
                    );
                }
            }
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(16))]

    #[test]
    fn frequency_jvp_matches_finite_differences(seed in any::<u64>(), l in 0usize..6, pi in any::<bool>(), input in any::<bool>()) {
        let mut enc = FrequencyEncoding::new(3, l).unwrap();
        enc.use_pi = pi;
        enc.include_input = input;
        jvp_check(&enc, seed)?;
    }

    #[test]
    fn fourier_jvp_matches_finite_differences(seed in any::<u64>(), scale in 0.1f64..10.0) {
        let enc = FourierFeatures::new(3, 16, scale, seed, &Device::Cpu, DType::F64).unwrap();
        jvp_check(&enc, seed)?;
    }
}

#[test]
fn layouts_and_dimensions() {
    let x = Tensor::new(&[[0.25f64, 0.5, -0.5]], &Device::Cpu).unwrap();
    let enc = FrequencyEncoding::new(3, 2).unwrap();
    assert_eq!(enc.out_dim(), 15);
    let v = v64(&enc.forward(&x).unwrap());
    // [x, sin(πx), cos(πx), sin(2πx), cos(2πx)]
    let expected = reference(&[0.25, 0.5, -0.5], 2);
    for (a, b) in v.iter().zip(&expected) {
        assert!((a - b).abs() < 1e-15);
    }
    let mut no_pi = FrequencyEncoding::new(3, 2).unwrap();
    no_pi.use_pi = false;
    no_pi.include_input = false;
    assert_eq!(no_pi.out_dim(), 12);
    assert!((v64(&no_pi.forward(&x).unwrap())[0] - 0.25f64.sin()).abs() < 1e-15);
    let ff = FourierFeatures::new(3, 256, 10.0, 1, &Device::Cpu, DType::F32).unwrap();
    assert_eq!(ff.out_dim(), 512);
    let again = FourierFeatures::new(3, 256, 10.0, 1, &Device::Cpu, DType::F32).unwrap();
    assert_eq!(
        v64(&ff.forward(&x).unwrap()),
        v64(&again.forward(&x).unwrap()),
        "seeded"
    );
}

#[test]
fn integrated_pe_reduces_to_pe_and_damps_high_frequencies() {
    let mu = Tensor::new(&[[0.3f64, -0.7, 1.1]], &Device::Cpu).unwrap();
    let zero = mu.zeros_like().unwrap();
    let ipe = v64(&integrated_pe(&mu, &zero, 0, 4).unwrap());
    let mut pe = FrequencyEncoding::new(3, 4).unwrap();
    pe.use_pi = false;
    pe.include_input = false;
    let pe = v64(&pe.forward(&mu).unwrap());
    for (a, b) in ipe.iter().zip(&pe) {
        assert!((a - b).abs() < 1e-15);
    }
    let wide = (zero.ones_like().unwrap() * 1.0).unwrap();
    let damped = v64(&integrated_pe(&mu, &wide, 0, 8).unwrap());
    // Frequency 2⁷ with variance 1: e^{−4⁷/2} underflows to exactly 0, finitely.
    assert!(damped[damped.len() - 1].abs() == 0.0 && damped.iter().all(|v| v.is_finite()));
    let e = integrated_pe(&mu, &zero, 5, 4).unwrap_err().to_string();
    assert!(e.starts_with("min_deg, max_deg"), "{e}");
}

#[test]
fn bad_inputs_name_the_argument() {
    let enc = FrequencyEncoding::new(3, 4).unwrap();
    let e = enc
        .forward(&Tensor::zeros((2, 2), DType::F32, &Device::Cpu).unwrap())
        .unwrap_err();
    assert!(e.to_string().starts_with("x: expected shape [N, 3]"), "{e}");
    let x = Tensor::zeros((2, 3), DType::F32, &Device::Cpu).unwrap();
    let e = enc
        .forward_jvp(
            &x,
            &Tensor::zeros((3, 1, 3), DType::F32, &Device::Cpu).unwrap(),
        )
        .unwrap_err();
    assert!(e.to_string().starts_with("dx: expected 2 rows"), "{e}");
    let e = enc
        .forward_jvp(
            &x,
            &Tensor::zeros((2, 1, 3), DType::F64, &Device::Cpu).unwrap(),
        )
        .unwrap_err();
    assert!(e.to_string().starts_with("dx: expected dtype F32"), "{e}");
    assert!(FrequencyEncoding::new(0, 4)
        .unwrap_err()
        .to_string()
        .starts_with("in_dim"));
    assert!(FrequencyEncoding::new(3, 61)
        .unwrap_err()
        .to_string()
        .starts_with("n_freqs"));
    assert!(
        FourierFeatures::new(3, 4, -1.0, 0, &Device::Cpu, DType::F32)
            .unwrap_err()
            .to_string()
            .starts_with("scale")
    );
    let mu = Tensor::zeros((2, 3), DType::F32, &Device::Cpu).unwrap();
    let e = integrated_pe(
        &mu,
        &Tensor::zeros((2, 2), DType::F32, &Device::Cpu).unwrap(),
        0,
        4,
    )
    .unwrap_err();
    assert!(e.to_string().starts_with("variances"), "{e}");
}

/// Inputs from tiny to huge (the exact reduction's regime), both signs: `[14, 3]`.
fn wide_inputs(dtype: DType) -> Tensor {
    let mut v = Vec::new();
    for (i, m) in [1e-7, 1e-3, 0.3, 1.0, 7.5, 1e3, 1e6].iter().enumerate() {
        for j in 0..6 {
            let s = if (i + j) % 2 == 0 { 1.0 } else { -1.0 };
            v.push(s * m * (1.0 + 0.137 * j as f64));
        }
    }
    Tensor::from_vec(v, (14, 3), &Device::Cpu)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

/// `sin(π·2ᵏx)`, `cos(π·2ᵏx)` in f64 with the exact reduction, for an `x` held exactly.
fn exact_sin_cos(x: f64, k: usize) -> (f64, f64) {
    let y = x * (k as f64).exp2();
    let r = y - 2.0 * (0.5 * y).round();
    ((PI * r).sin(), (PI * r).cos())
}

/// The frequency encoding's CPU op (what `forward` runs) against closed forms in f64 —
/// value to 1e-12 (f64) or f32 rounding (f32) up to `x = 10⁶` at L = 10 — and its
/// backward pass against the candle-ops tangents of `forward_jvp`.
#[test]
fn fused_frequency_encoding_matches_closed_forms_and_the_jvp_path() {
    for (dtype, tol) in [(DType::F64, 1e-12), (DType::F32, 2e-7)] {
        for include_input in [true, false] {
            let mut pe = FrequencyEncoding::new(3, 10).unwrap();
            pe.include_input = include_input;
            let x = Var::from_tensor(&wide_inputs(dtype)).unwrap();
            let xs = v64(x.as_tensor());
            let y = pe.forward(x.as_tensor()).unwrap();
            let (n, e) = y.dims2().unwrap();
            let yv = v64(&y);
            let head = if include_input { 3 } else { 0 };
            for p in 0..n {
                for k in 0..10 {
                    for d in 0..3 {
                        let (s, c) = exact_sin_cos(xs[3 * p + d], k);
                        let base = p * e + head + 6 * k;
                        assert!(
                            (yv[base + d] - s).abs() <= tol,
                            "{dtype:?} sin {} vs {s}",
                            yv[base + d]
                        );
                        assert!(
                            (yv[base + 3 + d] - c).abs() <= tol,
                            "{dtype:?} cos {} vs {c}",
                            yv[base + 3 + d]
                        );
                    }
                }
            }
            // ∂/∂x_j Σ γ(x) ⊙ c = Σ_cols c · (J e_j), the tangents from candle ops.
            let cw: Vec<f64> = (0..n * e)
                .map(|i| ((i * 7919) % 101) as f64 / 50.0 - 1.0)
                .collect();
            let c = Tensor::from_vec(cw.clone(), (n, e), &Device::Cpu)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let g = v64((&y * &c)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap()
                .get(x.as_tensor())
                .unwrap());
            let eye = Tensor::eye(3, dtype, &Device::Cpu)
                .unwrap()
                .unsqueeze(0)
                .unwrap()
                .broadcast_as((n, 3, 3))
                .unwrap()
                .contiguous()
                .unwrap();
            let (_, t) = pe.forward_jvp(x.as_tensor(), &eye).unwrap();
            let t = v64(&t);
            for p in 0..n {
                for j in 0..3 {
                    let want: f64 = (0..e)
                        .map(|col| cw[p * e + col] * t[(p * 3 + j) * e + col])
                        .sum();
                    let got = g[3 * p + j];
                    // The gradient scales with π2⁹ ≈ 1.6e3.
                    assert!(
                        (got - want).abs() <= 2e3 * tol.max(1e-9) * want.abs().max(1.0),
                        "{dtype:?} gradient {got} vs {want}"
                    );
                }
            }
        }
    }
}

#[test]
fn fused_frequency_encoding_keeps_nan_empty_batches_and_zero_frequencies() {
    let pe = FrequencyEncoding::new(3, 2).unwrap();
    let x = Tensor::new(&[[f32::NAN, 0.0, 1.0]], &Device::Cpu).unwrap();
    let y = v64(&pe.forward(&x).unwrap());
    assert!(y[0].is_nan() && y[1] == 0.0);
    let empty = Tensor::zeros((0, 3), DType::F32, &Device::Cpu).unwrap();
    assert_eq!(pe.forward(&empty).unwrap().dims(), &[0, 15]);
    // Zero frequencies: a zero-sized chunk once panicked inside candle's pool.
    let pe = FrequencyEncoding::new(3, 0).unwrap();
    let x = Var::from_tensor(&wide_inputs(DType::F64)).unwrap();
    let y = pe.forward(x.as_tensor()).unwrap();
    assert_eq!(v64(&y), v64(x.as_tensor()));
    let g = y.sum_all().unwrap().backward().unwrap();
    assert!(v64(g.get(x.as_tensor()).unwrap()).iter().all(|&v| v == 1.0));
}

/// The fused op's backward pass against central differences of its forward (f64).
#[test]
fn fused_frequency_gradient_matches_finite_differences() {
    let pe = FrequencyEncoding::new(2, 4).unwrap();
    let base = [0.31f64, -0.77, 2.5, 1e-4];
    let weight = |j: usize| ((j * 7919) % 101) as f64 / 50.0 - 1.0;
    let loss = |v: &[f64]| -> f64 {
        let x = Tensor::from_vec(v.to_vec(), (2, 2), &Device::Cpu).unwrap();
        let y = v64(&pe.forward(&x).unwrap());
        y.iter().enumerate().map(|(j, y)| y * weight(j)).sum()
    };
    let x =
        Var::from_tensor(&Tensor::from_vec(base.to_vec(), (2, 2), &Device::Cpu).unwrap()).unwrap();
    let y = pe.forward(x.as_tensor()).unwrap();
    let w: Vec<f64> = (0..y.elem_count()).map(weight).collect();
    let c = Tensor::from_vec(w, y.shape(), &Device::Cpu).unwrap();
    let g = v64((&y * c)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap()
        .get(x.as_tensor())
        .unwrap());
    for i in 0..4 {
        let mut f = |h: f64| {
            let mut v = base.to_vec();
            v[i] = h;
            loss(&v)
        };
        let fd = central_diff(&mut f, base[i], 1e-6, 1.0).expect("smooth");
        assert!(
            (fd - g[i]).abs() <= 1e-6 * fd.abs().max(1.0),
            "{i}: fd {fd} vs {}",
            g[i]
        );
    }
}
