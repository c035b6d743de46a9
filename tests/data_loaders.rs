//! Dataset layouts: hand-written samples of each public format parse to the cameras and
//! pixels they state, the Blender writer round-trips exactly, and malformed datasets are
//! errors naming the file and the field.
#![cfg(feature = "data")]

mod common;

/// The default configuration for one split.
fn of_split(split: Split) -> LoadConfig {
    LoadConfig {
        split,
        ..LoadConfig::default()
    }
}

use candle_core::{DType, Device};
use common::camera_ray;
use common::datasets::{detected_layout, flat, has_mask, npy, npz, pattern, pixel, png, scratch};
use neural_fields::camera::{Camera, Convention, Intrinsics};
use neural_fields::data::{
    load, load_eval, write_blender, Background, Bounds, Dataset, DatasetLayout, Image, LoadConfig,
    Split, View,
};
use neural_fields::glam::{DAffine3, DMat3, DQuat, DVec2, DVec3, EulerRot};
use neural_fields::Error;
use std::path::Path;

/// A camera-to-world pose looking at the origin from `eye` (OpenGL axes), as 4×4 rows.
fn look_rows(eye: DVec3) -> [[f64; 4]; 4] {
    let k = Intrinsics::new(10.0, 10.0, 2.0, 1.5, 4, 3).unwrap();
    let cam = Camera::look_at(k, eye, DVec3::ZERO, DVec3::Z, Convention::OpenGl).unwrap();
    rows_of(&cam.cam_to_world())
}

fn rows_of(p: &DAffine3) -> [[f64; 4]; 4] {
    let m = p.matrix3;
    let t = p.translation;
    [
        [m.row(0).x, m.row(0).y, m.row(0).z, t.x],
        [m.row(1).x, m.row(1).y, m.row(1).z, t.y],
        [m.row(2).x, m.row(2).y, m.row(2).z, t.z],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

fn eyes() -> Vec<DVec3> {
    vec![
        DVec3::new(4.0, 0.0, 1.0),
        DVec3::new(0.0, 4.0, 2.0),
        DVec3::new(-3.0, -2.0, 1.5),
        DVec3::new(1.0, -4.0, 0.5),
    ]
}

/// A Blender-synthetic folder: RGBA 4×3 frames named without extension.
fn blender_sample(dir: &Path, split: &str, n: usize) {
    let frames: Vec<serde_json::Value> = (0..n)
        .map(|i| {
            png(
                &dir.join(format!("{split}/r_{i}.png")),
                4,
                3,
                4,
                &pattern(4, 3, 4, i as u8),
            );
            serde_json::json!({
                "file_path": format!("./{split}/r_{i}"),
                "rotation": 0.012566370614359171,
                "transform_matrix": look_rows(eyes()[i % 4]),
            })
        })
        .collect();
    let json = serde_json::json!({ "camera_angle_x": 0.6911112070083618, "frames": frames });
    std::fs::write(
        dir.join(format!("transforms_{split}.json")),
        json.to_string(),
    )
    .unwrap();
}

/// Asserts that `result` is a format error naming a path ending in `file` and `field`.
fn expect_format<T>(result: neural_fields::Result<T>, file: &str, field: &str) {
    match result {
        Err(Error::Format { path, field: f, .. }) => {
            assert!(path.ends_with(file) && f == field, "{path}: {f}")
        }
        Err(other) => panic!("expected a format error, got {other}"),
        Ok(_) => panic!("expected a format error naming {file}: {field}"),
    }
}

fn format_field(e: &Error) -> (String, String) {
    match e {
        Error::Format { path, field, .. } => (path.clone(), field.clone()),
        other => panic!("expected a format error, got {other}"),
    }
}

#[test]
fn blender_sample_parses_to_its_cameras_and_pixels() {
    let dir = scratch("blender-sample");
    blender_sample(&dir, "train", 3);
    blender_sample(&dir, "test", 2);
    assert_eq!(detected_layout(&dir), DatasetLayout::Blender);
    let data = load(&dir, &LoadConfig::default()).unwrap();
    assert_eq!(data.views().len(), 3);
    assert_eq!(data.bounds(), None);
    let f = 0.5 * 4.0 / (0.5f64 * 0.6911112070083618).tan();
    for (i, view) in data.views().iter().enumerate() {
        let k = view.camera().intrinsics();
        assert!((k.fx - f).abs() < 1e-12 && (k.fy - f).abs() < 1e-12);
        assert_eq!((k.cx, k.cy, k.width, k.height), (2.0, 1.5, 4, 3));
        assert_eq!(view.camera().convention(), Convention::OpenGl);
        assert_eq!(rows_of(&view.camera().cam_to_world()), look_rows(eyes()[i]));
        assert_eq!(view.image().data(), &pattern(4, 3, 4, i as u8)[..]);
        assert!(has_mask(view));
        // Composited on white: c·a + (1 − a).
        let rgb = view.rgb([1.0; 3], &Device::Cpu, DType::F64).unwrap();
        let px = &pattern(4, 3, 4, i as u8)[4 * 5..4 * 6]; // pixel (1, 1)
        let a = f64::from(px[3]) / 255.0;
        let want = f64::from(px[0]) / 255.0 * a + (1.0 - a);
        let got = rgb.get(1).unwrap().get(1).unwrap().get(0).unwrap();
        assert!((got.to_scalar::<f64>().unwrap() - want).abs() < 1e-12);
    }
    let all = load(&dir, &of_split(Split::All));
    // No transforms_val.json: the error names it.
    match all {
        Err(Error::Io { path, .. }) => assert!(path.ends_with("transforms_val.json"), "{path}"),
        other => panic!("{other:?}"),
    }
    let test = load(&dir, &of_split(Split::Test)).unwrap();
    assert_eq!(test.views().len(), 2);
}

#[test]
fn nerfstudio_sample_parses_with_global_and_per_frame_intrinsics() {
    let dir = scratch("nerfstudio-sample");
    let frames: Vec<serde_json::Value> = (0..9)
        .map(|i| {
            let name = format!("images/frame_{:05}.jpg", i + 1);
            let img = image::RgbImage::from_fn(6, 4, |x, y| {
                image::Rgb([(x * 40) as u8, (y * 60) as u8, i as u8 * 20])
            });
            std::fs::create_dir_all(dir.join("images")).unwrap();
            img.save(dir.join(&name)).unwrap();
            let mut f = serde_json::json!({
                "file_path": name,
                "transform_matrix": look_rows(eyes()[i % 4]),
                "colmap_im_id": i + 1,
            });
            if i == 3 {
                f["fl_x"] = serde_json::json!(7.5);
                f["cx"] = serde_json::json!(3.25);
            }
            f
        })
        .collect();
    let json = serde_json::json!({
        "camera_model": "OPENCV",
        "fl_x": 5.5, "fl_y": 5.25, "cx": 2.9, "cy": 2.1, "w": 6, "h": 4,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "aabb_scale": 16,
        "frames": frames,
    });
    std::fs::write(dir.join("transforms.json"), json.to_string()).unwrap();
    assert_eq!(detected_layout(&dir), DatasetLayout::Nerfstudio);
    let train = load(&dir, &LoadConfig::default()).unwrap();
    // Every 8th frame (0 and 8) is held out.
    assert_eq!(train.views().len(), 7);
    assert!(train.views()[0].name().ends_with("frame_00002.jpg"));
    let k = train.views()[0].camera().intrinsics();
    assert_eq!(
        (k.fx, k.fy, k.cx, k.cy, k.width, k.height),
        (5.5, 5.25, 2.9, 2.1, 6, 4)
    );
    let k3 = train.views()[2].camera().intrinsics(); // frame 3 overrides fl_x and cx
    assert_eq!((k3.fx, k3.fy, k3.cx, k3.cy), (7.5, 5.25, 3.25, 2.1));
    assert!(!has_mask(&train.views()[0]));
    assert_eq!(
        train.bounds(),
        Some(Bounds::Aabb {
            min: [-8.0; 3],
            max: [8.0; 3]
        })
    );
    let test = load(&dir, &of_split(Split::Test)).unwrap();
    let names: Vec<&str> = test.views().iter().map(View::name).collect();
    assert!(names[0].ends_with("frame_00001.jpg") && names[1].ends_with("frame_00009.jpg"));
    // A frame subset, in the order given.
    let few = load(
        &dir,
        &LoadConfig {
            frames: Some(vec![4, 0]),
            ..LoadConfig::default()
        },
    )
    .unwrap();
    assert!(few.views()[0].name().ends_with("frame_00006.jpg"));
    assert!(few.views()[1].name().ends_with("frame_00002.jpg"));
    let bad = load(
        &dir,
        &LoadConfig {
            frames: Some(vec![7]),
            ..LoadConfig::default()
        },
    );
    assert!(matches!(
        bad,
        Err(Error::InvalidArgument { arg: "frames", .. })
    ));
}

#[test]
fn nerfstudio_scale_and_offset_move_camera_centres() {
    let dir = scratch("nerfstudio-scale");
    png(&dir.join("a.png"), 4, 3, 3, &pattern(4, 3, 3, 0));
    let json = serde_json::json!({
        "fl_x": 3.0, "w": 4, "h": 3, "scale": 0.5, "offset": [0.5, 0.25, -1.0],
        "frames": [{ "file_path": "a.png", "transform_matrix": look_rows(eyes()[0]) }],
    });
    std::fs::write(dir.join("transforms.json"), json.to_string()).unwrap();
    let all = load(&dir, &of_split(Split::All)).unwrap();
    let c = all.views()[0].camera().cam_to_world().translation;
    assert_eq!(c, eyes()[0] * 0.5 + DVec3::new(0.5, 0.25, -1.0));
}

/// A DTU-style folder: `n` 6×5 views of a camera `P = K·[R|t]` in a world frame that is
/// `scale_mat = diag(s, s, s, 1) + c` times the normalised one.
fn dtu_sample(dir: &Path, n: usize, s: f64, c: DVec3) -> Vec<(Intrinsics, DAffine3)> {
    let mut members = Vec::new();
    let mut truth = Vec::new();
    for i in 0..n {
        png(
            &dir.join(format!("image/{i:06}.png")),
            6,
            5,
            3,
            &pattern(6, 5, 3, i as u8),
        );
        png(
            &dir.join(format!("mask/{i:03}.png")),
            6,
            5,
            1,
            &pattern(6, 5, 1, i as u8),
        );
        let k = Intrinsics::new(8.0 + i as f64, 7.5, 3.1, 2.4, 6, 5).unwrap();
        // Normalised-frame camera (OpenCV axes) at distance 3.
        let eye_n = eyes()[i % 4].normalize() * 3.0;
        let cam = Camera::look_at(k, eye_n, DVec3::ZERO, DVec3::Z, Convention::OpenCv).unwrap();
        let c2w_n = cam.cam_to_world();
        // World frame: X = s·x_n + c, so the world camera has centre s·eye_n + c.
        let r_w2c = c2w_n.matrix3.transpose();
        let center_w = eye_n * s + c;
        let t = -(r_w2c * center_w);
        let kmat = DMat3::from_cols(
            DVec3::new(k.fx, 0.0, 0.0),
            DVec3::new(0.0, k.fy, 0.0),
            DVec3::new(k.cx, k.cy, 1.0),
        );
        let kr = kmat * r_w2c;
        let kt = kmat * t;
        let world: [[f64; 4]; 4] = std::array::from_fn(|r| {
            if r == 3 {
                [0.0, 0.0, 0.0, 1.0]
            } else {
                [kr.row(r).x, kr.row(r).y, kr.row(r).z, kt[r]]
            }
        });
        let scale = [
            [s, 0.0, 0.0, c.x],
            [0.0, s, 0.0, c.y],
            [0.0, 0.0, s, c.z],
            [0.0, 0.0, 0.0, 1.0],
        ];
        members.push((format!("world_mat_{i}"), npy(&[4, 4], &flat(&world))));
        members.push((format!("scale_mat_{i}"), npy(&[4, 4], &flat(&scale))));
        members.push((format!("world_mat_inv_{i}"), npy(&[4, 4], &flat(&world))));
        truth.push((k, c2w_n));
    }
    npz(&dir.join("cameras.npz"), &members);
    truth
}

#[test]
fn dtu_sample_decomposes_world_and_scale_matrices() {
    let dir = scratch("dtu-sample");
    let truth = dtu_sample(&dir, 3, 200.0, DVec3::new(30.0, -20.0, 500.0));
    assert_eq!(detected_layout(&dir), DatasetLayout::Dtu);
    let all = load(&dir, &of_split(Split::All)).unwrap();
    assert_eq!(all.views().len(), 3);
    assert_eq!(
        all.bounds(),
        Some(Bounds::Sphere {
            center: [0.0; 3],
            radius: 1.0
        })
    );
    for (view, (k, pose)) in all.views().iter().zip(&truth) {
        let got = view.camera();
        assert_eq!(got.convention(), Convention::OpenCv);
        let gk = got.intrinsics();
        for (a, b) in [(gk.fx, k.fx), (gk.fy, k.fy), (gk.cx, k.cx), (gk.cy, k.cy)] {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        assert!((got.cam_to_world().translation - pose.translation).length() < 1e-9);
        let dm = got.cam_to_world().matrix3 - pose.matrix3;
        assert!(dm.to_cols_array().iter().all(|x| x.abs() < 1e-9));
        // A mask file: a mask, and no alpha channel it could come from.
        assert!(view.mask(&Device::Cpu, DType::F32).unwrap().is_some());
        assert_eq!(view.image().size().2, 3);
    }
    // Hold-out rule: frame 0 is the test split.
    let test = load(&dir, &of_split(Split::Test)).unwrap();
    assert_eq!(test.views().len(), 1);
}

fn analytic_dataset(convention: Convention, channels: usize) -> Dataset {
    let views = eyes()
        .into_iter()
        .enumerate()
        .map(|(i, eye)| {
            let k = Intrinsics::new(9.25 + i as f64, 8.5, 3.3, 2.2, 7, 5).unwrap();
            let cam =
                Camera::look_at(k, eye, DVec3::new(0.1, 0.2, 0.3), DVec3::Z, convention).unwrap();
            let image = Image::new(7, 5, channels, pattern(7, 5, channels, i as u8)).unwrap();
            View::new(cam, image, None, format!("view {i}")).unwrap()
        })
        .collect();
    Dataset::new(views, Background::Color([0.0; 3]), None).unwrap()
}

#[test]
fn blender_writer_round_trips_poses_and_pixels_exactly() {
    for (convention, channels) in [(Convention::OpenGl, 4), (Convention::OpenCv, 3)] {
        let dir = scratch(&format!("writer-{convention:?}"));
        let data = analytic_dataset(convention, channels);
        write_blender(&dir, Split::Val, &data).unwrap();
        let back = load(
            &dir,
            &LoadConfig {
                split: Split::Val,
                layout: Some(DatasetLayout::Blender),
                ..LoadConfig::default()
            },
        )
        .unwrap();
        assert_eq!(back.views().len(), data.views().len());
        for (a, b) in data.views().iter().zip(back.views()) {
            let (ka, kb) = (a.camera().intrinsics(), b.camera().intrinsics());
            assert_eq!(ka, kb);
            // Same rays for every pixel, to 1e-12.
            for pixel in [
                DVec2::new(0.5, 0.5),
                DVec2::new(6.5, 4.5),
                DVec2::new(3.0, 1.25),
            ] {
                let (oa, da) = camera_ray(a.camera(), pixel);
                let (ob, db) = camera_ray(b.camera(), pixel);
                assert!((oa - ob).length() < 1e-12 && (da - db).length() < 1e-12);
            }
            let pa = a.image();
            let pb = b.image();
            assert_eq!(pb.size().2, 4);
            for v in 0..5 {
                for u in 0..7 {
                    let (x, y) = (pixel(pa, u, v), pixel(pb, u, v));
                    assert_eq!(&x[..3], &y[..3]);
                    assert_eq!(y[3], if channels == 4 { x[3] } else { 255 });
                }
            }
        }
        // Nothing but the dataset's files is left in the folder.
        let mut names: Vec<String> = std::fs::read_dir(dir.join("val"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["r_0.png", "r_1.png", "r_2.png", "r_3.png"]);
    }
}

#[test]
fn writer_leaves_no_half_written_file_when_the_destination_is_taken() {
    let dir = scratch("writer-fails");
    // A directory where the JSON should go: the rename fails.
    std::fs::create_dir_all(dir.join("transforms_test.json/x")).unwrap();
    let data = analytic_dataset(Convention::OpenGl, 4);
    let e = write_blender(&dir, Split::Test, &data).unwrap_err();
    assert!(
        matches!(&e, Error::Io { path, .. } if path.ends_with("transforms_test.json")),
        "{e}"
    );
    let leftovers: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains(".tmp"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn downscaling_scales_intrinsics_and_averages_pixels() {
    let dir = scratch("downscale");
    let data = analytic_dataset(Convention::OpenGl, 3);
    write_blender(&dir, Split::Train, &data).unwrap();
    let half = load(
        &dir,
        &LoadConfig {
            downscale: 2,
            ..LoadConfig::default()
        },
    )
    .unwrap();
    let (k, k0) = (
        half.views()[0].camera().intrinsics(),
        data.views()[0].camera().intrinsics(),
    );
    assert_eq!((k.width, k.height), (3, 2));
    assert!((k.fx - k0.fx / 2.0).abs() < 1e-12 && (k.cx - k0.cx / 2.0).abs() < 1e-12);
    // The ray through a downscaled pixel centre is the ray through the block's centre.
    let (_, d_half) = camera_ray(half.views()[0].camera(), DVec2::new(1.5, 0.5));
    let (_, d_full) = camera_ray(data.views()[0].camera(), DVec2::new(3.0, 1.0));
    assert!((d_half - d_full).length() < 1e-12);
    // Pixel (1, 0) averages full-resolution pixels (2..4, 0..2); alpha is 255 (RGB in).
    let full = data.views()[0].image();
    let want: f64 = [(2, 0), (3, 0), (2, 1), (3, 1)]
        .iter()
        .map(|&(u, v)| f64::from(pixel(full, u, v)[0]))
        .sum::<f64>()
        / 4.0;
    assert_eq!(pixel(half.views()[0].image(), 1, 0)[0], want.round() as u8);
    let e = load(
        &dir,
        &LoadConfig {
            downscale: 0,
            ..LoadConfig::default()
        },
    );
    assert!(matches!(
        e,
        Err(Error::InvalidArgument {
            arg: "downscale",
            ..
        })
    ));
}

// ---- bad input: every case is an error naming the file and the field ----

fn nerfstudio_one(dir: &Path, frame: serde_json::Value, top: serde_json::Value) {
    png(&dir.join("a.png"), 4, 3, 3, &pattern(4, 3, 3, 0));
    let mut json = top;
    json["frames"] = serde_json::json!([frame.clone(), frame]);
    std::fs::write(dir.join("transforms.json"), json.to_string()).unwrap();
}

#[test]
fn malformed_transforms_are_errors_naming_file_and_field() {
    let ok_frame =
        serde_json::json!({ "file_path": "a.png", "transform_matrix": look_rows(eyes()[0]) });
    let base = serde_json::json!({ "fl_x": 3.0, "w": 4, "h": 3 });
    let mut singular = look_rows(eyes()[0]);
    singular[0] = [0.0, 0.0, 0.0, 1.0];
    let mut sheared = look_rows(eyes()[0]);
    sheared[0][1] += 0.1;
    let with = |key: &str, value: serde_json::Value| {
        let mut f = ok_frame.clone();
        f[key] = value;
        f
    };
    let mut nan = serde_json::to_value(look_rows(eyes()[0])).unwrap();
    nan[1][2] = serde_json::Value::Null;
    let cases: Vec<(&str, serde_json::Value, serde_json::Value, &str)> = vec![
        (
            "singular",
            with("transform_matrix", serde_json::json!(singular)),
            base.clone(),
            "frames[0].transform_matrix",
        ),
        (
            "non-rigid",
            with("transform_matrix", serde_json::json!(sheared)),
            base.clone(),
            "frames[0].transform_matrix",
        ),
        (
            "nan-pose",
            with("transform_matrix", nan),
            base.clone(),
            "frames[0].transform_matrix",
        ),
        (
            "short-matrix",
            with(
                "transform_matrix",
                serde_json::json!([[1, 0, 0], [0, 1, 0]]),
            ),
            base.clone(),
            "frames[0].transform_matrix",
        ),
        (
            "fisheye",
            ok_frame.clone(),
            serde_json::json!({ "fl_x": 3.0, "camera_model": "OPENCV_FISHEYE" }),
            "camera_model",
        ),
        (
            "distortion",
            ok_frame.clone(),
            serde_json::json!({ "fl_x": 3.0, "k1": -0.02 }),
            "k1",
        ),
        (
            "no-focal",
            ok_frame.clone(),
            serde_json::json!({ "w": 4 }),
            "camera_angle_x",
        ),
        (
            "negative-focal",
            ok_frame.clone(),
            serde_json::json!({ "fl_x": -3.0 }),
            "fl_x",
        ),
        (
            "no-file-path",
            serde_json::json!({ "transform_matrix": look_rows(eyes()[0]) }),
            base.clone(),
            "frames[0].file_path",
        ),
    ];
    for (name, frame, top, field) in cases {
        let dir = scratch(&format!("bad-{name}"));
        nerfstudio_one(&dir, frame, top);
        let e = load(&dir, &of_split(Split::All)).expect_err(name);
        let (path, got) = format_field(&e);
        assert!(path.ends_with("transforms.json"), "{name}: {e}");
        assert_eq!(got, field, "{name}: {e}");
    }
}

#[test]
fn json_without_frames_and_empty_splits_are_errors_naming_the_file() {
    let dir = scratch("no-frames");
    std::fs::write(dir.join("transforms.json"), r#"{"camera_angle_x": 0.7}"#).unwrap();
    let e = load(&dir, &of_split(Split::All)).unwrap_err();
    assert_eq!(format_field(&e).1, "frames", "{e}");
    std::fs::write(
        dir.join("transforms.json"),
        r#"{"camera_angle_x": 0.7, "frames": []}"#,
    )
    .unwrap();
    let e = load(&dir, &of_split(Split::All)).unwrap_err();
    assert_eq!(format_field(&e).1, "frames", "{e}");
    std::fs::write(dir.join("transforms.json"), "{\"frames\": [").unwrap();
    let e = load(&dir, &of_split(Split::All)).unwrap_err();
    assert_eq!(format_field(&e).1, "JSON", "{e}");
    // One frame: the training split (every frame but each 8th) is empty.
    let one = scratch("one-frame");
    png(&one.join("a.png"), 4, 3, 3, &pattern(4, 3, 3, 0));
    let json = serde_json::json!({ "fl_x": 3.0, "frames": [{ "file_path": "a.png", "transform_matrix": look_rows(eyes()[0]) }] });
    std::fs::write(one.join("transforms.json"), json.to_string()).unwrap();
    let e = load(&one, &LoadConfig::default()).unwrap_err();
    let (path, field) = format_field(&e);
    assert!(
        path.ends_with("transforms.json") && field == "frames",
        "{e}"
    );
}

#[test]
fn missing_truncated_and_wrong_sized_images_are_errors_naming_the_image() {
    let frame =
        serde_json::json!({ "file_path": "a.png", "transform_matrix": look_rows(eyes()[0]) });
    // Wrong size: the JSON says 5 × 3, the file is 4 × 3.
    let dir = scratch("wrong-size");
    nerfstudio_one(
        &dir,
        frame.clone(),
        serde_json::json!({ "fl_x": 3.0, "w": 5, "h": 3 }),
    );
    let e = load(&dir, &of_split(Split::All)).unwrap_err();
    let (path, field) = format_field(&e);
    assert!(path.ends_with("a.png") && field == "image size", "{e}");
    // Truncated PNG.
    let bytes = std::fs::read(dir.join("a.png")).unwrap();
    std::fs::write(dir.join("a.png"), &bytes[..bytes.len() / 2]).unwrap();
    let e = load(&dir, &of_split(Split::All)).unwrap_err();
    let (path, _) = format_field(&e);
    assert!(path.ends_with("a.png"), "{e}");
    // Not an image at all.
    std::fs::write(dir.join("a.png"), b"hello").unwrap();
    assert!(
        format_field(&load(&dir, &of_split(Split::All)).unwrap_err())
            .0
            .ends_with("a.png")
    );
    // Missing.
    std::fs::remove_file(dir.join("a.png")).unwrap();
    match load(&dir, &of_split(Split::All)) {
        Err(Error::Io { path, .. }) => assert!(path.ends_with("a.png"), "{path}"),
        other => panic!("{other:?}"),
    }
    // A directory that is no dataset, and a missing directory.
    let empty = scratch("empty");
    assert_eq!(
        format_field(&load(&empty, &of_split(Split::All)).unwrap_err()).1,
        "layout"
    );
    assert!(matches!(
        load(&empty.join("nope"), &of_split(Split::All)),
        Err(Error::Io { .. })
    ));
}

#[test]
fn dtu_masks_of_another_size_and_missing_matrices_are_errors() {
    let dir = scratch("dtu-bad-mask");
    dtu_sample(&dir, 2, 1.0, DVec3::ZERO);
    png(&dir.join("mask/001.png"), 5, 5, 1, &pattern(5, 5, 1, 0));
    expect_format(
        load(&dir, &of_split(Split::All)),
        "mask/001.png",
        "mask size",
    );

    let dir = scratch("dtu-missing-matrix");
    dtu_sample(&dir, 2, 1.0, DVec3::ZERO);
    png(&dir.join("image/000002.png"), 6, 5, 3, &pattern(6, 5, 3, 2));
    png(&dir.join("mask/002.png"), 6, 5, 1, &pattern(6, 5, 1, 2));
    expect_format(
        load(&dir, &of_split(Split::All)),
        "cameras.npz",
        "world_mat_2",
    );

    let dir = scratch("dtu-singular");
    dtu_sample(&dir, 1, 1.0, DVec3::ZERO);
    npz(
        &dir.join("cameras.npz"),
        &[("world_mat_0".into(), npy(&[4, 4], &[0.0; 16]))],
    );
    let (path, field) = format_field(&load(&dir, &of_split(Split::All)).unwrap_err());
    assert!(
        path.ends_with("cameras.npz") && field.starts_with("world_mat_0"),
        "{field}"
    );

    let dir = scratch("dtu-not-zip");
    dtu_sample(&dir, 1, 1.0, DVec3::ZERO);
    std::fs::write(dir.join("cameras.npz"), b"PK\x03\x04 truncated").unwrap();
    let (path, _) = format_field(&load(&dir, &of_split(Split::All)).unwrap_err());
    assert!(path.ends_with("cameras.npz"));
}

#[test]
fn slightly_non_orthonormal_poses_are_orthonormalised() {
    // Exporters round rotations to ~7 digits; those load, as rigid cameras.
    let dir = scratch("rounded-pose");
    let rows = look_rows(eyes()[2]).map(|r| r.map(|x| (x * 1e5).round() / 1e5));
    let frame = serde_json::json!({ "file_path": "a.png", "transform_matrix": rows });
    nerfstudio_one(&dir, frame, serde_json::json!({ "fl_x": 3.0 }));
    let data = load(&dir, &of_split(Split::All)).unwrap();
    let m = data.views()[0].camera().cam_to_world().matrix3;
    let dev = (m.transpose() * m - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |a, b| a.max(b.abs()));
    assert!(dev < 1e-12, "{dev}");
    let _ = DQuat::from_euler(EulerRot::XYZ, 0.0, 0.0, 0.0);
}

#[test]
fn held_out_split_falls_back_to_val_only_where_the_layout_has_no_test_split() {
    // Blender with a test split: the test split, even when a val split exists too.
    let dir = scratch("eval-blender-test");
    blender_sample(&dir, "train", 2);
    blender_sample(&dir, "val", 1);
    blender_sample(&dir, "test", 3);
    let (eval, split) = load_eval(&dir, &LoadConfig::default()).unwrap();
    assert_eq!((split, eval.views().len()), (Split::Test, 3));
    // Without transforms_test.json: the val split.
    let dir = scratch("eval-blender-val");
    blender_sample(&dir, "train", 2);
    blender_sample(&dir, "val", 1);
    let (eval, split) = load_eval(&dir, &LoadConfig::default()).unwrap();
    assert_eq!((split, eval.views().len()), (Split::Val, 1));
    // A test split that is there but broken is an error, not a fallback.
    let dir = scratch("eval-blender-broken");
    blender_sample(&dir, "train", 2);
    blender_sample(&dir, "val", 1);
    std::fs::write(dir.join("transforms_test.json"), "{").unwrap();
    expect_format(
        load_eval(&dir, &LoadConfig::default()),
        "transforms_test.json",
        "JSON",
    );
    // IDR/DTU: the hold-out rule, as the test split; its scene box is the unit sphere's.
    let dir = scratch("eval-dtu");
    dtu_sample(&dir, 3, 200.0, DVec3::new(30.0, -20.0, 500.0));
    let (eval, split) = load_eval(&dir, &LoadConfig::default()).unwrap();
    assert_eq!((split, eval.views().len()), (Split::Test, 1));
    assert_eq!(eval.scene_box(0.3), [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]);
    // DTU images are 6×5: five cells per pixel of 6, raised to the coarsest level 16.
    assert_eq!(eval.hash_finest(), 30.0);
}

#[test]
fn scene_box_is_the_stated_bounds_or_without_masks_the_given_cube() {
    let cube = analytic_dataset(Convention::OpenGl, 3);
    assert_eq!(cube.bounds(), None);
    assert_eq!(cube.scene_box(1.5), [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5]);
    let views = cube.views().to_vec();
    let boxed = Dataset::new(
        views.clone(),
        Background::default(),
        Some(Bounds::Aabb {
            min: [-1.0, -2.0, -3.0],
            max: [4.0, 5.0, 6.0],
        }),
    )
    .unwrap();
    assert_eq!(boxed.scene_box(1.5), [-1.0, -2.0, -3.0, 4.0, 5.0, 6.0]);
    let ball = Dataset::new(
        views,
        Background::default(),
        Some(Bounds::Sphere {
            center: [1.0, 0.0, -1.0],
            radius: 0.5,
        }),
    )
    .unwrap();
    assert_eq!(ball.scene_box(1.5), [0.5, -0.5, -1.5, 1.5, 0.5, -0.5]);
    // The hash grid's finest level: five cells per pixel of the 7-pixel side.
    assert_eq!(cube.hash_finest(), 35.0);
}

/// The committed scene's coverage is its object's share of the pixels (RGBA views); views
/// without alpha or mask have none; fully transparent views have 0.
#[test]
fn coverage_counts_the_foreground_pixels_of_masked_views() {
    use neural_fields::data::{Background, Dataset, Image, View};
    let data = load(Path::new("examples/data/wuson"), &of_split(Split::Train)).unwrap();
    let c = data.coverage().expect("RGBA views have alpha");
    assert!(c > 0.01 && c < 0.5, "{c}");
    let cam = Camera::new(
        Intrinsics::new(2.0, 2.0, 1.0, 1.0, 2, 2).unwrap(),
        DAffine3::IDENTITY,
        Convention::OpenCv,
    )
    .unwrap();
    let view = |channels: usize, alpha: u8| {
        let px: Vec<u8> = (0..4)
            .flat_map(|_| {
                let mut p = vec![7u8; channels];
                if channels == 4 {
                    p[3] = alpha;
                }
                p
            })
            .collect();
        View::new(
            cam,
            Image::new(2, 2, channels, px).unwrap(),
            None,
            "v".into(),
        )
        .unwrap()
    };
    let of = |views| Dataset::new(views, Background::Color([1.0; 3]), None).unwrap();
    assert_eq!(of(vec![view(3, 0)]).coverage(), None);
    assert_eq!(of(vec![view(4, 0), view(4, 0)]).coverage(), Some(0.0));
    assert_eq!(of(vec![view(4, 255), view(4, 127)]).coverage(), Some(0.5));
    // Views without masks do not count towards the share.
    assert_eq!(of(vec![view(3, 0), view(4, 128)]).coverage(), Some(1.0));
}
