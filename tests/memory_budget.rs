//! `--memory` on hostile density (issue 26, item 2), with the peak RSS the OS reports for the
//! process (`wait4`'s `ru_maxrss`: anonymous and file-backed pages, the input's mapped pages
//! included): points in a uniform cube, every record eight times, 192 extra bytes per point,
//! one LAZ chunk for the whole file, every point at one position; `build` and the COPC export,
//! through run files (a budget below the input) and in memory (a budget above it). Each run
//! stays within the budget plus [`SLACK`] and gives every point back. Points at one position
//! under a budget below the input make a partition cell denser than a unit: a leaf read and
//! written in slices (`store/dense.rs`).

mod common;
use common::*;
use std::path::{Path, PathBuf};
use std::process::Command;

/// What a run may hold beyond `--memory`: the binary's own pages (about 45 MiB of text and
/// data mapped), thread stacks and allocator slack.
const SLACK: u64 = 64 << 20;

/// Points per generated input (600 k for the wide records).
const POINTS: u64 = 1_200_000;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs `c` to its end; its exit status and peak RSS in bytes, as the kernel counted it.
// The child is reaped by `wait4`, which clippy does not see.
#[allow(clippy::zombie_processes)]
fn peak_rss(mut c: Command) -> (i32, u64, String) {
    c.stdout(std::process::Stdio::null()).stderr(std::process::Stdio::piped());
    let child = c.spawn().expect("spawn");
    let pid = child.id() as libc::pid_t;
    let mut stderr = child.stderr.expect("stderr");
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        std::io::Read::read_to_string(&mut stderr, &mut s).ok();
        s
    });
    let mut status = 0;
    // SAFETY: a zeroed rusage is a valid value; wait4 fills it for the child we spawned.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: waits for our own child, writing into the two locals.
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut ru) };
    assert_eq!(r, pid, "wait4");
    let code = if libc::WIFEXITED(status) { libc::WEXITSTATUS(status) } else { -1 };
    (code, ru.ru_maxrss as u64 * 1024, reader.join().unwrap())
}

fn generate(dir: &Path, name: &str, args: &[&str]) -> PathBuf {
    let p = dir.join(name);
    run_ok(gen().args(args).args(["-o", s(&p)]));
    p
}

/// A hash of the input's records in canonical (sorted) order: `mortar sort`'s output, read in
/// small blocks. The test process holds no large buffer: a child forked while it did would
/// count those pages in its own peak RSS.
fn canonical(input: &Path, out: &Path) -> u64 {
    run_ok(mortar().args(["sort", s(input), "-o", s(out)]));
    let mut f = std::io::BufReader::new(std::fs::File::open(out).unwrap());
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = std::io::Read::read(&mut f, &mut buf).unwrap();
        if n == 0 {
            break;
        }
        for &b in &buf[..n] {
            h = (h ^ b as u64).wrapping_mul(0x100_0000_01b3);
        }
    }
    std::fs::remove_file(out).unwrap();
    h
}

fn copc_points(p: &Path) -> u64 {
    if let Some(py) = laspy_python() {
        let o = run_ok(Command::new(py).args([
            "-c",
            "import laspy,sys; f=laspy.read(sys.argv[1]); print(len(f.points))",
            s(p),
        ]));
        return String::from_utf8_lossy(&o.stdout).trim().parse().unwrap();
    }
    let j: serde_json::Value =
        serde_json::from_slice(&run_ok(mortar().args(["info", "--json", s(p)])).stdout).unwrap();
    j[0]["point_count"].as_u64().unwrap()
}

/// `build` and `export` of `input` under `memory`, within the budget, every point back.
fn check(dir: &Path, input: &Path, memory: &str, bytes: u64, points: u64, want: u64) {
    let store = dir.join("store");
    let mut c = mortar();
    c.args(["build", s(input), "-o", s(&store), "--memory", memory, "--json"]);
    let (code, peak, err) = peak_rss(c);
    let name = input.file_name().unwrap().to_string_lossy().to_string();
    assert_eq!(code, 0, "build {name} --memory {memory}: {err}");
    eprintln!("build  {name} --memory {memory}: peak RSS {} MiB", peak >> 20);
    assert!(
        peak <= bytes + SLACK,
        "build {name} --memory {memory}: peak RSS {} MiB over the budget ({} MiB + {} MiB)",
        peak >> 20,
        bytes >> 20,
        SLACK >> 20
    );
    assert!(
        canonical(&store, &dir.join("back.las")) == want,
        "build {name} --memory {memory}: the store does not give every record back"
    );
    std::fs::remove_dir_all(&store).unwrap();
    let copc = dir.join("out.copc.laz");
    let mut c = mortar();
    c.args(["export", s(input), "-o", s(&copc), "--memory", memory]);
    let (code, peak, err) = peak_rss(c);
    assert_eq!(code, 0, "export {name} --memory {memory}: {err}");
    eprintln!("export {name} --memory {memory}: peak RSS {} MiB", peak >> 20);
    assert!(
        peak <= bytes + SLACK,
        "export {name} --memory {memory}: peak RSS {} MiB over the budget ({} MiB + {} MiB)",
        peak >> 20,
        bytes >> 20,
        SLACK >> 20
    );
    assert_eq!(copc_points(&copc), points, "export {name} --memory {memory}");
    std::fs::remove_file(&copc).unwrap();
}

#[test]
fn hostile_density_stays_within_the_budget() {
    let dir = tempdir("memory-budget");
    let n = POINTS.to_string();
    let half = (POINTS / 2).to_string();
    let inputs = [
        (generate(&dir, "cube.las", &["--points", &n, "--shape", "cube"]), POINTS),
        (generate(&dir, "duplicates.las", &["--points", &n, "--shape", "duplicates"]), POINTS),
        (generate(&dir, "extra192.las", &["--points", &half, "--extra-bytes", "192"]), POINTS / 2),
        (generate(&dir, "one-chunk.laz", &["--points", &n, "--laz-chunk", &n]), POINTS),
        (generate(&dir, "coincident.las", &["--points", &n, "--shape", "coincident"]), POINTS),
    ];
    for (input, points) in &inputs {
        let want = canonical(input, &dir.join("want.las"));
        // through run files (the input's records alone are over the budget), then in memory
        for (memory, bytes) in [("96M", 96u64 << 20), ("256M", 256 << 20)] {
            check(&dir, input, memory, bytes, *points, want);
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
