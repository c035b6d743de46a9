//! NeRF volume rendering: samplers along rays, an occupancy-grid estimator that skips
//! empty space, and the regularisers used with volume rendering.
//!
//! The data path of one training step: rays → [`sampling`] (stratified, then importance
//! samples from the coarse weights; or [`grid::OccupancyGrid::sample`], which emits
//! samples only in occupied cells) → field at the samples → compositing → loss (+
//! [`regularizers`]).

pub mod grid;
pub mod regularizers;
pub mod sampling;
