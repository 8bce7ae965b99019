//! Building a [`KindSpec`] from Rust types.

use dnm_netlist::{KindSpec, ParamKind, ParamSpec, ParamValue, PortSpec, Trigger};

use crate::msg::{BytesMessage, Message};

/// Declares a module kind: its ports, parameters and trigger.
///
/// ```
/// use dnm_module::{Kind, msg::Tick};
/// let spec = Kind::new("relay", "forwards ticks")
///     .input::<Tick>("in")
///     .output::<Tick>("out")
///     .on_input()
///     .build();
/// assert_eq!(spec.inputs[0].message.schema_name, "dnm_msgs/Tick");
/// ```
#[derive(Debug, Clone)]
pub struct Kind {
    spec: KindSpec,
}

impl Kind {
    /// A kind that runs periodically at 10 Hz until told otherwise.
    pub fn new(name: &str, summary: &str) -> Self {
        Self {
            spec: KindSpec {
                name: name.to_string(),
                summary: summary.to_string(),
                inputs: Vec::new(),
                outputs: Vec::new(),
                params: Vec::new(),
                trigger: Trigger::Periodic { rate_hz: 10.0 },
            },
        }
    }

    pub fn input<M: Message>(mut self, name: &str) -> Self {
        self.spec.inputs.push(PortSpec {
            name: name.to_string(),
            message: M::message_type(),
        });
        self
    }

    pub fn output<M: Message>(mut self, name: &str) -> Self {
        self.spec.outputs.push(PortSpec {
            name: name.to_string(),
            message: M::message_type(),
        });
        self
    }

    pub fn bytes_input<M: BytesMessage>(mut self, name: &str, max_bytes: usize) -> Self {
        self.spec.inputs.push(PortSpec {
            name: name.to_string(),
            message: M::message_type(max_bytes),
        });
        self
    }

    pub fn bytes_output<M: BytesMessage>(mut self, name: &str, max_bytes: usize) -> Self {
        self.spec.outputs.push(PortSpec {
            name: name.to_string(),
            message: M::message_type(max_bytes),
        });
        self
    }

    fn param(
        mut self,
        name: &str,
        kind: ParamKind,
        default: Option<ParamValue>,
        doc: &str,
    ) -> Self {
        self.spec.params.push(ParamSpec {
            name: name.to_string(),
            kind,
            default,
            doc: doc.to_string(),
        });
        self
    }

    pub fn param_f64(self, name: &str, default: f64, doc: &str) -> Self {
        self.param(
            name,
            ParamKind::Float,
            Some(ParamValue::Float(default)),
            doc,
        )
    }

    pub fn param_i64(self, name: &str, default: i64, doc: &str) -> Self {
        self.param(name, ParamKind::Int, Some(ParamValue::Int(default)), doc)
    }

    pub fn param_bool(self, name: &str, default: bool, doc: &str) -> Self {
        self.param(name, ParamKind::Bool, Some(ParamValue::Bool(default)), doc)
    }

    pub fn param_string(self, name: &str, default: &str, doc: &str) -> Self {
        self.param(
            name,
            ParamKind::String,
            Some(ParamValue::String(default.to_string())),
            doc,
        )
    }

    /// A parameter the netlist must give.
    pub fn required_param(self, name: &str, kind: ParamKind, doc: &str) -> Self {
        self.param(name, kind, None, doc)
    }

    /// Step at `rate_hz` (the netlist may override it per module).
    pub fn periodic(mut self, rate_hz: f64) -> Self {
        self.spec.trigger = Trigger::Periodic { rate_hz };
        self
    }

    /// Step whenever an input connected in the active task has new data.
    pub fn on_input(mut self) -> Self {
        self.spec.trigger = Trigger::OnInput;
        self
    }

    pub fn build(self) -> KindSpec {
        self.spec
    }
}
