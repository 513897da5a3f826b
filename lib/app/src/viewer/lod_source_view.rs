//! A COPC file or an EPT directory in `mortar view` (issue 30 §1): each frame draws the nodes the
//! store's LOD rule selects for the window's camera ([`LodSource::select`]: the selection and
//! every node it refined, the tree being additive), and nodes stream in as the camera moves.
//!
//! - A node is decoded (its LAZ chunk or file, only the layers the colour mode needs) by
//!   background threads ([`NodeLoader`]) the first time a selection needs it, quantized on a frame
//!   of its own and coloured; the frame thread never waits for it. Until every selected node is
//!   there the frame draws those that are, and [`busy`](Content::busy) keeps the window drawing
//!   (a screenshot waits for the complete picture). Coarse nodes are asked for first.
//! - GPU: a decoded node is uploaded within the frame's upload budget
//!   ([`UPLOAD_BUDGET_MS`](super::store::UPLOAD_BUDGET_MS)) and stays on the GPU; when the
//!   scene holds more than four times what the view draws (and more than
//!   [`KEEP_POINTS`]), it is rebuilt from the current selection. CPU: decoded nodes stay in
//!   memory while selected, the others up to [`KEEP_POINTS`] points.
//! - Colours: the modes the point format has (C cycles them). What a mode cannot know from one
//!   node is fixed when the mode is first shown, from the root node (a sample of the whole
//!   cloud in COPC and EPT): `auto`'s choice of RGB or intensity, RGB's 8- or 16-bit depth,
//!   and the range of scalar modes (`--range`, else the 1st to 99th percentile of the root's
//!   values), so that a node's colours never change once drawn.
//! - On the CPU the drawn points are numbered in read order (COPC chunks by offset, EPT files by
//!   path), as a flat read numbers them, so depth ties resolve as in `mortar render`.
//! - `--json` reports what was read (`lod_source`: nodes and bytes read against the whole).

use super::content::{group_digits, Content, GpuDrawn};
use super::node_loader::{threads_alone, NodeLoader};
use super::store::{modes_of, upload_budget_ms, SLICE};
use crate::draw::raw::{self, ColorStats, LoadedPiece, Payload};
use crate::draw::ColorChoice;
use anyhow::{anyhow, bail, Result};
use mortar_core::grid::Grid;
use mortar_core::layout::RecordLayout;
use mortar_core::octree::LodOptions;
use mortar_core::quantize::BatchGrid;
use mortar_core::render::resolve::{resolve, ResolveOptions};
use mortar_core::render::{rasterize, Aabb, BatchRef, Camera, Framebuffer, RasterOptions};
use mortar_io::dataset::OpenOptions;
use mortar_io::lod_source::LodSource;
use mortar_render::{GpuContext, GpuError, GpuRasterizer, GpuScene, SceneOptions};
use std::collections::{HashMap, HashSet};
use std::sync::Arc;

/// Points of decoded nodes kept beyond what the view draws (CPU), and the size above which a GPU
/// scene holding four times what the view draws is rebuilt: 16 Mi points, about 256 MiB.
pub const KEEP_POINTS: u64 = 1 << 24;

/// One decoded node: its points quantized on a frame of their own, in read order, and their
/// colours in the view's mode.
struct Node {
    grid: BatchGrid,
    bounds: Aabb,
    words: [Vec<u32>; 3],
    colors: Vec<u32>,
}

impl Node {
    fn len(&self) -> usize {
        self.colors.len()
    }

    fn batch(&self, first_index: u32) -> BatchRef<'_> {
        BatchRef {
            grid: self.grid,
            bounds_min: self.bounds.min,
            bounds_max: self.bounds.max,
            words: [0, 1, 2].map(|w| &self.words[w][..]),
            first_index,
        }
    }
}

/// What a colour mode needs of the records and what it fixed from the root node (see the
/// module docs).
#[derive(Clone, Debug)]
struct Coloring {
    choice: ColorChoice,
    payload: Payload,
    stats: ColorStats,
    range: Option<[f64; 2]>,
    keep: Vec<&'static str>,
}

/// The GPU side: the scene and which nodes it holds (first batch, batches, points).
struct SourceGpu {
    scene: GpuScene,
    batches: HashMap<usize, (u32, u32, u64)>,
    /// Its colours are another mode's: the next frame starts a new scene.
    stale: bool,
}

/// A COPC file or an EPT directory shown in a window.
pub struct LodSourceView {
    label: String,
    src: Arc<LodSource>,
    open: OpenOptions,
    /// The grid points are drawn on (the root node's).
    grid: Grid,
    layout: RecordLayout,
    options: LodOptions,
    bounds: Aabb,
    modes: Vec<ColorChoice>,
    mode: usize,
    given: Option<[f64; 2]>,
    coloring: Coloring,
    /// The root node (fixes each mode's colouring).
    root: usize,
    /// Per node, its place in read order.
    rank: Vec<usize>,
    loader: NodeLoader<usize, Arc<Node>>,
    /// Decoded nodes held (CPU: drawn from here; GPU: until uploaded).
    held: HashMap<usize, Arc<Node>>,
    gpu: Option<SourceGpu>,
    /// The CPU rasterizer's visibility buffer, kept from frame to frame.
    fb: Option<Framebuffer>,
    /// Nodes decoded so far (what `bytes_read` counts).
    read: HashSet<usize>,
    /// Bytes of the whole source (once: an EPT directory's are a file system call per node).
    total_bytes: Option<u64>,
    incomplete: bool,
    /// Nodes and points the last frame drew.
    drawn: (u64, u64),
}

impl LodSourceView {
    /// The view of `src` (opened with `open`), in colour mode `color` (`range`: of scalar modes),
    /// framing `bounds`, selecting with `options`.
    pub fn new(
        src: LodSource,
        open: OpenOptions,
        bounds: Aabb,
        options: LodOptions,
        color: ColorChoice,
        range: Option<[f64; 2]>,
    ) -> Result<LodSourceView> {
        let label = src.path().display().to_string();
        if src.points() == 0 {
            bail!("{label}: no points to draw");
        }
        let layout = src.layout()?;
        let order = src.read_order();
        let mut rank = vec![0; order.len()];
        for (r, &i) in order.iter().enumerate() {
            rank[i] = r;
        }
        // The root (level 0) where the hierarchy has one, else the first node read.
        let root = (0..src.node_count())
            .filter(|&i| src.node_points(i) > 0)
            .min_by_key(|&i| (src.node_key(i).level, rank[i]))
            .ok_or_else(|| anyhow!("{label}: no points to draw"))?;
        let modes = modes_of(&layout);
        let want = match color {
            ColorChoice::Stored
            | ColorChoice::Mode(mortar_core::render::resolve::ColorMode::Rgb)
                if layout.has_rgb() =>
            {
                ColorChoice::Auto
            }
            c => c,
        };
        let mode = modes.iter().position(|&m| m == want).ok_or_else(|| {
            anyhow!("{label}: --color {}: the point format has no such attribute", color.name())
        })?;
        let total_bytes = src.total_bytes();
        let src = Arc::new(src);
        let (coloring, grid) = coloring_of(&src, &open, root, modes[mode], range, &layout)?;
        Ok(LodSourceView {
            label,
            src,
            open,
            grid,
            layout,
            options,
            bounds,
            modes,
            mode,
            given: range,
            coloring,
            root,
            rank,
            loader: NodeLoader::new(threads_alone()),
            held: HashMap::new(),
            gpu: None,
            fb: None,
            read: HashSet::new(),
            total_bytes,
            incomplete: true,
            drawn: (0, 0),
        })
    }

    /// The nodes to draw for `camera`, in read order.
    fn select(&self, camera: &Camera) -> Result<Vec<usize>> {
        let (mut nodes, _) =
            self.src.select(camera, &self.options).map_err(|e| anyhow!("{}: {e}", self.label))?;
        nodes.sort_unstable_by_key(|&i| self.rank[i]);
        Ok(nodes)
    }

    /// `nodes` coarse first (the order nodes are asked for).
    fn coarse_first(&self, nodes: &[usize]) -> Vec<usize> {
        let mut v = nodes.to_vec();
        v.sort_unstable_by_key(|&i| (self.src.node_key(i).level, self.rank[i]));
        v
    }

    /// Node `i` if decoded (moved into `held`), else asked for.
    fn node(&mut self, i: usize) -> Option<Arc<Node>> {
        if let Some(n) = self.held.get(&i) {
            return Some(n.clone());
        }
        let (src, open, coloring, grid) =
            (self.src.clone(), self.open.clone(), self.coloring.clone(), self.grid);
        let n = self.loader.take(i, move || move || decode(&src, &open, i, &coloring, grid))?;
        self.read.insert(i);
        self.held.insert(i, n.clone());
        Some(n)
    }

    /// Lets decoded nodes go, those of `keep` last, down to [`KEEP_POINTS`] points.
    fn trim(&mut self, keep: &HashSet<usize>) {
        let held: u64 = self.held.values().map(|n| n.len() as u64).sum();
        if held <= KEEP_POINTS {
            return;
        }
        let mut excess = held - KEEP_POINTS;
        let others: Vec<usize> = self.held.keys().filter(|i| !keep.contains(i)).copied().collect();
        for i in others {
            if excess == 0 {
                break;
            }
            if let Some(n) = self.held.remove(&i) {
                excess = excess.saturating_sub(n.len() as u64);
            }
        }
    }

    /// What was read against the whole (`lod_source` of `--json`).
    pub fn read_json(&self) -> serde_json::Value {
        let read: Vec<usize> = self.read.iter().copied().collect();
        let points: u64 = read.iter().map(|&i| self.src.node_points(i)).sum();
        serde_json::json!({
            "format": self.src.format(),
            "nodes_read": read.len(),
            "nodes": self.src.node_count(),
            "points_read": points,
            "points": self.src.points(),
            "bytes_read": self.src.index_bytes() + self.src.node_bytes(&read),
            "bytes": self.total_bytes,
            "hierarchy_pages": self.src.pages(),
            "bytes_fetched": self.src.bytes_fetched(),
        })
    }
}

/// The colouring of `choice` (see the module docs) from the root node `root`, and the grid its
/// points are on.
fn coloring_of(
    src: &LodSource,
    open: &OpenOptions,
    root: usize,
    choice: ColorChoice,
    range: Option<[f64; 2]>,
    layout: &RecordLayout,
) -> Result<(Coloring, Grid)> {
    let payload = raw::payload_for(layout, choice, src.path())?;
    let keep = choice.attributes(layout);
    let ds = src.dataset(&[root], open, &keep)?;
    let piece = raw::load_all(&ds, payload, 0)?;
    let mut stats = ColorStats::default();
    stats.add(&piece);
    let range =
        range.or_else(|| raw::payload_range(&piece.payload, choice, payload, &stats, &ds.grid));
    Ok((Coloring { choice, payload, stats, range, keep }, ds.grid))
}

/// Decodes node `i` of `src`, its points on `grid`, coloured by `c`.
fn decode(
    src: &LodSource,
    open: &OpenOptions,
    i: usize,
    c: &Coloring,
    grid: Grid,
) -> Result<Arc<Node>> {
    let name = || {
        let k = src.node_key(i);
        format!(
            "{}: node {}-{}-{}-{}",
            src.path().display(),
            k.level,
            k.index[0],
            k.index[1],
            k.index[2]
        )
    };
    let ds = src.dataset(&[i], open, &c.keep)?;
    let LoadedPiece { mut xyz, payload, .. } = raw::load_all(&ds, c.payload, 0)?;
    let (colors, _) =
        raw::payload_colors(&payload, c.choice, c.payload, &c.stats, &ds.grid, c.range);
    if ds.grid != grid {
        // A node file on a grid of its own (EPT): its points on the view's.
        for p in &mut xyz {
            for a in 0..3 {
                let v = grid.to_int(a, ds.grid.world(a, p[a] as i64));
                p[a] = i32::try_from(v)
                    .map_err(|_| anyhow!("{}: a point lies outside the view's grid", name()))?;
            }
        }
    }
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    for p in &xyz {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    if xyz.is_empty() {
        (lo, hi) = ([0; 3], [0; 3]);
    }
    let bg = BatchGrid::for_bounds(lo, hi)
        .ok_or_else(|| anyhow!("{}: its points span more than 30 bits", name()))?;
    let mut words = [
        Vec::with_capacity(xyz.len()),
        Vec::with_capacity(xyz.len()),
        Vec::with_capacity(xyz.len()),
    ];
    for p in &xyz {
        let w = bg.encode(*p);
        for k in 0..3 {
            words[k].push(w[k]);
        }
    }
    let world = |v: [i32; 3]| [0, 1, 2].map(|a| grid.world(a, v[a] as i64));
    let (a, b) = (world(lo), world(hi));
    let bounds = Aabb::new([0, 1, 2].map(|k| a[k].min(b[k])), [0, 1, 2].map(|k| a[k].max(b[k])));
    Ok(Arc::new(Node { grid: bg, bounds, words, colors }))
}

impl Content for LodSourceView {
    fn bounds(&self) -> Aabb {
        self.bounds
    }

    fn points(&self) -> u64 {
        self.src.points()
    }

    fn modes(&self) -> &[ColorChoice] {
        &self.modes
    }

    fn mode(&self) -> usize {
        self.mode
    }

    fn set_mode(&mut self, to: usize, _gpu: Option<&GpuContext>) -> Result<bool> {
        if to == self.mode {
            return Ok(true);
        }
        let (coloring, _) = coloring_of(
            &self.src,
            &self.open,
            self.root,
            self.modes[to],
            self.given,
            &self.layout,
        )?;
        self.mode = to;
        self.coloring = coloring;
        // Nodes are decoded again for the new mode's layers and colours.
        self.loader = NodeLoader::new(threads_alone());
        self.held.clear();
        if let Some(g) = &mut self.gpu {
            g.stale = true;
        }
        self.incomplete = true;
        Ok(true)
    }

    fn status(&self) -> Vec<String> {
        let j = self.read_json();
        vec![
            format!(
                "{} points, {} nodes ({})",
                group_digits(self.src.points()),
                group_digits(self.src.node_count() as u64),
                self.src.format().to_uppercase()
            ),
            format!(
                "drawn {} nodes, {} points; read {} of {} bytes",
                group_digits(self.drawn.0),
                group_digits(self.drawn.1),
                group_digits(j["bytes_read"].as_u64().unwrap_or(0)),
                group_digits(j["bytes"].as_u64().unwrap_or(0))
            ),
        ]
    }

    fn busy(&self) -> bool {
        self.incomplete
    }

    fn report(&self) -> Option<serde_json::Value> {
        Some(self.read_json())
    }

    fn use_gpu(&mut self, ctx: &GpuContext) -> Result<(), GpuError> {
        let scene = GpuScene::new(
            ctx,
            self.grid,
            1 << 20,
            SceneOptions { colors: true, ..Default::default() },
        )?;
        self.gpu = Some(SourceGpu { scene, batches: HashMap::new(), stale: false });
        Ok(())
    }

    fn draw_cpu(
        &mut self,
        camera: &Camera,
        options: &RasterOptions,
        resolve_options: &ResolveOptions,
    ) -> Result<(Vec<u32>, u64)> {
        self.loader.collect()?;
        let nodes = self.select(camera)?;
        let mut have = HashMap::new();
        for i in self.coarse_first(&nodes) {
            if let Some(n) = self.node(i) {
                have.insert(i, n);
            }
        }
        self.incomplete = have.len() < nodes.len();
        // Numbered in read order, as a flat read numbers them.
        let drawn: Vec<&Arc<Node>> = nodes.iter().filter_map(|i| have.get(i)).collect();
        let mut firsts = Vec::with_capacity(drawn.len());
        let mut refs = Vec::with_capacity(drawn.len());
        let mut next = 0u64;
        for n in &drawn {
            if next + n.len() as u64 > u32::MAX as u64 {
                bail!("{}: more than 2^32 points in one view", self.label);
            }
            firsts.push(next as u32);
            refs.push(n.batch(next as u32));
            next += n.len() as u64;
        }
        let (w, h) = (camera.width, camera.height);
        let fb = match &mut self.fb {
            Some(fb) if (fb.width(), fb.height()) == (w, h) => {
                fb.clear();
                fb
            }
            fb => fb.insert(Framebuffer::new(w, h)),
        };
        let s = rasterize(fb, &refs, &self.grid, camera, options)
            .map_err(|e| anyhow!("{}: {e}", self.label))?;
        let background = resolve_options.background;
        let color = |i: u32| {
            let k = firsts.partition_point(|&f| f <= i).saturating_sub(1);
            drawn
                .get(k)
                .and_then(|n| n.colors.get((i - firsts[k]) as usize))
                .copied()
                .unwrap_or(background)
        };
        let rgba = resolve(fb.keys_slice(), w, h, color, resolve_options);
        self.drawn = (drawn.len() as u64, next);
        let keep: HashSet<usize> = nodes.into_iter().collect();
        self.trim(&keep);
        Ok((rgba, s.points_drawn))
    }

    fn draw_gpu(
        &mut self,
        ctx: &GpuContext,
        raster: &mut GpuRasterizer,
        camera: &Camera,
        options: &RasterOptions,
        resolve: &ResolveOptions,
    ) -> Result<GpuDrawn> {
        let start = std::time::Instant::now();
        let label = self.label.clone();
        let gpu = |e: GpuError| anyhow!("{label}: GPU: {e}");
        self.loader.collect()?;
        let nodes = self.select(camera)?;
        let want: u64 = nodes.iter().map(|&i| self.src.node_points(i)).sum();
        let g = self.gpu.as_mut().ok_or_else(|| anyhow!("{label}: GPU: not set up"))?;
        if g.stale
            || g.scene.points() > (4 * want).max(KEEP_POINTS)
            || g.scene.points() + want >= 1 << 32
        {
            let options = SceneOptions { colors: true, ..Default::default() };
            let scene = GpuScene::new(ctx, self.grid, want.max(1 << 20), options).map_err(gpu)?;
            *g = SourceGpu { scene, batches: HashMap::new(), stale: false };
        }
        let mut ids = Vec::new();
        let mut uploaded = 0;
        let mut complete = true;
        for i in self.coarse_first(&nodes) {
            if let Some(&(b, k, _)) = self.gpu.as_ref().and_then(|g| g.batches.get(&i)) {
                ids.extend(b..b + k);
                continue;
            }
            if uploaded > 0 && start.elapsed().as_secs_f64() * 1e3 >= upload_budget_ms() {
                complete = false;
                continue;
            }
            let Some(n) = self.node(i) else {
                complete = false;
                continue;
            };
            let g = self.gpu.as_mut().expect("checked above");
            if g.scene.points() + n.len() as u64 >= 1 << 32 {
                complete = false;
                continue;
            }
            let first = g.scene.points() as u32;
            let b = g.scene.batches().len() as u32;
            let mut k = 0;
            // Slices of at most SLICE points: one workgroup each (as the store view uploads).
            for s in (0..n.len().max(1)).step_by(SLICE) {
                let e = (s + SLICE).min(n.len());
                let whole = n.batch(first);
                let part = BatchRef {
                    words: [0, 1, 2].map(|w| &whole.words[w][s..e]),
                    first_index: first + s as u32,
                    ..whole
                };
                g.scene.push(ctx, &part, Some(&n.colors[s..e])).map_err(gpu)?;
                k += 1;
            }
            g.batches.insert(i, (b, k, n.len() as u64));
            ids.extend(b..b + k);
            self.held.remove(&i);
            uploaded += 1;
        }
        // Asked for, coarse first, for the next frames.
        for i in self.coarse_first(&nodes) {
            if !self.gpu.as_ref().is_some_and(|g| g.batches.contains_key(&i)) {
                self.node(i);
            }
        }
        self.incomplete = !complete;
        let keep: HashSet<usize> = nodes.iter().copied().collect();
        self.trim(&keep);
        let g = self.gpu.as_mut().expect("checked above");
        let drawn: u64 = nodes.iter().filter_map(|i| g.batches.get(i)).map(|b| b.2).sum();
        self.drawn = (nodes.iter().filter(|i| g.batches.contains_key(i)).count() as u64, drawn);
        raster
            .draw_selected(ctx, &mut g.scene, Some(&ids), camera, options, Some(resolve))
            .map(|f| GpuDrawn::of(&f))
            .map_err(gpu)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mortar_core::octree::BuilderConfig;
    use mortar_core::render::Projection;
    use mortar_io::export::{export, ExportFormat, ExportOptions, PointOrder};
    use std::path::PathBuf;

    /// The sample exported as COPC (several levels).
    fn copc(tag: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("mortar-lodview-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let sample =
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data-samples/autzen_trim.laz");
        let ds = mortar_io::inputs::open(&[sample]).unwrap();
        let out = dir.join("s.copc.laz");
        let opts = ExportOptions {
            format: ExportFormat::Copc,
            memory: 1 << 30,
            config: BuilderConfig { leaf_capacity: 2000, ..Default::default() },
            order: PointOrder::Morton,
        };
        export(&ds, &out, &opts).unwrap();
        out
    }

    fn view(path: &std::path::Path, color: ColorChoice) -> LodSourceView {
        let (src, w) = LodSource::open(path).unwrap();
        assert!(w.is_none(), "{w:?}");
        let src = src.expect("a COPC file");
        let bounds = src.bounds(&OpenOptions::default()).unwrap();
        let options = LodOptions::default();
        LodSourceView::new(src, OpenOptions::default(), bounds, options, color, None).unwrap()
    }

    /// Frames until every selected node is drawn; the last image and the frames it took.
    fn settle(v: &mut LodSourceView, camera: &Camera) -> (Vec<u32>, usize) {
        let resolve = ResolveOptions { background: 0xff00_0000, ..Default::default() };
        for n in 1..100_000 {
            let (img, _) = v.draw_cpu(camera, &RasterOptions::default(), &resolve).unwrap();
            if !v.busy() {
                return (img, n);
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        panic!("the view never settled");
    }

    fn camera(b: &Aabb, eye_from: [f64; 3], target: [f64; 3]) -> Camera {
        let eye = [0, 1, 2].map(|a| target[a] + eye_from[a]);
        Camera::look_at(
            eye,
            target,
            [0.0, 0.0, 1.0],
            Projection::Perspective { fov_y: 0.6 },
            b,
            240,
            180,
        )
        .unwrap()
    }

    #[test]
    fn nodes_stream_in_as_the_camera_moves_and_end_as_a_fresh_view() {
        let path = copc("move");
        let mut v = view(&path, ColorChoice::Auto);
        let b = v.bounds();
        let (c, d) = (b.center(), b.diagonal());
        let far = camera(&b, [0.0, -d, d], c);
        let (_, frames) = settle(&mut v, &far);
        let first = v.read_json();
        assert!(frames >= 2, "the first frame waited for its nodes");
        // A closeup over one corner: the nodes it needs come over the next frames, and the
        // picture it settles on is a fresh view's of that camera.
        let corner =
            [b.min[0] + 0.2 * (b.max[0] - b.min[0]), b.min[1] + 0.3 * (b.max[1] - b.min[1]), c[2]];
        let near = camera(&b, [0.0, -0.05 * d, 0.08 * d], corner);
        let (moved, _) = settle(&mut v, &near);
        let after = v.read_json();
        let mut fresh = view(&path, ColorChoice::Auto);
        let (expected, _) = settle(&mut fresh, &near);
        assert_eq!(moved, expected, "the moved view differs from a fresh one");
        let n = |j: &serde_json::Value, k: &str| j[k].as_u64().unwrap();
        assert!(n(&after, "nodes_read") > n(&first, "nodes_read"), "{first} {after}");
        assert!(n(&fresh.read_json(), "nodes_read") < n(&after, "nodes_read"));
        assert!(n(&after, "nodes_read") < n(&after, "nodes"), "{after}");
        // A new colour mode decodes the nodes again for it and ends as a fresh view in it.
        let class = v
            .modes
            .iter()
            .position(|&m| {
                m == ColorChoice::Mode(mortar_core::render::resolve::ColorMode::Classification)
            })
            .unwrap();
        assert!(v.set_mode(class, None).unwrap());
        let (switched, _) = settle(&mut v, &near);
        let mut fresh =
            view(&path, ColorChoice::Mode(mortar_core::render::resolve::ColorMode::Classification));
        assert_eq!(switched, settle(&mut fresh, &near).0, "the switched view differs");
        assert_ne!(switched, moved);
        let _ = std::fs::remove_dir_all(path.parent().unwrap());
    }
}
