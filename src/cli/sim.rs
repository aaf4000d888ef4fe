//! `rigd sim`: the simulated rig's firmware served for tools outside rigd,
//! one rendered frame, and the list of scenes.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use rigd::model::profile::DEFAULT_PROFILE;
use rigd_core::geometry::Direction;
use rigd_core::Clock;
use rigd_sim::FaultRule;

use super::exit::bad_input;

/// Runs a `rigd sim` command.
pub fn run(cmd: SimCmd) -> Result<ExitCode> {
    match cmd {
        SimCmd::Serve {
            profile,
            speed,
            write_profile,
            sim_faults,
        } => sim_serve(&profile, speed, write_profile, sim_faults),
        SimCmd::Render(args) => sim_render(args).map(|()| ExitCode::SUCCESS),
        SimCmd::Scenes => sim_scenes().map(|()| ExitCode::SUCCESS),
    }
}

#[derive(Subcommand)]
pub enum SimCmd {
    /// Serve a profile's simulated firmware in real time, as hardware would be
    /// reached: serial devices (GRBL, ACL) on pseudo-terminals, relay modules on
    /// Modbus TCP on 127.0.0.1 (RTU modules also on a pty), cameras as PTP/IP
    /// cameras on 127.0.0.1 (gphoto2 drives them too). Prints the endpoints and a profile that points at them
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

#[derive(Args)]
pub struct RenderArgs {
    /// Rig profile: a TOML file or an embedded profile name.
    #[arg(long, default_value = DEFAULT_PROFILE)]
    pub profile: String,
    /// Scene: a built-in name (`rigd sim scenes`) or a scene file
    /// [default: the profile's [sim] scene, else flat-calibration]
    #[arg(long)]
    pub scene: Option<String>,
    /// Light direction θ,φ in degrees, sample frame.
    #[arg(long, value_parser = rigd::model::text::parse_direction, default_value = "0,0")]
    pub light: Direction,
    /// View direction θ,φ in degrees, sample frame.
    #[arg(long, value_parser = rigd::model::text::parse_direction, default_value = "0,0")]
    pub view: Direction,
    /// Camera of the profile [default: its first]
    #[arg(long)]
    pub camera: Option<String>,
    /// Frame size WIDTHxHEIGHT [default: the profile's [sim] frame_size]
    #[arg(long, value_parser = rigd::model::text::parse_frame_size)]
    pub size: Option<[u32; 2]>,
    /// Effect switches: `all`, `none`, or a list like `+interreflection,-noise`.
    #[arg(long, default_value = "")]
    pub effects: String,
    /// Noise seed of this frame.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Exposure relative to the camera's nominal one.
    #[arg(long, default_value_t = 1.0)]
    pub exposure: f64,
    /// A laser line: the plane crosses the sample plane at X mm, tilted
    /// TILT degrees (`X` or `X,TILT`, tilt 30 by default).
    #[arg(long, value_name = "X[,TILT]")]
    pub laser: Option<String>,
    /// Lamp off: only the laser lights the sample.
    #[arg(long)]
    pub lamp_off: bool,
    /// Focal length multiplier: a longer lens for a closer look.
    #[arg(long, default_value_t = 1.0)]
    pub zoom: f64,
    /// Output PNG; the metadata goes to the same name with .json.
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

fn sim_render(args: RenderArgs) -> Result<()> {
    let profile = rigd::rig::load_profile(&args.profile)?;
    let effects = args
        .effects
        .parse()
        .map_err(|e| bad_input(format!("--effects {}: {e}", args.effects)))?;
    let laser = args
        .laser
        .as_deref()
        .map(rigd::rig::sim::shot::parse_laser)
        .transpose()
        .map_err(|e| bad_input(format!("--laser {e}")))?;
    let req = rigd::rig::sim::shot::RenderRequest {
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
    let out = rigd::rig::sim::shot::render(&profile, &req)?;
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

fn sim_scenes() -> Result<()> {
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
) -> Result<ExitCode> {
    if !(speed.is_finite() && speed > 0.0) {
        return Err(bad_input(format!(
            "--speed {speed}: expected a positive factor"
        )));
    }
    let profile = rigd::rig::load_profile(source)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("cannot start the runtime")?;
    runtime.block_on(async move {
        let clock = Clock::scaled(speed);
        let served = rigd::rig::sim::serve::serve(&profile, faults, &clock)
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
