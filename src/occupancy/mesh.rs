//! Triangle meshes: validation, PLY and OBJ read/write, normalisation to the unit cube,
//! area-weighted surface sampling, and the topological checks (watertight, oriented)
//! used by the marching-cubes tests.
//!
//! Vertices are `f64` on the host (meshes are inputs and outputs of the pipeline, not
//! part of a gradient); [`points_tensor`] moves them to any device and dtype.
//!
//! Files written here load in standard tools: `assimp info` (assimp 5.2.5, Debian's
//! `assimp-utils`) imports the binary PLY written by `examples/fit_occupancy.rs`
//! (15 454 vertices, 30 896 triangles) and by `examples/quickstart.rs`; the format is the
//! plain `float x y z` + `list uchar int vertex_indices` layout that MeshLab, Blender and
//! trimesh read, with `uchar red green blue` vertex colours when the mesh has them. The
//! tests read every format back.

use crate::error::{Error, Result};
use crate::rng::SplitMix64;
use candle_core::{DType, Device, Tensor};
use std::collections::HashMap;
use std::path::Path;

/// A triangle mesh: vertex positions, triangles as vertex indices, optional per-vertex
/// normals and colours (one per vertex when present).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions `[V][3]`.
    pub vertices: Vec<[f64; 3]>,
    /// Triangles `[F][3]`, indices into `vertices`, counter-clockwise seen from outside.
    pub faces: Vec<[u32; 3]>,
    /// Optional per-vertex normals `[V][3]`.
    pub normals: Option<Vec<[f64; 3]>>,
    /// Optional per-vertex colours `[V][3]`: RGB components in `[0, 1]`, the values PLY
    /// stores as `uchar red green blue` divided by 255.
    pub colors: Option<Vec<[f64; 3]>>,
}

/// Surface samples: points `[n][3]` and the unit normals of their faces `[n][3]`.
pub type SurfaceSamples = (Vec<[f64; 3]>, Vec<[f64; 3]>);

/// A mesh file format, for [`Mesh::to_bytes`] and [`Mesh::from_bytes`].
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
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

fn mesh_err(expected: &str, got: impl Into<String>) -> Error {
    Error::invalid("mesh", expected.to_string(), got)
}

fn file_err(what: &'static str, expected: impl Into<String>, got: impl Into<String>) -> Error {
    Error::invalid(what, expected, got)
}

impl Mesh {
    /// A validated mesh from vertices and triangles (no normals, no colours).
    ///
    /// # Errors
    /// See [`Mesh::validate`].
    pub fn new(vertices: Vec<[f64; 3]>, faces: Vec<[u32; 3]>) -> Result<Self> {
        let m = Self {
            vertices,
            faces,
            normals: None,
            colors: None,
        };
        m.validate()?;
        Ok(m)
    }

    /// The mesh with per-vertex colours `colors` (RGB, each component in `[0, 1]`),
    /// validated.
    ///
    /// ```
    /// use neural_fields::occupancy::Mesh;
    ///
    /// let tri = Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], vec![[0, 1, 2]])?
    ///     .with_colors(vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])?;
    /// assert_eq!(tri.colors.as_ref().map(Vec::len), Some(3));
    /// assert!(tri.clone().with_colors(vec![[2.0, 0.0, 0.0]; 3]).is_err());
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// See [`Mesh::validate`]: a colour count other than the vertex count, or a component
    /// that is not finite or lies outside `[0, 1]` (naming `colors`).
    pub fn with_colors(mut self, colors: Vec<[f64; 3]>) -> Result<Self> {
        self.colors = Some(colors);
        self.validate()?;
        Ok(self)
    }

    /// Checks the mesh: at least one vertex and one face, every face index `< V`, every
    /// coordinate (and normal component) finite, normals (if any) one per vertex, colours
    /// (if any) one per vertex with every component finite and in `[0, 1]`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `mesh` and the first offending face, vertex,
    /// normal or colour (`colors[i]`).
    pub fn validate(&self) -> Result<()> {
        if self.vertices.is_empty() || self.faces.is_empty() {
            return Err(mesh_err(
                "at least one vertex and one face",
                format!(
                    "an empty mesh ({} vertices, {} faces)",
                    self.vertices.len(),
                    self.faces.len()
                ),
            ));
        }
        let nv = self.vertices.len();
        for (i, v) in self.vertices.iter().enumerate() {
            if v.iter().any(|c| !c.is_finite()) {
                return Err(mesh_err(
                    "finite vertex coordinates",
                    format!("vertex {i} = {v:?} (NaN or infinite)"),
                ));
            }
        }
        self.check_indices()?;
        if let Some(n) = &self.normals {
            if n.len() != nv {
                return Err(mesh_err(
                    "one normal per vertex",
                    format!("{} normals for {nv} vertices", n.len()),
                ));
            }
            if let Some(i) = n.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
                return Err(mesh_err(
                    "finite normals",
                    format!("normal {i} = {:?}", n[i]),
                ));
            }
        }
        if let Some(col) = &self.colors {
            if col.len() != nv {
                return Err(mesh_err(
                    "one entry of colors per vertex",
                    format!("{} colors for {nv} vertices", col.len()),
                ));
            }
            let in_unit = |c: &f64| (0.0..=1.0).contains(c); // false for NaN
            if let Some(i) = col.iter().position(|v| !v.iter().all(in_unit)) {
                return Err(mesh_err(
                    "colors with finite components in [0, 1]",
                    format!("colors[{i}] = {:?}", col[i]),
                ));
            }
        }
        Ok(())
    }

    /// Every face index below the vertex count (a `Mesh` built as a struct literal may
    /// break it; the geometric accessors check it before indexing).
    fn check_indices(&self) -> Result<()> {
        let nv = self.vertices.len();
        for (i, f) in self.faces.iter().enumerate() {
            if let Some(&bad) = f.iter().find(|&&k| k as usize >= nv) {
                return Err(mesh_err(
                    "face indices below the vertex count",
                    format!("face {i} = {f:?} indexes vertex {bad} of {nv}"),
                ));
            }
        }
        Ok(())
    }

    fn corners(&self, f: [u32; 3]) -> [[f64; 3]; 3] {
        [
            self.vertices[f[0] as usize],
            self.vertices[f[1] as usize],
            self.vertices[f[2] as usize],
        ]
    }

    /// Unnormalised face normal `(b − a) × (c − a)` (length = twice the area).
    fn face_cross(&self, f: [u32; 3]) -> [f64; 3] {
        let [a, b, c] = self.corners(f);
        cross(sub(b, a), sub(c, a))
    }

    /// Triangle areas `½‖(b − a) × (c − a)‖`, `[F]`.
    ///
    /// # Errors
    /// Naming `mesh` for a face index not below the vertex count.
    pub fn face_areas(&self) -> Result<Vec<f64>> {
        self.check_indices()?;
        Ok(self
            .faces
            .iter()
            .map(|&f| 0.5 * norm(self.face_cross(f)))
            .collect())
    }

    /// Unit face normals `(b − a) × (c − a) / ‖·‖` (zero for degenerate faces), `[F][3]`.
    ///
    /// # Errors
    /// Naming `mesh` for a face index not below the vertex count.
    pub fn face_normals(&self) -> Result<Vec<[f64; 3]>> {
        self.check_indices()?;
        Ok(self
            .faces
            .iter()
            .map(|&f| {
                let n = self.face_cross(f);
                let l = norm(n);
                if l > 0.0 {
                    [n[0] / l, n[1] / l, n[2] / l]
                } else {
                    [0.0; 3]
                }
            })
            .collect())
    }

    /// Area-weighted vertex normals (sum of the incident faces' `(b−a)×(c−a)`,
    /// normalised; zero for isolated vertices), `[V][3]`.
    ///
    /// # Errors
    /// Naming `mesh` for a face index not below the vertex count.
    pub fn vertex_normals(&self) -> Result<Vec<[f64; 3]>> {
        self.check_indices()?;
        let mut acc = vec![[0.0f64; 3]; self.vertices.len()];
        for &f in &self.faces {
            let n = self.face_cross(f);
            for &k in &f {
                for c in 0..3 {
                    acc[k as usize][c] += n[c];
                }
            }
        }
        for n in &mut acc {
            let l = norm(*n);
            if l > 0.0 {
                *n = [n[0] / l, n[1] / l, n[2] / l];
            }
        }
        Ok(acc)
    }

    /// Signed volume `Σ a·(b × c) / 6` over the faces: positive for a closed mesh whose
    /// faces are counter-clockwise seen from outside (outward normals).
    ///
    /// # Errors
    /// Naming `mesh` for a face index not below the vertex count.
    pub fn signed_volume(&self) -> Result<f64> {
        self.check_indices()?;
        Ok(self
            .faces
            .iter()
            .map(|&f| {
                let [a, b, c] = self.corners(f);
                dot(a, cross(b, c))
            })
            .sum::<f64>()
            / 6.0)
    }

    /// Axis-aligned bounds `(min, max)` of the vertices (`([∞; 3], [−∞; 3])` if none).
    #[must_use]
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for v in &self.vertices {
            for c in 0..3 {
                lo[c] = lo[c].min(v[c]);
                hi[c] = hi[c].max(v[c]);
            }
        }
        (lo, hi)
    }

    /// ONet's normalisation: translate the bounding-box centre to the origin and scale
    /// uniformly so that the longest side of the box is `1`, i.e. the mesh fits in
    /// `[−½, ½]³`. Normals (uniform scale) and colours are unchanged. Returns
    /// `(centre, scale)` with `p_new = (p − centre)·scale`.
    ///
    /// # Errors
    /// An invalid mesh, or all vertices at one point.
    pub fn normalize_unit_cube(&mut self) -> Result<([f64; 3], f64)> {
        self.validate()?;
        let (lo, hi) = self.bounds();
        let centre = [
            0.5 * (lo[0] + hi[0]),
            0.5 * (lo[1] + hi[1]),
            0.5 * (lo[2] + hi[2]),
        ];
        let ext = (0..3).map(|c| hi[c] - lo[c]).fold(0.0, f64::max);
        if ext <= 0.0 {
            return Err(mesh_err(
                "vertices spanning a box of positive size",
                "all vertices at one point",
            ));
        }
        let s = 1.0 / ext;
        for v in &mut self.vertices {
            for c in 0..3 {
                v[c] = (v[c] - centre[c]) * s;
            }
        }
        Ok((centre, s))
    }

    /// Counts `(boundary, non-manifold, misoriented)` edges: undirected edges used by one
    /// face, by more than two faces, and edges whose two faces traverse them in the same
    /// direction (inconsistent orientation).
    #[must_use]
    pub fn edge_report(&self) -> (usize, usize, usize) {
        let mut uses: HashMap<(u32, u32), (u32, u32)> = HashMap::new(); // (forward, backward)
        for f in &self.faces {
            for k in 0..3 {
                let (a, b) = (f[k], f[(k + 1) % 3]);
                let e = uses.entry((a.min(b), a.max(b))).or_insert((0, 0));
                if a < b {
                    e.0 += 1;
                } else {
                    e.1 += 1;
                }
            }
        }
        let mut boundary = 0;
        let mut nonmanifold = 0;
        let mut misoriented = 0;
        for &(fw, bw) in uses.values() {
            match fw + bw {
                1 => boundary += 1,
                2 => {
                    if fw != 1 {
                        misoriented += 1;
                    }
                }
                _ => nonmanifold += 1,
            }
        }
        (boundary, nonmanifold, misoriented)
    }

    /// True if every edge is shared by exactly two faces traversing it in opposite
    /// directions (closed, manifold along edges, consistently oriented).
    #[must_use]
    pub fn is_watertight_and_oriented(&self) -> bool {
        !self.faces.is_empty() && self.edge_report() == (0, 0, 0)
    }

    /// `n` points drawn uniformly on the surface (faces chosen with probability
    /// proportional to area, then uniform barycentric coordinates `(1 − √u, √u(1 − v),
    /// √u v)`), with the unit normals of their faces. Same `seed`, same points.
    ///
    /// # Errors
    /// Invalid mesh, or zero total area; naming `n` when `n` points cannot be allocated.
    pub fn sample_surface(&self, n: usize, seed: u64) -> Result<SurfaceSamples> {
        self.validate()?;
        let areas = self.face_areas()?;
        let mut cdf = Vec::with_capacity(areas.len());
        let mut acc = 0.0;
        for a in &areas {
            acc += a;
            cdf.push(acc);
        }
        if acc.is_nan() || acc <= 0.0 {
            return Err(mesh_err("a positive surface area", format!("{acc}")));
        }
        let normals = self.face_normals()?;
        let mut rng = SplitMix64::new(seed);
        let (mut pts, mut nrm) = (Vec::new(), Vec::new());
        // A count that cannot be allocated is an error, not an abort.
        if pts.try_reserve_exact(n).is_err() || nrm.try_reserve_exact(n).is_err() {
            return Err(Error::invalid(
                "n",
                "a sample count whose points fit in memory",
                format!("{n}"),
            ));
        }
        for _ in 0..n {
            let t = rng.uniform() * acc;
            let fi = cdf.partition_point(|&c| c <= t).min(cdf.len() - 1);
            let [a, b, c] = self.corners(self.faces[fi]);
            let su = rng.uniform().sqrt();
            let v = rng.uniform();
            let (wa, wb, wc) = (1.0 - su, su * (1.0 - v), su * v);
            pts.push([
                wa * a[0] + wb * b[0] + wc * c[0],
                wa * a[1] + wb * b[1] + wc * c[1],
                wa * a[2] + wb * b[2] + wc * c[2],
            ]);
            nrm.push(normals[fi]);
        }
        Ok((pts, nrm))
    }

    // ------------------------------------------------------------------ files

    /// Reads a `.ply` or `.obj` file (by extension, case-insensitive).
    ///
    /// # Errors
    /// I/O errors ([`Error::Io`] with the path); unknown extension; parse errors of
    /// [`Mesh::from_bytes`].
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|source| Error::Io {
            path: path.display().to_string(),
            source,
        })?;
        match extension(path).as_str() {
            "ply" => Self::from_bytes(&bytes, MeshFormat::PlyBinary),
            "obj" => Self::from_bytes(&bytes, MeshFormat::Obj),
            other => Err(file_err(
                "path",
                "a .ply or .obj file",
                format!("extension {other:?}"),
            )),
        }
    }

    /// Writes a `.ply` (binary little-endian) or `.obj` file, by extension.
    ///
    /// # Errors
    /// Invalid mesh, unknown extension, I/O errors.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        let bytes = match extension(path).as_str() {
            "ply" => self.to_bytes(MeshFormat::PlyBinary)?,
            "obj" => self.to_bytes(MeshFormat::Obj)?,
            other => {
                return Err(file_err(
                    "path",
                    "a .ply or .obj file",
                    format!("extension {other:?}"),
                ))
            }
        };
        std::fs::write(path, bytes).map_err(|source| Error::Io {
            path: path.display().to_string(),
            source,
        })
    }

    /// Serialises the mesh in `format`.
    ///
    /// - PLY: `element vertex` with `float x, y, z` (and `nx, ny, nz` when normals are
    ///   present; coordinates are written as 32-bit floats, the common convention read
    ///   by every tool), then `uchar red, green, blue` when colours are present (each
    ///   `round(c · 255)`, the vertex colours MeshLab and Blender read), `element face`
    ///   with `list uchar int vertex_indices`.
    /// - OBJ: `v x y z`, `vn` lines when normals are present, and 1-based `f a b c` (or
    ///   `f a//a b//b c//c` with normals). Colours are not written: OBJ has no standard
    ///   for them, so [`Mesh::colors`] is dropped.
    ///
    /// ```
    /// use neural_fields::occupancy::{Mesh, MeshFormat};
    ///
    /// let tri = Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], vec![[0, 1, 2]])?;
    /// for format in [MeshFormat::PlyAscii, MeshFormat::PlyBinary, MeshFormat::Obj] {
    ///     let back = Mesh::from_bytes(&tri.to_bytes(format)?, format)?;
    ///     assert_eq!(back.faces, tri.faces);
    /// }
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// Invalid mesh ([`Mesh::validate`]).
    pub fn to_bytes(&self, format: MeshFormat) -> Result<Vec<u8>> {
        match format {
            MeshFormat::PlyAscii => self.to_ply(false),
            MeshFormat::PlyBinary => self.to_ply(true),
            MeshFormat::Obj => Ok(self.to_obj()?.into_bytes()),
        }
    }

    /// Parses a mesh file's bytes in `format` (PLY in any encoding, or OBJ).
    ///
    /// - PLY (ASCII, binary little- or big-endian): reads `element vertex` (`x, y, z`,
    ///   optional `nx, ny, nz`, optional colours `red, green, blue` when all three are
    ///   present; any other properties, `alpha` among them, are skipped) and
    ///   `element face` (a list property named `vertex_indices` or `vertex_index`, any
    ///   count and index types). Other elements are skipped. Polygons with more than three vertices are
    ///   triangulated as fans `(0, i, i+1)`.
    /// - OBJ: `v` (extra components such as `w` or colours ignored), `vn`, and `f` with
    ///   `a`, `a/b`, `a//c` or `a/b/c` references, 1-based or negative (relative).
    ///   Polygons are fan-triangulated. Other statements (`vt`, `o`, `g`, `usemtl`,
    ///   `mtllib`, `s`, `l`, `p`) are ignored. Normals are kept only when every face
    ///   corner names the normal with the same index as its vertex (as
    ///   [`Mesh::to_bytes`] writes them); otherwise they are dropped. Invalid UTF-8 is
    ///   replaced; UTF-16 text is refused with an error naming the encoding.
    ///
    /// PLY colours: `uchar` values are divided by 255, other unsigned and signed integer
    /// types by their largest value (`ushort` by 65 535), and `float`/`double` values are
    /// taken as they are (already in `[0, 1]`).
    ///
    /// # Errors
    /// A malformed header or body, naming the line (ASCII and header) or the byte offset
    /// (binary) where it went wrong; a truncated file; faces with fewer than 3 vertices;
    /// malformed numbers or references; a PLY colour outside `[0, 1]` after that scaling
    /// (naming `colors`, the vertex and the line or byte offset); then [`Mesh::validate`].
    pub fn from_bytes(bytes: &[u8], format: MeshFormat) -> Result<Self> {
        match format {
            MeshFormat::PlyAscii | MeshFormat::PlyBinary => Self::from_ply(bytes),
            MeshFormat::Obj => {
                check_not_utf16(bytes)?;
                Self::from_obj(&String::from_utf8_lossy(bytes))
            }
        }
    }

    /// PLY bytes (see [`Mesh::to_bytes`]).
    fn to_ply(&self, binary: bool) -> Result<Vec<u8>> {
        self.validate()?;
        let has_n = self.normals.is_some();
        let has_c = self.colors.is_some();
        let mut out = Vec::new();
        let fmt = if binary {
            "binary_little_endian"
        } else {
            "ascii"
        };
        let mut header = format!(
            "ply\nformat {fmt} 1.0\ncomment neural-fields\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n",
            self.vertices.len()
        );
        if has_n {
            header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
        }
        if has_c {
            header.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
        }
        header.push_str(&format!(
            "element face {}\nproperty list uchar int vertex_indices\nend_header\n",
            self.faces.len()
        ));
        out.extend_from_slice(header.as_bytes());
        let empty = Vec::new();
        let normals = self.normals.as_ref().unwrap_or(&empty);
        let colors = self.colors.as_ref().unwrap_or(&empty);
        if !binary {
            {
                let mut s = String::new();
                for (i, v) in self.vertices.iter().enumerate() {
                    s.push_str(&format!("{} {} {}", v[0] as f32, v[1] as f32, v[2] as f32));
                    if has_n {
                        let n = normals[i];
                        s.push_str(&format!(" {} {} {}", n[0] as f32, n[1] as f32, n[2] as f32));
                    }
                    if has_c {
                        let [r, g, b] = colors[i].map(color_to_u8);
                        s.push_str(&format!(" {r} {g} {b}"));
                    }
                    s.push('\n');
                }
                for f in &self.faces {
                    s.push_str(&format!("3 {} {} {}\n", f[0], f[1], f[2]));
                }
                out.extend_from_slice(s.as_bytes());
            }
        } else {
            {
                for (i, v) in self.vertices.iter().enumerate() {
                    for c in v {
                        out.extend_from_slice(&(*c as f32).to_le_bytes());
                    }
                    if has_n {
                        for c in normals[i] {
                            out.extend_from_slice(&(c as f32).to_le_bytes());
                        }
                    }
                    if has_c {
                        out.extend_from_slice(&colors[i].map(color_to_u8));
                    }
                }
                for f in &self.faces {
                    out.push(3);
                    for &k in f {
                        out.extend_from_slice(&(k as i32).to_le_bytes());
                    }
                }
            }
        }
        Ok(out)
    }

    /// Parses PLY bytes (see [`Mesh::from_bytes`]).
    fn from_ply(bytes: &[u8]) -> Result<Self> {
        let header = parse_ply_header(bytes)?;
        let mut mesh = Mesh::default();
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
            let rgb = match (scalar("red"), scalar("green"), scalar("blue")) {
                (Some(r), Some(g), Some(b)) => Some([r, g, b]),
                _ => None,
            };
            if is_vertex && (xi.is_none() || yi.is_none() || zi.is_none()) {
                return Err(file_err(
                    "ply",
                    "vertex properties x, y and z",
                    format!("header line {}: missing", el.line),
                ));
            }
            let fi = el.props.iter().position(|p| {
                p.list.is_some() && (p.name == "vertex_indices" || p.name == "vertex_index")
            });
            if is_face && fi.is_none() {
                return Err(file_err(
                    "ply",
                    "a face list property vertex_indices or vertex_index",
                    format!("header line {}: none", el.line),
                ));
            }
            if el.props.is_empty() {
                // A property-less element holds no values in any encoding: there is
                // nothing to read, whatever its count (iterating a count such as 2⁶⁴ − 1
                // would never end).
                continue;
            }
            src.check_room(el)?;
            for row in 0..el.count {
                src.begin_row()?;
                let row_start = src.pos;
                let mut scalars = vec![0.0f64; el.props.len()];
                let mut list: Vec<i64> = Vec::new();
                for (pi, p) in el.props.iter().enumerate() {
                    match p.list {
                        Some(count_ty) => {
                            let n = src.read(count_ty)?;
                            if !(0.0..=1e7).contains(&n) || n.fract() != 0.0 {
                                return Err(file_err(
                                    "ply",
                                    "a list count between 0 and 10⁷",
                                    format!("{} {}: count {n}", src.position(), el.name),
                                ));
                            }
                            let keep = is_face && Some(pi) == fi;
                            for _ in 0..n as usize {
                                let v = src.read(p.ty)?;
                                if keep {
                                    list.push(v as i64);
                                }
                            }
                        }
                        None => scalars[pi] = src.read(p.ty)?,
                    }
                }
                src.end_row()?;
                if is_vertex {
                    // invariant: checked above that x, y, z exist.
                    let (x, y, z) = (xi.unwrap_or(0), yi.unwrap_or(0), zi.unwrap_or(0));
                    mesh.vertices.push([scalars[x], scalars[y], scalars[z]]);
                    if let (Some(a), Some(b), Some(c)) = (nxi, nyi, nzi) {
                        normals.push([scalars[a], scalars[b], scalars[c]]);
                    }
                    if let Some(ch) = rgb {
                        let c = ch.map(|k| scalars[k] / el.props[k].ty.color_scale());
                        if !c.iter().all(|x| (0.0..=1.0).contains(x)) {
                            let raw = ch.map(|k| scalars[k]);
                            return Err(file_err(
                                "ply",
                                "vertex colors (red, green, blue) in [0, 1] once scaled \
                                 (integers by their type's largest value, floats as they are)",
                                format!(
                                    "{}: vertex {row}: red, green, blue = {raw:?} → colors {c:?}",
                                    src.row_position(row_start)
                                ),
                            ));
                        }
                        colors.push(c);
                    }
                } else if is_face {
                    push_polygon(&mut mesh.faces, &list).map_err(|got| {
                        file_err(
                            "ply",
                            "faces with at least 3 non-negative indices",
                            format!("face {row}: {got}"),
                        )
                    })?;
                }
            }
        }
        src.finish()?;
        if !normals.is_empty() {
            mesh.normals = Some(normals);
        }
        if !colors.is_empty() {
            mesh.colors = Some(colors);
        }
        mesh.validate()?;
        Ok(mesh)
    }

    /// OBJ text (see [`Mesh::to_bytes`]).
    fn to_obj(&self) -> Result<String> {
        self.validate()?;
        let mut s = String::from("# neural-fields\n");
        for v in &self.vertices {
            s.push_str(&format!("v {} {} {}\n", v[0], v[1], v[2]));
        }
        if let Some(ns) = &self.normals {
            for n in ns {
                s.push_str(&format!("vn {} {} {}\n", n[0], n[1], n[2]));
            }
        }
        let with_n = self.normals.is_some();
        for f in &self.faces {
            let (a, b, c) = (f[0] + 1, f[1] + 1, f[2] + 1);
            if with_n {
                s.push_str(&format!("f {a}//{a} {b}//{b} {c}//{c}\n"));
            } else {
                s.push_str(&format!("f {a} {b} {c}\n"));
            }
        }
        Ok(s)
    }

    /// Parses OBJ text (see [`Mesh::from_bytes`]).
    fn from_obj(text: &str) -> Result<Self> {
        let mut mesh = Mesh::default();
        let mut vn: Vec<[f64; 3]> = Vec::new();
        let mut normals_match = true;
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
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
                            file_err(
                                "obj",
                                "three coordinates",
                                format!("line {line_no}: {line:?}"),
                            )
                        })?;
                        *slot = t.parse::<f64>().map_err(|_| {
                            file_err("obj", "a number", format!("line {line_no}: {t:?}"))
                        })?;
                    }
                    if kw == "v" {
                        mesh.vertices.push(c);
                    } else {
                        vn.push(c);
                    }
                }
                "f" => {
                    let mut poly = Vec::new();
                    for t in tok {
                        let mut parts = t.split('/');
                        let vi = resolve_obj_index(parts.next().unwrap_or(""), mesh.vertices.len())
                            .map_err(|e| {
                                file_err(
                                    "obj",
                                    "a face vertex reference",
                                    format!("line {line_no}: {t:?} ({e})"),
                                )
                            })?;
                        let _tex = parts.next();
                        match parts.next() {
                            Some(n) if !n.is_empty() => {
                                let ni = resolve_obj_index(n, vn.len()).map_err(|e| {
                                    file_err(
                                        "obj",
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
                    push_polygon(&mut mesh.faces, &poly).map_err(|got| {
                        file_err(
                            "obj",
                            "faces with at least 3 vertices",
                            format!("line {line_no}: {got}"),
                        )
                    })?;
                }
                _ => {}
            }
        }
        if normals_match && !vn.is_empty() && vn.len() == mesh.vertices.len() {
            mesh.normals = Some(vn);
        }
        mesh.validate()?;
        Ok(mesh)
    }
}

/// A `[N, 3]` tensor from host points.
///
/// # Errors
/// candle's.
pub fn points_tensor(points: &[[f64; 3]], device: &Device, dtype: DType) -> Result<Tensor> {
    let flat: Vec<f64> = points.iter().flatten().copied().collect();
    Ok(Tensor::from_vec(flat, (points.len(), 3), &Device::Cpu)?
        .to_dtype(dtype)?
        .to_device(device)?)
}

/// Refuses UTF-16 text (a byte-order mark, or NUL bytes among the first kilobyte, which
/// ASCII and UTF-8 text never holds), naming the encoding: read lossily as UTF-8 it
/// would parse as an empty mesh.
fn check_not_utf16(bytes: &[u8]) -> Result<()> {
    let bom = bytes.starts_with(&[0xFF, 0xFE]) || bytes.starts_with(&[0xFE, 0xFF]);
    if bom || bytes.iter().take(1024).any(|&b| b == 0) {
        return Err(file_err(
            "obj",
            "ASCII or UTF-8 text",
            "UTF-16 (or other NUL-bearing) text: convert the file to UTF-8",
        ));
    }
    Ok(())
}

fn extension(path: &Path) -> String {
    path.extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default()
}

/// A colour component in `[0, 1]` as a PLY `uchar`: `round(c · 255)`, clamped to `0..=255`.
fn color_to_u8(c: f64) -> u8 {
    // The clamp keeps the value in 0..=255, so the cast neither wraps nor saturates.
    (c * 255.0).round().clamp(0.0, 255.0) as u8
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

/// Fan-triangulates a polygon of vertex indices and appends the triangles.
fn push_polygon(faces: &mut Vec<[u32; 3]>, poly: &[i64]) -> std::result::Result<(), String> {
    if poly.len() < 3 {
        return Err(format!("{} vertices", poly.len()));
    }
    if let Some(&b) = poly.iter().find(|&&k| k < 0 || k > u32::MAX as i64) {
        return Err(format!("index {b}"));
    }
    for i in 1..poly.len() - 1 {
        faces.push([poly[0] as u32, poly[i] as u32, poly[i + 1] as u32]);
    }
    Ok(())
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
                "ply",
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
                return Err(file_err(
                    "ply",
                    "a file starting with \"ply\"",
                    format!("line 1: {line:?}"),
                ));
            }
            continue;
        }
        let bad = |what: &str| {
            file_err(
                "ply",
                what.to_string(),
                format!("header line {line_no}: {line:?}"),
            )
        };
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
        return Err(file_err("ply", "a format line in the header", "none"));
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
                    "ply",
                    "as many rows as the header declares",
                    format!("end of file at line {} (truncated)", self.line + 1),
                ));
            }
            let rel = self.bytes[self.pos..]
                .iter()
                .position(|&b| b == b'\n')
                .unwrap_or(self.bytes.len() - self.pos);
            let s = std::str::from_utf8(&self.bytes[self.pos..self.pos + rel])
                .map_err(|_| file_err("ply", "UTF-8 text", format!("line {}", self.line + 1)))?;
            self.pos += rel + 1;
            self.line += 1;
            self.tokens = s.split_whitespace().collect();
            self.tok = 0;
            if !self.tokens.is_empty() {
                return Ok(());
            }
        }
    }

    fn end_row(&mut self) -> Result<()> {
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
        let room = (left + 1) / min_row.max(1);
        if el.count > room {
            return Err(file_err(
                "ply",
                "element counts that the rest of the file can hold",
                format!(
                    "header line {}: element {} declares {} rows of at least {min_row} bytes, \
                     but {left} bytes remain (truncated or a lying header)",
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
                        "ply",
                        "as many values on the line as the element has properties",
                        format!("line {}: only {} values", self.line, self.tokens.len()),
                    ));
                };
                self.tok += 1;
                t.parse::<f64>()
                    .map_err(|_| file_err("ply", "a number", format!("line {}: {t:?}", self.line)))
            }
            enc => {
                let n = ty.size();
                if self.pos + n > self.bytes.len() {
                    return Err(file_err(
                        "ply",
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

    fn finish(&self) -> Result<()> {
        Ok(())
    }
}
