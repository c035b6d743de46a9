//! Multiresolution IsoSurface Extraction (MISE, Mescheder et al. 2019).

use super::isosurface::{evaluate_points, marching_cubes, Grid};
use crate::error::{check_scalar, Error, Result};
use crate::field::ImplicitSurface;
use crate::mesh::Mesh;
use candle_core::{DType, Device};
use rayon::prelude::*;

/// Settings of [`mise`].
#[derive(Clone, Debug)]
pub struct MiseConfig {
    /// Cells per axis of the coarsest grid, `r₀ ≥ 1` (ONet: 16 in the generator, 32 in
    /// the default config).
    pub resolution0: usize,
    /// Number of subdivisions `k`; the final grid has `r₀·2ᵏ` cells per axis.
    pub upsampling_steps: usize,
    /// Lower corner of the box (ONet: `−0.55` on each axis, the unit cube padded by 0.1).
    pub min: [f64; 3],
    /// Upper corner of the box.
    pub max: [f64; 3],
    /// The level τ; `None` uses [`ImplicitSurface::level`].
    pub level: Option<f64>,
    /// Points per field evaluation (`[chunk, 3]` tensors).
    pub chunk: usize,
    /// Device of the point tensors handed to the field.
    pub device: Device,
    /// Dtype of the point tensors (f32 or f64).
    pub dtype: DType,
}

impl MiseConfig {
    /// `r₀`, `k` on ONet's box `[−0.55, 0.55]³`, the field's level, chunks of 65 536
    /// points, on `device` in `dtype`.
    #[must_use]
    pub fn new(resolution0: usize, upsampling_steps: usize, device: &Device, dtype: DType) -> Self {
        Self {
            resolution0,
            upsampling_steps,
            min: [-0.55; 3],
            max: [0.55; 3],
            level: None,
            chunk: 65_536,
            device: device.clone(),
            dtype,
        }
    }
}

/// The logit of a probability threshold, `ln(p / (1 − p))`: MISE thresholds logits, so
/// ONet's probability threshold `p` becomes this level.
///
/// # Errors
/// `p` not in `(0, 1)`.
pub fn logit_threshold(p: f64) -> Result<f64> {
    if !(p > 0.0 && p < 1.0) {
        return Err(Error::invalid(
            "p",
            "a probability in (0, 1)",
            format!("{p}"),
        ));
    }
    Ok((p / (1.0 - p)).ln())
}

/// The result of [`mise`].
#[derive(Clone, Debug)]
pub struct MiseOutput {
    /// The extracted mesh (empty if the field does not cross the level in the box).
    pub mesh: Mesh,
    /// The final grid, evaluated near the surface and filled elsewhere.
    pub grid: Grid,
    /// Number of points at which the field was evaluated.
    pub evaluations: usize,
    /// Active cells at each level (`k + 1` entries).
    pub active_per_level: Vec<usize>,
}

/// Checks that `dtype` is f32 or f64 and returns the level: `level`, or the field's own.
fn dtype_and_level(surface: &dyn ImplicitSurface, dtype: DType, level: Option<f64>) -> Result<f64> {
    crate::error::check_dtype(dtype)?;
    let level = level.unwrap_or_else(|| surface.level());
    check_scalar(level, "level", false)?;
    Ok(level)
}

/// Extracts the level set of `surface` by MISE (below); the field is
/// evaluated through [`ImplicitSurface::value`] on batches of `config.chunk` points.
///
/// The point where the field is evaluated for grid index `(i, j, k)` is
/// `min + (i, j, k) ⊙ (max − min)/N`, exactly as in [`Grid::sample`] at the same final
/// resolution, so where MISE evaluated it agrees bit for bit with dense extraction.
///
/// Not differentiable (a mesh is an output); the field may be any device and dtype.
///
/// With `r₀ = resolution0` cells per axis and `k = upsampling_steps`, the final grid has
/// `N = r₀·2ᵏ` cells (`N + 1` points) per axis over the box `[min, max]³`:
///
/// 1. evaluate the field at the `(r₀ + 1)³` points of the coarse grid;
/// 2. a cell is *active* when its eight corners are not all on the same side of the
///    level τ; subdivide each active cell into eight, evaluate only the points that are
///    new (edge midpoints, face centres, the centre, shared between neighbours), and keep
///    as active the children that straddle τ; repeat `k` times;
/// 3. every point of the final grid that was never evaluated lies in a cell that was
///    inactive at some level (all eight corners on one side); it is filled, level by
///    level, with the trilinear interpolation of that cell's corners (the mean of the 2,
///    4 or 8 nearest coarser points), which keeps the side of the level set;
/// 4. run [`marching_cubes`] on the final grid.
///
/// Cost: `(r₀ + 1)³` plus `O(surface area × N²)` evaluations instead of `(N + 1)³`.
/// Surface parts thinner than a coarse cell can be missed (both corners outside), as in
/// the original. For occupancy probabilities with threshold `p` (ONet's 0.2 to 0.5), use
/// the level [`logit_threshold`]`(p)` on the logits.
///
/// # Errors
/// `resolution0 = 0`, a final resolution above 2048 cells per axis or whose `(N + 1)³`
/// vertices (5 bytes each) pass the allocation limit of 2³³ bytes (8 GiB; N ≤ 1197),
/// checked before anything is allocated (naming `upsampling_steps`), `chunk = 0`,
/// a bad box or level, dtype not f32/f64, errors or NaN values of the field.
pub fn mise(surface: &dyn ImplicitSurface, config: &MiseConfig) -> Result<MiseOutput> {
    let r0 = config.resolution0;
    let steps = config.upsampling_steps;
    if r0 == 0 {
        return Err(Error::invalid("resolution0", "at least 1 cell", "0"));
    }
    if steps > 11 || r0.saturating_mul(1 << steps) > 2048 {
        return Err(Error::invalid(
            "upsampling_steps",
            "a final resolution r₀·2ᵏ ≤ 2048",
            format!("{r0}·2^{steps}"),
        ));
    }
    let level = dtype_and_level(surface, config.dtype, config.level)?;
    let sign = surface.inside().sign() as f32;
    let tau = level as f32;
    let n = r0 << steps; // cells per axis
                         // A value (f32) and a state byte per vertex of the finest grid.
    crate::limits::check_bytes("upsampling_steps", &[n + 1, n + 1, n + 1], 5)?;
    let np = n + 1;
    let (min, max) = (config.min, config.max);
    // Validates the box.
    let mut grid = Grid::new(vec![0.0; 8], [2; 3], min, max)?;
    let h: [f64; 3] = std::array::from_fn(|c| (max[c] - min[c]) / n as f64);
    let position = |idx: usize| {
        let (i, j, k) = (idx % np, (idx / np) % np, idx / (np * np));
        [
            min[0] + i as f64 * h[0],
            min[1] + j as f64 * h[1],
            min[2] + k as f64 * h[2],
        ]
    };
    let at = |i: usize, j: usize, k: usize| i + np * (j + np * k);
    let mut values = vec![0.0f32; np * np * np];
    // 0 never evaluated, 1 evaluated, 2 queued for evaluation.
    let mut state = vec![0u8; np * np * np];
    let mut evaluations = 0usize;
    let mut evaluate = |ids: &[usize], values: &mut [f32], state: &mut [u8]| -> Result<()> {
        let v = evaluate_points(
            surface,
            ids,
            config.chunk,
            &config.device,
            config.dtype,
            position,
        )?;
        for (&id, x) in ids.iter().zip(v) {
            values[id] = x;
            state[id] = 1;
        }
        evaluations += ids.len();
        Ok(())
    };

    // Level 0.
    let mut s = 1usize << steps;
    let coarse: Vec<usize> = (0..=r0)
        .flat_map(|k| (0..=r0).flat_map(move |j| (0..=r0).map(move |i| (i, j, k))))
        .map(|(i, j, k)| at(i * s, j * s, k * s))
        .collect();
    evaluate(&coarse, &mut values, &mut state)?;
    let straddles = |values: &[f32], o: [usize; 3], s: usize| {
        let mut any_in = false;
        let mut any_out = false;
        for c in 0..8 {
            let idx = at(
                o[0] + s * (c & 1),
                o[1] + s * ((c >> 1) & 1),
                o[2] + s * (c >> 2),
            );
            if sign * (values[idx] - tau) > 0.0 {
                any_in = true;
            } else {
                any_out = true;
            }
        }
        any_in && any_out
    };
    let mut active: Vec<[usize; 3]> = (0..r0)
        .flat_map(|k| (0..r0).flat_map(move |j| (0..r0).map(move |i| [i * s, j * s, k * s])))
        .filter(|&o| straddles(&values, o, s))
        .collect();
    let mut active_per_level = vec![active.len()];

    for _ in 0..steps {
        let half = s / 2;
        let mut new_ids = Vec::new();
        for o in &active {
            for c in 0..3 {
                for b in 0..3 {
                    for a in 0..3 {
                        let idx = at(o[0] + a * half, o[1] + b * half, o[2] + c * half);
                        if state[idx] == 0 {
                            state[idx] = 2;
                            new_ids.push(idx);
                        }
                    }
                }
            }
        }
        new_ids.sort_unstable();
        evaluate(&new_ids, &mut values, &mut state)?;
        let vals = &values;
        active = active
            .par_iter()
            .flat_map_iter(|o| {
                (0..8).filter_map(move |c| {
                    let child = [
                        o[0] + half * (c & 1),
                        o[1] + half * ((c >> 1) & 1),
                        o[2] + half * (c >> 2),
                    ];
                    straddles(vals, child, half).then_some(child)
                })
            })
            .collect();
        active_per_level.push(active.len());
        s = half;
    }

    // Fill never-evaluated points, coarse to fine, from the coarser lattice around them.
    let mut s = 1usize << steps;
    while s > 1 {
        let half = s / 2;
        let vals = &values;
        let st = &state;
        let pp = np * np;
        // Each plane holding stride-`half` points is rebuilt from an immutable view
        // (fills read only coarse-lattice points, which no fill writes), then copied back.
        let planes: Vec<(usize, Vec<f32>)> = (0..np)
            .into_par_iter()
            .filter(|k| k % half == 0)
            .map(|k| {
                let mut out = vals[k * pp..(k + 1) * pp].to_vec();
                let span = |x: usize| -> [usize; 2] {
                    if x.is_multiple_of(s) {
                        [x, x]
                    } else {
                        [x - half, x + half]
                    }
                };
                let zs = span(k);
                for j in (0..np).step_by(half) {
                    let ys = span(j);
                    for i in (0..np).step_by(half) {
                        let idx = at(i, j, k);
                        if st[idx] != 0 {
                            continue;
                        }
                        let xs = span(i);
                        let mut sum = 0.0f32;
                        for z in zs {
                            for y in ys {
                                let row = at(0, y, z);
                                sum += vals[row + xs[0]] + vals[row + xs[1]];
                            }
                        }
                        out[i + np * j] = sum / 8.0;
                    }
                }
                (k, out)
            })
            .collect();
        for (k, plane_values) in planes {
            values[k * pp..(k + 1) * pp].copy_from_slice(&plane_values);
        }
        s = half;
    }
    grid.values = values;
    grid.dims = [np; 3];
    let mesh = marching_cubes(&grid, level, surface.inside())?;
    Ok(MiseOutput {
        mesh,
        grid,
        evaluations,
        active_per_level,
    })
}

/// Settings of [`refine_vertices`].
#[derive(Clone, Debug)]
pub struct RefineConfig {
    /// Newton steps per vertex (2–3 usually reach the field's precision).
    pub steps: usize,
    /// The largest total displacement of a vertex, in scene units (use about half the
    /// extraction's cell size: a marching-cubes vertex is never farther than a cell from
    /// the level set, and a larger step means the linearisation is not trustworthy).
    pub max_shift: f64,
    /// The level τ; `None` uses [`ImplicitSurface::level`].
    pub level: Option<f64>,
    /// Points per field evaluation (`[chunk, 3]` tensors).
    pub chunk: usize,
    /// Device of the point tensors handed to the field.
    pub device: Device,
    /// Dtype of the point tensors (f32 or f64).
    pub dtype: DType,
}

impl RefineConfig {
    /// Three steps, at most `max_shift` of displacement, the field's level, chunks of
    /// 65 536 points, on `device` in `dtype`.
    #[must_use]
    pub fn new(max_shift: f64, device: &Device, dtype: DType) -> Self {
        Self {
            steps: 3,
            max_shift,
            level: None,
            chunk: 65_536,
            device: device.clone(),
            dtype,
        }
    }
}

/// Moves every vertex of `mesh` onto the level set of `surface` by Newton steps along
/// the field's gradient (the optional refinement after [`mise`] or [`marching_cubes`]):
///
/// `p ← p − (f(p) − τ) ∇f(p) / ‖∇f(p)‖²`
///
/// the step each vertex would take to the zero of the field's linearisation along its
/// gradient. Linear interpolation on the grid leaves an error of order h² times the
/// field's curvature; each Newton step squares the relative error where the field is
/// smooth. A vertex whose gradient is zero or not finite, or whose step is not finite,
/// stays where it is; a vertex's total displacement is clamped to
/// `config.max_shift` (along the step direction), so a bad linearisation cannot tear
/// the mesh. Faces are kept (topology unchanged); normals, when present, are recomputed
/// from the moved faces ([`Mesh::vertex_normals`]).
///
/// ONet refines instead by optimising a per-face loss with RMSprop; the Newton
/// projection needs no step size and no random points, and converges in a few steps.
///
/// Not differentiable (a mesh is an output). `config.dtype`: f32 or f64; the field is
/// evaluated through [`ImplicitSurface::value_and_grad`] in chunks of `config.chunk`.
/// Returns the mean |f − τ| at the vertices before and after refinement.
///
/// # Errors
/// Naming `max_shift` when not finite and > 0, `chunk` when 0, `dtype` when not f32/f64,
/// `level` when not finite; whatever the field returns.
pub fn refine_vertices(
    surface: &dyn ImplicitSurface,
    mesh: &mut Mesh,
    config: &RefineConfig,
) -> Result<(f64, f64)> {
    check_scalar(config.max_shift, "max_shift", true)?;
    if config.chunk == 0 {
        return Err(Error::invalid("chunk", "a chunk size ≥ 1", "0"));
    }
    let level = dtype_and_level(surface, config.dtype, config.level)?;
    let start = mesh.vertices.clone();
    let residual = |mesh: &mut Mesh, step: bool| -> Result<f64> {
        let mut sum = 0.0;
        for (c, block) in mesh.vertices.chunks_mut(config.chunk).enumerate() {
            let flat: Vec<f64> = block.iter().flatten().copied().collect();
            let pts = candle_core::Tensor::from_vec(flat, (block.len(), 3), &Device::Cpu)?
                .to_dtype(config.dtype)?
                .to_device(&config.device)?;
            let (v, g) = surface.value_and_grad(&pts)?;
            let v: Vec<f64> = v.flatten_all()?.to_dtype(DType::F64)?.to_vec1()?;
            let g: Vec<f64> = g.flatten_all()?.to_dtype(DType::F64)?.to_vec1()?;
            for (i, p) in block.iter_mut().enumerate() {
                let r = v[i] - level;
                sum += r.abs();
                if !step {
                    continue;
                }
                let gi = [g[3 * i], g[3 * i + 1], g[3 * i + 2]];
                let g2 = gi[0] * gi[0] + gi[1] * gi[1] + gi[2] * gi[2];
                let scale = r / g2;
                if !(g2 > 0.0 && scale.is_finite()) {
                    continue;
                }
                let q = [
                    p[0] - scale * gi[0],
                    p[1] - scale * gi[1],
                    p[2] - scale * gi[2],
                ];
                // Clamp the total displacement from the original vertex.
                let o = start[c * config.chunk + i];
                let d = [q[0] - o[0], q[1] - o[1], q[2] - o[2]];
                let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                let k = if len > config.max_shift {
                    config.max_shift / len
                } else {
                    1.0
                };
                *p = [o[0] + k * d[0], o[1] + k * d[1], o[2] + k * d[2]];
            }
        }
        Ok(sum / mesh.vertices.len().max(1) as f64)
    };
    let before = residual(mesh, config.steps > 0)?;
    for _ in 1..config.steps {
        residual(mesh, true)?;
    }
    let after = if config.steps > 0 {
        residual(mesh, false)?
    } else {
        before
    };
    if mesh.normals.is_some() {
        mesh.normals = Some(mesh.vertex_normals()?);
    }
    Ok((before, after))
}
