//! The wiring of a committed netlist as tools see it: DNMs, modules with their ports' message
//! types and parameters, and every task's links. A DNM answers it on Zenoh, so a monitor or a
//! GUI can draw the connection layer and decode any port without the kinds' catalogue and
//! without running anything.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::{DnmDecl, Link, Netlist, ParamValue, PortSpec};

/// A netlist revision in force, wired.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Wiring {
    pub system: String,
    /// The DNM that answered.
    pub dnm: String,
    pub revision: u64,
    pub active_task: Option<String>,
    pub dnms: Vec<DnmDecl>,
    pub modules: Vec<WiredModule>,
    /// Every task's links, by task name.
    pub tasks: BTreeMap<String, Vec<Link>>,
}

/// One module of a [`Wiring`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WiredModule {
    pub name: String,
    pub kind: String,
    pub dnm: String,
    pub params: BTreeMap<String, ParamValue>,
    pub inputs: Vec<PortSpec>,
    pub outputs: Vec<PortSpec>,
}

impl Wiring {
    /// The wiring of `netlist` as revision `revision` with `active_task` in force, told by `dnm`.
    pub fn of(netlist: &Netlist, dnm: &str, revision: u64, active_task: Option<&str>) -> Self {
        Self {
            system: netlist.system.clone(),
            dnm: dnm.to_string(),
            revision,
            active_task: active_task.map(str::to_string),
            dnms: netlist.dnms.clone(),
            modules: netlist
                .modules
                .iter()
                .map(|m| {
                    let kind = netlist.kind_of(&m.name);
                    WiredModule {
                        name: m.name.clone(),
                        kind: m.kind.clone(),
                        dnm: m.dnm.clone(),
                        params: m.params.clone(),
                        inputs: kind
                            .map(|k| k.inputs.iter().map(PortSpec::without_body).collect())
                            .unwrap_or_default(),
                        outputs: kind
                            .map(|k| k.outputs.iter().map(PortSpec::without_body).collect())
                            .unwrap_or_default(),
                    }
                })
                .collect(),
            tasks: netlist
                .tasks
                .iter()
                .map(|(name, t)| (name.clone(), t.links.clone()))
                .collect(),
        }
    }

    pub fn module(&self, name: &str) -> Option<&WiredModule> {
        self.modules.iter().find(|m| m.name == name)
    }

    /// The links of the task in force (none without one).
    pub fn active_links(&self) -> &[Link] {
        self.active_task
            .as_ref()
            .and_then(|t| self.tasks.get(t))
            .map_or(&[], Vec::as_slice)
    }
}
