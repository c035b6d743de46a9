//! The candle side of every fused CPU op, written once: contiguity checks, the f32/f64
//! dispatch, storage extraction and the building of results. A kernel implements
//! [`CpuKernel`] on plain slices, generic over [`Real`]; [`cpu_fwd`] and [`cpu_bwd`] are
//! the bodies of candle's `CustomOpN::cpu_fwd` and `bwd`, and [`cpu_op!`](cpu_op) writes
//! the whole `CustomOpN` impl for a kernel whose backward pass is its
//! [`CpuKernel::backward`].

use super::activation::Precision;
#[cfg(feature = "cuda")]
use super::cuda::{view, GpuReal};
#[cfg(feature = "cuda")]
use candle_core::backend::BackendStorage;
#[cfg(feature = "cuda")]
use candle_core::cuda::cudarc::driver::{CudaSlice, CudaView};
#[cfg(feature = "cuda")]
use candle_core::{op::BackpropOp, CudaDevice, CudaStorage};
use candle_core::{CpuStorage, Layout, Shape, Storage, Tensor, WithDType};

/// The element types of the fused kernels: f32 and f64.
pub(crate) trait Real: WithDType + Precision {
    /// The slice of a CPU storage of this type, `None` for another dtype.
    fn slice(s: &CpuStorage) -> Option<&[Self]>;
    /// The mutable slice of a CPU storage of this type (in-place ops), `None` for
    /// another dtype.
    fn slice_mut(s: &mut CpuStorage) -> Option<&mut [Self]>;
    /// A CPU storage holding `v`.
    fn storage(v: Vec<Self>) -> CpuStorage;
}

impl Real for f32 {
    fn slice(s: &CpuStorage) -> Option<&[f32]> {
        match s {
            CpuStorage::F32(v) => Some(v),
            _ => None,
        }
    }

    fn slice_mut(s: &mut CpuStorage) -> Option<&mut [f32]> {
        match s {
            CpuStorage::F32(v) => Some(v),
            _ => None,
        }
    }

    fn storage(v: Vec<f32>) -> CpuStorage {
        CpuStorage::F32(v)
    }
}

impl Real for f64 {
    fn slice(s: &CpuStorage) -> Option<&[f64]> {
        match s {
            CpuStorage::F64(v) => Some(v),
            _ => None,
        }
    }

    fn slice_mut(s: &mut CpuStorage) -> Option<&mut [f64]> {
        match s {
            CpuStorage::F64(v) => Some(v),
            _ => None,
        }
    }

    fn storage(v: Vec<f64>) -> CpuStorage {
        CpuStorage::F64(v)
    }
}

/// A fused CPU kernel on `N` float inputs of one dtype, each handed over as its
/// contiguous elements.
pub(crate) trait CpuKernel<const N: usize>: Send + Sync {
    /// The op's name in error messages.
    const NAME: &'static str;

    /// The output's elements and shape. Checks the inputs' lengths.
    fn forward<T: Real>(&self, inputs: [&[T]; N]) -> candle_core::Result<(Vec<T>, Shape)>;

    /// The gradient of each input given the output's gradient `grad` (contiguous, the
    /// output's length), where `want[i]` says whether input `i` takes part in the
    /// autograd graph: a kernel may return `None` for an input it is not asked for (and
    /// `Some` for one it always computes). The default: no backward pass.
    fn backward<T: Real>(
        &self,
        inputs: [&[T]; N],
        grad: &[T],
        want: [bool; N],
    ) -> candle_core::Result<[Option<Vec<T>>; N]> {
        let _ = (inputs, grad, want);
        candle_core::bail!("{}: no backward pass", Self::NAME)
    }
}

/// The element ranges `(start, end)` of contiguous layouts, in the order given; the error
/// names the op (`op`) when one is not contiguous.
pub(crate) fn contiguous<const N: usize>(
    layouts: [&Layout; N],
    op: &str,
) -> candle_core::Result<[(usize, usize); N]> {
    let mut out = [(0, 0); N];
    for (o, l) in out.iter_mut().zip(layouts) {
        match l.contiguous_offsets() {
            Some(r) => *o = r,
            None => candle_core::bail!("{op}: inputs must be contiguous"),
        }
    }
    Ok(out)
}

/// The contiguous CPU elements of a tensor's storage; errors name the op and the input
/// (`what`).
pub(crate) fn cpu_slice<'a, T: WithDType>(
    st: &'a Storage,
    l: &Layout,
    op: &str,
    what: &str,
) -> candle_core::Result<&'a [T]> {
    match st {
        Storage::Cpu(c) => match l.contiguous_offsets() {
            Some((a, b)) => Ok(&c.as_slice::<T>()?[a..b]),
            None => candle_core::bail!("{op}: {what} must be contiguous"),
        },
        _ => candle_core::bail!("{op}: {what} must be on the CPU"),
    }
}

/// The contiguous elements of every input when all are of type `T`, `None` when one is
/// of another dtype.
fn slices<'a, T: Real, const N: usize>(
    inputs: [(&'a CpuStorage, &Layout); N],
    ranges: [(usize, usize); N],
) -> Option<[&'a [T]; N]> {
    let mut out: [&[T]; N] = [&[]; N];
    for ((o, (s, _)), (a, b)) in out.iter_mut().zip(inputs).zip(ranges) {
        *o = &T::slice(s)?[a..b];
    }
    Some(out)
}

/// `CustomOpN::cpu_fwd` of kernel `k`: checks that the inputs are contiguous and all f32
/// or all f64, and runs [`CpuKernel::forward`] in that type.
pub(crate) fn cpu_fwd<K: CpuKernel<N>, const N: usize>(
    k: &K,
    inputs: [(&CpuStorage, &Layout); N],
) -> candle_core::Result<(CpuStorage, Shape)> {
    let ranges = contiguous(inputs.map(|(_, l)| l), K::NAME)?;
    if let Some(x) = slices::<f32, N>(inputs, ranges) {
        let (v, shape) = k.forward(x)?;
        return Ok((f32::storage(v), shape));
    }
    if let Some(x) = slices::<f64, N>(inputs, ranges) {
        let (v, shape) = k.forward(x)?;
        return Ok((f64::storage(v), shape));
    }
    candle_core::bail!("{}: inputs must all be f32 or all f64", K::NAME)
}

/// `CustomOpN::bwd` of kernel `k`: the inputs' and the (contiguous) gradient's CPU
/// elements in the inputs' dtype, [`CpuKernel::backward`] with `want[i]` = whether input
/// `i` is part of the graph, and each gradient as a tensor of its input's shape.
pub(crate) fn cpu_bwd<K: CpuKernel<N>, const N: usize>(
    k: &K,
    inputs: [&Tensor; N],
    grad: &Tensor,
) -> candle_core::Result<[Option<Tensor>; N]> {
    fn run<K: CpuKernel<N>, T: Real, const N: usize>(
        k: &K,
        inputs: [&Tensor; N],
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; N]> {
        let guards = inputs.map(|t| t.storage_and_layout());
        let (gs, gl) = grad.storage_and_layout();
        let mut x: [&[T]; N] = [&[]; N];
        for (i, (o, (s, l))) in x.iter_mut().zip(&guards).enumerate() {
            *o = cpu_slice::<T>(
                s,
                l,
                K::NAME,
                ["first input", "second input", "third input"]
                    .get(i)
                    .copied()
                    .unwrap_or("input"),
            )?;
        }
        let g = cpu_slice::<T>(&gs, gl, K::NAME, "gradient")?;
        let grads = k.backward(x, g, inputs.map(Tensor::track_op))?;
        let mut out: [Option<Tensor>; N] = std::array::from_fn(|_| None);
        for ((o, v), t) in out.iter_mut().zip(grads).zip(inputs) {
            if let Some(v) = v {
                *o = Some(Tensor::from_vec(v, t.shape(), t.device())?);
            }
        }
        Ok(out)
    }
    let grad = grad.contiguous()?;
    match inputs.first().map(|t| t.dtype()) {
        Some(candle_core::DType::F32) => run::<K, f32, N>(k, inputs, &grad),
        Some(candle_core::DType::F64) => run::<K, f64, N>(k, inputs, &grad),
        other => candle_core::bail!("{}: unsupported dtype {other:?}", K::NAME),
    }
}

/// A fused op's CUDA kernels (feature `cuda`) on `N` float inputs of one dtype (the CPU kernel's shapes
/// and checks, run on the device).
#[cfg(feature = "cuda")]
pub(crate) trait CudaKernel<const N: usize>: CpuKernel<N> {
    /// The output's elements and shape.
    fn cuda_forward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        inputs: [CudaView<'_, T>; N],
    ) -> candle_core::Result<(CudaSlice<T>, Shape)>;

    /// The gradient of each input wanted (`want[i]`), given the output's gradient.
    fn cuda_backward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        inputs: [CudaView<'_, T>; N],
        grad: CudaView<'_, T>,
        want: [bool; N],
    ) -> candle_core::Result<[Option<CudaSlice<T>>; N]> {
        let _ = (dev, inputs, grad, want);
        candle_core::bail!("{}: no backward pass on CUDA", Self::NAME)
    }
}

/// `CustomOpN::cuda_fwd` of kernel `k`: contiguity, one dtype (f32 or f64), the views.
#[cfg(feature = "cuda")]
pub(crate) fn cuda_fwd<K: CudaKernel<N>, const N: usize>(
    k: &K,
    inputs: [(&CudaStorage, &Layout); N],
) -> candle_core::Result<(CudaStorage, Shape)> {
    fn run<K: CudaKernel<N>, T: GpuReal, const N: usize>(
        k: &K,
        inputs: [(&CudaStorage, &Layout); N],
    ) -> candle_core::Result<(CudaStorage, Shape)> {
        let dev = inputs[0].0.device().clone();
        let mut views = Vec::with_capacity(N);
        for (i, (s, l)) in inputs.iter().enumerate() {
            views.push(view::<T>(s, l, K::NAME, &format!("input {i}"))?);
        }
        let views: [CudaView<'_, T>; N] = views
            .try_into()
            .map_err(|_| candle_core::Error::Msg("input count".into()))?;
        let (out, shape) = k.cuda_forward(&dev, views)?;
        Ok((CudaStorage::wrap_cuda_slice(out, dev), shape))
    }
    let dtypes = inputs.map(|(s, _)| s.dtype());
    if dtypes.iter().all(|d| *d == candle_core::DType::F32) {
        return run::<K, f32, N>(k, inputs);
    }
    if dtypes.iter().all(|d| *d == candle_core::DType::F64) {
        return run::<K, f64, N>(k, inputs);
    }
    candle_core::bail!("{}: inputs must all be f32 or all f64", K::NAME)
}

/// `CustomOpN::bwd` of kernel `k` on CUDA inputs: [`CudaKernel::cuda_backward`] with
/// `want[i]` = whether input `i` is part of the graph, each gradient a tensor of its
/// input's shape.
#[cfg(feature = "cuda")]
pub(crate) fn cuda_bwd<K: CudaKernel<N>, const N: usize>(
    k: &K,
    inputs: [&Tensor; N],
    grad: &Tensor,
) -> candle_core::Result<[Option<Tensor>; N]> {
    fn run<K: CudaKernel<N>, T: GpuReal, const N: usize>(
        k: &K,
        inputs: [&Tensor; N],
        grad: &Tensor,
    ) -> candle_core::Result<[Option<Tensor>; N]> {
        let guards = inputs.map(|t| t.storage_and_layout());
        let (gs, gl) = grad.storage_and_layout();
        fn cuda<'a>(s: &'a Storage, op: &str) -> candle_core::Result<&'a CudaStorage> {
            match s {
                Storage::Cuda(c) => Ok(c),
                _ => candle_core::bail!("{op}: every input must be on the same CUDA device"),
            }
        }
        let mut views = Vec::with_capacity(N);
        for (i, (s, l)) in guards.iter().enumerate() {
            views.push(view::<T>(
                cuda(s, K::NAME)?,
                l,
                K::NAME,
                &format!("input {i}"),
            )?);
        }
        let views: [CudaView<'_, T>; N] = views
            .try_into()
            .map_err(|_| candle_core::Error::Msg("input count".into()))?;
        let gc = cuda(&gs, K::NAME)?;
        let dev = gc.device().clone();
        let g = view::<T>(gc, gl, K::NAME, "gradient")?;
        let grads = k.cuda_backward(&dev, views, g, inputs.map(Tensor::track_op))?;
        let mut out: [Option<Tensor>; N] = std::array::from_fn(|_| None);
        for ((o, v), t) in out.iter_mut().zip(grads).zip(inputs) {
            if let Some(v) = v {
                let st = Storage::Cuda(CudaStorage::wrap_cuda_slice(v, dev.clone()));
                *o = Some(Tensor::from_storage(
                    st,
                    t.shape().clone(),
                    BackpropOp::none(),
                    false,
                ));
            }
        }
        Ok(out)
    }
    let grad = grad.contiguous()?;
    match inputs.first().map(|t| t.dtype()) {
        Some(candle_core::DType::F32) => run::<K, f32, N>(k, inputs, &grad),
        Some(candle_core::DType::F64) => run::<K, f64, N>(k, inputs, &grad),
        other => candle_core::bail!("{}: unsupported dtype {other:?}", K::NAME),
    }
}

/// `impl CustomOpN for $ty` through [`cpu_fwd`] and [`cpu_bwd`], for a type that
/// implements [`CpuKernel<N>`]: `cpu_op!(Type, 2, "nf-op-name")` or with 1 or 3. With a
/// trailing `cuda` (`cpu_op!(Type, 2, "nf-op-name", cuda)`), for a type that also
/// implements `kernels::cuda::CudaKernel<N>`, the impl gains `cuda_fwd` and a `bwd` that
/// runs the CUDA backward for CUDA inputs (feature `cuda`).
macro_rules! cpu_op {
    ($ty:ty, 1, $name:literal $(, $cuda:ident)?) => {
        impl candle_core::CustomOp1 for $ty {
            fn name(&self) -> &'static str {
                $name
            }

            fn cpu_fwd(
                &self,
                s1: &candle_core::CpuStorage,
                l1: &candle_core::Layout,
            ) -> candle_core::Result<(candle_core::CpuStorage, candle_core::Shape)> {
                $crate::kernels::cpu_fwd(self, [(s1, l1)])
            }

            $(
                #[cfg(feature = "cuda")]
                fn cuda_fwd(
                    &self,
                    s1: &candle_core::CudaStorage,
                    l1: &candle_core::Layout,
                ) -> candle_core::Result<(candle_core::CudaStorage, candle_core::Shape)> {
                    let _ = stringify!($cuda);
                    $crate::kernels::cuda_fwd(self, [(s1, l1)])
                }
            )?

            fn bwd(
                &self,
                x: &candle_core::Tensor,
                _res: &candle_core::Tensor,
                grad: &candle_core::Tensor,
            ) -> candle_core::Result<Option<candle_core::Tensor>> {
                $(
                    #[cfg(feature = "cuda")]
                    if x.device().is_cuda() {
                        let _ = stringify!($cuda);
                        let [gx] = $crate::kernels::cuda_bwd(self, [x], grad)?;
                        return Ok(gx);
                    }
                )?
                let [gx] = $crate::kernels::cpu_bwd(self, [x], grad)?;
                Ok(gx)
            }
        }
    };
    ($ty:ty, 2, $name:literal $(, $cuda:ident)?) => {
        impl candle_core::CustomOp2 for $ty {
            fn name(&self) -> &'static str {
                $name
            }

            fn cpu_fwd(
                &self,
                s1: &candle_core::CpuStorage,
                l1: &candle_core::Layout,
                s2: &candle_core::CpuStorage,
                l2: &candle_core::Layout,
            ) -> candle_core::Result<(candle_core::CpuStorage, candle_core::Shape)> {
                $crate::kernels::cpu_fwd(self, [(s1, l1), (s2, l2)])
            }

            $(
                #[cfg(feature = "cuda")]
                fn cuda_fwd(
                    &self,
                    s1: &candle_core::CudaStorage,
                    l1: &candle_core::Layout,
                    s2: &candle_core::CudaStorage,
                    l2: &candle_core::Layout,
                ) -> candle_core::Result<(candle_core::CudaStorage, candle_core::Shape)> {
                    let _ = stringify!($cuda);
                    $crate::kernels::cuda_fwd(self, [(s1, l1), (s2, l2)])
                }
            )?

            fn bwd(
                &self,
                x: &candle_core::Tensor,
                y: &candle_core::Tensor,
                _res: &candle_core::Tensor,
                grad: &candle_core::Tensor,
            ) -> candle_core::Result<(Option<candle_core::Tensor>, Option<candle_core::Tensor>)>
            {
                $(
                    #[cfg(feature = "cuda")]
                    if x.device().is_cuda() {
                        let _ = stringify!($cuda);
                        let [gx, gy] = $crate::kernels::cuda_bwd(self, [x, y], grad)?;
                        return Ok((gx, gy));
                    }
                )?
                let [gx, gy] = $crate::kernels::cpu_bwd(self, [x, y], grad)?;
                Ok((gx, gy))
            }
        }
    };
    ($ty:ty, 3, $name:literal $(, $cuda:ident)?) => {
        impl candle_core::CustomOp3 for $ty {
            fn name(&self) -> &'static str {
                $name
            }

            fn cpu_fwd(
                &self,
                s1: &candle_core::CpuStorage,
                l1: &candle_core::Layout,
                s2: &candle_core::CpuStorage,
                l2: &candle_core::Layout,
                s3: &candle_core::CpuStorage,
                l3: &candle_core::Layout,
            ) -> candle_core::Result<(candle_core::CpuStorage, candle_core::Shape)> {
                $crate::kernels::cpu_fwd(self, [(s1, l1), (s2, l2), (s3, l3)])
            }

            $(
                #[cfg(feature = "cuda")]
                #[allow(clippy::too_many_arguments)]
                fn cuda_fwd(
                    &self,
                    s1: &candle_core::CudaStorage,
                    l1: &candle_core::Layout,
                    s2: &candle_core::CudaStorage,
                    l2: &candle_core::Layout,
                    s3: &candle_core::CudaStorage,
                    l3: &candle_core::Layout,
                ) -> candle_core::Result<(candle_core::CudaStorage, candle_core::Shape)> {
                    let _ = stringify!($cuda);
                    $crate::kernels::cuda_fwd(self, [(s1, l1), (s2, l2), (s3, l3)])
                }
            )?

            #[allow(clippy::type_complexity)]
            fn bwd(
                &self,
                x: &candle_core::Tensor,
                y: &candle_core::Tensor,
                z: &candle_core::Tensor,
                _res: &candle_core::Tensor,
                grad: &candle_core::Tensor,
            ) -> candle_core::Result<(
                Option<candle_core::Tensor>,
                Option<candle_core::Tensor>,
                Option<candle_core::Tensor>,
            )> {
                $(
                    #[cfg(feature = "cuda")]
                    if x.device().is_cuda() {
                        let _ = stringify!($cuda);
                        let [gx, gy, gz] = $crate::kernels::cuda_bwd(self, [x, y, z], grad)?;
                        return Ok((gx, gy, gz));
                    }
                )?
                let [gx, gy, gz] = $crate::kernels::cpu_bwd(self, [x, y, z], grad)?;
                Ok((gx, gy, gz))
            }
        }
    };
}
pub(crate) use cpu_op;
