//! NeRF volume rendering: samplers along rays, compositing samples into pixels, the
//! occupancy grid that skips empty space, and regularisers.
//!
//! One training step, in the batched layout:
//!
//! ```
//! use candle_core::{DType, Device, Tensor, Var};
//! use neural_fields::camera::Rays;
//! use neural_fields::volume::{composite, stratified, CompositeConfig, Jitter};
//!
//! let dev = Device::Cpu;
//! let rays = Rays::new(
//!     Tensor::new(&[[0.0f32, 0.0, -2.0], [0.3, 0.0, -2.0]], &dev)?,
//!     Tensor::new(&[[0.0f32, 0.0, 1.0], [0.0, 0.0, 1.0]], &dev)?,
//! )?;
//! let (near, far) = (Tensor::new(&[1.0f32, 1.0], &dev)?, Tensor::new(&[3.0f32, 3.0], &dev)?);
//! let intervals = stratified(&near, &far, 32, Jitter::PerSample, 7)?;   // [R, S] = [2, 32]
//! let points = intervals.positions(&rays)?;                             // [2, 32, 3]
//! // A "field": density 5 inside the unit ball, a learnable colour everywhere.
//! let inside = points.sqr()?.sum(2)?.lt(1.0)?.to_dtype(DType::F32)?;
//! let sigmas = (inside * 5.0)?;                                         // [2, 32]
//! let rgb = Var::zeros((1, 1, 3), DType::F32, &dev)?;
//! let colors = rgb.as_tensor().broadcast_as((2, 32, 3))?.contiguous()?;
//! let out = composite(&sigmas, &colors, &intervals, Some(&rays), &CompositeConfig::default())?;
//! let loss = (out.color - 1.0)?.sqr()?.mean_all()?;                    // target: white
//! let grads = loss.backward()?;
//! assert!(grads.get(rgb.as_tensor()).is_some());
//! # Ok::<(), neural_fields::Error>(())
//! ```
//!
//! What is here, all at this module's root:
//! - samplers: [`stratified`] intervals, importance samples from the coarse weights
//!   ([`sample_pdf`]), [`merge_sorted`], RegNeRF's annealed near/far
//!   ([`anneal_near_far`]);
//! - cone casting (mip-NeRF): [`conical_frustums`], the Gaussian of each interval's
//!   conical frustum, for [`crate::encoding::integrated_pe`];
//! - [`Intervals`] in the batched `[R, S]` or packed `[M]` [`Layout`] ([`Packed`]),
//!   their midpoints, lengths and positions;
//! - compositing: [`composite()`], [`render_weights`], [`accumulate`] — one function per
//!   operation, either layout; the fused CPU kernel runs on the CPU, candle ops elsewhere;
//! - the [`OccupancyGrid`] estimator, whose [`OccupancyGrid::sample`] emits samples only
//!   in occupied cells, in the packed layout, and given a density function only those
//!   that are visible and not empty;
//! - scene contraction (mip-NeRF 360): [`contract`] of points or (linearised) of
//!   Gaussians, for unbounded scenes;
//! - proposal-network sampling (mip-NeRF 360, [`proposal_sample`]) and its
//!   [`interlevel_loss`];
//! - regularisers: [`distortion_loss`], [`depth_smoothness`] (the trunc-exp density
//!   activation is [`crate::numerics::trunc_exp`]);
//! - [`Nerf`] / [`nerf`]: NeRF's radiance field (density trunk, view-dependent colour
//!   head, both [`crate::nn::Mlp`]s) with its fused training loss
//!   [`Nerf::color_loss`];
//! - [`render_image`]: a whole image from any per-ray renderer, in chunks, supersampled
//!   through the camera's pixel filter.
//!
//! See `docs/math.md`, section "Volume compositing", for the derivations.

mod compositing;
mod cone;
mod contraction;
mod fused;
mod grid;
mod layout;
mod nerf_model;
mod proposal;
mod reference;
mod regularizers;
mod render;
mod sampling;

pub use crate::kernels::X_MAX;
pub use compositing::{
    accumulate, composite, render_weights, visible_mask, Composite, CompositeConfig,
    DEFAULT_TERMINATION_EPS,
};
pub use cone::{conical_frustums, Covariance, Gaussians};
pub use contraction::contract;
pub use grid::{GridConfig, GridMarchConfig, GridSamples, OccupancyGrid};
pub use layout::{Intervals, Layout, Packed, Weights};
pub use nerf_model::{nerf, ColorLoss, DensityActivation, Nerf, NerfConfig};
pub use proposal::{interlevel_loss, proposal_sample, ProposalConfig, ProposalSamples, Spacing};
pub use regularizers::{depth_smoothness, distortion_loss, log_linear_schedule};
pub use render::{render_image, ImageConfig};
pub use sampling::{
    anneal_near_far, merge_sorted, sample_pdf, stratified, DensityFn, Jitter, ANNEAL_MID_RATIO,
    ANNEAL_P_START, PDF_PADDING,
};
