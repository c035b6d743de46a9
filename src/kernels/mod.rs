//! The crate's fused CPU kernels, one operation per file, below every module that uses
//! them (kernels import only `numerics`, `error`, `narrow` and candle; the modules above
//! pass their own types in through plain data and the traits defined here):
//!
//! * `mlp`: an MLP's every layer on a tile of points in one pass, forward and backward
//!   (`FusedMlp`, what [`crate::nn::Mlp`] runs on the CPU), and the layer plan it runs;
//! * `mlp_tangents`: the same MLP with forward-mode tangents (`FusedMlpJvp`, for
//!   [`crate::nn::Mlp::forward_with_jacobian`]);
//! * `nerf`: NeRF's density trunk and colour head as one op (`FusedNerf`);
//! * `nerf_loss`: NeRF's photometric loss, compositing included, as one op that computes
//!   its parameter gradient in the forward pass (`FusedNerfLoss`, with `RowEncode`, the
//!   encodings it evaluates inside its tiles);
//! * `hash_grid`: instant-NGP's multiresolution hash encoding (`FusedHashGrid`, what
//!   [`crate::encoding::HashGrid`] runs on the CPU), with the level geometry (`HashPlan`)
//!   its reference path shares;
//! * `grid_sample`: bilinear/trilinear sampling of feature planes and grids
//!   (`FusedGridSample`, for [`crate::encoding::grid_sample`]), with the sampling
//!   geometry (`GridGeometry`) its reference path shares;
//! * `scatter`: scatter-max pooling of point features into cells (`FusedScatterMax`, for
//!   [`crate::encoding::scatter`] with [`crate::encoding::Pooling::Max`]), which keeps the
//!   u32 cell index in the op's value;
//! * `frequency`: the frequency positional encoding with `2ᵏπ` (`FusedFrequency`, what
//!   [`crate::encoding::FrequencyEncoding`] runs on the CPU), whose rows the NeRF loss
//!   also evaluates inside its tiles;
//! * `integrated`: mip-NeRF's integrated positional encoding of rows `[μ, σ²]`
//!   (`FusedIntegrated`, what [`crate::encoding::integrated_pe`] runs on the CPU), on the
//!   frequency kernel's vectorised sines;
//! * `composite`: volume compositing of either sample layout with its O(S)-per-ray
//!   backward (`FusedComposite`), built for three instruction sets;
//! * `onet` and `cond_norm`: the ONet decoder's whole training pass (`FusedOnet`: every
//!   layer's product, bias, conditional batch norm, ReLU and residual sum, what
//!   [`crate::occupancy::OnetDecoder`] runs on the CPU in training) and its conditional
//!   batch norm with ReLU (`FusedCondNorm`), with the backward pass through the batch
//!   statistics, which with one group is plain batch norm (`FusedBatchNorm`, the image
//!   encoder's on the CPU);
//! * `conv`: a convolution of channels-last 3-D grids or 2-D images with its bias and an
//!   optional ReLU on its input (`FusedConv`, the image encoder's convolutions on the
//!   CPU), tile by tile without the full window matrix, and a chain of them as one op
//!   (`FusedConvStack`, the voxel encoder's);
//! * `pool`: `BufferPool`, the buffers a fused op's caller keeps between calls (the ONet
//!   decoder's rows, the voxel encoder's grids, the image encoder's weight matrices) so
//!   that no step faults them in afresh;
//! * `adam`: Adam's update as two in-place passes per variable (`AdamMoments`,
//!   `AdamUpdate`, what [`crate::nn::Adam`] runs);
//! * `activation` and `simd`: the vectorised hidden activations (ReLU, softplus with its
//!   slope and curvature) and the AVX-512 f32 matrix product of the MLP tiles;
//! * `parallel`: [`for_each_init`], which runs a kernel's items on candle's own CPU pool,
//!   and `wide`, which runs a loop compiled for AVX-512 or AVX2 where the CPU has them;
//! * `dispatch`: the candle side of every op, written once (below).
//!
//! Each kernel's reference path, made of candle ops and running on any device, stays
//! beside the operation in its module (e.g. `volume`'s compositing reference, the
//! `force_reference` paths of [`crate::nn::Mlp`] and of the encodings); the tests compare
//! every kernel with it.
//!
//! # Writing a kernel: the dispatch helper
//! A kernel is a type holding the op's shapes and settings that implements
//! [`CpuKernel<N>`] for its `N` float inputs (all f32 or all f64, every input handed over
//! as its contiguous elements):
//!
//! ```text
//! impl CpuKernel<2> for MyOp {
//!     const NAME: &'static str = "my op";             // names the op in errors
//!     fn forward<T: Real>(&self, [x, t]: [&[T]; 2])   // check lengths, compute
//!         -> candle_core::Result<(Vec<T>, Shape)> { … }
//!     fn backward<T: Real>(&self, [x, t]: [&[T]; 2], g: &[T], want: [bool; 2])
//!         -> candle_core::Result<[Option<Vec<T>>; 2]> { … }   // None where !want[i]
//! }
//! cpu_op!(MyOp, 2, "nf-my-op");                        // impl CustomOp2 for MyOp
//! ```
//!
//! [`cpu_op!`](cpu_op) writes `impl CustomOp1/2/3` whose `cpu_fwd` is [`cpu_fwd`]
//! (contiguity check, f32/f64 dispatch, the storage's slices, the result's storage) and
//! whose `bwd` is [`cpu_bwd`] (the inputs' and the contiguous gradient's CPU slices in the
//! inputs' dtype, `want[i]` = whether input `i` is part of the autograd graph, each
//! returned gradient as a tensor of its input's shape). An op whose backward pass is not
//! a function of its inputs (the NeRF loss keeps the gradient its forward pass computed)
//! implements `forward` only and writes its own `bwd`, still calling [`cpu_fwd`]. An op
//! with an input that is not f32/f64 (an index) keeps that input in the op's value or
//! reads it with [`cpu_slice`]; [`contiguous`] gives the element ranges of layouts.
//! Every kernel's scratch lives in per-worker state of [`for_each_init`], so no kernel
//! allocates per item.

mod activation;
mod adam;
#[cfg_attr(not(feature = "volume"), allow(dead_code))]
mod composite;
#[cfg_attr(not(feature = "occupancy"), allow(dead_code))]
mod cond_norm;
#[cfg_attr(not(feature = "occupancy"), allow(dead_code))]
mod conv;
#[cfg(feature = "cuda")]
pub(crate) mod cuda;
mod dispatch;
mod frequency;
mod grid_sample;
mod hash_grid;
mod integrated;
mod mlp;
mod mlp_tangents;
#[cfg_attr(not(feature = "volume"), allow(dead_code))]
mod nerf;
#[cfg_attr(not(feature = "volume"), allow(dead_code))]
mod nerf_loss;
#[cfg_attr(not(feature = "occupancy"), allow(dead_code))]
mod onet;
mod parallel;
#[cfg_attr(not(feature = "occupancy"), allow(dead_code))]
mod pool;
mod scatter;
#[cfg(target_arch = "x86_64")]
mod simd;

pub(crate) use activation::Act;
pub(crate) use adam::{AdamMoments, AdamUpdate};
// The compositing and NeRF kernels serve the `volume` feature.
#[cfg_attr(not(feature = "volume"), allow(unused_imports))]
pub use composite::X_MAX;
#[cfg_attr(not(feature = "volume"), allow(unused_imports))]
pub(crate) use composite::{FusedComposite, Geometry, KernelBuild, Segments};
#[cfg_attr(not(feature = "occupancy"), allow(unused_imports))]
pub(crate) use cond_norm::FusedBatchNorm;
#[cfg_attr(not(feature = "occupancy"), allow(unused_imports))]
pub(crate) use conv::{FusedConv, FusedConvStack};
#[allow(unused_imports)] // the dispatch helper's whole interface, for every kernel
pub(crate) use dispatch::{contiguous, cpu_bwd, cpu_fwd, cpu_op, cpu_slice, CpuKernel, Real};
#[cfg(feature = "cuda")]
pub(crate) use dispatch::{cuda_bwd, cuda_fwd, CudaKernel};
pub(crate) use frequency::{FusedFrequency, Trig};
pub(crate) use grid_sample::{FusedGridSample, GridCorners, GridGeometry};
pub(crate) use hash_grid::{FusedHashGrid, HashCorners, HashLevel, HashPlan};
pub(crate) use integrated::FusedIntegrated;
pub(crate) use mlp::{FusedMlp, LayerPlan};
pub(crate) use mlp_tangents::FusedMlpJvp;
#[cfg_attr(not(feature = "volume"), allow(unused_imports))]
pub(crate) use nerf::FusedNerf;
#[cfg_attr(not(feature = "volume"), allow(unused_imports))]
pub(crate) use nerf_loss::{Density, FusedNerfLoss, RowEncode};
#[cfg_attr(not(feature = "occupancy"), allow(unused_imports))]
pub(crate) use onet::FusedOnet;
#[cfg_attr(not(feature = "occupancy"), allow(unused_imports))]
pub(crate) use pool::BufferPool;
// Outside the kernels, only `volume` runs its own items on the pool.
#[cfg_attr(not(feature = "volume"), allow(unused_imports))]
pub(crate) use parallel::for_each_init;
pub(crate) use scatter::FusedScatterMax;

/// Whether the fused kernels run on `device`: always on the CPU; on CUDA when the crate
/// is built with the `cuda` feature (unless `NEURAL_FIELDS_CUDA_KERNELS=0`).
pub(crate) fn fused_on(device: &candle_core::Device) -> bool {
    #[cfg(feature = "cuda")]
    if device.is_cuda() {
        return cuda::enabled();
    }
    device.is_cpu()
}

/// Whether the fused kernels take `t`: f32 or f64, on a device they run on
/// ([`fused_on`]).
pub(crate) fn fused_for(t: &candle_core::Tensor) -> bool {
    fused_on(t.device()) && is_real(t)
}

/// Whether a kernel that exists only for the CPU takes `t`: f32 or f64 on the CPU.
#[cfg_attr(not(feature = "occupancy"), allow(dead_code))]
pub(crate) fn cpu_fused_for(t: &candle_core::Tensor) -> bool {
    t.device().is_cpu() && is_real(t)
}

fn is_real(t: &candle_core::Tensor) -> bool {
    matches!(t.dtype(), candle_core::DType::F32 | candle_core::DType::F64)
}
