//! The crate tour's NeRF step: a whole trainer on the public API. `cargo run --release --example
//! nerf_tour` trains on the committed scene, renders every test view, prints the mean PSNR.
use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use clap::Parser;
use neural_fields::data::{load, load_eval, psnr, write_png, LoadConfig, RaySampler};
use neural_fields::nn::{adam, build_seeded};
use neural_fields::volume::{composite, nerf, render_image, CompositeConfig, GridConfig};
use neural_fields::volume::{GridMarchConfig, ImageConfig, NerfConfig, OccupancyGrid};

#[derive(Parser)]
struct Args {
    #[arg(long, default_value = "examples/data/wuson")]
    data: std::path::PathBuf,
    #[arg(long, default_value_t = 300)]
    steps: usize,
    #[arg(long, default_value = "target/nerf_tour")]
    out: std::path::PathBuf,
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let (args, dev, dt) = (Args::parse(), Device::Cpu, DType::F32);
    let data = LoadConfig::default(); // white backgrounds; paths inside the dataset folder
    let (train, (test, _)) = (load(&args.data, &data)?, load_eval(&args.data, &data)?);
    let varmap = VarMap::new();
    let net = build_seeded(&varmap, dt, &dev, 0, |vb| nerf(&NerfConfig::default(), vb))?;
    let mut adam = adam(&varmap, 1e-3)?;
    let mut cells = GridConfig::default();
    (cells.aabb, cells.resolution, cells.decay) = ([-1.5, -1.5, -1.5, 1.5, 1.5, 1.5], 64, 0.7);
    let mut grid = OccupancyGrid::new(cells)?;
    let mut march = GridMarchConfig::default(); // nerfacc's: stop rays at transmittance 1e-4
    (march.step_size, march.jitter) = (0.04, None); // ~130 steps across the box
    let mut density = |p: &Tensor| net.density(p); // updates the grid, drops hidden samples
    let mut rays = RaySampler::new(&train, 0, &dev, dt)?;
    let mut config = CompositeConfig::default();
    for step in 0..args.steps {
        grid.update(step, 16, &dev, dt, &mut density)?;
        let batch = rays.pixels(1024)?;
        march.jitter = Some(step as u64);
        let kept = grid.sample(&batch.rays, &march, Some(&mut density))?;
        config.background = Some(batch.backgrounds);
        let out = net.color_loss(&batch.rays, &kept.intervals, &batch.colors, &config)?;
        adam.backward_step(&out.loss)?;
    }
    (march.jitter, config.background) = (None, Some(Tensor::ones(3, dt, &dev)?));
    let (mut total, mut views, image) = (0.0, Vec::new(), ImageConfig::default());
    for view in test.views() {
        let [color] = render_image(view.camera(), &image, &dev, dt, |r| {
            let iv = grid.sample(r, &march, Some(&mut density))?.intervals;
            let (sigma, rgb) = net.radiance(&iv.positions(r)?, &iv.directions(r)?)?;
            Ok([composite(&sigma, &rgb, &iv, Some(r), &config)?.color])
        })?;
        total += psnr(&color, &view.rgb([1.0; 3], &dev, dt)?, None)?;
        views.push(color);
    }
    std::fs::create_dir_all(&args.out)?; // one picture: every test view, side by side
    write_png(&args.out.join("nerf_tour.png"), &Tensor::cat(&views, 1)?)?;
    println!("test PSNR {:.2} dB", total / test.views().len() as f64);
    Ok(())
}
