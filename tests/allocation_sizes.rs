//! No buffer of a caller-chosen length in `src/` without a review: every
//! `Vec::with_capacity(n)`, `vec![x; n]` and `Tensor::zeros(shape)` whose size is not a
//! literal is either on the allowlist below with the reason its size is safe, or the test
//! fails. The reasons are of three kinds:
//! - **data**: the size is that of input the caller already holds in memory (a tensor, a
//!   slice, a mesh), or a small multiple of it, so it cannot ask for more than the input
//!   already takes;
//! - **checked**: the size was checked just above by the crate's allocation limit
//!   (`limits::check_bytes`, 2³³ bytes), or by a bound stated in the function's errors;
//! - **fixed**: the size is a compile-time or architecture constant (a tile, a layer
//!   count of a network that already allocated its weights).
//!
//! The check reads `src/` as text (comments, literals and `#[cfg(test)]` modules blanked,
//! test-only files left out), so a new site is a diff that names itself here.

use std::collections::BTreeMap;
use std::path::Path;

#[path = "common/source.rs"]
mod source;
use source::{rust_files, strip, without_test_modules};

/// The text from `open` (an opening bracket) to its matching close, exclusive, and
/// the index past the close.
fn bracketed(code: &str, open: usize) -> (String, usize) {
    let mut depth = 0;
    for (k, c) in code[open..].char_indices() {
        match c {
            '(' | '[' | '{' => depth += 1,
            ')' | ']' | '}' => {
                depth -= 1;
                if depth == 0 {
                    return (code[open + 1..open + k].to_string(), open + k + 1);
                }
            }
            _ => {}
        }
    }
    (code[open + 1..].to_string(), code.len())
}

/// The text after the first top-level `sep` of `inner`, if any.
fn after_top_level(inner: &str, sep: char) -> Option<String> {
    let mut depth = 0;
    for (k, c) in inner.char_indices() {
        match c {
            '(' | '[' | '{' => depth += 1,
            ')' | ']' | '}' => depth -= 1,
            c if c == sep && depth == 0 => return Some(inner[k + 1..].to_string()),
            _ => {}
        }
    }
    None
}

fn first_top_level(inner: &str) -> String {
    let mut depth = 0;
    for (k, c) in inner.char_indices() {
        match c {
            '(' | '[' | '{' => depth += 1,
            ')' | ']' | '}' => depth -= 1,
            ',' if depth == 0 => return inner[..k].to_string(),
            _ => {}
        }
    }
    inner.to_string()
}

fn normal(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// A size made of literals only (`3`, `1 << 20`, `(0, 3)`, `()`).
fn literal(size: &str) -> bool {
    size.chars()
        .all(|c| c.is_ascii_digit() || " _()<,*+".contains(c))
}

/// Every site in one file's code: `with_capacity(n)`, `vec![_; n]`, `Tensor::zeros(s)`
/// with a size that is not a literal.
fn sites(code: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (pat, kind) in [("with_capacity(", 0), ("vec![", 1), ("Tensor::zeros(", 2)] {
        let mut from = 0;
        while let Some(i) = code[from..].find(pat) {
            let at = from + i;
            from = at + pat.len();
            let before = code[..at].trim_end();
            if kind == 0 && before.ends_with("fn") {
                continue; // a definition
            }
            if kind == 1 && code[..at].ends_with(|c: char| c.is_ascii_alphanumeric() || c == '_') {
                continue; // smallvec![, …
            }
            let (inner, _) = bracketed(code, at + pat.len() - 1);
            let site = match kind {
                0 => {
                    let n = normal(&inner);
                    (!literal(&n)).then(|| format!("with_capacity({n})"))
                }
                1 => after_top_level(&inner, ';').and_then(|len| {
                    let n = normal(&len);
                    (!literal(&n)).then(|| format!("vec![_; {n}]"))
                }),
                _ => {
                    let s = normal(&first_top_level(&inner));
                    (!literal(&s)).then(|| format!("Tensor::zeros({s})"))
                }
            };
            out.extend(site);
        }
    }
    out
}

/// Every site in `src/`, by file (relative to `src/`), deduplicated with a count.
fn all_sites() -> BTreeMap<(String, String), usize> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut out = BTreeMap::new();
    for file in files {
        let rel = file
            .strip_prefix(&src)
            .expect("under src")
            .to_string_lossy()
            .replace('\\', "/");
        if rel.ends_with("tests.rs") || rel == "test_host.rs" {
            continue; // test-only files
        }
        let text = std::fs::read_to_string(&file).expect("readable source");
        let code = without_test_modules(&strip(&text));
        for site in sites(&code) {
            *out.entry((rel.clone(), site)).or_insert(0) += 1;
        }
    }
    out
}

/// Reviewed sites: (file under `src/`, site as the scan prints it, reason).
const ALLOWED: &[(&str, &str, &str)] = &[
    (
        "camera/align.rs",
        "vec![_; r.len()]",
        "data: a Jacobian row per residual, residuals of the point pairs held",
    ),
    (
        "camera/align.rs",
        "with_capacity(2 * pairs.len())",
        "data: two residuals per point pair held",
    ),
    (
        "camera/mod.rs",
        "with_capacity(2 * n)",
        "checked: subpixel_grid refuses more than 2^28 rows (and Camera::rays/render_image check_bytes first)",
    ),
    (
        "camera/mod.rs",
        "with_capacity(count)",
        "checked: cameras_around refuses count above 2^24 and check_bytes just above",
    ),
    (
        "camera/registration.rs",
        "vec![_; src.len()]",
        "data: one value per pixel of the planes held",
    ),
    (
        "camera/registration.rs",
        "vec![_; w * h]",
        "data: the planes of an image already held (Planes::of_image)",
    ),
    (
        "camera/registration.rs",
        "with_capacity(cameras.len())",
        "data: one result per camera of the slice held",
    ),
    (
        "data/batch.rs",
        "vec![_; n]",
        "checked: the batch size n is refused above 2^28 rays (check_count) first",
    ),
    (
        "data/batch.rs",
        "with_capacity(2 * n)",
        "checked: the batch size n is refused above 2^28 rays (check_count) first",
    ),
    (
        "data/batch.rs",
        "with_capacity(3 * n)",
        "checked: the batch size n is refused above 2^28 rays (check_count) first",
    ),
    (
        "data/batch.rs",
        "with_capacity(if masked { n } else { 0 })",
        "checked: the batch size n is refused above 2^28 rays (check_count) first",
    ),
    (
        "data/batch.rs",
        "with_capacity(n * kk)",
        "checked: n · k² is refused above 2^28 rays (check_count) first",
    ),
    (
        "data/batch.rs",
        "with_capacity(n)",
        "checked: the batch size n is refused above 2^28 rays (check_count) first",
    ),
    (
        "data/dataset.rs",
        "with_capacity(3 * w * h)",
        "data: the pixels of an image already decoded",
    ),
    (
        "data/dataset.rs",
        "with_capacity(w * h)",
        "data: the pixels of an image already decoded",
    ),
    (
        "data/image.rs",
        "with_capacity(values.len())",
        "data: the values of a tensor held",
    ),
    (
        "data/image.rs",
        "with_capacity(w * h * c)",
        "data: the pixels of a tensor or image held",
    ),
    (
        "data/metrics.rs",
        "vec![_; h * w]",
        "data: one value per pixel of the images compared",
    ),
    (
        "data/output.rs",
        "with_capacity(dataset.views().len())",
        "data: one frame per view of the dataset held",
    ),
    (
        "data/shapes.rs",
        "vec![_; n]",
        "checked: one split per shape of a category; ShapeCollectionConfig::validate refuses more than 2^20 shapes first",
    ),
    (
        "dvr/losses.rs",
        "vec![_; r]",
        "data: one value per ray held",
    ),
    (
        "dvr/losses.rs",
        "with_capacity(steps * chunk.len())",
        "checked: steps·chunk ≤ max(65 536, steps), and steps is checked by check_bytes above",
    ),
    (
        "dvr/marching.rs",
        "vec![_; brackets.len()]",
        "data: one value per bracket found on the rays held",
    ),
    (
        "dvr/marching.rs",
        "vec![_; r]",
        "data: one value per ray held",
    ),
    (
        "dvr/marching.rs",
        "with_capacity(2 * act.len())",
        "data: two points per active ray held",
    ),
    (
        "dvr/marching.rs",
        "with_capacity(3 * n)",
        "data: RayPoints::with_capacity, whose callers pass sizes checked or held",
    ),
    (
        "dvr/marching.rs",
        "with_capacity(3 * r)",
        "data: three coordinates per ray held",
    ),
    (
        "dvr/marching.rs",
        "with_capacity(brackets.len())",
        "data: one point per bracket found on the rays held",
    ),
    (
        "dvr/marching.rs",
        "with_capacity(held)",
        "checked: check_bytes on config.chunk_points just above",
    ),
    (
        "dvr/marching.rs",
        "with_capacity(n)",
        "data: RayPoints::with_capacity, whose callers pass sizes checked or held",
    ),
    (
        "dvr/marching.rs",
        "with_capacity(p.ids.len())",
        "data: one value per point of the chunk held",
    ),
    (
        "dvr/marching.rs",
        "with_capacity(p.pts.len())",
        "data: one value per coordinate of the chunk held",
    ),
    (
        "dvr/model.rs",
        "Tensor::zeros((n, 3))",
        "data: one row per ray of the batch held",
    ),
    (
        "dvr/model.rs",
        "vec![_; n]",
        "data: one flag per ray of the batch held",
    ),
    (
        "encoding/coarse_to_fine.rs",
        "vec![_; bands]",
        "data: one weight per band of the frequency encoding already built",
    ),
    (
        "encoding/feature_grid.rs",
        "Tensor::zeros((b * cells, c))",
        "checked: scatter's check_bytes on cells (B·cells·(C + 3) values)",
    ),
    (
        "encoding/feature_grid.rs",
        "vec![_; b * cells]",
        "checked: scatter's check_bytes on cells (B·cells·(C + 3) values)",
    ),
    (
        "encoding/feature_grid.rs",
        "vec![_; host.len()]",
        "data: one index per point of the tensor held",
    ),
    (
        "encoding/feature_grid.rs",
        "vec![_; total + 1]",
        "checked: scatter's check_bytes on cells (B·cells·(C + 3) values)",
    ),
    (
        "encoding/feature_grid.rs",
        "vec![_; total]",
        "checked: scatter's check_bytes on cells (B·cells·(C + 3) values)",
    ),
    (
        "encoding/feature_grid.rs",
        "with_capacity(b * n * corners)",
        "data: 2^D corners per point of the tensor held (D ≤ 3)",
    ),
    (
        "encoding/feature_grid.rs",
        "with_capacity(b * n * k)",
        "data: D values per point of the tensor held",
    ),
    (
        "encoding/feature_grid.rs",
        "with_capacity(corners)",
        "fixed: 2^D corners, D ≤ 3",
    ),
    (
        "encoding/hash.rs",
        "with_capacity(c.levels)",
        "checked: check_bytes on config.levels and the table just above",
    ),
    (
        "encoding/hash.rs",
        "with_capacity(corners)",
        "fixed: 2^D corners, D ≤ 4",
    ),
    (
        "encoding/hash.rs",
        "with_capacity(d)",
        "fixed: D ≤ 4 axes",
    ),
    (
        "encoding/hash.rs",
        "with_capacity(host.len())",
        "data: one value per coordinate of the positions held",
    ),
    (
        "encoding/hash.rs",
        "with_capacity(n * corners)",
        "data: 2^D corners per position held (D ≤ 4)",
    ),
    (
        "encoding/hash.rs",
        "with_capacity(n * d)",
        "data: D values per position held",
    ),
    (
        "encoding/hash.rs",
        "with_capacity(p.levels.len())",
        "checked: the levels were checked when the grid was built",
    ),
    (
        "flow/analytic.rs",
        "with_capacity(n)",
        "checked: check_bytes on n just above",
    ),
    (
        "kernels/cuda/hash_grid.rs",
        "with_capacity(3 * p.levels.len().max(1))",
        "fixed: the widths or layers of a network or encoding already built",
    ),
    (
        "kernels/cuda/nerf_loss.rs",
        "with_capacity(last)",
        "fixed: the widths or layers of a network or encoding already built",
    ),
    (
        "kernels/cuda/nerf_loss.rs",
        "with_capacity(net.layers.len())",
        "fixed: the widths or layers of a network or encoding already built",
    ),
    (
        "kernels/dispatch.rs",
        "with_capacity(N)",
        "fixed: the input count of an op, a compile-time constant",
    ),
    (
        "narrow.rs",
        "Tensor::zeros(shape)",
        "data: an empty tensor (the shape holds a zero extent: no element)",
    ),
    (
        "narrow.rs",
        "Tensor::zeros(one)",
        "data: one row of an empty shape's other extents, which the caller's tensors hold",
    ),
    (
        "field.rs",
        "Tensor::zeros((n, 1))",
        "data: an empty batch of points (n = 0)",
    ),
    (
        "field.rs",
        "Tensor::zeros(n)",
        "data: an empty batch of points (n = 0)",
    ),
    (
        "nn/training.rs",
        "Tensor::zeros((2, v.elem_count()))",
        "data: Adam's two moments per element of a variable the caller holds",
    ),
    (
        "data/hull.rs",
        "vec![_; (w + 1) * (h + 1)]",
        "data: one entry per pixel of an image the dataset holds",
    ),
    (
        "kernels/composite.rs",
        "vec![_; r * width]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/composite.rs",
        "with_capacity(if on { len } else { 0 })",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/composite.rs",
        "with_capacity(r)",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/frequency.rs",
        "vec![_; m]",
        "fixed: the widths or layers of a network or encoding already built",
    ),
    (
        "kernels/frequency.rs",
        "vec![_; rows * w]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/frequency.rs",
        "vec![_; x.len()]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/onet.rs",
        "vec![_; chunks * per]",
        "data: one weight-and-bias gradient per 2048-row chunk of the rows held, each the size of a layer's parameters held",
    ),
    (
        "kernels/onet.rs",
        "vec![_; cond.len()]",
        "data: the gradient of a fused op, the size of the input tensor held",
    ),
    (
        "kernels/pool.rs",
        "vec![_; len]",
        "data: a buffer of a fused op's callers: the decoder's rows (the rows held times the width of the weights held) or a convolution's grid (checked by VoxelEncoder::forward, B·R³·max(27, 4w) values)",
    ),
    (
        "kernels/onet.rs",
        "vec![_; p.len()]",
        "data: the gradient of a fused op, the size of the input tensor held",
    ),
    (
        "kernels/onet.rs",
        "vec![_; params.len()]",
        "data: the gradient of a fused op, the size of the input tensor held",
    ),
    (
        "kernels/onet.rs",
        "vec![_; self.rows]",
        "data: the output of a fused op, one value per row of the points held (checked against their length)",
    ),
    (
        "kernels/onet.rs",
        "vec![_; y.len().div_ceil(TILE * out)]",
        "data: one slot per 128-row tile of an output buffer held",
    ),
    (
        "kernels/onet.rs",
        "with_capacity(self.blocks + 1)",
        "data: one entry per layer of the decoder, whose weights are held",
    ),
    (
        "kernels/onet.rs",
        "with_capacity(self.blocks)",
        "data: one entry per layer of the decoder, whose weights are held",
    ),
    (
        "occupancy/onet.rs",
        "with_capacity(2 * norms.len())",
        "data: two tensors per normalisation layer of the decoder, whose weights are held",
    ),
    (
        "kernels/cond_norm.rs",
        "vec![_; beta.len()]",
        "data: the gradient of a fused op, the size of the input tensor held",
    ),
    (
        "kernels/cond_norm.rs",
        "vec![_; gamma.len()]",
        "data: the gradient of a fused op, the size of the input tensor held",
    ),
    (
        "kernels/cond_norm.rs",
        "vec![_; h]",
        "data: one row of the input tensor held",
    ),
    (
        "kernels/cond_norm.rs",
        "vec![_; k * h2]",
        "data: two rows per group a 128-row tile spans, at most 2·128 rows of the input held",
    ),
    (
        "kernels/cond_norm.rs",
        "vec![_; x.len()]",
        "data: the output or the input gradient of the fused batch norm, the size of the input tensor held",
    ),
    (
        "kernels/cond_norm.rs",
        "vec![_; len]",
        "data: the gradient of a fused op, the size of an input tensor held",
    ),
    (
        "kernels/cond_norm.rs",
        "vec![_; x.len().div_ceil(ROWS * h) * 2 * h]",
        "data: two rows per 128-row tile of the input tensor held, below its size",
    ),
    (
        "kernels/conv.rs",
        "vec![_; len]",
        "data: at most 256 output cells' windows, taps·Cᵢ columns, the weight tensor's row length",
    ),
    (
        "kernels/conv.rs",
        "vec![_; w.len()]",
        "data: the weight's gradient, the size of the weight tensor held",
    ),
    (
        "kernels/conv.rs",
        "vec![_; self.c_out]",
        "data: the bias's gradient, the size of the bias tensor held",
    ),
    (
        "kernels/conv.rs",
        "with_capacity(kd * kh)",
        "data: one entry per window row of the kernel, the weight tensor held has kd·kh·kw per output channel",
    ),
    (
        "kernels/conv.rs",
        "with_capacity(kd * kh * plen)",
        "data: kd·kh window rows of about one input row each (s·W' rounded up to 8 cells, plus kw), the kernel and the input grid held",
    ),
    (
        "kernels/conv.rs",
        "vec![_; self.out_len()]",
        "checked: VoxelEncoder::forward checks B·R³·max(27, 4w) values and ResnetEncoder::forward B·⌈H/2⌉·⌈W/2⌉·max(49·C, 9·w), which bound every convolution's output, with limits::check_bytes first",
    ),
    (
        "occupancy/resnet.rs",
        "Tensor::zeros(co)",
        "data: one value per output channel of the weight tensor held",
    ),
    (
        "kernels/conv.rs",
        "vec![_; layer.out_len()]",
        "checked: VoxelEncoder::forward checks B·R³·max(27, 4w) values, which bound every convolution's output, with limits::check_bytes first",
    ),
    (
        "kernels/conv.rs",
        "vec![_; params.len()]",
        "data: the gradient of the parameters tensor held",
    ),
    (
        "kernels/conv.rs",
        "with_capacity(last)",
        "data: one buffer per layer of the op, each layer's weights held",
    ),
    (
        "kernels/conv.rs",
        "with_capacity(self.layers.len())",
        "data: one range per layer of the op, each layer's weights held",
    ),
    (
        "kernels/conv.rs",
        "vec![_; x.len()]",
        "data: the gradient of a fused op, the size of the input tensor held",
    ),
    (
        "kernels/integrated.rs",
        "vec![_; m]",
        "fixed: 256 rows of scratch times the encoding's octaves and dimension",
    ),
    (
        "kernels/integrated.rs",
        "vec![_; rows * w]",
        "checked: integrated_pe checks the output's [N, 2·D·L] with limits::check_bytes first",
    ),
    (
        "kernels/integrated.rs",
        "vec![_; x.len()]",
        "data: the gradient of a fused op, the size of the input tensor held",
    ),
    (
        "kernels/grid_sample.rs",
        "vec![_; b * c * p]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/grid_sample.rs",
        "vec![_; part.len()]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/grid_sample.rs",
        "vec![_; x.len() / k * c]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/grid_sample.rs",
        "vec![_; x.len()]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/hash_grid.rs",
        "vec![_; (x.len() / d) * w]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/hash_grid.rs",
        "vec![_; level.rows * f]",
        "data: the rows of the hash table held (checked when the grid was built)",
    ),
    (
        "kernels/hash_grid.rs",
        "vec![_; total * f]",
        "data: the rows of the hash table held (checked when the grid was built)",
    ),
    (
        "kernels/hash_grid.rs",
        "vec![_; x.len()]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/hash_grid.rs",
        "with_capacity(p.levels.len())",
        "fixed: the widths or layers of a network or encoding already built",
    ),
    (
        "kernels/mlp.rs",
        "vec![_; chunks.max(1) * self.n_params]",
        "data: one gradient of the weights held per chunk of CHUNK = 2048 rows of the input held",
    ),
    (
        "kernels/mlp.rs",
        "vec![_; hidden]",
        "fixed: the widths or layers of a network or encoding already built",
    ),
    (
        "kernels/mlp.rs",
        "vec![_; n * out]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/mlp.rs",
        "vec![_; n * self.a0]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/mlp.rs",
        "vec![_; w]",
        "fixed: the widths or layers of a network or encoding already built",
    ),
    (
        "kernels/mlp.rs",
        "with_capacity(last)",
        "fixed: the widths or layers of a network or encoding already built",
    ),
    (
        "kernels/mlp.rs",
        "with_capacity(layers.len())",
        "fixed: the widths or layers of a network or encoding already built",
    ),
    (
        "kernels/mlp_tangents.rs",
        "vec![_; chunks.max(1) * np]",
        "data: one gradient of the weights held per chunk of CHUNK = 2048 rows of the input held",
    ),
    (
        "kernels/mlp_tangents.rs",
        "vec![_; da0.len()]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/mlp_tangents.rs",
        "vec![_; n * a]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/mlp_tangents.rs",
        "vec![_; n * k * a]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/mlp_tangents.rs",
        "vec![_; n * self.width()]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/mlp_tangents.rs",
        "vec![_; rows * self.mlp.a0]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/mlp_tangents.rs",
        "vec![_; rows * self.mlp.out_dim()]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/nerf.rs",
        "vec![_; TILE * h_in]",
        "fixed: a tile of TILE rows of the network's width (weights already built)",
    ),
    (
        "kernels/nerf.rs",
        "vec![_; TILE * self.head.out_dim()]",
        "fixed: a tile of TILE rows of the network's width (weights already built)",
    ),
    (
        "kernels/nerf.rs",
        "vec![_; TILE * t_out]",
        "fixed: a tile of TILE rows of the network's width (weights already built)",
    ),
    (
        "kernels/nerf.rs",
        "vec![_; chunks.max(1) * np]",
        "data: one gradient of the weights held per chunk of CHUNK = 2048 rows of the input held",
    ),
    (
        "kernels/nerf.rs",
        "vec![_; n * 4]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/nerf.rs",
        "vec![_; n * a0p]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/nerf.rs",
        "vec![_; n * dd]",
        "data: the output or gradient of a fused op, rows of the input tensor held times a width of the weights held",
    ),
    (
        "kernels/nerf_loss.rs",
        "vec![_; TILE * dd]",
        "fixed: a tile of TILE rows of the network's width (weights already built)",
    ),
    (
        "kernels/nerf_loss.rs",
        "vec![_; TILE * self.nets.trunk.a0]",
        "fixed: a tile of TILE rows of the network's width (weights already built)",
    ),
    (
        "kernels/nerf_loss.rs",
        "vec![_; chunks.len().max(1) * np]",
        "data: one gradient of the weights held per chunk of CHUNK = 2048 rows of the input held",
    ),
    (
        "kernels/nerf_loss.rs",
        "vec![_; chunks.len()]",
        "data: one gradient of the weights held per chunk of CHUNK = 2048 rows of the input held",
    ),
    (
        "kernels/scatter.rs",
        "vec![_; b * cells * c]",
        "checked: scatter's check_bytes on cells before the fused op runs",
    ),
    (
        "kernels/scatter.rs",
        "vec![_; b * n * c]",
        "checked: scatter's check_bytes on cells before the fused op runs",
    ),
    (
        "mesh/io/off.rs",
        "with_capacity(v)",
        "checked: the header's counts are bounded by the file's size just above",
    ),
    (
        "mesh/io/ply.rs",
        "vec![_; el.props.len()]",
        "data: one value per property of the header read",
    ),
    (
        "mesh/io/stl.rs",
        "with_capacity(84 + 50 * faces.len())",
        "data: 50 bytes per face of the mesh held",
    ),
    (
        "mesh/point_cloud.rs",
        "with_capacity(n)",
        "checked: check_bytes on n just above",
    ),
    (
        "mesh/triangle_mesh.rs",
        "vec![_; self.vertices.len()]",
        "data: one normal per vertex of the mesh held",
    ),
    (
        "mesh/triangle_mesh.rs",
        "with_capacity(areas.len())",
        "data: one value per face of the mesh held",
    ),
    (
        "mesh/triangle_mesh.rs",
        "with_capacity(n)",
        "checked: check_bytes on n just above",
    ),
    (
        "mesh/triangle_mesh.rs",
        "with_capacity(polygons.len())",
        "data: one triangle per polygon read",
    ),
    (
        "mesh/triangulate.rs",
        "vec![_; k]",
        "data: one flag per corner of the polygon held",
    ),
    (
        "nn/mlp.rs",
        "Tensor::zeros((n, d, c.dim(1)?))",
        "data: the Jacobian of the points held, D ≤ 4 columns per point",
    ),
    (
        "nn/mlp.rs",
        "with_capacity(2 * self.layers.len())",
        "fixed: the layers of a network already built",
    ),
    (
        "nn/mlp.rs",
        "with_capacity(config.depth + 1)",
        "checked: check_layers on config.depth just above",
    ),
    (
        "nn/resnet_fc.rs",
        "with_capacity(blocks)",
        "checked: check_layers on config.blocks just above",
    ),
    (
        "occupancy/conv_onet.rs",
        "with_capacity(config.blocks)",
        "checked: check_layers on config.blocks just above",
    ),
    (
        "occupancy/conv_onet.rs",
        "with_capacity(config.depth)",
        "checked: unet.depth is refused above 16 before the U-Net is built",
    ),
    (
        "occupancy/conv_onet.rs",
        "with_capacity(config.depth.saturating_sub(1))",
        "checked: unet.depth is refused above 16 before the U-Net is built",
    ),
    (
        "occupancy/conv_onet.rs",
        "with_capacity(index.len())",
        "data: one grid per index tensor held",
    ),
    (
        "occupancy/conv_onet.rs",
        "with_capacity(self.down.len())",
        "fixed: the levels of a U-Net already built",
    ),
    (
        "occupancy/isosurface.rs",
        "vec![_; nx]",
        "data: one row of the grid of values held",
    ),
    (
        "occupancy/isosurface.rs",
        "with_capacity(ids.len())",
        "data: one value per id held",
    ),
    (
        "occupancy/isosurface.rs",
        "with_capacity(nz + 1)",
        "data: one offset per slice of the grid of values held",
    ),
    (
        "occupancy/isosurface.rs",
        "with_capacity(total)",
        "data: the vertices already found on the grid's edges",
    ),
    (
        "occupancy/metrics.rs",
        "vec![_; points.len()]",
        "data: one axis per point held",
    ),
    (
        "occupancy/multires.rs",
        "vec![_; np * np * np]",
        "checked: check_bytes on the final resolution just above",
    ),
    (
        "occupancy/onet.rs",
        "Tensor::zeros((ONET_BLOCK - len, x.dim(1)?))",
        "fixed: padding to a block of ONET_BLOCK rows of the features held",
    ),
    (
        "occupancy/onet.rs",
        "Tensor::zeros(h)",
        "checked: check_layers on config.blocks and hidden first",
    ),
    (
        "occupancy/onet.rs",
        "with_capacity(config.blocks)",
        "checked: check_layers on config.blocks just above",
    ),
    (
        "occupancy/onet.rs",
        "with_capacity(n.div_ceil(ONET_BLOCK))",
        "data: one part per block of the rows held",
    ),
    (
        "occupancy/pointnet.rs",
        "with_capacity(config.layers)",
        "checked: check_layers on config.layers just above",
    ),
    (
        "occupancy/sampling.rs",
        "with_capacity(2 * tris.len() / WN_LEAF + 2)",
        "data: the nodes of a tree over the triangles held",
    ),
    (
        "occupancy/voxel.rs",
        "Tensor::zeros((b, 1, ci))",
        "data: one zero row per grid of the activations held",
    ),
    (
        "texture/mod.rs",
        "with_capacity(mesh.vertices.len())",
        "data: one colour per vertex of the mesh held",
    ),
    (
        "volume/compositing.rs",
        "vec![_; x.len()]",
        "data: one flag per sample of the tensor held",
    ),
    (
        "volume/grid.rs",
        "vec![_; cells]",
        "checked: check_bytes on config.resolution just above",
    ),
    (
        "volume/grid.rs",
        "vec![_; m]",
        "data: one flag per sample marched",
    ),
    (
        "volume/grid.rs",
        "vec![_; r]",
        "data: one count per ray held",
    ),
    (
        "volume/grid.rs",
        "with_capacity(chunk.len() * 3)",
        "data: three coordinates per cell of a chunk of the grid held",
    ),
    (
        "volume/grid.rs",
        "with_capacity(r)",
        "data: one count per ray held",
    ),
    (
        "volume/grid.rs",
        "with_capacity(self.density.len() / 2)",
        "data: half the cells of the grid held",
    ),
    (
        "volume/layout.rs",
        "vec![_; m]",
        "data: one value per packed sample held",
    ),
    (
        "volume/layout.rs",
        "vec![_; p.n_rays]",
        "data: one count per ray of the packing held",
    ),
    (
        "volume/layout.rs",
        "vec![_; r]",
        "data: one count per ray held",
    ),
    (
        "volume/layout.rs",
        "with_capacity(acc)",
        "data: the sum of the counts of the tensor held",
    ),
    (
        "volume/layout.rs",
        "with_capacity(counts.len() + 1)",
        "data: one offset per ray count held",
    ),
    (
        "volume/proposal.rs",
        "Tensor::zeros(r * s)",
        "data: one value per sample of the weights held",
    ),
    (
        "volume/proposal.rs",
        "with_capacity(proposals.len())",
        "data: one level per proposal network passed",
    ),
    (
        "volume/reference.rs",
        "Tensor::zeros((packed.n_rays, c))",
        "data: one row per ray of the packing held",
    ),
    (
        "volume/reference.rs",
        "vec![_; m]",
        "data: one value per packed sample held",
    ),
    (
        "volume/reference.rs",
        "vec![_; r * smax]",
        "data: the padded batch of the packed samples held",
    ),
    (
        "volume/render.rs",
        "vec![_; N]",
        "fixed: N, a const generic (the renderer's outputs)",
    ),
    (
        "volume/sampling.rs",
        "vec![_; r * m]",
        "checked: check_bytes on n just above",
    ),
    (
        "volume/sampling.rs",
        "vec![_; r * n]",
        "checked: check_bytes on n just above",
    ),
    (
        "volume/sampling.rs",
        "with_capacity(s + 1)",
        "data: one CDF value per bin of the weights held",
    ),
];

#[test]
fn every_caller_sized_allocation_is_reviewed() {
    let sites = all_sites();
    let unreviewed: Vec<String> = sites
        .keys()
        .filter(|(file, site)| !ALLOWED.iter().any(|(f, s, _)| f == file && s == site))
        .map(|(file, site)| format!("    (\"{file}\", \"{site}\", \"…\"),"))
        .collect();
    assert!(
        unreviewed.is_empty(),
        "{} allocation sites whose size is not a literal and that no one reviewed: check the \
         size with `limits::check_bytes` (or show it is bounded by data already held) and add \
         them to ALLOWED with the reason:\n{}",
        unreviewed.len(),
        unreviewed.join("\n")
    );
}

#[test]
fn every_allowlisted_site_exists_and_has_a_reason() {
    let sites = all_sites();
    for (file, site, reason) in ALLOWED {
        assert!(
            sites.contains_key(&(file.to_string(), site.to_string())),
            "allowlisted but gone (remove it): {file}: {site}"
        );
        assert!(reason.len() > 10, "no reason given for {file}: {site}");
    }
}

#[test]
fn the_scan_sees_caller_sized_sites_and_skips_literal_ones() {
    let code = "let a = Vec::with_capacity(n);\nlet b = vec![0.0; 3];\nlet c = vec![1, 2];\n\
                let d = vec![0u8; r * s];\nlet e = Tensor::zeros((), dt, dev)?;\n\
                let f = Tensor::zeros((n, 3), dt, dev)?;\nlet g = Vec::with_capacity(1 << 20);\n";
    assert_eq!(
        sites(code),
        [
            "with_capacity(n)",
            "vec![_; r * s]",
            "Tensor::zeros((n, 3))"
        ]
    );
    let hidden = strip("// Vec::with_capacity(n)\nlet s = \"vec![0; n]\";\n");
    assert!(sites(&hidden).is_empty());
}
