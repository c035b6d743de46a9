//! STL (stereolithography) reading and writing for [`Mesh`](crate::mesh::Mesh).
//!
//! STL stores a triangle soup: each facet repeats its three corners. The reader welds
//! corners with bit-identical coordinates (`-0.0` and `0.0` are one) into shared
//! vertices, so that a closed part reads as a closed mesh; the facets' stored normals
//! are ignored (they are redundant with the winding and often wrong in exported files).
//!
//! - **Binary**: an 80-byte header, a little-endian `u32` facet count, then 50 bytes per
//!   facet (normal, three corners as `f32`, a `u16` attribute). The file must be exactly
//!   `84 + 50·count` bytes: a count that does not match the file's size is an error
//!   naming both, before anything is allocated, so the work is bounded by the file.
//! - **ASCII**: `solid NAME`, then facets `facet normal nx ny nz` / `outer loop` /
//!   `vertex x y z` … / `endloop` / `endfacet`, and `endsolid`. Several solids in one
//!   file are read as one mesh; loops of more than three corners are triangulated as
//!   polygons. Every line is checked; an unknown keyword is an error naming its line.
//!
//! A file that starts with `solid` is ASCII unless its size is exactly that of a binary
//! file with the count its bytes 80..84 hold (binary headers written by some exporters
//! start with `solid` too).

use super::{check_not_utf16, Polygons};
use crate::error::{Error, Result};
use crate::mesh::vector::{cross, norm, sub};
use std::collections::HashMap;

fn stl_err(expected: impl Into<String>, got: impl Into<String>) -> Error {
    Error::invalid("stl", expected, got)
}

/// Corners welded into vertices, and polygons indexing them.
#[derive(Default)]
pub(crate) struct Soup {
    pub vertices: Vec<[f64; 3]>,
    pub polygons: Polygons,
    /// ASCII: the 1-based line of each facet, for errors.
    pub lines: Option<Vec<usize>>,
    index: HashMap<[u64; 3], u32>,
}

impl Soup {
    /// Where polygon `i` came from, for errors.
    pub(crate) fn locate(&self, i: usize) -> String {
        match &self.lines {
            Some(lines) => format!("facet at line {}", lines.get(i).copied().unwrap_or(0)),
            None => format!("facet {i} (byte {})", 84 + 50 * i),
        }
    }

    fn corner(&mut self, p: [f64; 3]) -> Result<i64> {
        // `+ 0.0` maps -0.0 to 0.0 so that the two weld.
        let key = p.map(|c| (c + 0.0).to_bits());
        if let Some(&i) = self.index.get(&key) {
            return Ok(i64::from(i));
        }
        let i = u32::try_from(self.vertices.len())
            .map_err(|_| stl_err("fewer than 2³² vertices", "more"))?;
        self.vertices.push(p);
        self.index.insert(key, i);
        Ok(i64::from(i))
    }
}

/// Parses STL bytes, ASCII or binary (see the module documentation).
pub(crate) fn read(bytes: &[u8]) -> Result<Soup> {
    let binary_count = bytes
        .get(80..84)
        .map(|b| u64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])));
    let binary_fits = binary_count.is_some_and(|n| 84 + 50 * n == bytes.len() as u64);
    let ascii = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .is_some_and(|i| bytes[i..].starts_with(b"solid"));
    if binary_fits || !ascii {
        read_binary(bytes, binary_count)
    } else {
        read_ascii(bytes)
    }
}

fn read_binary(bytes: &[u8], count: Option<u64>) -> Result<Soup> {
    if bytes.starts_with(&[0xFF, 0xFE]) || bytes.starts_with(&[0xFE, 0xFF]) {
        check_not_utf16("stl", bytes)?;
    }
    let Some(count) = count else {
        return Err(stl_err(
            "an ASCII STL (starting with \"solid\") or a binary STL of at least 84 bytes",
            format!("{} bytes", bytes.len()),
        ));
    };
    let need = 84 + 50 * count;
    if need != bytes.len() as u64 {
        return Err(stl_err(
            "a binary STL of 84 + 50 · (facet count) bytes",
            format!(
                "a header declaring {count} facets ({need} bytes) in a file of {} bytes \
                 (truncated, trailing data or a lying count)",
                bytes.len()
            ),
        ));
    }
    let mut soup = Soup::default();
    for (f, rec) in bytes[84..].chunks_exact(50).enumerate() {
        let mut poly = [0i64; 3];
        for (c, slot) in poly.iter_mut().enumerate() {
            let at = 12 + 12 * c;
            let p: [f64; 3] = std::array::from_fn(|k| {
                let o = at + 4 * k;
                f64::from(f32::from_le_bytes([
                    rec[o],
                    rec[o + 1],
                    rec[o + 2],
                    rec[o + 3],
                ]))
            });
            *slot = soup.corner(p)?;
        }
        soup.polygons
            .push(&poly)
            .map_err(|got| stl_err("facets of three corners", format!("facet {f}: {got}")))?;
    }
    Ok(soup)
}

fn read_ascii(bytes: &[u8]) -> Result<Soup> {
    check_not_utf16("stl", bytes)?;
    let text = std::str::from_utf8(bytes).map_err(|e| {
        stl_err(
            "ASCII text (or a binary STL of 84 + 50 · count bytes)",
            format!("a non-UTF-8 byte at {}", e.valid_up_to()),
        )
    })?;
    let mut soup = Soup::default();
    let mut lines = Vec::new();
    let mut poly: Vec<i64> = Vec::new();
    // Where we are: outside a solid, in a solid, in a facet, in its loop, after the loop.
    #[derive(Clone, Copy, PartialEq, Debug)]
    enum At {
        Outside,
        Solid,
        Facet,
        Loop,
        LoopDone,
    }
    let mut at = At::Outside;
    let mut facet_line = 0;
    for (ln, raw) in text.lines().enumerate() {
        let line_no = ln + 1;
        let mut tok = raw.split_whitespace();
        let Some(kw) = tok.next() else { continue };
        let bad = |expected: &str| {
            stl_err(
                expected.to_string(),
                format!("line {line_no}: {:?}", raw.trim()),
            )
        };
        at = match (at, kw) {
            (At::Outside, "solid") => At::Solid,
            (At::Solid, "endsolid") => At::Outside,
            (At::Solid, "facet") => {
                facet_line = line_no;
                At::Facet
            }
            (At::Facet, "outer") => {
                poly.clear();
                At::Loop
            }
            (At::Loop, "vertex") => {
                let mut p = [0.0; 3];
                for slot in &mut p {
                    *slot = tok
                        .next()
                        .and_then(|t| t.parse::<f64>().ok())
                        .ok_or_else(|| bad("vertex x y z (three numbers)"))?;
                }
                if tok.next().is_some() {
                    return Err(bad("vertex x y z (three numbers)"));
                }
                poly.push(soup.corner(p)?);
                At::Loop
            }
            (At::Loop, "endloop") => At::LoopDone,
            (At::LoopDone, "endfacet") => {
                soup.polygons.push(&poly).map_err(|got| {
                    stl_err(
                        "facets of at least three corners",
                        format!("facet at line {facet_line}: {got}"),
                    )
                })?;
                lines.push(facet_line);
                At::Solid
            }
            (state, _) => {
                let expected = match state {
                    At::Outside => "solid NAME",
                    At::Solid => "facet normal nx ny nz, or endsolid",
                    At::Facet => "outer loop",
                    At::Loop => "vertex x y z, or endloop",
                    At::LoopDone => "endfacet",
                };
                return Err(bad(expected));
            }
        };
    }
    if !matches!(at, At::Outside | At::Solid) {
        return Err(stl_err(
            "complete facets",
            format!("end of file inside the facet at line {facet_line} (truncated)"),
        ));
    }
    soup.lines = Some(lines);
    Ok(soup)
}

/// STL bytes of triangles `faces` over `vertices`, binary (little-endian, an 80-byte
/// header that does not start with `solid`) or ASCII; facet normals are the unit normals
/// of the triangles (zero for degenerate ones).
pub(crate) fn write(vertices: &[[f64; 3]], faces: &[[u32; 3]], binary: bool) -> Vec<u8> {
    let normal = |f: &[u32; 3]| {
        let [a, b, c] = f.map(|i| vertices[i as usize]);
        let n = cross(sub(b, a), sub(c, a));
        let l = norm(n);
        if l > 0.0 {
            n.map(|x| x / l)
        } else {
            [0.0; 3]
        }
    };
    if binary {
        let mut out = Vec::with_capacity(84 + 50 * faces.len());
        out.extend_from_slice(b"binary STL written by neural-fields");
        out.resize(80, b' ');
        // Meshes with 2³² or more faces do not fit in memory as `Vec<[u32; 3]>` anyway.
        out.extend_from_slice(&(faces.len() as u32).to_le_bytes());
        for f in faces {
            let corners = f.map(|i| vertices[i as usize]);
            for p in std::iter::once(normal(f)).chain(corners) {
                for c in p {
                    out.extend_from_slice(&(c as f32).to_le_bytes());
                }
            }
            out.extend_from_slice(&[0, 0]);
        }
        out
    } else {
        let mut s = String::from("solid neural-fields\n");
        for f in faces {
            let n = normal(f);
            s.push_str(&format!(
                "  facet normal {} {} {}\n    outer loop\n",
                n[0], n[1], n[2]
            ));
            for i in f {
                let p = vertices[*i as usize];
                s.push_str(&format!("      vertex {} {} {}\n", p[0], p[1], p[2]));
            }
            s.push_str("    endloop\n  endfacet\n");
        }
        s.push_str("endsolid neural-fields\n");
        s.into_bytes()
    }
}
