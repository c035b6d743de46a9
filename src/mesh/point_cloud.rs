//! Point clouds: positions with optional normals and colours, as scanners produce them
//! and as the encoders of Occupancy Networks and Texture Fields take them.

use super::io::{check_f32_range, in_file, obj, off, ply, read_file, write_file, MeshFormat};
use super::points::check_points;
use crate::error::{Error, Result};
use crate::rng::SplitMix64;
use std::path::Path;

/// Points `[N][3]` (N ≥ 1) with optional per-point normals and colours, as scanners
/// produce them and as the encoders of Occupancy Networks and Texture Fields take them.
///
/// A point cloud is valid by construction: its fields are private, and every
/// constructor checks that there is at least one point, that every coordinate and
/// normal is finite, and that colours lie in `[0, 1]`, one per point.
///
/// ```
/// use candle_core::{DType, Device};
/// use neural_fields::mesh::{points_to_tensor, MeshFormat, PointCloud};
///
/// let points = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
/// let cloud = PointCloud::new(points, Some(vec![[0.0, 0.0, 1.0]; 3]), None)?;
/// let back = PointCloud::from_bytes(&cloud.to_bytes(MeshFormat::PlyBinary)?, MeshFormat::PlyBinary)?;
/// assert_eq!(back, cloud);
/// // ONet-style encoder input: a fixed number of points per shape, as a batch of one.
/// let input = points_to_tensor(cloud.sample(300, 0)?.points(), &Device::Cpu, DType::F32)?;
/// let input = input.unsqueeze(0)?;
/// assert_eq!(input.dims(), &[1, 300, 3]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct PointCloud {
    points: Vec<[f64; 3]>,
    normals: Option<Vec<[f64; 3]>>,
    colors: Option<Vec<[f64; 3]>>,
}

impl PointCloud {
    /// A point cloud of `points` (at least one, finite) with optional per-point `normals`
    /// (finite, one per point; not required to be unit vectors: scanners store them as
    /// they are) and `colors` (RGB, components in `[0, 1]`, one per point).
    ///
    /// # Errors
    /// No points, or a non-finite coordinate (naming `points` and the point); a normal
    /// count other than the point count or a non-finite component (naming `normals`); a
    /// colour count other than the point count or a component outside `[0, 1]` or NaN
    /// (naming `colors`).
    pub fn new(
        points: Vec<[f64; 3]>,
        normals: Option<Vec<[f64; 3]>>,
        colors: Option<Vec<[f64; 3]>>,
    ) -> Result<Self> {
        if points.is_empty() {
            return Err(Error::invalid("points", "at least one point", "none"));
        }
        let nouns = ["point", "points"];
        check_points("points", nouns, &points, None, None)?;
        check_points("normals", nouns, &points, normals.as_deref(), None)?;
        check_points("colors", nouns, &points, None, colors.as_deref())?;
        Ok(Self {
            points,
            normals,
            colors,
        })
    }

    /// The positions `[N][3]`.
    #[must_use]
    pub fn points(&self) -> &[[f64; 3]] {
        &self.points
    }

    /// The normals `[N][3]`, if any.
    #[must_use]
    pub fn normals(&self) -> Option<&[[f64; 3]]> {
        self.normals.as_deref()
    }

    /// The colours `[N][3]` in `[0, 1]`, if any.
    #[must_use]
    pub fn colors(&self) -> Option<&[[f64; 3]]> {
        self.colors.as_deref()
    }

    /// `n` points of the cloud with their normals and colours, drawn uniformly: without
    /// replacement when `n ≤ N` (a random subset in random order), with replacement
    /// beyond (ONet feeds its encoder a fixed number of points, 300, per shape). Same
    /// `seed`, same points.
    ///
    /// # Errors
    /// `n = 0`, or `n` samples (80 bytes each) past the allocation limit of 2³³ bytes
    /// (8 GiB), checked before anything is allocated (naming `n`).
    pub fn sample(&self, n: usize, seed: u64) -> Result<PointCloud> {
        if n == 0 {
            return Err(Error::invalid("n", "at least one point", "0"));
        }
        // An index, a point, a normal and a colour: 80 bytes a sample at most.
        crate::limits::check_bytes("n", &[n], 80)?;
        let mut idx: Vec<usize> = Vec::with_capacity(n);
        let mut rng = SplitMix64::new(seed);
        let len = self.points.len();
        if n <= len {
            // A partial Fisher–Yates shuffle over a permutation of 0..N.
            let mut perm: Vec<usize> = (0..len).collect();
            for i in 0..n {
                let j = i + rng.below((len - i) as u64) as usize;
                perm.swap(i, j);
            }
            idx.extend_from_slice(&perm[..n]);
        } else {
            idx.extend((0..n).map(|_| rng.below(len as u64) as usize));
        }
        let pick = |v: &Vec<[f64; 3]>| idx.iter().map(|&i| v[i]).collect::<Vec<_>>();
        Ok(PointCloud {
            points: pick(&self.points),
            normals: self.normals.as_ref().map(pick),
            colors: self.colors.as_ref().map(pick),
        })
    }

    /// Reads a point cloud from a `.ply`, `.obj` or `.off` file (by extension,
    /// case-insensitive); see [`PointCloud::from_bytes`].
    ///
    /// # Errors
    /// I/O errors naming the path; an unknown extension; the errors of
    /// [`PointCloud::from_bytes`], as [`Error::Format`] naming the path.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let format = MeshFormat::from_path(path)?;
        let bytes = read_file(path)?;
        Self::from_bytes(&bytes, format).map_err(|e| in_file(e, path))
    }

    /// Writes the cloud as binary little-endian PLY (the only point-cloud format written);
    /// the extension must be `.ply`.
    ///
    /// # Errors
    /// Another extension; I/O errors naming the path.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        let format = match MeshFormat::from_path(path)? {
            MeshFormat::PlyAscii | MeshFormat::PlyBinary => MeshFormat::PlyBinary,
            other => {
                return Err(Error::invalid(
                    "path",
                    "a .ply file (point clouds are written as PLY)",
                    format!("{other:?}"),
                ))
            }
        };
        write_file(path, &self.to_bytes(format)?)
    }

    /// Parses a file's bytes in `format`: the vertices of a PLY (with `nx ny nz` and
    /// `red green blue` when present; extra properties such as `alpha` or scanners'
    /// `psz` are skipped), OBJ (`v` and, one per vertex, `vn`) or OFF file. Faces, if
    /// the file has any, are ignored: for points spread over a mesh's surface, use
    /// [`Mesh::sample_surface`](super::Mesh::sample_surface). The readers' bounds and
    /// checks are those of [`Mesh::from_bytes`](super::Mesh::from_bytes).
    ///
    /// # Errors
    /// STL (it holds triangles, not points); the readers' errors (truncation says how
    /// many rows were complete); a file without vertices.
    pub fn from_bytes(bytes: &[u8], format: MeshFormat) -> Result<Self> {
        let (points, normals, colors) = match format {
            MeshFormat::PlyAscii | MeshFormat::PlyBinary => {
                let c = ply::read(bytes)?;
                (c.vertices, c.normals, c.colors)
            }
            MeshFormat::Obj => {
                let c = obj::read(bytes)?;
                let normals = c.normals_by_count();
                (c.vertices, normals, None)
            }
            MeshFormat::Off => {
                let c = off::read(bytes)?;
                (c.vertices, c.normals, c.colors)
            }
            MeshFormat::StlAscii | MeshFormat::StlBinary => {
                return Err(Error::invalid(
                    "format",
                    "PLY, OBJ or OFF (STL holds triangles: read it with Mesh)",
                    format!("{format:?}"),
                ))
            }
        };
        if points.is_empty() {
            return Err(Error::invalid(
                "points",
                "a file with at least one vertex",
                "none",
            ));
        }
        check_points(
            "points",
            ["point", "points"],
            &points,
            normals.as_deref(),
            colors.as_deref(),
        )?;
        Ok(Self {
            points,
            normals,
            colors,
        })
    }

    /// The cloud as PLY (`element vertex` with `float x y z`, `nx ny nz` and
    /// `uchar red green blue` when present, no faces).
    ///
    /// # Errors
    /// A format other than PLY (naming `format`); a coordinate or normal beyond f32's
    /// range (naming `points` or `normals`).
    pub fn to_bytes(&self, format: MeshFormat) -> Result<Vec<u8>> {
        let binary = match format {
            MeshFormat::PlyAscii => false,
            MeshFormat::PlyBinary => true,
            other => {
                return Err(Error::invalid(
                    "format",
                    "PlyAscii or PlyBinary (point clouds are written as PLY)",
                    format!("{other:?}"),
                ))
            }
        };
        check_f32_range("points", "point", &self.points)?;
        check_f32_range("normals", "normal", self.normals().unwrap_or(&[]))?;
        Ok(ply::write(
            &self.points,
            self.normals.as_deref(),
            self.colors.as_deref(),
            None,
            binary,
        ))
    }
}
