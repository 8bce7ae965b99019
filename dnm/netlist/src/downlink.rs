//! The downlink plan: which outputs the ground keeps a record of, at what rate, and in which
//! order what it missed is sent again (`[[downlink]]` entries of a netlist).
//!
//! ```toml
//! [[downlink]]
//! output = "odometry.odom"   # module.output
//! rate_hz = 10               # at most this many samples a second (decimated on board)
//! priority = 1               # what the ground misses is sent again lowest number first
//! backfill = "newest_first"  # or "oldest_first"
//! ```
//!
//! A plan's sample set is fixed by the rule of [`Decimator`], which the rover applies live and
//! to its recording alike: the ground's copy can be compared with the rover's, sample for
//! sample.

use std::collections::BTreeSet;

use serde::Deserialize;
use toml::Spanned;

use crate::error::{Reporter, suggest};
use crate::spec::Catalog;
use crate::{Backfill, DownlinkEntry, Module, PortRef};

/// The most samples a second one entry downlinks.
pub const MAX_DOWNLINK_HZ: f64 = 100.0;
/// The least: one sample every 1000 s.
pub const MIN_DOWNLINK_HZ: f64 = 0.001;
/// Priorities run from 1 (sent again first) to this.
pub const LOWEST_PRIORITY: u8 = 9;

/// The rule that picks the samples of an entry, on their send times (the rover recording's
/// log times): a sample is kept when it is the first of its period, counted from the Unix
/// epoch. It looks only at the sample before it on the same channel, so the rover picks the
/// same samples live as it picks later from any stretch of its recording (given the sample
/// just before the stretch), and the ground's copy can be compared with the recording sample
/// for sample.
#[derive(Debug, Clone, Copy)]
pub struct Decimator {
    period_ns: u64,
    last: Option<u64>,
}

impl Decimator {
    pub fn new(period_ns: u64) -> Self {
        Self {
            period_ns: period_ns.max(1),
            last: None,
        }
    }

    /// Whether the sample sent at `stamp_ns` is kept. Samples are given in the order sent.
    pub fn keep(&mut self, stamp_ns: u64) -> bool {
        let keep = self
            .last
            .is_none_or(|last| stamp_ns / self.period_ns > last / self.period_ns);
        self.last = Some(stamp_ns);
        keep
    }

    /// A decimator that has seen the sample sent at `stamp_ns` (the one before a stretch read
    /// on its own).
    pub fn after(period_ns: u64, stamp_ns: u64) -> Self {
        Self {
            period_ns: period_ns.max(1),
            last: Some(stamp_ns),
        }
    }
}

/// `[[downlink]]` as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawDownlink {
    output: Spanned<String>,
    rate_hz: Spanned<f64>,
    priority: Option<Spanned<i64>>,
    backfill: Option<Spanned<String>>,
}

/// Validates the plan against the modules: each entry an existing output, kept once, at a rate
/// and priority in range.
pub(crate) fn validate(
    r: &mut Reporter<'_>,
    raw: &[Spanned<RawDownlink>],
    modules: &[Module],
    kinds: &Catalog,
) -> Vec<DownlinkEntry> {
    let mut plan = Vec::new();
    let mut seen = BTreeSet::new();
    for (i, d) in raw.iter().enumerate() {
        let d = d.get_ref();
        let field = format!("downlink[{i}]");
        let output = output(r, &d.output, &format!("{field}.output"), modules, kinds);
        let rate = *d.rate_hz.get_ref();
        let rate_ok = (MIN_DOWNLINK_HZ..=MAX_DOWNLINK_HZ).contains(&rate);
        if !rate_ok {
            r.error(
                Some(d.rate_hz.span()),
                format!("{field}.rate_hz"),
                format!("{rate} Hz is out of range for the downlink"),
                Some(format!(
                    "use a rate from {MIN_DOWNLINK_HZ} to {MAX_DOWNLINK_HZ} Hz (e.g. `rate_hz = 1`)"
                )),
            );
        }
        let priority = match &d.priority {
            None => Some(5),
            Some(p) if (1..=i64::from(LOWEST_PRIORITY)).contains(p.get_ref()) => {
                Some(*p.get_ref() as u8)
            }
            Some(p) => {
                r.error(
                    Some(p.span()),
                    format!("{field}.priority"),
                    format!("priority {} is out of range", p.get_ref()),
                    Some(format!(
                        "use 1 (what the ground missed of it is sent again first) to {LOWEST_PRIORITY}"
                    )),
                );
                None
            }
        };
        let backfill = match d.backfill.as_ref().map(|b| (b, b.get_ref().as_str())) {
            None => Some(Backfill::default()),
            Some((_, "newest_first")) => Some(Backfill::NewestFirst),
            Some((_, "oldest_first")) => Some(Backfill::OldestFirst),
            Some((b, other)) => {
                r.error(
                    Some(b.span()),
                    format!("{field}.backfill"),
                    format!("`{other}` is not a backfill order"),
                    Some("use `\"newest_first\"` or `\"oldest_first\"`".into()),
                );
                None
            }
        };
        let Some(output) = output else { continue };
        if !seen.insert(output.clone()) {
            r.error(
                Some(d.output.span()),
                format!("{field}.output"),
                format!("`{output}` is in the downlink plan twice"),
                Some("keep one entry per output".into()),
            );
            continue;
        }
        if let (true, Some(priority), Some(backfill)) = (rate_ok, priority, backfill) {
            plan.push(DownlinkEntry {
                output,
                rate_hz: rate,
                priority,
                backfill,
            });
        }
    }
    plan
}

/// An entry's `output`: `module.port`, an output of an existing module.
fn output(
    r: &mut Reporter<'_>,
    at: &Spanned<String>,
    field: &str,
    modules: &[Module],
    kinds: &Catalog,
) -> Option<PortRef> {
    let text = at.get_ref().trim();
    let Some((module, port)) = text
        .split_once('.')
        .filter(|(m, p)| !m.is_empty() && !p.is_empty() && !p.contains('.'))
    else {
        r.error(
            Some(at.span()),
            field,
            format!("`{text}` is not `module.output`"),
            Some("name the output as `\"odometry.odom\"`".into()),
        );
        return None;
    };
    let Some(m) = modules.iter().find(|m| m.name == module) else {
        r.error(
            Some(at.span()),
            field,
            format!("unknown module `{module}`"),
            Some(suggest(module, modules.iter().map(|m| m.name.as_str()))),
        );
        return None;
    };
    // A module of an unknown kind is reported where it is declared.
    let kind = &kinds.get(&m.kind)?.spec;
    if kind.output(port).is_none() {
        r.error(
            Some(at.span()),
            field,
            format!(
                "module `{module}` (kind `{}`) has no output `{port}`",
                kind.name
            ),
            Some(suggest(port, kind.outputs.iter().map(|p| p.name.as_str()))),
        );
        return None;
    }
    Some(PortRef {
        module: module.to_string(),
        port: port.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_decimator_keeps_the_first_sample_of_each_period_and_agrees_on_any_stretch() {
        // 50 Hz with jitter, kept at 10 Hz: about every fifth sample.
        let base = 1_700_000_000_000_000_000u64;
        let stamps: Vec<u64> = (0..500u64)
            .map(|i| base + i * 20_000_000 + (i * 7919 % 13) * 100_000)
            .collect();
        let mut d = Decimator::new(100_000_000);
        let kept: Vec<usize> = (0..stamps.len()).filter(|&i| d.keep(stamps[i])).collect();
        assert!((99..=101).contains(&kept.len()), "{}", kept.len());
        assert!(
            kept.windows(2).all(|w| (4..=6).contains(&(w[1] - w[0]))),
            "{kept:?}"
        );
        // A stretch read later, from the sample before it on, keeps the same samples.
        for from in [1usize, 37, 250] {
            let mut d = Decimator::after(100_000_000, stamps[from - 1]);
            let again: Vec<usize> = (from..stamps.len())
                .filter(|&i| d.keep(stamps[i]))
                .collect();
            let live: Vec<usize> = kept.iter().copied().filter(|&i| i >= from).collect();
            assert_eq!(again, live, "from {from}");
        }
    }
}
