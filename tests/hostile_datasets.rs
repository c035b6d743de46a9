//! Hostile dataset folders, generated here at test time: paths that leave the folder,
//! special files, a file named by many frames, a PNG whose header claims 32768², an image
//! far above the others, a load over its memory budget, and degenerate cameras in every
//! layout. Each gives an `Err` naming the file and the field, or a correct `Ok`, in
//! bounded time and memory (nothing here decodes more than a few hundred kB).
#![cfg(feature = "data")]

mod common;

use common::datasets::{flat, npy, npz, pattern, png, scratch};
use neural_fields::data::{load, LoadConfig, Split};
use neural_fields::Error;
use std::path::Path;
use std::time::{Duration, Instant};

/// A camera-to-world pose at `(0, −4, 0)` looking at the origin (OpenGL axes), 4×4 rows.
const POSE: [[f64; 4]; 4] = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 0.0, -1.0, -4.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// A Blender folder whose `transforms_train.json` has one frame per entry of `files`
/// (each a `file_path`), with `top` merged into the file's top level.
fn blender(dir: &Path, files: &[&str], top: serde_json::Value) {
    let frames: Vec<_> = files
        .iter()
        .map(|f| serde_json::json!({ "file_path": f, "transform_matrix": POSE }))
        .collect();
    let mut json = serde_json::json!({ "camera_angle_x": 0.69, "frames": frames });
    for (k, v) in top.as_object().unwrap() {
        json[k] = v.clone();
    }
    std::fs::write(dir.join("transforms_train.json"), json.to_string()).unwrap();
}

/// A nerfstudio folder: `transforms.json` with `top` and two frames of the image `a.png`
/// (8 × 6, RGB) whose frame entries get `frame` merged in.
fn nerfstudio(dir: &Path, top: serde_json::Value, frame: serde_json::Value) {
    png(&dir.join("a.png"), 8, 6, 3, &pattern(8, 6, 3, 1));
    let mut f = serde_json::json!({ "file_path": "a.png", "transform_matrix": POSE });
    for (k, v) in frame.as_object().unwrap() {
        f[k] = v.clone();
    }
    let mut json = serde_json::json!({ "fl_x": 10.0, "w": 8, "h": 6, "frames": [f.clone(), f] });
    for (k, v) in top.as_object().unwrap() {
        json[k] = v.clone();
    }
    std::fs::write(dir.join("transforms.json"), json.to_string()).unwrap();
}

/// The format error's `(path, field, got)`, or a panic naming what came instead.
fn format_error<T>(result: neural_fields::Result<T>) -> (String, String, String) {
    match result {
        Err(Error::Format {
            path, field, got, ..
        }) => (path, field, got),
        Err(other) => panic!("expected a format error, got {other}"),
        Ok(_) => panic!("expected a format error, got Ok"),
    }
}

fn allowing_outside() -> LoadConfig {
    LoadConfig {
        allow_outside_paths: true,
        ..LoadConfig::default()
    }
}

#[test]
fn outside_path_absolute_is_refused_unless_allowed() {
    let root = scratch("hostile-absolute");
    let dir = root.join("set");
    std::fs::create_dir_all(&dir).unwrap();
    let outside = root.join("elsewhere.png");
    png(&outside, 8, 6, 3, &pattern(8, 6, 3, 2));
    png(&dir.join("a.png"), 8, 6, 3, &pattern(8, 6, 3, 3));
    blender(
        &dir,
        &["a.png", outside.to_str().unwrap()],
        serde_json::json!({}),
    );
    let (path, field, got) = format_error(load(&dir, &LoadConfig::default()));
    assert!(path.ends_with("transforms_train.json"), "{path}");
    assert_eq!(field, "frames[1].file_path");
    assert!(got.contains("elsewhere.png"), "{got}");
    let data = load(&dir, &allowing_outside()).unwrap();
    assert_eq!(data.views().len(), 2);
}

#[test]
fn outside_path_dotdot_is_refused_unless_allowed() {
    let root = scratch("hostile-dotdot");
    let dir = root.join("set");
    std::fs::create_dir_all(dir.join("train")).unwrap();
    png(&root.join("secret.png"), 8, 6, 3, &pattern(8, 6, 3, 2));
    png(&dir.join("train/a.png"), 8, 6, 3, &pattern(8, 6, 3, 3));
    // `..` that stays inside the folder is fine; one that climbs out is not.
    blender(
        &dir,
        &["./train/../train/a.png", "./train/../../secret"],
        serde_json::json!({}),
    );
    let (_, field, got) = format_error(load(&dir, &LoadConfig::default()));
    assert_eq!(field, "frames[1].file_path");
    assert!(got.contains("secret"), "{got}");
    assert_eq!(load(&dir, &allowing_outside()).unwrap().views().len(), 2);
}

#[test]
fn outside_mask_path_is_refused() {
    let root = scratch("hostile-mask-path");
    let dir = root.join("set");
    std::fs::create_dir_all(&dir).unwrap();
    png(&root.join("m.png"), 8, 6, 1, &pattern(8, 6, 1, 2));
    nerfstudio(
        &dir,
        serde_json::json!({}),
        serde_json::json!({ "mask_path": "../m.png" }),
    );
    let (path, field, _) = format_error(load(&dir, &LoadConfig::default()));
    assert!(path.ends_with("transforms.json"), "{path}");
    assert_eq!(field, "frames[1].mask_path");
}

#[cfg(unix)]
#[test]
fn outside_path_through_a_symlink_is_refused() {
    let root = scratch("hostile-symlink");
    let dir = root.join("set");
    std::fs::create_dir_all(&dir).unwrap();
    png(&root.join("secret.png"), 8, 6, 3, &pattern(8, 6, 3, 2));
    std::os::unix::fs::symlink(root.join("secret.png"), dir.join("a.png")).unwrap();
    blender(&dir, &["a.png"], serde_json::json!({}));
    let (_, field, got) = format_error(load(&dir, &LoadConfig::default()));
    assert_eq!(field, "frames[0].file_path");
    assert!(got.contains("secret.png"), "{got}");
    // A symlink inside the folder to a file inside it is fine.
    std::fs::remove_file(dir.join("a.png")).unwrap();
    png(&dir.join("b.png"), 8, 6, 3, &pattern(8, 6, 3, 2));
    std::os::unix::fs::symlink(dir.join("b.png"), dir.join("a.png")).unwrap();
    assert_eq!(load(&dir, &LoadConfig::default()).unwrap().views().len(), 1);
}

#[cfg(unix)]
#[test]
fn special_files_are_refused_even_when_outside_paths_are_allowed() {
    let root = scratch("hostile-special");
    let mut cases = vec![
        ("/dev/zero".to_string(), "device"),
        ("/proc/self/environ".to_string(), "empty"),
    ];
    std::fs::create_dir_all(root.join("folder.png")).unwrap();
    cases.push(("folder.png".to_string(), "directory"));
    let fifo = root.join("fifo.png");
    let made_fifo = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .is_ok_and(|s| s.success());
    if made_fifo {
        cases.push(("fifo.png".to_string(), "FIFO"));
    }
    for (file, what) in cases {
        if file.starts_with('/') && !Path::new(&file).exists() {
            continue;
        }
        blender(&root, &[&file], serde_json::json!({}));
        let start = Instant::now();
        let (_, field, got) = format_error(load(&root, &allowing_outside()));
        assert!(start.elapsed() < Duration::from_secs(5), "{file}");
        assert_eq!(field, "frames[0].file_path", "{file}");
        assert!(got.contains(what), "{file}: {got}");
    }
}

#[test]
fn repeated_frame_is_decoded_once_and_shared() {
    let dir = scratch("hostile-repeated");
    png(&dir.join("a.png"), 64, 64, 4, &pattern(64, 64, 4, 1));
    let files = vec!["a.png"; 1000];
    blender(&dir, &files, serde_json::json!({}));
    // A budget of one decoded copy (64 · 64 · 4 bytes) admits the 1000 frames.
    let config = LoadConfig {
        max_decoded_bytes: 64 * 64 * 4,
        ..LoadConfig::default()
    };
    let data = load(&dir, &config).unwrap();
    assert_eq!(data.views().len(), 1000);
    let first = data.views()[0].image().data().as_ptr();
    assert!(data
        .views()
        .iter()
        .all(|v| v.image().data().as_ptr() == first));
    // One byte less is refused, with the figures.
    let config = LoadConfig {
        max_decoded_bytes: 64 * 64 * 4 - 1,
        ..LoadConfig::default()
    };
    let (path, field, got) = format_error(load(&dir, &config));
    assert!(path.ends_with("a.png"), "{path}");
    assert_eq!(field, "decoded size");
    assert!(got.contains("16384 bytes"), "{got}");
}

/// The CRC-32 of PNG chunks (ISO 3309).
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A PNG of a few dozen bytes whose header states `w × h` RGBA pixels: a signature, the
/// IHDR chunk, an IDAT of an empty zlib stream and IEND, each with a valid CRC.
fn png_header_only(w: u32, h: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let mut body = kind.to_vec();
        body.extend_from_slice(data);
        out.extend_from_slice(&body);
        out.extend_from_slice(&crc32(&body).to_be_bytes());
    };
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 6, 0, 0, 0]);
    chunk(b"IHDR", &ihdr);
    chunk(b"IDAT", &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01]);
    chunk(b"IEND", &[]);
    out
}

#[test]
fn png_bomb_header_is_refused_before_decoding() {
    let dir = scratch("hostile-bomb");
    let bomb = png_header_only(32768, 32768);
    assert!(bomb.len() < 100, "{}", bomb.len());
    std::fs::write(dir.join("bomb.png"), &bomb).unwrap();
    blender(&dir, &["bomb.png"], serde_json::json!({}));
    let start = Instant::now();
    let (path, field, got) = format_error(load(&dir, &LoadConfig::default()));
    assert!(start.elapsed() < Duration::from_secs(2));
    assert!(path.ends_with("bomb.png"), "{path}");
    assert_eq!(field, "image size");
    assert!(got.contains("32768 × 32768"), "{got}");
    // A bomb as a mask is refused the same way.
    let dir = scratch("hostile-bomb-mask");
    std::fs::write(dir.join("m.png"), &bomb).unwrap();
    nerfstudio(
        &dir,
        serde_json::json!({}),
        serde_json::json!({ "mask_path": "m.png" }),
    );
    let (path, field, _) = format_error(load(&dir, &LoadConfig::default()));
    assert!(
        path.ends_with("m.png") && field == "image size",
        "{path}: {field}"
    );
}

#[test]
fn image_far_above_the_median_is_refused() {
    let dir = scratch("hostile-outsize");
    for i in 0..3 {
        png(
            &dir.join(format!("{i}.png")),
            16,
            16,
            3,
            &pattern(16, 16, 3, i),
        );
    }
    png(&dir.join("big.png"), 80, 80, 3, &pattern(80, 80, 3, 9));
    blender(
        &dir,
        &["0.png", "1.png", "big.png", "2.png"],
        serde_json::json!({}),
    );
    let (path, field, got) = format_error(load(&dir, &LoadConfig::default()));
    assert!(path.ends_with("big.png"), "{path}");
    assert_eq!(field, "image size");
    assert!(got.contains("6400"), "{got}");
    // Sizes within 16× of the median load.
    png(&dir.join("big.png"), 64, 64, 3, &pattern(64, 64, 3, 9));
    assert_eq!(load(&dir, &LoadConfig::default()).unwrap().views().len(), 4);
}

#[test]
fn per_image_pixel_cap_is_configurable() {
    let dir = scratch("hostile-pixel-cap");
    png(&dir.join("a.png"), 16, 16, 3, &pattern(16, 16, 3, 1));
    blender(&dir, &["a.png"], serde_json::json!({}));
    let config = LoadConfig {
        max_image_pixels: 255,
        ..LoadConfig::default()
    };
    let (path, field, _) = format_error(load(&dir, &config));
    assert!(
        path.ends_with("a.png") && field == "image size",
        "{path}: {field}"
    );
    let config = LoadConfig {
        max_image_pixels: 256,
        ..LoadConfig::default()
    };
    assert!(load(&dir, &config).is_ok());
}

#[test]
fn sixteen_bit_and_grey_images_count_what_they_decode_to() {
    let dir = scratch("hostile-16bit");
    let data: Vec<u16> = (0..8 * 6 * 3).map(|i| (i * 997 % 65536) as u16).collect();
    let bytes: Vec<u8> = data.iter().flat_map(|x| x.to_ne_bytes()).collect();
    image::save_buffer(
        dir.join("a.png"),
        &bytes,
        8,
        6,
        image::ExtendedColorType::Rgb16,
    )
    .unwrap();
    png(&dir.join("g.png"), 8, 6, 1, &pattern(8, 6, 1, 2));
    blender(&dir, &["a.png", "g.png"], serde_json::json!({}));
    // The 16-bit file decodes to 8 · 6 · 6 bytes, the grey one is kept as 8 · 6 · 3.
    let need = 8 * 6 * 6 + 8 * 6 * 3;
    let exact = LoadConfig {
        max_decoded_bytes: need,
        ..LoadConfig::default()
    };
    let data = load(&dir, &exact).unwrap();
    assert_eq!(data.views()[0].image().size(), (8, 6, 3));
    assert_eq!(data.views()[1].image().size(), (8, 6, 3));
    let short = LoadConfig {
        max_decoded_bytes: need - 1,
        ..LoadConfig::default()
    };
    let (_, field, got) = format_error(load(&dir, &short));
    assert_eq!(field, "decoded size");
    assert!(got.contains(&format!("{need} bytes")), "{got}");
}

#[test]
fn degenerate_camera_in_json_is_refused_naming_the_field() {
    let pi = std::f64::consts::PI;
    // (top-level fields, frame fields, the field named)
    let cases = [
        (
            serde_json::json!({ "fl_x": null, "camera_angle_x": 1e-300 }),
            serde_json::json!({}),
            "camera_angle_x",
        ),
        (
            serde_json::json!({ "fl_x": null, "camera_angle_x": pi - 1e-15 }),
            serde_json::json!({}),
            "camera_angle_x",
        ),
        (
            serde_json::json!({ "fl_x": null, "camera_angle_x": 0.7, "camera_angle_y": 1e-9 }),
            serde_json::json!({}),
            "camera_angle_y",
        ),
        (
            serde_json::json!({ "fl_x": 1e300 }),
            serde_json::json!({}),
            "fl_x",
        ),
        (
            serde_json::json!({ "fl_x": 1e-300 }),
            serde_json::json!({}),
            "fl_x",
        ),
        (
            serde_json::json!({ "fl_y": 1e7 }),
            serde_json::json!({}),
            "fl_y",
        ),
        (
            serde_json::json!({ "cx": 1e300 }),
            serde_json::json!({}),
            "cx",
        ),
        (
            serde_json::json!({ "cy": -1e300 }),
            serde_json::json!({}),
            "cy",
        ),
        (
            serde_json::json!({ "w": 1e300 }),
            serde_json::json!({}),
            "w",
        ),
        (
            serde_json::json!({ "scale": 1e300 }),
            serde_json::json!({}),
            "scale",
        ),
        (
            serde_json::json!({ "scale": 1e-300 }),
            serde_json::json!({}),
            "scale",
        ),
        (
            serde_json::json!({ "offset": [0.0, 1e300, 0.0] }),
            serde_json::json!({}),
            "offset",
        ),
        (
            serde_json::json!({ "aabb_scale": 1e-300 }),
            serde_json::json!({}),
            "aabb_scale",
        ),
        (
            serde_json::json!({ "aabb_scale": 1e300 }),
            serde_json::json!({}),
            "aabb_scale",
        ),
        (
            serde_json::json!({ "scale": 1e6 }),
            serde_json::json!({}),
            "frames[1].transform_matrix",
        ),
        (
            serde_json::json!({}),
            serde_json::json!({ "fl_x": 1e300 }),
            "fl_x",
        ),
    ];
    for (i, (top, frame, want)) in cases.into_iter().enumerate() {
        let dir = scratch(&format!("hostile-camera-{i}"));
        let mut top = top;
        // `null` removes the key, for cases without a focal length.
        if top["fl_x"].is_null() && top.get("fl_x").is_some() {
            top.as_object_mut().unwrap().remove("fl_x");
            nerfstudio(&dir, serde_json::json!({}), frame);
            let path = dir.join("transforms.json");
            let mut json: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
            let obj = json.as_object_mut().unwrap();
            obj.remove("fl_x");
            for (k, v) in top.as_object().unwrap() {
                obj.insert(k.clone(), v.clone());
            }
            std::fs::write(&path, json.to_string()).unwrap();
        } else {
            nerfstudio(&dir, top.clone(), frame);
        }
        let (path, field, _) = format_error(load(&dir, &LoadConfig::default()));
        assert!(path.ends_with("transforms.json"), "case {i}: {path}");
        assert_eq!(field, want, "case {i}: {top}");
    }
}

#[test]
fn degenerate_camera_in_a_blender_split_is_refused() {
    let dir = scratch("hostile-camera-blender");
    png(&dir.join("a.png"), 8, 6, 3, &pattern(8, 6, 3, 1));
    blender(
        &dir,
        &["a.png"],
        serde_json::json!({ "camera_angle_x": 1e-300 }),
    );
    let (path, field, _) = format_error(load(&dir, &LoadConfig::default()));
    assert!(path.ends_with("transforms_train.json"), "{path}");
    assert_eq!(field, "camera_angle_x");
    // The limits themselves load.
    blender(
        &dir,
        &["a.png"],
        serde_json::json!({ "camera_angle_x": 1e-3 }),
    );
    assert!(load(&dir, &LoadConfig::default()).is_ok());
}

/// An IDR/DTU folder of two 8 × 6 frames whose `world_mat_i` is `K·[I | −c]` for the
/// focal length `f` and centre `c = (0, 0, −4)`, and whose `scale_mat_i` is `scale`.
fn dtu(dir: &Path, f: f64, scale: [[f64; 4]; 4]) {
    let mut members = Vec::new();
    for i in 0..2 {
        png(
            &dir.join(format!("image/{i:03}.png")),
            8,
            6,
            3,
            &pattern(8, 6, 3, i as u8),
        );
        let world = [
            [f, 0.0, 4.0, 16.0],
            [0.0, f, 3.0, 12.0],
            [0.0, 0.0, 1.0, 4.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        members.push((format!("world_mat_{i}"), npy(&[4, 4], &flat(&world))));
        members.push((format!("scale_mat_{i}"), npy(&[4, 4], &flat(&scale))));
    }
    npz(&dir.join("cameras.npz"), &members);
}

#[test]
fn degenerate_camera_in_dtu_matrices_is_refused() {
    let id = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let all = LoadConfig {
        split: Split::All,
        ..LoadConfig::default()
    };
    let dir = scratch("hostile-dtu-ok");
    dtu(&dir, 10.0, id);
    assert_eq!(load(&dir, &all).unwrap().views().len(), 2);
    let tiny = [
        [1e-300, 0.0, 0.0, 0.0],
        [0.0, 1e-300, 0.0, 0.0],
        [0.0, 0.0, 1e-300, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let mut huge = id;
    huge[0][3] = 1e300;
    for (i, (f, scale, want)) in [
        (1e300, id, "world_mat_0 · scale_mat_0"),
        (1e8, id, "world_mat_0 · scale_mat_0"),
        (1e-300, id, "world_mat_0 · scale_mat_0"),
        (10.0, tiny, "scale_mat_0"),
        (10.0, huge, "scale_mat_0"),
    ]
    .into_iter()
    .enumerate()
    {
        let dir = scratch(&format!("hostile-dtu-{i}"));
        dtu(&dir, f, scale);
        let (path, field, _) = format_error(load(&dir, &all));
        assert!(path.ends_with("cameras.npz"), "case {i}: {path}");
        assert_eq!(field, want, "case {i}");
    }
}
