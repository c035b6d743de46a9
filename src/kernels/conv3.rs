//! A 3×3×3 convolution with zero padding 1, stride 1 or 2, on channels-last grids, with
//! its bias and an optional ReLU on its input, as one CPU op (`FusedConv3`, what the voxel
//! encoder runs on the CPU). Each tile of output voxels gathers its `27·Cᵢ` inputs into a
//! per-worker buffer and multiplies it by the weight; the backward pass regathers the same
//! tiles, so neither pass holds the `[B·n³, 27·Cᵢ]` window matrix that the reference path
//! (candle's `index_select`, matrix product, bias and ReLU ops) allocates, and the input
//! gradient is scattered straight into its grid instead of through `index_add` and
//! candle's gradient sums.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::mlp::{matmul, View};
use super::parallel::for_each_init;
use candle_core::Shape;

/// Taps of a 3×3×3 kernel.
const TAPS: usize = 27;
/// A tap's input row when the tap falls in the padding.
const OUTSIDE: usize = usize::MAX;
/// Elements of a tile's gathered windows (rows × `27·Cᵢ`) that the tile size aims at.
const TILE_ELEMS: usize = 32_768;
/// Grids per backward work item, at most: the items keep one weight gradient each, so
/// the batch is split into at most this many (a count that does not depend on the
/// machine, so neither do the sums).
const MAX_ITEMS: usize = 8;

/// `y[b, o, j] = bias[j] + Σ_{t, i} w[j, i, t] · a(x)[b, s·o + t − 1, i]` for grids
/// `x: [B, side³, Cᵢ]` (voxel `(p, q, r)` at row `(p·side + q)·side + r`), weight
/// `w: [Cₒ, Cᵢ, 3, 3, 3]` (PyTorch's `Conv3d` layout, tap `t = (a·3 + b)·3 + c`), bias
/// `[Cₒ]`; output `[B, n³, Cₒ]` with `n = side / stride`; `a = ReLU` when `relu_input`,
/// else the identity; taps outside the grid read zero.
///
/// Backward: `∂L/∂bias = Σ_{b,o} g`, `∂L/∂w[j, i, t] = Σ_{b,o} g[b, o, j] · a(x)[b, s·o + t − 1, i]`,
/// `∂L/∂x[b, v, i] = a'(x[b, v, i]) · Σ_{(o, t) → v} Σ_j g[b, o, j] · w[j, i, t]`, with
/// `a'(x) = [x ≥ 0]` for the ReLU (candle's subgradient at 0).
#[derive(Clone, Debug)]
pub(crate) struct FusedConv3 {
    pub(crate) batch: usize,
    pub(crate) side: usize,
    pub(crate) stride: usize,
    pub(crate) c_in: usize,
    pub(crate) c_out: usize,
    pub(crate) relu_input: bool,
}

/// Per-worker scratch: one tile's gathered windows and its window gradients.
struct Scratch<T> {
    cols: Vec<T>,
    dcols: Vec<T>,
}

impl FusedConv3 {
    /// Side of the output grid.
    fn out_side(&self) -> usize {
        self.side / self.stride
    }

    /// Columns of the window matrix, `27·Cᵢ`.
    fn k(&self) -> usize {
        TAPS * self.c_in
    }

    /// Output voxels per tile.
    fn tile_rows(&self) -> usize {
        (TILE_ELEMS / self.k().max(1)).clamp(6, 256)
    }

    fn scratch<T: Real>(&self, dcols: bool) -> Scratch<T> {
        let len = self.tile_rows() * self.k();
        Scratch {
            cols: vec![T::from_f64(0.0); len],
            dcols: if dcols {
                vec![T::from_f64(0.0); len]
            } else {
                Vec::new()
            },
        }
    }

    /// The input rows (within its grid) of output voxel `o`'s 27 taps, [`OUTSIDE`] for a
    /// tap in the padding.
    #[inline(always)]
    fn window(&self, o: usize) -> [usize; TAPS] {
        let (n, side, s) = (self.out_side(), self.side, self.stride);
        // The input coordinates of the three taps along one axis.
        let along = |o: usize| {
            let mut p = [OUTSIDE; 3];
            for (a, p) in p.iter_mut().enumerate() {
                if let Some(q) = (s * o + a).checked_sub(1).filter(|&q| q < side) {
                    *p = q;
                }
            }
            p
        };
        let (pi, pj, pk) = (along(o / (n * n)), along((o / n) % n), along(o % n));
        let mut w = [OUTSIDE; TAPS];
        for (t, w) in w.iter_mut().enumerate() {
            let (a, b, c) = (pi[t / 9], pj[(t / 3) % 3], pk[t % 3]);
            if a != OUTSIDE && b != OUTSIDE && c != OUTSIDE {
                *w = (a * side + b) * side + c;
            }
        }
        w
    }

    /// Gathers the windows of output voxels `o0 .. o0 + rows` of grid `grid: [side³, Cᵢ]`
    /// into `cols: [rows, 27·Cᵢ]`, through the input activation.
    fn gather<T: Real>(&self, grid: &[T], o0: usize, rows: usize, cols: &mut [T]) {
        let ci = self.c_in;
        let zero = T::from_f64(0.0);
        let act = |x: T| {
            if !self.relu_input || x > zero {
                x
            } else {
                zero
            }
        };
        if ci == 1 {
            // One channel (the encoder's first convolution): one value per tap.
            for (r, row) in cols[..rows * TAPS].chunks_mut(TAPS).enumerate() {
                for (&v, d) in self.window(o0 + r).iter().zip(row) {
                    *d = if v == OUTSIDE { zero } else { act(grid[v]) };
                }
            }
            return;
        }
        for (r, row) in cols[..rows * TAPS * ci].chunks_mut(TAPS * ci).enumerate() {
            for (&v, dst) in self.window(o0 + r).iter().zip(row.chunks_mut(ci)) {
                if v == OUTSIDE {
                    dst.fill(zero);
                    continue;
                }
                let src = &grid[v * ci..(v + 1) * ci];
                if self.relu_input {
                    for (d, &x) in dst.iter_mut().zip(src) {
                        *d = if x > zero { x } else { zero };
                    }
                } else {
                    for (d, &x) in dst.iter_mut().zip(src) {
                        *d = x;
                    }
                }
            }
        }
    }

    /// The weight as `[27·Cᵢ, Cₒ]` (row `t·Cᵢ + i`, column `j`; the forward pass's), or
    /// with `by_output` as `[Cₒ, 27·Cᵢ]` (the backward pass's), row-major.
    fn weight_matrix<T: Real>(&self, w: &[T], by_output: bool) -> Vec<T> {
        let (ci, co, k) = (self.c_in, self.c_out, self.k());
        let mut m = vec![T::from_f64(0.0); k * co];
        for j in 0..co {
            for i in 0..ci {
                for t in 0..TAPS {
                    let at = if by_output {
                        j * k + t * ci + i
                    } else {
                        (t * ci + i) * co + j
                    };
                    m[at] = w[(j * ci + i) * TAPS + t];
                }
            }
        }
        m
    }

    fn check<T>(&self, [x, w, b]: [&[T]; 3]) -> candle_core::Result<()> {
        let (n, side) = (self.out_side(), self.side);
        if self.stride == 0 || side == 0 || n * self.stride != side {
            candle_core::bail!("fused conv3: side {side} with stride {}", self.stride)
        }
        let want = [
            self.batch * side.pow(3) * self.c_in,
            self.c_out * self.k(),
            self.c_out,
        ];
        if [x.len(), w.len(), b.len()] != want {
            candle_core::bail!(
                "fused conv3: input lengths {:?}, expected {want:?}",
                [x.len(), w.len(), b.len()]
            )
        }
        Ok(())
    }

    fn forward<T: Real>(&self, x: &[T], w: &[T], bias: &[T]) -> Vec<T> {
        let (co, k) = (self.c_out, self.k());
        let (n3, grid_len) = (self.out_side().pow(3), self.side.pow(3) * self.c_in);
        let wk = self.weight_matrix(w, false);
        let tile = self.tile_rows();
        let mut y = vec![T::from_f64(0.0); self.batch * n3 * co];
        // Tiles never straddle two grids: each grid's rows are cut on their own.
        let items: Vec<(usize, usize, &mut [T])> = y
            .chunks_mut(n3 * co)
            .enumerate()
            .flat_map(|(g, rows)| {
                rows.chunks_mut(tile * co)
                    .enumerate()
                    .map(move |(i, y)| (g, i * tile, y))
            })
            .collect();
        for_each_init(
            items,
            || self.scratch::<T>(false),
            |sc, (g, o0, y)| {
                let rows = y.len() / co;
                self.gather(&x[g * grid_len..(g + 1) * grid_len], o0, rows, &mut sc.cols);
                for row in y.chunks_mut(co) {
                    row.copy_from_slice(bias);
                }
                matmul(
                    (rows, co, k),
                    y,
                    View::rows(0, co),
                    true,
                    &sc.cols,
                    View::rows(0, k),
                    &wk,
                    View::rows(0, co),
                    T::from_f64(1.0),
                );
            },
        );
        y
    }

    /// `[∂L/∂x if wanted, ∂L/∂w, ∂L/∂bias]`.
    fn backward<T: Real>(
        &self,
        [x, w, _]: [&[T]; 3],
        g: &[T],
        want_x: bool,
    ) -> [Option<Vec<T>>; 3] {
        let (ci, co, k) = (self.c_in, self.c_out, self.k());
        let (n3, grid_len) = (self.out_side().pow(3), self.side.pow(3) * self.c_in);
        let wj = self.weight_matrix(w, true);
        let tile = self.tile_rows();
        let per_item = self.batch.div_ceil(MAX_ITEMS).max(1);
        let items_n = self.batch.div_ceil(per_item);
        // Per item: the weight gradient as `[Cₒ, 27·Cᵢ]`, then the bias gradient.
        let mut partial = vec![T::from_f64(0.0); items_n * (co * k + co)];
        let mut gx = want_x.then(|| vec![T::from_f64(0.0); x.len()]);
        let gx_items: Vec<Option<&mut [T]>> = match gx.as_mut() {
            Some(v) => v.chunks_mut(per_item * grid_len).map(Some).collect(),
            None => (0..items_n).map(|_| None).collect(),
        };
        let items: Vec<_> = partial
            .chunks_mut(co * k + co)
            .zip(gx_items)
            .enumerate()
            .collect();
        for_each_init(
            items,
            || self.scratch::<T>(want_x),
            |sc, (item, (acc, mut gx))| {
                let (gw, gb) = acc.split_at_mut(co * k);
                let first = item * per_item;
                for grid in first..(first + per_item).min(self.batch) {
                    let xg = &x[grid * grid_len..(grid + 1) * grid_len];
                    let local = grid - first;
                    for o0 in (0..n3).step_by(tile) {
                        let rows = tile.min(n3 - o0);
                        let gt = &g[(grid * n3 + o0) * co..(grid * n3 + o0 + rows) * co];
                        self.gather(xg, o0, rows, &mut sc.cols);
                        // ∂L/∂W [Cₒ, 27·Cᵢ] += gᵀ · cols.
                        matmul(
                            (co, k, rows),
                            gw,
                            View::rows(0, k),
                            true,
                            gt,
                            View::transposed(0, co),
                            &sc.cols,
                            View::rows(0, k),
                            T::from_f64(1.0),
                        );
                        for row in gt.chunks(co) {
                            for (b, &v) in gb.iter_mut().zip(row) {
                                *b += v;
                            }
                        }
                        let Some(gx) = gx.as_deref_mut() else {
                            continue;
                        };
                        // ∂L/∂cols [rows, 27·Cᵢ] = g · W, scattered onto the taps' voxels.
                        matmul(
                            (rows, k, co),
                            &mut sc.dcols,
                            View::rows(0, k),
                            false,
                            gt,
                            View::rows(0, co),
                            &wj,
                            View::rows(0, k),
                            T::from_f64(1.0),
                        );
                        let gxg = &mut gx[local * grid_len..(local + 1) * grid_len];
                        for (r, row) in sc.dcols[..rows * k].chunks(k).enumerate() {
                            for (&v, src) in self.window(o0 + r).iter().zip(row.chunks(ci)) {
                                if v == OUTSIDE {
                                    continue;
                                }
                                for (d, &s) in gxg[v * ci..(v + 1) * ci].iter_mut().zip(src) {
                                    *d += s;
                                }
                            }
                        }
                    }
                    if self.relu_input {
                        if let Some(gx) = gx.as_deref_mut() {
                            let gxg = &mut gx[local * grid_len..(local + 1) * grid_len];
                            for (d, &v) in gxg.iter_mut().zip(xg) {
                                if v < T::from_f64(0.0) {
                                    *d = T::from_f64(0.0);
                                }
                            }
                        }
                    }
                }
            },
        );
        // Sum the items' gradients in item order, then back to `[Cₒ, Cᵢ, 27]`.
        let (first, rest) = partial.split_at_mut(co * k + co);
        for p in rest.chunks(co * k + co) {
            for (a, &b) in first.iter_mut().zip(p) {
                *a += b;
            }
        }
        let mut gw = vec![T::from_f64(0.0); co * k];
        for j in 0..co {
            for i in 0..ci {
                for t in 0..TAPS {
                    gw[(j * ci + i) * TAPS + t] = first[j * k + t * ci + i];
                }
            }
        }
        let gb = first[co * k..].to_vec();
        [gx, Some(gw), Some(gb)]
    }
}

impl CpuKernel<3> for FusedConv3 {
    const NAME: &'static str = "fused conv3";

    /// Inputs `(x [B, side³, Cᵢ], w [Cₒ, Cᵢ, 3, 3, 3], bias [Cₒ])`; output `[B, n³, Cₒ]`.
    fn forward<T: Real>(&self, inputs: [&[T]; 3]) -> candle_core::Result<(Vec<T>, Shape)> {
        self.check(inputs)?;
        let [x, w, b] = inputs;
        let n3 = self.out_side().pow(3);
        Ok((
            FusedConv3::forward(self, x, w, b),
            Shape::from((self.batch, n3, self.c_out)),
        ))
    }

    fn backward<T: Real>(
        &self,
        inputs: [&[T]; 3],
        g: &[T],
        [want_x, _, _]: [bool; 3],
    ) -> candle_core::Result<[Option<Vec<T>>; 3]> {
        self.check(inputs)?;
        if g.len() != self.batch * self.out_side().pow(3) * self.c_out {
            candle_core::bail!("fused conv3: gradient of {} elements", g.len())
        }
        Ok(FusedConv3::backward(self, inputs, g, want_x))
    }
}
cpu_op!(FusedConv3, 3, "nf-fused-conv3");
