//! The crate tour's NeRF: trains at the library's defaults, prints the test PSNR, writes `--out`.
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
    #[arg(long, default_value_t = 1.0)]
    minutes: f64,
    #[arg(long, default_value = "target/nerf_tour.png")]
    out: std::path::PathBuf,
}
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let (args, dev, dt, varmap) = (Args::parse(), Device::Cpu, DType::F32, VarMap::new());
    let data = LoadConfig::default(); // white backgrounds; paths inside the dataset folder
    let (train, (test, _)) = (load(&args.data, &data)?, load_eval(&args.data, &data)?);
    let net = build_seeded(&varmap, dt, &dev, 0, |vb| nerf(&NerfConfig::default(), vb))?;
    let mut adam = adam(&varmap, 5e-3)?; // decays to 5e-4 over the run
    let aabb = train.scene_box(1.5); // here the silhouettes' visual hull + 5 %
    let side = (0..3).map(|a| aabb[a + 3] - aabb[a]).fold(0.0, f64::max);
    let (mut cells, mut march) = (GridConfig::default(), GridMarchConfig::default());
    (cells.aabb, march.step_size) = (aabb, side / 256.0); // a march at half a cell
    let mut grid = OccupancyGrid::new(cells)?;
    let mut density = |p: &Tensor| net.density(p); // updates the grid, drops hidden samples
    let mut rays = RaySampler::new(&train, 0, &dev, dt)?;
    let (mut config, clock) = (CompositeConfig::default(), std::time::Instant::now());
    let budget = || clock.elapsed().as_secs_f64() / 60.0 / args.minutes; // its fraction spent
    for step in (0..).take_while(|_| budget() < 1.0) {
        let fraction = |c: &[bool]| c.iter().filter(|&&o| o).count() as f64 / c.len() as f64;
        let occupied = || fraction(grid.occupied()); // counted when printed, every 100 steps
        (step % 100 == 0).then(|| println!("step {step}: grid {:.3} occupied", occupied()));
        adam.set_learning_rate(5e-3 * 0.1f64.powf(budget())); // to 5e-4
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
    write_png(&args.out, &Tensor::cat(&views, 1)?)?; // every test view, side by side
    println!("test PSNR {:.2} dB", total / test.views().len() as f64);
    Ok(())
}
