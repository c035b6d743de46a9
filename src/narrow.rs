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

/// `Tensor::from_vec(v, shape, device)` that also holds for an empty `v` on a GPU (see
/// [`empty`]). Every per-sample result built on the host (packed layouts, sampler
/// outputs) goes through it, since a batch whose rays all miss the scene or are skipped
/// holds no sample.
#[cfg_attr(not(feature = "volume"), allow(dead_code))] // the volume module's samplers
pub(crate) fn from_vec<T: candle_core::WithDType, S: Into<candle_core::Shape>>(
    v: Vec<T>,
    shape: S,
    device: &candle_core::Device,
) -> Result<Tensor> {
    let shape = shape.into();
    if v.is_empty() {
        return empty(shape, T::DTYPE, device);
    }
    Tensor::from_vec(v, shape, device)
}

/// A tensor of `shape` holding no element, on any device. candle allocates an empty
/// result's storage with zero bytes, which CUDA refuses (`CUDA_ERROR_INVALID_VALUE`, for a
/// copy from the host and for `Tensor::zeros` alike); off the CPU the empty tensor is
/// therefore a view of no rows into a one-row allocation. (candle ops whose result is
/// empty still fail there: the samplers keep their outputs non-empty off the CPU.)
#[cfg_attr(not(any(feature = "volume", feature = "data")), allow(dead_code))]
pub(crate) fn empty<S: Into<candle_core::Shape>>(
    shape: S,
    dtype: candle_core::DType,
    device: &candle_core::Device,
) -> Result<Tensor> {
    let shape = shape.into();
    let dims = shape.dims();
    match dims.iter().position(|&d| d == 0) {
        Some(axis) if !device.is_cpu() => {
            let mut one = dims.to_vec();
            one[axis] = 1;
            Tensor::zeros(one, dtype, device)?.narrow(axis, 0, 0)
        }
        _ => Tensor::zeros(shape, dtype, device),
    }
}

/// A tensor of `shape` and `dtype` on `device` from host f64 `values`, rounded on the
/// host for f32 (one upload, no cast on the device); an empty one through [`empty`].
#[cfg_attr(not(any(feature = "volume", feature = "data")), allow(dead_code))]
pub(crate) fn from_host(
    values: Vec<f64>,
    shape: &[usize],
    dtype: candle_core::DType,
    device: &candle_core::Device,
) -> Result<Tensor> {
    if values.is_empty() {
        return empty(shape, dtype, device);
    }
    let t = match dtype {
        candle_core::DType::F32 => {
            let v: Vec<f32> = values.into_iter().map(|x| x as f32).collect();
            Tensor::from_vec(v, shape, device)?
        }
        _ => Tensor::from_vec(values, shape, &candle_core::Device::Cpu)?
            .to_dtype(dtype)?
            .to_device(device)?,
    };
    Ok(t)
}
