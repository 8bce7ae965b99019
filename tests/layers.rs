//! The tree reads as the architecture: the DNM core knows neither Zenoh nor MCAP, module
//! processes link neither the DNM nor Zenoh nor MCAP, the wire types need serde only, and no
//! file imports another in a circle.

#![allow(clippy::unwrap_used)] // test helpers: failing loudly is right

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The packages `package` depends on (normal dependencies, all the way down).
fn dependencies(package: &str) -> BTreeSet<String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "tree",
            "--offline",
            "-e",
            "normal",
            "--prefix",
            "none",
            "-p",
            package,
        ])
        .arg("--manifest-path")
        .arg(workspace().join("Cargo.toml"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .collect()
}

#[test]
fn layers_depend_only_downwards() {
    let core = dependencies("dnm-core");
    for banned in [
        "zenoh",
        "mcap",
        "dnm-modules",
        "dnm-rover",
        "dnm-zenoh",
        "dnm-record",
    ] {
        assert!(!core.contains(banned), "dnm-core depends on {banned}");
    }
    let host = dependencies("dnm-module-host");
    for banned in [
        "zenoh",
        "mcap",
        "dnm-core",
        "dnm",
        "dnm-zenoh",
        "dnm-record",
    ] {
        assert!(
            !host.contains(banned),
            "dnm-module-host depends on {banned}"
        );
    }
    // Rerun (its SDK, and everything under it) is the monitor's alone: no DNM, module host,
    // station or the `dnm` command links it.
    for package in [
        "dnm",
        "dnm-core",
        "dnm-module-host",
        "dnm-zenoh",
        "dnm-record",
        "dnm-authority",
        "dnm-ground",
    ] {
        let deps = dependencies(package);
        for banned in ["rerun", "re_sdk", "re_log_encoding"] {
            assert!(!deps.contains(banned), "{package} depends on {banned}");
        }
    }
    assert!(dependencies("dnm-monitor").contains("rerun"));
    // The ground station (its web interface included) speaks the protocol and reads netlists:
    // it runs no DNM, no module and no shared memory.
    let ground = dependencies("dnm-ground");
    let ours: Vec<&String> = ground.iter().filter(|p| p.starts_with("dnm")).collect();
    assert_eq!(
        ours,
        ["dnm-ground", "dnm-netlist", "dnm-proto"],
        "dnm-ground depends on our crates"
    );
    assert!(
        !ground.contains("iceoryx2"),
        "dnm-ground depends on iceoryx2"
    );
    let proto = dependencies("dnm-proto");
    let ours: Vec<&String> = proto.iter().filter(|p| p.starts_with("dnm")).collect();
    assert_eq!(ours, ["dnm-proto"], "dnm-proto depends on our crates");
    assert!(proto.contains("serde") && !proto.contains("zenoh") && !proto.contains("iceoryx2"));
}

/// The code of a file without comments and without its test module.
fn code(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap();
    let text = text.split("#[cfg(test)]").next().unwrap_or_default();
    text.lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// Identifiers after `crate::` and inside `use crate::{...}`.
fn crate_refs(code: &str) -> Vec<String> {
    let ident = |s: &str| -> String {
        s.chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect()
    };
    let mut out = Vec::new();
    for (i, _) in code.match_indices("crate::") {
        let rest = &code[i + "crate::".len()..];
        if let Some(group) = rest.strip_prefix('{') {
            let group = &group[..group.find('}').unwrap_or(group.len())];
            out.extend(group.split(',').map(|item| ident(item.trim())));
        } else {
            out.push(ident(rest));
        }
    }
    out.retain(|s| !s.is_empty());
    out
}

/// Module files of one crate's `src/` (top level and nested), named as paths from the root.
fn modules(src: &Path, root_file: &str) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    let mut dirs = vec![src.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for e in std::fs::read_dir(&dir).unwrap().filter_map(Result::ok) {
            let path = e.path();
            if path.is_dir() {
                if path.file_name().is_some_and(|n| n != "bin") {
                    dirs.push(path);
                }
                continue;
            }
            if path.extension().is_none_or(|x| x != "rs") {
                continue;
            }
            let rel = path
                .strip_prefix(src)
                .unwrap()
                .to_string_lossy()
                .to_string();
            if (rel == "lib.rs" || rel == "main.rs") && rel != root_file {
                continue;
            }
            let name = if rel == root_file {
                "crate".to_string()
            } else {
                rel.trim_end_matches(".rs")
                    .trim_end_matches("/mod")
                    .replace('/', "::")
            };
            // Nested modules count as their top-level module.
            let top = name.split("::").next().unwrap_or_default().to_string();
            out.entry(top)
                .or_insert_with(String::new)
                .push_str(&code(&path));
        }
    }
    out
}

/// The first cycle among one crate's files, if any.
fn cycle(src: &Path, root_file: &str) -> Option<Vec<String>> {
    let mods = modules(src, root_file);
    let root = &mods["crate"];
    // Names the crate root defines itself, and names it re-exports from a module.
    let mut owner: BTreeMap<String, String> = BTreeMap::new();
    for line in root.lines().map(str::trim) {
        let words: Vec<&str> = line.split_whitespace().collect();
        for kw in ["struct", "enum", "fn", "trait", "type", "const", "static"] {
            if let Some(p) = words.iter().position(|w| *w == kw)
                && let Some(name) = words.get(p + 1)
            {
                let name: String = name
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                owner.entry(name).or_insert_with(|| "crate".into());
            }
        }
    }
    for (i, _) in root.match_indices("pub use ") {
        let rest = &root[i + "pub use ".len()..];
        let stmt = &rest[..rest.find(';').unwrap_or(rest.len())];
        let stmt = stmt.trim_start_matches("self::");
        if let Some((module, items)) = stmt.split_once("::")
            && mods.contains_key(module)
        {
            for item in items.trim_matches(|c| c == '{' || c == '}').split(',') {
                owner.insert(item.trim().to_string(), module.to_string());
            }
        }
    }
    let mut edges: BTreeMap<&str, BTreeSet<String>> = BTreeMap::new();
    for (m, text) in &mods {
        let mut to = BTreeSet::new();
        for r in crate_refs(text) {
            let target = if mods.contains_key(&r) {
                Some(r)
            } else {
                owner.get(&r).cloned()
            };
            if let Some(t) = target.filter(|t| t != m) {
                to.insert(t);
            }
        }
        edges.insert(m, to);
    }
    fn walk(n: &str, edges: &BTreeMap<&str, BTreeSet<String>>, path: &mut Vec<String>) -> bool {
        for next in edges.get(n).into_iter().flatten() {
            if let Some(i) = path.iter().position(|p| p == next) {
                path.drain(..i);
                path.push(next.clone());
                return true;
            }
            path.push(next.clone());
            if walk(next, edges, path) {
                return true;
            }
            path.pop();
        }
        false
    }
    mods.keys().find_map(|m| {
        let mut path = vec![m.clone()];
        walk(m, &edges, &mut path).then_some(path)
    })
}

#[test]
fn no_file_imports_another_in_a_circle() {
    let root = workspace();
    let crates = [
        "dnm",
        "dnm/proto",
        "dnm/core",
        "dnm/zenoh",
        "dnm/record",
        "dnm/netlist",
        "dnm/place",
        "modules/sdk",
        "modules/std",
        "modules/rover",
        "modules/host",
        "router",
        "ground",
        "dnm/authority",
        "monitor",
    ];
    for c in crates {
        let src = root.join(c).join("src");
        for root_file in ["lib.rs", "main.rs"] {
            if !src.join(root_file).exists() {
                continue;
            }
            if let Some(cycle) = cycle(&src, root_file) {
                panic!("{c} ({root_file}): {}", cycle.join(" -> "));
            }
        }
    }
}

#[test]
fn the_cycle_check_finds_a_cycle() {
    // Two files that import each other, and a root that re-exports one of them.
    let dir = std::env::temp_dir().join(format!("dnm-cycle-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("lib.rs"), "mod a;\nmod b;\npub use a::Thing;\n").unwrap();
    std::fs::write(
        dir.join("a.rs"),
        "use crate::b::helper;\npub struct Thing;\n",
    )
    .unwrap();
    std::fs::write(dir.join("b.rs"), "use crate::Thing;\npub fn helper() {}\n").unwrap();
    let found = cycle(&dir, "lib.rs");
    let _ = std::fs::remove_dir_all(&dir);
    let found = found.expect("no cycle found");
    assert!(
        found.contains(&"a".to_string()) && found.contains(&"b".to_string()),
        "{found:?}"
    );
}

/// Every `.rs` file of the workspace's crates (their `src/`), test modules left out.
fn sources() -> Vec<(PathBuf, String)> {
    let root = workspace();
    let mut out = Vec::new();
    let mut dirs: Vec<PathBuf> = [
        "dnm",
        "dnm/proto",
        "dnm/core",
        "dnm/zenoh",
        "dnm/record",
        "dnm/netlist",
        "dnm/place",
        "modules/sdk",
        "modules/std",
        "modules/rover",
        "modules/host",
        "router",
        "ground",
        "dnm/authority",
        "monitor",
    ]
    .iter()
    .map(|c| root.join(c).join("src"))
    .collect();
    while let Some(dir) = dirs.pop() {
        for e in std::fs::read_dir(&dir).unwrap().filter_map(Result::ok) {
            let path = e.path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|x| x == "rs") {
                let text = std::fs::read_to_string(&path).unwrap();
                let text = text
                    .split("#[cfg(test)]")
                    .next()
                    .unwrap_or_default()
                    .to_string();
                out.push((path, text));
            }
        }
    }
    out
}

/// Long loops are named phases: no function outside tests is over 150 lines (from its `fn`
/// line to its closing brace; `scripts/function-lengths` counts the same way and prints the
/// whole table).
#[test]
fn no_function_is_over_150_lines() {
    let mut long = Vec::new();
    for (path, text) in sources() {
        let lines: Vec<&str> = text.lines().collect();
        for (i, line) in lines.iter().enumerate() {
            let t = line.trim_start();
            let t = t
                .strip_prefix("pub ")
                .or_else(|| t.strip_prefix("pub(crate) "))
                .unwrap_or(t);
            let t = t.strip_prefix("async ").unwrap_or(t);
            if !t.starts_with("fn ") {
                continue;
            }
            // From the `fn` line to the brace that closes its body (a declaration has none).
            let (mut depth, mut opened) = (0i64, false);
            for (j, l) in lines.iter().enumerate().skip(i) {
                let code = l.split("//").next().unwrap_or_default();
                for c in code.chars() {
                    match c {
                        '{' => (depth, opened) = (depth + 1, true),
                        '}' => depth -= 1,
                        ';' if !opened && depth == 0 => break,
                        _ => {}
                    }
                }
                if !opened && code.trim_end().ends_with(';') {
                    break;
                }
                if opened && depth == 0 {
                    if j - i + 1 > 150 {
                        long.push(format!(
                            "{}:{} ({} lines)",
                            path.display(),
                            i + 1,
                            j - i + 1
                        ));
                    }
                    break;
                }
            }
        }
    }
    assert!(long.is_empty(), "split these into named phases: {long:#?}");
}

/// Errors callers can match: no public function of a library returns `Result<_, String>`.
#[test]
fn no_public_function_returns_a_string_error() {
    let mut found = Vec::new();
    for (path, text) in sources() {
        let mut rest = text.as_str();
        while let Some(i) = rest.find("pub fn ") {
            let sig = &rest[i..];
            let end = sig.find(['{', ';']).unwrap_or(sig.len());
            let sig: String = sig[..end].split_whitespace().collect::<Vec<_>>().join(" ");
            if let Some(r) = sig.find("Result<")
                && sig[r..].trim_end().ends_with(", String>")
            {
                found.push(format!("{}: {sig}", path.display()));
            }
            rest = &rest[i + 7..];
        }
    }
    assert!(found.is_empty(), "give these an error type: {found:#?}");
}
