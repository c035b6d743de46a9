//! Sparse views: train the NeRF of `examples/nerf.rs` from 3 views twice for the same wall
//! time, plain and regularised, and compare on the held-out views.
//!
//! ```text
//! cargo run --release --example sparse_views                       # committed dataset, 3 min per run
//! cargo run --release --example sparse_views -- --data DIR --frames 0,10,20 --minutes 5 --out out/sv
//! ```
//!
//! Both runs use the stratified sampler (32 samples) and the same seed. The plain run is
//! the NeRF example's model as it is. The regularised run adds, by default:
//! - a **frequency window** (FreeNeRF, Yang et al. 2023: BARF's coarse-to-fine window used
//!   as a regulariser) that opens the position encoding's octaves linearly over training
//!   and stops at 3 of its 10 (`--coarse-to-fine 0,3.3333`; `off` to drop it);
//! - a **view-independent colour** (`--view-dependence off`): from three views a colour
//!   head that sees the view direction explains wrong geometry by view-dependent colour;
//! - with `--regnerf on`, RegNeRF's regularisers (Niemeyer et al. 2022): the depth
//!   smoothness of 16 patches of 8 × 8 pixels rendered from random cameras around the
//!   training cameras ([`cameras_around`](neural_fields::camera::cameras_around)),
//!   weighted log-linearly over the first 512 steps (`--regnerf-weight START,END`,
//!   default RegNeRF's `400,0.1`), and the sampling range annealed from the middle of each
//!   ray's `[near, far]` over the first 256 steps. Off by default: on the committed
//!   object-centric scene they cost half the steps and gained nothing
//!   (docs/benchmarks.md, "Sparse views").
//!
//! Flags: `--data DIR` (default `examples/data/wuson`), `--frames I,J,K` (training views,
//! default `0,17,34`), `--minutes M` per run (default 3) or `--steps N`, `--out DIR`
//! (default `out/sparse_views`), `--seed S`, `--downscale K`, and the regularised run's
//! `--coarse-to-fine START,END|off`, `--view-dependence on|off`, `--regnerf on|off`,
//! `--regnerf-weight START,END`. Writes `OUT/plain/` and `OUT/regularised/` (each run's
//! own outputs, see `examples/nerf.rs`), `OUT/compare_{i}.png` (truth | plain |
//! regularised), `OUT/depth_{i}.png` (plain depth | regularised depth, on one colour
//! scale) and `OUT/metrics.json` with both runs' `psnr` and `depth_tv` (the mean absolute
//! difference of neighbouring depths where both pixels are opaque, lower is smoother) and
//! the regularisers used.

#[allow(dead_code)] // the NeRF example's `main`, flags and test are not used here
#[path = "nerf.rs"]
mod nerf;

use candle_core::{DType, Tensor};
use nerf::training;
use neural_fields::data::{colorize_depth, write_png};
use neural_fields::{Error, Result};
use std::path::PathBuf;

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
            let a = d[i * w + j];
            for (ii, jj) in [(i, j + 1), (i + 1, j)] {
                if ii < h && jj < w {
                    let b = d[ii * w + jj];
                    if a.is_finite() && b.is_finite() {
                        sum += (a - b).abs();
                        n += 1;
                    }
                }
            }
        }
    }
    Ok(if n == 0 { 0.0 } else { sum / n as f64 })
}

fn run() -> Result<()> {
    let mut minutes = Some(3.0);
    let mut base = nerf::Args {
        out: PathBuf::from("out/sparse_views"),
        sampler: nerf::Sampler::Stratified,
        samples: 32,
        pictures: 4,
        frames: Some(vec![0, 17, 34]),
        ..nerf::Args::default()
    };
    let mut it = std::env::args().skip(1);
    let bad = |m: String| Error::InvalidArgument {
        arg: "flags",
        expected: "see the example's docs".into(),
        got: m,
    };
    let mut reg = Regularisers::default();
    while let Some(flag) = it.next() {
        let value = it
            .next()
            .ok_or_else(|| bad(format!("{flag} needs a value")))?;
        match flag.as_str() {
            "--data" => base.data = value.into(),
            "--out" => base.out = value.into(),
            "--minutes" => {
                minutes = Some(
                    value
                        .parse()
                        .map_err(|_| bad(format!("--minutes {value}")))?,
                )
            }
            "--steps" => {
                base.steps = Some(value.parse().map_err(|_| bad(format!("--steps {value}")))?);
                minutes = None;
            }
            "--seed" => base.seed = value.parse().map_err(|_| bad(format!("--seed {value}")))?,
            "--downscale" => {
                base.downscale = value
                    .parse()
                    .map_err(|_| bad(format!("--downscale {value}")))?
            }
            "--frames" => {
                let list: std::result::Result<Vec<usize>, _> =
                    value.split(',').map(|v| v.trim().parse()).collect();
                base.frames = Some(list.map_err(|_| bad(format!("--frames {value}")))?);
            }
            "--regnerf-weight" => {
                base.regnerf_weight = nerf::regnerf_weight(&value).map_err(bad)?
            }
            "--coarse-to-fine" if value == "off" => reg.coarse_to_fine = None,
            "--coarse-to-fine" => {
                reg.coarse_to_fine = Some(training::window_span(&flag, &value).map_err(bad)?)
            }
            "--view-dependence" => {
                reg.view_dependence = training::on_off(&flag, &value).map_err(bad)?
            }
            "--regnerf" => reg.regnerf = training::on_off(&flag, &value).map_err(bad)?,
            other => return Err(bad(format!("unknown flag {other}"))),
        }
    }
    base.minutes = minutes;
    compare(&base, &reg)
}

/// What the regularised run adds to the plain one.
#[derive(Clone, Debug)]
struct Regularisers {
    /// The position encoding's window (see `examples/nerf.rs --coarse-to-fine`).
    coarse_to_fine: Option<(f64, f64)>,
    view_dependence: bool,
    /// RegNeRF's depth smoothness and annealed sampling range.
    regnerf: bool,
}

impl Default for Regularisers {
    fn default() -> Self {
        Self {
            coarse_to_fine: Some((0.0, 10.0 / 3.0)),
            view_dependence: false,
            regnerf: false,
        }
    }
}

/// Runs `base` plain and with `reg`, and writes the comparison to `base.out`.
fn compare(base: &nerf::Args, reg: &Regularisers) -> Result<()> {
    let minutes = base.minutes;
    let root = base.out.clone();
    let mut results = Vec::new();
    for name in ["plain", "regularised"] {
        println!("== {name}");
        let plain = nerf::Args {
            out: root.join(name),
            frames: base.frames.clone(),
            data: base.data.clone(),
            resume: None,
            proposal_samples: base.proposal_samples.clone(),
            ..*base
        };
        let args = if name == "plain" {
            plain
        } else {
            nerf::Args {
                regnerf: reg.regnerf,
                coarse_to_fine: reg.coarse_to_fine,
                view_dependence: reg.view_dependence,
                ..plain
            }
        };
        results.push(nerf::run(&args)?);
    }
    let (plain, reg_run) = (&results[0], &results[1]);
    let tv = |s: &nerf::Summary| -> Result<f64> {
        let v: Result<Vec<f64>> = s.renders.iter().map(|r| depth_tv(&r[2])).collect();
        let v = v?;
        Ok(v.iter().sum::<f64>() / v.len().max(1) as f64)
    };
    let (tv_plain, tv_reg) = (tv(plain)?, tv(reg_run)?);
    for (i, (a, b)) in plain
        .renders
        .iter()
        .zip(&reg_run.renders)
        .enumerate()
        .take(base.pictures)
    {
        write_png(
            &root.join(format!("compare_{i}.png")),
            &Tensor::cat(&[&a[0], &a[1], &b[1]], 1)?,
        )?;
        // One colour scale for both depth maps.
        let both = Tensor::cat(&[&a[2], &b[2]], 1)?;
        let (rgb, _) = colorize_depth(&both, None)?;
        write_png(&root.join(format!("depth_{i}.png")), &rgb)?;
    }
    let metrics = serde_json::json!({
        "plain": { "psnr": plain.psnr, "depth_tv": tv_plain },
        "regularised": { "psnr": reg_run.psnr, "depth_tv": tv_reg },
        "regularisers": {
            "coarse_to_fine": reg.coarse_to_fine.map(|(s, e)| [s, e]),
            "view_dependence": reg.view_dependence,
            "regnerf": reg.regnerf,
            "regnerf_weight": reg.regnerf.then_some(base.regnerf_weight),
        },
        "frames": base.frames,
        "minutes_per_run": minutes,
        "steps_per_run": base.steps,
    });
    std::fs::write(
        root.join("metrics.json"),
        serde_json::to_string_pretty(&metrics).expect("JSON"),
    )
    .map_err(|source| Error::Io {
        path: root.join("metrics.json").display().to_string(),
        source,
    })?;
    println!(
        "held-out PSNR: plain {:.2} dB, regularised {:.2} dB; depth TV: plain {tv_plain:.4}, regularised {tv_reg:.4}",
        plain.psnr, reg_run.psnr
    );
    Ok(())
}

fn main() -> std::process::ExitCode {
    match run() {
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

    /// Both runs for a few steps at a quarter of the resolution: the comparison files and
    /// both runs' metrics are written.
    #[test]
    fn a_shortened_comparison_writes_both_runs_and_the_metrics() {
        let out = std::env::temp_dir().join(format!("sparse-views-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let base = nerf::Args {
            steps: Some(3),
            out: out.clone(),
            sampler: nerf::Sampler::Stratified,
            downscale: 4,
            rays: 128,
            samples: 16,
            eval_every: 3,
            eval_views: 1,
            pictures: 1,
            frames: Some(vec![0, 17, 34]),
            ..nerf::Args::default()
        };
        compare(
            &base,
            &Regularisers {
                regnerf: true,
                ..Regularisers::default()
            },
        )
        .unwrap();
        let m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                .unwrap();
        assert_eq!(m["regularisers"]["view_dependence"], false, "{m}");
        for run in ["plain", "regularised"] {
            for key in ["psnr", "depth_tv"] {
                assert!(
                    m[run][key].as_f64().is_some_and(f64::is_finite),
                    "{run}.{key}: {m}"
                );
            }
        }
        assert!(out.join("compare_0.png").is_file() && out.join("depth_0.png").is_file());
        let _ = std::fs::remove_dir_all(&out);
    }
}
