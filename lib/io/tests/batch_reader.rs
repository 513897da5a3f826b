//! The batch-file reader: memory-mapped, zero-copy access to any batch's arrays, and values
//! that decode back to the source points.

use mortar_core::layout::{read_xyz, RecordLayout};
use mortar_io::batchfile::{AttributeSelection, BatchFile, BatchSink, Compression};
use mortar_io::dataset::SourceMeta;
use mortar_io::sink_las::{LasSink, Target};
use mortar_io::sort::{sort, OrderedSink, SortOptions};
use mortar_io::synth::{self, SynthOptions};

fn make_batch_file(
    dir: &std::path::Path,
    compression: Compression,
) -> (std::path::PathBuf, Vec<u8>) {
    let o = SynthOptions {
        points: 50_000,
        seed: 7,
        extent: 300.0,
        scale: 0.001,
        origin: [500_000.0, 5_000_000.0, 0.0],
        ..SynthOptions::default()
    };
    let layout = RecordLayout::new(3, 34).unwrap();
    let header = synth::header(&o);
    let grid = mortar_core::grid::Grid { scale: header.scale, offset: header.offset };
    let las = dir.join("in.las");
    let mut sink = LasSink::new(
        Target::File(las.clone()),
        false,
        SourceMeta { header, vlrs: vec![], evlrs: vec![], layout, grid },
        dir,
    )
    .unwrap();
    let (records, stats) = synth::records(&o, 0, o.points);
    sink.begin(&stats.summary()).unwrap();
    sink.write(&records).unwrap();
    sink.finish().unwrap();
    let ds = mortar_io::inputs::open(&[las]).unwrap();
    let attrs = AttributeSelection::All.resolve(&ds.layout).unwrap();
    let t = ds.source_meta();
    let out = dir.join(format!("{compression:?}.mbat"));
    let mut bs = BatchSink::new(&out, t, attrs, compression);
    sort(&ds, &SortOptions::with_memory(1 << 30, dir.to_path_buf()), &mut bs).unwrap();
    bs.finish().unwrap();
    (out, records)
}

#[test]
fn views_borrow_the_map_and_decode_to_the_source_points() {
    let dir = std::env::temp_dir().join(format!("mortar-io-reader-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (path, records) = make_batch_file(&dir, Compression::None);
    let f = BatchFile::open(&path).unwrap();
    assert_eq!(f.header.point_count, 50_000);
    let map = f.bytes().as_ptr_range();
    let mut decoded: Vec<[i32; 3]> = Vec::new();
    for i in 0..f.batch_count() {
        let b = f.batch(i).unwrap();
        for level in 0..3 {
            let w = b.words(level);
            assert_eq!(w.len(), b.len());
            assert!(
                map.contains(&(w.as_ptr() as *const u8)),
                "batch {i} words {level} are not in the map"
            );
        }
        assert!(map.contains(&(b.colors().as_ptr() as *const u8)));
        let g = b.entry.grid();
        for k in 0..b.len() {
            let p = g.decode_exact([b.words(0)[k], b.words(1)[k], b.words(2)[k]]);
            for a in 0..3 {
                assert!(p[a] >= b.entry.min[a] && p[a] <= b.entry.max[a]);
            }
            decoded.push(p);
        }
    }
    let mut src: Vec<[i32; 3]> = records.chunks_exact(34).map(read_xyz).collect();
    src.sort();
    decoded.sort();
    assert_eq!(src, decoded);
    // Any batch, in any order, with only the words asked for.
    let last = f.batch_count() - 1;
    let v = f.batch_sections(last, &[0]).unwrap();
    assert_eq!(v.words(0).len(), v.len());
    assert!(v.words(2).is_empty());

    // zstd files decode to the same arrays
    let (zpath, _) = make_batch_file(&dir, Compression::Zstd);
    let z = BatchFile::open(&zpath).unwrap();
    assert_eq!(z.batch_count(), f.batch_count());
    for i in [0, last] {
        let (a, b) = (f.batch(i).unwrap(), z.batch(i).unwrap());
        for level in 0..3 {
            assert_eq!(a.words(level), b.words(level));
        }
        assert_eq!(a.colors(), b.colors());
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn damaged_batch_files_are_refused() {
    let dir = std::env::temp_dir().join(format!("mortar-io-damaged-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (path, _) = make_batch_file(&dir, Compression::None);
    let good = std::fs::read(&path).unwrap();
    type Damage = Box<dyn Fn(&mut Vec<u8>)>;
    let cases: Vec<(&str, Damage)> = vec![
        ("truncated", Box::new(|b: &mut Vec<u8>| b.truncate(b.len() / 2))),
        ("bad-version", Box::new(|b: &mut Vec<u8>| b[8] = 99)),
        (
            "huge-batch-count",
            Box::new(|b: &mut Vec<u8>| b[24..32].copy_from_slice(&u64::MAX.to_le_bytes())),
        ),
        (
            "meta-outside",
            Box::new(|b: &mut Vec<u8>| b[48..56].copy_from_slice(&(1u64 << 40).to_le_bytes())),
        ),
    ];
    for (tag, patch) in cases {
        let mut b = good.clone();
        patch(&mut b);
        let p = dir.join(format!("{tag}.mbat"));
        std::fs::write(&p, &b).unwrap();
        let e = BatchFile::open(&p).expect_err(tag).to_string();
        assert!(e.contains(&format!("{tag}.mbat")), "{tag}: {e}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
