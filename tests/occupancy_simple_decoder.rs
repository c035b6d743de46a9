//! `occupancy::SimpleDecoder` (ONet's simple decoder): forward-mode spatial gradients against
//! finite differences, gradients to the code, batch independence, argument errors.
#![cfg(feature = "occupancy")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
use common::{central_diff, reseed, v64};
use neural_fields::field::{ConditionalField, Conditioned, ImplicitSurface};
use neural_fields::nn::build_seeded;
use neural_fields::occupancy::{simple_decoder, SimpleDecoderConfig};
use neural_fields::rng::SplitMix64;
use proptest::prelude::*;

fn config() -> SimpleDecoderConfig {
    SimpleDecoderConfig {
        hidden: 12,
        blocks: 3,
        code_dim: 5,
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// ∇ₚf by forward mode equals Richardson central differences, with every weight
    /// (including the zero-initialised residual layers) re-seeded to non-zero values.
    #[test]
    fn spatial_gradient_matches_finite_differences(seed in any::<u64>()) {
        let varmap = VarMap::new();
        let dec = build_seeded(&varmap, DType::F64, &Device::Cpu, seed, |vb| simple_decoder(&config(), vb)).unwrap();
        reseed(&varmap, seed ^ 1, 1.0);
        let mut rng = SplitMix64::new(seed ^ 2);
        let p = rng.uniform_tensor(&[4, 3], -0.5, 0.5, DType::F64, &Device::Cpu).unwrap();
        let c = rng.uniform_tensor(&[4, 5], -1.0, 1.0, DType::F64, &Device::Cpu).unwrap();
        let (v, g) = dec.value_and_grad_with_code(&p, &c).unwrap();
        prop_assert_eq!(v64(&v), v64(&dec.logits(&p, &c).unwrap()));
        let (pv, cv, g) = (v64(&p), v64(&c), v64(&g));
        for n in 0..4 {
            let gnorm = (0..3).map(|j| g[3 * n + j].powi(2)).sum::<f64>().sqrt();
            for j in 0..3 {
                let mut f = |x: f64| {
                    let mut q = pv[3 * n..3 * n + 3].to_vec();
                    q[j] = x;
                    let pt = Tensor::from_vec(q, (1, 3), &Device::Cpu).unwrap();
                    let ct = Tensor::from_vec(cv[5 * n..5 * n + 5].to_vec(), (1, 5), &Device::Cpu).unwrap();
                    v64(&dec.logits(&pt, &ct).unwrap())[0]
                };
                if let Some(fd) = central_diff(&mut f, pv[3 * n + j], 1e-5, gnorm + 1e-3) {
                    prop_assert!((g[3 * n + j] - fd).abs() <= 1e-6 * gnorm + 1e-9, "point {} axis {}: {} vs {}", n, j, g[3 * n + j], fd);
                }
            }
        }
    }
}

#[test]
fn values_train_the_code_normals_train_the_weights_and_points_are_batch_independent() {
    let varmap = VarMap::new();
    let dec = build_seeded(&varmap, DType::F64, &Device::Cpu, 7, |vb| {
        simple_decoder(&config(), vb)
    })
    .unwrap();
    reseed(&varmap, 8, 1.0);
    let code = Var::new(&[0.1f64, -0.2, 0.3, 0.4, -0.5], &Device::Cpu).unwrap();
    let bound = Conditioned::new(&dec, code.as_tensor().clone()).unwrap();
    let mut rng = SplitMix64::new(3);
    let p = rng
        .uniform_tensor(&[200, 3], -0.5, 0.5, DType::F64, &Device::Cpu)
        .unwrap();
    // A loss on the values trains the code.
    let g = bound
        .value(&p)
        .unwrap()
        .sqr()
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let gc = v64(g.get(&code).expect("the values depend on the code"));
    assert!(gc.iter().all(|v| v.is_finite()) && gc.iter().any(|v| *v != 0.0));
    // A loss on the normals trains the weights; with ReLU and an additive code the
    // normal is piecewise constant in the code, so the code gets no gradient from it.
    let (_, n) = bound.value_and_grad(&p).unwrap();
    let g = n.sqr().unwrap().sum_all().unwrap().backward().unwrap();
    let w = varmap.data().lock().unwrap()["fc_p.weight"].clone();
    let gw = v64(g.get(&w).expect("the normals depend on the first layer"));
    assert!(gw.iter().all(|v| v.is_finite()) && gw.iter().any(|v| *v != 0.0));
    let all = v64(&bound.value(&p).unwrap());
    let one = v64(&bound.value(&p.narrow(0, 17, 1).unwrap()).unwrap());
    assert!(
        (all[17] - one[0]).abs() <= 1e-12 * (1.0 + one[0].abs()),
        "{} vs {}",
        all[17],
        one[0]
    );
}

#[test]
fn residual_blocks_start_as_identity_and_errors_name_the_argument() {
    let varmap = VarMap::new();
    let dec = build_seeded(&varmap, DType::F32, &Device::Cpu, 1, |vb| {
        simple_decoder(&config(), vb)
    })
    .unwrap();
    let w = v64(varmap.data().lock().unwrap()["block0.fc_1.weight"].as_tensor());
    assert!(w.iter().all(|v| *v == 0.0), "fc_1 is zero-initialised");
    let p = Tensor::zeros((2, 3), DType::F32, &Device::Cpu).unwrap();
    let e = dec
        .logits(
            &p,
            &Tensor::zeros((2, 4), DType::F32, &Device::Cpu).unwrap(),
        )
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("codes: expected shape [2, 5]"), "{e}");
    let e = dec
        .logits(
            &Tensor::zeros((2, 2), DType::F32, &Device::Cpu).unwrap(),
            &Tensor::zeros((2, 5), DType::F32, &Device::Cpu).unwrap(),
        )
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("points: expected shape [N, 3]"), "{e}");
    let e = simple_decoder(
        &SimpleDecoderConfig {
            blocks: 0,
            ..config()
        },
        candle_nn::VarBuilder::zeros(DType::F32, &Device::Cpu),
    )
    .unwrap_err();
    assert!(e.to_string().starts_with("config.blocks"), "{e}");
}
