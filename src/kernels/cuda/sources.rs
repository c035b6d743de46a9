//! The CUDA C sources of the fused ops, one per operation. Each is compiled with
//! `typedef float real;` or `typedef double real;` and the helpers of the module's
//! prelude in front (see `super::function`).

/// softplus, σ(βx) and trunc-exp (numerics.rs).
pub(crate) const ACTIVATION: &str = include_str!("activation.cu");

/// Volume compositing, forward and backward, both layouts (kernels/composite.rs).
pub(crate) const COMPOSITE: &str = include_str!("composite.cu");

/// The frequency encoding with `2ᵏπ`, forward and backward (kernels/frequency.rs).
pub(crate) const FREQUENCY: &str = include_str!("frequency.cu");

/// mip-NeRF's integrated positional encoding, forward and backward
/// (kernels/integrated.rs).
pub(crate) const INTEGRATED: &str = include_str!("integrated.cu");

/// The multiresolution hash encoding: forward, table and position gradients
/// (kernels/hash_grid.rs).
pub(crate) const HASH_GRID: &str = include_str!("hash_grid.cu");

/// Bilinear/trilinear grid sampling: forward, feature and coordinate gradients
/// (kernels/grid_sample.rs).
pub(crate) const GRID_SAMPLE: &str = include_str!("grid_sample.cu");

/// Scatter-max pooling: the argmax by two atomic passes, forward and backward
/// (kernels/scatter.rs).
pub(crate) const SCATTER: &str = include_str!("scatter.cu");

/// NeRF's photometric loss: encodings, bias and activation passes, per-ray compositing
/// and loss with their backward pass (kernels/nerf_loss.rs).
pub(crate) const NERF_LOSS: &str = include_str!("nerf_loss.cu");

/// Adam's moment and parameter passes, in place (kernels/adam.rs).
pub(crate) const ADAM: &str = include_str!("adam.cu");
