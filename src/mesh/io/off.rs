//! OFF (Object File Format, the format of ModelNet and of many ShapeNet conversions)
//! reading and writing.
//!
//! The reader takes the ASCII variants `OFF`, `COFF` (vertex colours), `NOFF` (vertex
//! normals) and `CNOFF`/`NCOFF`: a keyword line, a line `V F [E]` (the edge count is
//! optional and ignored), `V` vertex lines `x y z [nx ny nz] [r g b [a]]`, then `F` face
//! lines `k i₁ … i_k [colour]`. ModelNet's files that run the keyword into the counts
//! (`OFF490 518 0`) are read too. `#` starts a comment; blank lines are skipped.
//! Colours are integers in `0..=255` (divided by 255) or, when written with a decimal
//! point, values in `[0, 1]`. Binary OFF (`OFF BINARY`) and the `ST`/`4`/`n` variants
//! are refused by name.
//!
//! The counts are checked against the file's size before anything is allocated (a
//! vertex line holds at least 6 bytes, a face line at least 8), and data after the last
//! face is an error, so a lying header cannot make the reader loop, allocate or drop
//! faces silently.

use super::{check_not_utf16, color_to_u8, Polygons};
use crate::error::{Error, Result};

fn off_err(expected: impl Into<String>, got: impl Into<String>) -> Error {
    Error::invalid("off", expected, got)
}

/// What an OFF file holds.
#[derive(Debug, Default)]
pub(crate) struct OffContent {
    pub vertices: Vec<[f64; 3]>,
    pub normals: Option<Vec<[f64; 3]>>,
    pub colors: Option<Vec<[f64; 3]>>,
    pub polygons: Polygons,
    /// The 1-based line of each face, for errors.
    pub lines: Vec<usize>,
}

/// Parses OFF bytes (see the module documentation).
pub(crate) fn read(bytes: &[u8]) -> Result<OffContent> {
    check_not_utf16("off", bytes)?;
    let text = std::str::from_utf8(bytes).map_err(|e| {
        off_err(
            "ASCII text (binary OFF is not read)",
            format!("a non-UTF-8 byte at {}", e.valid_up_to()),
        )
    })?;
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    // Non-blank lines without comments, with their 1-based numbers and byte offsets.
    let mut lines = text.lines().enumerate().filter_map(|(i, raw)| {
        let line = raw.split('#').next().unwrap_or("").trim();
        (!line.is_empty()).then_some((i + 1, line))
    });
    let Some((_, first)) = lines.next() else {
        return Err(off_err("an OFF keyword line", "an empty file"));
    };
    let keyword_len = first
        .find(|c: char| !c.is_ascii_alphabetic())
        .unwrap_or(first.len());
    let (keyword, rest) = first.split_at(keyword_len);
    let (colored, with_normals) = match keyword {
        "OFF" => (false, false),
        "COFF" => (true, false),
        "NOFF" => (false, true),
        "CNOFF" | "NCOFF" => (true, true),
        _ => {
            return Err(off_err(
                "the keyword OFF, COFF, NOFF or CNOFF (ST, 4 and n variants are not read)",
                format!("line 1: {first:?}"),
            ))
        }
    };
    let rest = rest.trim();
    if rest.starts_with("BINARY") {
        return Err(off_err("ASCII OFF", "OFF BINARY (binary OFF is not read)"));
    }
    // The counts: on the keyword line (ModelNet's `OFF490 518 0`) or the next one.
    let (count_line, counts) = if rest.is_empty() {
        lines
            .next()
            .ok_or_else(|| off_err("a line V F [E]", "end of file after the keyword"))?
    } else {
        (1, rest)
    };
    let nums: Vec<&str> = counts.split_whitespace().collect();
    let parse = |t: &str| t.parse::<u64>().ok();
    let (v, f) = match nums.as_slice() {
        [v, f] | [v, f, _] => match (parse(v), parse(f)) {
            (Some(v), Some(f)) => (v, f),
            _ => {
                return Err(off_err(
                    "V F [E] as integers",
                    format!("line {count_line}: {counts:?}"),
                ))
            }
        },
        _ => {
            return Err(off_err(
                "a line V F [E]",
                format!("line {count_line}: {counts:?}"),
            ))
        }
    };
    let room = bytes.len() as u64;
    if v.saturating_mul(6).saturating_add(f.saturating_mul(8)) > room + 1 {
        return Err(off_err(
            "counts that the file's size can hold (6 bytes a vertex line, 8 a face line)",
            format!(
                "line {count_line}: {v} vertices and {f} faces in a file of {room} bytes \
                 (truncated or a lying header)"
            ),
        ));
    }
    // Bounded by the file's size (checked above).
    let (v, f) = (v as usize, f as usize);
    let mut out = OffContent {
        vertices: Vec::with_capacity(v),
        ..OffContent::default()
    };
    let mut normals = Vec::new();
    let mut colors = Vec::new();
    let number = |t: &str, line: usize| {
        t.parse::<f64>()
            .map_err(|_| off_err("a number", format!("line {line}: {t:?}")))
    };
    for i in 0..v {
        let (ln, line) = lines.next().ok_or_else(|| {
            off_err(
                format!("{v} vertex lines"),
                format!("end of file after {i} (truncated)"),
            )
        })?;
        let toks: Vec<&str> = line.split_whitespace().collect();
        let need = 3 + if with_normals { 3 } else { 0 } + if colored { 3 } else { 0 };
        if toks.len() < need || toks.len() > need + 1 {
            return Err(off_err(
                format!(
                    "a vertex line of {need} values (or {} with alpha)",
                    need + 1
                ),
                format!("line {ln}: {} values", toks.len()),
            ));
        }
        let vals: Vec<f64> = toks[..need]
            .iter()
            .map(|t| number(t, ln))
            .collect::<Result<_>>()?;
        out.vertices.push([vals[0], vals[1], vals[2]]);
        let mut k = 3;
        if with_normals {
            normals.push([vals[3], vals[4], vals[5]]);
            k = 6;
        }
        if colored {
            let float = toks[k..k + 3].iter().any(|t| t.contains('.'));
            let c = [vals[k], vals[k + 1], vals[k + 2]].map(|x| if float { x } else { x / 255.0 });
            if !c.iter().all(|x| (0.0..=1.0).contains(x)) {
                return Err(Error::invalid(
                    "colors",
                    "vertex colours as integers in 0..=255 or decimals in [0, 1]",
                    format!("off line {ln}: {:?}", &toks[k..k + 3]),
                ));
            }
            colors.push(c);
        }
    }
    let mut poly: Vec<i64> = Vec::new();
    for i in 0..f {
        let (ln, line) = lines.next().ok_or_else(|| {
            off_err(
                format!("{f} face lines"),
                format!("end of file after {i} (truncated)"),
            )
        })?;
        let mut toks = line.split_whitespace();
        let k = toks
            .next()
            .and_then(|t| t.parse::<usize>().ok())
            .ok_or_else(|| off_err("a face line k i₁ … i_k", format!("line {ln}: {line:?}")))?;
        poly.clear();
        for _ in 0..k {
            let idx = toks
                .next()
                .and_then(|t| t.parse::<i64>().ok())
                .ok_or_else(|| {
                    off_err(
                        format!("{k} vertex indices after the count"),
                        format!("line {ln}: {line:?}"),
                    )
                })?;
            poly.push(idx);
        }
        // What follows the indices is the face's colour (up to four values), ignored.
        let extra = toks.count();
        if extra > 4 {
            return Err(off_err(
                "a face line k i₁ … i_k with at most a colour after it",
                format!("line {ln}: {extra} values after the indices"),
            ));
        }
        out.polygons.push(&poly).map_err(|got| {
            off_err(
                "faces of at least 3 vertices with indices in 0 to 2³² − 1",
                format!("line {ln}: {got}"),
            )
        })?;
        out.lines.push(ln);
    }
    if let Some((ln, line)) = lines.next() {
        return Err(off_err(
            "no data after the faces the header declares",
            format!(
                "line {ln}: {line:?} (a header that declares fewer faces than the file holds?)"
            ),
        ));
    }
    out.normals = with_normals.then_some(normals);
    out.colors = colored.then_some(colors);
    Ok(out)
}

/// OFF text of `vertices` and triangles `faces` (`COFF` with colours, as integers
/// `round(255 c)`; normals are not written).
pub(crate) fn write(
    vertices: &[[f64; 3]],
    colors: Option<&[[f64; 3]]>,
    faces: &[[u32; 3]],
) -> Vec<u8> {
    let mut s = String::from(if colors.is_some() { "COFF\n" } else { "OFF\n" });
    s.push_str(&format!("{} {} 0\n", vertices.len(), faces.len()));
    for (i, p) in vertices.iter().enumerate() {
        s.push_str(&format!("{} {} {}", p[0], p[1], p[2]));
        if let Some(c) = colors {
            let [r, g, b] = c[i].map(color_to_u8);
            s.push_str(&format!(" {r} {g} {b}"));
        }
        s.push('\n');
    }
    for t in faces {
        s.push_str(&format!("3 {} {} {}\n", t[0], t[1], t[2]));
    }
    s.into_bytes()
}
