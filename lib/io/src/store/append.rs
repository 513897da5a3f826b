//! `mortar build --append STORE MORE...` (issue 29 item 4): the store becomes the store of its
//! inputs followed by `MORE`, byte for byte the store a build of all of them in that order gives
//! (with the store's settings; any engine), and it changes atomically.
//!
//! How: the new store is built from the store's inputs and the new ones into a working directory
//! beside the store (`STORE.append`), by the engine the options pick, committing as any build
//! does, so that a stopped append continues with `--append --resume`; then the two directories
//! are exchanged in one step (`renameat2` with `RENAME_EXCHANGE`; readers that hold the old files
//! open keep reading them) and the old one is removed. Until the exchange the store is the old
//! one, whole; after it, the new one, whole.
//!
//! The store's inputs are its own points where it keeps their arrival ranks (`arrival.bin`,
//! written by the sorted, partitioned and GPU engines and a distributed build's merge:
//! [`super::arrival`]): its leaves' records are put back
//! in the order they arrived ([`Store::records_in_arrival_order`], all of them in memory) and
//! stand first in the new build, so the original files are not needed. (Where they are all
//! there, unchanged, and uncompressed LAS, they are read instead: faster than decoding.) A store without the file
//! (built by the incremental engine, or by an older mortar) is
//! built again from
//! its recorded inputs, which must still be there, unchanged (`build.json` names them with their
//! size and modification time).
//!
//! This whole build is what `--append` falls back to where the store's nodes cannot be kept
//! ([`super::patch`] says when); the store's points in arrival order must then fit in memory
//! beside the build (the partitioned engine does not read them piece by piece), or its
//! original inputs must be there.

use super::record::{BuildRecord, InputPrint};
use super::Store;
use crate::dataset::{Dataset, OpenOptions, RecordSource};
use crate::error::{Error, Result, StoreError};
use crate::las::{Header, LasMeta, Vlr};
use crate::source::Piece;
use mortar_core::layout::RecordLayout;
use mortar_core::octree::{BuilderConfig, ColorMode};
use std::borrow::Cow;
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
    /// Whether the store's own points stand for its inputs (it has `arrival.bin`); otherwise
    /// the recorded inputs are read again.
    pub from_store: bool,
    /// The new inputs as given.
    pub more: Vec<String>,
    /// The store's recorded inputs.
    pub recorded: Vec<InputPrint>,
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

impl AppendPlan {
    /// The inputs of the new store, merged: the store's points in arrival order (where
    /// `from_store`) or its recorded inputs, then the new ones.
    ///
    /// The store's points are held in memory in arrival order beside the build: where they and
    /// their sorted copy do not fit `memory`, or where the new inputs move the merged grid, the
    /// recorded inputs are read instead, and where those are gone, the append is refused.
    pub fn open_inputs(&self, opts: &OpenOptions, memory: u64) -> Result<Dataset> {
        let recorded = || -> Result<Dataset> {
            let paths = crate::inputs::expand(&self.inputs)?;
            crate::inputs::open_with(&paths, opts)
        };
        // The recorded inputs where the store's points cannot stand for them (`why`).
        let instead = |why: String| -> Result<Dataset> {
            match check_recorded(&self.store, &self.recorded) {
                Ok(()) => recorded(),
                Err(e) => Err(Error::Store {
                    path: self.store.clone(),
                    error: StoreError::Append {
                        why: format!("{why}, and its original inputs cannot be read instead ({e})"),
                    },
                }),
            }
        };
        if !self.from_store {
            return recorded();
        }
        let store = Store::open(&self.store)?;
        let rl = store.layout.record_len as u64;
        let need = store.header.points.saturating_mul(2 * rl + 24);
        if need > memory {
            return instead(format!(
                "appending from the store's own {} points needs about {} MiB of memory, over \
                 --memory ({} MiB): give more --memory",
                store.header.points,
                need >> 20,
                memory >> 20
            ));
        }
        let Some((records, declared)) = store.records_in_arrival_order()? else {
            return Err(Error::Store {
                path: self.store.clone(),
                error: StoreError::Append { why: "its arrival.bin went away".into() },
            });
        };
        let first: Box<dyn RecordSource> =
            Box::new(StoreInArrivalOrder::new(&store, records, declared, self.recorded.clone())?);
        drop(store);
        let mut warnings = Vec::new();
        let mut inputs = vec![first];
        for p in crate::inputs::expand(&self.more)? {
            let (src, mut w) = crate::inputs::open_source(&p)?;
            warnings.append(&mut w);
            inputs.push(src);
        }
        let mut ds = Dataset::with_options(inputs, opts)?;
        // The store's integers stand for its inputs' on its own grid only: new inputs that
        // change the merged grid would place them otherwise than the originals would be.
        // (A store without points places nothing.)
        if grid_moved(&ds) {
            drop(ds);
            return instead(
                "the new inputs change the store's scale or offset, so its own points cannot \
                 stand for its inputs exactly"
                    .into(),
            );
        }
        warnings.append(&mut ds.warnings);
        ds.warnings = warnings;
        Ok(ds)
    }
}

/// Whether the merged grid of `ds` is not its first input's (a store standing for its inputs,
/// with points): its integers would then stand for other positions than its inputs'.
pub(super) fn grid_moved(ds: &Dataset) -> bool {
    let own = &ds.inputs[0].header();
    let moved =
        (0..3).any(|a| ds.grid.scale[a] != own.scale[a] || ds.grid.offset[a] != own.offset[a]);
    moved && ds.inputs[0].point_count() > 0
}

/// A store's leaf records in arrival order, standing for the inputs it was built from (their
/// prints go into the new store's build record). [`stand_in`](Self::stand_in) makes one
/// without the records, for an append that reads the new inputs alone (`super::patch`).
pub(super) struct StoreInArrivalOrder {
    path: PathBuf,
    points: u64,
    meta: LasMeta,
    layout: RecordLayout,
    records: Vec<u8>,
    pieces: Vec<Piece>,
    declared: super::arrival::DeclaredBox,
    inputs: Vec<InputPrint>,
}

impl StoreInArrivalOrder {
    /// Its header is the store's (the points' bounds); `declared` is the box the inputs'
    /// headers declared, which placed the store's root.
    fn new(
        store: &Store,
        records: Vec<u8>,
        declared: super::arrival::DeclaredBox,
        inputs: Vec<InputPrint>,
    ) -> Result<StoreInArrivalOrder> {
        let rl = store.layout.record_len;
        let n = (records.len() / rl) as u64;
        let mut s = StoreInArrivalOrder::stand_in(store, declared, inputs);
        s.points = n;
        s.pieces = Self::pieces_of(n, rl);
        s.records = records;
        Ok(s)
    }

    /// The store standing for its inputs (header, layout, declared box, count, pieces) without
    /// its records: reading a piece fails.
    pub(super) fn stand_in(
        store: &Store,
        declared: super::arrival::DeclaredBox,
        inputs: Vec<InputPrint>,
    ) -> StoreInArrivalOrder {
        let n = store.header.points;
        StoreInArrivalOrder {
            path: store.path.clone(),
            points: n,
            meta: store.meta.clone(),
            layout: store.layout.clone(),
            records: Vec::new(),
            pieces: Self::pieces_of(n, store.layout.record_len),
            declared,
            inputs,
        }
    }

    fn pieces_of(n: u64, rl: usize) -> Vec<Piece> {
        let per = crate::source::piece_points(rl);
        (0..n.div_ceil(per))
            .map(|i| Piece {
                index: i as usize,
                first_point: i * per,
                points: per.min(n - i * per),
            })
            .collect()
    }
}

impl RecordSource for StoreInArrivalOrder {
    fn path(&self) -> &Path {
        &self.path
    }
    fn header(&self) -> &Header {
        &self.meta.header
    }
    fn vlrs(&self) -> &[Vlr] {
        &self.meta.vlrs
    }
    fn evlrs(&self) -> &[Vlr] {
        &self.meta.evlrs
    }
    fn layout(&self) -> &RecordLayout {
        &self.layout
    }
    fn point_count(&self) -> u64 {
        self.points
    }
    fn pieces(&self) -> Vec<Piece> {
        self.pieces.clone()
    }
    fn read_piece(&self, piece: &Piece) -> Result<Cow<'_, [u8]>> {
        let rl = self.layout.record_len;
        let s = piece.first_point as usize * rl;
        let e = s + piece.points as usize * rl;
        match self.records.get(s..e) {
            Some(r) => Ok(Cow::Borrowed(r)),
            None => Err(Error::Store {
                path: self.path.clone(),
                error: StoreError::PieceCount { piece: piece.index },
            }),
        }
    }
    fn is_compressed(&self) -> bool {
        false
    }
    fn borrows_pieces(&self) -> bool {
        true
    }
    fn declared_box(&self) -> Option<super::arrival::DeclaredBox> {
        Some(self.declared)
    }
    fn stands_for(&self) -> Option<&[InputPrint]> {
        Some(&self.inputs)
    }
}

/// Checks that the recorded inputs of `store` are all there, unchanged (size and modification
/// time), as an append that builds again from them needs.
fn check_recorded(store: &Path, recorded: &[InputPrint]) -> Result<()> {
    let bad =
        |why: String| Error::Store { path: store.to_path_buf(), error: StoreError::Append { why } };
    for InputPrint { path, bytes, modified_ns } in recorded {
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
    Ok(())
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
    // Mapped LAS inputs cost nothing to read, less than decoding the store's payloads (10 M
    // points on 2 cores: 1.64 s from the originals, 2.23 s from the store's points); LAZ ones
    // cost more (BENCHMARKS.md, "Append from the store's own points").
    let laz = |p: &InputPrint| p.path.to_ascii_lowercase().ends_with(".laz");
    let from_store = super::arrival::exists(store)
        && (record.inputs.iter().any(laz) || check_recorded(store, &record.inputs).is_err());
    if !from_store {
        check_recorded(store, &record.inputs)?;
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
    Ok(AppendPlan {
        store,
        inputs,
        config,
        work: PathBuf::from(work),
        from_store,
        more: more.to_vec(),
        recorded: record.inputs,
    })
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
