//! The CUDA kernels of [`FusedComposite`] (`sources::COMPOSITE`): one thread per ray, the
//! op's segments and geometry passed as device buffers.

use super::{FusedComposite, Geometry, Segments};
use crate::kernels::cuda::{function, launch, sources, upload, view, zeros, GpuReal};
use crate::kernels::CudaKernel;
use candle_core::cuda::cudarc::driver::{CudaSlice, CudaView, LaunchConfig, PushKernelArg};
use candle_core::{CudaDevice, Shape, Storage};
use std::sync::atomic::Ordering;

/// Threads per block of the per-ray kernels: small, so that a batch of a few thousand
/// rays spreads over many multiprocessors.
const RAYS_PER_BLOCK: u32 = 64;

fn per_ray(rays: usize) -> LaunchConfig {
    LaunchConfig {
        grid_dim: ((rays as u32).div_ceil(RAYS_PER_BLOCK).max(1), 1, 1),
        block_dim: (RAYS_PER_BLOCK, 1, 1),
        shared_mem_bytes: 0,
    }
}

/// The geometry of a launch: the second geometry row (t or the interval ends), the
/// kernel's mode (0: δ and t, 1: intervals) and the per-ray norms.
struct DeviceGeometry<'a, T> {
    g0: CudaView<'a, T>,
    g1: CudaView<'a, T>,
    mode: i32,
    norms: CudaSlice<f64>,
    has_norms: i32,
}

/// The ray segments of a launch.
struct DeviceSegments {
    offsets: CudaSlice<u64>,
    packed: i32,
    rays: u64,
    per_ray: u64,
}

impl FusedComposite {
    fn device_segments(&self, dev: &CudaDevice) -> candle_core::Result<DeviceSegments> {
        Ok(match &self.seg {
            Segments::Uniform { rays, s } => DeviceSegments {
                offsets: upload(dev, &[0u64])?,
                packed: 0,
                rays: *rays as u64,
                per_ray: *s as u64,
            },
            Segments::Offsets(o) => {
                let o: Vec<u64> = o.iter().map(|&x| x as u64).collect();
                DeviceSegments {
                    offsets: upload(dev, &o)?,
                    packed: 1,
                    rays: o.len().saturating_sub(1) as u64,
                    per_ray: 0,
                }
            }
        })
    }

    /// Calls `f` with the device geometry of the samples: δ and t from the geometry input
    /// or the captured t tensor, or the interval starts (the input), ends and norms.
    fn with_device_geometry<T: GpuReal, R>(
        &self,
        dev: &CudaDevice,
        geo: &CudaView<'_, T>,
        f: impl FnOnce(DeviceGeometry<'_, T>) -> candle_core::Result<R>,
    ) -> candle_core::Result<R> {
        let m = self.seg.n_samples();
        let ones = || upload(dev, &[1.0f64]);
        fn captured(s: &Storage) -> candle_core::Result<&candle_core::CudaStorage> {
            match s {
                Storage::Cuda(c) => Ok(c),
                _ => candle_core::bail!(
                    "fused composite: the captured geometry must be on the inputs' device"
                ),
            }
        }
        match &self.geometry {
            Geometry::Stacked => f(DeviceGeometry {
                g0: geo.slice(..m),
                g1: geo.slice(m..),
                mode: 0,
                norms: ones()?,
                has_norms: 0,
            }),
            Geometry::Deltas(t) => {
                let (st, l) = t.storage_and_layout();
                let c = captured(&st)?;
                let tm = view::<T>(c, l, "fused composite", "sample depths")?;
                f(DeviceGeometry {
                    g0: geo.slice(..),
                    g1: tm,
                    mode: 0,
                    norms: ones()?,
                    has_norms: 0,
                })
            }
            Geometry::Intervals { ends, norms } => {
                let (st, l) = ends.storage_and_layout();
                let c = captured(&st)?;
                let e = view::<T>(c, l, "fused composite", "interval ends")?;
                let (norms, has_norms) = match norms {
                    Some(n) => (upload(dev, n)?, 1),
                    None => (ones()?, 0),
                };
                f(DeviceGeometry {
                    g0: geo.slice(..),
                    g1: e,
                    mode: 1,
                    norms,
                    has_norms,
                })
            }
        }
    }
}

impl CudaKernel<3> for FusedComposite {
    fn cuda_forward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [s, d, v]: [CudaView<'_, T>; 3],
    ) -> candle_core::Result<(CudaSlice<T>, Shape)> {
        self.check_len(s.len(), d.len(), v.len())?;
        let rays = self.seg.n_rays();
        let shape = Shape::from((rays, self.width()));
        let mut out = zeros::<T>(dev, rays * self.width())?;
        let mut bad = dev.alloc_zeros::<i32>(1)?;
        let seg = self.device_segments(dev)?;
        let (k, opaque) = (self.k as u64, i32::from(self.opaque_last));
        self.with_device_geometry(dev, &d, |g| {
            let f = function::<T>(dev, "composite", sources::COMPOSITE, "nf_composite_fwd")?;
            let mut b = f.builder();
            b.arg(&s)
                .arg(&g.g0)
                .arg(&g.g1)
                .arg(&g.norms)
                .arg(&g.has_norms);
            b.arg(&g.mode).arg(&v).arg(&seg.offsets).arg(&seg.packed);
            b.arg(&seg.rays).arg(&seg.per_ray).arg(&k).arg(&opaque);
            b.arg(&mut out).arg(&mut bad);
            launch(b, per_ray(rays))
        })?;
        if dev.clone_dtoh(&bad)?.first().copied().unwrap_or(0) != 0 {
            self.bad.store(true, Ordering::Relaxed);
        }
        Ok((out, shape))
    }

    fn cuda_backward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [s, d, v]: [CudaView<'_, T>; 3],
        grad: CudaView<'_, T>,
        need: [bool; 3],
    ) -> candle_core::Result<[Option<CudaSlice<T>>; 3]> {
        self.check_len(s.len(), d.len(), v.len())?;
        let (m, rays) = (self.seg.n_samples(), self.seg.n_rays());
        if grad.len() != rays * self.width() {
            candle_core::bail!(
                "fused composite: gradient of {} elements for {rays} rays of {} columns",
                grad.len(),
                self.width()
            );
        }
        let tensors = !matches!(self.geometry, Geometry::Intervals { .. });
        let want_del = i32::from(need[1] && tensors);
        let want_t = i32::from(need[1] && matches!(self.geometry, Geometry::Stacked));
        let (want_sig, want_vals) = (i32::from(need[0]), i32::from(need[2]));
        let len = |on: i32, n: usize| if on != 0 { n } else { 1 };
        let mut gs = zeros::<T>(dev, len(want_sig, m))?;
        let mut gg = zeros::<T>(dev, len(want_del, m * self.geo_rows()))?;
        let mut gv = zeros::<T>(dev, len(want_vals, m * self.k))?;
        let seg = self.device_segments(dev)?;
        let (k, opaque, m64) = (self.k as u64, i32::from(self.opaque_last), m as u64);
        self.with_device_geometry(dev, &d, |g| {
            let f = function::<T>(dev, "composite", sources::COMPOSITE, "nf_composite_bwd")?;
            let mut b = f.builder();
            b.arg(&s)
                .arg(&g.g0)
                .arg(&g.g1)
                .arg(&g.norms)
                .arg(&g.has_norms);
            b.arg(&g.mode).arg(&v).arg(&seg.offsets).arg(&seg.packed);
            b.arg(&seg.rays).arg(&seg.per_ray).arg(&k).arg(&opaque);
            b.arg(&grad)
                .arg(&m64)
                .arg(&mut gs)
                .arg(&want_sig)
                .arg(&mut gg);
            b.arg(&want_del).arg(&want_t).arg(&mut gv).arg(&want_vals);
            launch(b, per_ray(rays))
        })?;
        let keep = |on: bool, v: CudaSlice<T>| on.then_some(v);
        Ok([
            keep(need[0], gs),
            keep(want_del != 0, gg),
            keep(need[2], gv),
        ])
    }
}
