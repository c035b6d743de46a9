//! Occupancy grid: empty-space skipping on an analytic scene that is mostly empty
//! renders the same image with far fewer samples; the EMA empties cells of a field that
//! has become empty; the march's intervals are well formed; bad input errs.
#![cfg(feature = "volume")]

use candle_core::{DType, Device, Tensor};
use neural_fields::camera::Rays;
use neural_fields::volume::{
    composite, CompositeConfig, GridConfig, GridMarchConfig, GridSamples, Layout, OccupancyGrid,
    Packed,
};
use neural_fields::{Error, Result};
use std::time::Instant;

/// The ball of the default scene: it fills 1.4% of the level-0 box [−1, 1]³ (the grid's
/// AABB) and 0.18% of the level-1 box.
const BALL_R: f64 = 0.3;
/// The ball that fills 5.0% of the grid's AABB [−1, 1]³ (4/3·π·r³ = 0.05·8): the
/// scene of the bar, 95% empty.
const BALL_R_95: f64 = 0.457_1;
const BALL_D: f64 = 20.0;
const UPDATES: usize = 16;

/// σ(p) = D·(1 − |p|²/r²)² inside the ball of radius r about the origin, 0 outside.
fn ball(r: f64) -> impl Fn(&Tensor) -> Result<Tensor> + Copy {
    move |p: &Tensor| {
        let r2 = p.sqr()?.sum(1)?;
        let u = r2.affine(-1.0 / (r * r), 1.0)?.relu()?;
        Ok((u.sqr()? * BALL_D)?)
    }
}

fn ball_sigma(p: &Tensor) -> Result<Tensor> {
    ball(BALL_R)(p)
}

/// A colour that varies across the ball: c(p) = 0.5 + p per channel.
fn ball_color(p: &Tensor) -> Result<Tensor> {
    Ok(p.affine(1.0, 0.5)?)
}

/// A grid on `aabb` with `resolution`³ cells per level, the other settings from `cfg`.
fn grid_with(
    aabb: [f64; 6],
    resolution: usize,
    levels: usize,
    cfg: GridConfig,
) -> Result<OccupancyGrid> {
    OccupancyGrid::new(GridConfig {
        aabb,
        resolution,
        levels,
        ..cfg
    })
}

/// A grid with the default settings.
fn grid_new(aabb: [f64; 6], resolution: usize, levels: usize) -> Result<OccupancyGrid> {
    grid_with(aabb, resolution, levels, GridConfig::default())
}

/// The fraction of occupied cells, over all levels.
fn occupied_fraction(grid: &OccupancyGrid) -> f64 {
    let occ = grid.occupied();
    occ.iter().filter(|&&o| o).count() as f64 / occ.len() as f64
}

/// The packed layout of the grid's samples.
fn packed(s: &GridSamples) -> &Packed {
    match &s.intervals.layout {
        Layout::Packed(p) => p,
        Layout::Batched => panic!("the grid emits packed intervals"),
    }
}

/// The number of samples the grid emitted.
fn n_samples(s: &GridSamples) -> usize {
    s.intervals.starts.dims()[0]
}

fn arg_of(e: Error) -> &'static str {
    match e {
        Error::InvalidArgument { arg, .. } => arg,
        other => panic!("expected InvalidArgument, got {other}"),
    }
}

/// A pinhole camera at (0, 0, −3) looking along +z; directions have unit z (not unit
/// length), as the camera module returns them.
fn rays(side: usize, dt: DType) -> Rays {
    let mut o = Vec::new();
    let mut d = Vec::new();
    for i in 0..side {
        for j in 0..side {
            let u = -0.45 + 0.9 * (i as f64 + 0.5) / side as f64;
            let v = -0.45 + 0.9 * (j as f64 + 0.5) / side as f64;
            o.extend([0.0, 0.0, -3.0]);
            d.extend([u, v, 1.0]);
        }
    }
    let dev = Device::Cpu;
    let n = side * side;
    Rays::new(
        Tensor::from_vec(o, (n, 3), &dev)
            .unwrap()
            .to_dtype(dt)
            .unwrap(),
        Tensor::from_vec(d, (n, 3), &dev)
            .unwrap()
            .to_dtype(dt)
            .unwrap(),
    )
    .unwrap()
}

fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_dtype(DType::F64)
        .unwrap()
        .to_scalar::<f64>()
        .unwrap()
}

fn render(s: &GridSamples, rays: &Rays, r: f64) -> Tensor {
    let pos = s.intervals.positions(rays).unwrap();
    let sigma = ball(r)(&pos).unwrap();
    let rgb = ball_color(&pos).unwrap();
    composite(
        &sigma,
        &rgb,
        &s.intervals,
        Some(rays),
        &CompositeConfig::default(),
    )
    .unwrap()
    .color
}

/// On the 98.6%-empty scene and on the 95%-empty one (the bar), in f32 and f64:
/// rendering through the grid gives the full render's colours within 1e-3 while
/// compositing at least 10× fewer samples. (Not counted: the warm-up updates, 16
/// evaluations of every one of the 65 536 cells, which a training loop spreads over its
/// steps, one update every k of them.)
#[test]
fn skipping_empty_space_matches_the_full_render_with_ten_times_fewer_samples() {
    for (r, dt) in [
        (BALL_R, DType::F32),
        (BALL_R, DType::F64),
        (BALL_R_95, DType::F32),
        (BALL_R_95, DType::F64),
    ] {
        let ball_sigma = ball(r);
        let rays = rays(48, dt);
        let aabb = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0];
        let full_grid = grid_new(aabb, 32, 2).unwrap();
        // The default grid is conservative (`dilate: true`); one jittered point per cell
        // misses thin slivers of the ball at cell corners, and nerfacc's rule
        // (`dilate: false`) is measured and printed too.
        let cfg = GridConfig::default();
        assert!(cfg.dilate);
        let mut grid = grid_with(aabb, 32, 2, cfg.clone()).unwrap();
        let mut plain = grid_with(
            aabb,
            32,
            2,
            GridConfig {
                dilate: false,
                ..cfg
            },
        )
        .unwrap();
        // Warm-up updates: every cell, a fresh jitter each time (16, as many as
        // nerfacc's schedule of one update every 16 steps over 256 warm-up steps).
        let clock = Instant::now();
        for step in 0..UPDATES {
            assert!(grid.update(step, 1, &Device::Cpu, dt, ball_sigma).unwrap());
        }
        let t_update = clock.elapsed().as_secs_f64() / UPDATES as f64;
        for step in 0..UPDATES {
            assert!(plain.update(step, 1, &Device::Cpu, dt, ball_sigma).unwrap());
        }
        let occ = occupied_fraction(&grid);
        let step = 4.0 / 512.0; // in t (|d| ≈ 1): 512 steps across the level-1 box
        let clock = Instant::now();
        let full = full_grid
            .sample(
                &rays,
                &GridMarchConfig {
                    near: 0.0,
                    far: f64::INFINITY,
                    step_size: step,
                    ..GridMarchConfig::default()
                },
                None,
            )
            .unwrap();
        let t_march_full = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let skip = grid
            .sample(
                &rays,
                &GridMarchConfig {
                    near: 0.0,
                    far: f64::INFINITY,
                    step_size: step,
                    ..GridMarchConfig::default()
                },
                None,
            )
            .unwrap();
        let t_march_skip = clock.elapsed().as_secs_f64();
        assert_eq!(full.n_marched, skip.n_marched);
        assert_eq!(
            n_samples(&full),
            full.n_marched,
            "a fresh grid keeps every sample"
        );
        let m_full = n_samples(&full);
        let m_skip = n_samples(&skip);
        let clock = Instant::now();
        let c_full = render(&full, &rays, r);
        let t_render_full = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let c_skip = render(&skip, &rays, r);
        let t_render_skip = clock.elapsed().as_secs_f64();
        let err = max_abs_diff(&c_full, &c_skip);
        let max_c = c_skip
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        let ratio = m_full as f64 / m_skip as f64;
        let undilated = plain
            .sample(
                &rays,
                &GridMarchConfig {
                    near: 0.0,
                    far: f64::INFINITY,
                    step_size: step,
                    ..GridMarchConfig::default()
                },
                None,
            )
            .unwrap();
        let err_plain = max_abs_diff(&c_full, &render(&undilated, &rays, r));
        println!(
            "grid skipping (ball r = {r}, {dt:?}, 48x48 rays, 2 levels of 32^3, occupied {:.2}% of cells): \
             {m_full} samples without skipping, {m_skip} with ({ratio:.1}x fewer); \
             max |colour error| {err:.3e} (max colour {max_c:.3})",
            100.0 * occ
        );
        println!(
            "  nerfacc rule (no dilation): {} samples ({:.1}x fewer), max |colour error| {:.3e}",
            n_samples(&undilated),
            m_full as f64 / n_samples(&undilated) as f64,
            err_plain,
        );
        println!(
            "  times: march {:.1} ms full / {:.1} ms skip; field + composite {:.1} ms full / \
             {:.1} ms skip; one warm-up update (65536 cells) {:.1} ms",
            1e3 * t_march_full,
            1e3 * t_march_skip,
            1e3 * t_render_full,
            1e3 * t_render_skip,
            1e3 * t_update
        );
        assert!(max_c > 0.3, "the ball must be visible");
        assert!(err <= 1e-3, "r = {r}, {dt:?}: max colour error {err}");
        assert!(
            ratio >= 10.0,
            "r = {r}, {dt:?}: only {ratio}x fewer samples"
        );
    }
}

#[test]
fn cells_of_a_field_that_becomes_empty_are_emptied_by_the_ema() {
    let aabb = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0];
    let cfg = GridConfig::default();
    let mut grid = grid_with(aabb, 16, 1, cfg.clone()).unwrap();
    let dev = Device::Cpu;
    for step in 0..4 {
        grid.update(step, 1, &dev, DType::F32, ball_sigma).unwrap();
    }
    let ball_cells = grid.occupied().iter().filter(|&&o| o).count();
    assert!(
        ball_cells > 0 && occupied_fraction(&grid) < 0.1,
        "{}",
        occupied_fraction(&grid)
    );
    assert!(grid.is_occupied([0.0, 0.0, 0.0]));
    assert!(!grid.is_occupied([0.9, 0.9, 0.9]));
    // No cell saw more than the field's maximum opacity, BALL_D times the cell's edge
    // 2/16 at the centre (the estimates reach about 0.9 of it: a jittered point near the
    // centre).
    let dmax = BALL_D * 2.0 / 16.0;
    // The densest cell drops below the floor after ⌈ln(dmax/floor)/ln(1/decay)⌉ updates.
    let bound = ((dmax / cfg.floor).ln() / (1.0 / cfg.decay).ln()).ceil() as usize;
    let empty = |p: &Tensor| Ok(p.sum(1)?.zeros_like()?);
    let mut emptied_at = None;
    for k in 1..=bound + 2 {
        grid.update(4 + k, 1, &dev, DType::F32, empty).unwrap();
        if k == 1 {
            assert!(
                occupied_fraction(&grid) > 0.0,
                "one decay step must not empty the grid"
            );
        }
        if occupied_fraction(&grid) == 0.0 {
            emptied_at = Some(k);
            break;
        }
    }
    println!("field became empty: grid emptied after {emptied_at:?} updates (bound {bound}, max density {dmax:.2})");
    let k = emptied_at.expect("grid never emptied");
    assert!(
        k <= bound + 1 && k + 22 >= bound,
        "emptied after {k}, bound {bound}"
    );
    assert!(!grid.is_occupied([0.0, 0.0, 0.0]));
}

/// The grid compared its threshold with the density σ itself, so that nerfacc's 0.01
/// (an opacity, σ·Δt) kept almost every cell of a trained field occupied and a user's
/// loop at the defaults never pruned. A constant density σ is occupied at the defaults
/// iff σ·Δ > 0.01, with Δ the cell's edge (the mean clamp cannot bite: every cell equals
/// the mean), on every level.
#[test]
fn the_threshold_is_an_opacity_per_cell_not_a_density() {
    let dev = Device::Cpu;
    for (levels, res, sigma, occupied) in [
        (1, 16, 0.1, true),   // Δ = 1/8: σ·Δ = 0.0125
        (1, 16, 0.07, false), // 0.00875 (occupied under the old rule: σ > 0.01)
        (1, 32, 0.1, false),  // Δ = 1/16: 0.00625
        (1, 32, 0.2, true),   // 0.0125
    ] {
        for dt in [DType::F32, DType::F64] {
            let mut grid = grid_new([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], res, levels).unwrap();
            let field = |p: &Tensor| Ok((p.sum(1)?.zeros_like()? + sigma)?);
            grid.update(0, 1, &dev, dt, field).unwrap();
            let f = occupied_fraction(&grid);
            let want = if occupied { 1.0 } else { 0.0 };
            assert_eq!(
                f, want,
                "res {res}, σ = {sigma}, {dt:?}: occupied fraction {f}"
            );
        }
    }
    // Two levels: the coarse level's cells are twice as wide, so σ = 0.06 is empty in
    // the fine level (σ·Δ = 0.0075) and occupied in the coarse one (0.015), up to the
    // dilation of the coarse level's occupied cells (same level only).
    let mut grid = grid_new([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 16, 2).unwrap();
    let field = |p: &Tensor| Ok((p.sum(1)?.zeros_like()? + 0.06)?);
    grid.update(0, 1, &dev, DType::F64, field).unwrap();
    assert!(!grid.is_occupied([0.0, 0.0, 0.0]));
    assert!(grid.is_occupied([1.5, 1.5, 1.5]));
}

#[test]
fn updates_run_every_n_steps_and_sample_a_subset_after_warm_up() {
    let aabb = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0];
    let cfg = GridConfig {
        warmup_steps: 2,
        ..GridConfig::default()
    };
    let mut grid = grid_with(aabb, 8, 2, cfg).unwrap();
    let dev = Device::Cpu;
    let points = std::cell::Cell::new(0usize);
    let f = |p: &Tensor| {
        points.set(points.get() + p.dims()[0]);
        Ok(p.sum(1)?.ones_like()?)
    };
    assert!(!grid.update(3, 2, &dev, DType::F64, f).unwrap());
    assert_eq!(points.get(), 0);
    assert!(grid.update(0, 2, &dev, DType::F64, f).unwrap());
    assert_eq!(points.get(), 2 * 512, "warm-up evaluates every cell");
    points.set(0);
    assert!(grid.update(4, 2, &dev, DType::F64, f).unwrap());
    assert_eq!(
        points.get(),
        2 * (128 + 128),
        "after warm-up: a quarter uniform + a quarter occupied per level"
    );
    assert_eq!(
        arg_of(grid.update(0, 0, &dev, DType::F64, f).unwrap_err()),
        "every_n"
    );
    let bad_shape = |p: &Tensor| Ok(p.clone());
    assert_eq!(
        arg_of(grid.update(0, 1, &dev, DType::F64, bad_shape).unwrap_err()),
        "sigma_fn"
    );
    let nan = |p: &Tensor| Ok((p.sum(1)? * f64::NAN)?);
    assert_eq!(
        arg_of(grid.update(0, 1, &dev, DType::F64, nan).unwrap_err()),
        "sigma_fn"
    );
}

#[test]
fn marched_intervals_are_sorted_contiguous_and_inside_the_box() {
    let aabb = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0];
    let grid = grid_new(aabb, 8, 1).unwrap();
    let dev = Device::Cpu;
    // Along +x through the centre from x = −3: box entry t = 2, exit t = 4.
    let o = Tensor::new(
        &[[-3.0f64, 0.0, 0.0], [-3.0, 5.0, 0.0], [0.0, 0.0, 0.0]],
        &dev,
    )
    .unwrap();
    let d = Tensor::new(
        &[[1.0f64, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0]],
        &dev,
    )
    .unwrap();
    let rays = Rays::new(o.clone(), d.clone()).unwrap();
    let s = grid
        .sample(
            &rays,
            &GridMarchConfig {
                near: 0.0,
                far: 100.0,
                step_size: 0.1,
                ..GridMarchConfig::default()
            },
            None,
        )
        .unwrap();
    let off: Vec<usize> = packed(&s)
        .offsets
        .to_vec1::<u32>()
        .unwrap()
        .into_iter()
        .map(|o| o as usize)
        .collect();
    assert_eq!(off[1] - off[0], 20, "2 units / 0.1");
    assert_eq!(
        off[2] - off[1],
        0,
        "a ray that misses the box has no samples"
    );
    // From the centre along +z with |d| = 2: t in [0, 0.5], 5 steps of 0.1.
    assert_eq!(off[3] - off[2], 5);
    let st = s.intervals.starts.to_vec1::<f64>().unwrap();
    let en = s.intervals.ends.to_vec1::<f64>().unwrap();
    assert!((st[0] - 2.0).abs() < 1e-12 && (en[19] - 4.0).abs() < 1e-12);
    for i in 0..st.len() {
        assert!(st[i] < en[i]);
        if i + 1 < st.len() && i + 1 != off[1] && i + 1 != off[2] {
            assert!((en[i] - st[i + 1]).abs() < 1e-15);
        }
    }
    let deltas = s
        .intervals
        .deltas(Some(&rays))
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    assert!((deltas[20] - 0.2).abs() < 1e-12, "δ scaled by |d| = 2");
    // Cone stepping: steps grow with t, so fewer samples.
    let c = grid
        .sample(
            &rays,
            &GridMarchConfig {
                cone_angle: 0.02,
                near: 0.0,
                far: 100.0,
                step_size: 0.01,
                ..GridMarchConfig::default()
            },
            None,
        )
        .unwrap();
    let f = grid
        .sample(
            &rays,
            &GridMarchConfig {
                near: 0.0,
                far: 100.0,
                step_size: 0.01,
                ..GridMarchConfig::default()
            },
            None,
        )
        .unwrap();
    assert!(
        c.n_marched < f.n_marched,
        "{} vs {}",
        c.n_marched,
        f.n_marched
    );
    // f32 rays give f32 intervals.
    let rays32 = Rays::new(
        o.to_dtype(DType::F32).unwrap(),
        d.to_dtype(DType::F32).unwrap(),
    )
    .unwrap();
    let s32 = grid
        .sample(
            &rays32,
            &GridMarchConfig {
                near: 0.0,
                far: 100.0,
                step_size: 0.1,
                ..GridMarchConfig::default()
            },
            None,
        )
        .unwrap();
    assert_eq!(s32.intervals.starts.dtype(), DType::F32);
    assert_eq!(packed(&s32).ray_indices.dims()[0], n_samples(&s32));
}

#[test]
fn grid_bad_input_errs_naming_the_argument() {
    assert_eq!(
        arg_of(grid_new([0.0, 0.0, 0.0, 1.0, -1.0, 1.0], 8, 1).unwrap_err()),
        "config.aabb"
    );
    assert_eq!(
        arg_of(grid_new([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 0, 1).unwrap_err()),
        "config.resolution"
    );
    assert_eq!(
        arg_of(grid_new([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 8, 0).unwrap_err()),
        "config.levels"
    );
    assert_eq!(
        arg_of(grid_new([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 4096, 4).unwrap_err()),
        "config.resolution"
    );
    let grid = grid_new([0.0, 0.0, 0.0, 1.0, 1.0, 1.0], 8, 1).unwrap();
    let dev = Device::Cpu;
    let o = Tensor::zeros((2, 3), DType::F32, &dev).unwrap();
    let d = Tensor::ones((2, 3), DType::F32, &dev).unwrap();
    let rays = Rays::new(o.clone(), d.clone()).unwrap();
    assert!(grid
        .sample(
            &rays,
            &GridMarchConfig {
                near: 0.0,
                far: 1.0,
                step_size: 0.1,
                ..GridMarchConfig::default()
            },
            None
        )
        .is_ok());
    assert_eq!(
        arg_of(
            grid.sample(
                &rays,
                &GridMarchConfig {
                    near: 2.0,
                    far: 1.0,
                    step_size: 0.1,
                    ..GridMarchConfig::default()
                },
                None
            )
            .unwrap_err()
        ),
        "far"
    );
    assert_eq!(
        arg_of(
            grid.sample(
                &rays,
                &GridMarchConfig {
                    near: -1.0,
                    far: 1.0,
                    step_size: 0.1,
                    ..GridMarchConfig::default()
                },
                None
            )
            .unwrap_err()
        ),
        "near"
    );
    assert_eq!(
        arg_of(
            grid.sample(
                &rays,
                &GridMarchConfig {
                    near: 0.0,
                    far: 1.0,
                    step_size: 0.0,
                    ..GridMarchConfig::default()
                },
                None
            )
            .unwrap_err()
        ),
        "step_size"
    );
    assert_eq!(
        arg_of(
            grid.sample(
                &rays,
                &GridMarchConfig {
                    cone_angle: -1.0,
                    near: 0.0,
                    far: 1.0,
                    step_size: 0.1,
                    ..GridMarchConfig::default()
                },
                None
            )
            .unwrap_err()
        ),
        "cone_angle"
    );
    assert_eq!(
        arg_of(
            grid.sample(
                &rays,
                &GridMarchConfig {
                    near: 0.0,
                    far: 1.0,
                    step_size: 1e-9,
                    ..GridMarchConfig::default()
                },
                None
            )
            .unwrap_err()
        ),
        "step_size"
    );
    // Zero, mismatched and mistyped directions and bad origins are rejected where the
    // rays are built (`Rays::new`), before any march.
    let zero = Tensor::zeros((2, 3), DType::F32, &dev).unwrap();
    assert_eq!(
        arg_of(Rays::new(o.clone(), zero).unwrap_err()),
        "directions"
    );
    let d3 = Tensor::ones((3, 3), DType::F32, &dev).unwrap();
    assert_eq!(arg_of(Rays::new(o.clone(), d3).unwrap_err()), "directions");
    let d64 = Tensor::ones((2, 3), DType::F64, &dev).unwrap();
    assert_eq!(arg_of(Rays::new(o.clone(), d64).unwrap_err()), "directions");
    let o2 = Tensor::zeros((2, 2), DType::F32, &dev).unwrap();
    assert_eq!(arg_of(Rays::new(o2, d).unwrap_err()), "origins");
}

/// A field with many occupied and empty regions at every level.
fn blobs(p: &Tensor) -> Result<Tensor> {
    let x = p.narrow(1, 0, 1)?.squeeze(1)?;
    let y = p.narrow(1, 1, 1)?.squeeze(1)?;
    let z = p.narrow(1, 2, 1)?.squeeze(1)?;
    let v = ((x * 3.1)?.sin()? * (y * 2.3)?.sin()?)?.mul(&(z * 1.7)?.sin()?)?;
    Ok(v.affine(1.0, -0.3)?.relu()?)
}

#[test]
fn jumping_over_empty_cells_gives_exactly_the_step_by_step_march() {
    let dev = Device::Cpu;
    let aabb = [-1.0, -0.5, -1.0, 1.0, 1.5, 0.5];
    let cfg = GridConfig {
        dilate: false,
        ..GridConfig::default()
    };
    let mut grid = grid_with(aabb, 16, 3, cfg).unwrap();
    for step in 0..4 {
        grid.update(step, 1, &dev, DType::F64, blobs).unwrap();
    }
    let occ = occupied_fraction(&grid);
    assert!(occ > 0.05 && occ < 0.95, "occupied fraction {occ}");
    let full_grid = grid_new(aabb, 16, 3).unwrap();
    // Random rays from outside and inside, plus rays along cell faces and level boundaries.
    let mut rng = neural_fields::rng::SplitMix64::new(9);
    let mut o = Vec::new();
    let mut d = Vec::new();
    for i in 0..600 {
        let mut u = || 2.0 * rng.uniform() - 1.0;
        if i < 400 {
            o.extend([4.0 * u(), 4.0 * u() + 0.5, 4.0 * u() - 0.25]);
            d.extend([u(), u(), u()]);
        } else if i < 500 {
            // Along x at y, z exactly on level-0 and level-1 cell faces.
            let k = (i - 400) as f64;
            o.extend([-5.0, -0.5 + 0.125 * (k % 17.0), -1.0 + 0.25 * (k % 9.0)]);
            d.extend([1.0, 0.0, 0.0]);
        } else {
            // Nearly parallel to a face, slowly crossing it.
            let k = (i - 500) as f64;
            o.extend([-5.0, 0.5 + 1e-3 * k, -0.25]);
            d.extend([1.0, 1e-12 * (k - 50.0), 1e-9]);
        }
    }
    let n = o.len() / 3;
    let o = Tensor::from_vec(o, (n, 3), &dev).unwrap();
    let d = Tensor::from_vec(d, (n, 3), &dev).unwrap();
    let rays = Rays::new(o.clone(), d.clone()).unwrap();
    for (h, jitter) in [0.01f64, 0.0137, 0.05]
        .into_iter()
        .flat_map(|h| [(h, None), (h, Some(h.to_bits()))])
    {
        let opts = GridMarchConfig {
            jitter,
            near: 0.0,
            far: f64::INFINITY,
            step_size: h,
            ..GridMarchConfig::default()
        };
        let full = full_grid.sample(&rays, &opts, None).unwrap();
        let skip = grid.sample(&rays, &opts, None).unwrap();
        assert_eq!(full.n_marched, skip.n_marched);
        // The step-by-step answer: every interval of the full march whose midpoint's
        // cell is occupied.
        let fs = full.intervals.starts.to_vec1::<f64>().unwrap();
        let fe = full.intervals.ends.to_vec1::<f64>().unwrap();
        let fr = packed(&full).ray_indices.to_vec1::<u32>().unwrap();
        let oh = o.to_vec2::<f64>().unwrap();
        let dh = d.to_vec2::<f64>().unwrap();
        let mut want = Vec::new();
        for i in 0..fs.len() {
            let r = fr[i] as usize;
            let m = 0.5 * (fs[i] + fe[i]);
            let p = [
                oh[r][0] + m * dh[r][0],
                oh[r][1] + m * dh[r][1],
                oh[r][2] + m * dh[r][2],
            ];
            if grid.is_occupied(p) {
                want.push((r as u32, fs[i], fe[i]));
            }
        }
        let ss = skip.intervals.starts.to_vec1::<f64>().unwrap();
        let se = skip.intervals.ends.to_vec1::<f64>().unwrap();
        let sr = packed(&skip).ray_indices.to_vec1::<u32>().unwrap();
        let got: Vec<(u32, f64, f64)> = (0..ss.len()).map(|i| (sr[i], ss[i], se[i])).collect();
        println!(
            "step {h}, jitter {jitter:?}: {} intervals marched, {} kept (occupied {:.1}% of cells)",
            full.n_marched,
            got.len(),
            100.0 * occ
        );
        assert_eq!(got.len(), want.len(), "step {h}");
        assert!(
            got == want,
            "step {h}: jumped march differs from the step-by-step one"
        );
    }
}

/// Per-ray (start, end) lists of packed grid samples.
fn per_ray(s: &GridSamples, rays: usize) -> Vec<Vec<(f64, f64)>> {
    let st = s.intervals.starts.to_vec1::<f64>().unwrap();
    let en = s.intervals.ends.to_vec1::<f64>().unwrap();
    let ri = packed(s).ray_indices.to_vec1::<u32>().unwrap();
    let mut out = vec![Vec::new(); rays];
    for i in 0..st.len() {
        out[ri[i] as usize].push((st[i], en[i]));
    }
    out
}

#[test]
fn a_jittered_march_tiles_the_same_range_with_a_shifted_lattice() {
    let full = grid_new([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 8, 1).unwrap();
    let rays = rays(6, DType::F64);
    let h = 0.05;
    let plain = per_ray(
        &full
            .sample(
                &rays,
                &GridMarchConfig {
                    near: 0.0,
                    far: 100.0,
                    step_size: h,
                    ..GridMarchConfig::default()
                },
                None,
            )
            .unwrap(),
        36,
    );
    let jittered: Vec<_> = [1u64, 2]
        .iter()
        .map(|&seed| {
            let opts = GridMarchConfig {
                near: 0.0,
                far: 100.0,
                step_size: h,
                jitter: Some(seed),
                ..GridMarchConfig::default()
            };
            per_ray(&full.sample(&rays, &opts, None).unwrap(), 36)
        })
        .collect();
    let mut first_lengths = Vec::new();
    for (r, p) in plain.iter().enumerate() {
        let (entry, exit) = (p[0].0, p[p.len() - 1].1);
        for j in &jittered {
            let j = &j[r];
            // The same range, tiled without gaps or overlaps.
            assert_eq!(j[0].0, entry, "ray {r}");
            assert_eq!(j[j.len() - 1].1, exit, "ray {r}");
            assert!(j.windows(2).all(|w| w[0].1 == w[1].0 && w[0].0 < w[0].1));
            // A partial first step, then whole steps (but the last).
            let first = j[0].1 - j[0].0;
            assert!(
                first > 0.0 && first <= h * (1.0 + 1e-12),
                "ray {r}: {first}"
            );
            for w in &j[1..j.len() - 1] {
                assert!((w.1 - w.0 - h).abs() < 1e-12, "ray {r}: {w:?}");
            }
            first_lengths.push(first / h);
        }
    }
    // Two seeds shift differently, and the shifts spread over (0, 1].
    assert_ne!(jittered[0], jittered[1]);
    let (lo, hi) = first_lengths
        .iter()
        .fold((1.0f64, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
    assert!(lo < 0.2 && hi > 0.8, "shifts in [{lo}, {hi}]");
    // The same seed gives the same march.
    let again = per_ray(
        &full
            .sample(
                &rays,
                &GridMarchConfig {
                    near: 0.0,
                    far: 100.0,
                    step_size: h,
                    jitter: Some(1),
                    ..GridMarchConfig::default()
                },
                None,
            )
            .unwrap(),
        36,
    );
    assert_eq!(again, jittered[0]);
}

/// A field with structure at every scale along the rays: a dense ball, a thin shell and
/// a faint haze, so that both thresholds bite somewhere.
fn layered(p: &Tensor) -> Result<Tensor> {
    let r2 = p.sqr()?.sum(1)?;
    let ball = (r2.affine(-1.0 / 0.09, 1.0)?.relu()?.sqr()? * 60.0)?;
    let shell = ((r2.affine(1.0, -0.36)?.abs()? * -200.0)?.exp()? * 3.0)?;
    let haze = (p.narrow(1, 0, 1)?.squeeze(1)?.affine(0.5, 0.5)?.relu()? * 0.05)?;
    Ok(((ball + shell)? + haze)?)
}

/// The march's intervals as host `(start, end)` pairs, per ray.
fn pairs(s: &GridSamples) -> Vec<Vec<(f64, f64)>> {
    let off = packed(s).offsets.to_vec1::<u32>().unwrap();
    let st = s
        .intervals
        .starts
        .to_dtype(DType::F64)
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    let en = s
        .intervals
        .ends
        .to_dtype(DType::F64)
        .unwrap()
        .to_vec1::<f64>()
        .unwrap();
    off.windows(2)
        .map(|w| {
            (w[0] as usize..w[1] as usize)
                .map(|i| (st[i], en[i]))
                .collect()
        })
        .collect()
}

/// With a density function, the grid's sampling keeps exactly the samples whose
/// transmittance (before them, over every occupied sample of the ray) is at least
/// `early_stop_eps` and whose opacity is at least `alpha_threshold`, as a brute-force
/// composite of all the samples gives them; the kept intervals are those of the plain
/// march, bit for bit; both thresholds at 0 keep everything.
#[test]
fn a_density_function_drops_exactly_the_hidden_and_the_empty_samples() {
    let dev = Device::Cpu;
    for dt in [DType::F64, DType::F32] {
        let rays = rays(12, dt);
        let mut grid = grid_new([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 32, 1).unwrap();
        grid.update(0, 1, &dev, dt, layered).unwrap();
        let march = GridMarchConfig {
            step_size: 0.02,
            ..GridMarchConfig::default()
        };
        let all = grid.sample(&rays, &march, None).unwrap();
        let sigma = layered(&all.intervals.positions(&rays).unwrap()).unwrap();
        let w = neural_fields::volume::render_weights(
            &sigma,
            &all.intervals,
            Some(&rays),
            &CompositeConfig::default(),
        )
        .unwrap();
        let host = |t: &Tensor| t.to_dtype(DType::F64).unwrap().to_vec1::<f64>().unwrap();
        let (trans, alpha) = (host(&w.transmittance), host(&w.alphas));
        let all_pairs: Vec<(f64, f64)> = pairs(&all).concat();
        let ray_of = packed(&all).ray_indices.to_vec1::<u32>().unwrap();
        let mut dropped_by = [0usize; 2];
        for (eps, thr) in [
            (1e-4, 0.0),
            (0.0, 1e-2),
            (1e-2, 5e-2),
            (0.0, 0.0),
            (1.0, 0.0),
        ] {
            let config = GridMarchConfig {
                early_stop_eps: eps,
                alpha_threshold: thr,
                ..march
            };
            let mut calls = 0;
            let mut f = |p: &Tensor| {
                calls += 1;
                layered(p)
            };
            let kept = grid.sample(&rays, &config, Some(&mut f)).unwrap();
            assert_eq!(calls, usize::from(eps > 0.0 || thr > 0.0));
            assert_eq!(kept.n_marched, all.n_marched);
            assert!(!kept.intervals.starts.track_op());
            // In f32, T and α of the brute force are rounded to f32: leave out the
            // samples within rounding of a threshold.
            let tol = if dt == DType::F32 { 1e-5 } else { 1e-12 };
            let mut want: Vec<Vec<(f64, f64)>> = vec![Vec::new(); rays.len()];
            let mut unsure = Vec::new();
            for (i, &(a, b)) in all_pairs.iter().enumerate() {
                let near = (trans[i] - eps).abs() <= tol * eps.max(1e-30)
                    || (alpha[i] - thr).abs() <= tol * thr.max(1e-30);
                if near {
                    unsure.push((a, b));
                }
                let hidden = trans[i] < eps;
                let empty = alpha[i] < thr;
                dropped_by[0] += usize::from(hidden);
                dropped_by[1] += usize::from(empty && !hidden);
                if !hidden && !empty {
                    want[ray_of[i] as usize].push((a, b));
                }
            }
            let got = pairs(&kept);
            for (ray, (g, w)) in got.iter().zip(&want).enumerate() {
                if unsure.is_empty() {
                    assert_eq!(g, w, "{dt:?}, eps {eps}, α {thr}, ray {ray}");
                } else {
                    let strip = |v: &Vec<(f64, f64)>| -> Vec<(f64, f64)> {
                        v.iter().filter(|x| !unsure.contains(x)).copied().collect()
                    };
                    assert_eq!(strip(g), strip(w), "{dt:?}, eps {eps}, α {thr}, ray {ray}");
                }
            }
            if eps == 0.0 && thr == 0.0 {
                assert_eq!(got, pairs(&all));
            }
        }
        assert!(
            dropped_by[0] > 0 && dropped_by[1] > 0,
            "both thresholds must drop samples in this scene: {dropped_by:?}"
        );
    }
}

/// The kept samples render with the gradients the same samples get from the full march
/// masked by hand: the sampling touches no graph (a density function over learnable
/// weights, not detached, leaves no trace in the gradients).
#[test]
fn gradients_through_the_kept_samples_are_those_of_the_masked_full_march() {
    let dev = Device::Cpu;
    let rays = rays(10, DType::F64);
    let mut grid = grid_new([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 32, 1).unwrap();
    grid.update(0, 1, &dev, DType::F64, layered).unwrap();
    let scale = candle_core::Var::new(&[1.5f64], &dev).unwrap();
    let tint = candle_core::Var::new(&[[0.2f64, 0.5, 0.9]], &dev).unwrap();
    let field = |p: &Tensor| -> Result<(Tensor, Tensor)> {
        let sigma = layered(p)?.broadcast_mul(scale.as_tensor())?;
        let rgb = ball_color(p)?.broadcast_mul(tint.as_tensor())?;
        Ok((sigma, rgb))
    };
    let march = GridMarchConfig {
        step_size: 0.02,
        early_stop_eps: 1e-3,
        alpha_threshold: 1e-2,
        ..GridMarchConfig::default()
    };
    let mut density = |p: &Tensor| Ok(field(p)?.0);
    let kept = grid.sample(&rays, &march, Some(&mut density)).unwrap();
    // By hand: the full march, the density, the same rule, `Intervals::retain`.
    let all = grid.sample(&rays, &march, None).unwrap().intervals;
    let sigma = field(&all.positions(&rays).unwrap()).unwrap().0.detach();
    let w = neural_fields::volume::render_weights(
        &sigma,
        &all,
        Some(&rays),
        &CompositeConfig::default(),
    )
    .unwrap();
    let mask = (w.transmittance.ge(1e-3).unwrap() * w.alphas.ge(1e-2).unwrap()).unwrap();
    let (by_hand, _) = all.retain(&mask).unwrap();
    assert_eq!(
        by_hand.starts.to_vec1::<f64>().unwrap(),
        kept.intervals.starts.to_vec1::<f64>().unwrap()
    );
    let loss = |iv: &neural_fields::volume::Intervals| {
        let (sigma, rgb) = field(&iv.positions(&rays).unwrap()).unwrap();
        let out = composite(&sigma, &rgb, iv, Some(&rays), &CompositeConfig::default()).unwrap();
        let grads = out
            .color
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        [&scale, &tint].map(|v| {
            grads
                .get(v.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f64>()
                .unwrap()
        })
    };
    let (a, b) = (loss(&kept.intervals), loss(&by_hand));
    assert_eq!(a, b);
    assert!(a[0][0].abs() > 0.0 && a[1].iter().all(|g| g.abs() > 0.0));
}

/// Extreme densities: a NaN or infinite density is refused naming `sigma_fn`; a huge
/// finite one is an opaque wall (nothing behind its first sample, no NaN); negative ones
/// count as 0 (nothing hidden); a wrong shape or dtype is refused.
#[test]
fn extreme_densities_are_refused_or_handled_without_nan() {
    let grid = grid_new([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 8, 1).unwrap();
    for dt in [DType::F32, DType::F64] {
        let rays = rays(4, dt);
        let march = GridMarchConfig {
            step_size: 0.05,
            alpha_threshold: 1e-3,
            ..GridMarchConfig::default()
        };
        let all = pairs(&grid.sample(&rays, &march, None).unwrap());
        let huge = if dt == DType::F32 { 3e38 } else { 1e300 };
        for bad in [f64::NAN, f64::INFINITY] {
            let mut f = |p: &Tensor| {
                Ok(p.narrow(1, 0, 1)?
                    .squeeze(1)?
                    .ones_like()?
                    .affine(0.0, bad)?)
            };
            let e = grid.sample(&rays, &march, Some(&mut f)).unwrap_err();
            assert_eq!(arg_of(e), "sigma_fn", "{bad}");
        }
        // A wall of density `huge` for z > 0: each ray keeps its samples up to and
        // including the first one in the wall.
        let mut wall = |p: &Tensor| {
            let z = p.narrow(1, 2, 1)?.squeeze(1)?;
            Ok((z.gt(0.0)?.to_dtype(dt)? * huge)?)
        };
        let kept = grid.sample(&rays, &march, Some(&mut wall)).unwrap();
        let got = pairs(&kept);
        for (ray, (g, a)) in got.iter().zip(&all).enumerate() {
            let z_of = |(s, e): (f64, f64)| -3.0 + 0.5 * (s + e);
            // Samples before the wall are empty (α = 0 < threshold) and dropped too; a ray
            // that leaves the box before the wall keeps nothing.
            let want: Vec<(f64, f64)> = a
                .iter()
                .copied()
                .filter(|&x| z_of(x) > 0.0)
                .take(1)
                .collect();
            assert_eq!(g, &want, "{dt:?} ray {ray}");
        }
        // Negative densities count as 0: with no opacity threshold nothing is dropped.
        let mut negative = |p: &Tensor| {
            Ok(p.narrow(1, 0, 1)?
                .squeeze(1)?
                .ones_like()?
                .affine(0.0, -5.0)?)
        };
        let no_alpha = GridMarchConfig {
            alpha_threshold: 0.0,
            ..march
        };
        let kept = grid.sample(&rays, &no_alpha, Some(&mut negative)).unwrap();
        assert_eq!(pairs(&kept), all);
        // Shape and dtype.
        let mut flat = |p: &Tensor| Ok(p.clone());
        let e = grid.sample(&rays, &march, Some(&mut flat)).unwrap_err();
        assert_eq!(arg_of(e), "sigma_fn");
        let other = if dt == DType::F32 {
            DType::F64
        } else {
            DType::F32
        };
        let mut wrong_dtype = |p: &Tensor| Ok(layered(p)?.to_dtype(other)?);
        let e = grid
            .sample(&rays, &march, Some(&mut wrong_dtype))
            .unwrap_err();
        assert_eq!(arg_of(e), "sigma_fn");
        // Thresholds outside [0, 1].
        for (eps, thr, name) in [
            (-1e-4, 0.0, "early_stop_eps"),
            (f64::NAN, 0.0, "early_stop_eps"),
            (1e-4, 1.5, "alpha_threshold"),
        ] {
            let config = GridMarchConfig {
                early_stop_eps: eps,
                alpha_threshold: thr,
                ..march
            };
            let e = grid.sample(&rays, &config, Some(&mut wall)).unwrap_err();
            assert_eq!(arg_of(e), name);
        }
    }
}

/// No rays, or rays that miss the grid: empty packed samples, and the density function
/// is never called.
#[test]
fn empty_batches_give_empty_samples_without_calling_the_density() {
    let dev = Device::Cpu;
    let grid = grid_new([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], 8, 1).unwrap();
    let march = GridMarchConfig {
        step_size: 0.05,
        alpha_threshold: 1e-2,
        ..GridMarchConfig::default()
    };
    let none = Rays::new(
        Tensor::zeros((0, 3), DType::F32, &dev).unwrap(),
        Tensor::zeros((0, 3), DType::F32, &dev).unwrap(),
    )
    .unwrap();
    let away = Rays::new(
        Tensor::new(&[[0.0f32, 0.0, 5.0], [3.0, 3.0, 3.0]], &dev).unwrap(),
        Tensor::new(&[[0.0f32, 0.0, 1.0], [1.0, 0.0, 0.0]], &dev).unwrap(),
    )
    .unwrap();
    for (rays, r) in [(none, 0), (away, 2)] {
        let mut called = false;
        let mut f = |p: &Tensor| {
            called = true;
            layered(p)
        };
        let s = grid.sample(&rays, &march, Some(&mut f)).unwrap();
        assert!(!called);
        assert_eq!(n_samples(&s), 0);
        assert_eq!(packed(&s).n_rays, r);
        assert_eq!(
            packed(&s).offsets.to_vec1::<u32>().unwrap(),
            vec![0u32; r + 1]
        );
    }
}

/// The dilation grows each occupied cell to the 3 × 3 × 3 block around it within its
/// level, cut at the level's faces: exactly, for a cell inside, on a corner and at the
/// second level.
#[test]
fn dilation_grows_each_occupied_cell_to_its_cube_of_neighbours() -> Result<()> {
    let res = 8usize;
    // One dense cell per case: (level, i, j, k).
    for (level, ijk) in [(0usize, [3usize, 4, 5]), (0, [0, 0, 7]), (1, [7, 0, 3])] {
        let mut grid = OccupancyGrid::new(GridConfig {
            aabb: [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0],
            resolution: res,
            // A dense level-0 cell lies inside a level-1 cell, which one jittered point
            // per cell could find dense too: one level there.
            levels: level + 1,
            warmup_steps: 1,
            ..GridConfig::default()
        })?;
        // Level l spans ±2^l; its cells have edge 2·2^l / res.
        let scale = (1usize << level) as f64;
        let edge = 2.0 * scale / res as f64;
        let lo: Vec<f64> = ijk.iter().map(|&i| -scale + i as f64 * edge).collect();
        let hi: Vec<f64> = lo.iter().map(|&l| l + edge).collect();
        let dense = |p: &Tensor| -> Result<Tensor> {
            let lo_t = Tensor::new(lo.as_slice(), p.device())?.to_dtype(p.dtype())?;
            let hi_t = Tensor::new(hi.as_slice(), p.device())?.to_dtype(p.dtype())?;
            let inside = p
                .broadcast_gt(&lo_t)?
                .mul(&p.broadcast_lt(&hi_t)?)?
                .min(1)?
                .to_dtype(p.dtype())?;
            Ok((inside * 1e4)?)
        };
        grid.update(0, 1, &Device::Cpu, DType::F32, dense)?;
        let occupied = grid.occupied();
        for l in 0..=level {
            for i in 0..res {
                for j in 0..res {
                    for k in 0..res {
                        let near = l == level
                            && [i, j, k]
                                .iter()
                                .zip(&ijk)
                                .all(|(&a, &b)| a.abs_diff(b) <= 1);
                        let cell = ((l * res + i) * res + j) * res + k;
                        assert_eq!(
                            occupied[cell], near,
                            "dense cell {level} {ijk:?}: cell {l} {i} {j} {k}"
                        );
                    }
                }
            }
        }
    }
    Ok(())
}
