//! Stiff cases of `data`: views, datasets, ray batches, image conversions, metrics and
//! image output at extreme values.

#![cfg(feature = "data")]

mod common;

use candle_core::{DType, Device, Tensor};

use common::stiff::{magnitudes, Expect, Suite, DTYPES};

use neural_fields::camera::{Camera, Convention, Intrinsics, PixelFilter};
use neural_fields::glam::{DAffine3, DVec3};

#[test]
fn data_stays_finite() {
    let mut s = Suite::default();
    sweep_data(&mut s);
    s.finish("data", DATA);
}

#[test]
fn every_public_data_function_is_swept_or_exempt() {
    common::stiff::check_coverage("stiff_cases_data", &[DATA], EXEMPT, &[], &[]);
}

/// Items swept by `sweep_data`.
const DATA: &[&str] = &[
    "data::Dataset::new",
    "data::Dataset::visual_hull",
    "data::RaySampler::new",
    "data::RaySampler::patches",
    "data::RaySampler::pixel_footprints",
    "data::RaySampler::pixels",
    "data::RaySampler::with_pixel_filter",
    "data::View::mask",
    "data::View::new",
    "data::View::rgb",
    "data::colorize_depth",
    "data::comparison_strip",
    "data::generate_shape",
    "data::load",
    "data::load_shape_collection",
    "data::psnr",
    "data::ssim",
    "data::write_blender",
    "data::write_png",
    "data::write_shape_collection",
    "data::write_shape_views",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    (
        "data::Dataset::coverage",
        "counts mask pixels (bytes); no float input",
    ),
    (
        "data::Dataset::hash_finest",
        "a resolution from the images' integer sizes",
    ),
    (
        "data::Dataset::scene_box",
        "the bounds the layout states or the given cube; checked in tests/data_loaders.rs",
    ),
    (
        "data::load_eval",
        "a loader: load's checks, with the split chosen by the files present",
    ),
    (
        "data::Dataset::with_poses",
        "moves the cameras: Camera::new's checks, swept",
    ),
    ("data::Background::", "constants"),
    ("data::Dataset::background", "getter"),
    ("data::Dataset::bounds", "getter"),
    ("data::Dataset::views", "getter"),
    ("data::LoadConfig::default", "constant"),
    ("data::View::camera", "getter"),
    ("data::View::image", "getter"),
    ("data::View::name", "getter"),
    ("data::Image::data", "getter"),
    ("data::Image::new", "bytes, no floats"),
    ("data::Image::size", "getter"),
    ("data::ShapeCategory::fmt", "the category's name"),
    ("data::ShapeCollectionConfig::default", "constant"),
    ("data::ShapeLoadConfig::default", "constant"),
];

fn sweep_data(s: &mut Suite) {
    use neural_fields::data::{
        colorize_depth, comparison_strip, load, psnr, ssim, write_blender, write_png, Background,
        Dataset, Image, LoadConfig, RaySampler, Split, View,
    };
    let d = Device::Cpu;
    let scalar = |x: f64| Ok::<_, neural_fields::Error>(Tensor::new(x, &d)?);
    let dir = std::env::temp_dir().join(format!("neural-fields-stiff-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for dtype in DTYPES {
        for &x in &magnitudes(dtype) {
            let tag = format!("{dtype:?}, {x}");
            let full = |shape: &[usize]| Tensor::full(x, shape, &d).and_then(|t| t.to_dtype(dtype));
            let half =
                |shape: &[usize]| Tensor::full(0.5, shape, &d).and_then(|t| t.to_dtype(dtype));
            s.case("data::psnr", &tag, Expect::FiniteOrErr, &[], || {
                let p = psnr(&full(&[12, 12, 3])?, &half(&[12, 12, 3])?, None)?;
                // Identical images (x = 0.5) give +∞ by contract; never NaN or −∞.
                assert!(!p.is_nan() && p != f64::NEG_INFINITY);
                Ok(if p == f64::INFINITY {
                    vec![]
                } else {
                    vec![scalar(p)?]
                })
            });
            s.case("data::ssim", &tag, Expect::FiniteOrErr, &[], || {
                let p = ssim(&full(&[12, 12, 3])?, &half(&[12, 12, 3])?, None)?;
                Ok(vec![scalar(p)?])
            });
            s.case("data::colorize_depth", &tag, Expect::Finite, &[], || {
                let depth = Tensor::cat(&[&full(&[2, 2])?, &half(&[2, 2])?], 1)?;
                let (rgb, (lo, hi)) = colorize_depth(&depth, None)?;
                Ok(vec![rgb, scalar(lo)?, scalar(hi)?])
            });
            s.case(
                "data::comparison_strip",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    Ok(vec![comparison_strip(
                        &half(&[2, 2, 3])?,
                        &full(&[2, 2, 3])?,
                    )?])
                },
            );
            // Four channels (RGBA) through the quantisation write_png does.
            s.case(
                "data::write_png",
                format!("{tag}, RGBA"),
                Expect::Finite,
                &[],
                || {
                    write_png(&dir.join("stiff_rgba.png"), &full(&[2, 3, 4])?)?;
                    Ok(vec![])
                },
            );
            s.case("data::write_png", &tag, Expect::Finite, &[], || {
                write_png(&dir.join("stiff.png"), &full(&[2, 3, 3])?)?;
                Ok(vec![])
            });
            s.case(
                "data::Dataset::visual_hull",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    // Two views of a centred blob (an 8 × 8 RGBA image, a 2 × 2 foreground),
                    // margin x.
                    let k = Intrinsics::new(8.0, 8.0, 4.0, 4.0, 8, 8)?;
                    let mut px = vec![0u8; 8 * 8 * 4];
                    for (u, v) in [(3, 3), (3, 4), (4, 3), (4, 4)] {
                        px[(v * 8 + u) * 4 + 3] = 255;
                    }
                    let views = [DVec3::new(0.0, 0.0, -3.0), DVec3::new(3.0, 0.0, 0.0)]
                        .into_iter()
                        .enumerate()
                        .map(|(i, eye)| {
                            let cam =
                                Camera::look_at(k, eye, DVec3::ZERO, DVec3::Y, Convention::OpenCv)?;
                            View::new(cam, Image::new(8, 8, 4, px.clone())?, None, format!("v{i}"))
                        })
                        .collect::<neural_fields::Result<Vec<_>>>()?;
                    let data = Dataset::new(views, Background::Color([1.0; 3]), None)?;
                    let b = data.visual_hull(x)?.expect("a foreground in every view");
                    Ok(vec![Tensor::new(&b[..], &d)?])
                },
            );
            s.case("data::Dataset::new", &tag, Expect::FiniteOrErr, &[], || {
                let k = Intrinsics::new(3.0, 3.0, 1.0, 1.0, 2, 2)?;
                let cam = Camera::new(k, DAffine3::IDENTITY, Convention::OpenCv)?;
                let view = View::new(cam, Image::new(2, 2, 3, vec![9; 12])?, None, "v".into())?;
                let data = Dataset::new(vec![view], Background::Color([x; 3]), None)?;
                Ok(vec![data.views()[0].rgb(
                    [x.clamp(0.0, 1.0); 3],
                    &d,
                    dtype,
                )?])
            });
        }
        s.case(
            "data::write_png",
            format!("{dtype:?}, bytes 0 and 255"),
            Expect::Finite,
            &[],
            || {
                let img = Image::new(2, 1, 3, vec![0, 0, 0, 255, 255, 255])?;
                write_png(&dir.join("stiff_ends.png"), &image_tensor(&img, &d, dtype)?)?;
                Ok(vec![image_tensor(&img, &d, dtype)?])
            },
        );
        // Cameras at extreme focal lengths and distances: rays finite or an error.
        for (f, eye) in [(1e-6, 1.0), (1e8, 1.0), (500.0, 1e10), (500.0, 1e-10)] {
            let tag = format!("{dtype:?}, fx {f}, eye at {eye}");
            let view = || -> neural_fields::Result<View> {
                let k = Intrinsics::new(f, f, 2.0, 2.0, 4, 4)?;
                let cam = Camera::look_at(
                    k,
                    DVec3::new(eye, 0.0, 0.0),
                    DVec3::ZERO,
                    DVec3::Z,
                    Convention::OpenGl,
                )?;
                View::new(
                    cam,
                    Image::new(4, 4, 4, (0..64).map(|i| (i * 4) as u8).collect())?,
                    None,
                    "v".into(),
                )
            };
            s.case("data::View::new", &tag, Expect::Finite, &[], || {
                let v = view()?;
                Ok(vec![
                    v.rgb([0.0; 3], &d, dtype)?,
                    v.mask(&d, dtype)?.expect("alpha"),
                ])
            });
            s.case("data::View::rgb", &tag, Expect::Finite, &[], || {
                Ok(vec![view()?.rgb([1.0; 3], &d, dtype)?])
            });
            s.case("data::View::mask", &tag, Expect::Finite, &[], || {
                Ok(view()?.mask(&d, dtype)?.into_iter().collect())
            });
            let data = Dataset::new(vec![view().unwrap()], Background::Random, None).unwrap();
            s.case(
                "data::RaySampler::new",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    RaySampler::new(&data, 0, &d, dtype)?;
                    Ok(vec![])
                },
            );
            s.case(
                "data::RaySampler::pixels",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let b = RaySampler::new(&data, 0, &d, dtype)?.pixels(64)?;
                    Ok(vec![
                        b.rays.directions().clone(),
                        b.rays.origins().clone(),
                        b.colors,
                        b.backgrounds,
                    ])
                },
            );
            s.case(
                "data::RaySampler::pixel_footprints",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let b = RaySampler::new(&data, 0, &d, dtype)?
                        .with_pixel_filter(PixelFilter::Box, true)?
                        .pixel_footprints(16, 2)?;
                    Ok(vec![b.rays.directions().clone(), b.colors, b.backgrounds])
                },
            );
            for half_width in [1.5, 64.0, 0.0, f64::INFINITY] {
                s.case(
                    "data::RaySampler::with_pixel_filter",
                    format!("{tag}, Blackman-Harris ±{half_width}"),
                    Expect::FiniteOrErr,
                    &[],
                    || {
                        let filter = PixelFilter::BlackmanHarris { half_width };
                        let mut sampler = RaySampler::new(&data, 0, &d, dtype)?
                            .with_pixel_filter(filter, true)?;
                        let (a, b) = (sampler.pixels(64)?, sampler.pixel_footprints(16, 3)?);
                        Ok(vec![
                            a.rays.directions().clone(),
                            b.rays.directions().clone(),
                        ])
                    },
                );
            }
            s.case(
                "data::RaySampler::patches",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let b = RaySampler::new(&data, 0, &d, dtype)?.patches(4, 3)?;
                    Ok(vec![b.rays.directions().clone(), b.colors])
                },
            );
            s.case(
                "data::write_blender",
                &tag,
                Expect::FiniteOrErr,
                &[],
                || {
                    let out = dir.join(format!("blender-{f}-{eye}"));
                    write_blender(&out, Split::Test, &data)?;
                    let back = load(
                        &out,
                        &LoadConfig {
                            split: Split::Test,
                            ..LoadConfig::default()
                        },
                    )?;
                    Ok(vec![back.views()[0].rgb([0.0; 3], &d, dtype)?])
                },
            );
        }
    }
    for downscale in [1, 7, 100, 101, usize::MAX] {
        s.case(
            "data::load",
            format!("downscale {downscale}"),
            Expect::FiniteOrErr,
            &[],
            || {
                let data = load(
                    std::path::Path::new("examples/data/wuson"),
                    &LoadConfig {
                        split: Split::Val,
                        downscale,
                        ..LoadConfig::default()
                    },
                )?;
                Ok(vec![data.views()[0].rgb([1.0; 3], &d, DType::F32)?])
            },
        );
    }
    sweep_shapes(s, &dir);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The procedural shape collection: every category's tree evaluated at extreme points,
/// collections written with extreme padding and noise, and views of extreme values.
fn sweep_shapes(s: &mut Suite, dir: &std::path::Path) {
    use neural_fields::data::{
        generate_shape, load_shape_collection, write_shape_collection, write_shape_views,
        ShapeCategory, ShapeCollectionConfig, ShapeLoadConfig,
    };
    use neural_fields::field::SignedDistance;
    let d = Device::Cpu;
    for dtype in DTYPES {
        for &x in &magnitudes(dtype) {
            for category in ShapeCategory::ALL {
                s.case(
                    "data::generate_shape",
                    format!("{dtype:?}, {category} at ({x}, −{x}, {x})"),
                    Expect::Finite,
                    &[],
                    || {
                        let shape = generate_shape(category, 7, &d, dtype)?;
                        let p = Tensor::new(&[[x, -x, x], [x, 0.0, 0.0]], &d)?.to_dtype(dtype)?;
                        let (dist, grad) = shape.distance_and_grad(&p)?;
                        Ok(vec![dist, grad])
                    },
                );
            }
        }
    }
    let collection = dir.join("shapes");
    for &x in &magnitudes(DType::F64) {
        let config = ShapeCollectionConfig {
            seed: x.to_bits(),
            categories: vec![ShapeCategory::ALL[x.to_bits() as usize % 5]],
            shapes_per_category: 1,
            uniform_points: 32,
            near_points: 16,
            near_sigmas: vec![x.abs().clamp(1e-300, 1.0)],
            surface_points: 16,
            voxel_resolution: 4,
            padding: x,
            ..ShapeCollectionConfig::default()
        };
        let points =
            |shape: &neural_fields::data::ShapeSample| -> neural_fields::Result<Vec<Tensor>> {
                Ok(vec![
                    Tensor::new(&shape.uniform_points[..], &d)?,
                    Tensor::new(&shape.near_points[..], &d)?,
                    Tensor::new(&shape.surface_points[..], &d)?,
                    Tensor::new(&shape.surface_normals[..], &d)?,
                ])
            };
        s.case(
            "data::write_shape_collection",
            format!("padding and σ from {x}"),
            Expect::FiniteOrErr,
            &[],
            || {
                write_shape_collection(&collection, &config)?;
                let loaded = load_shape_collection(&collection, &ShapeLoadConfig::default())?;
                points(&loaded.shapes[0])
            },
        );
        s.case(
            "data::load_shape_collection",
            format!("padding and σ from {x}"),
            Expect::FiniteOrErr,
            &[],
            || {
                let loaded = load_shape_collection(&collection, &ShapeLoadConfig::default())?;
                points(&loaded.shapes[0])
            },
        );
    }
    for dtype in DTYPES {
        for &x in &magnitudes(dtype) {
            s.case(
                "data::write_shape_views",
                format!("{dtype:?}, pixels {x}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let k = Intrinsics::new(4.0, 4.0, 1.5, 1.5, 3, 3)?;
                    let cam = Camera::look_at(
                        k,
                        DVec3::new(0.0, 0.0, 2.0),
                        DVec3::ZERO,
                        DVec3::Y,
                        Convention::OpenCv,
                    )?;
                    let image = Tensor::full(x, (3, 3, 3), &d)?.to_dtype(dtype)?;
                    write_shape_views(&collection, 0, &[(cam, image)])?;
                    let loaded = load_shape_collection(&collection, &ShapeLoadConfig::default())?;
                    let bytes = loaded.shapes[0].views[0].image.data().to_vec();
                    Ok(vec![Tensor::new(&bytes[..], &d)?.to_dtype(dtype)?])
                },
            );
        }
    }
}

/// An image's bytes as a `[H, W, C]` tensor of `byte / 255` in `dtype` on `device`.
fn image_tensor(
    img: &neural_fields::data::Image,
    device: &Device,
    dtype: DType,
) -> neural_fields::Result<Tensor> {
    let (w, h, c) = img.size();
    let t = Tensor::from_slice(img.data(), (h, w, c), device)?;
    Ok((t.to_dtype(dtype)? / 255.0)?)
}
