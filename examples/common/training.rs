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
