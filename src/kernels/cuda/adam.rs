//! The CUDA kernels of Adam's two in-place passes (`sources::ADAM`): one thread per
//! element.

use super::{AdamMoments, AdamUpdate};
use crate::kernels::cuda::{function, launch, launch_1d, sources, view, GpuReal};
use candle_core::backend::BackendStorage;
use candle_core::cuda::cudarc::driver::PushKernelArg;
use candle_core::{CudaStorage, Layout};

/// The mutable contiguous elements `[a, b)` of `s` and their count.
fn target<'a, T: GpuReal>(
    s: &'a mut CudaStorage,
    l: &Layout,
    op: &str,
) -> candle_core::Result<candle_core::cuda::cudarc::driver::CudaViewMut<'a, T>> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(s.as_cuda_slice_mut::<T>()?.slice_mut(a..b)),
        None => candle_core::bail!("{op}: the updated tensor must be contiguous"),
    }
}

fn run_moments<T: GpuReal>(
    op: &AdamMoments,
    s1: &mut CudaStorage,
    l1: &Layout,
    s2: &CudaStorage,
    l2: &Layout,
) -> candle_core::Result<()> {
    let dev = s2.device().clone();
    let g = view::<T>(s2, l2, "adam", "the gradient")?;
    let n = g.len();
    let mut mv = target::<T>(s1, l1, "adam")?;
    if mv.len() != 2 * n {
        candle_core::bail!("adam: moments of {} elements for {n} gradients", mv.len());
    }
    if n == 0 {
        return Ok(());
    }
    let f = function::<T>(&dev, "adam", sources::ADAM, "nf_adam_moments")?;
    let (b1, c1) = (T::from_f64(op.beta1), T::from_f64(1.0 - op.beta1));
    let (b2, c2) = (T::from_f64(op.beta2), T::from_f64(1.0 - op.beta2));
    let n64 = n as u64;
    let mut b = f.builder();
    b.arg(&mut mv)
        .arg(&g)
        .arg(&n64)
        .arg(&b1)
        .arg(&c1)
        .arg(&b2)
        .arg(&c2);
    launch(b, launch_1d(n))
}

fn run_update<T: GpuReal>(
    op: &AdamUpdate,
    s1: &mut CudaStorage,
    l1: &Layout,
    s2: &CudaStorage,
    l2: &Layout,
) -> candle_core::Result<()> {
    let dev = s2.device().clone();
    let mv = view::<T>(s2, l2, "adam", "the moments")?;
    let mut theta = target::<T>(s1, l1, "adam")?;
    let n = theta.len();
    if mv.len() != 2 * n {
        candle_core::bail!("adam: moments of {} elements for {n} values", mv.len());
    }
    if n == 0 {
        return Ok(());
    }
    let f = function::<T>(&dev, "adam", sources::ADAM, "nf_adam_update")?;
    let keep = T::from_f64(1.0 - op.decay);
    let (lr, eps) = (T::from_f64(op.lr), T::from_f64(op.eps));
    let (sm, sv) = (T::from_f64(op.scale_m), T::from_f64(op.scale_v));
    let n64 = n as u64;
    let mut b = f.builder();
    b.arg(&mut theta)
        .arg(&mv)
        .arg(&n64)
        .arg(&keep)
        .arg(&lr)
        .arg(&eps)
        .arg(&sm)
        .arg(&sv);
    launch(b, launch_1d(n))
}

/// [`AdamMoments`] on CUDA storages (f32 or f64, both of one dtype).
pub(super) fn moments(
    op: &AdamMoments,
    s1: &mut CudaStorage,
    l1: &Layout,
    s2: &CudaStorage,
    l2: &Layout,
) -> candle_core::Result<()> {
    match (s1.dtype(), s2.dtype()) {
        (candle_core::DType::F32, candle_core::DType::F32) => {
            run_moments::<f32>(op, s1, l1, s2, l2)
        }
        (candle_core::DType::F64, candle_core::DType::F64) => {
            run_moments::<f64>(op, s1, l1, s2, l2)
        }
        (a, b) => {
            candle_core::bail!("adam: moments {a:?} and gradient {b:?} must be both f32 or f64")
        }
    }
}

/// [`AdamUpdate`] on CUDA storages (f32 or f64, both of one dtype).
pub(super) fn update(
    op: &AdamUpdate,
    s1: &mut CudaStorage,
    l1: &Layout,
    s2: &CudaStorage,
    l2: &Layout,
) -> candle_core::Result<()> {
    match (s1.dtype(), s2.dtype()) {
        (candle_core::DType::F32, candle_core::DType::F32) => run_update::<f32>(op, s1, l1, s2, l2),
        (candle_core::DType::F64, candle_core::DType::F64) => run_update::<f64>(op, s1, l1, s2, l2),
        (a, b) => {
            candle_core::bail!("adam: variable {a:?} and moments {b:?} must be both f32 or f64")
        }
    }
}
