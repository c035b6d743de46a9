//! Fuzzes the image files of a dataset: `data::load` on a Blender directory whose
//! `transforms_train.json` names one frame, `train/r_0.png`, which holds the input (a
//! PNG, or anything else: its header is read first, checked against the load's budget,
//! and only then decoded). Any bytes must give `Ok` or `Err`, bounded in time and memory.
#![no_main]

use libfuzzer_sys::fuzz_target;
use neural_fields::data::{load, LoadConfig};
use std::path::PathBuf;
use std::sync::OnceLock;

const JSON: &[u8] = br#"{"camera_angle_x": 0.69, "frames": [{"file_path": "./train/r_0", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}]}"#;

fn dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("nf-fuzz-image-{}", std::process::id()));
        std::fs::create_dir_all(d.join("train")).expect("temp dir");
        std::fs::write(d.join("transforms_train.json"), JSON).expect("json");
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let d = dir();
    std::fs::write(d.join("train/r_0.png"), data).expect("write");
    if let Ok(ds) = load(d, &LoadConfig::default()) {
        assert_eq!(ds.views().len(), 1);
    }
});
