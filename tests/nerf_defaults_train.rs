//! A user's own NeRF loop at the library's defaults, on the committed scene: the two ways
//! it failed before the defaults were chosen across the scene suite.
//!
//! - The occupancy grid at `GridConfig::default()` never pruned (its threshold was
//!   compared with the density rather than with an opacity, and its decay and warm-up
//!   kept every cell for thousands of steps): every cell stayed occupied.
//! - At a learning rate of 5e-3 on a loose box (±1.5 around an object of radius 1), the
//!   model's initial density (σ ≈ e⁻¹) drove Adam to push σ to ~1e-4 everywhere within
//!   20 steps, from where it never came back: an empty scene.
#![cfg(all(feature = "volume", feature = "data"))]

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use neural_fields::data::{load, Dataset, LoadConfig, RaySampler};
use neural_fields::nn::{adam, build_seeded, Adam};
use neural_fields::volume::{
    nerf, CompositeConfig, GridConfig, GridMarchConfig, Nerf, NerfConfig, OccupancyGrid,
};

/// The committed scene, a `Nerf` at its defaults and Adam at 5e-3 (the plain PyTorch
/// NeRF's learning rate), f32 on the CPU.
fn setup() -> (Dataset, Nerf, Adam) {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/data/wuson");
    let train = load(&root, &LoadConfig::default()).unwrap();
    let varmap = VarMap::new();
    let config = NerfConfig::default();
    let net = build_seeded(&varmap, DType::F32, &Device::Cpu, 0, |vb| nerf(&config, vb)).unwrap();
    let opt = adam(&varmap, 5e-3).unwrap();
    (train, net, opt)
}

/// One step of the tour's loop on 256 rays: the grid's march (culled by the field's
/// density when `cull`), the fused loss, Adam. Returns the largest opacity of a ray.
fn train_step(
    (net, opt): (&Nerf, &mut Adam),
    (grid, march, cull): (&OccupancyGrid, &mut GridMarchConfig, bool),
    rays: &mut RaySampler,
    step: usize,
) -> f64 {
    let batch = rays.pixels(256).unwrap();
    march.jitter = Some(step as u64);
    let mut density = |p: &Tensor| net.density(p);
    let kept = grid
        .sample(&batch.rays, march, cull.then_some(&mut density as _))
        .unwrap();
    let config = CompositeConfig {
        background: Some(batch.backgrounds),
        ..CompositeConfig::default()
    };
    let out = net
        .color_loss(&batch.rays, &kept.intervals, &batch.colors, &config)
        .unwrap();
    let loss = out.loss.to_scalar::<f32>().unwrap();
    assert!(loss.is_finite(), "step {step}: loss {loss}");
    opt.backward_step(&out.loss).unwrap();
    out.opacity_max
}

fn occupied_fraction(grid: &OccupancyGrid) -> f64 {
    let occ = grid.occupied();
    occ.iter().filter(|&&o| o).count() as f64 / occ.len() as f64
}

/// `examples/nerf_tour.rs`'s loop (library defaults, the box from the visual hull, Adam at
/// 5e-3) on 256 rays per step: the grid falls below 30 % occupied within 1 000 steps.
#[test]
fn a_grid_at_its_defaults_prunes_within_a_thousand_steps() {
    let (dev, dt) = (Device::Cpu, DType::F32);
    let (train, net, mut opt) = setup();
    let cells = GridConfig {
        aabb: train
            .visual_hull(0.05)
            .unwrap()
            .expect("the views have alpha"),
        ..GridConfig::default()
    };
    let side = (0..3)
        .map(|a| cells.aabb[a + 3] - cells.aabb[a])
        .fold(0.0, f64::max);
    let mut grid = OccupancyGrid::new(cells).unwrap();
    let mut march = GridMarchConfig {
        step_size: side / 256.0,
        ..GridMarchConfig::default()
    };
    let mut rays = RaySampler::new(&train, 0, &dev, dt).unwrap();
    let mut pruned_at = None;
    for step in 0..1000 {
        let density = |p: &Tensor| net.density(p);
        if grid.update(step, 16, &dev, dt, density).unwrap() && occupied_fraction(&grid) < 0.3 {
            pruned_at = Some(step);
            break;
        }
        train_step((&net, &mut opt), (&grid, &mut march, true), &mut rays, step);
    }
    println!("grid below 30 % occupied at step {pruned_at:?}");
    assert!(
        pruned_at.is_some(),
        "after 1000 steps {:.3} of the grid is occupied",
        occupied_fraction(&grid)
    );
}

/// Every sample of the loose box ±1.5 (a one-cell grid), Adam at 5e-3: after 150 steps
/// the object's rays are opaque (the collapse left every ray below 1e-2).
#[test]
fn the_density_survives_a_high_learning_rate_on_a_loose_box() {
    let (train, net, mut opt) = setup();
    let grid = OccupancyGrid::new(GridConfig {
        aabb: [-1.5, -1.5, -1.5, 1.5, 1.5, 1.5],
        resolution: 1,
        ..GridConfig::default()
    })
    .unwrap();
    let mut march = GridMarchConfig {
        step_size: 3.0 / 64.0,
        ..GridMarchConfig::default()
    };
    let mut rays = RaySampler::new(&train, 0, &Device::Cpu, DType::F32).unwrap();
    let mut last = 0.0;
    for step in 0..150 {
        last = train_step(
            (&net, &mut opt),
            (&grid, &mut march, false),
            &mut rays,
            step,
        );
    }
    assert!(
        last > 0.5,
        "the largest opacity of a ray after 150 steps: {last}"
    );
}
