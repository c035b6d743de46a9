//! The stiff-case suite's shared parts: the case runner (`Suite`), the extreme inputs every
//! module's sweep draws from, and the scanner that checks each `tests/stiff_cases_*.rs`
//! file sweeps (or exempts with a reason) every public function of the source files it
//! owns.
//!
//! Items are named as users reach them: the crate module, then the type and the method,
//! or the function (`volume::composite`, `camera::Camera::new`), whatever file of the
//! module defines them.

use super::v64;
use candle_core::{DType, Device, Tensor, Var};
use std::collections::BTreeSet;

pub const DTYPES: [DType; 2] = [DType::F32, DType::F64];

/// Magnitudes every scalar sweep visits, within the dtype's finite range.
pub fn magnitudes(dtype: DType) -> Vec<f64> {
    let top = if dtype == DType::F32 { 1e30 } else { 1e300 };
    let mut v = vec![
        0.0, 1e-45, 1e-30, 1e-12, 1e-6, 0.5, 1.0, 88.0, 1e4, 1e10, top,
    ];
    if dtype == DType::F64 {
        v.extend([1e-300, 1e30]);
    }
    let neg: Vec<f64> = v.iter().map(|x| -x).collect();
    v.extend(neg);
    v
}

#[derive(Default)]
pub struct Suite {
    pub cases: usize,
    pub failures: Vec<String>,
    pub covered: BTreeSet<&'static str>,
}

/// What a case may do.
#[derive(Clone, Copy, PartialEq)]
pub enum Expect {
    /// Must succeed with finite outputs and gradients.
    Finite,
    /// May return `Err` (invalid input); if it succeeds, outputs must be finite.
    FiniteOrErr,
}

impl Suite {
    /// Runs one case: `f` returns output tensors; gradients of their sum w.r.t. `wrt`
    /// must be finite too.
    pub fn case(
        &mut self,
        item: &'static str,
        label: impl Into<String>,
        expect: Expect,
        wrt: &[&Var],
        f: impl FnOnce() -> neural_fields::Result<Vec<Tensor>>,
    ) {
        self.cases += 1;
        self.covered.insert(item);
        let label = format!("{item} [{}]", label.into());
        let outputs = match f() {
            Ok(o) => o,
            Err(e) => {
                if expect == Expect::Finite {
                    self.failures.push(format!("{label}: unexpected Err: {e}"));
                }
                return;
            }
        };
        let mut loss: Option<Tensor> = None;
        for (i, t) in outputs.iter().enumerate() {
            if !matches!(t.dtype(), DType::F32 | DType::F64) {
                continue;
            }
            if first_bad(t).is_some() {
                self.failures.push(format!(
                    "{label}: output {i} not finite: {:?}",
                    first_bad(t)
                ));
                return;
            }
            let s = t.to_dtype(DType::F64).unwrap().sum_all().unwrap();
            loss = Some(match loss {
                None => s,
                Some(l) => (l + s).unwrap(),
            });
        }
        if wrt.is_empty() {
            return;
        }
        let Some(loss) = loss else { return };
        let grads = match loss.backward() {
            Ok(g) => g,
            Err(e) => {
                self.failures.push(format!("{label}: backward failed: {e}"));
                return;
            }
        };
        for (j, v) in wrt.iter().enumerate() {
            if let Some(g) = grads.get(v) {
                if first_bad(g).is_some() {
                    self.failures.push(format!(
                        "{label}: gradient {j} not finite: {:?}",
                        first_bad(g)
                    ));
                }
            }
        }
    }

    /// Ends a family of cases: prints one summary line, fails with every failing case,
    /// and checks that the items the cases ran are exactly `listed` (the family's list,
    /// which the file's coverage test counts as swept).
    pub fn finish(self, family: &str, listed: &[&str]) {
        println!(
            "stiff cases, {family}: {} cases run over {} items, {} failures",
            self.cases,
            self.covered.len(),
            self.failures.len()
        );
        assert!(
            self.failures.is_empty(),
            "stiff-case failures in {family}:\n{}",
            self.failures.join("\n")
        );
        let listed: BTreeSet<&str> = listed.iter().copied().collect();
        let stale: Vec<_> = listed.symmetric_difference(&self.covered).collect();
        assert!(
            stale.is_empty(),
            "{family}: the list of swept items differs from what the cases ran: {stale:?}"
        );
    }
}

pub fn first_bad(t: &Tensor) -> Option<f64> {
    v64(t).into_iter().find(|x| !x.is_finite())
}

pub fn var(values: &[f64], shape: &[usize], dtype: DType) -> Var {
    Var::from_tensor(
        &Tensor::from_slice(values, shape, &Device::Cpu)
            .unwrap()
            .to_dtype(dtype)
            .unwrap(),
    )
    .unwrap()
}

/// Points at the singularities of the analytic shapes and the encodings (the origin, the
/// axes, a shape's centre), and far away, as an `[9, 3]` tensor.
pub fn extreme_points(dtype: DType) -> Tensor {
    let big = if dtype == DType::F32 { 1e30 } else { 1e150 };
    let rows: Vec<[f64; 3]> = vec![
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1e-30],
        [1e-30, 0.0, 0.0],
        [0.3, 0.0, 0.0],
        [0.0, 0.0, 0.3],
        [0.5, 0.5, 0.5],
        [big, 0.0, 0.0],
        [-big, big, -big],
        [1e10, -1e10, 3.0],
    ];
    let flat: Vec<f64> = rows.concat();
    Tensor::from_vec(flat, (rows.len(), 3), &Device::Cpu)
        .unwrap()
        .to_dtype(dtype)
        .unwrap()
}

/// Which `tests/stiff_cases_*.rs` file sweeps the public functions of which source files:
/// `(path under src/, file stem)`; the longest matching path wins.
pub const OWNERS: &[(&str, &str)] = &[
    ("lib.rs", "stiff_cases_numerics"),
    ("numerics.rs", "stiff_cases_numerics"),
    ("rng.rs", "stiff_cases_numerics"),
    ("error.rs", "stiff_cases_numerics"),
    ("narrow.rs", "stiff_cases_numerics"),
    ("test_host.rs", "stiff_cases_numerics"),
    ("field.rs", "stiff_cases_field"),
    ("encoding", "stiff_cases_encoding"),
    ("camera", "stiff_cases_camera"),
    ("nn/", "stiff_cases_nn"),
    ("kernels/", "stiff_cases_nn"),
    ("occupancy/", "stiff_cases_occupancy"),
    ("occupancy/mesh.rs", "stiff_cases_mesh"),
    ("occupancy/point_cloud.rs", "stiff_cases_mesh"),
    ("occupancy/ply.rs", "stiff_cases_mesh"),
    ("occupancy/stl.rs", "stiff_cases_mesh"),
    ("occupancy/off.rs", "stiff_cases_mesh"),
    ("occupancy/triangulate.rs", "stiff_cases_mesh"),
    ("mesh", "stiff_cases_mesh"),
    ("volume/", "stiff_cases_volume"),
    ("dvr/", "stiff_cases_dvr"),
    ("data/", "stiff_cases_data"),
    ("texture/", "stiff_cases_texture"),
    ("flow/", "stiff_cases_flow"),
];

/// The file stem that owns a source file (a path under `src/`, with `/` separators).
pub fn owner(src_path: &str) -> Option<&'static str> {
    OWNERS
        .iter()
        .filter(|(prefix, _)| src_path.starts_with(prefix))
        .max_by_key(|(prefix, _)| prefix.len())
        .map(|(_, stem)| *stem)
}

/// A public function or trait-impl method found in `src/`.
pub struct PublicItem {
    /// `module::Type::method` or `module::function`, `module` being the crate module.
    pub name: String,
    /// The file under `src/`, with `/` separators.
    pub file: String,
}

/// Public functions and trait-impl methods in `src/` (everything after a file's
/// `#[cfg(test)] mod` is skipped; methods that a macro defines are not seen).
pub fn public_items() -> Vec<PublicItem> {
    let mut items = Vec::new();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut stack = vec![root.clone()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
                continue;
            }
            if path.extension().and_then(|e| e.to_str()) != Some("rs") {
                continue;
            }
            let rel = path.strip_prefix(&root).unwrap();
            let file: Vec<String> = rel
                .iter()
                .map(|c| c.to_string_lossy().into_owned())
                .collect();
            let file = file.join("/");
            let module = rel
                .with_extension("")
                .iter()
                .next()
                .map(|c| c.to_string_lossy().into_owned())
                .filter(|m| m != "lib")
                .unwrap_or_default();
            let text = std::fs::read_to_string(&path).unwrap();
            let mut current: Option<(String, bool)> = None; // (type, is trait impl)
            let mut lines = text.lines().peekable();
            while let Some(line) = lines.next() {
                if line.starts_with("#[cfg(test)]")
                    && lines.peek().is_some_and(|next| next.starts_with("mod "))
                {
                    break;
                }
                if line.starts_with("impl") {
                    let head = line.trim_end_matches('{').trim();
                    let is_trait = head.contains(" for ");
                    let ty = head
                        .rsplit(" for ")
                        .next()
                        .unwrap()
                        .trim_start_matches("impl")
                        .trim();
                    let ty = ty.rsplit("> ").next().unwrap_or(ty);
                    let ty = ty
                        .split('<')
                        .next()
                        .unwrap()
                        .trim()
                        .rsplit("::")
                        .next()
                        .unwrap()
                        .to_string();
                    current = Some((ty, is_trait));
                    continue;
                }
                if line.starts_with('}') {
                    current = None;
                    continue;
                }
                let trimmed = line.trim_start();
                let indent = line.len() - trimmed.len();
                let name_after = |prefix: &str| {
                    trimmed
                        .strip_prefix(prefix)
                        .map(|r| r.split(['(', '<']).next().unwrap().to_string())
                };
                let prefix = if module.is_empty() {
                    String::new()
                } else {
                    format!("{module}::")
                };
                let name = match (&current, indent) {
                    (None, 0) => name_after("pub fn ").map(|n| format!("{prefix}{n}")),
                    (Some((ty, is_trait)), 4) => if *is_trait {
                        name_after("fn ")
                    } else {
                        name_after("pub fn ")
                    }
                    .map(|n| format!("{prefix}{ty}::{n}")),
                    _ => None,
                };
                if let Some(name) = name {
                    items.push(PublicItem {
                        name,
                        file: file.clone(),
                    });
                }
            }
        }
    }
    items
}

/// Checks the coverage of the stiff-case file `stem`: every public item of the source
/// files it owns (see `OWNERS`) is in one of its family lists `swept` or matches a prefix
/// of `exempt` (which gives the reason), and every listed item exists (or is named in
/// `unseen`: methods that a macro defines, which the scanner cannot see). `absent` names
/// items that the enabled features leave out of the build.
pub fn check_coverage(
    stem: &str,
    swept: &[&[&str]],
    exempt: &[(&str, &str)],
    absent: &[&str],
    unseen: &[&str],
) {
    let all = public_items();
    let swept: BTreeSet<&str> = swept.iter().flat_map(|l| l.iter().copied()).collect();
    let owned: BTreeSet<&str> = all
        .iter()
        .filter(|i| owner(&i.file) == Some(stem))
        .map(|i| i.name.as_str())
        .filter(|n| !absent.contains(n))
        .collect();
    assert!(!owned.is_empty(), "the scanner found no items for {stem}");
    let missing: Vec<&str> = owned
        .iter()
        .copied()
        .filter(|i| !swept.contains(i) && !exempt.iter().any(|(p, _)| i.starts_with(p)))
        .collect();
    assert!(
        missing.is_empty(),
        "public items neither swept in tests/{stem}.rs nor exempted with a reason:\n{}",
        missing.join("\n")
    );
    let names: BTreeSet<&str> = all.iter().map(|i| i.name.as_str()).collect();
    let unknown: Vec<&str> = swept
        .iter()
        .copied()
        .filter(|c| !names.contains(c) && !unseen.contains(c))
        .collect();
    assert!(
        unknown.is_empty(),
        "tests/{stem}.rs lists items that no longer exist: {unknown:?}"
    );
}

/// Checks that every source file with public items has a stiff-case file that owns it,
/// and that every owner in `OWNERS` is a file under `tests/`.
pub fn check_owners() {
    let all = public_items();
    assert!(all.len() > 50, "scanner found only {} items", all.len());
    let orphans: BTreeSet<&str> = all
        .iter()
        .filter(|i| owner(&i.file).is_none())
        .map(|i| i.file.as_str())
        .collect();
    assert!(
        orphans.is_empty(),
        "source files with public functions that no tests/stiff_cases_*.rs owns \
         (add them to OWNERS in tests/common/stiff.rs): {orphans:?}"
    );
    let tests = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests");
    let stems: BTreeSet<&str> = OWNERS.iter().map(|(_, stem)| *stem).collect();
    let gone: Vec<&str> = stems
        .into_iter()
        .filter(|stem| !tests.join(format!("{stem}.rs")).is_file())
        .collect();
    assert!(gone.is_empty(), "OWNERS names missing test files: {gone:?}");
}
