//! 8-bit images in memory, their decoding from PNG/JPEG files and integer downscaling.

use crate::error::{Error, Result};
use candle_core::{DType, Tensor};
use std::path::Path;

/// The largest image this crate decodes, in pixels (2¹⁸ × 2¹⁸ would be 2³⁶): a header that
/// claims more is refused before anything is allocated.
pub(crate) const MAX_PIXELS: u64 = 1 << 30;

/// An 8-bit image: `height` rows of `width` pixels of `channels` bytes, row-major, with
/// straight (not premultiplied) alpha when `channels == 4`.
///
/// Images keep the bytes of the file, so a dataset in memory takes no more than its decoded
/// image bytes; they become floating-point tensors in `[0, 1]` only batch by batch
/// ([`crate::data::RaySampler`]) or view by view ([`crate::data::View::rgb`]). 16-bit files are rounded to
/// 8 bits when decoded.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    width: usize,
    height: usize,
    channels: usize,
    data: Vec<u8>,
}

impl Image {
    /// An image from its bytes: `data.len() == width · height · channels`, `channels` 1
    /// (grey or mask), 3 (RGB) or 4 (RGBA, straight alpha).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `channels` unless 1, 3 or 4, `width` / `height` if
    /// 0, and `data` if its length is not `width · height · channels`.
    pub fn new(width: usize, height: usize, channels: usize, data: Vec<u8>) -> Result<Self> {
        if !matches!(channels, 1 | 3 | 4) {
            return Err(Error::invalid(
                "channels",
                "1, 3 or 4",
                channels.to_string(),
            ));
        }
        if width == 0 || height == 0 {
            return Err(Error::invalid(
                if width == 0 { "width" } else { "height" },
                "> 0",
                "0",
            ));
        }
        let want = width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(channels));
        if want != Some(data.len()) {
            return Err(Error::invalid(
                "data",
                format!("{width} × {height} × {channels} bytes"),
                format!("{} bytes", data.len()),
            ));
        }
        Ok(Self {
            width,
            height,
            channels,
            data,
        })
    }

    /// An image from a float tensor `[H, W]` or `[H, W, C]` (C = 1, 3 or 4) of values in
    /// `[0, 1]` (clamped), rounded to the nearest of 256 levels (`round(255 · v)`), as a
    /// PNG writer would. Any dtype and device; not differentiable (it leaves the graph).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `image` for another rank or channel count, an
    /// empty image, or a NaN.
    pub(crate) fn from_tensor(image: &Tensor) -> Result<Self> {
        let (h, w, c) = image_shape(image, "image")?;
        if !matches!(c, 1 | 3 | 4) {
            return Err(Error::invalid(
                "image",
                "an image with 1, 3 or 4 channels",
                format!("shape {:?}", image.dims()),
            ));
        }
        let values = image
            .flatten_all()?
            .to_dtype(DType::F64)?
            .to_vec1::<f64>()?;
        let mut data = Vec::with_capacity(values.len());
        for v in values {
            if v.is_nan() {
                return Err(Error::invalid("image", "no NaN values", "NaN"));
            }
            data.push((v.clamp(0.0, 1.0) * 255.0).round() as u8);
        }
        Self::new(w, h, c, data)
    }

    /// The size `(width, height, channels)`: pixels per row, rows, and bytes per pixel
    /// (1, 3 or 4), in the order [`Image::new`] takes them.
    #[must_use]
    pub fn size(&self) -> (usize, usize, usize) {
        (self.width, self.height, self.channels)
    }

    /// The bytes, row-major, `channels` per pixel.
    #[must_use]
    pub fn data(&self) -> &[u8] {
        &self.data
    }

    /// The bytes of pixel `(u, v)` (column, row); `None` outside the image.
    pub(crate) fn pixel(&self, u: usize, v: usize) -> Option<&[u8]> {
        if u >= self.width || v >= self.height {
            return None;
        }
        let i = (v * self.width + u) * self.channels;
        Some(&self.data[i..i + self.channels])
    }

    /// Decodes the PNG or JPEG at `path` (format from its bytes), keeping RGBA as 4
    /// channels and turning grey or grey-alpha into RGB(A) when `mask` is false, or into one
    /// grey channel (the luma) when it is true.
    pub(crate) fn decode(path: &Path, mask: bool) -> Result<Self> {
        // The file opened, so read errors now mean truncated or corrupt content.
        let bad = |e: image::ImageError| {
            Error::format(path, "image", "a complete PNG or JPEG file", e.to_string())
        };
        let reader = image::ImageReader::open(path)
            .map_err(|source| Error::Io {
                path: path.display().to_string(),
                source,
            })?
            .with_guessed_format()
            .map_err(|source| Error::Io {
                path: path.display().to_string(),
                source,
            })?;
        let mut decoder = reader.into_decoder().map_err(bad)?;
        let (w, h) = image::ImageDecoder::dimensions(&decoder);
        if u64::from(w) * u64::from(h) > MAX_PIXELS {
            return Err(Error::format(
                path,
                "image size",
                format!("at most {MAX_PIXELS} pixels"),
                format!("{w} × {h}"),
            ));
        }
        let mut limits = image::Limits::default();
        limits.max_alloc = Some(16 * MAX_PIXELS);
        image::ImageDecoder::set_limits(&mut decoder, limits).map_err(bad)?;
        let decoded = image::DynamicImage::from_decoder(decoder).map_err(bad)?;
        let (w, h) = (decoded.width() as usize, decoded.height() as usize);
        let (channels, data) = if mask {
            (1, decoded.into_luma8().into_raw())
        } else if decoded.color().has_alpha() {
            (4, decoded.into_rgba8().into_raw())
        } else {
            (3, decoded.into_rgb8().into_raw())
        };
        Self::new(w, h, channels, data)
    }

    /// Box-filter downscaling by an integer factor `k`: each output pixel averages a
    /// `k × k` block (colour weighted by alpha for RGBA, so that transparent pixels do not
    /// darken edges); a remainder of fewer than `k` rows or columns is cropped.
    pub(crate) fn downscale(&self, k: usize) -> Self {
        if k == 1 {
            return self.clone();
        }
        let (w, h, c) = (self.width / k, self.height / k, self.channels);
        let mut data = Vec::with_capacity(w * h * c);
        let mut acc = [0f64; 4];
        for v in 0..h {
            for u in 0..w {
                acc.fill(0.0);
                for dv in 0..k {
                    for du in 0..k {
                        // u·k + du < (width / k)·k ≤ width, and likewise for v.
                        let p = self
                            .pixel(u * k + du, v * k + dv)
                            .expect("block lies inside the image"); // invariant
                        let a = if c == 4 { f64::from(p[3]) } else { 1.0 };
                        for ch in 0..c.min(3) {
                            acc[ch] += a * f64::from(p[ch]);
                        }
                        if c == 4 {
                            acc[3] += a;
                        }
                    }
                }
                let n = (k * k) as f64;
                let weight = if c == 4 { acc[3] } else { n };
                for &sum in acc.iter().take(c.min(3)) {
                    let value = if weight > 0.0 { sum / weight } else { 0.0 };
                    data.push(value.round() as u8);
                }
                if c == 4 {
                    data.push((acc[3] / n).round() as u8);
                }
            }
        }
        Self {
            width: w,
            height: h,
            channels: c,
            data,
        }
    }
}

/// The `(H, W, C)` of a non-empty image tensor `[H, W]` (C = 1) or `[H, W, C]`.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `arg` for another rank or an empty image.
pub(crate) fn image_shape(t: &Tensor, arg: &'static str) -> Result<(usize, usize, usize)> {
    let dims = t.dims();
    let (h, w, c) = match dims[..] {
        [h, w] => (h, w, 1),
        [h, w, c] => (h, w, c),
        _ => {
            return Err(Error::invalid(
                arg,
                "an image [H, W] or [H, W, C]",
                format!("shape {dims:?}"),
            ))
        }
    };
    if h == 0 || w == 0 || c == 0 {
        return Err(Error::invalid(
            arg,
            "a non-empty image",
            format!("shape {dims:?}"),
        ));
    }
    Ok((h, w, c))
}
