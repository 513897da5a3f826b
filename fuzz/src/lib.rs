//! The bodies of mortar's fuzz targets, one function per target (FUZZING.md).
//!
//! Each takes the fuzzer's bytes, hands them to one of mortar's readers of untrusted input and,
//! where the reader accepts them, walks everything it exposes (every piece, batch, node), so a
//! claim that passed the reader's checks but is wrong shows up as a panic, a hang or a huge
//! allocation. Errors are the expected outcome for almost every input: they are formatted (as
//! mortar prints them) and dropped.
//!
//! The normal test suite replays the saved crash inputs (`fuzz/regressions/<target>/`) through
//! these same functions: `lib/io/tests/fuzz_regressions.rs` includes this file, so it must keep
//! compiling with nothing but `mortar_io` and `mortar_core`.

use mortar_core::layout::RecordLayout;
use mortar_core::octree::{
    select_nodes, Cube, IndexEntry, LodIndex, LodOptions, LodTree, NodeId, NodeKey,
};
use mortar_core::render::{Aabb, Camera, ViewPreset};
use mortar_io::batchfile::BatchFile;
use mortar_io::dataset::RecordSource;
use mortar_io::las::{self, Vlr};
use mortar_io::source::{Bytes, LasInput};
use mortar_io::store::Store;
use mortar_io::store::StoreLod;
use mortar_io::{crs, info};
use std::path::{Path, PathBuf};

/// Called once by every fuzz target before fuzzing (libFuzzer's `init`): keeps libfuzzer-sys's
/// panic hook (print, then abort, so a panic is a crash) except for panics raised inside laz-rs.
/// mortar runs every laz-rs call on untrusted bytes under `catch_unwind` and turns its panic into
/// an error naming the chunk (`source.rs`): those panics unwind to that handler instead. A laz-rs
/// panic that mortar does not catch still reaches libfuzzer-sys's own `catch_unwind` around the
/// target, which aborts: a crash.
pub fn init() {
    let fuzzer_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let in_laz = info.location().is_some_and(|l| l.file().contains("/laz-0."));
        if !in_laz {
            fuzzer_hook(info);
        }
    }));
}

/// The fuzz targets' global allocator: the system's, except that one allocation of more than
/// [`HUGE_ALLOCATION`] bytes prints a backtrace and aborts (a crash for libFuzzer). Without
/// AddressSanitizer (nightly only) libFuzzer's `-malloc_limit_mb` cannot see single allocations,
/// and its `-rss_limit_mb` only says that memory ran out, not where.
pub struct LimitAlloc;

/// Largest single allocation the fuzz targets allow (256 MiB: no fuzz input is larger than
/// 1 MiB, and nothing mortar reads should need more than a few hundred times its input).
pub const HUGE_ALLOCATION: usize = 256 << 20;

// SAFETY: forwards to the system allocator unchanged; only refuses (by aborting) huge requests.
unsafe impl std::alloc::GlobalAlloc for LimitAlloc {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        check_size(layout.size());
        unsafe { std::alloc::System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        check_size(layout.size());
        unsafe { std::alloc::System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        unsafe { std::alloc::System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: std::alloc::Layout, new_size: usize) -> *mut u8 {
        check_size(new_size);
        unsafe { std::alloc::System.realloc(ptr, layout, new_size) }
    }
}

fn check_size(size: usize) {
    if size > HUGE_ALLOCATION {
        eprintln!(
            "==mortar-fuzz== huge allocation: {size} bytes\n{}",
            std::backtrace::Backtrace::force_capture()
        );
        std::process::abort();
    }
}

/// Target `las_header`: the LAS/LAZ header, VLR and EVLR parser (`las::parse`, `las::parse_evlr`),
/// then what is read from the parsed records without the points: the record layout, the
/// extra-bytes descriptors and the CRS records.
pub fn las_header(data: &[u8]) {
    // An EVLR anywhere: the offset comes from the first two bytes.
    if data.len() >= 2 {
        let at = u16::from_le_bytes([data[0], data[1]]) as usize;
        let _ = ok(las::parse_evlr(data, at.min(data.len())));
    }
    let Some(meta) = ok(las::parse(data)) else { return };
    let h = &meta.header;
    let _ = ok(RecordLayout::new(h.point_format, h.record_len as usize));
    let all: Vec<&Vlr> = meta.vlrs.iter().chain(&meta.evlrs).collect();
    let _ = crs::describe(&all);
    let _ = info::extra_bytes(&meta.vlrs);
    for v in &all {
        let _ = (v.user_id_str(), v.description_str(), v.is_laszip(), v.is_copc());
    }
}

/// Target `vlr_records`: the readers of VLR payloads: extra-bytes descriptors (LASF_Spec 4) with
/// the record layout they extend, and the CRS records (GeoTIFF keys, doubles, ASCII, WKT).
/// Bytes: point format, record length (u16), then the payload; payloads for several records are
/// separated by `|||`.
pub fn vlr_records(data: &[u8]) {
    if data.len() < 3 {
        return;
    }
    let format = data[0];
    let record_len = u16::from_le_bytes([data[1], data[2]]) as usize;
    let _ = ok(RecordLayout::new(format, record_len));
    let mut parts = split(&data[3..], b"|||");
    let eb = vlr("LASF_Spec", 4, parts.next().unwrap_or(&[]));
    let _ = info::extra_bytes(std::slice::from_ref(&eb));
    let mut vlrs = vec![eb];
    for (id, p) in [34735u16, 34736, 34737, 2112].into_iter().zip(parts) {
        vlrs.push(vlr("LASF_Projection", id, p));
    }
    let refs: Vec<&Vlr> = vlrs.iter().collect();
    let _ = crs::describe(&refs);
    // The 3D Tiles export's placement: the WKT parsed and turned into PROJ.4, the projection
    // set up and one point transformed (`globe.rs`, `wkt.rs`).
    let records = crs::CrsRecords { vlrs: vlrs[1..].to_vec(), evlrs: Vec::new() };
    if let Ok(Some(g)) = mortar_io::globe::Globe::of_records(&records) {
        let _ = g.ecef([1000.0, 2000.0, 30.0]);
    }
}

/// Target `las_input`: a whole LAS/LAZ file as `mortar` opens it (`LasInput::from_bytes`: header,
/// VLRs, the LASzip VLR, the LAZ chunk table), then every piece decoded (laz-rs for LAZ chunks)
/// and `mortar info --stats` over it.
pub fn las_input(data: &[u8]) {
    let Some(input) =
        ok(LasInput::from_bytes(PathBuf::from("fuzz.las"), Bytes::Owned(data.to_vec())))
    else {
        return;
    };
    // Setting up laz-rs's decoder for a chunk costs ~10 ms in the instrumented build, and every
    // chunk goes through the same code: the first pieces and the last one are decoded, and the
    // stats pass (all pieces again) only runs for files of a few pieces.
    read_some(&input, 8);
    let few = input.pieces().len() <= 4;
    let _ = ok(info::describe(&input, if input.is_laz() { "laz" } else { "las" }, few, None));
}

/// Target `batch_file`: a batch file (`BatchFile::from_bytes`: header, JSON metadata, stored LAS
/// header and EVLRs, batch table), then every batch's sections and every record rebuilt.
pub fn batch_file(data: &[u8]) {
    let Some(f) = ok(BatchFile::from_bytes(Path::new("fuzz.mbat"), Bytes::Owned(data.to_vec())))
    else {
        return;
    };
    for i in 0..f.batch_count() {
        if let Some(b) = ok(f.batch(i)) {
            let _ = (b.words(0).len(), b.colors().len(), b.len());
        }
    }
    read_all(&f);
    let _ = ok(info::describe(&f, "batch", true, Some(&f)));
}

/// Splits the bytes of a store target input: `[u32 source.las length][u32 hierarchy.bin
/// length][source.las][hierarchy.bin][nodes.bin]` (little-endian; lengths are cut to the bytes
/// that exist).
pub fn split_store(data: &[u8]) -> [&[u8]; 3] {
    let len = |at: usize| {
        data.get(at..at + 4).map_or(0, |b| u32::from_le_bytes(b.try_into().unwrap()) as usize)
    };
    let rest = data.get(8..).unwrap_or(&[]);
    let a = len(0).min(rest.len());
    let (src, rest) = rest.split_at(a);
    let b = len(4).min(rest.len());
    let (hier, nodes) = rest.split_at(b);
    [src, hier, nodes]
}

/// The inverse of [`split_store`] (to make seeds from stores).
pub fn pack_store(source: &[u8], hierarchy: &[u8], nodes: &[u8]) -> Vec<u8> {
    let mut v = Vec::with_capacity(8 + source.len() + hierarchy.len() + nodes.len());
    v.extend_from_slice(&(source.len() as u32).to_le_bytes());
    v.extend_from_slice(&(hierarchy.len() as u32).to_le_bytes());
    v.extend_from_slice(source);
    v.extend_from_slice(hierarchy);
    v.extend_from_slice(nodes);
    v
}

/// Target `store`: an octree store (`Store::open` on a directory written from the bytes, see
/// [`split_store`]): `source.las`, the hierarchy and every node payload, every leaf read back
/// as records, then the LOD tree rebuilt from the hierarchy's keys (`StoreLod::new`), a node
/// selection for a framing camera and the selected nodes as batches.
pub fn store(data: &[u8]) {
    let dir = store_dir();
    let [src, hier, nodes] = split_store(data);
    for (name, bytes) in [
        (mortar_io::store::SOURCE_FILE, src),
        (mortar_io::store::HIERARCHY_FILE, hier),
        (mortar_io::store::NODES_FILE, nodes),
    ] {
        std::fs::write(dir.join(name), bytes).expect("write the store's files");
    }
    let Some(s) = ok(Store::open(&dir)) else { return };
    for i in 0..s.entries.len() {
        let _ = s.node(i).grid();
    }
    read_all(&s);
    let Some(lod) = ok(StoreLod::new(s)) else { return };
    walk(lod.index());
    let bounds = lod.bounds();
    for (preset, threshold) in [(ViewPreset::Iso, 64.0), (ViewPreset::Top, 0.0)] {
        let Some(cam) = ok(Camera::frame_perspective(&bounds, preset, 0.8, 64, 48)) else {
            continue;
        };
        let options =
            LodOptions { threshold_px: threshold, point_budget: Some(1 << 20), cull: true };
        if let Some(sel) = ok(lod.select(&cam, &options)) {
            if let Some(b) = ok(lod.batches(&sel.nodes)) {
                for i in 0..b.refs.len().min(64) as u32 {
                    let _ = (b.color(i), b.position(i));
                }
            }
        }
    }
}

/// Target `lod_index`: the octree rebuilt from a hierarchy's keys (`LodIndex::new`, what
/// `StoreLod::new` does with `hierarchy.bin`), then walked and selected from.
/// Bytes: root size log2, then 16 bytes per node: level (u8), leaf (u8), samples (u16), index
/// (3 x u32).
pub fn lod_index(data: &[u8]) {
    let Some((&log2, rest)) = data.split_first() else { return };
    let root = Cube { min: [-(1i64 << 20), 0, 7], size_log2: log2 };
    let entries: Vec<IndexEntry> = rest
        .chunks_exact(16)
        .map(|c| {
            let u = |o: usize| u32::from_le_bytes(c[o..o + 4].try_into().unwrap());
            IndexEntry {
                key: NodeKey { level: c[0], index: [u(4), u(8), u(12)] },
                leaf: c[1] & 1 == 1,
                samples: u16::from_le_bytes([c[2], c[3]]) as u64,
            }
        })
        .collect();
    let Some(index) = ok(LodIndex::new(root, &entries)) else { return };
    walk(&index);
    let grid = mortar_core::grid::Grid { scale: [0.01; 3], offset: [1000.0, 2000.0, 0.0] };
    let edge = 0.01 * (1u64 << root.size_log2.min(62)) as f64;
    let lo = [1000.0 + 0.01 * root.min[0] as f64, 2000.0, 0.07];
    let bounds = Aabb::new(lo, [lo[0] + edge, lo[1] + edge, lo[2] + edge]);
    if let Some(cam) = ok(Camera::frame_perspective(&bounds, ViewPreset::Iso, 0.8, 64, 48)) {
        for threshold in [0.0, 32.0] {
            let _ = ok(select_nodes(
                &index,
                &grid,
                &cam,
                &LodOptions { threshold_px: threshold, point_budget: Some(1000), cull: true },
            ));
        }
    }
}

/// Every query of a tree's structure, on every node.
fn walk(t: &dyn LodTree) {
    for i in 0..t.node_count() {
        let id = NodeId(i as u32);
        let _ = (t.cube(id), t.subtree_points(id), t.samples(id), t.is_leaf(id), t.children(id));
    }
}

/// Reads every piece of a source (what sort, batch and build do with it).
fn read_all(src: &dyn RecordSource) {
    read_some(src, usize::MAX);
}

/// Reads the first `n` pieces of a source and its last one.
fn read_some(src: &dyn RecordSource, n: usize) {
    let rl = src.layout().record_len;
    let pieces = src.pieces();
    let last = pieces.len().saturating_sub(1);
    for p in pieces.into_iter().enumerate().filter(|&(i, _)| i < n || i == last).map(|(_, p)| p) {
        if let Some(r) = ok(src.read_piece(&p)) {
            assert_eq!(
                r.len(),
                p.points as usize * rl,
                "piece {} of {} points holds {} bytes",
                p.index,
                p.points,
                r.len()
            );
        }
    }
}

/// The value, or `None` after formatting the error as mortar prints it (messages are built from
/// the damaged input too).
fn ok<T, E: std::fmt::Display>(r: Result<T, E>) -> Option<T> {
    r.map_err(|e| e.to_string()).ok()
}

fn vlr(user: &str, record_id: u16, data: &[u8]) -> Vlr {
    let mut user_id = [0u8; 16];
    user_id[..user.len()].copy_from_slice(user.as_bytes());
    Vlr { reserved: 0, user_id, record_id, description: [0; 32], data: data.to_vec() }
}

fn split<'a>(mut b: &'a [u8], sep: &'a [u8]) -> impl Iterator<Item = &'a [u8]> + 'a {
    let mut done = false;
    std::iter::from_fn(move || {
        if done {
            return None;
        }
        match b.windows(sep.len()).position(|w| w == sep) {
            Some(i) => {
                let (head, tail) = b.split_at(i);
                b = &tail[sep.len()..];
                Some(head)
            }
            None => {
                done = true;
                Some(b)
            }
        }
    })
}

/// This thread's scratch directory for the `store` target (under `$TMPDIR`; `fuzz/run.sh` points
/// that at a fresh folder in `/dev/shm` where it exists and removes it after the run), removed
/// when the thread ends (the test suite's threads do; a fuzzer's main thread may not).
fn store_dir() -> PathBuf {
    struct Scratch(PathBuf);
    impl Drop for Scratch {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
    thread_local! {
        static DIR: Scratch = {
            static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
            let k = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let d = std::env::temp_dir().join(format!("mortar-fuzz-store-{}-{k}", std::process::id()));
            std::fs::create_dir_all(&d).expect("create the store target's directory");
            Scratch(d)
        };
    }
    DIR.with(|d| d.0.clone())
}

/// Target `laz_pointwise`: LAZ files of LASzip's compressor 1 (pointwise: one arithmetic stream
/// from the first byte of the point data, no chunk table), as LASzip 1.x and early LAStools
/// wrote them, through `LasInput::from_bytes` and every piece's decode. The input is
/// `[flags u8][point count u32][stream...]`: flags bits 0-1 the point format (0-3), bit 2 items
/// of version 2 instead of 1, bit 3 a chunk size of u32::MAX in the VLR (as some writers left
/// it), bit 4 a second file of the same stream with a header count of 1,048,577 (more than one
/// piece); the stream is the compressed points.
pub fn laz_pointwise(data: &[u8]) {
    let Some(file) = pointwise_file(data) else { return };
    let Some(input) = ok(LasInput::from_bytes(PathBuf::from("fuzz.laz"), Bytes::Owned(file)))
    else {
        return;
    };
    read_some(&input, 3);
    let _ = ok(info::describe(&input, "laz", input.pieces().len() <= 2, None));
}

/// The LAZ file a [`laz_pointwise`] input stands for (`None` for inputs too short to say).
pub fn pointwise_file(data: &[u8]) -> Option<Vec<u8>> {
    let (&flags, rest) = data.split_first()?;
    let count = u32::from_le_bytes(rest.get(..4)?.try_into().ok()?) as u64;
    let count = if flags & 16 != 0 { 1_048_577 } else { count };
    let stream = &rest[4..];
    let format = flags & 3;
    let version: u16 = if flags & 4 != 0 { 2 } else { 1 };
    // (type, size): Point10, GpsTime, RGB12
    let mut items: Vec<(u16, u16)> = vec![(6, 20)];
    if format == 1 || format == 3 {
        items.push((7, 8));
    }
    if format >= 2 {
        items.push((8, 6));
    }
    let record_len: u16 = items.iter().map(|i| i.1).sum();
    let mut v = Vec::new();
    v.extend_from_slice(&1u16.to_le_bytes()); // compressor: pointwise
    v.extend_from_slice(&0u16.to_le_bytes()); // coder: arithmetic
    v.extend_from_slice(&[1, 2]); // LASzip 1.2
    v.extend_from_slice(&0u16.to_le_bytes()); // revision
    v.extend_from_slice(&0u32.to_le_bytes()); // options
    v.extend_from_slice(&(if flags & 8 != 0 { u32::MAX } else { 0 }).to_le_bytes()); // chunk size
    v.extend_from_slice(&(-1i64).to_le_bytes());
    v.extend_from_slice(&(-1i64).to_le_bytes());
    v.extend_from_slice(&(items.len() as u16).to_le_bytes());
    for (t, s) in &items {
        v.extend_from_slice(&t.to_le_bytes());
        v.extend_from_slice(&s.to_le_bytes());
        v.extend_from_slice(&version.to_le_bytes());
    }
    let laszip = vlr("laszip encoded", 22204, &v);
    let template = mortar_io::synth::header(&mortar_io::synth::SynthOptions::default());
    let h = las::HeaderOut {
        template: &template,
        point_format: format,
        compressed: true,
        record_len,
        point_count: count,
        points_by_return: [0; 15],
        scale: [0.01; 3],
        offset: [0.0; 3],
        min: [0.0; 3],
        max: [1000.0; 3],
        vlrs: std::slice::from_ref(&laszip),
        evlr_start: 0,
        evlr_count: 0,
    };
    let mut file = las::write_header(&h).ok()?;
    file.extend_from_slice(stream);
    Some(file)
}
