//! A run's processing as a list of steps with their options: what the
//! daemon's process jobs (`POST /api/v1/runs/{id}/process`) run, one step
//! after another, each exactly as its `rigd process` command runs it.
//!
//! Every field has a default, so `{}` is a complete request: the steps
//! follow from the run (a laser plan: `mdf`; one view only: photometric
//! stereo; otherwise `rectify` then `btf`), and the rectification sizes are
//! those of the README's demo (512² resampled, 128² stored).

use std::path::Path;

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::frames::RunFrames;
use super::mdf::{MdfConfig, PlaneModel};
use super::rectify::{RectifyConfig, TextureBits};
use super::ProcessError;

/// One processing step.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize, ToSchema,
)]
#[serde(rename_all = "kebab-case")]
pub enum ProcessStep {
    /// Register every frame and resample it to a frontal normtexture
    /// (`rigd process rectify`).
    Rectify,
    /// Compress the BTF per view slot (`rigd process btf`); needs `rectify`.
    Btf,
    /// Fit the reflectance models per texel (`rigd process fit`); needs
    /// `rectify`.
    Fit,
    /// The mesostructure distance function of a laser run (`rigd process mdf`).
    Mdf,
    /// Photometric stereo of a run whose camera looks down on the sample
    /// (`rigd process photometric-stereo RUN`).
    PhotometricStereo,
}

impl ProcessStep {
    /// The step's name, as in the API and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ProcessStep::Rectify => "rectify",
            ProcessStep::Btf => "btf",
            ProcessStep::Fit => "fit",
            ProcessStep::Mdf => "mdf",
            ProcessStep::PhotometricStereo => "photometric-stereo",
        }
    }

    /// Parses a step's name.
    pub fn parse(s: &str) -> Result<ProcessStep, String> {
        [
            ProcessStep::Rectify,
            ProcessStep::Btf,
            ProcessStep::Fit,
            ProcessStep::Mdf,
            ProcessStep::PhotometricStereo,
        ]
        .into_iter()
        .find(|step| step.name() == s.trim())
        .ok_or_else(|| {
            format!("unknown step `{s}`: expected rectify, btf, fit, mdf or photometric-stereo")
        })
    }

    /// Reads the normtextures of `rectify`.
    pub fn needs_normtextures(self) -> bool {
        matches!(self, ProcessStep::Btf | ProcessStep::Fit)
    }
}

/// Options of the `rectify` step (`rigd process rectify`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct RectifyOptions {
    /// Side of the frontal normtexture each frame is resampled to first.
    pub size: usize,
    /// Side of the stored textures.
    #[serde(rename = "final")]
    pub final_size: usize,
    /// Fraction of the normtexture kept around its centre, (0, 1].
    pub roi: f64,
    /// `top`, a shift `0` … `8`, `float` or `half` (see `rigd process
    /// rectify --help`).
    pub bits: String,
    /// Edge blend in final texels (0 = none); absent or null: a quarter of
    /// `final`, the band that removes the tile seam in the viewer.
    pub blend: Option<usize>,
}

impl Default for RectifyOptions {
    fn default() -> Self {
        RectifyOptions {
            size: 512,
            final_size: 128,
            roi: 1.0,
            bits: "top".into(),
            blend: None,
        }
    }
}

/// The default edge blend is `final / DEFAULT_BLEND_DIVISOR` texels. The
/// viewer tiles the textures 2 × 2 on its flat sample: without a blend the
/// tiles meet in a step five to seven times the texture's own neighbour
/// steps; an eighth brings it level with them, a quarter to 0.74–0.86 of
/// them, and a half is worse again, its wide mix flattening the texture
/// (`docs/processing.md`, "Tiling without a seam").
pub const DEFAULT_BLEND_DIVISOR: usize = 4;

impl RectifyOptions {
    /// The rectification's configuration, or why these options are wrong
    /// ([`RectifyConfig::check`]; the error names the option as the
    /// command line does, without its `--`).
    pub fn config(&self) -> Result<RectifyConfig, String> {
        let bits = TextureBits::parse(&self.bits)?;
        let cfg = RectifyConfig {
            size: self.size,
            roi: self.roi,
            final_size: self.final_size,
            blend: self
                .blend
                .unwrap_or(self.final_size / DEFAULT_BLEND_DIVISOR),
            bits,
        };
        cfg.check()?;
        Ok(cfg)
    }
}

/// Options of the `btf` step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct BtfOptions {
    /// Components kept per view slot, 1 … 256.
    pub components: usize,
}

impl Default for BtfOptions {
    fn default() -> Self {
        BtfOptions { components: 16 }
    }
}

impl BtfOptions {
    /// Why these options are wrong, if they are.
    pub fn check(&self) -> Result<(), String> {
        if (1..=256).contains(&self.components) {
            Ok(())
        } else {
            Err(format!("components {}: expected 1 … 256", self.components))
        }
    }
}

/// Options of the `fit` step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct FitOptions {
    /// Lobes of the non-linear model, 1 … 8.
    pub lobes: usize,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions { lobes: 2 }
    }
}

impl FitOptions {
    /// Why these options are wrong, if they are.
    pub fn check(&self) -> Result<(), String> {
        if (1..=8).contains(&self.lobes) {
            Ok(())
        } else {
            Err(format!("lobes {}: expected 1 … 8", self.lobes))
        }
    }
}

/// Options of the `mdf` step (`rigd process mdf`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct MdfOptions {
    /// `calibrated` or `emitter`.
    #[schema(value_type = String)]
    pub planes: PlaneModel,
    /// Use this many of the run's source positions [default: all].
    pub sources: Option<usize>,
    /// Grey level (0–1) a pixel's brightest frame must exceed.
    pub threshold: f64,
    /// Grey level (0–1) of the strip in the reference region.
    pub line_threshold: f64,
    /// Gaussian filter before the strip search, pixels (0 … 20).
    pub sigma: f64,
}

impl Default for MdfOptions {
    fn default() -> Self {
        let d = MdfConfig::default();
        MdfOptions {
            planes: d.planes,
            sources: d.sources,
            threshold: d.threshold,
            line_threshold: d.line_threshold,
            sigma: d.sigma_px,
        }
    }
}

impl MdfOptions {
    /// Why these options are wrong, if they are ([`MdfConfig::check`]).
    pub fn check(&self) -> Result<(), String> {
        self.config().check()
    }

    /// The MDF's settings.
    pub fn config(&self) -> MdfConfig {
        MdfConfig {
            sigma_px: self.sigma,
            threshold: self.threshold,
            line_threshold: self.line_threshold,
            planes: self.planes,
            sources: self.sources,
        }
    }
}

/// Options of the `photometric-stereo` step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct PsOptions {
    /// Reject shadowed and specular samples per pixel.
    pub robust: bool,
    /// Refuse light sets whose matrix has a larger condition number.
    pub max_condition: f64,
}

impl Default for PsOptions {
    fn default() -> Self {
        PsOptions {
            robust: false,
            max_condition: rigd_process::photometric_stereo::DEFAULT_MAX_CONDITION,
        }
    }
}

impl PsOptions {
    /// Why these options are wrong, if they are.
    pub fn check(&self) -> Result<(), String> {
        if self.max_condition.is_finite() && self.max_condition >= 1.0 {
            Ok(())
        } else {
            Err(format!(
                "max-condition {}: expected a finite number of at least 1",
                self.max_condition
            ))
        }
    }
}

/// What to do with a run: the steps and each step's options.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, ToSchema)]
#[serde(default, deny_unknown_fields)]
#[schema(example = json!({"steps": ["rectify", "btf"], "rectify": {"size": 128, "final": 32}, "btf": {"components": 4}}))]
pub struct ProcessOptions {
    /// The steps, run in the order rectify, btf, fit, mdf,
    /// photometric-stereo whatever order they are given in. Empty: chosen
    /// from the run (see [`default_steps`]).
    pub steps: Vec<ProcessStep>,
    /// Options of `rectify`.
    pub rectify: RectifyOptions,
    /// Options of `btf`.
    pub btf: BtfOptions,
    /// Options of `fit`.
    pub fit: FitOptions,
    /// Options of `mdf`.
    pub mdf: MdfOptions,
    /// Options of `photometric-stereo`.
    pub photometric_stereo: PsOptions,
}

/// What the choice and the checks of a run's steps depend on: read from
/// its frames once captured, or from its plan before.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RunFacts {
    /// A laser plan (Wang et al., §3.2).
    pub laser: bool,
    /// Every frame has the same view (a camera looking down).
    pub one_view: bool,
    /// Frames (or, from the plan, images planned).
    pub frames: usize,
    /// The run's normtextures are on disk already.
    pub rectified: bool,
}

fn same_view(a: rigd_core::geometry::Direction, b: rigd_core::geometry::Direction) -> bool {
    let (a, b) = (a.canonical(), b.canonical());
    (a.theta_deg - b.theta_deg).abs() < 1e-6 && (a.phi_deg - b.phi_deg).abs() < 1e-6
}

impl RunFacts {
    /// The facts of a captured run.
    pub fn of_run(run: &RunFrames) -> RunFacts {
        RunFacts {
            laser: run.meta.plan.laser.is_some(),
            one_view: run
                .entries
                .windows(2)
                .all(|w| same_view(w[0].view, w[1].view)),
            frames: run.entries.len(),
            rectified: crate::store::processed::normtextures_dir(&run.root)
                .join(crate::store::processed::NORMTEXTURE_INDEX)
                .is_file(),
        }
    }

    /// The facts of a run still to be captured with `plan`.
    pub fn of_plan(plan: &crate::plan::Plan) -> RunFacts {
        RunFacts {
            laser: plan.laser.is_some(),
            one_view: plan
                .pairs
                .windows(2)
                .all(|w| same_view(w[0].view, w[1].view)),
            frames: plan.pairs.len(),
            rectified: false,
        }
    }
}

/// The steps a run gets when none are asked for: `mdf` for a laser plan,
/// `photometric-stereo` when every frame has the same view (a camera
/// looking down, as on the VirTex rig), otherwise `rectify` and `btf`.
pub fn default_steps(facts: &RunFacts) -> Vec<ProcessStep> {
    if facts.laser {
        vec![ProcessStep::Mdf]
    } else if facts.one_view && facts.frames >= 3 {
        vec![ProcessStep::PhotometricStereo]
    } else {
        vec![ProcessStep::Rectify, ProcessStep::Btf]
    }
}

/// Why `rectify` is refused for frames of `size`: below
/// [`MIN_REGISTRABLE_FRAME`](crate::model::profile::MIN_REGISTRABLE_FRAME)
/// the holder's markers are not found at the 75° view ring.
pub fn check_frame_size(size: [u32; 2]) -> Result<(), String> {
    let [w, h] = size;
    let [min_w, min_h] = crate::model::profile::MIN_REGISTRABLE_FRAME;
    if w < min_w || h < min_h {
        return Err(format!(
            "frames of {w}×{h} are too small to process: below {min_w}×{min_h} the holder's markers are not found at the 75° view ring, so most frames would be registered from the pose alone; capture at {min_w}×{min_h} or more, or run `rigd process rectify` by hand to accept pose-only registration"
        ));
    }
    Ok(())
}

impl ProcessOptions {
    /// The options with the steps resolved for a run (defaults filled in,
    /// sorted into their running order), or why they cannot run on it.
    pub fn resolve(mut self, facts: &RunFacts) -> Result<ProcessOptions, String> {
        if self.steps.is_empty() {
            self.steps = default_steps(facts);
        }
        let asked = self.steps.len();
        self.steps.sort();
        self.steps.dedup();
        if self.steps.len() != asked {
            return Err("a step is named twice".into());
        }
        if self.steps.contains(&ProcessStep::Rectify) {
            self.rectify.config().map_err(|e| format!("rectify.{e}"))?;
        }
        for step in &self.steps {
            if step.needs_normtextures()
                && !facts.rectified
                && !self.steps.contains(&ProcessStep::Rectify)
            {
                return Err(format!(
                    "{} needs the run's normtextures: add the step `rectify`",
                    step.name()
                ));
            }
        }
        self.btf.check().map_err(|e| format!("btf.{e}"))?;
        self.fit.check().map_err(|e| format!("fit.{e}"))?;
        self.mdf.check().map_err(|e| format!("mdf.{e}"))?;
        if self.steps.contains(&ProcessStep::Mdf) && !facts.laser {
            return Err("mdf needs a run of a laser plan".into());
        }
        self.photometric_stereo
            .check()
            .map_err(|e| format!("photometric_stereo.{e}"))?;
        if facts.frames == 0 {
            return Err("the run has no frames".into());
        }
        Ok(self)
    }
}

/// Niceness of the processing threads (Linux: per thread), so a capture's
/// device calls are scheduled before them.
const NICENESS: i32 = 10;
/// Frames a stream registers between two looks at the journal.
pub const STREAM_BATCH: usize = 32;
/// How long a stream that found nothing new waits before it looks again.
pub const STREAM_POLL: std::time::Duration = std::time::Duration::from_secs(1);

/// Lowers the calling thread's priority to [`NICENESS`].
pub fn lower_priority() {
    // SAFETY: setpriority on the calling thread (who = 0); a failure only
    // leaves the thread at normal priority.
    #[cfg(target_os = "linux")]
    unsafe {
        libc::setpriority(libc::PRIO_PROCESS, 0, NICENESS);
    }
}

/// A rayon pool of one thread per core, each at [`NICENESS`]: processing
/// beside a capture takes the cores the capture leaves idle.
pub fn background_pool(name: &'static str) -> Result<rayon::ThreadPool, String> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(move |i| format!("{name}-{i}"))
        .start_handler(|_| lower_priority())
        .build()
        .map_err(|e| e.to_string())
}

/// Processing during a capture: the `rectify` step's first pass of each
/// frame as it is journaled ([`super::rectify::RectifyStream`]) and, when
/// the job has `btf`, each view slot's compression as soon as every light
/// of the slot has its texture ([`super::btf::compress_slot_ahead`]). The
/// steps after the capture take both as they are.
pub struct CaptureStream {
    root: std::path::PathBuf,
    rectify: super::rectify::RectifyStream,
    btf_components: Option<usize>,
    ahead: std::collections::BTreeSet<usize>,
}

/// Where a [`CaptureStream`] stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CaptureProgress {
    /// The frames' side.
    pub frames: super::rectify::StreamProgress,
    /// View slots compressed so far.
    pub slots_ahead: usize,
}

impl CaptureStream {
    /// The stream of `opts` over the run at `root`; None when it has no
    /// `rectify` step.
    pub fn new(root: &Path, opts: &ProcessOptions) -> Result<Option<CaptureStream>, ProcessError> {
        if !opts.steps.contains(&ProcessStep::Rectify) {
            return Ok(None);
        }
        let cfg = opts.rectify.config().map_err(ProcessError::Invalid)?;
        Ok(Some(CaptureStream {
            root: root.to_path_buf(),
            rectify: super::rectify::RectifyStream::new(root, cfg)?,
            btf_components: opts
                .steps
                .contains(&ProcessStep::Btf)
                .then_some(opts.btf.components),
            ahead: Default::default(),
        }))
    }

    /// The run's directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Registers up to [`STREAM_BATCH`] newly journaled frames, then
    /// compresses the view slots they completed, on the current rayon
    /// pool.
    pub fn advance(&mut self) -> Result<CaptureProgress, ProcessError> {
        use rayon::prelude::*;
        let frames = self.rectify.catch_up(STREAM_BATCH)?;
        if let Some(components) = self.btf_components {
            let ready: Vec<usize> = self
                .rectify
                .complete_slots()
                .into_iter()
                .filter(|s| !self.ahead.contains(s))
                .collect();
            if !ready.is_empty() {
                let index = self.rectify.partial_index();
                ready.par_iter().for_each(|&slot| {
                    if super::btf::slot_ahead_is_current(&self.root, &index, slot, components) {
                        return;
                    }
                    if let Err(e) =
                        super::btf::compress_slot_ahead(&self.root, &index, slot, components)
                    {
                        // Not tried again: `btf` compresses it after the capture.
                        tracing::warn!("compressing view slot {slot} during the capture: {e}");
                    }
                });
                self.ahead.extend(ready);
            }
        }
        Ok(CaptureProgress {
            frames,
            slots_ahead: self.ahead.len(),
        })
    }
}

/// Progress of a step: `(done, total)` in the step's own units (frames,
/// view slots, sweeps, rows).
pub type StepProgress<'a> = &'a (dyn Fn(usize, usize) + Sync);

/// Runs one step on the run at `root`, as its `rigd process` command does;
/// returns a one-line summary of what it wrote.
pub fn run_step(
    root: &Path,
    step: ProcessStep,
    opts: &ProcessOptions,
    progress: StepProgress<'_>,
) -> Result<String, ProcessError> {
    match step {
        ProcessStep::Rectify => {
            let cfg = opts.rectify.config().map_err(ProcessError::Invalid)?;
            let run = RunFrames::open(root)?;
            let index = super::rectify::rectify_run(&run, &cfg, progress)?;
            let by_method = index
                .summary
                .as_ref()
                .map(|s| {
                    s.frames_by_method
                        .iter()
                        .map(|(m, n)| format!("{n} {m}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                })
                .unwrap_or_default();
            let resumed = index.summary.as_ref().map_or(0, |s| s.resumed_frames);
            let damaged = index
                .summary
                .as_ref()
                .filter(|s| s.frames_damaged > 0)
                .map(|s| {
                    format!(
                        "; {} damaged (failed the SHA-256 check, filled from their slot's nearest lights)",
                        crate::store::image_list(&s.damaged)
                    )
                })
                .unwrap_or_default();
            Ok(format!(
                "{} frames into {}² textures ({by_method}){damaged}{}",
                index.frames.len(),
                index.size,
                if resumed > 0 {
                    format!(
                        "; {resumed} registered before (during the capture, as cluster tasks or by an interrupted run)"
                    )
                } else {
                    String::new()
                }
            ))
        }
        ProcessStep::Btf => {
            let r = super::btf::btf_run(root, opts.btf.components, progress)?;
            Ok(format!(
                "{} view slots × {} lights, C = {}: {:.1} MB{}",
                r.slots,
                r.lights,
                r.components,
                r.bytes as f64 / 1e6,
                if r.slots_ahead > 0 {
                    format!(
                        "; {} slots compressed ahead (during the capture or as cluster tasks)",
                        r.slots_ahead
                    )
                } else {
                    String::new()
                }
            ))
        }
        ProcessStep::Fit => {
            let rows = super::fit::fit_run(root, opts.fit.lobes, progress)?;
            Ok(rows
                .iter()
                .map(|r| format!("{}: RMS {:.5}", r.method, r.rms_error))
                .collect::<Vec<_>>()
                .join(", "))
        }
        ProcessStep::Mdf => {
            let run = RunFrames::open(root)?;
            let r = super::mdf::mdf_run(&run, &opts.mdf.config(), progress)?;
            Ok(format!(
                "{} views{}",
                r.views.len(),
                r.mean_error_mm
                    .map(|e| format!(", mean depth error {e:.3} mm"))
                    .unwrap_or_default()
            ))
        }
        ProcessStep::PhotometricStereo => {
            use rigd_process::photometric_stereo as ps;
            let run = RunFrames::open(root)?;
            let dataset = super::ps::ps_dataset_from_run(&run)?;
            let ps_opts = ps::PsOptions {
                robust: opts.photometric_stereo.robust,
                max_condition: opts.photometric_stereo.max_condition,
                progress: Some(progress),
                ..Default::default()
            };
            let result =
                ps::solve(&dataset, &ps_opts).map_err(|e| ProcessError::Invalid(e.to_string()))?;
            let out = crate::store::processed::ps_dir(root);
            ps::write_outputs(&result, &out).map_err(|e| ProcessError::Frame {
                path: out.clone(),
                message: e.to_string(),
            })?;
            let solved = result.valid.iter().filter(|v| **v).count();
            Ok(format!(
                "{solved} of {} pixels solved, mean residual {:.4}",
                result.width * result.height,
                result.report.mean_residual
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steps_parse_and_name_each_other() {
        for s in ["rectify", "btf", "fit", "mdf", "photometric-stereo"] {
            assert_eq!(ProcessStep::parse(s).map(ProcessStep::name), Ok(s));
        }
        assert!(ProcessStep::parse("sharpen").is_err());
    }

    #[test]
    fn an_empty_request_is_complete_and_bad_fields_are_refused() {
        let o: ProcessOptions = serde_json::from_str("{}").expect("defaults");
        assert_eq!(o.rectify.size, 512);
        assert_eq!(o.btf.components, 16);
        assert!(o.rectify.config().is_ok());
        let o: ProcessOptions =
            serde_json::from_str(r#"{"steps": ["btf", "rectify"], "rectify": {"final": 64}}"#)
                .expect("partial options");
        assert_eq!(o.rectify.final_size, 64);
        assert_eq!(o.rectify.size, 512);
        assert!(serde_json::from_str::<ProcessOptions>(r#"{"rectify": {"sise": 3}}"#).is_err());
        assert!(serde_json::from_str::<ProcessOptions>(r#"{"steps": ["sharpen"]}"#).is_err());
        let bad = RectifyOptions {
            blend: Some(128),
            ..Default::default()
        };
        assert!(bad.config().is_err());
        let bad = RectifyOptions {
            bits: "9".into(),
            ..Default::default()
        };
        assert!(bad.config().is_err());
    }

    /// The daemon's jobs refuse what `rigd process` refuses, with the same
    /// words: the option and its range.
    #[test]
    fn every_numeric_option_has_its_range() {
        let facts = RunFacts {
            laser: true,
            one_view: false,
            frames: 9,
            rectified: false,
        };
        let refused = |json: &str| {
            serde_json::from_str::<ProcessOptions>(json)
                .expect("parses")
                .resolve(&facts)
                .expect_err(json)
        };
        for (json, says) in [
            (
                r#"{"steps": ["rectify"], "rectify": {"size": 1}}"#,
                "rectify.size 1",
            ),
            (
                r#"{"steps": ["rectify"], "rectify": {"size": 256, "final": 300}}"#,
                "rectify.final 300: expected at most the size 256",
            ),
            (
                r#"{"steps": ["rectify"], "rectify": {"final": 0}}"#,
                "rectify.final 0",
            ),
            (r#"{"mdf": {"threshold": 2.0}}"#, "mdf.threshold 2"),
            (r#"{"mdf": {"sources": 0}}"#, "mdf.sources 0"),
            (r#"{"btf": {"components": 0}}"#, "btf.components 0"),
            (r#"{"fit": {"lobes": 9}}"#, "fit.lobes 9"),
            (
                r#"{"photometric_stereo": {"max_condition": 0.5}}"#,
                "photometric_stereo.max-condition 0.5",
            ),
        ] {
            let e = refused(json);
            assert!(e.contains(says), "{json}: {e}");
        }
    }
}
