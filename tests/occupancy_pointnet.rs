//! `occupancy::PointNetEncoder`: order invariance, shapes, argument errors, and one variational
//! ONet step (encoder → reparameterise → decoder → BCE + KL) whose gradients reach the
//! encoder and are finite.
#![cfg(feature = "occupancy")]

mod common;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use common::v64;
use neural_fields::field::ConditionalField;
use neural_fields::nn::{build_seeded, mlp, MlpConfig};
use neural_fields::occupancy::{kl_standard_normal, reconstruction_loss, reparameterize};
use neural_fields::occupancy::{pointnet_encoder, PointNetConfig};
use neural_fields::rng::SplitMix64;

fn config() -> PointNetConfig {
    PointNetConfig {
        hidden: 16,
        layers: 2,
        latent_dim: 4,
        point_features: 1,
    }
}

#[test]
fn code_does_not_depend_on_point_order() {
    let varmap = VarMap::new();
    let enc = build_seeded(&varmap, DType::F64, &Device::Cpu, 3, |vb| {
        pointnet_encoder(&config(), vb)
    })
    .unwrap();
    let mut rng = SplitMix64::new(1);
    let points = rng
        .uniform_tensor(&[2, 50, 3], -0.5, 0.5, DType::F64, &Device::Cpu)
        .unwrap();
    let occ = points
        .narrow(2, 0, 1)
        .unwrap()
        .squeeze(2)
        .unwrap()
        .gt(0.0)
        .unwrap()
        .to_dtype(DType::F64)
        .unwrap();
    let perm: Vec<u32> = (0..50u32).rev().collect();
    let idx = Tensor::new(perm.as_slice(), &Device::Cpu).unwrap();
    let (m1, l1) = enc.forward(&points, &occ).unwrap();
    let (m2, l2) = enc
        .forward(
            &points.index_select(&idx, 1).unwrap(),
            &occ.index_select(&idx, 1).unwrap(),
        )
        .unwrap();
    assert_eq!(m1.dims(), &[2, 4]);
    assert_eq!(l1.dims(), &[2, 4]);
    for (a, b) in v64(&m1)
        .iter()
        .zip(v64(&m2))
        .chain(v64(&l1).iter().zip(v64(&l2)))
    {
        assert!((a - b).abs() <= 1e-12 * (1.0 + a.abs()), "{a} vs {b}");
    }
    // Different shapes get different codes.
    let m = v64(&m1);
    assert!(m[..4] != m[4..]);
}

#[test]
fn variational_step_reaches_the_encoder_with_finite_gradients() {
    let d = Device::Cpu;
    let varmap = VarMap::new();
    let enc = build_seeded(&varmap, DType::F32, &d, 4, |vb| {
        pointnet_encoder(&config(), vb.pp("enc"))
    })
    .unwrap();
    let dec_config = MlpConfig {
        code_dim: 4,
        hidden: 16,
        depth: 2,
        ..MlpConfig::default()
    };
    let dec = build_seeded(&varmap, DType::F32, &d, 5, |vb| {
        mlp(&dec_config, vb.pp("dec"))
    })
    .unwrap();
    let mut rng = SplitMix64::new(2);
    let (b, k) = (3usize, 64usize);
    let points = rng
        .uniform_tensor(&[b, k, 3], -0.55, 0.55, DType::F32, &d)
        .unwrap();
    let occ = points
        .sqr()
        .unwrap()
        .sum(2)
        .unwrap()
        .lt(0.16)
        .unwrap()
        .to_dtype(DType::F32)
        .unwrap();
    let (mean, logvar) = enc.forward(&points, &occ).unwrap();
    let z = reparameterize(&mean, &logvar, 9).unwrap(); // [B, D]
    let codes = z
        .unsqueeze(1)
        .unwrap()
        .broadcast_as((b, k, 4))
        .unwrap()
        .reshape((b * k, 4))
        .unwrap();
    let logits = dec
        .forward_with_code(&points.reshape((b * k, 3)).unwrap(), &codes)
        .unwrap()
        .reshape((b, k))
        .unwrap();
    let loss = (reconstruction_loss(&logits, &occ).unwrap()
        + kl_standard_normal(&mean, &logvar)
            .unwrap()
            .mean_all()
            .unwrap())
    .unwrap();
    assert!(v64(&loss)[0].is_finite());
    let grads = loss.backward().unwrap();
    let data = varmap.data().lock().unwrap();
    let w = &data["enc.layer0.weight"];
    let g = v64(grads
        .get(w)
        .expect("the encoder's first layer receives a gradient"));
    assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|v| *v != 0.0));
}

#[test]
fn bad_inputs_name_the_argument() {
    let enc = pointnet_encoder(
        &config(),
        candle_nn::VarBuilder::zeros(DType::F32, &Device::Cpu),
    )
    .unwrap();
    let p = Tensor::zeros((2, 5, 3), DType::F32, &Device::Cpu).unwrap();
    let o = Tensor::zeros((2, 5), DType::F32, &Device::Cpu).unwrap();
    let cases = [
        (
            enc.forward(
                &Tensor::zeros((2, 5, 2), DType::F32, &Device::Cpu).unwrap(),
                &o,
            ),
            "points: expected shape [B, K, 3]",
        ),
        (
            enc.forward(
                &Tensor::zeros((2, 0, 3), DType::F32, &Device::Cpu).unwrap(),
                &o,
            ),
            "points: expected at least one point",
        ),
        (
            enc.forward(
                &p,
                &Tensor::zeros((2, 4), DType::F32, &Device::Cpu).unwrap(),
            ),
            "features: expected shape [2, 5]",
        ),
        (
            enc.forward(
                &p,
                &Tensor::zeros((2, 5), DType::F64, &Device::Cpu).unwrap(),
            ),
            "features: expected dtype F32",
        ),
    ];
    for (r, msg) in cases {
        let e = r.unwrap_err().to_string();
        assert!(e.starts_with(msg), "{e}");
    }
    let bad = PointNetConfig {
        layers: 0,
        ..config()
    };
    let e =
        pointnet_encoder(&bad, candle_nn::VarBuilder::zeros(DType::F32, &Device::Cpu)).unwrap_err();
    assert!(e.to_string().starts_with("config.layers"), "{e}");
}
