//! `mortar-bench-progressive`: see [`mortar_app::bench::progressive_bench`] for what it measures.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    mortar_app::bench::progressive_bench::run(mortar_app::bench::progressive_bench::Args::parse())
}
