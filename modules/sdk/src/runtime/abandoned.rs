//! Services a process left half-created when it died.
//!
//! iceoryx2 (0.10) creates a service's static description as a file with the permissions of
//! one being written, writes it, then makes it read-only: only a read-only description is
//! finished. A process killed between those two steps (SIGKILL, or SIGTERM while a module is
//! still opening its services) leaves the file writable for good. Everyone who opens the
//! service afterwards waits iceoryx2's creation timeout and fails with `HangsInCreation`, and
//! iceoryx2's dead-node cleanup reads such a file as absent, so it never removes it: the
//! module whose output it is can never start again in that namespace.
//!
//! A live process finishes a description within microseconds, and iceoryx2 itself gives up on
//! one unfinished after its creation timeout. So a description still unfinished after that
//! timeout was abandoned, and removing it lets the next open create the service afresh. It is
//! the only thing the dead creator left: its dynamic state is created after the description
//! is finished.

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use iceoryx2::config::Config;
use iceoryx2::prelude::SemanticString;

/// The permissions of a description still being written (iceoryx2's `INIT_PERMISSIONS`).
const BEING_WRITTEN: u32 = 0o600;

/// A description found abandoned, and whether removing it worked.
#[derive(Debug)]
struct Abandoned {
    file: PathBuf,
    removed: Result<(), std::io::Error>,
}

/// What [`remove_abandoned_services`] did.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct AbandonedSweep {
    /// Descriptions removed.
    pub removed: usize,
    /// Descriptions unfinished for less than the creation timeout: being written now, or
    /// abandoned too recently to tell. A sweep after the timeout decides.
    pub undecided: usize,
}

/// Removes the service descriptions of `config`'s namespace that have been unfinished for
/// longer than its creation timeout, and logs each. A directory that cannot be read holds
/// none this process could remove.
pub fn remove_abandoned_services(config: &Config) -> AbandonedSweep {
    let (found, undecided) = find_and_remove(config);
    for a in &found {
        match &a.removed {
            Ok(()) => tracing::warn!(
                file = %a.file.display(),
                "removed a service a process left half-created when it died"
            ),
            Err(e) => tracing::warn!(
                file = %a.file.display(),
                "cannot remove a service a process left half-created: {e}"
            ),
        }
    }
    AbandonedSweep {
        removed: found.iter().filter(|a| a.removed.is_ok()).count(),
        undecided,
    }
}

/// The descriptions found abandoned (and removed), and how many unfinished ones are too young
/// to tell.
fn find_and_remove(config: &Config) -> (Vec<Abandoned>, usize) {
    let age = config.global.creation_timeout;
    let Some((dir, prefix, suffix)) = description_files(config) else {
        return (Vec::new(), 0);
    };
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return (Vec::new(), 0);
    };
    let now = SystemTime::now();
    let mut found = Vec::new();
    let mut undecided = 0;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        if !(name.starts_with(&prefix) && name.ends_with(&suffix)) {
            continue;
        }
        let path = entry.path();
        match unfinished_for(&path, now) {
            Some(for_) if for_ > age => {
                let removed = std::fs::remove_file(&path);
                found.push(Abandoned {
                    file: path,
                    removed,
                });
            }
            Some(_) => undecided += 1,
            None => {}
        }
    }
    (found, undecided)
}

/// How long the description at `path` has been unfinished, if it is.
fn unfinished_for(path: &Path, now: SystemTime) -> Option<Duration> {
    use std::os::unix::fs::PermissionsExt;
    let meta = std::fs::symlink_metadata(path).ok()?;
    if !meta.is_file() || meta.permissions().mode() & 0o777 != BEING_WRITTEN {
        return None;
    }
    // A time in the future (a clock set back) reads as just written.
    Some(
        now.duration_since(meta.modified().ok()?)
            .unwrap_or_default(),
    )
}

/// The directory of `config`'s service descriptions, and their names' prefix and suffix.
fn description_files(config: &Config) -> Option<(PathBuf, String, String)> {
    let text = |bytes: &[u8]| std::str::from_utf8(bytes).ok().map(str::to_owned);
    let root = text(config.global.root_path().as_bytes())?;
    let services = text(config.global.service.directory.as_bytes())?;
    Some((
        Path::new(&root).join(services),
        text(config.global.prefix.as_bytes())?,
        text(
            config
                .global
                .service
                .static_config_storage_suffix
                .as_bytes(),
        )?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::dnm_config;
    use crate::runtime::services::event_service;
    use iceoryx2::prelude::{Node, NodeBuilder, ipc};
    use std::os::unix::fs::PermissionsExt;
    use std::path::Path;

    /// A namespace of its own for each test, and a node in it.
    fn namespace(tag: &str) -> (Config, Node<ipc::Service>) {
        let config = dnm_config(&format!("abandon{}{tag}_", std::process::id())).unwrap();
        let node = NodeBuilder::new().config(&config).create().unwrap();
        (config, node)
    }

    /// The file of the description of event service `name`, found by creating the service
    /// once (a description's name is a hash of the service's).
    fn description_of(config: &Config, node: &Node<ipc::Service>, name: &str) -> PathBuf {
        let (dir, prefix, suffix) = description_files(config).unwrap();
        let list = || -> Vec<PathBuf> {
            std::fs::read_dir(&dir)
                .unwrap()
                .flatten()
                .map(|e| e.path())
                .filter(|p| {
                    let n = p.file_name().unwrap().to_str().unwrap();
                    n.starts_with(&prefix) && n.ends_with(&suffix)
                })
                .collect()
        };
        let before = list();
        let service = event_service(node, name).unwrap();
        let new: Vec<_> = list().into_iter().filter(|p| !before.contains(p)).collect();
        drop(service);
        assert_eq!(new.len(), 1, "{new:?}");
        assert!(!new[0].exists(), "the service outlived its only user");
        new[0].clone()
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

        // What the module whose output it is meets when it starts again.
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
    fn only_descriptions_unfinished_past_the_creation_timeout_are_removed() {
        let (config, node) = namespace("age");
        let old = description_of(&config, &node, "old/ev");
        let young = description_of(&config, &node, "young/ev");
        let timeout = config.global.creation_timeout;
        abandon(&old, timeout * 2);
        abandon(&young, Duration::ZERO);
        // A finished service of the same namespace.
        let _alive = event_service(&node, "alive/ev").unwrap();

        let (found, undecided) = find_and_remove(&config);
        assert_eq!(found.len(), 1, "{found:?}");
        assert_eq!(undecided, 1);
        assert_eq!(found[0].file, old);
        assert!(found[0].removed.is_ok());
        assert!(!old.exists());
        assert!(young.exists(), "one being written now is left alone");
        std::fs::remove_file(&young).unwrap();
        assert_eq!(
            remove_abandoned_services(&config),
            AbandonedSweep::default()
        );
    }
}
