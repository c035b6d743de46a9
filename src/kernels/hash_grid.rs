//! instant-NGP's multiresolution hash encoding as one CPU op (`FusedHashGrid`, what
//! [`crate::encoding::HashGrid`] runs on the CPU): the level geometry it shares with the
//! encoding's reference path ([`HashPlan`], built by the encoding from its
//! configuration), the corners of a point at a level, and the forward pass, the table
//! gradient and the position gradient over points.
//!
//! With the `cuda` feature, the same op runs its CUDA kernels (`cuda/hash_grid.cu`) for
//! CUDA tensors.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::parallel::for_each_init;
use candle_core::{Shape, WithDType};
use std::sync::Arc;

/// instant-NGP's hashing primes, one per input dimension.
const PRIMES: [u32; 4] = [1, 2_654_435_761, 805_459_861, 3_674_653_429];

/// Points per work item of the fused forward and position-gradient passes.
const ROWS: usize = 512;

/// One level: cells per axis, first row in the concatenated table, rows, dense or hashed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct HashLevel {
    /// Cells per axis `N_l`.
    pub(crate) cells: u32,
    /// The level's first row in the concatenated table.
    pub(crate) offset: usize,
    /// The level's rows `T_l`.
    pub(crate) rows: usize,
    /// Dense indexing (`true`) or the spatial hash.
    pub(crate) dense: bool,
}

/// The level geometry shared by the fused op and the reference path.
#[derive(Debug)]
pub(crate) struct HashPlan {
    /// Input dimension `D` (1 to 4).
    pub(crate) d: usize,
    /// Features per level `F`.
    pub(crate) f: usize,
    /// The levels, coarsest first.
    pub(crate) levels: Vec<HashLevel>,
    /// The scene box's lower corner (`D` values).
    pub(crate) lo: Vec<f64>,
    /// The scene box's upper corner (`D` values).
    pub(crate) hi: Vec<f64>,
    /// `2ᵀ − 1`, the mask of a hashed level's rows.
    pub(crate) mask: u32,
    /// CUDA: the table gradient in fixed point (order-independent bits) instead of f64
    /// atomics. The CPU kernel sums in a fixed order either way.
    #[cfg_attr(not(feature = "cuda"), allow(dead_code))]
    pub(crate) deterministic: bool,
}

/// The corners of one point at one level: table rows, weights and, per axis, the
/// derivative of each weight w.r.t. the position (zero outside the box).
pub(crate) struct HashCorners {
    /// Corners in use, `2ᴰ`.
    pub(crate) n: usize,
    /// Each corner's row in the concatenated table.
    pub(crate) rows: [usize; 16],
    /// Each corner's interpolation weight.
    pub(crate) weights: [f64; 16],
    /// Each corner's weight derivative per position axis.
    pub(crate) dweights: [[f64; 4]; 16],
}

impl HashCorners {
    /// Scratch for [`HashPlan::corners`].
    pub(crate) fn new() -> Self {
        Self {
            n: 0,
            rows: [0; 16],
            weights: [0.0; 16],
            dweights: [[0.0; 4]; 16],
        }
    }
}

impl HashPlan {
    /// The normalised coordinates `t` of a point and `dt/dx` (zero where clamped).
    pub(crate) fn unit(&self, x: &[f64], t: &mut [f64; 4], dt: &mut [f64; 4]) {
        for k in 0..self.d {
            let ext = self.hi[k] - self.lo[k];
            let v = (x[k] - self.lo[k]) / ext;
            let inside = (0.0..=1.0).contains(&v);
            t[k] = v.clamp(0.0, 1.0);
            dt[k] = if inside { 1.0 / ext } else { 0.0 };
        }
    }

    /// [`HashPlan::unit`] of one row of a tensor's elements: `(t, dt/dx)`.
    fn unit_of<T: WithDType>(&self, row: &[T]) -> ([f64; 4], [f64; 4]) {
        let mut x = [0.0f64; 4];
        for (xk, r) in x.iter_mut().zip(row) {
            *xk = r.to_f64();
        }
        let (mut t, mut dt) = ([0.0; 4], [0.0; 4]);
        self.unit(&x, &mut t, &mut dt);
        (t, dt)
    }

    /// The cell, local coordinates and corners of normalised point `t` at `level`, and
    /// with `grads` the weights' derivatives w.r.t. the position. The corners are built
    /// axis by axis (corner `c` takes `i_k + 1` on axis `k` when bit `k` of `c` is set):
    /// `2ᴰ⁺¹` products instead of `D·2ᴰ`.
    pub(crate) fn corners(
        &self,
        level: &HashLevel,
        t: &[f64; 4],
        dt: &[f64; 4],
        grads: bool,
        out: &mut HashCorners,
    ) {
        let d = self.d;
        let n = f64::from(level.cells);
        let side = u64::from(level.cells) + 1;
        let mut stride = 1u64;
        out.n = 1;
        out.weights[0] = 1.0;
        let mut index = [0u64; 16];
        let mut hash = [0u32; 16];
        if grads {
            out.dweights[0] = [1.0; 4];
        }
        for k in 0..d {
            let u = t[k] * n;
            // t ∈ [0, 1], so u ∈ [0, N] and the cast is exact below 2³².
            let i = (u.floor() as u32).min(level.cells - 1);
            let w = u - f64::from(i);
            let dw = n * dt[k];
            let half = out.n;
            for c in 0..half {
                let hi = c + half;
                out.weights[hi] = out.weights[c] * w;
                out.weights[c] *= 1.0 - w;
                index[hi] = index[c] + u64::from(i + 1) * stride;
                index[c] += u64::from(i) * stride;
                hash[hi] = hash[c] ^ (i + 1).wrapping_mul(PRIMES[k]);
                hash[c] ^= i.wrapping_mul(PRIMES[k]);
                if grads {
                    let mut g = out.dweights[c];
                    for (j, (lo, up)) in g
                        .iter_mut()
                        .zip(out.dweights[hi].iter_mut())
                        .enumerate()
                        .take(d)
                    {
                        if j == k {
                            *up = *lo * dw;
                            *lo *= -dw;
                        } else {
                            *up = *lo * w;
                            *lo *= 1.0 - w;
                        }
                    }
                    out.dweights[c] = g;
                }
            }
            out.n *= 2;
            stride *= side;
        }
        for c in 0..out.n {
            let local = if level.dense {
                index[c] as usize
            } else {
                (hash[c] & self.mask) as usize
            };
            out.rows[c] = level.offset + local;
        }
    }

    /// Output columns, `L·F`.
    pub(crate) fn width(&self) -> usize {
        self.levels.len() * self.f
    }
}

/// The fused CPU op: `(x [N, D], table [R, F]) → [N, L·F]`. Its backward pass
/// accumulates the table gradient level by level, each level's points in order (the same
/// bit for bit at any thread count), and computes the position gradient only when the
/// positions are on the autograd graph.
pub(crate) struct FusedHashGrid(pub(crate) Arc<HashPlan>);

impl FusedHashGrid {
    fn run<T: WithDType>(&self, x: &[T], table: &[T]) -> Vec<T> {
        let p = &*self.0;
        let (d, f, w) = (p.d, p.f, p.width());
        let mut out = vec![T::from_f64(0.0); (x.len() / d) * w];
        let items: Vec<_> = out.chunks_mut(ROWS * w).zip(x.chunks(ROWS * d)).collect();
        for_each_init(items, HashCorners::new, |c, (out, x)| {
            for (o, row) in out.chunks_mut(w).zip(x.chunks(d)) {
                let (t, dt) = p.unit_of(row);
                for (l, level) in p.levels.iter().enumerate() {
                    p.corners(level, &t, &dt, false, c);
                    for j in 0..f {
                        let mut acc = 0.0;
                        for k in 0..c.n {
                            acc += c.weights[k] * table[c.rows[k] * f + j].to_f64();
                        }
                        o[l * f + j] = T::from_f64(acc);
                    }
                }
            }
        });
        out
    }

    /// The table gradient: level by level, each level's points in order (deterministic
    /// at any thread count), accumulated in f64.
    fn table_grad<T: WithDType>(&self, x: &[T], g: &[T]) -> Vec<T> {
        let p = &*self.0;
        let (d, f, w) = (p.d, p.f, p.width());
        let total: usize = p.levels.iter().map(|l| l.rows).sum();
        let mut grads = vec![T::from_f64(0.0); total * f];
        let mut parts: Vec<&mut [T]> = Vec::with_capacity(p.levels.len());
        let mut rest = grads.as_mut_slice();
        for level in &p.levels {
            let (head, tail) = rest.split_at_mut(level.rows * f);
            parts.push(head);
            rest = tail;
        }
        let items: Vec<_> = parts.into_iter().zip(p.levels.iter().enumerate()).collect();
        for_each_init(items, HashCorners::new, |c, (part, (l, level))| {
            let mut acc = vec![0.0f64; level.rows * f];
            for (row, gr) in x.chunks(d).zip(g.chunks(w)) {
                let (t, dt) = p.unit_of(row);
                p.corners(level, &t, &dt, false, c);
                for j in 0..f {
                    let gj = gr[l * f + j].to_f64();
                    if gj == 0.0 {
                        continue;
                    }
                    for k in 0..c.n {
                        acc[(c.rows[k] - level.offset) * f + j] += c.weights[k] * gj;
                    }
                }
            }
            for (o, a) in part.iter_mut().zip(&acc) {
                *o = T::from_f64(*a);
            }
        });
        grads
    }

    /// The position gradient, point by point.
    fn position_grad<T: WithDType>(&self, x: &[T], table: &[T], g: &[T]) -> Vec<T> {
        let p = &*self.0;
        let (d, f, w) = (p.d, p.f, p.width());
        let mut gx = vec![T::from_f64(0.0); x.len()];
        let items: Vec<_> = gx
            .chunks_mut(ROWS * d)
            .zip(x.chunks(ROWS * d))
            .zip(g.chunks(ROWS * w))
            .collect();
        for_each_init(items, HashCorners::new, |c, ((gx, x), g)| {
            for ((o, row), gr) in gx.chunks_mut(d).zip(x.chunks(d)).zip(g.chunks(w)) {
                let (t, dt) = p.unit_of(row);
                let mut acc = [0.0f64; 4];
                for (l, level) in p.levels.iter().enumerate() {
                    p.corners(level, &t, &dt, true, c);
                    for k in 0..c.n {
                        let mut s = 0.0;
                        for j in 0..f {
                            s += gr[l * f + j].to_f64() * table[c.rows[k] * f + j].to_f64();
                        }
                        for (a, dw) in acc.iter_mut().zip(&c.dweights[k]).take(d) {
                            *a += s * dw;
                        }
                    }
                }
                for k in 0..d {
                    o[k] = T::from_f64(acc[k]);
                }
            }
        });
        gx
    }
}

impl CpuKernel<2> for FusedHashGrid {
    const NAME: &'static str = "hash grid";

    fn forward<T: Real>(&self, [x, table]: [&[T]; 2]) -> candle_core::Result<(Vec<T>, Shape)> {
        let rows = x.len() / self.0.d;
        Ok((self.run(x, table), Shape::from((rows, self.0.width()))))
    }

    /// The table gradient always, the position gradient when `x` is on the graph.
    fn backward<T: Real>(
        &self,
        [x, table]: [&[T]; 2],
        grad: &[T],
        [want_x, _]: [bool; 2],
    ) -> candle_core::Result<[Option<Vec<T>>; 2]> {
        let gt = self.table_grad(x, grad);
        let gx = want_x.then(|| self.position_grad(x, table, grad));
        Ok([gx, Some(gt)])
    }
}

cpu_op!(FusedHashGrid, 2, "nf-hash-grid", cuda);

#[cfg(feature = "cuda")]
#[path = "cuda/hash_grid.rs"]
mod cuda;
