//! Scenes for the simulated cameras: a sample (heightfield, albedo, glossy
//! lobe, subsurface blur, macro folds) on a holder plate with registration
//! markers, read from `crates/sim/scenes/*.toml`, and the renderer that turns a
//! frame request into a sensor image computing only the effects the scene
//! and the request call for ([`effects`]). [`truth`] gives what a perfect
//! rig would measure, for judging the post-processing.

mod colour;
mod coverage;
pub mod effects;
mod exposure;
mod march;
mod noise;
mod rays;
mod render;
mod sensor;
mod shade;
mod shot;
pub mod spec;
mod surface;
pub mod truth;
mod visibility;

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use colour::{Response, SampleColour};
pub use effects::{Effect, EffectPlan, EffectSet, EffectSwitches};
pub use render::Rendered;
pub use rigd_core::holder::{Holder, Marker};
pub use rigd_core::lamp_drift::LampDrift;
pub use shot::{LaserSheet, Shot, WHITE_LEVEL};
pub use spec::SceneSpec;
use spec::{AlbedoSpec, HeightSpec, MacroSpec, SensorSpec};
use surface::SurfaceTexels;
pub use surface::{dome, dome_normal, Grid, DOME_FIELD_MM};
use visibility::VisibilityMaps;

/// The scenes shipped with rigd, by name.
const BUILTIN: &[(&str, &str)] = &[
    (
        "flat-calibration",
        include_str!("../../scenes/flat-calibration.toml"),
    ),
    ("corduroy", include_str!("../../scenes/corduroy.toml")),
    (
        "knitted-wool",
        include_str!("../../scenes/knitted-wool.toml"),
    ),
    ("leather", include_str!("../../scenes/leather.toml")),
    (
        "folded-cloth",
        include_str!("../../scenes/folded-cloth.toml"),
    ),
    ("ps-target", include_str!("../../scenes/ps-target.toml")),
];

/// The scene simulated cameras render when a profile names none.
pub const DEFAULT_SCENE: &str = "flat-calibration";

/// Why a scene could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The scene file does not parse, a value is out of range or an image
    /// it names cannot be read.
    #[error("{origin}: {message}")]
    Invalid {
        /// The file's path or the built-in scene's name.
        origin: String,
        /// The offending key and what is wrong with it.
        message: String,
    },
    /// The name is neither a built-in scene nor a path to a scene file.
    #[error("unknown scene `{name}` (built in: {known}; or give a path to a .toml file)")]
    Unknown {
        /// The name that was asked for.
        name: String,
        /// The built-in scene names, comma-separated.
        known: String,
    },
    /// A scene file could not be read: missing, not a regular file, or
    /// too large.
    #[error(transparent)]
    Io(#[from] rigd_core::read::ReadError),
    /// A client named a scene that is neither built in nor configured by
    /// the operator ([`Scene::offered`]); nothing was read.
    #[error("unknown scene `{name}` (known: {known})")]
    NotOffered {
        /// The name asked for, shortened to 64 characters.
        name: String,
        /// The scenes that can be asked for, comma-separated.
        known: String,
    },
}

fn invalid(origin: &str, message: impl Into<String>) -> SceneError {
    SceneError::Invalid {
        origin: origin.to_string(),
        message: message.into(),
    }
}

/// The glossy lobe in renderer units.
#[derive(Debug, Clone, Copy)]
pub struct Specular {
    /// Reflectance of the lobe (Ward's ρ_s), in [0, 1].
    pub strength: f64,
    /// Ward's roughness α along and across the tangent.
    pub alpha: [f64; 2],
    /// Unit tangent in the sample plane.
    pub tangent: [f64; 2],
}

/// A scene ready to render: grids baked, visibility maps computed.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The scene's name (e.g. `corduroy`).
    pub name: String,
    /// A line saying what the sample is.
    pub description: String,
    /// Half the sides of the sample as it lies on the holder (the
    /// holder's sample window), metres.
    pub sample_half: [f64; 2],
    /// Half the sides of the sample the scene describes, metres.
    pub material_half: [f64; 2],
    /// The holder plate under the sample, with its registration markers.
    pub holder: Holder,
    pub(crate) relief: Option<Relief>,
    pub(crate) albedo: Grid,
    /// The sample's tint over its albedo; `None`: neutral.
    pub(crate) colour: Option<SampleColour>,
    /// What a colour camera's photosites record.
    pub(crate) response: Response,
    pub(crate) specular: Option<Specular>,
    /// Subsurface blur standard deviation, metres.
    pub(crate) subsurface: f64,
    pub(crate) visibility: Option<VisibilityMaps>,
    pub(crate) sensor: SensorSpec,
    pub(crate) want: EffectSet,
    pub(crate) forbid: EffectSet,
    /// The heightfield as specified, for analytic checks.
    pub heightfield: HeightSpec,
    /// The macro folds as specified, if any, for analytic checks.
    pub macro_shape: Option<MacroSpec>,
}

/// The sample's surface when it is not flat: total height (macro folds plus
/// mesostructure) and its gradient.
#[derive(Debug, Clone)]
pub(crate) struct Relief {
    pub height: Grid,
    pub grad_x: Grid,
    pub grad_y: Grid,
    /// Highest point; the reference plane of the BTF and MDF (Wang et al., §3).
    pub top: f64,
    /// The steepest slope, which bounds how far a ray can safely step.
    pub max_slope: f64,
    /// Albedo, gradient and height interleaved for shading, when their
    /// grids share a layout.
    pub texels: Option<SurfaceTexels>,
}

impl Scene {
    /// Names of the built-in scenes.
    pub fn builtin_names() -> Vec<&'static str> {
        BUILTIN.iter().map(|(n, _)| *n).collect()
    }

    /// A built-in scene by name, or a scene file by path. Built-in scenes
    /// are baked once per process and shared.
    pub fn load(name_or_path: &str) -> Result<Arc<Scene>, SceneError> {
        if let Some(i) = BUILTIN.iter().position(|(n, _)| *n == name_or_path) {
            static CACHE: OnceLock<Vec<OnceLock<Arc<Scene>>>> = OnceLock::new();
            let cache = CACHE.get_or_init(|| BUILTIN.iter().map(|_| OnceLock::new()).collect());
            if let Some(s) = cache[i].get() {
                return Ok(s.clone());
            }
            let (name, text) = BUILTIN[i];
            let scene = Arc::new(Scene::from_toml(text, &format!("scene `{name}`"), None)?);
            return Ok(cache[i].get_or_init(|| scene).clone());
        }
        let path = Path::new(name_or_path);
        if path.extension().is_some_and(|e| e == "toml") || path.exists() {
            let text = rigd_core::read::read_text(path, rigd_core::read::TEXT_LIMIT)?;
            return Ok(Arc::new(Scene::from_toml(
                &text,
                &path.display().to_string(),
                path.parent(),
            )?));
        }
        Err(SceneError::Unknown {
            name: name_or_path.to_string(),
            known: Scene::builtin_names().join(", "),
        })
    }

    /// Whether `name` is a built-in scene's.
    pub fn is_builtin(name: &str) -> bool {
        BUILTIN.iter().any(|(n, _)| *n == name)
    }

    /// A scene a client names (over the API): a built-in one, or one the
    /// operator configured (`configured`, e.g. the profile's `[sim] scene`,
    /// matched as it was written). Anything else is refused without being
    /// read, so a client's name never becomes a path.
    pub fn offered(name: &str, configured: &[&str]) -> Result<Arc<Scene>, SceneError> {
        if Scene::is_builtin(name) || configured.contains(&name) {
            return Scene::load(name);
        }
        let mut known: Vec<&str> = Scene::builtin_names();
        known.extend(configured.iter().filter(|c| !Scene::is_builtin(c)));
        Err(SceneError::NotOffered {
            name: name.chars().take(64).collect(),
            known: known.join(", "),
        })
    }

    /// Parses, validates and bakes a scene. `base_dir` resolves image paths.
    /// A syntax error is named by its line and what was expected, never by
    /// quoting the text (which may not be a scene file at all).
    pub fn from_toml(
        text: &str,
        origin: &str,
        base_dir: Option<&Path>,
    ) -> Result<Scene, SceneError> {
        let spec: SceneSpec =
            rigd_core::config::parse(text, origin, rigd_core::config::Format::Toml)
                .map_err(|e| invalid(origin, e.detail()))?;
        Scene::build(spec, origin, base_dir)
    }

    fn build(spec: SceneSpec, origin: &str, base_dir: Option<&Path>) -> Result<Scene, SceneError> {
        validate(&spec, origin)?;
        let (mut want, mut forbid) = (EffectSet::NONE, EffectSet::NONE);
        for (name, on) in &spec.effects {
            let e: Effect = name
                .parse()
                .map_err(|m: String| invalid(origin, format!("effects.{name}: {m}")))?;
            if *on {
                want.insert(e);
            } else {
                forbid.insert(e);
            }
        }
        let s = &spec.sample;
        let half = [s.size_mm[0] * 5e-4, s.size_mm[1] * 5e-4];
        let texel = 2.0 * half[0].max(half[1]) / s.resolution as f64;
        let nx = ((2.0 * half[0] / texel).round() as usize).max(2);
        let ny = ((2.0 * half[1] / texel).round() as usize).max(2);
        let load_image = |path: &str, key: &str| -> Result<Grid, SceneError> {
            let full = base_dir.map_or_else(|| PathBuf::from(path), |d| d.join(path));
            let img = read_grey_png(&full)
                .map_err(|m| invalid(origin, format!("{key}: {}: {m}", full.display())))?;
            Ok(img.resample(nx, ny, texel))
        };
        let height_image = match &s.heightfield {
            HeightSpec::Image { path, amplitude_mm } => {
                let mut g = load_image(path, "sample.heightfield.path")?;
                for v in &mut g.data {
                    *v *= (*amplitude_mm * 1e-3) as f32;
                }
                Some(g)
            }
            _ => None,
        };
        let albedo_image = match &s.albedo {
            AlbedoSpec::Image { path, .. } => Some(load_image(path, "sample.albedo.path")?),
            _ => None,
        };
        let meso = (!matches!(s.heightfield, HeightSpec::None)).then(|| {
            Grid::bake(nx, ny, texel, |x, y| {
                surface::height(&s.heightfield, height_image.as_ref(), x, y)
            })
        });
        let meso_max = meso.as_ref().map_or(0.0, Grid::max);
        let albedo = Grid::bake(nx, ny, texel, |x, y| {
            let rel = match &meso {
                Some(m) if meso_max > 0.0 => m.sample(x, y) / meso_max,
                _ => 1.0,
            };
            surface::albedo(&s.albedo, albedo_image.as_ref(), x, y, rel)
        });
        let colour = match &s.colour {
            Some(c) => {
                let colour = SampleColour::new(c).map_err(|m| invalid(origin, m))?;
                let peak = albedo.max() * colour.max_component();
                if peak > 1.0 + 1e-9 {
                    return Err(invalid(
                        origin,
                        format!(
                            "sample.colour: a channel's reflectance would reach {peak:.2} \
                             where the albedo is highest; lower the albedo or choose a \
                             less saturated colour"
                        ),
                    ));
                }
                Some(colour)
            }
            None => None,
        };
        let response = match spec.sensor.colour_response {
            Some(m) => Response::new(m).map_err(|m| invalid(origin, m))?,
            None => Response::default(),
        };
        // The standard plate around this sample, until a rig's profile
        // puts it on its own holder ([`Scene::on_holder`]).
        let holder = Holder::new(&rigd_core::holder::HolderSpec {
            sample_mm: s.size_mm,
            ..Default::default()
        });
        let relief = match (&meso, &s.macro_shape) {
            (None, None) => None,
            _ => {
                let height = Grid::bake(nx, ny, texel, |x, y| {
                    meso.as_ref().map_or(0.0, |m| m.sample(x, y))
                        + surface::macro_height(s.macro_shape.as_ref(), x, y)
                });
                let (grad_x, grad_y) = height.gradient();
                let max_slope = grad_x
                    .data
                    .iter()
                    .zip(&grad_y.data)
                    .map(|(a, b)| (*a as f64).hypot(*b as f64))
                    .fold(0.0, f64::max);
                let top = height.max();
                let texels = SurfaceTexels::new(&albedo, &grad_x, &grad_y, &height);
                (top > 0.0).then_some(Relief {
                    height,
                    grad_x,
                    grad_y,
                    top,
                    max_slope,
                    texels,
                })
            }
        };
        let specular = s.specular.as_ref().filter(|l| l.strength > 0.0).map(|l| {
            let a = l.tangent_deg.to_radians();
            Specular {
                strength: l.strength,
                alpha: l.roughness,
                tangent: [a.cos(), a.sin()],
            }
        });
        let visibility = s
            .macro_shape
            .as_ref()
            .map(|m| VisibilityMaps::compute(m, &m.visibility, half));
        Ok(Scene {
            name: spec.name.clone(),
            description: spec.description.clone(),
            sample_half: half,
            material_half: half,
            holder,
            relief,
            albedo,
            colour,
            response,
            specular,
            subsurface: s.subsurface_mm * 1e-3,
            visibility,
            sensor: spec.sensor.clone(),
            want,
            forbid,
            heightfield: s.heightfield.clone(),
            macro_shape: s.macro_shape.clone(),
        })
    }

    /// Scene `name_or_path` (as [`Scene::load`]) on the holder plate a
    /// rig's profile describes.
    pub fn load_on(
        name_or_path: &str,
        holder: &rigd_core::holder::HolderSpec,
    ) -> Result<Arc<Scene>, SceneError> {
        let plate = holder.holder().map_err(|e| SceneError::Invalid {
            origin: "the profile".into(),
            message: e.to_string(),
        })?;
        Scene::load(name_or_path)?.on_holder(plate)
    }

    /// This scene's sample on a rig's holder plate (its profile's
    /// `[holder]`), in the plate's sample window. Refused when the sample
    /// the scene describes is smaller than the window.
    pub fn on_holder(&self, holder: Holder) -> Result<Arc<Scene>, SceneError> {
        let [wx, wy] = holder.sample_half;
        let [sx, sy] = self.material_half;
        if wx > sx + 1e-9 || wy > sy + 1e-9 {
            return Err(SceneError::Invalid {
                origin: self.name.clone(),
                message: format!(
                    "the sample is {:.0} × {:.0} mm, smaller than the holder `{}`'s sample \
                     window of {:.0} × {:.0} mm (holder.sample_mm)",
                    2e3 * sx,
                    2e3 * sy,
                    holder.name,
                    2e3 * wx,
                    2e3 * wy
                ),
            });
        }
        let mut scene = self.clone();
        scene.sample_half = holder.sample_half;
        scene.holder = holder;
        Ok(Arc::new(scene))
    }

    /// Whether (x, y) lies on the sample (else on the holder).
    pub fn on_sample(&self, x: f64, y: f64) -> bool {
        x.abs() <= self.sample_half[0] && y.abs() <= self.sample_half[1]
    }

    /// Height of the surface at (x, y), metres: 0 on the holder.
    pub fn height(&self, x: f64, y: f64) -> f64 {
        match &self.relief {
            Some(r) if self.on_sample(x, y) => r.height.sample(x, y),
            _ => 0.0,
        }
    }

    /// The unit surface normal at (x, y).
    pub fn normal(&self, x: f64, y: f64) -> [f64; 3] {
        match &self.relief {
            Some(r) if self.on_sample(x, y) => {
                let (gx, gy) = (r.grad_x.sample(x, y), r.grad_y.sample(x, y));
                let len = (gx * gx + gy * gy + 1.0).sqrt();
                [-gx / len, -gy / len, 1.0 / len]
            }
            _ => [0.0, 0.0, 1.0],
        }
    }

    /// Diffuse reflectance at (x, y): the sample's texel or the holder's.
    pub fn albedo(&self, x: f64, y: f64) -> f64 {
        if self.on_sample(x, y) {
            self.albedo.sample(x, y)
        } else {
            self.holder.albedo(x, y)
        }
    }

    /// Diffuse reflectance at (x, y) in linear sRGB: the sample's albedo
    /// times its tint, or the holder's (a colour patch's where there is
    /// one).
    pub fn albedo_rgb(&self, x: f64, y: f64) -> [f64; 3] {
        if self.on_sample(x, y) {
            let a = self.albedo.sample(x, y);
            self.tint(x, y).map(|t| a * t)
        } else {
            self.holder.reflectance(x, y)
        }
    }

    /// The sample's tint at (x, y) (luminance 1).
    #[inline]
    pub(crate) fn tint(&self, x: f64, y: f64) -> [f64; 3] {
        self.colour
            .as_ref()
            .map_or(colour::NEUTRAL, |c| c.tint(x, y))
    }

    /// Whether the sample has a colour (else it is neutral grey).
    pub fn is_coloured(&self) -> bool {
        self.colour.is_some()
    }

    /// The top of the relief: the BTF's and MDF's reference plane.
    pub fn reference_height(&self) -> f64 {
        self.relief.as_ref().map_or(0.0, |r| r.top)
    }

    /// Effects this scene can ever show, before a frame narrows them.
    pub fn capabilities(&self) -> EffectSet {
        let mut s = EffectSet::NONE;
        let relief = self.relief.is_some();
        if relief {
            s.insert(Effect::Relief);
            s.insert(Effect::Interreflection);
            if self.visibility.is_none() {
                s.insert(Effect::Shadows);
            }
        }
        if self.specular.is_some() {
            s.insert(Effect::Specular);
        }
        if self.subsurface > 0.0 {
            s.insert(Effect::Subsurface);
        }
        if self.visibility.is_some() {
            s.insert(Effect::VisibilityMaps);
        }
        if self.sensor.vignetting > 0.0 {
            s.insert(Effect::Vignetting);
        }
        if self.sensor.read_noise_dn > 0.0 || self.sensor.electrons_per_dn > 0.0 {
            s.insert(Effect::Noise);
        }
        s.insert(Effect::Laser);
        s
    }
}

fn validate(spec: &SceneSpec, origin: &str) -> Result<(), SceneError> {
    let s = &spec.sample;
    let bad = |key: &str, msg: String| Err(invalid(origin, format!("{key}: {msg}")));
    for (i, v) in s.size_mm.iter().enumerate() {
        if !(v.is_finite() && *v > 0.0 && *v <= 100.0) {
            return bad(
                &format!("sample.size_mm[{i}]"),
                format!("expected 0 < size ≤ 100 mm, got {v}"),
            );
        }
    }
    if !(16..=4096).contains(&s.resolution) {
        return bad(
            "sample.resolution",
            format!("expected 16 ..= 4096 texels, got {}", s.resolution),
        );
    }
    let unit = |key: &str, v: f64| -> Result<(), SceneError> {
        if (0.0..=1.0).contains(&v) {
            Ok(())
        } else {
            bad(key, format!("expected a value in [0, 1], got {v}"))
        }
    };
    let length = |key: &str, v: f64, max: f64| -> Result<(), SceneError> {
        if v.is_finite() && v > 0.0 && v <= max {
            Ok(())
        } else {
            bad(key, format!("expected 0 < value ≤ {max} mm, got {v}"))
        }
    };
    match &s.albedo {
        AlbedoSpec::Uniform { value } => unit("sample.albedo.value", *value)?,
        AlbedoSpec::Checks {
            dark,
            light,
            check_mm,
            thread_mm,
        } => {
            unit("sample.albedo.dark", *dark)?;
            unit("sample.albedo.light", *light)?;
            length("sample.albedo.check_mm", *check_mm, 100.0)?;
            length("sample.albedo.thread_mm", *thread_mm, 100.0)?;
        }
        AlbedoSpec::Yarn {
            base,
            variation,
            valley_darkening,
        } => {
            unit("sample.albedo.base", *base)?;
            unit("sample.albedo.variation", *variation)?;
            unit("sample.albedo.valley_darkening", *valley_darkening)?;
        }
        AlbedoSpec::Mottled {
            base,
            variation,
            feature_mm,
        } => {
            unit("sample.albedo.base", *base)?;
            unit("sample.albedo.variation", *variation)?;
            length("sample.albedo.feature_mm", *feature_mm, 100.0)?;
        }
        AlbedoSpec::Image { min, max, .. } => {
            unit("sample.albedo.min", *min)?;
            unit("sample.albedo.max", *max)?;
        }
    }
    match &s.heightfield {
        HeightSpec::None => {}
        HeightSpec::Ridges {
            amplitude_mm,
            period_mm,
            ..
        } => {
            length("sample.heightfield.amplitude_mm", *amplitude_mm, 10.0)?;
            length("sample.heightfield.period_mm", *period_mm, 100.0)?;
        }
        HeightSpec::Knit {
            amplitude_mm,
            stitch_width_mm,
            stitch_height_mm,
            yarn_radius_mm,
        } => {
            length("sample.heightfield.amplitude_mm", *amplitude_mm, 10.0)?;
            length("sample.heightfield.stitch_width_mm", *stitch_width_mm, 50.0)?;
            length(
                "sample.heightfield.stitch_height_mm",
                *stitch_height_mm,
                50.0,
            )?;
            length("sample.heightfield.yarn_radius_mm", *yarn_radius_mm, 20.0)?;
        }
        HeightSpec::Cells {
            amplitude_mm,
            cell_mm,
        } => {
            length("sample.heightfield.amplitude_mm", *amplitude_mm, 10.0)?;
            length("sample.heightfield.cell_mm", *cell_mm, 100.0)?;
        }
        HeightSpec::Domes {
            radius_mm,
            height_mm,
            count,
        } => {
            length("sample.heightfield.radius_mm", *radius_mm, 50.0)?;
            length(
                "sample.heightfield.height_mm",
                *height_mm,
                radius_mm.min(20.0),
            )?;
            if !(1..=20).contains(count) {
                return bad(
                    "sample.heightfield.count",
                    format!("expected 1 ..= 20, got {count}"),
                );
            }
        }
        HeightSpec::Image { amplitude_mm, .. } => {
            length("sample.heightfield.amplitude_mm", *amplitude_mm, 10.0)?
        }
    }
    if let Some(l) = &s.specular {
        if !(0.0..=1.0).contains(&l.strength) {
            return bad(
                "sample.specular.strength",
                format!("expected [0, 1], got {}", l.strength),
            );
        }
        for (i, a) in l.roughness.iter().enumerate() {
            if !(a.is_finite() && *a >= 0.01 && *a <= 1.0) {
                return bad(
                    &format!("sample.specular.roughness[{i}]"),
                    format!("expected 0.01 ..= 1, got {a}"),
                );
            }
        }
    }
    if !(s.subsurface_mm.is_finite() && (0.0..=5.0).contains(&s.subsurface_mm)) {
        return bad(
            "sample.subsurface_mm",
            format!("expected 0 ..= 5 mm, got {}", s.subsurface_mm),
        );
    }
    if let Some(m) = &s.macro_shape {
        length("sample.macro.fold_height_mm", m.fold_height_mm, 50.0)?;
        length("sample.macro.wavelength_mm", m.wavelength_mm, 200.0)?;
        let v = &m.visibility;
        if !(2..=128).contains(&v.vertices)
            || !(1..=256).contains(&v.theta_cells)
            || !(1..=512).contains(&v.phi_cells)
        {
            return bad(
                "sample.macro.visibility",
                "expected 2..=128 vertices, 1..=256 theta cells, 1..=512 phi cells".into(),
            );
        }
    }
    if spec.holder.is_some() {
        return bad(
            "holder",
            "the holder plate is the rig's: describe it in the profile's [holder] table \
             (docs/holder.md), not in a scene"
                .into(),
        );
    }
    let sn = &spec.sensor;
    if !(sn.read_noise_dn.is_finite() && sn.read_noise_dn >= 0.0) {
        return bad(
            "sensor.read_noise_dn",
            format!("expected ≥ 0, got {}", sn.read_noise_dn),
        );
    }
    if !(sn.electrons_per_dn.is_finite() && sn.electrons_per_dn >= 0.0) {
        return bad(
            "sensor.electrons_per_dn",
            format!("expected ≥ 0, got {}", sn.electrons_per_dn),
        );
    }
    unit("sensor.vignetting", sn.vignetting)?;
    Ok(())
}

/// A greyscale PNG as values in [0, 1].
fn read_grey_png(path: &Path) -> Result<Grid, String> {
    // The path is in the message already: only the reason is kept.
    let bytes = rigd_core::read::read_bounded(path, rigd_core::read::IMAGE_LIMIT)
        .map_err(|e| e.reason.to_string())?;
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().map_err(|e| e.to_string())?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
    let channels = info.color_type.samples();
    let (w, h) = (info.width as usize, info.height as usize);
    let mut data = Vec::with_capacity(w * h);
    // Rows run top to bottom in the file; the grid's y runs upwards.
    for j in (0..h).rev() {
        for i in 0..w {
            data.push(buf[(j * w + i) * channels] as f32 / 255.0);
        }
    }
    Ok(Grid {
        nx: w,
        ny: h,
        texel: 1.0,
        data,
    })
}

impl Grid {
    /// This image stretched over an `nx × ny` grid of `texel` metres.
    fn resample(&self, nx: usize, ny: usize, texel: f64) -> Grid {
        let (sx, sy) = (self.nx as f64 / nx as f64, self.ny as f64 / ny as f64);
        Grid::bake(nx, ny, texel, |x, y| {
            let i = x / texel + nx as f64 / 2.0;
            let j = y / texel + ny as f64 / 2.0;
            self.sample(
                (i * sx) - self.nx as f64 / 2.0,
                (j * sy) - self.ny as f64 / 2.0,
            )
        })
    }
}
