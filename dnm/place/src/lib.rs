//! Placing modules on DNMs (the paper's section IV): cluster the module graph so that modules
//! exchanging much data share a DNM, then map the clusters onto the netlist's DNMs.
//!
//! Link weights follow the paper: for connection n, w_n = K_char · D_n · E_m, with D_n the bytes
//! per message and E_m the producer's messages per second, normalised as w_nn = l · w_n / Σ w
//! over the l connections (K_char cancels in the normalisation). [`Weighting::Plain`] gives
//! every connection weight 1. Rates come from the netlist: a periodic module's rate; an
//! on-input module runs as fast as its fastest source.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! # let netlist: dnm_netlist::Netlist = unimplemented!();
//! use dnm_place::{PlaceOptions, Weighting, place};
//! let options = PlaceOptions {
//!     weighting: Weighting::Weighted,
//!     refine: true,
//!     capacity: None,
//!     max_dnms: None,
//!     ignore_pins: false,
//!     measured: None,
//! };
//! let placement = place(&netlist, &options)?;
//! println!("modularity {:.3}: {:?}", placement.modularity, placement.clusters);
//! # Ok(()) }
//! ```

pub mod cluster;

use std::collections::{BTreeMap, BTreeSet};

use cluster::{ClusterError, Clustering, Constraints, Graph};
use dnm_netlist::{Netlist, Payload, Trigger};
use serde::Serialize;

/// How links are weighted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Weighting {
    /// Every connection weighs 1 (Newman's method as such).
    Plain,
    /// Bytes per message times messages per second, normalised (the paper's weighted Newman).
    Weighted,
}

/// What `place` may do.
#[derive(Debug, Clone)]
pub struct PlaceOptions {
    pub weighting: Weighting,
    /// Run the Louvain-style refinement after the greedy merge.
    pub refine: bool,
    /// Most modules on one DNM.
    pub capacity: Option<usize>,
    /// Most DNMs used.
    pub max_dnms: Option<usize>,
    /// Treat pinned modules as free (to study placements as the paper does, without pins).
    pub ignore_pins: bool,
    /// Measured traffic per output port (from a recording), replacing the netlist's prediction.
    pub measured: Option<Measured>,
}

/// Measured traffic of output ports: (module, port) → (bytes per message, messages per second).
pub type Measured = BTreeMap<(String, String), (f64, f64)>;

impl Default for PlaceOptions {
    fn default() -> Self {
        Self {
            weighting: Weighting::Weighted,
            refine: false,
            capacity: None,
            max_dnms: None,
            ignore_pins: false,
            measured: None,
        }
    }
}

/// Why a placement cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum PlaceError {
    #[error("{0}")]
    Constraints(#[from] ClusterError),
}

/// The traffic of one link, as the netlist predicts it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LinkTraffic {
    pub from_module: String,
    pub from_port: String,
    pub to_module: String,
    pub bytes_per_message: f64,
    pub messages_per_second: f64,
}

/// Messages per second each module sends on each output: periodic modules at their rate,
/// on-input modules at the rate of their fastest source in any task.
pub fn module_rates(netlist: &Netlist) -> BTreeMap<String, f64> {
    let mut rates: BTreeMap<String, f64> = BTreeMap::new();
    for m in &netlist.modules {
        let rate = match netlist.kind_of(&m.name).map(|k| k.trigger) {
            Some(Trigger::Periodic { rate_hz }) => m.rate_hz.unwrap_or(rate_hz),
            _ => 0.0,
        };
        rates.insert(m.name.clone(), rate);
    }
    let links = netlist.all_links();
    // Propagate through on-input modules (bounded: a cycle cannot raise rates forever).
    for _ in 0..netlist.modules.len() {
        let mut changed = false;
        for l in &links {
            let to_on_input = netlist
                .kind_of(&l.to.module)
                .is_some_and(|k| k.trigger == Trigger::OnInput);
            let src = rates.get(&l.from.module).copied().unwrap_or(0.0);
            if to_on_input && rates.get(&l.to.module).is_some_and(|r| *r < src) {
                rates.insert(l.to.module.clone(), src);
                changed = true;
            }
        }
        if !changed {
            break;
        }
    }
    rates
}

/// Every link of every task, once, with its traffic: measured where `measured` has the port,
/// else predicted from the netlist.
pub fn traffic_with(netlist: &Netlist, measured: Option<&Measured>) -> Vec<LinkTraffic> {
    let mut links = traffic(netlist);
    if let Some(m) = measured {
        for l in &mut links {
            if let Some(&(bytes, rate)) = m.get(&(l.from_module.clone(), l.from_port.clone())) {
                l.bytes_per_message = bytes;
                l.messages_per_second = rate;
            }
        }
    }
    links
}

/// Every link of every task, once, with its predicted traffic.
pub fn traffic(netlist: &Netlist) -> Vec<LinkTraffic> {
    let rates = module_rates(netlist);
    let mut seen = BTreeSet::new();
    let mut out = Vec::new();
    for l in netlist.all_links() {
        if !seen.insert((l.from.clone(), l.to.clone())) {
            continue;
        }
        let bytes = netlist
            .kind_of(&l.from.module)
            .and_then(|k| k.outputs.iter().find(|p| p.name == l.from.port))
            .map_or(0.0, |p| match p.message.payload {
                Payload::Fixed { size_bytes } => size_bytes as f64,
                Payload::Bytes { max_bytes } => max_bytes as f64,
            });
        out.push(LinkTraffic {
            from_module: l.from.module.clone(),
            from_port: l.from.port.clone(),
            to_module: l.to.module.clone(),
            bytes_per_message: bytes,
            messages_per_second: rates.get(&l.from.module).copied().unwrap_or(0.0),
        });
    }
    out
}

/// The module graph as an undirected weighted graph, nodes in netlist order.
pub fn module_graph(netlist: &Netlist, weighting: Weighting) -> Graph {
    module_graph_with(netlist, weighting, None)
}

/// [`module_graph`] with measured traffic where known.
pub fn module_graph_with(
    netlist: &Netlist,
    weighting: Weighting,
    measured: Option<&Measured>,
) -> Graph {
    let index: BTreeMap<&str, usize> = netlist
        .modules
        .iter()
        .enumerate()
        .map(|(i, m)| (m.name.as_str(), i))
        .collect();
    let links = traffic_with(netlist, measured);
    let raw: Vec<f64> = links
        .iter()
        .map(|t| match weighting {
            Weighting::Plain => 1.0,
            Weighting::Weighted => t.bytes_per_message * t.messages_per_second,
        })
        .collect();
    let sum: f64 = raw.iter().sum();
    let l = links.len() as f64;
    let mut g = Graph::new(netlist.modules.len());
    for (t, w) in links.iter().zip(raw) {
        let (Some(&a), Some(&b)) = (
            index.get(t.from_module.as_str()),
            index.get(t.to_module.as_str()),
        ) else {
            continue;
        };
        // w_nn = l · w_n / Σ w
        let w = if sum > 0.0 { l * w / sum } else { 0.0 };
        g.add_edge(a, b, w);
    }
    g
}

/// A placement of every module on a DNM.
#[derive(Debug, Clone, Serialize)]
pub struct Placement {
    pub weighting: Weighting,
    pub refined: bool,
    /// Module → DNM.
    pub assignment: BTreeMap<String, String>,
    /// DNM → its modules.
    pub clusters: BTreeMap<String, Vec<String>>,
    /// DNMs this placement adds to the netlist (more clusters than declared DNMs), with their
    /// parent.
    pub new_dnms: Vec<(String, Option<String>)>,
    /// Modularity of the placement on the graph it was computed with.
    pub modularity: f64,
    /// Modularity of the same placement on the plain (unweighted) graph.
    pub plain_modularity: f64,
    pub predicted: Prediction,
}

/// Traffic between DNMs that a placement implies.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Prediction {
    pub messages_per_minute: f64,
    pub bytes_per_second: f64,
    pub dnms_used: usize,
}

/// What crosses DNMs under `assignment`: each output a remote DNM reads is sent once to each
/// such DNM (the DNM's egress publishes it once; Zenoh delivers it per remote DNM).
pub fn predict(netlist: &Netlist, assignment: &BTreeMap<String, String>) -> Prediction {
    predict_with(netlist, assignment, None)
}

/// [`predict`] with measured traffic where known.
pub fn predict_with(
    netlist: &Netlist,
    assignment: &BTreeMap<String, String>,
    measured: Option<&Measured>,
) -> Prediction {
    let mut sent: BTreeMap<(String, String, String), (f64, f64)> = BTreeMap::new();
    for t in traffic_with(netlist, measured) {
        let (Some(a), Some(b)) = (assignment.get(&t.from_module), assignment.get(&t.to_module))
        else {
            continue;
        };
        if a != b {
            sent.insert(
                (t.from_module.clone(), t.from_port.clone(), b.clone()),
                (t.messages_per_second, t.bytes_per_message),
            );
        }
    }
    let dnms: BTreeSet<&String> = assignment.values().collect();
    Prediction {
        // `+ 0.0` turns the empty sum's -0.0 into 0.
        messages_per_minute: sent.values().map(|(r, _)| r * 60.0).sum::<f64>() + 0.0,
        bytes_per_second: sent.values().map(|(r, b)| r * b).sum::<f64>() + 0.0,
        dnms_used: dnms.len(),
    }
}

/// Everything on the netlist's first DNM: the baseline.
pub fn single_dnm(netlist: &Netlist) -> BTreeMap<String, String> {
    let first = netlist
        .dnms
        .first()
        .map(|d| d.name.clone())
        .unwrap_or_else(|| "local".into());
    netlist
        .modules
        .iter()
        .map(|m| (m.name.clone(), first.clone()))
        .collect()
}

/// Clusters the module graph and maps clusters onto DNMs: a cluster holding modules pinned to
/// a DNM goes there; the others take the unused DNMs in declaration order, then new DNMs
/// `<first DNM>-<n>` under the first DNM.
pub fn place(netlist: &Netlist, options: &PlaceOptions) -> Result<Placement, PlaceError> {
    let measured = options.measured.as_ref();
    let g = module_graph_with(netlist, options.weighting, measured);
    let dnm_index: BTreeMap<&str, usize> = netlist
        .dnms
        .iter()
        .enumerate()
        .map(|(i, d)| (d.name.as_str(), i))
        .collect();
    let constraints = Constraints {
        pinned: netlist
            .modules
            .iter()
            .map(|m| {
                (m.pinned && !options.ignore_pins)
                    .then(|| dnm_index.get(m.dnm.as_str()).copied())
                    .flatten()
            })
            .collect(),
        capacity: options.capacity,
        max_communities: options.max_dnms,
    };
    let mut clustering: Clustering = cluster::greedy(&g, &constraints)?;
    if options.refine {
        cluster::refine(&g, &constraints, &mut clustering);
    }
    let k = clustering.communities();
    // Cluster → DNM.
    let mut target: Vec<Option<String>> = vec![None; k];
    for (m, &c) in netlist.modules.iter().zip(&clustering.community) {
        if m.pinned && !options.ignore_pins {
            target[c] = Some(m.dnm.clone());
        }
    }
    let mut free: Vec<String> = netlist
        .dnms
        .iter()
        .map(|d| d.name.clone())
        .filter(|d| !target.iter().flatten().any(|t| t == d))
        .collect();
    free.reverse();
    let first = netlist
        .dnms
        .first()
        .map(|d| d.name.clone())
        .unwrap_or_else(|| "local".into());
    let mut new_dnms = Vec::new();
    for t in target.iter_mut().filter(|t| t.is_none()) {
        *t = Some(match free.pop() {
            Some(d) => d,
            None => {
                // A fresh name: not declared, not made already.
                let name = (1..)
                    .map(|n| format!("{first}-{n}"))
                    .find(|n| netlist.dnm(n).is_none() && !new_dnms.iter().any(|(d, _)| d == n))
                    .unwrap_or_default();
                new_dnms.push((name.clone(), Some(first.clone())));
                name
            }
        });
    }
    let assignment: BTreeMap<String, String> = netlist
        .modules
        .iter()
        .zip(&clustering.community)
        .map(|(m, &c)| (m.name.clone(), target[c].clone().unwrap_or_default()))
        .collect();
    let mut clusters: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for (m, d) in &assignment {
        clusters.entry(d.clone()).or_default().push(m.clone());
    }
    let plain = module_graph(netlist, Weighting::Plain);
    Ok(Placement {
        weighting: options.weighting,
        refined: options.refine,
        predicted: predict_with(netlist, &assignment, measured),
        assignment,
        clusters,
        new_dnms,
        modularity: clustering.modularity,
        plain_modularity: plain.modularity(&clustering.community),
    })
}

/// Modularity of an existing assignment on the graph of `weighting`.
pub fn modularity_of(
    netlist: &Netlist,
    assignment: &BTreeMap<String, String>,
    weighting: Weighting,
) -> f64 {
    let g = module_graph(netlist, weighting);
    let mut ids: BTreeMap<&String, usize> = BTreeMap::new();
    let community: Vec<usize> = netlist
        .modules
        .iter()
        .map(|m| {
            let d = assignment.get(&m.name).unwrap_or(&m.dnm);
            let next = ids.len();
            *ids.entry(d).or_insert(next)
        })
        .collect();
    g.modularity(&community)
}
