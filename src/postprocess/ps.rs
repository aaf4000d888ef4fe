//! Photometric stereo of a run (Spence et al., §2): the frames and the lights
//! they were taken under.

use rigd_process::photometric_stereo::PsDataset;

use super::frames::RunFrames;
use super::ProcessError;
use crate::store::FrameEntry;

/// A photometric-stereo dataset from a run whose camera looks down on the
/// sample (VirTex): every frame of one camera, with the light each was
/// taken under. The camera's image axes are the sample's x and y (the
/// simulated and real VirTex cameras sit at the pole), so lights in the
/// sample frame are lights in the image frame photometric stereo expects.
///
/// A colour camera's frames are white-balanced and colour-corrected by the
/// run's colour calibration (measured now on the holder's patches if there
/// is none yet; [`super::rectify::colour::texture_colour`]): photometric stereo
/// then solves the normals on their luminance and gives RGB albedo, as
/// Spence et al. do. Without a calibration the frames are read as grey.
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
    let colour = super::rectify::colour::texture_colour(run, true)?;
    let mut images = Vec::with_capacity(entries.len());
    for e in &entries {
        let rgb = match &colour {
            Some(calibration) => run.corrected(e, calibration)?,
            None => None,
        };
        images.push(match rgb {
            Some(rgb) => rgb,
            None => run.image(e)?,
        });
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
