//! Every fused op over sizes that include 0: zero rays, zero samples per ray, zero
//! points, packed layouts with empty rays. Each call returns tensors of the right shape
//! whose values can be read (a zero-ray composite once returned a view past its
//! storage), and backward passes through them, on the fused and the reference path, in
//! f32 and f64.
#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use common::v64;
use neural_fields::encoding::{Encoding, FrequencyEncoding, PointEncoding};
use neural_fields::field::Field;
use neural_fields::nn::{mlp, Activation, MlpConfig};
use neural_fields::volume::Layout;
use neural_fields::volume::{composite, CompositeConfig, Intervals, Packed};
use neural_fields::volume::{nerf, NerfConfig};
use proptest::prelude::*;

fn dtype(f64_: bool) -> DType {
    if f64_ {
        DType::F64
    } else {
        DType::F32
    }
}

/// A `[dims]` variable filled with small positive values.
fn var(dims: &[usize], dt: DType) -> Var {
    let n: usize = dims.iter().product();
    let v: Vec<f64> = (0..n).map(|i| 0.1 + (i % 7) as f64 * 0.05).collect();
    let t = Tensor::from_vec(v, dims, &Device::Cpu)
        .and_then(|t| t.to_dtype(dt))
        .unwrap();
    Var::from_tensor(&t).unwrap()
}

/// Reads every output and runs backward through their sum; returns the gradients'
/// lengths of `inputs`.
fn read_and_backward(outputs: &[&Tensor], inputs: &[&Var]) -> Vec<usize> {
    let mut loss = Tensor::zeros((), outputs[0].dtype(), &Device::Cpu).unwrap();
    for o in outputs {
        let v = v64(o);
        assert!(v.iter().all(|x| x.is_finite()), "{v:?}");
        loss = (loss + o.sum_all().unwrap()).unwrap();
    }
    let grads = loss.backward().unwrap();
    inputs
        .iter()
        .map(|x| {
            grads
                .get(x.as_tensor())
                .map(|g| {
                    let g = v64(g);
                    assert!(g.iter().all(|x| x.is_finite()));
                    g.len()
                })
                .unwrap_or(0)
        })
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn composite_batched_with_zero_rays_or_samples(
        rays in 0usize..3, samples in 0usize..3, f64_ in any::<bool>(), reference in any::<bool>()
    ) {
        let dt = dtype(f64_);
        let config = CompositeConfig { force_reference: reference, ..CompositeConfig::default() };
        let sigmas = var(&[rays, samples], dt);
        let colors = var(&[rays, samples, 3], dt);
        let starts = Tensor::arange(0u32, (rays * samples) as u32, &Device::Cpu)
            .and_then(|t| t.to_dtype(dt))
            .and_then(|t| t.reshape((rays, samples)))
            .unwrap();
        let ends = (&starts + 1.0).unwrap();
        let iv = Intervals::new(starts, ends, Layout::Batched).unwrap();
        let out = composite(sigmas.as_tensor(), colors.as_tensor(), &iv, None, &config).unwrap();
        prop_assert_eq!(out.color.dims(), &[rays, 3]);
        prop_assert_eq!(out.depth.dims(), &[rays]);
        let lens = read_and_backward(&[&out.color, &out.depth, &out.opacity], &[&sigmas, &colors]);
        prop_assert!(lens[0] == 0 || lens[0] == rays * samples);
    }

    #[test]
    fn composite_packed_with_empty_rays(
        counts in proptest::collection::vec(0usize..3, 0..4), f64_ in any::<bool>(), reference in any::<bool>()
    ) {
        let dt = dtype(f64_);
        let config = CompositeConfig { force_reference: reference, ..CompositeConfig::default() };
        let m: usize = counts.iter().sum();
        let packed = Packed::from_counts(&counts, &Device::Cpu).unwrap();
        let starts = Tensor::arange(0u32, m as u32, &Device::Cpu)
            .and_then(|t| t.to_dtype(dt))
            .unwrap();
        let ends = (&starts + 1.0).unwrap();
        let iv = Intervals::new(starts, ends, Layout::Packed(packed)).unwrap();
        let sigmas = var(&[m], dt);
        let colors = var(&[m, 3], dt);
        let out = composite(sigmas.as_tensor(), colors.as_tensor(), &iv, None, &config).unwrap();
        prop_assert_eq!(out.color.dims(), &[counts.len(), 3]);
        read_and_backward(&[&out.color, &out.depth, &out.opacity], &[&sigmas, &colors]);
    }

    #[test]
    fn mlp_and_encoding_with_zero_points(
        n in 0usize..3, f64_ in any::<bool>(), reference in any::<bool>(), code_dim in 0usize..2
    ) {
        let dt = dtype(f64_);
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, dt, &Device::Cpu);
        let config = MlpConfig {
            depth: 3,
            hidden: 8,
            out_dim: 2,
            code_dim,
            activation: Activation::Softplus { beta: 10.0 },
            skips: vec![1],
            encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 2).unwrap()),
            force_reference: reference,
            ..MlpConfig::default()
        };
        let net = mlp(&config, vb).unwrap();
        let points = var(&[n, 3], dt);
        let codes = var(&[n, code_dim], dt);
        let code = (code_dim > 0).then(|| codes.as_tensor());
        let (y, jac) = net.forward_with_jacobian(points.as_tensor(), code).unwrap();
        prop_assert_eq!(y.dims(), &[n, 2]);
        prop_assert_eq!(jac.dims(), &[n, 3, 2]);
        let lens = read_and_backward(&[&y, &jac], &[&points]);
        prop_assert!(lens[0] == 0 || lens[0] == 3 * n);
        if code_dim == 0 {
            let y = Field::forward(&net, points.as_tensor()).unwrap();
            read_and_backward(&[&y], &[&points]);
        }
        let pe = FrequencyEncoding::new(3, 2).unwrap();
        let e = pe.forward(points.as_tensor()).unwrap();
        prop_assert_eq!(e.dims(), &[n, 15]);
        read_and_backward(&[&e], &[&points]);
    }

    #[test]
    fn nerf_with_zero_points(n in 0usize..3, f64_ in any::<bool>()) {
        let dt = dtype(f64_);
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, dt, &Device::Cpu);
        let net = nerf(&NerfConfig { width: 8, color_width: 8, ..NerfConfig::default() }, vb).unwrap();
        let p = var(&[n, 3], dt);
        let d = var(&[n, 3], dt);
        let (sigma, rgb) = net.radiance(p.as_tensor(), d.as_tensor()).unwrap();
        prop_assert_eq!(sigma.dims(), &[n]);
        prop_assert_eq!(rgb.dims(), &[n, 3]);
        read_and_backward(&[&sigma, &rgb], &[&p, &d]);
    }
}

#[cfg(feature = "texture")]
proptest! {
    #![proptest_config(ProptestConfig::with_cases(16))]

    #[test]
    fn joint_decoder_colours_zero_points(n in 0usize..3, f64_ in any::<bool>(), reference in any::<bool>()) {
        use neural_fields::field::ImplicitSurface;
        use neural_fields::texture::joint_decoder;
        use neural_fields::texture::{TextureField, TextureInput};
        let dt = dtype(f64_);
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, dt, &Device::Cpu);
        let config = MlpConfig { depth: 2, hidden: 8, force_reference: reference, ..MlpConfig::default() };
        let net = joint_decoder(&config, vb).unwrap();
        let p = var(&[n, 3], dt);
        let rgb = net.rgb(&TextureInput::new(p.as_tensor())).unwrap();
        prop_assert_eq!(rgb.dims(), &[n, 3]);
        let (value, grad) = net.value_and_grad(p.as_tensor()).unwrap();
        prop_assert_eq!(grad.dims(), &[n, 3]);
        read_and_backward(&[&rgb, &value, &grad], &[&p]);
    }
}
