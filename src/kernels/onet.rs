//! The ONet decoder's whole training pass as one CPU op (`FusedOnet`): the point layer,
//! every conditional-batch-norm ResNet block and the output layer, forward and backward,
//! where candle's ops take about ten tensors per layer (the product, the bias's broadcast
//! and its row sum, the residual sum) and the same again for their gradients, each
//! gradient added into a zero-filled one.
//!
//! ## Math
//! With rows `p: [N, 3]`, `net₀ = p W_pᵀ + b_p` and, for blocks `k = 0 … B − 1`,
//!
//! ```text
//! aₖ = CN₂ₖ(netₖ),   hₖ = aₖ W₀ₖᵀ + b₀ₖ,   a′ₖ = CN₂ₖ₊₁(hₖ),
//! netₖ₊₁ = netₖ + a′ₖ W₁ₖᵀ + b₁ₖ,
//! ```
//!
//! and the logit `l = CN₂B(net_B) w_outᵀ + b_out`, where `CNⱼ(x) = relu(γ ⊙ x̂ + β)` is the
//! conditional batch norm of [`FusedCondNorm`] (batch statistics over all `N` rows, the
//! scale and shift of row `n`'s group). The backward pass runs the chain rule in reverse:
//! for each linear layer `y = x Wᵀ + b`, `∂L/∂x = ḡ W`, `∂L/∂W = ḡᵀ x`, `∂L/∂b = Σ_rows ḡ`;
//! for each normalisation the fused norm's own backward pass; the residual adds its
//! gradient to the block's input.
//!
//! ## Execution
//! Layer by layer over all rows (each normalisation needs the statistics of the whole
//! batch before its first row), each product over row tiles of [`TILE`] on candle's CPU
//! pool with the crate's matrix product. A normalisation's output is never stored: each
//! product tile normalises its rows of the layer's input into a buffer of its own (in
//! cache) before multiplying, in both passes. The forward pass keeps every block's input
//! and hidden rows for the backward pass (the op's own slot, taken by the first backward
//! pass; a second recomputes them). The parameter gradients
//! are summed per chunk of [`CHUNK`] rows and the chunks in their order, so the result
//! does not depend on the thread count.
//!
//! Every `[N, H]` buffer of both passes comes from and returns to a [`BufferPool`] that
//! the decoder keeps between steps: a fresh buffer of that size is a fresh mapping of
//! zero pages, whose page faults took about half of the step's time with the system
//! allocator.

use super::cond_norm::{FusedCondNorm, Ready, Stats};
use super::dispatch::{cpu_op, CpuKernel, Real};
use super::mlp::{chunk_rows, matmul, sum_chunks, transpose, View, CHUNK, TILE};
use super::parallel::{for_each_init, wide};
use super::pool::BufferPool;
use candle_core::Shape;
use std::any::Any;
use std::sync::{Arc, Mutex, PoisonError};

/// The ONet decoder's training pass on `points: [N, 3]`, with the normalisations' scales
/// and shifts `cond` (norm-major: for normalisation `j` in the order block 0's two, block
/// 1's two, …, the output's, `γⱼ: [G, H]` then `βⱼ: [G, H]`, `G = N / group`) and the
/// linear layers' parameters `params` (for `fc_p`, each block's `fc0` and `fc1`, and
/// `fc_out` in that order: the row-major `[out, in]` weight, then the bias). Output: the
/// logits `[N]`.
#[derive(Debug)]
pub(crate) struct FusedOnet {
    rows: usize,
    hidden: usize,
    blocks: usize,
    group: usize,
    /// One fused normalisation per layer (`2B + 1`), whose `saved` statistics the caller
    /// reads after the forward pass.
    norms: Vec<FusedCondNorm>,
    /// The linear layers in `params`: `fc_p`, each block's `fc0` and `fc1`, `fc_out`.
    lin: Vec<Lin>,
    /// The forward pass's activations ([`Acts`] of the dtype), for the backward pass.
    acts: Mutex<Option<Box<dyn Any + Send>>>,
    scratch: Arc<BufferPool>,
}

/// What the forward pass keeps: `nets[k]` (block `k`'s input, `B + 1` with the output
/// normalisation's) and `hid[k]` (block `k`'s hidden rows); the normalisations' outputs
/// are computed tile by tile where a product reads them, and again in the backward pass.
struct Acts<T> {
    nets: Vec<Vec<T>>,
    hid: Vec<Vec<T>>,
}

/// A linear layer's `[out, in]` weight and `[out]` bias in the flat parameters.
#[derive(Clone, Copy, Debug)]
struct Lin {
    w: usize,
    b: usize,
    input: usize,
    out: usize,
}

impl Lin {
    fn weight<'a, T>(&self, p: &'a [T]) -> &'a [T] {
        &p[self.w..self.w + self.out * self.input]
    }

    fn bias<'a, T>(&self, p: &'a [T]) -> &'a [T] {
        &p[self.b..self.b + self.out]
    }

    /// `W` transposed, `[in, out]` row-major.
    fn transposed<T: Copy>(&self, p: &[T]) -> Vec<T> {
        let w = self.weight(p);
        let mut wt = w.to_vec();
        transpose(w, self.out, &mut wt);
        wt
    }
}

impl FusedOnet {
    /// The op for `rows` points of `hidden` features through `blocks` blocks, one code per
    /// `group` rows (`rows` a positive multiple of it), normalisation constant `eps`, its
    /// row buffers from `scratch`.
    pub(crate) fn new(
        (rows, hidden, blocks): (usize, usize, usize),
        group: usize,
        eps: f64,
        scratch: Arc<BufferPool>,
    ) -> Self {
        let norms = (0..2 * blocks + 1)
            .map(|_| FusedCondNorm {
                rows,
                width: hidden,
                group,
                eps,
                relu: true,
                saved: Arc::new(Mutex::new(None)),
            })
            .collect();
        Self {
            rows,
            hidden,
            blocks,
            group,
            norms,
            lin: layers(hidden, blocks),
            acts: Mutex::new(None),
            scratch,
        }
    }

    /// Each normalisation's batch statistics, set by the forward pass.
    pub(crate) fn saved(&self) -> Vec<Arc<Mutex<Option<Stats>>>> {
        self.norms.iter().map(|n| Arc::clone(&n.saved)).collect()
    }

    fn n_params(&self) -> usize {
        self.lin.last().map_or(0, |l| l.b + l.out)
    }

    /// Normalisation `j`'s scales and shifts in `cond`.
    fn affine<'a, T>(&self, cond: &'a [T], j: usize) -> (&'a [T], &'a [T]) {
        let gh = self.rows / self.group * self.hidden;
        (
            &cond[2 * j * gh..(2 * j + 1) * gh],
            &cond[(2 * j + 1) * gh..(2 * j + 2) * gh],
        )
    }

    fn check<T>(&self, [p, cond, params]: [&[T]; 3]) -> candle_core::Result<()> {
        let name = <Self as CpuKernel<3>>::NAME;
        if self.group == 0 || self.rows == 0 || !self.rows.is_multiple_of(self.group) {
            candle_core::bail!(
                "{name}: {} rows are not groups of {}",
                self.rows,
                self.group
            )
        }
        let gh = self.rows / self.group * self.hidden;
        let want = [
            ("points", p.len(), self.rows * 3),
            ("cond", cond.len(), (4 * self.blocks + 2) * gh),
            ("params", params.len(), self.n_params()),
        ];
        for (what, got, expected) in want {
            if got != expected {
                candle_core::bail!("{name}: {what} has {got} values, expected {expected}")
            }
        }
        Ok(())
    }

    /// Normalisation `j` over rows `x`, ready to apply: its statistics computed (and
    /// saved) in the forward pass, read from `saved` in the backward pass.
    fn ready<'a, T: Real>(&'a self, j: usize, cond: &'a [T], x: &[T], fresh: bool) -> Ready<'a, T> {
        self.norms[j].ready(x, self.affine(cond, j), fresh)
    }

    /// `y = (res or 0) + b + a Wᵀ` for rows `a = norm(x)` (or `x`), `x: [N, in]`, of
    /// layer `l`, into a new buffer.
    fn linear<T: Real>(
        &self,
        (x, norm): (&[T], Option<&Ready<'_, T>>),
        l: Lin,
        params: &[T],
        res: Option<&[T]>,
    ) -> Vec<T> {
        let mut y = self.scratch.take(x.len() / l.input * l.out);
        linear((x, norm), l, params, res, &mut y);
        y
    }

    fn run<T: Real>(&self, [p, cond, params]: [&[T]; 3]) -> (Vec<T>, Acts<T>) {
        let lin = &self.lin;
        let mut net = self.linear((p, None), lin[0], params, None);
        let mut acts = Acts {
            nets: Vec::with_capacity(self.blocks + 1),
            hid: Vec::with_capacity(self.blocks),
        };
        for k in 0..self.blocks {
            let n0 = self.ready(2 * k, cond, &net, true);
            let hid = self.linear((&net, Some(&n0)), lin[1 + 2 * k], params, None);
            let n1 = self.ready(2 * k + 1, cond, &hid, true);
            let next = self.linear((&hid, Some(&n1)), lin[2 + 2 * k], params, Some(&net));
            acts.nets.push(std::mem::replace(&mut net, next));
            acts.hid.push(hid);
        }
        let j = 2 * self.blocks;
        let nj = self.ready(j, cond, &net, true);
        let mut logits = vec![T::from_f64(0.0); self.rows];
        linear((&net, Some(&nj)), lin[j + 1], params, None, &mut logits);
        acts.nets.push(net);
        (logits, acts)
    }

    /// Returns the activations' buffers to the scratch.
    fn give_back<T: Real>(&self, acts: Acts<T>) {
        for v in acts.nets.into_iter().chain(acts.hid) {
            self.scratch.give(v);
        }
    }

    fn grad<T: Real>(
        &self,
        [p, cond, params]: [&[T]; 3],
        gl: &[T],
        want_points: bool,
    ) -> (Option<Vec<T>>, Vec<T>, Vec<T>) {
        let taken = self
            .acts
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take()
            .and_then(|b| b.downcast::<Acts<T>>().ok());
        let acts = match taken {
            Some(a) => *a,
            None => self.run([p, cond, params]).1,
        };
        let lin = &self.lin;
        let mut gp = vec![T::from_f64(0.0); params.len()];
        let mut gc = vec![T::from_f64(0.0); cond.len()];
        let gh = self.rows / self.group * self.hidden;
        // A hidden layer's input gradient (into a new buffer) and parameter gradients, its
        // input the output of normalisation `j` over rows `x`; with the normalisation,
        // ready for its own backward pass.
        let mut back = |(j, x): (usize, &[T]), l: Lin, g: &[T]| {
            let mut gx = self.scratch.take(x.len());
            let norm = self.ready(j, cond, x, false);
            linear_grad((x, Some(&norm)), l, params, g, Some(&mut gx)).write(l, &mut gp);
            (gx, norm)
        };
        // Normalisation `j`'s backward pass: its scales' and shifts' gradients into `gc`,
        // its rows' into a new buffer; `g` returns to the scratch.
        let mut norm_back = |j: usize, x: &[T], (g, norm): (Vec<T>, Ready<'_, T>)| {
            let mut gx = self.scratch.take(x.len());
            let [gg, gb] = norm.grad(x, &g, &mut gx);
            gc[2 * j * gh..(2 * j + 1) * gh].copy_from_slice(&gg);
            gc[(2 * j + 1) * gh..(2 * j + 2) * gh].copy_from_slice(&gb);
            self.scratch.give(g);
            gx
        };
        let j = 2 * self.blocks;
        let ga = back((j, &acts.nets[self.blocks]), lin[j + 1], gl);
        let mut gnet = norm_back(j, &acts.nets[self.blocks], ga);
        for k in (0..self.blocks).rev() {
            let ga1 = back((2 * k + 1, &acts.hid[k]), lin[2 + 2 * k], &gnet);
            let ghid = norm_back(2 * k + 1, &acts.hid[k], ga1);
            let ga0 = back((2 * k, &acts.nets[k]), lin[1 + 2 * k], &ghid);
            self.scratch.give(ghid);
            let gin = norm_back(2 * k, &acts.nets[k], ga0);
            add_assign(&mut gnet, &gin);
            self.scratch.give(gin);
        }
        let mut gpts = want_points.then(|| vec![T::from_f64(0.0); p.len()]);
        linear_grad((p, None), lin[0], params, &gnet, gpts.as_deref_mut()).write(lin[0], &mut gp);
        self.scratch.give(gnet);
        self.give_back(acts);
        (gpts, gc, gp)
    }
}

/// The linear layers of a decoder of width `h` with `blocks` blocks at their offsets in
/// the flat parameters: `fc_p`, then each block's `fc0` and `fc1`, then `fc_out`.
fn layers(h: usize, blocks: usize) -> Vec<Lin> {
    let mut shapes = vec![(3, h)];
    for _ in 0..blocks {
        shapes.extend([(h, h), (h, h)]);
    }
    shapes.push((h, 1));
    let mut at = 0;
    shapes
        .into_iter()
        .map(|(input, out)| {
            let l = Lin {
                w: at,
                b: at + out * input,
                input,
                out,
            };
            at = l.b + out;
            l
        })
        .collect()
}

/// `a += b`, elementwise, in parallel.
fn add_assign<T: Real>(a: &mut [T], b: &[T]) {
    let items: Vec<_> = a.chunks_mut(CHUNK * 64).zip(b.chunks(CHUNK * 64)).collect();
    for_each_init(
        items,
        || (),
        |_, (a, b)| {
            wide(|| {
                for (x, &y) in a.iter_mut().zip(b) {
                    *x += y;
                }
            })
        },
    );
}

/// `y = (res or 0) + b + a Wᵀ` for rows `a = norm(x)` (or `x` without a normalisation),
/// `x: [N, in]`, of linear layer `l` in `params`, into `y: [N, out]` (every value
/// written); each tile's normalised rows in a buffer of its own.
fn linear<T: Real>(
    (x, norm): (&[T], Option<&Ready<'_, T>>),
    l: Lin,
    params: &[T],
    res: Option<&[T]>,
    y: &mut [T],
) {
    let (input, out) = (l.input, l.out);
    let wt = l.transposed(params);
    let bias = l.bias(params);
    let res_tiles: Vec<Option<&[T]>> = match res {
        Some(r) => r.chunks(TILE * out).map(Some).collect(),
        None => vec![None; y.len().div_ceil(TILE * out)],
    };
    let items: Vec<_> = y
        .chunks_mut(TILE * out)
        .zip(x.chunks(TILE * input))
        .zip(res_tiles)
        .enumerate()
        .collect();
    for_each_init(items, Vec::new, |buf, (t, ((y, x), res))| {
        let x = normalised(norm, (t * TILE, x), buf);
        wide(|| {
            for (k, row) in y.chunks_mut(out).enumerate() {
                match res {
                    Some(r) => {
                        for ((v, &b), &r) in row.iter_mut().zip(bias).zip(&r[k * out..]) {
                            *v = r + b;
                        }
                    }
                    None => row.copy_from_slice(bias),
                }
            }
        });
        let r = x.len() / input;
        matmul(
            (r, out, input),
            y,
            View::rows(0, out),
            true,
            x,
            View::rows(0, input),
            &wt,
            View::rows(0, out),
            T::from_f64(1.0),
        );
    });
}

/// Rows `x` from row `first` on, normalised by `norm` into `buf` (resized to them), or
/// `x` itself without a normalisation.
fn normalised<'a, T: Real>(
    norm: Option<&Ready<'_, T>>,
    (first, x): (usize, &'a [T]),
    buf: &'a mut Vec<T>,
) -> &'a [T] {
    match norm {
        Some(n) => {
            buf.resize(x.len(), T::from_f64(0.0));
            n.apply(first, x, buf);
            buf
        }
        None => x,
    }
}

/// A linear layer's weight and bias gradients.
struct LinGrads<T> {
    w: Vec<T>,
    b: Vec<T>,
}

impl<T: Real> LinGrads<T> {
    fn write(self, l: Lin, gp: &mut [T]) {
        gp[l.w..l.w + self.w.len()].copy_from_slice(&self.w);
        gp[l.b..l.b + self.b.len()].copy_from_slice(&self.b);
    }
}

/// `(∂L/∂W = ḡᵀ a, ∂L/∂b = Σ_rows ḡ)` of `y = a Wᵀ + b` (layer `l`) for rows
/// `a = norm(x)` (or `x`), `x: [N, in]`, and `ḡ = gy: [N, out]`, and `∂L/∂a = ḡ W` into
/// `gx` (every value written) when given; each tile's normalised rows recomputed in a
/// buffer of its own.
fn linear_grad<T: Real>(
    (x, norm): (&[T], Option<&Ready<'_, T>>),
    l: Lin,
    params: &[T],
    gy: &[T],
    gx: Option<&mut [T]>,
) -> LinGrads<T> {
    let (input, out) = (l.input, l.out);
    let n = x.len() / input;
    let w = l.weight(params);
    let per = out * input + out;
    let chunks = n.div_ceil(CHUNK).max(1);
    let mut part = vec![T::from_f64(0.0); chunks * per];
    let items: Vec<_> = part
        .chunks_mut(per)
        .zip(x.chunks(CHUNK * input))
        .zip(gy.chunks(CHUNK * out))
        .zip(chunk_rows(gx, input, chunks))
        .enumerate()
        .collect();
    for_each_init(items, Vec::new, |buf, (c, (((part, x), gy), gx))| {
        let (pw, pb) = part.split_at_mut(out * input);
        let rows = gy.len() / out;
        for t in (0..rows).step_by(TILE) {
            let r = TILE.min(rows - t);
            let xt = (c * CHUNK + t, &x[t * input..(t + r) * input]);
            let (xt, gt) = (normalised(norm, xt, buf), &gy[t * out..(t + r) * out]);
            // ∂L/∂W += ḡᵀ x over the tile's rows.
            matmul(
                (out, input, r),
                pw,
                View::rows(0, input),
                true,
                gt,
                View::transposed(0, out),
                xt,
                View::rows(0, input),
                T::from_f64(1.0),
            );
        }
        wide(|| {
            for row in gy.chunks(out) {
                for (s, &g) in pb.iter_mut().zip(row) {
                    *s += g;
                }
            }
        });
        if let Some(gx) = gx {
            matmul(
                (rows, input, out),
                gx,
                View::rows(0, input),
                false,
                gy,
                View::rows(0, out),
                w,
                View::rows(0, input),
                T::from_f64(1.0),
            );
        }
    });
    sum_chunks(&mut part, per);
    let b = part.split_off(out * input);
    LinGrads { w: part, b }
}

impl CpuKernel<3> for FusedOnet {
    const NAME: &'static str = "ONet decoder";

    fn forward<T: Real>(&self, inputs: [&[T]; 3]) -> candle_core::Result<(Vec<T>, Shape)> {
        self.check(inputs)?;
        let (logits, acts) = self.run(inputs);
        *self.acts.lock().unwrap_or_else(PoisonError::into_inner) = Some(Box::new(acts));
        Ok((logits, Shape::from(self.rows)))
    }

    fn backward<T: Real>(
        &self,
        inputs: [&[T]; 3],
        grad: &[T],
        [want_points, _, _]: [bool; 3],
    ) -> candle_core::Result<[Option<Vec<T>>; 3]> {
        self.check(inputs)?;
        if grad.len() != self.rows {
            candle_core::bail!(
                "{}: gradient of {} values, expected {}",
                Self::NAME,
                grad.len(),
                self.rows
            )
        }
        let (gp, gc, gw) = self.grad(inputs, grad, want_points);
        Ok([gp, Some(gc), Some(gw)])
    }
}

cpu_op!(FusedOnet, 3, "nf-onet-decoder");
