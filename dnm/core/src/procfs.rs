//! CPU time and memory of processes, read from `/proc`.

use std::time::Instant;

pub use dnm_proto::Memory;

/// Reads `/proc/<pid>/status` for resident memory.
pub fn memory(pid: u32) -> Option<Memory> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| -> u64 {
        text.lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|rest| rest.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    Some(Memory {
        anon_kib: field("RssAnon:"),
        file_kib: field("RssFile:"),
        shmem_kib: field("RssShmem:"),
    })
}

/// User plus system CPU time of a process, in seconds.
pub fn cpu_seconds(pid: u32) -> Option<f64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &text[text.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    // SAFETY: sysconf has no preconditions.
    let ticks = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    Some((utime + stime) / ticks.max(1.0))
}

/// CPU use of one process between two readings.
#[derive(Debug, Clone, Copy)]
pub struct CpuMeter {
    last: Option<(Instant, f64)>,
    /// Percent of one core over the last interval.
    pub percent: f64,
}

impl Default for CpuMeter {
    fn default() -> Self {
        Self {
            last: None,
            percent: 0.0,
        }
    }
}

impl CpuMeter {
    /// Takes a reading; updates `percent` when half a second of wall time or more has passed
    /// since the reading it was last updated from (readings taken once a second, a little
    /// early or late, each update it).
    pub fn sample(&mut self, pid: u32) {
        let Some(cpu) = cpu_seconds(pid) else { return };
        let now = Instant::now();
        match self.last {
            Some((t, c)) if now.duration_since(t).as_secs_f64() >= 0.5 => {
                self.percent = 100.0 * (cpu - c) / now.duration_since(t).as_secs_f64();
                self.last = Some((now, cpu));
            }
            Some(_) => {}
            None => self.last = Some((now, cpu)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_own_process() {
        let pid = std::process::id();
        assert!(cpu_seconds(pid).is_some());
        let m = memory(pid).unwrap();
        assert!(m.private_kib() > 0);
    }
}
