//! The CUDA kernels of [`FusedScatterMax`] (`sources::SCATTER`): the per-(cell, channel)
//! maximum and argmax by two atomic passes over the values, then the output (one thread
//! per output element) or the gradient (one thread per value element). The op's u32 cell
//! index is uploaded per call.

use super::FusedScatterMax;
use crate::kernels::cuda::{function, launch, launch_1d, sources, upload, zeros, GpuReal};
use crate::kernels::CudaKernel;
use candle_core::cuda::cudarc::driver::{CudaSlice, CudaView, PushKernelArg};
use candle_core::{CudaDevice, Shape};

impl FusedScatterMax {
    /// Checks the lengths (`values: [B, N, C]`, the index `[B, N]`, `N < 2³² − 1`).
    fn check_lens(&self, values: usize) -> candle_core::Result<()> {
        let (b, n, c) = self.dims;
        if values != b * n * c || self.index.len() != b * n || n >= u32::MAX as usize {
            candle_core::bail!(
                "scatter max: {values} values and {} cell ids for B = {b}, N = {n}, C = {c}",
                self.index.len()
            );
        }
        Ok(())
    }

    /// The uploaded index and the argmax `arg [B, cells, C]` (`!a` for point `a`, 0 for an
    /// empty cell) of the values `v`.
    fn device_argmax<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        v: &CudaView<'_, T>,
    ) -> candle_core::Result<(CudaSlice<u32>, CudaSlice<u32>)> {
        let (b, n, c) = self.dims;
        let slots = b * self.cells * c;
        let idx = if self.index.is_empty() {
            upload(dev, &[0u32])?
        } else {
            upload(dev, &self.index)?
        };
        // Keys of the storage dtype's width: u32 (f32) or u64 (f64), as u32 words.
        let words = std::mem::size_of::<T>() / 4;
        let mut key = dev.alloc_zeros::<u32>((slots * words).max(2))?;
        let mut arg = dev.alloc_zeros::<u32>(slots.max(1))?;
        let dims = [b as u64, n as u64, c as u64, self.cells as u64];
        let f = function::<T>(dev, "scatter", sources::SCATTER, "nf_scatter_key")?;
        let mut args = f.builder();
        args.arg(v).arg(&idx);
        for d in &dims {
            args.arg(d);
        }
        args.arg(&mut key);
        launch(args, launch_1d(b * n * c))?;
        let f = function::<T>(dev, "scatter", sources::SCATTER, "nf_scatter_arg")?;
        let mut args = f.builder();
        args.arg(v).arg(&idx);
        for d in &dims {
            args.arg(d);
        }
        args.arg(&key).arg(&mut arg);
        launch(args, launch_1d(b * n * c))?;
        Ok((idx, arg))
    }
}

impl CudaKernel<1> for FusedScatterMax {
    fn cuda_forward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [v]: [CudaView<'_, T>; 1],
    ) -> candle_core::Result<(CudaSlice<T>, Shape)> {
        self.check_lens(v.len())?;
        let (b, n, c) = self.dims;
        let slots = b * self.cells * c;
        let (_idx, arg) = self.device_argmax(dev, &v)?;
        let mut out = zeros::<T>(dev, slots)?;
        let dims = [b as u64, n as u64, c as u64, self.cells as u64];
        let f = function::<T>(dev, "scatter", sources::SCATTER, "nf_scatter_out")?;
        let mut args = f.builder();
        args.arg(&v).arg(&arg);
        for d in &dims {
            args.arg(d);
        }
        args.arg(&mut out);
        launch(args, launch_1d(slots))?;
        Ok((out, Shape::from((b, self.cells, c))))
    }

    fn cuda_backward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [v]: [CudaView<'_, T>; 1],
        grad: CudaView<'_, T>,
        _: [bool; 1],
    ) -> candle_core::Result<[Option<CudaSlice<T>>; 1]> {
        self.check_lens(v.len())?;
        let (b, n, c) = self.dims;
        if grad.len() != b * self.cells * c {
            candle_core::bail!(
                "scatter max: gradient of {} elements for [{b}, {}, {c}]",
                grad.len(),
                self.cells
            );
        }
        let (idx, arg) = self.device_argmax(dev, &v)?;
        let mut gv = zeros::<T>(dev, v.len())?;
        let dims = [b as u64, n as u64, c as u64, self.cells as u64];
        let f = function::<T>(dev, "scatter", sources::SCATTER, "nf_scatter_grad")?;
        let mut args = f.builder();
        args.arg(&idx).arg(&arg).arg(&grad);
        for d in &dims {
            args.arg(d);
        }
        args.arg(&mut gv);
        launch(args, launch_1d(v.len()))?;
        Ok([Some(gv)])
    }
}
