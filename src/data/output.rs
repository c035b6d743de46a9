//! Pictures and datasets out: PNG writing (atomic), colour maps for depth and error,
//! comparison strips, and the Blender-layout writer.

use super::dataset::Dataset;
use super::image::Image;
use super::layout::Split;
use crate::camera::Convention;
use crate::error::{Error, Result};
use candle_core::{DType, Tensor};
use glam::DMat3;
use serde_json::Value;
use std::path::Path;

/// Writes `bytes` to `path` through a temporary file beside it and a rename, so that
/// `path` is either absent, its old content, or complete.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let io = |source| Error::Io {
        path: path.display().to_string(),
        source,
    };
    let name = path.file_name().ok_or_else(|| {
        io(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "no file name",
        ))
    })?;
    let tmp = path.with_file_name(format!(
        ".{}.tmp{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    let result = std::fs::write(&tmp, bytes).and_then(|()| std::fs::rename(&tmp, path));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.map_err(io)
}

/// 8-bit PNG bytes of `width × height` pixels with `channels` (1, 3 or 4) per pixel.
pub(crate) fn encode_png(
    width: usize,
    height: usize,
    channels: usize,
    data: &[u8],
) -> Result<Vec<u8>> {
    let color = match channels {
        1 => image::ExtendedColorType::L8,
        3 => image::ExtendedColorType::Rgb8,
        _ => image::ExtendedColorType::Rgba8,
    };
    let mut out = Vec::new();
    image::ImageEncoder::write_image(
        image::codecs::png::PngEncoder::new(&mut out),
        data,
        width as u32,
        height as u32,
        color,
    )
    .map_err(|e| Error::invalid("image", "an image the PNG encoder accepts", e.to_string()))?;
    Ok(out)
}

/// Writes an image tensor as an 8-bit PNG: `image: [H, W]` (grey, e.g. opacity) or
/// `[H, W, C]` with C = 1, 3 or 4, values in `[0, 1]` (clamped, then `round(255·v)`; a NaN is
/// an error). Any float dtype and device. The file is written to a temporary
/// name and renamed, never left half-written.
///
/// ```no_run
/// use candle_core::{DType, Device, Tensor};
/// let rgb = Tensor::ones((64, 64, 3), DType::F32, &Device::Cpu)?;
/// neural_fields::data::write_png("white.png".as_ref(), &rgb)?;
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `image` for a wrong shape or NaN values;
/// [`Error::Io`] naming the path if it cannot be written.
pub fn write_png(path: &Path, image: &Tensor) -> Result<()> {
    let img = Image::from_tensor(image)?;
    let (w, h, c) = img.size();
    let png = encode_png(w, h, c, img.data())?;
    write_atomic(path, &png)
}

/// The turbo colour map (Mikhailov 2019) at `t ∈ [0, 1]`, by its published polynomial fit.
fn turbo(t: f64) -> [f64; 3] {
    let t = t.clamp(0.0, 1.0);
    let poly = |c: [f64; 6]| c.iter().rev().fold(0.0, |acc, &k| acc * t + k);
    [
        poly([
            0.13572138,
            4.61539260,
            -42.66032258,
            132.13108234,
            -152.94239396,
            59.28637943,
        ]),
        poly([
            0.09140261,
            2.19418839,
            4.84296658,
            -14.18503333,
            4.27729857,
            2.82956604,
        ]),
        poly([
            0.10667330,
            12.64194608,
            -60.58204836,
            110.36276771,
            -89.90310912,
            27.34824973,
        ]),
    ]
    .map(|x| x.clamp(0.0, 1.0))
}

/// `[H, W]` values on the host, checking the shape.
fn plane(t: &Tensor, arg: &'static str) -> Result<(usize, usize, Vec<f64>)> {
    let dims = t.dims().to_vec();
    let [h, w] = dims[..] else {
        return Err(Error::invalid(arg, "shape [H, W]", format!("{dims:?}")));
    };
    if !matches!(t.dtype(), DType::F32 | DType::F64) {
        return Err(Error::invalid(
            arg,
            "f32 or f64",
            format!("{:?}", t.dtype()),
        ));
    }
    Ok((
        h,
        w,
        t.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?,
    ))
}

fn rgb_tensor(data: Vec<f64>, h: usize, w: usize, like: &Tensor) -> Result<Tensor> {
    Ok(Tensor::from_vec(data, (h, w, 3), like.device())?.to_dtype(like.dtype())?)
}

/// Colour-maps a depth image `depth: [H, W]` with turbo (near blue, far red) over `range`,
/// or over the finite values' `[min, max]` when `range` is `None`; non-finite depths are
/// black. Returns the `[H, W, 3]` picture (dtype and device of `depth`) and the range used,
/// to print beside it.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `depth` for another shape or dtype, `range` unless
/// finite with `lo < hi`.
pub fn colorize_depth(depth: &Tensor, range: Option<(f64, f64)>) -> Result<(Tensor, (f64, f64))> {
    let (h, w, d) = plane(depth, "depth")?;
    let (lo, hi) = match range {
        Some(r) => r,
        None => d
            .iter()
            .filter(|x| x.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            }),
    };
    let degenerate = lo.partial_cmp(&hi) != Some(std::cmp::Ordering::Less);
    let (lo, hi) = if range.is_none() && degenerate {
        // Constant or empty: any non-degenerate range shows it.
        let c = if lo.is_finite() { lo } else { 0.0 };
        (c, c + 1.0)
    } else {
        (lo, hi)
    };
    if !(lo.is_finite() && hi.is_finite() && lo < hi) {
        return Err(Error::invalid(
            "range",
            "finite (lo, hi) with lo < hi",
            format!("({lo}, {hi})"),
        ));
    }
    let data = d
        .iter()
        .flat_map(|&x| {
            if x.is_finite() {
                turbo((x - lo) / (hi - lo))
            } else {
                [0.0; 3]
            }
        })
        .collect();
    Ok((rgb_tensor(data, h, w, depth)?, (lo, hi)))
}

/// A side-by-side strip `target | pred | error` of two `[H, W, 3]` images in `[0, 1]`: the
/// error panel is the per-pixel mean absolute difference over channels through turbo on
/// `[0, 0.25]` (so 0.25 and above is red), the same scale for every picture. Returns
/// `[H, 3W, 3]` in the dtype and on the device of `pred`.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `pred` for another shape than `[H, W, 3]`, `target`
/// for another shape than `pred`'s.
pub fn comparison_strip(target: &Tensor, pred: &Tensor) -> Result<Tensor> {
    let dims = pred.dims().to_vec();
    if dims.len() != 3 || dims[2] != 3 {
        return Err(Error::invalid(
            "pred",
            "shape [H, W, 3]",
            format!("{dims:?}"),
        ));
    }
    if target.dims() != pred.dims() {
        return Err(Error::invalid(
            "target",
            format!("the shape of pred {dims:?}"),
            format!("{:?}", target.dims()),
        ));
    }
    let err = (pred - target.to_dtype(pred.dtype())?)?
        .abs()?
        .mean(2)?
        .to_dtype(DType::F64)?;
    let (h, w) = (dims[0], dims[1]);
    let heat: Vec<f64> = err
        .flatten_all()?
        .to_vec1::<f64>()?
        .iter()
        .flat_map(|&e| {
            if e.is_finite() {
                turbo(e / 0.25)
            } else {
                [0.0; 3]
            }
        })
        .collect();
    let heat = rgb_tensor(heat, h, w, pred)?;
    let target = target.to_dtype(pred.dtype())?.to_device(pred.device())?;
    Ok(Tensor::cat(&[&target, pred, &heat], 1)?)
}

/// Writes `dataset` as the `split` of a Blender-layout dataset in `dir` (created if
/// needed): `transforms_{split}.json` and `{split}/r_{i}.png`.
///
/// The JSON holds `camera_angle_x` (from the first view) and, per frame, `file_path`
/// (`./{split}/r_{i}`, without extension as in the published scenes), `transform_matrix`
/// (camera-to-world in OpenGL axes; OpenCV cameras are converted exactly, by negating the
/// second and third axes) and the exact pinhole intrinsics `fl_x, fl_y, cx, cy, w, h`, which
/// [`load`](crate::data::load) prefers over `camera_angle_x`, so that a write → load round
/// trip reproduces poses to rounding and pixels bit for bit. Images are written as RGBA
/// PNG (RGB images with a mask file take the mask as alpha), masks otherwise dropped.
///
/// Every file is written to a temporary name beside its destination and renamed into
/// place, the JSON last, so no file is left half-written and the JSON never names an image
/// that is not complete.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `split` for [`Split::All`]; [`Error::Io`] naming the
/// file that could not be written.
pub fn write_blender(dir: &Path, split: Split, dataset: &Dataset) -> Result<()> {
    if split == Split::All {
        return Err(Error::invalid("split", "train, val or test", "all"));
    }
    let name = split.name();
    let image_dir = dir.join(name);
    std::fs::create_dir_all(&image_dir).map_err(|source| Error::Io {
        path: image_dir.display().to_string(),
        source,
    })?;
    let first = dataset.views()[0].camera().intrinsics();
    let angle_x = 2.0 * (0.5 * first.width as f64 / first.fx).atan();
    let mut frames = Vec::with_capacity(dataset.views().len());
    for (i, view) in dataset.views().iter().enumerate() {
        let image = view.image();
        let (w, h, channels) = image.size();
        let rgba = match (channels, view.mask_image()) {
            (4, _) => image.data().to_vec(),
            (_, mask) => image
                .data()
                .chunks_exact(3)
                .enumerate()
                .flat_map(|(p, c)| [c[0], c[1], c[2], mask.map_or(255, |m| m.data()[p])])
                .collect(),
        };
        let png = encode_png(w, h, 4, &rgba)?;
        write_atomic(&image_dir.join(format!("r_{i}.png")), &png)?;
        let camera = view.camera();
        let mut m = camera.cam_to_world().matrix3;
        if camera.convention() == Convention::OpenCv {
            m = DMat3::from_cols(m.x_axis, -m.y_axis, -m.z_axis);
        }
        let t = camera.cam_to_world().translation;
        let rows: Vec<Value> = (0..3)
            .map(|r| Value::from(vec![m.row(r).x, m.row(r).y, m.row(r).z, t[r]]))
            .chain(std::iter::once(Value::from(vec![0.0, 0.0, 0.0, 1.0])))
            .collect();
        let k = camera.intrinsics();
        frames.push(serde_json::json!({
            "file_path": format!("./{name}/r_{i}"),
            "rotation": 0.0,
            "transform_matrix": rows,
            "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width, "h": k.height,
        }));
    }
    let json = serde_json::json!({ "camera_angle_x": angle_x, "frames": frames });
    let text = serde_json::to_string_pretty(&json).map_err(|e| Error::Io {
        path: dir.display().to_string(),
        source: std::io::Error::other(e),
    })?;
    write_atomic(
        &dir.join(format!("transforms_{name}.json")),
        text.as_bytes(),
    )
}
