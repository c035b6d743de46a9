//! The CUDA kernels of [`FusedGridSample`] (`sources::GRID_SAMPLE`): the forward pass and
//! the feature gradient one thread per (point, channel), the coordinate gradient one
//! thread per point; the geometry ([`GridGeometry`](super::GridGeometry)) passed as
//! scalars.

use super::FusedGridSample;
use crate::kernels::cuda::{function, launch, launch_1d, sources, zeros, GpuReal};
use crate::kernels::CudaKernel;
use candle_core::cuda::cudarc::driver::{CudaSlice, CudaView, LaunchArgs, PushKernelArg};
use candle_core::{CudaDevice, Shape};

/// The scalar arguments every kernel takes after its tensors: `B, N, C, k`, the sizes and
/// strides of the three coordinate axes and the spatial samples `P`.
struct Scalars {
    dims: [u64; 3],
    k: i32,
    geo: [u64; 7],
}

impl Scalars {
    fn push<'a>(&'a self, b: &mut LaunchArgs<'a>) {
        for v in &self.dims {
            b.arg(v);
        }
        b.arg(&self.k);
        for v in &self.geo {
            b.arg(v);
        }
    }
}

impl FusedGridSample {
    fn scalars(&self) -> Scalars {
        let g = &self.geometry;
        let (b, n, c) = self.dims;
        Scalars {
            dims: [b as u64, n as u64, c as u64],
            k: g.k as i32,
            geo: [
                g.size[0] as u64,
                g.size[1] as u64,
                g.size[2] as u64,
                g.stride[0] as u64,
                g.stride[1] as u64,
                g.stride[2] as u64,
                g.cells as u64,
            ],
        }
    }

    /// Checks the inputs' lengths (`features: [B, C, P]`, `coords: [B, N, k]`).
    fn check_lens(&self, features: usize, coords: usize) -> candle_core::Result<()> {
        let (b, n, c) = self.dims;
        let (k, p) = (self.geometry.k, self.geometry.cells);
        if !(2..=3).contains(&k) || features != b * c * p || coords != b * n * k {
            candle_core::bail!(
                "grid sample: {features} feature values and {coords} coordinates for \
                 B = {b}, N = {n}, C = {c}, k = {k}, {p} samples"
            );
        }
        Ok(())
    }
}

impl CudaKernel<2> for FusedGridSample {
    fn cuda_forward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [feat, x]: [CudaView<'_, T>; 2],
    ) -> candle_core::Result<(CudaSlice<T>, Shape)> {
        self.check_lens(feat.len(), x.len())?;
        let (b, n, c) = self.dims;
        let s = self.scalars();
        let mut out = zeros::<T>(dev, b * n * c)?;
        let f = function::<T>(dev, "grid_sample", sources::GRID_SAMPLE, "nf_gs_fwd")?;
        let mut args = f.builder();
        args.arg(&feat).arg(&x);
        s.push(&mut args);
        args.arg(&mut out);
        launch(args, launch_1d(b * n * c))?;
        Ok((out, Shape::from(self.dims)))
    }

    fn cuda_backward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [feat, x]: [CudaView<'_, T>; 2],
        grad: CudaView<'_, T>,
        [want_f, want_x]: [bool; 2],
    ) -> candle_core::Result<[Option<CudaSlice<T>>; 2]> {
        self.check_lens(feat.len(), x.len())?;
        let (b, n, c) = self.dims;
        if grad.len() != b * n * c {
            candle_core::bail!(
                "grid sample: gradient of {} elements for [{b}, {n}, {c}]",
                grad.len()
            );
        }
        let s = self.scalars();
        let gf = if want_f {
            let m = feat.len();
            let mut acc = dev.alloc_zeros::<f64>(m.max(1))?;
            let f = function::<T>(
                dev,
                "grid_sample",
                sources::GRID_SAMPLE,
                "nf_gs_bwd_features",
            )?;
            let mut args = f.builder();
            args.arg(&x).arg(&grad);
            s.push(&mut args);
            args.arg(&mut acc);
            launch(args, launch_1d(b * n * c))?;
            let mut gf = zeros::<T>(dev, m)?;
            let m64 = m as u64;
            let f = function::<T>(dev, "grid_sample", sources::GRID_SAMPLE, "nf_gs_cast")?;
            let mut args = f.builder();
            args.arg(&acc).arg(&mut gf).arg(&m64);
            launch(args, launch_1d(m))?;
            Some(gf)
        } else {
            None
        };
        let gx = if want_x {
            let mut gx = zeros::<T>(dev, x.len())?;
            let f = function::<T>(dev, "grid_sample", sources::GRID_SAMPLE, "nf_gs_bwd_coords")?;
            let mut args = f.builder();
            args.arg(&feat).arg(&x).arg(&grad);
            s.push(&mut args);
            args.arg(&mut gx);
            launch(args, launch_1d(b * n))?;
            Some(gx)
        } else {
            None
        };
        Ok([gf, gx])
    }
}
