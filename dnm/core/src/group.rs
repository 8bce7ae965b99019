//! A child's process group: a module process and whatever it starts (a wrapper script's real
//! module, a Python module's worker processes), or a module executable asked to describe
//! itself. Each is spawned as the leader of a group of its own, so signals meant for it reach
//! all of it: a module stopped, killed as hung or exited on its own leaves nothing behind that
//! would go on publishing as it.
//!
//! The group's id is the leader's pid, which stays the module's while the leader is not
//! reaped: everything here is done before the DNM waits for it.

/// Sends signal `sig` to child `pid` and every process of its group.
pub fn signal(pid: u32, sig: i32) {
    let Ok(pid) = i32::try_from(pid) else {
        return;
    };
    // SAFETY: kill(2) with a pid (and its group) of a child not reaped yet; the leader also
    // on its own, in case it left its group.
    unsafe {
        libc::kill(-pid, sig);
        libc::kill(pid, sig);
    }
}

/// Whether child `pid` has exited, without reaping it; `None`: it cannot be asked (not a
/// child of ours to wait for any more).
fn exited(pid: u32) -> Option<bool> {
    // SAFETY: an all-zero siginfo_t is valid; waitid(2) with WNOWAIT only reads the child's
    // state and leaves it to be reaped.
    unsafe {
        let mut info: libc::siginfo_t = std::mem::zeroed();
        let r = libc::waitid(
            libc::P_PID,
            pid,
            &mut info,
            libc::WEXITED | libc::WNOHANG | libc::WNOWAIT,
        );
        (r == 0).then(|| info.si_pid() != 0)
    }
}

/// Whether child `pid` may have exited (its reaping says for sure); if it has, what is left
/// of it (the helpers it started) is killed first, while its group is still its own.
pub fn kill_leftovers(pid: u32) -> bool {
    match exited(pid) {
        Some(true) => {
            signal(pid, libc::SIGKILL);
            true
        }
        Some(false) => false,
        // Nothing is signalled: its ids may be another's by now.
        None => true,
    }
}
