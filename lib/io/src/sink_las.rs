//! Writing Morton-ordered points as LAS or LAZ, to a file (atomically: temporary name, then
//! rename) or to stdout.

use crate::cleanup::TempPath;
use crate::dataset::SourceMeta;
use crate::error::{Error, Result};
use crate::las::{self, HeaderOut, Vlr};
use crate::sort::{OrderedSink, Summary};
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// Where the output goes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Target {
    File(PathBuf),
    Stdout,
}

impl Target {
    pub fn parse(s: &str) -> Target {
        if s == "-" {
            Target::Stdout
        } else {
            Target::File(PathBuf::from(s))
        }
    }
    pub fn display(&self) -> String {
        match self {
            Target::File(p) => p.display().to_string(),
            Target::Stdout => "<stdout>".into(),
        }
    }
}

enum Out {
    Las(BufWriter<File>),
    Stdout(BufWriter<std::io::Stdout>),
    Laz(Box<laz::ParLasZipCompressor<BufWriter<File>>>),
}

/// A LAS/LAZ writer for [`crate::sort::sort`].
pub struct LasSink {
    target: Target,
    compressed: bool,
    t: SourceMeta,
    /// The file being written (the target itself for LAS/LAZ files; a temporary for LAZ on stdout).
    tmp: Option<TempPath>,
    out: Option<Out>,
    summary: Option<Summary>,
    written: u64,
    /// Points per LAZ chunk (`None`: laz-rs's default, 50,000).
    laz_chunk: Option<u32>,
}

fn io_err(t: &Path) -> impl Fn(std::io::Error) -> Error + '_ {
    move |e| Error::io(t, e)
}

impl LasSink {
    /// `compressed` chooses LAZ; for files it follows the extension unless forced.
    pub fn new(
        target: Target,
        compressed: bool,
        template: SourceMeta,
        tmp_dir: &Path,
    ) -> Result<LasSink> {
        let tmp = match &target {
            Target::File(p) => Some(TempPath::beside(p)),
            Target::Stdout if compressed => {
                std::fs::create_dir_all(tmp_dir).map_err(|e| Error::io(tmp_dir, e))?;
                Some(TempPath::beside(&tmp_dir.join("stdout.laz")))
            }
            Target::Stdout => None,
        };
        Ok(LasSink {
            target,
            compressed,
            t: template,
            tmp,
            out: None,
            summary: None,
            written: 0,
            laz_chunk: None,
        })
    }

    /// Writes LAZ chunks of `points` points (synthetic inputs with huge chunks).
    pub fn laz_chunk_size(&mut self, points: u32) {
        self.laz_chunk = Some(points.max(1));
    }

    /// The LASzip VLR of the output.
    fn laz_vlr(&self) -> Result<laz::LazVlr> {
        let extra = (self.t.layout.record_len
            - mortar_core::layout::base_len(self.t.layout.format).unwrap())
            as u16;
        let mut b = laz::LazVlrBuilder::default()
            .with_point_format(self.t.layout.format, extra)
            .map_err(|error| Error::LazFormat { format: self.t.layout.format, error })?;
        if let Some(n) = self.laz_chunk {
            b = b.with_fixed_chunk_size(n);
        }
        Ok(b.build())
    }

    fn header_bytes(&self, s: &Summary, evlr_start: u64) -> Result<Vec<u8>> {
        let g = &self.t.grid;
        let mut vlrs = self.t.vlrs.clone();
        if self.compressed {
            let v = self.laz_vlr()?;
            let mut data = Vec::new();
            v.write_to(&mut data).map_err(|error| Error::LazSetup { error })?;
            let mut user_id = [0u8; 16];
            user_id[..14].copy_from_slice(b"laszip encoded");
            let mut description = [0u8; 32];
            let d = b"mortar (laz-rs)";
            description[..d.len()].copy_from_slice(d);
            vlrs.push(Vlr { reserved: 0, user_id, record_id: 22204, description, data });
        }
        let world = |a: usize, v: i32| g.offset[a] + g.scale[a] * v as f64;
        // internal waveform data travels as its EVLR: the header points at that record
        let mut template = self.t.header.clone();
        template.waveform_start = 0;
        if evlr_start > 0 && template.global_encoding & 0x2 != 0 {
            let mut at = evlr_start;
            for v in &self.t.evlrs {
                if crate::dataset::is_waveform_data(v) {
                    template.waveform_start = at;
                    break;
                }
                at += 60 + v.data.len() as u64;
            }
        }
        let h = HeaderOut {
            template: &template,
            point_format: self.t.layout.format,
            compressed: self.compressed,
            record_len: self.t.layout.record_len as u16,
            point_count: s.count,
            points_by_return: s.points_by_return,
            scale: g.scale,
            offset: g.offset,
            min: [world(0, s.min[0]), world(1, s.min[1]), world(2, s.min[2])],
            max: [world(0, s.max[0]), world(1, s.max[1]), world(2, s.max[2])],
            vlrs: &vlrs,
            evlr_start,
            evlr_count: if evlr_start > 0 { self.t.evlrs.len() as u32 } else { 0 },
        };
        las::write_header(&h)
            .map_err(|error| Error::Las { path: self.target.display().to_string().into(), error })
    }

    /// Finishes the file: LAZ chunk table, EVLRs, header fix-up, rename into place.
    pub fn finish(mut self) -> Result<u64> {
        let s = self
            .summary
            .clone()
            .ok_or(Error::SinkOrder { what: "sink finished before it began" })?;
        if self.written != s.count {
            return Err(Error::ShortWrite {
                path: self.target.display().to_string().into(),
                written: self.written,
                expected: s.count,
            });
        }
        let evlrs = las::write_evlrs(&self.t.evlrs);
        let has_evlrs = !self.t.evlrs.is_empty() && self.t.header.version.1 >= 4;
        match self.out.take() {
            Some(Out::Stdout(mut w)) => {
                if has_evlrs {
                    w.write_all(&evlrs).map_err(io_err(Path::new("<stdout>")))?;
                }
                w.flush().map_err(io_err(Path::new("<stdout>")))?;
            }
            Some(out) => {
                let tmp = self.tmp.as_ref().expect("file output has a temporary path");
                let p = tmp.path().to_path_buf();
                let mut w = match out {
                    Out::Las(w) => w,
                    Out::Laz(mut c) => {
                        c.done().map_err(|error| Error::LazCompress {
                            path: self.target.display().to_string().into(),
                            error,
                        })?;
                        c.into_inner()
                    }
                    Out::Stdout(_) => unreachable!(),
                };
                if has_evlrs {
                    let at = w.stream_position().map_err(io_err(&p))?;
                    w.write_all(&evlrs).map_err(io_err(&p))?;
                    let hb = self.header_bytes(&s, at)?;
                    w.seek(SeekFrom::Start(0)).map_err(io_err(&p))?;
                    w.write_all(&hb).map_err(io_err(&p))?;
                }
                let f = w.into_inner().map_err(|e| Error::io(&p, e.into_error()))?;
                drop(f);
                let tmp = self.tmp.take().unwrap();
                match &self.target {
                    Target::File(target) => tmp.persist(target).map_err(io_err(target))?,
                    Target::Stdout => {
                        let mut f = File::open(tmp.path()).map_err(io_err(tmp.path()))?;
                        let mut so = std::io::stdout().lock();
                        std::io::copy(&mut f, &mut so).map_err(io_err(Path::new("<stdout>")))?;
                        so.flush().map_err(io_err(Path::new("<stdout>")))?;
                    }
                }
            }
            None => return Err(Error::SinkOrder { what: "sink finished before it began" }),
        }
        Ok(s.count)
    }
}

impl OrderedSink for LasSink {
    fn begin(&mut self, s: &Summary) -> Result<()> {
        self.summary = Some(s.clone());
        let has_evlrs = !self.t.evlrs.is_empty() && self.t.header.version.1 >= 4;
        match (&self.target, self.compressed) {
            (Target::Stdout, false) => {
                // the EVLR position is known up front: right after the points
                let hb0 = self.header_bytes(s, 0)?;
                let evlr_start = if has_evlrs {
                    hb0.len() as u64 + s.count * self.t.layout.record_len as u64
                } else {
                    0
                };
                let hb = self.header_bytes(s, evlr_start)?;
                let mut w = BufWriter::with_capacity(1 << 20, std::io::stdout());
                w.write_all(&hb).map_err(io_err(Path::new("<stdout>")))?;
                self.out = Some(Out::Stdout(w));
            }
            _ => {
                let p = self.tmp.as_ref().unwrap().path().to_path_buf();
                let f = File::create(&p).map_err(io_err(&p))?;
                let mut w = BufWriter::with_capacity(1 << 20, f);
                let hb = self.header_bytes(s, 0)?;
                w.write_all(&hb).map_err(io_err(&p))?;
                if self.compressed {
                    let vlr = self.laz_vlr()?;
                    let c = laz::ParLasZipCompressor::new(w, vlr)
                        .map_err(|e| Error::LazSetup { error: std::io::Error::other(e) })?;
                    self.out = Some(Out::Laz(Box::new(c)));
                } else {
                    self.out = Some(Out::Las(w));
                }
            }
        }
        Ok(())
    }

    fn write(&mut self, records: &[u8]) -> Result<()> {
        let n = (records.len() / self.t.layout.record_len) as u64;
        let target = self.target.display();
        match self.out.as_mut() {
            Some(Out::Las(w)) => w.write_all(records).map_err(|e| Error::io(&target, e))?,
            Some(Out::Stdout(w)) => w.write_all(records).map_err(|e| Error::io(&target, e))?,
            Some(Out::Laz(c)) => c.compress_many(records).map_err(|e| Error::io(&target, e))?,
            None => return Err(Error::SinkOrder { what: "write before begin" }),
        }
        self.written += n;
        Ok(())
    }
}
