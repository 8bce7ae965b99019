//! Wall-clock time as every part of the system stamps it: nanoseconds since the Unix epoch.
//! Send times, decided instants, safings and time tags are all in it, so it is read in one
//! place.

use std::time::{SystemTime, UNIX_EPOCH};

/// Wall-clock time now, ns since the Unix epoch (0 for a clock set before 1970).
pub fn now_unix_ns() -> u64 {
    unix_ns(SystemTime::now())
}

/// `t` in ns since the Unix epoch (0 before it; saturates in the year 2554).
pub fn unix_ns(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn counts_from_the_epoch_and_never_wraps() {
        assert_eq!(unix_ns(UNIX_EPOCH + Duration::from_nanos(42)), 42);
        assert_eq!(unix_ns(UNIX_EPOCH - Duration::from_secs(1)), 0);
        assert_eq!(
            unix_ns(UNIX_EPOCH + Duration::from_secs(600 * 365 * 86_400)),
            u64::MAX
        );
        assert!(now_unix_ns() > 1_700_000_000_000_000_000);
    }
}
