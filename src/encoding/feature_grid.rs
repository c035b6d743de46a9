//! Differentiable sampling of feature planes and grids, and scatter pooling of point
//! features into cells: the pieces of Convolutional Occupancy Networks (Peng et al. 2020)
//! that candle lacks.
//!
//! * [`grid_sample`]: bilinear sampling of `[B, C, H, W]` planes or trilinear sampling of
//!   `[B, C, D, H, W]` grids at normalised coordinates in `[0, 1]`, differentiable w.r.t.
//!   the features and the coordinates.
//! * [`scatter`]: per-cell mean or maximum ([`Pooling`]) of point features `[B, N, C]`
//!   given each point's cell, differentiable w.r.t. the features.
//! * [`cell_index`]: the flat cell of each normalised point at a resolution.

use crate::error::{check_float, check_same, check_shape, Dim, Error, Result};
use crate::kernels::{FusedGridSample, FusedScatterMax, GridCorners, GridGeometry};
use crate::narrow::narrow;
use candle_core::{DType, Tensor};

/// Fails naming `arg` if `t` (float) holds a NaN.
fn check_no_nan(t: &Tensor, arg: &'static str) -> Result<()> {
    if t.elem_count() > 0 && t.ne(t)?.max_all()?.to_scalar::<u8>()? > 0 {
        return Err(Error::invalid(
            arg,
            "coordinates without NaN",
            "a NaN coordinate",
        ));
    }
    Ok(())
}

/// Checks `features` and `coords`; returns `(B, N, C, geometry)`.
fn check_sample(features: &Tensor, coords: &Tensor) -> Result<(usize, usize, usize, GridGeometry)> {
    check_float(features, "features")?;
    let fd = features.dims().to_vec();
    if !(fd.len() == 4 || fd.len() == 5) {
        return Err(Error::invalid(
            "features",
            "shape [B, C, H, W] or [B, C, D, H, W]",
            format!("shape {fd:?}"),
        ));
    }
    if let Some(a) = fd[2..].iter().position(|&s| s == 0) {
        return Err(Error::invalid(
            "features",
            "at least one sample along every spatial axis",
            format!("shape {fd:?} (axis {} is empty)", a + 2),
        ));
    }
    let k = fd.len() - 2;
    check_same(coords, "coords", features, "features")?;
    let cd = check_shape(
        coords,
        "coords",
        &[Dim::Is(fd[0]), Dim::Any("N"), Dim::Is(k)],
    )?;
    check_no_nan(coords, "coords")?;
    let g = GridGeometry::new(&fd[2..]);
    if fd[0]
        .checked_mul(g.cells)
        .is_none_or(|v| v > u32::MAX as usize)
    {
        return Err(Error::invalid(
            "features",
            "fewer than 2³² samples over the batch",
            format!("shape {fd:?}"),
        ));
    }
    Ok((fd[0], cd[1], fd[1], g))
}

/// Settings of [`grid_sample`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GridSampleConfig {
    /// Run the reference path (candle ops) even where [`grid_sample`] would run the fused
    /// op (CPU, or CUDA with the `cuda` feature): for second-order derivatives (the fused backward is first order
    /// only) and for comparing the two. Default `false`.
    pub force_reference: bool,
}

/// Samples `features` at `coords`: bilinear sampling of `[B, C, H, W]` planes or
/// trilinear sampling of `[B, C, D, H, W]` grids at normalised coordinates in `[0, 1]`.
///
/// **Convention.** A coordinate `c ∈ [0, 1]` on an axis of `S` samples lies at pixel
/// position `u = c·(S − 1)`: `c = 0` is the centre of the first sample, `c = 1` that of the
/// last (PyTorch's `grid_sample(features, 2c − 1, align_corners=True,
/// padding_mode="border")`, which is what the published decoder calls). `coords[..., 0]`
/// runs along the last axis (`W`), `coords[..., 1]` along `H`, `coords[..., 2]` along `D`.
/// Coordinates outside `[0, 1]` are clamped to it (border padding), and ±∞ with them.
///
/// **Formula.** Per axis, `i = min(⌊u⌋, S − 2)` and `w = u − i ∈ [0, 1]` (on an axis of
/// one sample, `i = 0` and `w = 0`); the result is the multilinear interpolation of the
/// `2ᵏ` corners (`k = 2` or 3):
///
/// `y[b, n, :] = Σ_{c ∈ {0,1}ᵏ} Π_a w_a^{c_a} (1 − w_a)^{1 − c_a} · F[b, :, i + c]`.
///
/// **Gradients.** `y` is linear in `F`: `∂y/∂F` is the corner weight. W.r.t. the coordinate
/// on axis `a`, `∂y/∂c_a = (S_a − 1) · Σ_c ±Π_{a' ≠ a}(…) F[i + c]`, continuous in value
/// across cell borders but not in slope. The derivative returned there is one-sided and
/// fixed by `i = ⌊u⌋`: on an interior border (`u` an integer in `1 … S − 2`) it is the
/// **right** derivative (the cell above), at `c = 0` the right derivative, at `c = 1` the
/// **left** derivative (the last cell; PyTorch's kernel instead reads a corner past the
/// border there, whose weight is zero, and returns a different value). Outside `[0, 1]` the
/// coordinate is clamped and its gradient is **zero**; exactly at 0 and at 1 it is the
/// inward one-sided derivative above (as PyTorch's `clip_coordinates_set_grad`, which
/// passes the gradient at the limits).
///
/// **Kernels.** With f32 or f64 features and coordinates of that dtype, on the CPU and
/// (feature `cuda`) on CUDA, a fused op ([`candle_core::CustomOp2`]) runs. On the CPU: the
/// forward pass and the coordinate gradient in parallel over blocks of points; the
/// feature gradient in parallel over (batch, block of 4 channels), each work item adding
/// the points of its batch in order into its own f64 accumulators, so that the result is
/// the same bit for bit at any thread count. On CUDA: the forward pass one thread per
/// (point, channel), the coordinate gradient one thread per point, both in f64 in the CPU
/// kernel's order; the feature gradient by atomic f64 additions (one thread per point
/// and channel), whose order, and so the last bits of the sums, varies from run to run.
/// The coordinate gradient is computed only when the coordinates are on the autograd
/// graph. Elsewhere (other devices and dtypes), or with
/// [`GridSampleConfig::force_reference`], a reference path of candle ops runs: corner
/// indices and clamping decided on the host from the coordinates (piecewise constant, no
/// gradient), weights from the coordinates on their device, the corners gathered with
/// `index_select` (whose backward is an `index_add`) and summed.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::encoding::{grid_sample, GridSampleConfig};
///
/// // One plane of one channel, 2 × 2 samples: f(x, y) = x + 10 y at the corners.
/// let f = Tensor::new(&[[[[0.0f32, 1.0], [10.0, 11.0]]]], &Device::Cpu)?; // [1, 1, 2, 2]
/// let p = Tensor::new(&[[[0.5f32, 0.25]]], &Device::Cpu)?;                  // [1, 1, 2]
/// let y = grid_sample(&f, &p, &GridSampleConfig::default())?;              // [1, 1, 1]
/// assert!((y.flatten_all()?.to_vec1::<f32>()?[0] - 3.0).abs() < 1e-6);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// * `features`: `[B, C, H, W]` (bilinear, `coords: [B, N, 2]`) or `[B, C, D, H, W]`
///   (trilinear, `coords: [B, N, 3]`), f32 or f64, every spatial axis non-empty;
/// * `coords`: same dtype and device, in `[0, 1]` (clamped otherwise), `N ≥ 0`;
/// * returns `[B, N, C]`.
///
/// Differentiable w.r.t. `features` and `coords` (zero w.r.t. a clamped coordinate;
/// one-sided on cell borders as documented). The fused op runs for f32/f64 on the CPU
/// and (feature `cuda`) on CUDA, the reference path of candle ops elsewhere or with
/// [`GridSampleConfig::force_reference`]; the two agree to rounding.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::encoding::{grid_sample, GridSampleConfig};
///
/// // A 2 × 2 × 2 grid holding its own x coordinate, read at x = 0.3, on both paths.
/// let f = Tensor::new(&[0.0f64, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0], &Device::Cpu)?
///     .reshape((1, 1, 2, 2, 2))?;
/// let p = Tensor::new(&[[[0.3f64, 0.9, 0.1]]], &Device::Cpu)?;
/// for force_reference in [false, true] {
///     let config = GridSampleConfig { force_reference };
///     let y = grid_sample(&f, &p, &config)?.flatten_all()?.to_vec1::<f64>()?;
///     assert!((y[0] - 0.3).abs() < 1e-12);
/// }
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// `features` not f32/f64 of rank 4 or 5 with non-empty spatial axes, or of 2³² samples
/// or more over the batch; `coords` not `[B, N, k]` (`k` = spatial rank) of the features'
/// dtype and device, or holding a NaN (naming `coords`).
pub fn grid_sample(
    features: &Tensor,
    coords: &Tensor,
    config: &GridSampleConfig,
) -> Result<Tensor> {
    let fused = !config.force_reference && crate::kernels::fused_for(features);
    if !fused {
        return grid_sample_reference(features, coords);
    }
    let (b, n, c, geometry) = check_sample(features, coords)?;
    let op = FusedGridSample {
        geometry,
        dims: (b, n, c),
    };
    Ok(features
        .contiguous()?
        .apply_op2(&coords.contiguous()?, op)?)
}

/// [`grid_sample`] by candle ops, on any device and float dtype (the path used where the
/// fused op does not run and with `force_reference`). Same arguments, result and gradients.
fn grid_sample_reference(features: &Tensor, coords: &Tensor) -> Result<Tensor> {
    let (b, n, c, g) = check_sample(features, coords)?;
    let k = g.k;
    let corners = 1usize << k;
    let dev = coords.device();
    let host: Vec<f64> = coords.to_dtype(DType::F64)?.flatten_all()?.to_vec1()?;
    let mut rows = Vec::with_capacity(b * n * corners);
    let mut origin = Vec::with_capacity(b * n * k);
    let mut clamped = Vec::with_capacity(b * n * k);
    let mut inside = Vec::with_capacity(b * n * k);
    let mut cs = GridCorners::new();
    for (p, row) in host.chunks(k).enumerate() {
        let base = (p / n.max(1)) * g.cells;
        g.corners(row, false, &mut cs);
        rows.extend(cs.offset[..corners].iter().map(|&o| (base + o) as u32));
        for (a, &ca) in row.iter().enumerate() {
            origin.push(g.axis(a, ca).0 as f64);
            clamped.push(ca.clamp(0.0, 1.0));
            inside.push(u8::from((0.0..=1.0).contains(&ca)));
        }
    }
    let dt = coords.dtype();
    let origin = Tensor::from_vec(origin, (b, n, k), dev)?.to_dtype(dt)?;
    let clamped = Tensor::from_vec(clamped, (b, n, k), dev)?.to_dtype(dt)?;
    let inside = Tensor::from_vec(inside, (b, n, k), dev)?;
    let cf = inside.where_cond(coords, &clamped)?;
    let scale: Vec<f64> = (0..k).map(|a| (g.size[a].max(1) - 1) as f64).collect();
    let scale = Tensor::new(scale.as_slice(), dev)?.to_dtype(dt)?;
    let w = (cf.broadcast_mul(&scale)? - origin)?; // [B, N, k]
    let one_minus = w.affine(-1.0, 1.0)?;
    let mut weights = Vec::with_capacity(corners);
    for q in 0..corners {
        let mut prod = Tensor::ones((b, n, 1), dt, dev)?;
        for a in 0..k {
            let col = if (q >> a) & 1 == 1 { &w } else { &one_minus };
            prod = (prod * narrow(col, 2, a, 1)?)?;
        }
        weights.push(prod);
    }
    let weights = Tensor::cat(&weights, 2)?; // [B, N, 2ᵏ]
    let table = features
        .reshape((b, c, g.cells))?
        .transpose(1, 2)?
        .contiguous()?
        .reshape((b * g.cells, c))?;
    let idx = Tensor::from_vec(rows, b * n * corners, dev)?;
    let feats = table.index_select(&idx, 0)?.reshape((b, n, corners, c))?;
    Ok(feats.broadcast_mul(&weights.unsqueeze(3)?)?.sum(2)?)
}

/// Checks a scatter call; returns `(B, N, C)` and the cell ids on the host.
fn check_scatter(
    values: &Tensor,
    index: &Tensor,
    cells: usize,
) -> Result<((usize, usize, usize), Vec<u32>)> {
    check_float(values, "values")?;
    let vd = check_shape(
        values,
        "values",
        &[Dim::Any("B"), Dim::Any("N"), Dim::Any("C")],
    )?;
    let (b, n, c) = (vd[0], vd[1], vd[2]);
    if index.dtype() != DType::U32 {
        return Err(Error::invalid(
            "index",
            "dtype u32",
            format!("{:?}", index.dtype()),
        ));
    }
    if !index.device().same_device(values.device()) {
        return Err(Error::invalid(
            "index",
            format!("device {:?} (that of values)", values.device()),
            format!("{:?}", index.device()),
        ));
    }
    check_shape(index, "index", &[Dim::Is(b), Dim::Is(n)])?;
    if b.checked_mul(cells).is_none_or(|v| v > u32::MAX as usize) {
        return Err(Error::invalid(
            "cells",
            "B·cells below 2³²",
            format!("{cells} cells for a batch of {b}"),
        ));
    }
    // The result (C values a cell) and the per-cell counts and offsets (3 more), counted
    // at 8 bytes each, before anything is allocated.
    crate::limits::check_bytes("cells", &[b, cells, c.saturating_add(3)], 8)?;
    let host: Vec<u32> = index.flatten_all()?.to_vec1()?;
    if let Some(p) = host.iter().position(|&i| i as usize >= cells) {
        return Err(Error::invalid(
            "index",
            format!("cell ids below cells = {cells}"),
            format!("{} at [{}, {}]", host[p], p / n.max(1), p % n.max(1)),
        ));
    }
    Ok(((b, n, c), host))
}

/// Flat cell ids `b·cells + index[b, n]` on `dev`.
fn flat_cells(host: &[u32], n: usize, cells: usize, dev: &candle_core::Device) -> Result<Tensor> {
    let flat: Vec<u32> = host
        .iter()
        .enumerate()
        .map(|(p, &i)| ((p / n.max(1)) * cells) as u32 + i)
        .collect();
    Ok(Tensor::from_vec(flat, host.len(), dev)?)
}

/// How [`scatter`] pools the points of a cell.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Pooling {
    /// The mean of the cell's points (as `torch_scatter.scatter_mean`).
    #[default]
    Mean,
    /// The maximum of the cell's points per channel (as `torch_scatter.scatter_max`).
    Max,
}

/// Settings of [`scatter`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ScatterConfig {
    /// The per-cell reduction. Default [`Pooling::Mean`].
    pub pooling: Pooling,
    /// Run the reference path (candle ops) even where [`Pooling::Max`] runs a fused op
    /// (CPU, or CUDA with the `cuda` feature; the mean is made of candle ops everywhere):
    /// for second-order derivatives (the fused backward is first order only) and for
    /// comparing the two. Default `false`.
    pub force_reference: bool,
}

/// Pools point features into cells: `values: [B, N, C]` (f32/f64), `index: [B, N]` (u32
/// cell ids below `cells`, same device) → `[B, cells, C]`, with `S_bq = {n : index[b, n]
/// = q}` the points of cell `q`:
///
/// * [`Pooling::Mean`]: `y[b, q, :] = (1 / |S_bq|) Σ_{n ∈ S_bq} values[b, n, :]`.
///   Differentiable w.r.t. `values` (`∂y[b, q]/∂values[b, n] = 1/|S_bq|` for
///   `n ∈ S_bq`). Candle ops on any device: an `index_add` of the values and a division
///   by the counts (counted on the host).
/// * [`Pooling::Max`]: `y[b, q, j] = max_{n ∈ S_bq} values[b, n, j]`; a NaN among a
///   cell's values gives NaN. Differentiable w.r.t. `values`: each `y[b, q, j]` passes
///   its gradient to one element, the maximising point `n` of that cell and channel;
///   among equal maxima, to the one with the **lowest point index** (and to the first NaN
///   if there is one). On the CPU (f32/f64) a fused op runs (one pass over the points per
///   batch, the backward recomputes the argmax); on CUDA (feature `cuda`, f32/f64) the
///   same op finds the argmax by two atomic passes (the maximum per cell and channel,
///   then the lowest point index holding it), with the same result and tie rule.
///   Elsewhere, or with
///   [`ScatterConfig::force_reference`], a reference path of candle ops runs in rounds
///   over ranks, without a `cells × N × C` tensor: the points of each cell are ordered by
///   index on the host (a counting sort of `index`) and the non-empty cells by decreasing
///   count, so that round `r` updates the running maxima of exactly the first `K_r` cells
///   (those with more than `r` points) with their `r`-th point
///   (`where_cond(candidate > running, candidate, running)`; strict, so ties keep the
///   earlier point). Memory `O(B·cells·C + N·C)`; the number of rounds is the largest
///   cell's point count.
///
/// Empty cells hold 0 (as `torch_scatter`).
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::encoding::{scatter, Pooling, ScatterConfig};
///
/// let v = Tensor::new(&[[[1.0f32], [3.0], [5.0]]], &Device::Cpu)?; // [1, 3, 1]
/// let i = Tensor::new(&[[2u32, 2, 0]], &Device::Cpu)?;             // [1, 3]
/// let mean = ScatterConfig::default();
/// let y = scatter(&v, &i, 3, &mean)?.flatten_all()?.to_vec1::<f32>()?;
/// assert_eq!(y, [5.0, 0.0, 2.0]);
/// for force_reference in [false, true] {
///     let max = ScatterConfig { pooling: Pooling::Max, force_reference };
///     let y = scatter(&v, &i, 3, &max)?.flatten_all()?.to_vec1::<f32>()?;
///     assert_eq!(y, [5.0, 0.0, 3.0]);
/// }
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// `values` not f32/f64 `[B, N, C]`; `index` not u32 `[B, N]` on the same device, or an
/// id ≥ `cells` (naming `index`); `B·cells ≥ 2³²`, or a result and its per-cell counts
/// (`B·cells·(C + 3)` values at 8 bytes) past the allocation limit of 2³³ bytes (8 GiB),
/// checked before anything is allocated (naming `cells`).
pub fn scatter(
    values: &Tensor,
    index: &Tensor,
    cells: usize,
    config: &ScatterConfig,
) -> Result<Tensor> {
    match config.pooling {
        Pooling::Mean => scatter_mean(values, index, cells),
        Pooling::Max => {
            let fused = !config.force_reference && crate::kernels::fused_for(values);
            if !fused {
                return scatter_max_reference(values, index, cells);
            }
            let (dims, index) = check_scatter(values, index, cells)?;
            let op = FusedScatterMax { cells, dims, index };
            Ok(values.contiguous()?.apply_op1(op)?)
        }
    }
}

/// [`Pooling::Mean`] of [`scatter`].
fn scatter_mean(values: &Tensor, index: &Tensor, cells: usize) -> Result<Tensor> {
    let ((b, n, c), host) = check_scatter(values, index, cells)?;
    let dev = values.device();
    let mut counts = vec![0.0f64; b * cells];
    for (p, &i) in host.iter().enumerate() {
        counts[(p / n.max(1)) * cells + i as usize] += 1.0;
    }
    let inv: Vec<f64> = counts.iter().map(|&k| 1.0 / k.max(1.0)).collect();
    let inv = Tensor::from_vec(inv, (b * cells, 1), dev)?.to_dtype(values.dtype())?;
    let sums = Tensor::zeros((b * cells, c), values.dtype(), dev)?;
    let sums = if n > 0 && c > 0 {
        let idx = flat_cells(&host, n, cells, dev)?;
        sums.index_add(&idx, &values.reshape((b * n, c))?, 0)?
    } else {
        sums
    };
    Ok(sums.broadcast_mul(&inv)?.reshape((b, cells, c))?)
}

/// [`Pooling::Max`] of [`scatter`] by candle ops on any device (the rounds described
/// there).
fn scatter_max_reference(values: &Tensor, index: &Tensor, cells: usize) -> Result<Tensor> {
    let ((b, n, c), host) = check_scatter(values, index, cells)?;
    let dev = values.device();
    let zeros = Tensor::zeros((b * cells, c), values.dtype(), dev)?;
    if n == 0 || c == 0 || b == 0 {
        return Ok(zeros.reshape((b, cells, c))?);
    }
    // Counting sort of the points by flat cell (stable: lower point index first).
    let total = b * cells;
    let mut count = vec![0u32; total];
    for (p, &i) in host.iter().enumerate() {
        count[(p / n) * cells + i as usize] += 1;
    }
    let mut start = vec![0usize; total + 1];
    for q in 0..total {
        start[q + 1] = start[q] + count[q] as usize;
    }
    let mut members = vec![0u32; host.len()];
    let mut fill = start.clone();
    for (p, &i) in host.iter().enumerate() {
        let q = (p / n) * cells + i as usize;
        members[fill[q]] = p as u32;
        fill[q] += 1;
    }
    // Non-empty cells by decreasing count (ties by cell id).
    let mut order: Vec<usize> = (0..total).filter(|&q| count[q] > 0).collect();
    order.sort_by(|&x, &y| count[y].cmp(&count[x]).then(x.cmp(&y)));
    let rounds = count[order[0]] as usize;
    let vals = values.reshape((b * n, c))?;
    let pick = |r: usize, k: usize| -> Result<Tensor> {
        let ids: Vec<u32> = order[..k].iter().map(|&q| members[start[q] + r]).collect();
        Ok(vals.index_select(&Tensor::from_vec(ids, k, dev)?, 0)?)
    };
    let k0 = order.len();
    let mut running = pick(0, k0)?;
    let mut k = k0;
    for r in 1..rounds {
        while k > 0 && count[order[k - 1]] as usize <= r {
            k -= 1;
        }
        let head = running.narrow(0, 0, k)?;
        let cand = pick(r, k)?;
        let take = cand
            .gt(&head)?
            .maximum(&(cand.ne(&cand)? * head.eq(&head)?)?)?;
        let head = take.where_cond(&cand, &head)?;
        running = if k < k0 {
            Tensor::cat(&[&head, &running.narrow(0, k, k0 - k)?], 0)?
        } else {
            head
        };
    }
    let ids: Vec<u32> = order.iter().map(|&q| q as u32).collect();
    let ids = Tensor::from_vec(ids, k0, dev)?;
    Ok(zeros.index_add(&ids, &running, 0)?.reshape((b, cells, c))?)
}

/// Flat cell ids of normalised points: `coords: [B, N, k]` (f32/f64, `k` = 2 or 3, in
/// `[0, 1]`) → `[B, N]` u32,
///
/// `x_a = ⌊clamp(c_a, 0, 1 − 10⁻⁶) · R⌋`, `id = x₀ + R·(x₁ + R·x₂)` (`x₀` fastest),
///
/// as the published code clamps and indexes (coordinates past the border fall in the
/// border cells). Not differentiable (the ids are integers). Computed in f64 on the
/// coordinates' device.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::encoding::cell_index;
///
/// let p = Tensor::new(&[[[0.0f32, 0.0], [0.99, 0.3], [1.0, 1.0], [-2.0, 0.5]]], &Device::Cpu)?;
/// let ids = cell_index(&p, 4)?.flatten_all()?.to_vec1::<u32>()?;
/// assert_eq!(ids, [0, 3 + 4, 15, 8]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// `coords` not f32/f64 `[B, N, 2]` or `[B, N, 3]`, or holding a NaN (naming `coords`);
/// `resolution` zero or with `resolutionᵏ ≥ 2³²` (naming `resolution`).
pub fn cell_index(coords: &Tensor, resolution: usize) -> Result<Tensor> {
    check_float(coords, "coords")?;
    let d = check_shape(
        coords,
        "coords",
        &[Dim::Any("B"), Dim::Any("N"), Dim::Any("k")],
    )?;
    let k = d[2];
    if !(k == 2 || k == 3) {
        return Err(Error::invalid(
            "coords",
            "shape [B, N, 2] or [B, N, 3]",
            format!("shape {d:?}"),
        ));
    }
    let cap = (resolution as u128).pow(k as u32);
    if resolution == 0 || cap > u128::from(u32::MAX) {
        return Err(Error::invalid(
            "resolution",
            format!("1 to ⌊(2³² − 1)^(1/{k})⌋"),
            resolution.to_string(),
        ));
    }
    check_no_nan(coords, "coords")?;
    let r = resolution as f64;
    let x = coords
        .to_dtype(DType::F64)?
        .clamp(0.0, 1.0 - 1e-6)?
        .affine(r, 0.0)?
        .floor()?
        .clamp(0.0, r - 1.0)?;
    let mut id = narrow(&x, 2, k - 1, 1)?;
    for a in (0..k - 1).rev() {
        id = (id.affine(r, 0.0)? + narrow(&x, 2, a, 1)?)?;
    }
    Ok(id.squeeze(2)?.to_dtype(DType::U32)?)
}
