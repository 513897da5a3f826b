//! `mortar build`: the octree LOD store of paper 004 (`lib/io/STORE_FORMAT.md`). The options and
//! the command are `mortar_app::build`'s; this prints what it did.

pub use mortar_app::build::Args;

pub fn run(a: Args) -> anyhow::Result<()> {
    let out = mortar_app::build::run(&a)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&out.json)?);
    } else if let Some(line) = out.line {
        eprintln!("{line}");
    }
    Ok(())
}
