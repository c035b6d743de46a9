//! Occupancy networks (Mescheder et al. 2019): meshes and their files, marching cubes,
//! Multiresolution IsoSurface Extraction (MISE), the ONet metrics, training losses and
//! point samplers.
//!
//! * [`mesh`]: [`Mesh`] with validation, PLY (ASCII and binary) and OBJ
//!   read/write, unit-cube normalisation, area-weighted surface sampling.
//! * [`mod@marching_cubes`]: watertight, consistently oriented marching cubes over a dense
//!   grid of values.
//! * [`mod@mise`]: coarse-to-fine extraction of the level set of any
//!   [`ImplicitSurface`](crate::field::ImplicitSurface), evaluating the field only near
//!   the surface.
//! * [`metrics`]: IoU, Chamfer-L1, normal consistency and F-score with ONet's conventions.
//! * [`losses`]: BCE summed over points and averaged over shapes, KL to `N(0, I)` and the
//!   reparameterised sample.
//! * [`sampling`]: uniform, near-surface and labelled samples (generalised winding
//!   number inside test, robust to small holes).

pub mod losses;
pub mod marching_cubes;
pub mod mesh;
pub mod metrics;
pub mod mise;
pub mod sampling;

pub use marching_cubes::{marching_cubes, Grid};
pub use mesh::{Mesh, PlyFormat};
pub use metrics::{iou, mesh_metrics, surface_metrics, KdTree, SurfaceMetrics};
pub use mise::{logit_threshold, mise, MiseConfig, MiseOutput};
