//! Occupancy Flow (Niemeyer et al., ICCV 2019) on a torus that twists, stretches and
//! moves: learn an occupancy decoder at time 0 and a velocity field whose flow carries
//! it through time, then report IoU over time, the error of the correspondences, and
//! meshes of every time with the same vertices (the time-0 mesh carried forward).
//!
//! ```text
//! cargo run --release --example occupancy_flow                      # 8 minutes
//! cargo run --release --example occupancy_flow -- --minutes 3 --out /tmp/oflow
//! cargo run --release --example occupancy_flow -- --steps 500 --solver dopri5:1e-3
//! ```
//!
//! Flags: `--minutes M` or `--steps N` (default 8 minutes of training, evaluation not
//! counted), `--out DIR` (default `target/occupancy_flow`), `--seed S`, `--solver` for
//! training (`rk4:N`, N steps per unit of time, default `rk4:4`; or `dopri5:RTOL`, with
//! `atol = RTOL/100`). Evaluation always integrates with Dormand–Prince at `rtol 1e-5`.
//!
//! The motion is analytic ([`DeformingTorus`]), so occupancy and
//! correspondences are exact at every time. Each step draws, as Occupancy Flow trains:
//! points at time 0 (BCE on the decoder), points at a random time carried back to 0
//! (BCE through the flow), and surface points of time 0 carried forward to
//! t ∈ {¼, ½, ¾, 1} (the correspondence loss, mean Euclidean distance, not squared).
//!
//! Writes to `OUT/`: `metrics.json` (`iou` per time, `iou_min`, `correspondence_l2` per
//! time, `correspondence_mean`, `correspondence_max`, `train_seconds`, `steps`, `solver`),
//! `curve.csv` (training seconds, step, loss, `iou_min`, `correspondence_mean`) and
//! `mesh_t0.00.ply` … `mesh_t1.00.ply` (the same faces at every time). Stops with an
//! error naming the step if a loss, a gradient or a weight becomes NaN or infinite.

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use clap::Parser;
use neural_fields::encoding::{FrequencyEncoding, PointEncoding};
use neural_fields::field::ImplicitSurface;
use neural_fields::flow::{
    correspondence_loss, velocity_field, DeformingTorus, Graph, OccupancyFlow, Solver,
    VelocityField, VelocityFieldConfig,
};
use neural_fields::mesh::{points_from_tensor, points_to_tensor};
use neural_fields::nn::{
    adam, build_seeded, mlp, Activation, Budget, Clock, FiniteGuard, Mlp, MlpConfig,
};
use neural_fields::numerics::bce_with_logits;
use neural_fields::occupancy::{iou, mise, MiseConfig};
use neural_fields::rng::SplitMix64;
use neural_fields::{Error, Result};
use serde_json::json;
use std::path::{Path, PathBuf};

/// Times at which the correspondence loss and the evaluation look.
const TIMES: [f64; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// Occupancy Flow on a torus that twists, stretches and moves: IoU over time, the error
/// of the correspondences, and meshes of every time with the same faces.
#[derive(Parser, Debug)]
struct Args {
    /// Minutes of training, evaluation not counted (default 8 without --steps).
    #[arg(long, conflicts_with = "steps")]
    minutes: Option<f64>,
    /// Training steps instead of minutes.
    #[arg(long)]
    steps: Option<usize>,
    /// The folder for metrics.json, curve.csv and the meshes.
    #[arg(long, default_value = "target/occupancy_flow")]
    out: PathBuf,
    /// The seed of the networks' weights and of the training points.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The training solver: rk4:N (N steps per unit of time) or dopri5:RTOL (atol =
    /// RTOL/100).
    #[arg(long, default_value = "rk4:4", value_parser = parse_solver)]
    solver: SolverFlag,
}

/// `--solver` as given, and the solver it names.
#[derive(Clone, Debug)]
struct SolverFlag {
    solver: Solver,
    name: String,
}

fn parse_solver(value: &str) -> std::result::Result<SolverFlag, String> {
    let solver = match value.split_once(':') {
        Some(("rk4", n)) => Solver::Rk4 {
            steps: n.parse().map_err(|_| format!("rk4:N: not a count: {n}"))?,
        },
        Some(("dopri5", r)) => {
            let rtol: f64 = r
                .parse()
                .map_err(|_| format!("dopri5:RTOL: not a number: {r}"))?;
            Solver::Dopri5 {
                rtol,
                atol: rtol / 100.0,
                max_steps: 10_000,
            }
        }
        _ => return Err(format!("rk4:N or dopri5:RTOL, not {value}")),
    };
    Ok(SolverFlag {
        solver,
        name: value.into(),
    })
}

/// Writes `text` to `path`.
fn write(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })
}

/// The two networks and their optimiser.
struct Model {
    varmap: VarMap,
    decoder: Mlp,
    velocity: VelocityField,
}

impl Model {
    fn new(seed: u64, device: &Device, dtype: DType) -> Result<Self> {
        let varmap = VarMap::new();
        let decoder_config = MlpConfig {
            hidden: 128,
            depth: 4,
            activation: Activation::Relu,
            encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 6)?),
            ..MlpConfig::default()
        };
        let decoder = build_seeded(&varmap, dtype, device, seed, |vb| {
            mlp(&decoder_config, vb.pp("decoder"))
        })?;
        let velocity_config = VelocityFieldConfig {
            hidden: 64,
            blocks: 3,
            code_dim: 0,
        };
        let velocity = build_seeded(&varmap, dtype, device, seed + 1, |vb| {
            velocity_field(&velocity_config, vb.pp("velocity"))
        })?;
        Ok(Self {
            varmap,
            decoder,
            velocity,
        })
    }

    fn flow(&self, solver: Solver, graph: Graph) -> OccupancyFlow<'_, Mlp> {
        OccupancyFlow {
            decoder: &self.decoder,
            velocity: &self.velocity,
            code: None,
            solver,
            graph,
        }
    }
}

/// Labelled points at time `t`: half uniform in the padded cube, half near the moved
/// surface (time-0 surface points plus Gaussian noise of σ = 0.03, carried by `Φ`).
fn labelled(n: usize, t: f64, rng: &mut SplitMix64) -> (Vec<[f64; 3]>, Vec<f32>) {
    let motion = DeformingTorus::default();
    let mut pts = Vec::with_capacity(n);
    for _ in 0..n / 2 {
        pts.push([0.0; 3].map(|_| 1.1 * rng.uniform() - 0.55));
    }
    let surface = motion
        .surface(n - n / 2, rng)
        .expect("the default torus and a training batch's count are valid"); // invariant
    for s in surface {
        let jittered = [0, 1, 2].map(|i| s[i] + 0.03 * rng.normal());
        pts.push(motion.carry(jittered, 0.0, t));
    }
    let labels = pts
        .iter()
        .map(|&p| f32::from(u8::from(motion.inside(p, t))))
        .collect();
    (pts, labels)
}

/// What the evaluation measures.
struct Evaluation {
    iou: Vec<f64>,
    correspondence: Vec<f64>,
}

impl Evaluation {
    fn iou_min(&self) -> f64 {
        self.iou.iter().copied().fold(f64::INFINITY, f64::min)
    }
    /// Mean over the times after 0.
    fn correspondence_mean(&self) -> f64 {
        self.correspondence[1..].iter().sum::<f64>() / (self.correspondence.len() - 1) as f64
    }
}

/// The held-out points: uniform points in the padded cube with their occupancy at each
/// time, and surface points of time 0 with where they are at each time.
struct Held {
    uniform: Tensor,
    truth: Vec<Vec<bool>>,
    surface: Tensor,
    surface_truth: Vec<Tensor>,
}

impl Held {
    fn new(device: &Device, dtype: DType) -> Result<Self> {
        let motion = DeformingTorus::default();
        let mut rng = SplitMix64::new(1234);
        let uniform: Vec<[f64; 3]> = (0..50_000)
            .map(|_| [0.0; 3].map(|_| 1.1 * rng.uniform() - 0.55))
            .collect();
        let truth = TIMES
            .iter()
            .map(|&t| uniform.iter().map(|&p| motion.inside(p, t)).collect())
            .collect();
        let surface = motion.surface(4000, &mut rng)?;
        let surface_truth = TIMES
            .iter()
            .map(|&t| {
                let moved: Vec<[f64; 3]> =
                    surface.iter().map(|&p| motion.carry(p, 0.0, t)).collect();
                points_to_tensor(&moved, device, dtype)
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            uniform: points_to_tensor(&uniform, device, dtype)?,
            truth,
            surface: points_to_tensor(&surface, device, dtype)?,
            surface_truth,
        })
    }
}

fn eval_solver() -> Solver {
    Solver::Dopri5 {
        rtol: 1e-5,
        atol: 1e-7,
        max_steps: 10_000,
    }
}

fn evaluate(model: &Model, held: &Held) -> Result<Evaluation> {
    let flow = model.flow(eval_solver(), Graph::Detach);
    let mut ious = Vec::new();
    for (i, &t) in TIMES.iter().enumerate() {
        let mut inside = Vec::with_capacity(held.truth[i].len());
        for chunk in 0..held.uniform.dim(0)?.div_ceil(25_000) {
            let n = (held.uniform.dim(0)? - chunk * 25_000).min(25_000);
            let p = held.uniform.narrow(0, chunk * 25_000, n)?;
            let logits = flow.logits(&p, t)?.to_dtype(DType::F64)?.to_vec1::<f64>()?;
            inside.extend(logits.into_iter().map(|l| l > 0.0));
        }
        ious.push(iou(&inside, &held.truth[i])?);
    }
    let moved = flow.correspondences(&held.surface, &TIMES)?;
    let correspondence = moved
        .iter()
        .zip(&held.surface_truth)
        .map(|(m, truth)| {
            let l = correspondence_loss(m, truth)?;
            Ok(l.to_dtype(DType::F64)?.to_scalar::<f64>()?)
        })
        .collect::<Result<_>>()?;
    Ok(Evaluation {
        iou: ious,
        correspondence,
    })
}

fn train_step(
    model: &Model,
    opt: &mut neural_fields::nn::Adam,
    solver: Solver,
    rng: &mut SplitMix64,
    device: &Device,
    dtype: DType,
) -> Result<(Tensor, candle_core::backprop::GradStore)> {
    let flow = model.flow(solver, Graph::Keep);
    let labels = |l: Vec<f32>| -> Result<Tensor> {
        Ok(Tensor::from_vec(l.clone(), l.len(), device)?.to_dtype(dtype)?)
    };
    // BCE at time 0 (the decoder alone).
    let (p0, y0) = labelled(2048, 0.0, rng);
    let logits0 = flow.logits(&points_to_tensor(&p0, device, dtype)?, 0.0)?;
    let bce0 = bce_with_logits(&logits0, &labels(y0)?)?.mean_all()?;
    // BCE at a random time, through the flow.
    let t = 0.05 + 0.95 * rng.uniform();
    let (pt, yt) = labelled(1024, t, rng);
    let logits_t = flow.logits(&points_to_tensor(&pt, device, dtype)?, t)?;
    let bce_t = bce_with_logits(&logits_t, &labels(yt)?)?.mean_all()?;
    // Correspondences: time-0 surface points carried to every time.
    let motion = DeformingTorus::default();
    let surface = motion.surface(256, rng)?;
    let moved = flow.correspondences(&points_to_tensor(&surface, device, dtype)?, &TIMES[1..])?;
    let mut corr = Tensor::zeros((), dtype, device)?;
    for (m, &t) in moved.iter().zip(&TIMES[1..]) {
        let truth: Vec<[f64; 3]> = surface.iter().map(|&p| motion.carry(p, 0.0, t)).collect();
        let l = correspondence_loss(m, &points_to_tensor(&truth, device, dtype)?)?;
        corr = (corr + l)?;
    }
    let corr = corr.affine(1.0 / (TIMES.len() - 1) as f64, 0.0)?;
    let loss = ((bce0 + bce_t)? + corr.affine(10.0, 0.0)?)?;
    let grads = loss.backward()?;
    opt.step(&grads)?;
    Ok((loss, grads))
}

fn run(a: &Args) -> Result<()> {
    let device = Device::Cpu;
    let dtype = DType::F32;
    std::fs::create_dir_all(&a.out).map_err(|source| Error::Io {
        path: a.out.display().to_string(),
        source,
    })?;
    let model = Model::new(a.seed, &device, dtype)?;
    let guard = FiniteGuard::new(&model.varmap);
    let mut opt = adam(&model.varmap, 1e-3)?;
    let held = Held::new(&device, dtype)?;
    let mut rng = SplitMix64::new(a.seed.wrapping_add(99));
    let mut clock = Clock::start(match a.steps {
        Some(n) => Budget::Steps(n),
        None => Budget::Minutes(a.minutes.unwrap_or(8.0)),
    })?;
    let bar = indicatif::ProgressBar::new(1000);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {percent}% {msg}")
            .expect("template")
            .progress_chars("=> "),
    );
    let mut curve = String::from("seconds,step,loss,iou_min,correspondence_mean\n");
    let mut next_eval = 120.0;
    let mut lr_dropped = false;
    let mut step = 0;
    let mut last_loss = f64::NAN;
    while clock.progress(step) < 1.0 {
        let (loss, grads) =
            train_step(&model, &mut opt, a.solver.solver, &mut rng, &device, dtype)?;
        guard.check(step, &loss, (step % 50 == 0).then_some(&grads))?;
        last_loss = loss.to_dtype(DType::F64)?.to_scalar::<f64>()?;
        step += 1;
        bar.set_position((1000.0 * clock.progress(step).min(1.0)) as u64);
        bar.set_message(format!("loss {last_loss:.4}"));
        if !lr_dropped && clock.progress(step) > 0.75 {
            opt.set_learning_rate(3e-4);
            lr_dropped = true;
        }
        if clock.train_seconds() > next_eval && clock.progress(step) < 1.0 {
            next_eval += 120.0;
            let seconds = clock.train_seconds();
            let e = clock.pause(|| {
                bar.suspend(|| -> Result<Evaluation> {
                    let e = evaluate(&model, &held)?;
                    println!(
                        "{seconds:>6.0} s  step {step:>5}  loss {last_loss:.4}  IoU min {:.4}  correspondence {:.4}",
                        e.iou_min(),
                        e.correspondence_mean()
                    );
                    Ok(e)
                })
            })?;
            curve += &format!(
                "{seconds:.1},{step},{last_loss:.6},{:.5},{:.5}\n",
                e.iou_min(),
                e.correspondence_mean()
            );
        }
    }
    bar.finish_and_clear();
    let train_seconds = clock.train_seconds();
    let e = evaluate(&model, &held)?;
    curve += &format!(
        "{train_seconds:.1},{step},{last_loss:.6},{:.5},{:.5}\n",
        e.iou_min(),
        e.correspondence_mean()
    );
    write(&a.out.join("curve.csv"), &curve)?;
    // Meshes: MISE on the time-0 decoder, its vertices carried to every time.
    let out = mise(
        &model.decoder as &dyn ImplicitSurface,
        &MiseConfig {
            resolution0: 32,
            upsampling_steps: 2,
            device: device.clone(),
            dtype,
            ..MiseConfig::new(32, 2, &Device::Cpu, DType::F32)
        },
    )?;
    let mut mesh = out.mesh;
    if mesh.faces.is_empty() {
        println!("the time-0 decoder has no surface: no meshes written");
    } else {
        let verts = points_to_tensor(&mesh.vertices, &device, dtype)?;
        let moved = model
            .flow(eval_solver(), Graph::Detach)
            .correspondences(&verts, &TIMES)?;
        for (m, t) in moved.iter().zip(TIMES) {
            mesh.vertices = points_from_tensor(&m.to_dtype(DType::F64)?)?;
            mesh.save(a.out.join(format!("mesh_t{t:.2}.ply")))?;
        }
    }
    let by_time = |v: &[f64], skip: usize| -> serde_json::Value {
        TIMES
            .iter()
            .zip(v)
            .skip(skip)
            .map(|(t, x)| (format!("{t:.2}"), json!(x)))
            .collect::<serde_json::Map<_, _>>()
            .into()
    };
    let metrics = json!({
        "iou": by_time(&e.iou, 0),
        "iou_min": e.iou_min(),
        "correspondence_l2": by_time(&e.correspondence, 1),
        "correspondence_mean": e.correspondence_mean(),
        "correspondence_max": e.correspondence[1..].iter().copied().fold(0.0, f64::max),
        "train_seconds": train_seconds,
        "steps": step,
        "solver": a.solver.name,
        "eval_solver": "dopri5:1e-5",
    });
    let metrics = serde_json::to_string_pretty(&metrics).expect("JSON");
    write(&a.out.join("metrics.json"), &metrics)?;
    println!("{metrics}");
    println!("wrote {}", a.out.display());
    Ok(())
}

fn main() {
    let a = Args::parse();
    if let Err(e) = run(&a) {
        eprintln!("occupancy_flow: {e}");
        std::process::exit(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A few steps train without error and every output is finite.
    #[test]
    fn a_short_run_writes_finite_metrics_and_meshes() {
        let out = std::env::temp_dir().join("occupancy_flow_test");
        let a = Args {
            minutes: None,
            steps: Some(3),
            out: out.clone(),
            seed: 1,
            solver: parse_solver("rk4:2").expect("a solver"),
        };
        run(&a).expect("a short run");
        let text = std::fs::read_to_string(out.join("metrics.json")).expect("metrics.json");
        let m: serde_json::Value = serde_json::from_str(&text).expect("JSON");
        for key in ["iou_min", "correspondence_mean", "train_seconds"] {
            assert!(m[key].as_f64().is_some_and(f64::is_finite), "{key}: {m}");
        }
    }
}
