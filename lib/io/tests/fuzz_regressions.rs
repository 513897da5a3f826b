//! Replays the fuzz targets' findings and seeds in the normal test suite (FUZZING.md): every
//! file of `fuzz/regressions/<target>/` (an input that crashed, hung or allocated hugely before
//! its fix) and of the seed corpus `fuzz/corpus/<target>/` goes through the same function the
//! fuzz target calls, so `cargo test` on any machine fails if a fixed bug comes back.

#[path = "../../../fuzz/src/lib.rs"]
#[allow(dead_code)]
mod targets;

use std::path::PathBuf;

fn replay(target: &str, run: fn(&[u8])) {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fuzz");
    let mut n = 0;
    for dir in ["regressions", "corpus"] {
        let d = root.join(dir).join(target);
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        let mut files: Vec<PathBuf> =
            rd.filter_map(|e| e.ok()).map(|e| e.path()).filter(|p| p.is_file()).collect();
        files.sort();
        for f in files {
            let bytes = std::fs::read(&f).unwrap();
            // A panic names the input: the test harness prints this line with it.
            eprintln!("replaying {}", f.display());
            run(&bytes);
            n += 1;
        }
    }
    assert!(n > 0, "no inputs for fuzz target {target} under {}", root.display());
}

#[test]
fn las_header() {
    replay("las_header", targets::las_header);
}

#[test]
fn vlr_records() {
    replay("vlr_records", targets::vlr_records);
}

#[test]
fn las_input() {
    replay("las_input", targets::las_input);
}

#[test]
fn batch_file() {
    replay("batch_file", targets::batch_file);
}

#[test]
fn store() {
    replay("store", targets::store);
}

#[test]
fn lod_index() {
    replay("lod_index", targets::lod_index);
}

// What each fixed finding must do now (the replays above only check that nothing panics; these
// also hold in builds without overflow checks, where some of the bugs were silent).

fn regression(target: &str, name: &str) -> Vec<u8> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../fuzz/regressions")
        .join(target)
        .join(name);
    std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// A WKT record whose text has a multi-byte character where the EPSG search looked for
/// `AUTHORITY[`: sliced a `str` inside a character (panic in every build).
#[test]
fn wkt_char_boundary() {
    for target in ["las_header", "vlr_records"] {
        let b = regression(target, "wkt-char-boundary");
        let text = String::from_utf8_lossy(&b).into_owned();
        let mut user_id = [0u8; 16];
        user_id[..15].copy_from_slice(b"LASF_Projection");
        let v = mortar_io::las::Vlr {
            reserved: 0,
            user_id,
            record_id: 2112,
            description: [0; 32],
            data: text.into_bytes(),
        };
        let _ = mortar_io::crs::describe(&[&v]);
    }
    // Many AUTHORITY objects in one WKT: linear now, not quadratic.
    let wkt = format!(
        "PROJCS[\"x\",{}AUTHORITY[\"EPSG\",\"32633\"]]",
        "AUTHORITY[\"X\",\"1\"],".repeat(50_000)
    );
    let mut user_id = [0u8; 16];
    user_id[..15].copy_from_slice(b"LASF_Projection");
    let v = mortar_io::las::Vlr {
        reserved: 0,
        user_id,
        record_id: 2112,
        description: [0; 32],
        data: wkt.into_bytes(),
    };
    let t = std::time::Instant::now();
    assert_eq!(mortar_io::crs::describe(&[&v]).epsg, Some(32633));
    assert!(t.elapsed().as_secs_f64() < 5.0, "{:?}", t.elapsed());
}

/// A batch file whose metadata puts an attribute past the end of the record: records() indexed
/// out of bounds. Now refused at open.
#[test]
fn batch_attribute_outside_record() {
    let b = regression("batch_file", "attribute-outside-record");
    let e = mortar_io::batchfile::BatchFile::from_bytes(
        std::path::Path::new("x.mbat"),
        mortar_io::source::Bytes::Owned(b),
    )
    .unwrap_err();
    assert!(e.to_string().contains("lies outside the"), "{e}");
}

/// A store whose first hierarchy entry claims level 40: naming the key in the error shifted a
/// u32 by 32+ (overflow panic with overflow checks, wrong digits without).
#[test]
fn key_name_deep_level() {
    let key = mortar_core::octree::NodeKey { level: 40, index: [u32::MAX; 3] };
    assert_eq!(key.name(), format!("r{}{}", "0".repeat(8), "7".repeat(32)));
    let b = regression("store", "key-name-deep-level");
    targets::store(&b);
}

/// A LAZ file without a usable chunk table (read sequentially) whose data ends in an offset to
/// a "table" claiming 2^28 chunks: laz's sequential decompressor allocated 11 GB for it (16-core
/// fuzz run, issue 12). Now the count is checked against the bytes first.
#[test]
fn laz_sequential_table() {
    let b = regression("las_input", "laz-sequential-table");
    targets::las_input(&b);
}

/// A chunk table entry whose byte count makes the running offset overflow (a panic in debug
/// builds, a wrapped offset that passed the bounds check in release builds). Now refused.
#[test]
fn laz_chunk_offset_overflow() {
    let b = regression("las_input", "laz-chunk-offset-overflow");
    targets::las_input(&b);
}

/// A LASzip VLR whose item sizes sum past 65,535: laz sums them in u16 (overflow).
#[test]
fn laz_item_sizes_overflow() {
    let b = regression("las_input", "laz-item-sizes-overflow");
    targets::las_input(&b);
}

/// A chunk table claiming 2^24 points for a chunk of a few bytes: the decode buffer (332 MB)
/// was sized by the claim (16-core fuzz run after findings 6-8). Now bounded by the bytes.
#[test]
fn laz_chunk_points() {
    let b = regression("las_input", "laz-chunk-points");
    targets::las_input(&b);
}

/// A LAZ chunk-table offset pointing inside the 8 bytes of the offset itself: the size of the
/// point data before the table was computed as `table - start - 8` and underflowed (CI fuzz run
/// of 2026-12-04). Now such an offset is no table.
#[test]
fn laz_chunk_table_in_offset() {
    let b = regression("las_input", "laz-chunk-table-in-offset");
    targets::las_input(&b);
}

/// A LAS 1.4 LAZ chunk whose layer sizes claim 2 GiB: laz-rs allocated that before reading.
/// Now the sizes are checked against the chunk's bytes first.
#[test]
fn laz_layer_size() {
    let b = regression("las_input", "laz-layer-size");
    let input = mortar_io::source::LasInput::from_bytes(
        PathBuf::from("x.laz"),
        mortar_io::source::Bytes::Owned(b),
    )
    .unwrap();
    let errors: Vec<String> = input
        .pieces()
        .iter()
        .filter_map(|p| input.read_piece(p).err())
        .map(|e| e.to_string())
        .collect();
    assert!(errors.iter().any(|e| e.contains("layers claim")), "{errors:?}");
}

/// A store whose hierarchy puts the root cube's corner near i64::MAX: the cube's world bounds
/// overflowed (`min + size`) in the LOD selection. Now refused by `StoreLod::new`.
#[test]
fn root_min_overflow() {
    let b = regression("store", "root-min-overflow");
    targets::store(&b);
    let [src, hier, nodes] = targets::split_store(&b);
    let dir = std::env::temp_dir().join(format!("mortar-root-min-overflow-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (name, bytes) in [("source.las", src), ("hierarchy.bin", hier), ("nodes.bin", nodes)] {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
    let r = mortar_io::store::Store::open(&dir).map(mortar_io::store::StoreLod::new);
    std::fs::remove_dir_all(&dir).unwrap();
    let e = r.expect("the store opens").unwrap_err();
    assert!(e.to_string().contains("outside the 32-bit grid"), "{e}");
}
