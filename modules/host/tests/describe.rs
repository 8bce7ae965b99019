//! The module host as a DNM and the `dnm` command see it: `describe` prints every built-in kind.

use std::process::Command;

#[test]
fn describe_lists_every_builtin_kind_as_json() {
    let out = Command::new(env!("CARGO_BIN_EXE_dnm-module-host"))
        .arg("describe")
        .output()
        .unwrap();
    assert!(out.status.success(), "{out:?}");
    let kinds: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap();
    let names: Vec<&str> = kinds.iter().filter_map(|k| k["name"].as_str()).collect();
    let expected: Vec<String> = dnm_module_host::registry()
        .specs()
        .into_iter()
        .map(|k| k.name)
        .collect();
    assert_eq!(names.len(), expected.len());
    for k in &expected {
        assert!(names.contains(&k.as_str()), "{k} missing from {names:?}");
    }
    assert!(names.contains(&"wheel_motor") && names.contains(&"ticker"));
}

#[test]
fn a_bad_launch_is_refused_with_a_message() {
    let out = Command::new(env!("CARGO_BIN_EXE_dnm-module-host"))
        .args(["run", "{not json"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(!out.stderr.is_empty());
}
