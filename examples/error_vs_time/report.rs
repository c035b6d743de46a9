//! Tables of error against run time, written as Markdown and as log–log SVG plots.
//!
//! Every study returns [`Table`]s whose rows say what was measured (`description`), the
//! knob value, the error and the median seconds per call. Nothing here knows about a
//! particular algorithm.
#![allow(dead_code)]

use candle_core::{DType, Tensor};
use std::fmt::Write as _;
use std::time::Instant;

/// One study's results: a table in the report and one plot.
pub struct Table {
    /// Short title, e.g. "Compositing colour error vs samples per ray".
    pub title: String,
    /// What was measured and how (scene, reference, error definition, timing method).
    pub description: String,
    /// Name of the knob column, e.g. "samples per ray".
    pub knob: String,
    /// Name of the error column, e.g. "max |C − C_exact|".
    pub error_name: String,
    /// What one unit of [`Row::work`] is ("rays", "samples", "field evaluations"); empty
    /// when the rows carry no work count (then the table has no work/throughput columns).
    pub work_unit: String,
    /// Header of the time column; `"time per call (s)"` unless a study measures something
    /// else (e.g. cumulative wall time of a training run).
    pub time_name: String,
    /// The rows, in any order; rows of one `series` form one curve.
    pub rows: Vec<Row>,
}

/// The usual time column: median wall time of one call.
pub const TIME_PER_CALL: &str = "time per call (s)";

/// One measurement.
pub struct Row {
    /// The method / configuration, e.g. "stratified, midpoints".
    pub series: String,
    /// The knob value.
    pub knob: f64,
    /// The error against the reference.
    pub error: f64,
    /// Median wall time of one call, in seconds (or what [`Table::time_name`] says).
    pub seconds: f64,
    /// Items processed by one call, in [`Table::work_unit`]s (0 when not counted); the
    /// report prints it and the throughput `work / seconds`.
    pub work: f64,
}

/// Flattens any float tensor into a `Vec<f64>`.
pub fn v64(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

/// Median wall time of `reps` runs of `f` (at least one), in seconds.
pub fn median_seconds(reps: usize, mut f: impl FnMut()) -> f64 {
    let mut times: Vec<f64> = (0..reps.max(1))
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

fn fmt_num(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else if (1e-3..1e5).contains(&x.abs()) {
        format!("{x:.4}")
            .trim_end_matches('0')
            .trim_end_matches('.')
            .to_string()
    } else {
        format!("{x:.3e}")
    }
}

/// A count or rate with at most three significant digits and a k/M/G suffix.
fn fmt_count(x: f64) -> String {
    match x.abs() {
        a if a >= 1e9 => format!("{:.3} G", x / 1e9),
        a if a >= 1e6 => format!("{:.3} M", x / 1e6),
        a if a >= 1e4 => format!("{:.1} k", x / 1e3),
        _ => format!("{x:.0}"),
    }
}

/// A file-name slug of a title.
pub fn slug(title: &str) -> String {
    let s: String = title
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() {
                c.to_ascii_lowercase()
            } else {
                '-'
            }
        })
        .collect();
    s.split('-')
        .filter(|p| !p.is_empty())
        .collect::<Vec<_>>()
        .join("-")
}

/// The Markdown of one table, referencing its plot at `plot_path` if given.
pub fn markdown(table: &Table, plot_path: Option<&str>) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "### {}\n\n{}\n", table.title, table.description);
    let unit = &table.work_unit;
    // A `|` inside a cell would end it: escape the names that may hold one.
    let cell = |t: &str| t.replace('|', "\\|");
    if unit.is_empty() {
        let _ = writeln!(
            s,
            "| series | {} | {} | {} |",
            cell(&table.knob),
            cell(&table.error_name),
            cell(&table.time_name)
        );
        let _ = writeln!(s, "|---|---:|---:|---:|");
    } else {
        let _ = writeln!(
            s,
            "| series | {} | {} | {} | {unit} per call | {unit} per second |",
            cell(&table.knob),
            cell(&table.error_name),
            cell(&table.time_name)
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|");
    }
    for r in &table.rows {
        let _ = write!(
            s,
            "| {} | {} | {} | {} |",
            cell(&r.series),
            fmt_num(r.knob),
            fmt_num(r.error),
            fmt_num(r.seconds)
        );
        if !unit.is_empty() {
            let rate = if r.seconds > 0.0 {
                r.work / r.seconds
            } else {
                0.0
            };
            let _ = write!(s, " {} | {} |", fmt_count(r.work), fmt_count(rate));
        }
        s.push('\n');
    }
    if let Some(p) = plot_path {
        let _ = writeln!(s, "\n![{}]({p})", table.title);
    }
    s
}

const COLORS: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
];

/// A log–log SVG plot of error (y) against time per call (x), one polyline per series.
/// Rows with a non-positive error or time are left out (they have no logarithm).
pub fn svg(table: &Table) -> String {
    let (w, h, ml, mr, mt, mb) = (720.0, 440.0, 80.0, 220.0, 40.0, 60.0);
    let pts: Vec<&Row> = table
        .rows
        .iter()
        .filter(|r| r.error > 0.0 && r.seconds > 0.0)
        .collect();
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n"
    );
    let _ = writeln!(
        s,
        "<text x=\"{}\" y=\"22\" font-size=\"15\">{}</text>",
        ml,
        escape(&table.title)
    );
    if pts.is_empty() {
        s.push_str("<text x=\"80\" y=\"200\">no positive data</text>\n</svg>\n");
        return s;
    }
    let lx: Vec<f64> = pts.iter().map(|r| r.seconds.log10()).collect();
    let ly: Vec<f64> = pts.iter().map(|r| r.error.log10()).collect();
    let (x0, x1) = (
        lx.iter().cloned().fold(f64::MAX, f64::min).floor(),
        lx.iter().cloned().fold(f64::MIN, f64::max).ceil(),
    );
    let (y0, y1) = (
        ly.iter().cloned().fold(f64::MAX, f64::min).floor(),
        ly.iter().cloned().fold(f64::MIN, f64::max).ceil(),
    );
    let (x1, y1) = (
        if x1 <= x0 { x0 + 1.0 } else { x1 },
        if y1 <= y0 { y0 + 1.0 } else { y1 },
    );
    let px = |v: f64| ml + (v - x0) / (x1 - x0) * (w - ml - mr);
    let py = |v: f64| h - mb - (v - y0) / (y1 - y0) * (h - mt - mb);
    // Grid and decade labels.
    for d in (x0 as i32)..=(x1 as i32) {
        let x = px(f64::from(d));
        let _ = writeln!(s, "<line x1=\"{x:.1}\" y1=\"{mt}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"#ddd\"/><text x=\"{x:.1}\" y=\"{:.1}\" text-anchor=\"middle\">1e{d}</text>", h - mb, h - mb + 18.0);
    }
    for d in (y0 as i32)..=(y1 as i32) {
        let y = py(f64::from(d));
        let _ = writeln!(s, "<line x1=\"{ml}\" y1=\"{y:.1}\" x2=\"{:.1}\" y2=\"{y:.1}\" stroke=\"#ddd\"/><text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\">1e{d}</text>", w - mr, ml - 6.0, y + 4.0);
    }
    let _ = writeln!(
        s,
        "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>",
        (ml + w - mr) / 2.0,
        h - 12.0,
        escape(&table.time_name)
    );
    let _ = writeln!(s, "<text x=\"16\" y=\"{:.1}\" transform=\"rotate(-90 16 {:.1})\" text-anchor=\"middle\">{}</text>", (mt + h - mb) / 2.0, (mt + h - mb) / 2.0, escape(&table.error_name));
    let mut series: Vec<&str> = Vec::new();
    for r in &pts {
        if !series.contains(&r.series.as_str()) {
            series.push(&r.series);
        }
    }
    for (i, name) in series.iter().enumerate() {
        let color = COLORS[i % COLORS.len()];
        let mut rows: Vec<&&Row> = pts.iter().filter(|r| r.series == *name).collect();
        rows.sort_by(|a, b| a.knob.total_cmp(&b.knob));
        let line: Vec<String> = rows
            .iter()
            .map(|r| format!("{:.1},{:.1}", px(r.seconds.log10()), py(r.error.log10())))
            .collect();
        let _ = writeln!(
            s,
            "<polyline fill=\"none\" stroke=\"{color}\" stroke-width=\"2\" points=\"{}\"/>",
            line.join(" ")
        );
        for r in &rows {
            let _ = writeln!(
                s,
                "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3\" fill=\"{color}\"/>",
                px(r.seconds.log10()),
                py(r.error.log10())
            );
        }
        let ly = mt + 16.0 * i as f64 + 10.0;
        let _ = writeln!(s, "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"12\" height=\"3\" fill=\"{color}\"/><text x=\"{:.1}\" y=\"{:.1}\">{}</text>", w - mr + 12.0, ly - 4.0, w - mr + 30.0, ly, escape(name));
    }
    s.push_str("</svg>\n");
    s
}

fn escape(t: &str) -> String {
    t.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}
