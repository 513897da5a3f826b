//! Issue 30 §2: inputs over HTTP. A COPC file served by a real HTTP server that honours ranges
//! (npm `http-server`, installed by tests/web/install.sh) is rendered with range requests: the
//! same picture as the local file, fetching only the closeup's share; plain LAS/LAZ over HTTP
//! give the outputs of the local files. Servers that misbehave (tests/http_server.py: one that
//! ignores Range, one whose bodies end early, one whose file keeps changing) and a missing file
//! give one-line errors naming the URL, exit 1, and no output.

mod common;
use common::*;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

/// A server process, killed on drop, and its base URL.
struct Server {
    child: Child,
    base: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// tests/http_server.py serving `dir` in `mode` (`ranges`, `short`, `etag`), or python's own
/// `http.server` (which ignores Range) for mode `plain`.
fn python_server(dir: &Path, mode: &str) -> Server {
    let mut c = Command::new("python3");
    if mode == "plain" {
        // Port 0 is not accepted here: take a free one first.
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        c.args(["-m", "http.server", &port.to_string(), "--bind", "127.0.0.1", "--directory"]);
        c.arg(dir).stdout(Stdio::null()).stderr(Stdio::null());
        let child = c.spawn().expect("python3");
        wait_for_port(port);
        return Server { child, base: format!("http://127.0.0.1:{port}") };
    }
    c.arg(root().join("tests/http_server.py")).arg(dir).arg(mode).stdout(Stdio::piped());
    let mut child = c.spawn().expect("python3");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let port: u16 = line.trim().parse().expect("the server's port");
    Server { child, base: format!("http://127.0.0.1:{port}") }
}

fn wait_for_port(port: u16) {
    for _ in 0..200 {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return;
        }
        std::thread::sleep(std::time::Duration::from_millis(25));
    }
    panic!("no server on port {port}");
}

/// npm `http-server` serving `dir`, or `None` (skipped) where tests/web is not installed; with
/// `MORTAR_REQUIRE_WEB=1` its absence fails.
fn http_server(dir: &Path) -> Option<Server> {
    let bin = root().join("tests/web/node_modules/.bin/http-server");
    if !bin.exists() {
        assert!(
            std::env::var("MORTAR_REQUIRE_WEB").as_deref() != Ok("1"),
            "MORTAR_REQUIRE_WEB=1 but tests/web is not installed (tests/web/install.sh)"
        );
        eprintln!("SKIP: no npm http-server (bash tests/web/install.sh)");
        return None;
    }
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let child = Command::new(bin)
        .arg(dir)
        .args(["-p", &port.to_string(), "-a", "127.0.0.1", "-s", "-c-1"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("http-server");
    wait_for_port(port);
    Some(Server { child, base: format!("http://127.0.0.1:{port}") })
}

fn render_json(input: &str, png: &Path, extra: &[&str]) -> serde_json::Value {
    let o = run_ok(
        mortar()
            .arg("render")
            .arg(input)
            .arg("-o")
            .arg(png)
            .args(["--width", "640", "--height", "480", "--backend", "cpu", "--json"])
            .args(extra),
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

/// A 1 M-point synthetic scan exported to COPC, and the sample LAZ, in a directory to serve.
fn served_files(tag: &str) -> PathBuf {
    let dir = tempdir(tag);
    let las = dir.join("g.las");
    run_ok(gen().args(["--points", "1000000", "--seed", "3", "-o"]).arg(&las));
    run_ok(mortar().arg("export").arg(&las).args(["-q", "-o"]).arg(dir.join("g.copc.laz")));
    std::fs::copy(root().join("data-samples/autzen_trim.laz"), dir.join("s.laz")).unwrap();
    dir
}

#[test]
fn copc_over_http_reads_a_closeup_with_range_requests() {
    let dir = served_files("http-copc");
    let Some(server) = http_server(&dir) else { return };
    let url = format!("{}/g.copc.laz", server.base);
    let local = dir.join("g.copc.laz");
    let closeup = ["--target", "500100,5000100,0", "--eye", "500100,5000040,60"];
    for extra in [&closeup[..], &["--lod-threshold", "0"][..]] {
        let (a, b) = (dir.join("remote.png"), dir.join("local.png"));
        let r = render_json(&url, &a, extra);
        let l = render_json(local.to_str().unwrap(), &b, extra);
        assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap(), "{extra:?}");
        let (rs, ls) = (&r["lod_source"], &l["lod_source"]);
        assert_eq!(rs["nodes_read"], ls["nodes_read"], "{rs} {ls}");
        assert_eq!(ls["bytes_fetched"], 0);
        let fetched = rs["bytes_fetched"].as_f64().unwrap();
        let bytes = rs["bytes"].as_f64().unwrap();
        if extra == closeup {
            // What was fetched is what was read, and the chunk table and EVLR headers.
            assert!(fetched < 0.25 * bytes, "a closeup fetched {fetched} of {bytes} bytes");
            assert!(fetched <= rs["bytes_read"].as_f64().unwrap() + 4096.0, "{rs}");
        }
    }
    // `info` on the URL names it and shows the hierarchy.
    let o = run_ok(mortar().arg("info").arg(&url).arg("--json"));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j[0]["path"], url.as_str(), "{j}");
    assert_eq!(j[0]["point_count"], 1_000_000);
    // Plain LAZ over HTTP: `sort` writes the bytes it writes from the local file.
    let (a, b) = (dir.join("remote.laz"), dir.join("local.laz"));
    run_ok(mortar().arg("sort").arg(format!("{}/s.laz", server.base)).arg("-o").arg(&a));
    run_ok(mortar().arg("sort").arg(dir.join("s.laz")).arg("-o").arg(&b));
    assert!(std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap(), "sort over HTTP differs");
    // A missing file: one line naming the URL, exit 1.
    let missing = format!("{}/nope.laz", server.base);
    let o = mortar().arg("info").arg(&missing).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains(&missing) && err.contains("404"), "{err}");
    assert_eq!(err.lines().count(), 1, "{err}");
}

#[test]
fn misbehaving_servers_give_clear_errors_and_no_output() {
    let dir = served_files("http-bad");
    let local = dir.join("g.copc.laz");
    let closeup = ["--target", "500100,5000100,0", "--eye", "500100,5000040,60"];
    // A server that ignores Range: the whole file is read, with a warning, and the picture is
    // the local file's.
    {
        let s = python_server(&dir, "plain");
        let (a, b) = (dir.join("plain.png"), dir.join("local.png"));
        let url = format!("{}/g.copc.laz", s.base);
        let o = run_ok(
            mortar()
                .arg("render")
                .arg(&url)
                .arg("-o")
                .arg(&a)
                .args(["--width", "640", "--height", "480", "--backend", "cpu"])
                .args(closeup),
        );
        assert!(String::from_utf8_lossy(&o.stderr).contains("ignores range requests"));
        render_json(local.to_str().unwrap(), &b, &closeup);
        assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    }
    // Bodies that end early, and a file that changes between requests: exit 1, one line naming
    // the URL and the problem, no output written.
    for (mode, says) in [("short", "ended after"), ("etag", "changed while it was read")] {
        let s = python_server(&dir, mode);
        let url = format!("{}/g.copc.laz", s.base);
        let png = dir.join(format!("{mode}.png"));
        let o = mortar()
            .arg("render")
            .arg(&url)
            .arg("-o")
            .arg(&png)
            .args(["--width", "320", "--height", "240", "--backend", "cpu"])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{mode}: {err}");
        assert!(err.contains(&url) && err.contains(says), "{mode}: {err}");
        assert_eq!(err.lines().filter(|l| l.contains("error")).count(), 1, "{mode}: {err}");
        assert!(!png.exists(), "{mode}: an output was written");
        let o = mortar()
            .arg("sort")
            .arg(format!("{}/s.laz", s.base))
            .arg("-o")
            .arg(dir.join("x.laz"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{mode} sort: {err}");
        assert!(!dir.join("x.laz").exists());
    }
    // The local copies are gone after each command.
    let left: Vec<_> = std::fs::read_dir(std::env::temp_dir())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with("mortar-http-"))
        .map(|e| e.path())
        .filter(|p| std::fs::read_dir(p).map(|mut d| d.next().is_some()).unwrap_or(false))
        .collect();
    assert!(left.iter().all(|p| !p.exists() || is_running(p)), "copies left: {left:?}");
}

/// Whether the copy directory `p` belongs to a process still running (another test's).
fn is_running(p: &Path) -> bool {
    let name = p.file_name().unwrap().to_string_lossy().to_string();
    let pid = name.trim_start_matches("mortar-http-");
    Path::new("/proc").join(pid).exists()
}

#[test]
fn ept_over_http_fetches_only_the_selected_node_files() {
    let Some(data) = shared_data() else { return };
    let parent = data.join("PyForestScan/example_data");
    let Some(server) = http_server(&parent) else { return };
    let dir = tempdir("http-ept");
    let local = parent.join("ept");
    let view = [
        "--target",
        "202150,2184150,1300",
        "--eye",
        "202150,2183950,1700",
        "--fov",
        "15",
        "--color",
        "classification",
    ];
    let l = render_json(local.to_str().unwrap(), &dir.join("local.png"), &view);
    for url in [format!("{}/ept/", server.base), format!("{}/ept/ept.json", server.base)] {
        let r = render_json(&url, &dir.join("remote.png"), &view);
        assert_eq!(
            std::fs::read(dir.join("remote.png")).unwrap(),
            std::fs::read(dir.join("local.png")).unwrap(),
            "{url}"
        );
        let (rs, ls) = (&r["lod_source"], &l["lod_source"]);
        assert_eq!((rs["format"].as_str(), &rs["nodes_read"]), (Some("ept"), &ls["nodes_read"]));
        // What was fetched is ept.json, the hierarchy and the selected nodes' files: what the
        // local read reads, a small share of the directory.
        assert_eq!(rs["bytes_fetched"], ls["bytes_read"], "{rs} {ls}");
        assert!(rs["bytes"].is_null(), "{rs}");
        let share = ls["bytes_read"].as_f64().unwrap() / ls["bytes"].as_f64().unwrap();
        assert!(share < 0.1, "{ls}");
    }
    // A directory without ept.json: one line naming it, exit 1.
    let o = mortar()
        .arg("render")
        .arg(format!("{}/nope/", server.base))
        .arg("-o")
        .arg(dir.join("x.png"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("nope/ept.json") && err.contains("404"), "{err}");
    assert!(!dir.join("x.png").exists());
}
