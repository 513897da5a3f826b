//! Inputs over HTTP and HTTPS (issue 30 §2), first form: a URL is read into a local sparse copy
//! (a temporary file as long as the remote one, holes where nothing was fetched), which every
//! reader then maps like any file.
//!
//! - A COPC file is read with range requests ([`Remote::fetch`]): the header and VLRs, the LAZ
//!   chunk table and the EVLRs (where COPC keeps its hierarchy) when it is opened
//!   ([`Remote::fetch_las_index`]), then only the chunks of the nodes a view selects
//!   ([`crate::lod_source::LodSource::dataset`], [`FETCHERS`] requests in flight, [`in_parallel`]);
//!   a view's loader threads fetch in parallel.
//! - Any other input (LAS, LAZ, a COPC file read flat) is fetched whole, in ranges of
//!   [`PIECE`] bytes streamed to the copy (not held in memory), before it is read.
//! - Every response is checked: the status (404, 403 and the others are one-line errors naming
//!   the URL), `Content-Range` against the range asked for, the body's length against the range
//!   (a body that ends early is an error), and the ETag (else Last-Modified) against the one the
//!   first response gave (a file changed between requests is an error). Transport errors, 5xx
//!   and 429 are retried 3 times with backoff (0.25, 0.5, 1 s); connections time out after 10 s,
//!   reads after 30 s.
//! - A server that ignores `Range` (answers 200 with the whole body) is read whole from that
//!   first answer, with a warning.
//! - The copies live in a temporary directory removed when the process ends normally or on
//!   Ctrl-C ([`crate::cleanup`]). `bytes_fetched` counts what came over the network.
//!
//! An EPT directory over HTTP (`…/ept.json` or `…/`) is read file by file: `ept.json` and the
//! hierarchy files whole when it is opened, each node's LAZ file whole when a view selects it
//! ([`FETCHERS`] at a time).
//!
//! Not done yet: a cache bounded below
//! the file's size (the copy holds what was fetched; its pages are the OS's page cache), and
//! plain LAS/LAZ decoded while they download (they are fetched whole first).

use crate::error::{Error, Result};
use std::collections::HashMap;
use std::io::Read;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

/// Bytes per range request when a whole file is fetched.
pub const PIECE: u64 = 16 << 20;

/// Whether `s` is an `http://` or `https://` URL.
pub fn is_url(s: &str) -> bool {
    let l = s.get(..8).unwrap_or(s).to_ascii_lowercase();
    l.starts_with("http://") || l.starts_with("https://")
}

/// A remote file and its local sparse copy.
#[derive(Debug)]
pub struct Remote {
    url: String,
    len: u64,
    /// ETag, else Last-Modified, of the first response.
    validator: Option<String>,
    file: std::fs::File,
    path: PathBuf,
    /// Byte ranges of the copy that were fetched (sorted, merged).
    have: Mutex<Vec<(u64, u64)>>,
    fetched: AtomicU64,
    agent: ureq::Agent,
}

/// The remotes opened by this process, by URL (a URL named twice is fetched once).
fn opened() -> &'static Mutex<HashMap<String, Arc<Remote>>> {
    static OPENED: OnceLock<Mutex<HashMap<String, Arc<Remote>>>> = OnceLock::new();
    OPENED.get_or_init(Default::default)
}

/// The directory of this process's copies (registered for removal).
fn copies_dir() -> Result<PathBuf> {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    if let Some(d) = DIR.get() {
        return Ok(d.clone());
    }
    let d = std::env::temp_dir().join(format!("mortar-http-{}", std::process::id()));
    std::fs::create_dir_all(&d).map_err(|e| Error::io(&d, e))?;
    // Registered for Ctrl-C and error exits; `remove_copies` at the end of a command.
    std::mem::forget(crate::cleanup::TempPath::adopt(d.clone()));
    Ok(DIR.get_or_init(|| d).clone())
}

/// An error about `url`.
fn http_error(url: &str, why: impl std::fmt::Display) -> Error {
    Error::Http { path: PathBuf::from(url), why: why.to_string() }
}

/// Bytes fetched from the URLs under `base` (an EPT directory's files).
pub fn fetched_under(base: &Path) -> u64 {
    let base = base.to_string_lossy();
    let opened = opened().lock().unwrap_or_else(|e| e.into_inner());
    opened.iter().filter(|(u, _)| u.starts_with(&*base)).map(|(_, r)| r.bytes_fetched()).sum()
}

/// `text` with the paths of this process's local copies replaced by their URLs (for messages).
pub fn with_urls(text: &str) -> String {
    let mut t = text.to_string();
    for (url, r) in opened().lock().unwrap_or_else(|e| e.into_inner()).iter() {
        t = t.replace(&r.path.display().to_string(), url);
    }
    t
}

/// Requests in flight at once when many ranges or files are fetched together.
pub const FETCHERS: usize = 8;

/// Runs `f` on every item, [`FETCHERS`] at a time on their own threads (HTTP requests wait on
/// the network, not on a core); the first error is returned.
pub fn in_parallel<T: Sync>(items: &[T], f: impl Fn(&T) -> Result<()> + Sync) -> Result<()> {
    if items.len() <= 1 {
        return items.iter().try_for_each(&f);
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    let failed: Mutex<Option<Error>> = Mutex::new(None);
    std::thread::scope(|s| {
        for _ in 0..FETCHERS.min(items.len()) {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                if i >= items.len() || failed.lock().unwrap_or_else(|e| e.into_inner()).is_some() {
                    return;
                }
                if let Err(e) = f(&items[i]) {
                    failed.lock().unwrap_or_else(|e| e.into_inner()).get_or_insert(e);
                }
            });
        }
    });
    match failed.into_inner().unwrap_or_else(|e| e.into_inner()) {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// Removes this process's copies (at the end of a command).
pub fn remove_copies() {
    let d = std::env::temp_dir().join(format!("mortar-http-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(d);
}

impl Remote {
    /// Opens `url` (once per process: the same [`Remote`] is returned again): one request for
    /// its first byte tells its length, its validator and whether the server honours ranges.
    pub fn open(url: &str) -> Result<Arc<Remote>> {
        if let Some(r) = opened().lock().unwrap_or_else(|e| e.into_inner()).get(url) {
            return Ok(r.clone());
        }
        let agent = ureq::AgentBuilder::new()
            .timeout_connect(Duration::from_secs(10))
            .timeout_read(Duration::from_secs(30))
            .build();
        let resp = with_retries(url, || agent.get(url).set("Range", "bytes=0-0"))?;
        let validator = validator_of(&resp);
        let name: String = url
            .rsplit('/')
            .next()
            .filter(|n| !n.is_empty())
            .unwrap_or("input")
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() || ".-_".contains(c) { c } else { '_' })
            .collect();
        let n = opened().lock().unwrap_or_else(|e| e.into_inner()).len();
        let path = copies_dir()?.join(format!("{n}-{name}"));
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        let remote = match resp.status() {
            206 => {
                let len = content_range(&resp)
                    .and_then(|(a, b, t)| (a == 0 && b == 0).then_some(t).flatten())
                    .ok_or_else(|| {
                        http_error(url, "the server's answer to a range request gives no length")
                    })?;
                file.set_len(len).map_err(|e| Error::io(&path, e))?;
                let r = Remote {
                    url: url.to_string(),
                    len,
                    validator,
                    file,
                    path,
                    have: Mutex::new(Vec::new()),
                    fetched: AtomicU64::new(1),
                    agent,
                };
                r.write_at(0, &[resp_body(url, resp, 1)?[0]])?;
                r.add(0, 1);
                r
            }
            _ => {
                // The whole file came: the server ignores Range.
                eprintln!(
                    "mortar: warning: {url}: the server ignores range requests; reading it whole"
                );
                let mut r = Remote {
                    url: url.to_string(),
                    len: 0,
                    validator,
                    file,
                    path,
                    have: Mutex::new(Vec::new()),
                    fetched: AtomicU64::new(0),
                    agent,
                };
                let announced = resp.header("Content-Length").and_then(|v| v.parse::<u64>().ok());
                let got = r.copy_body(0, resp, announced)?;
                r.len = got;
                r.add(0, got);
                r
            }
        };
        let r = Arc::new(remote);
        opened().lock().unwrap_or_else(|e| e.into_inner()).insert(url.to_string(), r.clone());
        Ok(r)
    }

    /// The remote of `url` if this process opened it.
    pub fn opened(url: &str) -> Option<Arc<Remote>> {
        opened().lock().unwrap_or_else(|e| e.into_inner()).get(url).cloned()
    }

    /// The URL.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The local copy's path (read it only where [`fetch`](Self::fetch) filled it).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bytes of the remote file.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether the remote file is empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Bytes fetched over the network so far.
    pub fn bytes_fetched(&self) -> u64 {
        self.fetched.load(Ordering::Relaxed)
    }

    fn add(&self, off: u64, len: u64) {
        let mut h = self.have.lock().unwrap_or_else(|e| e.into_inner());
        h.push((off, off + len));
        h.sort_unstable();
        let mut merged: Vec<(u64, u64)> = Vec::with_capacity(h.len());
        for &(a, b) in h.iter() {
            match merged.last_mut() {
                Some(l) if a <= l.1 => l.1 = l.1.max(b),
                _ => merged.push((a, b)),
            }
        }
        *h = merged;
    }

    /// The parts of `off..off + len` not fetched yet.
    fn missing(&self, off: u64, len: u64) -> Vec<(u64, u64)> {
        let h = self.have.lock().unwrap_or_else(|e| e.into_inner());
        let (mut at, end) = (off, off + len);
        let mut out = Vec::new();
        for &(a, b) in h.iter() {
            if b <= at {
                continue;
            }
            if a >= end {
                break;
            }
            if a > at {
                out.push((at, a));
            }
            at = at.max(b);
        }
        if at < end {
            out.push((at, end));
        }
        out
    }

    fn write_at(&self, off: u64, b: &[u8]) -> Result<()> {
        self.file.write_all_at(b, off).map_err(|e| Error::io(&self.path, e))
    }

    /// Streams a response body into the copy at `off`; checks it against `announced` bytes.
    fn copy_body(&self, off: u64, resp: ureq::Response, announced: Option<u64>) -> Result<u64> {
        let mut reader = resp.into_reader();
        let mut buf = vec![0u8; 1 << 20];
        let mut at = off;
        loop {
            let n = reader.read(&mut buf).map_err(|e| {
                let got = at - off;
                http_error(
                    &self.url,
                    match announced {
                        Some(a) => {
                            format!("the body ended after {got} of the {a} bytes announced ({e})")
                        }
                        None => format!("reading the body failed after {got} bytes: {e}"),
                    },
                )
            })?;
            if n == 0 {
                break;
            }
            self.write_at(at, &buf[..n])?;
            at += n as u64;
            self.fetched.fetch_add(n as u64, Ordering::Relaxed);
        }
        let got = at - off;
        if let Some(a) = announced {
            if got != a {
                return Err(http_error(
                    &self.url,
                    format!("the body ended after {got} of the {a} bytes announced"),
                ));
            }
        }
        Ok(got)
    }

    /// Makes `off..off + len` of the copy (clamped to the file) the remote file's bytes: the
    /// parts not fetched yet are asked for with range requests and checked (module docs).
    pub fn fetch(&self, off: u64, len: u64) -> Result<()> {
        let end = off.saturating_add(len).min(self.len);
        if off >= end {
            return Ok(());
        }
        for (a, b) in self.missing(off, end - off) {
            let mut at = a;
            while at < b {
                let e = (at + PIECE).min(b);
                self.fetch_range(at, e)?;
                at = e;
            }
        }
        Ok(())
    }

    /// Fetches the whole file.
    pub fn fetch_all(&self) -> Result<()> {
        self.fetch(0, self.len)
    }

    fn fetch_range(&self, a: u64, b: u64) -> Result<()> {
        let url = &self.url;
        let range = format!("bytes={a}-{}", b - 1);
        let resp = with_retries(url, || self.agent.get(url).set("Range", &range))?;
        if resp.status() != 206 {
            return Err(http_error(
                url,
                format!("asked for {range}, the server answered {} without it", resp.status()),
            ));
        }
        match content_range(&resp) {
            Some((x, y, t)) if x == a && y == b - 1 && t.is_none_or(|t| t == self.len) => {}
            other => {
                return Err(http_error(
                    url,
                    format!("asked for {range} of {} bytes, the server sent {other:?}", self.len),
                ))
            }
        }
        if let (Some(was), Some(now)) = (&self.validator, validator_of(&resp)) {
            if *was != now {
                return Err(http_error(
                    url,
                    format!("the file changed while it was read ({was} became {now})"),
                ));
            }
        }
        self.copy_body(a, resp, Some(b - a))?;
        self.add(a, b - a);
        Ok(())
    }

    /// Fetches what opening the copy as a LAS/LAZ file reads: the header and VLRs, the first 8
    /// bytes of the point data (a LAZ file's chunk table offset), the chunk table and the EVLRs.
    pub fn fetch_las_index(&self) -> Result<()> {
        self.fetch(0, 375)?;
        let mut h = [0u8; 375];
        let n = self.file.read_at(&mut h, 0).map_err(|e| Error::io(&self.path, e))?;
        if n < 227 || &h[..4] != b"LASF" {
            // Not LAS: the readers say what it is from the whole file.
            return self.fetch_all();
        }
        let u32_at = |o: usize| u32::from_le_bytes(h[o..o + 4].try_into().expect("4"));
        let u64_at = |o: usize| u64::from_le_bytes(h[o..o + 8].try_into().expect("8"));
        let point_data = u32_at(96) as u64;
        self.fetch(0, point_data + 8)?;
        let (evlr_start, evlrs) =
            if h[25] >= 4 && n >= 247 { (u64_at(235), u32_at(243)) } else { (0, 0) };
        let compressed = h[104] & 0x80 != 0;
        let mut tail_from =
            if evlrs > 0 && evlr_start > point_data { evlr_start } else { self.len };
        if compressed {
            let mut t = [0u8; 8];
            self.file.read_at(&mut t, point_data).map_err(|e| Error::io(&self.path, e))?;
            let table = i64::from_le_bytes(t);
            if table > point_data as i64 && (table as u64) < self.len {
                tail_from = tail_from.min(table as u64);
            } else {
                // No chunk table offset (a writer that did not finish it): read it all.
                return self.fetch_all();
            }
        }
        self.fetch(tail_from, self.len - tail_from.min(self.len))
    }
}

/// `(first, last, total)` of a `Content-Range: bytes A-B/T` header (`T` may be `*`).
fn content_range(resp: &ureq::Response) -> Option<(u64, u64, Option<u64>)> {
    let v = resp.header("Content-Range")?.trim();
    let v = v.strip_prefix("bytes")?.trim();
    let (r, t) = v.split_once('/')?;
    let (a, b) = r.split_once('-')?;
    Some((a.trim().parse().ok()?, b.trim().parse().ok()?, t.trim().parse().ok()))
}

fn validator_of(resp: &ureq::Response) -> Option<String> {
    resp.header("ETag")
        .map(|e| format!("ETag {e}"))
        .or_else(|| resp.header("Last-Modified").map(|m| format!("Last-Modified {m}")))
}

/// The first `n` bytes of a body.
fn resp_body(url: &str, resp: ureq::Response, n: usize) -> Result<Vec<u8>> {
    let mut v = vec![0u8; n];
    resp.into_reader()
        .read_exact(&mut v)
        .map_err(|e| http_error(url, format!("the body ended early: {e}")))?;
    Ok(v)
}

/// Runs the request `request` makes, retrying transport errors, 5xx and 429 (module docs);
/// other statuses are one-line errors.
fn with_retries(url: &str, request: impl Fn() -> ureq::Request) -> Result<ureq::Response> {
    let mut wait = Duration::from_millis(250);
    for attempt in 0.. {
        let last = attempt == 3;
        match request().call() {
            Ok(r) => return Ok(r),
            Err(ureq::Error::Status(code, r)) if (code >= 500 || code == 429) && !last => {
                drop(r);
            }
            Err(ureq::Error::Status(code, r)) => {
                let text = r.status_text().to_string();
                return Err(http_error(url, format!("HTTP {code} {text}").trim_end()));
            }
            Err(ureq::Error::Transport(t)) if last => {
                let why = match t.message() {
                    Some(m) => format!("{}: {m}", t.kind()),
                    None => t.kind().to_string(),
                };
                return Err(http_error(url, why));
            }
            Err(ureq::Error::Transport(_)) => {}
        }
        std::thread::sleep(wait);
        wait *= 2;
    }
    unreachable!("the loop returns by its 4th attempt")
}
