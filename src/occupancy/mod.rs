//! Occupancy networks (Mescheder et al. 2019): marching cubes, Multiresolution
//! IsoSurface Extraction (MISE), the ONet metrics, training losses and point samplers.
//! The meshes and point clouds they produce and consume, and their files, are in
//! [`crate::mesh`].
//!
//! * [`marching_cubes`]: watertight, consistently oriented marching cubes over a dense
//!   [`Grid`] of values.
//! * [`mise`]: coarse-to-fine extraction of the level set of any
//!   [`ImplicitSurface`](crate::field::ImplicitSurface), evaluating the field only near
//!   the surface; [`refine_vertices`] moves its vertices onto the level set.
//! * Metrics: [`iou`], and Chamfer-L1, normal consistency and F-score with ONet's
//!   conventions ([`surface_metrics`], [`mesh_metrics`]).
//! * Losses: BCE summed over points and averaged over shapes
//!   ([`reconstruction_loss`]), KL to `N(0, I)` ([`kl_standard_normal`]) and the
//!   reparameterised sample ([`reparameterize`]).
//! * Samplers: uniform ([`uniform_in_padded_cube`]), near-surface ([`near_surface`]) and
//!   labelled samples ([`winding_numbers`]: `|w| > ½` is an inside test robust to small
//!   holes).
//! * The models, built on [`crate::nn`]'s blocks: [`OnetDecoder`] / [`onet_decoder`],
//!   the ONet decoder with conditional normalisation that is batch-independent at
//!   inference (and the plain [`SimpleDecoder`]); [`PointNetEncoder`] /
//!   [`pointnet_encoder`], the variational ONet's encoder `q_ψ(z | points, occupancies)`;
//!   [`ConvOnetEncoder`] / [`conv_onet_encoder`] and [`LocalDecoder`] /
//!   [`local_decoder`], Convolutional Occupancy Networks (local PointNet pooled into three
//!   feature planes or a grid, a 2-D or 3-D U-Net, a decoder of interpolated local
//!   features; the grid's U-Net convolves in 3-D with candle's 2-D convolution);
//!   [`ResnetEncoder`] / [`resnet_encoder`], the single-view ONet's image encoder
//!   (ResNet-18's layout at a reduced width, images to the code `c`);
//!   [`VoxelEncoder`] / [`voxel_encoder`], the voxel super-resolution ONet's 3-D CNN
//!   (a stride-1 and four stride-2 convolutions, 32³ occupancy grids to the code `c`).
//!
//! ```
//! use candle_core::{DType, Device};
//! use neural_fields::field::{SignedDistance, Torus};
//! use neural_fields::mesh::{Mesh, MeshFormat};
//! use neural_fields::occupancy::{mesh_metrics, mise, MiseConfig};
//!
//! // Any ImplicitSurface works: an analytic torus here, a trained `Mlp` in practice.
//! let torus = Torus::new([0.0; 3], 0.3, 0.1, &Device::Cpu, DType::F32)?.occupancy(10.0);
//! let out = mise(&torus, &MiseConfig::new(16, 2, &Device::Cpu, DType::F32))?; // 64³
//! assert!(!out.mesh.faces.is_empty() && out.mesh.edge_report() == (0, 0, 0));
//! assert!(out.evaluations < 65 * 65 * 65 / 4);
//! let bytes = out.mesh.to_bytes(MeshFormat::PlyBinary)?;
//! let back = Mesh::from_bytes(&bytes, MeshFormat::PlyBinary)?;
//! let m = mesh_metrics(&back, &out.mesh, 10_000, 0.01, 0)?;
//! assert!(m.chamfer_l1 < 0.01 && m.normal_consistency.is_some_and(|n| n > 0.95));
//! # Ok::<(), neural_fields::Error>(())
//! ```

mod conv_onet;
mod isosurface;
mod losses;
mod metrics;
mod multires;
mod onet;
mod pointnet;
mod resnet;
mod sampling;
mod voxel;

pub use conv_onet::{
    conv_onet_encoder, local_decoder, ConvOnetConfig, ConvOnetEncoder, FeatureLayout, LocalDecoder,
    LocalDecoderConfig, LocalFeatures, SceneField, UnetConfig,
};
pub use isosurface::{marching_cubes, Grid};
pub use losses::{kl_standard_normal, reconstruction_loss, reparameterize};
pub use metrics::{chamfer_icp, iou, mesh_metrics, surface_metrics, KdTree, SurfaceMetrics};
pub use multires::{logit_threshold, mise, refine_vertices, MiseConfig, MiseOutput, RefineConfig};
pub use onet::{
    onet_decoder, simple_decoder, NormMode, OnetConfig, OnetDecoder, SimpleDecoder,
    SimpleDecoderConfig, ONET_BLOCK,
};
pub use pointnet::{pointnet_encoder, PointNetConfig, PointNetEncoder};
pub use resnet::{resnet_encoder, ResnetEncoder, ResnetEncoderConfig};
pub use sampling::{near_surface, uniform_in_padded_cube, winding_numbers, WindingConfig};
pub use voxel::{voxel_encoder, VoxelEncoder, VoxelEncoderConfig};
