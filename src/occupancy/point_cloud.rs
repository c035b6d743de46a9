//! Point clouds: positions with optional normals and colours, as scanners produce them
//! and as the encoders of Occupancy Networks and Texture Fields take them.
//!
//! A [`PointCloud`] is valid by construction: its fields are private, and every
//! constructor checks that there is at least one point, that every coordinate and
//! normal is finite, and that colours lie in `[0, 1]`, one per point.
//!
//! ```
//! use candle_core::{DType, Device};
//! use neural_fields::occupancy::{MeshFormat, PointCloud};
//!
//! let cloud = PointCloud::new(vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])?
//!     .with_normals(vec![[0.0, 0.0, 1.0]; 3])?;
//! let back = PointCloud::from_bytes(&cloud.to_bytes(MeshFormat::PlyBinary)?, MeshFormat::PlyBinary)?;
//! assert_eq!(back, cloud);
//! // ONet-style encoder input: a fixed number of points per shape, as a batch of one.
//! let input = cloud.sample(300, 0)?.to_tensor(&Device::Cpu, DType::F32)?.unsqueeze(0)?;
//! assert_eq!(input.dims(), &[1, 300, 3]);
//! # Ok::<(), neural_fields::Error>(())
//! ```

use super::mesh::{points_tensor, MeshFormat};
use super::{off, ply};
use crate::error::{Error, Result};
use crate::rng::SplitMix64;
use candle_core::{DType, Device, Tensor};
use std::path::Path;

/// Points `[N][3]` (N ≥ 1) with optional per-point normals and colours; see the
/// [module documentation](self).
#[derive(Clone, Debug, PartialEq)]
pub struct PointCloud {
    points: Vec<[f64; 3]>,
    normals: Option<Vec<[f64; 3]>>,
    colors: Option<Vec<[f64; 3]>>,
}

/// Checks positions and their optional normals and colours, naming `arg` and each
/// element `noun i`: at least one position, every coordinate and normal component
/// finite, one normal and one colour per position, colour components in `[0, 1]`.
pub(crate) fn check_points(
    arg: &'static str,
    [noun, nouns]: [&str; 2],
    points: &[[f64; 3]],
    normals: Option<&[[f64; 3]]>,
    colors: Option<&[[f64; 3]]>,
) -> Result<()> {
    let n = points.len();
    if let Some(i) = points.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
        return Err(Error::invalid(
            arg,
            format!("finite {noun} coordinates"),
            format!("{noun} {i} = {:?} (NaN or infinite)", points[i]),
        ));
    }
    if let Some(nr) = normals {
        if nr.len() != n {
            return Err(Error::invalid(
                arg,
                format!("one normal per {noun}"),
                format!("{} normals for {n} {nouns}", nr.len()),
            ));
        }
        if let Some(i) = nr.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
            return Err(Error::invalid(
                arg,
                "finite normals",
                format!("normal {i} = {:?}", nr[i]),
            ));
        }
    }
    if let Some(col) = colors {
        if col.len() != n {
            return Err(Error::invalid(
                arg,
                format!("one entry of colors per {noun}"),
                format!("{} colors for {n} {nouns}", col.len()),
            ));
        }
        let in_unit = |c: &f64| (0.0..=1.0).contains(c); // false for NaN
        if let Some(i) = col.iter().position(|v| !v.iter().all(in_unit)) {
            return Err(Error::invalid(
                arg,
                "colors with finite components in [0, 1]",
                format!("colors[{i}] = {:?}", col[i]),
            ));
        }
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

impl PointCloud {
    /// A point cloud of `points` (at least one, finite), without normals or colours.
    ///
    /// # Errors
    /// No points, or a non-finite coordinate (naming `points` and the point).
    pub fn new(points: Vec<[f64; 3]>) -> Result<Self> {
        if points.is_empty() {
            return Err(Error::invalid("points", "at least one point", "none"));
        }
        check_points("points", ["point", "points"], &points, None, None)?;
        Ok(Self {
            points,
            normals: None,
            colors: None,
        })
    }

    /// The cloud with per-point `normals` (finite, one per point; not required to be
    /// unit vectors: scanners store them as they are).
    ///
    /// # Errors
    /// A count other than the point count or a non-finite component (naming `normals`).
    pub fn with_normals(mut self, normals: Vec<[f64; 3]>) -> Result<Self> {
        check_points(
            "normals",
            ["point", "points"],
            &self.points,
            Some(&normals),
            None,
        )?;
        self.normals = Some(normals);
        Ok(self)
    }

    /// The cloud with per-point `colors` (RGB, components in `[0, 1]`, one per point).
    ///
    /// # Errors
    /// A count other than the point count or a component outside `[0, 1]` or NaN
    /// (naming `colors`).
    pub fn with_colors(mut self, colors: Vec<[f64; 3]>) -> Result<Self> {
        check_points(
            "colors",
            ["point", "points"],
            &self.points,
            None,
            Some(&colors),
        )?;
        self.colors = Some(colors);
        Ok(self)
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

    /// The number of points `N` (at least 1).
    #[must_use]
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Always `false`: a point cloud holds at least one point.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// `n` points of the cloud with their normals and colours, drawn uniformly: without
    /// replacement when `n ≤ N` (a random subset in random order), with replacement
    /// beyond (ONet feeds its encoder a fixed number of points, 300, per shape). Same
    /// `seed`, same points.
    ///
    /// # Errors
    /// `n = 0`, or more points than can be allocated (naming `n`).
    pub fn sample(&self, n: usize, seed: u64) -> Result<PointCloud> {
        if n == 0 {
            return Err(Error::invalid("n", "at least one point", "0"));
        }
        let mut idx: Vec<usize> = Vec::new();
        idx.try_reserve_exact(n).map_err(|_| {
            Error::invalid("n", "a number of points that fits in memory", n.to_string())
        })?;
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

    /// The positions as a `[N, 3]` tensor of `dtype` on `device` (add a batch axis with
    /// `unsqueeze(0)` for the encoders, which take `[B, N, 3]`).
    ///
    /// # Errors
    /// candle's (an unsupported dtype).
    pub fn to_tensor(&self, device: &Device, dtype: DType) -> Result<Tensor> {
        points_tensor(&self.points, device, dtype)
    }

    /// The normals as a `[N, 3]` tensor (the per-point features of Texture Fields'
    /// shape encoder, `PointNetEncoder::forward_features` with `point_features: 3`).
    ///
    /// # Errors
    /// A cloud without normals (naming `normals`); candle's.
    pub fn normals_tensor(&self, device: &Device, dtype: DType) -> Result<Tensor> {
        let n = self
            .normals
            .as_ref()
            .ok_or_else(|| Error::invalid("normals", "a point cloud with normals", "none"))?;
        points_tensor(n, device, dtype)
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
        let bytes = super::mesh::read_file(path)?;
        Self::from_bytes(&bytes, format).map_err(|e| super::mesh::in_file(e, path))
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
        super::mesh::write_file(path, &self.to_bytes(format)?)
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
                let c = super::mesh::parse_obj(bytes)?;
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
