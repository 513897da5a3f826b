//! `mortar-bench-decode`: the baseline of BENCHMARKS.md. Decodes LAS/LAZ files with the las
//! crate's parallel reader (`fill_points`, raw records, nothing else) and prints the time, so that
//! mortar's conversion can be compared with plain decoding of the same file in the same run.

use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let files: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(!files.is_empty(), "usage: mortar-bench-decode FILE...");
    let start = Instant::now();
    let mut total = 0u64;
    let mut checksum = 0u64;
    for f in &files {
        let mut r = las::Reader::from_path(f)?;
        let mut pd = las::PointDataBuilder::new().for_header(r.header()).build();
        loop {
            let n = r.fill_points(1 << 20, &mut pd)?;
            if n == 0 {
                break;
            }
            total += n;
            // touch the data so the decode cannot be skipped
            checksum = checksum
                .wrapping_add(pd.raw_bytes().iter().step_by(4096).map(|&b| b as u64).sum::<u64>());
        }
    }
    let secs = start.elapsed().as_secs_f64();
    println!(
        "{{\"points\": {total}, \"seconds\": {secs:.4}, \"points_per_second\": {:.0}, \"checksum\": {checksum}}}",
        total as f64 / secs
    );
    Ok(())
}
