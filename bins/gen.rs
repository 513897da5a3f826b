//! `mortar-gen`: writes a seeded synthetic scan as LAS/LAZ, for benchmarks larger than any fixture.
//!
//! `mortar-gen --points 20000000 --seed 1 -o bench-data/synth-20m.las`

use anyhow::Result;
use clap::{Parser, ValueEnum};
use mortar_io::synth::{self, Shape, SynthOptions};

/// Where the points are (`synth::Shape`).
#[derive(Clone, Copy, ValueEnum)]
enum ShapeArg {
    Airborne,
    Coincident,
    Cube,
    Duplicates,
}

#[derive(Parser)]
#[command(
    name = "mortar-gen",
    about = "Seeded synthetic airborne-like scan (LAS point format 3), or a hostile shape for memory tests"
)]
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
    /// airborne (default), coincident (every point at one position), cube (uniform),
    /// duplicates (every record eight times).
    #[arg(long, value_enum, default_value = "airborne")]
    shape: ShapeArg,
    /// Extra bytes per point (0-255), described by an Extra Bytes VLR.
    #[arg(long, default_value_t = 0)]
    extra_bytes: usize,
    /// Points per LAZ chunk (default 50,000; the point count gives one chunk for the file).
    #[arg(long)]
    laz_chunk: Option<u32>,
    #[arg(short, long)]
    output: String,
}

fn main() -> Result<()> {
    let a = Args::parse();
    anyhow::ensure!(a.origin.len() == 3, "--origin takes x,y,z");
    anyhow::ensure!(a.extent / a.scale < 2.0e9, "extent / scale must fit a 32-bit LAS integer");
    anyhow::ensure!(a.extra_bytes <= 255, "--extra-bytes takes 0 to 255");
    let shape = match a.shape {
        ShapeArg::Airborne => Shape::Airborne,
        ShapeArg::Coincident => Shape::Coincident,
        ShapeArg::Cube => Shape::Cube,
        ShapeArg::Duplicates => Shape::Duplicates,
    };
    let o = SynthOptions {
        points: a.points,
        seed: a.seed,
        extent: a.extent,
        scale: a.scale,
        origin: [a.origin[0], a.origin[1], a.origin[2]],
        shape,
        extra_bytes: a.extra_bytes,
    };
    synth::write_file(&o, &a.output, a.laz_chunk)?;
    Ok(())
}
