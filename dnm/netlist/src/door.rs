//! The one door through which a netlist from outside a process comes in: an operator's apply
//! or module edit, an authority's transaction or adoption, the netlist a running system hands a
//! DNM that joins it, the netlist a restarted authority finds in force. Every such path takes
//! the text through [`NetlistDoor::accept`], so what may come in is decided here once: the
//! parser the process was given (which decides which external kinds may be described; a DNM
//! gives one that never runs an executable outside its installed module folder) and this
//! system's name.
//!
//! The tests that try to get past it: this file's (another system's netlist, an invalid one, an
//! executable the parser refuses); the `dnm` crate's `parse_remote_netlist` test (the parser a
//! DNM and an authority give their door runs nothing outside `DNM_MODULE_DIR`);
//! `tests/security.rs` `only_the_operator_commands_a_secured_system` and `tests/zenoh_link.rs`
//! (an operator's apply naming `/usr/bin/touch` runs nothing, on a secured and an open system);
//! `tests/ground.rs` (an invalid netlist and another system's, applied through the authority);
//! `tests/fuzz.rs` (hostile values in every field of a netlist sent as a command).

use std::path::Path;
use std::sync::Arc;

use crate::{Netlist, NetlistError};

/// Validates netlist text; the path names it in errors.
pub type ParseNetlist = dyn Fn(&Path, &str) -> Result<Netlist, NetlistError> + Send + Sync;

/// Why a netlist from outside was not taken. Nothing running changed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AcceptError {
    /// It does not validate here (the diagnostics say where and what to do).
    #[error("netlist refused, nothing changed:\n{0}")]
    Invalid(#[source] NetlistError),
    /// It is another system's.
    #[error("netlist is for system `{netlist}`, this is `{here}`; nothing changed")]
    OtherSystem { netlist: String, here: String },
}

impl AcceptError {
    /// The refusal in a transaction's words (no "nothing changed": the transaction says what
    /// happens to it).
    pub fn in_transaction(&self) -> String {
        match self {
            AcceptError::Invalid(e) => format!("netlist refused:\n{e}"),
            AcceptError::OtherSystem { netlist, here } => {
                format!("netlist is for system `{netlist}`, this is `{here}`")
            }
        }
    }
}

/// Takes netlists from outside for one system (see the module documentation).
#[derive(Clone)]
pub struct NetlistDoor {
    system: String,
    parse: Arc<ParseNetlist>,
}

impl std::fmt::Debug for NetlistDoor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NetlistDoor")
            .field("system", &self.system)
            .finish_non_exhaustive()
    }
}

impl NetlistDoor {
    /// A door of `system` validating with `parse`.
    pub fn new(system: impl Into<String>, parse: Arc<ParseNetlist>) -> Self {
        Self {
            system: system.into(),
            parse,
        }
    }

    /// The system it takes netlists for.
    pub fn system(&self) -> &str {
        &self.system
    }

    /// Takes `text`, sent as `file`: it must validate with this door's parser and be a netlist
    /// of this door's system.
    pub fn accept(&self, file: &str, text: &str) -> Result<Netlist, AcceptError> {
        let netlist = (self.parse)(Path::new(file), text).map_err(AcceptError::Invalid)?;
        if netlist.system != self.system {
            return Err(AcceptError::OtherSystem {
                netlist: netlist.system,
                here: self.system.clone(),
            });
        }
        Ok(netlist)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::Catalog;

    fn door(system: &str) -> NetlistDoor {
        NetlistDoor::new(
            system,
            Arc::new(|file: &Path, text: &str| {
                Netlist::parse(file, text, &Catalog::new(), &mut |exec: &Path| {
                    Err(format!("`{}` is not run here", exec.display()).into())
                })
            }),
        )
    }

    const EMPTY: &str = "[system]\nname = \"beetle\"\n";

    #[test]
    fn takes_a_valid_netlist_of_its_system() {
        let n = door("beetle").accept("sent.toml", EMPTY);
        assert_eq!(n.map(|n| n.system), Ok("beetle".to_string()));
    }

    #[test]
    fn refuses_another_systems_netlist() {
        let e = door("other").accept("sent.toml", EMPTY).unwrap_err();
        assert!(matches!(e, AcceptError::OtherSystem { .. }), "{e}");
        assert!(
            e.to_string()
                .contains("netlist is for system `beetle`, this is `other`")
        );
    }

    #[test]
    fn refuses_an_invalid_netlist_naming_the_file() {
        let e = door("beetle")
            .accept("sent.toml", "[system]\nname = 3\n")
            .unwrap_err();
        let AcceptError::Invalid(inner) = &e else {
            panic!("{e}");
        };
        assert_eq!(inner.file, Path::new("sent.toml"));
        assert!(
            e.to_string()
                .starts_with("netlist refused, nothing changed:\n")
        );
    }

    #[test]
    fn never_runs_what_its_parser_refuses() {
        let text = format!(
            "{EMPTY}[[module]]\nname = \"m\"\nkind = \"x\"\n\n[kind.x]\nexec = \"/bin/sh\"\n"
        );
        let e = door("beetle").accept("sent.toml", &text).unwrap_err();
        assert!(e.to_string().contains("is not run here"), "{e}");
    }
}
