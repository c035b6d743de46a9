//! Hand-written dataset folders for the data tests: scratch directories, PNGs, JSON and
//! npz files with the key names and value ranges of the published datasets.

use std::io::Write;
use std::path::{Path, PathBuf};

/// An empty scratch directory unique to this process and `name`.
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir()
        .join("neural-fields-tests")
        .join(format!("{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A deterministic `w × h` image with `channels` bytes per pixel, distinct per `seed`.
pub fn pattern(w: usize, h: usize, channels: usize, seed: u8) -> Vec<u8> {
    (0..w * h * channels)
        .map(|i| ((i * 37 + usize::from(seed) * 101) % 251) as u8)
        .collect()
}

/// Writes a PNG (1, 3 or 4 channels) with the `image` crate, creating parent folders.
pub fn png(path: &Path, w: usize, h: usize, channels: usize, data: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let color = match channels {
        1 => image::ExtendedColorType::L8,
        3 => image::ExtendedColorType::Rgb8,
        _ => image::ExtendedColorType::Rgba8,
    };
    image::save_buffer(path, data, w as u32, h as u32, color).unwrap();
}

/// A `.npy` (version 1.0) of a row-major f64 array.
pub fn npy(shape: &[usize], data: &[f64]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for x in data {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

/// Writes an npz (stored members, as `np.savez`) of `(name, bytes)` members.
pub fn npz(path: &Path, members: &[(String, Vec<u8>)]) {
    let file = std::fs::File::create(path).unwrap();
    let mut zip = zip::ZipWriter::new(file);
    let options =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (name, bytes) in members {
        zip.start_file(format!("{name}.npy"), options).unwrap();
        zip.write_all(bytes).unwrap();
    }
    zip.finish().unwrap();
}

/// A 4×4 matrix's rows flattened.
pub fn flat(rows: &[[f64; 4]; 4]) -> Vec<f64> {
    rows.iter().flatten().copied().collect()
}

/// The bytes of pixel `(u, v)` (column, row) of `image`, from its row-major bytes.
pub fn pixel(image: &neural_fields::data::Image, u: usize, v: usize) -> &[u8] {
    let (w, h, c) = image.size();
    assert!(u < w && v < h, "pixel ({u}, {v}) outside {w} × {h}");
    let i = (v * w + u) * c;
    &image.data()[i..i + c]
}

/// Whether `view` has a mask: a mask file, or an alpha channel (`View::mask` is `Some`).
pub fn has_mask(view: &neural_fields::data::View) -> bool {
    view.mask(&candle_core::Device::Cpu, candle_core::DType::F32)
        .unwrap()
        .is_some()
}

/// The layout that `load` detects in `dir`: the only layout that, named in
/// `LoadConfig::layout`, loads the same training views as detection does.
pub fn detected_layout(dir: &Path) -> neural_fields::data::DatasetLayout {
    use neural_fields::data::{load, DatasetLayout, LoadConfig};
    let names = |layout: Option<DatasetLayout>| {
        let config = LoadConfig {
            layout,
            ..LoadConfig::default()
        };
        load(dir, &config).map(|d| {
            d.views()
                .iter()
                .map(|v| v.name().to_string())
                .collect::<Vec<_>>()
        })
    };
    let detected = names(None).unwrap();
    let same: Vec<DatasetLayout> = [
        DatasetLayout::Blender,
        DatasetLayout::Nerfstudio,
        DatasetLayout::Dtu,
    ]
    .into_iter()
    .filter(|&l| names(Some(l)).is_ok_and(|n| n == detected))
    .collect();
    assert_eq!(same.len(), 1, "layouts loading as detection does: {same:?}");
    same[0]
}
