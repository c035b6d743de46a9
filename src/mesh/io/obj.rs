//! Wavefront OBJ reading and writing.
//!
//! The reader takes `v` (extra components such as `w` or colours ignored), `vn`, and `f`
//! with `a`, `a/b`, `a//c` or `a/b/c` references, 1-based or negative (relative), and
//! ignores the other statements (`vt`, `o`, `g`, `usemtl`, `mtllib`, `s`, `l`, `p`).
//! Invalid UTF-8 is replaced; UTF-16 text is refused with an error naming the encoding.
//! The writer emits `v x y z`, `vn` lines when normals are given, and 1-based `f a b c`
//! (or `f a//a b//b c//c` with normals).

use super::{check_not_utf16, Polygons};
use crate::error::{Error, Result};

fn obj_err(expected: impl Into<String>, got: impl Into<String>) -> Error {
    Error::invalid("obj", expected, got)
}

/// What an OBJ file holds: vertices, normals (kept only when every face corner names
/// the normal with its vertex's index and there is one per vertex), polygons and the
/// line of each.
pub(crate) struct ObjContent {
    pub vertices: Vec<[f64; 3]>,
    /// The `vn` statements.
    pub vn: Vec<[f64; 3]>,
    /// Every face corner named the normal with its vertex's index.
    pub normals_match: bool,
    pub polygons: Polygons,
    pub lines: Vec<usize>,
}

impl ObjContent {
    /// The normals of a mesh: one per vertex, and every face corner named the normal
    /// with its vertex's index (as [`write`] writes them).
    pub(crate) fn normals_by_reference(&self) -> Option<Vec<[f64; 3]>> {
        if self.normals_match {
            self.normals_by_count()
        } else {
            None
        }
    }

    /// The normals of a point cloud: one `vn` per `v`.
    pub(crate) fn normals_by_count(&self) -> Option<Vec<[f64; 3]>> {
        (!self.vn.is_empty() && self.vn.len() == self.vertices.len()).then(|| self.vn.clone())
    }
}

/// Parses OBJ bytes (see [`Mesh::from_bytes`](crate::mesh::Mesh::from_bytes)).
pub(crate) fn read(bytes: &[u8]) -> Result<ObjContent> {
    check_not_utf16("obj", bytes)?;
    let text = String::from_utf8_lossy(bytes);
    let mut vertices: Vec<[f64; 3]> = Vec::new();
    let mut polygons = Polygons::default();
    let mut lines = Vec::new();
    let mut poly = Vec::new();
    let mut vn: Vec<[f64; 3]> = Vec::new();
    let mut normals_match = true;
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    for (ln, raw) in text.lines().enumerate() {
        let line_no = ln + 1;
        let line = raw.split('#').next().unwrap_or("").trim();
        let mut tok = line.split_whitespace();
        let Some(kw) = tok.next() else { continue };
        match kw {
            "v" | "vn" => {
                let mut c = [0.0; 3];
                for slot in &mut c {
                    let t = tok.next().ok_or_else(|| {
                        obj_err("three coordinates", format!("line {line_no}: {line:?}"))
                    })?;
                    *slot = t
                        .parse::<f64>()
                        .map_err(|_| obj_err("a number", format!("line {line_no}: {t:?}")))?;
                }
                if kw == "v" {
                    vertices.push(c);
                } else {
                    vn.push(c);
                }
            }
            "f" => {
                poly.clear();
                for t in tok {
                    let mut parts = t.split('/');
                    let vi = resolve_obj_index(parts.next().unwrap_or(""), vertices.len())
                        .map_err(|e| {
                            obj_err(
                                "a face vertex reference",
                                format!("line {line_no}: {t:?} ({e})"),
                            )
                        })?;
                    let _tex = parts.next();
                    match parts.next() {
                        Some(n) if !n.is_empty() => {
                            let ni = resolve_obj_index(n, vn.len()).map_err(|e| {
                                obj_err(
                                    "a face normal reference",
                                    format!("line {line_no}: {t:?} ({e})"),
                                )
                            })?;
                            if ni != vi {
                                normals_match = false;
                            }
                        }
                        _ => normals_match = false,
                    }
                    poly.push(vi);
                }
                polygons.push(&poly).map_err(|got| {
                    obj_err(
                        "faces of at least 3 vertices with indices in 1 to 2³²",
                        format!("line {line_no}: {got}"),
                    )
                })?;
                lines.push(line_no);
            }
            _ => {}
        }
    }
    Ok(ObjContent {
        vertices,
        vn,
        normals_match,
        polygons,
        lines,
    })
}

/// OBJ text of `vertices`, optional per-vertex `normals` and triangles `faces` (see the
/// module documentation). The caller validates the lengths.
pub(crate) fn write(
    vertices: &[[f64; 3]],
    normals: Option<&[[f64; 3]]>,
    faces: &[[u32; 3]],
) -> Vec<u8> {
    let mut s = String::from("# neural-fields\n");
    for v in vertices {
        s.push_str(&format!("v {} {} {}\n", v[0], v[1], v[2]));
    }
    if let Some(ns) = normals {
        for n in ns {
            s.push_str(&format!("vn {} {} {}\n", n[0], n[1], n[2]));
        }
    }
    for f in faces {
        let (a, b, c) = (f[0] + 1, f[1] + 1, f[2] + 1);
        if normals.is_some() {
            s.push_str(&format!("f {a}//{a} {b}//{b} {c}//{c}\n"));
        } else {
            s.push_str(&format!("f {a} {b} {c}\n"));
        }
    }
    s.into_bytes()
}

/// 1-based (or negative, relative) OBJ index → 0-based.
fn resolve_obj_index(t: &str, count: usize) -> std::result::Result<i64, String> {
    let i: i64 = t.parse().map_err(|_| format!("{t:?} is not an integer"))?;
    let z = if i > 0 {
        i - 1
    } else if i < 0 {
        count as i64 + i
    } else {
        return Err("index 0 (OBJ indices start at 1)".into());
    };
    if z < 0 {
        return Err(format!("relative index {i} before the first element"));
    }
    Ok(z)
}
