//! Differentiable neural-field primitives on candle.
#![deny(missing_docs)]

pub mod camera;
pub mod error;

pub use error::{Error, Result};
