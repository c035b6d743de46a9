//! Conditional batch normalisation and ReLU as one CPU op (`FusedCondNorm`, what the ONet
//! decoder's training pass runs on the CPU): the batch statistics, the per-code scale and
//! shift and the ReLU in two passes over the rows, and a backward pass that gives the
//! rows', scales' and shifts' gradients in three, where the same layer as candle ops
//! takes about twenty element-wise ops, reductions and broadcasts, each with its own
//! tensor.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::parallel::for_each_init;
use candle_core::{Shape, WithDType};
use std::sync::{Mutex, PoisonError};

/// `y = relu(γ_g ⊙ (x − μ)/√(v + ε) + β_g)` for rows `x: [N, H]`, with the batch mean `μ`
/// and the biased batch variance `v` of each column over all `N` rows, and row `n`'s scale
/// and shift `γ_g, β_g` rows `g = ⌊n / group⌋` of `gamma, beta: [N / group, H]`. Without
/// `relu` the ReLU is left out.
///
/// Backward, with `x̂ = (x − μ)·s`, `s = 1/√(v + ε)`, `ḡ = ∂L/∂y ⊙ [y > 0]` and
/// `u = ḡ ⊙ γ_g` (per row): `∂L/∂β_g = Σ_{n ∈ g} ḡ`, `∂L/∂γ_g = Σ_{n ∈ g} ḡ ⊙ x̂`,
/// `∂L/∂x = s ⊙ (u − mean_n(u) − x̂ ⊙ mean_n(u ⊙ x̂))` (the statistics' own dependence on
/// `x` included). Sums and statistics in f64; the statistics by two passes (mean, then
/// the squared deviations).
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
    /// Whether the ReLU follows.
    pub(crate) relu: bool,
    /// The forward pass's statistics, which the backward pass takes instead of
    /// recomputing them (the op's input is immutable; without them it recomputes).
    pub(crate) saved: Mutex<Option<Stats>>,
}

/// Rows per work item.
const ROWS: usize = 128;

/// The column means and `1/√(v + ε)` of rows `x: [N, H]`, f64.
#[derive(Debug)]
pub(crate) struct Stats {
    mean: Vec<f64>,
    scale: Vec<f64>,
}

/// One work item: its first row and its rows of one or two row-shaped buffers.
type Item<'a, T, U> = (usize, &'a [T], U);

impl FusedCondNorm {
    /// Column sums of `f(row index, row)` over the items of `x`, in parallel, added in
    /// item order (so the result does not depend on the scheduling).
    fn column_sums<T: WithDType>(&self, x: &[T], f: impl Fn(&[T], &mut [f64]) + Sync) -> Vec<f64> {
        let h = self.width;
        let mut partial = vec![0.0; x.len().div_ceil(ROWS * h.max(1)) * h];
        if h == 0 {
            return partial;
        }
        let items: Vec<_> = x.chunks(ROWS * h).zip(partial.chunks_mut(h)).collect();
        for_each_init(items, || (), |_, (x, acc)| f(x, acc));
        let mut sum = vec![0.0; h];
        for p in partial.chunks(h) {
            for (s, v) in sum.iter_mut().zip(p) {
                *s += v;
            }
        }
        sum
    }

    fn stats<T: WithDType>(&self, x: &[T]) -> Stats {
        let h = self.width;
        let n = self.rows.max(1) as f64;
        let mean: Vec<f64> = self
            .column_sums(x, |x, acc| {
                for row in x.chunks(h) {
                    for (a, v) in acc.iter_mut().zip(row) {
                        *a += v.to_f64();
                    }
                }
            })
            .into_iter()
            .map(|s| s / n)
            .collect();
        let scale = self
            .column_sums(x, |x, acc| {
                for row in x.chunks(h) {
                    for ((a, v), m) in acc.iter_mut().zip(row).zip(&mean) {
                        let d = v.to_f64() - m;
                        *a += d * d;
                    }
                }
            })
            .into_iter()
            .map(|s| 1.0 / (s / n + self.eps).sqrt())
            .collect();
        Stats { mean, scale }
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

    fn run<T: WithDType>(&self, x: &[T], gamma: &[T], beta: &[T]) -> Vec<T> {
        let h = self.width;
        let mut out = vec![T::from_f64(0.0); x.len()];
        if h == 0 || x.is_empty() {
            return out;
        }
        let st = self.stats(x);
        let items = self.items(x, &mut out);
        for_each_init(
            items,
            || (),
            |_, (first, x, out)| {
                for (r, (row, o)) in x.chunks(h).zip(out.chunks_mut(h)).enumerate() {
                    let g = (first + r) / self.group;
                    let (gr, br) = (&gamma[g * h..(g + 1) * h], &beta[g * h..(g + 1) * h]);
                    let columns = st.mean.iter().zip(&st.scale).zip(gr.iter().zip(br));
                    for ((o, x), ((m, sc), (gm, bt))) in o.iter_mut().zip(row).zip(columns) {
                        let y = gm.to_f64() * ((x.to_f64() - m) * sc) + bt.to_f64();
                        *o = T::from_f64(if self.relu { y.max(0.0) } else { y });
                    }
                }
            },
        );
        *self.saved.lock().unwrap_or_else(PoisonError::into_inner) = Some(st);
        out
    }

    /// The gradients of `x`, `gamma` and `beta` given the output's `grad`.
    fn grad<T: WithDType>(&self, x: &[T], gamma: &[T], beta: &[T], grad: &[T]) -> [Vec<T>; 3] {
        let h = self.width;
        let zeros = |len: usize| vec![T::from_f64(0.0); len];
        let (mut gx, mut gg, mut gb) = (zeros(x.len()), zeros(gamma.len()), zeros(beta.len()));
        if h == 0 || x.is_empty() {
            return [gx, gg, gb];
        }
        let saved = self
            .saved
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        let st = saved.unwrap_or_else(|| self.stats(x));
        let masked = |row: usize, j: usize, xh: f64, g: f64| -> f64 {
            let grp = row / self.group;
            let y = gamma[grp * h + j].to_f64() * xh + beta[grp * h + j].to_f64();
            if !self.relu || y > 0.0 {
                g
            } else {
                0.0
            }
        };
        // Pass 1, per item: Σu and Σu·x̂ (columns), and the scale's and shift's sums of the
        // groups the item's rows belong to (`[groups spanned, 2H]`, from its first group).
        let h2 = 2 * h;
        let n_items = self.rows.div_ceil(ROWS);
        let mut sums = vec![0.0; n_items * h2];
        let spans: Vec<(usize, usize)> = (0..n_items)
            .map(|i| {
                let (a, b) = (i * ROWS, ((i + 1) * ROWS).min(self.rows) - 1);
                (a / self.group, b / self.group - a / self.group + 1)
            })
            .collect();
        let mut affine: Vec<Vec<f64>> = spans.iter().map(|&(_, k)| vec![0.0; k * h2]).collect();
        let items: Vec<_> = x
            .chunks(ROWS * h)
            .zip(grad.chunks(ROWS * h))
            .zip(sums.chunks_mut(h2))
            .zip(affine.iter_mut())
            .enumerate()
            .collect();
        for_each_init(
            items,
            || (),
            |_, (i, (((x, g), s), aff))| {
                let first = i * ROWS;
                let g0 = spans[i].0;
                for (r, (row, grow)) in x.chunks(h).zip(g.chunks(h)).enumerate() {
                    let n = first + r;
                    let grp = n / self.group;
                    let a = &mut aff[(grp - g0) * h2..(grp - g0 + 1) * h2];
                    for j in 0..h {
                        let xh = (row[j].to_f64() - st.mean[j]) * st.scale[j];
                        let gy = masked(n, j, xh, grow[j].to_f64());
                        let u = gy * gamma[grp * h + j].to_f64();
                        s[j] += u;
                        s[h + j] += u * xh;
                        a[j] += gy * xh;
                        a[h + j] += gy;
                    }
                }
            },
        );
        let n = self.rows as f64;
        let (mut su, mut sux) = (vec![0.0; h], vec![0.0; h]);
        for s in sums.chunks(h2) {
            for j in 0..h {
                su[j] += s[j] / n;
                sux[j] += s[h + j] / n;
            }
        }
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
        for (o, v) in gg.iter_mut().zip(&dg) {
            *o = T::from_f64(*v);
        }
        for (o, v) in gb.iter_mut().zip(&db) {
            *o = T::from_f64(*v);
        }
        // Pass 2: the rows' gradient.
        let items: Vec<_> = self
            .items(x, &mut gx)
            .into_iter()
            .zip(grad.chunks(ROWS * h))
            .collect();
        for_each_init(
            items,
            || (),
            |_, ((first, x, out), g)| {
                for (r, ((row, o), grow)) in x
                    .chunks(h)
                    .zip(out.chunks_mut(h))
                    .zip(g.chunks(h))
                    .enumerate()
                {
                    let n = first + r;
                    let grp = n / self.group;
                    for j in 0..h {
                        let xh = (row[j].to_f64() - st.mean[j]) * st.scale[j];
                        let u = masked(n, j, xh, grow[j].to_f64()) * gamma[grp * h + j].to_f64();
                        o[j] = T::from_f64(st.scale[j] * (u - su[j] - xh * sux[j]));
                    }
                }
            },
        );
        [gx, gg, gb]
    }

    fn check<T>(&self, x: &[T], gamma: &[T], beta: &[T]) -> candle_core::Result<()> {
        let groups = if self.group == 0 || !self.rows.is_multiple_of(self.group) {
            candle_core::bail!(
                "{}: {} rows are not groups of {}",
                Self::NAME,
                self.rows,
                self.group
            )
        } else {
            self.rows / self.group
        };
        let want = [
            ("x", x.len(), self.rows * self.width),
            ("gamma", gamma.len(), groups * self.width),
            ("beta", beta.len(), groups * self.width),
        ];
        for (name, got, expected) in want {
            if got != expected {
                candle_core::bail!(
                    "{}: {name} has {got} values, expected {expected}",
                    Self::NAME
                )
            }
        }
        Ok(())
    }
}

impl CpuKernel<3> for FusedCondNorm {
    const NAME: &'static str = "conditional batch norm";

    fn forward<T: Real>(
        &self,
        [x, gamma, beta]: [&[T]; 3],
    ) -> candle_core::Result<(Vec<T>, Shape)> {
        self.check(x, gamma, beta)?;
        Ok((
            self.run(x, gamma, beta),
            Shape::from((self.rows, self.width)),
        ))
    }

    fn backward<T: Real>(
        &self,
        [x, gamma, beta]: [&[T]; 3],
        grad: &[T],
        _: [bool; 3],
    ) -> candle_core::Result<[Option<Vec<T>>; 3]> {
        self.check(x, gamma, beta)?;
        let [gx, gg, gb] = self.grad(x, gamma, beta, grad);
        Ok([Some(gx), Some(gg), Some(gb)])
    }
}

cpu_op!(FusedCondNorm, 3, "nf-cond-norm");
