//! Sparse views: train a NeRF from 3 views twice for the same budget, plain and
//! regularised, and compare on the held-out views.
//!
//! ```text
//! cargo run --release --example sparse_views                       # committed dataset, 3 min per run
//! cargo run --release --example sparse_views -- --data DIR --frames 0,10,20 --minutes 5 --out target/sv
//! ```
//!
//! **Training views**: `--frames`, else the three views spread most widely around the
//! scene: the three whose smallest pairwise angle, seen from the cameras' common focus,
//! is largest (`spread_views`).
//!
//! Both runs train [`Nerf`] (NeRF's defaults) with Adam (learning rate 1e-3 decaying
//! log-linearly to 1e-4) on `--rays` random pixels of the training views per step, each
//! ray composited over a random background, with `--samples` (32) jittered stratified
//! samples across the scene box (`--aabb H`: the cube ±H; else the box the layout states,
//! else the visual hull of the whole training split's silhouettes grown by 5 %, else
//! ±1.5: [`Dataset::scene_box`]) and the fused [`Nerf::color_loss`]; the same seed. The
//! box is the scene's bounds, as a layout may state them: only the three views' pixels
//! train, but three silhouettes of an object that leaves the frame bound little of it (a
//! box as wide as the cameras' cube, whose far side lets a field explain each view by a
//! picture behind the object). The
//! regularised run has:
//! - a **view-independent colour** (`--view-dependence off`, the default): from three
//!   views a colour head that sees the view direction explains wrong geometry by
//!   view-dependent colour;
//! - with `--coarse-to-fine START,END`, a **frequency window** (FreeNeRF, Yang et al.
//!   2023: BARF's coarse-to-fine window used as a regulariser) that opens the position
//!   encoding's octaves linearly from START to END (fractions of training; END > 1 leaves
//!   it partly closed: `0,3.3333` stops at 3 of its 10 octaves). Off by default: on the
//!   tuning scenes it lost to the view-independent colour alone (docs/benchmarks.md,
//!   "Sparse views: the window dropped");
//! - with `--regnerf on`, RegNeRF's regularisers (Niemeyer et al. 2022): the depth
//!   smoothness of 16 patches of 8 × 8 pixels rendered from random cameras around the
//!   training cameras ([`cameras_around`]), weighted log-linearly over the first 512 steps
//!   (`--regnerf-weight START,END`, default RegNeRF's `400,0.1`), and the sampling range
//!   annealed from the middle of each ray's `[near, far]` over the first 256 steps. Off by
//!   default: on the committed object-centric scene they cost half the steps and gained
//!   nothing (docs/benchmarks.md, "Sparse views").
//!
//! Held-out views are rendered on white with [`render_image`]. Writes, under `--out`
//! (default `target/sparse_views`): `plain/` and `regularised/` (each run's `metrics.json`
//! with `psnr`, `steps`, `train_seconds`, and `view_{i}.png`: truth | prediction | error),
//! `compare_{i}.png` (truth | plain | regularised), `depth_{i}.png` (plain depth |
//! regularised depth, on one colour scale) and `metrics.json` with both runs' `psnr` and
//! `depth_tv` (the mean absolute difference of neighbouring depths where both pixels are
//! opaque, lower is smoother), the regularisers used, the training `frames` and the
//! `scene_box` (`[x0, y0, z0, x1, y1, z1]`).

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use clap::Parser;
use neural_fields::camera::{cameras_around, patch_rays, ray_aabb, Camera, Convention, Rays};
use neural_fields::data::{
    colorize_depth, comparison_strip, load, psnr, write_png, Dataset, LoadConfig, RaySampler, Split,
};
use neural_fields::encoding::{CoarseToFine, PointEncoding};
use neural_fields::glam::{DMat3, DVec3};
use neural_fields::nn::{adam, build_seeded};
use neural_fields::volume::{
    anneal_near_far, composite, depth_smoothness, log_linear_schedule, render_image, stratified,
    Composite, CompositeConfig, ImageConfig, Intervals, Jitter, ANNEAL_MID_RATIO, ANNEAL_P_START,
};
use neural_fields::volume::{nerf, Nerf, NerfConfig};
use neural_fields::{Error, Result};
use std::path::{Path, PathBuf};
use std::time::Instant;

#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// The command line (see the module docs).
#[derive(Parser, Debug, Clone)]
#[command(about = "Train a NeRF from a few views, plain and regularised, and compare")]
struct Args {
    /// Dataset folder (Blender synthetic, nerfstudio or IDR/DTU layout).
    #[arg(long, default_value = "examples/data/wuson")]
    data: PathBuf,
    /// Read image and mask files outside the dataset folder (absolute paths, `../`,
    /// symlinks to elsewhere), which loading refuses by default.
    #[arg(long)]
    allow_outside_paths: bool,
    /// Training views (indices into the training split). Default: the three views spread
    /// most widely around the scene ([`spread_views`]).
    #[arg(long, value_delimiter = ',')]
    frames: Option<Vec<usize>>,
    /// Minutes of training per run (default 3 unless --steps is given).
    #[arg(long, conflicts_with = "steps")]
    minutes: Option<f64>,
    /// Optimiser steps per run.
    #[arg(long)]
    steps: Option<usize>,
    #[arg(long, default_value = "target/sparse_views")]
    out: PathBuf,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Divide the images' resolution by this.
    #[arg(long, default_value_t = 1)]
    downscale: usize,
    /// Rays per step.
    #[arg(long, default_value_t = 1024)]
    rays: usize,
    /// Stratified samples per ray.
    #[arg(long, default_value_t = 32)]
    samples: usize,
    /// Half-side of the scene cube. Without it: the box the layout states, else the
    /// visual hull of the training silhouettes grown by 5 %, else ±1.5.
    #[arg(long)]
    aabb: Option<f64>,
    /// Held-out views written as pictures.
    #[arg(long, default_value_t = 4)]
    pictures: usize,
    /// Regularised run: START,END of the encoding's window (e.g. 0,3.3333: opened to 3
    /// of its 10 octaves), or `off`.
    #[arg(long, value_parser = window, default_value = "off")]
    coarse_to_fine: Window,
    /// Regularised run: whether the colour depends on the view direction.
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "off")]
    view_dependence: bool,
    /// Regularised run: RegNeRF's depth smoothness and annealed sampling range.
    #[arg(long, value_parser = on_off, action = clap::ArgAction::Set, default_value = "off")]
    regnerf: bool,
    #[arg(long, value_parser = weights, default_value = "400,0.1")]
    regnerf_weight: [f64; 2],
}

/// `--coarse-to-fine`: the fractions of training over which the window opens, or none.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Window(Option<(f64, f64)>);

fn on_off(value: &str) -> std::result::Result<bool, String> {
    match value {
        "on" => Ok(true),
        "off" => Ok(false),
        other => Err(format!("on or off, not {other}")),
    }
}

fn pair(value: &str) -> std::result::Result<(f64, f64), String> {
    match value
        .split_once(',')
        .map(|(a, b)| (a.trim().parse(), b.trim().parse()))
    {
        Some((Ok(a), Ok(b))) if f64::is_finite(a) && f64::is_finite(b) => Ok((a, b)),
        _ => Err(format!("two numbers A,B, not {value}")),
    }
}

fn window(value: &str) -> std::result::Result<Window, String> {
    match value {
        "off" => Ok(Window(None)),
        _ => match pair(value)? {
            (s, e) if 0.0 <= s && s < e && s < 1.0 => Ok(Window(Some((s, e)))),
            _ => Err(format!(
                "START,END with 0 ≤ START < 1, START < END, not {value}"
            )),
        },
    }
}

fn weights(value: &str) -> std::result::Result<[f64; 2], String> {
    match pair(value)? {
        (a, b) if a > 0.0 && b > 0.0 => Ok([a, b]),
        _ => Err(format!("two weights > 0, not {value}")),
    }
}

/// What one run leaves: the mean held-out PSNR and, per held-out view, `[truth, colour,
/// depth, opacity]` (depth NaN where the opacity is below 0.5).
struct Run {
    psnr: f64,
    renders: Vec<[Tensor; 4]>,
}

/// Stratified intervals across the scene box (jittered with `seed`, annealed to RegNeRF's
/// range at `anneal = Some(step)`).
fn intervals(
    rays: &Rays,
    scene: [f64; 6],
    n: usize,
    seed: Option<u64>,
    anneal: Option<usize>,
) -> Result<Intervals> {
    let [x0, y0, z0, x1, y1, z1] = scene;
    let hit = ray_aabb(rays, [x0, y0, z0], [x1, y1, z1])?;
    let (near, far) = match anneal {
        Some(step) => anneal_near_far(
            &hit.near,
            &hit.far,
            step,
            256,
            ANNEAL_P_START,
            ANNEAL_MID_RATIO,
        )?,
        None => (hit.near, hit.far),
    };
    let jitter = if seed.is_some() {
        Jitter::PerSample
    } else {
        Jitter::None
    };
    stratified(&near, &far, n, jitter, seed.unwrap_or(0))
}

/// The field along `rays` at `iv`, composited over `background` (`[3]` or `[R, 3]`).
fn render(net: &Nerf, rays: &Rays, iv: &Intervals, background: &Tensor) -> Result<Composite> {
    let (r, s) = iv.starts.dims2()?;
    let positions = iv.positions(rays)?.reshape(((), 3))?;
    let (sigma, rgb) = net.radiance(&positions, &iv.directions(rays)?.reshape(((), 3))?)?;
    let config = CompositeConfig {
        background: Some(background.clone()),
        ..CompositeConfig::default()
    };
    composite(
        &sigma.reshape((r, s))?,
        &rgb.reshape((r, s, 3))?,
        iv,
        Some(rays),
        &config,
    )
}

/// RegNeRF's depth smoothness of 16 patches of 8 × 8 pixels seen from random cameras around
/// `cameras`, each pixel weighted by its own (detached) opacity.
fn patch_smoothness(
    net: &Nerf,
    cameras: &[Camera],
    scene: [f64; 6],
    args: &Args,
    step: usize,
) -> Result<Tensor> {
    const K: usize = 8;
    let seed = args.seed ^ step as u64;
    let unseen = cameras_around(cameras, 16, seed)?;
    let rays = patch_rays(&unseen, K, seed, &Device::Cpu, DType::F32)?;
    let iv = intervals(&rays, scene, args.samples, Some(seed), Some(step))?;
    let out = render(
        net,
        &rays,
        &iv,
        &Tensor::zeros(3, DType::F32, &Device::Cpu)?,
    )?;
    let depth = out.normalized_depth(1e-6)?.reshape((16, K, K))?;
    let opacity = out.opacity.detach().reshape((16, K, K))?;
    Ok(depth_smoothness(&depth, Some(&opacity))?.mean_all()?)
}

/// Three views of `data` spread around the scene: seen from the point nearest to every
/// camera's optical axis (least squares; the cameras' mean position when the axes are
/// parallel), the three whose smallest pairwise angle is largest (ties: the first in
/// index order). Returned in increasing order.
fn spread_views(data: &Dataset) -> Result<Vec<usize>> {
    let n = data.views().len();
    if n < 3 {
        return Err(Error::InvalidArgument {
            arg: "frames",
            expected: "a dataset with at least 3 training views".into(),
            got: format!("{n} views"),
        });
    }
    let axes: Vec<(DVec3, DVec3)> = data
        .views()
        .iter()
        .map(|v| {
            let pose = v.camera().cam_to_world();
            let forward = match v.camera().convention() {
                Convention::OpenCv => DVec3::Z,
                Convention::OpenGl => -DVec3::Z,
            };
            (
                pose.translation,
                (pose.matrix3 * forward).normalize_or_zero(),
            )
        })
        .collect();
    // Σ (I − ddᵀ) p = Σ (I − ddᵀ) o: the point nearest to every axis.
    let (mut a, mut b) = (DMat3::ZERO, DVec3::ZERO);
    for &(o, d) in &axes {
        let m = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += m;
        b += m * o;
    }
    let mean = axes.iter().map(|&(o, _)| o).sum::<DVec3>() / n as f64;
    let centre = if a.determinant().abs() > 1e-6 * n.pow(3) as f64 {
        a.inverse() * b
    } else {
        mean
    };
    let dirs: Vec<DVec3> = axes
        .iter()
        .map(|&(o, _)| (o - centre).normalize_or_zero())
        .collect();
    let angle: Vec<f64> = (0..n * n)
        .map(|ij| dirs[ij / n].dot(dirs[ij % n]).clamp(-1.0, 1.0).acos())
        .collect();
    let mut best = ([0, 1, 2], f64::NEG_INFINITY);
    for i in 0..n {
        for j in i + 1..n {
            let ij = angle[i * n + j];
            if ij <= best.1 {
                continue;
            }
            for k in j + 1..n {
                let least = ij.min(angle[i * n + k]).min(angle[j * n + k]);
                if least > best.1 {
                    best = ([i, j, k], least);
                }
            }
        }
    }
    Ok(best.0.to_vec())
}

/// What both runs share: the training views, the held-out views and the scene box.
struct Views {
    train: Dataset,
    eval: Dataset,
    scene: [f64; 6],
}

/// The views `args.frames` of the training split (random backgrounds) and the test
/// split (else the validation split), loaded once for both runs; refuses training views
/// without foreground.
fn load_views(args: &Args, config: &LoadConfig, scene: [f64; 6]) -> Result<Views> {
    let train = load(
        &args.data,
        &LoadConfig {
            frames: args.frames.clone(),
            background: neural_fields::data::Background::Random,
            ..config.clone()
        },
    )?;
    if train.coverage() == Some(0.0) {
        return Err(Error::InvalidArgument {
            arg: "data",
            expected: "training views with some foreground (alpha or mask ≥ ½)".into(),
            got: format!(
                "{} views whose every pixel is transparent",
                train.views().len()
            ),
        });
    }
    let eval = load(
        &args.data,
        &LoadConfig {
            split: Split::Test,
            ..config.clone()
        },
    )
    .or_else(|_| {
        load(
            &args.data,
            &LoadConfig {
                split: Split::Val,
                ..config.clone()
            },
        )
    })?;
    Ok(Views { train, eval, scene })
}

/// One run, plain or regularised, on `views`, written to `OUT/name`.
fn train(args: &Args, views: &Views, name: &str, regularised: bool) -> Result<Run> {
    let (dev, dt) = (Device::Cpu, DType::F32);
    let Views { train, eval, scene } = views;
    let scene = *scene;
    let span = regularised.then_some(args.coarse_to_fine.0).flatten();
    let varmap = VarMap::new();
    let windows = std::cell::RefCell::new(Vec::new());
    let net = build_seeded(&varmap, dt, &dev, args.seed, |vb| {
        let mut config = NerfConfig::default();
        if regularised && !args.view_dependence {
            config.direction_encoding = None;
        }
        windows.borrow_mut().clear();
        if span.is_some() {
            let window = CoarseToFine::new(config.position_encoding)?;
            windows.borrow_mut().push(window.clone());
            config.position_encoding = PointEncoding::CoarseToFine(window);
        }
        nerf(&config, vb)
    })?;
    let mut adam = adam(&varmap, 1e-3)?;
    let mut rays = RaySampler::new(train, args.seed, &dev, dt)?;
    let cameras: Vec<Camera> = train.views().iter().map(|v| *v.camera()).collect();
    let regnerf = regularised && args.regnerf;
    let seconds = args.minutes.unwrap_or(3.0) * 60.0;
    let start = Instant::now();
    let mut step = 0;
    let mut dead_since = None;
    loop {
        let progress = match args.steps {
            Some(n) => step as f64 / n.max(1) as f64 + f64::from(u8::from(n == 0)),
            None => start.elapsed().as_secs_f64() / seconds,
        };
        if progress >= 1.0 {
            break;
        }
        adam.set_learning_rate(log_linear_schedule(
            (progress * 1e4) as usize,
            1e-3,
            1e-4,
            10_000,
        ));
        let open = span.map_or(1.0, |(s, e)| ((progress - s) / (e - s)).clamp(0.0, 1.0));
        for w in windows.borrow().iter() {
            w.set_alpha(open * w.bands() as f64)?;
        }
        let batch = rays.pixels(args.rays)?;
        let seed = Some(args.seed ^ step as u64);
        let iv = intervals(
            &batch.rays,
            scene,
            args.samples,
            seed,
            regnerf.then_some(step),
        )?;
        let background = CompositeConfig {
            background: Some(batch.backgrounds.clone()),
            ..CompositeConfig::default()
        };
        let out = net.color_loss(&batch.rays, &iv, &batch.colors, &background)?;
        // A dead run: no training ray with any opacity for 100 steps in a row.
        let since = *dead_since.get_or_insert(step);
        if out.opacity_max >= 1e-3 {
            dead_since = None;
        } else if step + 1 - since >= 100 {
            return Err(Error::InvalidArgument {
                arg: "training",
                expected: "some opacity on the training rays within 100 steps".into(),
                got: format!(
                    "every ray's opacity below 1e-3 from step {since} to {step} ({name} run): the \
                     density collapsed to zero, or the scene box misses the scene"
                ),
            });
        }
        let mut loss = out.loss;
        if regnerf {
            let [w0, w1] = args.regnerf_weight;
            let smooth = patch_smoothness(&net, &cameras, scene, args, step)?;
            loss = (loss + (smooth * log_linear_schedule(step, w0, w1, 512))?)?;
        }
        if !loss.to_dtype(DType::F64)?.to_scalar::<f64>()?.is_finite() {
            return Err(Error::InvalidArgument {
                arg: "training",
                expected: "a finite loss".into(),
                got: format!("a NaN or infinity in the loss at step {step}"),
            });
        }
        adam.backward_step(&loss)?;
        step += 1;
    }
    let train_seconds = start.elapsed().as_secs_f64();
    let white = Tensor::ones(3, dt, &dev)?;
    let out = args.out.join(name);
    std::fs::create_dir_all(&out).map_err(|source| io(&out, source))?;
    let (mut total, mut renders) = (0.0, Vec::new());
    for (i, view) in eval.views().iter().enumerate() {
        let config = ImageConfig::default();
        let [color, depth, opacity] = render_image(view.camera(), &config, &dev, dt, |r| {
            let out = render(
                &net,
                r,
                &intervals(r, scene, args.samples, None, None)?,
                &white,
            )?;
            let depth = out.normalized_depth(1e-6)?;
            Ok([out.color, depth, out.opacity])
        })?;
        let nan = Tensor::full(f32::NAN, depth.shape(), &dev)?;
        let depth = opacity.ge(0.5)?.where_cond(&depth, &nan)?;
        let truth = view.rgb([1.0; 3], &dev, dt)?;
        total += psnr(&color, &truth, None)?;
        if i < args.pictures {
            let strip = comparison_strip(&truth, &color)?;
            write_png(&out.join(format!("view_{i}.png")), &strip)?;
        }
        renders.push([truth, color, depth, opacity]);
    }
    let psnr = total / eval.views().len() as f64;
    let metrics =
        serde_json::json!({ "psnr": psnr, "steps": step, "train_seconds": train_seconds });
    write_json(&out.join("metrics.json"), &metrics)?;
    println!("{name}: {step} steps in {train_seconds:.1} s, held-out PSNR {psnr:.2} dB");
    Ok(Run { psnr, renders })
}

fn io(path: &Path, source: std::io::Error) -> Error {
    Error::Io {
        path: path.display().to_string(),
        source,
    }
}

fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(value).expect("JSON");
    std::fs::write(path, text).map_err(|source| io(path, source))
}

/// Mean |d(i, j) − d(i, j+1)| and |d(i, j) − d(i+1, j)| over neighbours that are both
/// finite (opaque) in a `[H, W]` depth map.
fn depth_tv(depth: &Tensor) -> Result<f64> {
    let (h, w) = depth.dims2()?;
    let d = depth
        .to_dtype(DType::F64)?
        .flatten_all()?
        .to_vec1::<f64>()?;
    let (mut sum, mut n) = (0.0, 0usize);
    for i in 0..h {
        for j in 0..w {
            for (ii, jj) in [(i, j + 1), (i + 1, j)] {
                let (a, b) = (d[i * w + j], *d.get(ii * w + jj).unwrap_or(&f64::NAN));
                if ii < h && jj < w && a.is_finite() && b.is_finite() {
                    sum += (a - b).abs();
                    n += 1;
                }
            }
        }
    }
    Ok(if n == 0 { 0.0 } else { sum / n as f64 })
}

/// Both runs, and the comparison written to `args.out`.
fn compare(args: &Args) -> Result<()> {
    let config = LoadConfig {
        downscale: args.downscale,
        allow_outside_paths: args.allow_outside_paths,
        ..LoadConfig::default()
    };
    let all = load(&args.data, &config)?;
    let frames = match &args.frames {
        Some(frames) => frames.clone(),
        None => spread_views(&all)?,
    };
    let scene = match args.aabb {
        Some(h) => [-h, -h, -h, h, h, h],
        // The scene's bounds: the layout's box, else the hull of the whole training
        // split's silhouettes, else nerfacc's cube. Only the chosen views' pixels train.
        None => all.scene_box(1.5),
    };
    println!("training views {frames:?}, scene box {scene:.2?}");
    let args = &Args {
        frames: Some(frames),
        ..args.clone()
    };
    let views = load_views(args, &config, scene)?;
    let plain = train(args, &views, "plain", false)?;
    let reg = train(args, &views, "regularised", true)?;
    let tv = |run: &Run| -> Result<f64> {
        let v = run
            .renders
            .iter()
            .map(|r| depth_tv(&r[2]))
            .collect::<Result<Vec<f64>>>()?;
        Ok(v.iter().sum::<f64>() / v.len().max(1) as f64)
    };
    let (tv_plain, tv_reg) = (tv(&plain)?, tv(&reg)?);
    for (i, (a, b)) in plain
        .renders
        .iter()
        .zip(&reg.renders)
        .enumerate()
        .take(args.pictures)
    {
        let strip = Tensor::cat(&[&a[0], &a[1], &b[1]], 1)?;
        write_png(&args.out.join(format!("compare_{i}.png")), &strip)?;
        // One colour scale for both depth maps.
        let (rgb, _) = colorize_depth(&Tensor::cat(&[&a[2], &b[2]], 1)?, None)?;
        write_png(&args.out.join(format!("depth_{i}.png")), &rgb)?;
    }
    let metrics = serde_json::json!({
        "plain": { "psnr": plain.psnr, "depth_tv": tv_plain },
        "regularised": { "psnr": reg.psnr, "depth_tv": tv_reg },
        "regularisers": {
            "coarse_to_fine": args.coarse_to_fine.0.map(|(s, e)| [s, e]),
            "view_dependence": args.view_dependence,
            "regnerf": args.regnerf,
            "regnerf_weight": args.regnerf.then_some(args.regnerf_weight),
        },
        "frames": args.frames,
        "scene_box": scene,
        "minutes_per_run": args.steps.is_none().then(|| args.minutes.unwrap_or(3.0)),
        "steps_per_run": args.steps,
    });
    write_json(&args.out.join("metrics.json"), &metrics)?;
    println!(
        "held-out PSNR: plain {:.2} dB, regularised {:.2} dB; depth TV: plain {tv_plain:.4}, regularised {tv_reg:.4}",
        plain.psnr, reg.psnr
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    match compare(&Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("sparse_views: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod sparse_tests {
    use super::*;

    /// The rule's three views on the committed dataset (cameras around the origin) are
    /// farther apart than the fixed indices 0, 17, 34 that it replaced, and at least
    /// 100° apart pairwise; a dataset of two views is an error naming `frames`.
    #[test]
    fn spread_views_picks_views_far_apart() {
        let data = load(
            Path::new("examples/data/wuson"),
            &LoadConfig {
                downscale: 4,
                ..LoadConfig::default()
            },
        )
        .unwrap();
        let smallest = |frames: &[usize]| {
            let dir = |i: usize| {
                data.views()[i]
                    .camera()
                    .cam_to_world()
                    .translation
                    .normalize()
            };
            let mut least = f64::INFINITY;
            for (a, &i) in frames.iter().enumerate() {
                for &j in &frames[a + 1..] {
                    least = least.min(dir(i).dot(dir(j)).clamp(-1.0, 1.0).acos().to_degrees());
                }
            }
            least
        };
        let chosen = spread_views(&data).unwrap();
        assert_eq!(chosen.len(), 3);
        let (spread, fixed) = (smallest(&chosen), smallest(&[0, 17, 34]));
        assert!(
            spread >= 100.0 && spread > fixed,
            "{chosen:?}: {spread}° against {fixed}°"
        );
        let two = Dataset::new(data.views()[..2].to_vec(), data.background(), None).unwrap();
        match spread_views(&two) {
            Err(Error::InvalidArgument { arg, .. }) => assert_eq!(arg, "frames"),
            other => panic!("{other:?}"),
        }
    }

    /// Both runs for a few steps at a quarter of the resolution: the comparison files and
    /// both runs' metrics are written.
    #[test]
    fn a_shortened_comparison_writes_both_runs_and_the_metrics() {
        let out = std::env::temp_dir().join(format!("sparse-views-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let out_flag = out.display().to_string();
        let args = Args::parse_from([
            "sparse_views",
            "--steps",
            "3",
            "--out",
            &out_flag,
            "--downscale",
            "4",
            "--rays",
            "128",
            "--samples",
            "16",
            "--pictures",
            "1",
            "--regnerf",
            "on",
            "--coarse-to-fine",
            "0,3.3333",
        ]);
        // The defaults: a view-independent colour, no window, no RegNeRF.
        let d = Args::parse_from(["sparse_views"]);
        assert!(d.coarse_to_fine.0.is_none() && !d.view_dependence && !d.regnerf);
        compare(&args).unwrap();
        let m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                .unwrap();
        assert_eq!(m["regularisers"]["view_dependence"], false, "{m}");
        assert_eq!(
            m["regularisers"]["coarse_to_fine"],
            serde_json::json!([0.0, 3.3333])
        );
        // Three distinct views, chosen by the rule.
        let frames = m["frames"].as_array().unwrap();
        assert_eq!(frames.len(), 3, "{m}");
        assert!(frames[0].as_u64() < frames[1].as_u64() && frames[1].as_u64() < frames[2].as_u64());
        for run in ["plain", "regularised"] {
            for key in ["psnr", "depth_tv"] {
                assert!(
                    m[run][key].as_f64().is_some_and(f64::is_finite),
                    "{run}.{key}: {m}"
                );
            }
            assert!(out.join(run).join("metrics.json").is_file());
        }
        // The scene's bounds come from the whole training split, not the three views.
        let quarter = LoadConfig {
            downscale: 4,
            ..LoadConfig::default()
        };
        let whole = load(Path::new("examples/data/wuson"), &quarter).unwrap();
        let three = load(
            Path::new("examples/data/wuson"),
            &LoadConfig {
                frames: Some(spread_views(&whole).unwrap()),
                ..quarter
            },
        )
        .unwrap();
        let written: Vec<f64> = m["scene_box"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(written, whole.scene_box(1.5).to_vec(), "{m}");
        assert_ne!(written, three.scene_box(1.5).to_vec(), "{m}");
        assert!(out.join("compare_0.png").is_file() && out.join("depth_0.png").is_file());
        let _ = std::fs::remove_dir_all(&out);
    }
}
