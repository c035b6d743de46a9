//! PNG output of the examples.

use std::path::Path;

/// Writes 8-bit pixels (`width × height`, row-major, channels as `color` says) to a
/// PNG at `path`; errors are reported as [`neural_fields::Error::Io`] naming the path.
pub fn write_png(
    path: &Path,
    width: usize,
    height: usize,
    color: png::ColorType,
    pixels: &[u8],
) -> neural_fields::Result<()> {
    let io = |source: std::io::Error| neural_fields::Error::Io {
        path: path.display().to_string(),
        source,
    };
    let png_err = |e: png::EncodingError| io(std::io::Error::other(e.to_string()));
    let file = std::fs::File::create(path).map_err(io)?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), width as u32, height as u32);
    encoder.set_color(color);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()
        .map_err(png_err)?
        .write_image_data(pixels)
        .map_err(png_err)
}
