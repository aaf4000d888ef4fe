//! Export and import of normtextures in the formats existing BTF tools
//! read (UTIA folders, the Bonn UBO2003 zip).

use std::path::Path;

use rigd_core::geometry::Direction;

use super::rectify::{slot_of, FrameRegistration, NormtextureIndex};
use super::ProcessError;
use crate::store::processed::{normtextures_dir, NORMTEXTURE_INDEX};

/// Writes a rectified run's textures in an existing BTF tool's layout
/// (`rigd export`); returns how many.
pub fn export_run(
    run: &Path,
    format: rigd_process::export::Format,
    out: &Path,
    jpeg_quality: u8,
) -> Result<usize, ProcessError> {
    use rigd_process::export::{write, Texture};
    // The textures are only as whole as the run they were made from.
    crate::store::check_run(run)?;
    let index = NormtextureIndex::read(run)?;
    let mut textures = Vec::with_capacity(index.frames.len());
    let mut seen = std::collections::BTreeSet::new();
    for f in &index.frames {
        if !seen.insert(f.index) {
            return Err(ProcessError::Invalid(format!(
                "{}: image {} is listed twice (rectified from a journal with a line twice, as an older rigd's resume left it): run `rigd process rectify` again",
                normtextures_dir(run).join(NORMTEXTURE_INDEX).display(),
                f.index
            )));
        }
        let (Some(&light), Some(&view)) = (
            index.lights.get(f.light_index),
            index.views.get(f.view_slot),
        ) else {
            return Err(ProcessError::Invalid(format!(
                "{}: frame {} names light {} and view slot {}, which the index does not list",
                run.display(),
                f.index,
                f.light_index,
                f.view_slot
            )));
        };
        textures.push(Texture {
            light: (light),
            view: (view),
            image: index.load(run, f.view_slot, f.light_index)?,
        });
    }
    write(&textures, format, out, jpeg_quality).map_err(|e| ProcessError::Invalid(e.to_string()))
}

/// Reads textures in an export format into `out/processed/normtextures/`,
/// so `rigd process btf out` works on them (`rigd import`).
pub fn import_textures(
    format: rigd_process::export::Format,
    path: &Path,
    out: &Path,
) -> Result<NormtextureIndex, ProcessError> {
    use rigd_process::image_io::{write_png, PngDepth};
    let textures = rigd_process::export::read(format, path)
        .map_err(|e| ProcessError::Invalid(e.to_string()))?;
    let first = textures
        .first()
        .ok_or_else(|| ProcessError::Invalid(format!("{}: no textures found", path.display())))?;
    let size = first.image.width;
    let dir = normtextures_dir(out);
    crate::postprocess::create_dir(&dir)?;
    let (mut lights, mut views, mut frames) = (Vec::new(), Vec::new(), Vec::new());
    for (i, t) in textures.iter().enumerate() {
        if t.image.channels != first.image.channels {
            return Err(ProcessError::Invalid(format!(
                "{}: texture {i} has {} channels, the first {}",
                path.display(),
                t.image.channels,
                first.image.channels
            )));
        }
        if t.image.width != size || t.image.height != size {
            return Err(ProcessError::Invalid(format!(
                "{}: texture {i} is {}x{}, the first is {size}x{size}",
                path.display(),
                t.image.width,
                t.image.height
            )));
        }
        let view_slot = slot_of(&mut views, Direction::new(t.view.theta_deg, t.view.phi_deg));
        let light_index = slot_of(
            &mut lights,
            Direction::new(t.light.theta_deg, t.light.phi_deg),
        );
        let file = format!("v{view_slot:03}_l{light_index:03}.png");
        write_png(&dir.join(&file), &t.image, PngDepth::Eight).map_err(|e| {
            ProcessError::Frame {
                path: dir.join(&file),
                message: e.to_string(),
            }
        })?;
        frames.push(FrameRegistration {
            file: Some(file),
            ..FrameRegistration::new(i, view_slot, light_index)
        });
    }
    let index = NormtextureIndex {
        size,
        encoding: "png8".into(),
        bit_depth: 8,
        lights,
        views,
        frames,
        summary: None,
        roi: None,
        channels: first.image.channels,
    };
    let mut json =
        serde_json::to_vec_pretty(&index).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    crate::store::write_atomic(&dir.join(NORMTEXTURE_INDEX), &json)?;
    Ok(index)
}
