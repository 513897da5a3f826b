//! `mortar build --append STORE MORE...` (issue 29 item 4): the store becomes the store of its
//! inputs followed by `MORE`, byte for byte the store a build of all of them in that order gives
//! (with the store's settings; any engine), and it changes atomically.
//!
//! How, in this first form: the store's build record (`build.json`) names its inputs with their
//! size and modification time; they must still be there, unchanged. The new store is built from
//! them and the new inputs into a working directory beside the store (`STORE.append`), by the
//! engine the options pick, committing as any build does, so that a stopped append continues with
//! `--append --resume`; then the two directories are exchanged in one step (`renameat2` with
//! `RENAME_EXCHANGE`; readers that hold the old files open keep reading them) and the old one is
//! removed. Until the exchange the store is the old one, whole; after it, the new one, whole.
//!
//! What it does not do yet: it costs a whole build (the store's nodes that no new point touches
//! are built again rather than reused), and it needs the original inputs. Both need the store to
//! keep each point's arrival rank (the earliest old point of a cell of a node that splits or of
//! a grown root is not known from Morton-ordered leaves), a store format change not made yet.

use super::record::{BuildRecord, InputPrint};
use crate::error::{Error, Result, StoreError};
use mortar_core::octree::{BuilderConfig, ColorMode};
use std::path::{Path, PathBuf};

/// What `--append` builds: the inputs (the store's, then the new ones), the settings the store
/// was built with, and where the new store is built before it replaces the old one.
#[derive(Clone, Debug)]
pub struct AppendPlan {
    /// The store to extend.
    pub store: PathBuf,
    /// Its recorded inputs in their order, then the new ones.
    pub inputs: Vec<String>,
    /// The store's leaf capacity, depth limit and colour rule (from its build record).
    pub config: BuilderConfig,
    /// The working directory the new store is built in (`STORE.append`).
    pub work: PathBuf,
}

/// What the command line asked of an append besides the inputs: a leaf capacity and colour rule
/// other than the defaults must be the store's own; `resume` continues a stopped append.
#[derive(Clone, Copy, Debug, Default)]
pub struct AppendAsk {
    /// `--leaf-capacity` when given.
    pub leaf_capacity: Option<u32>,
    /// `--averaged-colors`.
    pub averaged_colors: bool,
    /// `--resume`.
    pub resume: bool,
}

/// Checks that `store` can be extended by `more` as `ask` says (a complete store with a build
/// record whose inputs are all present and unchanged, the same settings, no stopped append left
/// unless resumed) and says what to build. `more` must not be empty.
pub fn plan_append(store: &Path, more: &[String], ask: AppendAsk) -> Result<AppendPlan> {
    let plan = plan_inputs(store, more)?;
    let c = plan.config;
    let averaged = c.color_mode == ColorMode::Averaged;
    if ask.leaf_capacity.is_some_and(|l| l != c.leaf_capacity) || (ask.averaged_colors && !averaged)
    {
        return Err(Error::Store {
            path: store.to_path_buf(),
            error: StoreError::Append {
                why: format!(
                    "--append keeps the store's settings (leaf capacity {}, {} colours); give no \
                     other --leaf-capacity or --averaged-colors",
                    c.leaf_capacity,
                    if averaged { "averaged" } else { "first-come" }
                ),
            },
        });
    }
    check_work(&plan, ask.resume)?;
    Ok(plan)
}

impl AppendPlan {
    /// What to say of an append whose build failed: the store is unchanged, and one that
    /// `stopped` (its last commit kept) continues with `--append --resume`.
    pub fn failure(&self, stopped: bool) -> String {
        let store = self.store.display();
        if stopped {
            format!(
                "the append to {store} stopped, the store unchanged (`mortar build --append \
                 {store} <the same new inputs> --resume` continues it)"
            )
        } else {
            format!("the append to {store} failed, the store unchanged")
        }
    }
}

/// The plan's inputs and settings from the store's build record (see [`plan_append`]).
fn plan_inputs(store: &Path, more: &[String]) -> Result<AppendPlan> {
    let bad =
        |why: String| Error::Store { path: store.to_path_buf(), error: StoreError::Append { why } };
    if more.is_empty() {
        return Err(bad("--append needs at least one input to add".into()));
    }
    if !super::is_store(store) {
        return Err(bad("not a mortar store (no hierarchy.bin); --append extends a store".into()));
    }
    let Some(record) = BuildRecord::read(store)? else {
        return Err(bad("has no build record (build.json), so its inputs are not known; \
             --append builds again from them"
            .into()));
    };
    if !record.complete {
        return Err(bad(
            "its build did not finish; finish it first (`mortar build --resume` with its inputs)"
                .into(),
        ));
    }
    for InputPrint { path, bytes, modified_ns } in &record.inputs {
        let meta = std::fs::metadata(path).map_err(|e| {
            bad(format!(
                "--append builds again from the store's inputs, and {path} cannot be read ({e})"
            ))
        })?;
        let ns = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos());
        if meta.len() != *bytes || ns != *modified_ns {
            return Err(bad(format!(
                "--append builds again from the store's inputs, and {path} changed since the \
                 store was built (size or modification time)"
            )));
        }
    }
    let mut inputs: Vec<String> = record.inputs.iter().map(|i| i.path.clone()).collect();
    inputs.extend(more.iter().cloned());
    let config = BuilderConfig {
        leaf_capacity: record.leaf_capacity,
        max_level: record.max_level,
        color_mode: if record.colors == "averaged" {
            ColorMode::Averaged
        } else {
            ColorMode::FirstCome
        },
    };
    // `store/`, `.` or a link: the directory itself, so that the working directory is its
    // sibling, not its child.
    let store = std::fs::canonicalize(store).map_err(|e| Error::io(store, e))?;
    let mut work = store.as_os_str().to_owned();
    work.push(".append");
    Ok(AppendPlan { store, inputs, config, work: PathBuf::from(work) })
}

/// Checks, before an append builds into `plan.work`, that no stopped append is left there
/// unless `resume` continues it.
fn check_work(plan: &AppendPlan, resume: bool) -> Result<()> {
    let begun = std::fs::read_dir(&plan.work).map(|mut d| d.next().is_some()).unwrap_or(false);
    if begun && !resume {
        return Err(Error::Store {
            path: plan.store.clone(),
            error: StoreError::Append {
                why: format!(
                    "an append was begun in {} and stopped; continue it with `mortar build \
                     --append {} --resume` and the same inputs, or remove that directory",
                    plan.work.display(),
                    plan.store.display()
                ),
            },
        });
    }
    Ok(())
}

/// Puts the finished store `plan.work` in place of `plan.store` in one step and removes the old
/// one. Where the file system cannot exchange directories, the old store is first moved aside
/// (`STORE.append-old`), then the new one moved in.
pub fn replace_store(plan: &AppendPlan) -> Result<()> {
    if !exchange(&plan.work, &plan.store)? {
        let mut aside = plan.store.as_os_str().to_owned();
        aside.push(".append-old");
        let aside = PathBuf::from(aside);
        std::fs::rename(&plan.store, &aside).map_err(|e| Error::io(&plan.store, e))?;
        std::fs::rename(&plan.work, &plan.store).map_err(|e| Error::io(&plan.work, e))?;
        return std::fs::remove_dir_all(&aside).map_err(|e| Error::io(&aside, e));
    }
    // `work` now holds the old store.
    std::fs::remove_dir_all(&plan.work).map_err(|e| Error::io(&plan.work, e))
}

/// Exchanges the directories `a` and `b` atomically; `false` where the system cannot.
#[cfg(target_os = "linux")]
fn exchange(a: &Path, b: &Path) -> Result<bool> {
    use std::os::unix::ffi::OsStrExt;
    let c = |p: &Path| {
        std::ffi::CString::new(p.as_os_str().as_bytes())
            .map_err(|_| Error::io(p, std::io::Error::other("a NUL byte in the path")))
    };
    let (ca, cb) = (c(a)?, c(b)?);
    // SAFETY: two NUL-terminated paths, relative to the working directory.
    let r = unsafe {
        libc::syscall(
            libc::SYS_renameat2,
            libc::AT_FDCWD,
            ca.as_ptr(),
            libc::AT_FDCWD,
            cb.as_ptr(),
            libc::RENAME_EXCHANGE,
        )
    };
    if r == 0 {
        return Ok(true);
    }
    let e = std::io::Error::last_os_error();
    match e.raw_os_error() {
        Some(libc::ENOSYS) | Some(libc::EINVAL) | Some(libc::ENOTSUP) => Ok(false),
        _ => Err(Error::io(b, e)),
    }
}

#[cfg(not(target_os = "linux"))]
fn exchange(_: &Path, _: &Path) -> Result<bool> {
    Ok(false)
}
