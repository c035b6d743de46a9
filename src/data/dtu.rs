//! The IDR/DTU layout: `image/`, `mask/`, `cameras.npz` with `world_mat_i = K·[R|t]` and
//! `scale_mat_i`; a bounded reader of the npz (a zip of `.npy` members).

use super::layout::{
    cameras_file, in_range, pose_from_rows, read_capped, Bounds, FrameSpec, IntrinsicsSpec, Split,
    MAX_CAMERA_VALUE, MIN_FOCAL, MIN_SCALE,
};
use crate::camera::Convention;
use crate::error::{Error, Result};
use glam::{DMat3, DMat4, DVec3};
use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};

/// The largest `cameras.npz` read: the published DTU scenes' files take about 20 kB.
const MAX_NPZ_BYTES: u64 = 64 << 20;
/// The largest `.npy` member read (a 4×4 f64 matrix takes 128 bytes of data).
const MAX_MEMBER_BYTES: u64 = 1 << 20;
/// The largest number of images read from `image/`.
const MAX_IMAGES: usize = 1 << 20;

/// Image files of `dir`, sorted by name (IDR pairs the i-th with `world_mat_i`).
fn listing(dir: &Path) -> Result<Vec<PathBuf>> {
    let io = |source| Error::Io {
        path: dir.display().to_string(),
        source,
    };
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let path = entry.map_err(io)?.path();
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if path.is_file() && matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg")) {
            files.push(path);
            if files.len() > MAX_IMAGES {
                return Err(Error::format(
                    dir,
                    "images",
                    format!("at most {MAX_IMAGES} images"),
                    "more",
                ));
            }
        }
    }
    files.sort();
    Ok(files)
}

/// The frames of an IDR/DTU dataset's split (the hold-out rule of [`Split`]); bounds: the
/// unit sphere.
pub(crate) fn frames(dir: &Path, split: Split) -> Result<(Vec<FrameSpec>, Option<Bounds>)> {
    let cameras = cameras_file(dir).ok_or_else(|| Error::Io {
        path: dir.join("cameras.npz").display().to_string(),
        source: std::io::Error::new(std::io::ErrorKind::NotFound, "no cameras.npz"),
    })?;
    let images = listing(&dir.join("image"))?;
    if images.is_empty() {
        return Err(Error::format(
            dir.join("image"),
            "images",
            "at least one PNG or JPEG",
            "none",
        ));
    }
    let mask_dir = dir.join("mask");
    let masks = if mask_dir.is_dir() {
        let masks = listing(&mask_dir)?;
        if masks.len() != images.len() {
            return Err(Error::format(
                &mask_dir,
                "masks",
                format!("one mask per image ({})", images.len()),
                format!("{} masks", masks.len()),
            ));
        }
        Some(masks)
    } else {
        None
    };
    let npz = read_npz(&cameras)?;
    let mut out = Vec::new();
    for (i, image) in images.into_iter().enumerate() {
        if !split.holds(i) {
            continue;
        }
        let world = matrix(&npz, &cameras, &format!("world_mat_{i}"))?.ok_or_else(|| {
            Error::format(
                &cameras,
                format!("world_mat_{i}"),
                format!("a matrix for image {i}"),
                "no such member",
            )
        })?;
        let scale = matrix(&npz, &cameras, &format!("scale_mat_{i}"))?.unwrap_or(DMat4::IDENTITY);
        check_scale_mat(&scale, &cameras, &format!("scale_mat_{i}"))?;
        let field = format!("world_mat_{i} · scale_mat_{i}");
        let (k, pose) = decompose(&(world * scale), &cameras, &field)?;
        out.push(FrameSpec {
            image,
            mask: masks.as_ref().map(|m| m[i].clone()),
            intrinsics: k,
            cam_to_world: pose,
            convention: Convention::OpenCv,
            source: cameras.clone(),
            field,
            listed_in: dir.to_path_buf(),
            image_field: format!("image/ file {i}"),
            mask_field: format!("mask/ file {i}"),
        });
    }
    if out.is_empty() {
        return Err(Error::format(
            dir,
            "frames",
            "at least one frame in the split",
            "none",
        ));
    }
    let unit = Bounds::Sphere {
        center: [0.0; 3],
        radius: 1.0,
    };
    Ok((out, Some(unit)))
}

/// The member `name` as a 4×4 matrix (a 3×4 one gains the row `[0, 0, 0, 1]`).
fn matrix(npz: &HashMap<String, Npy>, path: &Path, name: &str) -> Result<Option<DMat4>> {
    let Some(m) = npz.get(name) else {
        return Ok(None);
    };
    if !matches!(m.shape[..], [3, 4] | [4, 4]) {
        return Err(Error::format(
            path,
            name,
            "a 3×4 or 4×4 matrix",
            format!("shape {:?}", m.shape),
        ));
    }
    let mut rows = DMat4::IDENTITY.to_cols_array_2d(); // symmetric: rows = columns
    for (r, row) in m.data.chunks_exact(4).enumerate() {
        rows[r].copy_from_slice(row);
    }
    let out = DMat4::from_cols_array_2d(&rows).transpose();
    if !out.is_finite() {
        return Err(Error::format(
            path,
            name,
            "finite entries",
            format!("{out:?}"),
        ));
    }
    Ok(Some(out))
}

/// Splits a projection `P = K·[R|t]` (rows of a 3×4 matrix) into pinhole intrinsics and a
/// camera-to-world pose in OpenCV axes, as OpenCV's `decomposeProjectionMatrix` does in
/// IDR: `M = K R` by an RQ decomposition (Gram–Schmidt on the rows of `M` from the last),
/// `K` normalised to `K₃₃ = 1` with a positive diagonal, the centre `C = −M⁻¹ p₄`. A skew
/// `K₀₁` is dropped if it moves no pixel of the image by more than 0.05 px, else refused.
fn decompose(p: &DMat4, path: &Path, field: &str) -> Result<(IntrinsicsSpec, glam::DAffine3)> {
    let bad =
        |got: String| Error::format(path, field, "a finite projection K·[R|t] of rank 3", got);
    let mut rows: [DVec3; 3] = std::array::from_fn(|r| p.row(r).truncate());
    let mut p4 = p.w_axis.truncate();
    let det = DMat3::from_cols(rows[0], rows[1], rows[2]).determinant();
    let scale = rows.iter().map(|r| r.length()).fold(0.0, f64::max);
    if !(det.is_finite() && det.abs() > 1e-12 * scale.powi(3)) {
        return Err(bad(format!("det M = {det:e}")));
    }
    if det < 0.0 {
        // P and −P are the same camera; pick the sign with det(R) = +1.
        rows = rows.map(|r| -r);
        p4 = -p4;
    }
    let k22 = rows[2].length();
    let r3 = rows[2] / k22;
    let k12 = rows[1].dot(r3);
    let v = rows[1] - k12 * r3;
    let k11 = v.length();
    let r2 = v / k11;
    let k02 = rows[0].dot(r3);
    let k01 = rows[0].dot(r2);
    let u = rows[0] - k01 * r2 - k02 * r3;
    let k00 = u.length();
    let r1 = u / k00;
    let (fx, fy, cx, cy, skew) = (k00 / k22, k11 / k22, k02 / k22, k12 / k22, k01 / k22);
    let m = DMat3::from_cols(rows[0], rows[1], rows[2]).transpose();
    let center = -(m.inverse() * p4);
    let r = DMat3::from_cols(r1, r2, r3).transpose(); // world → camera
    let c2w = r.transpose();
    let rows4 = [0, 1, 2].map(|i| {
        let row = c2w.row(i);
        [row.x, row.y, row.z, center[i]]
    });
    let pose = pose_from_rows(&rows4, path, field)?;
    let m = MAX_CAMERA_VALUE;
    in_range(fx, MIN_FOCAL, m, path, field, "a focal length fx in pixels")?;
    in_range(fy, MIN_FOCAL, m, path, field, "a focal length fy in pixels")?;
    in_range(cx, -m, m, path, field, "a principal point cx in pixels")?;
    in_range(cy, -m, m, path, field, "a principal point cy in pixels")?;
    for x in center.to_array() {
        in_range(x, -m, m, path, field, "a camera centre with coordinates")?;
    }
    // The skew moves pixel (x, y) by skew · (y − cy)/fy; bound |y − cy| by 2·cy.
    if (skew * 2.0 * cy.abs() / fy).abs() > 0.05 {
        return Err(Error::format(
            path,
            field,
            "no skew (K₀₁ shifting pixels by ≤ 0.05 px)",
            format!("K₀₁ / K₂₂ = {skew}"),
        ));
    }
    Ok((
        IntrinsicsSpec::Pinhole {
            fx,
            fy,
            cx: Some(cx),
            cy: Some(cy),
            size: None,
        },
        pose,
    ))
}

/// A `scale_mat` (IDR: the similarity taking the unit sphere to the object's bounding
/// sphere): entries of magnitude at most [`MAX_CAMERA_VALUE`], the last row
/// `[0, 0, 0, 1]`, and a 3×3 part of positive determinant whose scale (its cube root) is
/// at least [`MIN_SCALE`].
fn check_scale_mat(s: &DMat4, path: &Path, field: &str) -> Result<()> {
    let rows = s.transpose().to_cols_array_2d();
    let worst = rows.iter().flatten().fold(0.0f64, |a, x| a.max(x.abs()));
    in_range(
        worst,
        0.0,
        MAX_CAMERA_VALUE,
        path,
        field,
        "a similarity with entries of magnitude",
    )?;
    if rows[3] != [0.0, 0.0, 0.0, 1.0] {
        return Err(Error::format(
            path,
            field,
            "a last row [0, 0, 0, 1]",
            format!("{:?}", rows[3]),
        ));
    }
    let det = DMat3::from_mat4(*s).determinant();
    let scale = det.signum() * det.abs().cbrt();
    in_range(
        scale,
        MIN_SCALE,
        MAX_CAMERA_VALUE,
        path,
        field,
        "a scale (cube root of the determinant of the 3×3 part)",
    )?;
    Ok(())
}

/// One `.npy` array, as f64, row-major.
#[derive(Debug)]
pub(crate) struct Npy {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

/// Reads the members of an npz archive (`np.savez` or `np.savez_compressed`) that are
/// float arrays, keyed by name without `.npy`. Work and memory are bounded by
/// [`MAX_NPZ_BYTES`] and [`MAX_MEMBER_BYTES`] per member, whatever the headers claim.
pub(crate) fn read_npz(path: &Path) -> Result<HashMap<String, Npy>> {
    let bytes = read_capped(path, MAX_NPZ_BYTES)?;
    let bad = |field: String, got: String| {
        Error::format(path, field, "an npz archive of .npy float arrays", got)
    };
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(bytes))
        .map_err(|e| bad("zip".into(), e.to_string()))?;
    let mut out = HashMap::new();
    for i in 0..zip.len() {
        let mut member = zip
            .by_index(i)
            .map_err(|e| bad(format!("member {i}"), e.to_string()))?;
        let name = member
            .name()
            .map_err(|e| bad(format!("member {i}"), e.to_string()))?
            .to_string();
        let Some(key) = name.strip_suffix(".npy") else {
            continue;
        };
        let mut data = Vec::new();
        (&mut member)
            .take(MAX_MEMBER_BYTES + 1)
            .read_to_end(&mut data)
            .map_err(|e| bad(name.clone(), e.to_string()))?;
        if data.len() as u64 > MAX_MEMBER_BYTES {
            return Err(bad(name, format!("a member over {MAX_MEMBER_BYTES} bytes")));
        }
        if let Some(npy) =
            parse_npy(&data).map_err(|got| Error::format(path, &name, "a .npy array", got))?
        {
            out.insert(key.to_string(), npy);
        }
    }
    Ok(out)
}

/// Parses a `.npy` file; `Ok(None)` for arrays of other dtypes than f4/f8 (skipped).
fn parse_npy(bytes: &[u8]) -> std::result::Result<Option<Npy>, String> {
    let rest = bytes
        .strip_prefix(b"\x93NUMPY")
        .ok_or("no \\x93NUMPY magic")?;
    let (&major, rest) = rest.split_first().ok_or("a truncated header")?;
    let rest = rest.get(1..).ok_or("a truncated header")?;
    let (len, rest) = match major {
        1 => {
            let b = rest.get(..2).ok_or("a truncated header")?;
            (usize::from(u16::from_le_bytes([b[0], b[1]])), &rest[2..])
        }
        2 | 3 => {
            let b = rest.get(..4).ok_or("a truncated header")?;
            (
                u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize,
                &rest[4..],
            )
        }
        v => return Err(format!("format version {v}")),
    };
    let header = rest.get(..len).ok_or("a header longer than the member")?;
    let payload = &rest[len..];
    let header = std::str::from_utf8(header).map_err(|_| "a header that is not text")?;
    let descr = dict_value(header, "descr").ok_or("no descr")?;
    let descr = descr.trim_matches(|c| c == '\'' || c == '"');
    let (little, size) = match descr {
        "<f8" | "|f8" => (true, 8),
        ">f8" => (false, 8),
        "<f4" | "|f4" => (true, 4),
        ">f4" => (false, 4),
        _ => return Ok(None),
    };
    let fortran = dict_value(header, "fortran_order").ok_or("no fortran_order")? == "True";
    let shape_text = dict_value(header, "shape").ok_or("no shape")?;
    let shape = shape_text
        .trim_matches(|c| c == '(' || c == ')')
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| format!("shape {shape_text}"))
        })
        .collect::<std::result::Result<Vec<usize>, String>>()?;
    let count = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or_else(|| format!("shape {shape_text}"))?;
    if count.checked_mul(size) != Some(payload.len()) {
        return Err(format!(
            "{} data bytes where shape {shape_text} of {descr} needs {}",
            payload.len(),
            count.saturating_mul(size)
        ));
    }
    let mut data: Vec<f64> = payload
        .chunks_exact(size)
        .map(|c| element(c, little))
        .collect();
    if fortran && shape.len() == 2 {
        let (r, c) = (shape[0], shape[1]);
        data = (0..r * c).map(|i| data[(i % c) * r + i / c]).collect();
    } else if fortran && shape.len() > 2 {
        return Err("a Fortran-ordered array of rank > 2".into());
    }
    Ok(Some(Npy { shape, data }))
}

/// One little- or big-endian float of 4 or 8 bytes (`c.len()`), as f64.
fn element(c: &[u8], little: bool) -> f64 {
    let mut b = [0u8; 8];
    let n = c.len().min(8);
    b[..n].copy_from_slice(&c[..n]);
    let b4 = [b[0], b[1], b[2], b[3]];
    match (n, little) {
        (8, true) => f64::from_le_bytes(b),
        (8, false) => f64::from_be_bytes(b),
        (_, true) => f64::from(f32::from_le_bytes(b4)),
        (_, false) => f64::from(f32::from_be_bytes(b4)),
    }
}

/// The text of `key`'s value in a Python dict literal such as
/// `{'descr': '<f8', 'fortran_order': False, 'shape': (4, 4), }`.
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let at = header.find(&format!("'{key}'"))? + key.len() + 2;
    let rest = header[at..].trim_start().strip_prefix(':')?.trim_start();
    let end = if rest.starts_with('(') {
        rest.find(')')? + 1
    } else {
        rest.find([',', '}'])?
    };
    Some(rest[..end].trim())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(header: &str, payload: &[u8]) -> Vec<u8> {
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend_from_slice(&(header.len() as u16).to_le_bytes());
        b.extend_from_slice(header.as_bytes());
        b.extend_from_slice(payload);
        b
    }

    type TestResult = std::result::Result<(), Box<dyn std::error::Error>>;

    #[test]
    fn npy_parses_c_and_fortran_order() -> TestResult {
        let payload: Vec<u8> = (0..6).flat_map(|i| f64::from(i).to_le_bytes()).collect();
        let c = parse_npy(&npy(
            "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 3), }",
            &payload,
        ))?
        .ok_or("no array")?;
        assert_eq!(
            (c.shape, c.data),
            (vec![2, 3], vec![0., 1., 2., 3., 4., 5.])
        );
        let f = parse_npy(&npy(
            "{'descr': '<f8', 'fortran_order': True, 'shape': (2, 3), }",
            &payload,
        ))?
        .ok_or("no array")?;
        assert_eq!(f.data, vec![0., 2., 4., 1., 3., 5.]);
        Ok(())
    }

    #[test]
    fn npy_with_a_lying_shape_is_refused_without_allocating_it() {
        let payload = 1.0f64.to_le_bytes();
        let e = parse_npy(&npy(
            "{'descr': '<f8', 'fortran_order': False, 'shape': (4611686018427387904, 4), }",
            &payload,
        ));
        assert!(e.is_err(), "{:?}", e.map(|n| n.map(|n| n.shape)));
        let e = parse_npy(&npy(
            "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 2), }",
            &payload,
        ));
        assert!(e.unwrap_err().contains("needs 32"));
    }

    #[test]
    fn projection_decomposes_into_its_intrinsics_and_pose() -> TestResult {
        // K·[R|t] of a camera at c = (1, 2, 3) looking along a rotated axis.
        let (fx, fy, cx, cy) = (500.0, 480.0, 320.5, 240.25);
        let r = DMat3::from_quat(glam::DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0));
        let c = DVec3::new(1.0, 2.0, 3.0);
        let t = -(r * c);
        let k = DMat3::from_cols(
            DVec3::new(fx, 0.0, 0.0),
            DVec3::new(0.0, fy, 0.0),
            DVec3::new(cx, cy, 1.0),
        );
        let kr = k * r;
        let kt = k * t;
        // K·[R|t] times an arbitrary positive scale.
        let p = glam::DMat4::from_cols(
            (kr.x_axis * 7.0).extend(0.0),
            (kr.y_axis * 7.0).extend(0.0),
            (kr.z_axis * 7.0).extend(0.0),
            (kt * 7.0).extend(1.0),
        );
        let (spec, pose) = decompose(&p, Path::new("x"), "P")?;
        match spec {
            IntrinsicsSpec::Pinhole {
                fx: a,
                fy: b,
                cx: Some(c0),
                cy: Some(c1),
                ..
            } => {
                for (got, want) in [(a, fx), (b, fy), (c0, cx), (c1, cy)] {
                    assert!((got - want).abs() < 1e-9, "{got} vs {want}");
                }
            }
            other => return Err(format!("not a pinhole: {other:?}").into()),
        }
        assert!((pose.translation - c).length() < 1e-12);
        assert!((pose.matrix3 - r.transpose())
            .to_cols_array()
            .iter()
            .all(|x| x.abs() < 1e-12));
        // −P is the same camera.
        let neg = -p;
        let (_, pose2) = decompose(&neg, Path::new("x"), "P")?;
        assert!((pose2.translation - c).length() < 1e-12);
        Ok(())
    }
}
