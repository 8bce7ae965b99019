//! Turning a netlist into the references each module needs: the connection layer's netlist.

use dnm_module::protocol::{InputRoute, Plan, Source};
use dnm_netlist::{Netlist, PortRef};

/// Task names in slot order (sorted by name, so every DNM numbers them alike).
pub fn task_slots(netlist: &Netlist) -> Vec<String> {
    netlist.tasks.keys().cloned().collect()
}

/// The plan of one module for one revision: every output any task connects to its inputs,
/// and which one feeds each input in each task slot.
pub fn module_plan(netlist: &Netlist, module: &str, revision: u64) -> Plan {
    let tasks = task_slots(netlist);
    let mut sources: Vec<Source> = Vec::new();
    let mut inputs = Vec::new();
    if let Some(kind) = netlist.kind_of(module) {
        for port in &kind.inputs {
            let input = PortRef {
                module: module.to_string(),
                port: port.name.clone(),
            };
            let by_slot = tasks
                .iter()
                .map(|t| {
                    let from = netlist.tasks[t].source_of(&input)?;
                    let source = Source {
                        module: from.module.clone(),
                        port: from.port.clone(),
                    };
                    let idx = sources
                        .iter()
                        .position(|s| *s == source)
                        .unwrap_or_else(|| {
                            sources.push(source);
                            sources.len() - 1
                        });
                    Some(idx as u32)
                })
                .collect();
            inputs.push(InputRoute {
                port: port.name.clone(),
                by_slot,
            });
        }
    }
    Plan {
        revision,
        tasks,
        sources,
        inputs,
        stop: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    const NET: &str = r#"
[system]
name = "t"
[[module]]
name = "a"
kind = "ticker"
[[module]]
name = "b"
kind = "ticker"
[[module]]
name = "p"
kind = "pair"
[task.one]
links = ["a.out -> p.a", "b.out -> p.b"]
[task.two]
links = ["b.out -> p.a", "a.out -> p.b"]
[task.three]
links = ["a.out -> p.a"]
"#;

    #[test]
    fn plans_list_each_source_once_and_route_every_slot() {
        let n = Netlist::parse(
            Path::new("t.toml"),
            NET,
            &dnm_modules::catalog(),
            &mut |_| Err("none".into()),
        )
        .unwrap();
        let plan = module_plan(&n, "p", 7);
        assert_eq!(plan.revision, 7);
        assert_eq!(plan.tasks, ["one", "three", "two"]);
        assert_eq!(plan.sources.len(), 2);
        let a = &plan.inputs[0];
        let b = &plan.inputs[1];
        let src = |i: Option<u32>| i.map(|i| plan.sources[i as usize].module.as_str());
        assert_eq!(a.port, "a");
        assert_eq!(
            a.by_slot.iter().map(|s| src(*s)).collect::<Vec<_>>(),
            [Some("a"), Some("a"), Some("b")]
        );
        assert_eq!(
            b.by_slot.iter().map(|s| src(*s)).collect::<Vec<_>>(),
            [Some("b"), None, Some("a")]
        );
        // A source module has no inputs to route.
        assert!(module_plan(&n, "a", 7).inputs.is_empty());
    }
}
