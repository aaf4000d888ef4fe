//! A view slot's textures as the BTF compression and the reflectance fit
//! read them. A texel that read a pixel the sensor clipped (`rectify`'s
//! `clipped_mask`) holds a lower bound, not a measurement: it is replaced
//! by the inverse-angle-weighted mean of the same texel under the slot's
//! nearest lights (up to [`FILL_NEIGHBOURS`]) that did not clip there. A
//! texel clipped under every light of its slot is kept as it is, a lower
//! bound, and counted apart.

use std::path::Path;

use rigd_process::image_io::Image;
use serde::{Deserialize, Serialize};

use super::rectify::{NormtextureIndex, FILL_NEIGHBOURS};
use super::ProcessError;

/// What the fill did to a slot's (or a run's) clipped texels.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClipFill {
    /// Clipped texels replaced by their neighbouring lights' values.
    pub filled: usize,
    /// Clipped texels no neighbouring light measured unclipped: kept as
    /// read, lower bounds.
    pub left: usize,
}

impl std::ops::Add for ClipFill {
    type Output = ClipFill;

    /// Both counts added.
    fn add(self, other: ClipFill) -> ClipFill {
        ClipFill {
            filled: self.filled + other.filled,
            left: self.left + other.left,
        }
    }
}

/// The textures of view slot `slot`, one per light in the index's order,
/// with every clipped texel filled, and what the fill did.
pub fn load_slot(
    run: &Path,
    index: &NormtextureIndex,
    slot: usize,
) -> Result<(Vec<Image>, ClipFill), ProcessError> {
    let mut images = (0..index.lights.len())
        .map(|l| index.load(run, slot, l))
        .collect::<Result<Vec<_>, _>>()?;
    let masks = (0..index.lights.len())
        .map(|l| clip_mask(run, index, slot, l))
        .collect::<Result<Vec<_>, _>>()?;
    let fill = fill_clipped(&mut images, &masks, index)?;
    Ok((images, fill))
}

/// Light `light`'s clip mask in slot `slot`: true where a texel clipped;
/// None when none did.
fn clip_mask(
    run: &Path,
    index: &NormtextureIndex,
    slot: usize,
    light: usize,
) -> Result<Option<Vec<bool>>, ProcessError> {
    let Some(file) = index
        .frames
        .iter()
        .find(|f| f.view_slot == slot && f.light_index == light)
        .and_then(|f| f.clipped_mask.as_ref())
    else {
        return Ok(None);
    };
    let path = crate::store::processed::normtextures_dir(run).join(file);
    let mask = rigd_process::image_io::load_png(&path).map_err(|e| ProcessError::Frame {
        path: path.clone(),
        message: e.to_string(),
    })?;
    if (mask.width, mask.height) != (index.size, index.size) {
        return Err(ProcessError::Frame {
            path,
            message: format!(
                "a clip mask of {}×{} for textures of {}²",
                mask.width, mask.height, index.size
            ),
        });
    }
    Ok(Some(
        mask.data
            .chunks_exact(mask.channels.max(1))
            .map(|px| px[0] > 0.5)
            .collect(),
    ))
}

/// Fills each clipped texel of `images` (masks in the same order) from
/// the nearest lights, by the index's light directions, that did not clip
/// there.
fn fill_clipped(
    images: &mut [Image],
    masks: &[Option<Vec<bool>>],
    index: &NormtextureIndex,
) -> Result<ClipFill, ProcessError> {
    let mut fill = ClipFill::default();
    let clipped_at = |l: usize, t: usize| masks[l].as_ref().is_some_and(|m| m[t]);
    for (light, mask) in masks.iter().enumerate() {
        let Some(mask) = mask else {
            continue;
        };
        let channels = images[light].channels.max(1);
        if mask.len() * channels != images[light].data.len() {
            return Err(ProcessError::Invalid(format!(
                "light {light}'s clip mask has {} texels, its texture {}",
                mask.len(),
                images[light].data.len() / channels
            )));
        }
        // The other lights, nearest first, with their weights.
        let mut order: Vec<(usize, f64)> = (0..images.len())
            .filter(|&l| l != light && images[l].data.len() == images[light].data.len())
            .map(|l| {
                let angle = index.lights[light]
                    .angle_to_deg(index.lights[l])
                    .to_radians();
                // The same direction twice counts fully.
                (l, 1.0 / angle.max(1e-3))
            })
            .collect();
        order.sort_by(|a, b| b.1.total_cmp(&a.1));
        for texel in (0..mask.len()).filter(|&t| mask[t]) {
            let from: Vec<(usize, f64)> = order
                .iter()
                .copied()
                .filter(|&(l, _)| !clipped_at(l, texel))
                .take(FILL_NEIGHBOURS)
                .collect();
            if from.is_empty() {
                fill.left += 1;
                continue;
            }
            let total: f64 = from.iter().map(|(_, w)| w).sum();
            for c in 0..channels {
                let at = texel * channels + c;
                let value: f64 = from
                    .iter()
                    .map(|&(l, w)| w * f64::from(images[l].data[at]))
                    .sum();
                images[light].data[at] = (value / total) as f32;
            }
            fill.filled += 1;
        }
    }
    Ok(fill)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn index(lights: &[(f64, f64)]) -> NormtextureIndex {
        let mut v = serde_json::json!({
            "size": 2, "encoding": "png8", "bit_depth": 8,
            "lights": [], "views": [{"theta_deg": 0.0, "phi_deg": 0.0}], "frames": []
        });
        v["lights"] = lights
            .iter()
            .map(|&(t, p)| serde_json::json!({"theta_deg": t, "phi_deg": p}))
            .collect();
        serde_json::from_value(v).expect("an index")
    }

    fn image(values: [f32; 4]) -> Image {
        let mut img = Image::new(2, 2, 1);
        img.data = values.to_vec();
        img
    }

    #[test]
    fn a_clipped_texel_takes_its_nearest_unclipped_lights_and_one_clipped_everywhere_stays() {
        // Light 0 at 30°, its neighbours at 35° (near), 50° and 80°.
        let index = index(&[(30.0, 0.0), (35.0, 0.0), (50.0, 0.0), (80.0, 0.0)]);
        let mut images = vec![
            image([1.0, 0.2, 1.0, 1.0]),
            image([0.9, 0.3, 0.5, 1.0]),
            image([0.6, 0.4, 0.4, 1.0]),
            image([0.3, 0.5, 0.3, 1.0]),
        ];
        let clipped = |t: &[usize]| Some((0..4).map(|i| t.contains(&i)).collect::<Vec<_>>());
        // Texel 0 clipped under light 0 only; texel 2 under lights 0 and
        // 1; texel 3 under all four.
        let masks = vec![
            clipped(&[0, 2, 3]),
            clipped(&[2, 3]),
            clipped(&[3]),
            clipped(&[3]),
        ];
        let fill = fill_clipped(&mut images, &masks, &index).expect("filled");
        assert_eq!(
            fill,
            ClipFill {
                filled: 2 + 1,
                left: 4
            }
        );
        let w = |deg: f64| 1.0 / deg.to_radians();
        // Texel 0: lights 1, 2, 3 by inverse angle (5°, 20°, 50°).
        let want = (w(5.0) * 0.9 + w(20.0) * 0.6 + w(50.0) * 0.3) / (w(5.0) + w(20.0) + w(50.0));
        assert!((f64::from(images[0].data[0]) - want).abs() < 1e-6);
        // Texel 1 was not clipped: as measured.
        assert_eq!(images[0].data[1], 0.2);
        // Texel 2: light 1 clipped there too, so lights 2 and 3.
        let want = (w(20.0) * 0.4 + w(50.0) * 0.3) / (w(20.0) + w(50.0));
        assert!((f64::from(images[0].data[2]) - want).abs() < 1e-6);
        // Texel 3, clipped under every light, is kept.
        assert_eq!(images[0].data[3], 1.0);
        assert_eq!(images[3].data[3], 1.0);
        // Light 1's texel 2: light 0 clipped there too, so lights 2 and 3.
        let want = (w(15.0) * 0.4 + w(45.0) * 0.3) / (w(15.0) + w(45.0));
        assert!((f64::from(images[1].data[2]) - want).abs() < 1e-6);
    }
}
