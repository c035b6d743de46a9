//! The CUDA kernels of [`FusedIntegrated`] (`sources::INTEGRATED`): one thread per
//! (row, coordinate).

use super::FusedIntegrated;
use crate::kernels::cuda::{function, launch, launch_1d, sources, zeros, GpuReal};
use crate::kernels::CudaKernel;
use candle_core::cuda::cudarc::driver::{CudaSlice, CudaView, PushKernelArg};
use candle_core::{CudaDevice, Shape};

impl FusedIntegrated {
    fn check_rows(&self, n: usize) -> candle_core::Result<usize> {
        if self.dim == 0 || !n.is_multiple_of(2 * self.dim) || self.min_deg > self.max_deg {
            candle_core::bail!(
                "integrated positional encoding: {n} elements are not rows of {}",
                2 * self.dim
            );
        }
        Ok(n / (2 * self.dim))
    }

    /// The kernel's size arguments: rows, D, min_deg, max_deg.
    fn sizes(&self, rows: usize) -> [u64; 4] {
        [rows, self.dim, self.min_deg, self.max_deg].map(|v| v as u64)
    }
}

impl CudaKernel<1> for FusedIntegrated {
    fn cuda_forward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [x]: [CudaView<'_, T>; 1],
    ) -> candle_core::Result<(CudaSlice<T>, Shape)> {
        let rows = self.check_rows(x.len())?;
        let mut out = zeros::<T>(dev, rows * self.width())?;
        let f = function::<T>(dev, "integrated", sources::INTEGRATED, "nf_integrated_fwd")?;
        let [r, d, lo, hi] = self.sizes(rows);
        let mut b = f.builder();
        b.arg(&x).arg(&mut out).arg(&r).arg(&d).arg(&lo).arg(&hi);
        launch(b, launch_1d(rows * self.dim))?;
        Ok((out, Shape::from((rows, self.width()))))
    }

    fn cuda_backward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [x]: [CudaView<'_, T>; 1],
        grad: CudaView<'_, T>,
        _: [bool; 1],
    ) -> candle_core::Result<[Option<CudaSlice<T>>; 1]> {
        let rows = self.check_rows(x.len())?;
        if grad.len() != rows * self.width() {
            candle_core::bail!(
                "integrated positional encoding: gradient of {} elements",
                grad.len()
            );
        }
        let mut gx = zeros::<T>(dev, x.len())?;
        let f = function::<T>(dev, "integrated", sources::INTEGRATED, "nf_integrated_bwd")?;
        let [r, d, lo, hi] = self.sizes(rows);
        let mut b = f.builder();
        b.arg(&x)
            .arg(&grad)
            .arg(&mut gx)
            .arg(&r)
            .arg(&d)
            .arg(&lo)
            .arg(&hi);
        launch(b, launch_1d(rows * self.dim))?;
        Ok([Some(gx)])
    }
}
