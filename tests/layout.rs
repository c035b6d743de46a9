//! The crate's layout, checked from its source:
//! - it reads downward: no source file imports a file that imports it back (directly or
//!   through others), and the building blocks (`nn`) and the kernels import no feature
//!   module;
//! - its public surface is the committed list `tests/public_api.txt`, so that every
//!   addition or removal is a diff in review, within the budget of public functions.
//!   After a deliberate change, regenerate the list with
//!   `UPDATE_PUBLIC_API=1 cargo test --test layout`.
//!
//! The check reads `src/` as text: every `use` statement (braces expanded) and every
//! inline `crate::…` / `super::…` path is resolved to the file that defines the item it
//! names, following re-exports. A module's re-exports of its own submodules
//! (`pub use child::Item` in `mod.rs`) are the module policy, not an import, and are left
//! out; every other reference is an arrow. Circles are the strongly connected components
//! of those arrows with more than one file.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// One source file: its module path (`["volume", "grid"]`), its code with comments and
/// literals blanked, and the names it defines.
struct SourceFile {
    module: Vec<String>,
    code: String,
    defines: BTreeSet<String>,
}

#[path = "common/source.rs"]
mod source;
use source::{rust_files, strip, without_test_modules};

/// `src/a/b.rs` → `[a, b]`; `src/a/mod.rs` → `[a]`; `src/lib.rs` → `[]`.
fn module_of(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).expect("file under src");
    let mut parts: Vec<String> = rel
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop().expect("a file name");
    let stem = last.trim_end_matches(".rs");
    if stem != "mod" && stem != "lib" {
        parts.push(stem.to_string());
    }
    parts
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// The names a file defines at any depth: functions, types, traits, consts, statics,
/// macros.
fn definitions(code: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let words: Vec<&str> = code
        .split(|c: char| !(is_ident(c) || c == '!'))
        .filter(|w| !w.is_empty())
        .collect();
    for pair in words.windows(2) {
        if matches!(
            pair[0],
            "fn" | "struct" | "enum" | "trait" | "type" | "const" | "static" | "macro_rules!"
        ) {
            names.insert(pair[1].trim_end_matches('!').to_string());
        }
    }
    names
}

/// Expands a use tree (`a::{b, c::{d, e}}`) into whole paths.
fn expand(tree: &str, prefix: &[String], out: &mut Vec<Vec<String>>) {
    let tree = tree.trim();
    if tree.is_empty() {
        return;
    }
    // Split on top-level commas.
    let mut depth = 0;
    let mut start = 0;
    let bytes = tree.as_bytes();
    let mut parts = Vec::new();
    for (i, &c) in bytes.iter().enumerate() {
        match c {
            b'{' => depth += 1,
            b'}' => depth -= 1,
            b',' if depth == 0 => {
                parts.push(&tree[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    parts.push(&tree[start..]);
    if parts.len() > 1 {
        for p in parts {
            expand(p, prefix, out);
        }
        return;
    }
    let tree = parts[0].trim();
    if let Some(brace) = tree.find('{') {
        let head = tree[..brace].trim().trim_end_matches("::");
        let inner = &tree[brace + 1..tree.rfind('}').unwrap_or(tree.len())];
        let mut p = prefix.to_vec();
        p.extend(
            head.split("::")
                .filter(|s| !s.is_empty())
                .map(|s| s.trim().to_string()),
        );
        expand(inner, &p, out);
    } else {
        let tree = tree.split(" as ").next().unwrap_or(tree);
        let mut p = prefix.to_vec();
        p.extend(
            tree.split("::")
                .map(|s| s.trim().to_string())
                .filter(|s| !s.is_empty()),
        );
        if !p.is_empty() {
            out.push(p);
        }
    }
}

/// Every `use` statement of a file: (is `pub use`, expanded paths).
fn use_statements(code: &str) -> Vec<(bool, Vec<Vec<String>>)> {
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(pos) = find_word(rest, "use") {
        let before = rest[..pos].trim_end();
        let public = before.ends_with("pub") || before.ends_with(')') && before.contains("pub(");
        let after = &rest[pos + 3..];
        let end = after.find(';').unwrap_or(after.len());
        let mut paths = Vec::new();
        expand(&after[..end], &[], &mut paths);
        out.push((public, paths));
        rest = &after[end..];
    }
    out
}

fn find_word(text: &str, word: &str) -> Option<usize> {
    let mut from = 0;
    while let Some(i) = text[from..].find(word) {
        let at = from + i;
        let before_ok = at == 0 || !is_ident(text[..at].chars().last().unwrap_or(' '));
        let after = text[at + word.len()..].chars().next().unwrap_or(' ');
        if before_ok && after.is_whitespace() {
            return Some(at);
        }
        from = at + word.len();
    }
    None
}

/// Inline paths that start with `crate::` or `super::` outside `use` statements.
fn inline_paths(code: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    for start in ["crate::", "super::"] {
        let mut from = 0;
        while let Some(i) = code[from..].find(start) {
            let at = from + i;
            from = at + start.len();
            if at > 0 && is_ident(code[..at].chars().last().unwrap_or(' ')) {
                continue;
            }
            let mut path = Vec::new();
            let mut rest = &code[at..];
            loop {
                let len = rest.find(|c: char| !is_ident(c)).unwrap_or(rest.len());
                if len == 0 {
                    break;
                }
                path.push(rest[..len].to_string());
                rest = &rest[len..];
                if let Some(r) = rest.strip_prefix("::") {
                    rest = r;
                } else {
                    break;
                }
            }
            out.push(path);
        }
    }
    out
}

struct Crate {
    files: BTreeMap<PathBuf, SourceFile>,
    by_module: BTreeMap<Vec<String>, PathBuf>,
}

impl Crate {
    fn read() -> Crate {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
        let mut paths = Vec::new();
        rust_files(&src, &mut paths);
        let mut files = BTreeMap::new();
        let mut by_module = BTreeMap::new();
        for path in paths {
            let text = std::fs::read_to_string(&path).expect("source is UTF-8");
            let code = without_test_modules(&strip(&text));
            let module = module_of(&src, &path);
            let rel = path.strip_prefix(&src).expect("under src").to_path_buf();
            by_module.insert(module.clone(), rel.clone());
            let defines = definitions(&code);
            files.insert(
                rel,
                SourceFile {
                    module,
                    code,
                    defines,
                },
            );
        }
        Crate { files, by_module }
    }

    /// The file that defines the item a path names, seen from module `from`.
    fn resolve(&self, from: &[String], path: &[String], depth: usize) -> Option<PathBuf> {
        if depth > 8 || path.is_empty() {
            return None;
        }
        let mut module: Vec<String> = match path[0].as_str() {
            "crate" => Vec::new(),
            "super" => from[..from.len().saturating_sub(1)].to_vec(),
            "self" => from.to_vec(),
            _ => return None, // an external crate or a local name
        };
        let mut i = 1;
        while i < path.len() && path[i] == "super" {
            module.pop();
            i += 1;
        }
        while i < path.len() {
            let mut next = module.clone();
            next.push(path[i].clone());
            if self.by_module.contains_key(&next) {
                module = next;
                i += 1;
            } else {
                break;
            }
        }
        let file = self.by_module.get(&module)?.clone();
        let Some(name) = path.get(i) else {
            return Some(file);
        };
        if name == "*" || name == "self" {
            return Some(file);
        }
        let source = &self.files[&file];
        if source.defines.contains(name) {
            return Some(file);
        }
        // Follow the module's own imports of that name (re-exports).
        for (_, paths) in use_statements(&source.code) {
            for p in paths {
                if p.last() == Some(name) {
                    let p = self.absolute(&source.module, &p);
                    if let Some(found) = self.resolve(&source.module, &p, depth + 1) {
                        return Some(found);
                    }
                }
            }
        }
        Some(file)
    }

    /// A `use` path as written inside module `module` (a bare first segment names a
    /// child module there), as an absolute `crate::…` path where it is one of ours.
    fn absolute(&self, module: &[String], path: &[String]) -> Vec<String> {
        if matches!(path[0].as_str(), "crate" | "super" | "self") {
            return path.to_vec();
        }
        let mut child = module.to_vec();
        child.push(path[0].clone());
        if self.by_module.contains_key(&child) {
            let mut p = vec!["self".to_string()];
            p.extend(path.iter().cloned());
            return p;
        }
        path.to_vec()
    }

    /// Arrows file → file, leaving out a module's re-exports of its own submodules.
    fn arrows(&self) -> BTreeMap<PathBuf, BTreeSet<PathBuf>> {
        let mut arrows: BTreeMap<PathBuf, BTreeSet<PathBuf>> = BTreeMap::new();
        for (file, source) in &self.files {
            let mut targets = BTreeSet::new();
            let mut paths: Vec<(bool, Vec<String>)> = Vec::new();
            for (public, ps) in use_statements(&source.code) {
                for p in ps {
                    paths.push((public, self.absolute(&source.module, &p)));
                }
            }
            paths.extend(inline_paths(&source.code).into_iter().map(|p| (false, p)));
            for (public, path) in paths {
                let Some(target) = self.resolve(&source.module, &path, 0) else {
                    continue;
                };
                let target_module = &self.files[&target].module;
                let own_child = target_module.len() > source.module.len()
                    && target_module.starts_with(&source.module);
                if &target == file || (public && own_child) {
                    continue;
                }
                targets.insert(target);
            }
            arrows.insert(file.clone(), targets);
        }
        arrows
    }
}

/// Strongly connected components with more than one file (Tarjan).
fn circles(arrows: &BTreeMap<PathBuf, BTreeSet<PathBuf>>) -> Vec<Vec<PathBuf>> {
    struct State<'a> {
        arrows: &'a BTreeMap<PathBuf, BTreeSet<PathBuf>>,
        index: BTreeMap<&'a PathBuf, usize>,
        low: BTreeMap<&'a PathBuf, usize>,
        stack: Vec<&'a PathBuf>,
        on_stack: BTreeSet<&'a PathBuf>,
        next: usize,
        out: Vec<Vec<PathBuf>>,
    }
    fn visit<'a>(s: &mut State<'a>, v: &'a PathBuf) {
        s.index.insert(v, s.next);
        s.low.insert(v, s.next);
        s.next += 1;
        s.stack.push(v);
        s.on_stack.insert(v);
        for w in s.arrows.get(v).into_iter().flatten() {
            let Some((w, _)) = s.arrows.get_key_value(w) else {
                continue;
            };
            if !s.index.contains_key(w) {
                visit(s, w);
                let lw = s.low[w];
                let lv = s.low.get_mut(v).expect("visited");
                *lv = (*lv).min(lw);
            } else if s.on_stack.contains(w) {
                let iw = s.index[w];
                let lv = s.low.get_mut(v).expect("visited");
                *lv = (*lv).min(iw);
            }
        }
        if s.low[v] == s.index[v] {
            let mut component = Vec::new();
            while let Some(w) = s.stack.pop() {
                s.on_stack.remove(w);
                component.push(w.clone());
                if w == v {
                    break;
                }
            }
            if component.len() > 1 {
                component.sort();
                s.out.push(component);
            }
        }
    }
    let mut s = State {
        arrows,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        next: 0,
        out: Vec::new(),
    };
    for v in arrows.keys() {
        if !s.index.contains_key(v) {
            visit(&mut s, v);
        }
    }
    s.out
}

/// Circles accepted for now (none): a circle that is broken must leave this list, and no
/// new one may appear.
const KNOWN_CIRCLES: &[&[&str]] = &[];

#[test]
fn no_source_file_imports_a_file_that_imports_it_back() {
    let krate = Crate::read();
    let arrows = krate.arrows();
    let found: Vec<Vec<PathBuf>> = circles(&arrows);
    let known: Vec<Vec<PathBuf>> = KNOWN_CIRCLES
        .iter()
        .map(|c| c.iter().map(PathBuf::from).collect())
        .collect();
    let gone: Vec<&Vec<PathBuf>> = known.iter().filter(|c| !found.contains(c)).collect();
    assert!(
        gone.is_empty(),
        "these circles are gone: take them out of KNOWN_CIRCLES: {gone:?}"
    );
    let found: Vec<Vec<PathBuf>> = found.into_iter().filter(|c| !known.contains(c)).collect();
    let report: Vec<String> = found
        .iter()
        .map(|c| {
            let names: Vec<String> = c.iter().map(|p| p.display().to_string()).collect();
            let ties: Vec<String> = c
                .iter()
                .flat_map(|a| {
                    arrows[a]
                        .iter()
                        .filter(|b| c.contains(b))
                        .map(move |b| format!("{} -> {}", a.display(), b.display()))
                })
                .collect();
            format!("circle of {}: {}", names.join(", "), ties.join("; "))
        })
        .collect();
    assert!(
        found.is_empty(),
        "import circles in src/:\n{}",
        report.join("\n")
    );
}

/// The modules below the features: what each may import (besides itself).
const LOWER: &[(&str, &[&str])] = &[
    (
        "nn",
        &[
            "nn", "kernels", "numerics", "error", "limits", "rng", "narrow", "field", "encoding",
        ],
    ),
    (
        "kernels",
        &["kernels", "numerics", "error", "limits", "narrow"],
    ),
    (
        "numerics",
        &["numerics", "kernels", "error", "limits", "narrow"],
    ),
    ("error", &["error"]),
    ("limits", &["limits", "error"]),
    ("rng", &["rng", "error", "limits", "narrow"]),
];

/// Upward imports that are known and allowed to remain (none: every one found is an
/// error, and an entry here that is no longer found is one too).
const KNOWN_UPWARD: &[&str] = &[];

#[test]
fn building_blocks_and_kernels_import_no_feature_module() {
    let krate = Crate::read();
    let arrows = krate.arrows();
    let mut wrong = Vec::new();
    for (file, targets) in &arrows {
        let module = &krate.files[file].module;
        let Some((_, allowed)) = LOWER
            .iter()
            .find(|(top, _)| module.first().map(String::as_str) == Some(top))
        else {
            continue;
        };
        for t in targets {
            let top = krate.files[t].module.first().cloned().unwrap_or_default();
            // The crate root (lib.rs) holds only declarations and re-exports.
            if !top.is_empty() && !allowed.contains(&top.as_str()) {
                wrong.push(format!("{} imports {}", file.display(), t.display()));
            }
        }
    }
    let gone: Vec<&&str> = KNOWN_UPWARD
        .iter()
        .filter(|k| !wrong.iter().any(|w| w == *k))
        .collect();
    assert!(
        gone.is_empty(),
        "these imports are gone: take them out of KNOWN_UPWARD: {gone:?}"
    );
    wrong.retain(|w| !KNOWN_UPWARD.contains(&w.as_str()));
    assert!(
        wrong.is_empty(),
        "imports against the layering:\n{}",
        wrong.join("\n")
    );
}

/// The checker itself finds a circle and a wrong import when there is one, so that the
/// two tests above cannot pass by reading nothing.
#[test]
fn the_checker_sees_imports_and_circles() {
    let mut a = BTreeMap::new();
    let (x, y, z) = (
        PathBuf::from("x.rs"),
        PathBuf::from("y.rs"),
        PathBuf::from("z.rs"),
    );
    a.insert(x.clone(), BTreeSet::from([y.clone()]));
    a.insert(y.clone(), BTreeSet::from([z.clone()]));
    a.insert(z.clone(), BTreeSet::from([x.clone()]));
    assert_eq!(circles(&a), vec![vec![x.clone(), y.clone(), z.clone()]]);
    a.get_mut(&z).expect("z").clear();
    assert!(circles(&a).is_empty());

    let mut paths = Vec::new();
    expand("crate::{a::{B, c::D}, e as F}", &[], &mut paths);
    let joined: Vec<String> = paths.iter().map(|p| p.join("::")).collect();
    assert_eq!(joined, ["crate::a::B", "crate::a::c::D", "crate::e"]);
    let code = strip("let s = \"crate::fake\"; // crate::also_fake\nx = crate::real::f();");
    let inline: Vec<String> = inline_paths(&code).iter().map(|p| p.join("::")).collect();
    assert_eq!(inline, ["crate::real::f"]);

    // The real crate has arrows (the reader resolved something).
    let krate = Crate::read();
    let total: usize = krate.arrows().values().map(BTreeSet::len).sum();
    assert!(total > 50, "only {total} arrows read from src/");
}

/// The public-function budget: lines declaring a `pub fn` in `src/`. DESIGN.md's target
/// of 230 was reached by 0.3.0; this is a ratchet at today's count, lowered with every
/// cut and raised only with the issue that justifies it (232 after `dvr::occupancy_bce`
/// folded the freespace and missed-foreground losses): 231 `Dataset::coverage` (the
/// coverage check of a training loop), 232 `volume::conical_frustums` (cone casting),
/// 233 `volume::contract` (scene contraction of points and Gaussians); then 235:
/// `Rays::with_radii` and `Rays::radii` (rays carry mip-NeRF's cone radii, so that cone
/// casting, sub-pixel rays and unit directions keep them consistent), and
/// `Nerf::sample_inputs` (what the network evaluates per interval: midpoints, or the
/// frustums' Gaussians for the integrated encoding); 236: `Spacing::normalize` (the
/// s-space of unbounded rays, where the distortion loss is computed); 237:
/// `Dataset::visual_hull` (scene bounds from the data where a layout states none); 240:
/// `RoundedBox::new`, `Capsule::new` and `Cylinder::new` (issue 39's analytic shapes, each
/// validating its parameters like the other shapes' constructors; `Csg` is built from
/// public fields and adds no function); 242: `occupancy::resnet_encoder` and
/// `ResnetEncoder::forward` (issue 39's image encoder, configured by public fields); 246:
/// `data::generate_shape`, `write_shape_collection`, `load_shape_collection` and
/// `write_shape_views` (issue 39's procedural shape collection: one generator of a shape,
/// one writer, one loader and the writer of rendered views; configured by public fields);
/// 248: `occupancy::voxel_encoder` and `VoxelEncoder::forward` (issue 39's voxel encoder,
/// configured by public fields); 249: `OnetDecoder::logits_grouped` (one code per shape:
/// the conditional normalisation's γ(c), β(c) once per shape instead of once per point);
/// 247 after `OnetDecoder::logits` took both layouts (folding `logits_grouped`) and
/// `PointNetEncoder::forward` took `[B, K]` labels or `[B, K, F]` features (folding
/// `forward_features`).
const PUB_FN_BUDGET: usize = 247;

/// The public items of one file, one line each: `module item`, where item is
/// `fn Type::name`, `struct Name`, `use path`, … (`pub(crate)` and test modules left out).
fn public_items(source: &SourceFile) -> Vec<String> {
    let module = if source.module.is_empty() {
        "crate".to_string()
    } else {
        source.module.join("::")
    };
    let mut items = Vec::new();
    let mut owner: Option<String> = None;
    let lines: Vec<&str> = source.code.lines().collect();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i];
        let trimmed = line.trim_start();
        let indent = line.len() - trimmed.len();
        if indent == 0 && (trimmed.starts_with("impl") || trimmed.starts_with("unsafe impl")) {
            owner = impl_type(trimmed);
        } else if indent == 0 && trimmed.starts_with('}') {
            owner = None;
        }
        if let Some(rest) = trimmed.strip_prefix("pub ") {
            let rest = rest
                .trim_start_matches("async ")
                .trim_start_matches("unsafe ")
                .trim_start_matches("const fn ")
                .trim_start();
            let rest = if trimmed.contains("const fn ") {
                format!("fn {rest}")
            } else {
                rest.to_string()
            };
            let mut words = rest.split(|c: char| !(is_ident(c)));
            let kind = words.next().unwrap_or("");
            match kind {
                "fn" | "struct" | "enum" | "trait" | "type" | "const" | "static" | "mod" => {
                    let name = words.find(|w| !w.is_empty()).unwrap_or("");
                    let name = match (&owner, kind, indent > 0) {
                        (Some(t), "fn" | "const", true) => format!("{t}::{name}"),
                        _ => name.to_string(),
                    };
                    items.push(format!("{module} {kind} {name}"));
                }
                "use" => {
                    let mut text = rest.to_string();
                    let mut j = i;
                    while !text.contains(';') && j + 1 < lines.len() {
                        j += 1;
                        text.push_str(lines[j].trim());
                    }
                    let mut paths = Vec::new();
                    expand(
                        text.trim_start_matches("use")
                            .split(';')
                            .next()
                            .unwrap_or(""),
                        &[],
                        &mut paths,
                    );
                    for p in paths {
                        items.push(format!("{module} use {}", p.join("::")));
                    }
                    i = j;
                }
                _ => {}
            }
        }
        i += 1;
    }
    items
}

/// `impl<T> Trait for Type<T> {` → `Type`; `impl Type {` → `Type`.
fn impl_type(line: &str) -> Option<String> {
    let mut head = line
        .trim_start_matches("unsafe ")
        .trim_start_matches("impl");
    if head.starts_with('<') {
        let mut depth = 0;
        for (k, c) in head.char_indices() {
            match c {
                '<' => depth += 1,
                '>' => {
                    depth -= 1;
                    if depth == 0 {
                        head = &head[k + 1..];
                        break;
                    }
                }
                _ => {}
            }
        }
    }
    let head = head.split(" for ").last().unwrap_or(head).trim();
    let name: String = head.chars().take_while(|&c| is_ident(c)).collect();
    (!name.is_empty()).then_some(name)
}

fn surface() -> Vec<String> {
    let krate = Crate::read();
    let mut all: Vec<String> = krate.files.values().flat_map(public_items).collect();
    all.sort();
    all
}

#[test]
fn public_items_match_the_committed_list() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/public_api.txt");
    let now = surface().join("\n") + "\n";
    if std::env::var_os("UPDATE_PUBLIC_API").is_some() {
        std::fs::write(&path, &now).expect("tests/public_api.txt is writable");
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    let old: BTreeSet<&str> = committed.lines().collect();
    let new: BTreeSet<&str> = now.lines().collect();
    let added: Vec<&&str> = new.difference(&old).collect();
    let removed: Vec<&&str> = old.difference(&new).collect();
    assert!(
        added.is_empty() && removed.is_empty(),
        "the public surface changed; review it and regenerate tests/public_api.txt with \
         `UPDATE_PUBLIC_API=1 cargo test --test layout`\nadded: {added:#?}\nremoved: {removed:#?}"
    );
}

#[test]
fn public_functions_fit_the_budget() {
    let fns = surface().iter().filter(|l| l.contains(" fn ")).count();
    assert!(fns > 0, "no public function read from src/");
    assert!(
        fns <= PUB_FN_BUDGET,
        "{fns} public functions, over the budget of {PUB_FN_BUDGET}"
    );
}

#[test]
fn the_surface_reader_sees_methods_and_reexports() {
    let code = without_test_modules(&strip(
        "pub struct A;\nimpl<T: X> Tr for B<T> {\n    fn f() {}\n}\nimpl A {\n    pub fn new() -> A { A }\n    pub(crate) fn hidden() {}\n}\npub use x::{y::Z, W};\n#[cfg(test)]\nmod tests {\n    pub fn t() {}\n}\n",
    ));
    let file = SourceFile {
        module: vec!["m".to_string()],
        defines: definitions(&code),
        code,
    };
    assert_eq!(
        public_items(&file),
        ["m struct A", "m fn A::new", "m use x::y::Z", "m use x::W"]
    );
}

/// The longest an example's source file may be: examples are scripts on the library, and
/// what grows past this belongs in the library (or in the example's own test file).
const EXAMPLE_MAX_LINES: usize = 1_000;

#[test]
fn examples_are_short_scripts_without_included_paths() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples");
    let mut files = Vec::new();
    rust_files(&root, &mut files);
    assert!(
        !files.is_empty(),
        "no examples found under {}",
        root.display()
    );
    let mut long = Vec::new();
    let mut included = Vec::new();
    for file in &files {
        let text = std::fs::read_to_string(file).unwrap();
        let lines = text.lines().count();
        if lines > EXAMPLE_MAX_LINES {
            long.push(format!("{} ({lines} lines)", file.display()));
        }
        if text.lines().any(|l| l.trim_start().starts_with("#[path")) {
            included.push(file.display().to_string());
        }
    }
    assert!(
        long.is_empty(),
        "example files over {EXAMPLE_MAX_LINES} lines: {long:?}"
    );
    // The crate tour's NeRF step: a whole trainer on the public API in at most 60 lines.
    let tour = std::fs::read_to_string(root.join("nerf_tour.rs")).unwrap();
    let tour_lines = tour.lines().count();
    assert!(tour_lines <= 60, "nerf_tour.rs: {tour_lines} lines");
    assert!(
        included.is_empty(),
        "examples including files by #[path]: {included:?}"
    );
}
