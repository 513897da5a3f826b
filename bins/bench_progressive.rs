//! `mortar-bench-progressive`: see [`mortar_app::bench::progressive`] for what it measures.

use clap::Parser;

fn main() -> anyhow::Result<()> {
    mortar_app::bench::progressive::run(mortar_app::bench::progressive::Args::parse())
}
