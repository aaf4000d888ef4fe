//! `rigd process`: turn a run's frames into results (photometric stereo,
//! rectification, BTF compression, reflectance fits, the MDF, the reference
//! render).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};

use super::exit::bad_input;
use super::progress::progress_line;

/// Runs a `rigd process` command.
pub fn run(cmd: ProcessCmd) -> Result<ExitCode> {
    match cmd {
        ProcessCmd::PhotometricStereo(args) => photometric_stereo(args)?,
        ProcessCmd::Rectify(args) => rectify(args)?,
        ProcessCmd::Colour(args) => colour(args)?,
        ProcessCmd::Btf(args) => btf(args)?,
        ProcessCmd::Fit(args) => fit(args)?,
        ProcessCmd::Mdf(args) => mdf(args)?,
        ProcessCmd::MdfTexture(args) => mdf_texture(args)?,
        ProcessCmd::Render(args) => relight(args)?,
        ProcessCmd::Part(args) => part(args)?,
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(Subcommand)]
pub enum ProcessCmd {
    /// Photometric stereo (Spence et al., §2): albedo, normals, gradients p and q
    /// and a Frankot–Chellappa height map, from a VirTex run directory or from
    /// a folder of images with a light table. Writes normals.npy (H×W×3
    /// float32, unit, z towards the camera), albedo.npy, height.npy, p.npy,
    /// q.npy, PNG renderings of each and report.json into --out.
    PhotometricStereo(PsArgs),
    /// Register every frame of a run by its holder markers (Sattler et al., §3.2)
    /// and resample the sample to frontal textures: RUN/processed/
    /// normtextures/ with index.json (per frame: the marker residual in
    /// pixels, the markers used and rejected). Frames whose markers cannot be
    /// found are named in the error and the index.
    Rectify(RectifyArgs),
    /// White balance and a 3×3 colour correction of a colour camera, from
    /// the reference patches on the holder (white, red, green, grey, blue,
    /// yellow) in up to 8 of the run's most frontal frames, registered by
    /// their markers, averaged.
    /// Prints and keeps in RUN/processed/colour.json the gains, the matrix
    /// and each patch's colour difference ΔE*ab (CIE 1976) after
    /// correction, with the matrix fitted with and without that patch.
    Colour(ColourArgs),
    /// Compress a rectified run's BTF: a PCA per view slot (Sattler et al., §4.1)
    /// into RUN/processed/btf/ (btf.json + slot files), with the eigenvalue
    /// decay and the RMS error for C = 1 … 32 per slot in report.json.
    Btf(BtfArgs),
    /// Fit every texel of every view slot of a rectified run with the
    /// K-lobe reflectance model by Levenberg–Marquardt and with a PTM
    /// (Meseth et al., §4), and print the average error table (Meseth et al. Table 1);
    /// also RUN/processed/fit/report.json.
    Fit(FitArgs),
    /// The mesostructure distance function of a laser run (Wang et al., §3.2):
    /// each source's laser plane calibrated from the strip on the turntable
    /// and on the plate, the strip found per frame in the reference region
    /// outside the sample's box, space-time triangulation per pixel, and
    /// the sources of each view merged with Wang et al.'s weights. Writes
    /// RUN/processed/mdf/<view>.npy (float32 mm, −1 = none), an 8-bit
    /// .png per view and report.json; prints the depth error against the
    /// scene for simulated runs.
    Mdf(MdfArgs),
    /// A laser run's MDF resampled into a BTF run's texture space (Wang et
    /// al., §4): one layer per measured view, depths below the
    /// mesostructure's top plane, in RUN/processed/mdf-texture/, where the
    /// viewer's MDF silhouettes and shadows and `rigd process render
    /// --silhouettes mdf` read it.
    MdfTexture(MdfTextureArgs),
    /// The reference render of a processed run's BTF on a mesh, exactly as
    /// the viewer (`/viewer/RUN`) draws it: the four nearest view slots, the
    /// light interpolated from the four nearest measured lights, the smooth
    /// shadow boundary of Sattler et al. eq. 6; with `--silhouettes mdf`
    /// and `--shadows mdf` the mesostructure's silhouettes and shadows from
    /// the run's MDF texture (Wang et al., §4). Writes an 8-bit RGB PNG.
    Render(RelightArgs),
    /// One part of a step, as a task of the Slurm job array that
    /// `--executor slurm` submits runs it: frames of `rectify`, a view
    /// slot of `btf` or `fit`, or a whole `mdf` or `photometric-stereo`.
    /// It keeps its result where the step finds it and marks the part done
    /// in RUN/processed/slurm/STEP/done/. Not needed by hand.
    Part(PartArgs),
}

/// Where the steps run: this machine or a Slurm cluster.
#[derive(Args, Clone)]
pub struct ExecutorArgs {
    /// local: on this machine's cores; slurm: as a Slurm job array per step
    /// on the shared filesystem (docs/scaling.md), with sbatch, squeue,
    /// sacct and scancel on the PATH.
    #[arg(long, value_enum, default_value_t = ExecutorArg::Local)]
    pub executor: ExecutorArg,
    /// Slurm partition [default: the cluster's default].
    #[arg(long)]
    pub partition: Option<String>,
    /// Slurm account [default: yours].
    #[arg(long)]
    pub account: Option<String>,
    /// More sbatch options, split as a shell would, e.g.
    /// "--time=00:30:00 --mem=4G --cpus-per-task=2".
    #[arg(long, default_value = "", allow_hyphen_values = true)]
    pub slurm_opts: String,
    /// A folder the cluster's nodes mount at the same path; the run must be
    /// inside one. Repeatable.
    #[arg(long = "shared-path", value_name = "DIR")]
    pub shared_paths: Vec<PathBuf>,
    /// Frames per Slurm task of rectify.
    #[arg(long, default_value_t = rigd::postprocess::slurm::SlurmConfig::default().frames_per_task)]
    pub frames_per_task: usize,
    /// View slots per Slurm task of btf and fit.
    #[arg(long, default_value_t = rigd::postprocess::slurm::SlurmConfig::default().slots_per_task)]
    pub slots_per_task: usize,
    /// Times a failed Slurm task is submitted again.
    #[arg(long, default_value_t = rigd::postprocess::slurm::SlurmConfig::default().max_retries)]
    pub max_retries: u32,
    /// The rigd the Slurm tasks run, at a path every node sees [default:
    /// this executable].
    #[arg(long, value_name = "PATH")]
    pub slurm_rigd: Option<PathBuf>,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ExecutorArg {
    Local,
    Slurm,
}

impl ExecutorArgs {
    /// The executor's configuration; Slurm-only options without `--executor
    /// slurm` are refused rather than ignored.
    fn config(&self) -> Result<rigd::postprocess::executor::ProcessingConfig> {
        use rigd::postprocess::executor::{ExecutorKind, ProcessingConfig};
        use rigd::postprocess::slurm::SlurmConfig;
        let slurm_only = self.partition.is_some()
            || self.account.is_some()
            || !self.slurm_opts.is_empty()
            || !self.shared_paths.is_empty()
            || self.slurm_rigd.is_some();
        if self.executor == ExecutorArg::Local && slurm_only {
            return Err(bad_input(
                "--partition, --account, --slurm-opts, --shared-path and --slurm-rigd need --executor slurm",
            ));
        }
        Ok(ProcessingConfig {
            executor: match self.executor {
                ExecutorArg::Local => ExecutorKind::Local,
                ExecutorArg::Slurm => ExecutorKind::Slurm,
            },
            slurm: SlurmConfig {
                partition: self.partition.clone(),
                account: self.account.clone(),
                sbatch_options: self.slurm_opts.clone(),
                shared_paths: self.shared_paths.clone(),
                frames_per_task: self.frames_per_task,
                slots_per_task: self.slots_per_task,
                max_retries: self.max_retries,
                rigd: self.slurm_rigd.clone(),
                ..SlurmConfig::default()
            },
        })
    }

    fn is_slurm(&self) -> bool {
        self.executor == ExecutorArg::Slurm
    }
}

/// Runs `step` on Slurm as `--executor slurm` asks: the job arrays, then
/// the join here. Ctrl-C cancels the jobs (`scancel`).
fn on_slurm(
    exec: &ExecutorArgs,
    run: &std::path::Path,
    step: rigd::postprocess::pipeline::ProcessStep,
    opts: &rigd::postprocess::pipeline::ProcessOptions,
) -> Result<String> {
    let config = exec.config()?;
    config.check(run)?;
    let interrupted = super::signal::flag_on_signal();
    let cancel = || interrupted.load(std::sync::atomic::Ordering::SeqCst);
    let notes = |note: &str| eprintln!("{note}");
    let progress = progress_line("Slurm tasks done, then joined");
    config
        .run_step(run, step, opts, &progress, &notes, &cancel)
        .map_err(anyhow::Error::new)
}

#[derive(Args)]
pub struct PartArgs {
    /// The run directory (on the shared filesystem).
    pub run: PathBuf,
    /// The step: rectify, btf, fit, mdf or photometric-stereo.
    #[arg(long, value_parser = rigd::postprocess::pipeline::ProcessStep::parse)]
    pub step: rigd::postprocess::pipeline::ProcessStep,
    /// This task's part, 0 … parts − 1 (Slurm's SLURM_ARRAY_TASK_ID).
    #[arg(long)]
    pub part: usize,
    /// Parts the step was split into when it was submitted.
    #[arg(long)]
    pub parts: usize,
    /// Frames per part of rectify, as submitted.
    #[arg(long, default_value_t = rigd::postprocess::slurm::SlurmConfig::default().frames_per_task)]
    pub frames_per_part: usize,
    /// View slots per part of btf and fit, as submitted.
    #[arg(long, default_value_t = rigd::postprocess::slurm::SlurmConfig::default().slots_per_task)]
    pub slots_per_part: usize,
    /// The step's options (the JSON of the daemon's process request).
    #[arg(long)]
    pub options: PathBuf,
}

#[derive(Args)]
pub struct PsArgs {
    /// A run directory whose camera looks down on the sample (VirTex).
    #[arg(conflicts_with_all = ["images", "lights", "names", "intensities"])]
    pub run: Option<PathBuf>,
    /// Folder of PNG images (8/16-bit, grey or RGB), one per light.
    #[arg(long, requires = "lights")]
    pub images: Option<PathBuf>,
    /// Light table: one `x y z` direction per line, in image order
    /// (x right, y up, z towards the camera).
    #[arg(long, requires = "images")]
    pub lights: Option<PathBuf>,
    /// Image file names in light order, one per line [default: sorted names].
    #[arg(long, requires = "images")]
    pub names: Option<PathBuf>,
    /// Light intensities: one `r g b` per line; each image is divided by its own.
    #[arg(long, requires = "images")]
    pub intensities: Option<PathBuf>,
    /// PNG mask: non-zero pixels are solved.
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Reject shadowed and specular samples per pixel.
    #[arg(long)]
    pub robust: bool,
    /// Refuse light sets whose matrix has a larger condition number.
    #[arg(long, allow_negative_numbers = true, default_value_t = rigd_process::photometric_stereo::DEFAULT_MAX_CONDITION)]
    pub max_condition: f64,
    /// Output folder (created) [default: RUN/processed/ps for a run; the
    /// viewer looks there].
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub exec: ExecutorArgs,
}

#[derive(Args)]
pub struct RectifyArgs {
    /// The run directory.
    pub run: PathBuf,
    /// Side of the frontal normtexture each frame is resampled to first.
    #[arg(long, default_value_t = 1024)]
    pub size: usize,
    /// Fraction of the normtexture kept around its centre.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0)]
    pub roi: f64,
    /// Side of the stored textures.
    #[arg(long = "final", default_value_t = 256)]
    pub final_size: usize,
    /// Which 8 bits of the sensor value to keep: `top` (no clipping), a
    /// shift N for value >> N clipped at 255 (2 = the central 8 bits of 12,
    /// as Sattler et al. chose), `float` for linear float32 or `half` for linear
    /// float16 (Sattler et al.'s 16-bit floats), both .npy.
    #[arg(long, default_value = "top")]
    pub bits: String,
    /// Linear edge blending (Sattler et al., §3.2): the ROI is scaled to
    /// final + N texels and the extra band blended into the opposite edges,
    /// so the textures tile without seams. 0 = none: here every texel stays
    /// as measured unless asked; the daemon's processing blends a quarter of
    /// --final by default, which tiles in the viewer without a seam.
    #[arg(long, default_value_t = 0)]
    pub blend: usize,
    #[command(flatten)]
    pub exec: ExecutorArgs,
}

#[derive(Args)]
pub struct BtfArgs {
    /// The run directory (after `rigd process rectify`).
    pub run: PathBuf,
    /// Components kept per view slot.
    #[arg(long, default_value_t = 16)]
    pub components: usize,
    /// For a simulated run: after compressing, print the BTF's RMS error
    /// against the scene's true BTF (per channel for an RGB BTF) at this
    /// light and view, "θl,φl,θv,φv" in degrees, ideally a pair the plan
    /// did not measure. Repeatable.
    #[arg(long = "held-out", value_name = "θl,φl,θv,φv")]
    pub held_out: Vec<String>,
    #[command(flatten)]
    pub exec: ExecutorArgs,
}

/// Parses "θl,φl,θv,φv" (degrees) into a light and a view.
fn held_out_pair(
    s: &str,
) -> Result<(
    rigd_core::geometry::Direction,
    rigd_core::geometry::Direction,
)> {
    use rigd::model::text::check_direction;
    use rigd::plan::PLAN_THETA_DEG;
    use rigd_core::geometry::Direction;
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| bad_input(format!("--held-out {s}: expected θl,φl,θv,φv in degrees")))?;
    let [tl, pl, tv, pv] = v[..] else {
        return Err(bad_input(format!(
            "--held-out {s}: expected θl,φl,θv,φv in degrees"
        )));
    };
    // The directions a plan could have measured, φ normalised as a plan's.
    let check = |what: &str, d: Direction| {
        check_direction(d, PLAN_THETA_DEG)
            .map_err(|why| bad_input(format!("--held-out {s}: the {what}'s {why}")))
    };
    Ok((
        check("light", Direction::new(tl, pl))?,
        check("view", Direction::new(tv, pv))?,
    ))
}

#[derive(Args)]
pub struct FitArgs {
    /// The run directory (after `rigd process rectify`).
    pub run: PathBuf,
    /// Lobes of the non-linear model.
    #[arg(long, default_value_t = 2)]
    pub lobes: usize,
    #[command(flatten)]
    pub exec: ExecutorArgs,
}

#[derive(Args)]
pub struct MdfArgs {
    /// The run directory of a `--plan laser` capture.
    pub run: PathBuf,
    /// calibrated (Wang et al.'s: planes of a sweep parallel, at the
    /// calibrated angle) or emitter (planes through the profile's emitter).
    #[arg(long, value_enum, default_value_t = rigd::postprocess::mdf::PlaneModel::Calibrated)]
    pub planes: rigd::postprocess::mdf::PlaneModel,
    /// Use this many of the run's source positions, evenly picked [default: all].
    #[arg(long)]
    pub sources: Option<usize>,
    /// Grey level (0–1) each pixel's brightest frame must exceed to be
    /// triangulated; darker pixels are occluded (−1).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.15)]
    pub threshold: f64,
    /// Grey level (0–1) of the strip in the reference region, after the
    /// filter (the holder is dark, so the strip is dim there).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.02)]
    pub line_threshold: f64,
    /// Gaussian filter before the strip search, pixels.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0)]
    pub sigma: f64,
    #[command(flatten)]
    pub exec: ExecutorArgs,
}

#[derive(Args)]
pub struct ColourArgs {
    /// The run directory: a colour camera's frames of a holder with
    /// colour patches.
    pub run: PathBuf,
    /// Take this camera calibration (saved by `rigd camera colour --save`
    /// from a chart photograph) as the run's colour instead of measuring
    /// the holder's patches: for a plate without patches.
    #[arg(long, value_name = "FILE")]
    pub calibration: Option<PathBuf>,
}

#[derive(Args)]
pub struct MdfTextureArgs {
    /// The BTF run the MDF is for (its texture space and sample).
    pub run: PathBuf,
    /// The laser run of the same sample, after `rigd process mdf`.
    #[arg(long)]
    pub laser: PathBuf,
    /// Side of the texture, texels.
    #[arg(long, default_value_t = rigd::postprocess::mdf_texture::DEFAULT_MDF_TEXTURE_SIZE)]
    pub size: usize,
    /// Side of the sample square one texture tile covers, mm [default: the
    /// BTF run's sample times the --roi it was rectified with].
    #[arg(long, allow_negative_numbers = true)]
    pub tile_mm: Option<f64>,
}

/// Whether a render uses the MDF.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum MdfUse {
    /// Not at all: the mesh's own silhouette and no cast shadows.
    None,
    /// The run's MDF texture (`rigd process mdf-texture`).
    Mdf,
}

#[derive(Args)]
pub struct RelightArgs {
    /// The run directory (after `rigd process btf`).
    pub run: PathBuf,
    /// flat, cylinder, cloth or sphere.
    #[arg(long, default_value = "flat")]
    pub mesh: rigd_process::mesh::MeshKind,
    /// Directional light θ,φ in degrees, world frame (z up); θ up to 180
    /// (below the horizon: no light).
    #[arg(long, value_parser = parse_world_light, default_value = "30,45")]
    pub light: rigd_process::directions::Direction,
    /// Orbit camera θ,φ in degrees (θ 0 … 89).
    #[arg(long, value_parser = parse_orbit, default_value = "35,270")]
    pub view: rigd_process::directions::Direction,
    /// Image size WIDTHxHEIGHT.
    #[arg(long, default_value = "512x512", value_parser = rigd::model::text::parse_frame_size)]
    pub size: [u32; 2],
    /// Multiplies the BTF's values before display.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1.0)]
    pub exposure: f64,
    /// Eq. 6's offset α in degrees (Sattler et al. used 15 for a coarse mesh).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.0)]
    pub shadow_alpha: f64,
    /// btf, or plain: one frontal texture with Lambert's cosine (the
    /// comparison of Sattler et al. figures 13–14).
    #[arg(long, value_enum, default_value_t = ShadingArg::Btf)]
    pub shading: ShadingArg,
    /// Material tiles per world unit (the flat sample is 2 units across).
    #[arg(long, allow_negative_numbers = true, default_value_t = rigd::postprocess::viewer::DEFAULT_DENSITY)]
    pub density: f64,
    /// Mesostructure silhouettes (Wang et al., §4): every interval of the
    /// pixel's ray through the mesh tested against the MDF.
    #[arg(long, value_enum, default_value_t = MdfUse::None)]
    pub silhouettes: MdfUse,
    /// Cast shadows from an MDF-offset shadow map of the light.
    #[arg(long, value_enum, default_value_t = MdfUse::None)]
    pub shadows: MdfUse,
    /// The PNG to write.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub enum ShadingArg {
    Btf,
    Plain,
}

fn parse_angles(s: &str, theta_max: f64) -> Result<rigd_process::directions::Direction, String> {
    let d = rigd::model::text::parse_direction_within(s, theta_max)?;
    Ok(rigd_process::directions::Direction::new(
        d.theta_deg,
        d.phi_deg,
    ))
}

fn parse_world_light(s: &str) -> Result<rigd_process::directions::Direction, String> {
    parse_angles(s, 180.0)
}

fn parse_orbit(s: &str) -> Result<rigd_process::directions::Direction, String> {
    parse_angles(s, 89.0)
}

fn photometric_stereo(args: PsArgs) -> Result<()> {
    use rigd::postprocess::pipeline::{ProcessOptions, ProcessStep, PsOptions};
    use rigd_process::photometric_stereo as ps;
    PsOptions {
        robust: args.robust,
        max_condition: args.max_condition,
    }
    .check()
    .map_err(|e| bad_input(format!("--{e}")))?;
    args.exec.config()?;
    // Into the run: no other processor writes its files while this one
    // does. Into another folder, the run is only read.
    let _processing = (args.run.as_deref())
        .filter(|_| args.out.is_none())
        .map(rigd::store::ProcessingLock::acquire)
        .transpose()?;
    if args.exec.is_slurm() {
        let (Some(run), None) = (&args.run, &args.out) else {
            return Err(bad_input(
                "--executor slurm works on a run directory, into RUN/processed/ps (no --images, no --out)",
            ));
        };
        if args.mask.is_some() {
            return Err(bad_input(
                "--mask is not sent to Slurm: leave it out with --executor slurm",
            ));
        }
        let opts = ProcessOptions {
            steps: vec![ProcessStep::PhotometricStereo],
            photometric_stereo: PsOptions {
                robust: args.robust,
                max_condition: args.max_condition,
            },
            ..Default::default()
        };
        let started = Instant::now();
        let summary = on_slurm(&args.exec, run, ProcessStep::PhotometricStereo, &opts)?;
        println!("{summary} ({:.1} s)", started.elapsed().as_secs_f64());
        return Ok(());
    }
    #[cfg_attr(not(feature = "sim"), allow(unused_variables))]
    let (mut dataset, run) = match (&args.run, &args.images, &args.lights) {
        (Some(run), _, _) => {
            let frames = rigd::postprocess::frames::RunFrames::open(run)?;
            (
                rigd::postprocess::ps::ps_dataset_from_run(&frames)?,
                Some(frames),
            )
        }
        (None, Some(images), Some(lights)) => {
            let inputs = ps::PsInputs {
                images_dir: images.clone(),
                lights_file: lights.clone(),
                names_file: args.names.clone(),
                intensities_file: args.intensities.clone(),
                mask_file: None,
            };
            (ps::load_inputs(&inputs)?, None)
        }
        _ => {
            return Err(bad_input(
                "give a run directory, or --images DIR --lights FILE",
            ))
        }
    };
    let out = match (&args.out, &args.run) {
        (Some(out), _) => out.clone(),
        (None, Some(run)) => rigd::store::processed::ps_dir(run),
        (None, None) => return Err(bad_input("--out DIR is needed with --images")),
    };
    if let Some(mask) = &args.mask {
        let m = rigd_process::image_io::load_png(mask)?;
        dataset.mask = Some(
            m.data
                .chunks(m.channels)
                .map(|px| px.iter().any(|&v| v > 0.0))
                .collect(),
        );
    }
    let rows_done = progress_line("solving rows");
    let opts = ps::PsOptions {
        robust: args.robust,
        max_condition: args.max_condition,
        progress: Some(&rows_done),
        ..Default::default()
    };
    let started = Instant::now();
    let result = ps::solve(&dataset, &opts)?;
    let written = ps::write_outputs(&result, &out)?;
    let r = &result.report;
    println!(
        "{} images, {}x{}, light matrix condition number {:.3}, {} of {} pixels solved, mean residual {:.4}, {:.2} s",
        dataset.images.len(),
        result.width,
        result.height,
        r.condition_number,
        result.valid.iter().filter(|v| **v).count(),
        result.width * result.height,
        r.mean_residual,
        started.elapsed().as_secs_f64()
    );
    #[cfg(feature = "sim")]
    if let Some(run) = &run {
        if let Some(err) = rigd::truth::ps_error_against_truth(run, &result)? {
            println!(
                "against the scene `{}`: mean angular error {:.2}°, median {:.2}°, 95th percentile {:.2}° over {} sample pixels",
                err.scene, err.mean_deg, err.median_deg, err.p95_deg, err.pixels
            );
            let path = out.join("truth.json");
            let mut json = serde_json::to_vec_pretty(&err)?;
            json.push(b'\n');
            rigd::store::write_atomic(&path, &json)?;
        }
    }
    println!("wrote {} files into {}", written.len(), out.display());
    Ok(())
}

fn rectify(args: RectifyArgs) -> Result<()> {
    use rigd::postprocess::pipeline::{ProcessOptions, ProcessStep, RectifyOptions};
    let options = RectifyOptions {
        size: args.size,
        final_size: args.final_size,
        roi: args.roi,
        bits: args.bits.clone(),
        blend: Some(args.blend),
    };
    // The daemon's check of the same options, so both refuse alike.
    let cfg = options.config().map_err(|e| bad_input(format!("--{e}")))?;
    args.exec.config()?;
    // No other processor writes the run's files while this one does.
    let _processing = rigd::store::ProcessingLock::acquire(&args.run)?;
    if args.exec.is_slurm() {
        let opts = ProcessOptions {
            steps: vec![ProcessStep::Rectify],
            rectify: options,
            ..Default::default()
        };
        let started = Instant::now();
        let summary = on_slurm(&args.exec, &args.run, ProcessStep::Rectify, &opts)?;
        println!("{summary} ({:.1} s)", started.elapsed().as_secs_f64());
        let index = rigd::postprocess::rectify::NormtextureIndex::read(&args.run)?;
        if let Some(summary) = &index.summary {
            print!("{}", summary.table());
        }
        return Ok(());
    }
    let run = rigd::postprocess::frames::RunFrames::open(&args.run)?;
    let started = Instant::now();
    let index = rigd::postprocess::rectify::rectify_run(&run, &cfg, &progress_line("registering"))?;
    let rejected: usize = index.frames.iter().map(|f| f.markers_rejected.len()).sum();
    println!(
        "{} frames ({} views × {} lights) into {}² textures in {} ({:.1} s); {} markers rejected as outliers",
        index.frames.len(),
        index.views.len(),
        index.lights.len(),
        index.size,
        args.run.join("processed/normtextures").display(),
        started.elapsed().as_secs_f64(),
        rejected,
    );
    if let Some(summary) = &index.summary {
        print!("{}", summary.table());
    }
    Ok(())
}

fn btf(args: BtfArgs) -> Result<()> {
    use rigd::postprocess::pipeline::{BtfOptions, ProcessOptions, ProcessStep};
    let options = BtfOptions {
        components: args.components,
    };
    options.check().map_err(|e| bad_input(format!("--{e}")))?;
    let held_out = args
        .held_out
        .iter()
        .map(|s| held_out_pair(s))
        .collect::<Result<Vec<_>>>()?;
    if !held_out.is_empty() && !rigd::store::read_meta(&args.run)?.simulated {
        return Err(bad_input(
            "--held-out: ground truth exists only for simulated runs",
        ));
    }
    args.exec.config()?;
    // No other processor writes the run's files while this one does.
    let _processing = rigd::store::ProcessingLock::acquire(&args.run)?;
    if args.exec.is_slurm() {
        let opts = ProcessOptions {
            steps: vec![ProcessStep::Btf],
            btf: options,
            ..Default::default()
        };
        let started = Instant::now();
        let summary = on_slurm(&args.exec, &args.run, ProcessStep::Btf, &opts)?;
        println!("{summary} ({:.1} s)", started.elapsed().as_secs_f64());
        return Ok(());
    }
    let report = rigd::postprocess::btf::btf_run(
        &args.run,
        args.components,
        &progress_line("compressing view slots"),
    )?;
    println!(
        "{} view slots × {} lights, C = {}: {:.1} MB in {} ({:.1} s)",
        report.slots,
        report.lights,
        report.components,
        report.bytes as f64 / 1e6,
        args.run.join("processed/btf").display(),
        report.compress_s
    );
    if report.clipped.filled + report.clipped.left > 0 {
        println!(
            "clipped texels: {} filled from their slot's neighbouring lights, {} clipped under \
             every light and kept as read (lower bounds)",
            report.clipped.filled, report.clipped.left
        );
    }
    println!("C\tmean RMS error over slots (1 = full scale)");
    for (c, rms) in report.mean_rms_by_components.iter().enumerate() {
        if [1, 2, 4, 8, 16, 32].contains(&(c + 1)) {
            println!("{}\t{:.5}", c + 1, rms);
        }
    }
    print_truth_error(&args.run, &held_out)
}

/// The BTF's error against the simulated scene's truth at each pair.
#[cfg(feature = "sim")]
fn print_truth_error(
    run: &std::path::Path,
    pairs: &[(
        rigd_core::geometry::Direction,
        rigd_core::geometry::Direction,
    )],
) -> Result<()> {
    if pairs.is_empty() {
        return Ok(());
    }
    let errors = rigd::truth::btf_truth_error(run, pairs)?;
    println!("held out: RMS error against the true BTF, relative to the truth's RMS (per channel)");
    for e in errors {
        let per: Vec<String> = e
            .rms_by_channel
            .iter()
            .zip(&e.truth_rms_by_channel)
            .map(|(r, t)| format!("{r:.4} ({:.1} %)", 100.0 * r / t.max(f64::MIN_POSITIVE)))
            .collect();
        println!(
            "light θ {:.1}° φ {:.1}°, view θ {:.1}° φ {:.1}°: {}",
            e.light.theta_deg,
            e.light.phi_deg,
            e.view.theta_deg,
            e.view.phi_deg,
            per.join(", ")
        );
    }
    Ok(())
}

#[cfg(not(feature = "sim"))]
fn print_truth_error(
    _run: &std::path::Path,
    pairs: &[(
        rigd_core::geometry::Direction,
        rigd_core::geometry::Direction,
    )],
) -> Result<()> {
    if pairs.is_empty() {
        Ok(())
    } else {
        Err(bad_input(
            "--held-out needs the simulator, and this rigd was built without it (cargo feature `sim`)",
        ))
    }
}

fn fit(args: FitArgs) -> Result<()> {
    use rigd::postprocess::pipeline::{FitOptions, ProcessOptions, ProcessStep};
    let options = FitOptions { lobes: args.lobes };
    options.check().map_err(|e| bad_input(format!("--{e}")))?;
    args.exec.config()?;
    // No other processor writes the run's files while this one does.
    let _processing = rigd::store::ProcessingLock::acquire(&args.run)?;
    if args.exec.is_slurm() {
        let opts = ProcessOptions {
            steps: vec![ProcessStep::Fit],
            fit: options,
            ..Default::default()
        };
        let started = Instant::now();
        let summary = on_slurm(&args.exec, &args.run, ProcessStep::Fit, &opts)?;
        println!("{summary} ({:.1} s)", started.elapsed().as_secs_f64());
        return Ok(());
    }
    let rows = rigd::postprocess::fit::fit_run(
        &args.run,
        args.lobes,
        &progress_line("fitting view slots"),
    )?;
    println!("method\tmean |error|\tRMS error\tfit time\tconverged texels");
    for r in rows {
        println!(
            "{}\t{:.5}\t{:.5}\t{:.2} s\t{}",
            r.method, r.mean_abs_error, r.rms_error, r.fit_s, r.converged_texels
        );
    }
    Ok(())
}

fn mdf(args: MdfArgs) -> Result<()> {
    use rigd::postprocess::pipeline::{MdfOptions, ProcessOptions, ProcessStep};
    let options = MdfOptions {
        planes: args.planes,
        sources: args.sources,
        threshold: args.threshold,
        line_threshold: args.line_threshold,
        sigma: args.sigma,
    };
    options.check().map_err(|e| bad_input(format!("--{e}")))?;
    args.exec.config()?;
    // No other processor writes the run's files while this one does.
    let _processing = rigd::store::ProcessingLock::acquire(&args.run)?;
    if args.exec.is_slurm() {
        let opts = ProcessOptions {
            steps: vec![ProcessStep::Mdf],
            mdf: options,
            ..Default::default()
        };
        let started = Instant::now();
        let summary = on_slurm(&args.exec, &args.run, ProcessStep::Mdf, &opts)?;
        println!("{summary} ({:.1} s)", started.elapsed().as_secs_f64());
        return Ok(());
    }
    let run = rigd::postprocess::frames::RunFrames::open(&args.run)?;
    let cfg = options.config();
    let report = rigd::postprocess::mdf::mdf_run(&run, &cfg, &progress_line("sweeps analysed"))?;
    for why in &report.skipped {
        eprintln!("warning: left out: {why}");
    }
    println!("view	sources	valid	mean error	median	95th pct	coverage");
    for v in &report.views {
        match v.truth.filter(|t| t.pixels > 0) {
            Some(t) => println!(
                "{}	{}	{:.1}%	{:.3} mm	{:.3} mm	{:.3} mm	{:.1}%",
                v.name,
                v.sources,
                100.0 * v.valid_fraction,
                t.mean_mm,
                t.median_mm,
                t.p95_mm,
                100.0 * t.coverage
            ),
            None => println!(
                "{}	{}	{:.1}%	-	-	-	-",
                v.name,
                v.sources,
                100.0 * v.valid_fraction
            ),
        }
    }
    if let Some(e) = report.mean_error_mm {
        println!("mean depth error over views: {e:.3} mm");
    }
    println!(
        "wrote {}",
        rigd::store::processed::mdf_dir(&args.run).display()
    );
    Ok(())
}

/// One part of a step, as a Slurm task runs it.
fn part(args: PartArgs) -> Result<()> {
    use rigd::postprocess::parts;
    let bytes = rigd_core::read::read_bounded(&args.options, rigd_core::read::TEXT_LIMIT)
        .map_err(std::io::Error::from)
        .context("cannot read the options")?;
    let opts: rigd::postprocess::pipeline::ProcessOptions = serde_json::from_slice(&bytes)
        .map_err(|e| bad_input(format!("{}: {e}", args.options.display())))?;
    let sizes = parts::PartSizes {
        frames: args.frames_per_part,
        slots: args.slots_per_part,
    };
    let split = parts::split(&args.run, args.step, &opts, sizes)?;
    if split.parts() != args.parts {
        return Err(bad_input(format!(
            "{} of {} splits into {} parts now, {} when it was submitted: the run changed",
            args.step.name(),
            args.run.display(),
            split.parts(),
            args.parts
        )));
    }
    let started = Instant::now();
    let summary = parts::run_part(&args.run, args.step, &opts, split, args.part, &|_, _| {})?;
    rigd::postprocess::slurm::mark_done(&args.run, args.step, args.part, &summary)?;
    println!(
        "part {} of {}: {summary} ({:.1} s)",
        args.part,
        args.parts,
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

fn relight(args: RelightArgs) -> Result<()> {
    use rigd_process::relight::{RelightSettings, Shading};
    if !(args.density.is_finite() && args.density > 0.0 && args.density <= 64.0) {
        return Err(bad_input(format!(
            "--density {}: expected more than 0 and at most 64 tiles per unit",
            args.density
        )));
    }
    if !(args.shadow_alpha.is_finite() && (0.0..=45.0).contains(&args.shadow_alpha)) {
        return Err(bad_input(format!(
            "--shadow-alpha {}: expected 0 ..= 45 degrees",
            args.shadow_alpha
        )));
    }
    let settings = RelightSettings {
        width: args.size[0] as usize,
        height: args.size[1] as usize,
        light: args.light,
        view: args.view,
        exposure: args.exposure,
        shadow_alpha_deg: args.shadow_alpha,
        shading: match args.shading {
            ShadingArg::Btf => Shading::Btf,
            ShadingArg::Plain => Shading::Plain,
        },
    };
    let meso = rigd_process::silhouette::MesoSettings {
        silhouettes: args.silhouettes == MdfUse::Mdf,
        shadows: args.shadows == MdfUse::Mdf,
        density: args.density,
    };
    let started = Instant::now();
    let (img, report) =
        rigd::postprocess::viewer::render_run(&args.run, args.mesh, &settings, &meso)?;
    let data = img.pixels.iter().map(|&v| f32::from(v) / 255.0).collect();
    let image = rigd_process::image_io::Image {
        width: img.width,
        height: img.height,
        channels: 3,
        data,
    };
    rigd_process::image_io::write_png(&args.out, &image, rigd_process::image_io::PngDepth::Eight)?;
    println!(
        "{} on a {} mesh, light {},{} view {},{}: {}x{} in {:.2} s -> {}",
        args.run.display(),
        args.mesh.name(),
        args.light.theta_deg,
        args.light.phi_deg,
        args.view.theta_deg,
        args.view.phi_deg,
        img.width,
        img.height,
        started.elapsed().as_secs_f64(),
        args.out.display()
    );
    if let Some(r) = report {
        println!(
            "mesh outline {} px, background inside it {} px, cast shadow {} px, ray layers up to {} (of {})",
            r.outline_pixels,
            r.background_inside_outline,
            r.shadowed_pixels,
            r.layers_used,
            rigd_process::silhouette::MAX_PEEL_LAYERS
        );
    }
    Ok(())
}

fn colour(args: ColourArgs) -> Result<()> {
    use rigd::postprocess::{colour, ProcessError};
    let run = rigd::postprocess::frames::RunFrames::open(&args.run)?;
    // No other processor writes the run's files while this one does.
    let _processing = rigd::store::ProcessingLock::acquire(&args.run)?;
    if let Some(file) = &args.calibration {
        let (calibration, _) = match colour::import_calibration(&run, file) {
            Ok(taken) => taken,
            Err(ProcessError::Invalid(m)) => return Err(bad_input(m)),
            Err(e) => return Err(e.into()),
        };
        println!(
            "the {} fitted on {} ({}, mean CIEDE2000 {:.2} in the fit{}) corrects the run's \
             textures",
            calibration.correction.kind,
            calibration.source,
            calibration.chart,
            calibration.mean_delta_e2000,
            calibration
                .mean_delta_e2000_left_out
                .map_or(String::new(), |e| format!(", {e:.2} left out"))
        );
        println!("-> {}", colour::camera_colour_file(&args.run).display());
        return Ok(());
    }
    let report = match colour::calibrate_run(&run) {
        Ok(report) => report,
        Err(ProcessError::Invalid(m)) => return Err(bad_input(m)),
        Err(e) => return Err(e.into()),
    };
    print!("{}", report.table());
    println!("-> {}", colour::colour_file(&args.run).display());
    Ok(())
}

fn mdf_texture(args: MdfTextureArgs) -> Result<()> {
    // No other processor writes the run's files while this one does.
    let _processing = rigd::store::ProcessingLock::acquire(&args.run)?;
    let cfg = rigd::postprocess::mdf_texture::MdfTextureConfig {
        size: args.size,
        tile_mm: args.tile_mm,
    };
    let started = Instant::now();
    let header = rigd::postprocess::mdf_texture::mdf_texture(&args.run, &args.laser, &cfg)?;
    let mean = header.coverage.iter().sum::<f64>() / header.coverage.len().max(1) as f64;
    println!(
        "{} views of {} as {}×{} texels over a {:.1} mm tile, top plane {:.2} mm over the turntable, {:.0} % of texels measured on average ({:.1} s) -> {}",
        header.views.len(),
        args.laser.display(),
        header.size,
        header.size,
        header.tile_mm,
        header.top_mm,
        100.0 * mean,
        started.elapsed().as_secs_f64(),
        rigd::store::processed::mdf_texture_dir(&args.run).display()
    );
    Ok(())
}
