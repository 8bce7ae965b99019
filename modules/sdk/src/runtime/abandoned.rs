//! Services a process left half-created when it died.
//!
//! iceoryx2 (0.10) creates a service in this order: the creating node's tag for it, then the
//! service's static description (a file created writable, written, synced, then made
//! read-only: only a read-only description is finished), then its dynamic state. A process
//! killed before the description is finished (SIGKILL, a crash) leaves it writable for good.
//! Everyone who opens the service afterwards waits iceoryx2's creation timeout and fails with
//! `HangsInCreation`, and iceoryx2's dead-node cleanup reads such a file as absent, so it
//! never removes it: the module whose service it is could never start again in that
//! namespace.
//!
//! A description is abandoned when it is unfinished, no live node holds the tag its creator
//! wrote before creating it, and it has been unfinished for longer than the creation timeout
//! (a second guard, for a creator whose tag this process cannot see). Removing it lets the
//! next open create the service afresh: it is the only thing the dead creator left (its tag
//! goes with its node in iceoryx2's dead-node cleanup, its dynamic state did not exist yet).
//! Every sweep holds a lock on the services directory (shared by the namespaces of one
//! machine), so two processes recovering the same service never remove each other's fresh one.

use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use iceoryx2::config::Config;
use iceoryx2::node::{Node, NodeState, NodeView};
use iceoryx2::prelude::{CallbackProgression, SemanticString, ipc};

/// The permissions of a description still being written (iceoryx2's `INIT_PERMISSIONS`; a
/// finished one is read-only).
const BEING_WRITTEN: u32 = 0o600;

/// A service hash: 40 hexadecimal digits (SHA-1), as iceoryx2 names descriptions.
const HASH_LEN: usize = 40;

/// A description found abandoned, and whether removing it worked.
#[derive(Debug)]
struct Abandoned {
    file: PathBuf,
    removed: Result<(), std::io::Error>,
}

/// Longest a sweep waits for another process's to finish.
const LOCK_WAIT: Duration = Duration::from_secs(2);

/// What [`remove_abandoned_services`] did.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct AbandonedSweep {
    /// Descriptions removed (or found removed by another process meanwhile).
    pub removed: usize,
    /// Unfinished descriptions left alone: being written by a live process, or abandoned too
    /// recently to tell (1 also when another process's sweep held the folder past
    /// [`LOCK_WAIT`]). A sweep after the creation timeout decides.
    pub undecided: usize,
}

/// Removes the abandoned service descriptions of `config`'s namespace, logging each. A
/// directory that cannot be read holds none this process could remove.
pub fn remove_abandoned_services(config: &Config) -> AbandonedSweep {
    let (found, undecided) = find_and_remove(config, config.global.creation_timeout);
    let mut removed = 0;
    for a in &found {
        match &a.removed {
            Ok(()) => {
                removed += 1;
                tracing::warn!(
                    file = %a.file.display(),
                    "removed a service a process left half-created when it died"
                );
            }
            // Another process's sweep removed it first.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => removed += 1,
            Err(e) => tracing::warn!(
                file = %a.file.display(),
                "cannot remove a service a process left half-created: {e}"
            ),
        }
    }
    AbandonedSweep { removed, undecided }
}

/// The descriptions found abandoned (and removed), unfinished for longer than `timeout`, and
/// how many unfinished ones were left.
fn find_and_remove(config: &Config, timeout: Duration) -> (Vec<Abandoned>, usize) {
    let Some(names) = Names::of(config) else {
        return (Vec::new(), 0);
    };
    let Ok(dir) = std::fs::File::open(&names.services) else {
        return (Vec::new(), 0);
    };
    // One sweep at a time on the machine, waited for [`LOCK_WAIT`] at most (whoever holds the
    // lock may be stopped, or never let go): then this one is left undecided.
    let deadline = std::time::Instant::now() + LOCK_WAIT;
    loop {
        // SAFETY: flock(2) on a descriptor this function owns; released when `dir` closes.
        if unsafe { libc::flock(dir.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0 {
            break;
        }
        let busy = std::io::Error::last_os_error().kind() == std::io::ErrorKind::WouldBlock;
        if !busy {
            return (Vec::new(), 0);
        }
        if std::time::Instant::now() >= deadline {
            return (Vec::new(), 1);
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let Ok(entries) = std::fs::read_dir(&names.services) else {
        return (Vec::new(), 0);
    };
    let now = SystemTime::now();
    let mut creators: Option<Vec<PathBuf>> = None;
    let mut found = Vec::new();
    let mut undecided = 0;
    for entry in entries.flatten() {
        let path = entry.path();
        let Some(hash) = names.hash_of(&entry.file_name()) else {
            continue;
        };
        let Some(for_) = unfinished_for(&path, now) else {
            continue;
        };
        let live = creators.get_or_insert_with(|| live_node_dirs(config));
        let held = live.iter().any(|d| d.join(names.tag(&hash)).exists());
        if !held && for_ > timeout {
            let removed = std::fs::remove_file(&path);
            found.push(Abandoned {
                file: path,
                removed,
            });
        } else {
            undecided += 1;
        }
    }
    (found, undecided)
}

/// How long the description at `path` has been unfinished, if it is. One last written in the
/// future (the clock set back since) has been unfinished at least since the clock changed.
fn unfinished_for(path: &Path, now: SystemTime) -> Option<Duration> {
    use std::os::unix::fs::PermissionsExt;
    let meta = std::fs::symlink_metadata(path).ok()?;
    if !meta.is_file() || meta.permissions().mode() & 0o777 != BEING_WRITTEN {
        return None;
    }
    Some(
        now.duration_since(meta.modified().ok()?)
            .unwrap_or(Duration::MAX),
    )
}

/// The folders of the nodes of `config`'s namespace that may be alive (alive, or in a state
/// this process cannot judge), where their service tags are.
fn live_node_dirs(config: &Config) -> Vec<PathBuf> {
    let Some(root) = text(config.global.node_dir().as_bytes()) else {
        return Vec::new();
    };
    let mut dirs = Vec::new();
    let listed = Node::<ipc::Service>::list(config, |state| {
        let id = match &state {
            NodeState::Alive(view) => Some(view.id()),
            NodeState::Dead(_) => None,
            NodeState::Inaccessible(id) | NodeState::Undefined(id) => Some(id),
        };
        if let Some(id) = id {
            dirs.push(Path::new(&root).join(id.value().to_string()));
        }
        CallbackProgression::Continue
    });
    if listed.is_err() {
        // Nodes that cannot be listed may all be alive: every tag counts.
        return std::fs::read_dir(&root)
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.path())
            .collect();
    }
    dirs
}

fn text(bytes: &[u8]) -> Option<String> {
    std::str::from_utf8(bytes).ok().map(str::to_owned)
}

/// Where and under which names a namespace keeps its service descriptions and tags.
struct Names {
    services: PathBuf,
    prefix: String,
    suffix: String,
    tag_suffix: String,
}

impl Names {
    fn of(config: &Config) -> Option<Self> {
        let g = &config.global;
        Some(Self {
            services: Path::new(&text(g.root_path().as_bytes())?)
                .join(text(g.service.directory.as_bytes())?),
            prefix: text(g.prefix.as_bytes())?,
            suffix: text(g.service.static_config_storage_suffix.as_bytes())?,
            tag_suffix: text(g.node.service_tag_suffix.as_bytes())?,
        })
    }

    /// The service hash a file of this namespace's descriptions is named after (exactly a
    /// hash: a namespace whose prefix starts with this one's is another's).
    fn hash_of(&self, name: &std::ffi::OsStr) -> Option<String> {
        let hash = name
            .to_str()?
            .strip_prefix(&self.prefix)?
            .strip_suffix(&self.suffix)?;
        (hash.len() == HASH_LEN && hash.bytes().all(|b| b.is_ascii_hexdigit()))
            .then(|| hash.to_owned())
    }

    /// The file name of a node's tag for the service `hash`.
    fn tag(&self, hash: &str) -> String {
        format!("{}{hash}{}", self.prefix, self.tag_suffix)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::dnm_config;
    use crate::runtime::services::event_service;
    use iceoryx2::prelude::NodeBuilder;
    use std::os::unix::fs::PermissionsExt;

    /// A namespace of its own for each test, and a node in it.
    fn namespace(tag: &str) -> (Config, Node<ipc::Service>) {
        let config = dnm_config(&format!("abandon{}{tag}_", std::process::id())).unwrap();
        let node = NodeBuilder::new().config(&config).create().unwrap();
        (config, node)
    }

    /// The file of the description of event service `name` (named after a hash of the
    /// service's name), found by creating the service once and reading the descriptions.
    fn description_of(config: &Config, node: &Node<ipc::Service>, name: &str) -> PathBuf {
        let names = Names::of(config).unwrap();
        let service = event_service(node, name).unwrap();
        let says = format!("service_name = \"{name}\"");
        let file = std::fs::read_dir(&names.services)
            .unwrap()
            .flatten()
            .filter(|e| names.hash_of(&e.file_name()).is_some())
            .map(|e| e.path())
            .find(|p| std::fs::read_to_string(p).is_ok_and(|t| t.contains(&says)))
            .unwrap();
        drop(service);
        assert!(!file.exists(), "the service outlived its only user");
        file
    }

    /// Leaves at `file` what a creator killed before finishing leaves: the description,
    /// written, still writable, last written `ago`.
    fn abandon(file: &Path, ago: Duration) {
        let f = std::fs::File::create(file).unwrap();
        std::fs::set_permissions(file, std::fs::Permissions::from_mode(BEING_WRITTEN)).unwrap();
        f.set_modified(SystemTime::now() - ago).unwrap();
    }

    #[test]
    fn a_service_left_half_created_by_a_dead_process_opens_again() {
        let (config, node) = namespace("open");
        let file = description_of(&config, &node, "m/out/ev");
        abandon(&file, Duration::ZERO);

        // What the module whose output it is meets when it starts again: iceoryx2 waits its
        // creation timeout, then the description is abandoned by every rule.
        let service = event_service(&node, "m/out/ev").expect("the service opens");
        let mode = std::fs::metadata(&file).unwrap().permissions().mode() & 0o777;
        assert_ne!(mode, BEING_WRITTEN, "the description was created afresh");
        let listener = service.listener_builder().create().unwrap();
        let notifier = service.notifier_builder().create().unwrap();
        notifier.notify().unwrap();
        let mut heard = 0;
        listener.try_wait(|_| heard += 1).unwrap();
        assert_eq!(heard, 1);
    }

    #[test]
    fn only_descriptions_unfinished_past_the_timeout_are_removed() {
        let (config, node) = namespace("age");
        let old = description_of(&config, &node, "old/ev");
        let young = description_of(&config, &node, "young/ev");
        // A finished service of the same namespace, and an unfinished one of a namespace
        // whose prefix starts with this one's.
        let _alive = event_service(&node, "alive/ev").unwrap();
        let names = Names::of(&config).unwrap();
        let hash = names.hash_of(old.file_name().unwrap()).unwrap();
        let other = names
            .services
            .join(format!("{}b_{hash}{}", names.prefix, names.suffix));
        let hour = Duration::from_secs(3600);
        abandon(&old, hour * 2);
        abandon(&young, Duration::ZERO);
        abandon(&other, hour * 2);

        let (found, undecided) = find_and_remove(&config, hour);
        assert_eq!(found.len(), 1, "{found:?}");
        assert_eq!(found[0].file, old);
        assert!(found[0].removed.is_ok());
        assert_eq!(undecided, 1, "the young one is left for a later sweep");
        assert!(young.exists());
        assert!(
            other.exists(),
            "another namespace's file is not this one's to judge"
        );
        std::fs::remove_file(&young).unwrap();
        std::fs::remove_file(&other).unwrap();
        assert_eq!(
            remove_abandoned_services(&config),
            AbandonedSweep::default()
        );
    }

    #[test]
    fn a_sweep_held_up_elsewhere_is_left_undecided_not_waited_for() {
        // A root of its own: the lock held here holds up no other test's sweeps.
        let root = std::env::temp_dir().join(format!("dnm-held-{}", std::process::id()));
        let mut config = dnm_config(&format!("held{}_", std::process::id())).unwrap();
        let root_path = iceoryx2::prelude::Path::new(root.to_str().unwrap().as_bytes()).unwrap();
        config.global.set_root_path(&root_path);
        let names = Names::of(&config).unwrap();
        std::fs::create_dir_all(&names.services).unwrap();
        // Another sweep that never lets go (a process stopped in it): a lock of another open
        // of the folder, which conflicts with the sweep's own as another process's would.
        let held = std::fs::File::open(&names.services).unwrap();
        // SAFETY: flock(2) on a descriptor this test owns; released when it closes.
        assert_eq!(unsafe { libc::flock(held.as_raw_fd(), libc::LOCK_EX) }, 0);
        assert_eq!(
            remove_abandoned_services(&config),
            AbandonedSweep {
                removed: 0,
                undecided: 1
            }
        );
        drop(held);
        assert_eq!(
            remove_abandoned_services(&config),
            AbandonedSweep::default()
        );
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn a_description_whose_creator_is_alive_is_left_however_old() {
        let (config, node) = namespace("live");
        let file = description_of(&config, &node, "slow/ev");
        let names = Names::of(&config).unwrap();
        let hash = names.hash_of(file.file_name().unwrap()).unwrap();
        // What a live creator has when it writes the description: its tag for the service.
        let tag = Path::new(&text(config.global.node_dir().as_bytes()).unwrap())
            .join(node.id().value().to_string())
            .join(names.tag(&hash));
        std::fs::write(&tag, "").unwrap();
        abandon(&file, Duration::from_secs(7200));

        assert_eq!(
            remove_abandoned_services(&config),
            AbandonedSweep {
                removed: 0,
                undecided: 1
            }
        );
        assert!(file.exists());
        // Its creator gone (iceoryx2 removes a dead node's tags), the description is
        // abandoned.
        std::fs::remove_file(&tag).unwrap();
        assert_eq!(remove_abandoned_services(&config).removed, 1);
        assert!(!file.exists());
    }
}
