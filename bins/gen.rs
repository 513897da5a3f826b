//! `mortar-gen`: writes a seeded synthetic scan as LAS/LAZ, for benchmarks larger than any fixture.
//!
//! `mortar-gen --points 20000000 --seed 1 -o bench-data/synth-20m.las`

use anyhow::Result;
use clap::Parser;
use mortar_io::las::Header;
use mortar_io::dataset::SourceMeta;
use mortar_io::sink_las::{LasSink, Target};
use mortar_io::sort::{OrderedSink, PieceStats};
use mortar_io::synth::{self, SynthOptions};

#[derive(Parser)]
#[command(name = "mortar-gen", about = "Seeded synthetic airborne-like scan (LAS point format 3)")]
struct Args {
    #[arg(long, default_value_t = 1_000_000)]
    points: u64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Side of the square scene in metres.
    #[arg(long, default_value_t = 1000.0)]
    extent: f64,
    #[arg(long, default_value_t = 0.001)]
    scale: f64,
    /// World x,y,z of the scene corner, e.g. 6400000,0,0 for ECEF-scale coordinates.
    #[arg(long, default_value = "500000,5000000,0", value_delimiter = ',')]
    origin: Vec<f64>,
    #[arg(short, long)]
    output: String,
}

fn main() -> Result<()> {
    let a = Args::parse();
    anyhow::ensure!(a.origin.len() == 3, "--origin takes x,y,z");
    let o = SynthOptions { points: a.points, seed: a.seed, extent: a.extent, scale: a.scale, origin: [a.origin[0], a.origin[1], a.origin[2]] };
    anyhow::ensure!(a.extent / a.scale < 2.0e9, "extent / scale must fit a 32-bit LAS integer");
    let header: Header = synth::header(&o);
    let layout = mortar_core::layout::RecordLayout::new(3, 34)?;
    let grid = mortar_core::grid::Grid { scale: header.scale, offset: header.offset };
    let template = SourceMeta { header, vlrs: Vec::new(), evlrs: Vec::new(), layout, grid };
    let compressed = a.output.to_ascii_lowercase().ends_with(".laz");
    let mut sink = LasSink::new(Target::parse(&a.output), compressed, template, &std::env::temp_dir())?;
    // statistics first (the header needs bounds), then the points
    let step = 1u64 << 22;
    let mut total = PieceStats::default();
    let mut first = 0;
    while first < o.points {
        let n = step.min(o.points - first);
        total.merge(&synth::records(&o, first, n).1);
        first += n;
    }
    sink.begin(&total.summary())?;
    let mut first = 0;
    while first < o.points {
        let n = step.min(o.points - first);
        sink.write(&synth::records(&o, first, n).0)?;
        first += n;
    }
    sink.finish()?;
    Ok(())
}
