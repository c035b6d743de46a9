//! Differentiable neural-field primitives on candle.
#![deny(missing_docs)]

pub mod error;
#[cfg(feature = "volume")]
pub mod volume;

pub use error::{Error, Result};
