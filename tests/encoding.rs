//! Encodings: accuracy against f64 references in f32, range-reduced sin/cos for huge
//! arguments, forward-mode JVPs against finite differences, IPE limits, validation.

mod common;

use candle_core::{DType, Device, Tensor};
use common::{central_diff, uniform, v64};
use neural_fields::encoding::{integrated_pe, Encoding, FourierFeatures, FrequencyEncoding};
use neural_fields::numerics::{safe_cos, safe_sin};
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
        let (s, c) = (v64(&safe_sin(&t).unwrap()), v64(&safe_cos(&t).unwrap()));
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
    assert_eq!(v64(ff.matrix()), v64(again.matrix()), "seeded");
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
