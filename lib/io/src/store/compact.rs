//! `mortar build --compact store/`: rewrites a store so that `nodes.bin` holds only the
//! payloads its last commit uses (stores of the incremental engine keep superseded versions of
//! nodes that changed between commits; the sorted engine writes each node once), and upgrades
//! it: raw (version 2) payloads are coded (`codec.rs`; those larger than
//! [`CODE_LIMIT`](super::codec::CODE_LIMIT) stay raw) and the hierarchy says
//! version 3. So a version 2 store becomes a version 3 store of the same points.
//!
//! The compacted store is written beside the old one (`<store>.compacting`, every payload copied
//! in hierarchy order, the commit protocol as in a build), then the directories are swapped by
//! two renames (the old one to `<store>.old`, the new one in its place) and the old one is
//! removed. A reader that has the old store open keeps reading its files (they are unlinked, not
//! changed). Run it when no build writes the store. A crash between the two renames leaves
//! `<store>.old` and `<store>.compacting`, which the error of the next run names.

use super::format::*;
use super::reader::Store;
use crate::error::{Error, Result, StoreError};
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

/// What a compaction did.
#[derive(Clone, Copy, Debug, Default)]
pub struct CompactReport {
    /// Bytes of `nodes.bin` before.
    pub before: u64,
    /// Bytes after (the live payloads).
    pub after: u64,
    /// Nodes.
    pub nodes: u64,
}

fn beside(dir: &Path, suffix: &str) -> PathBuf {
    let mut name = dir.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(suffix);
    dir.with_file_name(name)
}

/// Compacts the store `dir` (see the module docs).
pub fn compact(dir: &Path) -> Result<CompactReport> {
    let (tmp, old) = (beside(dir, ".compacting"), beside(dir, ".old"));
    for p in [&tmp, &old] {
        if p.exists() {
            return Err(Error::Store { path: p.to_path_buf(), error: StoreError::CompactionLeft });
        }
    }
    let store = Store::open(dir)?;
    let before = std::fs::metadata(dir.join(NODES_FILE))
        .map_err(|e| Error::io(dir.join(NODES_FILE), e))?
        .len();
    let guard = crate::cleanup::TempPath::adopt(tmp.clone());
    std::fs::create_dir(&tmp).map_err(|e| Error::io(&tmp, e))?;
    for f in [SOURCE_FILE, super::record::RECORD_FILE] {
        let src = dir.join(f);
        if src.exists() {
            std::fs::copy(&src, tmp.join(f)).map_err(|e| Error::io(&src, e))?;
        }
    }
    let np = tmp.join(NODES_FILE);
    let mut out = std::io::BufWriter::with_capacity(
        8 << 20,
        File::create(&np).map_err(|e| Error::io(&np, e))?,
    );
    let mut entries = Vec::with_capacity(store.entries.len());
    let mut at = 0u64;
    for (i, e) in store.entries.iter().enumerate() {
        crate::cleanup::check_interrupted()?;
        let d = store.node_bytes(i);
        // Raw (version 2) payloads are coded on the way, up to the size a build codes in memory.
        let raw =
            super::codec::codec_of(&bytemuck::pod_read_unaligned(&d[..64])) == super::codec::RAW;
        let coded = raw.then(|| super::codec::encode(d.to_vec()));
        let d = coded.as_deref().unwrap_or(d);
        out.write_all(d).map_err(|err| Error::io(&np, err))?;
        entries.push(NodeEntry { offset: at, length: d.len() as u64, ..*e });
        at += d.len() as u64;
    }
    let f = out.into_inner().map_err(|e| Error::io(&np, e.into_error()))?;
    f.sync_all().map_err(|e| Error::io(&np, e))?;
    let header = HierarchyHeader { nodes_len: at, version: VERSION, ..store.header };
    let mut bytes = bytemuck::bytes_of(&header).to_vec();
    bytes.extend_from_slice(bytemuck::cast_slice(&entries));
    let hp = tmp.join(HIERARCHY_FILE);
    {
        let mut h = File::create(&hp).map_err(|e| Error::io(&hp, e))?;
        h.write_all(&bytes).map_err(|e| Error::io(&hp, e))?;
        h.sync_all().map_err(|e| Error::io(&hp, e))?;
    }
    // The copy must read back as the same store before it replaces the old one.
    let check = Store::open(&tmp)?;
    if check.header.points != store.header.points || check.entries.len() != store.entries.len() {
        return Err(Error::Store { path: tmp.clone(), error: StoreError::CompactionCheck });
    }
    drop(check);
    let nodes = store.entries.len() as u64;
    drop(store);
    std::fs::rename(dir, &old).map_err(|e| Error::io(dir, e))?;
    if let Err(e) = std::fs::rename(&tmp, dir) {
        let _ = std::fs::rename(&old, dir);
        return Err(Error::io(&tmp, e));
    }
    guard.keep();
    if let Some(parent) = dir
        .parent()
        .and_then(|p| File::open(if p.as_os_str().is_empty() { Path::new(".") } else { p }).ok())
    {
        let _ = parent.sync_all();
    }
    std::fs::remove_dir_all(&old).map_err(|e| Error::io(&old, e))?;
    Ok(CompactReport { before, after: at, nodes })
}
