//! The scene file format (`crates/sim/scenes/*.toml`), as parsed. Strict: unknown
//! keys are errors, so a typo never silently renders the wrong sample.
//! Lengths in the file are millimetres; the renderer works in metres.

use serde::Deserialize;

/// A whole scene file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    /// The scene's name (e.g. `corduroy`).
    pub name: String,
    /// A line saying what the sample is, shown by `rigd sim scenes`.
    #[serde(default)]
    pub description: String,
    /// The sample (`[sample]`).
    pub sample: SampleSpec,
    /// Refused when present: the holder plate is the rig's, described by
    /// the profile's `[holder]` table, not a sample's.
    #[serde(default)]
    pub holder: Option<serde::de::IgnoredAny>,
    /// Sensor noise and vignetting (`[sensor]`); absent: none.
    #[serde(default)]
    pub sensor: SensorSpec,
    /// Effects the scene forbids (`false`) or wants even when they are off
    /// by default (`true`). Absent: live exactly when the scene can show it.
    #[serde(default)]
    pub effects: std::collections::BTreeMap<String, bool>,
}

/// The sample on the holder (`[sample]`): its size, pattern, relief and
/// gloss.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SampleSpec {
    /// Side lengths, at most 100 × 100 mm.
    pub size_mm: [f64; 2],
    /// Texels across the longer side of the sampled height and albedo grids.
    #[serde(default = "default_resolution")]
    pub resolution: usize,
    /// The diffuse reflectance pattern.
    pub albedo: AlbedoSpec,
    /// The mesostructure relief; absent: flat.
    #[serde(default)]
    pub heightfield: HeightSpec,
    /// The glossy lobe; absent: matte.
    #[serde(default)]
    pub specular: Option<SpecularSpec>,
    /// Standard deviation of the subsurface blur of the irradiance, mm.
    #[serde(default)]
    pub subsurface_mm: f64,
    /// Non-planar macro shape (a folded cloth).
    #[serde(default, rename = "macro")]
    pub macro_shape: Option<MacroSpec>,
    /// The sample's colour; absent: neutral (grey).
    #[serde(default)]
    pub colour: Option<ColourSpec>,
}

/// The sample's colour, chosen by `kind`. Its diffuse reflectance in linear
/// sRGB is the `albedo` pattern times a tint: each `rgb` given here scaled
/// to luminance 1 (Rec. 709 weights), so a monochrome sensor sees the
/// `albedo` pattern unchanged and a colour sensor sees its hue.
#[derive(Debug, Clone, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum ColourSpec {
    /// One dye over the whole sample.
    Dye {
        /// The dye's colour, linear sRGB; only its chromaticity counts.
        rgb: [f64; 3],
    },
    /// Bands of yarn of alternating colours (a striped two-colour knit).
    Stripes {
        /// The yarns' colours in turn, linear sRGB.
        rgb: Vec<[f64; 3]>,
        /// Width of one band, mm.
        width_mm: f64,
        /// Direction across the bands, degrees from +x (90: horizontal
        /// bands, stacked along y).
        #[serde(default)]
        direction_deg: f64,
    },
}

fn default_resolution() -> usize {
    512
}

/// The sample's diffuse reflectance, chosen by `pattern`. Reflectances are
/// in [0, 1].
#[derive(Debug, Clone, Deserialize)]
#[serde(tag = "pattern", rename_all = "kebab-case", deny_unknown_fields)]
pub enum AlbedoSpec {
    /// One reflectance everywhere.
    Uniform {
        /// The reflectance.
        value: f64,
    },
    /// A printed calibration pattern: checks with a fine thread print.
    Checks {
        /// Reflectance at the pattern's darkest point (dark check, thread
        /// trough).
        dark: f64,
        /// Reflectance at the pattern's lightest point (light check, thread
        /// crest).
        light: f64,
        /// Side of one check, mm.
        check_mm: f64,
        /// Period of the thread print along x, mm.
        thread_mm: f64,
    },
    /// Dyed yarn: a base colour varying along and across the wales/loops
    /// of the heightfield, darker in its valleys.
    Yarn {
        /// The mean reflectance.
        base: f64,
        /// Relative variation of the noise: the reflectance spans
        /// `base × (1 ± variation)`.
        variation: f64,
        /// Fraction by which the reflectance drops at the bottom of the
        /// relief (0: none; 1: black there).
        #[serde(default)]
        valley_darkening: f64,
    },
    /// Mottled: value noise around a base.
    Mottled {
        /// The mean reflectance.
        base: f64,
        /// Absolute amplitude of the noise: the reflectance spans
        /// `base ± variation`.
        variation: f64,
        /// Size of the mottling's features, mm.
        feature_mm: f64,
    },
    /// A greyscale PNG stretched over the sample, scaled to [min, max].
    Image {
        /// The PNG, relative to the scene file.
        path: String,
        /// Reflectance of black.
        min: f64,
        /// Reflectance of white.
        max: f64,
    },
}

/// The sample's mesostructure relief, chosen by `kind`. Heights are above
/// the relief's base (height 0).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum HeightSpec {
    /// A flat sample: no relief, no ray marching, no shadows.
    #[default]
    None,
    /// Parallel rounded ridges (corduroy wales) along `direction_deg`.
    Ridges {
        /// Height of a wale above the grooves, mm.
        amplitude_mm: f64,
        /// Distance between neighbouring wales, mm.
        period_mm: f64,
        /// Direction the wales run in the sample plane, degrees from +x.
        #[serde(default)]
        direction_deg: f64,
    },
    /// Interlocking V-shaped knit loops (stockinette).
    Knit {
        /// Height of the yarn's crest, mm.
        amplitude_mm: f64,
        /// Width of one stitch (along x), mm.
        stitch_width_mm: f64,
        /// Height of one stitch row (along y), mm.
        stitch_height_mm: f64,
        /// Radius of the yarn in the sample plane, mm.
        yarn_radius_mm: f64,
    },
    /// Shallow cellular relief (grained leather).
    Cells {
        /// Height of the grains above the creases between them, mm.
        amplitude_mm: f64,
        /// Size of one grain cell, mm.
        cell_mm: f64,
    },
    /// Spherical caps on a grid: normals known in closed form.
    Domes {
        /// Radius of the sphere each cap is cut from, mm.
        radius_mm: f64,
        /// Height of a cap above the base, mm (at most `radius_mm`).
        height_mm: f64,
        /// Caps per side: `count × count` caps in equal cells of a 100 mm
        /// square.
        count: usize,
    },
    /// A greyscale PNG: black = 0, white = `amplitude_mm`.
    Image {
        /// The PNG, relative to the scene file.
        path: String,
        /// Height of white, mm.
        amplitude_mm: f64,
    },
}

/// The glossy lobe: Ward's anisotropic model.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpecularSpec {
    /// Reflectance of the lobe (Ward's ρ_s).
    pub strength: f64,
    /// Roughness along and across the tangent; equal for an isotropic lobe.
    pub roughness: [f64; 2],
    /// The tangent (thread direction) in the sample plane, degrees from +x.
    #[serde(default)]
    pub tangent_deg: f64,
}

/// A macro shape: sinusoidal folds of the whole sample (a folded cloth).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MacroSpec {
    /// Fold height above the holder, crest to trough, mm.
    pub fold_height_mm: f64,
    /// Distance from one fold crest to the next, mm.
    pub wavelength_mm: f64,
    /// Direction across the folds (along which the height varies), degrees
    /// from +x.
    #[serde(default)]
    pub direction_deg: f64,
    /// Binary visibility maps (Ganster et al., hemisphere model).
    #[serde(default)]
    pub visibility: VisibilitySpec,
}

/// Resolution of a macro shape's binary visibility maps (Ganster et al.).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VisibilitySpec {
    /// Vertices across each side of the sample.
    pub vertices: usize,
    /// Hemisphere cells: polar rings and azimuth sectors.
    pub theta_cells: usize,
    /// Azimuth sectors of the hemisphere.
    pub phi_cells: usize,
}

impl Default for VisibilitySpec {
    fn default() -> Self {
        VisibilitySpec {
            vertices: 24,
            theta_cells: 16,
            phi_cells: 48,
        }
    }
}

/// The simulated sensor's noise and vignetting (`[sensor]`); zero turns
/// each off.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorSpec {
    /// Read noise, in digital numbers at the frame's bit depth.
    #[serde(default)]
    pub read_noise_dn: f64,
    /// Conversion gain for shot noise, electrons per digital number; 0 = none.
    #[serde(default)]
    pub electrons_per_dn: f64,
    /// Fraction of the natural cos⁴ fall-off applied (0 = none, 1 = full).
    #[serde(default)]
    pub vignetting: f64,
    /// Seed of the noise; a frame's own seed is mixed in.
    #[serde(default)]
    pub seed: u64,
    /// A colour camera's raw response: row c is what its red, green or blue
    /// photosites record of unit linear-sRGB red, green and blue light.
    /// The rows' sums are the channels' quantum efficiencies relative to
    /// green's; the off-diagonal terms are the overlap of the filters'
    /// passbands, which the colour correction undoes. Absent:
    /// [`DEFAULT_COLOUR_RESPONSE`].
    #[serde(default)]
    pub colour_response: Option<[[f64; 3]; 3]>,
}

/// A colour camera's raw response when a scene gives none: green most
/// sensitive, red and blue about two thirds of it, the passbands
/// overlapping as a CMOS sensor's dyes do (white balance gains of about
/// 1.6 red and 1.45 blue).
pub const DEFAULT_COLOUR_RESPONSE: [[f64; 3]; 3] =
    [[0.50, 0.12, 0.02], [0.10, 0.80, 0.10], [0.02, 0.12, 0.55]];
