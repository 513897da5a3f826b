//! `mortar build --compact store/`: rewrites a store's payload segments, one at a time, so
//! that each holds only the payloads its last commit uses (stores of the incremental engine keep
//! superseded versions of nodes that changed between commits; a merge leaves the nodes of a part
//! that a leaf above the cut absorbed), and upgrades it: raw (version 2) payloads are coded
//! (`codec.rs`; those larger than [`CODE_LIMIT`](super::codec::CODE_LIMIT) stay raw) and the
//! hierarchy says version 3. So a version 2 store becomes a version 3 store of the same points.
//!
//! A segment that needs it is rewritten into a new segment file (the next unused number: its
//! live payloads in hierarchy order), synced, and committed as a build commits (the hierarchy
//! written beside, synced, renamed over `hierarchy.bin`; the entries now point into the new
//! segment); then the old segment file is removed (`nodes.bin`, segment 0, is left empty, where
//! a later `--resume` would append). So the extra disk space is one segment's live bytes, a
//! crash leaves the store at its last commit (at worst with one unreferenced segment file, which
//! the next compaction removes), and a reader that has the old commit open keeps reading the
//! removed file (it is unlinked, not changed). Run it when no build writes the store.

use super::format::*;
use super::reader::Store;
use crate::error::{Error, Result};
use std::fs::File;
use std::io::Write;
use std::path::Path;

/// What a compaction did.
#[derive(Clone, Copy, Debug, Default)]
pub struct CompactReport {
    /// Bytes of the payload segment files before.
    pub before: u64,
    /// Bytes after (the live payloads).
    pub after: u64,
    /// Nodes.
    pub nodes: u64,
    /// Segments rewritten.
    pub segments: u64,
}

/// The bytes of the segment files `dir` holds that the hierarchy `covered` names (with their
/// uncommitted tails), and the numbers of `nodes-<s>.bin` files it does not name.
fn segment_files(dir: &Path, covered: &[u64]) -> Result<(u64, Vec<u32>)> {
    let mut bytes = 0;
    let mut stray = Vec::new();
    for e in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let e = e.map_err(|e| Error::io(dir, e))?;
        let name = e.file_name().to_string_lossy().to_string();
        let s = if name == NODES_FILE {
            Some(0)
        } else {
            name.strip_prefix("nodes-")
                .and_then(|r| r.strip_suffix(".bin"))
                .and_then(|n| n.parse::<u32>().ok())
                .filter(|&n| n > 0 && segment_file(n) == name)
        };
        let Some(s) = s else { continue };
        if covered.get(s as usize).is_some_and(|&c| c > 0) || s == 0 {
            bytes += e.metadata().map_err(|err| Error::io(e.path(), err))?.len();
        } else {
            stray.push(s);
        }
    }
    Ok((bytes, stray))
}

/// Compacts the store `dir` (see the module docs).
pub fn compact(dir: &Path) -> Result<CompactReport> {
    let store = Store::open(dir)?;
    let mut header = store.header;
    let mut entries = store.entries.clone();
    let mut covered = store.covered.clone();
    let (before, stray) = segment_files(dir, &covered)?;
    // Files a stopped compaction left, which no commit names.
    for s in stray {
        let p = dir.join(segment_file(s));
        std::fs::remove_file(&p).map_err(|e| Error::io(&p, e))?;
    }
    let mut rewritten = 0;
    // A version 2 store's hierarchy says version 3 once its payloads are coded (its first
    // rewritten segment is all of them: a version 2 store has one).
    header.version = VERSION;
    for s in 0..covered.len() as u32 {
        crate::cleanup::check_interrupted()?;
        let file = dir.join(segment_file(s));
        let held = if covered[s as usize] == 0 && !file.exists() {
            0
        } else {
            std::fs::metadata(&file).map_err(|e| Error::io(&file, e))?.len()
        };
        let live: Vec<usize> = (0..entries.len()).filter(|&i| entries[i].segment == s).collect();
        let live_bytes: u64 = live.iter().map(|&i| entries[i].length).sum();
        // A version 2 store is upgraded: its raw payloads coded (a version 3 store's raw
        // payloads are raw because coding would not shrink them, or too large to code).
        let upgrade = store.header.version < VERSION
            && live.iter().any(|&i| {
                super::codec::codec_of(&bytemuck::pod_read_unaligned(&store.node_bytes(i)[..64]))
                    == super::codec::RAW
            });
        if live_bytes == held && !upgrade {
            continue;
        }
        if live.is_empty() && held == 0 {
            continue;
        }
        // The next unused number.
        let n = covered.len() as u32;
        let np = dir.join(segment_file(n));
        let guard = crate::cleanup::TempPath::adopt(np.clone());
        let mut out = std::io::BufWriter::with_capacity(
            8 << 20,
            File::create(&np).map_err(|e| Error::io(&np, e))?,
        );
        let mut at = 0u64;
        for &i in &live {
            crate::cleanup::check_interrupted()?;
            let d = store.node_bytes(i);
            // Raw (version 2) payloads are coded on the way, up to the size a build codes.
            let is_raw = super::codec::codec_of(&bytemuck::pod_read_unaligned(&d[..64]))
                == super::codec::RAW;
            let key = mortar_core::octree::NodeKey {
                level: entries[i].level as u8,
                index: entries[i].index,
            };
            let order = super::codec::Order::of(store.root_cube(), key, &store.layout);
            let coded = is_raw.then(|| super::codec::encode(d.to_vec(), order));
            let d = coded.as_deref().unwrap_or(d);
            out.write_all(d).map_err(|err| Error::io(&np, err))?;
            entries[i] = NodeEntry { segment: n, offset: at, length: d.len() as u64, ..entries[i] };
            at += d.len() as u64;
        }
        let f = out.into_inner().map_err(|e| Error::io(&np, e.into_error()))?;
        f.sync_all().map_err(|e| Error::io(&np, e))?;
        drop(f);
        covered.push(at);
        covered[s as usize] = 0;
        header.commit += 1;
        header.nodes_len = covered[0];
        commit_hierarchy(dir, &header, &entries, &covered)?;
        guard.keep();
        // The old segment is no longer named: removed (nodes.bin left empty for appends).
        std::fs::remove_file(&file).map_err(|e| Error::io(&file, e))?;
        if s == 0 {
            File::create(&file).map_err(|e| Error::io(&file, e))?;
        }
        rewritten += 1;
    }
    drop(store);
    // The compacted store must read back as the same store.
    let check = Store::open(dir)?;
    let (after, _) = segment_files(dir, &check.covered)?;
    Ok(CompactReport { before, after, nodes: check.entries.len() as u64, segments: rewritten })
}

/// Writes the hierarchy `header` + `entries` + segment table of `covered` to `dir` atomically
/// (beside, synced, renamed, the directory synced).
fn commit_hierarchy(
    dir: &Path,
    header: &HierarchyHeader,
    entries: &[NodeEntry],
    covered: &[u64],
) -> Result<()> {
    let mut bytes = bytemuck::bytes_of(header).to_vec();
    bytes.extend_from_slice(bytemuck::cast_slice(entries));
    bytes.extend_from_slice(&segments_bytes(covered));
    let hp = dir.join(HIERARCHY_FILE);
    let tmp = dir.join(format!("{HIERARCHY_FILE}.tmp"));
    {
        let mut h = File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
        h.write_all(&bytes).map_err(|e| Error::io(&tmp, e))?;
        h.sync_all().map_err(|e| Error::io(&tmp, e))?;
    }
    std::fs::rename(&tmp, &hp).map_err(|e| Error::io(&hp, e))?;
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
    Ok(())
}
