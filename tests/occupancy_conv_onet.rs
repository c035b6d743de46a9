//! Convolutional Occupancy Networks: shapes of the plane and grid variants, gradients
//! reaching every parameter, the 3-D convolution against a direct sum (values and
//! gradients), invariance of the encoder to the order of the input points, and errors.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use common::v64;
use neural_fields::field::Field;
use neural_fields::mesh::PointCloud;
use neural_fields::occupancy::reconstruction_loss;
use neural_fields::occupancy::{
    conv3d, conv_onet_encoder, local_decoder, ConvOnetConfig, ConvOnetEncoder, FeatureLayout,
    LocalDecoder, LocalDecoderConfig, LocalFeatures, UnetConfig,
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
        assert_eq!(f.batch_and_channels(), (2, 6));
        let q = cloud(2, 2, 17, DType::F32);
        assert_eq!(dec.logits(&q, &f).unwrap().dims(), &[2, 17]);
        // One scene as a Field; a batch of two cannot be bound.
        let pc = PointCloud::new(
            vec![[0.1, 0.2, 0.3], [-0.2, 0.1, 0.0], [0.4, -0.4, 0.1]],
            None,
            None,
        )
        .unwrap();
        let one = enc.encode_cloud(&pc).unwrap();
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

/// `y[b, o, z, y, x] = Σ w[o, i, a, β, γ] x_pad[b, i, z + a, y + β, x + γ]` by loops,
/// and its adjoints (the gradients of `Σ G ⊙ y` w.r.t. `x` and `w`).
#[allow(clippy::type_complexity)]
fn naive(
    x: &[f64],
    xd: [usize; 5],
    w: &[f64],
    wd: [usize; 5],
    pad: usize,
    g: Option<&[f64]>,
) -> (Vec<f64>, [usize; 5], Vec<f64>, Vec<f64>) {
    let [b, ci, d, h, wi] = xd;
    let [co, _, kd, kh, kw] = wd;
    let (od, oh, ow) = (
        d + 2 * pad + 1 - kd,
        h + 2 * pad + 1 - kh,
        wi + 2 * pad + 1 - kw,
    );
    let od5 = [b, co, od, oh, ow];
    let mut y = vec![0.0; b * co * od * oh * ow];
    let mut gx = vec![0.0; x.len()];
    let mut gw = vec![0.0; w.len()];
    for n in 0..b {
        for o in 0..co {
            for z in 0..od {
                for yy in 0..oh {
                    for xx in 0..ow {
                        let yi = (((n * co + o) * od + z) * oh + yy) * ow + xx;
                        let gy = g.map_or(0.0, |g| g[yi]);
                        for i in 0..ci {
                            for a in 0..kd {
                                for be in 0..kh {
                                    for ga in 0..kw {
                                        let (pz, py, px) = (z + a, yy + be, xx + ga);
                                        if pz < pad || py < pad || px < pad {
                                            continue;
                                        }
                                        let (sz, sy, sx) = (pz - pad, py - pad, px - pad);
                                        if sz >= d || sy >= h || sx >= wi {
                                            continue;
                                        }
                                        let xi = (((n * ci + i) * d + sz) * h + sy) * wi + sx;
                                        let wi_ = (((o * ci + i) * kd + a) * kh + be) * kw + ga;
                                        y[yi] += w[wi_] * x[xi];
                                        gx[xi] += w[wi_] * gy;
                                        gw[wi_] += x[xi] * gy;
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    (y, od5, gx, gw)
}

#[test]
fn conv3d_matches_the_direct_sum_in_values_and_gradients() {
    let mut rng = SplitMix64::new(9);
    for (xd, wd, pad) in [
        ([2usize, 3, 4, 5, 3], [4usize, 3, 3, 3, 3], 1usize),
        ([1, 2, 5, 4, 6], [3, 2, 2, 3, 1], 0),
        ([1, 2, 3, 3, 3], [2, 2, 1, 1, 1], 0),
        ([1, 1, 2, 3, 2], [2, 1, 3, 2, 3], 2),
    ] {
        let xv: Vec<f64> = (0..xd.iter().product())
            .map(|_| rng.uniform() - 0.5)
            .collect();
        let wv: Vec<f64> = (0..wd.iter().product())
            .map(|_| rng.uniform() - 0.5)
            .collect();
        let x = Var::from_vec(xv.clone(), xd.as_slice(), &Device::Cpu).unwrap();
        let w = Var::from_vec(wv.clone(), wd.as_slice(), &Device::Cpu).unwrap();
        let y = conv3d(x.as_tensor(), w.as_tensor(), pad).unwrap();
        let (want, od, _, _) = naive(&xv, xd, &wv, wd, pad, None);
        assert_eq!(y.dims(), od.as_slice());
        let got = v64(&y);
        let err = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-12, "{xd:?} {wd:?} pad {pad}: {err}");
        let gy: Vec<f64> = (0..want.len())
            .map(|i| ((i * 31) % 7) as f64 - 3.0)
            .collect();
        let gt = Tensor::from_vec(gy.clone(), od.as_slice(), &Device::Cpu).unwrap();
        let grads = (y * gt).unwrap().sum_all().unwrap().backward().unwrap();
        let (_, _, gx, gw) = naive(&xv, xd, &wv, wd, pad, Some(&gy));
        for (name, got, want) in [
            ("input", v64(grads.get(x.as_tensor()).unwrap()), gx),
            ("weight", v64(grads.get(w.as_tensor()).unwrap()), gw),
        ] {
            let err = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(err < 1e-11, "{name} {xd:?} {wd:?} pad {pad}: {err}");
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
    let x = Tensor::zeros((1, 2, 3, 3, 3), DType::F64, &d).unwrap();
    assert_eq!(
        arg_of(
            conv3d(
                &x,
                &Tensor::zeros((1, 3, 3, 3, 3), DType::F64, &d).unwrap(),
                1
            )
            .unwrap_err()
        ),
        "weight"
    );
    assert_eq!(
        arg_of(
            conv3d(
                &x,
                &Tensor::zeros((1, 2, 6, 3, 3), DType::F64, &d).unwrap(),
                1
            )
            .unwrap_err()
        ),
        "weight"
    );
    assert_eq!(
        arg_of(conv3d(&x.flatten_all().unwrap(), &x, 1).unwrap_err()),
        "input"
    );
}
