//! The station's web interface: the page (built into the binary, no JavaScript toolchain) and
//! what it asks the station for besides the command API of [`crate::http`]:
//!
//! | request | answer |
//! |---|---|
//! | `GET /` | the page: task generation, the module connection view and the onboard sequences (uploaded, started, paused, resumed, cancelled through `POST /commands`; their state from `GET /api/live`'s link) |
//! | `GET /api/live` | the connection layer now: the wiring in force, every DNM's glance (states, restarts, hangs, rate, CPU, switches, events), the link, the station |
//! | `GET /api/netlist` | the netlist in force: revision, file, text, and the text as a JSON document the page edits |
//! | `GET /api/kinds` | every kind the rover can run: ports, message types, parameters |
//! | `POST /api/check` with `{"file":"x.toml","doc":{…}}` | the document as netlist text and `dnm check`'s located errors (`line`, `column`, `field`, `message`, `help`) against the rover's kinds |
//! | `GET /api/watch?module=M&port=P&since=N` | the output's samples after `N`, decoded (it is watched while asked for) |
//! | `GET /api/frame?module=M&port=P` | a watched camera output's newest frame, JPEG |

use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dnm_netlist::{Catalog, DescribeError, KindSource, KindSpec, Netlist};
use serde::Serialize;

use crate::view::SystemView;

pub(crate) const INDEX_HTML: &str = include_str!("../web/index.html");
pub(crate) const APP_JS: &str = include_str!("../web/app.js");
pub(crate) const STYLE_CSS: &str = include_str!("../web/style.css");

/// How long the rover's kinds are kept before they are asked again.
const KINDS_TTL: Duration = Duration::from_secs(60);

/// The order sections are written in (others follow, alphabetically).
const SECTIONS: [&str; 5] = ["system", "kind", "dnm", "module", "task"];

/// One located problem of a draft, as `dnm check --json` gives it.
#[derive(Debug, Clone, Serialize)]
pub struct Problem {
    pub line: Option<usize>,
    pub column: Option<usize>,
    pub field: String,
    pub message: String,
    pub help: Option<String>,
}

/// A draft checked: its netlist text and what is wrong with it.
#[derive(Debug, Clone, Serialize)]
pub struct Checked {
    pub ok: bool,
    pub file: String,
    /// The draft as netlist text (what an apply sends and an export saves).
    pub toml: String,
    pub errors: Vec<Problem>,
}

/// The web interface's state: the view of the system and the rover's kinds.
pub struct Web {
    pub view: SystemView,
    kinds: Mutex<Option<(Instant, u64, Arc<Catalog>)>>,
}

impl std::fmt::Debug for Web {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Web").finish_non_exhaustive()
    }
}

impl Web {
    pub fn new(view: SystemView) -> Self {
        Self {
            view,
            kinds: Mutex::new(None),
        }
    }

    /// The rover's kinds, asked again when the revision in force changes or after a minute.
    pub fn kinds(&self) -> Arc<Catalog> {
        let revision = self.view.live().wiring.map_or(0, |w| w.revision);
        if let Ok(k) = self.kinds.lock()
            && let Some((at, rev, c)) = k.as_ref()
            && *rev == revision
            && at.elapsed() < KINDS_TTL
            && c.iter().next().is_some()
        {
            return c.clone();
        }
        let c = Arc::new(self.view.kinds());
        if let Ok(mut k) = self.kinds.lock() {
            *k = Some((Instant::now(), revision, c.clone()));
        }
        c
    }
}

/// Why a netlist's text is no document the page can edit.
#[derive(Debug, thiserror::Error)]
pub enum DocumentError {
    #[error("{0}")]
    Toml(#[from] toml::de::Error),
    #[error("{0}")]
    Json(#[from] serde_json::Error),
}

/// A netlist's text as the JSON document the page edits (an error: it is not TOML).
pub fn document(text: &str) -> Result<serde_json::Value, DocumentError> {
    let table: toml::Table = toml::from_str(text)?;
    Ok(serde_json::to_value(table)?)
}

/// Why a draft could not be written as netlist text.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error(
        "the draft is not a netlist document ({0}); every value must be text, a number, true/false, a list or a table"
    )]
    NotADocument(#[source] toml::ser::Error),
    #[error("writing `{key}`: {source}")]
    Write {
        key: String,
        #[source]
        source: toml::ser::Error,
    },
}

/// A JSON document as netlist text, sections in the usual order.
pub fn render(doc: &serde_json::Value) -> Result<String, RenderError> {
    let table: toml::Table = toml::Table::try_from(doc).map_err(RenderError::NotADocument)?;
    let mut keys: Vec<&String> = table.keys().collect();
    keys.sort_by_key(|k| {
        (
            SECTIONS
                .iter()
                .position(|s| s == k)
                .unwrap_or(SECTIONS.len()),
            k.to_string(),
        )
    });
    let mut out = String::from("# Written by the ground station's task editor.\n");
    for k in keys {
        let mut one = toml::Table::new();
        one.insert(k.clone(), table[k].clone());
        let text = toml::to_string(&one).map_err(|source| RenderError::Write {
            key: k.clone(),
            source,
        })?;
        out.push('\n');
        out.push_str(&text);
    }
    Ok(out)
}

/// Checks a draft the way `dnm check` does, against the rover's kinds. A kind declared with
/// `exec` must be one the rover has installed (the station runs nothing).
pub fn check(doc: &serde_json::Value, file: &str, kinds: &Catalog) -> Checked {
    let file = sanitize_file(file);
    let problem = |field: &str, message: String, help: Option<&str>| Problem {
        line: None,
        column: None,
        field: field.into(),
        message,
        help: help.map(str::to_string),
    };
    let text = match render(doc) {
        Ok(t) => t,
        Err(e) => {
            return Checked {
                ok: false,
                file,
                toml: String::new(),
                errors: vec![problem("", e.to_string(), None)],
            };
        }
    };
    if kinds.iter().next().is_none() {
        return Checked {
            ok: false,
            file,
            toml: text,
            errors: vec![problem(
                "",
                "the station has not heard the rover's kinds yet".into(),
                Some("wait for the link to the rover to come up"),
            )],
        };
    }
    let mut describe = |exec: &Path| -> Result<KindSpec, DescribeError> {
        let wanted = exec.file_name();
        kinds
            .iter()
            .find(|e| matches!(&e.source, KindSource::Exec { path } if Path::new(path).file_name() == wanted))
            .map(|e| e.spec.clone())
            .ok_or_else(|| {
                DescribeError::NotRun(format!(
                    "the rover has no module executable `{}` installed",
                    exec.display()
                ))
            })
    };
    match Netlist::parse(Path::new(&file), &text, kinds, &mut describe) {
        Ok(_) => Checked {
            ok: true,
            file,
            toml: text,
            errors: Vec::new(),
        },
        Err(e) => Checked {
            ok: false,
            file,
            toml: text,
            errors: e
                .diagnostics
                .into_iter()
                .map(|d| Problem {
                    line: d.location.map(|l| l.0),
                    column: d.location.map(|l| l.1),
                    field: d.field,
                    message: d.message,
                    help: d.help,
                })
                .collect(),
        },
    }
}

/// A file name for the draft: a plain `name.toml`, never a path.
fn sanitize_file(file: &str) -> String {
    let base: String = file
        .rsplit('/')
        .next()
        .unwrap_or_default()
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        .collect();
    let base = base.trim_start_matches('.');
    if base.is_empty() {
        "draft.toml".into()
    } else if base.ends_with(".toml") {
        base.into()
    } else {
        format!("{base}.toml")
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_document_round_trips_with_sections_in_order() {
        let text = "[[module]]\nname = \"a\"\nkind = \"ticker\"\n\n[system]\nname = \"s\"\n\n[task.t]\nlinks = [\"a.out -> b.in\"]\n";
        let doc = document(text).unwrap();
        let out = render(&doc).unwrap();
        let system = out.find("[system]").unwrap();
        let module = out.find("[[module]]").unwrap();
        let task = out.find("[task.t]").unwrap();
        assert!(system < module && module < task, "{out}");
        assert_eq!(document(&out).unwrap(), doc);
    }

    #[test]
    fn a_draft_that_is_not_a_document_says_so() {
        let c = check(&serde_json::json!({"system": null}), "x", &Catalog::new());
        assert!(!c.ok);
        assert!(
            c.errors[0].message.contains("not a netlist document"),
            "{c:?}"
        );
    }

    #[test]
    fn file_names_stay_plain() {
        assert_eq!(sanitize_file("../../etc/passwd"), "passwd.toml");
        assert_eq!(sanitize_file("my task.toml"), "mytask.toml");
        assert_eq!(sanitize_file(""), "draft.toml");
        assert_eq!(sanitize_file(".hidden"), "hidden.toml");
    }
}
