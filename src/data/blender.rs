//! The Blender synthetic layout (NeRF): `transforms_{train,val,test}.json`, one file per
//! split, with `camera_angle_x` and per-frame `file_path` / `transform_matrix`
//! (camera-to-world, OpenGL axes). Each split file is read by the nerfstudio reader,
//! whose format extends this one (exact `fl_x, fl_y, cx, cy, w, h`, when present, are
//! preferred over `camera_angle_x`).

use super::layout::{Bounds, FrameSpec, Split};
use super::nerfstudio::read_transforms;
use crate::error::Result;
use std::path::Path;

/// The frames (and stated bounds) of a Blender dataset's split:
/// `dir/transforms_{split}.json`, or the three split files in the order train, val, test
/// for [`Split::All`].
pub(crate) fn frames(dir: &Path, split: Split) -> Result<(Vec<FrameSpec>, Option<Bounds>)> {
    let names = match split {
        Split::All => vec!["train", "val", "test"],
        one => vec![one.name()],
    };
    let mut all = Vec::new();
    let mut bounds = None;
    for name in names {
        let path = dir.join(format!("transforms_{name}.json"));
        let (frames, b) = read_transforms(&path, |_| true)?;
        all.extend(frames);
        bounds = bounds.or(b);
    }
    Ok((all, bounds))
}
