//! Runs the standard module kinds as module processes. Started by a DNM, one process per module.

fn main() -> std::process::ExitCode {
    dnm_module::host_main(&dnm_modules::registry())
}
