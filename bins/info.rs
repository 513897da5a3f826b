//! `mortar info`: describe inputs, as text or as JSON (`docs/info-json.md`).

use anyhow::Result;
use mortar_app::cli as common;
use mortar_io::batchfile::BatchFile;
use mortar_io::info::{describe, FileInfo};
use mortar_io::inputs::{self, InputKind};
use mortar_io::source::LasInput;
use std::io::Write;
use std::path::Path;

#[derive(clap::Args)]
pub struct Args {
    /// LAS/LAZ files, batch files, directories, glob patterns, or - for stdin.
    #[arg(required = true)]
    pub inputs: Vec<String>,
    /// One JSON document on stdout: an array with one object per input.
    #[arg(long)]
    pub json: bool,
    /// Read every point: real bounds, attribute ranges, class and return counts.
    #[arg(long)]
    pub stats: bool,
}

fn info_of(p: &Path, stats: bool) -> Result<FileInfo> {
    match InputKind::of(p) {
        InputKind::Store => {
            let s = mortar_io::store::Store::open(p)?;
            let mut info = describe(&s, "store", stats, None)?;
            info.store = Some(mortar_io::info::store_info(&s));
            return Ok(info);
        }
        InputKind::BatchFile => {
            let b = BatchFile::open(p)?;
            return Ok(describe(&b, "batch", stats, Some(&b))?);
        }
        InputKind::Stdin | InputKind::Las => {}
    }
    let i = LasInput::open(p)?;
    let mut info = describe(&i, if i.is_laz() { "laz" } else { "las" }, stats, None)?;
    info.hierarchy = mortar_io::info::copc_summary(&i);
    let mut w = i.meta.warnings.clone();
    w.append(&mut info.warnings);
    info.warnings = w;
    Ok(info)
}

pub fn run(a: Args) -> Result<()> {
    // An EPT directory is described as one input (its hierarchy); anything else file by file.
    let mut infos = Vec::new();
    for input in &a.inputs {
        if let Some(dir) = mortar_io::ept::ept_dir(Path::new(input)) {
            let (info, warning) = mortar_io::info::ept_info(&dir)?;
            if let Some(w) = warning {
                common::warn(&w);
            }
            if let Some(info) = info {
                infos.push(info);
                continue;
            }
        }
        for p in inputs::expand(std::slice::from_ref(input))? {
            infos.push(info_of(&p, a.stats)?);
        }
    }
    let mut out = std::io::stdout().lock();
    if a.json {
        serde_json::to_writer_pretty(&mut out, &infos)?;
        writeln!(out)?;
        return Ok(());
    }
    for i in &infos {
        for w in &i.warnings {
            common::warn(&format!("{}: {w}", i.path));
        }
        print_text(&mut out, i)?;
    }
    Ok(())
}

fn print_text(o: &mut impl Write, i: &FileInfo) -> std::io::Result<()> {
    writeln!(o, "{}", i.path)?;
    writeln!(
        o,
        "  kind            {} (LAS {}, point format {}, {} bytes per point)",
        i.kind, i.version, i.point_format, i.record_length
    )?;
    writeln!(o, "  points          {}", i.point_count)?;
    let by_ret: Vec<String> =
        i.points_by_return.iter().take_while(|&&c| c > 0).map(|c| c.to_string()).collect();
    if !by_ret.is_empty() {
        writeln!(o, "  by return       {}", by_ret.join(" "))?;
    }
    writeln!(o, "  scale           {} {} {}", i.scale[0], i.scale[1], i.scale[2])?;
    writeln!(o, "  offset          {} {} {}", i.offset[0], i.offset[1], i.offset[2])?;
    writeln!(o, "  header bounds   {}", bounds_text(&i.header_bounds, i.scale))?;
    writeln!(o, "  crs             {}", i.crs.summary())?;
    writeln!(o, "  software        {} / {}", i.generating_software, i.system_identifier)?;
    let names: Vec<&str> = i.attributes.iter().map(|a| a.name.as_str()).collect();
    writeln!(o, "  attributes      {}", names.join(", "))?;
    for e in &i.extra_bytes {
        writeln!(o, "  extra bytes     {} ({}) {}", e.name, e.data_type, e.description)?;
    }
    for v in &i.vlrs {
        writeln!(
            o,
            "  vlr             {} {} ({} bytes) {}",
            v.user_id, v.record_id, v.length, v.description
        )?;
    }
    for v in &i.evlrs {
        writeln!(
            o,
            "  evlr            {} {} ({} bytes) {}",
            v.user_id, v.record_id, v.length, v.description
        )?;
    }
    if let Some(b) = &i.batch {
        writeln!(
            o,
            "  batches         {} ({} to {} points), compression {}",
            b.batch_count, b.smallest_batch, b.largest_batch, b.compression
        )?;
        let h: Vec<String> =
            b.bits_histogram.iter().map(|(k, v)| format!("{k} bits: {v}")).collect();
        writeln!(o, "  batch bits      {}", h.join(", "))?;
        writeln!(
            o,
            "  colour          {}{}",
            b.color_source,
            b.rgb_bits.map(|x| format!(" ({x}-bit)")).unwrap_or_default()
        )?;
        if !b.dropped_attributes.is_empty() {
            writeln!(o, "  dropped         {}", b.dropped_attributes.join(", "))?;
        }
    }
    if let Some(s) = &i.store {
        writeln!(o, "  octree          {} nodes: {} leaves ({} empty, largest {} points, capacity {}), {} inner nodes with {} voxels, depth {}", s.nodes, s.leaves, s.empty_leaves, s.largest_leaf, s.leaf_capacity, s.inner_nodes, s.voxels, s.depth)?;
        writeln!(
            o,
            "  store           commit {}, {} bytes of node payloads",
            s.commit, s.nodes_bytes
        )?;
    }
    if let Some(c) = &i.hierarchy {
        match &c.error {
            Some(e) => writeln!(o, "  {:<15} hierarchy not usable: {e}", c.format)?,
            None => {
                writeln!(
                    o,
                    "  {:<15} {} nodes, {} points in {} levels ({} hierarchy pages), spacing {}",
                    c.format,
                    c.nodes,
                    c.points,
                    c.levels.len(),
                    c.hierarchy_pages,
                    c.spacing
                )?;
                for l in &c.levels {
                    writeln!(
                        o,
                        "    level {:<3}     {} nodes, {} points",
                        l.level, l.nodes, l.points
                    )?;
                }
            }
        }
    }
    if let Some(s) = &i.stats {
        writeln!(o, "  real bounds     {}", bounds_text(&s.bounds, i.scale))?;
        for (k, r) in &s.ranges {
            writeln!(o, "  {:<15} [{}, {}]", k, r.min, r.max)?;
        }
        let c: Vec<String> =
            s.classification_counts.iter().map(|(k, v)| format!("{k}: {v}")).collect();
        writeln!(o, "  classes         {}", c.join(", "))?;
        let r: Vec<String> = s.return_counts.iter().map(|(k, v)| format!("{k}: {v}")).collect();
        writeln!(o, "  returns         {}", r.join(", "))?;
    }
    Ok(())
}

/// `x [min, max]  y [...]  z [...]` with as many decimals as each axis's scale has.
fn bounds_text(b: &mortar_io::info::Bounds, scale: [f64; 3]) -> String {
    (0..3)
        .map(|a| {
            let d = mortar_io::info::grid_decimals(scale[a]);
            format!("{} [{:.d$}, {:.d$}]", ["x", "y", "z"][a], b.min[a], b.max[a])
        })
        .collect::<Vec<_>>()
        .join("  ")
}
