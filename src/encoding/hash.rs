//! instant-NGP's multiresolution hash encoding ([`HashGrid`]) and its reference path; the
//! fused op is the kernel layer's `FusedHashGrid`, which this module builds from the
//! grid's level geometry and runs on the CPU and, with the `cuda` feature, on CUDA.

use super::{check_tangents, Encoding};
use crate::error::{check_finite, check_float, check_shape, Dim, Error, Result};
use crate::kernels::{FusedHashGrid, HashCorners, HashLevel, HashPlan};
use crate::limits;
use candle_core::{DType, Tensor};
use candle_nn::{Init, VarBuilder};
use std::sync::Arc;

/// Settings of [`hash_grid`].
#[derive(Clone, Debug, PartialEq)]
pub struct HashGridConfig {
    /// Input dimension `D`, 1 to 4 (3 for points).
    pub in_dim: usize,
    /// Number of levels `L` (instant-NGP: 16).
    pub levels: usize,
    /// Features per level `F` (instant-NGP: 2).
    pub features: usize,
    /// `T`: each level's table holds at most `2ᵀ` rows. Default 15: 32 Ki rows, 256 KiB
    /// of f32 features per level at `F = 2`, which a core's L2 cache holds, and about 0.95 M
    /// parameters in all, which Adam updates every step. (instant-NGP uses 19 on GPUs.)
    /// On the NeRF example's dataset, 2 cores, finest resolution 2048: 0.066 s per step
    /// against 0.12 s with 17 over the first 2.5 minutes, and a higher held-out PSNR then
    /// (docs/benchmarks.md).
    pub log2_table_size: u32,
    /// Coarsest resolution `N_min` (cells per axis; instant-NGP: 16).
    pub base_resolution: f64,
    /// Finest resolution `N_max` (instant-NGP: 2048 × the scene's scale).
    pub finest_resolution: f64,
    /// The scene box's lower corner (`D` values); points are clamped into the box.
    pub lo: Vec<f64>,
    /// The scene box's upper corner (`D` values, each above `lo`).
    pub hi: Vec<f64>,
    /// The tables start uniform in `[−s, s]` (instant-NGP: 1e-4).
    pub init_scale: f64,
    /// Run the reference path (candle ops) even where [`Encoding::forward`] would run the
    /// fused op (CPU, or CUDA with the `cuda` feature): for second-order derivatives (the fused backward is first order
    /// only) and for comparing the two. Two grids built from the same `VarBuilder` map
    /// share one table, so a grid and its reference twin evaluate the same parameters.
    /// Default `false`.
    pub force_reference: bool,
    /// Make the table gradient's bits independent of thread scheduling on CUDA. The CUDA
    /// kernel adds every point's contribution to a table entry with atomics; in f64 by
    /// default (`false`: the order of the additions, hence the last bits, varies from run to
    /// run), or with `true` in 64-bit fixed point with a power-of-two scale
    /// `S = 2^⌊62 − log₂(N·max|g|)⌋` (`N` points, `g` the upstream gradient), whose
    /// integer sums do not depend on the order: the same inputs give the same gradient bit
    /// for bit, within `K·N·max|g|·2⁻⁶³` of the exact sum for an entry that `K` points
    /// touch (and the f64 atomics where `max|g|` is not finite). Costs one read-back of
    /// `max|g|` per backward pass. The CPU kernel is deterministic either way (it sums in
    /// a fixed order) and ignores this. Default `false`.
    pub deterministic: bool,
}

impl Default for HashGridConfig {
    /// 3-D points in `[−1, 1]³`, 16 levels of 2 features, tables of `2¹⁵` rows,
    /// resolutions 16 to 2048, initialised in `U(−1e-4, 1e-4)`, the fused op where it runs.
    fn default() -> Self {
        Self {
            in_dim: 3,
            levels: 16,
            features: 2,
            log2_table_size: 15,
            base_resolution: 16.0,
            finest_resolution: 2048.0,
            lo: vec![-1.0; 3],
            hi: vec![1.0; 3],
            init_scale: 1e-4,
            force_reference: false,
            deterministic: false,
        }
    }
}

/// A multiresolution hash grid: its configuration and table `[Σ_l T_l, F]`; build it
/// with [`hash_grid`].
///
/// Multiresolution hash encoding (Müller et al. 2022, instant-NGP) with a fused op (CPU, and
/// CUDA with the `cuda` feature).
///
/// A point `x ∈ ℝᴰ` (D ≤ 4) is mapped into the unit cube of the scene box,
/// `t = clamp((x − lo) / (hi − lo), 0, 1)`, and looked up at `L` levels of resolution
/// `N_l = ⌊N_min · b^l⌋` (cells per axis), `b = (N_max / N_min)^{1/(L−1)}`. At level `l`,
/// `u = t·N_l`, the cell is `i = min(⌊u⌋, N_l − 1)` and the local coordinates
/// `w = u − i ∈ [0, 1]ᴰ`; the `2ᴰ` corners `i + c` (`c ∈ {0, 1}ᴰ`) index the level's
/// table of `T_l` rows of `F` features, and the output is the multilinear interpolation
///
/// `y_l = Σ_c (Π_d w_d^{c_d} (1 − w_d)^{1 − c_d}) · θ_l[h_l(i + c)]`,
///
/// concatenated over levels: `[N, L·F]`, level-major. The index `h_l` is dense
/// (`Σ_d v_d (N_l + 1)^d`) on levels whose `(N_l + 1)ᴰ` vertices fit the table
/// (`T_l = (N_l + 1)ᴰ` then), and otherwise the spatial hash
/// `(⊕_d v_d · π_d) mod 2ᵀ` with instant-NGP's primes `π = (1, 2654435761, 805459861,
/// 3674653429)`, in wrapping 32-bit arithmetic. Distinct vertices may then share a row
/// (collisions); training resolves them as instant-NGP does, by the gradient of the
/// finer levels' many samples.
///
/// **Gradients.** The output is linear in the tables: `∂y/∂θ` is the interpolation
/// weight of each corner. W.r.t. the position it is piecewise smooth: inside a cell
/// `∂y_l/∂x_d = (N_l / (hi_d − lo_d)) · Σ_c θ_l[h(i + c)] ∂w_c/∂w_d`, continuous across
/// cell faces in value but not in slope (a kink on every face at every level), and zero
/// outside the box, where `t` is clamped. Points on a face belong to the cell above
/// (`⌊u⌋`), except on the box's upper face, which belongs to the last cell.
///
/// **The fused op** (f32/f64; on the CPU, and on CUDA with the `cuda` feature) runs the
/// forward pass over points in parallel. Its backward pass computes the position gradient
/// only when the positions are on the autograd graph (a `Var` or the result of tracked
/// ops), so a NeRF step, whose sample positions are data, does not pay for it. On the CPU
/// it accumulates the table gradient level by level, each level's points in order, so
/// that it is the same bit for bit at any thread count; on CUDA (one thread per level and
/// point) by atomic f64 additions, whose order, and so the last bits of the sums, varies
/// from run to run; the forward pass and the position gradient are computed in f64 in
/// the CPU kernel's order on either device. The reference path ([`HashGridConfig::force_reference`], candle ops:
/// the indices and cells computed on the host, the weights and the gathers on the
/// tensors' device, `index_select` whose backward is an `index_add`) runs on any device,
/// is used where the fused op does not run, and is what [`Encoding::forward_jvp`] uses
/// (its tangents stay differentiable w.r.t. the table, which normals and the eikonal loss
/// need).
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::{VarBuilder, VarMap};
/// use neural_fields::encoding::{hash_grid, Encoding, HashGridConfig};
///
/// let varmap = VarMap::new();
/// let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
/// let grid = hash_grid(&HashGridConfig::default(), vb.pp("grid"))?;
/// let x = Tensor::new(&[[0.1f32, -0.2, 0.3], [0.5, 0.5, 0.5]], &Device::Cpu)?;
/// let y = grid.forward(&x)?;
/// assert_eq!(y.dims(), &[2, 32]); // 16 levels × 2 features
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct HashGrid {
    config: HashGridConfig,
    table: Tensor,
    plan: Arc<HashPlan>,
}

/// Builds a [`HashGrid`] whose table (`table`, `[Σ_l T_l, F]`) comes from `vb`, uniform in
/// `[−init_scale, init_scale]`, in `vb`'s dtype and device.
///
/// Over an object's scene box, train the table with Adam at ε = 1e-15 (instant-NGP's;
/// [`crate::nn::Adam`] with `ParamsAdamW { eps: 1e-15, .. }`): where a table entry's
/// gradients are below about ε, ε instead of their scale sets Adam's step, and a NeRF's
/// table over a tight scene box stalled for 15 000 steps at the usual 1e-8. Over a
/// contracted unbounded scene 1e-8 did better on the report capture (docs/benchmarks.md,
/// "Adam's ε and the hash grid" and "ε in an unbounded scene, probed").
///
/// # Errors
/// `config.in_dim` outside 1..=4; zero `levels` or `features`; `log2_table_size`
/// outside 1..=24; resolutions that are not finite, below 1, decreasing, or whose vertex
/// coordinates would not fit in 32 bits (`finest_resolution` ≥ 2³² − 1); `lo`/`hi` not
/// `in_dim` finite values with `lo < hi`; a table (`Σ_l T_l × features` values of `vb`'s
/// dtype) past the allocation limit of 2³³ bytes (8 GiB), refused before anything is
/// allocated and named `config.levels × config.features × table rows`; errors of `vb`.
pub fn hash_grid(config: &HashGridConfig, vb: VarBuilder) -> Result<HashGrid> {
    let plan = Arc::new(plan(config, vb.dtype().size_in_bytes())?);
    let rows = plan.levels.iter().map(|l| l.rows).sum::<usize>();
    let s = config.init_scale;
    let table = vb.get_with_hints(
        (rows, config.features),
        "table",
        Init::Uniform { lo: -s, up: s },
    )?;
    Ok(HashGrid {
        config: config.clone(),
        table,
        plan,
    })
}

fn plan(c: &HashGridConfig, elem_bytes: usize) -> Result<HashPlan> {
    let bad =
        |arg: &'static str, expected: &str, got: String| Err(Error::invalid(arg, expected, got));
    if !(1..=4).contains(&c.in_dim) {
        return bad("config.in_dim", "1 to 4", c.in_dim.to_string());
    }
    if c.levels == 0 || c.features == 0 {
        return bad(
            "config.levels, config.features",
            "at least 1 each",
            format!("{}, {}", c.levels, c.features),
        );
    }
    if !(1..=24).contains(&c.log2_table_size) {
        return bad(
            "config.log2_table_size",
            "1 to 24",
            c.log2_table_size.to_string(),
        );
    }
    let (base, finest) = (c.base_resolution, c.finest_resolution);
    if !(base.is_finite() && finest.is_finite() && base >= 1.0 && finest >= base) {
        return bad(
            "config.base_resolution, config.finest_resolution",
            "finite resolutions with 1 ≤ base ≤ finest",
            format!("{base}, {finest}"),
        );
    }
    // Vertex coordinates run to N_l, which must fit u32 (and N_l + 1 too).
    if finest >= f64::from(u32::MAX) - 1.0 {
        return bad(
            "config.finest_resolution",
            "below 2³² − 1 (vertex coordinates are 32-bit)",
            finest.to_string(),
        );
    }
    let d = c.in_dim;
    if c.lo.len() != d || c.hi.len() != d {
        return bad(
            "config.lo, config.hi",
            "in_dim values each",
            format!("{} and {} values for in_dim {d}", c.lo.len(), c.hi.len()),
        );
    }
    if let Some(k) =
        (0..d).find(|&k| !(c.lo[k].is_finite() && c.hi[k].is_finite() && c.lo[k] < c.hi[k]))
    {
        return bad(
            "config.lo, config.hi",
            "finite bounds with lo < hi on every axis",
            format!("axis {k}: lo {}, hi {}", c.lo[k], c.hi[k]),
        );
    }
    let growth = if c.levels > 1 {
        (finest.ln() - base.ln()) / (c.levels - 1) as f64
    } else {
        0.0
    };
    let cap = 1u64 << c.log2_table_size;
    // Every level holds at least min(2^D, T) rows: a first bound on the table before the
    // levels are even counted, then the exact table and the level list.
    let min_rows = (1usize << d).min(cap as usize);
    let what = "config.levels × config.features × table rows";
    limits::check_bytes(what, &[c.levels, c.features, min_rows], elem_bytes)?;
    let level = |l: usize| {
        // The product can round a hair past finest; clamp to the stated bounds.
        let n = (base * (growth * l as f64).exp())
            .floor()
            .clamp(1.0, finest.max(1.0));
        let cells = n as u32;
        let side = u64::from(cells) + 1;
        let vertices = (0..d).try_fold(1u64, |acc, _| acc.checked_mul(side));
        let dense = vertices.is_some_and(|v| v <= cap);
        let rows = match vertices {
            Some(v) if dense => v as usize,
            _ => cap as usize,
        };
        (cells, rows, dense)
    };
    let total: usize = (0..c.levels).map(|l| level(l).1).sum();
    limits::check_bytes(what, &[total, c.features], elem_bytes)?;
    limits::check_bytes(
        "config.levels",
        &[c.levels],
        std::mem::size_of::<HashLevel>(),
    )?;
    let mut levels = Vec::with_capacity(c.levels);
    let mut offset = 0usize;
    for l in 0..c.levels {
        let (cells, rows, dense) = level(l);
        levels.push(HashLevel {
            cells,
            offset,
            rows,
            dense,
        });
        offset += rows;
    }
    if offset > u32::MAX as usize {
        return bad(
            "config.levels",
            "tables of fewer than 2³² rows in all",
            format!("{offset} rows over {} levels", c.levels),
        );
    }
    Ok(HashPlan {
        d,
        f: c.features,
        levels,
        lo: c.lo.clone(),
        hi: c.hi.clone(),
        mask: (cap - 1) as u32,
        deterministic: c.deterministic,
    })
}

/// Checks the positions: f32/f64 `[N, D]` with finite coordinates. NaN and ±∞ are both
/// refused (a finite point outside the box is clamped into it; an infinite one used to be
/// clamped too, answering the box's face for a point that is nowhere).
fn check_positions(x: &Tensor, d: usize) -> Result<usize> {
    check_float(x, "x")?;
    let n = check_shape(x, "x", &[Dim::Any("N"), Dim::Is(d)])?[0];
    if n > 0 {
        check_finite(x, "x")?;
    }
    Ok(n)
}

impl HashGrid {
    /// The configuration.
    #[must_use]
    pub(crate) fn config(&self) -> &HashGridConfig {
        &self.config
    }

    /// The table `[Σ_l T_l, F]` (a `Var` of the `VarBuilder`'s map when built from one).
    #[cfg(test)]
    fn table(&self) -> &Tensor {
        &self.table
    }

    /// Each level's cells per axis, rows and whether it is dense (`false`: hashed).
    #[cfg(test)]
    fn levels(&self) -> Vec<(u32, usize, bool)> {
        self.plan
            .levels
            .iter()
            .map(|l| (l.cells, l.rows, l.dense))
            .collect()
    }

    fn fused(&self, x: &Tensor) -> bool {
        !self.config.force_reference
            && crate::kernels::fused_for(x)
            && crate::kernels::fused_on(self.table.device())
            && x.dtype() == self.table.dtype()
    }

    /// The encoding by candle ops (any device): `x: [N, D]` → `[N, L·F]`, differentiable
    /// w.r.t. `x` and the table. The cells and table rows are computed on the host from
    /// `x` (they are piecewise constant: no gradient flows through them), the weights and
    /// the gathers on `x`'s device.
    fn forward_reference(&self, x: &Tensor) -> Result<Tensor> {
        let n = self.check(x)?;
        let p = &self.plan;
        let (d, f, corners) = (p.d, p.f, 1usize << p.d);
        let (host, t) = self.unit_tensor(x)?;
        let mut outs = Vec::with_capacity(p.levels.len());
        for level in &p.levels {
            let (rows, origin, _) = self.level_data(&host, level);
            let origin = Tensor::from_vec(origin, (n, d), x.device())?.to_dtype(x.dtype())?;
            let w = ((&t * f64::from(level.cells))? - origin)?; // [N, D]
            let one_minus = w.affine(-1.0, 1.0)?;
            let mut weights = Vec::with_capacity(corners);
            for cc in 0..corners {
                let mut prod = Tensor::ones((n, 1), x.dtype(), x.device())?;
                for k in 0..d {
                    let col = if (cc >> k) & 1 == 1 { &w } else { &one_minus };
                    prod = (prod * col.narrow(1, k, 1)?)?;
                }
                weights.push(prod);
            }
            let weights = Tensor::cat(&weights, 1)?; // [N, 2ᴰ]
            let idx = Tensor::from_vec(rows, n * corners, x.device())?;
            let feats = self.table.index_select(&idx, 0)?.reshape((n, corners, f))?;
            outs.push(feats.broadcast_mul(&weights.unsqueeze(2)?)?.sum(1)?);
        }
        Ok(Tensor::cat(&outs, 1)?)
    }

    /// `x` on the host (f64) and the normalised coordinates `t: [N, D]` on `x`'s device:
    /// `(x − lo)/(hi − lo)` where it lies in `[0, 1]` (differentiable there, including on
    /// the box's faces), the clamped constant outside (no gradient).
    fn unit_tensor(&self, x: &Tensor) -> Result<(Vec<f64>, Tensor)> {
        let p = &self.plan;
        let d = p.d;
        let host: Vec<f64> = x.to_dtype(DType::F64)?.flatten_all()?.to_vec1()?;
        let dev = x.device();
        let n = host.len() / d;
        let (mut clamped, mut inside) = (
            Vec::with_capacity(host.len()),
            Vec::with_capacity(host.len()),
        );
        let (mut t, mut dt) = ([0.0; 4], [0.0; 4]);
        for row in host.chunks(d) {
            p.unit(row, &mut t, &mut dt);
            clamped.extend_from_slice(&t[..d]);
            inside.extend(dt[..d].iter().map(|&r| u8::from(r != 0.0)));
        }
        let lo = Tensor::new(p.lo.as_slice(), dev)?.to_dtype(x.dtype())?;
        let ext: Vec<f64> = (0..d).map(|k| p.hi[k] - p.lo[k]).collect();
        let ext = Tensor::new(ext.as_slice(), dev)?.to_dtype(x.dtype())?;
        let scaled = x.broadcast_sub(&lo)?.broadcast_div(&ext)?;
        let clamped = Tensor::from_vec(clamped, (n, d), dev)?.to_dtype(x.dtype())?;
        let inside = Tensor::from_vec(inside, (n, d), dev)?;
        Ok((host, inside.where_cond(&scaled, &clamped)?))
    }

    /// One level's table rows `[N·2ᴰ]`, cell origins `[N·D]` and rates `N_l · dt/dx`
    /// `[N·D]` (zero outside the box), from the host positions.
    fn level_data(&self, host: &[f64], level: &HashLevel) -> (Vec<u32>, Vec<f64>, Vec<f64>) {
        let p = &self.plan;
        let (d, corners) = (p.d, 1usize << p.d);
        let n = host.len() / d;
        let nl = f64::from(level.cells);
        let mut rows = Vec::with_capacity(n * corners);
        let mut origin = Vec::with_capacity(n * d);
        let mut rate = Vec::with_capacity(n * d);
        let mut c = HashCorners::new();
        let (mut t, mut dt) = ([0.0; 4], [0.0; 4]);
        for row in host.chunks(d) {
            p.unit(row, &mut t, &mut dt);
            p.corners(level, &t, &dt, false, &mut c);
            // Tables hold fewer than 2³² rows (checked when the grid is built).
            rows.extend(c.rows[..corners].iter().map(|&r| r as u32));
            for k in 0..d {
                origin.push((t[k] * nl).floor().min(nl - 1.0));
                rate.push(nl * dt[k]);
            }
        }
        (rows, origin, rate)
    }

    fn check(&self, x: &Tensor) -> Result<usize> {
        let n = check_positions(x, self.plan.d)?;
        if x.dtype() != self.table.dtype() || !x.device().same_device(self.table.device()) {
            return Err(Error::invalid(
                "x",
                format!("the table's dtype {:?} and device", self.table.dtype()),
                format!("{:?} on {:?}", x.dtype(), x.device().location()),
            ));
        }
        Ok(n)
    }
}

impl Encoding for HashGrid {
    fn in_dim(&self) -> usize {
        self.plan.d
    }

    fn out_dim(&self) -> usize {
        self.plan.width()
    }

    /// `x: [N, D]` → `[N, L·F]`: the fused op on the CPU and (feature `cuda`) on CUDA
    /// (f32/f64), the reference path of candle ops elsewhere or with
    /// [`HashGridConfig::force_reference`]. Differentiable
    /// w.r.t. the table and `x` (to second order on the reference path only).
    ///
    /// # Errors
    /// `x` not f32/f64 `[N, D]`, NaN or ±∞ in `x` (refused, not clamped), a dtype or device other than the table's.
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if !self.fused(x) {
            return self.forward_reference(x);
        }
        self.check(x)?;
        Ok(x.contiguous()?
            .apply_op2(&self.table.contiguous()?, FusedHashGrid(self.plan.clone()))?)
    }

    /// Values and tangents `J·dx` through the reference path (candle ops), so that both
    /// stay differentiable w.r.t. the table and `x`: the tangent of `w` is
    /// `N_l / (hi − lo) · dx` inside the box and 0 outside.
    fn forward_jvp(&self, x: &Tensor, dx: &Tensor) -> Result<(Tensor, Tensor)> {
        let n = self.check(x)?;
        let d = self.plan.d;
        check_tangents(x, dx, n, d)?;
        // J·dx = Σ_d ∂y/∂x_d · dx_d: [N, K, D] × [N, D, E].
        let y = self.forward_reference(x)?;
        let jac = self.jacobian_reference(x)?;
        Ok((y, dx.contiguous()?.matmul(&jac)?))
    }
}

impl HashGrid {
    /// `∂γ/∂x: [N, D, L·F]` by candle ops: per level, `∂w_c/∂x_d` (the weights' analytic
    /// derivatives, zero outside the box) times the gathered features. Differentiable
    /// w.r.t. the table (the derivative of the weights w.r.t. `x` is piecewise constant
    /// or linear in `x` and carries its own graph).
    fn jacobian_reference(&self, x: &Tensor) -> Result<Tensor> {
        let n = self.check(x)?;
        let p = &self.plan;
        let (d, f, corners) = (p.d, p.f, 1usize << p.d);
        let (host, t) = self.unit_tensor(x)?;
        let dev = x.device();
        let mut per_level = Vec::with_capacity(p.levels.len());
        for level in &p.levels {
            let (rows, origin, rate) = self.level_data(&host, level);
            let origin = Tensor::from_vec(origin, (n, d), dev)?.to_dtype(x.dtype())?;
            let rate = Tensor::from_vec(rate, (n, d), dev)?.to_dtype(x.dtype())?;
            let w = ((&t * f64::from(level.cells))? - origin)?;
            let one_minus = w.affine(-1.0, 1.0)?;
            // dweights[c][j] = rate_j · (±1) · Π_{k≠j} (w_k or 1 − w_k): [N, 2ᴰ, D].
            let mut cols = Vec::with_capacity(corners);
            for cc in 0..corners {
                let mut per_axis = Vec::with_capacity(d);
                for j in 0..d {
                    let sign = if (cc >> j) & 1 == 1 { 1.0 } else { -1.0 };
                    let mut prod = rate.narrow(1, j, 1)?.affine(sign, 0.0)?;
                    for k in (0..d).filter(|&k| k != j) {
                        let col = if (cc >> k) & 1 == 1 { &w } else { &one_minus };
                        prod = (prod * col.narrow(1, k, 1)?)?;
                    }
                    per_axis.push(prod);
                }
                cols.push(Tensor::cat(&per_axis, 1)?.unsqueeze(1)?); // [N, 1, D]
            }
            let dweights = Tensor::cat(&cols, 1)?; // [N, 2ᴰ, D]
            let idx = Tensor::from_vec(rows, n * corners, dev)?;
            let feats = self.table.index_select(&idx, 0)?.reshape((n, corners, f))?;
            // [N, D, 2ᴰ] × [N, 2ᴰ, F] → [N, D, F]
            per_level.push(dweights.transpose(1, 2)?.contiguous()?.matmul(&feats)?);
        }
        Ok(Tensor::cat(&per_level, 2)?)
    }
}

#[cfg(test)]
mod tests {
    use super::{hash_grid, HashGridConfig};
    use crate::encoding::Encoding;
    use candle_core::{DType, Device};
    use candle_nn::{VarBuilder, VarMap};

    #[test]
    fn levels_are_dense_until_the_table_is_full_then_hashed() {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let g = hash_grid(&HashGridConfig::default(), vb).unwrap();
        let levels = g.levels();
        assert_eq!(levels.len(), 16);
        assert_eq!(levels[0], (16, 17 * 17 * 17, true));
        assert_eq!(levels[15].0, 2048);
        assert!(levels.iter().all(|&(n, rows, dense)| dense
            == ((n as usize + 1).pow(3) <= 1 << 15)
            && rows <= 1 << 15));
        assert!(!levels[15].2);
        assert_eq!(g.out_dim(), 32);
        assert_eq!(
            g.table().dims(),
            &[levels.iter().map(|l| l.1).sum::<usize>(), 2]
        );
    }
}
