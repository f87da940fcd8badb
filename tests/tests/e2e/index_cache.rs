//! The persistent index cache: a drive opened from the cache is the drive a scan makes
//! (streams, stamps, transforms, skip and damage reports) and builds the same samples
//! bit for bit; a file rewritten in place is scanned again even at the same size and
//! modification time; damaged or foreign entries are ignored with a reason; two
//! processes filling one cache at once both succeed and leave whole entries.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use superflow_pipeline::drive::{Dataset, Drive, IngestConfig};
use superflow_pipeline::sample::{SampleBuilder, SampleConfig};
use superflow_recordings::Dialect;
use superflow_recordings::damaged::write_damaged;
use superflow_tests::{pipeline_binary, sample_drive, scratch};

fn config(cache: Option<&Path>) -> IngestConfig {
    IngestConfig {
        index_cache: Some(cache.map_or_else(|| PathBuf::from("off"), Path::to_path_buf)),
        ..IngestConfig::default()
    }
}

/// Every part of a drive that indexing determines.
fn assert_same_drive(a: &Drive, b: &Drive, what: &str) {
    assert_eq!(a.files.len(), b.files.len(), "{what}");
    for (fa, fb) in a.files.iter().zip(&b.files) {
        assert_eq!(fa.path(), fb.path(), "{what}");
        assert_eq!(
            fa.scanned(),
            fb.scanned(),
            "{what}: {}",
            fa.path().display()
        );
    }
    assert_eq!(a.channels, b.channels, "{what}: channels");
    assert_eq!(a.lidar, b.lidar, "{what}: lidar");
    assert_eq!(a.cameras, b.cameras, "{what}: cameras");
    assert_eq!(a.label_clouds, b.label_clouds, "{what}: label clouds");
    assert!(a.tf == b.tf, "{what}: transforms differ");
    assert_eq!(a.frozen_edges, b.frozen_edges, "{what}: frozen edges");
    assert_eq!(a.map_frame, b.map_frame, "{what}");
    assert_eq!(a.ego_frame, b.ego_frame, "{what}");
    assert_eq!(a.skipped, b.skipped, "{what}: skips");
}

/// The sample drives (the ROS 2 one with its labels sidecar) and every damaged
/// recording, in `dir`.
fn inputs(dir: &Path) -> Vec<PathBuf> {
    let drives = superflow_recordings::sample_drives_dir();
    for name in [
        "street_ros2.mcap",
        "street_ros2.labels.mcap",
        "street_foxglove.mcap",
    ] {
        std::fs::copy(drives.join(name), dir.join(name)).unwrap();
    }
    let damaged = dir.join("damaged");
    std::fs::create_dir_all(&damaged).unwrap();
    write_damaged(&damaged).unwrap();
    vec![
        dir.join("street_ros2.mcap"),
        dir.join("street_foxglove.mcap"),
        damaged,
    ]
}

#[test]
fn a_cache_hit_is_the_drive_a_scan_makes_and_builds_the_same_samples() {
    let dir = scratch::dir("index-cache", "same");
    let cache = dir.join("cache");
    let inputs = inputs(&dir);
    let scanned = Dataset::open(&inputs, &config(None)).unwrap();
    let filled = Dataset::open(&inputs, &config(Some(&cache))).unwrap();
    let hit = Dataset::open(&inputs, &config(Some(&cache))).unwrap();
    let files = scanned.indexed.files();
    assert_eq!(scanned.indexed.scanned, files);
    assert_eq!(filled.indexed.from_cache, 0);
    // Only the recordings without a usable summary (cut short) are scanned every time.
    let uncacheable = filled.indexed.uncacheable;
    assert!(
        (1..files / 2).contains(&uncacheable),
        "{:?}",
        filled.indexed
    );
    assert_eq!(
        hit.indexed.from_cache,
        files - uncacheable,
        "{:?}",
        hit.indexed
    );
    assert!(hit.indexed.bytes_scanned < filled.indexed.bytes_scanned);
    let entries = std::fs::read_dir(&cache).unwrap().count();
    assert_eq!(entries, files - uncacheable);
    for ((a, b), c) in scanned.drives.iter().zip(&filled.drives).zip(&hit.drives) {
        let name = a.file_list();
        assert_same_drive(a, b, &format!("{name}, scanned into the cache"));
        assert_same_drive(a, c, &format!("{name}, from the cache"));
    }
    // Damage is reported the same through the cache.
    let damaged = |d: &Dataset| {
        d.drives
            .iter()
            .flat_map(|d| &d.files)
            .filter(|f| !f.damage.is_empty())
            .count()
    };
    assert!(damaged(&hit) > 3);
    assert_eq!(damaged(&hit), damaged(&scanned));

    // The same samples, bit for bit, from the two sample drives.
    let two = &inputs[..2];
    let scanned = Dataset::open(two, &config(None)).unwrap();
    let hit = Dataset::open(two, &config(Some(&cache))).unwrap();
    assert_eq!(hit.indexed.from_cache, 3);
    let mut recipe = SampleConfig::default();
    recipe.augment.enabled = true;
    let a = SampleBuilder::new(&scanned, recipe.clone()).unwrap();
    let b = SampleBuilder::new(&hit, recipe).unwrap();
    assert_eq!(a.plan().keyframes.len(), b.plan().keyframes.len());
    assert!(a.plan().keyframes.len() >= 10);
    for k in 0..a.plan().keyframes.len() {
        let mut x = a.build(1, k as u64).unwrap();
        let mut y = b.build(1, k as u64).unwrap();
        x.times = Default::default();
        y.times = Default::default();
        assert!(x == y, "keyframe {k}: the samples differ");
    }
    std::fs::remove_dir_all(dir).unwrap();
}

/// `bytes` written again by mcap's writer, uncompressed, with every LiDAR sweep's stamp
/// moved by `shift_nanos` (the ROS 2 header's nanoseconds): the same records of the same
/// sizes, so the same file size and summary, and other content.
fn rewritten(bytes: &[u8], shift_nanos: u32) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    let mut writer = mcap::WriteOptions::new()
        .compression(None)
        .chunk_size(Some(256 * 1024))
        .create(&mut out)
        .unwrap();
    for message in mcap::MessageStream::new(bytes).unwrap() {
        let mut message = message.unwrap();
        let schema = message.channel.schema.as_ref().map(|s| s.name.as_str());
        if schema == Some("sensor_msgs/msg/PointCloud2") {
            // CDR: 4 bytes of encapsulation, then header.stamp.sec (4) and .nanosec (4).
            let mut data = message.data.into_owned();
            let nanos = u32::from_le_bytes(data[8..12].try_into().unwrap());
            assert!(
                nanos < 999_000_000,
                "a stamp this close to a second is not moved"
            );
            data[8..12].copy_from_slice(&(nanos + shift_nanos).to_le_bytes());
            message.data = data.into();
        }
        writer.write(&message).unwrap();
    }
    writer.finish().unwrap();
    drop(writer);
    out.into_inner()
}

#[test]
fn a_file_rewritten_in_place_with_its_size_and_time_is_indexed_again() {
    let dir = scratch::dir("index-cache", "rewrite");
    let cache = dir.join("cache");
    let original = sample_drive(Dialect::Ros2).unwrap().bytes;
    let before = rewritten(&original, 0);
    let after = rewritten(&original, 1_000);
    assert_eq!(before.len(), after.len());
    assert_ne!(before, after);
    let path = dir.join("drive.mcap");
    std::fs::write(&path, &before).unwrap();
    let mtime = std::fs::metadata(&path).unwrap().modified().unwrap();
    let first = Drive::open(std::slice::from_ref(&path), &config(Some(&cache))).unwrap();
    let stamps = |d: &Drive| {
        d.lidar
            .as_ref()
            .unwrap()
            .sweeps
            .iter()
            .map(|s| s.stamp.nanos())
            .collect::<Vec<_>>()
    };
    // Rewritten in place (same inode), then given back its size's twin and old time.
    std::fs::OpenOptions::new()
        .write(true)
        .open(&path)
        .and_then(|mut f| {
            use std::io::Write;
            f.write_all(&after)?;
            f.set_times(std::fs::FileTimes::new().set_modified(mtime))
        })
        .unwrap();
    assert_eq!(std::fs::metadata(&path).unwrap().modified().unwrap(), mtime);
    let again = Dataset::open(std::slice::from_ref(&path), &config(Some(&cache))).unwrap();
    assert_eq!(again.indexed.from_cache, 0, "{:?}", again.indexed);
    let moved: Vec<i64> = stamps(&first).iter().map(|s| s + 1_000).collect();
    assert_eq!(stamps(&again.drives[0]), moved);
    let scanned = Drive::open(std::slice::from_ref(&path), &config(None)).unwrap();
    assert_same_drive(&scanned, &again.drives[0], "the rewritten file");
    std::fs::remove_dir_all(dir).unwrap();
}

fn index(inputs: &[PathBuf], cache: &Path) -> Output {
    index_within(&[], inputs, cache, 600).expect("`index` ends")
}

/// The names in `cache`, asserting they are whole entries only: the files' and the
/// drives' camera scans (`index` plans), no temporary file.
fn whole_entries_only(cache: &Path) -> Vec<String> {
    let names: Vec<String> = std::fs::read_dir(cache)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(
        names
            .iter()
            .all(|n| n.ends_with(".sfidx") || n.ends_with(".sfscan")),
        "{names:?}"
    );
    names
}

fn text(output: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

#[test]
fn damaged_or_foreign_cache_entries_are_ignored_with_a_reason() {
    let dir = scratch::dir("index-cache", "entries");
    let cache = dir.join("cache");
    let inputs = inputs(&dir)[..2].to_vec();
    let filled = index(&inputs, &cache);
    let (out, err) = text(&filled);
    assert!(filled.status.success(), "{out}\n{err}");
    assert!(out.contains("cache hits      0 of 3"), "{out}");
    // The files' entries (`index` also stores each drive's camera scan, `.sfscan`).
    let entries = file_entries(&cache);
    assert_eq!(entries.len(), 3);
    let hit = index(&inputs, &cache);
    assert!(
        text(&hit).0.contains("cache hits      3 of 3"),
        "{:?}",
        text(&hit)
    );

    // One entry cut short, one with a flipped bit, one of another format version.
    let whole: Vec<Vec<u8>> = entries.iter().map(|e| std::fs::read(e).unwrap()).collect();
    std::fs::write(&entries[0], &whole[0][..whole[0].len() / 2]).unwrap();
    let mut flipped = whole[1].clone();
    let at = flipped.len() - 100;
    flipped[at] ^= 0x10;
    std::fs::write(&entries[1], &flipped).unwrap();
    let mut other = whole[2].clone();
    other[8..12].copy_from_slice(&999u32.to_le_bytes());
    std::fs::write(&entries[2], &other).unwrap();
    let again = index(&inputs, &cache);
    let (out, err) = text(&again);
    assert!(again.status.success(), "{out}\n{err}");
    assert!(out.contains("cache hits      0 of 3"), "{out}");
    assert!(!err.contains("panicked"), "{err}");
    for reason in [
        "truncated: payload",
        "its checksum does not match its content",
        "written in index format 999",
    ] {
        let line = err
            .lines()
            .find(|l| l.contains(reason))
            .unwrap_or_else(|| panic!("no INFO line with `{reason}`:\n{err}"));
        assert!(
            line.contains("INFO") && line.contains("indexing the file again"),
            "{line}"
        );
    }
    // Scanned again, the entries are whole again.
    let healed = index(&inputs, &cache);
    assert!(
        text(&healed).0.contains("cache hits      3 of 3"),
        "{:?}",
        text(&healed)
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn two_processes_filling_one_cache_at_once_both_succeed() {
    let dir = scratch::dir("index-cache", "concurrent");
    let cache = dir.join("cache");
    let inputs = inputs(&dir);
    let (a, b) = std::thread::scope(|s| {
        let a = s.spawn(|| index(&inputs, &cache));
        let b = s.spawn(|| index(&inputs, &cache));
        (a.join().unwrap(), b.join().unwrap())
    });
    for output in [&a, &b] {
        let (out, err) = text(output);
        assert!(output.status.success(), "{out}\n{err}");
    }
    let alone = Dataset::open(&inputs, &config(None)).unwrap();
    let files = alone.indexed.files();
    let hit = Dataset::open(&inputs, &config(Some(&cache))).unwrap();
    assert_eq!(
        hit.indexed.from_cache + hit.indexed.uncacheable,
        files,
        "{:?}",
        hit.indexed
    );
    for (x, y) in alone.drives.iter().zip(&hit.drives) {
        assert_same_drive(x, y, &x.file_list());
    }
    let names = whole_entries_only(&cache);
    let indexes = names.iter().filter(|n| n.ends_with(".sfidx")).count();
    assert_eq!(indexes, files - hit.indexed.uncacheable);
    std::fs::remove_dir_all(dir).unwrap();
}

/// `index` of `inputs` into `cache`, through `wrap` (e.g. `unshare …`) when given, killed
/// after `secs`: `None` then.
fn index_within(wrap: &[&str], inputs: &[PathBuf], cache: &Path, secs: u64) -> Option<Output> {
    let binary = pipeline_binary(env!("CARGO_BIN_EXE_superflow-subscriber"));
    let mut command = match wrap.split_first() {
        Some((program, args)) => {
            let mut c = Command::new(program);
            c.args(args).arg(binary);
            c
        }
        None => Command::new(binary),
    };
    let child = command
        .arg("index")
        .arg("--mcap")
        .args(inputs)
        .arg("--index-cache")
        .arg(cache)
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let id = child.id();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(child.wait_with_output());
    });
    match rx.recv_timeout(std::time::Duration::from_secs(secs)) {
        Ok(output) => Some(output.unwrap()),
        Err(_) => {
            let _ = Command::new("kill").arg("-9").arg(id.to_string()).status();
            None
        }
    }
}

/// The `.sfidx` entries of `cache`, sorted.
fn file_entries(cache: &Path) -> Vec<PathBuf> {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(cache)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "sfidx"))
        .collect();
    entries.sort();
    entries
}

/// Whether `unshare` with these flags works here (user namespaces may be off): a test
/// that needs it says so and passes without it.
fn unshare_works(flags: &str) -> bool {
    let works = Command::new("unshare")
        .args([flags, "true"])
        .status()
        .is_ok_and(|s| s.success());
    if !works {
        eprintln!("SKIPPED: `unshare {flags}` is not permitted on this machine");
    }
    works
}

/// What stands at an entry's name may be anything a writer of the directory put there:
/// a FIFO (a plain open blocks forever), a symbolic link to `/dev/zero` (a plain read
/// never ends), an entry renamed under another file's name, or an entry whose chunk
/// record is shorter than a record head. Each is skipped with a WARN line saying what it
/// is, the files are scanned again, and their entries are then whole again.
#[test]
fn fifos_links_and_forged_entries_are_skipped_without_hanging() {
    let dir = scratch::dir("index-cache", "hostile");
    let cache = dir.join("cache");
    let inputs = inputs(&dir)[..2].to_vec();
    let filled = index(&inputs, &cache);
    assert!(filled.status.success(), "{:?}", text(&filled));
    let entries = file_entries(&cache);
    assert_eq!(entries.len(), 3);
    std::fs::remove_file(&entries[0]).unwrap();
    let made = Command::new("mkfifo").arg(&entries[0]).status().unwrap();
    assert!(made.success());
    std::fs::remove_file(&entries[1]).unwrap();
    std::os::unix::fs::symlink("/dev/zero", &entries[1]).unwrap();
    // The third file's entry under the second's name, as a rename would leave it.
    let third = std::fs::read(&entries[2]).unwrap();
    let moved = dir.join("moved");
    std::fs::write(&moved, &third).unwrap();
    let started = std::time::Instant::now();
    let again = index_within(&[], &inputs, &cache, 60)
        .expect("`index` hung on a FIFO or a link to /dev/zero in the cache");
    let (out, err) = text(&again);
    assert!(again.status.success(), "{out}\n{err}");
    assert!(out.contains("cache hits      1 of 3"), "{out}");
    assert!(started.elapsed().as_secs() < 60);
    for reason in [
        "not a regular file but a FIFO",
        "a symbolic link (not followed)",
    ] {
        let line = err
            .lines()
            .find(|l| l.contains(reason))
            .unwrap_or_else(|| panic!("no line with `{reason}`:\n{err}"));
        assert!(
            line.contains("WARN") && line.contains("indexing the file again"),
            "{line}"
        );
    }
    // Renamed entries and a forged chunk length.
    let entries = file_entries(&cache);
    assert!(entries.iter().all(|e| e.is_file() && !e.is_symlink()));
    std::fs::copy(&moved, &entries[0]).unwrap();
    let forged = index(&inputs, &cache);
    let (out, err) = text(&forged);
    assert!(forged.status.success(), "{out}\n{err}");
    assert!(err.contains("it is the entry of another key"), "{err}");
    assert!(out.contains("cache hits      2 of 3"), "{out}");
    std::fs::remove_dir_all(dir).unwrap();
}

/// Two Kubernetes pods on one cache: each pipeline is PID 1 of its own PID namespace,
/// with the same thread ids. Both index the same files into one cache at once: both
/// succeed without a warning, the entries are whole, and no temporary file is left.
#[test]
fn two_pods_with_pid_1_index_into_one_cache_at_once() {
    if !unshare_works("-Urpf") {
        return;
    }
    let dir = scratch::dir("index-cache", "pods");
    let cache = dir.join("cache");
    let inputs = inputs(&dir);
    // Several copies, so that the pods write many entries at the same moments.
    let more = dir.join("more");
    std::fs::create_dir_all(&more).unwrap();
    let drives = superflow_recordings::sample_drives_dir();
    for i in 0..6 {
        std::fs::copy(
            drives.join("street_foxglove.mcap"),
            more.join(format!("copy{i}.mcap")),
        )
        .unwrap();
    }
    let mut all = inputs.clone();
    all.push(more);
    let wrap = ["unshare", "-Urpf", "--mount-proc"];
    let (a, b) = std::thread::scope(|s| {
        let a = s.spawn(|| index_within(&wrap, &all, &cache, 300));
        let b = s.spawn(|| index_within(&wrap, &all, &cache, 300));
        (a.join().unwrap().unwrap(), b.join().unwrap().unwrap())
    });
    for output in [&a, &b] {
        let (out, err) = text(output);
        assert!(output.status.success(), "{out}\n{err}");
        for trouble in ["cannot be written", "index cache entry ignored"] {
            assert!(!err.contains(trouble), "{err}");
        }
    }
    whole_entries_only(&cache);
    let hit = Dataset::open(&all, &config(Some(&cache))).unwrap().indexed;
    assert_eq!(hit.scanned, 0, "{hit:?}");
    assert_eq!(hit.from_cache + hit.uncacheable, hit.files(), "{hit:?}");
    std::fs::remove_dir_all(dir).unwrap();
}

/// A cache that cannot be written (a read-only bind mount; root ignores permissions, a
/// mount does not): `index` says how many entries it could not store and fails, so that
/// an index step does not pass while every node then scans everything again.
#[test]
fn index_fails_when_it_cannot_store_what_it_indexed() {
    if !unshare_works("-Urm") {
        return;
    }
    let dir = scratch::dir("index-cache", "readonly");
    let cache = dir.join("cache");
    std::fs::create_dir_all(&cache).unwrap();
    let inputs = inputs(&dir)[..2].to_vec();
    let binary = pipeline_binary(env!("CARGO_BIN_EXE_superflow-subscriber"));
    let script = format!(
        "mount --bind '{c}' '{c}' && mount -o remount,bind,ro '{c}' && exec '{b}' index --mcap '{i0}' '{i1}' --index-cache '{c}'",
        c = cache.display(),
        b = binary.display(),
        i0 = inputs[0].display(),
        i1 = inputs[1].display(),
    );
    let output = Command::new("unshare")
        .args(["-Urm", "sh", "-c", &script])
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    let (out, err) = text(&output);
    assert_eq!(output.status.code(), Some(1), "{out}\n{err}");
    assert!(out.contains("cache hits      0 of 3"), "{out}");
    assert!(
        err.contains("index cache entries could not be stored"),
        "{err}"
    );
    assert!(err.contains("Read-only file system"), "{err}");
    // Writable again, the same command succeeds.
    let ok = index(&inputs, &cache);
    assert!(ok.status.success(), "{:?}", text(&ok));
    std::fs::remove_dir_all(dir).unwrap();
}

/// A cache directory its group or every user may write is refused at start with what to
/// do; entries of another build are indexed again; `index --prune` removes what this
/// build cannot use and temporary files of writers that died.
#[test]
fn a_cache_others_may_write_is_refused_and_prune_tidies_it() {
    use std::os::unix::fs::PermissionsExt;
    let dir = scratch::dir("index-cache", "tidy");
    let cache = dir.join("cache");
    let inputs = inputs(&dir)[..2].to_vec();
    let filled = index(&inputs, &cache);
    assert!(filled.status.success(), "{:?}", text(&filled));
    let mode = std::fs::metadata(&cache).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o700, "made private whatever the umask");
    for (mode, who) in [(0o770, "its group"), (0o777, "every user")] {
        std::fs::set_permissions(&cache, std::fs::Permissions::from_mode(mode)).unwrap();
        let refused = index(&inputs, &cache);
        let (out, err) = text(&refused);
        assert_eq!(refused.status.code(), Some(1), "{out}\n{err}");
        assert!(err.contains(&format!("writable by {who}")), "{err}");
        assert!(err.contains(&cache.display().to_string()), "{err}");
    }
    std::fs::set_permissions(&cache, std::fs::Permissions::from_mode(0o700)).unwrap();
    // An entry of another build: same format, another writer identity.
    let entries = file_entries(&cache);
    let bytes = std::fs::read(&entries[0]).unwrap();
    let writer_len = usize::from(u16::from_le_bytes([bytes[12], bytes[13]]));
    let mut other = bytes[..12].to_vec();
    other.extend_from_slice(&(5u16).to_le_bytes());
    other.extend_from_slice(b"0.0.1");
    other.extend_from_slice(&bytes[14 + writer_len..]);
    std::fs::write(&entries[0], &other).unwrap();
    let again = index(&inputs, &cache);
    let (out, err) = text(&again);
    assert!(out.contains("cache hits      2 of 3"), "{out}");
    assert!(
        err.contains("written by superflow-pipeline 0.0.1, this is"),
        "{err}"
    );
    // Prune: an entry of another build, a damaged one, a dead writer's temporary file.
    std::fs::write(&entries[0], &other).unwrap();
    std::fs::write(&entries[1], b"SFINDEX\0 damaged").unwrap();
    let stale = cache.join(format!(".{:032x}.sfidx.0123456789abcdef.tmp", 7));
    std::fs::write(&stale, b"half an entry").unwrap();
    let day_ago = std::time::SystemTime::now() - std::time::Duration::from_secs(86_400);
    std::fs::File::options()
        .write(true)
        .open(&stale)
        .unwrap()
        .set_modified(day_ago)
        .unwrap();
    let pruned = Command::new(pipeline_binary(env!("CARGO_BIN_EXE_superflow-subscriber")))
        .args(["index", "--prune", "--index-cache"])
        .arg(&cache)
        .output()
        .unwrap();
    let (out, err) = text(&pruned);
    assert!(pruned.status.success(), "{out}\n{err}");
    assert!(
        out.contains("pruned          2 unusable entries, 0 evicted"),
        "{out}"
    );
    assert!(out.contains("1 stale temporary files"), "{out}");
    assert!(!stale.exists() && !entries[0].exists() && !entries[1].exists());
    assert!(entries[2].exists());
    std::fs::remove_dir_all(dir).unwrap();
}
