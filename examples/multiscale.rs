//! Writes the multiscale variant of a Blender-layout dataset, as mip-NeRF's multiscale
//! Blender benchmark does: every view of every split at full, ½, ¼ and ⅛ resolution
//! (`--levels`), each level box-filtered from the full image (colour weighted by alpha) with
//! its intrinsics scaled, the levels of one view consecutive (`r_{4i + l}.png` is view `i`
//! at level `l`).
//!
//! ```text
//! cargo run --release --example multiscale -- --data examples/data/wuson --out target/wuson_multiscale
//! cargo run --release --example nerf -- --data target/wuson_multiscale --encoding ipe
//! ```
//!
//! The `nerf` example trains on such a dataset with each pixel drawn in proportion to its
//! area ([`neural_fields::data::RaySampler::pixels`]: every image weighs the same, mip-NeRF's
//! loss weighting) and reports the held-out PSNR per scale (`psnr_per_scale` in its
//! `metrics.json`). A split the source lacks is skipped; the source's stated bounds are
//! not carried over (the Blender layout states none).

use clap::Parser;
use neural_fields::data::{load, write_blender, Dataset, LoadConfig, Split};
use neural_fields::{Error, Result};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(about = "Write the multiscale variant of a Blender-layout dataset")]
struct Args {
    /// The source dataset folder (Blender layout: transforms_{train,val,test}.json).
    #[arg(long)]
    data: PathBuf,
    /// The folder to write (created if needed).
    #[arg(long)]
    out: PathBuf,
    /// Resolution levels: 1 (full) … 4 (full, ½, ¼, ⅛; the benchmark's).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..=8))]
    levels: u32,
    /// Image and mask paths may lead outside the dataset folder.
    #[arg(long)]
    allow_outside_paths: bool,
}

/// The views of `split` at each level, interleaved view by view.
fn multiscale(args: &Args, split: Split) -> Result<Dataset> {
    let mut levels = Vec::new();
    for l in 0..args.levels {
        let config = LoadConfig {
            split,
            downscale: 1 << l,
            allow_outside_paths: args.allow_outside_paths,
            ..LoadConfig::default()
        };
        levels.push(load(&args.data, &config)?);
    }
    let n = levels[0].views().len();
    let views = (0..n)
        .flat_map(|i| levels.iter().map(move |d| d.views()[i].clone()))
        .collect();
    Dataset::new(views, levels[0].background(), None)
}

fn run(args: &Args) -> Result<()> {
    let mut written = 0;
    for (split, name) in [
        (Split::Train, "train"),
        (Split::Val, "val"),
        (Split::Test, "test"),
    ] {
        if !args.data.join(format!("transforms_{name}.json")).is_file() {
            println!("{}: no {name} split, skipped", args.data.display());
            continue;
        }
        let data = multiscale(args, split)?;
        write_blender(&args.out, split, &data)?;
        println!(
            "{name}: {} images ({} levels)",
            data.views().len(),
            args.levels
        );
        written += 1;
    }
    if written == 0 {
        return Err(Error::InvalidArgument {
            arg: "data",
            expected: "a Blender-layout folder with transforms_{train,val,test}.json".into(),
            got: args.data.display().to_string(),
        });
    }
    println!("wrote {}", args.out.display());
    Ok(())
}

fn main() -> std::process::ExitCode {
    match run(&Args::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("multiscale: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}
