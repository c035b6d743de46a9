//! The committed dataset's cameras against Blender's own projections, and the ray batches:
//! seeded, consistent with the camera module, with the colours, masks and backgrounds of
//! their pixels.
#![cfg(feature = "data")]

mod common;

/// The default configuration for one split.
fn of_split(split: Split) -> LoadConfig {
    LoadConfig {
        split,
        ..LoadConfig::default()
    }
}

use candle_core::{DType, Device, IndexOp, Tensor};
use common::v64;
use neural_fields::camera::{Camera, Convention, Intrinsics, PixelFilter};
use neural_fields::data::{
    load, Background, Dataset, DatasetLayout, Image, LoadConfig, RaySampler, Split, View,
};
use neural_fields::glam::{DVec2, DVec3};
use neural_fields::Error;
use std::path::Path;

const WUSON: &str = "examples/data/wuson";
const WUSON_DTU: &str = "examples/data/wuson_dtu";

fn json(path: &str) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn vec3(v: &serde_json::Value) -> DVec3 {
    DVec3::new(
        v[0].as_f64().unwrap(),
        v[1].as_f64().unwrap(),
        v[2].as_f64().unwrap(),
    )
}

/// Checks that `point` projects with `camera` to Blender's pixel, and that the ray through
/// Blender's pixel passes within half a pixel of `point`; returns the worst deviations in
/// pixels.
fn check_point(camera: &Camera, point: DVec3, blender: DVec2) -> (f64, f64) {
    let p = camera
        .project(point)
        .expect("the point is in front of the camera");
    let reprojection = (p.truncate() - blender).length();
    let (o, d) = common::camera_ray(camera, blender);
    // Distance of the point from the ray, in pixels at the point's depth (d has unit depth).
    let t = (point - o).dot(d) / d.length_squared();
    let miss = (o + d * t - point).length() / t * camera.intrinsics().fx;
    assert!(
        reprojection < 0.5 && miss < 0.5,
        "{reprojection} px, {miss} px"
    );
    (reprojection, miss)
}

#[test]
fn committed_blender_dataset_rays_pass_through_blender_projected_vertices() {
    let points = json(&format!("{WUSON}/points.json"));
    let verts: Vec<DVec3> = points["points"]
        .as_array()
        .unwrap()
        .iter()
        .map(vec3)
        .collect();
    let mut worst = (0.0f64, 0.0f64);
    let mut checked = 0;
    for (split, name) in [
        (Split::Train, "train"),
        (Split::Val, "val"),
        (Split::Test, "test"),
    ] {
        let data = load(Path::new(WUSON), &of_split(split)).unwrap();
        let frames = points["frames"][name].as_array().unwrap();
        assert_eq!(frames.len(), data.views().len());
        for (view, frame) in data.views().iter().zip(frames) {
            let file = frame["file_path"]
                .as_str()
                .unwrap()
                .trim_start_matches("./");
            assert!(
                view.name().ends_with(&format!("{file}.png")),
                "{}",
                view.name()
            );
            for (vert, px) in verts.iter().zip(frame["pixels"].as_array().unwrap()) {
                let px = DVec2::new(px[0].as_f64().unwrap(), px[1].as_f64().unwrap());
                let (a, b) = check_point(view.camera(), *vert, px);
                worst = (worst.0.max(a), worst.1.max(b));
                checked += 1;
            }
        }
    }
    assert_eq!(checked, 80 * 8);
    // Blender's own numbers agree to rounding, far inside the half pixel required.
    assert!(worst.0 < 1e-3 && worst.1 < 1e-3, "{worst:?}");
}

#[test]
fn committed_dtu_dataset_rays_pass_through_blender_projected_vertices() {
    let points = json(&format!("{WUSON_DTU}/points.json"));
    let scale = points["dtu_scale"].as_f64().unwrap() * 1.1; // scale_mat's radius (README)
    let offset = vec3(&points["dtu_offset"]);
    let verts: Vec<DVec3> = points["points"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| (vec3(p) - offset) / scale) // into the normalised frame of the cameras
        .collect();
    assert_eq!(
        common::datasets::detected_layout(Path::new(WUSON_DTU)),
        DatasetLayout::Dtu
    );
    let data = load(Path::new(WUSON_DTU), &of_split(Split::All)).unwrap();
    let frames = points["frames"].as_array().unwrap();
    assert_eq!(frames.len(), data.views().len());
    let mut worst = 0.0f64;
    for (view, frame) in data.views().iter().zip(frames) {
        assert!(view.name().ends_with(frame["image"].as_str().unwrap()));
        // A mask file: a mask, and no alpha channel it could come from.
        assert!(view.mask(&Device::Cpu, DType::F32).unwrap().is_some());
        assert_eq!(view.image().size().2, 3);
        for (vert, px) in verts.iter().zip(frame["pixels"].as_array().unwrap()) {
            assert!(vert.length() < 1.0, "inside the unit sphere");
            let px = DVec2::new(px[0].as_f64().unwrap(), px[1].as_f64().unwrap());
            let (a, b) = check_point(view.camera(), *vert, px);
            worst = worst.max(a).max(b);
        }
    }
    assert!(worst < 1e-3, "{worst}");
}

#[test]
fn committed_dataset_has_the_documented_splits_and_masks() {
    let counts: Vec<usize> = [Split::Train, Split::Val, Split::Test, Split::All]
        .into_iter()
        .map(|split| {
            load(Path::new(WUSON), &of_split(split))
                .unwrap()
                .views()
                .len()
        })
        .collect();
    assert_eq!(counts, [50, 10, 20, 80]);
    let test = load(Path::new(WUSON), &of_split(Split::Test)).unwrap();
    let dtu = load(Path::new(WUSON_DTU), &of_split(Split::All)).unwrap();
    // The DTU copy's masks are the Blender renders' alpha ≥ 0.5.
    for (a, b) in test.views().iter().zip(dtu.views()) {
        let alpha = a
            .mask(&Device::Cpu, DType::F64)
            .unwrap()
            .unwrap()
            .ge(0.5)
            .unwrap();
        let mask = b
            .mask(&Device::Cpu, DType::F64)
            .unwrap()
            .unwrap()
            .ge(0.5)
            .unwrap();
        let differ = alpha
            .ne(&mask)
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap()
            .sum_all()
            .unwrap();
        assert_eq!(differ.to_scalar::<f64>().unwrap(), 0.0);
    }
}

/// Two views of different sizes, RGBA with varying alpha.
fn two_views() -> Dataset {
    let views = [(10usize, 10usize, 0u8), (20, 12, 1)]
        .into_iter()
        .map(|(w, h, s)| {
            let k = Intrinsics::new(12.0, 11.0, w as f64 / 2.0, h as f64 / 2.0, w, h).unwrap();
            let eye = DVec3::new(3.0, -2.0 + f64::from(s), 1.0);
            let cam = Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenGl).unwrap();
            let data = common::datasets::pattern(w, h, 4, s);
            View::new(
                cam,
                Image::new(w, h, 4, data).unwrap(),
                None,
                format!("v{s}"),
            )
            .unwrap()
        })
        .collect();
    Dataset::new(views, Background::Color([0.2, 0.4, 0.6]), None).unwrap()
}

fn u32s(t: &Tensor) -> Vec<u32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

#[test]
fn sampled_rays_colours_and_masks_are_those_of_their_pixels() {
    let data = two_views();
    for dtype in [DType::F32, DType::F64] {
        let tol = if dtype == DType::F32 { 1e-6 } else { 1e-12 };
        let mut sampler = RaySampler::new(&data, 7, &Device::Cpu, dtype).unwrap();
        let batch = sampler.pixels(500).unwrap();
        assert_eq!(batch.colors.dtype(), dtype);
        let (views, pixels) = (u32s(&batch.views), u32s(&batch.pixels));
        let colors = v64(&batch.colors);
        let masks = v64(batch.masks.as_ref().unwrap());
        let bgs = v64(&batch.backgrounds);
        for i in 0..500 {
            let view = &data.views()[views[i] as usize];
            let (u, v) = (pixels[2 * i] as usize, pixels[2 * i + 1] as usize);
            let rgb = v64(&view
                .rgb([0.2, 0.4, 0.6], &Device::Cpu, DType::F64)
                .unwrap()
                .i((v, u))
                .unwrap());
            for c in 0..3 {
                assert!((colors[3 * i + c] - rgb[c]).abs() < tol);
                assert_eq!(bgs[3 * i + c] as f32, [0.2f32, 0.4, 0.6][c]);
            }
            let alpha = f64::from(common::datasets::pixel(view.image(), u, v)[3]) / 255.0;
            assert!((masks[i] - alpha).abs() < tol);
        }
        // The rays are the camera module's rays through the pixel centres.
        for view_index in 0..2u32 {
            let rows: Vec<usize> = (0..500).filter(|&i| views[i] == view_index).collect();
            let centres: Vec<f64> = rows
                .iter()
                .flat_map(|&i| {
                    [
                        f64::from(pixels[2 * i]) + 0.5,
                        f64::from(pixels[2 * i + 1]) + 0.5,
                    ]
                })
                .collect();
            let centres = Tensor::from_vec(centres, (rows.len(), 2), &Device::Cpu)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let want = data.views()[view_index as usize]
                .camera()
                .rays_for_pixels(&centres)
                .unwrap();
            let idx = Tensor::new(
                rows.iter().map(|&i| i as u32).collect::<Vec<_>>(),
                &Device::Cpu,
            )
            .unwrap();
            let got_d = v64(&batch.rays.directions().index_select(&idx, 0).unwrap());
            let got_o = v64(&batch.rays.origins().index_select(&idx, 0).unwrap());
            for (a, b) in got_d.iter().zip(v64(want.directions())) {
                assert!((a - b).abs() < 10.0 * tol, "{a} vs {b}");
            }
            for (a, b) in got_o.iter().zip(v64(want.origins())) {
                assert!((a - b).abs() < 10.0 * tol);
            }
        }
    }
}

#[test]
fn sampling_is_seeded_and_weighs_views_by_pixel_count() {
    let data = two_views();
    let draw = |seed| {
        let mut s = RaySampler::new(&data, seed, &Device::Cpu, DType::F32).unwrap();
        let b = s.pixels(30_000).unwrap();
        (u32s(&b.views), u32s(&b.pixels))
    };
    let (a, b, c) = (draw(1), draw(1), draw(2));
    assert_eq!(a, b);
    assert_ne!(a.1, c.1);
    // View 1 has 240 of the 340 pixels: that fraction of the rays, within 4.5 standard
    // deviations.
    let frac = a.0.iter().filter(|&&v| v == 1).count() as f64 / 30_000.0;
    let q = 240.0 / 340.0;
    let sd = (q * (1.0 - q) / 30_000.0f64).sqrt();
    assert!((frac - q).abs() < 4.5 * sd, "{frac}");
    // Every pixel index is inside its view.
    for i in 0..30_000 {
        let (w, h) = if a.0[i] == 0 { (10, 10) } else { (20, 12) };
        assert!(a.1[2 * i] < w && a.1[2 * i + 1] < h);
    }
}

#[test]
fn patches_are_k_by_k_blocks_of_adjacent_pixels_in_one_view() {
    let data = two_views();
    let mut sampler = RaySampler::new(&data, 3, &Device::Cpu, DType::F64).unwrap();
    let (count, k) = (40, 4);
    let batch = sampler.patches(count, k).unwrap();
    assert_eq!(batch.rays.len(), count * k * k);
    let (views, pixels) = (u32s(&batch.views), u32s(&batch.pixels));
    for p in 0..count {
        let base = p * k * k;
        let (u0, v0) = (pixels[2 * base], pixels[2 * base + 1]);
        for i in 0..k {
            for j in 0..k {
                let r = base + i * k + j;
                assert_eq!(views[r], views[base]);
                assert_eq!(
                    (pixels[2 * r], pixels[2 * r + 1]),
                    (u0 + j as u32, v0 + i as u32)
                );
            }
        }
    }
    // `colors` reshapes into the patches.
    assert_eq!(
        batch.colors.reshape((count, k, k, 3)).unwrap().dims(),
        &[count, k, k, 3]
    );
    // A patch as large as the smaller view still fits in both; larger fits only the wider.
    assert!(sampler.patches(5, 10).is_ok());
    let wide = sampler.patches(50, 11);
    assert!(u32s(&wide.unwrap().views).iter().all(|&v| v == 1));
    assert!(matches!(
        sampler.patches(1, 13),
        Err(Error::InvalidArgument { arg: "k", .. })
    ));
    assert!(matches!(
        sampler.patches(0, 2),
        Err(Error::InvalidArgument { arg: "count", .. })
    ));
    assert!(matches!(
        sampler.patches(usize::MAX, 2),
        Err(Error::InvalidArgument { arg: "count", .. })
    ));
    assert!(matches!(
        sampler.pixels(0),
        Err(Error::InvalidArgument { arg: "n", .. })
    ));
}

#[test]
fn random_backgrounds_are_drawn_per_ray_and_composited_into_the_targets() {
    let views = two_views().views().to_vec();
    let data = Dataset::new(views, Background::Random, None).unwrap();
    let mut sampler = RaySampler::new(&data, 11, &Device::Cpu, DType::F64).unwrap();
    let batch = sampler.pixels(2000).unwrap();
    let (views, pixels) = (u32s(&batch.views), u32s(&batch.pixels));
    let (colors, bgs) = (v64(&batch.colors), v64(&batch.backgrounds));
    let mean_bg = bgs.iter().sum::<f64>() / bgs.len() as f64;
    assert!((mean_bg - 0.5).abs() < 0.02, "{mean_bg}");
    for i in 0..2000 {
        let p = common::datasets::pixel(
            data.views()[views[i] as usize].image(),
            pixels[2 * i] as usize,
            pixels[2 * i + 1] as usize,
        );
        let a = f64::from(p[3]) / 255.0;
        for c in 0..3 {
            let want = f64::from(p[c]) / 255.0 * a + bgs[3 * i + c] * (1.0 - a);
            assert!((colors[3 * i + c] - want).abs() < 1e-12);
        }
    }
    // Evaluation uses white.
    assert_eq!(data.background().eval_color(), [1.0; 3]);
}

/// A whole view chunk by chunk: its camera's rays (row-major, pixel centres) narrowed to
/// each chunk, with the view's colours on the evaluation background in the same order.
#[test]
fn view_chunks_cover_the_image_in_row_major_order() {
    let data = two_views();
    let (w, h) = (20usize, 12usize);
    let view = &data.views()[1];
    let all = view.camera().rays(&Device::Cpu, DType::F32).unwrap();
    let rgb = view
        .rgb(data.background().eval_color(), &Device::Cpu, DType::F32)
        .unwrap()
        .reshape((w * h, 3))
        .unwrap();
    let mut colors = Vec::new();
    let mut start = 0;
    while start < w * h {
        let len = 64.min(w * h - start);
        let chunk = all.narrow(start, len).unwrap();
        let first = view
            .camera()
            .rays_for_pixels(
                &Tensor::new(
                    &[[(start % w) as f32 + 0.5, (start / w) as f32 + 0.5]],
                    &Device::Cpu,
                )
                .unwrap(),
            )
            .unwrap();
        assert_eq!(
            v64(&chunk.directions().narrow(0, 0, 1).unwrap()),
            v64(first.directions())
        );
        colors.extend(v64(&rgb.narrow(0, start, len).unwrap()));
        start += len;
    }
    let want = v64(&view.rgb([0.2, 0.4, 0.6], &Device::Cpu, DType::F32).unwrap());
    assert_eq!(colors, want);
    assert!(data.views().get(2).is_none(), "two views");
    assert_eq!(arg(all.narrow(239, 2)), "len");
    assert_eq!(arg(all.narrow(usize::MAX, 2)), "start");
    assert_eq!(arg(view.camera().rays(&Device::Cpu, DType::U8)), "dtype");
}

/// A jittering sampler sends each ray through a random point of its own pixel (spread over
/// the pixel, not at its centre), draws the same pixels as a sampler without jitter, and
/// keeps patches on pixel centres; the sub-pixel grid of a camera averages to the centres.
#[test]
fn jittered_rays_stay_inside_their_pixels_and_subpixel_grids_average_to_centres() {
    let data = load(Path::new(WUSON), &of_split(Split::Train)).unwrap();
    let d = Device::Cpu;
    let plain = RaySampler::new(&data, 5, &d, DType::F64)
        .unwrap()
        .pixels(512)
        .unwrap();
    let mut sampler = RaySampler::new(&data, 5, &d, DType::F64)
        .unwrap()
        .with_pixel_filter(PixelFilter::Box, true)
        .unwrap();
    let batch = sampler.pixels(512).unwrap();
    assert_eq!(
        batch.pixels.to_vec2::<u32>().unwrap(),
        plain.pixels.to_vec2::<u32>().unwrap()
    );
    let px = batch.pixels.to_vec2::<u32>().unwrap();
    let (mut fractions, mut spread) = (Vec::new(), 0.0f64);
    for (i, [fu, fv]) in in_pixel(&data, &batch).into_iter().enumerate() {
        let px = &px[i];
        assert!(
            (-1e-9..1.0 + 1e-9).contains(&fu) && (-1e-9..1.0 + 1e-9).contains(&fv),
            "ray {i} leaves pixel {px:?}: ({fu}, {fv})"
        );
        spread = spread.max((fu - 0.5).abs()).max((fv - 0.5).abs());
        fractions.push(fu);
    }
    let mean = fractions.iter().sum::<f64>() / fractions.len() as f64;
    assert!(spread > 0.4, "offsets hug the centre: {spread}");
    assert!(
        (mean - 0.5).abs() < 0.05,
        "offsets are not uniform: mean {mean}"
    );
    // Patches stay on the centres.
    let patch = sampler.patches(1, 2).unwrap();
    let centres = {
        let camera = data.views()[patch.views.to_vec1::<u32>().unwrap()[0] as usize].camera();
        let px = patch.pixels.to_vec2::<u32>().unwrap();
        let at: Vec<f64> = px
            .iter()
            .flat_map(|p| [f64::from(p[0]) + 0.5, f64::from(p[1]) + 0.5])
            .collect();
        camera
            .rays_for_pixels(&Tensor::from_vec(at, (4, 2), &d).unwrap())
            .unwrap()
    };
    let diff = (patch.rays.directions() - centres.directions())
        .unwrap()
        .abs()
        .unwrap()
        .max_keepdim(0)
        .unwrap()
        .max_keepdim(1)
        .unwrap()
        .squeeze(0)
        .unwrap()
        .squeeze(0)
        .unwrap()
        .to_scalar::<f64>()
        .unwrap();
    assert!(diff < 1e-12, "{diff}");
    // The mean of each pixel's k × k sub-pixel centres is the pixel centre.
    let camera = data.views()[0].camera();
    let k = 3;
    for filter in [PixelFilter::Box, PixelFilter::CYCLES] {
        let sub = camera.subpixel_grid(k, filter, &d, DType::F64).unwrap();
        let n = sub.dim(0).unwrap() / (k * k);
        let means = sub.reshape((n, k * k, 2)).unwrap().mean(1).unwrap();
        let centres = camera
            .subpixel_grid(1, PixelFilter::Box, &d, DType::F64)
            .unwrap();
        let err = v64(&(means - centres).unwrap())
            .into_iter()
            .fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(err < 1e-12, "{filter:?}: {err}");
    }
}

/// `pixel_footprints(n, k)`: `n` pixels drawn as `pixels(n)` draws them, each pixel's `k²`
/// rays through its sub-pixel centres (as `Camera::subpixel_grid` places them) or, jittered,
/// through one random point of each sub-pixel; per-ray colours and backgrounds repeat the
/// pixel's; bad `k` and `n` are errors naming them.
#[test]
fn pixel_footprints_cover_each_pixel_with_its_subpixel_grid() {
    let data = load(Path::new(WUSON), &of_split(Split::Train)).unwrap();
    let d = Device::Cpu;
    let (n, k) = (64, 3);
    let plain = RaySampler::new(&data, 11, &d, DType::F64)
        .unwrap()
        .pixels(n)
        .unwrap();
    for jitter in [false, true] {
        let batch = RaySampler::new(&data, 11, &d, DType::F64)
            .unwrap()
            .with_pixel_filter(PixelFilter::Box, jitter)
            .unwrap()
            .pixel_footprints(n, k)
            .unwrap();
        assert_eq!(batch.rays.len(), n * k * k);
        let px = batch.pixels.to_vec2::<u32>().unwrap();
        let colors = batch.colors.to_vec2::<f64>().unwrap();
        let bgs = batch.backgrounds.to_vec2::<f64>().unwrap();
        // The same pixels and backgrounds as `pixels(n)` with the same seed, each repeated.
        let want_px = plain.pixels.to_vec2::<u32>().unwrap();
        let want_bg = plain.backgrounds.to_vec2::<f64>().unwrap();
        let want_c = plain.colors.to_vec2::<f64>().unwrap();
        let at = in_pixel(&data, &batch);
        for r in 0..n * k * k {
            let (p, sub) = (r / (k * k), r % (k * k));
            assert_eq!(px[r], want_px[p], "ray {r}");
            assert_eq!(bgs[r], want_bg[p], "ray {r}");
            assert_eq!(colors[r], want_c[p], "ray {r}");
            // Sub-pixel (i, j) of the pixel: [(j, i), (j + 1, i + 1)] / k.
            let (i, j) = ((sub / k) as f64, (sub % k) as f64);
            let fu = at[r][0] * k as f64 - j;
            let fv = at[r][1] * k as f64 - i;
            if jitter {
                assert!(
                    (-1e-9..1.0 + 1e-9).contains(&fu) && (-1e-9..1.0 + 1e-9).contains(&fv),
                    "ray {r} leaves its sub-pixel: ({fu}, {fv})"
                );
            } else {
                assert!(
                    (fu - 0.5).abs() < 1e-9 && (fv - 0.5).abs() < 1e-9,
                    "ray {r} misses its sub-pixel centre: ({fu}, {fv})"
                );
            }
        }
    }
    let mut sampler = RaySampler::new(&data, 0, &d, DType::F32).unwrap();
    assert_eq!(arg(sampler.pixel_footprints(4, 0)), "k");
    assert_eq!(arg(sampler.pixel_footprints(4, 65)), "k");
    assert_eq!(arg(sampler.pixel_footprints(0, 2)), "n");
    assert_eq!(arg(sampler.pixel_footprints(1 << 27, 2)), "n");
}

/// The argument an `InvalidArgument` error names.
fn arg<T>(r: neural_fields::Result<T>) -> &'static str {
    match r {
        Err(Error::InvalidArgument { arg, .. }) => arg,
        Err(e) => panic!("{e}"),
        Ok(_) => panic!("expected an invalid argument"),
    }
}

/// The Blackman–Harris window's cumulative distribution by the trapezoid rule on its
/// density (independent of the closed form the library inverts), at offset `x` in pixels.
fn blackman_harris_cdf(x: f64, h: f64) -> f64 {
    let density = |t: f64| {
        let v = std::f64::consts::TAU * (t / (2.0 * h) + 0.5);
        0.35875 - 0.48829 * v.cos() + 0.14128 * (2.0 * v).cos() - 0.01168 * (3.0 * v).cos()
    };
    let steps = 20_000;
    let integral = |to: f64| {
        let dt = (to + h) / steps as f64;
        (0..steps)
            .map(|i| 0.5 * (density(-h + i as f64 * dt) + density(-h + (i + 1) as f64 * dt)) * dt)
            .sum::<f64>()
    };
    integral(x.clamp(-h, h)) / integral(h)
}

/// With Cycles' filter, a jittering sampler's rays pass through offsets from the pixel
/// centre that follow the Blackman–Harris distribution (empirical distribution within
/// 0.03 of it, spreading into the neighbouring pixels), with the pixel's own colour; its
/// footprints without jitter sit at the filter's stratum medians, as
/// `Camera::subpixel_grid` places them; a bad filter is refused naming `filter`.
#[test]
fn a_sampler_with_cycles_filter_draws_offsets_from_the_filter() {
    let data = load(Path::new(WUSON), &of_split(Split::Train)).unwrap();
    let d = Device::Cpu;
    let filter = PixelFilter::CYCLES;
    let plain = RaySampler::new(&data, 3, &d, DType::F64)
        .unwrap()
        .pixels(4096)
        .unwrap();
    let mut sampler = RaySampler::new(&data, 3, &d, DType::F64)
        .unwrap()
        .with_pixel_filter(filter, true)
        .unwrap();
    let batch = sampler.pixels(4096).unwrap();
    assert_eq!(
        batch.colors.to_vec2::<f64>().unwrap(),
        plain.colors.to_vec2::<f64>().unwrap()
    );
    let offsets = |b: &neural_fields::data::RayBatch| -> Vec<[f64; 2]> {
        let centred = |[x, y]: [f64; 2]| [x - 0.5, y - 0.5];
        in_pixel(&data, b).into_iter().map(centred).collect()
    };
    let mut xs: Vec<f64> = offsets(&batch).into_iter().flatten().collect();
    xs.sort_by(f64::total_cmp);
    let n = xs.len() as f64;
    let worst = xs
        .iter()
        .enumerate()
        .map(|(i, &x)| (blackman_harris_cdf(x, 1.5) - (i as f64 + 0.5) / n).abs())
        .fold(0.0f64, f64::max);
    assert!(worst < 0.03, "empirical distribution off by {worst}");
    assert!(
        xs[0] < -0.6 && xs[xs.len() - 1] > 0.6,
        "no rays into the neighbours"
    );
    assert!(xs[0] >= -1.5 - 1e-9 && xs[xs.len() - 1] <= 1.5 + 1e-9);
    // Footprints without jitter: the stratum medians of the filter.
    let k = 3;
    let feet = RaySampler::new(&data, 3, &d, DType::F64)
        .unwrap()
        .with_pixel_filter(filter, false)
        .unwrap()
        .pixel_footprints(8, k)
        .unwrap();
    // The sub-pixel grid of pixel (0, 0): row j of its first k is at the corner plus
    // ½ + q((j + ½)/k), q the filter's quantile.
    let grid = data.views()[0]
        .camera()
        .subpixel_grid(k, filter, &d, DType::F64)
        .unwrap()
        .to_vec2::<f64>()
        .unwrap();
    for (r, [x, y]) in offsets(&feet).into_iter().enumerate() {
        let (i, j) = ((r % (k * k)) / k, r % k);
        let want = |m: usize| grid[m][0] - 0.5;
        assert!(
            (x - want(j)).abs() < 1e-9 && (y - want(i)).abs() < 1e-9,
            "ray {r}"
        );
    }
    let bad = RaySampler::new(&data, 3, &d, DType::F64)
        .unwrap()
        .with_pixel_filter(PixelFilter::BlackmanHarris { half_width: 0.0 }, false);
    assert!(matches!(bad, Err(Error::InvalidArgument { arg, .. }) if arg == "filter"));
}

/// Where each ray of `batch` passes through the image of its view, relative to its
/// pixel's top-left corner (a point on the ray projected by the view's camera).
fn in_pixel(data: &Dataset, batch: &neural_fields::data::RayBatch) -> Vec<[f64; 2]> {
    let (o, dir) = (
        batch.rays.origins().to_vec2::<f64>().unwrap(),
        batch.rays.directions().to_vec2::<f64>().unwrap(),
    );
    let views = batch.views.to_vec1::<u32>().unwrap();
    batch
        .pixels
        .to_vec2::<u32>()
        .unwrap()
        .iter()
        .enumerate()
        .map(|(i, px)| {
            let camera = data.views()[views[i] as usize].camera();
            let point = DVec3::from_slice(&o[i]) + 2.0 * DVec3::from_slice(&dir[i]);
            let p = camera.project(point).unwrap();
            [p.x - f64::from(px[0]), p.y - f64::from(px[1])]
        })
        .collect()
}
