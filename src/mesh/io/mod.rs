//! Mesh and point-cloud files: [`MeshFormat`], one reader and writer per format (PLY,
//! OBJ, STL, OFF), and what they share: [`Polygons`] (the faces as files store them,
//! before triangulation), the UTF-16 check of the text formats, the 32-bit float range
//! check of the binary ones, and file reading and writing with errors naming the path.
//!
//! The readers and writers exchange plain data (vertices, optional normals and colours,
//! polygons); [`Mesh`](super::Mesh) and [`PointCloud`](super::PointCloud) build on them.
//! Every reader's work and memory are bounded by the file's size, whatever its header
//! claims.

pub(super) mod obj;
pub(super) mod off;
pub(super) mod ply;
pub(super) mod stl;

use crate::error::{Error, Result};
use std::path::Path;

/// A mesh file format, for [`Mesh::to_bytes`](super::Mesh::to_bytes) and
/// [`Mesh::from_bytes`](super::Mesh::from_bytes) (and their point-cloud twins).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshFormat {
    /// PLY, written as `format ascii 1.0`. Reading accepts every PLY encoding (the
    /// header names it), whichever PLY variant is passed.
    PlyAscii,
    /// PLY, written as `format binary_little_endian 1.0`. Reading accepts every PLY
    /// encoding.
    PlyBinary,
    /// Wavefront OBJ (ASCII).
    Obj,
    /// STL, written as ASCII (`solid` … `endsolid`). Reading accepts both STL
    /// encodings, whichever STL variant is passed.
    StlAscii,
    /// STL, written as binary (80-byte header, facet count, 50 bytes per facet).
    /// Reading accepts both STL encodings.
    StlBinary,
    /// OFF (ASCII; `COFF` when the mesh has colours), as ModelNet and many ShapeNet
    /// conversions store meshes.
    Off,
}

impl MeshFormat {
    /// The format of a file by its extension, case-insensitive: `.ply` → `PlyBinary`,
    /// `.obj` → `Obj`, `.stl` → `StlBinary`, `.off` → `Off` (for reading, each variant
    /// reads every encoding of its format).
    ///
    /// # Errors
    /// Another extension, naming `path`.
    pub(crate) fn from_path(path: &Path) -> Result<Self> {
        let extension = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        match extension.as_str() {
            "ply" => Ok(Self::PlyBinary),
            "obj" => Ok(Self::Obj),
            "stl" => Ok(Self::StlBinary),
            "off" => Ok(Self::Off),
            other => Err(Error::invalid(
                "path",
                "a .ply, .obj, .stl or .off file",
                format!("{} (extension {other:?})", path.display()),
            )),
        }
    }
}

/// Polygons as one flat list of vertex indices and the index where each polygon ends.
#[derive(Debug, Default, Clone, PartialEq)]
pub(crate) struct Polygons {
    pub indices: Vec<u32>,
    pub ends: Vec<usize>,
}

impl Polygons {
    /// Appends a polygon, refusing fewer than three vertices and indices that are
    /// negative or beyond `u32`.
    pub(crate) fn push(&mut self, poly: &[i64]) -> std::result::Result<(), String> {
        if poly.len() < 3 {
            return Err(format!("{} vertices", poly.len()));
        }
        if let Some(&b) = poly.iter().find(|&&k| k < 0 || k > i64::from(u32::MAX)) {
            return Err(format!("index {b}"));
        }
        // The check above keeps every index in u32's range.
        self.indices.extend(poly.iter().map(|&k| k as u32));
        self.ends.push(self.indices.len());
        Ok(())
    }

    /// The number of polygons.
    pub(crate) fn len(&self) -> usize {
        self.ends.len()
    }

    /// The polygons in order.
    pub(crate) fn iter(&self) -> impl Iterator<Item = &[u32]> {
        let starts = std::iter::once(0).chain(self.ends.iter().copied());
        starts
            .zip(self.ends.iter().copied())
            .map(move |(a, b)| &self.indices[a..b])
    }
}

/// Refuses UTF-16 text (a byte-order mark, or NUL bytes among the first kilobyte, which
/// ASCII and UTF-8 text never holds), naming the encoding: read lossily as UTF-8 it
/// would parse as an empty mesh.
pub(crate) fn check_not_utf16(what: &'static str, bytes: &[u8]) -> Result<()> {
    let bom = bytes.starts_with(&[0xFF, 0xFE]) || bytes.starts_with(&[0xFE, 0xFF]);
    if bom || bytes.iter().take(1024).any(|&b| b == 0) {
        return Err(Error::invalid(
            what,
            "ASCII or UTF-8 text",
            "UTF-16 (or other NUL-bearing) text: convert the file to UTF-8",
        ));
    }
    Ok(())
}

/// Refuses coordinates that a 32-bit float cannot hold (PLY and binary STL store
/// `float`): written as they are, they would become infinities in the file.
pub(crate) fn check_f32_range(arg: &'static str, what: &str, v: &[[f64; 3]]) -> Result<()> {
    let max = f64::from(f32::MAX);
    if let Some(i) = v.iter().position(|p| p.iter().any(|c| c.abs() > max)) {
        return Err(Error::invalid(
            arg,
            format!("{what} within ±3.4e38, as the file's 32-bit floats hold"),
            format!("{what} {i} = {:?}", v[i]),
        ));
    }
    Ok(())
}

/// A colour component in `[0, 1]` as an 8-bit value (PLY's `uchar`, OFF's integers):
/// `round(c · 255)`, clamped to `0..=255`.
pub(crate) fn color_to_u8(c: f64) -> u8 {
    // The clamp keeps the value in 0..=255, so the cast neither wraps nor saturates.
    (c * 255.0).round().clamp(0.0, 255.0) as u8
}

/// The bytes of the file at `path` (an error naming the path).
pub(crate) fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Writes `bytes` to `path` (an error naming the path).
pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })
}

/// A reader's error as an error about the file at `path`: [`Error::Format`] naming the
/// file and the format or argument the reader named.
pub(crate) fn in_file(e: Error, path: &Path) -> Error {
    match e {
        Error::InvalidArgument { arg, expected, got } => Error::format(path, arg, expected, got),
        other => other,
    }
}
