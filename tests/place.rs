//! `dnm place` on Beetle-One: pinned modules stay, the written netlist validates and applies as
//! placed, impossible constraints fail with a message naming the fix.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

use std::process::Command;

use serde_json::Value;

const DNM: &str = env!("CARGO_BIN_EXE_dnm");

fn place(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(DNM)
        .arg("place")
        .arg(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../configs/beetle.toml"
        ))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn placement_keeps_pins_and_writes_a_valid_netlist() {
    let dir = std::env::temp_dir().join(format!("dnm-place-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("placed.toml");
    let (ok, stdout, stderr) = place(&["--refine", "--json", "--write", out.to_str().unwrap()]);
    assert!(ok, "{stderr}");
    let r: Value = serde_json::from_str(&stdout).unwrap();
    let assignment = &r["placement"]["assignment"];
    for (module, dnm) in [
        ("motor_left", "drive"),
        ("motor_right", "drive"),
        ("watchdog", "drive"),
        ("camera", "vision"),
        ("joystick", "ground"),
        ("imu", "rover"),
    ] {
        assert_eq!(assignment[module], dnm, "{module} is pinned to {dnm}");
    }
    let q = r["placement"]["modularity"].as_f64().unwrap();
    assert!((-0.5..=1.0).contains(&q));
    // The comparison covers the four placements; one DNM has no traffic between DNMs.
    let rows = r["comparison"].as_array().unwrap();
    assert_eq!(rows.len(), 4);
    assert_eq!(rows[1]["predicted"]["messages_per_minute"], 0.0);
    // The written netlist validates and puts every module where the placement said.
    let check = Command::new(DNM)
        .args(["check", "--json"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(check.status.success());
    let checked: Value = serde_json::from_slice(&check.stdout).unwrap();
    for m in checked["modules"].as_array().unwrap() {
        assert_eq!(m["dnm"], assignment[m["name"].as_str().unwrap()], "{m}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn impossible_constraints_are_refused_with_the_fix() {
    // Beetle-One pins modules to four DNMs: three are not enough.
    let (ok, _, stderr) = place(&["--max-dnms", "3"]);
    assert!(!ok);
    assert!(
        stderr.contains("4 pinned groups") && stderr.contains("raise the maximum"),
        "{stderr}"
    );
    // Five modules are pinned to the motor board.
    let (ok, _, stderr) = place(&["--capacity", "4"]);
    assert!(!ok);
    assert!(stderr.contains("capacity of 4"), "{stderr}");
}
