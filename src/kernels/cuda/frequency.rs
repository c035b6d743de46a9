//! The CUDA kernels of [`FusedFrequency`] (`sources::FREQUENCY`): one thread per
//! (row, coordinate).

use super::FusedFrequency;
use crate::kernels::cuda::{function, launch, launch_1d, sources, zeros, GpuReal};
use crate::kernels::CudaKernel;
use candle_core::cuda::cudarc::driver::{CudaSlice, CudaView, PushKernelArg};
use candle_core::{CudaDevice, Shape};

impl FusedFrequency {
    fn check_rows(&self, n: usize) -> candle_core::Result<usize> {
        if self.in_dim == 0 || !n.is_multiple_of(self.in_dim) {
            candle_core::bail!(
                "frequency encoding: {n} elements are not rows of {}",
                self.in_dim
            );
        }
        Ok(n / self.in_dim)
    }
}

impl CudaKernel<1> for FusedFrequency {
    fn cuda_forward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [x]: [CudaView<'_, T>; 1],
    ) -> candle_core::Result<(CudaSlice<T>, Shape)> {
        let rows = self.check_rows(x.len())?;
        let mut out = zeros::<T>(dev, rows * self.width())?;
        let f = function::<T>(dev, "frequency", sources::FREQUENCY, "nf_frequency_fwd")?;
        let (r, d, l) = (rows as u64, self.in_dim as u64, self.n_freqs as u64);
        let inc = i32::from(self.include_input);
        let mut b = f.builder();
        b.arg(&x).arg(&mut out).arg(&r).arg(&d).arg(&l).arg(&inc);
        launch(b, launch_1d(x.len()))?;
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
            candle_core::bail!("frequency encoding: gradient of {} elements", grad.len());
        }
        let mut gx = zeros::<T>(dev, x.len())?;
        let f = function::<T>(dev, "frequency", sources::FREQUENCY, "nf_frequency_bwd")?;
        let (r, d, l) = (rows as u64, self.in_dim as u64, self.n_freqs as u64);
        let inc = i32::from(self.include_input);
        let mut b = f.builder();
        b.arg(&x)
            .arg(&grad)
            .arg(&mut gx)
            .arg(&r)
            .arg(&d)
            .arg(&l)
            .arg(&inc);
        launch(b, launch_1d(x.len()))?;
        Ok([Some(gx)])
    }
}
