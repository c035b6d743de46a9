//! Triangle meshes: validation, geometry (areas, normals, signed volume, bounds),
//! normalisation to the unit cube, area-weighted surface sampling, the topological checks
//! (watertight, oriented) used by the marching-cubes tests, and reading and writing in
//! every [`MeshFormat`].
//!
//! Vertices are `f64` on the host (meshes are inputs and outputs of the pipeline, not
//! part of a gradient); [`points_to_tensor`](super::points_to_tensor) moves them to any
//! device and dtype.
//!
//! Files written here load in standard tools: `assimp info` (assimp 5.2.5, Debian's
//! `assimp-utils`) imports the binary PLY written by `examples/fit_occupancy.rs`
//! (15 454 vertices, 30 896 triangles) and by `examples/quickstart.rs`; the format is the
//! plain `float x y z` + `list uchar int vertex_indices` layout that MeshLab, Blender and
//! trimesh read, with `uchar red green blue` vertex colours when the mesh has them. The
//! tests read every format back.

use super::io::{check_f32_range, in_file, obj, off, ply, read_file, stl, write_file};
use super::io::{MeshFormat, Polygons};
use super::points::check_points;
use super::triangulate::triangulate;
use super::vector::{cross, dot, norm, sub};
use crate::error::{Error, Result};
use crate::rng::SplitMix64;
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

    /// Checks the mesh: at least one vertex and one face, every face index `< V`, every
    /// coordinate (and normal component) finite, normals (if any) one per vertex, colours
    /// (if any) one per vertex with every component finite and in `[0, 1]`. The fields
    /// are public: set normals or colours, then validate (the writers validate too).
    ///
    /// ```
    /// use neural_fields::mesh::Mesh;
    ///
    /// let mut tri = Mesh::new(vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], vec![[0, 1, 2]])?;
    /// tri.colors = Some(vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
    /// tri.validate()?;
    /// tri.colors = Some(vec![[2.0, 0.0, 0.0]; 3]);
    /// assert!(tri.validate().is_err());
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
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
    pub(crate) fn face_areas(&self) -> Result<Vec<f64>> {
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
    pub(crate) fn face_normals(&self) -> Result<Vec<[f64; 3]>> {
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
    /// `(centre, scale)` with `p_new = (p − centre)·scale` (up to rounding).
    ///
    /// The centre and the half extent are formed as `lo/2 + hi/2` and `hi/2 − lo/2`, and
    /// each vertex as `(p − centre)/half · ½`, so that no intermediate overflows: a mesh
    /// spanning ±1e308 (whose extent `hi − lo` is +∞ in f64) is normalised like any other.
    ///
    /// # Errors
    /// An invalid mesh (NaN or ±∞ vertices are refused by [`Mesh::validate`]), all vertices
    /// at one point, or a box so small (a subnormal extent) that its scale `1/extent` is
    /// not finite; the mesh is unchanged then.
    pub fn normalize_unit_cube(&mut self) -> Result<([f64; 3], f64)> {
        self.validate()?;
        let (lo, hi) = self.bounds();
        let centre: [f64; 3] = std::array::from_fn(|c| 0.5 * lo[c] + 0.5 * hi[c]);
        let half = (0..3)
            .map(|c| 0.5 * hi[c] - 0.5 * lo[c])
            .fold(0.0, f64::max);
        if half <= 0.0 {
            return Err(mesh_err(
                "vertices spanning a box of positive size",
                "all vertices at one point",
            ));
        }
        let s = 0.5 / half;
        if !s.is_finite() {
            return Err(mesh_err(
                "a box whose scale 1/extent is finite",
                format!("an extent of {:e}", 2.0 * half),
            ));
        }
        for v in &mut self.vertices {
            for c in 0..3 {
                v[c] = (v[c] - centre[c]) / half * 0.5;
            }
        }
        Ok((centre, s))
    }

    /// Counts `(boundary, non-manifold, misoriented)` edges: undirected edges used by one
    /// face, by more than two faces, and edges whose two faces traverse them in the same
    /// direction (inconsistent orientation). A mesh with faces and `(0, 0, 0)` is
    /// watertight and consistently oriented (closed, manifold along edges).
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

    /// `n` points drawn uniformly on the surface (faces chosen with probability
    /// proportional to area, then uniform barycentric coordinates `(1 − √u, √u(1 − v),
    /// √u v)`), with the unit normals of their faces. Same `seed`, same points.
    ///
    /// # Errors
    /// Invalid mesh (non-finite vertices included), or zero total area; naming `n` when
    /// `n` samples (48 bytes each) pass the allocation limit of 2³³ bytes (8 GiB), checked
    /// before anything is allocated.
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
        // A count past the allocation limit is an error, not an abort: a point and a
        // normal, 48 bytes a sample.
        crate::limits::check_bytes("n", &[n], 48)?;
        let (mut pts, mut nrm) = (Vec::with_capacity(n), Vec::with_capacity(n));
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
    /// each extension reads every encoding of its format; see [`Mesh::from_bytes`]).
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
    /// use neural_fields::mesh::{Mesh, MeshFormat};
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
            MeshFormat::Obj => obj::write(v, self.normals.as_deref(), f),
            MeshFormat::StlAscii => stl::write(v, f, false),
            MeshFormat::StlBinary => stl::write(v, f, true),
            MeshFormat::Off => off::write(v, c, f),
        })
    }

    /// Parses a mesh file's bytes in `format` (PLY in any encoding, OBJ, STL in either
    /// encoding, OFF).
    ///
    /// - PLY (ASCII, binary little- or big-endian): reads `element vertex` (`x, y, z`,
    ///   optional `nx, ny, nz`, optional colours `red, green, blue` when all three are
    ///   present; any other properties, `alpha` among them, are skipped) and
    ///   `element face` (a list property named `vertex_indices` or `vertex_index`, any
    ///   count and index types). Other elements are skipped.
    /// - OBJ: `v` (extra components such as `w` or colours ignored), `vn`, and `f` with
    ///   `a`, `a/b`, `a//c` or `a/b/c` references, 1-based or negative (relative).
    ///   Other statements (`vt`, `o`, `g`, `usemtl`,
    ///   `mtllib`, `s`, `l`, `p`) are ignored. Normals are kept only when every face
    ///   corner names the normal with the same index as its vertex (as
    ///   [`Mesh::to_bytes`] writes them); otherwise they are dropped. Invalid UTF-8 is
    ///   replaced; UTF-16 text is refused with an error naming the encoding.
    ///
    /// - STL: facets welded into shared vertices (corners with bit-identical
    ///   coordinates); the stored facet normals are ignored.
    /// - OFF: `OFF`, `COFF`, `NOFF` and `CNOFF`, with normals and colours when present.
    ///
    /// Polygons with more than three vertices are triangulated in their own plane: fans
    /// for convex polygons, ear clipping for concave ones; self-intersecting polygons are
    /// refused.
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
                let c = obj::read(bytes)?;
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
    fn from_polygons(
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
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A face index past the vertices is an error naming the mesh, not a panic; the
    /// valid prefix still works.
    #[test]
    fn face_areas_and_normals_name_the_mesh_for_an_out_of_range_index() {
        let mesh = Mesh {
            vertices: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            faces: vec![[0, 1, 2], [0, 2, 7]],
            normals: None,
            colors: None,
        };
        let names_mesh = |e: Error| match e {
            Error::InvalidArgument { arg, expected, got } => {
                assert_eq!(arg, "mesh");
                assert!(expected.contains("face indices"), "{expected}");
                assert!(
                    got.contains("face 1") && got.contains("vertex 7 of 3"),
                    "{got}"
                );
            }
            other => panic!("expected an error naming the mesh, got {other:?}"),
        };
        names_mesh(mesh.face_areas().unwrap_err());
        names_mesh(mesh.face_normals().unwrap_err());
        let ok = Mesh {
            faces: vec![[0, 1, 2]],
            ..mesh
        };
        assert_eq!(ok.face_areas().unwrap(), vec![0.5]);
        assert_eq!(ok.face_normals().unwrap(), vec![[0.0, 0.0, 1.0]]);
    }
}
