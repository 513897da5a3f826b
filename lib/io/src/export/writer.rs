//! The writer of the format asked for, behind [`NodeWriter`]: where the export's two paths (in
//! memory and through run files) meet the two formats.

use super::nodes::{Frame, NodeWriter};
use super::options::{ExportFormat, ExportReport};
use super::{copc, potree, tiles3d};
use crate::dataset::Dataset;
use crate::error::Result;
use crate::sort::PieceStats;
use std::path::Path;

/// Opens the writer of `format` at `out` for the nodes of `frame`.
pub(crate) fn open_writer<'a>(
    ds: &'a Dataset,
    frame: Frame,
    out: &Path,
    format: ExportFormat,
    stats: &PieceStats,
    report: &mut ExportReport,
) -> Result<Box<dyn NodeWriter + 'a>> {
    Ok(match format {
        ExportFormat::Copc => {
            Box::new(copc::CopcWriter::create(ds, frame, out, &mut report.warnings)?)
        }
        ExportFormat::Potree => Box::new(potree::PotreeWriter::create(ds, frame, out)?),
        ExportFormat::Tiles3d => {
            Box::new(tiles3d::Tiles3dWriter::create(ds, frame, out, stats, &mut report.warnings)?)
        }
    })
}
