//! `rigd serve`: the daemon with its HTTP API and dashboard.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::Args;
use rigd::rig::FaultRule;

#[derive(Args)]
pub struct ServeArgs {
    /// Rig profile: a TOML file or an embedded profile name; a file means
    /// its hardware unless --sim [default: the simulated bonn-gonioreflectometer]
    #[arg(long)]
    pub profile: Option<String>,
    /// Drive the simulated rig (implied without --profile).
    #[arg(long)]
    pub sim: bool,
    /// Address to listen on. Reads are open to loopback clients; every
    /// mutating route needs the bearer token.
    #[arg(long, default_value = rigd::server::DEFAULT_LISTEN)]
    pub listen: std::net::SocketAddr,
    /// Data directory: runs/<id>/ (run directories), queue.json, token.
    #[arg(long = "data", default_value = rigd::server::DEFAULT_DATA)]
    pub data: PathBuf,
    /// Simulated physical seconds per wall second. The default 200 runs a
    /// demo H1 capture on the simulated Bonn rig (6561 images, about 10 h
    /// physical) in about 3 minutes.
    #[arg(long, default_value_t = rigd::server::DEFAULT_SIM_SPEED, allow_negative_numbers = true)]
    pub sim_speed: f64,
    /// File holding the API token [default: DATA/token, generated at first
    /// start with mode 0600].
    #[arg(long)]
    pub token_file: Option<PathBuf>,
    /// Inject a fault into the simulated rig of every new run (same SPEC as
    /// `rigd run --sim-fault`, e.g. camera:transfer:3:disconnect). Repeatable.
    #[cfg(feature = "sim")]
    #[arg(long = "sim-fault", value_name = "SPEC")]
    pub sim_faults: Vec<FaultRule>,
    /// The other rigs' daemons, shown with this one in the dashboard's
    /// "Rigs" panel (GET /api/v1/peers), where their runs can be paused or
    /// aborted: a TOML file of [[peer]] tables with name, url and token or
    /// token_file (docs/api.md, "Peers"). A bad file stops the start.
    #[arg(long, value_name = "FILE")]
    pub peers: Option<PathBuf>,
    /// The daemon's configuration: a TOML file whose [processing] table
    /// says where process jobs run, e.g. executor = "slurm" and a
    /// [processing.slurm] table with partition, shared_paths, … (docs/scaling.md),
    /// and whose [http] table sets the HTTP server's timeouts and limits
    /// (docs/api.md, "Security").
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
}

/// The file of `rigd serve --config`.
#[derive(Debug, Default, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
struct DaemonFile {
    processing: rigd::postprocess::executor::ProcessingConfig,
    http: rigd::server::http::HttpLimits,
}

fn read_config(path: &std::path::Path) -> Result<DaemonFile> {
    rigd_core::config::load(
        path,
        rigd_core::read::TEXT_LIMIT,
        rigd_core::config::Format::Toml,
    )
    .map_err(|e| super::exit::bad_input(e.to_string()))
}

/// Runs `rigd serve` until a signal stops it.
pub fn run(args: ServeArgs) -> Result<ExitCode> {
    let peers = match &args.peers {
        Some(file) => rigd::server::peers::load(file)?,
        None => Vec::new(),
    };
    let file = match &args.config {
        Some(path) => read_config(path)?,
        None => DaemonFile::default(),
    };
    let config = rigd::server::ServerConfig {
        sim: args.sim || args.profile.is_none(),
        profile: args.profile,
        listen: args.listen,
        data_dir: args.data,
        sim_speed: args.sim_speed,
        token_file: args.token_file,
        #[cfg(feature = "sim")]
        sim_faults: args.sim_faults,
        #[cfg(not(feature = "sim"))]
        sim_faults: Vec::<FaultRule>::new(),
        peers,
        processing: file.processing,
        http: file.http,
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the runtime")?;
    runtime.block_on(rigd::server::serve(config))?;
    Ok(ExitCode::SUCCESS)
}
