//! The log of a resumable partitioned build (`done.bin` in `.partition/`): one record per
//! finished visit (its key, where the walk stood after it, its entries with their payloads'
//! checksums, the points it added, the hash of their arrival ranks and its candidates, each
//! record checksummed), read back by `--resume` up to the first record that is not whole or
//! whose payloads or ranks are not as logged.

use super::checksum::checksum;
use crate::error::{Error, Result};
use crate::store::format::NodeEntry;
use crate::store::runs::Cands;
use mortar_core::octree::NodeKey;
use rayon::prelude::*;
use std::path::Path;

pub(super) const LOG: &str = "done.bin";
const LOG_MAGIC: u32 = 0x4d50_4c47;
/// A record's bytes before its entries.
const HEAD: usize = 60;

/// A finished visit as the log keeps it.
pub(super) struct Logged {
    pub(super) seq_after: u64,
    pub(super) cands: Cands,
}

fn fnv(b: &[u8]) -> u64 {
    b.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &x| (h ^ x as u64).wrapping_mul(0x100_0000_01b3))
}

/// One log record: the visit's key, where the walk stood after it, its nodes and candidates.
#[allow(clippy::too_many_arguments)]
pub(super) fn log_record(
    key: NodeKey,
    seq_after: u64,
    points: u64,
    ranks_hash: u64,
    nodes_end: u64,
    entries: &[(u32, u64, NodeEntry)],
    hashes: &[u64],
    cands: &Cands,
    rl: usize,
) -> Vec<u8> {
    let mut b = Vec::new();
    for v in [
        LOG_MAGIC,
        key.level as u32,
        key.index[0],
        key.index[1],
        key.index[2],
        entries.len() as u32,
        cands.pos.len() as u32,
    ] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for v in [seq_after, points, nodes_end, ranks_hash] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for ((_, seq, e), h) in entries.iter().zip(hashes) {
        b.extend_from_slice(&seq.to_le_bytes());
        b.extend_from_slice(&h.to_le_bytes());
        b.extend_from_slice(bytemuck::bytes_of(e));
    }
    for i in 0..cands.pos.len() {
        for a in cands.pos[i] {
            b.extend_from_slice(&a.to_le_bytes());
        }
        b.extend_from_slice(&cands.arrival[i].to_le_bytes());
        b.extend_from_slice(&cands.records[i * rl..(i + 1) * rl]);
    }
    let h = fnv(&b);
    b.extend_from_slice(&h.to_le_bytes());
    b
}

/// What a stopped walk left: the visits by key, every logged entry with its payload checksum,
/// the points they added, and where `nodes.bin` ended after the last one.
pub(super) type LogState = (
    std::collections::HashMap<(u32, [u32; 3]), Logged>,
    Vec<(u32, u64, NodeEntry)>,
    Vec<u64>,
    u64,
    u64,
);

/// The log's records up to the first that is not whole, whose payloads in `nodes` are not what
/// it wrote or (with `ranks`, the ranks file of [`super::ranks`]) whose leaves' ranks are not;
/// the log is cut after them.
pub(super) fn read_log(
    path: &Path,
    nodes: &Path,
    rl: usize,
    ranks: Option<&Path>,
) -> Result<LogState> {
    let b = std::fs::read(path).unwrap_or_default();
    let mut visits = std::collections::HashMap::new();
    let (mut entries, mut hashes, mut points, mut end, mut at) =
        (Vec::new(), Vec::new(), 0u64, 0u64, 0usize);
    let nf = std::fs::File::open(nodes).ok();
    let rf = ranks.and_then(|p| std::fs::File::open(p).ok());
    let payload_ok = |e: &NodeEntry, h: u64| -> bool {
        use std::os::unix::fs::FileExt;
        let Some(f) = &nf else { return false };
        let mut buf = vec![0u8; e.length as usize];
        f.read_exact_at(&mut buf, e.offset).is_ok() && checksum(&buf) == h
    };
    let es = std::mem::size_of::<NodeEntry>();
    let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().expect("4 bytes"));
    let u64_at = |o: usize| u64::from_le_bytes(b[o..o + 8].try_into().expect("8 bytes"));
    while b.len() >= at + HEAD {
        if u32_at(at) != LOG_MAGIC {
            break;
        }
        let (ne, nc) = (u32_at(at + 20) as usize, u32_at(at + 24) as usize);
        let len = HEAD + ne * (16 + es) + nc * (20 + rl);
        if b.len() < at + len + 8 || fnv(&b[at..at + len]) != u64_at(at + len) {
            break;
        }
        let key = (u32_at(at + 4), [u32_at(at + 8), u32_at(at + 12), u32_at(at + 16)]);
        let (seq_after, p, nodes_end) = (u64_at(at + 28), u64_at(at + 36), u64_at(at + 44));
        if ranks.is_some() && !super::ranks::ranks_ok(rf.as_ref(), points, p, u64_at(at + 52)) {
            break;
        }
        let mut o = at + HEAD;
        let mut these = Vec::with_capacity(ne);
        for _ in 0..ne {
            let (seq, h) = (u64_at(o), u64_at(o + 8));
            let e: NodeEntry = bytemuck::pod_read_unaligned(&b[o + 16..o + 16 + es]);
            these.push((e.level, seq, e, h));
            o += 16 + es;
        }
        if !these.par_iter().all(|(_, _, e, h)| payload_ok(e, *h)) {
            break;
        }
        for (l, seq, e, h) in these {
            entries.push((l, seq, e));
            hashes.push(h);
        }
        let mut cands = Cands::default();
        for _ in 0..nc {
            let q = [0, 1, 2].map(|a| {
                i32::from_le_bytes(b[o + 4 * a..o + 4 * a + 4].try_into().expect("4 bytes"))
            });
            cands.push(q, u64_at(o + 12), &b[o + 20..o + 20 + rl]);
            o += 20 + rl;
        }
        visits.insert(key, Logged { seq_after, cands });
        points += p;
        end = nodes_end;
        at += len + 8;
    }
    if at < b.len() {
        let f =
            std::fs::OpenOptions::new().write(true).open(path).map_err(|e| Error::io(path, e))?;
        f.set_len(at as u64).map_err(|e| Error::io(path, e))?;
    }
    Ok((visits, entries, hashes, points, end))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::format::LEAF;
    use crate::store::partitioned::testing::{bytes, scratch};

    #[test]
    fn the_log_keeps_whole_records_whose_payloads_are_there_and_cuts_the_rest() {
        let (dir, rl) = (scratch("log"), 20);
        let nodes = dir.join("nodes.bin");
        let payloads = [bytes(96, 5), bytes(40, 6), bytes(64, 7)];
        std::fs::write(&nodes, payloads.concat()).unwrap();
        let entry = |i: usize, off: u64| NodeEntry {
            level: 3,
            kind: LEAF,
            index: [i as u32, 1, 2],
            segment: 0,
            count: 4,
            offset: off,
            length: payloads[i].len() as u64,
        };
        let mut cands = Cands::default();
        cands.push([1, 2, 3], 77, &bytes(rl, 8));
        cands.push([-4, 5, 6], 78, &bytes(rl, 9));
        let key = |i: u32| NodeKey { level: 3, index: [i, 1, 2] };
        // The leaves' ranks of the three visits: 10, 20 and 5 of them.
        let ranks: Vec<u64> = (0..35u64).map(|i| i * 7 % 35).collect();
        let rh = |r: std::ops::Range<usize>| {
            let mut h = super::super::checksum::RankHash::default();
            h.add(&ranks[r]);
            h.finish()
        };
        let rank_file = dir.join("ranks.bin");
        std::fs::write(&rank_file, bytemuck::cast_slice(&ranks)).unwrap();
        let r0 = log_record(
            key(0),
            1,
            10,
            rh(0..10),
            96,
            &[(3, 0, entry(0, 0))],
            &[checksum(&payloads[0])],
            &cands,
            rl,
        );
        let r1 = log_record(
            key(1),
            2,
            20,
            rh(10..30),
            136,
            &[(3, 1, entry(1, 96))],
            &[checksum(&payloads[1])],
            &Cands::default(),
            rl,
        );
        let log = dir.join(LOG);
        std::fs::write(&log, [r0.clone(), r1.clone()].concat()).unwrap();
        let (visits, entries, hashes, points, end) =
            read_log(&log, &nodes, rl, Some(&rank_file)).unwrap();
        assert_eq!((visits.len(), entries.len(), hashes.len(), points, end), (2, 2, 2, 30, 136));
        let v = &visits[&(3, [0, 1, 2])];
        assert_eq!((v.seq_after, &v.cands.pos, &v.cands.arrival), (1, &cands.pos, &cands.arrival));
        assert_eq!(v.cands.records, cands.records);
        // A record torn by a kill: the whole records before it are kept, the log is cut there.
        let r2 = log_record(
            key(2),
            3,
            5,
            rh(30..35),
            200,
            &[(3, 2, entry(2, 136))],
            &[checksum(&payloads[2])],
            &Cands::default(),
            rl,
        );
        std::fs::write(&log, [r0.clone(), r1.clone(), r2[..r2.len() - 3].to_vec()].concat())
            .unwrap();
        let (visits, _, _, points, end) = read_log(&log, &nodes, rl, Some(&rank_file)).unwrap();
        assert_eq!((visits.len(), points, end), (2, 30, 136));
        assert_eq!(std::fs::metadata(&log).unwrap().len(), (r0.len() + r1.len()) as u64);
        // A record whose payload in nodes.bin is not what it logged (written, not synced).
        let mut nb = std::fs::read(&nodes).unwrap();
        nb[100] ^= 0xff;
        std::fs::write(&nodes, &nb).unwrap();
        let (visits, _, _, points, _) = read_log(&log, &nodes, rl, Some(&rank_file)).unwrap();
        assert_eq!((visits.len(), points), (1, 10), "the second visit's payload changed");
        // Whole records, the payloads as written, but the second visit's ranks lost (as after a
        // power loss) or the ranks file cut short: the log is cut before it.
        std::fs::write(&nodes, payloads.concat()).unwrap();
        std::fs::write(&log, [r0.clone(), r1.clone()].concat()).unwrap();
        let mut lost = ranks.clone();
        lost[12] = 0;
        std::fs::write(&rank_file, bytemuck::cast_slice(&lost)).unwrap();
        let (visits, _, _, points, _) = read_log(&log, &nodes, rl, Some(&rank_file)).unwrap();
        assert_eq!((visits.len(), points), (1, 10), "the second visit's ranks changed");
        std::fs::write(&log, [r0.clone(), r1.clone()].concat()).unwrap();
        std::fs::write(&rank_file, bytemuck::cast_slice(&ranks[..25])).unwrap();
        let (visits, _, _, points, _) = read_log(&log, &nodes, rl, Some(&rank_file)).unwrap();
        assert_eq!((visits.len(), points), (1, 10), "the ranks file ends in the second visit");
        // A distributed job keeps no ranks: none are checked.
        std::fs::write(&log, [r0.clone(), r1.clone()].concat()).unwrap();
        let (visits, _, _, points, _) = read_log(&log, &nodes, rl, None).unwrap();
        assert_eq!((visits.len(), points), (2, 30));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
