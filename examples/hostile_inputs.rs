//! Hostile inputs: every file reader of the crate against files that are truncated, lie
//! about their counts, claim huge counts, amplify a small file into much work, hold NaN or
//! infinity, are not UTF-8, are directories or are missing, and dataset folders that name
//! files outside themselves, repeat one frame, hold an image bomb, unusual images, an
//! empty split or degenerate cameras; a markdown table of the
//! outcome, time and peak memory of each case.
//!
//! ```text
//! cargo run --release --example hostile_inputs                   # target/hostile_inputs/
//! cargo run --release --example hostile_inputs -- --out docs      # regenerates the docs' table
//! ```
//!
//! Each case's file (or dataset folder) is written into a fresh scratch directory
//! (`$TMPDIR/nf-hostile-<pid>/NN`, removed at the end) and read in a child process: this
//! executable with `--read READER PATH`, under `/usr/bin/time -v` when it exists (its
//! maximum resident set size is the peak RSS column; without it the column reads n/a),
//! killed after 2 s (a hang is a finding: `TIMEOUT`). The child calls one reader and
//! prints exactly one line, `ok: <summary>` or `err: <the error's Display>`, exiting 0
//! either way, so that a panic or an abort shows as `PANIC`. The readers:
//!
//! | reader | call |
//! |---|---|
//! | `ply`, `obj`, `stl`, `off` | `Mesh::load(path)` (the extension picks the format) |
//! | `cloud` | `PointCloud::load(path)`; every PLY case is read by `ply` and by `cloud` |
//! | `blender` | `data::load(dir, &LoadConfig::default())` (the layout is detected: Blender `transforms_train.json` or nerfstudio `transforms.json`) |
//! | `npz` | `data::load(dir, &LoadConfig { split: Split::All, .. })` on an IDR/DTU folder (`cameras.npz`, `image/`, `mask/`) |
//!
//! The time column is the child's wall time as the parent measures it (process start
//! included). Each reader's first row is a valid control file, so that every hostile case
//! fails for its own reason and not for a broken fixture.
//!
//! The table goes to `OUT/hostile_inputs.md` (`--out`, default `target/hostile_inputs`) and
//! to stdout, below the command, the date (UTC), the machine
//! and the git commit. The command is a check: it exits non-zero when a case panics or
//! aborts, runs past 2 s, peaks above 256 MiB, or ends otherwise than expected: hostile
//! cases must be errors; the controls and the cases that are legitimate files (a
//! property-less PLY element with a huge count, convex 255-gons, a stray byte in an OBJ
//! group name) must load. Unix only (process groups, `/usr/bin/time`, `uname`).

use clap::Parser;
use image::codecs::jpeg::JpegEncoder;
use image::codecs::png::PngEncoder;
use image::{ExtendedColorType, ImageEncoder};
use neural_fields::data::{load, LoadConfig, Split};
use neural_fields::mesh::{Mesh, MeshFormat, PointCloud};
use std::error::Error;
use std::fs;
use std::io::Write;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::rc::Rc;
use std::time::{Duration, Instant};

type Res<T> = Result<T, Box<dyn Error>>;
/// A file's bytes, generated when the case runs.
type Bytes = Rc<dyn Fn() -> Res<Vec<u8>>>;
/// Writes a case's input into its scratch directory and returns the path to read.
type Make = Rc<dyn Fn(&Path) -> Res<PathBuf>>;

const LIMIT: Duration = Duration::from_secs(2);
const MAX_RSS_MIB: f64 = 256.0;
const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/data");
/// The length of an outcome in the table.
const OUTCOME_CHARS: usize = 160;

const CONTROL: &str = "0 control";
const TRUNCATED: &str = "1 truncated";
const LYING: &str = "2 lying count";
const HUGE: &str = "3 huge count";
const AMPLIFY: &str = "4 amplification";
const NAN: &str = "5 NaN / Inf";
const UTF8: &str = "6 non-UTF-8";
const DIRECTORY: &str = "7 directory";
const MISSING: &str = "8 missing";
const DATASET: &str = "9 dataset folder";

/// Every file reader of the crate against hostile files: a table of the outcome, time
/// and peak memory of each case; exits non-zero on an unexpected outcome.
#[derive(Parser, Debug)]
struct Args {
    /// The folder for hostile_inputs.md (`--out docs` regenerates the docs' table).
    #[arg(long, default_value = "target/hostile_inputs")]
    out: PathBuf,
    /// The child process: read PATH with READER (ply, obj, stl, off, cloud, blender, npz)
    /// and print one line, `ok: …` or `err: …`.
    #[arg(long, num_args = 2, value_names = ["READER", "PATH"], conflicts_with = "out")]
    read: Option<Vec<String>>,
}

fn main() -> Res<()> {
    let args = Args::parse();
    if let Some([reader, path]) = args.read.as_deref() {
        let line = match read(reader, Path::new(path)) {
            Ok(summary) => format!("ok: {summary}"),
            Err(e) => format!("err: {e}"),
        };
        println!("{}", line.replace('\n', " "));
        return Ok(());
    }
    let given: Vec<String> = std::env::args().skip(1).collect();
    report(&args.out.join("hostile_inputs.md"), &given)
}

/// The child: one reader on one path, summarised.
fn read(reader: &str, path: &Path) -> Res<String> {
    Ok(match reader {
        "ply" | "obj" | "stl" | "off" => {
            let mesh = Mesh::load(path)?;
            let (faces, bytes) = (mesh.faces.len(), fs::metadata(path)?.len());
            format!(
                "mesh {} vertices {faces} faces ({bytes} bytes, {:.3} faces/byte)",
                mesh.vertices.len(),
                faces as f64 / bytes as f64
            )
        }
        "cloud" => format!("cloud {} points", PointCloud::load(path)?.points().len()),
        "blender" => format!(
            "dataset, views: {}",
            load(path, &LoadConfig::default())?.views().len()
        ),
        "npz" => {
            let config = LoadConfig {
                split: Split::All,
                ..LoadConfig::default()
            };
            format!("dataset, views: {}", load(path, &config)?.views().len())
        }
        other => return Err(format!("unknown reader {other:?}").into()),
    })
}

// ---------------------------------------------------------------------------- cases

#[derive(Clone, Copy, PartialEq)]
enum Expect {
    Loads,
    Fails,
}

#[derive(Clone)]
struct Case {
    class: &'static str,
    reader: &'static str,
    input: &'static str,
    expect: Expect,
    /// `None`: the class cannot apply to the format (the input says why).
    make: Option<Make>,
}

fn case(
    class: &'static str,
    reader: &'static str,
    expect: Expect,
    input: &'static str,
    make: Option<Make>,
) -> Case {
    Case {
        class,
        reader,
        input,
        expect,
        make,
    }
}

/// The cases, a table: class, reader, expected outcome, input, how to write it.
#[rustfmt::skip]
fn cases() -> Vec<Case> {
    use Expect::{Fails, Loads};
    use MeshFormat::{Obj, Off, PlyAscii, PlyBinary, StlAscii, StlBinary};
    let na = |class, reader, why| case(class, reader, Fails, why, None);
    let list = vec![
        // Controls: the fixtures the hostile cases start from.
        case(CONTROL, "ply", Loads, "binary cube PLY (8 vertices, 12 faces)",
            file("x.ply", || base(PlyBinary))),
        case(CONTROL, "obj", Loads, "cube OBJ", file("x.obj", || base(Obj))),
        case(CONTROL, "stl", Loads, "binary cube STL", file("x.stl", || base(StlBinary))),
        case(CONTROL, "off", Loads, "cube OFF", file("x.off", || base(Off))),
        case(CONTROL, "blender", Loads, "Blender `transforms_train.json`, 1 frame, 100×100 PNG",
            blender("transforms_train.json", || Ok(blender_json()))),
        case(CONTROL, "blender", Loads, "nerfstudio `transforms.json`, `w`, `h` = 100, 2 frames \
            (the train split skips frame 0)",
            blender("transforms.json", || Ok(nerfstudio(100)))),
        case(CONTROL, "npz", Loads, "`cameras.npz` (stored): 4×4 `<f8` `world_mat_0`; image, mask",
            dtu(|| npz_world(npy("(4, 4)", &WORLD)))),
        // 1. Truncated.
        case(TRUNCATED, "ply", Fails, "binary cube PLY minus its last 10 bytes",
            file("x.ply", || Ok(cut(base(PlyBinary)?, 10)))),
        case(TRUNCATED, "obj", Fails, "cube OBJ whose last face line has 2 refs",
            file("x.obj", || Ok(drop_last_field(&base(Obj)?)))),
        case(TRUNCATED, "stl", Fails, "binary cube STL minus its last 20 bytes",
            file("x.stl", || Ok(cut(base(StlBinary)?, 20)))),
        case(TRUNCATED, "off", Fails, "cube OFF without its last face line",
            file("x.off", || Ok(drop_last_line(&base(Off)?)))),
        case(TRUNCATED, "blender", Fails, "`transforms_train.json` cut inside `transform_matrix`",
            blender("transforms_train.json", || Ok(cut(blender_json(), 20)))),
        case(TRUNCATED, "npz", Fails, "the control's `cameras.npz` cut in half",
            dtu(|| npz_world(npy("(4, 4)", &WORLD)).map(|b| b[..b.len() / 2].to_vec()))),
        // 2. Lying counts: a header count smaller than the data.
        case(LYING, "ply", Fails, "cube PLY declaring `element face 10`; 12 faces follow",
            file("x.ply", || edit(&base(PlyBinary)?, "element face 12", b"element face 10"))),
        na(LYING, "obj", "n/a: OBJ declares no counts"),
        case(LYING, "stl", Fails, "binary cube STL declaring 11 facets; 12 follow",
            file("x.stl", || Ok(with_count(base(StlBinary)?, 11)))),
        case(LYING, "off", Fails, "cube OFF declaring `8 11 0`; 12 faces follow",
            file("x.off", || edit(&base(Off)?, "8 12 0", b"8 11 0"))),
        na(LYING, "blender", "n/a: JSON declares no counts"),
        case(LYING, "npz", Fails, "`world_mat_0.npy` header shape (5, 4, 4), 4×4 data",
            dtu(|| npz_world(npy("(5, 4, 4)", &WORLD)))),
        // 3. Huge counts.
        case(HUGE, "ply", Fails, "cube PLY declaring `element vertex 18446744073709551615`",
            file("x.ply", || edit(&base(PlyBinary)?, "vertex 8", b"vertex 18446744073709551615"))),
        case(HUGE, "ply", Loads, "property-less `element junk 18446744073709551615` before the \
            cube (legitimate: it holds no data)",
            file("x.ply", || edit(&base(PlyBinary)?, "element vertex",
                b"element junk 18446744073709551615\nelement vertex"))),
        case(HUGE, "obj", Fails, "(OBJ has no counts) cube + face `f 1 2 4294967297` (2³² + 1)",
            file("x.obj", || Ok([base(Obj)?, b"f 1 2 4294967297\n".to_vec()].concat()))),
        case(HUGE, "stl", Fails, "binary cube STL declaring 4294967295 facets",
            file("x.stl", || Ok(with_count(base(StlBinary)?, u32::MAX)))),
        case(HUGE, "off", Fails, "cube OFF with counts `1000000000000 1 0`",
            file("x.off", || edit(&base(Off)?, "8 12 0", b"1000000000000 1 0"))),
        case(HUGE, "blender", Fails, "nerfstudio `transforms.json`, `w`, `h` = 1000000000, PNG 100²",
            blender("transforms.json", || Ok(nerfstudio(1_000_000_000)))),
        case(HUGE, "npz", Fails, "`world_mat_0.npy` header shape (1099511627776, 4, 4), 4×4 data",
            dtu(|| npz_world(npy("(1099511627776, 4, 4)", &WORLD)))),
        // 4. Amplification: a small file that would take much work or memory.
        case(AMPLIFY, "ply", Loads, "40 faces of a convex 255-gon, `list uint int` (legitimate)",
            file("x.ply", || Ok(ply_ngon(255, 40, 255)))),
        case(AMPLIFY, "ply", Fails, "`property list uint int` face with count 4000000000",
            file("x.ply", || Ok(ply_ngon(3, 1, 4_000_000_000)))),
        case(AMPLIFY, "obj", Fails, "`f` with 100 000 refs cycling a concave 10-corner star",
            file("x.obj", || Ok(star_obj(0.4)))),
        case(AMPLIFY, "obj", Fails, "`f` with 100 000 refs cycling a convex decagon (10 000 turns)",
            file("x.obj", || Ok(star_obj(1.0)))),
        case(AMPLIFY, "stl", Fails, "ASCII STL loop of 100 000 `vertex` lines cycling the star",
            file("x.stl", || Ok(star_stl()))),
        case(AMPLIFY, "off", Fails, "OFF face of 100 000 corners cycling the star",
            file("x.off", || Ok(star_off()))),
        case(AMPLIFY, "blender", Fails, "`transforms_train.json`: 100 000 nested `[` … `]`",
            blender("transforms_train.json", || Ok(nested(100_000)))),
        case(AMPLIFY, "npz", Fails, "deflated `world_mat_0.npy` (1 MiB) inflating to 1 GiB",
            dtu(npz_bomb)),
        // 5. NaN / Inf.
        case(NAN, "ply", Fails, "ASCII cube PLY, first vertex `nan 0 0`",
            file("x.ply", || edit(&base(PlyAscii)?, "header\n0 0 0", b"header\nnan 0 0"))),
        case(NAN, "obj", Fails, "cube OBJ, first vertex `v 0 inf 0`",
            file("x.obj", || edit(&base(Obj)?, "v 0 0 0", b"v 0 inf 0"))),
        case(NAN, "stl", Fails, "binary cube STL, a corner with x = NaN",
            file("x.stl", || Ok(nan_corner(base(StlBinary)?)))),
        case(NAN, "off", Fails, "cube OFF, first vertex `nan 0 0`",
            file("x.off", || edit(&base(Off)?, "0\n0 0 0", b"0\nnan 0 0"))),
        case(NAN, "blender", Fails, "`transform_matrix` entry `1e999`",
            blender("transforms_train.json", || edit(&blender_json(), "1, 4]", b"1, 1e999]"))),
        case(NAN, "npz", Fails, "`world_mat_0` with a NaN entry",
            dtu(|| npz_world(npy("(4, 4)", &nan_world())))),
        // 6. Non-UTF-8.
        case(UTF8, "ply", Fails, "ASCII cube PLY, byte 0xFF in the first vertex line",
            file("x.ply", || edit(&base(PlyAscii)?, "header\n0 0 0", b"header\n0 \xFF 0"))),
        case(UTF8, "obj", Fails, "cube OBJ as UTF-16LE with a BOM",
            file("x.obj", || Ok(utf16le(&base(Obj)?)))),
        case(UTF8, "obj", Loads, "cube OBJ after a line `g \\xFF` (legitimate: names are ignored)",
            file("x.obj", || Ok([b"g \xFF\n".to_vec(), base(Obj)?].concat()))),
        case(UTF8, "stl", Fails, "ASCII cube STL, byte 0xFF in a `vertex` line",
            file("x.stl", || edit(&base(StlAscii)?, "vertex 0 0 0", b"vertex 0 \xFF 0"))),
        case(UTF8, "off", Fails, "cube OFF, byte 0xFF in the first vertex line",
            file("x.off", || edit(&base(Off)?, "0\n0 0 0", b"0\n0 \xFF 0"))),
        case(UTF8, "blender", Fails, "byte 0xFF inside the `file_path` string",
            blender("transforms_train.json", || edit(&blender_json(), "r_0", b"r_\xFF0"))),
        case(UTF8, "npz", Fails, "`world_mat_0.npy` header with byte 0xFF",
            dtu(|| npz_world(edit(&npy("(4, 4)", &WORLD), "fortran_", b"fortran\xFF")?))),
        // 7. A directory where a file is expected.
        case(DIRECTORY, "ply", Fails, "directory `x.ply`", directory("x.ply")),
        case(DIRECTORY, "obj", Fails, "directory `x.obj`", directory("x.obj")),
        case(DIRECTORY, "stl", Fails, "directory `x.stl`", directory("x.stl")),
        case(DIRECTORY, "off", Fails, "directory `x.off`", directory("x.off")),
        case(DIRECTORY, "blender", Fails, "`transforms_train.json` is a directory",
            make("", vec![BLENDER_PNG, ("transforms_train.json", Src::Dir)])),
        case(DIRECTORY, "npz", Fails, "`cameras.npz` is a directory",
            make("", vec![DTU_IMAGE, DTU_MASK, ("cameras.npz", Src::Dir)])),
        // 8. Missing.
        case(MISSING, "ply", Fails, "nonexistent `missing.ply`", make("missing.ply", vec![])),
        case(MISSING, "obj", Fails, "nonexistent `missing.obj`", make("missing.obj", vec![])),
        case(MISSING, "stl", Fails, "nonexistent `missing.stl`", make("missing.stl", vec![])),
        case(MISSING, "off", Fails, "nonexistent `missing.off`", make("missing.off", vec![])),
        case(MISSING, "blender", Fails, "empty directory", make("", vec![])),
        case(MISSING, "npz", Fails, "empty directory", make("", vec![])),
        // 9. Dataset folders: paths out of the folder, repeated frames, image bombs,
        // unusual but legitimate images, empty splits, degenerate cameras.
        case(DATASET, "blender", Fails, "`file_path` `/proc/self/environ` (absolute, outside the folder)",
            blender("transforms_train.json", || Ok(blender_frames(0.69, &["/proc/self/environ"])))),
        case(DATASET, "blender", Fails, "`file_path` `../r_0`: an existing PNG beside the folder",
            make("data", vec![("r_0.png", Src::Copy("wuson/train/r_0.png")),
                ("data/transforms_train.json", bytes(|| Ok(blender_frames(0.69, &["../r_0"]))))])),
        case(DATASET, "blender", Loads, "1000 frames naming one PNG (decoded once, shared)",
            blender("transforms_train.json", || Ok(blender_frames(0.69, &["./train/r_0"; 1000])))),
        case(DATASET, "blender", Fails, "a 67-byte PNG whose header states 32768 × 32768 RGBA",
            make("", vec![("train/r_0.png", bytes(|| Ok(png_header_only(32_768, 32_768)))),
                ("transforms_train.json", bytes(|| Ok(blender_json())))])),
        case(DATASET, "blender", Loads, "16-bit RGBA PNG, 8 × 8",
            image_folder(|| png(8, 8, ExtendedColorType::Rgba16))),
        case(DATASET, "blender", Loads, "greyscale PNG, 8 × 8",
            image_folder(|| png(8, 8, ExtendedColorType::L8))),
        case(DATASET, "blender", Loads, "a 1 × 1 frame",
            image_folder(|| png(1, 1, ExtendedColorType::Rgba8))),
        case(DATASET, "blender", Loads, "a JPEG frame (nerfstudio `train/r_0.jpg`), 8 × 8",
            make("", vec![("train/r_0.jpg", bytes(|| jpeg(8, 8))),
                ("transforms.json", bytes(|| Ok(nerfstudio_frame("train/r_0.jpg", 8, 8.0))))])),
        case(DATASET, "blender", Fails, "nerfstudio `fl_x` = `fl_y` = 1e300",
            make("", vec![("train/r_0.jpg", bytes(|| jpeg(8, 8))),
                ("transforms.json", bytes(|| Ok(nerfstudio_frame("train/r_0.jpg", 8, 1e300))))])),
        case(DATASET, "npz", Fails, "`world_mat_0` with a focal length of 1e300",
            dtu(|| npz_world(npy("(4, 4)", &huge_focal_world())))),
        case(DATASET, "blender", Fails, "an empty split (`frames: []`)",
            blender("transforms_train.json", || Ok(blender_frames(0.69, &[])))),
        case(DATASET, "blender", Fails, "`camera_angle_x` 1e-300 (a focal length of 1e302)",
            blender("transforms_train.json", || Ok(blender_frames(1e-300, &["./train/r_0"])))),
        case(DATASET, "blender", Fails, "`camera_angle_x` π − 1e-15 (directions up to 1e15)",
            blender("transforms_train.json", || Ok(blender_frames(std::f64::consts::PI - 1e-15, &["./train/r_0"])))),
    ];
    // Every PLY case is read as a mesh and as a point cloud.
    list.into_iter()
        .flat_map(|c| {
            let twin = (c.reader == "ply").then(|| Case {
                reader: "cloud",
                ..c.clone()
            });
            std::iter::once(c).chain(twin)
        })
        .collect()
}

// ---------------------------------------------------------------------------- fixtures

/// What a scratch-directory entry holds.
#[derive(Clone)]
enum Src {
    Bytes(Bytes),
    /// A copy of a file under `examples/data`.
    Copy(&'static str),
    Dir,
}

const BLENDER_PNG: (&str, Src) = ("train/r_0.png", Src::Copy("wuson/train/r_0.png"));
const DTU_IMAGE: (&str, Src) = ("image/000000.png", Src::Copy("wuson_dtu/image/000000.png"));
const DTU_MASK: (&str, Src) = ("mask/000.png", Src::Copy("wuson_dtu/mask/000.png"));

/// Writes `entries` into the case's directory; the reader gets `read` in it (`""`: the
/// directory itself).
fn make(read: &'static str, entries: Vec<(&'static str, Src)>) -> Option<Make> {
    Some(Rc::new(move |dir: &Path| {
        for (name, src) in &entries {
            let path = dir.join(name);
            if let Some(parent) = path.parent() {
                fs::create_dir_all(parent)?;
            }
            match src {
                Src::Bytes(bytes) => fs::write(&path, bytes()?)?,
                Src::Copy(from) => {
                    fs::copy(Path::new(DATA).join(from), &path)?;
                }
                Src::Dir => fs::create_dir(&path)?,
            }
        }
        Ok(if read.is_empty() {
            dir.to_path_buf()
        } else {
            dir.join(read)
        })
    }))
}

fn bytes(f: impl Fn() -> Res<Vec<u8>> + 'static) -> Src {
    Src::Bytes(Rc::new(f))
}

/// A directory `name` where a file is expected.
fn directory(name: &'static str) -> Option<Make> {
    make(name, vec![(name, Src::Dir)])
}

/// `depth` nested JSON lists.
fn nested(depth: usize) -> Vec<u8> {
    ["[".repeat(depth), "]".repeat(depth)].concat().into()
}

/// One file `name`.
fn file(name: &'static str, f: impl Fn() -> Res<Vec<u8>> + 'static) -> Option<Make> {
    make(name, vec![(name, bytes(f))])
}

/// A Blender or nerfstudio folder: the JSON file `name` and the image it names.
fn blender(name: &'static str, json: impl Fn() -> Res<Vec<u8>> + 'static) -> Option<Make> {
    make("", vec![BLENDER_PNG, (name, bytes(json))])
}

/// An IDR/DTU folder: `cameras.npz`, one image and its mask.
fn dtu(npz: impl Fn() -> Res<Vec<u8>> + 'static) -> Option<Make> {
    make("", vec![DTU_IMAGE, DTU_MASK, ("cameras.npz", bytes(npz))])
}

/// A unit cube, 8 vertices and 12 triangles.
fn base(format: MeshFormat) -> Res<Vec<u8>> {
    let vertices = (0..8u32)
        .map(|i| [i & 1, (i >> 1) & 1, (i >> 2) & 1].map(f64::from))
        .collect();
    let faces = vec![
        [0, 2, 3],
        [0, 3, 1],
        [4, 5, 7],
        [4, 7, 6],
        [0, 1, 5],
        [0, 5, 4],
        [2, 6, 7],
        [2, 7, 3],
        [0, 4, 6],
        [0, 6, 2],
        [1, 3, 7],
        [1, 7, 5],
    ];
    Ok(Mesh::new(vertices, faces)?.to_bytes(format)?)
}

/// `b` with the first `from` replaced by `to`.
fn edit(b: &[u8], from: &str, to: &[u8]) -> Res<Vec<u8>> {
    let at = b
        .windows(from.len())
        .position(|w| w == from.as_bytes())
        .ok_or_else(|| format!("{from:?} is not in the fixture"))?;
    Ok([&b[..at], to, &b[at + from.len()..]].concat())
}

/// `b` without its last `n` bytes.
fn cut(mut b: Vec<u8>, n: usize) -> Vec<u8> {
    b.truncate(b.len().saturating_sub(n));
    b
}

/// Text without its last line.
fn drop_last_line(b: &[u8]) -> Vec<u8> {
    let body = b.strip_suffix(b"\n").unwrap_or(b);
    let at = body.iter().rposition(|&c| c == b'\n').map_or(0, |i| i + 1);
    body[..at].to_vec()
}

/// Text whose last line loses its last field.
fn drop_last_field(b: &[u8]) -> Vec<u8> {
    let body = b.strip_suffix(b"\n").unwrap_or(b);
    let at = body.iter().rposition(|&c| c == b' ').unwrap_or(0);
    [&body[..at], b"\n"].concat()
}

/// A binary STL with its facet count replaced.
fn with_count(mut b: Vec<u8>, count: u32) -> Vec<u8> {
    b[80..84].copy_from_slice(&count.to_le_bytes());
    b
}

/// A binary STL whose first facet's first corner has x = NaN (bytes 96..100).
fn nan_corner(mut b: Vec<u8>) -> Vec<u8> {
    b[96..100].copy_from_slice(&f32::NAN.to_le_bytes());
    b
}

fn utf16le(b: &[u8]) -> Vec<u8> {
    let text = String::from_utf8_lossy(b);
    let units = text.encode_utf16().flat_map(u16::to_le_bytes);
    [0xFF, 0xFE].into_iter().chain(units).collect()
}

/// A binary PLY: the corners of a regular `n`-gon, then `faces` faces listing them all
/// behind a `uint` count of `count` (`n`, or a lie).
fn ply_ngon(n: u32, faces: usize, count: u32) -> Vec<u8> {
    let mut b = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\n\
         property float y\nproperty float z\nelement face {faces}\n\
         property list uint int vertex_indices\nend_header\n"
    )
    .into_bytes();
    for i in 0..n {
        let a = i as f32 * std::f32::consts::TAU / n as f32;
        b.extend([a.cos(), a.sin(), 0.0].iter().flat_map(|c| c.to_le_bytes()));
    }
    for _ in 0..faces {
        b.extend(count.to_le_bytes());
        b.extend((0..n).flat_map(u32::to_le_bytes));
    }
    b
}

/// The number of corner references of the amplifying polygons.
const REFS: usize = 100_000;

/// Ten corners (z = 0) alternating between radius 1 and `inner`: a 5-pointed star
/// (concave) for `inner` = 0.4, a convex decagon for 1.
fn polygon(inner: f64) -> Vec<[f64; 2]> {
    (0..10)
        .map(|k| {
            let (r, a) = (
                if k % 2 == 0 { 1.0 } else { inner },
                f64::from(k) * 0.2 * std::f64::consts::PI,
            );
            [r * a.cos(), r * a.sin()]
        })
        .collect()
}

/// `REFS` 0-based indices cycling through 10 corners, offset by `first`.
fn cycle(first: usize) -> String {
    let refs: Vec<String> = (0..REFS).map(|i| (i % 10 + first).to_string()).collect();
    refs.join(" ")
}

fn corner_lines(prefix: &str, corners: impl Iterator<Item = [f64; 2]>) -> String {
    corners
        .map(|[x, y]| format!("{prefix}{x} {y} 0\n"))
        .collect()
}

fn star_obj(inner: f64) -> Vec<u8> {
    let v = corner_lines("v ", polygon(inner).into_iter());
    format!("{v}f {}\n", cycle(1)).into_bytes()
}

fn star_off() -> Vec<u8> {
    let v = corner_lines("", polygon(0.4).into_iter());
    format!("OFF\n10 1 0\n{v}{REFS} {}\n", cycle(0)).into_bytes()
}

fn star_stl() -> Vec<u8> {
    let v = corner_lines("vertex ", polygon(0.4).into_iter().cycle().take(REFS));
    format!("solid star\nfacet normal 0 0 1\nouter loop\n{v}endloop\nendfacet\nendsolid star\n")
        .into_bytes()
}

/// A camera 4 units up the z axis looking down it (OpenGL axes).
const POSE: &str = "[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]";

/// A Blender `transforms_train.json`: one frame.
fn blender_json() -> Vec<u8> {
    let frame = format!(r#"{{"file_path": "./train/r_0", "transform_matrix": {POSE}}}"#);
    format!(r#"{{"camera_angle_x": 0.69, "frames": [{frame}]}}"#).into_bytes()
}

/// A Blender `transforms_train.json` with `camera_angle_x` and one frame per file path.
fn blender_frames(angle: f64, paths: &[&str]) -> Vec<u8> {
    let frames: Vec<String> = paths
        .iter()
        .map(|p| format!(r#"{{"file_path": "{p}", "transform_matrix": {POSE}}}"#))
        .collect();
    format!(
        r#"{{"camera_angle_x": {angle:e}, "frames": [{}]}}"#,
        frames.join(", ")
    )
    .into_bytes()
}

/// A Blender folder whose one frame is the PNG `image` writes.
fn image_folder(image: impl Fn() -> Res<Vec<u8>> + 'static) -> Option<Make> {
    make(
        "",
        vec![
            ("train/r_0.png", bytes(image)),
            ("transforms_train.json", bytes(|| Ok(blender_json()))),
        ],
    )
}

/// A `w × h` PNG of mid-grey pixels of `color` (8- or 16-bit, grey or RGB(A)).
fn png(w: u32, h: u32, color: ExtendedColorType) -> Res<Vec<u8>> {
    let pixels = vec![0x80u8; (w * h) as usize * color.bits_per_pixel() as usize / 8];
    let mut out = Vec::new();
    PngEncoder::new(&mut out).write_image(&pixels, w, h, color)?;
    Ok(out)
}

/// A `w × h` mid-grey RGB JPEG.
fn jpeg(w: u32, h: u32) -> Res<Vec<u8>> {
    let pixels = vec![0x80u8; (3 * w * h) as usize];
    let mut out = Vec::new();
    JpegEncoder::new(&mut out).write_image(&pixels, w, h, ExtendedColorType::Rgb8)?;
    Ok(out)
}

/// A nerfstudio `transforms.json` of two `size × size` frames naming `file`, focal length
/// `f`.
fn nerfstudio_frame(file: &str, size: u32, f: f64) -> Vec<u8> {
    let c = f64::from(size) / 2.0;
    let frame = format!(r#"{{"file_path": "{file}", "transform_matrix": {POSE}}}"#);
    format!(
        r#"{{"fl_x": {f:e}, "fl_y": {f:e}, "cx": {c}, "cy": {c}, "w": {size}, "h": {size}, "frames": [{frame}, {frame}]}}"#
    )
    .into_bytes()
}

/// [`WORLD`] with the focal length 1e300 instead of 100.
fn huge_focal_world() -> [f64; 16] {
    let mut w = WORLD;
    (w[0], w[5]) = (1e300, 1e300);
    w
}

/// A PNG of a few dozen bytes whose header states `w × h` RGBA pixels: the signature, an
/// IHDR chunk, an IDAT of an empty zlib stream and IEND, each with its CRC.
fn png_header_only(w: u32, h: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let body = [kind, data].concat();
        let mut crc = flate2::Crc::new();
        crc.update(&body);
        out.extend_from_slice(&body);
        out.extend_from_slice(&crc.sum().to_be_bytes());
    };
    chunk(
        b"IHDR",
        &[&w.to_be_bytes()[..], &h.to_be_bytes(), &[8, 6, 0, 0, 0]].concat(),
    );
    chunk(b"IDAT", &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01]);
    chunk(b"IEND", &[]);
    out
}

/// A nerfstudio `transforms.json` stating the image size `w = h = size`; two frames.
fn nerfstudio(size: u64) -> Vec<u8> {
    let frame = format!(r#"{{"file_path": "train/r_0.png", "transform_matrix": {POSE}}}"#);
    let camera =
        format!(r#""fl_x": 100, "fl_y": 100, "cx": 50, "cy": 50, "w": {size}, "h": {size}"#);
    format!(r#"{{{camera}, "frames": [{frame}, {frame}]}}"#).into_bytes()
}

/// `K·[R|t]` of a 100×100 camera (f = 100, centre (50, 50)) at (0, 0, −3) looking along +z.
const WORLD: [f64; 16] = [
    100., 0., 50., 150., 0., 100., 50., 150., 0., 0., 1., 3., 0., 0., 0., 1.,
];

fn nan_world() -> [f64; 16] {
    let mut w = WORLD;
    w[0] = f64::NAN;
    w
}

/// A `.npy` (version 1.0) of little-endian f64 `values` whose header states `shape`.
fn npy(shape: &str, values: &[f64]) -> Vec<u8> {
    let mut h = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + h.len() + 1) % 64 != 0 {
        h.push(' ');
    }
    h.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend((h.len() as u16).to_le_bytes());
    b.extend(h.as_bytes());
    b.extend(values.iter().flat_map(|v| v.to_le_bytes()));
    b
}

/// An npz (stored, as `np.savez` writes) holding `world_mat_0.npy`.
fn npz_world(world: Vec<u8>) -> Res<Vec<u8>> {
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let stored =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    zip.start_file("world_mat_0.npy", stored)?;
    zip.write_all(&world)?;
    Ok(zip.finish()?.into_inner())
}

/// An npz whose deflated `world_mat_0.npy` (about 1 MiB) inflates to a 1 GiB array of
/// zeros, shape (8388608, 4, 4), with a header that states it truthfully.
fn npz_bomb() -> Res<Vec<u8>> {
    const GIB: usize = 1 << 30;
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let deflated = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    zip.start_file("world_mat_0.npy", deflated)?;
    zip.write_all(&npy(&format!("({}, 4, 4)", GIB / 128), &[]))?;
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..GIB / zeros.len() {
        zip.write_all(&zeros)?;
    }
    Ok(zip.finish()?.into_inner())
}

// ---------------------------------------------------------------------------- running

enum Outcome {
    Ok(String),
    Err(String),
    Panic(String),
    Timeout,
}

struct Run {
    outcome: Outcome,
    secs: f64,
    rss_mib: Option<f64>,
}

/// Reads `path` with `reader` in a child process, killed (with `/usr/bin/time`, its whole
/// process group) after [`LIMIT`].
fn measure(exe: &Path, reader: &str, path: &Path, dir: &Path, time_v: bool) -> Res<Run> {
    let (out_path, err_path) = (dir.join("child.stdout"), dir.join("child.stderr"));
    let mut cmd = if time_v {
        let mut c = Command::new("/usr/bin/time");
        c.arg("-v").arg(exe);
        c
    } else {
        Command::new(exe)
    };
    cmd.arg("--read")
        .arg(reader)
        .arg(path)
        .stdin(Stdio::null())
        .stdout(fs::File::create(&out_path)?)
        .stderr(fs::File::create(&err_path)?)
        .env_remove("RUST_BACKTRACE")
        .process_group(0);
    let start = Instant::now();
    let mut child = cmd.spawn()?;
    let status = loop {
        if let Some(status) = child.try_wait()? {
            break Some(status);
        }
        if start.elapsed() > LIMIT {
            let group = format!("-{}", child.id());
            Command::new("kill")
                .args(["-KILL", "--", &group])
                .status()?;
            child.wait()?;
            break None;
        }
        std::thread::sleep(Duration::from_millis(2));
    };
    let secs = start.elapsed().as_secs_f64();
    let stdout = String::from_utf8_lossy(&fs::read(&out_path)?).into_owned();
    let stderr = String::from_utf8_lossy(&fs::read(&err_path)?).into_owned();
    let rss_mib = stderr.lines().find_map(|l| {
        let kb = l
            .trim()
            .strip_prefix("Maximum resident set size (kbytes):")?;
        Some(kb.trim().parse::<f64>().ok()? / 1024.0)
    });
    let line = stdout.lines().next().unwrap_or("");
    let outcome = match (
        status,
        line.strip_prefix("ok: "),
        line.strip_prefix("err: "),
    ) {
        (None, _, _) => Outcome::Timeout,
        (Some(s), Some(summary), _) if s.success() => Outcome::Ok(summary.into()),
        (Some(s), _, Some(error)) if s.success() => Outcome::Err(error.into()),
        // The child's own stderr (time -v's report is indented), or its exit status.
        (Some(s), _, _) => {
            let own: Vec<&str> = stderr.lines().filter(|l| !l.starts_with('\t')).collect();
            Outcome::Panic(if own.is_empty() {
                s.to_string()
            } else {
                own.join(" ")
            })
        }
    };
    Ok(Run {
        outcome,
        secs,
        rss_mib,
    })
}

/// A table cell: one line, at most `max` characters, `|` escaped.
fn cell(s: &str, max: usize) -> String {
    let s = s.replace('\n', " ");
    let mut t: String = s.chars().take(max).collect();
    if s.chars().count() > max {
        t.push('…');
    }
    t.replace('|', "\\|")
}

/// Stdout of a command that succeeded, trimmed.
fn sh(program: &str, args: &[&str]) -> Option<String> {
    let out = Command::new(program).args(args).output().ok()?;
    let text = String::from_utf8_lossy(&out.stdout).trim().to_string();
    out.status.success().then_some(text)
}

/// The parent: runs every case, writes the table to `out` and stdout.
fn report(out: &Path, args: &[String]) -> Res<()> {
    let scratch = std::env::temp_dir().join(format!("nf-hostile-{}", std::process::id()));
    let _ = fs::remove_dir_all(&scratch);
    let rows = run_cases(&scratch);
    let _ = fs::remove_dir_all(&scratch);
    let (rows, failures) = rows?;

    let profile = if cfg!(debug_assertions) {
        ""
    } else {
        " --release"
    };
    let command = format!(
        "cargo run{profile} --example hostile_inputs{}{}",
        if args.is_empty() { "" } else { " --" },
        args.iter().map(|a| format!(" {a}")).collect::<String>()
    );
    let date = sh("date", &["-u", "+%Y-%m-%d %H:%M UTC"]).unwrap_or_else(|| "unknown".into());
    let arch = sh("uname", &["-m"]).unwrap_or_else(|| "unknown".into());
    let cpu = fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            let line = s.lines().find(|l| l.starts_with("model name"))?;
            Some(line.split_once(':')?.1.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let git = |args: &[&str]| sh("git", &[&["-C", env!("CARGO_MANIFEST_DIR")], args].concat());
    let commit = match git(&["rev-parse", "--short", "HEAD"]) {
        Some(c) if git(&["status", "--porcelain"]).is_some_and(|s| !s.is_empty()) => {
            format!("{c}-dirty")
        }
        Some(c) => c,
        None => "unknown".into(),
    };
    let memory = if Path::new("/usr/bin/time").exists() {
        "peak RSS is the maximum resident set size `/usr/bin/time -v` reports"
    } else {
        "no `/usr/bin/time` here, so no peak RSS"
    };
    let mut md = format!(
        "# Hostile inputs\n\n\
         `{command}` — {date}, {arch} ({cpu}), commit `{commit}`.\n\n\
         Each case writes a file (or dataset folder) and reads it in a child process \
         (`hostile_inputs --read READER PATH`, killed after {} s); time is the child's wall \
         time, process start included; {memory}. Controls are valid files that must load; \
         hostile cases must fail with an error, except the rows marked legitimate. Paths in \
         the scratch directory read `$TMP`. See `examples/hostile_inputs.rs` for the exact \
         bytes of each case.\n\n\
         | class | reader | input | outcome | time (s) | peak RSS (MiB) |\n\
         |---|---|---|---|---|---|\n",
        LIMIT.as_secs()
    );
    for row in &rows {
        md.push_str(&format!("| {} |\n", row.join(" | ")));
    }
    md.push_str(&format!("\n{} cases; ", rows.len()));
    if failures.is_empty() {
        md.push_str("every outcome as expected.\n");
    } else {
        md.push_str(&format!("{} unexpected:\n\n", failures.len()));
        for f in &failures {
            md.push_str(&format!("- {f}\n"));
        }
    }
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        fs::create_dir_all(dir)?;
    }
    fs::write(out, &md)?;
    print!("{md}");
    if !failures.is_empty() {
        eprintln!(
            "{} unexpected outcomes (see {})",
            failures.len(),
            out.display()
        );
        std::process::exit(1);
    }
    Ok(())
}

/// The table's rows and the failures, one line each.
type Rows = (Vec<[String; 6]>, Vec<String>);

fn run_cases(scratch: &Path) -> Res<Rows> {
    let exe = std::env::current_exe()?;
    let time_v = Path::new("/usr/bin/time").exists();
    let tmp = scratch.display().to_string();
    let (mut rows, mut failures) = (Vec::new(), Vec::new());
    for (i, case) in cases().iter().enumerate() {
        let row = |outcome: String, secs: String, rss: String| {
            let (class, reader) = (case.class.to_string(), case.reader.to_string());
            [class, reader, cell(case.input, 200), outcome, secs, rss]
        };
        let Some(make) = &case.make else {
            rows.push(row("n/a".into(), String::new(), String::new()));
            continue;
        };
        let dir = scratch.join(format!("{i:02}"));
        fs::create_dir_all(&dir)?;
        let path = make(&dir)?;
        let run = measure(&exe, case.reader, &path, &dir, time_v)?;
        let (outcome, problem) = match &run.outcome {
            Outcome::Ok(s) => (
                format!("Ok: {s}"),
                (case.expect == Expect::Fails).then_some("a hostile case loaded"),
            ),
            Outcome::Err(e) => (
                format!("Err: {}", e.replace(&tmp, "$TMP")),
                (case.expect == Expect::Loads).then_some("a legitimate file failed"),
            ),
            Outcome::Panic(p) => (
                format!("PANIC: {}", p.replace(&tmp, "$TMP")),
                Some("panic or abort"),
            ),
            Outcome::Timeout => ("TIMEOUT".into(), Some("ran past the time limit")),
        };
        let too_big = run.rss_mib.is_some_and(|m| m > MAX_RSS_MIB);
        let problem = problem.or(too_big.then_some("peak RSS over the limit"));
        let outcome = cell(&outcome, OUTCOME_CHARS);
        let rss = run.rss_mib.map_or("n/a".into(), |m| format!("{m:.1}"));
        eprintln!(
            "{i:>2} {:<16} {:<8} {:>7.3} s {rss:>6} MiB  {outcome}",
            case.class, case.reader, run.secs
        );
        if let Some(p) = problem {
            failures.push(format!(
                "{} / {} ({}): {p}: {outcome}",
                case.class, case.reader, case.input
            ));
        }
        rows.push(row(outcome, format!("{:.3}", run.secs), rss));
    }
    Ok((rows, failures))
}
