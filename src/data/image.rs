//! 8-bit images in memory, their decoding from PNG/JPEG files and integer downscaling.

use crate::error::{Error, Result};
use candle_core::{DType, Tensor};
use std::path::Path;

/// What an image file's header says, read before any pixel is decoded: the size, the
/// bytes of the decoder's output in the file's own pixel format (`native_bytes`: 16-bit
/// channels take 2 bytes) and the bytes of the 8-bit image kept (`kept_bytes`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Header {
    pub width: usize,
    pub height: usize,
    pub native_bytes: u64,
    pub kept_bytes: u64,
}

impl Header {
    /// The bytes a decode holds at its peak, counted against a load's budget: the larger
    /// of the decoder's output and the 8-bit image kept.
    pub(crate) fn decoded_bytes(&self) -> u64 {
        self.native_bytes.max(self.kept_bytes)
    }
}

/// The limits of a decoder opened to read a header: no image buffer is allocated yet,
/// and the decoder's own allocations (metadata chunks) stay below what `max_pixels`
/// pixels of 16-bit RGBA would take.
fn reader_limits(max_pixels: u64) -> image::Limits {
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(max_pixels.saturating_mul(8).saturating_add(16 << 20));
    limits
}

/// A decoder of the file at `path` (format guessed from its bytes) under `limits`; the
/// header is read, no pixel.
fn open_decoder(path: &Path, limits: image::Limits) -> Result<impl image::ImageDecoder> {
    let io = |source| Error::Io {
        path: path.display().to_string(),
        source,
    };
    let mut reader = image::ImageReader::open(path)
        .map_err(io)?
        .with_guessed_format()
        .map_err(io)?;
    reader.limits(limits);
    reader
        .into_decoder()
        .map_err(|e| Error::format(path, "image", "a PNG or JPEG file", e.to_string()))
}

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

    /// Reads the header of the PNG or JPEG at `path` (format from its bytes), without
    /// decoding any pixel: its size and the bytes that decoding it will hold.
    ///
    /// # Errors
    /// [`Error::Io`] naming `path` if it cannot be opened or read; [`Error::Format`] naming
    /// it for a header that is not a PNG or JPEG one, or that states more than
    /// `max_pixels` pixels (checked before anything of that size is allocated).
    pub(crate) fn header(path: &Path, mask: bool, max_pixels: u64) -> Result<Header> {
        let decoder = open_decoder(path, reader_limits(max_pixels))?;
        let (w, h) = image::ImageDecoder::dimensions(&decoder);
        let pixels = u64::from(w) * u64::from(h);
        if pixels > max_pixels {
            return Err(Error::format(
                path,
                "image size",
                format!("at most {max_pixels} pixels (LoadConfig::max_image_pixels)"),
                format!("{w} × {h} = {pixels} pixels, stated by the header"),
            ));
        }
        let native = image::ImageDecoder::total_bytes(&decoder);
        let alpha = image::ImageDecoder::color_type(&decoder).has_alpha();
        let channels = if mask {
            1
        } else if alpha {
            4
        } else {
            3
        };
        Ok(Header {
            width: w as usize,
            height: h as usize,
            native_bytes: native,
            kept_bytes: pixels * channels,
        })
    }

    /// Decodes the PNG or JPEG at `path`, whose header [`Image::header`] read, keeping RGBA
    /// as 4 channels and turning grey or grey-alpha into RGB(A) when `mask` is false, or
    /// into one grey channel (the luma) when it is true. The decoder's limits hold it to
    /// the header's size.
    pub(crate) fn decode(path: &Path, mask: bool, header: &Header) -> Result<Self> {
        // The file opened, so read errors now mean truncated or corrupt content.
        let bad = |e: image::ImageError| {
            Error::format(path, "image", "a complete PNG or JPEG file", e.to_string())
        };
        let mut limits = image::Limits::default();
        limits.max_image_width = u32::try_from(header.width).ok();
        limits.max_image_height = u32::try_from(header.height).ok();
        limits.max_alloc = Some(
            header
                .native_bytes
                .saturating_mul(2)
                .saturating_add(16 << 20),
        );
        let decoder = open_decoder(path, limits)?;
        let decoded = image::DynamicImage::from_decoder(decoder).map_err(bad)?;
        let (w, h) = (decoded.width() as usize, decoded.height() as usize);
        if (w, h) != (header.width, header.height) {
            return Err(Error::format(
                path,
                "image size",
                format!(
                    "{} × {}, as its header said when first read",
                    header.width, header.height
                ),
                format!("{w} × {h} (the file changed while loading)"),
            ));
        }
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
