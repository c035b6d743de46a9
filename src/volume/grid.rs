//! An occupancy-grid estimator (in the spirit of nerfacc's `OccGridEstimator`): a
//! multi-resolution binary grid over an axis-aligned box, updated from the field every
//! few steps, and a ray marcher that emits samples only in occupied cells.

use super::compositing::{visible_mask, DEFAULT_TERMINATION_EPS};
use super::layout::{host_f64, Intervals, Layout, Packed};
use super::sampling::{stream, DensityFn};
use crate::camera::Rays;
use crate::error::{check_finite, check_float, check_same, check_scalar, Error, Result};
use crate::kernels::X_MAX;
use crate::narrow::from_host;
use crate::rng::SplitMix64;
use candle_core::{DType, Device, Tensor};
use rayon::prelude::*;

/// An [`OccupancyGrid`]'s box, resolution and update rule (see [`OccupancyGrid`]).
#[derive(Clone, Debug, PartialEq)]
pub struct GridConfig {
    /// The level-0 box `[x₀, y₀, z₀, x₁, y₁, z₁]`. Default `[−1, −1, −1, 1, 1, 1]`.
    pub aabb: [f64; 6],
    /// Cells per axis and level. Default 64: nerfacc's 128 is for the GPU; on a CPU an
    /// update of 128³ cells (about a million density evaluations every 16 steps after
    /// warm-up) outweighs the training step, and at the library's defaults 64³ reached
    /// 3.1–6.7 dB more in two minutes on every scene of the tuning set
    /// (docs/benchmarks.md, "Defaults across the scene suite").
    pub resolution: usize,
    /// Number of levels; level `l` covers the box scaled by `2^l` about its centre.
    /// Default 1.
    pub levels: usize,
    /// Opacity above which a cell is occupied (before the mean clamp): a cell is
    /// occupied when `σ·Δ`, its density times its mean edge length `Δ` (the opacity
    /// exponent of a ray crossing it), exceeds this. Default 0.01, nerfacc's `occ_thre`
    /// in nerfacc's units (nerfacc compares it with σ times its march step, which is
    /// usually a few times finer than a cell: this grid keeps somewhat more cells).
    /// In densities, 0.01 is `σ > 0.01/Δ`: 0.32 for 64 cells across a box of side 2.
    pub threshold: f64,
    /// Lower bound of the effective threshold τ. Default 1e-4.
    pub floor: f64,
    /// Decay of the per-cell estimate (`dᵢ ← max(decay·dᵢ, σ·Δ)`). Default 0.8: a cell
    /// that once saw the opacity `D` needs `⌈ln(D/τ)/ln(1/decay)⌉` updates that evaluate
    /// it to empty (11 from D = 10τ), so that a grid updated every 16 steps prunes within
    /// the first few hundred steps (nerfacc's 0.95, for GPU schedules of tens of
    /// thousands of steps, needs 45).
    pub decay: f64,
    /// Updates at steps below this evaluate every cell. Default 128.
    pub warmup_steps: usize,
    /// Points per call of the density function. Default 65 536.
    pub chunk_size: usize,
    /// Seed of the cell jitter and subset draws (mixed with the step). Default 0.
    pub seed: u64,
    /// Conservative occupancy: also mark occupied every cell next to (26-neighbourhood,
    /// same level) a cell whose density is above τ. Default `true`; `false` is nerfacc's
    /// rule. One jittered point per cell and update can miss a thin sliver of density
    /// at a cell's corner, and samples there are then dropped from every render
    /// (measured in tests/volume_grid.rs after 16 warm-up updates: a colour error of
    /// 1.7e-2 without dilation, 0 with it, on a ball that fills 1.4% of the box);
    /// dilation keeps such cells at the cost of a shell of extra cells (about 2× the
    /// samples there). On the scene suite the shell is about a third of the occupied
    /// cells after 1 000 training steps, and without it a scene of limbs one or two
    /// pixels wide lost 3.7 dB (docs/benchmarks.md, "What the plate's occupied cells
    /// are").
    pub dilate: bool,
}

impl Default for GridConfig {
    fn default() -> Self {
        GridConfig {
            aabb: [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0],
            resolution: 64,
            levels: 1,
            threshold: 0.01,
            floor: 1e-4,
            decay: 0.8,
            warmup_steps: 128,
            chunk_size: 65_536,
            seed: 0,
            dilate: true,
        }
    }
}

/// A multi-resolution binary occupancy grid over an axis-aligned box, updated from the
/// field every few steps, and a ray marcher that emits samples only in occupied cells.
///
/// # Grid
/// Level 0 covers the box `aabb = [x₀, y₀, z₀, x₁, y₁, z₁]`; level `l` covers the box
/// with the same centre and `2^l` times the extent, so that unbounded-ish scenes get
/// coarse cells far away. Each level has `resolution³` cells. A point belongs to the
/// finest level whose box contains it; points outside the last level are empty.
///
/// # Update
/// Every cell keeps an opacity estimate `dᵢ` (host f32). An update evaluates the
/// field's density σ at one point per chosen cell, jittered uniformly inside the cell,
/// and sets `dᵢ ← max(decay·dᵢ, σ·Δ)` with `Δ` the cell's mean edge length at its level
/// (nerfacc's decayed maximum of the opacity `σ·Δt`, with the cell for the step). During
/// warm-up every cell is evaluated; after it, per level, a quarter of the cells drawn
/// uniformly and a quarter drawn from the occupied ones. A cell is then occupied iff
/// `dᵢ > τ` with `τ = min(threshold, max(mean(d), floor))`: the mean clamp keeps the
/// densest cells occupied while the field's scale is still small early in training, and
/// the floor lets a field that has become empty everywhere empty the grid (a cell that
/// saw the opacity `D` is empty after at most `⌈ln(D/floor)/ln(1/decay)⌉` updates that
/// evaluate it). With [`GridConfig::dilate`], the occupied set is then grown by one
/// cell in every direction (a conservative grid that does not miss thin slivers of
/// density at cell corners).
///
/// A new grid has every cell occupied, so that nothing is skipped before the first
/// update.
///
/// # Sampling
/// [`OccupancyGrid::sample`] marches each ray with a fixed step `Δt` (or, with a cone
/// angle `c > 0`, `Δt = clamp(c·t, step_size, max_step)`) from
/// `max(near, t_entry)` to `min(far, t_exit)` of the outermost box, and keeps the
/// interval `[t, t + Δt]` iff the cell containing its midpoint is occupied. The kept
/// intervals are exactly the ones the same march would produce without a grid, minus
/// those in empty cells: skipping changes a render only through density the grid has
/// missed. With a fixed step, interval `k` is `[t₀ + k·Δt, min(t₀ + (k+1)·Δt, t₁)]` and
/// runs of steps inside one empty cell are jumped over in O(1) (the jump is verified so
/// that the result is exactly the step-by-step one; see `skip_empty`); cone stepping
/// visits every step. The traversal runs on the host over `to_vec` copies of the rays, in
/// parallel over rays with rayon; the results are placed on the rays' device. Given the
/// field's density, the sampling also drops the samples hidden behind spent
/// transmittance and the empty ones, so that only the samples worth the whole network
/// come out.
#[derive(Clone, Debug)]
pub struct OccupancyGrid {
    density: Vec<f32>,
    occupied: Vec<bool>,
    config: GridConfig,
}

/// How [`OccupancyGrid::sample`] marches (the range `[near, far]` in ray parameter `t`,
/// the step, optional cone stepping and jitter) and which samples a density function
/// lets through (`early_stop_eps`, `alpha_threshold`). The defaults are nerfacc's; set
/// the rest with struct-update syntax:
/// `GridMarchConfig { step_size: 1e-2, ..GridMarchConfig::default() }`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridMarchConfig {
    /// Start of the march, `≥ 0`. Default 0.
    pub near: f64,
    /// End of the march, `> near` (may be `+∞`: the march stops at the grid's box).
    /// Default `+∞`.
    pub far: f64,
    /// Step `Δt > 0`, in units of `t` (world units for unit directions). Default 1e-3.
    pub step_size: f64,
    /// Cone angle `c ≥ 0`: the step is `clamp(c·t, step_size, max_step)`; 0 (the
    /// default) gives a fixed step.
    pub cone_angle: f64,
    /// Largest step under cone stepping (default 1e10).
    pub max_step: f64,
    /// `Some(seed)`: shift each ray's fixed-step lattice by a random fraction of a step
    /// (nerfacc's stratified march, for training), so that over the steps a field sees
    /// every point along a ray rather than the same `t` each time; the first interval is
    /// then the partial one `[t_entry, t_entry + u·Δt]`, `u ∈ (0, 1]` uniform, drawn per
    /// ray from `seed` and the ray index. The intervals still tile `[t_entry, t_exit]`.
    /// The seed should change every training step. `None` (the default): the lattice
    /// starts at `t_entry` (evaluation). Cone stepping ignores it.
    pub jitter: Option<u64>,
    /// With a density function: drop the samples behind which the transmittance
    /// `Tᵢ = exp(−Σ_{j<i} σⱼδⱼ)` has fallen below this, in `[0, 1]` (0 drops none).
    /// Default 1e-4 ([`DEFAULT_TERMINATION_EPS`], nerfacc's `early_stop_eps`).
    pub early_stop_eps: f64,
    /// With a density function: drop the samples whose opacity `αᵢ = 1 − e^{−σᵢδᵢ}` is
    /// below this, in `[0, 1]` (0 drops none). Default 0 (nerfacc's `alpha_thre`).
    pub alpha_threshold: f64,
}

impl Default for GridMarchConfig {
    fn default() -> Self {
        GridMarchConfig {
            near: 0.0,
            far: f64::INFINITY,
            step_size: 1e-3,
            cone_angle: 0.0,
            max_step: 1e10,
            jitter: None,
            early_stop_eps: DEFAULT_TERMINATION_EPS,
            alpha_threshold: 0.0,
        }
    }
}

/// The position `o + m·d`.
fn point(o: &[f64; 3], d: &[f64; 3], m: f64) -> [f64; 3] {
    [o[0] + m * d[0], o[1] + m * d[1], o[2] + m * d[2]]
}

/// A fixed-step march along one ray.
struct FixedMarch {
    o: [f64; 3],
    d: [f64; 3],
    /// Origin of the step lattice, `≤ entry` (below it when jittered).
    t0: f64,
    /// Where the march enters the box (or `near`).
    entry: f64,
    t1: f64,
    h: f64,
    n_steps: usize,
}

impl FixedMarch {
    /// Interval `k`: `[max(t0 + k·h, entry), min(t0 + (k + 1)·h, t1)]`.
    fn interval(&self, k: usize) -> (f64, f64) {
        let t = (self.t0 + k as f64 * self.h).max(self.entry);
        let te = (self.t0 + (k + 1) as f64 * self.h).min(self.t1);
        (t, te)
    }

    /// The position at the midpoint of interval `k`.
    fn midpoint(&self, k: usize) -> (f64, [f64; 3]) {
        let (t, te) = self.interval(k);
        let m = 0.5 * (t + te);
        (m, point(&self.o, &self.d, m))
    }
}

/// One ray's march: its kept intervals and how many it visited, or the ray index when
/// it would take too many steps.
type RayMarch = std::result::Result<(Vec<(f64, f64)>, usize), usize>;

/// Samples emitted by [`OccupancyGrid::sample`]: packed [`Intervals`] (ready for
/// [`crate::volume::composite()`] and [`Intervals::positions`]) and the work they saved.
#[derive(Clone, Debug)]
#[non_exhaustive]
pub struct GridSamples {
    /// `[M]` kept intervals in ray parameter `t`, ray by ray, sorted along each ray, in
    /// the packed [`Layout`] (`Layout::Packed`, with the per-ray offsets).
    pub intervals: Intervals,
    /// How many intervals the march visited in all, kept or not: the number of samples
    /// the same march would have evaluated without the grid.
    pub n_marched: usize,
}

impl OccupancyGrid {
    /// A grid over `config.aabb = [x₀, y₀, z₀, x₁, y₁, z₁]` with `config.levels` levels
    /// of `config.resolution³` cells and the update rule of `config` (the defaults are
    /// nerfacc's), every cell occupied.
    ///
    /// ```
    /// use candle_core::{DType, Device, Tensor};
    /// use neural_fields::camera::Rays;
    /// use neural_fields::volume::{GridConfig, GridMarchConfig, OccupancyGrid};
    ///
    /// let dev = Device::Cpu;
    /// let mut grid = OccupancyGrid::new(GridConfig { resolution: 32, ..GridConfig::default() })?;
    /// // Density: a ball of radius 0.3 (a trained field's density in practice).
    /// let ball = |p: &Tensor| -> neural_fields::Result<Tensor> {
    ///     Ok((p.sqr()?.sum(1)?.lt(0.09)?.to_dtype(DType::F32)? * 50.0)?)
    /// };
    /// grid.update(0, 1, &dev, DType::F32, ball)?;                  // warm-up: every cell
    /// let occupied = grid.occupied().iter().filter(|&&o| o).count();
    /// assert!(occupied < 32 * 32 * 32 / 20);
    /// let rays = Rays::new(
    ///     Tensor::new(&[[0.0f32, 0.0, -2.0], [0.9, 0.9, -2.0]], &dev)?,
    ///     Tensor::new(&[[0.0f32, 0.0, 1.0], [0.0, 0.0, 1.0]], &dev)?,
    /// )?;
    /// let march = GridMarchConfig { far: 4.0, step_size: 0.01, ..GridMarchConfig::default() };
    /// let samples = grid.sample(&rays, &march, None)?;
    /// let m = samples.intervals.starts.dim(0)?;                   // packed: [M]
    /// assert!(m > 0 && m < samples.n_marched);                      // empty space skipped
    /// assert_eq!(samples.intervals.positions(&rays)?.dims(), &[m, 3]);
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// Naming `config.aabb` when it is not finite with `x₀ < x₁`, `y₀ < y₁`, `z₀ < z₁`;
    /// `config.resolution` or `config.levels` when 0, when the grid would exceed 2³¹
    /// cells, or when its 5 bytes a cell (`levels · resolution³ · 5`) pass the allocation
    /// limit of 2³³ bytes (8 GiB; resolution 1200 at one level is refused), checked before
    /// anything is allocated; `config` when `threshold` or `floor` is not finite and ≥ 0, `decay` is not in
    /// `[0, 1]`, or `chunk_size` is 0.
    pub fn new(config: GridConfig) -> Result<Self> {
        let (aabb, resolution, levels) = (config.aabb, config.resolution, config.levels);
        let ok = aabb.iter().all(|x| x.is_finite()) && (0..3).all(|a| aabb[a] < aabb[a + 3]);
        if !ok {
            return Err(Error::invalid(
                "config.aabb",
                "finite [x0, y0, z0, x1, y1, z1] with min < max on each axis",
                format!("{aabb:?}"),
            ));
        }
        if resolution == 0 {
            return Err(Error::invalid("config.resolution", "at least 1", "0"));
        }
        if levels == 0 || levels > 16 {
            return Err(Error::invalid(
                "config.levels",
                "1 to 16 levels",
                format!("{levels}"),
            ));
        }
        let cells = resolution
            .checked_pow(3)
            .and_then(|c| c.checked_mul(levels))
            .filter(|&c| c <= 1 << 31)
            .ok_or_else(|| {
                Error::invalid(
                    "config.resolution",
                    "at most 2^31 cells in all",
                    format!("{levels} levels of {resolution}^3"),
                )
            })?;
        // A density (f32) and an occupancy flag per cell.
        crate::limits::check_bytes("config.resolution", &[cells], 5)?;
        let bad = |x: f64| !(x.is_finite() && x >= 0.0);
        if bad(config.threshold)
            || bad(config.floor)
            || !(0.0..=1.0).contains(&config.decay)
            || config.chunk_size == 0
        {
            return Err(Error::invalid(
                "config",
                "threshold, floor ≥ 0 and finite, decay in [0, 1], chunk_size ≥ 1",
                format!("{config:?}"),
            ));
        }
        Ok(OccupancyGrid {
            density: vec![0.0; cells],
            occupied: vec![true; cells],
            config,
        })
    }

    /// Per-cell occupancy, `levels · resolution³` values; cell `(l, i, j, k)` (x, y, z
    /// indices) is at `((l·res + i)·res + j)·res + k`. The occupied fraction is
    /// `occupied().iter().filter(|&&o| o).count() as f64 / occupied().len() as f64`.
    #[must_use]
    pub fn occupied(&self) -> &[bool] {
        &self.occupied
    }

    fn centre_half(&self) -> ([f64; 3], [f64; 3]) {
        let a = &self.config.aabb;
        (
            [
                0.5 * (a[0] + a[3]),
                0.5 * (a[1] + a[4]),
                0.5 * (a[2] + a[5]),
            ],
            [
                0.5 * (a[3] - a[0]),
                0.5 * (a[4] - a[1]),
                0.5 * (a[5] - a[2]),
            ],
        )
    }

    /// Cell index → (level, `[i, j, k]`) (x, y, z indices within the level), in 32-bit
    /// arithmetic (the grid holds at most 2³¹ cells; 64-bit division is slower).
    fn decode(&self, cell: usize) -> (usize, [usize; 3]) {
        let res = self.config.resolution as u32;
        let cell = cell as u32;
        let per_level = res * res * res;
        let (level, rest) = (cell / per_level, cell % per_level);
        let (i, jk) = (rest / (res * res), rest % (res * res));
        (
            level as usize,
            [i as usize, (jk / res) as usize, (jk % res) as usize],
        )
    }

    /// The cell containing `p`, or `None` outside the last level.
    fn cell_of(&self, p: [f64; 3]) -> Option<usize> {
        let (c, h) = self.centre_half();
        let q = (0..3)
            .map(|a| (p[a] - c[a]).abs() / h[a])
            .fold(0.0f64, f64::max);
        if !q.is_finite() {
            return None;
        }
        let mut level = 0usize;
        let mut scale = 1.0f64;
        while q > scale {
            level += 1;
            scale *= 2.0;
            if level >= self.config.levels {
                return None;
            }
        }
        let res = self.config.resolution;
        let mut idx = level;
        for a in 0..3 {
            let lo = c[a] - h[a] * scale;
            let cell = 2.0 * h[a] * scale / res as f64;
            let i = ((p[a] - lo) / cell).floor();
            let i = if i < 0.0 {
                0
            } else {
                (i as usize).min(res - 1)
            };
            idx = idx * res + i;
        }
        Some(idx)
    }

    /// Box dilation by one cell within each level, as three separable passes (x, y, z).
    /// The cells are visited in index order with their coordinates counted alongside
    /// (no division per cell).
    fn dilate(&mut self) {
        let res = self.config.resolution;
        let strides = [res * res, res, 1];
        for (axis, stride) in strides.into_iter().enumerate() {
            let src = self.occupied.clone();
            let mut ijk = [0usize; 3];
            for (i, o) in self.occupied.iter_mut().enumerate() {
                let coord = ijk[axis];
                if !*o {
                    let lower = coord > 0 && src[i - stride];
                    let upper = coord + 1 < res && src[i + stride];
                    *o = lower || upper;
                }
                // The next cell's (i, j, k) within its level: k fastest.
                ijk[2] += 1;
                if ijk[2] == res {
                    ijk[2] = 0;
                    ijk[1] += 1;
                    if ijk[1] == res {
                        ijk[1] = 0;
                        ijk[0] += 1;
                        if ijk[0] == res {
                            ijk[0] = 0;
                        }
                    }
                }
            }
        }
    }

    /// The next step to visit after step `k` of `march`, whose midpoint lies in the
    /// empty cell `cell`: the first step whose midpoint may lie outside that cell.
    ///
    /// The jump target `j` is estimated from where the ray leaves the cell (or enters
    /// the next finer level's box, slightly enlarged), with one step of margin, and then
    /// verified: the midpoint of step `j − 1` must map to `cell` too. Midpoint
    /// coordinates are monotone in the step index, even in floating point (every
    /// operation producing them is monotone), so each axis index of the steps between
    /// lies between those of steps `k` and `j − 1`, i.e. equals the cell's; and as each
    /// `|p_a − c_a|` is quasi-convex along the ray, their level cannot be coarser, nor
    /// (by the enlarged finer box) finer. Hence every skipped step has its midpoint in
    /// `cell`: jumping gives exactly the intervals of the step-by-step march.
    fn skip_empty(&self, cell: usize, k: usize, march: &FixedMarch) -> usize {
        let res = self.config.resolution;
        let (level, ijk) = self.decode(cell);
        let scale = (1u64 << level) as f64;
        let (c, h) = self.centre_half();
        let (m, _) = march.midpoint(k);
        let (o, d) = (&march.o, &march.d);
        let mut t_exit = f64::INFINITY;
        for a in 0..3 {
            if d[a] != 0.0 {
                let lo = c[a] - h[a] * scale;
                let size = 2.0 * h[a] * scale / res as f64;
                let upper = usize::from(d[a] > 0.0);
                let bound = lo + (ijk[a] + upper) as f64 * size;
                t_exit = t_exit.min((bound - o[a]) / d[a]);
            }
        }
        if level >= 1 {
            let inner = 0.5 * scale * (1.0 + 1e-9);
            let (mut t_in, mut t_out) = (f64::NEG_INFINITY, f64::INFINITY);
            for a in 0..3 {
                let (lo, hi) = (c[a] - h[a] * inner, c[a] + h[a] * inner);
                if d[a] == 0.0 {
                    if o[a] < lo || o[a] > hi {
                        t_in = f64::INFINITY;
                        t_out = f64::NEG_INFINITY;
                    }
                } else {
                    let (ta, tb) = ((lo - o[a]) / d[a], (hi - o[a]) / d[a]);
                    t_in = t_in.max(ta.min(tb));
                    t_out = t_out.min(ta.max(tb));
                }
            }
            if t_in <= t_out && t_out >= m {
                if t_in <= m {
                    return k + 1;
                }
                t_exit = t_exit.min(t_in);
            }
        }
        let j = ((t_exit - march.t0) / march.h - 0.5).floor() - 1.0;
        if j.is_nan() || j < (k + 2) as f64 {
            return k + 1;
        }
        let j = if j >= march.n_steps as f64 {
            march.n_steps
        } else {
            j as usize
        };
        if j < k + 2 {
            return k + 1;
        }
        let (_, p_end) = march.midpoint(j - 1);
        if self.cell_of(p_end) == Some(cell) {
            j
        } else {
            k + 1
        }
    }

    /// Whether the point `p` lies in an occupied cell (false outside the last level).
    #[must_use]
    pub fn is_occupied(&self, p: [f64; 3]) -> bool {
        self.cell_of(p).is_some_and(|i| self.occupied[i])
    }

    /// Updates the grid from the field's density, if `step` is a multiple of `every_n`.
    ///
    /// `sigma_fn` maps points `[N, 3]` (dtype `dtype`, on `device`, `N ≤ chunk_size`)
    /// to densities `[N]` or `[N, 1]` (after the density activation, ≥ 0; negative
    /// values count as 0). It is called without a gradient being needed: detach inside
    /// it, or pass a closure over a detached copy of the field. See [`OccupancyGrid`] for
    /// which cells are evaluated and the decayed-maximum rule. Returns whether an update
    /// ran.
    ///
    /// # Errors
    /// Naming `every_n` when 0; `dtype` when not f32 or f64; `sigma_fn` when it returns a
    /// wrong shape or non-finite values; whatever `sigma_fn` returns.
    pub fn update<F>(
        &mut self,
        step: usize,
        every_n: usize,
        device: &Device,
        dtype: DType,
        mut sigma_fn: F,
    ) -> Result<bool>
    where
        F: FnMut(&Tensor) -> Result<Tensor>,
    {
        if every_n == 0 {
            return Err(Error::invalid("every_n", "at least 1", "0"));
        }
        crate::error::check_dtype(dtype)?;
        if !step.is_multiple_of(every_n) {
            return Ok(false);
        }
        let res = self.config.resolution;
        let per_level = res * res * res;
        let mut rng = stream(self.config.seed, step as u64);
        let cells: Vec<usize> = if step < self.config.warmup_steps {
            (0..self.density.len()).collect()
        } else {
            let mut chosen = Vec::with_capacity(self.density.len() / 2);
            let quarter = (per_level / 4).max(1);
            for l in 0..self.config.levels {
                let base = l * per_level;
                for _ in 0..quarter {
                    chosen.push(base + rng.below(per_level as u64) as usize);
                }
                let occ: Vec<usize> = (base..base + per_level)
                    .filter(|&i| self.occupied[i])
                    .collect();
                if !occ.is_empty() {
                    for _ in 0..quarter {
                        chosen.push(occ[rng.below(occ.len() as u64) as usize]);
                    }
                }
            }
            chosen
        };
        let (c, h) = self.centre_half();
        // The mean edge of a level-0 cell: σ·edge is the opacity of one cell's crossing.
        let edge0 = (0..3).map(|a| 2.0 * h[a] / res as f64).sum::<f64>() / 3.0;
        // Each level's lower corner and cell size per axis.
        let corner_size: Vec<[(f64, f64); 3]> = (0..self.config.levels)
            .map(|level| {
                let scale = (1u64 << level) as f64;
                [0, 1, 2].map(|a| (c[a] - h[a] * scale, 2.0 * h[a] * scale / res as f64))
            })
            .collect();
        let mut levels = Vec::new();
        for chunk in cells.chunks(self.config.chunk_size) {
            let mut pts = Vec::with_capacity(chunk.len() * 3);
            levels.clear();
            for &cell in chunk {
                let (level, ijk) = self.decode(cell);
                levels.push(level);
                for (a, &(lo, size)) in corner_size[level].iter().enumerate() {
                    pts.push(lo + (ijk[a] as f64 + rng.uniform()) * size);
                }
            }
            let n = chunk.len();
            let points = from_host(pts, &[n, 3], dtype, device)?;
            let sigma = sigma_fn(&points)?;
            let ok = sigma.dims() == [n] || sigma.dims() == [n, 1];
            if !ok {
                return Err(Error::invalid(
                    "sigma_fn",
                    format!("densities of shape [{n}] or [{n}, 1]"),
                    format!("shape {:?}", sigma.dims()),
                ));
            }
            check_float(&sigma, "sigma_fn")?;
            let s = host_f64(&sigma)?;
            if s.iter().any(|x| !x.is_finite()) {
                return Err(Error::invalid(
                    "sigma_fn",
                    "finite densities",
                    "NaN or infinity",
                ));
            }
            let decay = self.config.decay as f32;
            for ((&cell, &level), &v) in chunk.iter().zip(&levels).zip(&s) {
                let edge = edge0 * (1u64 << level) as f64;
                let v = (v.max(0.0) * edge) as f32;
                let d = &mut self.density[cell];
                *d = (*d * decay).max(v);
            }
        }
        let mean =
            self.density.iter().map(|&d| f64::from(d)).sum::<f64>() / self.density.len() as f64;
        let tau = self.config.threshold.min(mean.max(self.config.floor));
        for (o, &d) in self.occupied.iter_mut().zip(&self.density) {
            *o = f64::from(d) > tau;
        }
        if self.config.dilate {
            self.dilate();
        }
        Ok(true)
    }

    /// Marches rays through the grid and returns the samples worth a full evaluation of
    /// the field: the intervals in occupied cells and, given a density function, of
    /// those only the ones that are visible and not empty (nerfacc's
    /// `OccGridEstimator.sampling`).
    ///
    /// * `rays`: `R` rays, f32 or f64 (directions need not be unit: `t` is the ray
    ///   parameter, and `step_size` is in units of `t`).
    /// * `config`: [`GridMarchConfig`]; the march covers `[max(near, t_entry),
    ///   min(far, t_exit)]` of the outermost level's box with steps
    ///   `Δt = clamp(cone_angle·t, step_size, max_step)` (fixed for `cone_angle = 0`).
    /// * `sigma_fn`: `None` keeps every interval in an occupied cell. `Some(f)`: `f` is
    ///   called once with the positions `[M, 3]` of all of them (the midpoints
    ///   [`Intervals::positions`], the rays' dtype and device) and returns their
    ///   densities σ, `[M]` or `[M, 1]` (negative values count as 0); sample `i` of a ray
    ///   is then kept iff
    ///
    ///   ```text
    ///   Tᵢ = exp(−Σ_{j<i} xⱼ) ≥ early_stop_eps   and   αᵢ = 1 − e^{−xᵢ} ≥ alpha_threshold,
    ///   xᵢ = min(σᵢδᵢ, X_MAX),  δᵢ = (endᵢ − startᵢ)·‖d‖,
    ///   ```
    ///
    ///   the sums running over all of the ray's intervals in occupied cells (a dropped
    ///   empty sample still attenuates what lies behind it). `f` is not called when
    ///   there is no interval, or when both thresholds are 0. Its result is only read
    ///   back to the host: nothing of its graph is kept, so it may as well be detached.
    ///   Dropping the samples behind `T < ε` changes a composite by less than `ε` in
    ///   opacity (see [`DEFAULT_TERMINATION_EPS`]); dropping empty samples changes the
    ///   transmittance of those behind by a factor of at most `1/(1 − alpha_threshold)`
    ///   per dropped sample.
    ///
    /// Returns [`GridSamples`]: packed intervals `[M']` in the rays' dtype and device,
    /// sorted along each ray; without a density function the last interval of a ray
    /// ends at its exit point. Off the CPU (CUDA, where candle cannot hold an empty
    /// result) a batch of rays that keeps no interval holds one zero-length interval
    /// `[0, 0]` on ray 0 instead: its opacity `1 − e^{−σ·0} = 0` gives it weight 0 and no
    /// gradient, so every composite, loss and gradient is that of the empty batch.
    /// Detached: the intervals carry no gradient (get one to
    /// origins and directions through [`Intervals::positions`]); kept intervals are
    /// exactly those of the march without `sigma_fn`, bit for bit.
    ///
    /// ```
    /// use candle_core::{DType, Device, Tensor};
    /// use neural_fields::camera::Rays;
    /// use neural_fields::volume::{GridConfig, GridMarchConfig, OccupancyGrid};
    ///
    /// let dev = Device::Cpu;
    /// let grid = OccupancyGrid::new(GridConfig { resolution: 16, ..GridConfig::default() })?;
    /// let rays = Rays::new(Tensor::new(&[[0.0f32, 0.0, -2.0]], &dev)?, Tensor::new(&[[0.0f32, 0.0, 1.0]], &dev)?)?;
    /// // An opaque wall at z > 0: every sample behind it is hidden.
    /// let mut wall = |p: &Tensor| -> neural_fields::Result<Tensor> {
    ///     Ok((p.narrow(1, 2, 1)?.squeeze(1)?.gt(0.0)?.to_dtype(DType::F32)? * 1e4)?)
    /// };
    /// let config = GridMarchConfig { step_size: 0.1, ..GridMarchConfig::default() };
    /// let all = grid.sample(&rays, &config, None)?;
    /// let visible = grid.sample(&rays, &config, Some(&mut wall))?;
    /// assert_eq!(all.intervals.starts.dim(0)?, 20);          // z from −1 to 1
    /// assert_eq!(visible.intervals.starts.dim(0)?, 11);      // up to the wall's first sample
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// Naming `near`, `far`, `step_size`, `cone_angle`, `max_step`, `early_stop_eps`,
    /// `alpha_threshold` for bad scalars; `step_size` when a single ray would take more
    /// than 2²⁴ steps; `sigma_fn` when it returns another shape or dtype than
    /// `[M]`/`[M, 1]` of the rays', or a NaN or infinite density; whatever `sigma_fn`
    /// returns.
    pub fn sample(
        &self,
        rays: &Rays,
        config: &GridMarchConfig,
        sigma_fn: Option<DensityFn<'_>>,
    ) -> Result<GridSamples> {
        let GridMarchConfig {
            near,
            far,
            step_size,
            cone_angle,
            max_step,
            jitter,
            early_stop_eps,
            alpha_threshold,
        } = *config;
        let r = rays.len();
        let (origins, directions) = (rays.origins(), rays.directions());
        check_scalar(near, "near", false)?;
        if near < 0.0 {
            return Err(Error::invalid("near", "a number ≥ 0", format!("{near}")));
        }
        if far.is_nan() || far <= near {
            return Err(Error::invalid(
                "far",
                "a number > near",
                format!("{far} (near {near})"),
            ));
        }
        check_scalar(step_size, "step_size", true)?;
        check_scalar(cone_angle, "cone_angle", false)?;
        if cone_angle < 0.0 {
            return Err(Error::invalid(
                "cone_angle",
                "a number ≥ 0",
                format!("{cone_angle}"),
            ));
        }
        check_scalar(max_step, "max_step", true)?;
        for (x, name) in [
            (early_stop_eps, "early_stop_eps"),
            (alpha_threshold, "alpha_threshold"),
        ] {
            if !(0.0..=1.0).contains(&x) {
                return Err(Error::invalid(name, "a number in [0, 1]", format!("{x}")));
            }
        }
        // Origins and directions side by side, `[R, 6]`: one read-back from a GPU.
        let od = host_f64(&Tensor::cat(&[origins.detach(), directions.detach()], 1)?)?;
        let (c, h) = self.centre_half();
        let outer = (1u64 << (self.config.levels - 1)) as f64;
        let lo = [
            c[0] - h[0] * outer,
            c[1] - h[1] * outer,
            c[2] - h[2] * outer,
        ];
        let hi = [
            c[0] + h[0] * outer,
            c[1] + h[1] * outer,
            c[2] + h[2] * outer,
        ];
        let max_steps: usize = 1 << 24;
        let per_ray: Vec<RayMarch> = (0..r)
            .into_par_iter()
            .map(|ray| {
                let row = &od[6 * ray..6 * ray + 6];
                let oo = [row[0], row[1], row[2]];
                let dd = [row[3], row[4], row[5]];
                let (mut t0, mut t1) = (near, far);
                for a in 0..3 {
                    if dd[a] == 0.0 {
                        if oo[a] < lo[a] || oo[a] > hi[a] {
                            return Ok((Vec::new(), 0));
                        }
                    } else {
                        let inv = 1.0 / dd[a];
                        let (ta, tb) = ((lo[a] - oo[a]) * inv, (hi[a] - oo[a]) * inv);
                        t0 = t0.max(ta.min(tb));
                        t1 = t1.min(ta.max(tb));
                    }
                }
                let mut kept = Vec::new();
                if cone_angle > 0.0 {
                    let mut marched = 0usize;
                    let mut t = t0;
                    while t < t1 {
                        if marched >= max_steps {
                            return Err(ray);
                        }
                        let dt = (cone_angle * t).clamp(step_size, max_step.max(step_size));
                        let te = (t + dt).min(t1);
                        let m = 0.5 * (t + te);
                        marched += 1;
                        if self.is_occupied(point(&oo, &dd, m)) {
                            kept.push((t, te));
                        }
                        t = te;
                    }
                    return Ok((kept, marched));
                }
                // Fixed step: interval k is [max(t0 + k·h, entry), min(t0 + (k + 1)·h,
                // t1)] for k < n_steps, and runs of empty cells are jumped over.
                if t0.is_nan() || t1.is_nan() || t0 >= t1 {
                    return Ok((kept, 0));
                }
                let h = step_size;
                let entry = t0;
                if let Some(seed) = jitter {
                    // The lattice starts v·h before the entry, v ~ U[0, 1): the first
                    // interval is [entry, entry + (1 − v)·h], unless that rounds to empty.
                    let mut rng =
                        SplitMix64::new(seed ^ (ray as u64).wrapping_mul(0xD1B5_4A32_D192_ED03));
                    let shifted = entry - rng.uniform() * h;
                    if shifted + h > entry {
                        t0 = shifted;
                    }
                }
                let approx = ((t1 - t0) / h).ceil();
                if approx.is_nan() || approx > max_steps as f64 {
                    return Err(ray);
                }
                let mut n_steps = approx as usize;
                while n_steps > 0 && t0 + (n_steps - 1) as f64 * h >= t1 {
                    n_steps -= 1;
                }
                while t0 + n_steps as f64 * h < t1 {
                    n_steps += 1;
                }
                let march = FixedMarch {
                    o: oo,
                    d: dd,
                    t0,
                    entry,
                    t1,
                    h,
                    n_steps,
                };
                let mut k = 0usize;
                while k < n_steps {
                    let (t, te) = march.interval(k);
                    let p = point(&oo, &dd, 0.5 * (t + te));
                    match self.cell_of(p) {
                        Some(c) if self.occupied[c] => {
                            kept.push((t, te));
                            k += 1;
                        }
                        Some(c) => k = self.skip_empty(c, k, &march),
                        None => k += 1,
                    }
                }
                let marched = n_steps;
                Ok((kept, marched))
            })
            .collect();
        let mut counts = Vec::with_capacity(r);
        let mut starts = Vec::new();
        let mut ends = Vec::new();
        let mut n_marched = 0usize;
        for res in per_ray {
            let (kept, marched) = res.map_err(|ray| {
                Error::invalid(
                    "step_size",
                    "at most 2^24 steps per ray",
                    format!("step {step_size} too small for ray {ray}"),
                )
            })?;
            counts.push(kept.len());
            n_marched += marched;
            for (a, b) in kept {
                starts.push(a);
                ends.push(b);
            }
        }
        let (dtype, device) = (origins.dtype(), origins.device());
        null_interval_if_empty(&mut starts, &mut ends, &mut counts, device);
        let m = starts.len();
        let marched = Intervals {
            starts: from_host(starts.clone(), &[m], dtype, device)?,
            ends: from_host(ends.clone(), &[m], dtype, device)?,
            layout: Layout::Packed(Packed::from_counts(&counts, device)?),
        };
        let Some(sigma_fn) = sigma_fn else {
            return Ok(GridSamples {
                intervals: marched,
                n_marched,
            });
        };
        if m == 0 || (early_stop_eps == 0.0 && alpha_threshold == 0.0) {
            return Ok(GridSamples {
                intervals: marched,
                n_marched,
            });
        }
        let keep = worth_evaluating(&marched, rays, sigma_fn, early_stop_eps, alpha_threshold)?;
        let mut kept_counts = vec![0usize; r];
        let (mut kept_starts, mut kept_ends) = (Vec::new(), Vec::new());
        let mut i = 0;
        for (ray, &count) in counts.iter().enumerate() {
            for _ in 0..count {
                if keep[i] {
                    kept_counts[ray] += 1;
                    kept_starts.push(starts[i]);
                    kept_ends.push(ends[i]);
                }
                i += 1;
            }
        }
        null_interval_if_empty(&mut kept_starts, &mut kept_ends, &mut kept_counts, device);
        let k = kept_starts.len();
        Ok(GridSamples {
            intervals: Intervals {
                starts: from_host(kept_starts, &[k], dtype, device)?,
                ends: from_host(kept_ends, &[k], dtype, device)?,
                layout: Layout::Packed(Packed::from_counts(&kept_counts, device)?),
            },
            n_marched,
        })
    }
}

/// Off the CPU, gives a batch of rays with no interval one zero-length interval `[0, 0]`
/// on ray 0 (weight 0; see [`OccupancyGrid::sample`]): candle allocates an empty
/// tensor's results with zero bytes, which CUDA refuses.
fn null_interval_if_empty(
    starts: &mut Vec<f64>,
    ends: &mut Vec<f64>,
    counts: &mut [usize],
    device: &Device,
) {
    if starts.is_empty() && !device.is_cpu() {
        if let Some(first) = counts.first_mut() {
            *first = 1;
            starts.push(0.0);
            ends.push(0.0);
        }
    }
}

/// Which of the packed `intervals` along `rays` are visible and not empty under the
/// densities `sigma_fn` gives at their positions (see [`OccupancyGrid::sample`]).
fn worth_evaluating(
    intervals: &Intervals,
    rays: &Rays,
    sigma_fn: DensityFn<'_>,
    early_stop_eps: f64,
    alpha_threshold: f64,
) -> Result<Vec<bool>> {
    let Layout::Packed(packed) = &intervals.layout else {
        return Err(Error::invalid(
            "intervals",
            "the march's packed intervals",
            "batched intervals",
        ));
    };
    let m = packed.ray_indices.dim(0)?;
    let sigma = sigma_fn(&intervals.positions(rays)?)?;
    if sigma.dims() != [m] && sigma.dims() != [m, 1] {
        return Err(Error::invalid(
            "sigma_fn",
            format!("densities of shape [{m}] or [{m}, 1]"),
            format!("shape {:?}", sigma.dims()),
        ));
    }
    check_same(&sigma, "sigma_fn", &intervals.starts, "rays")?;
    let sigma = sigma.detach().flatten_all()?;
    check_finite(&sigma, "sigma_fn")?;
    let sigma = sigma.relu()?;
    let mut keep = vec![true; m];
    if early_stop_eps > 0.0 {
        let visible = visible_mask(&sigma, intervals, Some(rays), early_stop_eps)?;
        for (k, v) in keep.iter_mut().zip(visible.to_vec1::<u8>()?) {
            *k = v != 0;
        }
    }
    if alpha_threshold > 0.0 {
        // x = min(σδ, X_MAX) in the rays' dtype, as compositing forms it; α = −expm1(−x).
        let x = (sigma * intervals.deltas(Some(rays))?)?.minimum(X_MAX)?;
        for (k, x) in keep.iter_mut().zip(host_f64(&x)?) {
            *k &= -(-x).exp_m1() >= alpha_threshold;
        }
    }
    Ok(keep)
}
