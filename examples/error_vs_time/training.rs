//! End-to-end curves: the bundled training examples, run as child processes
//! (`cargo run --release --example NAME`), with the metrics they print against the wall
//! time they print, or the `curve.csv` they write. Full mode only: each run takes from
//! half a minute to a few minutes.

use crate::report::{Row, Table};

/// How to read one example's progress table: rows are the printed lines of exactly
/// `columns` numbers (after the run's label, for examples that train several runs);
/// `time` is the column of wall seconds, `step` the training step.
struct Curve {
    example: &'static str,
    args: Vec<String>,
    /// What the example trains, for the series names.
    what: &'static str,
    /// The labels that start the progress rows of each run the example prints (one
    /// series per run), or none for unlabelled rows.
    runs: &'static [&'static str],
    columns: usize,
    step: usize,
    time: usize,
    /// (column, series name, how the column becomes an error).
    metrics: &'static [(usize, &'static str, Metric)],
}

/// How a printed metric becomes the error plotted.
#[derive(Clone, Copy)]
enum Metric {
    /// The value itself (Chamfer-L1).
    Value,
    /// 1 − value (IoU).
    OneMinus,
    /// The mean squared error 10^(−PSNR/10) of a PSNR in dB.
    MseOfPsnr,
}

impl Metric {
    fn error(self, v: f64) -> f64 {
        match self {
            Metric::Value => v,
            Metric::OneMinus => 1.0 - v,
            Metric::MseOfPsnr => 10f64.powf(-v / 10.0),
        }
    }
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

/// The flags of the committed-dataset examples' runs read from `curve.csv`: two minutes
/// of training, no pictures.
const CSV_FLAGS: &[&str] = &["--minutes", "2", "--pictures", "0"];

/// The folder `--out` of one variant's run (a temporary folder named after it).
fn variant_out(example: &str, label: &str) -> std::path::PathBuf {
    let dir: String = label
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    std::env::temp_dir().join(format!("nf_{example}_{dir}"))
}

/// A training example on `data` (the series' name for its data), once per variant
/// (`(label, flags)`: the flags added to `common` and `--out DIR`, the label naming the
/// series): the rows of its `curve.csv` (`step, train_seconds, metric…`) as errors against
/// training seconds, one series per metric column (`(column, name, how it becomes an
/// error)`).
fn csv_curves(
    rows: &mut Vec<Row>,
    notes: &mut Vec<String>,
    (example, data, common): (&str, &str, &[&str]),
    variants: &[(&str, &[&str])],
    metrics: &[(usize, &str, Metric)],
) {
    for &(label, flags) in variants {
        let out = variant_out(example, label);
        let args: Vec<String> = common
            .iter()
            .chain(flags)
            .chain(&["--out"])
            .map(|s| s.to_string())
            .chain([out.to_string_lossy().into_owned()])
            .collect();
        let run = format!("`{example} {}`", flags.join(" "));
        if let Err(why) = run_example(example, &args) {
            notes.push(format!("{run} did not run ({why})"));
            continue;
        }
        let csv = match std::fs::read_to_string(out.join("curve.csv")) {
            Ok(s) => s,
            Err(e) => {
                notes.push(format!("{run} wrote no curve.csv ({e})"));
                continue;
            }
        };
        for line in csv.lines().skip(1) {
            let v: Vec<f64> = line
                .split(',')
                .filter_map(|t| t.trim().parse().ok())
                .collect();
            for &(col, name, metric) in metrics {
                if let (Some(&step), Some(&seconds), Some(&x)) = (v.first(), v.get(1), v.get(col)) {
                    rows.push(Row {
                        series: format!("{example} ({data}, {label}): {name}"),
                        knob: step,
                        error: metric.error(x),
                        seconds,
                        work: 0.0,
                    });
                }
            }
        }
    }
}

/// The rows of numbers with exactly `columns` entries in `stdout`; with a `label`, only
/// the lines that start with it (the label itself not counted).
fn numeric_rows(stdout: &str, columns: usize, label: Option<&str>) -> Vec<Vec<f64>> {
    stdout
        .lines()
        .filter_map(|l| {
            let mut tokens = l.split_whitespace();
            if let Some(label) = label {
                if tokens.next() != Some(label) {
                    return None;
                }
            }
            let v: Option<Vec<f64>> = tokens.map(|t| t.parse().ok()).collect();
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
            args: vec!["--out".into(), out("nf_quickstart")],
            what: "quickstart (torus, 4×64 MLP)",
            runs: &[],
            columns: 4,
            step: 0,
            time: 3,
            metrics: &[(2, "1 − IoU", Metric::OneMinus)],
        },
        Curve {
            example: "quickstart",
            args: vec![
                "--encoding".into(),
                "hash".into(),
                "--out".into(),
                out("nf_quickstart_hash"),
            ],
            what: "quickstart --encoding hash (torus, hash grid + 2×64 MLP)",
            runs: &[],
            columns: 4,
            step: 0,
            time: 3,
            metrics: &[(2, "1 − IoU", Metric::OneMinus)],
        },
        Curve {
            example: "fit_occupancy",
            args: vec![
                "--out".into(),
                out("nf_fit_occupancy"),
                "/usr/share/assimp/models/PLY/Wuson.ply".into(),
            ],
            what: "fit_occupancy (Wuson.ply, 4×128 MLP)",
            runs: &[],
            columns: 8,
            step: 0,
            time: 7,
            metrics: &[
                (2, "1 − IoU", Metric::OneMinus),
                (3, "Chamfer-L1", Metric::Value),
            ],
        },
        Curve {
            example: "tiny_nerf",
            args: vec!["--out".into(), out("nf_tiny_nerf")],
            what: "tiny_nerf (fuzzy ball, 4×64 MLP)",
            runs: &["stratified", "grid"],
            columns: 6,
            step: 0,
            time: 5,
            metrics: &[(2, "held-out MSE", Metric::MseOfPsnr)],
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
        let runs: Vec<Option<&str>> = if c.runs.is_empty() {
            vec![None]
        } else {
            c.runs.iter().map(|r| Some(*r)).collect()
        };
        for run in runs {
            let table = numeric_rows(&stdout, c.columns, run);
            if table.is_empty() {
                notes.push(format!("`{}` printed no progress rows", c.example));
            }
            let what = match run {
                Some(run) => format!("{}, {run}", c.what),
                None => c.what.to_string(),
            };
            for r in &table {
                for &(col, name, metric) in c.metrics {
                    rows.push(Row {
                        series: format!("{what}: {name}"),
                        knob: r[c.step],
                        error: metric.error(r[col]),
                        seconds: r[c.time],
                        work: 0.0,
                    });
                }
            }
        }
    }
    // Trained through the images' own pixel filter (4 rays per pixel from Cycles'
    // Blackman-Harris window, their mean against the pixel) and evaluated with it.
    const THROUGH_FILTER: &[&str] = &[
        "--train-supersample",
        "2",
        "--pixel-filter",
        "cycles",
        "--eval-supersample",
        "3",
    ];
    let hash_through_filter: Vec<&str> = ["--encoding", "hash"]
        .iter()
        .chain(THROUGH_FILTER)
        .copied()
        .collect();
    csv_curves(
        &mut rows,
        &mut notes,
        ("nerf", "wuson", CSV_FLAGS),
        &[
            ("grid", &["--sampler", "grid"]),
            ("stratified", &["--sampler", "stratified"]),
            ("proposal", &["--sampler", "proposal"]),
            ("hash", &["--encoding", "hash"]),
            ("hash, Cycles' pixel filter", &hash_through_filter),
            ("PE, Cycles' pixel filter", THROUGH_FILTER),
        ],
        &[(2, "held-out MSE", Metric::MseOfPsnr)],
    );
    csv_curves(
        &mut rows,
        &mut notes,
        ("dvr_multiview", "wuson", CSV_FLAGS),
        &[
            ("dvr", &["--model", "dvr"]),
            ("idr", &["--model", "idr"]),
            ("hash", &["--encoding", "hash"]),
        ],
        &[
            (2, "held-out 1 − mask IoU", Metric::OneMinus),
            (3, "held-out masked MSE", Metric::MseOfPsnr),
        ],
    );
    // The shape prior across a collection of 100 shapes per category, generated (once) by
    // the first run into its output folder and read by the others.
    let collection = variant_out("shape_prior", "points").join("collection");
    let collection = collection.to_string_lossy().into_owned();
    let with_data =
        |input: &'static str| -> [&str; 4] { ["--input", input, "--data", &collection] };
    let (voxels, image) = (with_data("voxels"), with_data("image"));
    csv_curves(
        &mut rows,
        &mut notes,
        (
            "shape_prior",
            "100 shapes per category",
            &[
                "--minutes",
                "3",
                "--shapes-per-category",
                "100",
                "--test-shapes",
                "32",
            ],
        ),
        &[
            ("points", &["--input", "points"]),
            ("voxels", &voxels),
            ("image", &image),
        ],
        &[(2, "1 − test IoU (32 shapes)", Metric::OneMinus)],
    );
    vec![Table {
        title: "End-to-end training: error vs wall time".into(),
        description: format!(
            "The bundled examples, each run once by this command with its default settings \
             (`cargo run --release --example quickstart`, and again with `-- --encoding hash`; \
             `cargo run --release --example fit_occupancy`, which trains for 150 s on \
             Wuson.ply normalised to the unit cube; `cargo run --release --example tiny_nerf`, \
             which trains a NeRF twice, with stratified samples and with occupancy-grid \
             skipping), reading the progress rows they print: the training step, the metric \
             and the wall time since training started (quickstart, tiny_nerf) or since the \
             example started, labelling included (fit_occupancy). IoU on held-out uniform \
             points of the padded cube; Chamfer-L1 of the MISE mesh against the input mesh \
             (100 000 samples each, unscaled: the ONet papers print ×10); held-out MSE = \
             10^(−PSNR/10) of tiny_nerf's held-out view (the training time excludes rendering \
             it); NeRF on the committed dataset (`cargo run --release --example nerf -- \
             --minutes 2 --sampler S`, once per sampler, and `--encoding hash` with the grid \
             sampler; and both encodings trained and evaluated through Cycles' pixel filter, \
             `--encoding pe|hash --train-supersample 2 --pixel-filter cycles \
             --eval-supersample 3`), the held-out MSE of its `curve.csv` (PSNR on the first 4 \
             test views every 250 steps) against training seconds (evaluation excluded); 3-D \
             reconstruction from the committed dataset's masked views (`cargo run --release \
             --example dvr_multiview -- --minutes 2` with `--model dvr` (an occupancy network \
             and a texture field), `--model idr` (IDR's SDF and rendering network) and \
             `--encoding hash` (the dvr model on hash grids)), 1 − mask IoU and the MSE inside \
             the true masks of its `curve.csv` (first 4 test views every 500 steps); 3-D \
             reconstruction learned across shapes (`cargo run --release --example \
             shape_prior -- --minutes 3 --shapes-per-category 100 --test-shapes 32 --input \
             points|voxels|image`, on the collection of seed 0 that the first run generates: \
             415 training shapes), 1 − IoU on 32 test shapes of its `curve.csv` (every 60 s \
             of training).{}",
            if notes.is_empty() {
                String::new()
            } else {
                format!(" Not measured: {}.", notes.join("; "))
            }
        ),
        knob: "training step".into(),
        error_name: "error (1 − IoU, Chamfer-L1 or held-out MSE)".into(),
        work_unit: String::new(),
        time_name: "wall time since start (s)".into(),
        rows,
    }]
}
