//! Fuzzes the IDR/DTU layout's `cameras.npz` (zip container, `.npy` members): `data::load`
//! on a directory whose `cameras.npz` holds the input, beside one real image and mask.
//! Any bytes must give `Ok` or `Err`, bounded in time and memory.
#![no_main]

use libfuzzer_sys::fuzz_target;
use neural_fields::data::{load, LoadConfig, Split};
use std::path::PathBuf;
use std::sync::OnceLock;

const IMAGE: &[u8] = include_bytes!("../../examples/data/wuson_dtu/image/000000.png");
const MASK: &[u8] = include_bytes!("../../examples/data/wuson_dtu/mask/000.png");

fn dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("nf-fuzz-npz-{}", std::process::id()));
        std::fs::create_dir_all(d.join("image")).expect("temp dir");
        std::fs::create_dir_all(d.join("mask")).expect("temp dir");
        std::fs::write(d.join("image/000000.png"), IMAGE).expect("image");
        std::fs::write(d.join("mask/000.png"), MASK).expect("mask");
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let d = dir();
    std::fs::write(d.join("cameras.npz"), data).expect("write");
    let config = LoadConfig {
        split: Split::All,
        ..LoadConfig::default()
    };
    if let Ok(ds) = load(d, &config) {
        assert!(!ds.views().is_empty());
    }
});
