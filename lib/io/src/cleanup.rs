//! Temporary files and directories that must not outlive an error or a Ctrl-C.
//!
//! Every partial output is written under a temporary name and registered here; the binary's
//! Ctrl-C handler calls [`remove_all`]. [`TempPath`] removes its path when dropped (error paths),
//! and [`TempPath::persist`] renames it into place when the work succeeded.
//!
//! Here too: the Ctrl-C flag the handler sets and long loops poll ([`INTERRUPTED`],
//! [`check_interrupted`]), and the phase timer `MORTAR_TRACE` prints ([`trace`]).

use crate::error::{Error, Result};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

static REGISTRY: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn register(p: &Path) {
    REGISTRY.lock().unwrap_or_else(|e| e.into_inner()).push(p.to_path_buf());
}

fn unregister(p: &Path) {
    REGISTRY.lock().unwrap_or_else(|e| e.into_inner()).retain(|q| q != p);
}

fn remove(p: &Path) {
    if p.is_dir() {
        let _ = std::fs::remove_dir_all(p);
    } else {
        let _ = std::fs::remove_file(p);
    }
}

/// Removes every registered temporary path (for the Ctrl-C handler).
pub fn remove_all() {
    let paths = std::mem::take(&mut *REGISTRY.lock().unwrap_or_else(|e| e.into_inner()));
    for p in paths {
        remove(&p);
    }
}

/// A registered temporary file or directory, removed on drop unless persisted.
#[derive(Debug)]
pub struct TempPath {
    path: PathBuf,
    keep: bool,
}

impl TempPath {
    /// A temporary name next to `target` (same directory, so the final rename is atomic).
    pub fn beside(target: &Path) -> TempPath {
        let dir = target.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
        let name = target
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "out".into());
        let path = dir.join(format!(".{name}.mortar-tmp-{}", std::process::id()));
        register(&path);
        TempPath { path, keep: false }
    }

    /// A fresh temporary directory under `parent`.
    pub fn dir_in(parent: &Path, tag: &str) -> std::io::Result<TempPath> {
        static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let path = parent.join(format!(".mortar-{tag}-{}-{n}", std::process::id()));
        register(&path);
        std::fs::create_dir_all(&path)?;
        Ok(TempPath { path, keep: false })
    }

    /// Takes charge of an existing path (a directory being built): removed on drop and on Ctrl-C
    /// unless kept.
    pub fn adopt(path: PathBuf) -> TempPath {
        register(&path);
        TempPath { path, keep: false }
    }

    /// Leaves the path where it is, now and on Ctrl-C.
    pub fn keep(mut self) {
        self.keep = true;
        unregister(&self.path);
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Renames the temporary file to `target`.
    pub fn persist(mut self, target: &Path) -> std::io::Result<()> {
        std::fs::rename(&self.path, target)?;
        unregister(&self.path);
        self.keep = true;
        Ok(())
    }
}

impl Drop for TempPath {
    fn drop(&mut self) {
        if !self.keep {
            remove(&self.path);
            unregister(&self.path);
        }
    }
}

/// Set by the binary's Ctrl-C handler; long loops check it and stop with [`Error::Interrupted`].
pub static INTERRUPTED: AtomicBool = AtomicBool::new(false);

/// [`Error::Interrupted`] once the binary's Ctrl-C handler has set [`INTERRUPTED`].
pub fn check_interrupted() -> Result<()> {
    if INTERRUPTED.load(Ordering::Relaxed) {
        Err(Error::Interrupted)
    } else {
        Ok(())
    }
}

/// Prints the time since `t0` when `MORTAR_TRACE` is set (for profiling phases).
pub fn trace(phase: &str, t0: std::time::Instant) {
    if std::env::var_os("MORTAR_TRACE").is_some() {
        eprintln!("mortar: trace: {phase} done at {:.3} s", t0.elapsed().as_secs_f64());
    }
}
