//! `dnm certs`: a system's certificate authority, the certificates of its computers, ground
//! stations and observers, and Zenoh configurations that use them: mutual TLS on every link and
//! access control generated from the netlist and the identities' roles.
//!
//! A folder holds the authority (`ca.pem`, `ca.key`), one `NAME.pem`/`NAME.key` per identity and
//! `identities.toml`, the inventory the access control is generated from. A certificate's common
//! name is the identity's name; that is what Zenoh's access control matches.

use std::collections::BTreeSet;
use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, bail};
use clap::Subcommand;
use dnm_netlist::Netlist;
use dnm_proto::keys;
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose,
};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

const INVENTORY: &str = "identities.toml";

#[derive(Subcommand, Debug)]
pub enum CertsCmd {
    /// Create the system's certificate authority in DIR (refuses to overwrite one).
    Init {
        #[arg(long)]
        dir: PathBuf,
        /// The system's name (as in the netlist's `[system] name`).
        #[arg(long)]
        system: String,
        /// Years the authority is valid.
        #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u16).range(1..=100))]
        years: u16,
    },
    /// Issue a certificate for an identity.
    Issue {
        #[arg(long)]
        dir: PathBuf,
        /// The identity's name: the certificate's common name.
        name: String,
        /// `rover` (a computer running DNMs), `router` (forwards for everyone), `operator` (a
        /// ground station: commands and reads) or `observer` (reads only).
        #[arg(long)]
        role: Role,
        /// DNMs this computer runs (role `rover`): only these may publish their ports.
        #[arg(long = "dnm")]
        dnms: Vec<String>,
        /// Host names and addresses the identity is reached at when it listens (repeatable;
        /// default: localhost and 127.0.0.1).
        #[arg(long = "host")]
        hosts: Vec<String>,
        /// Years the certificate is valid.
        #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u16).range(1..=100))]
        years: u16,
    },
    /// Write the Zenoh configuration of an identity: mutual TLS with its certificate and, when
    /// it listens, access control generated from the netlist and the identities.
    Config {
        #[arg(long)]
        dir: PathBuf,
        name: String,
        /// The system's netlist (its DNMs name the port keys each computer may publish on).
        #[arg(long)]
        netlist: PathBuf,
        /// A Zenoh configuration to start from (e.g. configs/zenoh/rover-router.json5).
        #[arg(long)]
        base: Option<PathBuf>,
        /// `router`, `peer` or `client` (default: `router` for routers, else `client`).
        #[arg(long)]
        mode: Option<String>,
        /// Endpoints to listen on, e.g. tls/0.0.0.0:7447 (repeatable).
        #[arg(long)]
        listen: Vec<String>,
        /// Endpoints to connect to, e.g. tls/rover.local:7447 (repeatable).
        #[arg(long)]
        connect: Vec<String>,
        /// Where to write it (default: standard output).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// List the identities.
    List {
        #[arg(long)]
        dir: PathBuf,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    Rover,
    Router,
    Operator,
    Observer,
}

impl Role {
    fn as_str(self) -> &'static str {
        match self {
            Role::Rover => "rover",
            Role::Router => "router",
            Role::Operator => "operator",
            Role::Observer => "observer",
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Identity {
    pub name: String,
    pub role: Role,
    #[serde(default)]
    pub dnms: Vec<String>,
}

#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Inventory {
    pub system: String,
    #[serde(default, rename = "identity")]
    pub identities: Vec<Identity>,
}

impl Inventory {
    fn load(dir: &Path) -> anyhow::Result<Self> {
        let path = dir.join(INVENTORY);
        let text = std::fs::read_to_string(&path).with_context(|| {
            format!(
                "reading {}; create the authority first with `dnm certs init --dir {} --system NAME`",
                path.display(),
                dir.display()
            )
        })?;
        toml::from_str(&text).with_context(|| format!("{}: not an inventory", path.display()))
    }

    fn save(&self, dir: &Path) -> anyhow::Result<()> {
        let path = dir.join(INVENTORY);
        std::fs::write(&path, toml::to_string_pretty(self)?)
            .with_context(|| format!("writing {}", path.display()))
    }

    fn identity(&self, name: &str) -> anyhow::Result<&Identity> {
        self.identities
            .iter()
            .find(|i| i.name == name)
            .with_context(|| {
                let known: Vec<&str> = self.identities.iter().map(|i| i.name.as_str()).collect();
                format!("no identity `{name}` (issued: {known:?}); issue it with `dnm certs issue`")
            })
    }
}

pub fn run(cmd: CertsCmd) -> anyhow::Result<ExitCode> {
    match cmd {
        CertsCmd::Init { dir, system, years } => {
            init(&dir, &system, years)?;
            println!(
                "certificate authority of `{system}` in {}: keep ca.key off the rover",
                dir.display()
            );
        }
        CertsCmd::Issue {
            dir,
            name,
            role,
            dnms,
            hosts,
            years,
        } => {
            issue(&dir, &name, role, &dnms, &hosts, years)?;
            println!(
                "{}: {name}.pem and {name}.key ({})",
                dir.display(),
                role.as_str()
            );
        }
        CertsCmd::Config {
            dir,
            name,
            netlist,
            base,
            mode,
            listen,
            connect,
            out,
        } => {
            // Only its names are needed: nothing it declares runs.
            let text = std::fs::read_to_string(&netlist)
                .with_context(|| format!("reading {}", netlist.display()))?;
            let netlist =
                dnm::parse_recorded_netlist(&netlist, &text).map_err(anyhow::Error::msg)?;
            let text = zenoh_config(
                &dir,
                &name,
                &netlist,
                base.as_deref(),
                mode.as_deref(),
                &listen,
                &connect,
            )?;
            match out {
                Some(p) => {
                    std::fs::write(&p, text).with_context(|| format!("writing {}", p.display()))?
                }
                None => println!("{text}"),
            }
        }
        CertsCmd::List { dir } => {
            let inv = Inventory::load(&dir)?;
            println!("system {}", inv.system);
            for i in &inv.identities {
                println!("{:<24} {:<9} {}", i.name, i.role.as_str(), i.dnms.join(","));
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn check_name(what: &str, name: &str) -> anyhow::Result<()> {
    if name.is_empty()
        || name.len() > 64
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    {
        bail!("{what} `{name}`: use 1 to 64 letters, digits, `-` or `_`");
    }
    Ok(())
}

/// Writes a file no one else may read, refusing to replace one.
fn write_private(path: &Path, text: &str) -> anyhow::Result<()> {
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)
        .with_context(|| format!("creating {} (it must not exist yet)", path.display()))?;
    f.write_all(text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

fn write_new(path: &Path, text: &str) -> anyhow::Result<()> {
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)
        .with_context(|| format!("creating {} (it must not exist yet)", path.display()))?;
    f.write_all(text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

/// From today (00:00 UTC) to `years` later.
fn validity(params: &mut CertificateParams, years: u16) {
    let today = time::OffsetDateTime::now_utc().replace_time(time::Time::MIDNIGHT);
    params.not_before = today;
    params.not_after = today + time::Duration::days(365 * i64::from(years.max(1)));
}

pub fn init(dir: &Path, system: &str, years: u16) -> anyhow::Result<()> {
    check_name("system", system)?;
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let key = KeyPair::generate()?;
    let mut params = CertificateParams::new(Vec::<String>::new())?;
    params.distinguished_name.push(
        DnType::CommonName,
        format!("{system} certificate authority"),
    );
    params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    params.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    validity(&mut params, years);
    let cert = params.self_signed(&key)?;
    write_private(&dir.join("ca.key"), &key.serialize_pem())?;
    write_new(&dir.join("ca.pem"), &cert.pem())?;
    Inventory {
        system: system.into(),
        identities: Vec::new(),
    }
    .save(dir)
}

pub fn issue(
    dir: &Path,
    name: &str,
    role: Role,
    dnms: &[String],
    hosts: &[String],
    years: u16,
) -> anyhow::Result<()> {
    check_name("identity", name)?;
    if name == "ca" {
        bail!("identity `ca` is the authority's own file name; choose another");
    }
    for d in dnms {
        check_name("DNM", d)?;
    }
    if role != Role::Rover && !dnms.is_empty() {
        bail!("--dnm is for role `rover` (the DNMs the computer runs)");
    }
    let mut inv = Inventory::load(dir)?;
    if inv.identities.iter().any(|i| i.name == name) {
        bail!("identity `{name}` is already issued in {}", dir.display());
    }
    let ca_key = KeyPair::from_pem(
        &std::fs::read_to_string(dir.join("ca.key"))
            .with_context(|| format!("reading {}/ca.key", dir.display()))?,
    )?;
    let ca_pem = std::fs::read_to_string(dir.join("ca.pem"))
        .with_context(|| format!("reading {}/ca.pem", dir.display()))?;
    let issuer = Issuer::from_ca_cert_pem(&ca_pem, &ca_key)?;
    let hosts = if hosts.is_empty() {
        vec!["localhost".to_string(), "127.0.0.1".to_string()]
    } else {
        hosts.to_vec()
    };
    let key = KeyPair::generate()?;
    let mut params = CertificateParams::new(hosts)?;
    params.distinguished_name.push(DnType::CommonName, name);
    params
        .distinguished_name
        .push(DnType::OrganizationalUnitName, role.as_str());
    params
        .distinguished_name
        .push(DnType::OrganizationName, inv.system.clone());
    params.is_ca = IsCa::ExplicitNoCa;
    params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    // Every identity both listens and connects (routers do both).
    params.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    validity(&mut params, years);
    let cert = params.signed_by(&key, &issuer)?;
    write_private(&dir.join(format!("{name}.key")), &key.serialize_pem())?;
    write_new(&dir.join(format!("{name}.pem")), &cert.pem())?;
    inv.identities.push(Identity {
        name: name.into(),
        role,
        dnms: dnms.to_vec(),
    });
    inv.save(dir)
}

/// The Zenoh configuration of identity `name`, as JSON.
pub fn zenoh_config(
    dir: &Path,
    name: &str,
    netlist: &Netlist,
    base: Option<&Path>,
    mode: Option<&str>,
    listen: &[String],
    connect: &[String],
) -> anyhow::Result<String> {
    let inv = Inventory::load(dir)?;
    if inv.system != netlist.system {
        bail!(
            "the authority in {} is for system `{}`, the netlist is of `{}`",
            dir.display(),
            inv.system,
            netlist.system
        );
    }
    let me = inv.identity(name)?;
    let dir = std::fs::canonicalize(dir).with_context(|| format!("{}", dir.display()))?;
    let path = |f: String| dir.join(f).display().to_string();
    let mut config = match base {
        Some(b) => {
            let c =
                zenoh::Config::from_file(b).map_err(|e| anyhow::anyhow!("{}: {e}", b.display()))?;
            serde_json::from_str::<Value>(&c.to_string())
                .with_context(|| format!("{}: not representable as JSON", b.display()))?
        }
        None => json!({}),
    };
    let mode = mode.unwrap_or(if me.role == Role::Router {
        "router"
    } else {
        "client"
    });
    let set = |config: &mut Value, path: &[&str], value: Value| {
        let mut v = config;
        for (i, k) in path.iter().enumerate() {
            if !v.is_object() {
                *v = json!({});
            }
            let Some(obj) = v.as_object_mut() else {
                return;
            };
            if i + 1 == path.len() {
                obj.insert((*k).to_string(), value);
                return;
            }
            v = obj.entry((*k).to_string()).or_insert_with(|| json!({}));
        }
    };
    set(&mut config, &["mode"], json!(mode));
    if !listen.is_empty() {
        set(&mut config, &["listen", "endpoints"], json!(listen));
    }
    if !connect.is_empty() {
        set(&mut config, &["connect", "endpoints"], json!(connect));
    }
    if matches!(me.role, Role::Rover | Role::Router) {
        // The system's own computers wait for their router however long it takes to come up
        // (an operator's command fails at once instead).
        set(&mut config, &["connect", "timeout_ms"], json!(-1));
        set(&mut config, &["connect", "exit_on_failure"], json!(false));
    }
    // Only the endpoints given: nothing announced or found on the network.
    set(
        &mut config,
        &["scouting", "multicast", "enabled"],
        json!(false),
    );
    let cert = path(format!("{name}.pem"));
    let key = path(format!("{name}.key"));
    set(
        &mut config,
        &["transport", "link", "tls"],
        json!({
            "root_ca_certificate": path("ca.pem".into()),
            "listen_certificate": cert,
            "listen_private_key": key,
            "connect_certificate": cert,
            "connect_private_key": key,
            "enable_mtls": true,
            "verify_name_on_connect": true,
        }),
    );
    if mode != "client" && config.pointer("/listen/endpoints").is_none() {
        // Zenoh's default for peers and routers listens on every interface, in the clear.
        set(&mut config, &["listen", "endpoints"], json!([]));
    }
    // Every endpoint of the result, from the base file too (plain or per mode).
    for side in ["listen", "connect"] {
        let mut found = Vec::new();
        endpoints(
            config
                .pointer(&format!("/{side}/endpoints"))
                .unwrap_or(&Value::Null),
            &mut found,
        );
        if let Some(ep) = found.iter().find(|e| !e.starts_with("tls/")) {
            bail!(
                "{side} endpoint `{ep}`: a secured system uses tls/ endpoints only (give \
                 --{side} tls/HOST:PORT, or remove it from the base configuration)"
            );
        }
    }
    if mode != "client" {
        // Anything that accepts links checks what comes through them.
        set(
            &mut config,
            &["access_control"],
            access_control(&inv, netlist),
        );
    }
    // Checked by Zenoh itself before anyone relies on it.
    let text = serde_json::to_string_pretty(&config)?;
    zenoh::Config::from_json5(&text).map_err(|e| anyhow::anyhow!("generated config: {e}"))?;
    Ok(text)
}

/// The endpoint strings of a Zenoh `endpoints` value: a list, or lists per mode.
fn endpoints(v: &Value, out: &mut Vec<String>) {
    match v {
        Value::String(e) => out.push(e.clone()),
        Value::Array(a) => a.iter().for_each(|e| endpoints(e, out)),
        Value::Object(o) => o.values().for_each(|e| endpoints(e, out)),
        _ => {}
    }
}

/// Zenoh access control for a system: what each role may do on the system's keys, and which
/// ports each computer may publish. Everything else is denied.
pub fn access_control(inv: &Inventory, netlist: &Netlist) -> Value {
    let sys = &netlist.system;
    let all = format!("{sys}/**");
    let reads = vec![
        keys::all_dnms(sys),
        format!("{}/netlist", keys::all_dnms(sys)),
        keys::wiring(sys, "*"),
        format!("{sys}/module/**"),
        format!("{sys}/port/**"),
    ];
    // Where a system is commanded through its authority, operators reach only the authority
    // (a DNM takes switches and applies from nowhere else); else also each DNM.
    // A station's uplinks go on the key of its own name (below, per operator), so an operator
    // speaks only as the station its certificate names.
    let commands = if dnm::commanded_by_authority(netlist) {
        Vec::new()
    } else {
        vec![keys::cmd(sys, "*")]
    };
    let mut rules = vec![
        // What anyone admitted may be sent: state, telemetry, answers.
        json!({
            "id": "to-everyone",
            "flows": ["egress"],
            "permission": "allow",
            "messages": ["put", "delete", "reply", "declare_subscriber", "declare_queryable",
                         "liveliness_token"],
            "key_exprs": [all],
        }),
        json!({
            "id": "read",
            "flows": ["ingress"],
            "permission": "allow",
            "messages": ["query", "liveliness_query"],
            "key_exprs": reads,
        }),
        json!({
            "id": "watch",
            "flows": ["ingress"],
            "permission": "allow",
            "messages": ["declare_subscriber", "declare_liveliness_subscriber"],
            "key_exprs": [all],
        }),
        // Observers watch outputs at the limited rates only: every sample of every output (and
        // every camera frame) would cost the rover's DNMs and the radio what an operator decides.
        json!({
            "id": "observe",
            "flows": ["ingress"],
            "permission": "allow",
            "messages": ["declare_subscriber", "declare_liveliness_subscriber"],
            "key_exprs": [
                format!("{sys}/dnm/**"),
                format!("{sys}/module/**"),
                format!("{sys}/port/**"),
                keys::authority_beat(sys),
                keys::watch_all(sys, keys::WatchRate::Hz10),
                keys::watch_all(sys, keys::WatchRate::Hz1),
                // What stations filled in of their record, drawn by monitors.
                keys::ground_filled_all(sys),
            ],
        }),
        // The system's computers are asked (their DNMs' queryables) and their liveliness is
        // watched; what each may answer for is its own (below).
        json!({
            "id": "to-node",
            "flows": ["egress"],
            "permission": "allow",
            "messages": ["query", "liveliness_query", "declare_liveliness_subscriber"],
            "key_exprs": [all],
        }),
        // Routers carry everyone's traffic (each checked where it entered).
        json!({
            "id": "forward",
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "messages": ["put", "delete", "declare_subscriber", "query", "declare_queryable",
                         "reply", "liveliness_token", "declare_liveliness_subscriber",
                         "liveliness_query"],
            "key_exprs": [all],
        }),
    ];
    rules.extend(record_rules(sys));
    let direct = !commands.is_empty();
    if direct {
        rules.push(json!({
            "id": "command",
            "flows": ["ingress"],
            "permission": "allow",
            "messages": ["query"],
            "key_exprs": commands,
        }));
    }
    // One subject per identity, so each link matches exactly one policy and a refusal logged
    // by Zenoh is final.
    let mut subjects = Vec::new();
    let mut policies = Vec::new();
    let declared: BTreeSet<&str> = netlist.dnms.iter().map(|d| d.name.as_str()).collect();
    for i in &inv.identities {
        let mut granted: Vec<String> = match i.role {
            // An observer keeps no record: what it would ask of the recordings is the
            // operators' radio budget.
            Role::Observer => vec!["to-everyone", "read", "observe"],
            Role::Operator if direct => {
                vec!["to-everyone", "read", "watch", "command", "record", "fill"]
            }
            Role::Operator => vec!["to-everyone", "read", "watch", "record", "fill"],
            Role::Rover => vec!["to-everyone", "read", "watch", "to-node"],
            Role::Router => vec!["forward"],
        }
        .into_iter()
        .map(str::to_string)
        .collect();
        let own: Vec<&str> = i
            .dnms
            .iter()
            .map(String::as_str)
            .filter(|d| declared.contains(d))
            .collect();
        for (id, rule) in identity_rules(netlist, i, &own) {
            rules.push(rule);
            granted.push(id);
        }
        let subject = format!("id-{}", i.name);
        subjects.push(json!({ "id": subject, "cert_common_names": [i.name] }));
        policies.push(json!({
            "id": format!("{}-{}", i.role.as_str(), i.name),
            "rules": granted,
            "subjects": [subject],
        }));
    }
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

/// The rules of a station's record of the rover: what it asks and hears of the downlink, and
/// what it tells the ground's monitors.
fn record_rules(sys: &str) -> [Value; 2] {
    [
        // A station keeps its own record of the rover: it subscribes to the downlink (with
        // history and recovery from the publishers' caches) and asks the recordings.
        json!({
            "id": "record",
            "flows": ["ingress"],
            "permission": "allow",
            "messages": ["query", "liveliness_query", "declare_subscriber",
                         "declare_liveliness_subscriber", "liveliness_token"],
            // (`**` never matches a verbatim chunk: zenoh-ext's `@adv` keys are named.)
            "key_exprs": [
                format!("{sys}/downlink/**"),
                format!("{sys}/downlink/**/@adv/**"),
                keys::downlink_channels(sys),
                keys::downlink_history(sys, "*"),
            ],
        }),
        // A station tells the ground's monitors what it filled in of its record (on the
        // ground's keys only: nothing a rover's DNM reads).
        json!({
            "id": "fill",
            "flows": ["ingress"],
            "permission": "allow",
            "messages": ["put"],
            "key_exprs": [keys::ground_filled_all(sys)],
        }),
    ]
}

/// A rule letting one identity send `messages` on `key_exprs`, by its id.
fn ingress_rule(id: String, messages: &[&str], key_exprs: Vec<String>) -> (String, Value) {
    let rule = json!({
        "id": id,
        "flows": ["ingress"],
        "permission": "allow",
        "messages": messages,
        "key_exprs": key_exprs,
    });
    (id, rule)
}

/// The rules of one identity of its own: a computer answers for its own DNMs only (their
/// state, netlist, commands, modules and ports), keeps their liveliness and publishes their
/// ports, nothing else; the authority's host also answers the stations, beats and sends the
/// DNMs their transactions; an operator's station sends its uplinks on its own name's key.
fn identity_rules(netlist: &Netlist, i: &Identity, own: &[&str]) -> Vec<(String, Value)> {
    let sys = &netlist.system;
    let mut out = Vec::new();
    if i.role == Role::Operator {
        out.push(ingress_rule(
            format!("station-{}", i.name),
            &["query"],
            vec![keys::authority_station(sys, &i.name)],
        ));
    }
    if i.role != Role::Rover || own.is_empty() {
        return out;
    }
    let mut answers: Vec<String> = own
        .iter()
        .flat_map(|d| {
            [
                keys::dnm(sys, d),
                format!("{}/**", keys::dnm(sys, d)),
                format!("{sys}/module/{d}/**"),
                format!("{sys}/port/{d}/**"),
                // The downlink's caches (zenoh-ext's `@adv` keys), channels and recording.
                format!("{sys}/downlink/{d}/**"),
                format!("{sys}/downlink/{d}/**/@adv/**"),
                keys::downlink_channel(sys, &format!("/{d}/**")),
                keys::downlink_history(sys, d),
            ]
        })
        .collect();
    let authority = netlist.authority().is_some_and(|a| own.contains(&a));
    if authority {
        answers.push(keys::authority_stations(sys));
    }
    out.push(ingress_rule(
        format!("answer-{}", i.name),
        &["declare_queryable", "reply", "liveliness_token"],
        answers,
    ));
    if authority {
        out.push(ingress_rule(
            format!("beat-{}", i.name),
            &["put"],
            vec![keys::authority_beat(sys)],
        ));
        out.push(ingress_rule(
            format!("transact-{}", i.name),
            &["query"],
            vec![keys::cmd(sys, "*")],
        ));
    }
    let owned = own
        .iter()
        .flat_map(|d| {
            [
                format!("{sys}/port/{d}/**"),
                format!("{sys}/watch/{d}/**"),
                format!("{sys}/downlink/{d}/**"),
                format!("{sys}/downlink/{d}/**/@adv/**"),
                keys::downlink_channel(sys, &format!("/{d}/**")),
            ]
        })
        .collect();
    out.push(ingress_rule(
        format!("publish-{}", i.name),
        &["put", "delete"],
        owned,
    ));
    out
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    #[test]
    fn names_are_plain() {
        assert!(check_name("identity", "ground-1").is_ok());
        for bad in ["", "a/b", "a b", "../x", &"x".repeat(65)] {
            assert!(check_name("identity", bad).is_err(), "{bad:?}");
        }
    }
}
