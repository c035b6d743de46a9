//! The nerfstudio / instant-NGP layout: one `transforms.json` with pinhole intrinsics
//! (`fl_x, fl_y, cx, cy, w, h`, global or per frame), `camera_model`, distortion
//! coefficients (refused unless zero), `scale`/`offset` applied to the camera centres,
//! `aabb_scale` as the stated bounds, and per-frame `file_path`, `mask_path` and
//! `transform_matrix` (camera-to-world, OpenGL axes).
//!
//! Its reader of one `transforms*.json` file, [`read_transforms`], also reads the Blender
//! layout's split files: nerfstudio's format extends Blender's (the same frames and
//! `transform_matrix`, with `camera_angle_x` when no focal length is given).

use super::layout::{
    in_range, pose_from_rows, read_capped, Bounds, FrameSpec, IntrinsicsSpec, Split,
    MAX_CAMERA_VALUE, MIN_ANGLE, MIN_FOCAL, MIN_SCALE,
};
use crate::camera::Convention;
use crate::error::{Error, Result};
use glam::DAffine3;
use serde_json::{Map, Value};
use std::path::{Path, PathBuf};

/// The largest `transforms*.json` read (a million frames take about 300 MB; the published
/// datasets take under 10 MB).
const MAX_JSON_BYTES: u64 = 256 << 20;

/// Image extensions tried, in order, for a `file_path` without one (the Blender synthetic
/// files name `./train/r_0` for `./train/r_0.png`).
const EXTENSIONS: [&str; 5] = ["png", "PNG", "jpg", "jpeg", "JPG"];

/// Distortion coefficients of the nerfstudio layout; any non-zero one is refused.
const DISTORTION: [&str; 6] = ["k1", "k2", "k3", "k4", "p1", "p2"];

/// The frames (and stated bounds) of a nerfstudio dataset's split: `dir/transforms.json`,
/// with the hold-out rule of [`Split`].
pub(crate) fn frames(dir: &Path, split: Split) -> Result<(Vec<FrameSpec>, Option<Bounds>)> {
    read_transforms(&dir.join("transforms.json"), |i| split.holds(i))
}

/// The frames of the `transforms*.json` file at `path` whose index passes `keep`, and the
/// bounds it states (`aabb_scale`).
pub(crate) fn read_transforms(
    path: &Path,
    keep: impl Fn(usize) -> bool,
) -> Result<(Vec<FrameSpec>, Option<Bounds>)> {
    let bytes = read_capped(path, MAX_JSON_BYTES)?;
    let root: Value = serde_json::from_slice(&bytes)
        .map_err(|e| Error::format(path, "JSON", "valid JSON", e.to_string()))?;
    let Some(root) = root.as_object() else {
        return Err(Error::format(
            path,
            "top level",
            "a JSON object",
            kind(&root),
        ));
    };
    let Some(frames) = root.get("frames") else {
        return Err(Error::format(
            path,
            "frames",
            "a list of frames",
            "no `frames` key",
        ));
    };
    let Some(frames) = frames.as_array() else {
        return Err(Error::format(
            path,
            "frames",
            "a list of frames",
            kind(frames),
        ));
    };
    let dir = path.parent().unwrap_or(Path::new("."));
    let (scale, offset) = scale_offset(root, path)?;
    let mut out = Vec::new();
    for (i, frame) in frames.iter().enumerate() {
        if !keep(i) {
            continue;
        }
        let field = format!("frames[{i}]");
        let Some(obj) = frame.as_object() else {
            return Err(Error::format(path, &field, "a JSON object", kind(frame)));
        };
        let intrinsics = intrinsics(obj, root, path, &field)?;
        let rows = matrix(obj, path, &format!("{field}.transform_matrix"))?;
        let pose = pose_from_rows(&rows, path, &format!("{field}.transform_matrix"))?;
        let pose = DAffine3::from_mat3_translation(pose.matrix3, pose.translation * scale + offset);
        for x in pose.translation.to_array() {
            in_range(
                x,
                -MAX_CAMERA_VALUE,
                MAX_CAMERA_VALUE,
                path,
                &format!("{field}.transform_matrix"),
                "a camera centre (after scale and offset) with coordinates",
            )?;
        }
        let file = string(obj, "file_path", path, &field)?.ok_or_else(|| {
            Error::format(path, format!("{field}.file_path"), "an image path", "none")
        })?;
        let mask = string(obj, "mask_path", path, &field)?.map(|m| dir.join(m));
        out.push(FrameSpec {
            image: resolve(dir, &file),
            mask,
            intrinsics,
            cam_to_world: pose,
            convention: Convention::OpenGl,
            source: path.to_path_buf(),
            field: format!("{field}.transform_matrix"),
            listed_in: path.to_path_buf(),
            image_field: format!("{field}.file_path"),
            mask_field: format!("{field}.mask_path"),
        });
    }
    if out.is_empty() {
        return Err(Error::format(
            path,
            "frames",
            "at least one frame in the split",
            format!("none of {} frames", frames.len()),
        ));
    }
    let bounds = match root.get("aabb_scale") {
        Some(v) => {
            let s = v.as_f64().ok_or_else(|| {
                Error::format(path, "aabb_scale", "a positive number", v.to_string())
            })?;
            let s = in_range(
                s,
                MIN_SCALE,
                MAX_CAMERA_VALUE,
                path,
                "aabb_scale",
                "a positive number",
            )?;
            // instant-NGP: the scene extends `aabb_scale` unit cubes around the offset.
            let c = offset.to_array();
            Some(Bounds::Aabb {
                min: c.map(|x| x - 0.5 * s),
                max: c.map(|x| x + 0.5 * s),
            })
        }
        None => None,
    };
    Ok((out, bounds))
}

/// `scale` and `offset` (instant-NGP): camera centres become `scale · t + offset`.
fn scale_offset(root: &Map<String, Value>, path: &Path) -> Result<(f64, glam::DVec3)> {
    let scale = match root.get("scale") {
        Some(v) => {
            let s = v
                .as_f64()
                .ok_or_else(|| Error::format(path, "scale", "a positive number", v.to_string()))?;
            in_range(
                s,
                MIN_SCALE,
                MAX_CAMERA_VALUE,
                path,
                "scale",
                "a positive number",
            )?
        }
        None => 1.0,
    };
    let offset = match root.get("offset") {
        Some(v) => {
            let o: Option<Vec<f64>> = v.as_array().map(|a| {
                a.iter()
                    .filter_map(Value::as_f64)
                    .filter(|x| x.is_finite() && x.abs() <= MAX_CAMERA_VALUE)
                    .collect()
            });
            match o {
                Some(o) if o.len() == 3 => glam::DVec3::new(o[0], o[1], o[2]),
                _ => {
                    return Err(Error::format(
                        path,
                        "offset",
                        format!("three numbers in [-{MAX_CAMERA_VALUE:e}, {MAX_CAMERA_VALUE:e}]"),
                        v.to_string(),
                    ))
                }
            }
        }
        None => glam::DVec3::ZERO,
    };
    Ok((scale, offset))
}

fn kind(v: &Value) -> String {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "a list",
        Value::Object(_) => "an object",
    }
    .to_string()
}

fn string(obj: &Map<String, Value>, key: &str, path: &Path, field: &str) -> Result<Option<String>> {
    match obj.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::String(s)) => Ok(Some(s.clone())),
        Some(other) => Err(Error::format(
            path,
            format!("{field}.{key}"),
            "a string",
            kind(other),
        )),
    }
}

/// A number under `key` in the frame, else in the file's top level.
fn number(
    frame: &Map<String, Value>,
    root: &Map<String, Value>,
    key: &str,
    path: &Path,
    field: &str,
) -> Result<Option<f64>> {
    let (value, name) = match (frame.get(key), root.get(key)) {
        (Some(v), _) => (v, format!("{field}.{key}")),
        (None, Some(v)) => (v, key.to_string()),
        (None, None) => return Ok(None),
    };
    match value.as_f64() {
        Some(x) if x.is_finite() => Ok(Some(x)),
        _ => Err(Error::format(
            path,
            name,
            "a finite number",
            value.to_string(),
        )),
    }
}

fn size(
    frame: &Map<String, Value>,
    root: &Map<String, Value>,
    key: &str,
    path: &Path,
    field: &str,
) -> Result<Option<usize>> {
    match number(frame, root, key, path, field)? {
        None => Ok(None),
        Some(x) if x >= 1.0 && x.fract() == 0.0 && x <= MAX_CAMERA_VALUE => Ok(Some(x as usize)),
        Some(x) => Err(Error::format(
            path,
            key,
            format!("a positive integer up to {MAX_CAMERA_VALUE:e}"),
            x.to_string(),
        )),
    }
}

fn intrinsics(
    frame: &Map<String, Value>,
    root: &Map<String, Value>,
    path: &Path,
    field: &str,
) -> Result<IntrinsicsSpec> {
    let model = match (frame.get("camera_model"), root.get("camera_model")) {
        (Some(v), _) | (None, Some(v)) => Some(v),
        (None, None) => None,
    };
    if let Some(model) = model {
        let name = model.as_str().unwrap_or_default();
        if !matches!(
            name,
            "OPENCV" | "PINHOLE" | "SIMPLE_PINHOLE" | "PERSPECTIVE"
        ) {
            return Err(Error::format(
                path,
                "camera_model",
                "a pinhole model (OPENCV, PINHOLE, SIMPLE_PINHOLE; fisheye and equirectangular cameras are not supported)",
                model.to_string(),
            ));
        }
    }
    for key in DISTORTION {
        if let Some(k) = number(frame, root, key, path, field)? {
            if k != 0.0 {
                return Err(Error::format(
                    path,
                    key,
                    "no lens distortion (undistort the images first, e.g. with COLMAP's image_undistorter)",
                    k.to_string(),
                ));
            }
        }
    }
    let fx = number(frame, root, "fl_x", path, field)?;
    let fy = number(frame, root, "fl_y", path, field)?;
    let focal = |x: f64, key: &str| {
        in_range(
            x,
            MIN_FOCAL,
            MAX_CAMERA_VALUE,
            path,
            key,
            "a focal length in pixels",
        )
    };
    let principal = |key: &str| -> Result<Option<f64>> {
        number(frame, root, key, path, field)?
            .map(|x| {
                in_range(
                    x,
                    -MAX_CAMERA_VALUE,
                    MAX_CAMERA_VALUE,
                    path,
                    key,
                    "a principal point coordinate in pixels",
                )
            })
            .transpose()
    };
    if let Some(fx) = fx {
        let fx = focal(fx, "fl_x")?;
        let fy = focal(fy.unwrap_or(fx), "fl_y")?;
        let w = size(frame, root, "w", path, field)?;
        let h = size(frame, root, "h", path, field)?;
        return Ok(IntrinsicsSpec::Pinhole {
            fx,
            fy,
            cx: principal("cx")?,
            cy: principal("cy")?,
            size: w.zip(h),
        });
    }
    let angle = |key: &str| -> Result<Option<f64>> {
        match number(frame, root, key, path, field)? {
            Some(a) => in_range(
                a,
                MIN_ANGLE,
                std::f64::consts::PI - MIN_ANGLE,
                path,
                key,
                "a field of view in radians",
            )
            .map(Some),
            None => Ok(None),
        }
    };
    match angle("camera_angle_x")? {
        Some(angle_x) => Ok(IntrinsicsSpec::Fov {
            angle_x,
            angle_y: angle("camera_angle_y")?,
        }),
        None => Err(Error::format(
            path,
            "camera_angle_x",
            "camera_angle_x or fl_x (the focal length)",
            "neither",
        )),
    }
}

fn matrix(obj: &Map<String, Value>, path: &Path, field: &str) -> Result<Vec<[f64; 4]>> {
    let Some(value) = obj.get("transform_matrix") else {
        return Err(Error::format(path, field, "a 4×4 matrix", "no such key"));
    };
    let bad = || {
        Error::format(
            path,
            field,
            "a 3×4 or 4×4 matrix of numbers",
            value.to_string(),
        )
    };
    let rows = value.as_array().ok_or_else(bad)?;
    if rows.len() > 4 {
        return Err(bad());
    }
    rows.iter()
        .map(|row| {
            let row = row.as_array().filter(|r| r.len() == 4).ok_or_else(bad)?;
            let mut out = [0.0; 4];
            for (o, v) in out.iter_mut().zip(row) {
                // NaN has no JSON spelling; `null` in its place is reported as NaN.
                *o = if v.is_null() {
                    f64::NAN
                } else {
                    v.as_f64().ok_or_else(bad)?
                };
            }
            Ok(out)
        })
        .collect()
}

/// `dir/file`, with an image extension appended when `file` has none and the file without
/// one does not exist.
fn resolve(dir: &Path, file: &str) -> PathBuf {
    let path = dir.join(file);
    if path.extension().is_some() || path.is_file() {
        return path;
    }
    EXTENSIONS
        .iter()
        .map(|e| dir.join(format!("{file}.{e}")))
        .find(|p| p.is_file())
        .unwrap_or(path)
}
