//! The scene file format (`crates/sim/scenes/*.toml`), as parsed. Strict: unknown
//! keys are errors, so a typo never silently renders the wrong sample.
//! Lengths in the file are millimetres; the renderer works in metres.

pub use rigd_core::holder::HolderSpec;
use serde::Deserialize;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub sample: SampleSpec,
    #[serde(default)]
    pub holder: HolderSpec,
    #[serde(default)]
    pub sensor: SensorSpec,
    /// Effects the scene forbids (`false`) or wants even when they are off
    /// by default (`true`). Absent: live exactly when the scene can show it.
    #[serde(default)]
    pub effects: std::collections::BTreeMap<String, bool>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SampleSpec {
    /// Side lengths, at most 100 × 100 mm.
    pub size_mm: [f64; 2],
    /// Texels across the longer side of the sampled height and albedo grids.
    #[serde(default = "default_resolution")]
    pub resolution: usize,
    pub albedo: AlbedoSpec,
    #[serde(default)]
    pub heightfield: HeightSpec,
    #[serde(default)]
    pub specular: Option<SpecularSpec>,
    /// Standard deviation of the subsurface blur of the irradiance, mm.
    #[serde(default)]
    pub subsurface_mm: f64,
    /// Non-planar macro shape (a folded cloth).
    #[serde(default, rename = "macro")]
    pub macro_shape: Option<MacroSpec>,
}

fn default_resolution() -> usize {
    512
}

#[derive(Debug, Clone, Deserialize)]
#[serde(tag = "pattern", rename_all = "kebab-case", deny_unknown_fields)]
pub enum AlbedoSpec {
    /// One reflectance everywhere.
    Uniform { value: f64 },
    /// A printed calibration pattern: checks with a fine thread print.
    Checks {
        dark: f64,
        light: f64,
        check_mm: f64,
        thread_mm: f64,
    },
    /// Dyed yarn: a base colour varying along and across the wales/loops
    /// of the heightfield, darker in its valleys.
    Yarn {
        base: f64,
        variation: f64,
        #[serde(default)]
        valley_darkening: f64,
    },
    /// Mottled: value noise around a base.
    Mottled {
        base: f64,
        variation: f64,
        feature_mm: f64,
    },
    /// A greyscale PNG stretched over the sample, scaled to [min, max].
    Image { path: String, min: f64, max: f64 },
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum HeightSpec {
    /// A flat sample: no relief, no ray marching, no shadows.
    #[default]
    None,
    /// Parallel rounded ridges (corduroy wales) along `direction_deg`.
    Ridges {
        amplitude_mm: f64,
        period_mm: f64,
        #[serde(default)]
        direction_deg: f64,
    },
    /// Interlocking V-shaped knit loops (stockinette).
    Knit {
        amplitude_mm: f64,
        stitch_width_mm: f64,
        stitch_height_mm: f64,
        yarn_radius_mm: f64,
    },
    /// Shallow cellular relief (grained leather).
    Cells { amplitude_mm: f64, cell_mm: f64 },
    /// Spherical caps on a grid: normals known in closed form.
    Domes {
        radius_mm: f64,
        height_mm: f64,
        count: usize,
    },
    /// A greyscale PNG: black = 0, white = `amplitude_mm`.
    Image { path: String, amplitude_mm: f64 },
}

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

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MacroSpec {
    /// Fold height above the holder, crest to trough, mm.
    pub fold_height_mm: f64,
    pub wavelength_mm: f64,
    #[serde(default)]
    pub direction_deg: f64,
    /// Binary visibility maps (Ganster et al., hemisphere model).
    #[serde(default)]
    pub visibility: VisibilitySpec,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VisibilitySpec {
    /// Vertices across each side of the sample.
    pub vertices: usize,
    /// Hemisphere cells: polar rings and azimuth sectors.
    pub theta_cells: usize,
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
}
