//! Conditional batch normalisation and ReLU over rows (`FusedCondNorm`, a layer of the
//! fused ONet decoder, [`super::onet`]): the batch statistics in one pass over the rows
//! and the per-code scale and shift and the ReLU in a second (or tile by tile where a
//! product reads them, [`Ready::apply`]), and a backward pass that gives
//! the rows', scales' and shifts' gradients in two, where the same layer as candle ops
//! takes about twenty element-wise ops, reductions and broadcasts, each with its own
//! tensor. With one scale and shift for all rows and the ReLU optional it is plain batch
//! normalisation, an op of its own (`FusedBatchNorm`, the image encoder's on the CPU).

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::parallel::{for_each_init, wide, Wide};
use candle_core::Shape;
use candle_core::WithDType;
use std::sync::{Arc, Mutex, PoisonError};

/// `y = a(γ_g ⊙ (x − μ)/√(v + ε) + β_g)`, `a` the ReLU (or the identity without `relu`),
/// for rows `x: [N, H]`, with the batch mean `μ`
/// and the biased batch variance `v` of each column over all `N` rows, and row `n`'s scale
/// and shift `γ_g, β_g` rows `g = ⌊n / group⌋` of `gamma, beta: [N / group, H]`.
///
/// Backward, with `x̂ = (x − μ)·s`, `s = 1/√(v + ε)`, `ḡ = ∂L/∂y ⊙ [y ≥ 0]` (`∂L/∂y`
/// without `relu`) and
/// `u = ḡ ⊙ γ_g` (per row): `∂L/∂β_g = Σ_{n ∈ g} ḡ`, `∂L/∂γ_g = Σ_{n ∈ g} ḡ ⊙ x̂`,
/// `∂L/∂x = s ⊙ (u − mean_n(u) − x̂ ⊙ mean_n(u ⊙ x̂))` (the statistics' own dependence on
/// `x` included). Statistics and sums in f64 (the statistics by one pass of shifted sums,
/// [`FusedCondNorm::stats`]); each value's own arithmetic in the dtype, as
/// `(x − μ)·(γ_g s) + β_g`, the difference taken first as the reference ops take it.
#[derive(Debug)]
pub(crate) struct FusedCondNorm {
    /// Rows `N`.
    pub(crate) rows: usize,
    /// Columns `H`.
    pub(crate) width: usize,
    /// Rows per scale and shift row (`N` divisible by it, `≥ 1`).
    pub(crate) group: usize,
    /// `ε > 0`.
    pub(crate) eps: f64,
    /// The ReLU after the affine map.
    pub(crate) relu: bool,
    /// The forward pass's statistics, shared with the caller (which updates its running
    /// statistics from them) and read by the backward pass instead of recomputing them
    /// (the op's input is immutable; without them it recomputes).
    pub(crate) saved: Arc<Mutex<Option<Stats>>>,
}

/// Rows per work item.
const ROWS: usize = 128;

/// The column means, biased variances and `1/√(v + ε)` of rows `x: [N, H]`, f64.
#[derive(Clone, Debug)]
pub(crate) struct Stats {
    pub(crate) mean: Vec<f64>,
    pub(crate) var: Vec<f64>,
    scale: Vec<f64>,
}

/// One work item: its first row and its rows of one or two row-shaped buffers.
type Item<'a, T, U> = (usize, &'a [T], U);

impl FusedCondNorm {
    /// The column statistics of rows `x` in one pass over memory: with each column
    /// shifted by its first row's value `K`, the per-item sums of `d = x − K` and `d²` in
    /// parallel, added in item order (so the result does not depend on the scheduling),
    /// then `μ = K + Σd/N`, `v = Σd²/N − (Σd/N)²`. Since `K` is one of the values,
    /// `(μ − K)² ≤ N·v`, so the subtraction loses at most a factor `N` of the sums'
    /// relative precision (f64), however large the mean is against the spread.
    fn stats<T: WithDType>(&self, x: &[T]) -> Stats {
        let h = self.width;
        if h == 0 || x.len() < h {
            let zeros = vec![0.0; h];
            let scale = vec![1.0 / self.eps.sqrt(); h];
            return Stats {
                mean: zeros.clone(),
                var: zeros,
                scale,
            };
        }
        let shift: Vec<f64> = x[..h].iter().map(|v| v.to_f64()).collect();
        // Per item: its columns' `Σd`, then their `Σd²`.
        let mut partial = vec![0.0; x.len().div_ceil(ROWS * h) * 2 * h];
        let items: Vec<_> = x.chunks(ROWS * h).zip(partial.chunks_mut(2 * h)).collect();
        for_each_init(
            items,
            || (),
            |_, (x, acc)| {
                wide(|| {
                    let (s1, s2) = acc.split_at_mut(h);
                    for row in x.chunks(h) {
                        let cols = row.iter().zip(&shift).zip(s1.iter_mut().zip(s2.iter_mut()));
                        for ((v, k), (s1, s2)) in cols {
                            let d = v.to_f64() - k;
                            *s1 += d;
                            *s2 += d * d;
                        }
                    }
                })
            },
        );
        let (mut s1, mut s2) = (vec![0.0; h], vec![0.0; h]);
        for p in partial.chunks(2 * h) {
            for j in 0..h {
                s1[j] += p[j];
                s2[j] += p[h + j];
            }
        }
        let n = (x.len() / h) as f64;
        let mean = s1.iter().zip(&shift).map(|(s, k)| k + s / n).collect();
        let var: Vec<f64> = s1
            .iter()
            .zip(&s2)
            .map(|(s1, s2)| (s2 / n - (s1 / n) * (s1 / n)).max(0.0))
            .collect();
        let scale = var.iter().map(|v| 1.0 / (v + self.eps).sqrt()).collect();
        Stats { mean, var, scale }
    }

    /// Row items of `ROWS` rows: each item's first row, its rows of `x`, and the same
    /// rows of `out`.
    fn items<'a, T, U>(&self, x: &'a [T], out: &'a mut [U]) -> Vec<Item<'a, T, &'a mut [U]>> {
        let h = self.width.max(1);
        x.chunks(ROWS * h)
            .zip(out.chunks_mut(ROWS * h))
            .enumerate()
            .map(|(i, (x, o))| (i * ROWS, x, o))
            .collect()
    }

    /// The column means in `T` and the per-group slopes `γ_g ⊙ s` (`[N / group, H]`), so
    /// that a row's output is `(x − μ)·slope + β` (the difference first, as the
    /// reference ops take it, then one multiply-add per value).
    fn slopes<T: WithDType>(&self, st: &Stats, gamma: &[T]) -> (Vec<T>, Vec<T>) {
        let h = self.width.max(1);
        let mean = st.mean.iter().map(|&m| T::from_f64(m)).collect();
        let slope = gamma
            .chunks(h)
            .flat_map(|g| g.iter().zip(&st.scale))
            .map(|(g, s)| T::from_f64(g.to_f64() * s))
            .collect();
        (mean, slope)
    }

    /// The [`Columns`] of this layer over `mean`, `slope`, `beta` and `scale` (empty in
    /// the forward pass), without the backward pass's column terms.
    fn columns<'a, T: WithDType>(
        &self,
        mean: &'a [T],
        slope: &'a [T],
        beta: &'a [T],
        scale: &'a [T],
    ) -> Columns<'a, T> {
        Columns {
            width: self.width,
            group: self.group,
            mean,
            slope,
            beta,
            scale,
            c: &[],
            e: &[],
            lo: T::from_f64(if self.relu { 0.0 } else { f64::NEG_INFINITY }),
        }
    }

    /// The layer's output rows into `out` (`x`'s length; every value written); the
    /// statistics into `saved`. `gamma`, `beta`: `[N / group, H]`.
    pub(super) fn run<T: WithDType>(&self, x: &[T], gamma: &[T], beta: &[T], out: &mut [T]) {
        if self.width == 0 || x.is_empty() {
            out.fill(T::from_f64(0.0));
            return;
        }
        let ready = self.ready(x, (gamma, beta), true);
        let items = self.items(x, out);
        for_each_init(
            items,
            || (),
            |_, (first, x, out)| ready.apply(first, x, out),
        );
    }

    /// The layer over rows `x` ready to apply to any of its rows ([`Ready::apply`]). With
    /// `fresh` (the forward pass) the batch statistics of `x` are computed here and left
    /// in `saved`; without, they are `saved`'s ([`FusedCondNorm::saved_stats`]).
    pub(super) fn ready<'a, T: WithDType>(
        &'a self,
        x: &[T],
        (gamma, beta): (&'a [T], &'a [T]),
        fresh: bool,
    ) -> Ready<'a, T> {
        let st = if fresh {
            let st = self.stats(x);
            *self.saved.lock().unwrap_or_else(PoisonError::into_inner) = Some(st.clone());
            st
        } else {
            self.saved_stats(x)
        };
        let (mean, slope) = self.slopes(&st, gamma);
        Ready {
            norm: self,
            mean,
            slope,
            scale: st.scale,
            gamma,
            beta,
        }
    }

    /// The statistics in `saved`, or those of `x` where none are (a second backward pass).
    fn saved_stats<T: WithDType>(&self, x: &[T]) -> Stats {
        let saved = self
            .saved
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone();
        saved.unwrap_or_else(|| self.stats(x))
    }
}

/// What the row loops of one layer read: the column means, the per-group slopes and
/// shifts (`[N / group, H]`), and for the backward pass the scales `s` and the rows'
/// gradient's column terms `c = s ⊙ mean_n(u)`, `e = s² ⊙ mean_n(u ⊙ x̂)`. Each loop runs
/// inside [`wide`], into which these `#[inline(always)]` methods are inlined.
struct Columns<'a, T> {
    width: usize,
    group: usize,
    mean: &'a [T],
    slope: &'a [T],
    beta: &'a [T],
    scale: &'a [T],
    c: &'a [T],
    e: &'a [T],
    /// The ReLU's cut, 0, or −∞ without the ReLU (no value is below it).
    lo: T,
}

impl<T: WithDType> Columns<'_, T> {
    /// Row `n`'s group's slopes and shifts.
    #[inline(always)]
    fn affine(&self, n: usize) -> (&[T], &[T]) {
        let (h, g) = (self.width, n / self.group);
        (
            &self.slope[g * h..(g + 1) * h],
            &self.beta[g * h..(g + 1) * h],
        )
    }

    /// `g` where the ReLU passes `y = (x − μ)·slope + β`, `y ≥ 0` as candle's ReLU
    /// derivative (everywhere without the ReLU).
    #[inline(always)]
    fn masked(&self, (x, m, a, b): (T, T, T, T), g: T) -> T {
        if (x - m) * a + b < self.lo {
            T::from_f64(0.0)
        } else {
            g
        }
    }

    /// The output rows `out` of rows `x` from row `first` on.
    #[inline(always)]
    fn forward(&self, first: usize, x: &[T], out: &mut [T]) {
        let (h, lo) = (self.width, self.lo);
        for (r, (row, o)) in x.chunks(h).zip(out.chunks_mut(h)).enumerate() {
            let (a, b) = self.affine(first + r);
            let columns = self.mean.iter().zip(a).zip(b);
            for ((o, &x), ((&m, &a), &b)) in o.iter_mut().zip(row).zip(columns) {
                let y = (x - m) * a + b;
                *o = if y < lo { lo } else { y };
            }
        }
    }

    /// Adds rows `x` (from row `first` on, with gradients `g`) into their groups' sums
    /// `aff` (`[groups spanned, 2H]` from group `g0`): `Σ ḡ ⊙ x̂`, then `Σ ḡ`.
    #[inline(always)]
    fn sums(&self, first: usize, g0: usize, (x, g): (&[T], &[T]), aff: &mut [f64]) {
        let h = self.width;
        for (r, (row, grow)) in x.chunks(h).zip(g.chunks(h)).enumerate() {
            let grp = (first + r) / self.group;
            let (dg, db) = aff[(grp - g0) * 2 * h..(grp - g0 + 1) * 2 * h].split_at_mut(h);
            let (a, b) = self.affine(first + r);
            let columns = self.mean.iter().zip(self.scale).zip(a.iter().zip(b));
            let sums = dg.iter_mut().zip(db.iter_mut());
            for (((&x, &gy), ((&m, &s), (&a, &b))), (dg, db)) in
                row.iter().zip(grow).zip(columns).zip(sums)
            {
                let gy = self.masked((x, m, a, b), gy);
                *dg += (gy * ((x - m) * s)).to_f64();
                *db += gy.to_f64();
            }
        }
    }

    /// The rows' gradient `ḡ ⊙ slope − c − (x − μ) ⊙ e` into `out`.
    #[inline(always)]
    fn grad(&self, first: usize, (x, g): (&[T], &[T]), out: &mut [T]) {
        let h = self.width;
        let rows = x.chunks(h).zip(out.chunks_mut(h)).zip(g.chunks(h));
        for (r, ((row, o), grow)) in rows.enumerate() {
            let (a, b) = self.affine(first + r);
            let columns = self.mean.iter().zip(a.iter().zip(b));
            let terms = columns.zip(self.c.iter().zip(self.e));
            for (((o, &x), &gy), ((&m, (&a, &b)), (&c, &e))) in
                o.iter_mut().zip(row).zip(grow).zip(terms)
            {
                let gy = self.masked((x, m, a, b), gy);
                *o = gy * a - c - (x - m) * e;
            }
        }
    }
}

/// A layer with its statistics, ready to apply to any of its rows and to take its
/// gradients: the column means and the per-group slopes in `T`
/// ([`FusedCondNorm::slopes`]), the statistics' scales `s = 1/√(σ² + ε)`, and the
/// per-group scales and shifts.
pub(super) struct Ready<'a, T> {
    norm: &'a FusedCondNorm,
    mean: Vec<T>,
    slope: Vec<T>,
    scale: Vec<f64>,
    gamma: &'a [T],
    beta: &'a [T],
}

impl<T: WithDType> Ready<'_, T> {
    /// The layer's output rows for rows `x` from row `first` on, into `out` (`x`'s
    /// length; every value written).
    pub(super) fn apply(&self, first: usize, x: &[T], out: &mut [T]) {
        let cols = self.norm.columns(&self.mean, &self.slope, self.beta, &[]);
        wide(Pass(&cols, Rows::Forward { first, x, out }));
    }

    /// The gradients of `gamma` and `beta` given the output's `grad`, and `x`'s into `gx`
    /// (`x`'s length; every value written).
    ///
    /// With `d = x − μ` and `ḡ` the gradient masked by the ReLU, one pass sums each
    /// group's `Σ ḡ` (`∂L/∂β_g`) and `Σ ḡ ⊙ x̂` (`∂L/∂γ_g`); since `γ` is constant
    /// within a group, the column means the rows' gradient needs follow from them:
    /// `mean_n(u) = Σ_g γ_g ⊙ ∂L/∂β_g / N`, `mean_n(u ⊙ x̂) = Σ_g γ_g ⊙ ∂L/∂γ_g / N`. A
    /// second pass writes `∂L/∂x = ḡ ⊙ γ_g s − s ⊙ mean_n(u) − d ⊙ s² ⊙ mean_n(u ⊙ x̂)`.
    pub(super) fn grad(&self, x: &[T], grad: &[T], gx: &mut [T]) -> [Vec<T>; 2] {
        let (norm, gamma, beta) = (self.norm, self.gamma, self.beta);
        let h = norm.width;
        let zeros = |len: usize| vec![T::from_f64(0.0); len];
        let (mut gg, mut gb) = (zeros(gamma.len()), zeros(beta.len()));
        if h == 0 || x.is_empty() {
            gx.fill(T::from_f64(0.0));
            return [gg, gb];
        }
        let scale: Vec<T> = self.scale.iter().map(|&s| T::from_f64(s)).collect();
        let mut cols = norm.columns(&self.mean, &self.slope, beta, &scale);
        // Pass 1, per item: the scale's and shift's sums of the groups its rows belong to
        // (`[groups spanned, 2H]`, from its first group).
        let h2 = 2 * h;
        let n_items = norm.rows.div_ceil(ROWS);
        let spans: Vec<(usize, usize)> = (0..n_items)
            .map(|i| {
                let (a, b) = (i * ROWS, ((i + 1) * ROWS).min(norm.rows) - 1);
                (a / norm.group, b / norm.group - a / norm.group + 1)
            })
            .collect();
        let mut affine: Vec<Vec<f64>> = spans.iter().map(|&(_, k)| vec![0.0; k * h2]).collect();
        let items: Vec<_> = x
            .chunks(ROWS * h)
            .zip(grad.chunks(ROWS * h))
            .zip(affine.iter_mut())
            .enumerate()
            .collect();
        for_each_init(
            items,
            || (),
            |_, (i, ((x, g), aff))| {
                wide(Pass(
                    &cols,
                    Rows::Sums {
                        first: i * ROWS,
                        g0: spans[i].0,
                        x,
                        g,
                        aff,
                    },
                ))
            },
        );
        let (mut dg, mut db) = (vec![0.0; gamma.len()], vec![0.0; beta.len()]);
        for (&(g0, _), aff) in spans.iter().zip(&affine) {
            for (k, a) in aff.chunks(h2).enumerate() {
                let at = (g0 + k) * h;
                for j in 0..h {
                    dg[at + j] += a[j];
                    db[at + j] += a[h + j];
                }
            }
        }
        // Pass 2: the rows' gradient, `ḡ ⊙ slope − c − d ⊙ e`.
        let n = norm.rows as f64;
        let (mut su, mut sux) = (vec![0.0; h], vec![0.0; h]);
        for ((gm, dg), db) in gamma.chunks(h).zip(dg.chunks(h)).zip(db.chunks(h)) {
            for j in 0..h {
                su[j] += gm[j].to_f64() * db[j] / n;
                sux[j] += gm[j].to_f64() * dg[j] / n;
            }
        }
        let c: Vec<T> = su
            .iter()
            .zip(&self.scale)
            .map(|(u, s)| T::from_f64(s * u))
            .collect();
        let e: Vec<T> = sux
            .iter()
            .zip(&self.scale)
            .map(|(u, s)| T::from_f64(s * s * u))
            .collect();
        for (o, v) in gg.iter_mut().zip(&dg) {
            *o = T::from_f64(*v);
        }
        for (o, v) in gb.iter_mut().zip(&db) {
            *o = T::from_f64(*v);
        }
        (cols.c, cols.e) = (&c, &e);
        let items: Vec<_> = norm
            .items(x, gx)
            .into_iter()
            .zip(grad.chunks(ROWS * h))
            .collect();
        for_each_init(
            items,
            || (),
            |_, ((first, x, out), g)| wide(Pass(&cols, Rows::Grad { first, x, g, out })),
        );
        [gg, gb]
    }
}

/// One work item of one of the row passes.
enum Rows<'a, T> {
    /// [`Columns::forward`].
    Forward {
        first: usize,
        x: &'a [T],
        out: &'a mut [T],
    },
    /// [`Columns::sums`].
    Sums {
        first: usize,
        g0: usize,
        x: &'a [T],
        g: &'a [T],
        aff: &'a mut [f64],
    },
    /// [`Columns::grad`].
    Grad {
        first: usize,
        x: &'a [T],
        g: &'a [T],
        out: &'a mut [T],
    },
}

/// A pass's item with the columns it reads, run by [`wide`].
struct Pass<'a, 'b, T>(&'a Columns<'b, T>, Rows<'a, T>);

impl<T: WithDType> Wide for Pass<'_, '_, T> {
    type Out = ();
    #[inline(always)]
    fn run(self) {
        let Pass(cols, rows) = self;
        match rows {
            Rows::Forward { first, x, out } => cols.forward(first, x, out),
            Rows::Sums {
                first,
                g0,
                x,
                g,
                aff,
            } => cols.sums(first, g0, (x, g), aff),
            Rows::Grad { first, x, g, out } => cols.grad(first, (x, g), out),
        }
    }
}

/// Batch normalisation of rows `x: [N, H]` with scale and shift `gamma, beta: [H]` and an
/// optional ReLU, as one op: [`FusedCondNorm`] with one group of all `N` rows. The forward
/// pass's statistics are left in [`FusedBatchNorm::saved`] for the caller's running
/// statistics.
#[derive(Debug)]
pub(crate) struct FusedBatchNorm(FusedCondNorm);

impl FusedBatchNorm {
    /// The op over `rows × width` rows with `ε = eps`, the ReLU after it where `relu`.
    pub(crate) fn new(rows: usize, width: usize, eps: f64, relu: bool) -> Self {
        Self(FusedCondNorm {
            rows,
            width,
            group: rows.max(1),
            eps,
            relu,
            saved: Arc::new(Mutex::new(None)),
        })
    }

    /// Where the forward pass leaves its batch statistics (read by the backward pass too).
    pub(crate) fn saved(&self) -> Arc<Mutex<Option<Stats>>> {
        Arc::clone(&self.0.saved)
    }

    fn check<T>(&self, [x, g, b]: [&[T]; 3]) -> candle_core::Result<()> {
        let n = &self.0;
        if n.rows == 0 {
            candle_core::bail!("fused batch norm: no rows")
        }
        let want = [n.rows * n.width, n.width, n.width];
        if [x.len(), g.len(), b.len()] != want {
            candle_core::bail!(
                "fused batch norm: input lengths {:?}, expected {want:?}",
                [x.len(), g.len(), b.len()]
            )
        }
        Ok(())
    }
}

impl CpuKernel<3> for FusedBatchNorm {
    const NAME: &'static str = "fused batch norm";

    /// Inputs `(x [N, H], gamma [H], beta [H])`; output `[N, H]`.
    fn forward<T: Real>(&self, inputs: [&[T]; 3]) -> candle_core::Result<(Vec<T>, Shape)> {
        self.check(inputs)?;
        let [x, g, b] = inputs;
        let mut out = vec![T::from_f64(0.0); x.len()];
        self.0.run(x, g, b, &mut out);
        Ok((out, Shape::from((self.0.rows, self.0.width))))
    }

    fn backward<T: Real>(
        &self,
        inputs: [&[T]; 3],
        grad: &[T],
        [want_x, _, _]: [bool; 3],
    ) -> candle_core::Result<[Option<Vec<T>>; 3]> {
        self.check(inputs)?;
        if grad.len() != inputs[0].len() {
            candle_core::bail!("fused batch norm: gradient of {} elements", grad.len())
        }
        let [x, g, b] = inputs;
        let mut gx = vec![T::from_f64(0.0); x.len()];
        let [gg, gb] = self.0.ready(x, (g, b), false).grad(x, grad, &mut gx);
        Ok([want_x.then_some(gx), Some(gg), Some(gb)])
    }
}
cpu_op!(FusedBatchNorm, 3, "nf-fused-batch-norm");

#[cfg(test)]
mod tests {
    use super::{FusedCondNorm, ROWS};
    use std::sync::{Arc, Mutex};

    /// The one-pass shifted statistics equal a plain two-pass mean and variance over all
    /// rows, in f32 and f64, for row counts of whole and partial items, with the mean far
    /// above the spread (where a sum of squares would cancel).
    #[test]
    fn one_pass_statistics_equal_two_pass_ones_with_a_large_mean() {
        fn check<T: candle_core::WithDType>(rows: usize, width: usize, offset: f64) {
            let x: Vec<T> = (0..rows * width)
                .map(|i| {
                    let u = ((i as u64).wrapping_mul(2654435761) % 1000) as f64 / 1000.0;
                    T::from_f64(offset * (1.0 + (i % width) as f64) + (u - 0.5) * 0.02)
                })
                .collect();
            let norm = FusedCondNorm {
                rows,
                width,
                group: rows,
                eps: 1e-5,
                relu: false,
                saved: Arc::new(Mutex::new(None)),
            };
            let st = norm.stats(&x);
            for j in 0..width {
                let col: Vec<f64> = x
                    .iter()
                    .skip(j)
                    .step_by(width)
                    .map(|v| v.to_f64())
                    .collect();
                let mean = col.iter().sum::<f64>() / rows as f64;
                let var = col.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / rows as f64;
                assert!(
                    (st.mean[j] - mean).abs() <= 1e-12 * mean.abs().max(1.0),
                    "{rows}x{width} column {j}: mean {} vs {mean}",
                    st.mean[j]
                );
                assert!(
                    (st.var[j] - var).abs() <= 1e-9 * var,
                    "{rows}x{width} column {j}: variance {} vs {var}",
                    st.var[j]
                );
            }
        }
        for (rows, width) in [(1, 3), (ROWS, 4), (3 * ROWS + 17, 5), (1000, 16)] {
            check::<f32>(rows, width, 1e4);
            check::<f64>(rows, width, 1e6);
            check::<f64>(rows, width, 0.0);
        }
    }
}
