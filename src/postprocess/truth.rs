//! Ground truth of simulated runs: how far a result is from the scene the
//! simulator rendered (photometric-stereo normals, BTF textures). Needs
//! the simulator (cargo feature `sim`).

use std::path::Path;

use rigd_core::geometry::Direction;
use rigd_process::photometric_stereo::PsResult;
use rigd_sim::scene::{Scene, Shot};
use serde::Serialize;

use rigd_process::mdf::{DisplacementImage, PinholeCamera};

use super::btf::{btf_error, HeldOutError};
use super::frames::RunFrames;
use super::mdf::DepthError;
use super::rectify::NormtextureIndex;
use super::ProcessError;
use crate::kinematics::camera::camera_geometry;
use crate::store::read_meta;

/// How far recovered normals are from the scene's true ones.
#[derive(Debug, Clone, Serialize)]
pub struct NormalError {
    /// The simulated scene the run rendered.
    pub scene: String,
    /// Pixels on the sample that photometric stereo solved.
    pub pixels: usize,
    /// Mean angle between recovered and true normal, degrees.
    pub mean_deg: f64,
    /// Median of that angle, degrees.
    pub median_deg: f64,
    /// 95th percentile of that angle, degrees.
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

/// What a perfect rig's normtexture of `scene` at (light, view) holds:
/// `Scene::true_btf` over the sample square, `size`² texels (row 0 the +y
/// edge, column 0 the −x edge), each averaged over its area (4 × 4
/// samples, as the registration's area filter averages the frame's
/// pixels; point samples would alias the relief's highlights), scaled as
/// the sensor scales radiance ([`rigd_sim::scene::WHITE_LEVEL`] of full
/// scale for a white Lambertian sample lit frontally) with a directional
/// lamp (a rig's lamp fall-off therefore counts as error).
pub fn true_texture(scene: &Scene, size: usize, light: Direction, view: Direction) -> Vec<f32> {
    use rayon::prelude::*;
    const SUB: usize = 4;
    let [hx, hy] = scene.sample_half;
    let (l, v) = (light.to_vector(), view.to_vector());
    let mut out = vec![0f32; size * size];
    out.par_chunks_mut(size.max(1))
        .enumerate()
        .for_each(|(j, row)| {
            for (i, texel) in row.iter_mut().enumerate() {
                let mut sum = 0.0;
                for sj in 0..SUB {
                    let y =
                        hy - (j as f64 + (sj as f64 + 0.5) / SUB as f64) / size as f64 * 2.0 * hy;
                    for si in 0..SUB {
                        let x = -hx
                            + (i as f64 + (si as f64 + 0.5) / SUB as f64) / size as f64 * 2.0 * hx;
                        sum += scene.true_btf(x, y, l, v, Default::default());
                    }
                }
                *texel = (rigd_sim::scene::WHITE_LEVEL * sum / (SUB * SUB) as f64) as f32;
            }
        });
    out
}

/// Compares the run's compressed BTF (`processed/btf/`) at each (light,
/// view) with the simulated run's scene ([`true_texture`]).
pub fn btf_truth_error(
    run: &Path,
    pairs: &[(Direction, Direction)],
) -> Result<Vec<HeldOutError>, ProcessError> {
    let meta = read_meta(run)?;
    if !meta.simulated {
        return Err(ProcessError::Invalid(format!(
            "{}: ground truth exists only for simulated runs",
            run.display()
        )));
    }
    let scene = Scene::load(meta.profile.sim.scene_name())?;
    let size = NormtextureIndex::read(run)?.size;
    let truths: Vec<Vec<f32>> = pairs
        .iter()
        .map(|&(l, v)| true_texture(&scene, size, l, v))
        .collect();
    btf_error(run, pairs, &truths)
}

/// The scene of a simulated laser run, for the MDF's truth; `None` for
/// hardware runs.
pub fn mdf_truth_scene(
    run: &RunFrames,
) -> Result<Option<std::sync::Arc<rigd_sim::scene::Scene>>, ProcessError> {
    if !run.meta.simulated {
        return Ok(None);
    }
    let name = run
        .meta
        .sim_scene
        .as_ref()
        .map(|s| s.name.clone())
        .unwrap_or_else(|| run.meta.profile.sim.scene_name().to_string());
    Ok(Some(rigd_sim::scene::Scene::load(&name)?))
}

/// The measured displacement against the true one, over pixels whose true
/// surface point lies in the sample's bounding box: the distance along the
/// pixel's ray from the reference plane to the first surface hit.
pub fn depth_error(
    scene: &rigd_sim::scene::Scene,
    cam: &PinholeCamera,
    d: &DisplacementImage,
    reference_m: f64,
    box_half: f64,
) -> DepthError {
    let shot = rigd_sim::scene::Shot {
        view: cam.centre,
        width: cam.width as u32,
        height: cam.height as u32,
        focal_px: Some(cam.focal_px),
        camera_distance_m: Some(
            (cam.centre[0].powi(2) + cam.centre[1].powi(2) + cam.centre[2].powi(2)).sqrt(),
        ),
        ..rigd_sim::scene::Shot::default()
    };
    let mut errors = Vec::new();
    let mut sample_pixels = 0usize;
    for j in 0..d.height {
        for i in 0..d.width {
            let Some(p) = scene.true_surface_point(&shot, i, j) else {
                continue;
            };
            if p[0].abs() > box_half || p[1].abs() > box_half {
                continue;
            }
            sample_pixels += 1;
            let measured = d.depth[j * d.width + i];
            if measured < 0.0 {
                continue;
            }
            let (o, dir) = cam.ray(i, j);
            if dir[2] >= 0.0 {
                continue;
            }
            let t_ref = (o[2] - reference_m) / -dir[2];
            let t_hit = (0..3).map(|k| (p[k] - o[k]) * dir[k]).sum::<f64>();
            let truth = t_hit - t_ref;
            errors.push((f64::from(measured) - truth).abs() * 1e3);
        }
    }
    errors.sort_by(f64::total_cmp);
    let pick = |q: f64| {
        errors
            .get(((errors.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    DepthError {
        pixels: errors.len(),
        coverage: errors.len() as f64 / sample_pixels.max(1) as f64,
        mean_mm: if errors.is_empty() {
            f64::NAN
        } else {
            errors.iter().sum::<f64>() / errors.len() as f64
        },
        median_mm: pick(0.5),
        p95_mm: pick(0.95),
    }
}
