//! End-to-end curves: the bundled training examples, run as child processes
//! (`cargo run --release --example NAME`), with the metrics they print against the wall
//! time they print. Full mode only: each run takes from half a minute to a few minutes.

use crate::report::{Row, Table};

/// How to read one example's progress table: rows are the printed lines of exactly
/// `columns` numbers; `time` is the column of wall seconds, `step` the training step.
struct Curve {
    example: &'static str,
    args: Vec<String>,
    /// What the example trains, for the series names.
    what: &'static str,
    columns: usize,
    step: usize,
    time: usize,
    /// (column, series name, error = 1 − value instead of the value).
    metrics: &'static [(usize, &'static str, bool)],
}

/// Runs `cargo run --release --example NAME -- ARGS` (the `cargo` that runs this command)
/// and returns its standard output, or why it could not.
fn run_example(example: &str, args: &[String]) -> Result<String, String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = std::process::Command::new(cargo)
        .args(["run", "--release", "--quiet", "--example", example, "--"])
        .args(args)
        .output()
        .map_err(|e| format!("could not start cargo: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "{}: {}",
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The rows of numbers with exactly `columns` entries in `stdout`.
fn numeric_rows(stdout: &str, columns: usize) -> Vec<Vec<f64>> {
    stdout
        .lines()
        .filter_map(|l| {
            let v: Option<Vec<f64>> = l.split_whitespace().map(|t| t.parse().ok()).collect();
            v.filter(|v| v.len() == columns)
        })
        .collect()
}

pub fn run(quick: bool) -> Vec<Table> {
    if quick {
        return Vec::new();
    }
    let tmp = std::env::temp_dir();
    let out = |name: &str| tmp.join(name).to_string_lossy().into_owned();
    let curves = [
        Curve {
            example: "quickstart",
            args: vec![out("nf_quickstart_torus.ply")],
            what: "quickstart (torus, 4×64 MLP)",
            columns: 4,
            step: 0,
            time: 3,
            metrics: &[(2, "1 − IoU", true)],
        },
        Curve {
            example: "fit_occupancy",
            args: vec![
                "/usr/share/assimp/models/PLY/Wuson.ply".into(),
                out("nf_fit_occupancy.ply"),
            ],
            what: "fit_occupancy (Wuson.ply, 4×128 MLP)",
            columns: 8,
            step: 0,
            time: 7,
            metrics: &[(2, "1 − IoU", true), (3, "Chamfer-L1", false)],
        },
    ];
    let mut rows = Vec::new();
    let mut notes = Vec::new();
    for c in &curves {
        let stdout = match run_example(c.example, &c.args) {
            Ok(s) => s,
            Err(why) => {
                notes.push(format!("`{}` did not run ({why})", c.example));
                continue;
            }
        };
        let table = numeric_rows(&stdout, c.columns);
        if table.is_empty() {
            notes.push(format!("`{}` printed no progress rows", c.example));
        }
        for r in &table {
            for &(col, name, complement) in c.metrics {
                rows.push(Row {
                    series: format!("{}: {name}", c.what),
                    knob: r[c.step],
                    error: if complement { 1.0 - r[col] } else { r[col] },
                    seconds: r[c.time],
                    work: 0.0,
                });
            }
        }
    }
    vec![Table {
        title: "End-to-end training: error vs wall time".into(),
        description: format!(
            "The bundled examples, each run once by this command with its default settings \
             (`cargo run --release --example quickstart`; `cargo run --release --example \
             fit_occupancy`, which trains for 150 s on Wuson.ply normalised to the unit cube), \
             reading the progress rows they print: the training step, the metric and the wall \
             time since training started (quickstart) or since the example started, labelling \
             included (fit_occupancy). IoU on held-out uniform points of the padded cube; \
             Chamfer-L1 of the MISE mesh against the input mesh (100 000 samples each, \
             unscaled: the ONet papers print ×10).{}",
            if notes.is_empty() {
                String::new()
            } else {
                format!(" Not measured: {}.", notes.join("; "))
            }
        ),
        knob: "training step".into(),
        error_name: "error (1 − IoU, or Chamfer-L1)".into(),
        work_unit: String::new(),
        time_name: "wall time since start (s)".into(),
        rows,
    }]
}
