//! Issue 15: a build split by `mortar plan` into jobs (`mortar build --plan --job`) and joined
//! by `mortar merge` is the store one machine builds: the same entries in the same order and
//! the same payload bytes, node for node, for N = 1, 2, 7 and 16 jobs, on the samples, on real
//! files alone and merged, and on a synthetic scan; headers that lie are refused by the jobs
//! (and planned with --scan); missing, repeated and foreign parts are refused; a job killed
//! half-way and run again gives the same part. With `MORTAR_SLURM=1` (`.ci/run` starts a
//! one-node cluster) `deploy/slurm/submit.sh` runs the plan, the job array and the merge on
//! Slurm, and the store is compared with the one-machine store.

mod common;

use common::*;
use mortar_io::store::Store;
use std::path::{Path, PathBuf};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

const LEAF: &str = "3000";

/// The one-machine store of `inputs`.
fn one_machine(inputs: &[PathBuf], out: &Path) {
    run_ok(mortar().arg("build").args(inputs).args([
        "-o",
        s(out),
        "--quiet",
        "--leaf-capacity",
        LEAF,
    ]));
}

/// Plans `inputs` in `n` jobs, runs every job (with a memory budget that splits them into
/// units) and merges the parts; the store's path, or the first error.
fn distributed(inputs: &[PathBuf], n: usize, dir: &Path, scan: bool) -> Result<PathBuf, String> {
    let plan = dir.join(format!("plan{n}.json"));
    let mut c = mortar();
    c.arg("plan").args(inputs).args([
        "--jobs",
        &n.to_string(),
        "-o",
        s(&plan),
        "--quiet",
        "--leaf-capacity",
        LEAF,
    ]);
    if scan {
        c.arg("--scan");
    }
    let o = c.output().unwrap();
    if !o.status.success() {
        return Err(String::from_utf8_lossy(&o.stderr).into());
    }
    let mut parts = Vec::new();
    for i in 0..n {
        let part = dir.join(format!("n{n}-part{i:02}"));
        let o = mortar()
            .args([
                "build",
                "--plan",
                s(&plan),
                "--job",
                &i.to_string(),
                "-o",
                s(&part),
                "--quiet",
                "--memory",
                "32M",
            ])
            .output()
            .unwrap();
        if !o.status.success() {
            assert_eq!(o.status.code(), Some(1));
            return Err(String::from_utf8_lossy(&o.stderr).into());
        }
        parts.push(part);
    }
    let store = dir.join(format!("merged{n}"));
    let o = mortar()
        .arg("merge")
        .args(&parts)
        .args(["-o", s(&store), "--quiet", "--json"])
        .output()
        .unwrap();
    if !o.status.success() {
        return Err(String::from_utf8_lossy(&o.stderr).into());
    }
    std::fs::write(dir.join(format!("merge{n}.json")), &o.stdout).unwrap();
    for p in parts {
        std::fs::remove_dir_all(p).unwrap();
    }
    Ok(store)
}

/// The stores hold the same entries in the same order with the same payloads, and the same
/// arrival ranks (`arrival.bin`, byte for byte) where the first has them.
fn assert_same_store(a: &Path, b: &Path, name: &str) {
    same_ranks(a, b, name);
    let (sa, sb) = (Store::open(a).unwrap(), Store::open(b).unwrap());
    assert_eq!(sa.header.points, sb.header.points, "{name}: points");
    assert_eq!(sa.root_cube(), sb.root_cube(), "{name}: root");
    assert_eq!((sa.header.min, sa.header.max), (sb.header.min, sb.header.max), "{name}: bounds");
    assert_eq!(sa.entries.len(), sb.entries.len(), "{name}: node count");
    for (i, (x, y)) in sa.entries.iter().zip(&sb.entries).enumerate() {
        assert_eq!(
            (x.level, x.kind, x.index, x.count, x.length),
            (y.level, y.kind, y.index, y.count, y.length),
            "{name}: entry {i}"
        );
        assert!(
            sa.node_bytes(i) == sb.node_bytes(i),
            "{name}: payload of node {i} ({:?})",
            (x.level, x.index)
        );
    }
    let live: u64 = sb.entries.iter().map(|e| e.length).sum();
    assert_eq!(
        live,
        sb.covered.iter().sum::<u64>(),
        "{name}: the payload segments hold only live payloads"
    );
}

/// The stores' `arrival.bin` are the same bytes, where the first has one.
fn same_ranks(a: &Path, b: &Path, name: &str) {
    if let Ok(x) = std::fs::read(a.join("arrival.bin")) {
        let y = std::fs::read(b.join("arrival.bin"))
            .unwrap_or_else(|e| panic!("{name}: no arrival.bin in {}: {e}", b.display()));
        assert!(x == y, "{name}: arrival.bin differs ({} and {} bytes)", x.len(), y.len());
    }
}

fn sets() -> Vec<(String, Vec<PathBuf>)> {
    let mut out: Vec<(String, Vec<PathBuf>)> = std::fs::read_dir(root().join("data-samples"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "laz" || e == "las"))
        .map(|p| (p.file_name().unwrap().to_string_lossy().to_string(), vec![p]))
        .collect();
    if let Some(data) = shared_data() {
        let files = readable_fixtures(&data);
        let bcts: Vec<PathBuf> =
            files.iter().filter(|f| f.to_string_lossy().contains("bcts_")).cloned().collect();
        let ept: Vec<PathBuf> = files
            .iter()
            .filter(|f| f.to_string_lossy().contains("ept-data/"))
            .take(8)
            .cloned()
            .collect();
        out.push(("bcts merged".into(), bcts));
        out.push(("8 EPT tiles merged".into(), ept));
        // every 12th real file alone, the larger ones first
        let mut big: Vec<PathBuf> = files
            .into_iter()
            .filter(|f| std::fs::metadata(f).map(|m| m.len()).unwrap_or(0) > 20_000)
            .collect();
        big.sort();
        out.extend(big.into_iter().step_by(12).map(|f| (f.display().to_string(), vec![f])));
    }
    out
}

#[test]
fn merged_stores_equal_the_one_machine_store() {
    let d = tempdir("dist-equal");
    let synth = d.join("synth.las");
    run_ok(gen().args(["--points", "400000", "--seed", "7", "-o", s(&synth)]));
    let mut all = sets();
    all.push(("synthetic 400k".into(), vec![synth.clone()]));
    let mut compared = 0;
    for (name, inputs) in &all {
        if inputs.is_empty() {
            continue;
        }
        let one = d.join("one");
        let _ = std::fs::remove_dir_all(&one);
        let o = mortar()
            .arg("build")
            .args(inputs)
            .args(["-o", s(&one), "--quiet", "--leaf-capacity", LEAF])
            .output()
            .unwrap();
        if !o.status.success() {
            continue; // not buildable on one machine either (e.g. no points)
        }
        for n in [1, 2, 7, 16] {
            match distributed(inputs, n, &d, false) {
                Ok(store) => {
                    assert_same_store(&one, &store, &format!("{name}, {n} jobs"));
                    if name.starts_with("synthetic") {
                        // Merged by linking each part's nodes.bin in as a segment: no payload
                        // byte copied (the parts are removed by now: the links hold the data).
                        let j: serde_json::Value = serde_json::from_slice(
                            &std::fs::read(d.join(format!("merge{n}.json"))).unwrap(),
                        )
                        .unwrap();
                        assert_eq!(j["linked_parts"].as_u64(), Some(n as u64), "{name}: {j}");
                        assert_eq!(j["copied_bytes"].as_u64(), Some(0), "{name}: {j}");
                        let st = Store::open(&store).unwrap();
                        assert_eq!(st.covered.len(), n + 1, "{name}: a segment per part");
                        assert!(st.entries.iter().any(|e| e.segment as usize == n));
                    }
                    if n == 7 && name.starts_with("synthetic") {
                        // the same points back, byte for byte
                        let (a, b) = (d.join("a.las"), d.join("b.las"));
                        run_ok(mortar().args(["sort", s(&one), "-o", s(&a), "--quiet"]));
                        run_ok(mortar().args(["sort", s(&store), "-o", s(&b), "--quiet"]));
                        assert!(
                            std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap(),
                            "{name}: mortar sort differs"
                        );
                    }
                    std::fs::remove_dir_all(&store).unwrap();
                    compared += 1;
                }
                // headers that lie: refused by a job, and planned with --scan
                Err(e) if e.contains("--scan") => {
                    let store = distributed(inputs, n, &d, true)
                        .unwrap_or_else(|e| panic!("{name}, {n} jobs, --scan: {e}"));
                    assert_same_store(&one, &store, &format!("{name}, {n} jobs, --scan"));
                    std::fs::remove_dir_all(&store).unwrap();
                    compared += 1;
                }
                Err(e) => panic!("{name}, {n} jobs: {e}"),
            }
        }
    }
    assert!(compared >= 4 * 3, "compared {compared} builds");
    std::fs::remove_dir_all(&d).unwrap();
}

/// A merged store keeps the one-machine build's arrival ranks (compared by
/// [`assert_same_store`] everywhere above), so `--append` extends it in place without its
/// original inputs: the one-machine store of all inputs, node for node, ranks included.
#[test]
fn a_merged_store_is_extended_in_place_without_its_inputs() {
    let d = tempdir("dist-append");
    let (a, b) = (d.join("a.las"), d.join("b.las"));
    run_ok(gen().args(["--points", "400000", "--seed", "9", "-o", s(&a)]));
    run_ok(gen().args(["--points", "60000", "--seed", "4", "--extent", "300"]).args([
        "--origin",
        "500200,5000200,0",
        "-o",
        s(&b),
    ]));
    let whole = d.join("whole");
    one_machine(&[a.clone(), b.clone()], &whole);
    let store = distributed(std::slice::from_ref(&a), 4, &d, false).unwrap();
    std::fs::rename(&a, d.join("moved.las")).unwrap();
    let o = run_ok(mortar().args(["build", "--append", s(&store), s(&b), "--quiet", "--json"]));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(j["kept_nodes"].as_u64().unwrap() > 0, "nothing kept: {j}");
    same_ranks(&whole, &store, "appended in place");
    let (x, y) = (Store::open(&whole).unwrap(), Store::open(&store).unwrap());
    assert_eq!(x.header.points, y.header.points);
    assert_eq!(x.entries.len(), y.entries.len(), "node count");
    for (i, (e, f)) in x.entries.iter().zip(&y.entries).enumerate() {
        let key = |e: &mortar_io::store::NodeEntry| (e.level, e.kind, e.index, e.count, e.length);
        assert_eq!(key(e), key(f), "node {i}");
        assert!(x.node_bytes(i) == y.node_bytes(i), "node {i}'s payload differs");
    }
    std::fs::remove_dir_all(&d).unwrap();
}

/// A LAS file whose header's bounds leave out part of its points (max x moved down).
fn lying(dir: &Path) -> PathBuf {
    let p = dir.join("lying.las");
    run_ok(gen().args(["--points", "200000", "--seed", "3", "-o", s(&p)]));
    let mut b = std::fs::read(&p).unwrap();
    let max_x = f64::from_le_bytes(b[179..187].try_into().unwrap());
    let min_x = f64::from_le_bytes(b[187..195].try_into().unwrap());
    b[179..187].copy_from_slice(&(min_x + 0.6 * (max_x - min_x)).to_le_bytes());
    std::fs::write(&p, b).unwrap();
    p
}

#[test]
fn lying_headers_and_bad_parts_are_refused() {
    let d = tempdir("dist-faults");
    let f = lying(&d);
    let other = d.join("other.las");
    run_ok(gen().args([
        "--points",
        "150000",
        "--seed",
        "4",
        "--origin",
        "500600,5000000,0",
        "-o",
        s(&other),
    ]));
    let inputs = vec![f.clone(), other.clone()];
    // the jobs that read the lying file refuse it, naming it and --scan
    let e = distributed(&inputs, 4, &d, false).unwrap_err();
    assert!(e.contains("lying.las") && e.contains("--scan"), "{e}");
    // with --scan the plan is right
    let one = d.join("one");
    one_machine(&inputs, &one);
    let store = distributed(&inputs, 4, &d, true).unwrap();
    assert_same_store(&one, &store, "lying header, --scan");
    std::fs::remove_dir_all(&store).unwrap();
    // parts: a complete set of 3 jobs, and one of another plan
    let plan = d.join("p3.json");
    run_ok(mortar().args([
        "plan",
        s(&other),
        s(&f),
        "--scan",
        "--jobs",
        "3",
        "-o",
        s(&plan),
        "--quiet",
        "--leaf-capacity",
        LEAF,
    ]));
    let part = |i: usize| d.join(format!("q{i}"));
    for i in 0..3 {
        run_ok(mortar().args([
            "build",
            "--plan",
            s(&plan),
            "--job",
            &i.to_string(),
            "-o",
            s(&part(i)),
            "--quiet",
        ]));
    }
    let plan2 = d.join("p2.json");
    run_ok(mortar().args(["plan", s(&other), "--jobs", "2", "-o", s(&plan2), "--quiet"]));
    let foreign = d.join("foreign");
    run_ok(mortar().args([
        "build",
        "--plan",
        s(&plan2),
        "--job",
        "0",
        "-o",
        s(&foreign),
        "--quiet",
    ]));
    let out = d.join("merged");
    for (parts, want) in [
        (vec![part(0), part(1)], "missing"),
        (vec![part(0), part(1), part(1), part(2)], "again"),
        (vec![part(0), part(1), part(2), foreign.clone()], "another plan"),
        (vec![part(0), part(1), d.join("nothing")], "not a part"),
    ] {
        let o = mortar().arg("merge").args(&parts).args(["-o", s(&out)]).output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(err.contains(want), "{want}: {err}");
        assert!(!out.exists(), "a refused merge wrote {}", out.display());
    }
    // a plan edited by hand, and a damaged part: clear errors
    let text = std::fs::read_to_string(&plan).unwrap();
    let edited = d.join("edited.json");
    std::fs::write(&edited, text.replacen("\"leaf_capacity\": 3000", "\"leaf_capacity\": 7", 1))
        .unwrap();
    let o = mortar()
        .args(["build", "--plan", s(&edited), "--job", "0", "-o", s(&d.join("e0"))])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("edited.json"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(!d.join("e0").exists());
    let o = mortar()
        .args(["build", "--plan", s(&plan), "--job", "3", "-o", s(&d.join("e0"))])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "job 3 of 3 jobs");
    let broken = d.join("broken");
    run_ok(mortar().args(["build", "--plan", s(&plan), "--job", "2", "-o", s(&broken), "--quiet"]));
    let eb = std::fs::read(broken.join("entries.bin")).unwrap();
    std::fs::write(broken.join("entries.bin"), &eb[..eb.len() / 2]).unwrap();
    let o = mortar()
        .arg("merge")
        .args([part(0), part(1), broken.clone()])
        .args(["-o", s(&out)])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("broken") && err.contains("damaged"), "{err}");
    assert!(!out.exists());
    // a part's arrival ranks cut short: refused, the file named; a part without them (an
    // older mortar's): merged, the store without ranks (extended from its inputs)
    let ranks = part(2).join("arrival.bin");
    let kept = std::fs::read(&ranks).unwrap();
    std::fs::write(&ranks, &kept[..kept.len() - 3]).unwrap();
    let o = mortar().arg("merge").args([part(0), part(1), part(2)]).args(["-o", s(&out)]).output();
    let o = o.unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("q2/arrival.bin") && err.contains("truncated"), "{err}");
    assert!(!out.exists());
    // well-formed ranks that name a point twice: refused, the part named
    std::fs::write(&ranks, &kept).unwrap();
    let points = |p: &Path| -> u64 {
        let j: serde_json::Value =
            serde_json::from_slice(&std::fs::read(p.join("part.json")).unwrap()).unwrap();
        j["points"].as_u64().unwrap()
    };
    let rf =
        mortar_io::store::arrival::RankFile::open(&part(2), points(&part(2))).unwrap().unwrap();
    let mut r = Vec::new();
    rf.copy(0..rf.len(), &mut None, &mut r).unwrap();
    let rf0 = mortar_io::store::arrival::RankFile::open(&part(0), points(&part(0)));
    let mut r0 = Vec::new();
    let rf0 = rf0.unwrap().unwrap();
    rf0.copy(0..1, &mut None, &mut r0).unwrap();
    let mid = r.len() / 2;
    r[mid] = r0[0];
    let (declared, colors) = (rf.declared, rf.colors.unwrap());
    drop(rf);
    mortar_io::store::arrival::write(&part(2), r.len(), |i| r[i], declared, colors).unwrap();
    let o = mortar().arg("merge").args([part(0), part(1), part(2)]).args(["-o", s(&out)]).output();
    let o = o.unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        (err.contains("q2") || err.contains("q0"))
            && err.contains("twice")
            && err.contains("arrival.bin"),
        "{err}"
    );
    assert!(!out.exists());
    std::fs::remove_file(&ranks).unwrap();
    run_ok(mortar().arg("merge").args([part(0), part(1), part(2)]).args(["-o", s(&out), "-q"]));
    assert!(out.join("nodes.bin").exists() && !out.join("arrival.bin").exists());
    std::fs::remove_dir_all(&out).unwrap();
    std::fs::write(&ranks, &kept).unwrap();
    // a job run again gives the same part; one killed half-way and run again too
    let snapshot = |p: &Path| -> Vec<Vec<u8>> {
        ["nodes.bin", "entries.bin", "candidates.bin", "arrival.bin", "part.json"]
            .iter()
            .map(|n| std::fs::read(p.join(n)).unwrap())
            .collect()
    };
    let before = snapshot(&part(1));
    run_ok(mortar().args([
        "build",
        "--plan",
        s(&plan),
        "--job",
        "1",
        "-o",
        s(&part(1)),
        "--quiet",
    ]));
    assert!(snapshot(&part(1)) == before, "a repeated job gives another part");
    std::fs::remove_dir_all(part(1)).unwrap();
    let mut child = mortar()
        .args([
            "build",
            "--plan",
            s(&plan),
            "--job",
            "1",
            "-o",
            s(&part(1)),
            "--quiet",
            "--threads",
            "1",
        ])
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(150));
    child.kill().unwrap();
    let _ = child.wait();
    // merging now fails (or the job had finished)
    if !part(1).join("part.json").exists() {
        let o = mortar()
            .arg("merge")
            .args([part(0), part(1), part(2)])
            .args(["-o", s(&out)])
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(1));
        assert!(!out.exists());
    }
    run_ok(mortar().args([
        "build",
        "--plan",
        s(&plan),
        "--job",
        "1",
        "-o",
        s(&part(1)),
        "--quiet",
    ]));
    assert!(snapshot(&part(1)) == before, "a job run again after a kill gives another part");
    let stale: Vec<String> = entries(&d).into_iter().filter(|n| n.starts_with(".q1.")).collect();
    assert!(stale.is_empty(), "the killed attempt's files stay: {stale:?}");
    run_ok(mortar().arg("merge").args([part(0), part(1), part(2)]).args([
        "-o",
        s(&out),
        "--quiet",
    ]));
    let one = d.join("one-b");
    one_machine(&[other, f], &one);
    assert_same_store(&one, &out, "after a kill");
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn a_slurm_job_array_builds_the_one_machine_store() {
    if std::env::var("MORTAR_SLURM").as_deref() != Ok("1") {
        eprintln!(
            "SKIP: no Slurm cluster (MORTAR_SLURM=1 after deploy/slurm/localhost-cluster.sh)"
        );
        return;
    }
    let d = tempdir("dist-slurm");
    let mut all: Vec<(String, Vec<PathBuf>)> =
        sets().into_iter().filter(|(n, _)| n == "autzen_trim.laz" || n == "bcts merged").collect();
    all.retain(|(_, i)| !i.is_empty());
    let bin = PathBuf::from(env!("CARGO_BIN_EXE_mortar"));
    for (k, (name, inputs)) in all.iter().enumerate() {
        let out = d.join(format!("run{k}"));
        let o = std::process::Command::new("bash")
            .arg(root().join("deploy/slurm/submit.sh"))
            .arg("5")
            .arg(&out)
            .args(inputs)
            .env("MORTAR", &bin)
            .env("WAIT", "1")
            .env("CPUS", "1")
            .env("LEAF", LEAF)
            .env("MEMORY", "64M")
            .output()
            .unwrap();
        let logs = std::fs::read_dir(out.join("logs"))
            .map(|r| {
                r.filter_map(|e| e.ok())
                    .map(|e| {
                        format!(
                            "{}: {}",
                            e.path().display(),
                            std::fs::read_to_string(e.path()).unwrap_or_default()
                        )
                    })
                    .collect::<Vec<_>>()
                    .join("\n")
            })
            .unwrap_or_default();
        assert!(
            o.status.success(),
            "{name}: submit.sh failed: {}\n{logs}",
            String::from_utf8_lossy(&o.stderr)
        );
        let one = d.join(format!("one{k}"));
        one_machine(inputs, &one);
        assert_same_store(&one, &out.join("store"), &format!("{name} on Slurm"));
        assert_eq!(std::fs::read_dir(out.join("parts")).unwrap().count(), 5, "{name}: five parts");
    }
    std::fs::remove_dir_all(&d).unwrap();
}
