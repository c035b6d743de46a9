//! BARF's coarse-to-fine window: the band weights' closed forms, the windowed encodings
//! against the plain ones (frequency encoding and hash grid, f32 and f64), tangents and
//! position gradients against finite differences in f64, clones sharing the window, a
//! network built on a windowed encoding, and the inputs it refuses.

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use neural_fields::encoding::{
    hash_grid, CoarseToFine, Encoding, FourierFeatures, FrequencyEncoding, HashGridConfig,
    PointEncoding,
};
use neural_fields::field::ImplicitSurface;
use neural_fields::nn::{mlp, MlpConfig};
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;

const DTYPES: [DType; 2] = [DType::F32, DType::F64];

fn points(seed: u64, n: usize, dtype: DType) -> Tensor {
    SplitMix64::new(seed)
        .uniform_tensor(&[n, 3], -1.0, 1.0, dtype, &Device::Cpu)
        .unwrap()
}

fn rows(t: &Tensor) -> Vec<Vec<f64>> {
    t.to_dtype(DType::F64).unwrap().to_vec2::<f64>().unwrap()
}

fn frequency(l: usize) -> CoarseToFine {
    CoarseToFine::new(PointEncoding::Frequency(
        FrequencyEncoding::new(3, l).unwrap(),
    ))
    .unwrap()
}

/// BARF's band weight `w_k(α) = (1 − cos(π·clamp(α − k, 0, 1)))/2` (its closed forms are
/// tested beside the window, in `src/encoding/coarse_to_fine.rs`).
fn band_weight(alpha: f64, k: usize) -> f64 {
    let u = (alpha - k as f64).clamp(0.0, 1.0);
    0.5 * (1.0 - (std::f64::consts::PI * u).cos())
}

#[test]
fn a_refused_alpha_leaves_the_window_where_it_was() {
    let x = points(5, 7, DType::F64);
    let c = frequency(3);
    let before = rows(&c.forward(&x).unwrap());
    let e = c.set_alpha(f64::NAN).unwrap_err();
    assert!(e.to_string().contains("alpha"), "{e}");
    assert_eq!(
        rows(&c.forward(&x).unwrap()),
        before,
        "a refused α leaves the window where it was"
    );
}

#[test]
fn encodings_without_ordered_bands_are_refused_naming_inner() {
    let ff = FourierFeatures::new(3, 4, 1.0, 0, &Device::Cpu, DType::F32).unwrap();
    let windowed = PointEncoding::CoarseToFine(frequency(2));
    for inner in [
        PointEncoding::Identity,
        PointEncoding::Fourier(ff),
        windowed,
    ] {
        let e = CoarseToFine::new(inner).unwrap_err();
        assert!(e.to_string().contains("inner"), "{e}");
    }
}

#[test]
fn frequency_window_scales_each_band_and_keeps_the_input() {
    for dtype in DTYPES {
        let x = points(1, 17, dtype);
        let plain = FrequencyEncoding::new(3, 4).unwrap();
        let y = rows(&plain.forward(&x).unwrap());
        let c = frequency(4);
        let enc = PointEncoding::CoarseToFine(c.clone());
        for alpha in [0.0, 0.3, 1.5, 2.0, 3.99] {
            c.set_alpha(alpha).unwrap();
            let w: Vec<f64> = (0..4).map(|k| band_weight(alpha, k)).collect();
            let got = rows(&enc.forward(&x).unwrap());
            for (gr, yr) in got.iter().zip(&y) {
                for (col, (g, v)) in gr.iter().zip(yr).enumerate() {
                    // Columns: 3 inputs, then per band 3 sines and 3 cosines.
                    let weight = if col < 3 { 1.0 } else { w[(col - 3) / 6] };
                    let tol = if dtype == DType::F32 { 1e-6 } else { 1e-14 };
                    assert!(
                        (g - v * weight).abs() <= tol,
                        "{dtype:?} α {alpha} col {col}"
                    );
                }
            }
        }
        // At α = L the plain encoding, bit for bit.
        c.set_alpha(4.0).unwrap();
        assert_eq!(rows(&enc.forward(&x).unwrap()), y);
    }
}

#[test]
fn hash_window_keeps_the_coarsest_level() {
    for dtype in DTYPES {
        let varmap = VarMap::new();
        let config = HashGridConfig {
            levels: 4,
            features: 2,
            log2_table_size: 10,
            base_resolution: 2.0,
            finest_resolution: 16.0,
            ..HashGridConfig::default()
        };
        let g = hash_grid(
            &config,
            VarBuilder::from_varmap(&varmap, dtype, &Device::Cpu),
        )
        .unwrap();
        let x = points(2, 9, dtype);
        let y = rows(&g.forward(&x).unwrap());
        let c = CoarseToFine::new(PointEncoding::HashGrid(g)).unwrap();
        assert_eq!(c.bands(), 3);
        c.set_alpha(1.5).unwrap();
        let got = rows(&c.forward(&x).unwrap());
        let level_weight = [1.0, 1.0, 0.5, 0.0];
        for (gr, yr) in got.iter().zip(&y) {
            for (col, (g, v)) in gr.iter().zip(yr).enumerate() {
                let expected = v * level_weight[col / 2];
                assert!(
                    (g - expected).abs() <= 1e-7 * v.abs().max(1e-30),
                    "{dtype:?} col {col}"
                );
            }
        }
    }
}

#[test]
fn clones_share_the_window() {
    let x = points(6, 5, DType::F64);
    let c = frequency(3);
    let in_config = PointEncoding::CoarseToFine(c.clone());
    let closed = rows(&c.forward(&x).unwrap());
    c.set_alpha(1.25).unwrap();
    let opened = rows(&c.forward(&x).unwrap());
    assert_ne!(opened, closed);
    match in_config {
        PointEncoding::CoarseToFine(inner) => {
            assert_eq!(rows(&inner.forward(&x).unwrap()), opened)
        }
        _ => unreachable!(),
    }
}

/// A network on a windowed encoding: its value follows the window, and its normals
/// (forward-mode tangents through the window) are finite and match the central
/// differences of its value in f64.
#[test]
fn an_mlp_on_a_windowed_encoding_follows_the_window() {
    let c = frequency(6);
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F64, &Device::Cpu);
    let config = MlpConfig {
        hidden: 32,
        depth: 2,
        encoding: PointEncoding::CoarseToFine(c.clone()),
        ..MlpConfig::sdf(0.5)
    };
    let net = mlp(&config, vb).unwrap();
    let x = points(3, 8, DType::F64);
    c.set_alpha(0.0).unwrap();
    let v0 = rows(&net.value(&x).unwrap().unsqueeze(1).unwrap());
    c.set_alpha(6.0).unwrap();
    let v1 = rows(&net.value(&x).unwrap().unsqueeze(1).unwrap());
    c.set_alpha(2.7).unwrap();
    let (_, grad) = net.value_and_grad(&x).unwrap();
    let grad = rows(&grad);
    let h = 1e-6;
    let xs = rows(&x);
    for (i, p) in xs.iter().enumerate() {
        for d in 0..3 {
            let shifted = |s: f64| {
                let mut q = p.clone();
                q[d] += s;
                let t = Tensor::new(&[[q[0], q[1], q[2]]], &Device::Cpu).unwrap();
                rows(&net.value(&t).unwrap().unsqueeze(1).unwrap())[0][0]
            };
            let fd = (shifted(h) - shifted(-h)) / (2.0 * h);
            assert!(
                (fd - grad[i][d]).abs() <= 1e-6 * (1.0 + fd.abs()),
                "point {i} axis {d}: {fd} vs {}",
                grad[i][d]
            );
        }
    }
    // With every band but the input held back, the geometric initialisation's sphere
    // is still there, so both values are finite and they differ only through the bands.
    assert!(v0
        .iter()
        .flatten()
        .chain(v1.iter().flatten())
        .all(|v| v.is_finite()));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// The windowed encoding's position gradient (reverse mode through the window) and
    /// its tangents (forward mode) against central differences in f64, at any α and
    /// over coordinates up to ±1e3.
    #[test]
    fn gradients_match_finite_differences(
        seed in 0u64..1000,
        alpha in -1.0f64..6.0,
        scale in prop::sample::select(vec![1e-3, 1.0, 1e3]),
    ) {
        let c = frequency(5);
        c.set_alpha(alpha).unwrap();
        let enc = PointEncoding::CoarseToFine(c);
        let x0 = (points(seed, 4, DType::F64) * scale).unwrap();
        let mut rng = SplitMix64::new(seed + 7);
        let cot = rng.uniform_tensor(&[4, 33], -1.0, 1.0, DType::F64, &Device::Cpu).unwrap();
        let x = Var::from_tensor(&x0).unwrap();
        let loss = (enc.forward(&x).unwrap() * &cot).unwrap().sum_all().unwrap();
        let grad = rows(&loss.backward().unwrap().get(&x).unwrap().clone());
        let dx = rng.uniform_tensor(&[4, 1, 3], -1.0, 1.0, DType::F64, &Device::Cpu).unwrap();
        let (_, tangent) = enc.forward_jvp(&x0, &dx).unwrap();
        let tangent = rows(&tangent.squeeze(1).unwrap());
        // The encoding's largest frequency is 2⁴π ≈ 50 at any scale of x, so a fixed step
        // keeps the truncation error (h²·50³/6) and the rounding error (1e-16·|x|·50/h) of
        // the differences below 1e-5 for |x| up to 1e3.
        let h = 1e-6;
        let value = |t: &Tensor| (enc.forward(t).unwrap() * &cot).unwrap().sum_all().unwrap().to_scalar::<f64>().unwrap();
        let xs = rows(&x0);
        for i in 0..4 {
            for d in 0..3 {
                let mut plus = xs.clone();
                let mut minus = xs.clone();
                plus[i][d] += h;
                minus[i][d] -= h;
                let fd = (value(&Tensor::new(plus, &Device::Cpu).unwrap()) - value(&Tensor::new(minus, &Device::Cpu).unwrap())) / (2.0 * h);
                prop_assert!((fd - grad[i][d]).abs() <= 1e-5 * (1.0 + fd.abs()), "grad {i},{d}: {fd} vs {}", grad[i][d]);
            }
        }
        // Tangent = J·dx: compare with the directional difference of each column.
        let dxs = rows(&dx.squeeze(1).unwrap());
        let shifted = |s: f64| {
            let q: Vec<Vec<f64>> = xs.iter().zip(&dxs).map(|(p, v)| p.iter().zip(v).map(|(a, b)| a + s * b).collect()).collect();
            rows(&enc.forward(&Tensor::new(q, &Device::Cpu).unwrap()).unwrap())
        };
        let (p, m) = (shifted(h), shifted(-h));
        for i in 0..4 {
            for e in 0..33 {
                let fd = (p[i][e] - m[i][e]) / (2.0 * h);
                prop_assert!((fd - tangent[i][e]).abs() <= 1e-5 * (1.0 + fd.abs()), "tangent {i},{e}: {fd} vs {}", tangent[i][e]);
            }
        }
    }
}
