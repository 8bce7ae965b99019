//! One module added, replaced or removed in a netlist's text: what `dnm module` and a ground
//! station's module commands do to the netlist in force.

use dnm_proto::station::ModuleEdit;

/// Why a module edit could not be made to the netlist's text. Nothing changed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ModuleEditError {
    #[error("parameter `{0}` must be `key=value`")]
    Parameter(String),
    #[error("link `{0}` must be `TASK:from.port -> to.port`")]
    Link(String),
    #[error("module `{0}` exists already; replace it or pick another name")]
    Exists(String),
    #[error("the netlist in force has no module `{0}`")]
    NoModule(String),
    /// The netlist's text is not the shape a netlist has (`what` says where).
    #[error("the netlist in force {what}")]
    Shape { what: String },
    #[error("writing the edited netlist: {0}")]
    Write(#[source] toml::ser::Error),
}

fn shape(what: &str) -> ModuleEditError {
    ModuleEditError::Shape {
        what: what.to_string(),
    }
}

/// `key=value`, the value read as TOML (a bare word is a string).
pub fn param_value(kv: &str) -> Result<(String, toml::Value), ModuleEditError> {
    let (k, v) = kv
        .split_once('=')
        .ok_or_else(|| ModuleEditError::Parameter(kv.to_string()))?;
    let v = v.trim();
    let value = format!("v = {v}")
        .parse::<toml::Table>()
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(v.to_string()));
    Ok((k.trim().to_string(), value))
}

fn params(list: &[String]) -> Result<toml::Table, ModuleEditError> {
    let mut p = toml::Table::new();
    for kv in list {
        let (k, v) = param_value(kv)?;
        p.insert(k, v);
    }
    Ok(p)
}

/// The netlist `text` with `edit` made, and a sentence saying what changed. The result still
/// has to be validated (the kind may not exist, a link may not fit).
pub fn edit_netlist(text: &str, edit: &ModuleEdit) -> Result<(String, String), ModuleEditError> {
    let mut doc: toml::Table = text
        .parse()
        .map_err(|e| shape(&format!("does not parse: {e}")))?;
    let modules = doc
        .entry("module")
        .or_insert_with(|| toml::Value::Array(Vec::new()))
        .as_array_mut()
        .ok_or_else(|| shape("has a `module` that is not an array"))?;
    let what = match edit {
        ModuleEdit::Add {
            name,
            kind,
            dnm,
            params: ps,
            links,
        } => {
            if modules
                .iter()
                .any(|m| m.get("name").and_then(|n| n.as_str()) == Some(name.as_str()))
            {
                return Err(ModuleEditError::Exists(name.clone()));
            }
            let mut m = toml::Table::new();
            m.insert("name".into(), name.clone().into());
            m.insert("kind".into(), kind.clone().into());
            if let Some(d) = dnm {
                m.insert("dnm".into(), d.clone().into());
            }
            let p = params(ps)?;
            if !p.is_empty() {
                m.insert("params".into(), p.into());
            }
            modules.push(m.into());
            for l in links {
                let (task, link) = l
                    .split_once(':')
                    .ok_or_else(|| ModuleEditError::Link(l.clone()))?;
                let to = link
                    .split_once("->")
                    .map(|(_, t)| t.trim().to_string())
                    .unwrap_or_default();
                let tasks = doc
                    .entry("task")
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                    .as_table_mut()
                    .ok_or_else(|| shape("has a `task` that is not a table"))?;
                let t = tasks
                    .entry(task.trim())
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                    .as_table_mut()
                    .ok_or_else(|| shape("has a task that is not a table"))?;
                let list = t
                    .entry("links")
                    .or_insert_with(|| toml::Value::Array(Vec::new()))
                    .as_array_mut()
                    .ok_or_else(|| shape("has `links` that are not an array"))?;
                // The new link takes over the input it feeds.
                list.retain(|x| {
                    x.as_str()
                        .and_then(|s| s.split_once("->"))
                        .is_none_or(|(_, t)| t.trim() != to)
                });
                list.push(link.trim().into());
            }
            format!("added module `{name}`")
        }
        ModuleEdit::Remove { name } => {
            let before = modules.len();
            modules.retain(|m| m.get("name").and_then(|n| n.as_str()) != Some(name.as_str()));
            if modules.len() == before {
                return Err(ModuleEditError::NoModule(name.clone()));
            }
            if let Some(tasks) = doc.get_mut("task").and_then(|t| t.as_table_mut()) {
                let prefix = format!("{name}.");
                for (_, t) in tasks.iter_mut() {
                    if let Some(list) = t.get_mut("links").and_then(|l| l.as_array_mut()) {
                        list.retain(|x| {
                            x.as_str().is_none_or(|s| {
                                !s.split("->").any(|side| side.trim().starts_with(&prefix))
                            })
                        });
                    }
                }
            }
            format!("removed module `{name}`")
        }
        ModuleEdit::Replace {
            name,
            kind,
            params: ps,
        } => {
            let m = modules
                .iter_mut()
                .find(|m| m.get("name").and_then(|n| n.as_str()) == Some(name.as_str()))
                .and_then(|m| m.as_table_mut())
                .ok_or_else(|| ModuleEditError::NoModule(name.clone()))?;
            // Another kind starts from its own defaults; the same kind keeps the parameters
            // not given (an operator changing one does not reset the others).
            let same_kind = kind
                .as_deref()
                .is_none_or(|k| m.get("kind").and_then(|v| v.as_str()) == Some(k));
            if let Some(k) = kind.as_ref().filter(|_| !same_kind) {
                m.insert("kind".into(), k.clone().into());
                m.remove("params");
            }
            if !ps.is_empty() {
                let mut merged = match m.get("params") {
                    Some(toml::Value::Table(t)) => t.clone(),
                    Some(_) => {
                        return Err(shape(&format!(
                            "has `params` of `{name}` that are not a table"
                        )));
                    }
                    None => toml::Table::new(),
                };
                merged.extend(params(ps)?);
                m.insert("params".into(), merged.into());
            }
            format!("replaced module `{name}`")
        }
    };
    let text = toml::to_string(&doc).map_err(ModuleEditError::Write)?;
    Ok((text, what))
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = r#"
[system]
name = "s"
[[module]]
name = "a"
kind = "counter"
[[module]]
name = "b"
kind = "printer"
[task.t]
links = ["a.out -> b.in"]
"#;

    #[test]
    fn remove_drops_the_module_and_its_links() {
        let (text, what) = edit_netlist(TEXT, &ModuleEdit::Remove { name: "a".into() }).unwrap();
        assert_eq!(what, "removed module `a`");
        assert!(
            !text.contains("counter") && !text.contains("a.out"),
            "{text}"
        );
    }

    #[test]
    fn replace_sets_kind_and_params_keeps_the_others_of_the_same_kind_and_refuses_unknown_modules()
    {
        let edit = ModuleEdit::Replace {
            name: "b".into(),
            kind: Some("logger".into()),
            params: vec!["level=2".into(), "tag=x".into()],
        };
        let (text, _) = edit_netlist(TEXT, &edit).unwrap();
        assert!(
            text.contains("logger") && text.contains("level = 2"),
            "{text}"
        );
        assert!(text.contains(r#"tag = "x""#), "{text}");
        // The same kind: the parameters given change, the others stay.
        let (text, _) = edit_netlist(
            &text,
            &ModuleEdit::Replace {
                name: "b".into(),
                kind: None,
                params: vec!["level=3".into()],
            },
        )
        .unwrap();
        assert!(
            text.contains("level = 3") && text.contains(r#"tag = "x""#),
            "{text}"
        );
        let (text, _) = edit_netlist(
            &text,
            &ModuleEdit::Replace {
                name: "b".into(),
                kind: Some("logger".into()),
                params: vec!["level=4".into()],
            },
        )
        .unwrap();
        assert!(text.contains("level = 4") && text.contains("tag"), "{text}");
        // Another kind starts from its own defaults.
        let (text, _) = edit_netlist(
            &text,
            &ModuleEdit::Replace {
                name: "b".into(),
                kind: Some("printer".into()),
                params: vec!["width=80".into()],
            },
        )
        .unwrap();
        assert!(
            text.contains("width = 80") && !text.contains("level") && !text.contains("tag"),
            "{text}"
        );
        let e = edit_netlist(TEXT, &ModuleEdit::Remove { name: "z".into() }).unwrap_err();
        assert_eq!(e, ModuleEditError::NoModule("z".into()));
        assert!(e.to_string().contains("no module `z`"), "{e}");
    }
}
