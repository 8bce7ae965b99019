//! The built-in module kinds, standard and Beetle-One's, as one registry. The
//! `dnm-module-host` executable runs them as module processes (`dnm-module-host run LAUNCH`) and
//! describes them (`dnm-module-host describe`); the `dnm` command reads the same registry for
//! its catalogue.
//!
//! ```
//! let kinds = dnm_module_host::registry().specs();
//! assert!(kinds.iter().any(|k| k.name == "ticker"));
//! ```

/// Every built-in kind: the standard ones and Beetle-One's.
pub fn registry() -> dnm_module::Registry {
    dnm_rover::register(dnm_modules::registry())
}
