//! Fan-out: one output read by many modules. A port's subscriber slots follow the netlist, and
//! what a port's shared memory cannot hold is refused by `dnm check`. Its own test binary: its 65
//! module processes starting at once would starve the tests beside it on a small machine.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::process::Command;

use dnm_module::msg::Tick;

mod support;

use support::system::{System, collect};

#[test]
fn one_output_feeds_64_inputs_and_check_refuses_what_a_port_cannot_hold() {
    // A port's subscriber slots follow the netlist: 64 readers of one output.
    let mut fan = String::from(
        "[system]\nname = \"SYSTEM\"\n\n[[dnm]]\nname = \"main\"\n\n[[module]]\nname = \"src\"\nkind = \"ticker\"\nrate_hz = 50\nparams = { origin = 7 }\n",
    );
    let mut links = Vec::new();
    for i in 0..64 {
        fan += &format!("\n[[module]]\nname = \"fan{i}\"\nkind = \"relay\"\n");
        links.push(format!("\"src.out -> fan{i}.in\""));
    }
    fan += &format!("\n[task.a]\nlinks = [{}]\n", links.join(", "));
    let sys = System::start(&fan);
    let outs: Vec<_> = (0..64)
        .map(|i| sys.subscribe::<Tick>(&format!("fan{i}"), "out"))
        .collect();
    for (i, out) in outs.iter().enumerate() {
        let ticks = collect::<Tick>(out, |t| t.len() >= 3);
        assert!(
            ticks.iter().all(|t| t.origin == 7),
            "fan{i} relayed {ticks:?}"
        );
    }
    assert!(sys.status().modules.iter().all(|m| m.restarts == 0));

    // A camera-sized output read by more modules than its shared memory is sized for is
    // refused by `dnm check`, at the link that goes over, with the limit and the fix.
    let dir = std::env::temp_dir().join(format!("dnm-fanout-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut big = String::from(
        "[system]\nname = \"big\"\n\n[[module]]\nname = \"cam\"\nkind = \"blob_source\"\nparams = { bytes = 1048576 }\n",
    );
    let mut links = Vec::new();
    for i in 0..5 {
        big += &format!("\n[[module]]\nname = \"view{i}\"\nkind = \"latency\"\n");
        links.push(format!("\"cam.out -> view{i}.in\""));
    }
    big += &format!("\n[task.a]\nlinks = [{}]\n", links.join(", "));
    let path = dir.join("big.toml");
    std::fs::write(&path, &big).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .args(["check", "--json"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let e = &v["errors"][0];
    assert_eq!(e["field"], "task.a.links[4]", "{v}");
    let message = e["message"].as_str().unwrap();
    assert!(
        message.contains("`cam.out` would feed 5 modules") && message.contains("at most 4"),
        "{message}"
    );
    assert!(e["help"].as_str().unwrap().contains("relay"), "{v}");
    // Four readers fit.
    std::fs::write(&path, big.replace(", \"cam.out -> view4.in\"", "")).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .arg("check")
        .arg(&path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    let _ = std::fs::remove_dir_all(&dir);
}
