//! Scatter-max pooling of point features into cells as one CPU op (`FusedScatterMax`,
//! what [`crate::encoding::scatter`] runs on the CPU for the maximum): one pass over the
//! points per batch, and a backward pass that recomputes the argmax and passes each
//! cell's gradient to its maximising point.
//!
//! With the `cuda` feature, the same op runs its CUDA kernels (`cuda/scatter.cu`) for
//! CUDA tensors.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::parallel::for_each_init;
use candle_core::{Shape, WithDType};

/// The fused CPU scatter-max: `values [B, N, C] → [B, cells, C]`, given each point's cell
/// (`index`, `B·N` ids below `cells`, the op's own copy of the u32 index tensor, which is
/// not differentiable). Among equal maxima the lowest point index wins, and a NaN over
/// any number; empty cells hold 0.
pub(crate) struct FusedScatterMax {
    /// Cells per batch.
    pub(crate) cells: usize,
    /// `(B, N, C)`: batch, points per batch, channels.
    pub(crate) dims: (usize, usize, usize),
    /// The cell of every point, `[B, N]` flattened, each below `cells`.
    pub(crate) index: Vec<u32>,
}

impl FusedScatterMax {
    /// The argmax point of every (cell, channel) of one batch (`u32::MAX`: empty cell),
    /// by one pass over the points in order: a later point replaces the running maximum
    /// only if strictly greater, or NaN over a non-NaN.
    fn argmax<T: WithDType>(&self, v: &[T], idx: &[u32], c: usize, arg: &mut [u32]) {
        arg.fill(u32::MAX);
        for (p, (&q, row)) in idx.iter().zip(v.chunks(c)).enumerate() {
            let slot = &mut arg[q as usize * c..(q as usize + 1) * c];
            for (j, (s, x)) in slot.iter_mut().zip(row).enumerate() {
                if *s == u32::MAX {
                    *s = p as u32;
                    continue;
                }
                let cur = v[*s as usize * c + j].to_f64();
                let x = x.to_f64();
                if x > cur || (x.is_nan() && !cur.is_nan()) {
                    *s = p as u32;
                }
            }
        }
    }

    fn run<T: WithDType>(&self, v: &[T]) -> Vec<T> {
        let (b, n, c) = self.dims;
        let (cells, idx) = (self.cells, self.index.as_slice());
        let mut out = vec![T::from_f64(0.0); b * cells * c];
        if out.is_empty() {
            return out;
        }
        let items: Vec<_> = out.chunks_mut(cells * c).enumerate().collect();
        for_each_init(items, Vec::new, |arg: &mut Vec<u32>, (bi, o)| {
            arg.resize(cells * c, 0);
            let vb = &v[bi * n * c..(bi + 1) * n * c];
            self.argmax(vb, &idx[bi * n..(bi + 1) * n], c, arg);
            for (j, (oj, &a)) in o.iter_mut().zip(arg.iter()).enumerate() {
                if a != u32::MAX {
                    *oj = vb[a as usize * c + j % c];
                }
            }
        });
        out
    }

    fn grad<T: WithDType>(&self, v: &[T], g: &[T]) -> Vec<T> {
        let (b, n, c) = self.dims;
        let (cells, idx) = (self.cells, self.index.as_slice());
        let mut out = vec![T::from_f64(0.0); b * n * c];
        if out.is_empty() {
            return out;
        }
        let items: Vec<_> = out.chunks_mut(n * c).enumerate().collect();
        for_each_init(items, Vec::new, |arg: &mut Vec<u32>, (bi, o)| {
            arg.resize(cells * c, 0);
            self.argmax(
                &v[bi * n * c..(bi + 1) * n * c],
                &idx[bi * n..(bi + 1) * n],
                c,
                arg,
            );
            let gb = &g[bi * cells * c..(bi + 1) * cells * c];
            for (j, &a) in arg.iter().enumerate() {
                if a != u32::MAX {
                    o[a as usize * c + j % c] = gb[j];
                }
            }
        });
        out
    }
}

impl CpuKernel<1> for FusedScatterMax {
    const NAME: &'static str = "scatter max";

    fn forward<T: Real>(&self, [v]: [&[T]; 1]) -> candle_core::Result<(Vec<T>, Shape)> {
        let (b, _, c) = self.dims;
        Ok((self.run(v), Shape::from((b, self.cells, c))))
    }

    fn backward<T: Real>(
        &self,
        [v]: [&[T]; 1],
        grad: &[T],
        _: [bool; 1],
    ) -> candle_core::Result<[Option<Vec<T>>; 1]> {
        Ok([Some(self.grad(v, grad))])
    }
}

cpu_op!(FusedScatterMax, 1, "nf-scatter-max", cuda);

#[cfg(feature = "cuda")]
#[path = "cuda/scatter.rs"]
mod cuda;
