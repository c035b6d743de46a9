//! Fused CPU compositing op (placeholder: delegates to the reference path until the
//! kernel lands).

use super::composite::{
    composite_packed_reference, composite_reference, Composite, CompositeOptions, Packed,
};
use crate::error::Result;
use candle_core::Tensor;

/// Fused compositing (currently the reference path).
///
/// # Errors
/// As [`composite_reference`].
pub fn composite_fused(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    opts: &CompositeOptions,
) -> Result<Composite> {
    composite_reference(sigmas, colors, deltas, t_mids, opts)
}

/// Fused packed compositing (currently the reference path).
///
/// # Errors
/// As [`composite_packed_reference`].
pub fn composite_packed_fused(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    packed: &Packed,
    opts: &CompositeOptions,
) -> Result<Composite> {
    composite_packed_reference(sigmas, colors, deltas, t_mids, packed, opts)
}
