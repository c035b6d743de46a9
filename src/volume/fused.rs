//! The entry of the fused compositing op ([`crate::kernels`]' `FusedComposite`): CPU
//! inputs in either sample layout become the op's segments and geometry, and a bad value
//! the kernel flags becomes an error naming the argument.

use super::layout::{bad_intervals, check_nonneg_finite, host_f64, Layout as SampleLayout};
use crate::error::{Error, Result};
pub(crate) use crate::kernels::KernelBuild;
use crate::kernels::{FusedComposite, Geometry, Segments};
use candle_core::Tensor;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// The geometry of the samples for [`composite`].
pub(crate) enum FusedGeometry<'a> {
    /// δ and t as tensors of the samples' shape (either may carry a graph).
    Tensors {
        deltas: &'a Tensor,
        t_mids: &'a Tensor,
    },
    /// Constant interval bounds (no graph) and optional constant per-ray direction norms
    /// `[R]`: δ = (ends − starts)·norm and t = (starts + ends)/2 are formed in the kernel.
    Intervals {
        starts: &'a Tensor,
        ends: &'a Tensor,
        norms: Option<&'a Tensor>,
    },
}

/// The fused op over validated CPU inputs in either layout: returns colour Σwᵢcᵢ
/// `[R, C]`, opacity Σwᵢ `[R]` and depth Σwᵢtᵢ `[R]` (no background), differentiable
/// (first order) w.r.t. `sigmas`, `colors` and tensor geometry. `build` is the best
/// kernel build the call may use.
///
/// # Errors
/// `sigmas` when not on the CPU or when a density is NaN, negative or infinite;
/// `intervals` when a constant interval has a non-finite or negative length (both
/// checked in the kernel's own pass; the entry points need no pass of their own).
pub(crate) fn composite(
    sigmas: &Tensor,
    colors: &Tensor,
    geometry: FusedGeometry<'_>,
    layout: &SampleLayout,
    opaque_last: bool,
    build: KernelBuild,
) -> Result<(Tensor, Tensor, Tensor)> {
    if !crate::kernels::fused_on(sigmas.device()) {
        return Err(Error::invalid(
            "sigmas",
            "a tensor on a device with the fused kernel (the CPU, or CUDA with the `cuda` feature)",
            format!("{:?}", sigmas.device()),
        ));
    }
    let c = colors.dims().last().copied().unwrap_or(0);
    let seg = match layout {
        SampleLayout::Batched => {
            let (rays, s) = sigmas.dims2()?;
            Segments::Uniform { rays, s }
        }
        SampleLayout::Packed(p) => Segments::Offsets(p.offsets_arc()),
    };
    let (geo, geometry) = match geometry {
        FusedGeometry::Tensors { deltas, t_mids } if t_mids.track_op() => {
            (Tensor::stack(&[deltas, t_mids], 0)?, Geometry::Stacked)
        }
        FusedGeometry::Tensors { deltas, t_mids } => {
            (deltas.contiguous()?, Geometry::Deltas(t_mids.contiguous()?))
        }
        FusedGeometry::Intervals {
            starts,
            ends,
            norms,
        } => {
            let norms = match norms {
                Some(n) => Some(host_f64(n)?.into()),
                None => None,
            };
            let ends = ends.contiguous()?;
            (starts.contiguous()?, Geometry::Intervals { ends, norms })
        }
    };
    let bad = Arc::new(AtomicBool::new(false));
    let op = FusedComposite::new(seg, c, geometry, opaque_last, build, bad.clone());
    let out = sigmas
        .contiguous()?
        .apply_op3(&geo, &colors.contiguous()?, op)?;
    if bad.load(Ordering::Relaxed) {
        // The kernel only knows that some value was bad: name it (and where it is).
        check_nonneg_finite(sigmas, "sigmas")?;
        return Err(bad_intervals());
    }
    let color = out.narrow(1, 0, c)?;
    let depth = crate::narrow::narrow(&out, 1, c, 1)?.squeeze(1)?;
    let opacity = crate::narrow::narrow(&out, 1, c + 1, 1)?.squeeze(1)?;
    Ok((color, opacity, depth))
}

#[cfg(test)]
#[path = "fused_tests.rs"]
mod tests;
