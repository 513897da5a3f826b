//! `mortar-bench-render`: see [`mortar_app::bench::render`] for what it measures.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    mortar_app::bench::render::run(mortar_app::bench::render::Args::parse())
}
