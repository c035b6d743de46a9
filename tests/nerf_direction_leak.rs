//! Regression: `NerfConfig { direction_encoding: None, .. }` is documented as a
//! view-independent colour, but the colour head received the raw unit direction (the
//! identity encoding) and so still depended on the view. Only directions of the same unit
//! vector were compared, which hid it. Now the head sees the zero vector.

mod common;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use common::v64;
use neural_fields::nn::build_seeded;
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{nerf, NerfConfig};

fn colours(force_reference: bool, dtype: DType) -> (Vec<f64>, Vec<f64>, Option<Tensor>) {
    let config = NerfConfig {
        direction_encoding: None,
        width: 16,
        color_width: 8,
        force_reference,
        ..NerfConfig::default()
    };
    let varmap = VarMap::new();
    let net = build_seeded(&varmap, dtype, &Device::Cpu, 11, |vb| nerf(&config, vb)).unwrap();
    let mut rng = SplitMix64::new(3);
    let p = rng
        .uniform_tensor(&[64, 3], -1.0, 1.0, dtype, &Device::Cpu)
        .unwrap();
    let d1 = rng
        .uniform_tensor(&[64, 3], -1.0, 1.0, dtype, &Device::Cpu)
        .unwrap();
    let d2 = rng
        .uniform_tensor(&[64, 3], -1.0, 1.0, dtype, &Device::Cpu)
        .unwrap();
    let d1 = candle_core::Var::from_tensor(&d1).unwrap();
    let (_, a) = net.radiance(&p, d1.as_tensor()).unwrap();
    let (_, b) = net.radiance(&p, &d2).unwrap();
    let grads = a.sum_all().unwrap().backward().unwrap();
    (v64(&a), v64(&b), grads.get(d1.as_tensor()).cloned())
}

#[test]
fn without_a_direction_encoding_the_colour_ignores_the_view() {
    for dtype in [DType::F32, DType::F64] {
        for force_reference in [false, true] {
            let (a, b, grad) = colours(force_reference, dtype);
            assert_eq!(a, b, "{dtype:?}, reference path {force_reference}");
            // The colour is constant in the direction: no gradient reaches it, or a zero one.
            if let Some(g) = grad {
                let g = v64(&g);
                assert!(g.iter().all(|&x| x == 0.0), "{g:?}");
            }
        }
    }
}
