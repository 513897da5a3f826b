//! The front door for inputs: the one place that says what kind of input a path is, expands the
//! command line's inputs (directories, glob patterns, stdin) and opens them, as one record source
//! each or merged into a [`Dataset`]. It stands above everything it opens (LAS/LAZ files, batch
//! files, stores), so none of those needs to know the others; every caller that asks "what is
//! this input?" asks here.

use crate::batchfile::{is_batch_file, BatchFile};
use crate::dataset::{Dataset, OpenOptions, RecordSource};
use crate::error::{Error, Result};
use crate::source::LasInput;
use crate::store::{is_store, Store};
use std::path::{Path, PathBuf};

/// What an input path holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InputKind {
    /// `-`: LAS/LAZ bytes on standard input.
    Stdin,
    /// An octree store directory (`mortar build`).
    Store,
    /// A batch file (`mortar batch`), known by its first bytes.
    BatchFile,
    /// Anything else, read as a LAS or LAZ file (which says what is wrong with it, if anything).
    Las,
}

impl InputKind {
    /// The kind of `path`: stdin, a store, a batch file, or LAS/LAZ.
    pub fn of(path: &Path) -> InputKind {
        if path == Path::new("-") {
            InputKind::Stdin
        } else if is_store(path) {
            InputKind::Store
        } else if path.is_file() && is_batch_file(path) {
            InputKind::BatchFile
        } else {
            InputKind::Las
        }
    }

    /// Whether the input is a LAS/LAZ file or stdin (the inputs that are decoded as they are
    /// read, as the progressive renderer draws them).
    pub fn is_las(self) -> bool {
        matches!(self, InputKind::Stdin | InputKind::Las)
    }
}

/// Expands command-line inputs: files as given, stores as given, directories to their
/// `.las`/`.laz` files (sorted, recursive), glob patterns to their matches (sorted), `-` to stdin,
/// `http://` and `https://` URLs to a local copy of the whole file ([`crate::remote`]).
pub fn expand(args: &[String]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for a in args {
        if a == "-" {
            out.push(PathBuf::from("-"));
            continue;
        }
        if crate::remote::is_url(a) {
            let r = crate::remote::Remote::open(a)?;
            r.fetch_all()?;
            out.push(r.path().to_path_buf());
            continue;
        }
        let p = Path::new(a);
        if is_store(p) {
            out.push(p.to_path_buf());
        } else if p.is_dir() {
            let mut found = Vec::new();
            collect_dir(p, &mut found)?;
            if found.is_empty() {
                return Err(Error::NoLasInDirectory { path: p.to_path_buf() });
            }
            found.sort();
            out.extend(found);
        } else if p.exists() {
            out.push(p.to_path_buf());
        } else if a.contains(['*', '?', '[']) {
            let paths =
                glob::glob(a).map_err(|error| Error::BadPattern { pattern: a.clone(), error })?;
            let mut found: Vec<PathBuf> =
                paths.filter_map(|r| r.ok()).filter(|p| p.is_file()).collect();
            if found.is_empty() {
                return Err(Error::NoMatch { pattern: a.clone() });
            }
            found.sort();
            out.extend(found);
        } else {
            return Err(Error::NotFound { path: p.to_path_buf() });
        }
    }
    if out.is_empty() {
        return Err(Error::NoInput);
    }
    Ok(out)
}

fn collect_dir(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    let rd = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    for entry in rd {
        let entry = entry.map_err(|e| Error::io(dir, e))?;
        let p = entry.path();
        if p.is_dir() {
            collect_dir(&p, out)?;
        } else if let Some(ext) = p.extension().and_then(|e| e.to_str()) {
            if ext.eq_ignore_ascii_case("las") || ext.eq_ignore_ascii_case("laz") {
                out.push(p);
            }
        }
    }
    Ok(())
}

/// Opens one input as a record source, with the warnings its reading gave (LAS/LAZ headers
/// that lie, say), each prefixed with the path.
pub fn open_source(path: &Path) -> Result<(Box<dyn RecordSource>, Vec<String>)> {
    Ok(match InputKind::of(path) {
        InputKind::Store => (Box::new(Store::open(path)?), Vec::new()),
        InputKind::BatchFile => (Box::new(BatchFile::open(path)?), Vec::new()),
        InputKind::Stdin | InputKind::Las => {
            let i = LasInput::open(path)?;
            let w = i.meta.warnings.iter().map(|w| format!("{}: {w}", path.display())).collect();
            (Box::new(i), w)
        }
    })
}

/// Opens LAS/LAZ files, batch files and stores and merges them; warnings about each file come
/// first.
pub fn open(paths: &[PathBuf]) -> Result<Dataset> {
    open_with(paths, &OpenOptions::default())
}

/// [`open`] with the user's choices.
pub fn open_with(paths: &[PathBuf], opts: &OpenOptions) -> Result<Dataset> {
    let mut warnings = Vec::new();
    let mut inputs: Vec<Box<dyn RecordSource>> = Vec::new();
    for p in paths {
        let (src, mut w) = open_source(p)?;
        warnings.append(&mut w);
        inputs.push(src);
    }
    let mut ds = Dataset::with_options(inputs, opts)?;
    warnings.append(&mut ds.warnings);
    ds.warnings = warnings;
    Ok(ds)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/autzen_trim.laz")
    }

    #[test]
    fn each_kind_of_input_is_told_apart() {
        let dir = std::env::temp_dir().join(format!("mortar-inputs-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        assert_eq!(InputKind::of(Path::new("-")), InputKind::Stdin);
        assert_eq!(InputKind::of(&sample()), InputKind::Las);
        // A file that is neither is left to the LAS reader, which names what is wrong.
        let junk = dir.join("junk.bin");
        std::fs::write(&junk, b"not a point cloud").unwrap();
        assert_eq!(InputKind::of(&junk), InputKind::Las);
        let e = open_source(&junk).err().expect("junk is refused");
        assert!(e.to_string().contains("junk.bin"), "{e}");
        // A directory of LAS files is not a store; it expands to its files.
        assert_eq!(InputKind::of(&dir), InputKind::Las);
        let copy = dir.join("a.laz");
        std::fs::copy(sample(), &copy).unwrap();
        assert_eq!(expand(&[dir.display().to_string()]).unwrap(), vec![copy.clone()]);
        assert!(matches!(
            expand(&[dir.join("*.nothing").display().to_string()]),
            Err(Error::NoMatch { .. })
        ));
        assert!(matches!(expand(&[]), Err(Error::NoInput)));
        let ds = open(&[copy]).unwrap();
        assert_eq!(ds.declared_points(), 110_000);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
