//! `mortar-bench-gpu`: see [`mortar_app::bench::gpu`] for what it measures.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    mortar_app::bench::gpu::run(mortar_app::bench::gpu::Args::parse())
}
