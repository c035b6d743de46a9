//! The CUDA kernels of [`FusedHashGrid`] (`sources::HASH_GRID`): the forward pass and the
//! table gradient one thread per (level, point), the position gradient one thread per
//! point; the level geometry stays on the host ([`HashPlan`]) and is uploaded per call.

use super::{FusedHashGrid, HashPlan};
use crate::kernels::cuda::{function, launch, launch_1d, sources, upload, zeros, GpuReal};
use crate::kernels::CudaKernel;
use candle_core::cuda::cudarc::driver::{CudaSlice, CudaView, PushKernelArg};
use candle_core::{CudaDevice, Shape};

/// The plan as the kernels read it.
struct DevicePlan {
    /// `[L, 3]`: cells per axis, first row, dense flag (1) or hashed (0).
    levels: CudaSlice<u64>,
    /// `[2, D]`: the box's lower corner, then its extent `hi − lo`.
    bounds: CudaSlice<f64>,
    d: i32,
    f: u64,
    l: u64,
    mask: u32,
    /// Rows of the concatenated table.
    rows: u64,
}

fn device_plan(p: &HashPlan, dev: &CudaDevice) -> candle_core::Result<DevicePlan> {
    let mut levels = Vec::with_capacity(3 * p.levels.len().max(1));
    for l in &p.levels {
        levels.extend([u64::from(l.cells), l.offset as u64, u64::from(l.dense)]);
    }
    if levels.is_empty() {
        levels.extend([1, 0, 1]);
    }
    let mut bounds: Vec<f64> = p.lo[..p.d].to_vec();
    bounds.extend((0..p.d).map(|k| p.hi[k] - p.lo[k]));
    Ok(DevicePlan {
        levels: upload(dev, &levels)?,
        bounds: upload(dev, &bounds)?,
        d: p.d as i32,
        f: p.f as u64,
        l: p.levels.len() as u64,
        mask: p.mask,
        rows: p.levels.iter().map(|l| l.rows as u64).sum(),
    })
}

impl FusedHashGrid {
    /// Checks the inputs' lengths (`x: [N, D]`, `table: [Σ T_l, F]`); returns `N`.
    fn check_lens(&self, x: usize, table: usize) -> candle_core::Result<usize> {
        let p = &*self.0;
        let rows: usize = p.levels.iter().map(|l| l.rows).sum();
        if !(1..=4).contains(&p.d) || !x.is_multiple_of(p.d) || table != rows * p.f {
            candle_core::bail!(
                "hash grid: {x} position values for D = {} and {table} table values for \
                 {rows} rows of {} features",
                p.d,
                p.f
            );
        }
        Ok(x / p.d)
    }
}

/// The fixed-point scale `S = 2^⌊62 − log₂(N·max|g|)⌋` of the deterministic table
/// gradient (`HashPlan::deterministic`), or `None` for the f64 atomics: when the plan
/// does not ask for it, or `max|g|` is not finite (the sums must then carry NaN or ∞).
/// With `max|g| = 0` the scale is 1 and every sum 0. An entry's sum is bounded by
/// `N·max|g|` (each point adds weights summing to at most 1 per level), so every sum
/// lies within `±2⁶²`.
fn fixed_point_scale<T: GpuReal>(
    plan: &HashPlan,
    dev: &CudaDevice,
    grad: &CudaView<'_, T>,
    n: usize,
) -> candle_core::Result<Option<f64>> {
    if !plan.deterministic {
        return Ok(None);
    }
    let mut mx = dev.alloc_zeros::<u64>(1)?;
    let m64 = grad.len() as u64;
    let f = function::<T>(dev, "hash_grid", sources::HASH_GRID, "nf_hash_grad_max")?;
    let mut b = f.builder();
    b.arg(grad).arg(&m64).arg(&mut mx);
    launch(b, launch_1d(grad.len()))?;
    let bits = dev.clone_dtoh(&mx)?.first().copied().unwrap_or(0);
    let max = f64::from_bits(bits);
    if !max.is_finite() {
        return Ok(None);
    }
    if max == 0.0 {
        return Ok(Some(1.0));
    }
    let bound = (n.max(1) as f64) * max;
    // Clamped so that S stays finite for subnormal bounds (every term is then below 2⁶²
    // anyway).
    let e = (62.0 - bound.log2()).floor().clamp(-1000.0, 1000.0) as i32;
    Ok(Some(2f64.powi(e)))
}

impl CudaKernel<2> for FusedHashGrid {
    fn cuda_forward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [x, table]: [CudaView<'_, T>; 2],
    ) -> candle_core::Result<(CudaSlice<T>, Shape)> {
        let n = self.check_lens(x.len(), table.len())?;
        let w = self.0.width();
        let dp = device_plan(&self.0, dev)?;
        let mut out = zeros::<T>(dev, n * w)?;
        let n64 = n as u64;
        let f = function::<T>(dev, "hash_grid", sources::HASH_GRID, "nf_hash_fwd")?;
        let mut b = f.builder();
        b.arg(&x)
            .arg(&table)
            .arg(&dp.levels)
            .arg(&dp.bounds)
            .arg(&n64)
            .arg(&dp.d);
        b.arg(&dp.f)
            .arg(&dp.l)
            .arg(&dp.mask)
            .arg(&dp.rows)
            .arg(&mut out);
        launch(b, launch_1d(n * self.0.levels.len()))?;
        Ok((out, Shape::from((n, w))))
    }

    /// The table gradient always, the position gradient when `x` is on the graph (as the
    /// CPU kernel).
    fn cuda_backward<T: GpuReal>(
        &self,
        dev: &CudaDevice,
        [x, table]: [CudaView<'_, T>; 2],
        grad: CudaView<'_, T>,
        [want_x, _]: [bool; 2],
    ) -> candle_core::Result<[Option<CudaSlice<T>>; 2]> {
        let n = self.check_lens(x.len(), table.len())?;
        let w = self.0.width();
        if grad.len() != n * w {
            candle_core::bail!(
                "hash grid: gradient of {} elements for {n} points of {w} columns",
                grad.len()
            );
        }
        let dp = device_plan(&self.0, dev)?;
        let n64 = n as u64;
        let m = table.len();
        let gt = match fixed_point_scale::<T>(&self.0, dev, &grad, n)? {
            Some(scale) => {
                let mut acc = dev.alloc_zeros::<u64>(m.max(1))?;
                let ft = function::<T>(
                    dev,
                    "hash_grid",
                    sources::HASH_GRID,
                    "nf_hash_bwd_table_fixed",
                )?;
                let mut b = ft.builder();
                b.arg(&x)
                    .arg(&dp.levels)
                    .arg(&dp.bounds)
                    .arg(&n64)
                    .arg(&dp.d)
                    .arg(&dp.f);
                b.arg(&dp.l)
                    .arg(&dp.mask)
                    .arg(&dp.rows)
                    .arg(&grad)
                    .arg(&scale)
                    .arg(&mut acc);
                launch(b, launch_1d(n * self.0.levels.len()))?;
                let mut gt = zeros::<T>(dev, m)?;
                let m64 = m as u64;
                let fc = function::<T>(dev, "hash_grid", sources::HASH_GRID, "nf_hash_cast_fixed")?;
                let mut b = fc.builder();
                b.arg(&acc).arg(&scale).arg(&mut gt).arg(&m64);
                launch(b, launch_1d(m))?;
                gt
            }
            None => {
                let mut acc = dev.alloc_zeros::<f64>(m.max(1))?;
                let ft = function::<T>(dev, "hash_grid", sources::HASH_GRID, "nf_hash_bwd_table")?;
                let mut b = ft.builder();
                b.arg(&x)
                    .arg(&dp.levels)
                    .arg(&dp.bounds)
                    .arg(&n64)
                    .arg(&dp.d)
                    .arg(&dp.f);
                b.arg(&dp.l)
                    .arg(&dp.mask)
                    .arg(&dp.rows)
                    .arg(&grad)
                    .arg(&mut acc);
                launch(b, launch_1d(n * self.0.levels.len()))?;
                let mut gt = zeros::<T>(dev, m)?;
                let m64 = m as u64;
                let fc = function::<T>(dev, "hash_grid", sources::HASH_GRID, "nf_hash_cast")?;
                let mut b = fc.builder();
                b.arg(&acc).arg(&mut gt).arg(&m64);
                launch(b, launch_1d(m))?;
                gt
            }
        };
        let gx = if want_x {
            let mut gx = zeros::<T>(dev, x.len())?;
            let fx = function::<T>(dev, "hash_grid", sources::HASH_GRID, "nf_hash_bwd_x")?;
            let mut b = fx.builder();
            b.arg(&x)
                .arg(&table)
                .arg(&dp.levels)
                .arg(&dp.bounds)
                .arg(&n64)
                .arg(&dp.d);
            b.arg(&dp.f)
                .arg(&dp.l)
                .arg(&dp.mask)
                .arg(&dp.rows)
                .arg(&grad)
                .arg(&mut gx);
            launch(b, launch_1d(n))?;
            Some(gx)
        } else {
            None
        };
        Ok([gx, Some(gt)])
    }
}
