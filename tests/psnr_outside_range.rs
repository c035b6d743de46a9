//! `data::psnr` of images outside their data range [0, 1] (an image in [0, 255]) returned
//! −33 dB without a word; `psnr` and `ssim` now refuse such values naming the argument.

use candle_core::{DType, Device, Tensor};
use neural_fields::data::{psnr, ssim};

#[test]
fn images_outside_zero_one_are_refused_naming_the_argument() {
    let dev = Device::Cpu;
    let ok = Tensor::full(0.5f64, (16, 16, 3), &dev).unwrap();
    let bytes = Tensor::full(200.0f64, (16, 16, 3), &dev).unwrap();
    let negative = Tensor::full(-0.5f64, (16, 16, 3), &dev).unwrap();
    for (pred, target, arg) in [
        (&bytes, &ok, "pred"),
        (&ok, &bytes, "target"),
        (&negative, &ok, "pred"),
    ] {
        for e in [psnr(pred, target, None), ssim(pred, target, None)] {
            let e = e.unwrap_err().to_string();
            assert!(
                e.starts_with(&format!("{arg}: ")) && e.contains("[0, 1]"),
                "{e}"
            );
        }
    }
    // The ends of the range, and a rounding hair past them, are in it.
    let one = Tensor::ones((16, 16, 3), DType::F32, &dev).unwrap();
    let hair = (one.clone() + 1e-6).unwrap();
    assert!(psnr(&one, &hair, None).unwrap() > 100.0);
    assert!(ssim(&one.zeros_like().unwrap(), &one, None).is_ok());
}
