//! What the examples that train on datasets share: the held-out split, the scene box,
//! the NaN/Inf guard, the named variables and the JSON writer.
#![allow(dead_code)] // each example uses a part

use candle_core::{DType, Tensor, Var};
use candle_nn::VarMap;
use neural_fields::data::{load, Bounds, Dataset, LoadConfig, Split};
use neural_fields::{Error, Result};
use std::path::Path;

/// The held-out split of the dataset in `dir`: `test` if the layout has one, else `val`,
/// loaded with `config` (whose split is replaced); returns it with its name.
pub fn load_eval(dir: &Path, config: &LoadConfig) -> Result<(Dataset, &'static str)> {
    let with = |split| LoadConfig {
        split,
        ..config.clone()
    };
    match load(dir, &with(Split::Test)) {
        Ok(d) => Ok((d, "test")),
        Err(_) => Ok((load(dir, &with(Split::Val))?, "val")),
    }
}

/// The scene box `[x0, y0, z0, x1, y1, z1]`: the layout's bounds (nerfstudio's
/// `aabb_scale`, DTU's unit sphere), or the cube of half-side `half` for layouts that
/// state none (Blender).
pub fn scene_box(data: &Dataset, half: f64) -> [f64; 6] {
    match data.bounds() {
        Some(Bounds::Aabb { min, max }) => [min[0], min[1], min[2], max[0], max[1], max[2]],
        Some(Bounds::Sphere {
            center: c,
            radius: r,
        }) => [c[0] - r, c[1] - r, c[2] - r, c[0] + r, c[1] + r, c[2] + r],
        _ => [-half, -half, -half, half, half, half],
    }
}

/// The finest resolution of a hash grid for `data`: five cells per pixel of its images'
/// larger side (100 px → 500; instant-NGP's 2048 is for 800 px), at least 16.
pub fn hash_finest(data: &Dataset) -> f64 {
    let side = data
        .views()
        .iter()
        .map(|v| {
            let k = v.camera().intrinsics();
            k.width.max(k.height)
        })
        .max()
        .unwrap_or(1);
    ((5 * side) as f64).max(16.0)
}

/// Stops on a NaN or infinity in `t`, naming the step and the tensor.
pub fn check_finite(t: &Tensor, step: usize, what: &str) -> Result<()> {
    let s = t
        .abs()?
        .sum_all()?
        .to_dtype(DType::F64)?
        .to_scalar::<f64>()?;
    if s.is_finite() {
        Ok(())
    } else {
        Err(Error::InvalidArgument {
            arg: "training",
            expected: "finite losses, gradients and weights".into(),
            got: format!("a NaN or infinity in {what} at step {step}"),
        })
    }
}

/// The variables of `varmap` with their names, sorted by name.
pub fn named_vars(varmap: &VarMap) -> Vec<(String, Var)> {
    let data = varmap.data().lock().expect("an unpoisoned varmap");
    let mut vars: Vec<_> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    vars
}

/// Checks the gradients of `vars` in `grads` (those that have one), naming the variable.
pub fn check_gradients(
    grads: &candle_core::backprop::GradStore,
    vars: &[(String, Var)],
    step: usize,
) -> Result<()> {
    for (name, var) in vars {
        if let Some(g) = grads.get(var) {
            check_finite(g, step, &format!("the gradient of {name}"))?;
        }
    }
    Ok(())
}

/// Checks the values of `vars`, naming the variable.
pub fn check_weights(vars: &[(String, Var)], step: usize) -> Result<()> {
    for (name, var) in vars {
        check_finite(var.as_tensor(), step, &format!("the weight {name}"))?;
    }
    Ok(())
}

/// Writes `value` as pretty JSON to `path`.
pub fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    std::fs::write(path, serde_json::to_string_pretty(value).expect("JSON")).map_err(|source| {
        Error::Io {
            path: path.display().to_string(),
            source,
        }
    })
}

/// Writes `text` to `path`.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Creates the output folder.
pub fn create_dir(path: &Path) -> Result<()> {
    std::fs::create_dir_all(path).map_err(|source| Error::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Calls `take(flag, value)` for each `--flag value` pair of the command line; `--help`
/// (or a flag without a value) returns the usage.
pub fn parse_flags(
    usage: &str,
    mut take: impl FnMut(&str, &str) -> std::result::Result<(), String>,
) -> std::result::Result<(), String> {
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        if flag == "--help" || flag == "-h" {
            return Err(usage.into());
        }
        let value = it.next().ok_or(format!("{flag} needs a value\n{usage}"))?;
        take(&flag, &value)?;
    }
    Ok(())
}

/// `value` of `flag` as a number.
pub fn number(flag: &str, value: &str) -> std::result::Result<f64, String> {
    value
        .parse()
        .map_err(|_| format!("{flag}: not a number: {value}"))
}

/// `value` of `flag` as a count.
pub fn count(flag: &str, value: &str) -> std::result::Result<usize, String> {
    value
        .parse()
        .map_err(|_| format!("{flag}: not a count: {value}"))
}

/// `value` of `flag` as two finite numbers `A,B`.
pub fn pair(flag: &str, value: &str, example: &str) -> std::result::Result<[f64; 2], String> {
    let bad = || format!("{flag}: two numbers like {example}, not {value}");
    let parts: Vec<f64> = value
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| bad())?;
    match parts[..] {
        [a, b] if a.is_finite() && b.is_finite() => Ok([a, b]),
        _ => Err(bad()),
    }
}

/// `--coarse-to-fine START,END`: the fractions of training over which the coarse-to-fine
/// windows open (0 ≤ START < END). With END > 1 the windows are still opening when
/// training ends (at `(1 − START)/(END − START)` of their bands), which caps the
/// encoding's frequencies.
pub fn window_span(flag: &str, value: &str) -> std::result::Result<(f64, f64), String> {
    match pair(flag, value, "0.1,0.5")? {
        [s, e] if 0.0 <= s && s < e && s < 1.0 => Ok((s, e)),
        _ => Err(format!(
            "{flag}: START,END with 0 ≤ START < 1 and START < END, not {value}"
        )),
    }
}

/// Opens each window to `α = bands · clamp((progress − START)/(END − START), 0, 1)`;
/// `span: None` opens them fully. Evaluations after training pass `progress = 1`: the
/// windows as training left them.
pub fn open_windows(
    windows: &[neural_fields::encoding::CoarseToFine],
    progress: f64,
    span: Option<(f64, f64)>,
) -> Result<()> {
    let open = span.map_or(1.0, |(start, end)| {
        ((progress - start) / (end - start)).clamp(0.0, 1.0)
    });
    for w in windows {
        w.set_alpha(open * w.bands() as f64)?;
    }
    Ok(())
}

/// `value` of `flag` as `on` or `off`.
pub fn on_off(flag: &str, value: &str) -> std::result::Result<bool, String> {
    match value {
        "on" => Ok(true),
        "off" => Ok(false),
        other => Err(format!("{flag}: on or off, not {other}")),
    }
}

/// The training budget of the command line's `--data`, `--minutes`, `--steps`, `--out`
/// and `--seed`: takes one of those flags (returns `false` for any other).
pub fn take_run_flag(
    flag: &str,
    value: &str,
    data: &mut std::path::PathBuf,
    minutes: &mut Option<f64>,
    steps: &mut Option<usize>,
    out: &mut std::path::PathBuf,
    seed: &mut u64,
) -> std::result::Result<bool, String> {
    match flag {
        "--data" => *data = value.into(),
        "--minutes" => *minutes = Some(number(flag, value)?),
        "--steps" => *steps = Some(count(flag, value)?),
        "--out" => *out = value.into(),
        "--seed" => {
            *seed = value
                .parse()
                .map_err(|_| format!("--seed: not a u64: {value}"))?
        }
        _ => return Ok(false),
    }
    Ok(true)
}

/// `--minutes` or `--steps`, not both, `default_minutes` when neither; positive minutes.
pub fn check_budget(
    minutes: &mut Option<f64>,
    steps: Option<usize>,
    default_minutes: f64,
) -> std::result::Result<(), String> {
    if minutes.is_some() && steps.is_some() {
        return Err("give --minutes or --steps, not both".into());
    }
    if minutes.is_none() && steps.is_none() {
        *minutes = Some(default_minutes);
    }
    if minutes.is_some_and(|m| !(m > 0.0 && m.is_finite())) {
        return Err("--minutes must be positive".into());
    }
    Ok(())
}

/// A training run's clock: the budget (`steps`, or seconds of training with evaluation
/// excluded) and its progress bar.
pub struct Clock {
    steps: Option<usize>,
    seconds: Option<f64>,
    start: std::time::Instant,
    paused: f64,
    /// The progress bar (steps, or seconds of training).
    pub bar: indicatif::ProgressBar,
}

impl Clock {
    /// Starts the clock for `steps` or `minutes` (one of them; `--steps 0` trains nothing).
    pub fn start(steps: Option<usize>, minutes: Option<f64>) -> Self {
        let seconds = minutes.map(|m| m * 60.0);
        let len = match (steps, seconds) {
            (Some(n), _) => n as u64,
            (None, Some(s)) => s.ceil() as u64,
            (None, None) => 0,
        };
        let bar = indicatif::ProgressBar::new(len);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] {pos}/{len} {msg}",
            )
            .expect("template")
            .progress_chars("=> "),
        );
        Self {
            steps,
            seconds,
            start: std::time::Instant::now(),
            paused: 0.0,
            bar,
        }
    }

    /// Seconds of training so far (evaluation excluded).
    pub fn train_seconds(&self) -> f64 {
        self.start.elapsed().as_secs_f64() - self.paused
    }

    /// The fraction of the budget spent before `step`; 1 or more ends the run.
    pub fn progress(&self, step: usize) -> f64 {
        match (self.steps, self.seconds) {
            (Some(0), _) => 1.0,
            (Some(n), _) => step as f64 / n as f64,
            (None, Some(s)) => self.train_seconds() / s,
            (None, None) => 1.0,
        }
    }

    /// Moves the bar to `step` done.
    pub fn tick(&self, step: usize) {
        match self.steps {
            Some(_) => self.bar.set_position(step as u64),
            None => self.bar.set_position(self.train_seconds() as u64),
        }
    }

    /// Runs `f` (an evaluation) off the training clock, printing above the bar.
    pub fn off_clock<T>(&mut self, f: impl FnOnce() -> T) -> T {
        let t = std::time::Instant::now();
        let out = self.bar.suspend(f);
        self.paused += t.elapsed().as_secs_f64();
        out
    }
}
