//! Fuzzes the Blender and nerfstudio layouts' JSON: `data::load` on a directory whose
//! `transforms_train.json` (first input byte even) or `transforms.json` (odd) holds the
//! rest of the input, beside one real 100×100 image at `train/r_0.png` and `img.png`.
//! Any bytes must give `Ok` or `Err`, bounded in time and memory.
#![no_main]

use libfuzzer_sys::fuzz_target;
use neural_fields::data::{load, LoadConfig};
use std::path::PathBuf;
use std::sync::OnceLock;

const IMAGE: &[u8] = include_bytes!("../../examples/data/wuson/train/r_0.png");

fn dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("nf-fuzz-json-{}", std::process::id()));
        std::fs::create_dir_all(d.join("train")).expect("temp dir");
        std::fs::write(d.join("train/r_0.png"), IMAGE).expect("image");
        std::fs::write(d.join("img.png"), IMAGE).expect("image");
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let Some((&which, json)) = data.split_first() else {
        return;
    };
    let d = dir();
    let (name, other) = if which % 2 == 0 {
        ("transforms_train.json", "transforms.json")
    } else {
        ("transforms.json", "transforms_train.json")
    };
    let _ = std::fs::remove_file(d.join(other));
    std::fs::write(d.join(name), json).expect("write");
    if let Ok(ds) = load(d, &LoadConfig::default()) {
        assert!(!ds.views().is_empty());
    }
});
