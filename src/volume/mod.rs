//! NeRF volume rendering: compositing samples along rays into pixels.
//!
//! The compositing half of this module turns per-sample densities σᵢ ≥ 0, interval
//! lengths δᵢ ≥ 0 and per-sample values (colours, depths) into per-ray results:
//!
//! - xᵢ = σᵢδᵢ, αᵢ = 1 − e^{−xᵢ} (computed as −expm1(−xᵢ)),
//! - Tᵢ = exp(−Σ_{j<i} xⱼ) by one exclusive sum in log space,
//! - wᵢ = Tᵢαᵢ, C = Σ wᵢcᵢ + (1 − Σ wᵢ)·c_bg.
//!
//! Two layouts are supported: batched `[R, S]` (every ray has `S` samples) and packed
//! `[M]` with per-ray offsets ([`composite::Packed`]), for rays with different sample
//! counts (including none).
//!
//! Two implementations agree to rounding: the reference path
//! ([`composite::composite_reference`]) from plain candle ops on any device and dtype, and
//! the fused CPU op ([`fused::composite_fused`]) with an O(S)-per-ray analytic backward.
//! [`composite::composite`] picks the fused op on CPU and the reference path elsewhere.
//!
//! Early termination ([`composite::visible_mask`]) marks samples whose transmittance
//! has fallen below ε, so that the caller can skip evaluating the field there.
//! [`activations`] holds the density activations (trunc-exp, softplus).
//!
//! See `docs/math.md`, section "Volume compositing", for the derivations.
//!
//! The sampling half: [`sampling`] (stratified intervals, importance samples from the
//! coarse weights, merge, annealed near/far), [`grid`] (an occupancy-grid estimator
//! whose [`grid::OccupancyGrid::sample`] emits samples only in occupied cells, in the
//! packed layout) and [`regularizers`] (distortion loss, depth smoothness).

pub mod activations;
pub mod composite;
pub mod fused;
pub mod grid;
pub mod regularizers;
pub mod sampling;
