//! Ground truth of simulated runs: how far a result is from the scene the
//! simulator rendered (photometric-stereo normals, BTF textures, the MDF's
//! depths). Needs the simulator (cargo feature `sim`); processing itself
//! never does: it reads the holder from the run's profile, and takes the
//! MDF's truth through [`crate::postprocess::mdf::DepthTruth`], which
//! [`install`] provides.

use std::path::Path;
use std::sync::Arc;

use rigd_core::geometry::Direction;
use rigd_process::photometric_stereo::PsResult;
use rigd_sim::scene::{Scene, Shot};
use serde::Serialize;

use rigd_process::mdf::{DisplacementImage, PinholeCamera};

use crate::kinematics::camera::camera_geometry;
use crate::postprocess::accuracy::{ErrorStats, PixelError, PixelErrors};
use crate::postprocess::btf::{btf_error, HeldOutError};
use crate::postprocess::frames::RunFrames;
use crate::postprocess::rectify::NormtextureIndex;
use crate::postprocess::ProcessError;
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
    /// Standard error of `mean_deg` over 16 × 16-pixel tiles
    /// ([`tile_spread`]); NaN with fewer than two tiles.
    pub spread_deg: f64,
}

/// Compares photometric-stereo normals of a simulated run with the true
/// normals of the surface point each pixel sees.
pub fn ps_error_against_truth(
    run: &RunFrames,
    result: &PsResult,
) -> Result<Option<NormalError>, ProcessError> {
    Ok(ps_pixel_errors_against_truth(run, result)?
        .and_then(|(scene, pixels)| NormalError::of(scene, &pixels.stats(|_| true))))
}

/// [`ps_error_against_truth`] pixel by pixel: the scene's name, and the
/// angle at every sample pixel photometric stereo solved.
pub fn ps_pixel_errors_against_truth(
    run: &RunFrames,
    result: &PsResult,
) -> Result<Option<(String, PixelErrors)>, ProcessError> {
    if !run.meta.simulated {
        return Ok(None);
    }
    let Some(first) = run.entries.first() else {
        return Ok(None);
    };
    let scene = scene_of(&run.meta)?;
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
    Ok(Some((
        scene.name.clone(),
        normal_errors(&scene, &shot, result),
    )))
}

impl NormalError {
    /// The summary of a scene's normal errors; None without a pixel.
    pub fn of(scene: String, stats: &ErrorStats) -> Option<NormalError> {
        (stats.pixels > 0).then_some(NormalError {
            scene,
            pixels: stats.pixels,
            mean_deg: stats.mean,
            median_deg: stats.median,
            p95_deg: stats.p95,
            spread_deg: stats.spread,
        })
    }
}

/// Mean, median and 95th percentile angle between `result`'s valid normals
/// and the true normals, over pixels that see the sample.
pub fn normal_error(scene: &Scene, shot: &Shot, result: &PsResult) -> Option<NormalError> {
    NormalError::of(
        scene.name.clone(),
        &normal_errors(scene, shot, result).stats(|_| true),
    )
}

/// The angle between `result`'s normal and the true one at every pixel
/// that sees the sample, in degrees; sample pixels photometric stereo did
/// not solve are unmeasured.
pub fn normal_errors(scene: &Scene, shot: &Shot, result: &PsResult) -> PixelErrors {
    let mut pixels = vec![PixelError::OffSample; result.width * result.height];
    for j in 0..result.height {
        for i in 0..result.width {
            let k = j * result.width + i;
            let Some(p) = scene.true_surface_point(shot, i, j) else {
                continue;
            };
            if !scene.on_sample(p[0], p[1]) {
                continue;
            }
            if !result.valid.get(k).copied().unwrap_or(false) {
                pixels[k] = PixelError::Unmeasured;
                continue;
            }
            let t = scene.true_normal(p[0], p[1]);
            let n = result.normals[k];
            let c = (t[0] * n[0] as f64 + t[1] * n[1] as f64 + t[2] * n[2] as f64).clamp(-1.0, 1.0);
            pixels[k] = PixelError::Measured(c.acos().to_degrees());
        }
    }
    PixelErrors {
        width: result.width,
        pixels,
    }
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
    true_texture_channels(scene, size, light, view, 1)
}

/// [`true_texture`] with `channels` values per texel: 1 grey, 3 linear
/// sRGB red, green and blue interleaved ([`Scene::true_btf_channel`]),
/// what a colour-corrected RGB normtexture holds.
pub fn true_texture_channels(
    scene: &Scene,
    size: usize,
    light: Direction,
    view: Direction,
    channels: usize,
) -> Vec<f32> {
    use rayon::prelude::*;
    let (l, v) = (light.to_vector(), view.to_vector());
    let channels = if channels == 3 { 3 } else { 1 };
    let mut out = vec![0f32; size * size * channels];
    out.par_chunks_mut((size * channels).max(1))
        .enumerate()
        .for_each(|(j, row)| {
            for (k, texel) in row.iter_mut().enumerate() {
                let (i, c) = (k / channels, k % channels);
                let sum: f64 = texel_points(scene, size, j, i)
                    .map(|(x, y)| {
                        if channels == 3 {
                            scene.true_btf_channel(x, y, l, v, c)
                        } else {
                            scene.true_btf(x, y, l, v, Default::default())
                        }
                    })
                    .sum();
                *texel = (rigd_sim::scene::WHITE_LEVEL * sum / TEXEL_SAMPLES as f64) as f32;
            }
        });
    out
}

/// Samples per side of a texel in the truth: 4 × 4.
const TEXEL_SUB: usize = 4;
/// Samples per texel.
const TEXEL_SAMPLES: usize = TEXEL_SUB * TEXEL_SUB;

/// The sample-plane points (metres) the truth averages for texel (row `j`,
/// column `i`) of a `size`² normtexture: a 4 × 4 grid over its area.
fn texel_points(
    scene: &Scene,
    size: usize,
    j: usize,
    i: usize,
) -> impl Iterator<Item = (f64, f64)> {
    let [hx, hy] = scene.sample_half;
    let n = TEXEL_SUB as f64;
    (0..TEXEL_SAMPLES).map(move |s| {
        let (sj, si) = ((s / TEXEL_SUB) as f64, (s % TEXEL_SUB) as f64);
        let y = hy - (j as f64 + (sj + 0.5) / n) / size as f64 * 2.0 * hy;
        let x = -hx + (i as f64 + (si + 0.5) / n) / size as f64 * 2.0 * hx;
        (x, y)
    })
}

/// A grey normtexture as a camera with a finite full scale records it.
#[derive(Debug, Clone, PartialEq)]
pub struct ExposedTexture {
    /// Each texel the mean of its samples, each sample held at the full
    /// scale: what a clipped pixel reads.
    pub texels: Vec<f32>,
    /// Texels with at least one sample at the full scale.
    pub clipped_texels: usize,
    /// Share of all samples at the full scale.
    pub clipped_share: f64,
}

/// [`true_texture`] as recorded with each of `full_scales`, in one pass:
/// the full scale in the truth's units, where a white Lambertian sample
/// lit frontally reads [`rigd_sim::scene::WHITE_LEVEL`], so 1 is the
/// sensor's full scale at the profile's exposure and `f` that of an
/// exposure `f` times shorter. Noise, vignetting and the lamp's fall-off
/// are left out: a sample clips exactly where its radiance reaches the
/// full scale.
pub fn exposed_textures(
    scene: &Scene,
    size: usize,
    light: Direction,
    view: Direction,
    full_scales: &[f64],
) -> Vec<ExposedTexture> {
    use rayon::prelude::*;
    let (l, v) = (light.to_vector(), view.to_vector());
    let scales = full_scales.len();
    // Per texel and full scale: the clipped sum and the clipped samples.
    let per_texel: Vec<Vec<(f64, usize)>> = (0..size * size)
        .into_par_iter()
        .map(|t| {
            let mut acc = vec![(0.0, 0usize); scales];
            for (x, y) in texel_points(scene, size, t / size, t % size) {
                let value =
                    rigd_sim::scene::WHITE_LEVEL * scene.true_btf(x, y, l, v, Default::default());
                for (a, &full) in acc.iter_mut().zip(full_scales) {
                    a.0 += value.min(full);
                    a.1 += usize::from(value >= full);
                }
            }
            acc
        })
        .collect();
    (0..scales)
        .map(|k| {
            let texels = per_texel
                .iter()
                .map(|acc| (acc[k].0 / TEXEL_SAMPLES as f64) as f32)
                .collect();
            let clipped: Vec<usize> = per_texel.iter().map(|acc| acc[k].1).collect();
            ExposedTexture {
                texels,
                clipped_texels: clipped.iter().filter(|&&n| n > 0).count(),
                clipped_share: clipped.iter().sum::<usize>() as f64
                    / (TEXEL_SAMPLES * size * size).max(1) as f64,
            }
        })
        .collect()
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
    let scene = scene_of(&meta)?;
    let index = NormtextureIndex::read(run)?;
    let truths: Vec<Vec<f32>> = pairs
        .iter()
        .map(|&(l, v)| true_texture_channels(&scene, index.size, l, v, index.channels))
        .collect();
    btf_error(run, pairs, &truths)
}

/// The scene a simulated run rendered, on the holder its profile
/// describes.
fn scene_of(meta: &crate::store::RunMeta) -> Result<Arc<Scene>, ProcessError> {
    let name = match &meta.sim_scene {
        Some(s) => s.name.clone(),
        None => crate::rig::sim::profile_scene(&meta.profile)
            .map_err(|e| ProcessError::Invalid(format!("the run's profile: {e}")))?,
    };
    Scene::load_on(&name, &meta.profile.holder)
        .map_err(|e| ProcessError::Invalid(format!("the run's simulated scene: {e}")))
}

/// Makes MDF steps measure simulated runs against their scene
/// ([`crate::postprocess::mdf::DepthTruth`]); call once at start-up.
pub fn install() {
    crate::postprocess::mdf::install_depth_truth(mdf_truth);
}

/// The MDF's truth of a simulated laser run; `None` for hardware runs.
fn mdf_truth(
    run: &RunFrames,
) -> Result<Option<Box<dyn crate::postprocess::mdf::DepthTruth>>, ProcessError> {
    if !run.meta.simulated {
        return Ok(None);
    }
    Ok(Some(Box::new(SceneDepth(scene_of(&run.meta)?))))
}

/// A scene as the MDF's depth truth.
struct SceneDepth(Arc<Scene>);

impl crate::postprocess::mdf::DepthTruth for SceneDepth {
    fn depth_errors(
        &self,
        cam: &PinholeCamera,
        d: &DisplacementImage,
        reference_m: f64,
        box_half: f64,
    ) -> PixelErrors {
        depth_errors(&self.0, cam, d, reference_m, box_half)
    }
}

/// The measured displacement against the true one, pixel by pixel, over
/// pixels whose true surface point lies in the sample's bounding box: the
/// distance along the pixel's ray from the reference plane to the first
/// surface hit.
pub fn depth_errors(
    scene: &rigd_sim::scene::Scene,
    cam: &PinholeCamera,
    d: &DisplacementImage,
    reference_m: f64,
    box_half: f64,
) -> PixelErrors {
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
    let mut pixels = vec![PixelError::OffSample; d.width * d.height];
    for j in 0..d.height {
        for i in 0..d.width {
            let Some(p) = scene.true_surface_point(&shot, i, j) else {
                continue;
            };
            if p[0].abs() > box_half || p[1].abs() > box_half {
                continue;
            }
            let k = j * d.width + i;
            pixels[k] = PixelError::Unmeasured;
            let measured = d.depth[k];
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
            pixels[k] = PixelError::Measured((f64::from(measured) - truth).abs() * 1e3);
        }
    }
    PixelErrors {
        width: d.width,
        pixels,
    }
}
