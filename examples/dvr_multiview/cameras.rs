//! The camera side of a `dvr_multiview` run: the perturbation of the training cameras,
//! their learnable poses and rays, the registrations and the test-time refinement, the
//! alignment of the learnt frame to the dataset's, and the run's `poses.json`.

use super::*;
use candle_core::Var;
use neural_fields::camera::{
    align_cameras, align_similarity, pose_rays, register_poses, Camera, Rays, RegistrationConfig,
};
use neural_fields::glam::{DMat3, DMat4};
use neural_fields::nn::Adam;

/// The camera-to-world poses of `data`'s views.
pub(super) fn poses_of(data: &Dataset) -> Vec<DAffine3> {
    data.views()
        .iter()
        .map(|v| v.camera().cam_to_world())
        .collect()
}

/// The cameras of `data`'s views (intrinsics, convention) at `poses`.
pub(super) fn cameras_at(data: &Dataset, poses: &[DAffine3]) -> Result<Vec<Camera>> {
    Ok(data
        .with_poses(poses)?
        .views()
        .iter()
        .map(|v| *v.camera())
        .collect())
}

/// `data` with every camera rotated by `degrees` about a random axis through its centre
/// and its centre shifted by `fraction` of its distance to the origin (seeded).
pub(super) fn perturb(data: &Dataset, degrees: f64, fraction: f64, seed: u64) -> Result<Dataset> {
    let mut rng = SplitMix64::new(seed);
    let mut unit = || {
        let v = DVec3::new(rng.normal(), rng.normal(), rng.normal());
        v / v.length().max(1e-12)
    };
    let mut moved = poses_of(data);
    for pose in &mut moved {
        let rotation = DMat3::from_axis_angle(unit(), degrees.to_radians()) * pose.matrix3;
        let centre = pose.translation + unit() * fraction * pose.translation.length();
        *pose = DAffine3::from_mat3_translation(rotation, centre);
    }
    data.with_poses(&moved)
}

/// The refined poses, and the least-squares fit of their centres onto the true ones: the
/// map from the learnt frame to the dataset's that BARF compares poses after.
pub(super) fn alignment(
    poses: &[PoseParam],
    truth: &[DAffine3],
) -> Result<(Similarity, Vec<DAffine3>)> {
    let refined = poses
        .iter()
        .map(PoseParam::to_affine)
        .collect::<Result<Vec<_>>>()?;
    let centres = |p: &[DAffine3]| p.iter().map(|p| p.translation).collect::<Vec<_>>();
    Ok((
        align_similarity(&centres(&refined), &centres(truth))?,
        refined,
    ))
}

/// At most 2 000 of `mesh`'s vertices, evenly spread over its vertex list.
pub(super) fn mesh_points(mesh: &Mesh) -> Vec<DVec3> {
    let every = mesh.vertices.len().div_ceil(2_000).max(1);
    mesh.vertices
        .iter()
        .step_by(every)
        .map(|&v| DVec3::from_array(v))
        .collect()
}

/// The map from the learnt frame to the dataset's under which the refined and the true
/// training cameras see the extracted surface alike ([`align_cameras`]), or `centres`
/// (said on stderr) when the mesh is empty or no camera sees it.
pub(super) fn view_alignment(
    train: &Dataset,
    (refined, truth): (&[DAffine3], &[DAffine3]),
    mesh: &Mesh,
    centres: Similarity,
) -> Result<Similarity> {
    if mesh.vertices.is_empty() {
        return Ok(centres);
    }
    let (from, to) = (cameras_at(train, refined)?, cameras_at(train, truth)?);
    let aligned = align_cameras(&from, &to, &mesh_points(mesh));
    Ok(aligned.unwrap_or_else(|e| {
        eprintln!("the scene is placed by the camera centres' fit: {e}");
        centres
    }))
}

/// `eval` with its cameras moved into the learnt frame by the inverse of `frame`.
pub(super) fn in_learnt_frame(eval: &Dataset, frame: &Similarity) -> Result<Dataset> {
    let (scale, rotation) = (1.0 / frame.scale, frame.rotation.inverse());
    let translation = -(rotation * frame.translation) * scale;
    let inverse = Similarity {
        scale,
        rotation,
        translation,
    };
    eval.with_poses(
        &poses_of(eval)
            .iter()
            .map(|p| inverse.apply(*p))
            .collect::<Vec<_>>(),
    )
}

/// `mesh` (in the learnt frame) moved into the dataset's frame by `frame`.
pub(super) fn mesh_to_dataset_frame(mut mesh: Mesh, frame: &Similarity) -> Mesh {
    for v in &mut mesh.vertices {
        *v = frame.apply(DVec3::from_array(*v)).to_array();
    }
    for n in mesh.normals.iter_mut().flatten() {
        *n = (frame.rotation * DVec3::from_array(*n)).to_array();
    }
    mesh
}

/// The rays of `batch` (drawn from `data`) cast from the learnable `poses`, through the
/// centres of the batch's pixels.
pub(super) fn batch_rays(poses: &[PoseParam], data: &Dataset, batch: &RayBatch) -> Result<Rays> {
    let cameras: Vec<Camera> = data.views().iter().map(|v| *v.camera()).collect();
    let pixels = (batch.pixels.to_dtype(batch.colors.dtype())? + 0.5)?;
    pose_rays(poses, &cameras, &batch.views, &pixels)
}

/// The crate's [`Adam`] on the pose variables `vars` at `lr` (0 freezes them, which
/// `nn::adam` refuses; no weight decay).
pub(super) fn pose_adam(vars: Vec<Var>, lr: f64) -> Result<Adam> {
    let params = candle_nn::ParamsAdamW {
        lr,
        weight_decay: 0.0,
        ..Default::default()
    };
    Ok(Adam::new(vars, params)?)
}

/// BARF's test-time refinement: each camera of `eval` (already in the learnt frame) is
/// refined against its own image with the network fixed, `steps` Adam steps at `lr` on
/// 256 rays, with the training loss at the end of its schedule.
pub(super) fn refine_eval_poses(
    model: &SurfaceModel,
    eval: &Dataset,
    steps: usize,
    lr: f64,
    seed: u64,
) -> Result<Dataset> {
    let (device, dtype) = (Device::Cpu, DType::F32);
    let mut refined = Vec::with_capacity(eval.views().len());
    for (v, view) in eval.views().iter().enumerate() {
        let one = Dataset::new(vec![view.clone()], eval.background(), eval.bounds())?;
        let pose = PoseParam::from_affine(&view.camera().cam_to_world(), &device, dtype)?;
        let mut opt = pose_adam(vec![pose.rotation.clone(), pose.translation.clone()], lr)?;
        let mut sampler = RaySampler::new(&one, seed ^ v as u64, &device, dtype)?;
        for step in 0..steps {
            let batch = sampler.patches(64, 2)?;
            let rays = batch_rays(std::slice::from_ref(&pose), &one, &batch)?;
            let mask = batch_mask(&batch, &one)?;
            let loss = model.loss(&rays, &batch.colors, mask, 1.0, seed ^ step as u64)?;
            opt.step(&loss.total.backward()?)?;
        }
        refined.push(pose.to_affine()?);
    }
    eval.with_poses(&refined)
}

/// `rounds` registrations of `data`'s cameras, from `poses`, to the scene the network
/// renders ([`register_poses`]); `report(round, poses)` sees the poses after each.
pub(super) fn register(
    model: &SurfaceModel,
    data: &Dataset,
    poses: &[DAffine3],
    rounds: usize,
    report: &mut dyn FnMut(usize, &[DAffine3]),
) -> Result<Vec<DAffine3>> {
    let mut images = Vec::with_capacity(data.views().len());
    for v in data.views() {
        let rgb = v.rgb([1.0; 3], &Device::Cpu, DType::F32)?;
        images.push(Tensor::cat(&[rgb, mask_of(v)?.unsqueeze(2)?], 2)?);
    }
    let mut cameras = cameras_at(data, poses)?;
    let render = |rays: &Rays| -> Result<(Tensor, Tensor, Tensor)> {
        let seen = model.shade(rays)?;
        Ok((seen.rgb, seen.depth, seen.coverage))
    };
    for round in 0..rounds {
        cameras = register_poses(&cameras, &images, render, &RegistrationConfig::default())?;
        report(
            round,
            &cameras.iter().map(Camera::cam_to_world).collect::<Vec<_>>(),
        );
    }
    Ok(cameras.iter().map(Camera::cam_to_world).collect())
}

/// Sets each pose of `poses` to the matching rigid transform of `to`.
pub(super) fn set_poses(poses: &[PoseParam], to: &[DAffine3]) -> Result<()> {
    for (p, pose) in poses.iter().zip(to) {
        let fresh = PoseParam::from_affine(pose, p.translation.device(), p.translation.dtype())?;
        p.rotation.set(fresh.rotation.as_tensor())?;
        p.translation.set(fresh.translation.as_tensor())?;
    }
    Ok(())
}

/// One registration of the training cameras (`poses`, learnt on `train`) to the scene at
/// `step`, printing the pose errors against `truth` (unaligned). The cameras stay where
/// the registration puts them, in the scene's frame.
pub(super) fn register_training(
    model: &SurfaceModel,
    args: &Args,
    train: &Dataset,
    (poses, truth): (&[PoseParam], &[DAffine3]),
    step: usize,
) -> Result<()> {
    let current = poses
        .iter()
        .map(PoseParam::to_affine)
        .collect::<Result<Vec<_>>>()?;
    let refined = register(model, train, &current, args.lm_iterations, &mut |it, p| {
        if let Ok((r, t)) = pose_error(p, truth) {
            let t = 100.0 * t;
            println!("step {step}, registration {it}: poses {r:.3}° / {t:.3} % (unaligned)");
        }
    })?;
    set_poses(poses, &refined)
}

/// The learnt-frame poses of `path` (a run's `poses.json`), one per view of `data`, by
/// name.
///
/// # Errors
/// [`Error::Format`] naming `path` when it is not such a file or lacks a view of `data`.
pub(super) fn read_poses(path: &Path, data: &Dataset) -> Result<Vec<DAffine3>> {
    let expected = "dvr_multiview's poses.json (views: name, cam_to_world 4 × 4)";
    let bad = |field: &str| format_error(path, field, expected);
    let text = std::fs::read_to_string(path).map_err(|_| bad("(file)"))?;
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|_| bad("(JSON)"))?;
    let views = json["views"].as_array().ok_or_else(|| bad("views"))?;
    let read = |v: &View| -> Result<DAffine3> {
        let name = format!("views[name = {}]", v.name());
        let entry = views
            .iter()
            .find(|e| e["name"] == v.name())
            .ok_or_else(|| bad(&name))?;
        let m: Vec<Vec<f64>> = serde_json::from_value(entry["cam_to_world"].clone())
            .map_err(|_| bad("cam_to_world"))?;
        if m.len() != 4 || m.iter().any(|r| r.len() != 4) {
            return Err(bad("cam_to_world"));
        }
        let col = |c: usize| DVec3::new(m[0][c], m[1][c], m[2][c]);
        Ok(DAffine3::from_cols(col(0), col(1), col(2), col(3)))
    };
    data.views().iter().map(read).collect()
}

/// Writes the refined training cameras to `path`: each view's name and camera-to-world
/// matrix (4 × 4, rows) in the learnt frame and moved by `frame` into the dataset's.
pub(super) fn write_poses(
    path: &Path,
    data: &Dataset,
    refined: &[DAffine3],
    frame: &Similarity,
) -> Result<()> {
    let rows = |p: &DAffine3| {
        (0..4)
            .map(|r| DMat4::from(*p).row(r).to_array())
            .collect::<Vec<_>>()
    };
    let views: Vec<serde_json::Value> = data.views().iter().zip(refined).map(|(v, p)| {
        serde_json::json!({"name": v.name(), "cam_to_world": rows(p), "cam_to_world_aligned": rows(&frame.apply(*p))})
    }).collect();
    write_json(path, &serde_json::json!({ "views": views }))
}
