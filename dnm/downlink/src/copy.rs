//! The ground's copy of the rover's channels: which messages it holds, where it has gaps, and
//! how complete it is.

use std::collections::{BTreeMap, BTreeSet};

use serde::{Deserialize, Serialize};

use crate::protocol::Announce;

/// A stretch of a channel the ground does not hold: `[from_ns, to_ns]`, rover send times.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Gap {
    pub from_ns: u64,
    pub to_ns: u64,
}

/// Empty periods of a plan entry between two messages held that make a gap.
const GAP_PERIODS: u64 = 2;

/// What the ground holds of one channel.
#[derive(Debug, Default)]
pub(crate) struct ChannelCopy {
    pub announce: Option<Announce>,
    /// (log time, sequence) of every message held.
    pub held: BTreeSet<(u64, u32)>,
    /// Log times of the messages that came from the rover's recording (filled in later).
    pub backfilled: BTreeSet<u64>,
    /// Bytes of the messages held.
    pub bytes: u64,
    pub duplicates: u64,
    /// Stretches the rover answered it recorded nothing of its plan in.
    pub unrecorded: Vec<Gap>,
    /// The first and last log times of the channel in the rover's recording, as last heard.
    pub recorded: Option<(u64, u64)>,
    /// Stretches whose answer came back short (the link dropped some of its replies): asked
    /// for again whole, since a message lost alone leaves no gap between those held.
    pub recheck: Vec<Gap>,
}

impl ChannelCopy {
    /// Takes message (time, seq) of `len` bytes (`backfilled`: from the rover's recording);
    /// false if it was held already.
    pub fn take(&mut self, time: u64, seq: u32, len: usize, backfilled: bool) -> bool {
        let fresh = self.held.insert((time, seq));
        if fresh {
            self.bytes += len as u64;
            if backfilled {
                self.backfilled.insert(time);
            }
        } else {
            self.duplicates += 1;
        }
        fresh
    }

    fn period_ns(&self) -> Option<u64> {
        self.announce.as_ref().and_then(|a| a.period_ns)
    }

    /// Where the copy has gaps up to `settled_ns` (what is newer may still arrive live or be
    /// recovered from the publishers' caches), oldest first, leaving out what the rover holds
    /// nothing of. Only a plan entry with a rate has gaps that show: the plan keeps the first
    /// message of each of its periods, so two periods or more with none between two messages
    /// held are a gap. (A single lost message is the live recovery's to fill, from the
    /// publishers' caches; a single empty period is also what an output at its plan's rate
    /// shows now and then.)
    pub fn gaps(&self, settled_ns: u64) -> Vec<Gap> {
        let Some(period) = self.period_ns().filter(|p| *p > 0) else {
            return Vec::new();
        };
        let apart = |a: u64, b: u64| b / period > (a / period).saturating_add(GAP_PERIODS);
        let mut out = Vec::new();
        // Before the first message held: from where the rover's recording starts (or, until
        // the rover has said, from the start of time).
        let start = self.recorded.map_or(0, |r| r.0);
        let mut prev: Option<u64> = None;
        for &(t, _) in &self.held {
            match prev {
                None if t > start => out.push(Gap {
                    from_ns: start,
                    to_ns: t - 1,
                }),
                Some(p) if apart(p, t) => out.push(Gap {
                    from_ns: p.saturating_add(1),
                    to_ns: t - 1,
                }),
                _ => {}
            }
            prev = Some(t);
        }
        // After the last message held, up to the last the rover recorded as last heard (an
        // output that stopped leaves no gap; newer messages, live or not, show new gaps).
        let tail_end = self.recorded.map_or(settled_ns, |r| settled_ns.min(r.1));
        match prev {
            None if tail_end > start => out.push(Gap {
                from_ns: start,
                to_ns: tail_end,
            }),
            Some(p) if apart(p, tail_end) => out.push(Gap {
                from_ns: p.saturating_add(1),
                to_ns: tail_end,
            }),
            _ => {}
        }
        out.extend(self.recheck.iter().copied());
        let mut out = merged(out);
        out.retain(|g| g.from_ns <= settled_ns);
        for g in &mut out {
            g.to_ns = g.to_ns.min(settled_ns);
        }
        out.retain(|g| {
            !self
                .unrecorded
                .iter()
                .any(|u| u.from_ns <= g.from_ns && g.to_ns <= u.to_ns)
        });
        out
    }

    /// Marks `gap` as a stretch the rover holds nothing of, merged with those it touches.
    pub fn unrecorded(&mut self, gap: Gap) {
        self.unrecorded.push(gap);
        self.unrecorded = merged(std::mem::take(&mut self.unrecorded));
    }

    /// The answer for `asked` came back short: it is asked for again.
    pub fn recheck(&mut self, asked: Gap) {
        self.recheck.push(asked);
        self.recheck = merged(std::mem::take(&mut self.recheck));
    }

    /// Every message of `covered` came: it needs no second look.
    pub fn checked(&mut self, covered: Gap) {
        let mut left = Vec::with_capacity(self.recheck.len());
        for g in self.recheck.drain(..) {
            if g.to_ns < covered.from_ns || g.from_ns > covered.to_ns {
                left.push(g);
                continue;
            }
            if g.from_ns < covered.from_ns {
                left.push(Gap {
                    from_ns: g.from_ns,
                    to_ns: covered.from_ns - 1,
                });
            }
            if g.to_ns > covered.to_ns {
                left.push(Gap {
                    from_ns: covered.to_ns + 1,
                    to_ns: g.to_ns,
                });
            }
        }
        self.recheck = left;
    }
}

/// `gaps` sorted, those that overlap or touch made one.
fn merged(mut gaps: Vec<Gap>) -> Vec<Gap> {
    gaps.sort_by_key(|g| g.from_ns);
    let mut out: Vec<Gap> = Vec::with_capacity(gaps.len());
    for g in gaps {
        match out.last_mut() {
            Some(m) if g.from_ns <= m.to_ns.saturating_add(1) => m.to_ns = m.to_ns.max(g.to_ns),
            _ => out.push(g),
        }
    }
    out
}

/// How complete the ground's copy of one channel is.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ChannelStatus {
    pub topic: String,
    /// The DNM that records it, and its plan's rate (none: every message, as switches and
    /// events).
    pub dnm: Option<String>,
    pub rate_hz: Option<f64>,
    /// Messages held (received in this run or found in the session's files).
    pub received: u64,
    /// Messages the plan asks for over the stretch held: those held and those in its gaps.
    pub expected: u64,
    /// Rover send times of the oldest and newest held, Unix ns.
    pub first_unix_ns: Option<u64>,
    pub last_unix_ns: Option<u64>,
    /// The oldest stretch still missing, and how many there are.
    pub oldest_gap: Option<Gap>,
    pub gaps: usize,
    /// Bytes still to come for the gaps (at the size of the messages held).
    pub backlog_bytes: u64,
    /// Stretches the rover recorded nothing of (shown as gaps, never filled).
    pub unrecorded: Vec<Gap>,
    /// Messages received again that the copy already held.
    pub duplicates: u64,
    /// Where in time the copy's messages lie, from the first held to now (settled).
    pub timeline: Option<Timeline>,
}

/// A channel's copy over time: [`TIMELINE_BINS`] stretches of equal length, each with the
/// messages held that arrived live and those filled in from the recording.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Timeline {
    pub from_ns: u64,
    pub to_ns: u64,
    pub live: Vec<u32>,
    pub backfilled: Vec<u32>,
    /// Messages the plan asks for in a stretch (none: an output without a rate).
    pub expected_per_bin: Option<f64>,
}

/// Stretches of a [`Timeline`].
pub const TIMELINE_BINS: usize = 60;

impl ChannelCopy {
    fn timeline(&self, settled_ns: u64) -> Option<Timeline> {
        let from = self.held.first()?.0;
        let to = self
            .held
            .last()?
            .0
            .max(settled_ns)
            .max(from.saturating_add(1));
        let width = (to - from).div_ceil(TIMELINE_BINS as u64).max(1);
        let (mut live, mut backfilled) = (vec![0u32; TIMELINE_BINS], vec![0u32; TIMELINE_BINS]);
        for &(t, _) in &self.held {
            let bin = (((t - from) / width) as usize).min(TIMELINE_BINS - 1);
            if self.backfilled.contains(&t) {
                backfilled[bin] += 1;
            } else {
                live[bin] += 1;
            }
        }
        Some(Timeline {
            from_ns: from,
            to_ns: from.saturating_add(width.saturating_mul(TIMELINE_BINS as u64)),
            live,
            backfilled,
            expected_per_bin: self.period_ns().map(|p| width as f64 / p as f64),
        })
    }
}

/// The status of the whole copy.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RecordStatus {
    /// The session folder.
    pub dir: String,
    pub channels: Vec<ChannelStatus>,
    /// The downlink's budget (bytes a second; none: unlimited) and what the station measured
    /// over the last seconds, live and backfill together.
    pub budget_bytes_per_s: Option<u64>,
    pub measured_bytes_per_s: f64,
    /// The most one request of the backfill asks for now (what it may put in the link's
    /// queues ahead of a command): smaller while the link drains less.
    pub request_bytes: u64,
    /// What the backfill's answers delivered lately, bytes a second.
    pub delivered_bytes_per_s: Option<f64>,
    pub backlog_bytes: u64,
    /// How long the backlog takes to clear at the budget (or at what the answers delivered
    /// lately, if less).
    pub seconds_to_clear: Option<f64>,
    /// Messages the rover's publishers could no longer give (gone from their caches before
    /// the ground asked; the recording still has them).
    pub missed_live: u64,
}

/// Every channel's copy, by topic.
pub(crate) type Copies = BTreeMap<String, ChannelCopy>;

/// Each channel's status as of `settled_ns`.
pub(crate) fn channel_statuses(copies: &Copies, settled_ns: u64) -> Vec<ChannelStatus> {
    copies
        .iter()
        .map(|(topic, c)| {
            let gaps = c.gaps(settled_ns);
            let period = c.period_ns();
            // Before the rover said where its recording starts, a gap from the start of time
            // counts from the first message held.
            let floor = c
                .recorded
                .map(|r| r.0)
                .or_else(|| c.held.first().map(|h| h.0))
                .unwrap_or(u64::MAX);
            let missing: u64 = period.map_or(0, |p| {
                gaps.iter()
                    .map(|g| g.to_ns.saturating_sub(g.from_ns.max(floor)) / p.max(1))
                    .fold(0, u64::saturating_add)
            });
            let received = c.held.len() as u64;
            let average = c.bytes.checked_div(received).unwrap_or(0);
            ChannelStatus {
                topic: topic.clone(),
                dnm: c.announce.as_ref().map(|a| a.dnm.clone()),
                rate_hz: period.map(|p| 1e9 / p as f64),
                received,
                expected: received.saturating_add(missing),
                first_unix_ns: c.held.first().map(|h| h.0),
                last_unix_ns: c.held.last().map(|h| h.0),
                // From where the rover's recording starts, once it said.
                oldest_gap: gaps
                    .iter()
                    .map(|g| Gap {
                        from_ns: g.from_ns.max(floor),
                        to_ns: g.to_ns,
                    })
                    .find(|g| g.from_ns < g.to_ns),
                gaps: gaps.len(),
                backlog_bytes: missing.saturating_mul(average),
                unrecorded: c.unrecorded.clone(),
                duplicates: c.duplicates,
                timeline: c.timeline(settled_ns),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn copy(period_ms: u64, held_ms: &[u64]) -> ChannelCopy {
        let mut c = ChannelCopy {
            announce: Some(Announce {
                dnm: "rover".into(),
                desc: dnm_record::tap::ChannelDesc {
                    topic: "/rover/a/out".into(),
                    schema_name: String::new(),
                    schema_encoding: String::new(),
                    schema: String::new(),
                    message_encoding: String::new(),
                    metadata: BTreeMap::new(),
                },
                period_ns: Some(period_ms * 1_000_000),
                priority: 1,
                newest_first: true,
            }),
            recorded: Some((1_000_000, 2_000_000_000)),
            ..ChannelCopy::default()
        };
        for (i, t) in held_ms.iter().enumerate() {
            c.take(t * 1_000_000, i as u32, 10, i % 2 == 1);
        }
        c
    }

    #[test]
    fn gaps_are_the_stretches_between_messages_further_apart_than_the_plan_allows() {
        let ms = 1_000_000;
        // 10 Hz: a period of 100 ms with no message held is a gap.
        let c = copy(100, &[1, 101, 220, 300, 900, 1000]);
        let gaps = c.gaps(1_300 * ms);
        assert_eq!(
            gaps,
            vec![
                Gap {
                    from_ns: 300 * ms + 1,
                    to_ns: 900 * ms - 1
                },
                Gap {
                    from_ns: 1000 * ms + 1,
                    to_ns: 1_300 * ms
                }
            ]
        );
        // Not settled yet: the tail is not a gap.
        assert_eq!(c.gaps(1_150 * ms).len(), 1);
        // What the rover recorded nothing of is no gap to fill.
        let mut c = c;
        c.unrecorded.push(Gap {
            from_ns: 300 * ms,
            to_ns: 900 * ms,
        });
        assert_eq!(c.gaps(1_150 * ms), vec![]);
        let s = &channel_statuses(&BTreeMap::from([("/rover/a/out".into(), c)]), 1_300 * ms)[0];
        assert_eq!((s.received, s.gaps, s.expected), (6, 1, 8));
        assert_eq!(s.backlog_bytes, 20);
        // Held messages over time, live and filled in (every other one here).
        let t = s.timeline.as_ref().unwrap();
        assert_eq!(t.live.iter().sum::<u32>(), 3);
        assert_eq!(t.backfilled.iter().sum::<u32>(), 3);
        assert!(t.to_ns >= 1_300 * ms);
    }

    #[test]
    fn a_later_outage_is_a_gap_though_the_rover_last_said_it_recorded_less() {
        let ms = 1_000_000;
        // The recording said it ends at 1000 ms; then the link went down and came back.
        let mut c = copy(100, &[1, 101, 201, 301, 401, 501, 601, 701, 801, 901, 1000]);
        for (i, t) in [2000u64, 2100, 2200].iter().enumerate() {
            c.take(t * ms, 100 + i as u32, 10, false);
        }
        c.recorded = Some((ms, 1000 * ms));
        assert_eq!(
            c.gaps(3000 * ms),
            vec![Gap {
                from_ns: 1000 * ms + 1,
                to_ns: 2000 * ms - 1
            }]
        );
        // What the rover answered it holds nothing of merges into one stretch.
        c.unrecorded(Gap {
            from_ns: 1000 * ms + 1,
            to_ns: 1500 * ms,
        });
        c.unrecorded(Gap {
            from_ns: 1500 * ms + 1,
            to_ns: 2000 * ms - 1,
        });
        assert_eq!(c.unrecorded.len(), 1);
        assert_eq!(c.gaps(3000 * ms), vec![]);
    }

    #[test]
    fn a_message_held_twice_is_counted_once() {
        let mut c = copy(100, &[1]);
        assert!(!c.take(1_000_000, 0, 10, true));
        assert_eq!((c.held.len(), c.duplicates, c.bytes), (1, 1, 10));
    }

    #[test]
    fn a_stretch_answered_short_is_asked_for_again_until_answered_whole() {
        // Every period held but one: a message lost alone is no gap...
        let mut c = copy(100, &[1, 100, 200, 400, 500, 600, 700, 800, 900]);
        let ms = |m: u64| m * 1_000_000;
        assert_eq!(c.gaps(ms(900)), vec![]);
        // ...but the stretch whose answer came back short is one.
        c.recheck(Gap {
            from_ns: ms(150),
            to_ns: ms(450),
        });
        c.recheck(Gap {
            from_ns: ms(400),
            to_ns: ms(650),
        });
        assert_eq!(
            c.gaps(ms(900)),
            vec![Gap {
                from_ns: ms(150),
                to_ns: ms(650)
            }]
        );
        // An answer that covered its middle leaves both ends to ask for.
        c.checked(Gap {
            from_ns: ms(300),
            to_ns: ms(500),
        });
        assert_eq!(
            c.recheck,
            vec![
                Gap {
                    from_ns: ms(150),
                    to_ns: ms(300) - 1
                },
                Gap {
                    from_ns: ms(500) + 1,
                    to_ns: ms(650)
                }
            ]
        );
        c.checked(Gap {
            from_ns: 0,
            to_ns: ms(900),
        });
        assert_eq!(c.gaps(ms(900)), vec![]);
    }
}
