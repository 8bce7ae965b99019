//! `dnm-router`: a Zenoh router with our configurations (`configs/zenoh/*-router.json5`), for
//! machines that join networks without hosting DNMs. `dnm router` does the same.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use dnm_router::{ZenohOptions, run_router};

#[derive(Parser, Debug)]
#[command(
    name = "dnm-router",
    version,
    about = "Zenoh router joining the rover's and the ground's networks"
)]
struct Cli {
    /// Zenoh JSON5 configuration, e.g. configs/zenoh/rover-router.json5.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Endpoint to listen on (repeatable), e.g. tcp/0.0.0.0:7447.
    #[arg(long)]
    listen: Vec<String>,
    /// Endpoint of another router to connect to (repeatable).
    #[arg(long)]
    connect: Vec<String>,
    /// No multicast scouting.
    #[arg(long)]
    no_multicast: bool,
}

fn main() -> ExitCode {
    dnm_router::init_logging("info");
    let cli = Cli::parse();
    let options = ZenohOptions {
        config: cli.config,
        mode: None,
        listen: cli.listen,
        connect: cli.connect,
        no_multicast: cli.no_multicast,
    };
    match run_router(&options) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", dnm_router::error_report(&e));
            ExitCode::FAILURE
        }
    }
}
