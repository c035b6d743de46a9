//! NeRF's two networks as one CPU op: the density trunk and the colour head of
//! [`crate::volume::Nerf`], each a [`FusedMlp`], on a tile of points in one pass.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::mlp::{chunk_rows, sum_chunks, FusedMlp, Params, Rows, Scratch, CHUNK, TILE};
use super::parallel::for_each_init;
use candle_core::Shape;

/// NeRF's two networks as one op ([`crate::volume::Nerf`]): the trunk on the encoded position
/// `[N, E_p]` gives the raw density and a feature `[N, W]`; the colour head runs on
/// `[encoded direction, feature]`. Output `[N, 4]`: the raw density and the raw colour
/// (activations are applied outside). Parameters: the trunk's flat parameters, then the
/// head's. The feature never leaves the tile, so the pass allocates nothing per point
/// beyond its output, and the backward pass hands the head's input gradient straight to
/// the trunk.
#[derive(Clone, Debug)]
pub(crate) struct FusedNerf {
    pub trunk: FusedMlp,
    pub head: FusedMlp,
}

/// Per-worker scratch of [`FusedNerf`]: each network's, the trunk's output, the head's
/// input and output, and their gradients.
pub(super) struct NerfScratch<T> {
    pub(super) trunk: Scratch<T>,
    pub(super) head: Scratch<T>,
    pub(super) yt: Vec<T>,
    pub(super) ha0: Vec<T>,
    pub(super) yh: Vec<T>,
    pub(super) g_ha0: Vec<T>,
    pub(super) g_yt: Vec<T>,
}

impl FusedNerf {
    /// Output columns: the raw density and the raw colour.
    pub(super) fn width(&self) -> usize {
        4
    }

    /// Widths: encoded direction, trunk output (1 + feature), head input.
    pub(super) fn widths(&self) -> (usize, usize, usize) {
        let t_out = self.trunk.out_dim();
        let h_in = self.head.a0;
        (h_in + 1 - t_out, t_out, h_in)
    }

    pub(super) fn scratch<T: Real>(&self) -> NerfScratch<T> {
        let (_, t_out, h_in) = self.widths();
        let z = T::from_f64(0.0);
        NerfScratch {
            trunk: self.trunk.scratch(),
            head: self.head.scratch(),
            yt: vec![z; TILE * t_out],
            ha0: vec![z; TILE * h_in],
            yh: vec![z; TILE * self.head.out_dim()],
            g_ha0: vec![z; TILE * h_in],
            g_yt: vec![z; TILE * t_out],
        }
    }

    /// The trunk and the head's input of one tile (left in `sc`); returns the rows.
    pub(super) fn trunk_tile<T: Real>(
        &self,
        ep: &[T],
        ed: &[T],
        pt: Params<'_, T>,
        sc: &mut NerfScratch<T>,
    ) -> usize {
        let (dd, t_out, h_in) = self.widths();
        let rows = ep.len() / self.trunk.a0;
        self.trunk
            .forward_tile(ep, pt, Rows::plain(rows), &mut sc.trunk, &mut sc.yt);
        for r in 0..rows {
            let row = &mut sc.ha0[r * h_in..(r + 1) * h_in];
            row[..dd].copy_from_slice(&ed[r * dd..(r + 1) * dd]);
            row[dd..].copy_from_slice(&sc.yt[r * t_out + 1..(r + 1) * t_out]);
        }
        rows
    }

    /// The trunk's and the head's [`Params`] views of `params`, with `wt` holding both
    /// networks' transposed weights.
    pub(super) fn split<'a, T: Real>(
        &self,
        params: &'a [T],
        wt: &'a [T],
    ) -> (Params<'a, T>, Params<'a, T>) {
        let (pt, ph) = params.split_at(self.trunk.n_params);
        let (wtt, wth) = wt.split_at(self.trunk.n_params);
        (Params { p: pt, wt: wtt }, Params { p: ph, wt: wth })
    }

    /// Both networks' transposed weights, trunk then head.
    pub(super) fn transposed<T: Real>(&self, params: &[T]) -> Vec<T> {
        let (pt, ph) = params.split_at(self.trunk.n_params);
        let mut wt = self.trunk.transposed(pt);
        wt.extend(self.head.transposed(ph));
        wt
    }

    pub(super) fn forward<T: Real>(&self, ep: &[T], ed: &[T], params: &[T], n: usize) -> Vec<T> {
        let (dd, _, _) = self.widths();
        let wt = self.transposed(params);
        let (pt, ph) = self.split(params, &wt);
        let mut y = vec![T::from_f64(0.0); n * 4];
        let items: Vec<_> = y
            .chunks_mut(TILE * 4)
            .zip(ep.chunks(TILE * self.trunk.a0))
            .zip(ed.chunks(TILE * dd))
            .collect();
        let t_out = self.trunk.out_dim();
        for_each_init(
            items,
            || self.scratch::<T>(),
            |sc, ((y, ep), ed)| {
                let rows = self.trunk_tile(ep, ed, pt, sc);
                let (ha0, yh) = (&sc.ha0, &mut sc.yh);
                self.head
                    .forward_tile(ha0, ph, Rows::plain(rows), &mut sc.head, yh);
                for r in 0..rows {
                    y[4 * r] = sc.yt[r * t_out];
                    y[4 * r + 1..4 * r + 4].copy_from_slice(&sc.yh[3 * r..3 * r + 3]);
                }
            },
        );
        y
    }

    /// `(∂L/∂enc_pos, ∂L/∂enc_dir)` where wanted, and `∂L/∂params`.
    #[allow(clippy::type_complexity)]
    pub(super) fn backward<T: Real>(
        &self,
        ep: &[T],
        ed: &[T],
        params: &[T],
        gy: &[T],
        n: usize,
        want: (bool, bool),
    ) -> (Option<Vec<T>>, Option<Vec<T>>, Vec<T>) {
        let (dd, _, _) = self.widths();
        let wt = self.transposed(params);
        let (pt, ph) = self.split(params, &wt);
        let (a0p, np) = (self.trunk.a0, params.len());
        let chunks = n.div_ceil(CHUNK);
        let mut gp = vec![T::from_f64(0.0); chunks.max(1) * np];
        let mut gep = want.0.then(|| vec![T::from_f64(0.0); n * a0p]);
        let mut ged = want.1.then(|| vec![T::from_f64(0.0); n * dd]);
        let items: Vec<_> = gp
            .chunks_mut(np)
            .zip(ep.chunks(CHUNK * a0p))
            .zip(ed.chunks(CHUNK * dd))
            .zip(gy.chunks(CHUNK * 4))
            .zip(
                chunk_rows(gep.as_deref_mut(), a0p, chunks)
                    .into_iter()
                    .zip(chunk_rows(ged.as_deref_mut(), dd, chunks)),
            )
            .collect();
        for_each_init(
            items,
            || self.scratch::<T>(),
            |sc, ((((gp, ep), ed), gy), (mut gep, mut ged))| {
                let (gpt, gph) = gp.split_at_mut(self.trunk.n_params);
                let rows = gy.len() / 4;
                for t in (0..rows).step_by(TILE) {
                    let r = TILE.min(rows - t);
                    self.trunk_tile(
                        &ep[t * a0p..(t + r) * a0p],
                        &ed[t * dd..(t + r) * dd],
                        pt,
                        sc,
                    );
                    self.backward_tile(
                        &ep[t * a0p..(t + r) * a0p],
                        (pt, ph),
                        &gy[4 * t..4 * (t + r)],
                        sc,
                        (gpt, gph),
                        (
                            gep.as_deref_mut().map(|g| &mut g[t * a0p..(t + r) * a0p]),
                            ged.as_deref_mut().map(|g| &mut g[t * dd..(t + r) * dd]),
                        ),
                        true,
                    );
                }
            },
        );
        sum_chunks(&mut gp, np);
        (gep, ged, gp)
    }

    /// The backward pass of one tile after [`FusedNerf::trunk_tile`] on it (which left
    /// the trunk's activations and the head's input in `sc`): the head (recomputing its
    /// forward pass when `head_recompute`; else `sc` holds it), then the trunk. `gy: [r,
    /// 4]` is the gradient of the op's output rows; the parameter gradients accumulate
    /// into `gp` (trunk, head) and the encoded inputs' gradients, where given, are
    /// written to `ga` (position, direction).
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    pub(super) fn backward_tile<T: Real>(
        &self,
        ep: &[T],
        (pt, ph): (Params<'_, T>, Params<'_, T>),
        gy: &[T],
        sc: &mut NerfScratch<T>,
        (gpt, gph): (&mut [T], &mut [T]),
        (gep, mut ged): (Option<&mut [T]>, Option<&mut [T]>),
        head_recompute: bool,
    ) {
        let (dd, t_out, h_in) = self.widths();
        let r = gy.len() / 4;
        for i in 0..r {
            sc.yh[3 * i..3 * i + 3].copy_from_slice(&gy[4 * i + 1..4 * i + 4]);
        }
        let (ha0, yh, g_ha0) = (&sc.ha0, &sc.yh, &mut sc.g_ha0[..r * h_in]);
        self.head.backward_tile(
            ha0,
            ph,
            yh,
            Rows::plain(r),
            &mut sc.head,
            gph,
            Some(g_ha0),
            head_recompute,
        );
        for i in 0..r {
            sc.g_yt[i * t_out] = gy[4 * i];
            sc.g_yt[i * t_out + 1..(i + 1) * t_out]
                .copy_from_slice(&sc.g_ha0[i * h_in + dd..(i + 1) * h_in]);
            if let Some(g) = ged.as_deref_mut() {
                g[i * dd..(i + 1) * dd].copy_from_slice(&sc.g_ha0[i * h_in..i * h_in + dd]);
            }
        }
        self.trunk.backward_tile(
            ep,
            pt,
            &sc.g_yt,
            Rows::plain(r),
            &mut sc.trunk,
            gpt,
            gep,
            false,
        );
    }

    pub(super) fn check(
        &self,
        n_ep: usize,
        n_ed: usize,
        n_params: usize,
    ) -> candle_core::Result<usize> {
        let (dd, _, _) = self.widths();
        let n = self.trunk.check(n_ep, self.trunk.n_params)?;
        if n_params != self.trunk.n_params + self.head.n_params || n_ed != n * dd {
            candle_core::bail!("fused NeRF: {n_ed} direction features or {n_params} parameters do not match {n} points")
        }
        Ok(n)
    }
}

impl CpuKernel<3> for FusedNerf {
    const NAME: &'static str = "fused NeRF";

    /// Inputs `(encoded positions [N, E_p], encoded directions [N, E_d], params)`;
    /// output `[N, 4]`.
    fn forward<T: Real>(&self, [x, y, p]: [&[T]; 3]) -> candle_core::Result<(Vec<T>, Shape)> {
        let n = self.check(x.len(), y.len(), p.len())?;
        Ok((
            FusedNerf::forward(self, x, y, p, n),
            Shape::from((n, self.width())),
        ))
    }

    fn backward<T: Real>(
        &self,
        [x, y, p]: [&[T]; 3],
        g: &[T],
        [want_x, want_y, _]: [bool; 3],
    ) -> candle_core::Result<[Option<Vec<T>>; 3]> {
        let n = self.check(x.len(), y.len(), p.len())?;
        if g.len() != n * self.width() {
            candle_core::bail!("{}: gradient of {} elements", Self::NAME, g.len())
        }
        let (gx, gy, gp) = FusedNerf::backward(self, x, y, p, g, n, (want_x, want_y));
        Ok([gx, gy, Some(gp)])
    }
}
cpu_op!(FusedNerf, 3, "nf-fused-nerf");
