//! Post-processing of run directories: loads what `rigd_process` needs from
//! a run (frames, their directions) and, for simulated runs, measures the
//! result against the scene's ground truth.

use std::path::{Path, PathBuf};

use rigd_process::image_io::Image;
use rigd_process::photometric_stereo::{PsDataset, PsResult};
use rigd_sim::scene::{Scene, Shot};
use serde::Serialize;

use crate::connect::sim::camera_geometry;
use crate::store::{decode_png, read_journal, read_meta, FrameEntry, RunMeta, JOURNAL_FILE};

#[derive(Debug, thiserror::Error)]
pub enum ProcessError {
    #[error("{0}")]
    Store(#[from] crate::store::StoreError),
    #[error("{path}: {message}")]
    Frame { path: PathBuf, message: String },
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Scene(#[from] rigd_sim::scene::SceneError),
}

/// A run's metadata and every frame it wrote, in capture order.
pub struct RunFrames {
    pub root: PathBuf,
    pub meta: RunMeta,
    pub entries: Vec<FrameEntry>,
}

impl RunFrames {
    pub fn open(root: &Path) -> Result<RunFrames, ProcessError> {
        let meta = read_meta(root)?;
        let (mut entries, _) = read_journal(&root.join(JOURNAL_FILE))?;
        entries.sort_by_key(|e| e.index);
        Ok(RunFrames {
            root: root.to_path_buf(),
            meta,
            entries,
        })
    }

    /// One frame as linear values in [0, 1].
    pub fn image(&self, entry: &FrameEntry) -> Result<Image, ProcessError> {
        let path = self.root.join(&entry.file);
        let bytes = std::fs::read(&path).map_err(|e| ProcessError::Frame {
            path: path.clone(),
            message: e.to_string(),
        })?;
        let (w, h, pixels) = decode_png(&bytes).map_err(|message| ProcessError::Frame {
            path: path.clone(),
            message,
        })?;
        let full = ((1u32 << entry.bit_depth.clamp(1, 16)) - 1) as f32;
        let mut img = Image::new(w as usize, h as usize, 1);
        for (d, p) in img.data.iter_mut().zip(pixels) {
            *d = p as f32 / full;
        }
        Ok(img)
    }
}

/// A photometric-stereo dataset from a run whose camera looks down on the
/// sample (VirTex): every frame of one camera, with the light each was
/// taken under. The camera's image axes are the sample's x and y (the
/// simulated and real VirTex cameras sit at the pole), so lights in the
/// sample frame are lights in the image frame photometric stereo expects.
pub fn ps_dataset_from_run(run: &RunFrames) -> Result<PsDataset, ProcessError> {
    let first = run.entries.first().ok_or_else(|| {
        ProcessError::Invalid(format!("{}: the run has no frames", run.root.display()))
    })?;
    let camera = first.camera.clone();
    let entries: Vec<&FrameEntry> = run.entries.iter().filter(|e| e.camera == camera).collect();
    for e in &entries {
        if e.achieved_view.theta_deg > 1.0 {
            return Err(ProcessError::Invalid(format!(
                "{}: frame {} of camera {camera} looks from θ = {:.1}°: photometric stereo here needs a camera at the pole",
                run.root.display(),
                e.index,
                e.achieved_view.theta_deg
            )));
        }
    }
    let mut images = Vec::with_capacity(entries.len());
    for e in &entries {
        images.push(run.image(e)?);
    }
    Ok(PsDataset {
        image_names: entries.iter().map(|e| e.file.clone()).collect(),
        images,
        lights: entries
            .iter()
            .map(|e| e.achieved_light.to_vector())
            .collect(),
        intensities: None,
        mask: None,
        lights_origin: format!("{} (journal)", run.root.display()),
    })
}

/// How far recovered normals are from the scene's true ones.
#[derive(Debug, Clone, Serialize)]
pub struct NormalError {
    pub scene: String,
    /// Pixels on the sample that photometric stereo solved.
    pub pixels: usize,
    pub mean_deg: f64,
    pub median_deg: f64,
    pub p95_deg: f64,
}

/// Compares photometric-stereo normals of a simulated run with the true
/// normals of the surface point each pixel sees.
pub fn ps_error_against_truth(
    run: &RunFrames,
    result: &PsResult,
) -> Result<Option<NormalError>, ProcessError> {
    if !run.meta.simulated {
        return Ok(None);
    }
    let Some(first) = run.entries.first() else {
        return Ok(None);
    };
    let scene = Scene::load(run.meta.profile.sim.scene_name())?;
    let size = [result.width as u32, result.height as u32];
    let geometry = camera_geometry(&run.meta.profile, &first.camera, size).ok_or_else(|| {
        ProcessError::Invalid(format!(
            "the run's profile has no camera `{}`",
            first.camera
        ))
    })?;
    let shot = Shot {
        view: first.achieved_view.to_vector(),
        width: size[0],
        height: size[1],
        focal_px: Some(geometry.focal_px),
        camera_distance_m: geometry.distance_m,
        ..Shot::default()
    };
    Ok(normal_error(&scene, &shot, result))
}

/// Mean, median and 95th percentile angle between `result`'s valid normals
/// and the true normals, over pixels that see the sample.
pub fn normal_error(scene: &Scene, shot: &Shot, result: &PsResult) -> Option<NormalError> {
    let mut angles = Vec::new();
    for j in 0..result.height {
        for i in 0..result.width {
            let k = j * result.width + i;
            if !result.valid[k] {
                continue;
            }
            let Some(p) = scene.true_surface_point(shot, i, j) else {
                continue;
            };
            if !scene.on_sample(p[0], p[1]) {
                continue;
            }
            let t = scene.true_normal(p[0], p[1]);
            let n = result.normals[k];
            let c = (t[0] * n[0] as f64 + t[1] * n[1] as f64 + t[2] * n[2] as f64).clamp(-1.0, 1.0);
            angles.push(c.acos().to_degrees());
        }
    }
    if angles.is_empty() {
        return None;
    }
    angles.sort_by(f64::total_cmp);
    let n = angles.len();
    Some(NormalError {
        scene: scene.name.clone(),
        pixels: n,
        mean_deg: angles.iter().sum::<f64>() / n as f64,
        median_deg: angles[n / 2],
        p95_deg: angles[(n * 95 / 100).min(n - 1)],
    })
}
