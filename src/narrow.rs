//! `narrow` that stays readable on empty tensors (crate-private).
//!
//! candle's `narrow(dim, start, len)` with `start > 0` on a tensor that holds no elements
//! (a batch of zero rays or points) returns a view whose offset lies past its empty
//! storage; reading it (`to_vec*`, a contiguous copy) panics inside candle ("range start
//! index … out of range for slice of length 0"). An empty tensor has no values to skip,
//! so narrowing it at offset 0 gives the same (empty) result with an offset of 0, still
//! on the autograd graph. Every split of a batch-sized result along a non-batch axis goes
//! through [`narrow`].

use candle_core::{shape::Dim, Result, Tensor};

/// `t.narrow(dim, start, len)`, readable when `t` is empty (see the module docs).
pub(crate) fn narrow<D: Dim>(t: &Tensor, dim: D, start: usize, len: usize) -> Result<Tensor> {
    if t.elem_count() == 0 {
        t.narrow(dim, 0, len)
    } else {
        t.narrow(dim, start, len)
    }
}

/// `Tensor::from_vec(v, shape, device)` that also holds for an empty `v` on a GPU: a
/// copy of zero bytes from the host is not a valid CUDA copy, so an empty result is made
/// with `Tensor::zeros` instead (the same empty tensor on the CPU). Every per-sample
/// result built on the host (packed layouts, sampler outputs) goes through it, since a
/// batch whose rays all miss the scene or are skipped holds no sample.
#[cfg_attr(not(feature = "volume"), allow(dead_code))] // the volume module's samplers
pub(crate) fn from_vec<T: candle_core::WithDType, S: Into<candle_core::Shape>>(
    v: Vec<T>,
    shape: S,
    device: &candle_core::Device,
) -> Result<Tensor> {
    let shape = shape.into();
    if v.is_empty() {
        return Tensor::zeros(shape, T::DTYPE, device);
    }
    Tensor::from_vec(v, shape, device)
}
