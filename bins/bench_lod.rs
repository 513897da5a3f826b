//! `mortar-bench-lod`: see [`mortar_app::bench::lod`] for what it measures.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    mortar_app::bench::lod::run(mortar_app::bench::lod::Args::parse())
}
