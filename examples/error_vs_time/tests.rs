//! Runs every study in quick mode, so the report command never rots: each table has
//! rows, finite non-negative errors and positive times, and renders to Markdown and SVG.

#[cfg(feature = "volume")]
use crate::cone;
#[cfg(feature = "dvr")]
use crate::dvr;
use crate::encoding;
#[cfg(all(feature = "flow", feature = "occupancy"))]
use crate::flow;
#[cfg(feature = "occupancy")]
use crate::mise;
use crate::report::{self, Table};
#[cfg(feature = "volume")]
use crate::volume;

fn check(tables: Vec<Table>) {
    assert!(!tables.is_empty());
    for t in &tables {
        assert!(!t.rows.is_empty(), "{}: no rows", t.title);
        for r in &t.rows {
            assert!(
                r.error.is_finite() && r.error >= 0.0,
                "{}: error {}",
                t.title,
                r.error
            );
            assert!(
                r.seconds > 0.0 && r.seconds.is_finite(),
                "{}: time {}",
                t.title,
                r.seconds
            );
        }
        let md = report::markdown(t, Some("plots/x.svg"));
        assert!(md.contains(&t.title) && md.lines().count() >= t.rows.len() + 4);
        assert!(report::svg(t).contains("<polyline"));
    }
}

#[test]
fn encoding_study_runs_quick() {
    let tables = encoding::run(true);
    // The exact reduction must beat the naive f32 encoding at L = 10 by two orders.
    let err = |series: &str| {
        tables[0]
            .rows
            .iter()
            .find(|r| r.series.starts_with(series) && r.knob == 10.0)
            .map(|r| r.error)
            .unwrap()
    };
    assert!(
        err("f32, exact") * 100.0 < err("f32, naive"),
        "{} vs {}",
        err("f32, exact"),
        err("f32, naive")
    );
    check(tables);
}

#[cfg(feature = "volume")]
#[test]
fn volume_study_runs_quick() {
    let tables = volume::run(true);
    // More samples must not make stratified compositing worse on this scene.
    let strat: Vec<f64> = tables[0]
        .rows
        .iter()
        .filter(|r| r.series == "stratified")
        .map(|r| r.error)
        .collect();
    assert!(strat.windows(2).all(|w| w[1] <= w[0] * 1.01), "{strat:?}");
    check(tables);
}

#[cfg(feature = "dvr")]
#[test]
fn dvr_study_runs_quick() {
    let tables = dvr::run(true);
    // On the analytic torus, secant refinement must not make the depth worse at the
    // finest sampling.
    let torus = &tables[0];
    let finest = torus.rows.iter().map(|r| r.knob).fold(0.0, f64::max);
    let err = |series: &str| {
        torus
            .rows
            .iter()
            .find(|r| r.series == series && r.knob == finest)
            .map(|r| r.error)
            .unwrap()
    };
    assert!(
        err("8 secant steps") <= err("0 secant steps"),
        "{}: {} vs {}",
        torus.title,
        err("8 secant steps"),
        err("0 secant steps")
    );
    check(tables);
}

#[cfg(feature = "occupancy")]
#[test]
fn mise_study_runs_quick() {
    let tables = mise::run(true);
    check(tables);
}

#[cfg(all(feature = "flow", feature = "occupancy"))]
#[test]
fn flow_study_runs_quick() {
    let tables = flow::run(true);
    // RK4 converges: 64 steps are at least 10⁴ times more accurate than 1 (order 4 over
    // 6 doublings would give 1.7·10⁷) in f64, and Dormand–Prince at rtol 1e-8 is within
    // 1e-6 of the closed form.
    let rows = &tables[0].rows;
    let err = |series: &str, knob: f64| {
        rows.iter()
            .find(|r| r.series.starts_with(series) && r.series.ends_with("F64") && r.knob == knob)
            .map(|r| r.error)
            .unwrap()
    };
    assert!(
        err("RK4", 64.0) * 1e4 < err("RK4", 1.0),
        "{} vs {}",
        err("RK4", 64.0),
        err("RK4", 1.0)
    );
    assert!(err("Dormand", 1e-8) < 1e-6, "{}", err("Dormand", 1e-8));
    check(tables);
}

#[cfg(feature = "volume")]
#[test]
fn cone_study_runs_quick() {
    let tables = cone::run(true);
    // The closed form agrees with the finest quadrature, and the quadrature converges.
    let rows = &tables[0].rows;
    let f64_row = rows
        .iter()
        .find(|r| r.series == "closed form, f64")
        .unwrap();
    assert!(f64_row.error < 1e-3, "{}", f64_row.error);
    let quad: Vec<f64> = rows
        .iter()
        .filter(|r| r.series.starts_with("midpoint"))
        .map(|r| r.error)
        .collect();
    assert!(quad.windows(2).all(|w| w[1] < w[0]), "{quad:?}");
    check(tables);
}
