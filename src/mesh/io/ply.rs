//! PLY (Stanford polygon file format) reading and writing, shared by [`Mesh`] and
//! [`PointCloud`].
//!
//! The reader accepts ASCII and binary (little- and big-endian) files with any elements
//! and properties; it keeps `vertex` positions, normals (`nx ny nz`) and colours
//! (`red green blue`), and the `vertex_indices`/`vertex_index` lists of `face`. Its work
//! and memory are bounded by the file's size whatever the header claims:
//!
//! - every element's row count is checked against the bytes that remain before any row
//!   is read (binary: the row's smallest size; ASCII: two bytes, a value and a newline);
//! - property-less elements hold nothing and are skipped without iterating their count;
//! - every list item takes at least one byte of the file, so the polygon indices kept
//!   take at most 4 bytes of memory per byte of file, and their triangles at most 12
//!   (each triangle consumes one index of its polygon);
//! - data after the declared rows is an error, so a header that declares fewer rows than
//!   the file holds (a lying count) is not read as a smaller mesh.
//!
//! [`Mesh`]: crate::mesh::Mesh
//! [`PointCloud`]: crate::mesh::PointCloud

use super::{check_not_utf16, color_to_u8, Polygons};
use crate::error::{Error, Result};

fn file_err(expected: impl Into<String>, got: impl Into<String>) -> Error {
    Error::invalid("ply", expected, got)
}

/// What a PLY file holds, as [`Mesh`](crate::mesh::Mesh) and
/// [`PointCloud`](crate::mesh::PointCloud) read it.
#[derive(Debug, Default)]
pub(crate) struct PlyContent {
    pub vertices: Vec<[f64; 3]>,
    /// Present when every vertex has `nx ny nz`.
    pub normals: Option<Vec<[f64; 3]>>,
    /// Present when every vertex has `red green blue`, scaled to `[0, 1]`.
    pub colors: Option<Vec<[f64; 3]>>,
    /// The faces' vertex indices, polygon after polygon.
    pub polygons: Polygons,
}

/// Parses PLY bytes (see the module documentation).
pub(crate) fn read(bytes: &[u8]) -> Result<PlyContent> {
    let header = parse_ply_header(bytes)?;
    let mut out = PlyContent::default();
    let mut normals = Vec::new();
    let mut colors = Vec::new();
    let mut src = PlySource::new(bytes, &header);
    for el in &header.elements {
        let is_vertex = el.name == "vertex";
        let is_face = el.name == "face";
        let idx = |n: &str| el.props.iter().position(|p| p.name == n);
        let (xi, yi, zi) = (idx("x"), idx("y"), idx("z"));
        let (nxi, nyi, nzi) = (idx("nx"), idx("ny"), idx("nz"));
        // Colours only when all three channels are scalar properties.
        let scalar = |n: &str| idx(n).filter(|&i| el.props[i].list.is_none());
        // `diffuse_red` … is what some scanners and old exporters write.
        let channel = |n: &str| scalar(n).or_else(|| scalar(&format!("diffuse_{n}")));
        let rgb = match (channel("red"), channel("green"), channel("blue")) {
            (Some(r), Some(g), Some(b)) => Some([r, g, b]),
            _ => None,
        };
        let xyz = match (xi, yi, zi) {
            (Some(x), Some(y), Some(z)) => Some((x, y, z)),
            _ if is_vertex => {
                return Err(file_err(
                    "vertex properties x, y and z",
                    format!("header line {}: missing", el.line),
                ))
            }
            _ => None,
        };
        let fi = el.props.iter().position(|p| {
            p.list.is_some() && (p.name == "vertex_indices" || p.name == "vertex_index")
        });
        if is_face && fi.is_none() {
            return Err(file_err(
                "a face list property vertex_indices or vertex_index",
                format!("header line {}: none", el.line),
            ));
        }
        if el.props.is_empty() {
            // A property-less element holds no values in any encoding: there is nothing
            // to read, whatever its count (iterating a count such as 2⁶⁴ − 1 would never
            // end).
            continue;
        }
        src.check_room(el)?;
        let mut scalars = vec![0.0f64; el.props.len()];
        let mut list: Vec<i64> = Vec::new();
        for row in 0..el.count {
            let complete = |e: Error| match e {
                Error::InvalidArgument { arg, expected, got } => Error::InvalidArgument {
                    arg,
                    expected,
                    got: format!("{got}; {row} of {} {} rows complete", el.count, el.name),
                },
                other => other,
            };
            src.begin_row().map_err(complete)?;
            let row_start = src.pos;
            list.clear();
            for (pi, p) in el.props.iter().enumerate() {
                match p.list {
                    Some(count_ty) => {
                        let n = src.read(count_ty).map_err(complete)?;
                        if !(0.0..=1e7).contains(&n) || n.fract() != 0.0 {
                            return Err(file_err(
                                "a list count between 0 and 10⁷",
                                format!("{} {}: count {n}", src.position(), el.name),
                            ));
                        }
                        let keep = is_face && Some(pi) == fi;
                        for _ in 0..n as usize {
                            let v = src.read(p.ty).map_err(complete)?;
                            if keep {
                                list.push(v as i64);
                            }
                        }
                    }
                    None => scalars[pi] = src.read(p.ty).map_err(complete)?,
                }
            }
            src.end_row()?;
            if let (true, Some((x, y, z))) = (is_vertex, xyz) {
                out.vertices.push([scalars[x], scalars[y], scalars[z]]);
                if let (Some(a), Some(b), Some(c)) = (nxi, nyi, nzi) {
                    normals.push([scalars[a], scalars[b], scalars[c]]);
                }
                if let Some(ch) = rgb {
                    let c = ch.map(|k| scalars[k] / el.props[k].ty.color_scale());
                    if !c.iter().all(|x| (0.0..=1.0).contains(x)) {
                        let raw = ch.map(|k| scalars[k]);
                        return Err(Error::invalid(
                            "colors",
                            "vertex colors (red, green, blue) in [0, 1] once scaled \
                             (integers by their type's largest value, floats as they are)",
                            format!(
                                "ply {}: vertex {row}: red, green, blue = {raw:?} → colors {c:?}",
                                src.row_position(row_start)
                            ),
                        ));
                    }
                    colors.push(c);
                }
            } else if is_face {
                out.polygons.push(&list).map_err(|got| {
                    file_err(
                        "faces of at least 3 vertices with indices in 0 to 2³² − 1",
                        format!("face {row}: {got}"),
                    )
                })?;
            }
        }
    }
    src.finish()?;
    if !normals.is_empty() {
        out.normals = Some(normals);
    }
    if !colors.is_empty() {
        out.colors = Some(colors);
    }
    Ok(out)
}

/// PLY bytes: `element vertex` with `float x, y, z` (and `nx, ny, nz` when normals are
/// given), then `uchar red, green, blue` when colours are given (each
/// `round(c · 255)`), and `element face` with `list uchar int vertex_indices` when
/// `faces` is given. ASCII or binary little-endian. The caller validates the lengths.
pub(crate) fn write(
    vertices: &[[f64; 3]],
    normals: Option<&[[f64; 3]]>,
    colors: Option<&[[f64; 3]]>,
    faces: Option<&[[u32; 3]]>,
    binary: bool,
) -> Vec<u8> {
    let fmt = if binary {
        "binary_little_endian"
    } else {
        "ascii"
    };
    let mut header = format!(
        "ply\nformat {fmt} 1.0\ncomment neural-fields\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n",
        vertices.len()
    );
    if normals.is_some() {
        header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if colors.is_some() {
        header.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    if let Some(f) = faces {
        header.push_str(&format!(
            "element face {}\nproperty list uchar int vertex_indices\n",
            f.len()
        ));
    }
    header.push_str("end_header\n");
    let mut out = header.into_bytes();
    // Coordinates are written as 32-bit floats, the convention every tool reads.
    for (i, v) in vertices.iter().enumerate() {
        let mut row: Vec<f32> = v.iter().map(|&c| c as f32).collect();
        if let Some(n) = normals {
            row.extend(n[i].iter().map(|&c| c as f32));
        }
        let rgb = colors.map(|c| c[i].map(color_to_u8));
        if binary {
            for c in row {
                out.extend_from_slice(&c.to_le_bytes());
            }
            if let Some(rgb) = rgb {
                out.extend_from_slice(&rgb);
            }
        } else {
            let mut line: Vec<String> = row.iter().map(f32::to_string).collect();
            if let Some(rgb) = rgb {
                line.extend(rgb.iter().map(u8::to_string));
            }
            out.extend_from_slice(line.join(" ").as_bytes());
            out.push(b'\n');
        }
    }
    for f in faces.unwrap_or(&[]) {
        if binary {
            out.push(3);
            for &k in f {
                // Validated meshes index fewer than 2³¹ vertices (they hold them in memory).
                out.extend_from_slice(&(k as i32).to_le_bytes());
            }
        } else {
            out.extend_from_slice(format!("3 {} {} {}\n", f[0], f[1], f[2]).as_bytes());
        }
    }
    out
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PlyTy {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl PlyTy {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }
    /// The divisor that maps a colour stored in this type to `[0, 1]`: the type's largest
    /// value for integers, `1` for floats (already in `[0, 1]`).
    fn color_scale(self) -> f64 {
        match self {
            Self::I8 => f64::from(i8::MAX),
            Self::U8 => f64::from(u8::MAX),
            Self::I16 => f64::from(i16::MAX),
            Self::U16 => f64::from(u16::MAX),
            Self::I32 => f64::from(i32::MAX),
            Self::U32 => f64::from(u32::MAX),
            Self::F32 | Self::F64 => 1.0,
        }
    }
    /// Whether a value read from ASCII text fits this type, as the binary encodings'
    /// values do by construction: integers whole and in range, `float` within ±3.4e38
    /// (non-finite values pass here and are refused where coordinates are checked).
    fn holds(self, v: f64) -> bool {
        let int = |lo: f64, hi: f64| v.fract() == 0.0 && (lo..=hi).contains(&v);
        match self {
            Self::I8 => int(i8::MIN.into(), i8::MAX.into()),
            Self::U8 => int(0.0, u8::MAX.into()),
            Self::I16 => int(i16::MIN.into(), i16::MAX.into()),
            Self::U16 => int(0.0, u16::MAX.into()),
            Self::I32 => int(i32::MIN.into(), i32::MAX.into()),
            Self::U32 => int(0.0, u32::MAX.into()),
            Self::F32 => !v.is_finite() || v.abs() <= f64::from(f32::MAX),
            Self::F64 => true,
        }
    }
    /// The type's name as PLY headers spell it.
    fn name(self) -> &'static str {
        match self {
            Self::I8 => "char",
            Self::U8 => "uchar",
            Self::I16 => "short",
            Self::U16 => "ushort",
            Self::I32 => "int",
            Self::U32 => "uint",
            Self::F32 => "float",
            Self::F64 => "double",
        }
    }
    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
}

#[derive(Debug)]
struct PlyProp {
    name: String,
    ty: PlyTy,
    /// `Some(count type)` for a list property (then `ty` is the item type).
    list: Option<PlyTy>,
}

#[derive(Debug)]
struct PlyElement {
    name: String,
    count: usize,
    props: Vec<PlyProp>,
    line: usize,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PlyEncoding {
    Ascii,
    Le,
    Be,
}

struct PlyHeader {
    encoding: PlyEncoding,
    elements: Vec<PlyElement>,
    /// Byte offset of the body.
    body: usize,
    /// Line number (1-based) of the first body line.
    body_line: usize,
}

fn parse_ply_header(bytes: &[u8]) -> Result<PlyHeader> {
    let mut pos = 0usize;
    let mut line_no = 0usize;
    let mut encoding = None;
    let mut elements: Vec<PlyElement> = Vec::new();
    loop {
        let Some(rel) = bytes[pos..].iter().position(|&b| b == b'\n') else {
            return Err(file_err(
                "a header ending in end_header",
                format!("end of file at header line {}", line_no + 1),
            ));
        };
        let line = String::from_utf8_lossy(&bytes[pos..pos + rel])
            .trim()
            .to_string();
        pos += rel + 1;
        line_no += 1;
        let toks: Vec<&str> = line.split_whitespace().collect();
        if line_no == 1 {
            if line != "ply" {
                check_not_utf16("ply", bytes)?;
                return Err(file_err(
                    "a file starting with \"ply\"",
                    format!("line 1: {line:?}"),
                ));
            }
            continue;
        }
        let bad =
            |what: &str| file_err(what.to_string(), format!("header line {line_no}: {line:?}"));
        match toks.first().copied() {
            Some("format") => {
                encoding = Some(match toks.get(1).copied() {
                    Some("ascii") => PlyEncoding::Ascii,
                    Some("binary_little_endian") => PlyEncoding::Le,
                    Some("binary_big_endian") => PlyEncoding::Be,
                    _ => {
                        return Err(bad(
                            "format ascii, binary_little_endian or binary_big_endian",
                        ))
                    }
                });
            }
            Some("element") => {
                let (Some(name), Some(count)) =
                    (toks.get(1), toks.get(2).and_then(|c| c.parse().ok()))
                else {
                    return Err(bad("element NAME COUNT"));
                };
                elements.push(PlyElement {
                    name: (*name).to_string(),
                    count,
                    props: Vec::new(),
                    line: line_no,
                });
            }
            Some("property") => {
                let Some(el) = elements.last_mut() else {
                    return Err(bad("a property after an element"));
                };
                let prop = if toks.get(1) == Some(&"list") {
                    match (
                        toks.get(2).and_then(|t| PlyTy::parse(t)),
                        toks.get(3).and_then(|t| PlyTy::parse(t)),
                        toks.get(4),
                    ) {
                        (Some(c), Some(t), Some(n)) => PlyProp {
                            name: (*n).to_string(),
                            ty: t,
                            list: Some(c),
                        },
                        _ => return Err(bad("property list COUNT_TYPE ITEM_TYPE NAME")),
                    }
                } else {
                    match (toks.get(1).and_then(|t| PlyTy::parse(t)), toks.get(2)) {
                        (Some(t), Some(n)) => PlyProp {
                            name: (*n).to_string(),
                            ty: t,
                            list: None,
                        },
                        _ => return Err(bad("property TYPE NAME")),
                    }
                };
                el.props.push(prop);
            }
            Some("end_header") => break,
            // comment, obj_info, and stray text some exporters leave (Blender 2.47
            // writes a bare line after `comment`): ignored.
            _ => {}
        }
    }
    let Some(encoding) = encoding else {
        return Err(file_err("a format line in the header", "none"));
    };
    Ok(PlyHeader {
        encoding,
        elements,
        body: pos,
        body_line: line_no + 1,
    })
}

/// A cursor over a PLY body that reports positions as lines (ASCII) or byte offsets.
struct PlySource<'a> {
    bytes: &'a [u8],
    enc: PlyEncoding,
    pos: usize,
    line: usize,
    tokens: Vec<&'a str>,
    tok: usize,
}

impl<'a> PlySource<'a> {
    fn new(bytes: &'a [u8], h: &PlyHeader) -> Self {
        Self {
            bytes,
            enc: h.encoding,
            pos: h.body,
            line: h.body_line - 1,
            tokens: Vec::new(),
            tok: 0,
        }
    }

    fn position(&self) -> String {
        match self.enc {
            PlyEncoding::Ascii => format!("line {}", self.line),
            _ => format!("byte {}", self.pos),
        }
    }

    /// The position of the row that began at byte `row_start` (binary) or on the current
    /// line (ASCII).
    fn row_position(&self, row_start: usize) -> String {
        match self.enc {
            PlyEncoding::Ascii => format!("line {}", self.line),
            _ => format!("byte {row_start}"),
        }
    }

    fn begin_row(&mut self) -> Result<()> {
        if self.enc != PlyEncoding::Ascii {
            return Ok(());
        }
        loop {
            if self.pos >= self.bytes.len() {
                return Err(file_err(
                    "as many rows as the header declares",
                    format!("end of file at line {} (truncated)", self.line + 1),
                ));
            }
            let rel = self.bytes[self.pos..]
                .iter()
                .position(|&b| b == b'\n')
                .unwrap_or(self.bytes.len() - self.pos);
            let s = std::str::from_utf8(&self.bytes[self.pos..self.pos + rel])
                .map_err(|_| file_err("UTF-8 text", format!("line {}", self.line + 1)))?;
            self.pos += rel + 1;
            self.line += 1;
            self.tokens = s.split_whitespace().collect();
            self.tok = 0;
            if !self.tokens.is_empty() {
                return Ok(());
            }
        }
    }

    /// ASCII: the row must use every value on its line (one row per line).
    fn end_row(&mut self) -> Result<()> {
        if self.enc == PlyEncoding::Ascii && self.tok < self.tokens.len() {
            return Err(file_err(
                "one row per line, with as many values as the element has properties",
                format!(
                    "line {}: {} values where the row takes {}",
                    self.line,
                    self.tokens.len(),
                    self.tok
                ),
            ));
        }
        Ok(())
    }

    /// Checks, before any row is read, that the bytes left can hold `el.count` rows of
    /// the element's smallest size (binary: its scalars and list counts; ASCII: one
    /// character and a newline), so that the work of the loop is bounded by the file's
    /// size, not by a number in its header.
    fn check_room(&self, el: &PlyElement) -> Result<()> {
        let min_row = match self.enc {
            PlyEncoding::Ascii => 2,
            _ => el
                .props
                .iter()
                .map(|p| p.list.unwrap_or(p.ty).size())
                .sum::<usize>(),
        };
        let left = self.bytes.len().saturating_sub(self.pos);
        // The last ASCII row needs no newline.
        let slack = usize::from(self.enc == PlyEncoding::Ascii);
        let room = (left + slack) / min_row.max(1);
        if el.count > room {
            return Err(file_err(
                "element counts that the rest of the file can hold",
                format!(
                    "header line {}: element {} declares {} rows of at least {min_row} bytes, \
                     but {left} bytes remain, room for at most {room} complete rows \
                     (truncated or a lying header)",
                    el.line, el.name, el.count
                ),
            ));
        }
        Ok(())
    }

    fn read(&mut self, ty: PlyTy) -> Result<f64> {
        match self.enc {
            PlyEncoding::Ascii => {
                let Some(t) = self.tokens.get(self.tok) else {
                    return Err(file_err(
                        "as many values on the line as the element has properties",
                        format!("line {}: only {} values", self.line, self.tokens.len()),
                    ));
                };
                self.tok += 1;
                let v = t
                    .parse::<f64>()
                    .map_err(|_| file_err("a number", format!("line {}: {t:?}", self.line)))?;
                if !ty.holds(v) {
                    return Err(file_err(
                        format!("a value that the declared type {} holds", ty.name()),
                        format!("line {}: {t:?}", self.line),
                    ));
                }
                Ok(v)
            }
            enc => {
                let n = ty.size();
                if self.pos + n > self.bytes.len() {
                    return Err(file_err(
                        "as many bytes as the header declares",
                        format!("end of file at byte {} (truncated)", self.bytes.len()),
                    ));
                }
                let mut b = [0u8; 8];
                b[..n].copy_from_slice(&self.bytes[self.pos..self.pos + n]);
                if enc == PlyEncoding::Be {
                    b[..n].reverse();
                }
                self.pos += n;
                Ok(match ty {
                    PlyTy::I8 => f64::from(b[0] as i8),
                    PlyTy::U8 => f64::from(b[0]),
                    PlyTy::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
                    PlyTy::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
                    PlyTy::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    PlyTy::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    PlyTy::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    PlyTy::F64 => f64::from_le_bytes(b),
                })
            }
        }
    }

    /// Refuses data after the declared rows (ASCII: anything but whitespace), so that a
    /// header declaring fewer rows than the file holds is an error, not a smaller mesh.
    fn finish(&self) -> Result<()> {
        let rest = self.bytes.get(self.pos..).unwrap_or(&[]);
        let trailing = match self.enc {
            PlyEncoding::Ascii => rest.iter().any(|b| !b.is_ascii_whitespace()),
            _ => !rest.is_empty(),
        };
        if trailing {
            let at = match self.enc {
                PlyEncoding::Ascii => format!("line {}", self.line + 1),
                _ => format!("byte {}", self.pos),
            };
            return Err(file_err(
                "no data after the rows the header declares",
                format!(
                    "{} bytes of trailing data from {at} (a header that declares fewer rows \
                     than the file holds?)",
                    rest.len()
                ),
            ));
        }
        Ok(())
    }
}
