//! `rigd process mdf-texture`: a laser run's MDF (`rigd process mdf`, one
//! displacement image per view in camera pixels) resampled into a BTF run's
//! texture space, where the renderers read it (Wang et al., §4 indexes the
//! MDF by texture coordinate and view direction).
//!
//! Per view and texel: the texel's point on the mesostructure's top plane,
//! projected into the view's camera; the nearest pixel's displacement,
//! which runs along that pixel's ray from the laser run's reference plane,
//! less the ray's length between the reference plane and the top plane.
//! The top plane is the 99th percentile of the measured surface heights
//! over the tile (so the ridges of the sample touch the mesh and the rest
//! lies below it), found first with the reference plane's texel positions.
//! Texels the view did not measure stay −1.

use std::path::Path;

use rigd_process::mdf::{MdfTexture, MdfTextureHeader, NO_DEPTH};
use rigd_process::npy;
use serde::Deserialize;

use super::frames::RunFrames;
use super::mdf::{view_camera, ViewSummary};
use super::ProcessError;

/// Side of the MDF texture unless asked otherwise, texels.
pub const DEFAULT_MDF_TEXTURE_SIZE: usize = 128;
/// Share of the measured heights at or below the top plane.
const TOP_QUANTILE: f64 = 0.99;

/// What [`mdf_texture`] is asked for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MdfTextureConfig {
    /// Side of the texture, texels.
    pub size: usize,
    /// Side of the sample square one texture tile covers, mm; None: the
    /// BTF run's sample (the holder's) times the ROI `rectify` kept.
    pub tile_mm: Option<f64>,
}

impl Default for MdfTextureConfig {
    fn default() -> Self {
        MdfTextureConfig {
            size: DEFAULT_MDF_TEXTURE_SIZE,
            tile_mm: None,
        }
    }
}

/// The part of `processed/mdf/report.json` the resampling reads.
#[derive(Deserialize)]
struct MdfReportViews {
    reference_mm: f64,
    views: Vec<ViewSummary>,
}

/// One view's displacement image and camera.
struct ViewImage {
    summary: ViewSummary,
    camera: rigd_process::mdf::PinholeCamera,
    width: usize,
    height: usize,
    depth_mm: Vec<f32>,
}

impl ViewImage {
    /// The displacement (mm, along the ray from the reference plane) of
    /// the pixel that sees `p` (metres, sample frame), and the cosine of
    /// that pixel's ray with the sample normal; None where it sees nothing
    /// measured.
    fn at(&self, p: [f64; 3]) -> Option<(f64, f64)> {
        let [x, y] = self.camera.project(p)?;
        if !(x >= 0.0 && y >= 0.0 && x < self.width as f64 && y < self.height as f64) {
            return None;
        }
        let (i, j) = (x.floor() as usize, y.floor() as usize);
        let d = *self.depth_mm.get(j * self.width + i)?;
        let (_, dir) = self.camera.ray(i, j);
        let cos = dir[2].abs();
        (d >= 0.0 && cos > 1e-3).then_some((f64::from(d), cos))
    }
}

/// The side of the sample square a BTF run's textures cover, mm: its
/// holder's sample times the ROI its `rectify` kept (1 for an index that
/// does not say, as `rectify` wrote before it recorded the ROI).
pub fn default_tile_mm(btf_run: &Path) -> Result<f64, ProcessError> {
    let meta = crate::store::read_meta(btf_run)?;
    let (_, half) = super::rectify::holder_of(&meta)?;
    let roi = super::rectify::NormtextureIndex::read(btf_run)?
        .roi
        .unwrap_or(1.0);
    Ok(2.0 * half[0] * 1e3 * roi)
}

/// Resamples `laser_run`'s MDF into `btf_run`'s texture space and writes it
/// to `btf_run/processed/mdf-texture/`.
pub fn mdf_texture(
    btf_run: &Path,
    laser_run: &Path,
    cfg: &MdfTextureConfig,
) -> Result<MdfTextureHeader, ProcessError> {
    let n = cfg.size;
    if !(8..=1024).contains(&n) {
        return Err(ProcessError::Invalid(format!(
            "MDF texture side {n}: expected 8 … 1024 texels"
        )));
    }
    let tile_mm = match cfg.tile_mm {
        Some(t) if t.is_finite() && t > 0.0 => t,
        Some(t) => {
            return Err(ProcessError::Invalid(format!(
                "tile {t} mm: expected a positive side"
            )))
        }
        None => default_tile_mm(btf_run)?,
    };
    let laser = RunFrames::open(laser_run)?;
    let mdf_dir = crate::store::processed::mdf_dir(laser_run);
    let report_path = mdf_dir.join("report.json");
    let bytes = std::fs::read(&report_path).map_err(|e| {
        ProcessError::Invalid(format!(
            "{}: {e}; run `rigd process mdf {}` first",
            report_path.display(),
            laser_run.display()
        ))
    })?;
    let report: MdfReportViews = serde_json::from_slice(&bytes)
        .map_err(|e| ProcessError::Invalid(format!("{}: {e}", report_path.display())))?;
    let frame = laser
        .entries
        .iter()
        .find(|e| e.laser.is_some())
        .ok_or_else(|| {
            ProcessError::Invalid(format!("{} holds no laser frames", laser_run.display()))
        })?;
    let size = [frame.width, frame.height];
    let mut views = Vec::with_capacity(report.views.len());
    for summary in report.views {
        let camera = view_camera(&laser.meta.profile, &summary.camera, size, summary.view)?;
        let path = mdf_dir.join(format!("{}.npy", summary.name));
        let depth = npy::read_f32(&path)
            .map_err(|e| ProcessError::Invalid(format!("{}: {e}", path.display())))?;
        if depth.shape != [size[1] as usize, size[0] as usize] {
            return Err(ProcessError::Invalid(format!(
                "{}: shape {:?}, the laser frames are {}×{}",
                path.display(),
                depth.shape,
                size[0],
                size[1]
            )));
        }
        views.push(ViewImage {
            summary,
            camera,
            width: size[0] as usize,
            height: size[1] as usize,
            depth_mm: depth.data,
        });
    }
    if views.is_empty() {
        return Err(ProcessError::Invalid(format!(
            "{} has no MDF views",
            report_path.display()
        )));
    }
    let reference_m = report.reference_mm * 1e-3;
    // Texel centre (x, y) of the tile at height z, metres; row 0 at +y.
    let texel_point = |x: usize, y: usize, z: f64| {
        let side = tile_mm * 1e-3;
        [
            ((x as f64 + 0.5) / n as f64 - 0.5) * side,
            (0.5 - (y as f64 + 0.5) / n as f64) * side,
            z,
        ]
    };
    // 1. The top plane from the surface heights seen at the reference plane.
    let mut heights: Vec<f64> = views
        .iter()
        .flat_map(|v| {
            (0..n * n).filter_map(move |k| {
                let (d, cos) = v.at(texel_point(k % n, k / n, reference_m))?;
                Some(report.reference_mm - d * cos)
            })
        })
        .collect();
    if heights.is_empty() {
        return Err(ProcessError::Invalid(format!(
            "no view of {} measured the {tile_mm} mm tile around the sample's centre",
            laser_run.display()
        )));
    }
    heights.sort_by(f64::total_cmp);
    let top_mm = heights[((heights.len() - 1) as f64 * TOP_QUANTILE).round() as usize]
        .min(report.reference_mm);
    // 2. Each texel's depth below the top plane along its view ray.
    let top_m = top_mm * 1e-3;
    let mut depth_mm = Vec::with_capacity(views.len() * n * n);
    let mut coverage = Vec::with_capacity(views.len());
    for v in &views {
        let before = depth_mm.len();
        depth_mm.extend(
            (0..n * n).map(|k| match v.at(texel_point(k % n, k / n, top_m)) {
                Some((d, cos)) => (d - (report.reference_mm - top_mm) / cos).max(0.0) as f32,
                None => NO_DEPTH,
            }),
        );
        let measured = depth_mm[before..].iter().filter(|&&d| d >= 0.0).count();
        coverage.push(measured as f64 / (n * n) as f64);
    }
    let header = MdfTextureHeader {
        size: n,
        views: views.iter().map(|v| v.summary.view).collect(),
        tile_mm,
        top_mm,
        coverage,
        source: laser_run.display().to_string(),
    };
    let texture = MdfTexture::new(header, depth_mm)
        .map_err(|e| ProcessError::Invalid(format!("MDF texture: {e}")))?;
    texture
        .write(&crate::store::processed::mdf_texture_dir(btf_run))
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    Ok(texture.header().clone())
}
