//! Runs the built-in module kinds (standard and Beetle-One) as module processes. Started by a
//! DNM, one process per module. Links the kinds and the module SDK only, not the DNM.

fn main() -> std::process::ExitCode {
    dnm_module::host_main(&dnm_module_host::registry())
}
