//! The hash grid refused NaN positions but clamped infinite ones into its box, answering
//! the features of a face for a point that is nowhere; ±∞ is now refused as NaN is.

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use neural_fields::encoding::{hash_grid, Encoding, HashGridConfig};

#[test]
fn infinite_positions_are_refused_as_nan_is() {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    for force_reference in [false, true] {
        let config = HashGridConfig {
            force_reference,
            ..HashGridConfig::default()
        };
        let grid = hash_grid(&config, vb.pp(format!("g{force_reference}"))).unwrap();
        for bad in [f32::INFINITY, f32::NEG_INFINITY, f32::NAN] {
            let x = Tensor::new(&[[0.1f32, 0.2, 0.3], [bad, 0.0, 0.0]], &Device::Cpu).unwrap();
            let e = grid.forward(&x).unwrap_err().to_string();
            assert!(e.starts_with("x: "), "{e}");
        }
        let x = Tensor::new(&[[0.1f32, 0.2, 0.3], [5.0, -5.0, 0.0]], &Device::Cpu).unwrap();
        assert!(
            grid.forward(&x).is_ok(),
            "finite points outside the box are clamped"
        );
    }
}
