//! Detached root finding along rays: evenly spaced samples + secant refinement
//! ([`march`]) and IDR-style sphere tracing for SDFs
//! ([`sphere_trace`]).

use crate::camera::{Intersection, Rays};
use crate::error::{check_finite, check_float, check_same, check_shape};
use crate::error::{Dim, Error, Result};
use crate::field::{ImplicitSurface, Inside};
use candle_core::{DType, Device, Tensor};

/// What the march found on one ray.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RayStatus {
    /// A crossing from outside to inside was found and refined; the depth is the surface.
    Hit,
    /// No crossing in `[near, far]` (or the ray missed the bounding volume); depth = `far`
    /// (0 for rays masked out by an [`Intersection`]).
    Miss,
    /// The first sample is already inside (`s(near) > 0`); depth = `near`, no surface.
    StartsInside,
    /// A crossing was found, but the ray meets the surface at a grazing angle:
    /// `|∇f·w| / (‖∇f‖‖w‖)` below the configured threshold (or `∇f = 0`) at the last
    /// refinement point. The depth is the refined crossing; its implicit gradient is
    /// guarded (bounded) by [`crate::dvr::implicit_surface`].
    Grazing,
    /// A crossing was found but the refinement did not reach the tolerance: the last
    /// secant step (or, with no secant steps, the bracket) is longer than
    /// `tolerance·(far − near)`. The depth is the best estimate.
    NotConverged,
}

impl RayStatus {
    /// Whether the ray has a surface point (`Hit`, `Grazing` or `NotConverged`).
    #[must_use]
    pub fn has_surface(self) -> bool {
        matches!(
            self,
            RayStatus::Hit | RayStatus::Grazing | RayStatus::NotConverged
        )
    }
}

/// How a bracket `[t_lo, t_hi]` with `s_lo ≤ 0 < s_hi` is refined.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SecantRule {
    /// Plain regula falsi (DVR's secant): replace the end with the sign of the new value.
    RegulaFalsi,
    /// Illinois variant: as regula falsi, and halve the stored value of an end that is
    /// kept twice in a row. Superlinear (order ≈ 1.44 per evaluation).
    Illinois,
}

/// Configuration of [`march`].
#[derive(Clone, Debug)]
pub struct MarchConfig {
    /// Number `n ≥ 2` of evenly spaced samples per ray, both ends included.
    pub steps: usize,
    /// Number `k` of secant refinement steps (each one field evaluation per bracketed ray).
    pub secant_steps: usize,
    /// Largest number of points passed to the field in one call (≥ 1): bounds memory.
    pub chunk_points: usize,
    /// `Some(c)`: classify a hit as [`RayStatus::Grazing`] when
    /// `|∇f·w|/(‖∇f‖‖w‖) < c` at the last secant point (that evaluation then uses
    /// `value_and_grad`, so the count of evaluations is unchanged; needs `k ≥ 1`).
    pub grazing_threshold: Option<f64>,
    /// Relative tolerance: a hit is [`RayStatus::NotConverged`] if its last secant step
    /// (or its bracket, with `k = 0`) exceeds `tolerance·(far − near)`.
    pub tolerance: f64,
    /// The secant rule.
    pub rule: SecantRule,
}

impl Default for MarchConfig {
    /// 128 steps, 8 secant steps (DVR's training values), chunks of 65 536 points,
    /// grazing below cos = 1e-3, tolerance 1e-4, Illinois rule.
    fn default() -> Self {
        Self {
            steps: 128,
            secant_steps: 8,
            chunk_points: 65_536,
            grazing_threshold: Some(1e-3),
            tolerance: 1e-4,
            rule: SecantRule::Illinois,
        }
    }
}

impl MarchConfig {
    fn check(&self) -> Result<()> {
        if self.steps < 2 {
            return Err(Error::invalid(
                "config.steps",
                "at least 2",
                format!("{}", self.steps),
            ));
        }
        if self.chunk_points == 0 {
            return Err(Error::invalid("config.chunk_points", "at least 1", "0"));
        }
        // One ray's samples (a point and its ray, 32 bytes each) are held together.
        crate::limits::check_bytes("config.steps", &[self.steps], 32)?;
        if let Some(c) = self.grazing_threshold {
            if !(c.is_finite() && c >= 0.0) {
                return Err(Error::invalid(
                    "config.grazing_threshold",
                    "a finite number ≥ 0",
                    format!("{c}"),
                ));
            }
        }
        if !(self.tolerance.is_finite() && self.tolerance >= 0.0) {
            return Err(Error::invalid(
                "config.tolerance",
                "a finite number ≥ 0",
                format!("{}", self.tolerance),
            ));
        }
        Ok(())
    }
}

/// A coarse-to-fine schedule of march steps over training iterations (DVR starts with few
/// samples and doubles them as the surface sharpens).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StepSchedule {
    milestones: Vec<(usize, usize)>,
}

impl Default for StepSchedule {
    /// DVR's schedule: 16 → 32 → 64 → 128 steps, doubling at iterations 50 000, 100 000
    /// and 200 000.
    fn default() -> Self {
        Self {
            milestones: vec![(0, 16), (50_000, 32), (100_000, 64), (200_000, 128)],
        }
    }
}

impl StepSchedule {
    /// A schedule from `(first_iteration, steps)` pairs: from `first_iteration` on, use
    /// `steps`. The first pair must start at iteration 0.
    ///
    /// # Errors
    /// `milestones` empty, not starting at 0, not strictly increasing in iteration, or
    /// with a step count below 2.
    pub fn new(milestones: Vec<(usize, usize)>) -> Result<Self> {
        match milestones.first() {
            Some((0, _)) => {}
            _ => {
                return Err(Error::invalid(
                    "milestones",
                    "a non-empty list starting at iteration 0",
                    format!("{milestones:?}"),
                ))
            }
        }
        let increasing = milestones.windows(2).all(|p| p[0].0 < p[1].0);
        if !increasing || milestones.iter().any(|m| m.1 < 2) {
            return Err(Error::invalid(
                "milestones",
                "strictly increasing iterations and steps ≥ 2",
                format!("{milestones:?}"),
            ));
        }
        Ok(Self { milestones })
    }

    /// The number of steps at training `iteration`.
    fn steps_at(&self, iteration: usize) -> usize {
        self.milestones
            .iter()
            .rev()
            .find(|m| m.0 <= iteration)
            .map_or(2, |m| m.1)
    }

    /// A [`MarchConfig`] for `iteration`: `base` with `steps` from the schedule.
    #[must_use]
    pub fn config_at(&self, iteration: usize, base: &MarchConfig) -> MarchConfig {
        MarchConfig {
            steps: self.steps_at(iteration),
            ..base.clone()
        }
    }
}

/// The detached result of a march over `R` rays.
#[derive(Clone, Debug)]
pub struct Hits {
    /// Depth (ray parameter) `t`, `[R]`, detached, dtype and device of the rays. The
    /// surface for rays with a surface; `far` for misses (0 if masked out by the
    /// bounds); `near` for rays starting inside.
    pub depth: Tensor,
    /// `o + t·w`, `[R, 3]`, detached.
    pub points: Tensor,
    /// Per-ray status (`R` entries: `hits.status.len()` is the ray count, and
    /// `hits.status.iter().filter(|&&s| s == RayStatus::Hit).count()` counts the hits).
    pub status: Vec<RayStatus>,
    /// `[R]` u8: 1 where the ray has a surface point ([`RayStatus::has_surface`]).
    pub mask: Tensor,
    /// Total number of points at which the field was evaluated.
    pub evaluations: usize,
}

impl Hits {
    /// Indices of the rays with a surface point, ascending.
    #[must_use]
    pub(crate) fn surface_indices(&self) -> Vec<u32> {
        self.status
            .iter()
            .enumerate()
            .filter(|(_, s)| s.has_surface())
            .map(|(i, _)| i as u32) // invariant: ray counts fit in u32 (candle indices)
            .collect()
    }
}

/// The secant point of a bracket, with a bisection fallback.
///
/// Returns `(t, bisected)`: `t = t_lo − s_lo·(t_hi − t_lo)/(s_hi − s_lo)` if the
/// denominator is finite and > 0 and `t ∈ [t_lo, t_hi]`; otherwise the midpoint
/// `t_lo + (t_hi − t_lo)/2` and `bisected = true`. Never NaN for finite `t_lo ≤ t_hi`.
#[must_use]
pub(crate) fn secant_point(t_lo: f64, s_lo: f64, t_hi: f64, s_hi: f64) -> (f64, bool) {
    let width = t_hi - t_lo;
    let denom = s_hi - s_lo;
    if denom.is_finite() && denom > 0.0 {
        let t = t_lo - s_lo * (width / denom);
        if t.is_finite() && t >= t_lo && t <= t_hi {
            return (t, false);
        }
    }
    (t_lo + 0.5 * width, true)
}

/// Rays on the host in f64.
pub(crate) struct HostRays {
    pub(crate) o: Vec<[f64; 3]>,
    pub(crate) w: Vec<[f64; 3]>,
    pub(crate) near: Vec<f64>,
    pub(crate) far: Vec<f64>,
    pub(crate) active: Vec<bool>,
    pub(crate) dtype: DType,
    pub(crate) device: Device,
}

fn rows3(t: &Tensor) -> Result<Vec<[f64; 3]>> {
    Ok(t.detach()
        .to_dtype(DType::F64)?
        .to_vec2::<f64>()?
        .into_iter()
        .map(|r| [r[0], r[1], r[2]])
        .collect())
}

fn vec1(t: &Tensor) -> Result<Vec<f64>> {
    Ok(t.detach().to_dtype(DType::F64)?.to_vec1::<f64>()?)
}

/// Reads validated rays to the host (every ray active on `[0, 1]` until bounds are set).
pub(crate) fn read_rays(rays: &Rays) -> Result<HostRays> {
    let r = rays.len();
    Ok(HostRays {
        o: rows3(rays.origins())?,
        w: rows3(rays.directions())?,
        near: vec![0.0; r],
        far: vec![1.0; r],
        active: vec![true; r],
        dtype: rays.origins().dtype(),
        device: rays.origins().device().clone(),
    })
}

fn read_bound(t: &Tensor, arg: &'static str, like: &Tensor, r: usize) -> Result<Vec<f64>> {
    check_float(t, arg)?;
    check_shape(t, arg, &[Dim::Is(r)])?;
    check_same(t, arg, like, "origins")?;
    check_finite(t, arg)?;
    vec1(t)
}

/// Reads the rays and the search range: a ray is searched iff `hit = 1` and
/// `far > near`; `far < near` on a ray with `hit = 1` is an error, and so are bounds
/// whose points overflow the rays' dtype.
pub(crate) fn read_problem(rays: &Rays, range: &Intersection) -> Result<HostRays> {
    let r = rays.len();
    let mut host = read_rays(rays)?;
    check_shape(&range.hit, "hit", &[Dim::Is(r)])?;
    host.near = read_bound(&range.near, "near", rays.origins(), r)?;
    host.far = read_bound(&range.far, "far", rays.origins(), r)?;
    let hit: Vec<u8> = range.hit.to_dtype(DType::U8)?.to_vec1::<u8>()?;
    if let Some(i) = (0..r).find(|&i| hit[i] != 0 && host.far[i] < host.near[i]) {
        return Err(Error::invalid(
            "far",
            "far ≥ near on every ray with hit = 1",
            format!("near = {} > far = {} at ray {i}", host.near[i], host.far[i]),
        ));
    }
    host.active = (0..r)
        .map(|i| hit[i] != 0 && host.far[i] > host.near[i])
        .collect();
    let largest = if host.dtype == DType::F32 {
        f64::from(f32::MAX)
    } else {
        f64::MAX
    };
    for i in 0..r {
        let t_max = host.near[i].abs().max(host.far[i].abs());
        let reach = (0..3).all(|k| host.o[i][k].abs() + t_max * host.w[i][k].abs() <= largest);
        if host.active[i] && !reach {
            return Err(Error::invalid(
                "far",
                "points o + t·w representable in the rays' dtype for t in [near, far]",
                format!("an overflow at ray {i}"),
            ));
        }
    }
    Ok(host)
}

/// Host points to evaluate, each with the index of its ray (for fields with one latent
/// code per ray; see [`ImplicitSurface::value_on_rays`]).
#[derive(Default)]
pub(crate) struct RayPoints {
    pts: Vec<f64>,
    ids: Vec<u32>,
}

impl RayPoints {
    pub(crate) fn with_capacity(n: usize) -> Self {
        Self {
            pts: Vec::with_capacity(3 * n),
            ids: Vec::with_capacity(n),
        }
    }

    pub(crate) fn clear(&mut self) {
        self.pts.clear();
        self.ids.clear();
    }

    /// Adds the point `o + t·w` of ray `ray`.
    pub(crate) fn push(&mut self, ray: usize, o: &[f64; 3], w: &[f64; 3], t: f64) {
        self.pts.extend_from_slice(&point(o, w, t));
        // Ray counts are far below 2³² (the host copies alone would not fit otherwise).
        self.ids.push(ray as u32);
    }
}

/// Evaluates `s = σ(f − τ)` (and `σ∇f`) at host points, in chunks.
pub(crate) struct Evaluator<'a, F: ?Sized> {
    field: &'a F,
    dtype: DType,
    device: Device,
    chunk: usize,
    sign: f64,
    level: f64,
    pub(crate) count: usize,
}

impl<'a, F: ImplicitSurface + ?Sized> Evaluator<'a, F> {
    pub(crate) fn new(field: &'a F, rays: &HostRays, chunk: usize) -> Self {
        Self {
            field,
            dtype: rays.dtype,
            device: rays.device.clone(),
            chunk: chunk.max(1),
            sign: field.inside().sign(),
            level: field.level(),
            count: 0,
        }
    }

    /// Chunks of `(points [M, 3], ray indices [M])` on the rays' device and dtype.
    fn upload<'p>(
        &'p self,
        p: &'p RayPoints,
    ) -> impl Iterator<Item = Result<(Tensor, Tensor)>> + 'p {
        p.pts
            .chunks(3 * self.chunk)
            .zip(p.ids.chunks(self.chunk))
            .map(move |(c, ids)| {
                let pts = Tensor::from_slice(c, (ids.len(), 3), &Device::Cpu)?
                    .to_dtype(self.dtype)?
                    .to_device(&self.device)?;
                let ids =
                    Tensor::from_slice(ids, ids.len(), &Device::Cpu)?.to_device(&self.device)?;
                Ok((pts, ids))
            })
    }

    /// `s` at the points.
    pub(crate) fn values(&mut self, p: &RayPoints) -> Result<Vec<f64>> {
        let mut out = Vec::with_capacity(p.ids.len());
        for chunk in self.upload(p) {
            let (pts, ids) = chunk?;
            let f = nan_free(vec1(&self.field.value_on_rays(&pts, &ids)?)?, p, out.len())?;
            out.extend(f.into_iter().map(|v| self.sign * (v - self.level)));
        }
        self.count += p.ids.len();
        Ok(out)
    }

    /// `s` and `σ∇f` (flattened `[M, 3]`) at the points.
    pub(crate) fn values_and_grads(&mut self, p: &RayPoints) -> Result<(Vec<f64>, Vec<f64>)> {
        let mut vals = Vec::with_capacity(p.ids.len());
        let mut grads = Vec::with_capacity(p.pts.len());
        for chunk in self.upload(p) {
            let (pts, ids) = chunk?;
            let (f, g) = self.field.value_and_grad_on_rays(&pts, &ids)?;
            let f = nan_free(vec1(&f)?, p, vals.len())?;
            vals.extend(f.into_iter().map(|v| self.sign * (v - self.level)));
            let g = g
                .detach()
                .to_dtype(DType::F64)?
                .flatten_all()?
                .to_vec1::<f64>()?;
            grads.extend(g.into_iter().map(|v| self.sign * v));
        }
        self.count += p.ids.len();
        Ok((vals, grads))
    }
}

/// The field's values of a chunk whose first point is `p`'s point `start`, refused if one
/// is NaN: a field that cannot say where the surface is must not read as a clean miss.
fn nan_free(f: Vec<f64>, p: &RayPoints, start: usize) -> Result<Vec<f64>> {
    match f.iter().position(|v| v.is_nan()) {
        None => Ok(f),
        Some(i) => {
            let k = start + i;
            let at = p.pts.get(3 * k..3 * k + 3).unwrap_or(&[]);
            Err(Error::invalid(
                "field",
                "values that are not NaN along the rays (±∞ is a side of the surface)",
                format!(
                    "NaN at {at:?} on ray {}",
                    p.ids.get(k).map_or(0, |&r| r as usize)
                ),
            ))
        }
    }
}

fn point(o: &[f64; 3], w: &[f64; 3], t: f64) -> [f64; 3] {
    [o[0] + t * w[0], o[1] + t * w[1], o[2] + t * w[2]]
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// A bracket `[t_lo, t_hi]` with `s_lo ≤ 0 < s_hi` (values possibly Illinois-scaled).
#[derive(Clone, Copy, Debug)]
struct Bracket {
    t_lo: f64,
    s_lo: f64,
    t_hi: f64,
    s_hi: f64,
    /// Which end was replaced last: `Some(true)` = high end.
    last_hi: Option<bool>,
}

/// Per-ray results on the host.
pub(crate) struct HostHits {
    pub(crate) depth: Vec<f64>,
    pub(crate) status: Vec<RayStatus>,
}

/// Samples and refines the rays `todo` on `[near, far]`, writing into `out`.
pub(crate) fn march_host<F: ImplicitSurface + ?Sized>(
    ev: &mut Evaluator<'_, F>,
    rays: &HostRays,
    todo: &[usize],
    config: &MarchConfig,
    out: &mut HostHits,
) -> Result<()> {
    let n = config.steps;
    let per_chunk = (config.chunk_points / n).max(1);
    let mut brackets: Vec<(usize, Bracket)> = Vec::new();
    // A chunk's points (32 bytes each) are held together.
    let held =
        crate::limits::check_bytes("config.chunk_points", &[n, per_chunk.min(todo.len())], 32)?;
    let mut pts = RayPoints::with_capacity(held);
    for chunk in todo.chunks(per_chunk) {
        pts.clear();
        for &i in chunk {
            let (a, b) = (rays.near[i], rays.far[i]);
            for j in 0..n {
                let t = a + (b - a) * (j as f64 / (n - 1) as f64);
                pts.push(i, &rays.o[i], &rays.w[i], t);
            }
        }
        let s = ev.values(&pts)?;
        for (ci, &i) in chunk.iter().enumerate() {
            let s = &s[ci * n..(ci + 1) * n];
            let (a, b) = (rays.near[i], rays.far[i]);
            let tj = |j: usize| a + (b - a) * (j as f64 / (n - 1) as f64);
            if s[0] > 0.0 {
                out.status[i] = RayStatus::StartsInside;
                out.depth[i] = a;
            } else if let Some(j) = (1..n).find(|&j| s[j] > 0.0) {
                brackets.push((
                    i,
                    Bracket {
                        t_lo: tj(j - 1),
                        s_lo: s[j - 1],
                        t_hi: tj(j),
                        s_hi: s[j],
                        last_hi: None,
                    },
                ));
            } else {
                out.status[i] = RayStatus::Miss;
                out.depth[i] = b;
            }
        }
    }
    refine(ev, rays, &mut brackets, config, out)
}

fn refine<F: ImplicitSurface + ?Sized>(
    ev: &mut Evaluator<'_, F>,
    rays: &HostRays,
    brackets: &mut [(usize, Bracket)],
    config: &MarchConfig,
    out: &mut HostHits,
) -> Result<()> {
    let k = config.secant_steps;
    let mut last_t = vec![f64::NAN; brackets.len()];
    let mut grazing = vec![false; brackets.len()];
    let mut pts = RayPoints::with_capacity(brackets.len());
    for step in 0..k {
        pts.clear();
        for (b, (i, br)) in brackets.iter().enumerate() {
            let (t, _) = secant_point(br.t_lo, br.s_lo, br.t_hi, br.s_hi);
            last_t[b] = t;
            pts.push(*i, &rays.o[*i], &rays.w[*i], t);
        }
        let with_grad = step + 1 == k && config.grazing_threshold.is_some();
        let (s, g) = if with_grad {
            let (s, g) = ev.values_and_grads(&pts)?;
            (s, Some(g))
        } else {
            (ev.values(&pts)?, None)
        };
        for (b, (i, br)) in brackets.iter_mut().enumerate() {
            let hi = s[b] > 0.0;
            let illinois = config.rule == SecantRule::Illinois && br.last_hi == Some(hi);
            if hi {
                br.t_hi = last_t[b];
                br.s_hi = s[b];
                if illinois {
                    br.s_lo *= 0.5;
                }
            } else {
                br.t_lo = last_t[b];
                br.s_lo = s[b];
                if illinois {
                    br.s_hi *= 0.5;
                }
            }
            br.last_hi = Some(hi);
            if let (Some(g), Some(c)) = (&g, config.grazing_threshold) {
                let g = &g[3 * b..3 * b + 3];
                let w = &rays.w[*i];
                let cos = dot(g, w).abs() / (dot(g, g).sqrt() * dot(w, w).sqrt());
                grazing[b] = cos.is_nan() || cos < c;
            }
        }
    }
    for (b, (i, br)) in brackets.iter().enumerate() {
        let (t, _) = secant_point(br.t_lo, br.s_lo, br.t_hi, br.s_hi);
        let err = if k == 0 {
            br.t_hi - br.t_lo
        } else {
            (t - last_t[b]).abs().min(br.t_hi - br.t_lo)
        };
        out.depth[*i] = t;
        out.status[*i] = if grazing[b] {
            RayStatus::Grazing
        } else if err > config.tolerance * (rays.far[*i] - rays.near[*i]) {
            RayStatus::NotConverged
        } else {
            RayStatus::Hit
        };
    }
    Ok(())
}

/// Builds the [`Hits`] tensors from host results.
pub(crate) fn finish(rays: &HostRays, out: HostHits, evaluations: usize) -> Result<Hits> {
    let r = out.depth.len();
    let mut p = Vec::with_capacity(3 * r);
    for i in 0..r {
        p.extend_from_slice(&point(&rays.o[i], &rays.w[i], out.depth[i]));
    }
    let mask: Vec<u8> = out
        .status
        .iter()
        .map(|s| u8::from(s.has_surface()))
        .collect();
    let to = |t: Tensor| -> Result<Tensor> { Ok(t.to_dtype(rays.dtype)?.to_device(&rays.device)?) };
    Ok(Hits {
        depth: to(Tensor::from_vec(out.depth, r, &Device::Cpu)?)?,
        points: to(Tensor::from_vec(p, (r, 3), &Device::Cpu)?)?,
        mask: Tensor::from_vec(mask, r, &Device::Cpu)?.to_device(&rays.device)?,
        status: out.status,
        evaluations,
    })
}

fn run_march<F: ImplicitSurface + ?Sized>(
    field: &F,
    rays: &HostRays,
    config: &MarchConfig,
) -> Result<Hits> {
    config.check()?;
    let r = rays.o.len();
    let mut out = HostHits {
        depth: (0..r)
            .map(|i| if rays.active[i] { rays.far[i] } else { 0.0 })
            .collect(),
        status: vec![RayStatus::Miss; r],
    };
    let todo: Vec<usize> = (0..r).filter(|&i| rays.active[i]).collect();
    let mut ev = Evaluator::new(field, rays, config.chunk_points);
    march_host(&mut ev, rays, &todo, config, &mut out)?;
    let count = ev.count;
    finish(rays, out, count)
}

/// Finds the first surface crossing on each ray `o + t·w`, `t ∈ [near, far]`, by `n`
/// evenly spaced samples and `k` secant steps (the math below). Detached: the outputs
/// carry no graph.
///
/// * `field`: any [`ImplicitSurface`] (occupancy or SDF; its `level` and `inside` sign
///   are respected), evaluated through [`ImplicitSurface::value_on_rays`]: a
///   [`crate::field::Conditioned`] field with an `[R, D]` code gives every ray its own
///   code (a batch of rays through different shapes).
/// * `rays`: `R` rays, f32 or f64; directions need not be unit (depth is in units of
///   `|w|`).
/// * `range`: the part of each ray to search, `near, far: [R]` in the rays' dtype and
///   device, e.g. from [`crate::camera::ray_aabb`] or [`crate::camera::ray_sphere`], or
///   [`Intersection::new`] for the same or explicit bounds on every ray. Rays with
///   `hit = 0` or `near = far` get [`RayStatus::Miss`] (depth 0) without any field
///   evaluation.
///
/// Cost: `n` evaluations per searched ray plus `k` per ray with a crossing, in calls of
/// at most `config.chunk_points` points; memory is O(R + chunk_points).
///
/// # Math
/// Along a ray `r(t) = o + t·w`, `t ∈ [near, far]`, the march looks at
/// `s(t) = σ·(f(r(t)) − τ)` with `σ = +1` for [`Inside::Positive`] fields (occupancy
/// logits) and `σ = −1` for [`Inside::Negative`] ones (SDFs), so that "inside" is `s > 0`
/// for both. It evaluates `s` at `n` evenly spaced parameters
/// `tⱼ = near + (far − near)·j/(n − 1)`, and the first crossing from outside to inside is
/// the first `j ≥ 1` with `s(tⱼ) > 0` (all earlier samples satisfy `s ≤ 0`). The bracket
/// `[t_lo, t_hi] = [tⱼ₋₁, tⱼ]` is refined by `k` secant steps
/// `t = t_lo − s_lo·(t_hi − t_lo)/(s_hi − s_lo)`, each followed by one evaluation and the
/// replacement of the bracket end with the same sign, and the returned depth is the
/// secant point of the final bracket (so a ray costs exactly `n + k` evaluations). The
/// secant point falls back to the midpoint (bisection) when `s_hi − s_lo` is not a finite
/// positive number (equal values, overflow, NaN) or the point is not inside the bracket.
/// With [`SecantRule::Illinois`] (the default), the value kept at a bracket end that
/// survives twice in a row is halved, which keeps the bracket and makes convergence
/// superlinear where plain regula falsi ([`SecantRule::RegulaFalsi`], DVR's rule) can get
/// stuck at one end.
///
/// Everything here is detached: the outputs carry no graph, and nothing from the march is
/// needed by [`crate::dvr::implicit_surface`], which makes the depth differentiable.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `near` / `far` / `hit` (a shape other than `[R]`, a
/// dtype or device other than the rays', non-finite bounds), `far` if `far < near` on a
/// ray with `hit = 1` (which [`crate::camera::ray_aabb`] and
/// [`crate::camera::ray_sphere`] never produce) or if `o + t·w` overflows the dtype on
/// `[near, far]`, `config.*` for an invalid configuration (`config.steps` or
/// `config.chunk_points` also when one chunk's points, 32 bytes each, would pass the
/// allocation limit of 2³³ bytes, 8 GiB, checked before anything is allocated); naming
/// `field` when it returns NaN at a sample (a field error, not a miss; ±∞ is taken as a
/// side of the surface); errors of the field.
pub fn march<F: ImplicitSurface + ?Sized>(
    field: &F,
    rays: &Rays,
    range: &Intersection,
    config: &MarchConfig,
) -> Result<Hits> {
    let host = read_problem(rays, range)?;
    run_march(field, &host, config)
}

/// Configuration of [`sphere_trace`] (IDR's defaults).
#[derive(Clone, Debug)]
pub struct SphereTraceConfig {
    /// Iterations of sphere tracing from both ends (10).
    pub max_iters: usize,
    /// Convergence threshold on `|f − τ|` (5e-5, in field units = distance).
    pub threshold: f64,
    /// On overshoot (`f − τ < 0` after a step), step back by this fraction of the last
    /// step (0.5).
    pub step_back: f64,
    /// The sampling march + secant used for rays that did not converge (100 steps,
    /// 8 secant steps), on the interval left between the two fronts.
    pub fallback: MarchConfig,
}

impl Default for SphereTraceConfig {
    fn default() -> Self {
        Self {
            max_iters: 10,
            threshold: 5e-5,
            step_back: 0.5,
            fallback: MarchConfig {
                steps: 100,
                ..MarchConfig::default()
            },
        }
    }
}

/// Sphere tracing for signed distance fields, IDR-style: from both ends of `[near, far]`
/// at once, `t_front ← t_front + d/|w|` and `t_back ← t_back − d/|w|` with
/// `d = f(o + t·w) − τ`, until `|d| < threshold`; a front that overshoots (`d < 0`) steps
/// back by `step_back` times its last step. After `max_iters` iterations, a converged
/// front is a [`RayStatus::Hit`] (or [`RayStatus::Grazing`], tested with one extra
/// `value_and_grad` evaluation when `fallback.grazing_threshold` is set); rays whose
/// fronts crossed are misses; the others are marched with `config.fallback` on
/// `[t_front, t_back]`. A ray whose first point is inside is
/// [`RayStatus::StartsInside`]; a back end that starts inside stays at `far`.
///
/// Shapes, dtypes and the detached outputs as [`march`]. The field must be an SDF (or a
/// lower bound of the distance) for the steps to be safe.
///
/// # Errors
/// As [`march`] (a NaN value of the field is an error naming `field`, not a miss);
/// `field` if its inside is not [`Inside::Negative`]; `config.max_iters`
/// if 0, `config.threshold` unless > 0, `config.step_back` unless in (0, 1).
pub fn sphere_trace<F: ImplicitSurface + ?Sized>(
    field: &F,
    rays: &Rays,
    range: &Intersection,
    config: &SphereTraceConfig,
) -> Result<Hits> {
    if field.inside() != Inside::Negative {
        return Err(Error::invalid(
            "field",
            "a signed distance field (inside negative)",
            "an inside-positive field",
        ));
    }
    if config.max_iters == 0 {
        return Err(Error::invalid("config.max_iters", "at least 1", "0"));
    }
    crate::error::check_scalar(config.threshold, "config.threshold", true)?;
    if !(config.step_back > 0.0 && config.step_back < 1.0) {
        return Err(Error::invalid(
            "config.step_back",
            "a fraction in (0, 1)",
            format!("{}", config.step_back),
        ));
    }
    config.fallback.check()?;
    let rays = read_problem(rays, range)?;
    let r = rays.o.len();
    let mut ev = Evaluator::new(field, &rays, config.fallback.chunk_points);
    let mut out = HostHits {
        depth: rays.far.clone(),
        status: vec![RayStatus::Miss; r],
    };
    let len: Vec<f64> = rays.w.iter().map(|w| dot(w, w).sqrt()).collect();
    // Distances are σ·s with σ = −1: d = f − τ = −s.
    let mut tf = rays.near.clone();
    let mut tb = rays.far.clone();
    // Rays outside the range (hit = 0 or near = far) are misses at depth 0, never
    // evaluated.
    let act: Vec<usize> = (0..r).filter(|&i| rays.active[i]).collect();
    for i in (0..r).filter(|&i| !rays.active[i]) {
        out.depth[i] = 0.0;
    }
    let mut pts = RayPoints::with_capacity(2 * act.len());
    for &i in &act {
        pts.push(i, &rays.o[i], &rays.w[i], tf[i]);
        pts.push(i, &rays.o[i], &rays.w[i], tb[i]);
    }
    let s = ev.values(&pts)?;
    let (mut df, mut db) = (vec![0.0; r], vec![0.0; r]);
    for (k, &i) in act.iter().enumerate() {
        df[i] = -s[2 * k];
        db[i] = -s[2 * k + 1];
    }
    let back_ok: Vec<bool> = db.iter().map(|&d| d >= 0.0).collect();
    // The last front / back positions known to be outside (d ≥ 0).
    let mut safe_f = tf.clone();
    let mut safe_b = tb.clone();
    let mut last_f = vec![0.0; r];
    let mut last_b = vec![0.0; r];
    // 0 = running, 1 = front converged, 2 = done (miss or starts inside).
    let mut state = vec![2u8; r];
    for &i in &act {
        state[i] = 0;
        if df[i] < 0.0 {
            state[i] = 2;
            out.status[i] = RayStatus::StartsInside;
            out.depth[i] = rays.near[i];
        } else if df[i].abs() < config.threshold {
            state[i] = 1;
        }
    }
    for _ in 0..config.max_iters {
        let running: Vec<usize> = (0..r).filter(|&i| state[i] == 0).collect();
        if running.is_empty() {
            break;
        }
        pts.clear();
        for &i in &running {
            // Front.
            let step = if df[i] < 0.0 {
                -config.step_back * last_f[i]
            } else {
                df[i] / len[i]
            };
            last_f[i] = if df[i] < 0.0 {
                last_f[i] * (1.0 - config.step_back)
            } else {
                step
            };
            tf[i] += step;
            // Back.
            if back_ok[i] && db[i].abs() >= config.threshold {
                let step = if db[i] < 0.0 {
                    -config.step_back * last_b[i]
                } else {
                    db[i] / len[i]
                };
                last_b[i] = if db[i] < 0.0 {
                    last_b[i] * (1.0 - config.step_back)
                } else {
                    step
                };
                tb[i] -= step;
            }
            pts.push(i, &rays.o[i], &rays.w[i], tf[i]);
            pts.push(i, &rays.o[i], &rays.w[i], tb[i]);
        }
        let s = ev.values(&pts)?;
        for (k, &i) in running.iter().enumerate() {
            df[i] = -s[2 * k];
            if df[i] >= 0.0 {
                safe_f[i] = tf[i];
            }
            if back_ok[i] {
                db[i] = -s[2 * k + 1];
                if db[i] >= 0.0 {
                    safe_b[i] = tb[i];
                }
            }
            // The fronts passed each other while both are outside: no surface between.
            // (A front that overshot into the inside steps back first.)
            if tf[i] > tb[i] && df[i] >= 0.0 && (!back_ok[i] || db[i] >= 0.0) {
                state[i] = 2;
                out.status[i] = RayStatus::Miss;
                out.depth[i] = rays.far[i];
            } else if df[i].abs() < config.threshold {
                state[i] = 1;
            }
        }
    }
    // Converged fronts: hits (grazing test with one gradient evaluation).
    let conv: Vec<usize> = (0..r).filter(|&i| state[i] == 1).collect();
    for &i in &conv {
        out.depth[i] = tf[i];
        out.status[i] = RayStatus::Hit;
    }
    if let Some(c) = config.fallback.grazing_threshold {
        pts.clear();
        for &i in &conv {
            pts.push(i, &rays.o[i], &rays.w[i], tf[i]);
        }
        if !conv.is_empty() {
            let (_, g) = ev.values_and_grads(&pts)?;
            for (k, &i) in conv.iter().enumerate() {
                let g = &g[3 * k..3 * k + 3];
                let cos = dot(g, &rays.w[i]).abs() / (dot(g, g).sqrt() * len[i]);
                if cos.is_nan() || cos < c {
                    out.status[i] = RayStatus::Grazing;
                }
            }
        }
    }
    // Unconverged: sampling + secant on [t_front, t_back].
    let rest: Vec<usize> = (0..r).filter(|&i| state[i] == 0).collect();
    if !rest.is_empty() {
        let sub = HostRays {
            o: rays.o.clone(),
            w: rays.w.clone(),
            near: safe_f.clone(),
            far: safe_b.clone(),
            active: vec![true; r],
            dtype: rays.dtype,
            device: rays.device.clone(),
        };
        let todo: Vec<usize> = rest
            .into_iter()
            .filter(|&i| safe_b[i] > safe_f[i])
            .collect();
        march_host(&mut ev, &sub, &todo, &config.fallback, &mut out)?;
        for &i in &todo {
            // The fallback starts at a front known to be outside, so "starts inside"
            // means a value at exactly that point flipped sign (a non-SDF field):
            // report the front as an unconverged estimate.
            if out.status[i] == RayStatus::StartsInside {
                out.status[i] = RayStatus::NotConverged;
                out.depth[i] = safe_f[i];
            } else if out.status[i] == RayStatus::Miss {
                out.depth[i] = rays.far[i];
            }
        }
    }
    let count = ev.count;
    finish(&rays, out, count)
}

#[cfg(test)]
mod tests {
    use super::secant_point;

    #[test]
    fn secant_denominator_zero_falls_back_to_bisection() {
        // Equal values, overflow and NaN give the midpoint.
        assert_eq!(secant_point(1.0, 0.0, 3.0, 0.0), (2.0, true));
        assert_eq!(secant_point(1.0, -f64::MAX, 3.0, f64::MAX), (2.0, true));
        assert_eq!(secant_point(1.0, f64::NAN, 3.0, 1.0), (2.0, true));
        assert_eq!(secant_point(1.0, -1.0, 3.0, 1.0), (2.0, false));
        assert_eq!(secant_point(1.0, 0.0, 3.0, 5.0), (1.0, false));
    }

    /// The stiff cases: brackets of extreme width and values (overflowing, zero, NaN and
    /// infinite denominators) give a finite point inside the bracket.
    #[test]
    fn secant_point_is_finite_at_extreme_brackets() {
        let m = f64::MAX;
        for (lo, slo, hi, shi) in [
            (0.0, -m, 1.0, m),
            (0.0, 0.0, 1.0, 0.0),
            (0.0, f64::NAN, 1.0, 1.0),
            (-1e300, -1e-300, 1e300, 1e-300),
            (0.0, -f64::INFINITY, 1.0, f64::INFINITY),
        ] {
            let (t, _) = secant_point(lo, slo, hi, shi);
            assert!(
                t.is_finite() && (lo..=hi).contains(&t),
                "[{lo:e}, {hi:e}], s {slo:e}…{shi:e}: {t}"
            );
        }
    }
}
