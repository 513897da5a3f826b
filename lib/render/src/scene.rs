//! Point data on the GPU: batches streamed in one at a time into chunked storage buffers.
//!
//! A chunk holds the coarse, medium and fine words (and optionally the RGBA8 colours) of whole
//! batches, one `u32` per point each, in a buffer no larger than the device's largest storage
//! binding (128 MiB on lavapipe, up to 2 GiB on NVIDIA; at most 1 GiB here so that allocations stay
//! reasonable). A batch never straddles two chunks. Batches arrive in point-index order
//! (`first_index` consecutive from 0, as in a batch file), so the index the framebuffer stores is
//! the batch file's point index and the colour of index `i` sits at `i - chunk.first_index`.
//! Uploads go through a host staging area per chunk and are written when it fills, when a chunk
//! is full, or before a frame is drawn ([`GpuScene::flush`]), so data can keep arriving between
//! frames.

use crate::context::{GpuContext, GpuError};
use mortar_core::grid::Grid;
use mortar_core::quantize::BatchGrid;
use mortar_core::render::gpu::{DrawRecord, PlanBatch};
use mortar_core::render::{Aabb, BatchRef};

/// The largest chunk, in points (1 GiB per word buffer).
pub const MAX_CHUNK_POINTS: u32 = 1 << 28;

/// Points staged on the host before a write to the GPU.
const STAGING_POINTS: usize = 4 << 20;

/// Choices of a scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct SceneOptions {
    /// Points per chunk (`None`: as many as the device's largest binding holds, at most
    /// [`MAX_CHUNK_POINTS`]). Small values exercise the chunking in tests.
    pub chunk_points: Option<u32>,
    /// Whether batches come with colours (for the resolve pass).
    pub colors: bool,
}

/// Where one batch is and what the planner needs to know of it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GpuBatch {
    /// Quantization frame.
    pub grid: BatchGrid,
    /// World bounds of its points.
    pub bounds: Aabb,
    /// Chunk holding it.
    pub chunk: u32,
    /// Position of its first point in the chunk.
    pub offset: u32,
    /// Number of points.
    pub count: u32,
    /// Index of its first point.
    pub first_index: u32,
}

pub(crate) struct Chunk {
    pub words: [wgpu::Buffer; 3],
    pub colors: Option<wgpu::Buffer>,
    pub capacity: u32,
    pub len: u32,
    /// Point index of the chunk's first point.
    pub first_index: u32,
    /// Points of the chunk already written to the GPU.
    pub written: u32,
}

/// The batches on the GPU.
pub struct GpuScene {
    grid: Grid,
    options: SceneOptions,
    chunk_points: u32,
    expected_points: u64,
    points: u64,
    pub(crate) chunks: Vec<Chunk>,
    pub(crate) batches: Vec<GpuBatch>,
    staged: [Vec<u32>; 4],
    /// Bytes written since the last wait for the GPU (bounds wgpu's staging memory).
    unwaited: u64,
    /// Every batch as the GPU plan pass reads it (`shaders/plan.wgsl`), in batch order.
    pub(crate) plan: Vec<PlanBatch>,
    /// The plan batches on the GPU (the first `plan_written` of `plan`).
    pub(crate) plan_buffer: Option<wgpu::Buffer>,
    plan_written: usize,
    /// Per chunk (in order): its first draw record and its number of batches. Each chunk's
    /// records start at a storage-offset boundary, so that one binding of the records buffer
    /// per chunk serves its draw dispatch.
    pub(crate) record_ranges: Vec<(u32, u32)>,
    /// Records the plan pass writes (padding between chunks included).
    pub(crate) records_total: u32,
    /// Records per storage-offset alignment.
    record_align: u32,
}

impl GpuScene {
    /// An empty scene of points on the world grid `grid`. `expected_points` sizes the chunks
    /// (the last one is no larger than needed); more points may still come: chunks beyond the
    /// expected points hold half the points so far (at least 1 Mi, at most a chunk), so that a
    /// scene filled node by node (a store view) keeps few chunks.
    pub fn new(
        ctx: &GpuContext,
        grid: Grid,
        expected_points: u64,
        options: SceneOptions,
    ) -> Result<GpuScene, GpuError> {
        let by_device = (ctx.max_binding() / 4).min(MAX_CHUNK_POINTS as u64) as u32 & !255;
        let chunk_points = options.chunk_points.unwrap_or(by_device).min(by_device).max(1);
        Ok(GpuScene {
            grid,
            options,
            chunk_points,
            expected_points,
            points: 0,
            chunks: Vec::new(),
            batches: Vec::new(),
            staged: Default::default(),
            unwaited: 0,
            plan: Vec::new(),
            plan_buffer: None,
            plan_written: 0,
            record_ranges: Vec::new(),
            records_total: 0,
            record_align: (ctx.limits().min_storage_buffer_offset_alignment.max(1) as usize)
                .div_ceil(std::mem::size_of::<DrawRecord>()) as u32,
        })
    }

    /// The world grid of the points' integer coordinates.
    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// Points added so far.
    pub fn points(&self) -> u64 {
        self.points
    }

    /// Batches added so far.
    pub fn batches(&self) -> &[GpuBatch] {
        &self.batches
    }

    /// Number of chunks.
    pub fn chunk_count(&self) -> usize {
        self.chunks.len()
    }

    /// Points per full chunk.
    pub fn chunk_points(&self) -> u32 {
        self.chunk_points
    }

    /// Whether the scene holds colours.
    pub fn has_colors(&self) -> bool {
        self.options.colors
    }

    /// Bytes of GPU memory the chunks occupy.
    pub fn gpu_bytes(&self) -> u64 {
        self.chunks.iter().map(|c| c.capacity as u64 * 4 * (3 + c.colors.is_some() as u64)).sum()
    }

    /// Adds one batch (its `first_index` must be the number of points added before) and, if the
    /// scene has colours, its points' RGBA8 colours.
    pub fn push(
        &mut self,
        ctx: &GpuContext,
        b: &BatchRef<'_>,
        colors: Option<&[u32]>,
    ) -> Result<(), GpuError> {
        let n = b.len();
        if b.words[1].len() != n || b.words[2].len() != n {
            return Err(mortar_core::render::RasterError::WordCounts {
                batch: self.batches.len(),
                lengths: b.words.map(<[u32]>::len),
            }
            .into());
        }
        if b.first_index as u64 != self.points {
            return Err(GpuError::FirstIndex { expected: self.points, got: b.first_index });
        }
        if self.points + n as u64 > 1u64 << 32 {
            return Err(mortar_core::render::RasterError::IndexOverflow {
                batch: self.batches.len(),
                first_index: b.first_index,
                count: n,
            }
            .into());
        }
        match (self.options.colors, colors) {
            (true, Some(c)) if c.len() == n => {}
            (true, Some(c)) => {
                return Err(GpuError::Colors(format!(
                    "{} colours for a batch of {n} points",
                    c.len()
                )))
            }
            (true, None) => {
                return Err(GpuError::Colors(
                    "the scene has colours but a batch came without".into(),
                ))
            }
            (false, Some(_)) => {
                return Err(GpuError::Colors("the scene was made without colours".into()))
            }
            (false, None) => {}
        }
        if n > self.chunk_points as usize {
            return Err(GpuError::TooLarge {
                what: "one batch",
                needed: n as u64 * 4,
                limit: self.chunk_points as u64 * 4,
            });
        }
        let chunk = match self.chunks.last() {
            Some(c) if c.capacity - c.len >= n as u32 => self.chunks.len() - 1,
            _ => {
                self.flush(ctx)?;
                self.new_chunk(ctx, n as u32)?
            }
        };
        if self.record_ranges.len() <= chunk {
            let first = self.records_total.div_ceil(self.record_align) * self.record_align;
            self.record_ranges.push((first, 0));
            self.records_total = first;
        }
        let range = &mut self.record_ranges[chunk];
        let record = range.0 + range.1;
        range.1 += 1;
        self.records_total = record + 1;
        self.plan.push(PlanBatch::new(
            &self.grid,
            &b.grid,
            &b.bounds(),
            n as u32,
            self.chunks[chunk].len,
            b.first_index,
            record,
        ));
        let c = &mut self.chunks[chunk];
        self.batches.push(GpuBatch {
            grid: b.grid,
            bounds: b.bounds(),
            chunk: chunk as u32,
            offset: c.len,
            count: n as u32,
            first_index: b.first_index,
        });
        c.len += n as u32;
        self.points += n as u64;
        for (s, w) in self.staged.iter_mut().zip(b.words) {
            s.extend_from_slice(w);
        }
        if let Some(col) = colors {
            self.staged[3].extend_from_slice(col);
        }
        if self.staged[0].len() >= STAGING_POINTS {
            self.flush(ctx)?;
        }
        Ok(())
    }

    /// Makes a chunk for at least `at_least` more points and returns its position.
    fn new_chunk(&mut self, ctx: &GpuContext, at_least: u32) -> Result<usize, GpuError> {
        let remaining = self.expected_points.saturating_sub(self.points);
        let wanted =
            if remaining >= at_least as u64 { remaining } else { (self.points / 2).max(1 << 20) };
        let capacity = (wanted.min(self.chunk_points as u64) as u32).max(at_least).max(1);
        let first_index = self.points as u32;
        let make = |label: &str| {
            ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: capacity as u64 * 4,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        };
        let words = [make("coarse words"), make("medium words"), make("fine words")];
        let colors = self.options.colors.then(|| make("colours"));
        ctx.check()?;
        self.chunks.push(Chunk { words, colors, capacity, len: 0, first_index, written: 0 });
        Ok(self.chunks.len() - 1)
    }

    /// Replaces the colours of every point added so far (`colors[i]` is point `i`'s RGBA8) without
    /// touching the coordinate words: a colour-mode switch costs 4 bytes per point. Staged points
    /// are written first.
    pub fn set_colors(&mut self, ctx: &GpuContext, colors: &[u32]) -> Result<(), GpuError> {
        if !self.options.colors {
            return Err(GpuError::Colors("the scene was made without colours".into()));
        }
        if colors.len() as u64 != self.points {
            return Err(GpuError::Colors(format!(
                "{} colours for a scene of {} points",
                colors.len(),
                self.points
            )));
        }
        self.flush(ctx)?;
        for c in &self.chunks {
            let first = c.first_index as usize;
            if let Some(buf) = &c.colors {
                ctx.queue.write_buffer(
                    buf,
                    0,
                    bytemuck::cast_slice(&colors[first..first + c.len as usize]),
                );
            }
        }
        ctx.queue.submit([]);
        ctx.check()
    }

    /// Writes the plan batches not yet on the GPU (the buffer grows by half when full, written
    /// anew).
    fn flush_plan(&mut self, ctx: &GpuContext) {
        if self.plan_written == self.plan.len() {
            return;
        }
        let size = std::mem::size_of::<PlanBatch>() as u64;
        let needed = self.plan.len() as u64 * size;
        if self.plan_buffer.as_ref().is_none_or(|b| b.size() < needed) {
            let grown = crate::buffers::grown_size(
                ctx,
                self.plan_buffer.as_ref().map_or(0, |b| b.size()),
                needed,
            );
            self.plan_buffer = Some(ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("plan batches"),
                size: grown,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
            self.plan_written = 0;
        }
        if let Some(buf) = &self.plan_buffer {
            ctx.queue.write_buffer(
                buf,
                self.plan_written as u64 * size,
                bytemuck::cast_slice(&self.plan[self.plan_written..]),
            );
        }
        self.plan_written = self.plan.len();
    }

    /// Writes the staged points (and the new batches' plan records) to the GPU.
    pub fn flush(&mut self, ctx: &GpuContext) -> Result<(), GpuError> {
        self.flush_plan(ctx);
        let Some(c) = self.chunks.last_mut() else { return Ok(()) };
        if self.staged[0].is_empty() {
            return Ok(());
        }
        let offset = c.written as u64 * 4;
        for (buf, s) in c.words.iter().zip(&self.staged[..3]) {
            ctx.queue.write_buffer(buf, offset, bytemuck::cast_slice(s));
        }
        if let Some(buf) = &c.colors {
            ctx.queue.write_buffer(buf, offset, bytemuck::cast_slice(&self.staged[3]));
        }
        c.written += self.staged[0].len() as u32;
        self.unwaited += self.staged.iter().map(|s| s.len() as u64 * 4).sum::<u64>();
        for s in &mut self.staged {
            s.clear();
        }
        ctx.queue.submit([]);
        // wgpu keeps a staging copy of every write until the GPU has done it: wait now and then
        // so that streaming billions of points does not hold them all in host memory.
        if self.unwaited > 1 << 30 {
            self.unwaited = 0;
            return ctx.wait();
        }
        ctx.check()
    }
}
