//! Convolutional Occupancy Networks: shapes of the plane and grid variants, gradients
//! reaching every parameter, invariance of the encoder to the order of the input points,
//! and errors. (The crate-private 3-D convolution is tested against a direct sum in
//! `src/occupancy/conv_onet.rs`.)

mod common;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use common::v64;
use neural_fields::field::Field;
use neural_fields::mesh::{points_to_tensor, PointCloud};
use neural_fields::occupancy::reconstruction_loss;
use neural_fields::occupancy::{
    conv_onet_encoder, local_decoder, ConvOnetConfig, ConvOnetEncoder, FeatureLayout, LocalDecoder,
    LocalDecoderConfig, LocalFeatures, UnetConfig,
};
use neural_fields::rng::SplitMix64;

fn small(layout: FeatureLayout) -> ConvOnetConfig {
    ConvOnetConfig {
        layout,
        hidden: 8,
        blocks: 3,
        feature_dim: 6,
        unet: UnetConfig {
            depth: 2,
            start_filters: 4,
        },
        ..ConvOnetConfig::default()
    }
}

fn model(config: &ConvOnetConfig, dtype: DType) -> (VarMap, ConvOnetEncoder, LocalDecoder) {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, dtype, &Device::Cpu);
    let enc = conv_onet_encoder(config, vb.pp("enc")).unwrap();
    let dec = local_decoder(
        &LocalDecoderConfig {
            hidden: 8,
            blocks: 2,
            feature_dim: config.feature_dim,
            padding: config.padding,
        },
        vb.pp("dec"),
    )
    .unwrap();
    common::reseed(&varmap, 7, 1.0);
    (varmap, enc, dec)
}

fn cloud(seed: u64, b: usize, n: usize, dtype: DType) -> Tensor {
    SplitMix64::new(seed)
        .uniform_tensor(&[b, n, 3], -0.5, 0.5, dtype, &Device::Cpu)
        .unwrap()
}

#[test]
fn planes_and_grid_have_the_documented_shapes() {
    for (layout, dims) in [
        (FeatureLayout::Planes { resolution: 8 }, vec![2, 6, 8, 8]),
        (FeatureLayout::Grid { resolution: 4 }, vec![2, 6, 4, 4, 4]),
    ] {
        let (_, enc, dec) = model(&small(layout), DType::F32);
        let f = enc.forward(&cloud(1, 2, 50, DType::F32)).unwrap();
        match &f {
            LocalFeatures::Planes { xz, xy, yz } => {
                for p in [xz, xy, yz] {
                    assert_eq!(p.dims(), dims.as_slice());
                }
            }
            LocalFeatures::Grid(g) => assert_eq!(g.dims(), dims.as_slice()),
        }
        let q = cloud(2, 2, 17, DType::F32);
        assert_eq!(dec.logits(&q, &f).unwrap().dims(), &[2, 17]);
        // One scene as a Field; a batch of two cannot be bound.
        let pc = PointCloud::new(
            vec![[0.1, 0.2, 0.3], [-0.2, 0.1, 0.0], [0.4, -0.4, 0.1]],
            None,
            None,
        )
        .unwrap();
        let one = enc
            .forward(
                &points_to_tensor(pc.points(), &Device::Cpu, DType::F32)
                    .unwrap()
                    .unsqueeze(0)
                    .unwrap(),
            )
            .unwrap();
        let field = dec.bind(one).unwrap();
        let y = field.forward(&q.get(0).unwrap()).unwrap();
        assert_eq!(y.dims(), &[17, 1]);
        assert_eq!(arg_of(dec.bind(f).unwrap_err()), "features");
    }
}

#[test]
fn gradients_reach_every_parameter() {
    for layout in [
        FeatureLayout::Planes { resolution: 8 },
        FeatureLayout::Grid { resolution: 4 },
    ] {
        let (varmap, enc, dec) = model(&small(layout), DType::F64);
        let f = enc.forward(&cloud(3, 2, 80, DType::F64)).unwrap();
        let q = cloud(4, 2, 64, DType::F64);
        let logits = dec.logits(&q, &f).unwrap();
        let targets = q
            .sqr()
            .unwrap()
            .sum(2)
            .unwrap()
            .lt(0.1)
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap();
        let loss = reconstruction_loss(&logits, &targets).unwrap();
        let grads = loss.backward().unwrap();
        let data = varmap.data().lock().unwrap();
        assert!(data.keys().any(|k| k.starts_with("enc.unet")));
        assert!(data.keys().any(|k| k.starts_with("enc.block2.shortcut")));
        for (name, var) in data.iter() {
            let g = grads
                .get(var.as_tensor())
                .unwrap_or_else(|| panic!("{layout:?}: no gradient for {name}"));
            let g = v64(g);
            assert!(g.iter().all(|v| v.is_finite()), "{name}");
            assert!(
                g.iter().any(|&v| v != 0.0),
                "{layout:?}: zero gradient for {name}"
            );
        }
    }
}

#[test]
fn the_encoder_does_not_depend_on_the_order_of_the_points() {
    for layout in [
        FeatureLayout::Planes { resolution: 8 },
        FeatureLayout::Grid { resolution: 4 },
    ] {
        let (_, enc, _) = model(&small(layout), DType::F64);
        let pts = cloud(5, 1, 120, DType::F64);
        let mut perm: Vec<u32> = (0..120).collect();
        let mut rng = SplitMix64::new(6);
        for i in (1..perm.len()).rev() {
            perm.swap(i, rng.below(i as u64 + 1) as usize);
        }
        let perm = Tensor::from_vec(perm, 120, &Device::Cpu).unwrap();
        let shuffled = pts.index_select(&perm, 1).unwrap();
        let a = enc.forward(&pts).unwrap();
        let b = enc.forward(&shuffled).unwrap();
        let flat = |f: &LocalFeatures| -> Vec<f64> {
            match f {
                LocalFeatures::Planes { xz, xy, yz } => {
                    [xz, xy, yz].iter().flat_map(|t| v64(t)).collect()
                }
                LocalFeatures::Grid(g) => v64(g),
            }
        };
        let (a, b) = (flat(&a), flat(&b));
        let err = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 0.0);
        assert!(err <= 1e-12 * scale, "{layout:?}: {err}");
    }
}

fn arg_of(e: neural_fields::Error) -> String {
    match e {
        neural_fields::Error::InvalidArgument { arg, .. } => arg.to_string(),
        other => panic!("not an argument error: {other}"),
    }
}

#[test]
fn bad_inputs_and_configurations_are_errors_naming_the_argument() {
    let (_, enc, dec) = model(&small(FeatureLayout::Planes { resolution: 8 }), DType::F64);
    let d = Device::Cpu;
    let nan = Tensor::new(&[[[0.1f64, f64::NAN, 0.0]]], &d).unwrap();
    for (r, arg) in [
        (
            enc.forward(&Tensor::zeros((1, 0, 3), DType::F64, &d).unwrap()),
            "points",
        ),
        (
            enc.forward(&Tensor::zeros((1, 5, 2), DType::F64, &d).unwrap()),
            "points",
        ),
        (
            enc.forward(&Tensor::zeros((1, 5, 3), DType::F32, &d).unwrap()),
            "points",
        ),
        (enc.forward(&nan), "points"),
    ] {
        assert_eq!(arg_of(r.unwrap_err()), arg);
    }
    let f = enc.forward(&cloud(1, 1, 10, DType::F64)).unwrap();
    for (r, arg) in [
        (
            dec.logits(&Tensor::zeros((2, 4, 3), DType::F64, &d).unwrap(), &f),
            "points",
        ),
        (
            dec.logits(&Tensor::zeros((1, 4, 3), DType::F32, &d).unwrap(), &f),
            "points",
        ),
        (dec.logits(&nan, &f), "points"),
        (
            dec.logits(
                &Tensor::zeros((1, 4, 3), DType::F64, &d).unwrap(),
                &LocalFeatures::Grid(Tensor::zeros((1, 5, 2, 2, 2), DType::F64, &d).unwrap()),
            ),
            "features",
        ),
    ] {
        assert_eq!(arg_of(r.unwrap_err()), arg);
    }
    let vb = VarBuilder::from_varmap(&VarMap::new(), DType::F32, &d);
    let bad = |c: ConvOnetConfig| arg_of(conv_onet_encoder(&c, vb.clone()).unwrap_err());
    let base = small(FeatureLayout::Planes { resolution: 8 });
    assert_eq!(bad(ConvOnetConfig { hidden: 0, ..base }), "config.hidden");
    assert_eq!(
        bad(ConvOnetConfig {
            layout: FeatureLayout::Planes { resolution: 6 },
            unet: UnetConfig {
                depth: 3,
                start_filters: 4
            },
            ..base
        }),
        "config.layout.resolution"
    );
    assert_eq!(
        bad(ConvOnetConfig {
            layout: FeatureLayout::Grid { resolution: 0 },
            ..base
        }),
        "config.layout.resolution"
    );
    assert_eq!(
        bad(ConvOnetConfig {
            padding: -1.0,
            ..base
        }),
        "config.padding"
    );
}
