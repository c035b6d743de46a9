//! Adam's update as two in-place ops per variable, so that a step costs two passes over
//! each variable's elements instead of a dozen candle ops with their allocations:
//!
//! * `AdamMoments` on the moments `[2, n]` (row 0: `m`, row 1: `v`) with the gradient
//!   `g: [n]`: `m ← β₁m + (1 − β₁)g`, `v ← β₂v + (1 − β₂)g²`;
//! * `AdamUpdate` on the variable `θ: [n]` with the moments:
//!   `θ ← θ(1 − λ) − lr · (m·s_m) / (√(v·s_v) + ε)`, `s_m = 1/(1 − β₁ᵗ)`,
//!   `s_v = 1/(1 − β₂ᵗ)`, `λ = lr·weight_decay` (decoupled weight decay).
//!
//! The arithmetic is candle-nn's `AdamW` step, in the variable's dtype, in the same
//! order; the reference path (candle ops) is in `nn::training`. Every operand must be
//! contiguous; NaN and infinities propagate (a training loop's finite guard reports them).

use crate::kernels::Real;
use candle_core::{CpuStorage, InplaceOp2, Layout};

/// `m ← β₁m + (1 − β₁)g`, `v ← β₂v + (1 − β₂)g²` in place on the moments `[2, n]`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct AdamMoments {
    pub beta1: f64,
    pub beta2: f64,
}

/// `θ ← θ(1 − λ) − lr·(m·s_m)/(√(v·s_v) + ε)` in place on the variable.
#[derive(Clone, Copy, Debug)]
pub(crate) struct AdamUpdate {
    pub lr: f64,
    /// `λ = lr · weight_decay`.
    pub decay: f64,
    pub eps: f64,
    /// `1/(1 − β₁ᵗ)`.
    pub scale_m: f64,
    /// `1/(1 − β₂ᵗ)`.
    pub scale_v: f64,
}

/// The contiguous element range of `l`, or an error naming the op and operand.
fn range(l: &Layout, op: &str, what: &str) -> candle_core::Result<(usize, usize)> {
    match l.contiguous_offsets() {
        Some(r) => Ok(r),
        None => candle_core::bail!("{op}: {what} must be contiguous"),
    }
}

impl AdamMoments {
    pub(crate) fn run<T: Real>(&self, mv: &mut [T], g: &[T]) -> candle_core::Result<()> {
        let n = g.len();
        if mv.len() != 2 * n {
            candle_core::bail!("adam: moments of {} elements for {n} gradients", mv.len());
        }
        let (b1, c1) = (T::from_f64(self.beta1), T::from_f64(1.0 - self.beta1));
        let (b2, c2) = (T::from_f64(self.beta2), T::from_f64(1.0 - self.beta2));
        let (m, v) = mv.split_at_mut(n);
        for ((m, v), &g) in m.iter_mut().zip(v.iter_mut()).zip(g) {
            *m = *m * b1 + g * c1;
            *v = *v * b2 + g * g * c2;
        }
        Ok(())
    }
}

impl AdamUpdate {
    pub(crate) fn run<T: Real>(&self, theta: &mut [T], mv: &[T]) -> candle_core::Result<()> {
        let n = theta.len();
        if mv.len() != 2 * n {
            candle_core::bail!("adam: moments of {} elements for {n} values", mv.len());
        }
        let keep = T::from_f64(1.0 - self.decay);
        let (lr, eps) = (T::from_f64(self.lr), T::from_f64(self.eps));
        let (sm, sv) = (T::from_f64(self.scale_m), T::from_f64(self.scale_v));
        let (m, v) = mv.split_at(n);
        for ((t, &m), &v) in theta.iter_mut().zip(m).zip(v) {
            // √ in f64 rounds to the same f32 as an f32 √ (53 ≥ 2·24 + 2 bits).
            let root = T::from_f64((v * sv).to_f64().sqrt());
            let step = (m * sm) / (root + eps);
            *t = *t * keep - step * lr;
        }
        Ok(())
    }
}

/// Runs `f` on the mutable elements of `s1` and the elements of `s2` in `s1`'s dtype.
fn cpu_pair(
    op: &str,
    s1: &mut CpuStorage,
    l1: &Layout,
    s2: &CpuStorage,
    l2: &Layout,
    f32_fn: impl FnOnce(&mut [f32], &[f32]) -> candle_core::Result<()>,
    f64_fn: impl FnOnce(&mut [f64], &[f64]) -> candle_core::Result<()>,
) -> candle_core::Result<()> {
    let (a1, b1) = range(l1, op, "the updated tensor")?;
    let (a2, b2) = range(l2, op, "the operand")?;
    if let (Some(x), Some(y)) = (f32::slice_mut(s1), f32::slice(s2)) {
        return f32_fn(&mut x[a1..b1], &y[a2..b2]);
    }
    if let (Some(x), Some(y)) = (f64::slice_mut(s1), f64::slice(s2)) {
        return f64_fn(&mut x[a1..b1], &y[a2..b2]);
    }
    candle_core::bail!("{op}: operands must be both f32 or both f64")
}

impl InplaceOp2 for AdamMoments {
    fn name(&self) -> &'static str {
        "nf-adam-moments"
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<()> {
        cpu_pair(
            self.name(),
            s1,
            l1,
            s2,
            l2,
            |m, g| self.run(m, g),
            |m, g| self.run(m, g),
        )
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &mut candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> candle_core::Result<()> {
        cuda::moments(self, s1, l1, s2, l2)
    }
}

impl InplaceOp2 for AdamUpdate {
    fn name(&self) -> &'static str {
        "nf-adam-update"
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<()> {
        cpu_pair(
            self.name(),
            s1,
            l1,
            s2,
            l2,
            |t, mv| self.run(t, mv),
            |t, mv| self.run(t, mv),
        )
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &mut candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> candle_core::Result<()> {
        cuda::update(self, s1, l1, s2, l2)
    }
}

#[cfg(feature = "cuda")]
#[path = "cuda/adam.rs"]
mod cuda;
