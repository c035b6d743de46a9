//! `texture` and its networks: gradients against central finite differences in f64 (the
//! Texture Fields decoder w.r.t. points and codes; IDR's colour at the implicit surface
//! point w.r.t. the geometry's weights, through p̂ *and* through the normal; the
//! image-gradient loss), closed forms, f32/f64, and bad input naming the argument.

#![cfg(feature = "texture")]
#![allow(clippy::needless_range_loop)]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use common::{central_diff_bound, close, reseed, uniform, v64};
use neural_fields::encoding::{FrequencyEncoding, PointEncoding};
use neural_fields::field::{Field, ImplicitSurface};
use neural_fields::nn::{build_seeded, MlpConfig};
use neural_fields::rng::SplitMix64;
use neural_fields::texture::{image_gradient_loss, TextureField, TextureInput};
use neural_fields::texture::{
    joint_decoder, rendering_net, texture_decoder, RenderingNetConfig, TextureDecoderConfig,
};
use proptest::prelude::*;

const DEV: Device = Device::Cpu;

/// Central difference of `loss()` along entry `i` of `v` (restored afterwards), with its
/// error bar ([`common::central_diff_bound`]).
fn fd(v: &Var, i: usize, h: f64, loss: &mut dyn FnMut() -> f64) -> Option<(f64, f64)> {
    let x0 = v64(v.as_tensor())[i];
    let mut f = |x: f64| {
        common::set_entry(v, i, x);
        loss()
    };
    let d = central_diff_bound(&mut f, x0, h, 1.0);
    common::set_entry(v, i, x0);
    d
}

/// `Σ rgb ⊙ c` for fixed random weights `c: [N, 3]`.
fn weighted(rgb: &Tensor, c: &Tensor) -> Tensor {
    (rgb * c).unwrap().sum_all().unwrap()
}

/// A small decoder with both codes and a frequency encoding of the points.
fn fd_config() -> TextureDecoderConfig {
    TextureDecoderConfig {
        hidden: 16,
        blocks: 3,
        shape_code_dim: 4,
        image_code_dim: 2,
        encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 3).unwrap()),
    }
}

fn texture_setup(seed: u64, n: usize, scale: f64) -> (VarMap, Var, Var, Var, Tensor) {
    let config = fd_config();
    let varmap = VarMap::new();
    build_seeded(&varmap, DType::F64, &DEV, seed, |vb| {
        texture_decoder(&config, vb)
    })
    .unwrap();
    // The zero-initialised layers would make every input gradient vanish.
    reseed(&varmap, seed ^ 3, 1.0);
    let mut rng = SplitMix64::new(seed);
    let p = Var::from_tensor(&uniform(&mut rng, n, 3, -scale, scale, DType::F64)).unwrap();
    let c = Var::from_tensor(&uniform(&mut rng, n, 4, -1.0, 1.0, DType::F64)).unwrap();
    let z = Var::from_tensor(&uniform(&mut rng, n, 2, -1.0, 1.0, DType::F64)).unwrap();
    let w = uniform(&mut rng, n, 3, -1.0, 1.0, DType::F64);
    (varmap, p, c, z, w)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]

    /// The Texture Fields decoder's colour w.r.t. the points, the shape code and the
    /// image code, at ordinary and large coordinates.
    #[test]
    fn texture_decoder_gradients_match_finite_differences(
        seed in any::<u64>(),
        scale in prop_oneof![Just(1.0), Just(50.0)],
    ) {
        let (varmap, p, c, z, w) = texture_setup(seed, 5, scale);
        let config = fd_config();
        let net = texture_decoder(&config, VarBuilder::from_varmap(&varmap, DType::F64, &DEV)).unwrap();
        let loss = || {
            let input = TextureInput { shape_code: Some(c.as_tensor()), image_code: Some(z.as_tensor()), ..TextureInput::new(p.as_tensor()) };
            weighted(&net.rgb(&input).unwrap(), &w)
        };
        let grads = loss().backward().unwrap();
        let (mut checked, mut total) = (0, 0);
        for (name, v) in [("points", &p), ("shape_code", &c), ("image_code", &z)] {
            let g = v64(grads.get(v).unwrap());
            for i in 0..v.elem_count() {
                total += 1;
                if let Some((num, bar)) = fd(v, i, 1e-4, &mut || loss().to_scalar::<f64>().unwrap()) {
                    checked += 1;
                    // Saturated colours at scale 50 give gradients near 1e-9, below the
                    // 1e-10 floor's reach of an h = 1e-4 stencil: allow twice its error bar
                    // (an estimate, not a bound: a CI run saw 2.05e-9 against ± 1.25e-9 on a
                    // gradient of 8e-7, the seed kept in tests/texture.proptest-regressions).
                    let err = (g[i] - num).abs();
                    prop_assert!(close(g[i], num, 1e-6, 1e-4) || err <= 2.0 * bar, "{name}[{i}]: {} vs FD {num} ± {bar:e}", g[i]);
                }
            }
        }
        // ReLU kinks inside the stencil skip an entry; most must be checked.
        prop_assert!(2 * checked >= total, "only {checked} of {total} entries checked");
    }
}

#[test]
fn texture_decoder_starts_grey_and_reads_only_its_codes() -> neural_fields::Result<()> {
    for dtype in [DType::F32, DType::F64] {
        let varmap = VarMap::new();
        let config = TextureDecoderConfig {
            shape_code_dim: 3,
            ..TextureDecoderConfig::default()
        };
        let net = build_seeded(&varmap, dtype, &DEV, 1, |vb| texture_decoder(&config, vb))?;
        let p = Tensor::ones((7, 3), dtype, &DEV)?.affine(1e6, 0.0)?;
        let c = Tensor::ones((7, 3), dtype, &DEV)?;
        let rgb = net.rgb(&TextureInput {
            shape_code: Some(&c),
            ..TextureInput::new(&p)
        })?;
        assert_eq!(rgb.dtype(), dtype);
        assert!(
            v64(&rgb).iter().all(|&x| x == 0.5),
            "σ(0) at initialisation"
        );
        let missing = net.rgb(&TextureInput::new(&p)).unwrap_err().to_string();
        assert!(
            missing.starts_with("shape_code: expected [N, 3]"),
            "{missing}"
        );
        let bad = Tensor::ones((6, 3), dtype, &DEV)?;
        let e = net
            .rgb(&TextureInput {
                shape_code: Some(&bad),
                ..TextureInput::new(&p)
            })
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("shape_code: expected shape [7, 3]"), "{e}");
        let e = net
            .rgb(&TextureInput::new(&Tensor::ones((7, 2), dtype, &DEV)?))
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("points"), "{e}");
        // An empty batch is an empty colour set.
        let empty = Tensor::zeros((0, 3), dtype, &DEV)?;
        let e0 = Tensor::zeros((0, 3), dtype, &DEV)?;
        assert_eq!(
            net.rgb(&TextureInput {
                shape_code: Some(&e0),
                ..TextureInput::new(&empty)
            })?
            .dims(),
            &[0, 3]
        );
    }
    let zero = TextureDecoderConfig {
        blocks: 0,
        ..TextureDecoderConfig::default()
    };
    let e = texture_decoder(&zero, VarBuilder::zeros(DType::F32, &DEV)).unwrap_err();
    assert!(e.to_string().starts_with("config.blocks"), "{e}");
    // Encodings of other than 3-D points are refused, naming the field.
    let two_d = PointEncoding::Frequency(FrequencyEncoding::new(2, 3)?);
    let e = texture_decoder(
        &TextureDecoderConfig {
            encoding: two_d.clone(),
            ..TextureDecoderConfig::default()
        },
        VarBuilder::zeros(DType::F32, &DEV),
    )
    .unwrap_err();
    assert!(e.to_string().starts_with("config.encoding"), "{e}");
    let e = rendering_net(
        &RenderingNetConfig {
            point_encoding: two_d,
            ..RenderingNetConfig::default()
        },
        VarBuilder::zeros(DType::F32, &DEV),
    )
    .unwrap_err();
    assert!(e.to_string().starts_with("config.point_encoding"), "{e}");
    Ok(())
}

#[test]
fn rendering_net_modes_read_what_they_are_configured_to() -> neural_fields::Result<()> {
    let n = 6;
    let p = Tensor::zeros((n, 3), DType::F64, &DEV)?;
    let v = Tensor::ones((n, 3), DType::F64, &DEV)?;
    let nrm = Tensor::ones((n, 3), DType::F64, &DEV)?;
    let f = Tensor::ones((n, 5), DType::F64, &DEV)?;
    let full = TextureInput {
        view_dirs: Some(&v),
        normals: Some(&nrm),
        features: Some(&f),
        ..TextureInput::new(&p)
    };
    let pe = PointEncoding::Frequency(FrequencyEncoding::new(3, 3)?);
    for (view, normals, features, point_encoding) in [
        (Some(4), true, 5, PointEncoding::Identity),
        (None, true, 5, PointEncoding::Identity),
        (Some(2), false, 5, PointEncoding::Identity),
        (None, false, 0, PointEncoding::Identity),
        (Some(4), true, 5, pe.clone()),
    ] {
        let config = RenderingNetConfig {
            feature_dim: features,
            view_frequencies: view,
            use_normals: normals,
            hidden: 16,
            depth: 2,
            force_reference: false,
            point_encoding,
        };
        let varmap = VarMap::new();
        let net = build_seeded(&varmap, DType::F64, &DEV, 2, |vb| {
            rendering_net(&config, vb)
        })?;
        let rgb = net.rgb(&full)?;
        assert_eq!(rgb.dims(), &[n, 3]);
        assert!(v64(&rgb).iter().all(|x| (0.0..=1.0).contains(x)));
        // Inputs the mode does not read may be missing.
        let mut only = TextureInput::new(&p);
        if view.is_some() {
            only.view_dirs = Some(&v);
        }
        if normals {
            only.normals = Some(&nrm);
        }
        if features > 0 {
            only.features = Some(&f);
        }
        assert_eq!(v64(&net.rgb(&only)?), v64(&rgb));
        // The fused op and the reference path agree.
        let reference = rendering_net(
            &RenderingNetConfig {
                force_reference: true,
                ..config.clone()
            },
            VarBuilder::from_varmap(&varmap, DType::F64, &DEV),
        )?;
        for (a, b) in v64(&reference.rgb(&full)?).iter().zip(v64(&rgb)) {
            assert!((a - b).abs() < 1e-12);
        }
    }
    let config = RenderingNetConfig {
        feature_dim: 5,
        hidden: 8,
        depth: 1,
        ..RenderingNetConfig::default()
    };
    let net = build_seeded(&VarMap::new(), DType::F64, &DEV, 2, |vb| {
        rendering_net(&config, vb)
    })?;
    for (input, name) in [
        (
            TextureInput {
                normals: Some(&nrm),
                features: Some(&f),
                ..TextureInput::new(&p)
            },
            "view_dirs",
        ),
        (
            TextureInput {
                view_dirs: Some(&v),
                features: Some(&f),
                ..TextureInput::new(&p)
            },
            "normals",
        ),
        (
            TextureInput {
                view_dirs: Some(&v),
                normals: Some(&nrm),
                ..TextureInput::new(&p)
            },
            "features",
        ),
        (
            TextureInput {
                view_dirs: Some(&v),
                normals: Some(&nrm),
                features: Some(&nrm),
                ..TextureInput::new(&p)
            },
            "features",
        ),
    ] {
        let e = net.rgb(&input).unwrap_err().to_string();
        assert!(e.starts_with(name), "{e}");
    }
    // A zero view direction stays finite (the normalisation is floored).
    let zero = Tensor::zeros((n, 3), DType::F64, &DEV)?;
    let rgb = net.rgb(&TextureInput {
        view_dirs: Some(&zero),
        normals: Some(&nrm),
        features: Some(&f),
        ..TextureInput::new(&p)
    })?;
    assert!(v64(&rgb).iter().all(|x| x.is_finite()));
    Ok(())
}

#[test]
fn joint_decoder_is_a_surface_and_a_texture_of_one_trunk() -> neural_fields::Result<()> {
    for dtype in [DType::F32, DType::F64] {
        let varmap = VarMap::new();
        let config = MlpConfig {
            hidden: 16,
            depth: 2,
            out_dim: 1, // replaced by 4
            ..MlpConfig::default()
        };
        let net = build_seeded(&varmap, dtype, &DEV, 3, |vb| joint_decoder(&config, vb))?;
        let mut rng = SplitMix64::new(4);
        let p = uniform(&mut rng, 9, 3, -1.0, 1.0, dtype);
        let raw = v64(&Field::forward(&net, &p)?);
        let logit = v64(&net.value(&p)?);
        let rgb = v64(&net.rgb(&TextureInput::new(&p))?);
        let tol = if dtype == DType::F32 { 1e-6 } else { 1e-14 };
        for i in 0..9 {
            assert!((logit[i] - raw[4 * i]).abs() <= tol);
            for c in 0..3 {
                let s = 1.0 / (1.0 + (-raw[4 * i + 1 + c]).exp());
                assert!((rgb[3 * i + c] - s).abs() <= tol);
            }
        }
        let (value, grad) = net.value_and_grad(&p)?;
        assert_eq!(v64(&value).len(), 9);
        assert_eq!(grad.dims(), &[9, 3]);
    }
    Ok(())
}

/// The geometry of IDR: an SDF Mlp (geometric init, softplus) with a feature output,
/// perturbed so that it is not a sphere.
fn geometry(seed: u64, features: usize) -> (VarMap, neural_fields::nn::Mlp) {
    let varmap = VarMap::new();
    let cfg = MlpConfig {
        hidden: 16,
        depth: 2,
        out_dim: 1 + features,
        activation: neural_fields::nn::Activation::Softplus { beta: 10.0 },
        ..MlpConfig::sdf(0.5)
    };
    build_seeded(&varmap, DType::F64, &DEV, seed, |vb| {
        neural_fields::nn::mlp(&cfg, vb)
    })
    .unwrap();
    let mut rng = SplitMix64::new(seed ^ 99);
    for v in common::sorted_vars(&varmap) {
        let noise = common::normal_tensor(&mut rng, v.dims(), 0.0, 0.05, DType::F64, &DEV).unwrap();
        v.set(&(v.as_tensor() + noise).unwrap()).unwrap();
    }
    let net =
        neural_fields::nn::mlp(&cfg, VarBuilder::from_varmap(&varmap, DType::F64, &DEV)).unwrap();
    (varmap, net)
}

#[cfg(feature = "dvr")]
mod idr {
    use super::*;
    use neural_fields::camera::{Intersection, Rays};
    use neural_fields::dvr::{implicit_surface, march, ImplicitConfig};
    use neural_fields::nn::Mlp;
    use neural_fields::texture::RenderingNet;

    /// Rays from distance 2 through points near the origin, each ending on the geometry.
    fn rays(seed: u64, r: usize) -> (Rays, Intersection) {
        let mut rng = SplitMix64::new(seed);
        let (mut o, mut w) = (vec![], vec![]);
        for _ in 0..r {
            let d = [rng.normal(), rng.normal(), rng.normal()];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            for k in 0..3 {
                let target = 0.15 * (2.0 * rng.uniform() - 1.0);
                o.push(target - 2.0 * d[k] / l);
                w.push(d[k] / l);
            }
        }
        (
            Rays::new(
                Tensor::from_vec(o, (r, 3), &DEV).unwrap(),
                Tensor::from_vec(w, (r, 3), &DEV).unwrap(),
            )
            .unwrap(),
            Intersection::new(
                Tensor::zeros(r, DType::F64, &DEV).unwrap(),
                Tensor::full(4.0f64, r, &DEV).unwrap(),
            )
            .unwrap(),
        )
    }

    /// `Σ c ⊙ rgb(p̂, v, ∇f(p̂), feature(p̂))` over the rays that hit; `detach_normal`
    /// cuts the path through the normal. `None` when a ray misses.
    fn colour_loss(
        geo: &Mlp,
        tex: &RenderingNet,
        rays: &Rays,
        range: &Intersection,
        c: &Tensor,
        detach_normal: bool,
    ) -> Option<Tensor> {
        let hits = march(geo, rays, range, &common::hits::accurate_march()).unwrap();
        if !hits.status.iter().all(|s| s.has_surface()) {
            return None;
        }
        let surf = implicit_surface(geo, rays, &hits, &ImplicitConfig::default()).unwrap();
        let (y, jac) = geo.forward_with_jacobian(&surf.points, None).unwrap();
        let k = y.dim(1).unwrap();
        let normal = jac.narrow(2, 0, 1).unwrap().squeeze(2).unwrap();
        let normal = if detach_normal {
            normal.detach()
        } else {
            normal
        };
        let feature = y.narrow(1, 1, k - 1).unwrap();
        let dirs = rays.directions().index_select(&surf.indices, 0).unwrap();
        let input = TextureInput {
            normals: Some(&normal),
            view_dirs: Some(&dirs),
            features: Some(&feature),
            ..TextureInput::new(&surf.points)
        };
        Some(weighted(&tex.rgb(&input).unwrap(), c))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(8))]

        /// IDR's colour loss at the implicit surface point reaches the geometry's weights
        /// through p̂ and through the normal, and equals finite differences of the whole
        /// march → surface → colour pipeline.
        #[test]
        fn idr_colour_gradient_wrt_geometry_matches_finite_differences(seed in any::<u64>()) {
            let (geo_vars, geo) = geometry(seed, 4);
            // Every other seed reads p̂ through a frequency encoding: the gradient then also
            // runs through the encoding's Jacobian.
            let config = RenderingNetConfig {
                feature_dim: 4,
                hidden: 16,
                depth: 2,
                point_encoding: if seed % 2 == 0 {
                    PointEncoding::Identity
                } else {
                    PointEncoding::Frequency(FrequencyEncoding::new(3, 2).unwrap())
                },
                ..RenderingNetConfig::default()
            };
            let tex_vars = VarMap::new();
            let tex = build_seeded(&tex_vars, DType::F64, &DEV, seed ^ 1, |vb| rendering_net(&config, vb)).unwrap();
            let (rays, range) = rays(seed, 4);
            let c = uniform(&mut SplitMix64::new(seed ^ 2), 4, 3, -1.0, 1.0, DType::F64);
            let loss = colour_loss(&geo, &tex, &rays, &range, &c, false);
            prop_assume!(loss.is_some());
            let grads = loss.unwrap().backward().unwrap();
            let cut = colour_loss(&geo, &tex, &rays, &range, &c, true).unwrap().backward().unwrap();
            let mut rng = SplitMix64::new(seed ^ 5);
            let vars = common::sorted_vars(&geo_vars);
            let (mut checked, mut normal_matters) = (0, 0);
            for _ in 0..8 {
                let v = &vars[rng.below(vars.len() as u64) as usize];
                let i = rng.below(v.elem_count() as u64) as usize;
                let analytic = grads.get(v).map_or(0.0, |g| v64(g)[i]);
                let without_normal = cut.get(v).map_or(0.0, |g| v64(g)[i]);
                if (analytic - without_normal).abs() > 1e-6 * analytic.abs().max(1e-3) {
                    normal_matters += 1;
                }
                let numeric = fd(v, i, 1e-5, &mut || {
                    colour_loss(&geo, &tex, &rays, &range, &c, false)
                        .map_or(f64::NAN, |l| l.to_scalar::<f64>().unwrap())
                });
                if let Some((num, _)) = numeric.filter(|x| x.0.is_finite()) {
                    checked += 1;
                    prop_assert!(close(analytic, num, 1e-5, 1e-4), "weight: {analytic:e} vs FD {num:e}");
                }
            }
            prop_assert!(checked >= 4, "only {checked} of 8 entries checked");
            prop_assert!(normal_matters >= 1, "the normal path changed no gradient");
        }
    }
}

#[test]
fn image_gradient_loss_closed_form_mask_and_gradient() -> neural_fields::Result<()> {
    // Two 2×2 patches of one channel; the second has an invalid pixel.
    let target = Tensor::new(
        &[[1.0f64], [0.0], [1.0], [1.0], [0.0], [1.0], [0.0], [0.0]],
        &DEV,
    )?;
    let pred = Tensor::new(
        &[[0.2f64], [0.4], [0.9], [0.0], [0.3], [0.3], [0.3], [0.3]],
        &DEV,
    )?;
    // Patch 0: Δx 1 vs −0.2, Δy 0 vs −0.7 → 1.2 + 0.7.
    let all = image_gradient_loss(&pred, &target, None, 2)?.to_scalar::<f64>()?;
    // Patch 1: Δx −1 vs 0, Δy 0 vs 0 → 1; mean (1.9 + 1) / 2.
    assert!((all - 1.45).abs() < 1e-15, "{all}");
    let valid = Tensor::new(&[1u8, 1, 1, 1, 1, 0, 1, 1], &DEV)?;
    let masked = image_gradient_loss(&pred, &target, Some(&valid), 2)?.to_scalar::<f64>()?;
    assert!((masked - 1.9).abs() < 1e-15, "{masked}");
    let none = Tensor::zeros(8, DType::U8, &DEV)?;
    assert_eq!(
        image_gradient_loss(&pred, &target, Some(&none), 2)?.to_scalar::<f64>()?,
        0.0
    );
    // Gradient w.r.t. pred by central differences (away from |·|'s kink).
    let mut rng = SplitMix64::new(7);
    let pv = Var::from_tensor(&uniform(&mut rng, 3 * 9, 3, 0.0, 1.0, DType::F64))?;
    let tv = uniform(&mut rng, 3 * 9, 3, 0.0, 1.0, DType::F64);
    let g = v64(image_gradient_loss(pv.as_tensor(), &tv, None, 3)?
        .backward()?
        .get(&pv)
        .expect("a gradient"));
    let mut checked = 0;
    for i in 0..pv.elem_count() {
        let num = fd(&pv, i, 1e-6, &mut || {
            image_gradient_loss(pv.as_tensor(), &tv, None, 3)
                .unwrap()
                .to_scalar::<f64>()
                .unwrap()
        });
        if let Some((num, _)) = num {
            checked += 1;
            assert!(close(g[i], num, 1e-7, 1e-6), "{i}: {} vs {num}", g[i]);
        }
    }
    assert!(checked > 60, "{checked}");
    // f32 and extreme values stay finite.
    let big = Tensor::full(3e38f32, (8, 3), &DEV)?;
    let small = Tensor::full(-3e38f32, (8, 3), &DEV)?;
    let l = image_gradient_loss(&big, &small, None, 2)?.to_scalar::<f32>()?;
    assert_eq!(
        l, 0.0,
        "equal neighbours have zero gradients whatever their value"
    );
    // Bad input names the argument.
    for (k, name) in [(1, "k"), (3, "k")] {
        let e = image_gradient_loss(&pred, &target, None, k).unwrap_err();
        assert!(e.to_string().starts_with(name), "{e}");
    }
    let e = image_gradient_loss(&pred, &target.narrow(0, 0, 4)?, None, 2).unwrap_err();
    assert!(e.to_string().starts_with("target"), "{e}");
    let e = image_gradient_loss(&pred, &target, Some(&valid.narrow(0, 0, 4)?), 2).unwrap_err();
    assert!(e.to_string().starts_with("valid"), "{e}");
    Ok(())
}

#[cfg(feature = "occupancy")]
#[test]
fn pointnet_encodes_points_with_normals_order_independently() -> neural_fields::Result<()> {
    use neural_fields::occupancy::{pointnet_encoder, PointNetConfig};
    let config = PointNetConfig {
        hidden: 16,
        layers: 2,
        latent_dim: 8,
        point_features: 3,
    };
    let varmap = VarMap::new();
    let enc = build_seeded(&varmap, DType::F64, &DEV, 5, |vb| {
        pointnet_encoder(&config, vb)
    })?;
    let mut rng = SplitMix64::new(6);
    let p = uniform(&mut rng, 10, 3, -1.0, 1.0, DType::F64).reshape((1, 10, 3))?;
    let n = uniform(&mut rng, 10, 3, -1.0, 1.0, DType::F64).reshape((1, 10, 3))?;
    let (mu, logvar) = enc.forward(&p, &n)?;
    assert_eq!((mu.dims(), logvar.dims()), (&[1, 8][..], &[1, 8][..]));
    let perm = Tensor::new(&[3u32, 7, 0, 1, 9, 2, 8, 4, 6, 5], &DEV)?;
    let (mu2, _) = enc.forward(&p.index_select(&perm, 1)?, &n.index_select(&perm, 1)?)?;
    assert_eq!(v64(&mu), v64(&mu2));
    let e = enc.forward(&p, &n.narrow(2, 0, 2)?).unwrap_err();
    assert!(e.to_string().starts_with("features"), "{e}");
    // `[B, K]` labels are read as one feature: refused with three.
    let occ = Tensor::ones((1, 10), DType::F64, &DEV)?;
    let e = enc.forward(&p, &occ).unwrap_err();
    assert!(e.to_string().starts_with("features"), "{e}");
    // With one feature per point, `[B, K]` and `[B, K, 1]` are the same input.
    let one = PointNetConfig {
        point_features: 1,
        ..config
    };
    let enc1 = build_seeded(&VarMap::new(), DType::F64, &DEV, 5, |vb| {
        pointnet_encoder(&one, vb)
    })?;
    let labels = uniform(&mut rng, 10, 1, 0.0, 1.0, DType::F64).reshape((1, 10))?;
    let (flat, _) = enc1.forward(&p, &labels)?;
    let (column, _) = enc1.forward(&p, &labels.unsqueeze(2)?)?;
    assert_eq!(v64(&flat), v64(&column));
    Ok(())
}

#[test]
fn vertex_colors_evaluate_in_chunks_and_reject_bad_colours() -> neural_fields::Result<()> {
    use neural_fields::mesh::Mesh;
    use neural_fields::texture::vertex_colors;
    let mesh = Mesh::new(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ],
        vec![[0, 1, 2], [0, 1, 3]],
    )?;
    let mut calls = 0;
    let colors = vertex_colors(&mesh, 3, &DEV, DType::F32, |p| {
        calls += 1;
        Ok(p.affine(0.5, 0.25)?)
    })?;
    assert_eq!(calls, 2);
    assert_eq!(colors[1], [0.75, 0.25, 0.25]);
    assert_eq!(colors.len(), 4);
    let e = vertex_colors(&mesh, 0, &DEV, DType::F32, |p| Ok(p.clone())).unwrap_err();
    assert!(e.to_string().starts_with("chunk"), "{e}");
    let e =
        vertex_colors(&mesh, 8, &DEV, DType::F32, |p| Ok(p.affine(f64::NAN, 0.0)?)).unwrap_err();
    assert!(e.to_string().starts_with("colors"), "{e}");
    let e = vertex_colors(&mesh, 8, &DEV, DType::F32, |p| Ok(p.narrow(1, 0, 2)?)).unwrap_err();
    assert!(e.to_string().starts_with("colors"), "{e}");
    Ok(())
}
