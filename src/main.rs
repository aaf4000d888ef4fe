//! The `rigd` command line.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::{Args, Parser, Subcommand};
use rigd::engine::command::Command;
use rigd::engine::launch::{self, NewRun};
use rigd::engine::{EventKind, Outcome, PausePolicy};
use rigd::model::geometry::Direction;
use rigd::model::profile::{Profile, DEFAULT_PROFILE};
use rigd::model::run_state::RunState;
use rigd::plan::Order;
use rigd::schedule::timing::Timing;
use rigd_core::Clock;
use rigd_sim::FaultRule;

/// Exit codes, so scripts can tell what happened.
const EXIT_PAUSED: u8 = 3;
const EXIT_ENDED_BADLY: u8 = 4;
const EXIT_INTERRUPTED: u8 = 130;
const EXIT_BAD_INPUT: u8 = 2;

#[derive(Parser)]
#[command(
    name = "rigd",
    version,
    about = "Control daemon for BTF measurement rigs",
    long_about = "Control daemon for BTF (bidirectional texture function) measurement rigs: \
plans captures over the hemisphere, drives the rig (or its simulation), and writes datasets that lose nothing.",
    after_help = "Exit codes: 0 done, 2 bad input, 3 run paused (resume it with `rigd run --resume DIR`), \
4 run aborted or failed, 130 interrupted (resumable)."
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Show sampling plans.
    Plan {
        #[command(subcommand)]
        command: PlanCmd,
    },
    /// Check rig profiles.
    Profile {
        #[command(subcommand)]
        command: ProfileCmd,
    },
    /// Capture a BTF: run a plan on a rig into a run directory, or resume one.
    Run(RunArgs),
    /// Run the daemon: the HTTP API (/api/v1, docs at /api/docs) driving one
    /// run at a time, with a queue. SIGINT/SIGTERM pause the active run
    /// (resumable after restart) and stop.
    Serve(ServeArgs),
    /// Write a rectified run's textures for existing BTF tools: `utia` (a
    /// folder per view of tl…_pl…_tv…_pv….png) or `ubo2003` (a zip of
    /// `tl… pl… tv… pv….jpg`, integer degrees, as the Bonn 2003 database).
    Export(ExportArgs),
    /// What accuracy costs in time on this rig and material: sampling plans
    /// (H2, H1, ring subsets, grids, a dense reference) against held-out BTF
    /// error, PCA components, and the simulator's effects against render
    /// time; prints the table and writes tradeoff.csv, tradeoff.json and
    /// tradeoff.svg (error against physical time) into --out.
    Tradeoff(TradeoffArgs),
    /// Read textures in an export format (ours or a database's) into
    /// OUT/processed/normtextures/, ready for `rigd process btf OUT`.
    Import(ImportArgs),
    /// Turn captured frames into results: photometric stereo, BTF
    /// compression.
    Process {
        #[command(subcommand)]
        command: ProcessCmd,
    },
    /// The simulated rig's firmware, for tools outside rigd.
    Sim {
        #[command(subcommand)]
        command: SimCmd,
    },
}

#[derive(Subcommand)]
enum SimCmd {
    /// Serve a profile's simulated firmware in real time, as hardware would be
    /// reached: serial devices (GRBL, ACL) on pseudo-terminals, relay modules on
    /// Modbus TCP on 127.0.0.1 (RTU modules also on a pty), cameras as PTP over
    /// a loopback socket. Prints the endpoints and a profile that points at them
    /// (`rigd run --profile THAT_FILE` drives the served rig), then runs until
    /// interrupted.
    Serve {
        /// Rig profile: a TOML file or an embedded profile name.
        #[arg(long, default_value = DEFAULT_PROFILE)]
        profile: String,
        /// Physical seconds per wall second (1 = real time).
        #[arg(long, default_value_t = 1.0)]
        speed: f64,
        /// Also write the served profile to this file.
        #[arg(long, value_name = "FILE")]
        write_profile: Option<PathBuf>,
        /// Inject a fault, as `rigd run --sim-fault`. Repeatable.
        #[arg(long = "sim-fault", value_name = "SPEC")]
        sim_faults: Vec<FaultRule>,
    },
    /// Render one frame of a scene as a profile's camera sees it, to a PNG
    /// (at the camera's bit depth) with a JSON file beside it: the live
    /// effects, the render time and where every marker landed.
    Render(RenderArgs),
    /// List the built-in scenes and what each can show.
    Scenes,
}

#[derive(Subcommand)]
enum ProcessCmd {
    /// Photometric stereo (seed 003 §2): albedo, normals, gradients p and q
    /// and a Frankot–Chellappa height map, from a VirTex run directory or from
    /// a folder of images with a light table. Writes normals.npy (H×W×3
    /// float32, unit, z towards the camera), albedo.npy, height.npy, p.npy,
    /// q.npy, PNG renderings of each and report.json into --out.
    PhotometricStereo(PsArgs),
    /// Register every frame of a run by its holder markers (seed 000 §3.2)
    /// and resample the sample to frontal textures: RUN/processed/
    /// normtextures/ with index.json (per frame: the marker residual in
    /// pixels, the markers used and rejected). Frames whose markers cannot be
    /// found are named in the error and the index.
    Rectify(RectifyArgs),
    /// Compress a rectified run's BTF: a PCA per view slot (seed 000 §4.1)
    /// into RUN/processed/btf/ (btf.json + slot files), with the eigenvalue
    /// decay and the RMS error for C = 1 … 32 per slot in report.json.
    Btf(BtfArgs),
    /// Fit every texel of every view slot of a rectified run with the
    /// K-lobe reflectance model by Levenberg–Marquardt and with a PTM
    /// (seed 001 §4), and print the average error table (seed 001 Table 1);
    /// also RUN/processed/fit/report.json.
    Fit(FitArgs),
    /// The mesostructure distance function of a laser run (seed 002 §3.2):
    /// each source's laser plane calibrated from the strip on the turntable
    /// and on the plate, the strip found per frame in the reference region
    /// outside the sample's box, space-time triangulation per pixel, and
    /// the sources of each view merged with the seed's weights. Writes
    /// RUN/processed/mdf/<view>.npy (float32 mm, −1 = none), an 8-bit
    /// .png per view and report.json; prints the depth error against the
    /// scene for simulated runs.
    Mdf(MdfArgs),
    /// The reference render of a processed run's BTF on a mesh, exactly as
    /// the viewer (`/viewer/RUN`) draws it: the four nearest view slots, the
    /// light interpolated from the four nearest measured lights, the smooth
    /// shadow boundary of seed 000 eq. 6. Writes an 8-bit RGB PNG.
    Render(RelightArgs),
}

#[derive(Args)]
struct RelightArgs {
    /// The run directory (after `rigd process btf`).
    run: PathBuf,
    /// flat, cylinder or cloth.
    #[arg(long, default_value = "flat")]
    mesh: rigd_process::mesh::MeshKind,
    /// Directional light θ,φ in degrees, world frame (z up); θ up to 180
    /// (below the horizon: no light).
    #[arg(long, value_parser = parse_world_light, default_value = "30,45")]
    light: rigd_process::directions::Direction,
    /// Orbit camera θ,φ in degrees (θ 0 … 89).
    #[arg(long, value_parser = parse_orbit, default_value = "35,270")]
    view: rigd_process::directions::Direction,
    /// Image size WIDTHxHEIGHT.
    #[arg(long, default_value = "512x512", value_parser = rigd::rig::shot::parse_frame_size)]
    size: [u32; 2],
    /// Multiplies the BTF's values before display.
    #[arg(long, default_value_t = 1.0)]
    exposure: f64,
    /// Eq. 6's offset α in degrees (the seed used 15 for a coarse mesh).
    #[arg(long, default_value_t = 0.0)]
    shadow_alpha: f64,
    /// btf, or plain: one frontal texture with Lambert's cosine (the
    /// comparison of seed 000 figures 13–14).
    #[arg(long, value_enum, default_value_t = ShadingArg::Btf)]
    shading: ShadingArg,
    /// Material tiles per world unit (the flat sample is 2 units across).
    #[arg(long, default_value_t = rigd::postprocess::viewer::DEFAULT_DENSITY)]
    density: f64,
    /// The PNG to write.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ShadingArg {
    Btf,
    Plain,
}

fn parse_angles(s: &str, theta_max: f64) -> Result<rigd_process::directions::Direction, String> {
    let d = rigd::rig::shot::parse_direction_within(s, theta_max)?;
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

#[derive(Args)]
struct MdfArgs {
    /// The run directory of a `--plan laser` capture.
    run: PathBuf,
    /// calibrated (the seed's: planes of a sweep parallel, at the
    /// calibrated angle) or emitter (planes through the profile's emitter).
    #[arg(long, value_enum, default_value_t = rigd::postprocess::mdf::PlaneModel::Calibrated)]
    planes: rigd::postprocess::mdf::PlaneModel,
    /// Use this many of the run's source positions, evenly picked [default: all].
    #[arg(long)]
    sources: Option<usize>,
    /// Grey level (0–1) each pixel's brightest frame must exceed to be
    /// triangulated; darker pixels are occluded (−1).
    #[arg(long, default_value_t = 0.15)]
    threshold: f64,
    /// Grey level (0–1) of the strip in the reference region, after the
    /// filter (the holder is dark, so the strip is dim there).
    #[arg(long, default_value_t = 0.02)]
    line_threshold: f64,
    /// Gaussian filter before the strip search, pixels.
    #[arg(long, default_value_t = 1.0)]
    sigma: f64,
}

#[derive(Args)]
struct TradeoffArgs {
    /// Rig profile: a TOML file or an embedded profile name.
    #[arg(long, default_value = DEFAULT_PROFILE)]
    profile: String,
    /// The material: a built-in scene or a scene file.
    #[arg(long, default_value = "corduroy")]
    scene: String,
    /// Where to write tradeoff.csv, .json and .svg.
    #[arg(long, default_value = ".")]
    out: PathBuf,
    /// Side of the normtextures, texels.
    #[arg(long, default_value_t = 16)]
    texture: usize,
    /// Held-out (light, view) pairs.
    #[arg(long, default_value_t = 24)]
    held_out: usize,
    /// PCA components for the plan rows.
    #[arg(long, default_value_t = 16)]
    components: usize,
    /// Frame size of the fidelity renders, WIDTHxHEIGHT.
    #[arg(long, default_value = "256x192", value_parser = rigd::rig::shot::parse_frame_size)]
    render_size: [u32; 2],
}

#[derive(Args)]
struct ExportArgs {
    /// The run directory (after `rigd process rectify`).
    run: PathBuf,
    /// utia or ubo2003.
    #[arg(long)]
    format: rigd_process::export::Format,
    /// A folder (utia) or a .zip file (ubo2003).
    #[arg(long)]
    out: PathBuf,
    /// JPEG quality for ubo2003, 1 ..= 100.
    #[arg(long, default_value_t = 95)]
    quality: u8,
}

#[derive(Args)]
struct ImportArgs {
    /// A utia folder or a ubo2003 zip.
    path: PathBuf,
    /// utia or ubo2003.
    #[arg(long)]
    format: rigd_process::export::Format,
    /// Directory to create the normtextures in.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args)]
struct FitArgs {
    /// The run directory (after `rigd process rectify`).
    run: PathBuf,
    /// Lobes of the non-linear model.
    #[arg(long, default_value_t = 2)]
    lobes: usize,
}

#[derive(Args)]
struct RectifyArgs {
    /// The run directory.
    run: PathBuf,
    /// Side of the frontal normtexture each frame is resampled to first.
    #[arg(long, default_value_t = 1024)]
    size: usize,
    /// Fraction of the normtexture kept around its centre.
    #[arg(long, default_value_t = 1.0)]
    roi: f64,
    /// Side of the stored textures.
    #[arg(long = "final", default_value_t = 256)]
    final_size: usize,
    /// Which 8 bits of the sensor value to keep: `top` (no clipping), a
    /// shift N for value >> N clipped at 255 (2 = the central 8 bits of 12,
    /// as seed 000 chose), `float` for linear float32 or `half` for linear
    /// float16 (the seed's 16-bit floats), both .npy.
    #[arg(long, default_value = "top")]
    bits: String,
    /// Linear edge blending (seed 000 §3.2): the ROI is scaled to
    /// final + N texels and the extra band blended into the opposite edges,
    /// so the textures tile without seams. 0 = none.
    #[arg(long, default_value_t = 0)]
    blend: usize,
}

#[derive(Args)]
struct BtfArgs {
    /// The run directory (after `rigd process rectify`).
    run: PathBuf,
    /// Components kept per view slot.
    #[arg(long, default_value_t = 16)]
    components: usize,
}

#[derive(Args)]
struct PsArgs {
    /// A run directory whose camera looks down on the sample (VirTex).
    #[arg(conflicts_with_all = ["images", "lights", "names", "intensities"])]
    run: Option<PathBuf>,
    /// Folder of PNG images (8/16-bit, grey or RGB), one per light.
    #[arg(long, requires = "lights")]
    images: Option<PathBuf>,
    /// Light table: one `x y z` direction per line, in image order
    /// (x right, y up, z towards the camera).
    #[arg(long, requires = "images")]
    lights: Option<PathBuf>,
    /// Image file names in light order, one per line [default: sorted names].
    #[arg(long, requires = "images")]
    names: Option<PathBuf>,
    /// Light intensities: one `r g b` per line; each image is divided by its own.
    #[arg(long, requires = "images")]
    intensities: Option<PathBuf>,
    /// PNG mask: non-zero pixels are solved.
    #[arg(long)]
    mask: Option<PathBuf>,
    /// Reject shadowed and specular samples per pixel.
    #[arg(long)]
    robust: bool,
    /// Refuse light sets whose matrix has a larger condition number.
    #[arg(long, default_value_t = rigd_process::photometric_stereo::DEFAULT_MAX_CONDITION)]
    max_condition: f64,
    /// Output folder (created) [default: RUN/processed/ps for a run; the
    /// viewer looks there].
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(Args)]
struct RenderArgs {
    /// Rig profile: a TOML file or an embedded profile name.
    #[arg(long, default_value = DEFAULT_PROFILE)]
    profile: String,
    /// Scene: a built-in name (`rigd sim scenes`) or a scene file
    /// [default: the profile's [sim] scene, else flat-calibration]
    #[arg(long)]
    scene: Option<String>,
    /// Light direction θ,φ in degrees, sample frame.
    #[arg(long, value_parser = rigd::rig::shot::parse_direction, default_value = "0,0")]
    light: Direction,
    /// View direction θ,φ in degrees, sample frame.
    #[arg(long, value_parser = rigd::rig::shot::parse_direction, default_value = "0,0")]
    view: Direction,
    /// Camera of the profile [default: its first]
    #[arg(long)]
    camera: Option<String>,
    /// Frame size WIDTHxHEIGHT [default: the profile's [sim] frame_size]
    #[arg(long, value_parser = rigd::rig::shot::parse_frame_size)]
    size: Option<[u32; 2]>,
    /// Effect switches: `all`, `none`, or a list like `+interreflection,-noise`.
    #[arg(long, default_value = "")]
    effects: String,
    /// Noise seed of this frame.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Exposure relative to the camera's nominal one.
    #[arg(long, default_value_t = 1.0)]
    exposure: f64,
    /// A laser line: the plane crosses the sample plane at X mm, tilted
    /// TILT degrees (`X` or `X,TILT`, tilt 30 by default).
    #[arg(long, value_name = "X[,TILT]")]
    laser: Option<String>,
    /// Lamp off: only the laser lights the sample.
    #[arg(long)]
    lamp_off: bool,
    /// Focal length multiplier: a longer lens for a closer look.
    #[arg(long, default_value_t = 1.0)]
    zoom: f64,
    /// Output PNG; the metadata goes to the same name with .json.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
}

#[derive(Args)]
struct ServeArgs {
    /// Rig profile: a TOML file or an embedded profile name; a file means
    /// its hardware unless --sim [default: the simulated bonn-gonioreflectometer]
    #[arg(long)]
    profile: Option<String>,
    /// Drive the simulated rig (implied without --profile).
    #[arg(long)]
    sim: bool,
    /// Address to listen on. Reads are open to loopback clients; every
    /// mutating route needs the bearer token.
    #[arg(long, default_value = rigd::server::DEFAULT_LISTEN)]
    listen: std::net::SocketAddr,
    /// Data directory: runs/<id>/ (run directories), queue.json, token.
    #[arg(long = "data", default_value = rigd::server::DEFAULT_DATA)]
    data: PathBuf,
    /// Simulated physical seconds per wall second. The default 200 runs a
    /// demo H1 capture on the simulated Bonn rig (6561 images, about 10 h
    /// physical) in about 3 minutes.
    #[arg(long, default_value_t = rigd::server::DEFAULT_SIM_SPEED, allow_negative_numbers = true)]
    sim_speed: f64,
    /// File holding the API token [default: DATA/token, generated at first
    /// start with mode 0600].
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// Inject a fault into the simulated rig of every new run (same SPEC as
    /// `rigd run --sim-fault`, e.g. camera:transfer:3:disconnect). Repeatable.
    #[arg(long = "sim-fault", value_name = "SPEC")]
    sim_faults: Vec<FaultRule>,
}

#[derive(Subcommand)]
enum PlanCmd {
    /// List every image of a plan with its directions, feasibility and set-points,
    /// and the totals: image count and estimated physical capture time.
    Show {
        /// h1, h2, grid12x8, lamps, or a plan file (.json/.toml)
        plan: String,
        /// Rig profile: a TOML file or an embedded profile name.
        #[arg(long, default_value = DEFAULT_PROFILE)]
        profile: String,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
        /// Exposure time for every camera, seconds (default: the profile's).
        #[arg(long, allow_negative_numbers = true)]
        exposure: Option<f64>,
        /// Trigger order: optimised (the shortest physical time under the
        /// motion model) or naive (the plan's nested loops).
        #[arg(long, value_enum, default_value_t = Order::Optimised)]
        order: Order,
    },
}

#[derive(Subcommand)]
enum ProfileCmd {
    /// Parse and validate a profile; print a one-line summary.
    Check {
        /// A TOML file or an embedded profile name.
        profile: String,
    },
    /// List the embedded profiles.
    List,
}

#[derive(Args)]
struct RunArgs {
    /// Rig profile: a TOML file or an embedded profile name
    /// [default: the simulated bonn-gonioreflectometer]
    #[arg(long)]
    profile: Option<String>,
    /// Drive the simulated rig (virtual time) instead of hardware.
    #[arg(long)]
    sim: bool,
    /// h1, h2, grid12x8, lamps, or a plan file [default: the profile's default plan]
    #[arg(long)]
    plan: Option<String>,
    /// Sample name, recorded in the dataset.
    #[arg(long, default_value = "sample")]
    sample: String,
    /// Run directory to create (must not exist or be empty)
    /// [default: runs/SAMPLE-PLAN-TIMESTAMP]
    #[arg(long)]
    out: Option<PathBuf>,
    /// Simulated frame size, WIDTHxHEIGHT [default: the profile's [sim] frame_size]
    #[arg(long, value_parser = rigd::rig::shot::parse_frame_size)]
    frame_size: Option<[u32; 2]>,
    /// Scene the simulated cameras render: a built-in name (`rigd sim
    /// scenes`) or a scene file [default: the profile's [sim] scene, else
    /// flat-calibration]
    #[arg(long)]
    scene: Option<String>,
    /// Operator name, recorded in the dataset.
    #[arg(long)]
    operator: Option<String>,
    /// Free-text notes, recorded in the dataset.
    #[arg(long)]
    notes: Option<String>,
    /// Exposure time for every camera, seconds (default: the profile's).
    #[arg(long, allow_negative_numbers = true)]
    exposure: Option<f64>,
    /// Trigger order: optimised (the shortest physical time under the
    /// motion model) or naive (the plan's nested loops) [default:
    /// optimised; laser plans keep theirs].
    #[arg(long, value_enum)]
    order: Option<Order>,
    /// Resume the run in this directory (all other run options come from it).
    #[arg(long, conflicts_with_all = ["profile", "plan", "out", "frame_size", "scene", "operator", "notes", "exposure", "order"])]
    resume: Option<PathBuf>,
    /// Inject a fault into the simulated firmware: DEVICE:OP:N:KIND[:sticky], fired on
    /// the Nth OP command the device receives. OP: GRBL axes home, move, info;
    /// ACL arm home, move, define, query; Modbus lamps set, ready; PTP cameras
    /// expose, transfer, set_exposure; or * for any. KIND: timeout (no answer),
    /// disconnect, bad-frame (garbled reply or frame), alarm=TEXT (the device's
    /// own fault: GRBL ALARM, Modbus exception, PTP GeneralError). Repeatable.
    /// See firmware-protocols/README.md.
    #[arg(long = "sim-fault", value_name = "SPEC")]
    sim_faults: Vec<FaultRule>,
    /// Progress display: a bar on a terminal, log lines otherwise.
    #[arg(long, value_enum, default_value = "auto")]
    progress: Progress,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Progress {
    Auto,
    Bar,
    Log,
    None,
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let result = match cli.command {
        Cmd::Plan {
            command:
                PlanCmd::Show {
                    plan,
                    profile,
                    json,
                    exposure,
                    order,
                },
        } => plan_show(&plan, &profile, json, exposure, order).map(|_| ExitCode::SUCCESS),
        Cmd::Profile { command } => profile_cmd(command).map(|_| ExitCode::SUCCESS),
        Cmd::Run(args) => run(args),
        Cmd::Sim {
            command:
                SimCmd::Serve {
                    profile,
                    speed,
                    write_profile,
                    sim_faults,
                },
        } => sim_serve(&profile, speed, write_profile, sim_faults),
        Cmd::Process {
            command: ProcessCmd::PhotometricStereo(args),
        } => photometric_stereo(args).map(|_| ExitCode::SUCCESS),
        Cmd::Process {
            command: ProcessCmd::Rectify(args),
        } => rectify(args).map(|_| ExitCode::SUCCESS),
        Cmd::Process {
            command: ProcessCmd::Btf(args),
        } => btf(args).map(|_| ExitCode::SUCCESS),
        Cmd::Process {
            command: ProcessCmd::Fit(args),
        } => fit(args).map(|_| ExitCode::SUCCESS),
        Cmd::Process {
            command: ProcessCmd::Mdf(args),
        } => mdf(args).map(|_| ExitCode::SUCCESS),
        Cmd::Process {
            command: ProcessCmd::Render(args),
        } => relight(args).map(|_| ExitCode::SUCCESS),
        Cmd::Tradeoff(args) => tradeoff(args).map(|_| ExitCode::SUCCESS),
        Cmd::Export(args) => {
            if !(1..=100).contains(&args.quality) {
                eprintln!("error: --quality {}: expected 1 ..= 100", args.quality);
                return ExitCode::from(EXIT_BAD_INPUT);
            }
            rigd::postprocess::export_run(&args.run, args.format, &args.out, args.quality)
                .map(|n| {
                    println!("{n} textures written to {}", args.out.display());
                    ExitCode::SUCCESS
                })
                .map_err(anyhow::Error::from)
        }
        Cmd::Import(args) => rigd::postprocess::import_textures(args.format, &args.path, &args.out)
            .map(|index| {
                println!(
                    "{} textures ({} views × {} lights, {}²) in {}",
                    index.frames.len(),
                    index.views.len(),
                    index.lights.len(),
                    index.size,
                    args.out.join("processed/normtextures").display()
                );
                ExitCode::SUCCESS
            })
            .map_err(anyhow::Error::from),
        Cmd::Sim {
            command: SimCmd::Render(args),
        } => sim_render(args).map(|_| ExitCode::SUCCESS),
        Cmd::Sim {
            command: SimCmd::Scenes,
        } => sim_scenes().map(|_| ExitCode::SUCCESS),
        Cmd::Serve(args) => serve(args),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(EXIT_BAD_INPUT)
        }
    }
}

fn serve(args: ServeArgs) -> anyhow::Result<ExitCode> {
    let config = rigd::server::ServerConfig {
        sim: args.sim || args.profile.is_none(),
        profile: args.profile,
        listen: args.listen,
        data_dir: args.data,
        sim_speed: args.sim_speed,
        token_file: args.token_file,
        sim_faults: args.sim_faults,
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the runtime")?;
    runtime.block_on(rigd::server::serve(config))?;
    Ok(ExitCode::SUCCESS)
}

fn profile_cmd(cmd: ProfileCmd) -> anyhow::Result<()> {
    match cmd {
        ProfileCmd::Check { profile } => {
            let p = Profile::load(&profile)?;
            println!(
                "{}: ok: profile `{}`, {} devices, default plan {}",
                profile,
                p.name,
                p.devices.len(),
                p.default_plan
            );
        }
        ProfileCmd::List => {
            for (name, _) in rigd::model::profile::EMBEDDED {
                let p = Profile::load(name)?;
                println!("{name}\t{}", p.description);
            }
        }
    }
    Ok(())
}

fn plan_show(
    plan: &str,
    profile: &str,
    json: bool,
    exposure: Option<f64>,
    order: Order,
) -> anyhow::Result<()> {
    if let Some(e) = exposure {
        if !(e.is_finite() && e > 0.0) {
            bail!("--exposure {e}: expected a positive number of seconds");
        }
    }
    let profile = Profile::load(profile)?;
    let solver = rigd::kinematics::Solver::new(&profile)?;
    let offer = rigd::schedule::rig_offer(&profile, &solver);
    let mut resolved = rigd::plan::resolve(plan, &offer)?;
    if resolved.laser.is_none() {
        resolved.order = order;
    }
    let (schedule, report) = rigd::schedule::build_with_report(&profile, &solver, &resolved);
    let estimate = Timing::new(&profile, exposure).estimate_s(&schedule, |_| false);
    let infeasible = schedule.infeasible().count();
    if json {
        let steps: Vec<serde_json::Value> = schedule
            .images
            .iter()
            .map(|img| {
                let mut v = serde_json::to_value(img).unwrap_or_default();
                if let Some(obj) = v.as_object_mut() {
                    obj.insert(
                        "setpoints".into(),
                        serde_json::to_value(&schedule.triggers[img.trigger].setpoints)
                            .unwrap_or_default(),
                    );
                }
                v
            })
            .collect();
        let out = serde_json::json!({
            "plan": schedule.plan,
            "profile": schedule.profile,
            "steps_total": schedule.images.len(),
            "triggers_total": schedule.triggers.len(),
            "infeasible_total": infeasible,
            "estimated_physical_s": estimate,
            "order": resolved.order,
            "order_report": report,
            "steps": steps,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!(
        "{:>6} {:>6} {:<8} {:>14} {:>14} {:<8} set-points",
        "image", "trig", "camera", "light θ/φ", "view θ/φ", "feasible"
    );
    for img in &schedule.images {
        let sp = &schedule.triggers[img.trigger].setpoints;
        let mut points: Vec<String> = sp.axes.iter().map(|(k, v)| format!("{k}={v:.3}")).collect();
        if let Some(arm) = &sp.arm {
            points.push(format!(
                "arm=[{}]",
                arm.iter()
                    .map(|q| format!("{q:.3}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        points.push(format!("lamp={}", sp.lamp));
        println!(
            "{:>6} {:>6} {:<8} {:>6.2}/{:>6.2} {:>6.2}/{:>6.2} {:<8} {}{}",
            img.index,
            img.trigger,
            img.camera,
            img.light.theta_deg,
            img.light.phi_deg,
            img.view.theta_deg,
            img.view.phi_deg,
            if img.feasible { "yes" } else { "NO" },
            points.join(" "),
            img.reason
                .as_ref()
                .map(|r| format!("  ({r})"))
                .unwrap_or_default()
        );
    }
    match &report.kept {
        Some(why) => println!("order: as planned ({why})"),
        None => println!(
            "order: {:?}; physical time (motion-model estimate, profile exposures): naive {}, optimised {} ({:.1} % shorter), lower bound {} ({}; optimised is within {:.3}×)",
            resolved.order,
            hms(report.naive_s),
            hms(report.optimised_s),
            100.0 * (1.0 - report.optimised_s / report.naive_s.max(1e-9)),
            hms(report.lower_bound_s),
            report.bound,
            report.gap()
        ),
    }
    println!(
        "plan {} on {}: {} images in {} triggers, {} infeasible (substituted), estimated physical capture time {}",
        schedule.plan,
        schedule.profile,
        schedule.images.len(),
        schedule.triggers.len(),
        infeasible,
        hms(estimate)
    );
    Ok(())
}

/// Seconds as `1h02m03s`.
fn hms(s: f64) -> String {
    let s = s.max(0.0).round() as u64;
    if s >= 3600 {
        format!("{}h{:02}m{:02}s", s / 3600, (s % 3600) / 60, s % 60)
    } else if s >= 60 {
        format!("{}m{:02}s", s / 60, s % 60)
    } else {
        format!("{s}s")
    }
}

fn run(args: RunArgs) -> anyhow::Result<ExitCode> {
    // The embedded default is the simulated rig; a profile file names real
    // hardware unless --sim says otherwise.
    let simulated = match &args.resume {
        Some(dir) => {
            rigd::store::read_meta(dir)
                .with_context(|| format!("cannot resume {}", dir.display()))?
                .simulated
        }
        None => args.sim || args.profile.is_none(),
    };
    if !simulated && !args.sim_faults.is_empty() {
        bail!("--sim-fault needs the simulated rig (--sim)");
    }
    if let Some(e) = args.exposure {
        if !(e.is_finite() && e > 0.0) {
            bail!("--exposure {e}: expected a positive number of seconds");
        }
    }
    // The simulated rig runs in virtual time: a paused runtime whose clock
    // jumps whenever every task waits. Hardware runs on the wall clock.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(simulated)
        .build()
        .context("cannot start the runtime")?;
    runtime.block_on(async move {
        let clock = if simulated {
            Clock::virtual_time()
        } else {
            Clock::real()
        };
        let prepared = match &args.resume {
            Some(dir) => {
                launch::prepare_resume(dir, args.sim_faults.clone(), clock, PausePolicy::Return)
                    .await
                    .with_context(|| format!("cannot resume {}", dir.display()))?
            }
            None => {
                let source = args
                    .profile
                    .clone()
                    .unwrap_or_else(|| DEFAULT_PROFILE.to_string());
                let mut profile = Profile::load(&source)?;
                if let Some(scene) = &args.scene {
                    // The run records its profile, so a resume renders
                    // the same scene.
                    rigd_sim::scene::Scene::load(scene)?;
                    profile.sim.scene = Some(scene.clone());
                }
                let plan = args
                    .plan
                    .clone()
                    .unwrap_or_else(|| profile.default_plan.clone());
                let out = args.out.clone().unwrap_or_else(|| {
                    let stamp = humantime::format_rfc3339_seconds(std::time::SystemTime::now())
                        .to_string()
                        .replace(':', "");
                    PathBuf::from("runs").join(format!(
                        "{}-{}-{}",
                        args.sample,
                        plan_stem(&plan),
                        stamp
                    ))
                });
                let req = NewRun {
                    profile_source: if std::path::Path::new(&source).exists() {
                        source.clone()
                    } else {
                        format!("<embedded {source}>")
                    },
                    profile,
                    plan,
                    sample: args.sample.clone(),
                    operator: args.operator.clone(),
                    notes: args.notes.clone(),
                    exposure_s: args.exposure,
                    frame_size: args.frame_size,
                    out,
                    simulated,
                    order: args.order,
                };
                launch::prepare_new(req, args.sim_faults.clone(), clock, PausePolicy::Return)
                    .await?
            }
        };
        drive(prepared, args.progress).await
    })
}

fn plan_stem(plan: &str) -> String {
    std::path::Path::new(plan)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "plan".into())
}

/// Runs the engine with a progress display and signal handling; prints the summary.
async fn drive(p: launch::Prepared, progress: Progress) -> anyhow::Result<ExitCode> {
    let wall = Instant::now();
    let root = p.root.clone();
    let mut events = p.handle.events.subscribe();
    let commands = p.handle.commands.clone();
    // The reporter ends when the engine drops the last event sender.
    drop(p.handle);
    let mode = match progress {
        Progress::Auto if std::io::stderr().is_terminal() => Progress::Bar,
        Progress::Auto => Progress::Log,
        m => m,
    };
    eprintln!(
        "run {}: {} images, {} already taken; estimated physical time {}",
        root.display(),
        p.frames_total,
        p.frames_done,
        hms(p.estimate_s)
    );
    if !p.retake.is_empty() {
        eprintln!(
            "retaking {} frames found missing or damaged",
            p.retake.len()
        );
    }
    let total = p.frames_total as u64;
    let end_estimate = p.t_offset_s + p.estimate_s;
    let bar = (mode == Progress::Bar).then(|| {
        let bar = indicatif::ProgressBar::new(total);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{bar:40.cyan/blue} {pos}/{len} frames  {msg}  wall {elapsed_precise} eta {eta}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar.set_position(p.frames_done as u64);
        bar
    });
    let reporter = tokio::spawn(async move {
        let mut last_log = Instant::now();
        let mut last_pct = u64::MAX;
        loop {
            let ev = match events.recv().await {
                Ok(ev) => ev,
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
                Err(_) => break,
            };
            match &ev.kind {
                EventKind::Step {
                    frames_done,
                    frames_total,
                    ..
                } => {
                    let eta = hms(end_estimate - ev.t_s);
                    let msg = format!("physical {} (eta {eta})", hms(ev.t_s));
                    if let Some(bar) = &bar {
                        bar.set_position(*frames_done as u64);
                        bar.set_message(msg);
                    } else if mode == Progress::Log {
                        let pct = *frames_done as u64 * 100 / (*frames_total as u64).max(1);
                        if pct / 5 != last_pct / 5 || last_log.elapsed() > Duration::from_secs(30) {
                            eprintln!(
                                "progress: {frames_done}/{frames_total} frames ({pct}%), {msg}"
                            );
                            last_pct = pct;
                            last_log = Instant::now();
                        }
                    }
                }
                EventKind::State { to, reason, .. } => {
                    let line = match reason {
                        Some(r) => format!("state: {to} ({r})"),
                        None => format!("state: {to}"),
                    };
                    match &bar {
                        Some(bar) => bar.println(line),
                        None if mode != Progress::None => eprintln!("{line}"),
                        None => {}
                    }
                }
                EventKind::Retry {
                    device,
                    reason,
                    attempt,
                } => {
                    let line = format!("retry {attempt} on {device}: {reason}");
                    match &bar {
                        Some(bar) => bar.println(line),
                        None if mode != Progress::None => eprintln!("{line}"),
                        None => {}
                    }
                }
                EventKind::Refused { .. } => {}
            }
        }
        if let Some(bar) = bar {
            bar.finish_and_clear();
        }
    });
    let engine = tokio::spawn(p.engine.run());
    let interrupted = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let flag = interrupted.clone();
    let signals = tokio::spawn(async move {
        rigd::server::wait_for_signal().await;
        flag.store(true, std::sync::atomic::Ordering::SeqCst);
        eprintln!("interrupted: finishing the frame in flight, then stopping (resumable)");
        let _ = commands.send(Command::Detach).await;
    });
    let outcome: Outcome = engine.await.context("engine task failed")??;
    signals.abort();
    let _ = reporter.await;
    let wall_s = wall.elapsed().as_secs_f64();
    eprintln!(
        "{}: {} of {} frames; physical duration {} ({:.1} s); wall time {:.1} s",
        outcome.state,
        outcome.frames_written,
        outcome.frames_total,
        hms(outcome.physical_s),
        outcome.physical_s,
        wall_s
    );
    Ok(match outcome.state {
        RunState::Completed => {
            println!("{}", root.display());
            ExitCode::SUCCESS
        }
        RunState::Paused if interrupted.load(std::sync::atomic::Ordering::SeqCst) => {
            ExitCode::from(EXIT_INTERRUPTED)
        }
        RunState::Paused => {
            eprintln!(
                "paused: {}; fix the cause, then `rigd run --resume {}`",
                outcome.reason.unwrap_or_default(),
                root.display()
            );
            ExitCode::from(EXIT_PAUSED)
        }
        _ => {
            eprintln!("{}", outcome.reason.unwrap_or_default());
            ExitCode::from(EXIT_ENDED_BADLY)
        }
    })
}

fn sim_render(args: RenderArgs) -> anyhow::Result<()> {
    let profile = Profile::load(&args.profile)?;
    let effects = args
        .effects
        .parse()
        .map_err(|e| anyhow::anyhow!("--effects {}: {e}", args.effects))?;
    let laser = args
        .laser
        .as_deref()
        .map(rigd::rig::shot::parse_laser)
        .transpose()
        .map_err(|e| anyhow::anyhow!("--laser {e}"))?;
    let req = rigd::rig::shot::RenderRequest {
        scene: args.scene,
        camera: args.camera,
        light: args.light,
        view: args.view,
        size: args.size,
        effects,
        seed: args.seed,
        exposure: args.exposure,
        laser,
        lamp_off: args.lamp_off,
        zoom: args.zoom,
    };
    let out = rigd::rig::shot::render(&profile, &req)?;
    let meta_path = out.write(&args.out)?;
    println!(
        "{}: scene {} from {} at light {:.1},{:.1} view {:.1},{:.1}, {}x{} {}-bit, effects {} ({:.1} ms); metadata in {}",
        args.out.display(),
        out.scene.name,
        out.camera,
        req.light.theta_deg,
        req.light.phi_deg,
        req.view.theta_deg,
        req.view.phi_deg,
        out.rendered.width,
        out.rendered.height,
        out.rendered.bit_depth,
        out.rendered.plan.live,
        out.render_ms,
        meta_path.display()
    );
    Ok(())
}

fn photometric_stereo(args: PsArgs) -> anyhow::Result<()> {
    use rigd_process::photometric_stereo as ps;
    let (mut dataset, run) = match (&args.run, &args.images, &args.lights) {
        (Some(run), _, _) => {
            let frames = rigd::postprocess::RunFrames::open(run)?;
            (
                rigd::postprocess::ps_dataset_from_run(&frames)?,
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
        _ => bail!("give a run directory, or --images DIR --lights FILE"),
    };
    let out = match (&args.out, &args.run) {
        (Some(out), _) => out.clone(),
        (None, Some(run)) => rigd::postprocess::viewer::ps_dir(run),
        (None, None) => bail!("--out DIR is needed with --images"),
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
    if let Some(run) = &run {
        if let Some(err) = rigd::postprocess::ps_error_against_truth(run, &result)? {
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

/// A progress line on stderr for long processing.
fn progress_line(what: &'static str) -> impl Fn(usize, usize) + Sync {
    move |done: usize, total: usize| {
        if done == total || done % 16 == 0 {
            eprint!("\r{what}: {done}/{total}");
            if done == total {
                eprintln!();
            }
        }
    }
}

fn rectify(args: RectifyArgs) -> anyhow::Result<()> {
    use rigd::postprocess::TextureBits;
    let bits = match args.bits.as_str() {
        "top" => TextureBits::Top8,
        "float" => TextureBits::Float,
        "half" => TextureBits::Half,
        s => match s.parse::<u8>() {
            Ok(shift) if shift <= 8 => TextureBits::Shift(shift),
            _ => bail!("--bits {s}: expected `top`, a shift 0 ..= 8, `float` or `half`"),
        },
    };
    let cfg = rigd::postprocess::RectifyConfig {
        size: args.size,
        roi: args.roi,
        final_size: args.final_size,
        blend: args.blend,
        bits,
    };
    let run = rigd::postprocess::RunFrames::open(&args.run)?;
    let started = Instant::now();
    let index = rigd::postprocess::rectify_run(&run, &cfg, &progress_line("registering"))?;
    let rms: Vec<f64> = index.frames.iter().filter_map(|f| f.rms_px).collect();
    let worst = index
        .frames
        .iter()
        .filter_map(|f| f.max_px)
        .fold(0.0, f64::max);
    let rejected: usize = index.frames.iter().map(|f| f.markers_rejected.len()).sum();
    println!(
        "{} frames registered ({} views × {} lights): marker residual RMS mean {:.3} px, worst marker {:.3} px, {} markers rejected as outliers; {}² textures in {} ({:.1} s)",
        rms.len(),
        index.views.len(),
        index.lights.len(),
        rms.iter().sum::<f64>() / rms.len().max(1) as f64,
        worst,
        rejected,
        index.size,
        args.run.join("processed/normtextures").display(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

fn btf(args: BtfArgs) -> anyhow::Result<()> {
    if args.components == 0 {
        bail!("--components 0: expected at least 1");
    }
    let report = rigd::postprocess::btf_run(
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
    println!("C\tmean RMS error over slots (1 = full scale)");
    for (c, rms) in report.mean_rms_by_components.iter().enumerate() {
        if [1, 2, 4, 8, 16, 32].contains(&(c + 1)) {
            println!("{}\t{:.5}", c + 1, rms);
        }
    }
    Ok(())
}

fn fit(args: FitArgs) -> anyhow::Result<()> {
    if !(1..=8).contains(&args.lobes) {
        bail!("--lobes {}: expected 1 ..= 8", args.lobes);
    }
    let rows =
        rigd::postprocess::fit_run(&args.run, args.lobes, &progress_line("fitting view slots"))?;
    println!("method\tmean |error|\tRMS error\tfit time\tconverged texels");
    for r in rows {
        println!(
            "{}\t{:.5}\t{:.5}\t{:.2} s\t{}",
            r.method, r.mean_abs_error, r.rms_error, r.fit_s, r.converged_texels
        );
    }
    Ok(())
}

fn tradeoff(args: TradeoffArgs) -> anyhow::Result<()> {
    let profile = Profile::load(&args.profile)?;
    let cfg = rigd::tradeoff::TradeoffConfig {
        texture: args.texture,
        held_out: args.held_out,
        components: args.components,
        render_size: args.render_size,
    };
    let started = Instant::now();
    let report = rigd::tradeoff::run(&profile, &args.scene, &cfg, &args.out, &|what| {
        eprintln!(
            "tradeoff: {what} ({:.0} s)",
            started.elapsed().as_secs_f64()
        );
    })?;
    println!(
        "{} on {}, {}² textures, {} held-out pairs",
        report.scene, report.profile, report.texture, report.held_out
    );
    println!("family\tsetting\timages\tphysical time\tbytes\terror\tcompute\tdetail");
    for r in &report.rows {
        println!(
            "{}\t{}\t{}\t{}\t{}\t{}\t{}\t{}",
            r.family,
            r.setting,
            r.images
                .map(|x| x.to_string())
                .unwrap_or_else(|| "-".into()),
            r.physical_s.map(hms).unwrap_or_else(|| "-".into()),
            r.bytes
                .map(|b| format!("{:.1} MB", b as f64 / 1e6))
                .unwrap_or_else(|| "-".into()),
            r.error
                .map(|e| match r.unit.as_str() {
                    "relative" => format!("{:.2} %", 100.0 * e),
                    "degrees" => format!("{e:.2}°"),
                    unit => format!("{e:.3} {unit}"),
                })
                .unwrap_or_else(|| "-".into()),
            r.compute_s
                .map(|t| format!("{t:.2} s"))
                .unwrap_or_else(|| "-".into()),
            r.detail.as_deref().unwrap_or(""),
        );
    }
    for m in &report.method {
        println!("note: {m}");
    }
    println!("wrote {}/tradeoff.{{csv,json,svg}}", args.out.display());
    Ok(())
}

fn relight(args: RelightArgs) -> anyhow::Result<()> {
    use rigd_process::render::{RenderSettings, Shading};
    if !(args.density.is_finite() && args.density > 0.0 && args.density <= 64.0) {
        bail!(
            "--density {}: expected more than 0 and at most 64 tiles per unit",
            args.density
        );
    }
    if !(args.shadow_alpha.is_finite() && (0.0..=45.0).contains(&args.shadow_alpha)) {
        bail!(
            "--shadow-alpha {}: expected 0 ..= 45 degrees",
            args.shadow_alpha
        );
    }
    let settings = RenderSettings {
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
    let started = Instant::now();
    let img = rigd::postprocess::viewer::render_run(&args.run, args.mesh, args.density, &settings)?;
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
    Ok(())
}

fn mdf(args: MdfArgs) -> anyhow::Result<()> {
    if !(args.sigma.is_finite() && (0.0..=20.0).contains(&args.sigma)) {
        bail!("--sigma {}: expected 0 ..= 20 pixels", args.sigma);
    }
    let run = rigd::postprocess::RunFrames::open(&args.run)?;
    let cfg = rigd::postprocess::mdf::MdfConfig {
        sigma_px: args.sigma,
        threshold: args.threshold,
        line_threshold: args.line_threshold,
        planes: args.planes,
        sources: args.sources,
    };
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
    println!("wrote {}", args.run.join("processed").join("mdf").display());
    Ok(())
}

fn sim_scenes() -> anyhow::Result<()> {
    for name in rigd_sim::scene::Scene::builtin_names() {
        let scene = rigd_sim::scene::Scene::load(name)?;
        println!(
            "{name}\t{}\n\t{}",
            scene.description,
            scene.describe_effects()
        );
    }
    Ok(())
}

fn sim_serve(
    source: &str,
    speed: f64,
    write_profile: Option<PathBuf>,
    faults: Vec<FaultRule>,
) -> anyhow::Result<ExitCode> {
    if !(speed.is_finite() && speed > 0.0) {
        bail!("--speed {speed}: expected a positive factor");
    }
    let profile = Profile::load(source)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("cannot start the runtime")?;
    runtime.block_on(async move {
        let clock = Clock::scaled(speed);
        let served = rigd::rig::serve::serve(&profile, faults, &clock)
            .await
            .context("cannot serve the simulated rig")?;
        let toml = toml::to_string(&served.profile).context("cannot write the served profile")?;
        println!("# rigd sim serve: {} at {speed}x real time", profile.name);
        for e in &served.endpoints {
            println!("#   {:<28} {:<14} {}", e.device, e.protocol, e.address);
        }
        if let Some(path) = &write_profile {
            rigd::store::write_atomic(path, toml.as_bytes())
                .with_context(|| format!("cannot write {}", path.display()))?;
            println!("# profile written to {}", path.display());
        }
        println!("{toml}");
        println!("# ready; Ctrl-C stops");
        use std::io::Write;
        let _ = std::io::stdout().flush();
        rigd::server::wait_for_signal().await;
        anyhow::Ok(ExitCode::SUCCESS)
    })
}
