//! Issue 13, faults: `mortar build --resume` after SIGKILL at 20 moments gives the store an
//! uninterrupted build gives (same hierarchy, same payloads); after each kill the store opens at
//! its last commit and renders. A build that runs out of file size (`ulimit -f`) ends with a
//! clear error and its last commit readable, and resumes. Readers that open the store in a loop
//! while a build appends never see a torn commit.

mod common;

use common::*;
use mortar_io::dataset::RecordSource;
use mortar_io::store::Store;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn input(dir: &Path, points: u64) -> PathBuf {
    let p = dir.join("in.las");
    run_ok(gen().args(["--points", &points.to_string(), "--seed", "7", "-o"]).arg(&p));
    p
}

/// `mortar build --resume INPUT -o OUT`.
fn resume(input: &Path, out: &Path) -> Command {
    let mut c = mortar();
    c.arg("build").arg("--resume").arg(input).arg("-o").arg(out);
    c
}

/// The hierarchy (header and entries), the live payloads and the arrival ranks (where the
/// engine keeps them) of a store.
fn snapshot(dir: &Path) -> (Vec<u8>, Vec<u8>, Vec<u8>) {
    let mut h = std::fs::read(dir.join("hierarchy.bin")).unwrap();
    // The commit number counts commits, and a partitioned build's provisional commits come
    // every --commit-every seconds: not part of what the store holds.
    h[16..24].fill(0);
    let s = Store::open(dir).unwrap();
    let nodes = std::fs::read(dir.join("nodes.bin")).unwrap();
    let arrival = std::fs::read(dir.join("arrival.bin")).unwrap_or_default();
    (h, nodes[..s.header.nodes_len as usize].to_vec(), arrival)
}

/// A store that was stopped: empty, or it opens at its last commit and draws.
fn check_stopped(dir: &Path, render: bool) {
    if !dir.join("hierarchy.bin").exists() {
        return;
    }
    let s =
        Store::open(dir).unwrap_or_else(|e| panic!("the store must open at its last commit: {e}"));
    let pts = s.header.points;
    let read: u64 = s
        .pieces()
        .iter()
        .map(|p| s.read_piece(p).unwrap().len() as u64 / s.layout.record_len as u64)
        .sum();
    assert_eq!(read, pts);
    let lod = mortar_io::store::StoreLod::new(s).expect("the last commit is a drawable tree");
    assert!(lod.index().point_count() > 0 || pts == 0);
    if render {
        let png = dir.with_extension("png");
        run_ok(
            mortar()
                .arg("render")
                .arg(dir)
                .arg("-o")
                .arg(&png)
                .args(["--width", "160", "--height", "120"]),
        );
        assert!(std::fs::metadata(&png).unwrap().len() > 0);
    }
}

#[test]
fn resume_after_sigkill_at_20_moments_gives_the_uninterrupted_store() {
    let dir = tempdir("resume-kill");
    let inp = input(&dir, 3_000_000);
    let reference = dir.join("ref");
    let t = Instant::now();
    run_ok(mortar().arg("build").arg(&inp).arg("-o").arg(&reference));
    let full = t.elapsed();
    let want = snapshot(&reference);
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    let mut stopped_with_commits = 0;
    for k in 0..20 {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        // Moments spread over the whole build and a little past it.
        let at = full.mul_f64((seed % 1000) as f64 / 1000.0 * 1.1);
        let out = dir.join(format!("s{k}"));
        let mut child = mortar()
            .arg("build")
            .arg(&inp)
            .arg("-o")
            .arg(&out)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(at);
        let _ = child.kill(); // SIGKILL
        let _ = child.wait();
        if out.join("hierarchy.bin").exists() {
            stopped_with_commits += 1;
        }
        check_stopped(&out, k % 5 == 0);
        let o = run_ok(resume(&inp, &out).arg("--json"));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(j["points"], 3_000_000, "kill {k} at {at:?}: {j}");
        assert!(
            snapshot(&out) == want,
            "kill {k} at {at:?}: the resumed store differs from the uninterrupted one ({j})"
        );
        let _ = std::fs::remove_dir_all(&out);
    }
    assert!(
        stopped_with_commits >= 5,
        "only {stopped_with_commits} kills left a commit (build {full:?})"
    );
    // Resuming a complete store leaves it as it is; other inputs are refused before anything is written.
    let o = run_ok(&mut resume(&inp, &reference));
    assert!(String::from_utf8_lossy(&o.stderr).contains("complete"));
    assert!(snapshot(&reference) == want);
    let other = dir.join("other.las");
    run_ok(gen().args(["--points", "1000", "--seed", "8", "-o"]).arg(&other));
    let o = resume(&other, &reference).output().unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("was built from"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(snapshot(&reference) == want);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_build_out_of_file_size_keeps_its_last_commit_and_resumes() {
    let dir = tempdir("resume-full");
    let inp = input(&dir, 1_500_000);
    let reference = dir.join("ref");
    run_ok(mortar().arg("build").arg(&inp).arg("-o").arg(&reference));
    let want = snapshot(&reference);
    let total = want.1.len() as u64;
    let out = dir.join("s");
    // Files may grow to a little over half the store's payloads (bash counts 1024-byte blocks).
    let limit = total / 2 / 1024;
    let o = Command::new("bash")
        .arg("-c")
        .arg(format!("ulimit -f {limit}; exec \"$0\" build \"$1\" -o \"$2\"",))
        .arg(env!("CARGO_BIN_EXE_mortar"))
        .arg(&inp)
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("nodes.bin")
            && err.contains("keeps its last commit")
            && err.contains("--resume"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
    check_stopped(&out, true);
    run_ok(&mut resume(&inp, &out));
    assert!(snapshot(&out) == want);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn readers_never_see_a_torn_commit() {
    let dir = tempdir("resume-readers");
    let inp = input(&dir, 3_000_000);
    for engine in ["sorted", "incremental"] {
        let out = dir.join(engine);
        let mut child = mortar()
            .arg("build")
            .arg(&inp)
            .arg("-o")
            .arg(&out)
            .args([
                "--engine",
                engine,
                "--commit-every",
                "0",
                "--batch-points",
                "200000",
                "--leaf-capacity",
                "20000",
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let mut opened = 0;
        let mut commits = std::collections::BTreeSet::new();
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            let done = child.try_wait().unwrap().is_some();
            if out.join("hierarchy.bin").exists() {
                let s = Store::open(&out)
                    .unwrap_or_else(|e| panic!("{engine}: a reader saw a torn commit: {e}"));
                commits.insert(s.header.commit);
                let pts = s.header.points;
                let read: u64 = s
                    .pieces()
                    .iter()
                    .map(|p| s.read_piece(p).unwrap().len() as u64 / s.layout.record_len as u64)
                    .sum();
                assert_eq!(read, pts, "{engine}");
                mortar_io::store::StoreLod::new(s)
                    .unwrap_or_else(|e| panic!("{engine}: a commit that does not draw: {e}"));
                opened += 1;
            }
            if done {
                break;
            }
            assert!(Instant::now() < deadline, "{engine}: the build did not end");
        }
        assert!(child.wait().unwrap().success());
        assert!(opened >= 2 && commits.len() >= 2, "{engine}: {opened} opens, commits {commits:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn compact_keeps_the_store_and_drops_superseded_payloads() {
    let dir = tempdir("compact");
    let inp = input(&dir, 400_000);
    let store = dir.join("s");
    // Small batches with a commit after each: leaves are rewritten many times.
    run_ok(mortar().arg("build").arg(&inp).arg("-o").arg(&store).args([
        "--engine",
        "incremental",
        "--batch-points",
        "20000",
        "--commit-every",
        "0",
    ]));
    let before = Store::open(&store).unwrap();
    let live: u64 = before.entries.iter().map(|e| e.length).sum();
    assert!(
        before.header.nodes_len as f64 > 1.5 * live as f64,
        "{} of {live}",
        before.header.nodes_len
    );
    let sorted_before = dir.join("a.las");
    run_ok(mortar().arg("sort").arg(&store).arg("-o").arg(&sorted_before));
    drop(before);
    let o = run_ok(mortar().arg("build").arg("--compact").arg(&store).arg("--json"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["bytes_after"].as_u64(), Some(live));
    assert_eq!(j["segments_rewritten"].as_u64(), Some(1));
    let after = Store::open(&store).unwrap();
    // Segment 0 (nodes.bin) was rewritten into segment 1, committed, then emptied.
    assert_eq!(after.covered, vec![0, live], "the segments hold exactly the live payloads");
    assert_eq!(std::fs::metadata(store.join("nodes.bin")).unwrap().len(), 0);
    assert_eq!(std::fs::metadata(store.join("nodes-1.bin")).unwrap().len(), live);
    assert!(after.entries.iter().all(|e| e.segment == 1));
    // A second compaction has nothing to do.
    let o = run_ok(mortar().arg("build").arg("--compact").arg(&store).arg("--json"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["segments_rewritten"].as_u64(), Some(0));
    assert_eq!(j["bytes_after"].as_u64(), Some(live));
    let sorted_after = dir.join("b.las");
    run_ok(mortar().arg("sort").arg(&store).arg("-o").arg(&sorted_after));
    assert!(std::fs::read(&sorted_before).unwrap() == std::fs::read(&sorted_after).unwrap());
    check_stopped(&store, true);
    assert!(
        entries(&dir).iter().all(|e| !e.contains("compacting") && !e.ends_with(".old")),
        "{:?}",
        entries(&dir)
    );
    // Not a store: a clear error.
    let o = mortar().arg("build").arg("--compact").arg(&inp).output().unwrap();
    assert_eq!(o.status.code(), Some(1));
    let _ = std::fs::remove_dir_all(&dir);
}

/// The partitioned engine (inputs larger than `--memory`) makes its final commit at the end (and
/// provisional ones before, `tests/store_live.rs`); what a killed build keeps is its partition
/// and the log of finished units in `.partition/`, and
/// `--resume` continues from them to the uninterrupted store, byte for byte (18 SIGKILLs), also
/// when a run file or `nodes.bin` lost bytes (as after a power loss: checked by checksums, and
/// redone) and when the state files are not what mortar wrote.
#[test]
fn a_partitioned_build_resumes_after_sigkill_to_the_uninterrupted_store() {
    let dir = tempdir("resume-partitioned");
    let inp = input(&dir, 2_000_000);
    let args = ["--memory", "16M", "--engine", "partitioned"];
    let reference = dir.join("ref");
    let t = Instant::now();
    let o =
        run_ok(mortar().arg("build").arg(&inp).arg("-o").arg(&reference).args(args).arg("--json"));
    let full = t.elapsed();
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["engine"], "partitioned", "{j}");
    assert!(!reference.join(".partition").exists(), "the partition is removed at the end");
    let want = snapshot(&reference);
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    let (mut kept_partition, mut kept_units) = (0, 0);
    for k in 0..18 {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        let at = full.mul_f64((seed % 1000) as f64 / 1000.0);
        let out = dir.join(format!("p{k}"));
        let mut child = mortar()
            .arg("build")
            .arg(&inp)
            .arg("-o")
            .arg(&out)
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(at);
        let _ = child.kill(); // SIGKILL
        let _ = child.wait();
        if out.join(".partition/manifest.json").exists() {
            kept_partition += 1;
        }
        // What a power loss may leave: bytes that never reached the disk. Each is found by its
        // checksum and redone.
        let flip = |p: &Path| {
            if let Ok(mut b) = std::fs::read(p) {
                if !b.is_empty() {
                    let i = b.len() / 2;
                    b[i] ^= 0x5a;
                    std::fs::write(p, b).unwrap();
                }
            }
        };
        // And state files that are not what mortar wrote: never trusted, never a panic.
        let state = out.join(".partition");
        match k % 6 {
            _ if out.join("hierarchy.bin").exists() || !state.exists() => {} // finished, or nothing kept
            1 => flip(&state.join("run-0.bin")),
            2 => flip(&out.join("nodes.bin")),
            3 => std::fs::write(
                state.join("manifest.json"),
                b"{\"cells\": 18446744073709551615, \"runs\": [\"../../x\"]}",
            )
            .unwrap(),
            4 => std::fs::write(state.join("tables.bin"), [1u8; 24]).unwrap(),
            5 => {
                // A record header claiming 2^32 - 1 entries, then the end of the file.
                let mut b = std::fs::read(state.join("done.bin")).unwrap_or_default();
                b.extend_from_slice(&0x4d50_4c47u32.to_le_bytes());
                b.extend_from_slice(&[0xff; 60]);
                std::fs::write(state.join("done.bin"), b).unwrap();
            }
            _ => {}
        }
        let o = run_ok(resume(&inp, &out).args(args).arg("--json"));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(j["points"], 2_000_000, "kill {k} at {at:?}: {j}");
        if j["kept_nodes"].as_u64().unwrap_or(0) > 0 {
            kept_units += 1;
        }
        assert!(
            snapshot(&out) == want,
            "kill {k} at {at:?}: the resumed store differs from the uninterrupted one ({j})"
        );
        assert!(!out.join(".partition").exists());
        let _ = std::fs::remove_dir_all(&out);
    }
    assert!(kept_partition >= 3 && kept_units >= 2, "kills kept the partition {kept_partition} times and units {kept_units} times (build {full:?})");
    let _ = std::fs::remove_dir_all(&dir);
}
