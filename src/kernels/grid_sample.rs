//! Bilinear and trilinear sampling of feature planes and grids as one CPU op
//! (`FusedGridSample`, what [`crate::encoding::grid_sample`] runs on the CPU): the
//! sampling geometry it shares with the encoding's reference path ([`GridGeometry`]),
//! the corners of a point, and the forward pass, the feature gradient and the coordinate
//! gradient.
//!
//! With the `cuda` feature, the same op runs its CUDA kernels (`cuda/grid_sample.cu`)
//! for CUDA tensors.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::parallel::for_each_init;
use candle_core::{Shape, WithDType};

/// Points per work item of the fused forward and coordinate-gradient passes.
const ROWS: usize = 256;

/// Channels per work item of the fused feature-gradient pass (a fixed split, so the
/// order of every sum does not depend on the number of threads).
const CHANNEL_BLOCK: usize = 4;

/// The geometry of a sampling call: spatial sizes per coordinate axis and the strides of
/// the flattened spatial index.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct GridGeometry {
    /// Coordinate axes `k` (2 or 3).
    pub(crate) k: usize,
    /// Samples along coordinate axis `a` (`a = 0`: W, 1: H, 2: D).
    pub(crate) size: [usize; 3],
    /// Stride of coordinate axis `a` in the flattened spatial index.
    pub(crate) stride: [usize; 3],
    /// Spatial samples in all, `Π size`.
    pub(crate) cells: usize,
}

impl GridGeometry {
    /// From the spatial dims in the features' order (`[H, W]` or `[D, H, W]`).
    pub(crate) fn new(spatial: &[usize]) -> Self {
        let k = spatial.len();
        let (mut size, mut stride) = ([1usize; 3], [0usize; 3]);
        let mut s = 1;
        for a in 0..k {
            size[a] = spatial[k - 1 - a];
            stride[a] = s;
            s *= size[a];
        }
        Self {
            k,
            size,
            stride,
            cells: s,
        }
    }

    /// One axis of one point: the lower sample `i`, the local coordinate `w`, the rate
    /// `∂w/∂c` (zero when clamped) and the clamped coordinate.
    pub(crate) fn axis(&self, a: usize, c: f64) -> (usize, f64, f64) {
        let n = self.size[a];
        if n < 2 {
            return (0, 0.0, 0.0);
        }
        let s = (n - 1) as f64;
        let inside = (0.0..=1.0).contains(&c);
        let u = c.clamp(0.0, 1.0) * s;
        // u ∈ [0, S − 1], so the cast is exact.
        let i = (u.floor() as usize).min(n - 2);
        (i, u - i as f64, if inside { s } else { 0.0 })
    }

    /// The corners of one point: flat spatial offsets, weights and, with `grads`, each
    /// weight's derivative per coordinate axis. Built axis by axis (corner `q` takes
    /// `i_a + 1` on axis `a` when bit `a` of `q` is set).
    pub(crate) fn corners(&self, c: &[f64], grads: bool, out: &mut GridCorners) {
        out.n = 1;
        out.offset[0] = 0;
        out.weight[0] = 1.0;
        out.dweight[0] = [1.0; 3];
        for (a, &ca) in c.iter().enumerate().take(self.k) {
            let (i, w, dw) = self.axis(a, ca);
            let step = if self.size[a] > 1 { self.stride[a] } else { 0 };
            let half = out.n;
            for q in 0..half {
                let hi = q + half;
                out.offset[hi] = out.offset[q] + (i * self.stride[a] + step);
                out.offset[q] += i * self.stride[a];
                out.weight[hi] = out.weight[q] * w;
                out.weight[q] *= 1.0 - w;
                if grads {
                    let mut lo = out.dweight[q];
                    let mut up = lo;
                    for j in 0..self.k {
                        if j == a {
                            up[j] *= dw;
                            lo[j] *= -dw;
                        } else {
                            up[j] *= w;
                            lo[j] *= 1.0 - w;
                        }
                    }
                    out.dweight[q] = lo;
                    out.dweight[hi] = up;
                }
            }
            out.n *= 2;
        }
    }
}

/// The corners of one point (at most 8).
pub(crate) struct GridCorners {
    /// Corners in use, `2ᵏ`.
    pub(crate) n: usize,
    /// Each corner's flat spatial offset.
    pub(crate) offset: [usize; 8],
    /// Each corner's interpolation weight.
    pub(crate) weight: [f64; 8],
    /// Each corner's weight derivative per coordinate axis.
    pub(crate) dweight: [[f64; 3]; 8],
}

impl GridCorners {
    /// Scratch for [`GridGeometry::corners`].
    pub(crate) fn new() -> Self {
        Self {
            n: 0,
            offset: [0; 8],
            weight: [0.0; 8],
            dweight: [[0.0; 3]; 8],
        }
    }
}

/// The fused CPU op: `(features [B, C, …], coords [B, N, k]) → [B, N, C]`. The forward
/// pass and the coordinate gradient run in parallel over blocks of points; the feature
/// gradient over (batch, block of 4 channels), each work item adding its batch's points
/// in order into its own f64 accumulators (the same bit for bit at any thread count). The
/// coordinate gradient is computed only when the coordinates are on the autograd graph.
pub(crate) struct FusedGridSample {
    /// The features' spatial geometry.
    pub(crate) geometry: GridGeometry,
    /// `(B, N, C)`: batch, points per batch, channels.
    pub(crate) dims: (usize, usize, usize),
}

/// A point's coordinates as f64.
fn point<T: WithDType>(row: &[T]) -> [f64; 3] {
    let mut c = [0.0; 3];
    for (x, r) in c.iter_mut().zip(row) {
        *x = r.to_f64();
    }
    c
}

impl FusedGridSample {
    fn run<T: WithDType>(&self, f: &[T], x: &[T]) -> Vec<T> {
        let g = &self.geometry;
        let (_, n, c) = self.dims;
        let k = g.k;
        let p = g.cells;
        let mut out = vec![T::from_f64(0.0); x.len() / k * c];
        if out.is_empty() {
            return out;
        }
        let items: Vec<_> = out
            .chunks_mut(ROWS * c)
            .zip(x.chunks(ROWS * k))
            .enumerate()
            .collect();
        for_each_init(items, GridCorners::new, |cs, (item, (out, x))| {
            for (j, (o, row)) in out.chunks_mut(c).zip(x.chunks(k)).enumerate() {
                let bi = (item * ROWS + j) / n;
                g.corners(&point(row), false, cs);
                let fb = &f[bi * c * p..(bi + 1) * c * p];
                for (ch, oc) in o.iter_mut().enumerate() {
                    let plane = &fb[ch * p..(ch + 1) * p];
                    let mut acc = 0.0;
                    for q in 0..cs.n {
                        acc += cs.weight[q] * plane[cs.offset[q]].to_f64();
                    }
                    *oc = T::from_f64(acc);
                }
            }
        });
        out
    }

    /// `∂L/∂F: [B, C, P]`: one work item per (batch, block of channels), each adding its
    /// batch's points in order into f64 accumulators (deterministic at any thread count).
    fn features_grad<T: WithDType>(&self, x: &[T], gr: &[T]) -> Vec<T> {
        let g = &self.geometry;
        let (b, n, c) = self.dims;
        let (k, p) = (g.k, g.cells);
        let mut out = vec![T::from_f64(0.0); b * c * p];
        if out.is_empty() || n == 0 {
            return out;
        }
        let mut items = Vec::new();
        for (bi, fb) in out.chunks_mut(c * p).enumerate() {
            for (blk, part) in fb.chunks_mut(CHANNEL_BLOCK * p).enumerate() {
                items.push((bi, blk * CHANNEL_BLOCK, part));
            }
        }
        for_each_init(items, GridCorners::new, |cs, (bi, c0, part)| {
            let width = part.len() / p;
            let mut acc = vec![0.0f64; part.len()];
            let xs = &x[bi * n * k..(bi + 1) * n * k];
            let gs = &gr[bi * n * c..(bi + 1) * n * c];
            for (row, grow) in xs.chunks(k).zip(gs.chunks(c)) {
                g.corners(&point(row), false, cs);
                for j in 0..width {
                    let gj = grow[c0 + j].to_f64();
                    if gj == 0.0 {
                        continue;
                    }
                    let a = &mut acc[j * p..(j + 1) * p];
                    for q in 0..cs.n {
                        a[cs.offset[q]] += cs.weight[q] * gj;
                    }
                }
            }
            for (o, a) in part.iter_mut().zip(&acc) {
                *o = T::from_f64(*a);
            }
        });
        out
    }

    /// `∂L/∂coords: [B, N, k]`, point by point.
    fn coords_grad<T: WithDType>(&self, f: &[T], x: &[T], gr: &[T]) -> Vec<T> {
        let g = &self.geometry;
        let (_, n, c) = self.dims;
        let (k, p) = (g.k, g.cells);
        let mut out = vec![T::from_f64(0.0); x.len()];
        if out.is_empty() {
            return out;
        }
        let items: Vec<_> = out
            .chunks_mut(ROWS * k)
            .zip(x.chunks(ROWS * k))
            .zip(gr.chunks(ROWS * c.max(1)))
            .enumerate()
            .collect();
        for_each_init(items, GridCorners::new, |cs, (item, ((out, x), gr))| {
            for (j, ((o, row), grow)) in out
                .chunks_mut(k)
                .zip(x.chunks(k))
                .zip(gr.chunks(c.max(1)))
                .enumerate()
            {
                let bi = (item * ROWS + j) / n;
                g.corners(&point(row), true, cs);
                let fb = &f[bi * c * p..(bi + 1) * c * p];
                let mut acc = [0.0f64; 3];
                for q in 0..cs.n {
                    let mut s = 0.0;
                    for ch in 0..c {
                        s += grow[ch].to_f64() * fb[ch * p + cs.offset[q]].to_f64();
                    }
                    for (a, d) in acc.iter_mut().zip(&cs.dweight[q]).take(k) {
                        *a += s * d;
                    }
                }
                for (oa, a) in o.iter_mut().zip(&acc) {
                    *oa = T::from_f64(*a);
                }
            }
        });
        out
    }
}

impl CpuKernel<2> for FusedGridSample {
    const NAME: &'static str = "grid sample";

    fn forward<T: Real>(&self, [f, x]: [&[T]; 2]) -> candle_core::Result<(Vec<T>, Shape)> {
        Ok((self.run(f, x), Shape::from(self.dims)))
    }

    fn backward<T: Real>(
        &self,
        [f, x]: [&[T]; 2],
        grad: &[T],
        [want_f, want_x]: [bool; 2],
    ) -> candle_core::Result<[Option<Vec<T>>; 2]> {
        let gf = want_f.then(|| self.features_grad(x, grad));
        let gx = want_x.then(|| self.coords_grad(f, x, grad));
        Ok([gf, gx])
    }
}

cpu_op!(FusedGridSample, 2, "nf-grid-sample", cuda);

#[cfg(feature = "cuda")]
#[path = "cuda/grid_sample.rs"]
mod cuda;
