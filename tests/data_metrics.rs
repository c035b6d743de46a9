//! PSNR and SSIM against scikit-image's values (recorded by
//! `python3 tests/data/metrics/make_reference.py`), and the picture writers.
#![cfg(feature = "data")]

mod common;

use candle_core::{DType, Device, Tensor};
use common::datasets::scratch;
use neural_fields::data::{colorize_depth, comparison_strip, psnr, ssim, write_png, Image};
use neural_fields::Error;
use std::path::Path;

const DIR: &str = "tests/data/metrics";

/// A PNG as `[H, W, C]` (or `[H, W]` for grey) of `byte / 255` in `dtype`.
fn read(name: &str, dtype: DType) -> Tensor {
    let img = image::open(Path::new(DIR).join(name)).unwrap();
    let (w, h) = (img.width() as usize, img.height() as usize);
    let t = match img.color().channel_count() {
        1 => Tensor::from_vec(img.into_luma8().into_raw(), (h, w), &Device::Cpu),
        _ => Tensor::from_vec(img.into_rgb8().into_raw(), (h, w, 3), &Device::Cpu),
    }
    .unwrap();
    (t.to_dtype(dtype).unwrap() / 255.0).unwrap()
}

#[test]
fn ssim_and_psnr_match_scikit_image() {
    let expected: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(Path::new(DIR).join("expected.json")).unwrap(),
    )
    .unwrap();
    let pairs = expected["pairs"].as_array().unwrap();
    assert_eq!(pairs.len(), 4);
    for dtype in [DType::F64, DType::F32] {
        for pair in pairs {
            let a = read(pair["a"].as_str().unwrap(), dtype);
            let b = read(pair["b"].as_str().unwrap(), dtype);
            let name = pair["name"].as_str().unwrap();
            let s = ssim(&a, &b, None).unwrap();
            let want = pair["ssim"].as_f64().unwrap();
            assert!(
                (s - want).abs() < 1e-4,
                "{name} {dtype:?}: ssim {s} vs {want}"
            );
            if dtype == DType::F64 {
                // In f64 the same arithmetic agrees far beyond the required 1e-4.
                assert!((s - want).abs() < 1e-10, "{name}: ssim {s} vs {want}");
            }
            let p = psnr(&a, &b, None).unwrap();
            match &pair["psnr"] {
                serde_json::Value::String(inf) => {
                    assert_eq!(inf, "inf");
                    assert_eq!(p, f64::INFINITY, "{name}");
                }
                v => {
                    let want = v.as_f64().unwrap();
                    assert!(
                        (p - want).abs() < 1e-4,
                        "{name} {dtype:?}: psnr {p} vs {want}"
                    );
                }
            }
        }
    }
}

#[test]
fn masked_metrics_count_only_masked_pixels() {
    let a = read("rgb64x48_a.png", DType::F64);
    let b = read("rgb64x48_b.png", DType::F64);
    // Mask out the left half: the masked PSNR is the PSNR of the right half alone.
    let mask = Tensor::cat(
        &[
            Tensor::zeros((48, 32), DType::F64, &Device::Cpu).unwrap(),
            Tensor::ones((48, 32), DType::F64, &Device::Cpu).unwrap(),
        ],
        1,
    )
    .unwrap();
    let right = |t: &Tensor| t.narrow(1, 32, 32).unwrap();
    let masked = psnr(&a, &b, Some(&mask)).unwrap();
    assert!((masked - psnr(&right(&a), &right(&b), None).unwrap()).abs() < 1e-12);
    // A full mask changes nothing; an empty one is an error naming the mask.
    let ones = Tensor::ones((48, 64), DType::F64, &Device::Cpu).unwrap();
    assert_eq!(
        ssim(&a, &b, Some(&ones)).unwrap(),
        ssim(&a, &b, None).unwrap()
    );
    let zeros = ones.zeros_like().unwrap();
    assert!(matches!(
        psnr(&a, &b, Some(&zeros)),
        Err(Error::InvalidArgument { arg: "mask", .. })
    ));
    assert!(matches!(
        ssim(&a, &b, Some(&zeros)),
        Err(Error::InvalidArgument { arg: "mask", .. })
    ));
    // Masked SSIM differs from the unmasked one on this pair (the shift is not uniform).
    let s_masked = ssim(&a, &b, Some(&mask)).unwrap();
    assert!(s_masked.is_finite() && (s_masked - ssim(&a, &b, None).unwrap()).abs() > 1e-6);
}

#[test]
fn metrics_of_extreme_images_are_finite_or_infinite_never_nan() {
    let black = Tensor::zeros((16, 16, 3), DType::F32, &Device::Cpu).unwrap();
    let white = Tensor::ones((16, 16, 3), DType::F32, &Device::Cpu).unwrap();
    assert_eq!(psnr(&black, &black, None).unwrap(), f64::INFINITY);
    assert_eq!(psnr(&black, &white, None).unwrap(), 0.0);
    assert_eq!(ssim(&black, &black, None).unwrap(), 1.0);
    let s = ssim(&black, &white, None).unwrap();
    assert!(s.is_finite() && s.abs() < 1e-3, "{s}");
}

#[test]
fn metrics_refuse_bad_input_naming_the_argument() {
    let a = Tensor::zeros((16, 16, 3), DType::F64, &Device::Cpu).unwrap();
    let arg = |r: neural_fields::Result<f64>| match r {
        Err(Error::InvalidArgument { arg, .. }) => arg,
        other => panic!("{other:?}"),
    };
    let small = Tensor::zeros((10, 16, 3), DType::F64, &Device::Cpu).unwrap();
    assert_eq!(arg(ssim(&small, &small, None)), "pred");
    assert_eq!(arg(psnr(&a, &small, None)), "target");
    let nan = (a.clone() * f64::NAN).unwrap();
    assert_eq!(arg(psnr(&nan, &a, None)), "pred");
    assert_eq!(arg(ssim(&a, &nan, None)), "target");
    let empty = Tensor::zeros((0, 16, 3), DType::F64, &Device::Cpu).unwrap();
    assert_eq!(arg(psnr(&empty, &empty, None)), "pred");
    let rank4 = Tensor::zeros((1, 16, 16, 3), DType::F64, &Device::Cpu).unwrap();
    assert_eq!(arg(psnr(&rank4, &rank4, None)), "pred");
    let mask = Tensor::ones((16, 15), DType::F64, &Device::Cpu).unwrap();
    assert_eq!(arg(psnr(&a, &a, Some(&mask))), "mask");
}

#[test]
fn png_writer_round_trips_bytes_and_refuses_nan() {
    let dir = scratch("png-writer");
    let data: Vec<u8> = (0..5 * 7 * 4).map(|i| (i * 7 % 256) as u8).collect();
    let img = Image::new(7, 5, 4, data.clone()).unwrap();
    for dtype in [DType::F32, DType::F64] {
        let t = (Tensor::from_slice(img.data(), (5, 7, 4), &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
            / 255.0)
            .unwrap();
        let path = dir.join(format!("rgba-{dtype:?}.png"));
        write_png(&path, &t).unwrap();
        let back = image::open(&path).unwrap().into_rgba8().into_raw();
        assert_eq!(back, data, "{dtype:?}");
    }
    // Opacity as a grey [H, W] picture.
    let opacity = Tensor::new(&[[0.0f32, 0.5], [1.0, 2.0]], &Device::Cpu).unwrap();
    write_png(&dir.join("opacity.png"), &opacity).unwrap();
    let grey = image::open(dir.join("opacity.png"))
        .unwrap()
        .into_luma8()
        .into_raw();
    assert_eq!(grey, vec![0, 128, 255, 255]);
    let nan = Tensor::new(&[[f32::NAN]], &Device::Cpu).unwrap();
    assert!(matches!(
        write_png(&dir.join("nan.png"), &nan),
        Err(Error::InvalidArgument { arg: "image", .. })
    ));
    assert!(!dir.join("nan.png").exists());
    // A path in a missing folder is an I/O error naming it.
    let e = write_png(&dir.join("missing/x.png"), &opacity).unwrap_err();
    assert!(
        matches!(&e, Error::Io { path, .. } if path.ends_with("missing/x.png")),
        "{e}"
    );
}

#[test]
fn depth_colour_map_reports_its_range_and_blacks_out_non_finite_depths() {
    let depth = Tensor::new(&[[2.0f64, 3.0], [6.0, f64::NAN]], &Device::Cpu).unwrap();
    let (rgb, range) = colorize_depth(&depth, None).unwrap();
    assert_eq!(range, (2.0, 6.0));
    assert_eq!(rgb.dims(), &[2, 2, 3]);
    let px: Vec<Vec<Vec<f64>>> = rgb.to_vec3().unwrap();
    assert_eq!(px[1][1], vec![0.0; 3]);
    // A quarter of the range is blue-ish, the far end red-ish (turbo).
    assert!(
        px[0][1][2] > px[0][1][0] && px[1][0][0] > px[1][0][2],
        "{px:?}"
    );
    let (_, fixed) = colorize_depth(&depth, Some((0.0, 10.0))).unwrap();
    assert_eq!(fixed, (0.0, 10.0));
    assert!(colorize_depth(&depth, Some((1.0, 1.0))).is_err());
    // Constant depth still maps (to the low end) without NaN.
    let flat = Tensor::full(4.0f32, (3, 3), &Device::Cpu).unwrap();
    let (c, _) = colorize_depth(&flat, None).unwrap();
    assert!(c
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
        .iter()
        .all(|x| x.is_finite()));
}

#[test]
fn strips_and_normal_pictures_have_the_documented_layout() {
    let gt = Tensor::full(0.25f32, (4, 5, 3), &Device::Cpu).unwrap();
    let pred = Tensor::full(0.5f32, (4, 5, 3), &Device::Cpu).unwrap();
    let strip = comparison_strip(&gt, &pred).unwrap();
    assert_eq!(strip.dims(), &[4, 15, 3]);
    let v: Vec<Vec<Vec<f32>>> = strip.to_vec3().unwrap();
    assert_eq!(v[0][0], vec![0.25; 3]);
    assert_eq!(v[0][5], vec![0.5; 3]);
    // An error of 0.25 is the top of the scale: turbo's dark red end.
    assert!(v[0][10][0] > 0.4 && v[0][10][2] < 0.1, "{:?}", v[0][10]);
    let n = Tensor::new(&[[[0.0f32, 0.0, 1.0], [-1.0, 0.0, 0.0]]], &Device::Cpu).unwrap();
    // Normals as colours (n + 1) / 2, as the module documentation writes them.
    let c: Vec<Vec<Vec<f32>>> = n.affine(0.5, 0.5).unwrap().to_vec3().unwrap();
    assert_eq!(c[0], vec![vec![0.5, 0.5, 1.0], vec![0.0, 0.5, 0.5]]);
    assert!(comparison_strip(&gt, &gt.narrow(1, 0, 4).unwrap()).is_err());
}
