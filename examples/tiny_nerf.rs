//! A tiny NeRF: learn a radiance field from 16 views of an analytic scene, twice: with
//! stratified samples along every ray, and with the occupancy grid skipping empty space.
//!
//! ```text
//! cargo run --release --example tiny_nerf            # writes tiny_nerf.png
//! cargo run --release --example tiny_nerf -- out.png
//! ```
//!
//! The scene is a fuzzy ball (density σ(p) = 8·(1 − |p|²/r²)², r = 0.6) whose colour
//! varies in space, inside the unit sphere. Its 40 × 40 ground-truth views (cameras on a
//! sphere of radius 3, one view held out) are rendered with this crate's compositing at
//! 1024 samples per ray (error far below what training reaches). The model is the
//! NeRF recipe at small scale: a 4 × 64 ReLU MLP on a frequency encoding (L = 6) with
//! four outputs, density `trunc_exp(raw₀ − 1)` and colour `sigmoid(raw₁…₃)`; each step
//! renders 1024 random rays from 4 training views and minimises the mean squared colour
//! error with Adam.
//!
//! The two runs differ only in where the samples come from:
//! - **stratified**: 48 jittered samples per ray between the ray's entry and exit of the
//!   unit sphere ([`stratified`]), composited in the batched layout ([`composite`]);
//! - **grid**: an [`OccupancyGrid`] (32³ cells over [−1, 1]³) updated from the network's
//!   density every 16 steps; rays are marched with the same step length (2/48) and keep
//!   only intervals in occupied cells, composited in the packed layout (the same
//!   [`composite`]). After warm-up it evaluates a fraction of the samples.
//!
//! Prints the held-out PSNR against training time (held-out renders left out) for both,
//! and writes the held-out view as `reference | stratified | grid` to a PNG. About 85 s
//! on 2 cores (`docs/tiny_nerf.png` is its output).
//!
//! The example uses mimalloc as its global allocator. candle allocates fresh tensors for
//! every op of every step; with glibc's default malloc, blocks of this size go back to
//! the kernel when freed and fault back in on the next step, which made this example
//! about 3× slower (most of its time in the kernel). A training binary of your own should
//! do the same, or set `GLIBC_TUNABLES` as docs/benchmarks.md describes.

use candle_core::{DType, Device, Tensor};
use candle_nn::Optimizer;
use neural_fields::camera::{ray_sphere, Camera, Rays};
use neural_fields::data::{psnr, write_png};
use neural_fields::encoding::{FrequencyEncoding, PointEncoding};
use neural_fields::field::Field;
use neural_fields::glam::DVec3;
use neural_fields::nn::{Activation, Mlp, MlpConfig};
use neural_fields::rng::SplitMix64;
use neural_fields::volume::{
    composite, stratified, trunc_exp, Composite, CompositeConfig, GridConfig, GridMarchConfig,
    Jitter, OccupancyGrid,
};
use neural_fields::Result;
use std::time::Instant;

#[path = "common/cameras.rs"]
mod cameras;
mod common;

// candle allocates fresh tensors every step; see the module docs.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

const SIDE: usize = 40;
const VIEWS: usize = 17;
const HELD_OUT: usize = 0;
const RAYS_PER_VIEW: usize = 256;
const VIEWS_PER_STEP: usize = 4;
const SAMPLES: usize = 48;
const STEPS: usize = 300;
const EVAL_EVERY: usize = 50;
/// Grid updates every this many steps (grid run).
const GRID_EVERY: usize = 8;
const BALL_R: f64 = 0.6;
const BALL_D: f64 = 8.0;
/// The grid march's step in t: the unit sphere's diameter over `SAMPLES`, so that both
/// runs place samples equally densely.
const GRID_STEP: f64 = 2.0 / SAMPLES as f64;
/// Rays per chunk when rendering a whole view (bounds the memory of one forward pass).
const CHUNK: usize = 400;

/// The scene's density σ(p) = D·(1 − |p|²/r²)² inside the ball, 0 outside: `[N, 3]` →
/// `[N]`.
fn scene_sigma(p: &Tensor) -> Result<Tensor> {
    let u = p
        .sqr()?
        .sum(1)?
        .affine(-1.0 / (BALL_R * BALL_R), 1.0)?
        .relu()?;
    Ok((u.sqr()? * BALL_D)?)
}

/// The scene's colour c(p) = 0.5 + 0.45·sin(8p + φ) per channel, φ = (0, 2, 4):
/// `[N, 3]` → `[N, 3]`.
fn scene_rgb(p: &Tensor) -> Result<Tensor> {
    let phase = Tensor::new(&[0.0f64, 2.0, 4.0], p.device())?.to_dtype(p.dtype())?;
    Ok(((p * 8.0)?.broadcast_add(&phase)?.sin()? * 0.45)?.affine(1.0, 0.5)?)
}

/// The model's density `[N]` and colour `[N, 3]` at `points: [N, 3]`.
fn radiance(net: &Mlp, points: &Tensor) -> Result<(Tensor, Tensor)> {
    let raw = Field::forward(net, points)?;
    let sigma = trunc_exp(&raw.narrow(1, 0, 1)?.squeeze(1)?.affine(1.0, -1.0)?)?;
    let rgb = candle_nn::ops::sigmoid(&raw.narrow(1, 1, 3)?)?;
    Ok((sigma, rgb))
}

/// Renders `rays` with `n` samples per ray between the entry and exit of the unit sphere
/// (rays that miss it get the black background): stratified intervals (jittered with
/// `seed` when given), the density and colour of `field` at the midpoints, batched
/// compositing.
fn render_stratified(
    rays: &Rays,
    n: usize,
    seed: Option<u64>,
    field: impl Fn(&Tensor) -> Result<(Tensor, Tensor)>,
) -> Result<Composite> {
    let bounds = ray_sphere(rays, [0.0; 3], 1.0)?;
    let jitter = if seed.is_some() {
        Jitter::PerSample
    } else {
        Jitter::None
    };
    let iv = stratified(&bounds.near, &bounds.far, n, jitter, seed.unwrap_or(0))?;
    let r = rays.len();
    // Sample positions o + t·d at the midpoints: [R, n, 3] → [R·n, 3].
    let pos = iv.positions(rays)?.reshape((r * n, 3))?;
    let (sigma, rgb) = field(&pos)?;
    composite(
        &sigma.reshape((r, n))?,
        &rgb.reshape((r, n, 3))?,
        &iv,
        Some(rays),
        &CompositeConfig::default(),
    )
}

/// Renders `rays` through `grid`: a fixed-step march (2/48 in t) that keeps intervals in
/// occupied cells, the network at their midpoints, packed compositing. Also returns the
/// number of samples evaluated.
fn render_grid(rays: &Rays, grid: &OccupancyGrid, net: &Mlp) -> Result<(Composite, usize)> {
    let march = GridMarchConfig::new(0.0, f64::INFINITY, GRID_STEP);
    let iv = grid.sample(rays, &march)?.intervals;
    let m = iv.starts.dims1()?;
    let (sigma, rgb) = radiance(net, &iv.positions(rays)?)?;
    let out = composite(&sigma, &rgb, &iv, Some(rays), &CompositeConfig::default())?;
    Ok((out, m))
}

/// How samples are placed in a training run.
#[derive(Clone, Copy, PartialEq)]
enum Mode {
    Stratified,
    Grid,
}

/// Renders the whole of `rays` in chunks; colour `[N, 3]` and samples evaluated.
fn render_view(
    rays: &Rays,
    mode: Mode,
    net: &Mlp,
    grid: &OccupancyGrid,
) -> Result<(Tensor, usize)> {
    let mut colours = Vec::new();
    let mut evaluated = 0;
    for start in (0..rays.len()).step_by(CHUNK) {
        let chunk = rays.narrow(start, CHUNK.min(rays.len() - start))?;
        let (out, m) = match mode {
            Mode::Stratified => {
                let out = render_stratified(&chunk, SAMPLES, None, |p| radiance(net, p))?;
                (out, chunk.len() * SAMPLES)
            }
            Mode::Grid => render_grid(&chunk, grid, net)?,
        };
        colours.push(out.color.detach());
        evaluated += m;
    }
    Ok((Tensor::cat(&colours, 0)?, evaluated))
}

/// One training run; returns the held-out rendering.
fn train(
    mode: Mode,
    cameras: &[Camera],
    images: &[Tensor],
    device: &Device,
    dtype: DType,
) -> Result<Tensor> {
    let config = MlpConfig {
        out_dim: 4,
        hidden: 64,
        depth: 4,
        activation: Activation::Relu,
        encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 6)?),
        ..MlpConfig::default()
    };
    let (net, mut opt) = common::seeded_mlp(&config, 0, 5e-3, device, dtype)?;
    // nerfacc's decay (0.95 per update) suits its 20 000-step schedules: a cell that saw
    // the initial density (≈ e⁻¹) needs ~70 updates to fall below the threshold. This
    // run is 50× shorter, so the grid forgets faster and updates more often.
    let mut grid = OccupancyGrid::new(GridConfig {
        aabb: [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0],
        resolution: 32,
        levels: 1,
        decay: 0.6,
        ..GridConfig::default()
    })?;
    let held_out = cameras[HELD_OUT].rays(device, dtype)?;
    let mut rng = SplitMix64::new(7);
    let name = match mode {
        Mode::Stratified => "stratified",
        Mode::Grid => "grid",
    };
    let start = Instant::now();
    // Wall time spent rendering the held-out view, left out of the training time.
    let mut eval_secs = 0.0;
    let mut evaluated_total = 0usize;
    for step in 0..=STEPS {
        if mode == Mode::Grid {
            // The grid sees the network's density, detached (no graph is built).
            grid.update(step, GRID_EVERY, device, dtype, |p: &Tensor| {
                Ok(radiance(&net, p)?.0.detach())
            })?;
        }
        // A batch: RAYS_PER_VIEW random pixels of each of VIEWS_PER_STEP training views.
        let (mut os, mut ds, mut targets) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..VIEWS_PER_STEP {
            let v = 1 + rng.below((VIEWS - 1) as u64) as usize;
            let (rays, idx) =
                cameras[v].random_rays(RAYS_PER_VIEW, rng.next_u64(), device, dtype)?;
            os.push(rays.origins().clone());
            ds.push(rays.directions().clone());
            targets.push(images[v].index_select(&idx, 0)?);
        }
        let rays = Rays::new(Tensor::cat(&os, 0)?, Tensor::cat(&ds, 0)?)?;
        let target = Tensor::cat(&targets, 0)?;
        let (out, evaluated) = match mode {
            Mode::Stratified => (
                render_stratified(&rays, SAMPLES, Some(rng.next_u64()), |p| radiance(&net, p))?,
                rays.len() * SAMPLES,
            ),
            Mode::Grid => render_grid(&rays, &grid, &net)?,
        };
        evaluated_total += evaluated;
        let loss = (out.color - &target)?.sqr()?.mean_all()?;
        opt.backward_step(&loss)?;
        if step % EVAL_EVERY == 0 {
            let train_time = start.elapsed().as_secs_f64() - eval_secs;
            let clock = Instant::now();
            let (image, _) = render_view(&held_out, mode, &net, &grid)?;
            eval_secs += clock.elapsed().as_secs_f64();
            println!(
                "{name:>10} {step:>5} {:>10.5} {:>8.2} {:>9.1} {:>9.1} {:>8.1}",
                loss.to_dtype(DType::F64)?.to_scalar::<f64>()?,
                psnr(&image, &images[HELD_OUT], None)?,
                evaluated as f64 / rays.len() as f64,
                100.0 * grid.occupied_fraction(),
                train_time,
            );
        }
    }
    let (image, evaluated) = render_view(&held_out, mode, &net, &grid)?;
    println!(
        "{name}: held-out PSNR {:.2} dB after {STEPS} steps in {:.1} s of training; {:.1} \
         samples per ray evaluated in training on average, {:.1} to render the held-out view",
        psnr(&image, &images[HELD_OUT], None)?,
        start.elapsed().as_secs_f64() - eval_secs,
        evaluated_total as f64 / ((STEPS + 1) * VIEWS_PER_STEP * RAYS_PER_VIEW) as f64,
        evaluated as f64 / held_out.len() as f64,
    );
    if mode == Mode::Grid {
        println!(
            "grid: {:.1} % of its cells occupied",
            100.0 * grid.occupied_fraction()
        );
    }
    Ok(image)
}

fn main() -> Result<()> {
    let device = Device::Cpu;
    let dtype = DType::F32;
    let path = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "tiny_nerf.png".into());

    // Cameras on a sphere of radius 3 looking at the origin (a golden-angle spiral).
    let cameras = (0..VIEWS)
        .map(|i| {
            let z = 0.8 - 1.6 * (i as f64 + 0.5) / VIEWS as f64;
            let phi = i as f64 * 2.399_963;
            let rxy = (1.0 - z * z).sqrt();
            let eye = 3.0 * DVec3::new(rxy * phi.cos(), rxy * phi.sin(), z);
            cameras::looking_at_origin(SIDE, 0.55, eye)
        })
        .collect::<Result<Vec<_>>>()?;
    let t = Instant::now();
    let images = cameras
        .iter()
        .map(|cam| {
            let rays = cam.rays(&device, DType::F64)?;
            let field = |p: &Tensor| Ok((scene_sigma(p)?, scene_rgb(p)?));
            let img = render_stratified(&rays, 1024, None, field)?.color;
            Ok(img.to_dtype(dtype)?)
        })
        .collect::<Result<Vec<_>>>()?;
    println!(
        "{VIEWS} ground-truth views of {SIDE}x{SIDE} rendered in {:.1} s (view {HELD_OUT} held out)",
        t.elapsed().as_secs_f64()
    );
    println!(
        "{:>10} {:>5} {:>10} {:>8} {:>9} {:>9} {:>8}",
        "run", "step", "train mse", "PSNR/dB", "samples", "occupied%", "time/s"
    );
    let strat = train(Mode::Stratified, &cameras, &images, &device, dtype)?;
    let grid = train(Mode::Grid, &cameras, &images, &device, dtype)?;
    write_panels(&path, &[&images[HELD_OUT], &strat, &grid])?;
    println!("wrote {path} (held-out view: reference | stratified | grid)");
    Ok(())
}

/// Writes `SIDE × SIDE` RGB images (`[SIDE², 3]` in [0, 1]) side by side, each pixel
/// scaled up 4×, to an 8-bit PNG.
fn write_panels(path: &str, panels: &[&Tensor]) -> Result<()> {
    const UP: usize = 4;
    let images = panels
        .iter()
        .map(|t| {
            // [SIDE², 3] → [1, 3, SIDE, SIDE] for candle's nearest upsampling, and back.
            let chw = t
                .reshape((SIDE, SIDE, 3))?
                .permute((2, 0, 1))?
                .unsqueeze(0)?;
            let up = chw.upsample_nearest2d(SIDE * UP, SIDE * UP)?;
            Ok(up.squeeze(0)?.permute((1, 2, 0))?)
        })
        .collect::<Result<Vec<Tensor>>>()?;
    write_png(std::path::Path::new(path), &Tensor::cat(&images, 1)?)
}
