//! Sparse views (RegNeRF): train the NeRF of `examples/nerf.rs` from 3 views twice for the
//! same wall time, without and with RegNeRF's regularisers, and compare on the held-out
//! views.
//!
//! ```text
//! cargo run --release --example sparse_views                       # committed dataset, 3 min per run
//! cargo run --release --example sparse_views -- --data DIR --frames 0,10,20 --minutes 5 --out out/sv
//! ```
//!
//! Both runs use the stratified sampler and the same seed. The regularised run adds, as in
//! RegNeRF (Niemeyer et al. 2022): the depth smoothness of 16 patches of 8 × 8 pixels
//! rendered from random cameras around the training cameras
//! ([`cameras_around`](neural_fields::camera::cameras_around)), weighted `400 → 0.1`
//! log-linearly over the first 512 steps, and the sampling range annealed from the middle
//! of each ray's `[near, far]` over the first 256 steps.
//!
//! Flags: `--data DIR` (default `examples/data/wuson`), `--frames I,J,K` (training views,
//! default `0,17,34`), `--minutes M` per run (default 3) or `--steps N`, `--out DIR`
//! (default `out/sparse_views`), `--seed S`, `--downscale K`, `--regnerf-weight START,END`
//! (the depth smoothness's weight schedule, default RegNeRF's `400,0.1`). Writes `OUT/plain/` and
//! `OUT/regnerf/` (each run's own outputs, see `examples/nerf.rs`), `OUT/compare_{i}.png`
//! (truth | plain | RegNeRF), `OUT/depth_{i}.png` (plain depth | RegNeRF depth, on one
//! colour scale) and `OUT/metrics.json` with both runs' `psnr` and `depth_tv` (the mean
//! absolute difference of neighbouring depths where both pixels are opaque, lower is
//! smoother).

#[allow(dead_code)] // the NeRF example's `main`, flags and test are not used here
#[path = "nerf.rs"]
mod nerf;

use candle_core::{DType, Tensor};
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
            other => return Err(bad(format!("unknown flag {other}"))),
        }
    }
    base.minutes = minutes;
    compare(&base)
}

/// Runs `base` without and with RegNeRF and writes the comparison to `base.out`.
fn compare(base: &nerf::Args) -> Result<()> {
    let minutes = base.minutes;
    let root = base.out.clone();
    let mut results = Vec::new();
    for regnerf in [false, true] {
        let name = if regnerf { "regnerf" } else { "plain" };
        println!("== {name}");
        let args = nerf::Args {
            out: root.join(name),
            regnerf,
            frames: base.frames.clone(),
            data: base.data.clone(),
            resume: None,
            ..*base
        };
        results.push(nerf::run(&args)?);
    }
    let (plain, reg) = (&results[0], &results[1]);
    let tv = |s: &nerf::Summary| -> Result<f64> {
        let v: Result<Vec<f64>> = s.renders.iter().map(|r| depth_tv(&r[2])).collect();
        let v = v?;
        Ok(v.iter().sum::<f64>() / v.len().max(1) as f64)
    };
    let (tv_plain, tv_reg) = (tv(plain)?, tv(reg)?);
    for (i, (a, b)) in plain
        .renders
        .iter()
        .zip(&reg.renders)
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
        "regnerf": { "psnr": reg.psnr, "depth_tv": tv_reg },
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
        "held-out PSNR: plain {:.2} dB, RegNeRF {:.2} dB; depth TV: plain {tv_plain:.4}, RegNeRF {tv_reg:.4}",
        plain.psnr, reg.psnr
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
        compare(&base).unwrap();
        let m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap())
                .unwrap();
        for run in ["plain", "regnerf"] {
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
