//! Progress bars (issue 13): on a terminal, `build`, `batch` and `sort` draw a bar per stage with
//! percent, count, rate and time left; on a pipe they print nothing of it, and `--json` is
//! unchanged. The terminal is a pseudo-terminal made by util-linux `script`.

mod common;
use common::*;
use std::process::Command;

fn has_script() -> bool {
    Command::new("script").arg("--version").output().is_ok_and(|o| o.status.success())
}

#[test]
fn bars_on_a_terminal_nothing_on_a_pipe() {
    let dir = tempdir("progress");
    let input = dir.join("in.laz");
    run_ok(gen().args(["--points", "3000000", "--seed", "4", "-o"]).arg(&input));
    let bin = env!("CARGO_BIN_EXE_mortar");
    let jobs: Vec<(String, &str)> = vec![
        (
            format!("{bin} build {} -o {}", input.display(), dir.join("store").display()),
            "mortar build: ",
        ),
        (
            format!("{bin} batch {} -o {}", input.display(), dir.join("b.mbat").display()),
            "mortar batch: reading (points)",
        ),
        (
            format!("{bin} sort {} -o {}", input.display(), dir.join("s.las").display()),
            "mortar sort: ",
        ),
    ];
    for (cmd, _) in &jobs {
        // On a pipe: no bar, no escape sequences.
        let json_flag = if cmd.contains(" sort ") { "" } else { " --json" };
        let out = Command::new("sh").arg("-c").arg(format!("{cmd}{json_flag}")).output().unwrap();
        assert!(out.status.success(), "{cmd}: {}", String::from_utf8_lossy(&out.stderr));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains('%') && !err.contains('\u{1b}'), "{cmd}: progress on a pipe: {err}");
        if !json_flag.is_empty() {
            let json: serde_json::Value =
                serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{cmd} --json: {e}"));
            assert_eq!(json["points"].as_u64(), Some(3_000_000), "{cmd}: {json}");
        }
        let _ = std::fs::remove_dir_all(dir.join("store"));
    }
    if !has_script() {
        eprintln!("SKIP: no util-linux script for a pseudo-terminal");
        return;
    }
    for (cmd, want) in &jobs {
        let out = Command::new("script")
            .args(["-q", "-e", "-c"])
            .arg(format!("stty cols 120; {cmd}"))
            .arg("/dev/null")
            .output()
            .unwrap();
        let tty = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{cmd} on a terminal: {tty}");
        assert!(
            tty.contains(want) && tty.contains("% ") && tty.contains("left"),
            "{cmd}: no bar on a terminal: {tty}"
        );
        let _ = std::fs::remove_dir_all(dir.join("store"));
    }
    let _ = std::fs::remove_dir_all(&dir);
}
