//! Regression: a NaN (or infinite) colour composited to a NaN pixel and NaN density
//! gradients without an error, while a NaN density was rejected.
#![cfg(feature = "volume")]

use candle_core::{DType, Device, Tensor};
use neural_fields::volume::{composite, stratified, CompositeConfig, Jitter};
use neural_fields::Error;

#[test]
fn nan_or_infinite_colour_is_an_error_naming_colors() {
    let dev = Device::Cpu;
    for dtype in [DType::F32, DType::F64] {
        let near = Tensor::zeros(2, dtype, &dev).unwrap();
        let far = Tensor::ones(2, dtype, &dev).unwrap();
        let iv = stratified(&near, &far, 4, Jitter::None, 0).unwrap();
        let sigmas = Tensor::ones((2, 4), dtype, &dev).unwrap();
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let mut c = vec![0.5f64; 2 * 4 * 3];
            c[13] = bad;
            let colors = Tensor::from_vec(c, (2, 4, 3), &dev)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            for force_reference in [false, true] {
                let config = CompositeConfig {
                    force_reference,
                    ..CompositeConfig::default()
                };
                match composite(&sigmas, &colors, &iv, None, &config) {
                    Err(Error::InvalidArgument { arg, got, .. }) => {
                        assert_eq!(arg, "colors");
                        assert!(got.contains("flat index 13"), "{got}");
                    }
                    other => {
                        panic!("{dtype:?} {bad}: expected an error naming colors, got {other:?}")
                    }
                }
            }
        }
        // Finite colours of any sign and size still composite.
        let colors = Tensor::full(-1e30f64, (2, 4, 3), &dev)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        assert!(composite(&sigmas, &colors, &iv, None, &CompositeConfig::default()).is_ok());
    }
}
