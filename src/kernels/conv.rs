//! A convolution with zero padding of channels-last 3-D grids or 2-D images, with its bias
//! and an optional ReLU on its input, as one CPU op (`FusedConv`: the voxel encoder's
//! 3×3×3 convolutions and the image encoder's k×k ones on the CPU). Each tile of output
//! cells gathers its `taps·Cᵢ` inputs into a per-worker buffer and multiplies it by the
//! weight; the backward pass regathers the same tiles, so neither pass holds the
//! `[B·cells, taps·Cᵢ]` window matrix that a reference path (candle's `index_select` or
//! `conv2d`, matrix product, bias and ReLU ops) allocates, and the input gradient is
//! scattered straight into its grid instead of through `index_add` or a transposed
//! convolution. A one-channel input (the voxel encoder's first convolution, three values
//! per window row) is computed by lines of output cells straight from the grid instead
//! ([`Lines`]): its window matrix would be 27 times the grid for a 27-deep product. The
//! weight matrices and the backward pass's per-item partial sums come from a
//! [`BufferPool`] (the chain's, kept between steps), so a large layer's are not faulted in
//! afresh on every call.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::mlp::{matmul, View};
use super::parallel::{for_each_init, wide, Wide};
use super::pool::BufferPool;
use candle_core::Shape;
use std::any::Any;
use std::sync::{Arc, Mutex, PoisonError};

/// Elements of a tile's gathered windows (rows × `taps·Cᵢ`) that the tile size aims at.
const TILE_ELEMS: usize = 32_768;
/// Output rows per tile of the backward pass, at least.
const DEPTH_ROWS: usize = 128;
/// Grids per backward work item are chosen so that there are at most this many items:
/// the items keep one weight gradient each (a count that does not depend on the machine,
/// so neither do the sums).
const MAX_ITEMS: usize = 8;
/// Output rows per backward work item, at least (fewer items for small outputs, so that
/// a late stage does not zero and sum eight copies of a large weight for a few rows).
const ITEM_ROWS: usize = 64;
/// Outputs per register group of a one-channel convolution (16 f32 values fill one
/// AVX-512 register).
const LANES: usize = 16;
/// Forward work items of a one-channel convolution (lines of output cells split into
/// about this many).
const LINE_ITEMS: usize = 64;
/// Output cells of a line that the one-channel path computes together, each in its own
/// registers (independent sums, so the additions overlap instead of waiting on one
/// another).
const LINE_BLOCK: usize = 8;

/// `y[b, o, j] = bias[j] + Σ_{t, i} w[j, i, t] · a(x)[b, s·o + t − p, i]` for grids
/// `x: [B, D·H·W, Cᵢ]` (cell `(d, h, w)` at row `(d·H + h)·W + w`; an image has `D = 1`),
/// weight `w: [Cₒ, Cᵢ, k_D, k_H, k_W]` (PyTorch's `Conv3d`/`Conv2d` layout, tap
/// `t = (a·k_H + b)·k_W + c`), bias `[Cₒ]`; output `[B, D'·H'·W', Cₒ]` with
/// `n' = ⌊(n + 2p − k)/s⌋ + 1` per axis (PyTorch's sizes); `a = ReLU` when `relu_input`,
/// else the identity; taps outside the grid read zero.
///
/// Backward: `∂L/∂bias = Σ_{b,o} g`, `∂L/∂w[j, i, t] = Σ_{b,o} g[b, o, j] · a(x)[b, s·o + t − p, i]`,
/// `∂L/∂x[b, v, i] = a'(x[b, v, i]) · Σ_{(o, t) → v} Σ_j g[b, o, j] · w[j, i, t]`, with
/// `a'(x) = [x ≥ 0]` for the ReLU (candle's subgradient at 0).
#[derive(Clone, Debug)]
pub(crate) struct FusedConv {
    pub(crate) batch: usize,
    /// Input extent per axis, `[D, H, W]` (an image: `[1, H, W]`).
    pub(crate) size: [usize; 3],
    /// Kernel extent per axis (`[3, 3, 3]`; an image's `[1, k, k]`).
    pub(crate) kernel: [usize; 3],
    /// Zero padding per axis (an image's `[0, p, p]`).
    pub(crate) pad: [usize; 3],
    /// The stride, the same on every axis (an axis of extent 1 with kernel 1 and no padding
    /// keeps extent 1 at any stride).
    pub(crate) stride: usize,
    pub(crate) c_in: usize,
    pub(crate) c_out: usize,
    pub(crate) relu_input: bool,
    /// Where the op, run on its own, takes its weight matrix and partial sums from
    /// between calls (a fresh pool per call without one; a [`FusedConvStack`] passes its
    /// own).
    pub(crate) pool: Option<Arc<BufferPool>>,
}

/// The coordinates of cell `o` of a grid of extents `out` (row-major, the last axis
/// fastest).
#[inline(always)]
fn cell(o: usize, out: [usize; 3]) -> [usize; 3] {
    [o / (out[1] * out[2]), (o / out[2]) % out[1], o % out[2]]
}

/// Per-worker scratch: one tile's gathered windows and its window gradients.
struct Scratch<T> {
    cols: Vec<T>,
    dcols: Vec<T>,
}

impl FusedConv {
    /// A 3×3×3 convolution with padding 1 of cubic grids of side `side`.
    pub(crate) fn cubic(
        batch: usize,
        side: usize,
        stride: usize,
        [c_in, c_out]: [usize; 2],
        relu_input: bool,
    ) -> Self {
        Self {
            batch,
            size: [side; 3],
            kernel: [3; 3],
            pad: [1; 3],
            stride,
            c_in,
            c_out,
            relu_input,
            pool: None,
        }
    }

    /// A `k × k` convolution with padding `⌊k/2⌋` of `h × w` images, its input taken as
    /// it is (no ReLU).
    pub(crate) fn square(
        batch: usize,
        [h, w]: [usize; 2],
        k: usize,
        stride: usize,
        [c_in, c_out]: [usize; 2],
    ) -> Self {
        Self {
            batch,
            size: [1, h, w],
            kernel: [1, k, k],
            pad: [0, k / 2, k / 2],
            stride,
            c_in,
            c_out,
            relu_input: false,
            pool: None,
        }
    }

    /// The op with its buffers kept in `pool` between calls.
    pub(crate) fn with_pool(self, pool: Arc<BufferPool>) -> Self {
        Self {
            pool: Some(pool),
            ..self
        }
    }

    /// `pool`, or `local` where the op has none.
    fn pool_or<'a>(&'a self, local: &'a BufferPool) -> &'a BufferPool {
        self.pool.as_deref().unwrap_or(local)
    }

    /// Output extent per axis; `None` where an axis is too small for its kernel or the
    /// stride is zero.
    pub(crate) fn out_size(&self) -> Option<[usize; 3]> {
        let mut out = [0; 3];
        for (o, ((&n, &p), &k)) in out
            .iter_mut()
            .zip(self.size.iter().zip(&self.pad).zip(&self.kernel))
        {
            *o = (n + 2 * p).checked_sub(k)?.checked_div(self.stride)? + 1;
        }
        Some(out)
    }

    /// Output cells per grid.
    fn out_cells(&self) -> usize {
        self.out_size().map_or(0, |o| o.iter().product())
    }

    /// Taps of the kernel.
    fn taps(&self) -> usize {
        self.kernel.iter().product()
    }

    /// Columns of the window matrix, `taps·Cᵢ`.
    fn k(&self) -> usize {
        self.taps() * self.c_in
    }

    /// Output cells per tile: about [`TILE_ELEMS`] gathered values, and in the backward
    /// pass at least [`DEPTH_ROWS`] (each tile adds its rows' products to the whole
    /// `Cₒ × taps·Cᵢ` weight gradient, so a shallow tile rereads it for few products).
    fn tile_rows(&self, backward: bool) -> usize {
        let rows = (TILE_ELEMS / self.k().max(1)).clamp(6, 256);
        if backward {
            rows.max(DEPTH_ROWS)
        } else {
            rows
        }
    }

    /// A worker's tile buffers for the forward or the backward pass (`dcols`: with the
    /// window gradient's).
    fn scratch<T: Real>(&self, backward: bool, dcols: bool) -> Scratch<T> {
        let len = self.tile_rows(backward) * self.k();
        Scratch {
            cols: vec![T::from_f64(0.0); len],
            dcols: if dcols {
                vec![T::from_f64(0.0); len]
            } else {
                Vec::new()
            },
        }
    }

    /// Calls `f(d, run)` for each row `(a, b)` of output cell `o`'s window (taps
    /// `(a, b, 0 … k_W − 1)`, columns `d … d + k_W·Cᵢ` of its window row): `run` is
    /// `Some((src, c0, c1))` where taps `c0 … c1 − 1` are inside the grid, their `(c1 −
    /// c0)·Cᵢ` inputs contiguous from element `src` of the grid (channels-last, so the
    /// taps along the last axis are one run), and the other taps of the row read zero;
    /// `None` where the whole row is outside.
    #[inline(always)]
    fn runs(
        &self,
        o: usize,
        out: [usize; 3],
        mut f: impl FnMut(usize, Option<(usize, usize, usize)>),
    ) {
        let (size, k, s, ci) = (self.size, self.kernel, self.stride, self.c_in);
        let at = cell(o, out);
        // The input coordinate of offset `a` on axis `axis`, if inside.
        let coord = |axis: usize, a: usize| {
            (s * at[axis] + a)
                .checked_sub(self.pad[axis])
                .filter(|&p| p < size[axis])
        };
        let first = s * at[2];
        let (c0, c1) = self.row_taps(first);
        let run = k[2] * ci;
        let mut d = 0;
        for a in 0..k[0] {
            let p = coord(0, a);
            for b in 0..k[1] {
                let row = match (p, coord(1, b)) {
                    (Some(p), Some(q)) if c1 > c0 => {
                        let r = first + c0 - self.pad[2];
                        Some((((p * size[1] + q) * size[2] + r) * ci, c0, c1))
                    }
                    _ => None,
                };
                f(d, row);
                d += run;
            }
        }
    }

    /// The taps `c0 … c1 − 1` along the last axis that read inside the grid for an output
    /// cell whose window starts at padded column `first` (`s·w'`).
    #[inline(always)]
    fn row_taps(&self, first: usize) -> (usize, usize) {
        let (n, k, p) = (self.size[2], self.kernel[2], self.pad[2]);
        let c0 = p.saturating_sub(first).min(k);
        (c0, (n + p).saturating_sub(first).clamp(c0, k))
    }

    /// The grid row of output cell `o`'s first tap where its whole window lies inside
    /// the grid (no padding read), else `None`.
    #[inline(always)]
    fn inside(&self, o: usize, out: [usize; 3]) -> Option<usize> {
        let (size, k, s) = (self.size, self.kernel, self.stride);
        let at = cell(o, out);
        let mut lo = [0; 3];
        for (((lo, at), (&p, &k)), &n) in lo
            .iter_mut()
            .zip(at)
            .zip(self.pad.iter().zip(&k))
            .zip(&size)
        {
            *lo = (s * at).checked_sub(p)?;
            if *lo + k > n {
                return None;
            }
        }
        Some(((lo[0] * size[1] + lo[1]) * size[2] + lo[2]) * self.c_in)
    }

    /// Gathers the windows of output rows `r0 .. r0 + rows` of the batch (row `g·cells + o`
    /// is cell `o` of grid `g`; a tile may span grids) from `x: [B, D·H·W, Cᵢ]` into
    /// `cols: [rows, taps·Cᵢ]`, through the input activation.
    fn gather<T: Real>(&self, x: &[T], r0: usize, rows: usize, sc: &mut Scratch<T>) {
        let (ci, k) = (self.c_in, self.k());
        let Some(out) = self.out_size() else { return };
        let (cells, grid_len) = (self.out_cells(), self.size.iter().product::<usize>() * ci);
        let zero = T::from_f64(0.0);
        let (relu, run) = (self.relu_input, self.kernel[2] * ci);
        let ([k0, k1, _], [_, s1, s2]) = (self.kernel, self.size);
        for (r, row) in sc.cols[..rows * k].chunks_mut(k).enumerate() {
            let (g, o) = ((r0 + r) / cells, (r0 + r) % cells);
            let grid = &x[g * grid_len..(g + 1) * grid_len];
            if ci == 1 && run == 3 && !relu {
                // Three values per window row (one input channel, the voxel encoder's
                // first convolution): inside the grid, fixed-size moves instead of a
                // call per row.
                if let Some(first) = self.inside(o, out) {
                    for (ab, dst) in row.chunks_exact_mut(3).enumerate() {
                        let src = first + ((ab / k1) * s1 + ab % k1) * s2;
                        dst.copy_from_slice(&grid[src..src + 3]);
                    }
                    debug_assert_eq!(row.len(), 3 * k0 * k1);
                    continue;
                }
            }
            self.runs(o, out, |d, taps| {
                let dst = &mut row[d..d + run];
                let Some((src, c0, c1)) = taps else {
                    dst.fill(zero);
                    return;
                };
                dst[..c0 * ci].fill(zero);
                dst[c1 * ci..].fill(zero);
                let (dst, src) = (&mut dst[c0 * ci..c1 * ci], &grid[src..src + (c1 - c0) * ci]);
                if relu {
                    for (d, &x) in dst.iter_mut().zip(src) {
                        *d = if x > zero { x } else { zero };
                    }
                } else {
                    dst.copy_from_slice(src);
                }
            });
        }
    }

    /// The weight as `[taps·Cᵢ, Cₒ]` (row `t·Cᵢ + i`, column `j`; the forward pass's), or
    /// with `by_output` as `[Cₒ, taps·Cᵢ]` (the backward pass's), row-major, in a buffer of
    /// `pool` (every value written).
    fn weight_matrix<T: Real>(&self, w: &[T], by_output: bool, pool: &BufferPool) -> Vec<T> {
        let (ci, co, k, taps) = (self.c_in, self.c_out, self.k(), self.taps());
        let mut m = pool.take::<T>(k * co);
        if by_output {
            // Row `j` is a transpose of `w`'s `[Cᵢ, taps]` block `j`.
            for (row, wj) in m.chunks_mut(k.max(1)).zip(w.chunks(k.max(1))) {
                for (i, wi) in wj.chunks(taps.max(1)).enumerate() {
                    for (t, &v) in wi.iter().enumerate() {
                        row[t * ci + i] = v;
                    }
                }
            }
            return m;
        }
        // Sixteen output channels at a time: each destination run is one cache line and
        // the sixteen source rows stay in the L1 cache.
        for j0 in (0..co).step_by(16) {
            let jn = (j0 + 16).min(co);
            for i in 0..ci {
                for t in 0..taps {
                    let at = (t * ci + i) * co;
                    for (jj, d) in m[at + j0..at + jn].iter_mut().enumerate() {
                        *d = w[((j0 + jj) * ci + i) * taps + t];
                    }
                }
            }
        }
        m
    }

    /// Whether the op runs by lines of output cells ([`Lines`]): one input channel and
    /// whole register groups of outputs. Otherwise by gathered tiles.
    fn by_lines(&self) -> bool {
        self.c_in == 1 && self.c_out.is_multiple_of(LANES)
    }

    fn check<T>(&self, [x, w, b]: [&[T]; 3]) -> candle_core::Result<()> {
        if self.out_size().is_none() {
            candle_core::bail!(
                "fused conv: input {:?} with kernel {:?}, padding {:?} and stride {}",
                self.size,
                self.kernel,
                self.pad,
                self.stride
            )
        }
        let want = [
            self.batch * self.size.iter().product::<usize>() * self.c_in,
            self.c_out * self.k(),
            self.c_out,
        ];
        if [x.len(), w.len(), b.len()] != want {
            candle_core::bail!(
                "fused conv: input lengths {:?}, expected {want:?}",
                [x.len(), w.len(), b.len()]
            )
        }
        Ok(())
    }

    /// Output elements, `B·cells'·Cₒ`.
    fn out_len(&self) -> usize {
        self.batch * self.out_cells() * self.c_out
    }

    /// Input elements, `B·D·H·W·Cᵢ`.
    fn in_len(&self) -> usize {
        self.batch * self.size.iter().product::<usize>() * self.c_in
    }

    /// The output into `y` (`out_len` values, every one written); the weight matrix in a
    /// buffer of `pool`.
    fn forward_into<T: Real>(&self, x: &[T], w: &[T], bias: &[T], y: &mut [T], pool: &BufferPool) {
        let (co, k) = (self.c_out, self.k());
        let wk = self.weight_matrix(w, false, pool);
        if self.by_lines() {
            self.forward_lines(x, &wk, bias, y);
            pool.give(wk);
            return;
        }
        let tile = self.tile_rows(false);
        let items: Vec<(usize, &mut [T])> = y
            .chunks_mut(tile * co)
            .enumerate()
            .map(|(i, y)| (i * tile, y))
            .collect();
        for_each_init(
            items,
            || self.scratch::<T>(false, false),
            |sc, (r0, y)| {
                let rows = y.len() / co;
                self.gather(x, r0, rows, sc);
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
        pool.give(wk);
    }

    /// `∂L/∂w` into `gw` (`[Cₒ, Cᵢ, k…]`), `∂L/∂bias` into `gb`, and `∂L/∂x` into `gx`
    /// where given (`x`'s length); every value of each written. The weight matrix and the
    /// work items' partial sums in buffers of `pool`.
    fn backward_into<T: Real>(
        &self,
        [x, w]: [&[T]; 2],
        g: &[T],
        gx: Option<&mut [T]>,
        [gw, gb]: [&mut [T]; 2],
        pool: &BufferPool,
    ) {
        let (ci, co, k, taps) = (self.c_in, self.c_out, self.k(), self.taps());
        let Some(out) = self.out_size() else {
            return;
        };
        let (cells, grid_len) = (self.out_cells(), self.size.iter().product::<usize>() * ci);
        // The one-channel path reads the weight by taps (`[taps, Cₒ]`), the other by outputs.
        let lines = self.by_lines();
        let wj = self.weight_matrix(w, !lines, pool);
        // Whole grids per item (each item scatters into its own grids only).
        let items_n = (self.batch * cells)
            .div_ceil(ITEM_ROWS)
            .clamp(1, MAX_ITEMS.min(self.batch.max(1)));
        let per_item = self.batch.div_ceil(items_n).max(1);
        let items_n = self.batch.div_ceil(per_item);
        // Per item: the weight gradient as `[Cₒ, taps·Cᵢ]` (the one-channel path's as
        // `[taps, Cₒ]`), then the bias gradient.
        let mut partial = pool.take::<T>(items_n * (co * k + co));
        partial.fill(T::from_f64(0.0));
        let want_x = gx.is_some();
        let gx_items: Vec<Option<&mut [T]>> = match gx {
            Some(v) => {
                v.fill(T::from_f64(0.0));
                v.chunks_mut(per_item * grid_len).map(Some).collect()
            }
            None => (0..items_n).map(|_| None).collect(),
        };
        let items: Vec<_> = partial
            .chunks_mut(co * k + co)
            .zip(gx_items)
            .enumerate()
            .collect();
        if lines {
            let lines_per_grid = cells / out[2].max(1);
            for_each_init(
                items,
                || (),
                |_, (item, (acc, gx))| {
                    let first = item * per_item;
                    let last = (first + per_item).min(self.batch);
                    let pass = LinePass::Backward {
                        g: &g[first * cells * co..last * cells * co],
                        acc,
                        gx,
                    };
                    wide(Lines {
                        conv: self,
                        x,
                        wk: &wj,
                        first: first * lines_per_grid,
                        pass,
                    });
                },
            );
        } else {
            self.backward_tiles(x, &wj, g, items, per_item, want_x);
        }
        // Sum the items' gradients in item order, then back to `[Cₒ, Cᵢ, taps]`.
        let (first, rest) = partial.split_at_mut(co * k + co);
        for p in rest.chunks(co * k + co) {
            for (a, &b) in first.iter_mut().zip(p) {
                *a += b;
            }
        }
        for j in 0..co {
            for i in 0..ci {
                for t in 0..taps {
                    gw[(j * ci + i) * taps + t] = if lines {
                        first[t * co + j]
                    } else {
                        first[j * k + t * ci + i]
                    };
                }
            }
        }
        gb.copy_from_slice(&first[co * k..]);
        pool.give(partial);
        pool.give(wj);
    }

    /// The backward pass's work items on gathered tiles (inputs of more than one channel):
    /// per item, `acc` (`[Cₒ, taps·Cᵢ]` then `[Cₒ]`) accumulates the weight's and the
    /// bias's gradients over the item's grids, and `gx` where given (the item's grids,
    /// zeroed) receives `∂L/∂x`.
    fn backward_tiles<T: Real>(
        &self,
        x: &[T],
        wj: &[T],
        g: &[T],
        items: Vec<WorkItem<'_, T>>,
        per_item: usize,
        want_x: bool,
    ) {
        let (ci, co, k) = (self.c_in, self.c_out, self.k());
        let Some(out) = self.out_size() else {
            return;
        };
        let (cells, grid_len) = (self.out_cells(), self.size.iter().product::<usize>() * ci);
        let tile = self.tile_rows(true);
        for_each_init(
            items,
            || self.scratch::<T>(true, want_x),
            |sc, (item, (acc, mut gx))| {
                let (gw, gb) = acc.split_at_mut(co * k);
                let first = item * per_item;
                let last = (first + per_item).min(self.batch);
                let end = last * cells;
                for r0 in (first * cells..end).step_by(tile) {
                    let rows = tile.min(end - r0);
                    let gt = &g[r0 * co..(r0 + rows) * co];
                    self.gather(x, r0, rows, sc);
                    // ∂L/∂W [Cₒ, taps·Cᵢ] += gᵀ · cols.
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
                    // ∂L/∂cols [rows, taps·Cᵢ] = g · W, scattered onto the taps' cells.
                    matmul(
                        (rows, k, co),
                        &mut sc.dcols,
                        View::rows(0, k),
                        false,
                        gt,
                        View::rows(0, co),
                        wj,
                        View::rows(0, k),
                        T::from_f64(1.0),
                    );
                    for (r, row) in sc.dcols[..rows * k].chunks(k).enumerate() {
                        let (grid, o) = ((r0 + r) / cells, (r0 + r) % cells);
                        let local = grid - first;
                        let gxg = &mut gx[local * grid_len..(local + 1) * grid_len];
                        self.runs(o, out, |d, taps| {
                            if let Some((dst, c0, c1)) = taps {
                                let src = &row[d + c0 * ci..d + c1 * ci];
                                let dst = &mut gxg[dst..dst + (c1 - c0) * ci];
                                for (d, &s) in dst.iter_mut().zip(src) {
                                    *d += s;
                                }
                            }
                        });
                    }
                }
                if self.relu_input {
                    if let Some(gx) = gx.as_deref_mut() {
                        let xs = &x[first * grid_len..last * grid_len];
                        for (d, &v) in gx.iter_mut().zip(xs) {
                            if v < T::from_f64(0.0) {
                                *d = T::from_f64(0.0);
                            }
                        }
                    }
                }
            },
        );
    }

    /// The output of a one-channel convolution into `y` (every value written), by lines
    /// of output cells straight from the grid ([`Lines`]); `wk` as `[taps, Cₒ]`.
    fn forward_lines<T: Real>(&self, x: &[T], wk: &[T], bias: &[T], y: &mut [T]) {
        let Some(out) = self.out_size() else {
            return;
        };
        let line = out[2] * self.c_out;
        let lines = y.len() / line.max(1);
        let per = lines.div_ceil(LINE_ITEMS).max(1);
        let items: Vec<(usize, &mut [T])> = y
            .chunks_mut(per * line)
            .enumerate()
            .map(|(i, y)| (i * per, y))
            .collect();
        for_each_init(
            items,
            || (),
            |_, (first, y)| {
                wide(Lines {
                    conv: self,
                    x,
                    wk,
                    first,
                    pass: LinePass::Forward { bias, y },
                })
            },
        );
    }
}

/// A backward work item: its index, its partial sums (`[Cₒ, taps·Cᵢ]` then `[Cₒ]`) and
/// its grids' input gradient where asked.
type WorkItem<'a, T> = (usize, (&'a mut [T], Option<&'a mut [T]>));

/// Lines of output cells of a one-channel convolution (`Cᵢ = 1`; line `(g, d', h')` is
/// the `W'` cells of grid `g` at `(d', h')`, lines numbered from `first` in that order),
/// computed straight from the grid: each window row's inputs along the line are copied
/// once, zero-padded, and each tap adds its input times its weight row `wk[t]`
/// (`wk: [taps, Cₒ]`), [`LANES`] outputs of [`LINE_BLOCK`] cells at a time in registers,
/// so no window matrix is gathered. `Cₒ` is a multiple of [`LANES`]. Run by [`wide`].
struct Lines<'a, T> {
    conv: &'a FusedConv,
    x: &'a [T],
    wk: &'a [T],
    first: usize,
    pass: LinePass<'a, T>,
}

enum LinePass<'a, T> {
    /// `y`: the lines' outputs (`W'·Cₒ` values each), every value written.
    Forward { bias: &'a [T], y: &'a mut [T] },
    /// `g`: the lines' cotangents, whole grids; `acc` accumulates `∂L/∂w` as `[taps, Cₒ]`
    /// then `∂L/∂bias`; `gx` (those grids, zeroed) receives `∂L/∂x`.
    Backward {
        g: &'a [T],
        acc: &'a mut [T],
        gx: Option<&'a mut [T]>,
    },
}

impl<T: Real> Wide for Lines<'_, T> {
    type Out = ();
    #[inline(always)]
    fn run(self) {
        let Lines {
            conv,
            x,
            wk,
            first,
            mut pass,
        } = self;
        let Some([_, oh_n, ow_n]) = conv.out_size() else {
            return;
        };
        let (co, zero) = (conv.c_out, T::from_f64(0.0));
        let groups = co / LANES;
        let wl = wk.as_chunks::<LANES>().0;
        let ([dn, hn, wn], [kd, kh, kw], [pd, ph, pw]) = (conv.size, conv.kernel, conv.pad);
        let (s, relu, grid_len) = (conv.stride, conv.relu_input, dn * hn * wn);
        let act = |v: T| {
            if relu && v.partial_cmp(&zero) != Some(std::cmp::Ordering::Greater) {
                zero
            } else {
                v
            }
        };
        let lines_per_grid = conv.out_cells() / ow_n.max(1);
        let line_len = ow_n * co;
        let n_lines = match &pass {
            LinePass::Forward { y, .. } => y.len(),
            LinePass::Backward { g, .. } => g.len(),
        } / line_len.max(1);
        let first_grid = first / lines_per_grid.max(1);
        // Each window row's inputs along the line, the activation applied and zeros
        // outside the grid: `pad[i] = a(x[s·w' + c − p])` at `i = s·w' + c`, long enough
        // for whole blocks of `LINE_BLOCK` cells.
        let plen = s * (ow_n.div_ceil(LINE_BLOCK) * LINE_BLOCK).saturating_sub(1) + kw;
        let mut pad: Vec<T> = Vec::with_capacity(kd * kh * plen);
        // The window rows `(a, b)` inside the grid for the current line: the grid offset
        // of the row's first cell and the tap index of `(a, b, 0)`.
        let mut rows: Vec<(usize, usize)> = Vec::with_capacity(kd * kh);
        for l in 0..n_lines {
            let line = first + l;
            let (gi, rem) = (line / lines_per_grid, line % lines_per_grid);
            let (od, oh) = (rem / oh_n, rem % oh_n);
            let grid = &x[gi * grid_len..(gi + 1) * grid_len];
            rows.clear();
            pad.clear();
            for a in 0..kd {
                let Some(id) = (s * od + a).checked_sub(pd).filter(|&p| p < dn) else {
                    continue;
                };
                for b in 0..kh {
                    if let Some(ih) = (s * oh + b).checked_sub(ph).filter(|&p| p < hn) {
                        let r0 = (id * hn + ih) * wn;
                        rows.push((r0, (a * kh + b) * kw));
                        let at = pad.len();
                        pad.resize(at + plen, zero);
                        let inside = pad[at..at + plen].iter_mut().skip(pw);
                        for (d, &v) in inside.zip(&grid[r0..r0 + wn]) {
                            *d = act(v);
                        }
                    }
                }
            }
            let ys = l * line_len..(l + 1) * line_len;
            match &mut pass {
                LinePass::Forward { bias, y } => {
                    // Per block of cells and group of `LANES` outputs, every tap into one
                    // register per cell.
                    let bias = bias.as_chunks::<LANES>().0;
                    let cells = y[ys].as_chunks_mut::<LANES>().0;
                    for (q, &b) in bias.iter().enumerate() {
                        for ow in (0..ow_n).step_by(LINE_BLOCK) {
                            let mut acc = [b; LINE_BLOCK];
                            for (prow, &(_, t0)) in pad.chunks_exact(plen).zip(&rows) {
                                for c in 0..kw {
                                    let w = &wl[(t0 + c) * groups + q];
                                    let xs = &prow[s * ow + c..];
                                    for (k, acc) in acc.iter_mut().enumerate() {
                                        let v = xs[s * k];
                                        for i in 0..LANES {
                                            acc[i] += v * w[i];
                                        }
                                    }
                                }
                            }
                            for (k, acc) in acc.iter().enumerate().take(ow_n - ow) {
                                cells[(ow + k) * groups + q] = *acc;
                            }
                        }
                    }
                }
                LinePass::Backward { g, acc, gx } => {
                    let gl = &g[ys];
                    let gc = gl.as_chunks::<LANES>().0;
                    // Per tap and group of `LANES` outputs, the line's cells into one
                    // register: `∂L/∂w[t] += Σ_{w'} a(x[tap]) · g[w']` (the padding's
                    // zeros add nothing).
                    let taps = kd * kh * kw;
                    for (prow, &(_, t0)) in pad.chunks_exact(plen).zip(&rows) {
                        for c in 0..kw {
                            let at = &mut acc[(t0 + c) * co..(t0 + c + 1) * co];
                            for (q, at) in at.as_chunks_mut::<LANES>().0.iter_mut().enumerate() {
                                let mut sum = [zero; LANES];
                                for ow in 0..ow_n {
                                    let (v, gv) = (prow[s * ow + c], &gc[ow * groups + q]);
                                    for i in 0..LANES {
                                        sum[i] += v * gv[i];
                                    }
                                }
                                for i in 0..LANES {
                                    at[i] += sum[i];
                                }
                            }
                        }
                    }
                    if let Some(gx) = gx.as_deref_mut() {
                        let gxg = &mut gx[(gi - first_grid) * grid_len..][..grid_len];
                        for &(r0, t0) in &rows {
                            for c in 0..kw {
                                let t = t0 + c;
                                // ∂L/∂x[tap] += Σ_j g[w', j] · w[j, t] (only when asked),
                                // for the cells whose tap `c` reads inside the row:
                                // `0 ≤ s·w' + c − p < W`.
                                let lo = pw.saturating_sub(c).div_ceil(s);
                                let hi = match (wn + pw).checked_sub(c + 1) {
                                    Some(v) => (v / s + 1).min(ow_n),
                                    None => 0,
                                };
                                for ow in lo..hi {
                                    let g = &gl[ow * co..(ow + 1) * co];
                                    let mut dot = zero;
                                    for (&g, &w) in g.iter().zip(&wk[t * co..]) {
                                        dot += g * w;
                                    }
                                    gxg[r0 + s * ow + c - pw] += dot;
                                }
                            }
                        }
                    }
                    for gc in gl.chunks_exact(co) {
                        for (b, &v) in acc[taps * co..(taps + 1) * co].iter_mut().zip(gc) {
                            *b += v;
                        }
                    }
                }
            }
        }
        // ∂L/∂x through the input ReLU: zero where the input is negative.
        if let LinePass::Backward { gx: Some(gx), .. } = pass {
            if relu {
                let xs = &x[first_grid * grid_len..first_grid * grid_len + gx.len()];
                for (d, &v) in gx.iter_mut().zip(xs) {
                    if v < zero {
                        *d = zero;
                    }
                }
            }
        }
    }
}

impl CpuKernel<3> for FusedConv {
    const NAME: &'static str = "fused conv";

    /// Inputs `(x [B, D·H·W, Cᵢ], w [Cₒ, Cᵢ, k_D, k_H, k_W], bias [Cₒ])` (any shape of
    /// these lengths); output `[B, D'·H'·W', Cₒ]`.
    fn forward<T: Real>(&self, inputs: [&[T]; 3]) -> candle_core::Result<(Vec<T>, Shape)> {
        self.check(inputs)?;
        let [x, w, b] = inputs;
        let mut y = vec![T::from_f64(0.0); self.out_len()];
        let local = BufferPool::default();
        self.forward_into(x, w, b, &mut y, self.pool_or(&local));
        Ok((y, Shape::from((self.batch, self.out_cells(), self.c_out))))
    }

    fn backward<T: Real>(
        &self,
        inputs: [&[T]; 3],
        g: &[T],
        [want_x, _, _]: [bool; 3],
    ) -> candle_core::Result<[Option<Vec<T>>; 3]> {
        self.check(inputs)?;
        if g.len() != self.out_len() {
            candle_core::bail!("fused conv: gradient of {} elements", g.len())
        }
        let [x, w, _] = inputs;
        let mut gx = want_x.then(|| vec![T::from_f64(0.0); x.len()]);
        let (mut gw, mut gb) = (
            vec![T::from_f64(0.0); w.len()],
            vec![T::from_f64(0.0); self.c_out],
        );
        let local = BufferPool::default();
        let pool = self.pool_or(&local);
        self.backward_into([x, w], g, gx.as_deref_mut(), [&mut gw, &mut gb], pool);
        Ok([gx, Some(gw), Some(gb)])
    }
}
cpu_op!(FusedConv, 3, "nf-fused-conv");

/// A chain of [`FusedConv`] layers as one op, layer `l`'s input the output of layer
/// `l − 1` (each layer's `relu_input` applying the ReLU between them): inputs `(x, params)`
/// with `x` the first layer's input and `params` every layer's weight (`[Cₒ, Cᵢ, k…]`)
/// then bias (`[Cₒ]`), layer by layer; output the last layer's. The intermediate outputs
/// and their gradients live in buffers of `pool`, kept between calls, and the forward
/// pass's outputs in the op for its backward pass: a chain whose first layer writes a
/// large grid (the voxel encoder's) holds no fresh buffer of that size in either pass.
/// The same function as the layers applied one by one, and the same gradients.
#[derive(Debug)]
pub(crate) struct FusedConvStack {
    layers: Vec<FusedConv>,
    pool: Arc<BufferPool>,
    /// The forward pass's intermediate outputs (a `Vec<Vec<T>>` of the dtype).
    saved: Mutex<Option<Box<dyn Any + Send>>>,
}

impl FusedConvStack {
    /// The op over `layers` (each layer's input length the previous one's output length;
    /// checked when it runs), with buffers from `pool`.
    pub(crate) fn new(layers: Vec<FusedConv>, pool: Arc<BufferPool>) -> Self {
        Self {
            layers,
            pool,
            saved: Mutex::new(None),
        }
    }

    /// The outputs of every layer but the last, in buffers of the pool, for the first
    /// layer's input `x` and the layers' `ranges` in `params` (from [`Self::check`]).
    fn intermediates<T: Real>(
        &self,
        x: &[T],
        params: &[T],
        ranges: &[(usize, usize, usize)],
    ) -> Vec<Vec<T>> {
        let last = self.layers.len().saturating_sub(1);
        let mut outs: Vec<Vec<T>> = Vec::with_capacity(last);
        for (layer, &(w0, b0, b1)) in self.layers[..last].iter().zip(ranges) {
            let input = outs.last().map_or(x, |o| o.as_slice());
            let mut out = self.pool.take::<T>(layer.out_len());
            layer.forward_into(
                input,
                &params[w0..b0],
                &params[b0..b1],
                &mut out,
                &self.pool,
            );
            outs.push(out);
        }
        outs
    }

    /// The output shape `[B, cells, Cₒ]` of the last layer.
    fn out_shape(&self) -> Shape {
        match self.layers.last() {
            Some(l) => Shape::from((l.batch, l.out_cells(), l.c_out)),
            None => Shape::from(0),
        }
    }

    /// Each layer's `(weight, bias)` ranges in `params`, after checking the chain.
    fn check<T>(&self, [x, params]: [&[T]; 2]) -> candle_core::Result<Vec<(usize, usize, usize)>> {
        let Some(first) = self.layers.first() else {
            candle_core::bail!("fused conv stack: no layers")
        };
        if x.len() != first.in_len() {
            candle_core::bail!(
                "fused conv stack: input of {} elements, expected {}",
                x.len(),
                first.in_len()
            )
        }
        let mut at = 0;
        let mut ranges = Vec::with_capacity(self.layers.len());
        for (l, layer) in self.layers.iter().enumerate() {
            if layer.out_size().is_none() {
                candle_core::bail!("fused conv stack: layer {l} has no output")
            }
            if l > 0 && layer.in_len() != self.layers[l - 1].out_len() {
                candle_core::bail!(
                    "fused conv stack: layer {l}'s input is not layer {}'s output",
                    l - 1
                )
            }
            let w = layer.c_out * layer.k();
            ranges.push((at, at + w, at + w + layer.c_out));
            at += w + layer.c_out;
        }
        if params.len() != at {
            candle_core::bail!(
                "fused conv stack: {} parameters, expected {at}",
                params.len()
            )
        }
        Ok(ranges)
    }
}

impl CpuKernel<2> for FusedConvStack {
    const NAME: &'static str = "fused conv stack";

    fn forward<T: Real>(&self, inputs: [&[T]; 2]) -> candle_core::Result<(Vec<T>, Shape)> {
        let ranges = self.check(inputs)?;
        let [x, params] = inputs;
        let outs = self.intermediates(x, params, &ranges);
        let (layer, &(w0, b0, b1)) = (&self.layers[outs.len()], &ranges[outs.len()]);
        let mut y = vec![T::from_f64(0.0); layer.out_len()];
        let input = outs.last().map_or(x, |o| o.as_slice());
        layer.forward_into(input, &params[w0..b0], &params[b0..b1], &mut y, &self.pool);
        *self.saved.lock().unwrap_or_else(PoisonError::into_inner) = Some(Box::new(outs));
        Ok((y, self.out_shape()))
    }

    fn backward<T: Real>(
        &self,
        inputs: [&[T]; 2],
        g: &[T],
        [want_x, _]: [bool; 2],
    ) -> candle_core::Result<[Option<Vec<T>>; 2]> {
        let ranges = self.check(inputs)?;
        let [x, params] = inputs;
        let last = self.layers.len() - 1;
        if g.len() != self.layers[last].out_len() {
            candle_core::bail!("fused conv stack: gradient of {} elements", g.len())
        }
        let saved = self
            .saved
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        let outs = match saved.map(|b| b.downcast::<Vec<Vec<T>>>()) {
            Some(Ok(outs)) if outs.len() == last => *outs,
            // Not kept (a second backward pass): run the layers again.
            _ => self.intermediates(x, params, &ranges),
        };
        let mut gp = vec![T::from_f64(0.0); params.len()];
        let mut gx = want_x.then(|| vec![T::from_f64(0.0); x.len()]);
        // The gradient w.r.t. the current layer's output (`g` for the last).
        let mut grad: Option<Vec<T>> = None;
        for (l, (layer, &(w0, b0, b1))) in self.layers.iter().zip(&ranges).enumerate().rev() {
            let input = if l == 0 { x } else { &outs[l - 1] };
            let mut g_in = (l > 0).then(|| self.pool.take::<T>(layer.in_len()));
            let gin = match g_in.as_deref_mut() {
                Some(b) => Some(b),
                None => gx.as_deref_mut(),
            };
            let (gw, gb) = gp[w0..b1].split_at_mut(b0 - w0);
            layer.backward_into(
                [input, &params[w0..b0]],
                grad.as_deref().unwrap_or(g),
                gin,
                [gw, gb],
                &self.pool,
            );
            if let Some(old) = std::mem::replace(&mut grad, g_in) {
                self.pool.give(old);
            }
        }
        if let Some(old) = grad {
            self.pool.give(old);
        }
        outs.into_iter().for_each(|v| self.pool.give(v));
        Ok([gx, Some(gp)])
    }
}
cpu_op!(FusedConvStack, 2, "nf-fused-conv-stack");
