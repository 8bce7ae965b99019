//! Validation of netlist text: good files load into the model, every class of bad input gets
//! an error naming the line and field.

#![allow(clippy::unwrap_used)] // test helpers: failing loudly is right

use std::path::Path;

use dnm_netlist::*;
use proptest::prelude::*;

fn msg(name: &str, size: usize) -> MessageType {
    MessageType {
        schema_name: name.into(),
        encoding: "dnm-pod".into(),
        schema: String::new(),
        payload: Payload::Fixed { size_bytes: size },
        standard: None,
    }
}

fn port(name: &str, m: &MessageType) -> PortSpec {
    PortSpec {
        name: name.into(),
        message: m.clone(),
    }
}

fn catalog() -> Catalog {
    let twist = msg("t/Twist", 16);
    let ticks = msg("t/Ticks", 16);
    let mut c = Catalog::new();
    let mut add = |name: &str, inputs: Vec<PortSpec>, outputs: Vec<PortSpec>, params| {
        c.insert(
            KindSpec {
                name: name.into(),
                summary: String::new(),
                inputs,
                outputs,
                params,
                trigger: Trigger::OnInput,
            },
            KindSource::BuiltIn,
        )
    };
    add("joystick", vec![], vec![port("twist", &twist)], vec![]);
    add("planner", vec![], vec![port("twist", &twist)], vec![]);
    add(
        "drive",
        vec![port("cmd", &twist)],
        vec![port("ticks", &ticks)],
        vec![
            ParamSpec {
                name: "track_m".into(),
                kind: ParamKind::Float,
                default: Some(ParamValue::Float(0.5)),
                doc: String::new(),
            },
            ParamSpec {
                name: "board".into(),
                kind: ParamKind::String,
                default: None,
                doc: "serial device".into(),
            },
        ],
    );
    add("odometry", vec![port("ticks", &ticks)], vec![], vec![]);
    c
}

const GOOD: &str = r#"
[system]
name = "beetle"
default_task = "teleop"

[[dnm]]
name = "rover"

[[dnm]]
name = "ground"
parent = "rover"

[[module]]
name = "joystick"
kind = "joystick"
dnm = "ground"

[[module]]
name = "planner"
kind = "planner"

[[module]]
name = "drive"
kind = "drive"
rate_hz = 50
restart = "always"
params = { track_m = 1, board = "/dev/ttyS0" }

[[module]]
name = "odometry"
kind = "odometry"

[task.teleop]
links = ["joystick.twist -> drive.cmd", "drive.ticks -> odometry.ticks"]

[task.auto]
description = "computer control"
links = ["planner.twist -> drive.cmd", "drive.ticks -> odometry.ticks"]
"#;

fn parse(text: &str) -> Result<Netlist, NetlistError> {
    Netlist::parse(
        Path::new("configs/test.toml"),
        text,
        &catalog(),
        &mut |_| Err("no executables in tests".into()),
    )
}

/// Parses `text` expecting failure; returns the rendered error.
fn error_of(text: &str) -> String {
    match parse(text) {
        Ok(_) => panic!("netlist was accepted:\n{text}"),
        Err(e) => e.to_string(),
    }
}

fn good_with(from: &str, to: &str) -> String {
    assert!(GOOD.contains(from), "fixture lacks {from}");
    GOOD.replacen(from, to, 1)
}

fn line_of(text: &str, needle: &str) -> usize {
    text.lines().position(|l| l.contains(needle)).unwrap() + 1
}

#[test]
fn good_netlist_builds_the_model_and_graph() {
    let n = parse(GOOD).unwrap();
    assert_eq!(n.system, "beetle");
    assert_eq!(n.initial_task(), Some("teleop"));
    assert_eq!(n.dnms.len(), 2);
    assert_eq!(n.dnm("ground").unwrap().parent.as_deref(), Some("rover"));
    let drive = n.module("drive").unwrap();
    assert_eq!(drive.dnm, "rover", "unpinned modules run on the first DNM");
    assert_eq!(drive.pinned_dnm, None);
    assert_eq!(
        drive.params["track_m"],
        ParamValue::Float(1.0),
        "ints coerce to floats"
    );
    assert_eq!(drive.restart.mode, RestartMode::Always);
    assert_eq!(n.module("joystick").unwrap().dnm, "ground");
    // 3 distinct links: the ticks link is shared by both tasks.
    let g = n.graph();
    assert_eq!(g.node_count(), 4);
    assert_eq!(g.edge_count(), 3);
    let shared = g
        .edge_indices()
        .map(|e| &g[e])
        .find(|c| c.from_port == "ticks")
        .unwrap();
    assert_eq!(shared.tasks.len(), 2);
    let teleop = &n.tasks["teleop"];
    let cmd = PortRef {
        module: "drive".into(),
        port: "cmd".into(),
    };
    assert_eq!(teleop.source_of(&cmd).unwrap().module, "joystick");
    assert_eq!(n.tasks["auto"].source_of(&cmd).unwrap().module, "planner");
}

#[test]
fn unknown_module_in_link_names_line_and_suggests() {
    let text = good_with(
        "\"joystick.twist -> drive.cmd\"",
        "\"joystik.twist -> drive.cmd\"",
    );
    let e = error_of(&text);
    let line = line_of(&text, "joystik.twist");
    assert!(e.contains(&format!("configs/test.toml:{line}:")), "{e}");
    assert!(e.contains("task.teleop.links[0]"), "{e}");
    assert!(e.contains("unknown module `joystik`"), "{e}");
    assert!(e.contains("did you mean `joystick`"), "{e}");
}

#[test]
fn unknown_kind_is_reported_with_fix() {
    let text = good_with("kind = \"planner\"", "kind = \"planer\"");
    let e = error_of(&text);
    assert!(
        e.contains(&format!(":{}:", line_of(&text, "\"planer\""))),
        "{e}"
    );
    assert!(e.contains("module[1].kind"), "{e}");
    assert!(e.contains("unknown kind `planer`"), "{e}");
    assert!(e.contains("did you mean `planner`"), "{e}");
}

#[test]
fn unknown_port_and_direction_are_reported() {
    let e = error_of(&good_with(
        "joystick.twist -> drive.cmd",
        "joystick.speed -> drive.cmd",
    ));
    assert!(e.contains("has no output port `speed`"), "{e}");
    let e = error_of(&good_with(
        "joystick.twist -> drive.cmd",
        "drive.cmd -> drive.cmd",
    ));
    assert!(
        e.contains("it is an input: links go output -> input"),
        "{e}"
    );
}

#[test]
fn unknown_dnm_pin_and_parent_are_reported() {
    let text = good_with("dnm = \"ground\"", "dnm = \"grond\"");
    let e = error_of(&text);
    assert!(e.contains("module[0].dnm"), "{e}");
    assert!(
        e.contains("pinned to DNM `grond`, which does not exist"),
        "{e}"
    );
    assert!(
        e.contains(&format!(":{}:", line_of(&text, "\"grond\""))),
        "{e}"
    );
    let e = error_of(&good_with("parent = \"rover\"", "parent = \"mars\""));
    assert!(
        e.contains("dnm[1].parent: parent DNM `mars` is not declared"),
        "{e}"
    );
}

#[test]
fn dnm_cycle_is_reported() {
    let text = good_with(
        "name = \"rover\"\n",
        "name = \"rover\"\nparent = \"ground\"\n",
    );
    let e = error_of(&text);
    assert!(e.contains("is its own ancestor"), "{e}");
}

#[test]
fn input_fed_twice_in_one_task_is_reported() {
    let text = good_with(
        "links = [\"joystick.twist -> drive.cmd\",",
        "links = [\"joystick.twist -> drive.cmd\", \"planner.twist -> drive.cmd\",",
    );
    let e = error_of(&text);
    assert!(e.contains("task.teleop.links[1]"), "{e}");
    assert!(
        e.contains("input `drive.cmd` is fed by both `joystick.twist` and `planner.twist`"),
        "{e}"
    );
}

#[test]
fn type_mismatch_is_reported() {
    let text = good_with(
        "drive.ticks -> odometry.ticks\"]\n\n[task.auto]",
        "joystick.twist -> odometry.ticks\"]\n\n[task.auto]",
    );
    let e = error_of(&text);
    assert!(e.contains("type mismatch"), "{e}");
    assert!(
        e.contains("t/Twist (16 B)") && e.contains("t/Ticks (16 B)"),
        "{e}"
    );
}

#[test]
fn duplicate_names_are_reported() {
    let text = good_with("name = \"planner\"", "name = \"joystick\"");
    let e = error_of(&text);
    assert!(e.contains("module `joystick` is declared twice"), "{e}");
    let text = good_with("name = \"ground\"", "name = \"rover\"");
    assert!(error_of(&text).contains("DNM `rover` is declared twice"));
    // Duplicate task tables are a TOML error, located too.
    let text = format!("{GOOD}\n[task.auto]\nlinks = []\n");
    let e = error_of(&text);
    assert!(e.contains("duplicate key"), "{e}");
    let lines: Vec<&str> = text.lines().collect();
    let last = lines.iter().rposition(|l| *l == "[task.auto]").unwrap() + 1;
    assert!(e.contains(&format!(":{last}:")), "{e}");
}

#[test]
fn params_are_checked() {
    let e = error_of(&good_with("track_m = 1,", "track = 1,"));
    assert!(
        e.contains("has no parameter `track`") && e.contains("did you mean `track_m`"),
        "{e}"
    );
    let e = error_of(&good_with("track_m = 1,", "track_m = \"wide\","));
    assert!(e.contains("parameter `track_m` must be a float"), "{e}");
    let e = error_of(&good_with(", board = \"/dev/ttyS0\"", ""));
    assert!(e.contains("needs parameter `board`"), "{e}");
}

#[test]
fn unknown_fields_and_syntax_errors_are_located() {
    let text = good_with("rate_hz = 50", "rate = 50");
    let e = error_of(&text);
    assert!(e.contains("unknown field `rate`"), "{e}");
    assert!(
        e.contains(&format!(":{}:", line_of(&text, "rate = 50"))),
        "{e}"
    );
    let e = error_of("[system\nname = 1");
    assert!(e.contains("configs/test.toml:1:"), "{e}");
    let e = error_of(&good_with(
        "default_task = \"teleop\"",
        "default_task = \"drive\"",
    ));
    assert!(e.contains("default task `drive` is not defined"), "{e}");
}

#[test]
fn all_errors_are_reported_at_once() {
    let text = good_with("kind = \"planner\"", "kind = \"nope\"").replace(
        "drive.ticks -> odometry.ticks\"]\n\n[task.auto]",
        "drive.ticks -> odometry.tick\"]\n\n[task.auto]",
    );
    let err = parse(&text).unwrap_err();
    assert!(err.diagnostics.len() >= 3, "{err}");
}

#[test]
fn no_dnm_declared_means_one_local_dnm() {
    let text = "[system]\nname = \"s\"\n[[module]]\nname = \"j\"\nkind = \"joystick\"\n";
    let n = parse(text).unwrap();
    assert_eq!(n.dnms.len(), 1);
    assert_eq!(n.module("j").unwrap().dnm, DEFAULT_DNM);
    assert_eq!(n.initial_task(), None);
}

proptest! {
    /// Any well-formed link list either validates or yields located diagnostics; it never panics,
    /// and every accepted task has at most one source per input.
    #[test]
    fn random_links_validate_or_fail_cleanly(links in proptest::collection::vec(
        (0usize..4, 0usize..3, 0usize..4, 0usize..3), 0..8)) {
        let mods = ["joystick", "planner", "drive", "odometry"];
        let ports = ["twist", "cmd", "ticks"];
        let body: Vec<String> = links.iter()
            .map(|(a, p, b, q)| format!("\"{}.{} -> {}.{}\"", mods[*a], ports[*p], mods[*b], ports[*q]))
            .collect();
        let text = GOOD.replace("[task.auto]", &format!("[task.random]\nlinks = [{}]\n\n[task.auto]", body.join(", ")));
        match parse(&text) {
            Ok(n) => {
                let t = &n.tasks["random"];
                let mut inputs: Vec<_> = t.links.iter().map(|l| &l.to).collect();
                let before = inputs.len();
                inputs.sort();
                inputs.dedup();
                prop_assert_eq!(before, inputs.len());
            }
            Err(e) => {
                prop_assert!(!e.diagnostics.is_empty());
                prop_assert!(e.diagnostics.iter().all(|d| d.location.is_some()));
            }
        }
    }
}

#[test]
fn pins_need_a_dnm_and_are_kept() {
    let pinned = good_with("dnm = \"ground\"\n", "dnm = \"ground\"\npinned = true\n");
    let n = parse(&pinned).unwrap();
    assert!(n.module("joystick").unwrap().pinned);
    assert!(!n.module("drive").unwrap().pinned);
    let text = good_with(
        "name = \"joystick\"\nkind = \"joystick\"\ndnm = \"ground\"\n",
        "name = \"joystick\"\nkind = \"joystick\"\npinned = true\n",
    );
    let e = error_of(&text);
    assert!(
        e.contains("module[0].pinned: module `joystick` is pinned but names no DNM"),
        "{e}"
    );
    assert!(
        e.contains(&format!(":{}:", line_of(&text, "pinned = true"))),
        "{e}"
    );
}

#[test]
fn rates_and_hang_deadlines_out_of_range_are_located() {
    // A tiny positive rate has no usable period (it used to panic the module).
    for rate in ["1e-300", "0.001", "20000.0", "0", "-5"] {
        let text = good_with("rate_hz = 50", &format!("rate_hz = {rate}"));
        let e = error_of(&text);
        let line = line_of(&text, "rate_hz");
        assert!(
            e.contains(&format!("configs/test.toml:{line}:")),
            "{rate}: {e}"
        );
        assert!(e.contains("module[2].rate_hz"), "{rate}: {e}");
        assert!(e.contains("0.01 to 10000"), "{rate}: {e}");
    }
    let ok = parse(&good_with(
        "rate_hz = 50",
        "rate_hz = 0.01\nhung_after = \"1.5s\"",
    ))
    .unwrap();
    assert_eq!(ok.module("drive").unwrap().hung_after_ms, Some(1500));
    for (value, says) in [
        ("\"100ms\"", "outside 500 ms"),
        ("\"2 days\"", "not a duration"),
        ("\"-1s\"", "not a duration"),
    ] {
        let text = good_with("rate_hz = 50", &format!("hung_after = {value}"));
        let e = error_of(&text);
        let line = line_of(&text, "hung_after");
        assert!(e.contains(&format!("configs/test.toml:{line}:")), "{e}");
        assert!(
            e.contains("module[2].hung_after") && e.contains(says),
            "{value}: {e}"
        );
    }
}

#[test]
fn durations_read_with_their_units() {
    use dnm_netlist::parse_duration_ms;
    assert_eq!(parse_duration_ms("500ms"), Some(500));
    assert_eq!(parse_duration_ms("2s"), Some(2000));
    assert_eq!(parse_duration_ms("1.5s"), Some(1500));
    assert_eq!(parse_duration_ms("1m"), Some(60_000));
    assert_eq!(parse_duration_ms("5"), None);
    assert_eq!(parse_duration_ms("-1s"), None);
    assert_eq!(parse_duration_ms("1e300s"), None);
}

#[test]
fn a_downlink_plan_is_read_with_its_defaults() {
    let text = format!(
        "{GOOD}\n[[downlink]]\noutput = \"drive.ticks\"\nrate_hz = 10\npriority = 2\n\
         backfill = \"oldest_first\"\n\n[[downlink]]\noutput = \"joystick.twist\"\nrate_hz = 0.2\n"
    );
    let n = parse(&text).unwrap();
    assert_eq!(n.downlink.len(), 2);
    let ticks = &n.downlink[0];
    assert_eq!(ticks.output.to_string(), "drive.ticks");
    assert_eq!((ticks.priority, ticks.backfill), (2, Backfill::OldestFirst));
    assert_eq!(ticks.period_ns(), 100_000_000);
    let twist = &n.downlink[1];
    assert_eq!((twist.priority, twist.backfill), (5, Backfill::NewestFirst));
    assert!(parse(GOOD).unwrap().downlink.is_empty());
}

#[test]
fn a_bad_downlink_entry_names_its_line_field_and_fix() {
    let cases = [
        (
            "output = \"drive.cmd\"\nrate_hz = 1",
            "downlink[0].output",
            "has no output `cmd`",
        ),
        (
            "output = \"driv.ticks\"\nrate_hz = 1",
            "downlink[0].output",
            "did you mean `drive`",
        ),
        (
            "output = \"drive\"\nrate_hz = 1",
            "downlink[0].output",
            "not `module.output`",
        ),
        (
            "output = \"drive.ticks\"\nrate_hz = 500",
            "downlink[0].rate_hz",
            "out of range",
        ),
        (
            "output = \"drive.ticks\"\nrate_hz = 1\npriority = 0",
            "downlink[0].priority",
            "use 1",
        ),
        (
            "output = \"drive.ticks\"\nrate_hz = 1\nbackfill = \"random\"",
            "downlink[0].backfill",
            "newest_first",
        ),
        (
            "output = \"drive.ticks\"\nrate_hz = 1\n[[downlink]]\noutput = \"drive.ticks\"\nrate_hz = 2",
            "downlink[1].output",
            "in the downlink plan twice",
        ),
    ];
    for (entry, field, says) in cases {
        let text = format!("{GOOD}\n[[downlink]]\n{entry}\n");
        let err = error_of(&text);
        assert!(err.contains(field), "{entry}: {err}");
        assert!(err.contains(says), "{entry}: {err}");
        assert!(
            err.contains("configs/test.toml:"),
            "{entry}: names the line: {err}"
        );
    }
}
