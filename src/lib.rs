//! Differentiable neural-field primitives on candle.
#![deny(missing_docs)]

pub mod encoding;
pub mod error;
pub mod field;
pub mod nn;
pub mod numerics;
pub mod rng;
#[cfg(feature = "volume")]
pub mod volume;

pub use error::{Error, Result};
