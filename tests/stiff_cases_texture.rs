//! Stiff cases of `texture`: the texture networks, the image-gradient loss and vertex
//! colours at extreme inputs.

#![cfg(feature = "texture")]

mod common;

use candle_core::{DType, Device, Tensor, Var};

use common::stiff::{extreme_points, magnitudes, var, Expect, Suite};

use neural_fields::encoding::{FrequencyEncoding, PointEncoding};
use neural_fields::field::{Field, ImplicitSurface};
use neural_fields::nn::{build_seeded, MlpConfig};
use neural_fields::rng::SplitMix64;

#[test]
fn texture_stays_finite() {
    let mut s = Suite::default();
    sweep_texture(&mut s);
    s.finish("texture", TEXTURE);
}

#[test]
fn every_public_texture_function_is_swept_or_exempt() {
    common::stiff::check_coverage("stiff_cases_texture", &[TEXTURE], EXEMPT, &[], &[]);
}

/// Items swept by `sweep_texture`.
const TEXTURE: &[&str] = &[
    "texture::JointDecoder::forward",
    "texture::JointDecoder::rgb",
    "texture::JointDecoder::value",
    "texture::JointDecoder::value_and_grad",
    "texture::RenderingNet::rgb",
    "texture::TextureDecoder::rgb",
    "texture::joint_decoder",
    "texture::rendering_net",
    "texture::texture_decoder",
    "texture::image_gradient_loss",
    "texture::vertex_colors",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    (
        "texture::TextureInput::",
        "builder: stores references to its tensors, computes nothing",
    ),
    ("texture::TextureDecoderConfig::default", "constant"),
    ("texture::RenderingNetConfig::default", "constant"),
    ("texture::JointDecoder::out_dim", "constant"),
    ("texture::JointDecoder::inside", "constant"),
];

/// The texture networks at extreme points, normals, directions, features and codes (zero
/// directions and normals included); the image-gradient loss on extreme colours; vertex
/// colours from a closure that returns extreme or non-finite values.
fn sweep_texture(s: &mut Suite) {
    use neural_fields::texture::{image_gradient_loss, TextureField, TextureInput};
    use neural_fields::texture::{
        joint_decoder, rendering_net, texture_decoder, RenderingNetConfig, TextureDecoderConfig,
    };
    let d = Device::Cpu;
    for dtype in [DType::F32, DType::F64] {
        let big = if dtype == DType::F32 { 1e30 } else { 1e150 };
        let tag = format!("{dtype:?}, |x| up to {big:e}");
        let pts = extreme_points(dtype);
        let n = pts.dim(0).unwrap();
        let p = Var::from_tensor(&pts).unwrap();
        let mut rng = SplitMix64::new(11);
        let extreme = |cols: usize, rng: &mut SplitMix64| -> Var {
            let values: Vec<f64> = (0..n * cols)
                .map(|i| match i % 5 {
                    0 => 0.0,
                    1 => big,
                    2 => -1e-30,
                    _ => rng.normal(),
                })
                .collect();
            var(&values, &[n, cols], dtype)
        };
        let (nrm, dirs, feat) = (
            extreme(3, &mut rng),
            extreme(3, &mut rng),
            extreme(2, &mut rng),
        );
        let (c, z) = (extreme(2, &mut rng), extreme(1, &mut rng));
        let tcfg = TextureDecoderConfig {
            hidden: 8,
            blocks: 2,
            shape_code_dim: 2,
            image_code_dim: 1,
            encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 4).unwrap()),
        };
        let vm = candle_nn::VarMap::new();
        let tex = build_seeded(&vm, dtype, &d, 1, |vb| texture_decoder(&tcfg, vb)).unwrap();
        for item in ["texture::texture_decoder", "texture::TextureDecoder::rgb"] {
            s.case(item, &tag, Expect::Finite, &[&p, &c, &z], || {
                let input = TextureInput {
                    shape_code: Some(c.as_tensor()),
                    image_code: Some(z.as_tensor()),
                    ..TextureInput::new(p.as_tensor())
                };
                Ok(vec![tex.rgb(&input)?])
            });
        }
        let rcfg = RenderingNetConfig {
            feature_dim: 2,
            hidden: 8,
            depth: 2,
            ..RenderingNetConfig::default()
        };
        let vm = candle_nn::VarMap::new();
        let render = build_seeded(&vm, dtype, &d, 2, |vb| rendering_net(&rcfg, vb)).unwrap();
        for item in ["texture::rendering_net", "texture::RenderingNet::rgb"] {
            s.case(
                item,
                &tag,
                Expect::Finite,
                &[&p, &nrm, &dirs, &feat],
                || {
                    let input = TextureInput {
                        normals: Some(nrm.as_tensor()),
                        view_dirs: Some(dirs.as_tensor()),
                        features: Some(feat.as_tensor()),
                        ..TextureInput::new(p.as_tensor())
                    };
                    Ok(vec![render.rgb(&input)?])
                },
            );
        }
        let jcfg = MlpConfig {
            hidden: 8,
            depth: 2,
            ..MlpConfig::default()
        };
        let vm = candle_nn::VarMap::new();
        let joint = build_seeded(&vm, dtype, &d, 3, |vb| joint_decoder(&jcfg, vb)).unwrap();
        for item in ["texture::joint_decoder", "texture::JointDecoder::rgb"] {
            s.case(item, &tag, Expect::Finite, &[&p], || {
                Ok(vec![joint.rgb(&TextureInput::new(p.as_tensor()))?])
            });
        }
        s.case(
            "texture::JointDecoder::value",
            &tag,
            Expect::Finite,
            &[&p],
            || Ok(vec![joint.value(p.as_tensor())?]),
        );
        s.case(
            "texture::JointDecoder::forward",
            &tag,
            Expect::Finite,
            &[&p],
            || Ok(vec![Field::forward(&joint, p.as_tensor())?]),
        );
        s.case(
            "texture::JointDecoder::value_and_grad",
            &tag,
            Expect::Finite,
            &[&p],
            || {
                let (v, g) = joint.value_and_grad(p.as_tensor())?;
                Ok(vec![v, g])
            },
        );
        // The image-gradient loss on 2 × 2 patches of extreme colours.
        let mags = magnitudes(dtype);
        let colours = |shift: usize| -> Var {
            let values: Vec<f64> = (0..8 * 3).map(|i| mags[(i + shift) % mags.len()]).collect();
            var(&values, &[8, 3], dtype)
        };
        let (pred, target) = (colours(0), colours(5));
        let valid = Tensor::new(&[1u8, 1, 1, 1, 1, 0, 1, 1], &d).unwrap();
        s.case(
            "texture::image_gradient_loss",
            format!(
                "{dtype:?}, colours in ±{:e}",
                mags.iter().fold(0.0f64, |m, x| m.max(x.abs()))
            ),
            Expect::Finite,
            &[&pred, &target],
            || {
                Ok(vec![
                    image_gradient_loss(pred.as_tensor(), target.as_tensor(), Some(&valid), 2)?,
                    image_gradient_loss(pred.as_tensor(), target.as_tensor(), None, 2)?,
                ])
            },
        );
        {
            use neural_fields::mesh::Mesh;
            use neural_fields::texture::vertex_colors;
            let mesh = Mesh::new(
                vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                vec![[0, 1, 2]],
            )
            .unwrap();
            for value in [0.0, 1e-300, 1.0, 1e300, -1e300, f64::INFINITY, f64::NAN] {
                s.case(
                    "texture::vertex_colors",
                    format!("{dtype:?}, closure returns {value:e}"),
                    // ±1e300 is infinite in f32, and an infinite colour is an error.
                    if value.is_finite() && (dtype == DType::F64 || value.abs() < 1e38) {
                        Expect::Finite
                    } else {
                        Expect::FiniteOrErr
                    },
                    &[],
                    || {
                        let colors = vertex_colors(&mesh, 2, &d, dtype, |p| {
                            Ok(Tensor::full(value, p.dims(), &d)?.to_dtype(dtype)?)
                        })?;
                        let flat: Vec<f64> = colors.concat();
                        Ok(vec![Tensor::from_vec(flat.clone(), flat.len(), &d)?])
                    },
                );
            }
        }
    }
}
