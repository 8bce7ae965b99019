//! A session's manifest, written at every rotation of a recorder that runs for weeks: what it
//! costs in memory must not grow with the session's files, and what it says must be what the
//! files say, whether a file's entry was read from the file or taken from the manifest before.
#![allow(clippy::unwrap_used)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use dnm_record::session::{self, MANIFEST, Manifest};

/// The system's allocator, counting the bytes each thread holds and the most it held since the
/// last reset (per thread: the tests of this file run side by side).
struct Counting;

thread_local! {
    static HELD: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

fn count(bytes: isize) {
    // A thread being torn down has no counters left: what it frees then is not counted.
    let _ = HELD.try_with(|held| {
        let now = held.get() + bytes;
        held.set(now);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
    });
}

// SAFETY: every call is passed on to the system's allocator unchanged; only counted.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as the caller promised for `layout`.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            count(layout.size() as isize);
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, layout: Layout) {
        // SAFETY: `p` was allocated by `alloc` with `layout`.
        unsafe { System.dealloc(p, layout) };
        count(-(layout.size() as isize));
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Heap this thread held at most while `f` ran, beyond what it held when it started.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let before = HELD.with(Cell::get);
    PEAK.with(|p| p.set(before));
    let out = f();
    (out, (PEAK.with(Cell::get) - before).max(0) as usize)
}

const TOPICS: [&str; 12] = [
    "motor_left/state",
    "motor_left/state/raw",
    "motor_right/state",
    "motor_right/state/raw",
    "encoders/ticks",
    "mixer/left",
    "mixer/right",
    "watchdog/state",
    "watchdog/twist",
    "world/state",
    "world/state/raw",
    "odometry/odom",
];

/// A closed MCAP file as a recorder of DNM `dnm` writes it: a message on each of its channels,
/// the netlist of `revision` attached.
fn write_file(path: &Path, dnm: &str, revision: u64, t0: u64) {
    let mut w = mcap::Writer::new(std::io::BufWriter::new(
        std::fs::File::create(path).unwrap(),
    ))
    .unwrap();
    let mut meta = BTreeMap::new();
    meta.insert("dnm".to_string(), dnm.to_string());
    for (i, topic) in TOPICS.iter().enumerate() {
        let id = w
            .add_channel(0, &format!("/{dnm}/{topic}"), "cdr", &meta)
            .unwrap();
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: id,
                sequence: 0,
                log_time: t0 + i as u64,
                publish_time: t0 + i as u64,
            },
            &[0u8; 16],
        )
        .unwrap();
    }
    let text = format!("# the netlist of revision {revision}\n[system]\nname = \"m\"\n");
    dnm_record::record::netlist_records(&mut w, t0, revision, "netlist.toml", &text).unwrap();
    w.finish().unwrap();
}

/// A session folder with `n` closed files of two DNMs, the netlist changing every 40 files.
fn session(name: &str, n: usize) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("dnm-manifest-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    add_files(&dir, 0, n);
    dir
}

/// Files `from..to` of the session (each DNM's `rec-<dnm>.mcap`, `.1.mcap`, ...).
fn add_files(dir: &Path, from: usize, to: usize) {
    for i in from..to {
        let dnm = if i % 2 == 0 { "drive" } else { "nav" };
        let k = i / 2;
        let name = if k == 0 {
            format!("rec-{dnm}.mcap")
        } else {
            format!("rec-{dnm}.{k}.mcap")
        };
        write_file(
            &dir.join(name),
            dnm,
            1 + (i / 40) as u64,
            1_000_000 * i as u64,
        );
    }
}

/// Asserts two manifests say the same, naming the first thing they disagree on.
fn assert_same(a: &Manifest, b: &Manifest) {
    let names = |m: &Manifest| m.files.iter().map(|f| f.name.clone()).collect::<Vec<_>>();
    assert_eq!(names(a), names(b), "the files listed");
    for (x, y) in a.files.iter().zip(&b.files) {
        assert_eq!(x, y, "the entry of {}", x.name);
    }
    assert_eq!(a.netlists, b.netlists, "the netlists");
    assert_eq!(a, b);
}

#[test]
fn a_manifest_costs_no_more_memory_for_a_thousand_files_than_for_a_hundred() {
    let small = session("small", 100);
    let large = session("large", 1000);
    // Written once (every entry read from its file), then at a rotation: the entries of the
    // closed files taken from the manifest before, one new file read.
    for dir in [&small, &large] {
        session::write_manifest(dir).unwrap();
    }
    let n = |dir: &Path| session::files(dir).unwrap().len();
    add_files(&small, 100, 101);
    add_files(&large, 1000, 1001);
    let (written, small_peak) = peak_of(|| session::write_manifest(&small).unwrap());
    assert_eq!(written.files, n(&small));
    let (written, large_peak) = peak_of(|| session::write_manifest(&large).unwrap());
    assert_eq!(written.files, n(&large));
    assert_eq!(written.messages, 1001 * TOPICS.len() as u64);
    // What grows with the files is their paths as the folder is listed (a path and a little
    // more each); a manifest held whole would hold each file's entry, several times that.
    let path = large.join("rec-drive.500.mcap").as_os_str().len();
    let manifest_bytes = std::fs::metadata(large.join(MANIFEST)).unwrap().len() as usize;
    let grown = large_peak.saturating_sub(small_peak);
    eprintln!(
        "peak heap writing the manifest: {small_peak} B for 101 files, {large_peak} B for 1001"
    );
    assert!(
        grown < 900 * (path + 96),
        "writing the manifest of 1001 files held {large_peak} bytes at most, of 101 files \
         {small_peak}: {grown} more for 900 files (the manifest is {manifest_bytes} bytes)"
    );
    for dir in [small, large] {
        let _ = std::fs::remove_dir_all(dir);
    }
}

#[test]
fn a_manifest_written_at_a_rotation_says_what_one_read_from_the_files_says() {
    let dir = session("same", 90);
    session::write_manifest(&dir).unwrap();
    add_files(&dir, 90, 97);
    // A file rewritten at another size since (its entry must be read again), and one removed.
    write_file(&dir.join("rec-drive.3.mcap"), "drive", 10, 5);
    std::fs::remove_file(dir.join("rec-nav.10.mcap")).unwrap();
    session::write_manifest(&dir).unwrap();
    let at_rotation = written(&dir);
    // The same session indexed from its files alone.
    std::fs::remove_file(dir.join(MANIFEST)).unwrap();
    let from_files = session::index(&dir).unwrap();
    assert_same(&at_rotation, &from_files);
    assert_eq!(at_rotation.files.len(), 96);
    assert_eq!(at_rotation.revisions, [1, 2, 3, 10]);
    assert_eq!(at_rotation.netlists.len(), 4);
    assert!(at_rotation.files.iter().all(|f| f.complete));
    let rewritten = at_rotation
        .files
        .iter()
        .find(|f| f.name == "rec-drive.3.mcap")
        .unwrap();
    assert_eq!(rewritten.start_unix_ns, Some(5));
    assert_eq!(rewritten.revisions, [10]);
    assert!(
        !at_rotation
            .files
            .iter()
            .any(|f| f.name == "rec-nav.10.mcap")
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_manifest_of_the_earlier_layout_without_its_netlists_cut_short_or_out_of_order_is_taken_up() {
    let dir = session("earlier", 20);
    let whole = session::index(&dir).unwrap();
    // As manifests were written before (one JSON document, indented), with its netlists lost:
    // the entries are taken from it, the netlists read again from the files.
    let mut without = whole.clone();
    without.netlists.clear();
    std::fs::write(
        dir.join(MANIFEST),
        serde_json::to_vec_pretty(&without).unwrap(),
    )
    .unwrap();
    session::write_manifest(&dir).unwrap();
    assert_same(&written(&dir), &whole);
    // A manifest cut short (a disk filled up): what it lists is used, the rest read.
    let text = std::fs::read(dir.join(MANIFEST)).unwrap();
    std::fs::write(dir.join(MANIFEST), &text[..text.len() / 2]).unwrap();
    session::write_manifest(&dir).unwrap();
    assert_same(&written(&dir), &whole);
    // Its entries out of order, one twice, one of a file gone: the folder's files, once each.
    let mut shuffled = whole.clone();
    shuffled.files.reverse();
    shuffled.files.push(whole.files[3].clone());
    let mut gone = whole.files[4].clone();
    gone.name = "rec-drive.77.mcap".into();
    shuffled.files.insert(5, gone);
    std::fs::write(dir.join(MANIFEST), serde_json::to_vec(&shuffled).unwrap()).unwrap();
    session::write_manifest(&dir).unwrap();
    assert_same(&written(&dir), &whole);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The manifest written in `dir`, read as any JSON reader reads it.
fn written(dir: &Path) -> Manifest {
    serde_json::from_slice(&std::fs::read(dir.join(MANIFEST)).unwrap()).unwrap()
}
