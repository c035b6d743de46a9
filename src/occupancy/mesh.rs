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

use super::ply::{self, Polygons};
use super::point_cloud::{check_f32_range, check_points};
use super::triangulate::triangulate;
use super::{off, stl};
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
    pub fn from_path(path: &Path) -> Result<Self> {
        match extension(path).as_str() {
            "ply" => Ok(Self::PlyBinary),
            "obj" => Ok(Self::Obj),
            "stl" => Ok(Self::StlBinary),
            "off" => Ok(Self::Off),
            other => Err(file_err(
                "path",
                "a .ply, .obj, .stl or .off file",
                format!("{} (extension {other:?})", path.display()),
            )),
        }
    }
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
        check_points(
            "mesh",
            ["vertex", "vertices"],
            &self.vertices,
            self.normals.as_deref(),
            self.colors.as_deref(),
        )?;
        self.check_indices()
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

    /// Reads a `.ply`, `.obj`, `.stl` or `.off` file (by extension, case-insensitive;
    /// see [`MeshFormat::from_path`] and [`Mesh::from_bytes`]).
    ///
    /// # Errors
    /// I/O errors ([`Error::Io`] with the path); an unknown extension; the parse errors
    /// of [`Mesh::from_bytes`], as [`Error::Format`] naming the path.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let format = MeshFormat::from_path(path)?;
        let bytes = read_file(path)?;
        Self::from_bytes(&bytes, format).map_err(|e| in_file(e, path))
    }

    /// Writes a `.ply` (binary little-endian), `.obj`, `.stl` (binary) or `.off` file,
    /// by extension.
    ///
    /// # Errors
    /// Invalid mesh, unknown extension, I/O errors.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        let bytes = self.to_bytes(MeshFormat::from_path(path)?)?;
        write_file(path, &bytes)
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
    /// Invalid mesh ([`Mesh::validate`]); for PLY and binary STL, which store 32-bit floats,
    /// a coordinate or normal beyond ±3.4e38 (naming `mesh`).
    pub fn to_bytes(&self, format: MeshFormat) -> Result<Vec<u8>> {
        self.validate()?;
        if matches!(
            format,
            MeshFormat::PlyAscii | MeshFormat::PlyBinary | MeshFormat::StlBinary
        ) {
            check_f32_range("mesh", "vertex", &self.vertices)?;
            check_f32_range("mesh", "normal", self.normals.as_deref().unwrap_or(&[]))?;
        }
        let (v, f, c) = (&self.vertices, &self.faces, self.colors.as_deref());
        Ok(match format {
            MeshFormat::PlyAscii | MeshFormat::PlyBinary => ply::write(
                v,
                self.normals.as_deref(),
                c,
                Some(f),
                format == MeshFormat::PlyBinary,
            ),
            MeshFormat::Obj => self.to_obj().into_bytes(),
            MeshFormat::StlAscii => stl::write(v, f, false),
            MeshFormat::StlBinary => stl::write(v, f, true),
            MeshFormat::Off => off::write(v, c, f),
        })
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
        let mesh = match format {
            MeshFormat::PlyAscii | MeshFormat::PlyBinary => {
                let c = ply::read(bytes)?;
                let mut m =
                    Self::from_polygons(c.vertices, &c.polygons, "ply", |i| format!("face {i}"))?;
                m.normals = c.normals;
                m.colors = c.colors;
                m
            }
            MeshFormat::Obj => {
                let c = parse_obj(bytes)?;
                let normals = c.normals_by_reference();
                let mut m = Self::from_polygons(c.vertices, &c.polygons, "obj", |i| {
                    format!("line {}", c.lines[i])
                })?;
                m.normals = normals;
                m
            }
            MeshFormat::StlAscii | MeshFormat::StlBinary => {
                let mut soup = stl::read(bytes)?;
                let polygons = std::mem::take(&mut soup.polygons);
                let vertices = std::mem::take(&mut soup.vertices);
                Self::from_polygons(vertices, &polygons, "stl", |i| soup.locate(i))?
            }
            MeshFormat::Off => {
                let c = off::read(bytes)?;
                let mut m = Self::from_polygons(c.vertices, &c.polygons, "off", |i| {
                    format!("line {}", c.lines[i])
                })?;
                m.normals = c.normals;
                m.colors = c.colors;
                m
            }
        };
        mesh.validate()?;
        Ok(mesh)
    }

    /// A mesh from vertices and polygons, triangulated ([`triangulate`]); a file with
    /// vertices and no polygons is refused as the point cloud it is.
    pub(crate) fn from_polygons(
        vertices: Vec<[f64; 3]>,
        polygons: &Polygons,
        what: &'static str,
        locate: impl Fn(usize) -> String,
    ) -> Result<Self> {
        if polygons.len() == 0 && !vertices.is_empty() {
            return Err(file_err(
                what,
                "a mesh with faces",
                format!(
                    "a point cloud ({} point{}, no faces): read it with PointCloud::load or \
                     PointCloud::from_bytes",
                    vertices.len(),
                    if vertices.len() == 1 { "" } else { "s" }
                ),
            ));
        }
        let mut faces = Vec::with_capacity(polygons.len());
        let nv = vertices.len();
        for (i, poly) in polygons.iter().enumerate() {
            if let Some(&bad) = poly.iter().find(|&&k| k as usize >= nv) {
                let list = if poly.len() <= 16 {
                    format!(" = {poly:?}")
                } else {
                    String::new()
                };
                return Err(file_err(
                    what,
                    "face indices below the vertex count",
                    format!("{}{list} indexes vertex {bad} of {nv}", locate(i)),
                ));
            }
            triangulate(&vertices, poly, &mut faces).map_err(|got| {
                file_err(
                    what,
                    "faces of at least 3 vertices forming simple polygons (not self-intersecting, wound once)",
                    format!("{}: {got}", locate(i)),
                )
            })?;
        }
        Ok(Self {
            vertices,
            faces,
            normals: None,
            colors: None,
        })
    }

    /// OBJ text (see [`Mesh::to_bytes`]).
    fn to_obj(&self) -> String {
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
        s
    }
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
    /// with its vertex's index (as [`Mesh::to_bytes`] writes them).
    pub fn normals_by_reference(&self) -> Option<Vec<[f64; 3]>> {
        if self.normals_match {
            self.normals_by_count()
        } else {
            None
        }
    }

    /// The normals of a point cloud: one `vn` per `v`.
    pub fn normals_by_count(&self) -> Option<Vec<[f64; 3]>> {
        (!self.vn.is_empty() && self.vn.len() == self.vertices.len()).then(|| self.vn.clone())
    }
}

/// Parses OBJ bytes (see [`Mesh::from_bytes`]).
pub(crate) fn parse_obj(bytes: &[u8]) -> Result<ObjContent> {
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
                polygons.push(&poly).map_err(|got| {
                    file_err(
                        "obj",
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

/// A `[N, 3]` tensor of `dtype` on `device` from host points `[N][3]`.
///
/// # Errors
/// A coordinate that is not finite in `dtype` (1e300 overflows f32 to infinity), naming
/// `points` and the point; candle's.
pub fn points_tensor(points: &[[f64; 3]], device: &Device, dtype: DType) -> Result<Tensor> {
    let flat: Vec<f64> = points.iter().flatten().copied().collect();
    let t = Tensor::from_vec(flat, (points.len(), 3), &Device::Cpu)?.to_dtype(dtype)?;
    if !points.is_empty() {
        let back: Vec<f64> = t.to_dtype(DType::F64)?.flatten_all()?.to_vec1()?;
        if let Some(i) = back.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                "points",
                format!("coordinates that are finite in {dtype:?}"),
                format!("point {} = {:?}", i / 3, points[i / 3]),
            ));
        }
    }
    Ok(t.to_device(device)?)
}

/// Refuses UTF-16 text (a byte-order mark, or NUL bytes among the first kilobyte, which
/// ASCII and UTF-8 text never holds), naming the encoding: read lossily as UTF-8 it
/// would parse as an empty mesh.
pub(crate) fn check_not_utf16(what: &'static str, bytes: &[u8]) -> Result<()> {
    let bom = bytes.starts_with(&[0xFF, 0xFE]) || bytes.starts_with(&[0xFE, 0xFF]);
    if bom || bytes.iter().take(1024).any(|&b| b == 0) {
        return Err(file_err(
            what,
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
