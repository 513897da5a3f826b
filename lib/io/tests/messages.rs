//! The messages of mortar-io's typed errors are those mortar printed before they were typed
//! (users and the binary's tests look for them): a sample of each kind, spelled out in full.

use mortar_io::error::*;
use mortar_io::las;
use std::path::PathBuf;

fn p(s: &str) -> PathBuf {
    PathBuf::from(s)
}

#[test]
fn messages_begin_with_the_path_and_keep_their_wording() {
    let cases: Vec<(Error, &str)> = vec![
        (Error::NotFound { path: p("a.las") }, "a.las: no such file or directory"),
        (Error::NoInput, "no input given"),
        (Error::Las { path: p("a.las"), error: LasError::NoSignature }, "a.las: not a LAS/LAZ file (no LASF signature)"),
        (
            Error::Las { path: p("a.las"), error: LasError::Evlr { index: 2, error: Box::new(LasError::EvlrTooLong { len: 9 }) } },
            "a.las: EVLR 2: claims 9 bytes, more than the file holds",
        ),
        (
            Error::Truncated { path: p("a.las"), declared: 10, available: 4, bytes: 80, record_len: 20 },
            "a.las: header says 10 points but the file holds only 4 (80 bytes of point data, 20 per point): truncated or damaged",
        ),
        (Error::Laz { path: p("a.laz"), error: LazError::BadTable { error: None } }, "a.laz: LAZ chunk table is corrupt"),
        (
            Error::Laz { path: p("a.laz"), error: LazError::BadTable { error: Some(std::io::Error::other("short")) } },
            "a.laz: LAZ chunk table is corrupt: short",
        ),
        (
            Error::Laz { path: p("a.laz"), error: LazError::ChunkLayers { chunk: 3, total: 100, room: 7 } },
            "a.laz: LAZ chunk 3 is corrupt: its layers claim 100 bytes but 7 follow",
        ),
        (
            Error::CrsConflict { path: p("b.las"), crs: "EPSG:1".into(), first: p("a.las"), first_crs: "EPSG:2".into() },
            "b.las: its CRS, EPSG:1, differs from that of a.las, EPSG:2; refusing to merge them (reproject one, or choose with --assign-crs FILE|EPSG:CODE)",
        ),
        (
            Error::AssignCrsFile { error: Box::new(Error::Las { path: p("c.las"), error: LasError::Version { major: 2, minor: 0 } }) },
            "c.las: --assign-crs: unsupported LAS version 2.0",
        ),
        (
            Error::KeptCommit { error: Box::new(Error::io("s/nodes.bin", std::io::Error::other("disk full"))), store: p("s"), commit: 3 },
            "s/nodes.bin: disk full; the store s keeps its last commit (commit 3), readable; `mortar build --resume` continues it",
        ),
        (
            Error::Store { path: p("s/nodes.bin"), error: StoreError::PayloadCount { node: 4, held: 2, saved: Some(3) } },
            "s/nodes.bin: node 4: the last payload holds 2 points, Some(3) were saved",
        ),
        (
            Error::Payload { path: p("s/nodes.bin"), error: PayloadError::InNode { node: "7".into(), error: Box::new(PayloadError::Damaged) } },
            "s/nodes.bin: node 7: damaged payload",
        ),
        (
            Error::Plan { path: p("a.las"), error: PlanError::OutsideBox { min: [0; 3], max: [9; 3], lo: [1; 3], hi: [8; 3], scanned: false } },
            "a.las: its points reach outside the box the plan took for it ([0, 0, 0] .. [9, 9, 9] against [1, 1, 1] .. [8, 8, 8] on the grid) (its header's bounds are wrong); plan again with --scan",
        ),
        (
            Error::Job { error: JobError::MissingParts { jobs: 3, first: 1, missing: vec![1, 2] } },
            "the plan has 3 jobs and part 1 is missing (missing: [1, 2]); run those jobs and merge all parts",
        ),
        (
            Error::Render { path: p("f.mbat"), error: RenderError::NoColour { format: 1, has_rgb: false } },
            "f.mbat: --color rgb: the points have no colour (the point format has no RGB, point format 1); try --color intensity",
        ),
        (
            Error::Render { path: p("f.mbat"), error: RenderError::MissingAttribute { mode: "gps-time", attribute: "gps_time", format: 0, not_kept: false } },
            "f.mbat: --color gps-time: needs the attribute 'gps_time', but point format 0 has no such field",
        ),
        (
            Error::Render { path: p("f.mbat"), error: RenderError::MissingAttribute { mode: "intensity", attribute: "intensity", format: 0, not_kept: true } },
            "f.mbat: --color intensity: needs the attribute 'intensity', but it was not kept when the batch file was written (batch again with --attributes all)",
        ),
        (Error::ThreadPanicked { thread: "a page-in" }, "a page-in thread panicked"),
        (Error::TooManyPoints { what: "sort" }, "too many points for one in-memory sort"),
    ];
    for (e, want) in cases {
        assert_eq!(e.to_string(), want);
    }
}

#[test]
fn paths_are_found_renamed_and_stripped() {
    let e = Error::Batch { path: p("/tmp/x/input.mbat"), error: BatchError::NotBatchFile };
    assert_eq!(e.path(), Some(p("/tmp/x/input.mbat").as_path()));
    assert_eq!(e.problem(), "not a mortar batch file");
    let e = e.renamed(&p("/tmp/x/input.mbat"), &p("a.las b.las"));
    assert_eq!(e.to_string(), "a.las b.las: not a mortar batch file");
    assert_eq!(Error::NoInput.path(), None);
}

#[test]
fn the_las_parser_says_why() {
    assert!(matches!(las::parse(b"LASF"), Err(LasError::TooShort { len: 4 })));
    assert_eq!(
        las::parse(b"nope").unwrap_err().to_string(),
        "not a LAS/LAZ file (no LASF signature)"
    );
}
