//! LAZ chunks larger than one piece (`LAZ_PIECE_POINTS`) are decoded in pieces by kept stream
//! decoders: every piece, read in any order and from several threads, gives the records that
//! were written, in point formats 3 (pointwise chunked) and 6 (layered), with and without
//! skipped layers; and LASzip's pointwise compressor (one stream, no chunk table) decodes too.

use mortar_core::layout::RecordLayout;
use mortar_io::dataset::SourceMeta;
use mortar_io::sink_las::{LasSink, Target};
use mortar_io::sort::{OrderedSink, PieceStats};
use mortar_io::source::{LasInput, LAZ_PIECE_POINTS};
use mortar_io::synth::{self, SynthOptions};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

fn tempdir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("mortar-io-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Seeded records of `layout` whose positions are small (what a writer can put on a grid) and
/// whose other bytes are noise.
fn records(layout: &RecordLayout, n: usize, seed: u64) -> Vec<u8> {
    let rl = layout.record_len;
    let mut out = vec![0u8; n * rl];
    out.par_chunks_mut(rl).enumerate().for_each(|(i, r)| {
        let mut h = seed ^ (i as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        for b in r.iter_mut() {
            h ^= h << 13;
            h ^= h >> 7;
            h ^= h << 17;
            *b = h as u8;
        }
        for a in 0..3 {
            let v = ((h >> (a * 16)) & 0xffff) as i32 + (i as i32 % 1000);
            r[4 * a..4 * a + 4].copy_from_slice(&v.to_le_bytes());
        }
        if layout.format >= 6 {
            // returns: number 1 of 1 (a valid return byte), scanner channel 0
            r[14] = 0x11;
        }
    });
    out
}

fn write_laz(path: &Path, layout: RecordLayout, recs: &[u8], chunk: u32) {
    let o = SynthOptions::default();
    let mut header = synth::header(&o);
    if layout.format >= 6 {
        header.version = (1, 4);
        header.header_size = 375;
    }
    header.point_format = layout.format;
    header.record_len = layout.record_len as u16;
    let grid = mortar_core::grid::Grid { scale: header.scale, offset: header.offset };
    let mut sink = LasSink::new(
        Target::File(path.to_path_buf()),
        true,
        SourceMeta { header, vlrs: vec![], evlrs: vec![], layout: layout.clone(), grid },
        path.parent().unwrap(),
    )
    .unwrap();
    sink.laz_chunk_size(chunk);
    let stats = PieceStats::of(recs, &layout);
    sink.begin(&stats.summary()).unwrap();
    sink.write(recs).unwrap();
    sink.finish().unwrap();
}

/// Every piece read in reverse and in parallel equals the records written.
fn check_pieces(input: &LasInput, recs: &[u8], rl: usize) {
    let pieces = input.pieces().to_vec();
    assert!(pieces.len() > 1, "the chunk should be cut into pieces");
    assert!(pieces.iter().all(|p| p.points <= LAZ_PIECE_POINTS));
    let got: Vec<(u64, Vec<u8>)> = pieces
        .par_iter()
        .rev()
        .map(|p| (p.first_point, input.read_piece(p).unwrap().into_owned()))
        .collect();
    for (first, bytes) in got {
        let s = first as usize * rl;
        assert!(bytes == recs[s..s + bytes.len()], "piece at point {first} differs");
    }
    // one thread, in order, twice (the kept decoders continue, then start again)
    for _ in 0..2 {
        let mut all = Vec::with_capacity(recs.len());
        for p in &pieces {
            all.extend_from_slice(&input.read_piece(p).unwrap());
        }
        assert!(all == recs, "the pieces in order differ from the records");
    }
}

#[test]
fn one_chunk_larger_than_a_piece_decodes_exactly() {
    let dir = tempdir("laz-big-chunk");
    let n = LAZ_PIECE_POINTS as usize + 5_000;
    for (format, rl) in [(3u8, 34usize), (6, 30)] {
        let layout = RecordLayout::new(format, rl).unwrap();
        let recs = records(&layout, n, format as u64);
        let p = dir.join(format!("pdrf{format}.laz"));
        write_laz(&p, layout.clone(), &recs, n as u32);
        let input = LasInput::open(&p).unwrap();
        assert_eq!(input.point_count, n as u64);
        check_pieces(&input, &recs, rl);
        if format == 6 {
            // layers skipped: the kept decoders decode the new selection; skipped bytes read 0
            let mut only = LasInput::open(&p).unwrap();
            only.decode_only(&["intensity"]);
            let piece = only.pieces()[1];
            let got = only.read_piece(&piece).unwrap();
            let s = piece.first_point as usize * rl;
            for (g, r) in got.chunks_exact(rl).zip(recs[s..].chunks_exact(rl)) {
                assert_eq!(&g[..14], &r[..14], "positions and intensity are decoded");
                assert!(g[16..].iter().all(|&b| b == 0), "skipped layers read as zero");
            }
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn several_chunks_larger_than_a_piece_and_small_ones() {
    let dir = tempdir("laz-chunks");
    let layout = RecordLayout::new(3, 34).unwrap();
    let chunk = LAZ_PIECE_POINTS as usize + 100;
    let n = 2 * chunk + 7;
    let recs = records(&layout, n, 9);
    let p = dir.join("chunks.laz");
    // two chunks of a piece and 100 points, each cut in two, and a small last one
    write_laz(&p, layout, &recs, chunk as u32);
    let input = LasInput::open(&p).unwrap();
    assert_eq!(input.pieces().len(), 5);
    check_pieces(&input, &recs, 34);
    std::fs::remove_dir_all(&dir).unwrap();
}
