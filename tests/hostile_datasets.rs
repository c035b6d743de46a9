//! Hostile dataset folders, generated here at test time: paths that leave the folder,
//! special files, and degenerate cameras in every layout. Each gives an `Err` naming the
//! file and the field, or a correct `Ok`, in bounded time.
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
