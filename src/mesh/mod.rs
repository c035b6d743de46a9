//! Triangle meshes and point clouds on the host, their files and the conversion of
//! points to and from tensors. Always built: every feature that touches a surface
//! (occupancy networks, texture fields, DVR's evaluation) shares these types.
//!
//! * [`Mesh`]: vertices, triangles, optional per-vertex normals and colours; validation,
//!   face and vertex normals, areas, signed volume, bounds, unit-cube normalisation,
//!   area-weighted surface sampling ([`SurfaceSamples`]) and the topological checks
//!   (watertight, consistently oriented).
//! * [`PointCloud`]: points with optional normals and colours (PLY, OBJ and OFF files
//!   without faces, scanners' output), validated by construction.
//! * Files in every [`MeshFormat`]: PLY (ASCII and binary), OBJ, STL (ASCII and binary)
//!   and OFF, read and written by [`Mesh::load`], [`Mesh::save`], [`Mesh::from_bytes`],
//!   [`Mesh::to_bytes`] and their [`PointCloud`] twins. Every reader's work and memory are
//!   bounded by the file's size, whatever its header claims; polygons are triangulated in
//!   their own plane (fans for convex polygons, ear clipping for concave ones).
//! * [`points_to_tensor`] and [`points_from_tensor`]: host points `[N][3]` to a `[N, 3]`
//!   tensor of any device and dtype, and back.
//!
//! ```
//! use candle_core::{DType, Device};
//! use neural_fields::mesh::{points_from_tensor, points_to_tensor, Mesh, MeshFormat, PointCloud};
//!
//! // A tetrahedron, counter-clockwise seen from outside.
//! let v = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
//! let tet = Mesh::new(v, vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])?;
//! assert!(!tet.faces.is_empty() && tet.edge_report() == (0, 0, 0));
//! assert!((tet.signed_volume()? - 1.0 / 6.0).abs() < 1e-12);
//! let back = Mesh::from_bytes(&tet.to_bytes(MeshFormat::Off)?, MeshFormat::Off)?;
//! assert_eq!(back, tet);
//! // Points on its surface, as an encoder's input and back.
//! let (points, normals) = tet.sample_surface(100, 0)?;
//! let cloud = PointCloud::new(points, Some(normals), None)?;
//! let t = points_to_tensor(cloud.points(), &Device::Cpu, DType::F64)?; // [100, 3]
//! assert_eq!(points_from_tensor(&t)?, cloud.points());
//! # Ok::<(), neural_fields::Error>(())
//! ```

mod io;
mod point_cloud;
mod points;
mod triangle_mesh;
mod triangulate;
// The vector helpers serve `occupancy` too (marching cubes, samplers, metrics).
pub(crate) mod vector;

pub use io::MeshFormat;
pub use point_cloud::PointCloud;
pub use points::{points_from_tensor, points_to_tensor};
pub use triangle_mesh::{Mesh, SurfaceSamples};
