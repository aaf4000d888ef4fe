//! Colour: the sample's tint over its grey albedo ([`SampleColour`]) and
//! what a colour camera's photosite records of a surface ([`Response`]).
//!
//! A surface's diffuse reflectance in linear sRGB is its grey albedo times
//! a tint of luminance 1, so a monochrome camera renders every scene as it
//! always has, and a colour camera's photosite of channel c records
//! `albedo × (response[c] · tint)`. Interreflected light is bounced as
//! grey: its colour is not tracked (a second-order term of the knit's
//! loops only).

use rigd_core::holder::luminance;

use super::spec::{ColourSpec, DEFAULT_COLOUR_RESPONSE};

/// The tint of neutral surfaces.
pub(crate) const NEUTRAL: [f64; 3] = [1.0, 1.0, 1.0];

/// The sample's colour, baked from its [`ColourSpec`].
#[derive(Debug, Clone)]
pub(crate) struct SampleColour {
    /// Tints of luminance 1, in turn across the bands (one for a dye).
    tints: Vec<[f64; 3]>,
    /// Unit direction across the bands and a band's width, metres.
    bands: Option<([f64; 2], f64)>,
}

impl SampleColour {
    /// Bakes `spec`; the message names the key that is wrong.
    pub(crate) fn new(spec: &ColourSpec) -> Result<SampleColour, String> {
        let (colours, bands) = match spec {
            ColourSpec::Dye { rgb } => (vec![*rgb], None),
            ColourSpec::Stripes {
                rgb,
                width_mm,
                direction_deg,
            } => {
                if !(width_mm.is_finite() && *width_mm > 0.0 && *width_mm <= 100.0) {
                    return Err(format!(
                        "sample.colour.width_mm: expected 0 < width ≤ 100 mm, got {width_mm}"
                    ));
                }
                if rgb.len() < 2 {
                    return Err("sample.colour.rgb: stripes need at least two colours".into());
                }
                let a = direction_deg.to_radians();
                (rgb.clone(), Some(([a.cos(), a.sin()], width_mm * 1e-3)))
            }
        };
        let tints = colours
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let y = luminance(*c);
                if c.iter().all(|v| v.is_finite() && *v >= 0.0) && y > 1e-6 {
                    Ok(c.map(|v| v / y))
                } else {
                    Err(format!(
                        "sample.colour.rgb[{i}]: expected finite non-negative values with \
                         some light in them, got {c:?}"
                    ))
                }
            })
            .collect::<Result<_, _>>()?;
        Ok(SampleColour { tints, bands })
    }

    /// The tint at (x, y), metres.
    #[inline]
    pub(crate) fn tint(&self, x: f64, y: f64) -> [f64; 3] {
        let band = match self.bands {
            Some(([dx, dy], width)) => {
                let k = ((x * dx + y * dy) / width).floor();
                k.rem_euclid(self.tints.len() as f64) as usize
            }
            None => 0,
        };
        self.tints.get(band).copied().unwrap_or(NEUTRAL)
    }

    /// The largest channel of any tint: the sample's reflectance reaches
    /// its grey albedo's maximum times this.
    pub(crate) fn max_component(&self) -> f64 {
        self.tints
            .iter()
            .flat_map(|t| t.iter().copied())
            .fold(0.0, f64::max)
    }
}

/// A colour camera's raw response ([`super::spec::SensorSpec::colour_response`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Response(pub [[f64; 3]; 3]);

impl Default for Response {
    fn default() -> Response {
        Response(DEFAULT_COLOUR_RESPONSE)
    }
}

impl Response {
    /// Checks the matrix: finite, non-negative, every channel sensitive.
    pub(crate) fn new(m: [[f64; 3]; 3]) -> Result<Response, String> {
        for (c, row) in m.iter().enumerate() {
            if !row.iter().all(|v| v.is_finite() && (0.0..=4.0).contains(v))
                || row.iter().sum::<f64>() <= 0.0
            {
                return Err(format!(
                    "sensor.colour_response[{c}]: expected values in [0, 4], not all 0, \
                     got {row:?}"
                ));
            }
        }
        Ok(Response(m))
    }

    /// What channel `c`'s photosite records of unit linear-sRGB red,
    /// green and blue.
    #[inline]
    pub(crate) fn filter(&self, c: usize) -> &[f64; 3] {
        &self.0[c.min(2)]
    }
}

/// What a channel that records `filter` of unit red, green and blue sees
/// of a surface of tint `tint`, per unit of grey albedo and irradiance.
#[inline]
pub(crate) fn filtered(filter: &[f64; 3], tint: [f64; 3]) -> f64 {
    filter[0] * tint[0] + filter[1] * tint[1] + filter[2] * tint[2]
}

/// The channels of linear sRGB as filters: what a perfect colour camera,
/// corrected, records.
pub(crate) const SRGB_CHANNELS: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tints_have_unit_luminance_and_stripes_alternate() {
        let spec = ColourSpec::Stripes {
            rgb: vec![[0.5, 0.1, 0.1], [0.1, 0.1, 0.5]],
            width_mm: 9.0,
            direction_deg: 90.0,
        };
        let c = SampleColour::new(&spec).expect("valid");
        let (red, blue) = (c.tint(0.0, 0.001), c.tint(0.0, 0.010));
        assert!((luminance(red) - 1.0).abs() < 1e-12);
        assert!((luminance(blue) - 1.0).abs() < 1e-12);
        assert!(red[0] > red[2] && blue[2] > blue[0]);
        // Below zero the bands go on alternating (no doubled band at 0).
        assert_eq!(c.tint(0.0, -0.001), blue);
        assert_eq!(c.tint(0.0, -0.010), red);
        // Along the bands the colour stays.
        assert_eq!(c.tint(0.04, 0.001), red);
    }

    #[test]
    fn bad_colours_name_their_key() {
        let black = ColourSpec::Dye { rgb: [0.0; 3] };
        assert!(SampleColour::new(&black).is_err_and(|m| m.contains("rgb[0]")));
        let one = ColourSpec::Stripes {
            rgb: vec![[1.0; 3]],
            width_mm: 5.0,
            direction_deg: 0.0,
        };
        assert!(SampleColour::new(&one).is_err_and(|m| m.contains("two colours")));
        let bad = [[0.5, 0.1, 0.0], [0.0; 3], [0.0, 0.1, 0.5]];
        assert!(Response::new(bad).is_err_and(|m| m.contains("colour_response[1]")));
    }

    #[test]
    fn a_neutral_surface_reads_each_channel_s_efficiency() {
        let r = Response::default();
        for (c, row) in DEFAULT_COLOUR_RESPONSE.iter().enumerate() {
            let sum: f64 = row.iter().sum();
            assert!((filtered(r.filter(c), NEUTRAL) - sum).abs() < 1e-12);
        }
        assert!((filtered(r.filter(1), NEUTRAL) - 1.0).abs() < 1e-12);
    }
}

#[cfg(test)]
mod render_tests {
    use super::super::{Scene, Shot};
    use super::{filtered, Response, NEUTRAL};
    use rigd_core::Cfa;

    /// Frame size: a 7 mm patch is about 7 pixels across.
    const W: usize = 288;
    const H: usize = 192;

    fn shot(cfa: Option<Cfa>) -> Shot {
        Shot {
            light: [0.3, 0.1, 0.95],
            width: W as u32,
            height: H as u32,
            cfa,
            ..Shot::default()
        }
    }

    /// Mean linear value over the photosites of `channel` whose pixel
    /// `keep` accepts.
    fn site_mean(
        values: &[f32],
        cfa: Cfa,
        channel: usize,
        keep: impl Fn(usize, usize) -> bool,
    ) -> f64 {
        let (mut sum, mut n) = (0.0, 0);
        for (k, v) in values.iter().enumerate() {
            let (x, y) = (k % W, k / W);
            if cfa.channel_at(x, y) == channel && keep(x, y) {
                sum += f64::from(*v);
                n += 1;
            }
        }
        sum / f64::from(n.max(1))
    }

    #[test]
    fn a_bayer_sensor_sees_a_neutral_scene_at_each_channel_s_efficiency() {
        let scene = Scene::load("flat-calibration").expect("scene");
        let (mono, _) = scene.render_linear(&shot(None));
        let (bayer, _) = scene.render_linear(&shot(Some(Cfa::Grbg)));
        let r = Response::default();
        for (k, (m, b)) in mono.iter().zip(&bayer).enumerate() {
            let c = Cfa::Grbg.channel_at(k % W, k / W);
            let want = f64::from(*m) * filtered(r.filter(c), NEUTRAL);
            assert!(
                (f64::from(*b) - want).abs() <= 1e-4 * want.abs() + 1e-4,
                "pixel {k}"
            );
        }
    }

    #[test]
    fn a_bayer_sensor_sees_the_dye_and_the_patches_colours() {
        let holder = rigd_core::holder::HolderSpec {
            colour_patches: true,
            ..Default::default()
        };
        let scene = Scene::load("corduroy")
            .expect("scene")
            .on_holder(holder.holder().expect("the standard plate with patches"))
            .expect("on the holder");
        assert!(scene.is_coloured());
        let cfa = Cfa::Rggb;
        let (bayer, _) = scene.render_linear(&shot(Some(cfa)));
        // The centre of the frame is the rust-dyed sample: red photosites
        // well above blue ones, white-balanced by the response.
        let centre = |x: usize, y: usize| (108..180).contains(&x) && (60..132).contains(&y);
        let r = Response::default();
        let red = site_mean(&bayer, cfa, 0, centre) / filtered(r.filter(0), NEUTRAL);
        let blue = site_mean(&bayer, cfa, 2, centre) / filtered(r.filter(2), NEUTRAL);
        assert!(red > 1.8 * blue, "red {red}, blue {blue}");
        // The red patch on the holder: its tile's red photosite well above
        // its blue one.
        let patch = scene
            .holder
            .patches
            .iter()
            .find(|p| p.name == "red")
            .expect("a red patch");
        let [px, py] = scene
            .plate_pixel(&shot(Some(cfa)), patch.centre)
            .expect("in the frame");
        // The RGGB tile whose top-left photosite is nearest the centre.
        let (x0, y0) = ((px as usize) & !1, (py as usize) & !1);
        let site = |x: usize, y: usize| f64::from(bayer[y * W + x]);
        let (tile_red, tile_blue) = (site(x0, y0), site(x0 + 1, y0 + 1));
        assert!(tile_red > 3.0 * tile_blue, "{tile_red} {tile_blue}");
        // The truth agrees: the albedo's red over its blue.
        let [tr, _, tb] = scene.albedo_rgb(0.001, 0.002);
        assert!(tr > 3.0 * tb, "{tr} {tb}");
        // A monochrome camera sees the albedo as before: its luminance.
        let rgb = scene.albedo_rgb(0.001, 0.002);
        let grey = scene.albedo(0.001, 0.002);
        assert!((rigd_core::holder::luminance(rgb) - grey).abs() < 1e-9);
    }
}
