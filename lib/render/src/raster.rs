//! The GPU rasterizer (paper 003 §3.2-3.3 in wgpu compute shaders): per frame the host plans every
//! batch with the same [`Planner`] as the CPU reference (culling, precision, projection), uploads
//! one [`DrawRecord`] per drawn batch, and the GPU runs the passes of `shaders/`: clear, draw
//! batches (one workgroup of 128 threads per batch; 64-bit `atomicMin` or the 32-bit two-pass
//! path) and, when asked, resolve. The keys it leaves are those of
//! [`mortar_core::render::rasterize`] for the same view (see `docs/render.md` for where a GPU may
//! round differently).

use crate::context::{AtomicPath, GpuContext, GpuError};
use crate::scene::GpuScene;
use crate::shaders::Pass;
use mortar_core::render::framebuffer::EMPTY_KEY;
use mortar_core::render::gpu::{DrawRecord, FrameUniforms, ResolveUniforms};
use mortar_core::render::{BatchPlan, Camera, Planner, RasterError, RasterOptions, RasterStats};
use rayon::prelude::*;
use std::num::NonZeroU64;
use std::sync::mpsc;
use std::time::Instant;

/// GPU time of each pass of a frame, from timestamp queries, in milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GpuTimings {
    /// Clearing the framebuffer.
    pub clear_ms: f64,
    /// Drawing the batches (both steps on the 32-bit path).
    pub draw_ms: f64,
    /// Resolving indices to colours (`None` when not run).
    pub resolve_ms: Option<f64>,
}

/// What one frame did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GpuFrame {
    /// Batches culled and drawn, points per precision, points drawn (counted on the GPU).
    pub stats: RasterStats,
    /// GPU pass times, where the device has timestamps.
    pub timings: Option<GpuTimings>,
    /// Host seconds spent planning the batches (culling, precision, projections).
    pub plan_seconds: f64,
    /// Host seconds from the start of the frame until the GPU finished it.
    pub frame_seconds: f64,
}

struct Pipelines {
    clear: wgpu::ComputePipeline,
    draw: Vec<wgpu::ComputePipeline>,
    resolve: wgpu::ComputePipeline,
}

/// The framebuffer, pipelines and per-frame buffers of one viewport size.
pub struct GpuRasterizer {
    width: u32,
    height: u32,
    path: AtomicPath,
    pipelines: Pipelines,
    /// 64-bit keys (`width * height * 8` bytes), or the 32-bit path's depths.
    keys: wgpu::Buffer,
    /// The 32-bit path's point indices.
    indices: Option<wgpu::Buffer>,
    counters: wgpu::Buffer,
    frame_uniforms: wgpu::Buffer,
    records: Option<wgpu::Buffer>,
    image: Option<wgpu::Buffer>,
    resolve_uniforms: Vec<wgpu::Buffer>,
    queries: Option<(wgpu::QuerySet, wgpu::Buffer)>,
}

pub(crate) fn pipeline(ctx: &GpuContext, pass: Pass) -> wgpu::ComputePipeline {
    let module = ctx.device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(pass.file()),
        source: wgpu::ShaderSource::Wgsl(pass.source().into()),
    });
    ctx.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(pass.file()),
        layout: None,
        module: &module,
        entry_point: Some("main"),
        // The passes initialise the little workgroup memory they use (common/counters.wgsl).
        compilation_options: wgpu::PipelineCompilationOptions { zero_initialize_workgroup_memory: false, ..Default::default() },
        cache: None,
    })
}

pub(crate) fn storage(ctx: &GpuContext, label: &str, size: u64, extra: wgpu::BufferUsages) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: size.max(4),
        usage: wgpu::BufferUsages::STORAGE | extra,
        mapped_at_creation: false,
    })
}

pub(crate) fn entry(binding: u32, resource: wgpu::BindingResource<'_>) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry { binding, resource }
}

/// Timestamp slots: clear begin/end, draw begin/end, resolve begin/end.
const QUERIES: u32 = 6;

impl GpuRasterizer {
    /// A rasterizer for `width x height` pixels on the context's atomic path.
    pub fn new(ctx: &GpuContext, width: u32, height: u32) -> Result<GpuRasterizer, GpuError> {
        let pixels = width as u64 * height as u64;
        let path = ctx.atomic_path();
        let key_bytes = pixels * if path == AtomicPath::U64 { 8 } else { 4 };
        if key_bytes > ctx.max_binding() || pixels == 0 {
            return Err(GpuError::TooLarge { what: "the framebuffer", needed: key_bytes, limit: ctx.max_binding() });
        }
        let draw = match path {
            AtomicPath::U64 => vec![pipeline(ctx, Pass::Draw64)],
            AtomicPath::TwoPass32 => vec![pipeline(ctx, Pass::DrawDepth32), pipeline(ctx, Pass::DrawIndex32)],
        };
        let pipelines = Pipelines { clear: pipeline(ctx, Pass::Clear), draw, resolve: pipeline(ctx, Pass::Resolve) };
        let copy = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        let keys = storage(ctx, "keys", key_bytes, copy);
        let indices = (path == AtomicPath::TwoPass32).then(|| storage(ctx, "indices", pixels * 4, copy));
        let counters = storage(ctx, "counters", 8, copy);
        let frame_uniforms = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("frame uniforms"),
            size: std::mem::size_of::<FrameUniforms>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let queries = ctx.has_timestamps().then(|| {
            let set = ctx.device.create_query_set(&wgpu::QuerySetDescriptor { label: Some("pass times"), ty: wgpu::QueryType::Timestamp, count: QUERIES });
            let buf = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("pass times"),
                size: QUERIES as u64 * 8,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            (set, buf)
        });
        ctx.check()?;
        Ok(GpuRasterizer {
            width,
            height,
            path,
            pipelines,
            keys,
            indices,
            counters,
            frame_uniforms,
            records: None,
            image: None,
            resolve_uniforms: Vec::new(),
            queries,
        })
    }

    /// The atomic path in use.
    pub fn atomic_path(&self) -> AtomicPath {
        self.path
    }

    /// The viewport size `(width, height)` in pixels.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Changes the viewport size: the framebuffer (and the resolved image) are made anew, the
    /// pipelines kept. A frame must be drawn before the next read.
    pub fn resize(&mut self, ctx: &GpuContext, width: u32, height: u32) -> Result<(), GpuError> {
        if (width, height) == (self.width, self.height) {
            return Ok(());
        }
        let pixels = width as u64 * height as u64;
        let key_bytes = pixels * if self.path == AtomicPath::U64 { 8 } else { 4 };
        if key_bytes > ctx.max_binding() || pixels == 0 {
            return Err(GpuError::TooLarge { what: "the framebuffer", needed: key_bytes, limit: ctx.max_binding() });
        }
        let copy = wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST;
        self.keys = storage(ctx, "keys", key_bytes, copy);
        self.indices = (self.path == AtomicPath::TwoPass32).then(|| storage(ctx, "indices", pixels * 4, copy));
        self.image = None;
        self.width = width;
        self.height = height;
        ctx.check()
    }

    /// The resolved image of the last frame drawn with `resolve` (RGBA8 packed
    /// `r | g << 8 | b << 16 | a << 24`, row-major, `width * height` words; a storage buffer), for
    /// passes that use it on the GPU (the window's present pass).
    pub fn image_buffer(&self) -> Option<&wgpu::Buffer> {
        self.image.as_ref()
    }

    fn timestamps(&self, begin: u32) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        self.queries.as_ref().map(|(set, _)| wgpu::ComputePassTimestampWrites {
            query_set: set,
            beginning_of_pass_write_index: Some(begin),
            end_of_pass_write_index: Some(begin + 1),
        })
    }

    /// Draws the scene for `camera` into a cleared framebuffer; with `resolve` (a background
    /// colour) also resolves the image from the scene's colours. Waits for the GPU.
    pub fn draw(&mut self, ctx: &GpuContext, scene: &mut GpuScene, camera: &Camera, options: &RasterOptions, resolve: Option<u32>) -> Result<GpuFrame, GpuError> {
        self.draw_selected(ctx, scene, None, camera, options, resolve)
    }

    /// [`draw`](Self::draw) of only the scene's batches listed in `selected` (positions in
    /// [`GpuScene::batches`], any order, each at most once; `None`: every batch). The framebuffer
    /// holds the scene's point indices as usual, so the resolve needs no change: this is how a
    /// level-of-detail selection is drawn from a scene holding every node once.
    pub fn draw_selected(&mut self, ctx: &GpuContext, scene: &mut GpuScene, selected: Option<&[u32]>, camera: &Camera, options: &RasterOptions, resolve: Option<u32>) -> Result<GpuFrame, GpuError> {
        let start = Instant::now();
        if camera.width != self.width || camera.height != self.height {
            return Err(RasterError::Viewport { fb_width: self.width, fb_height: self.height, width: camera.width, height: camera.height }.into());
        }
        if resolve.is_some() && !scene.has_colors() {
            return Err(GpuError::Colors("resolve asked for but the scene has no colours".into()));
        }
        scene.flush(ctx)?;
        let planner = Planner::new(camera, scene.grid(), options)?;

        // Plan every batch (in parallel), then lay the drawn ones out per chunk, each chunk's
        // records starting at a storage-offset boundary (padding records have no points).
        // The batches to draw, in scene order (so that each chunk's records are contiguous).
        let order: Vec<u32> = match selected {
            None => (0..scene.batches.len() as u32).collect(),
            Some(ids) => {
                let mut v = ids.to_vec();
                v.sort_unstable();
                v.dedup();
                if let Some(&bad) = v.iter().find(|&&i| i as usize >= scene.batches.len()) {
                    return Err(GpuError::Selection(format!("batch {bad} selected, but the scene holds {}", scene.batches.len())));
                }
                v
            }
        };
        let plans: Vec<BatchPlan> = order.par_iter().map(|&i| {
            let b = &scene.batches[i as usize];
            planner.plan(&b.grid, &b.bounds, b.count as usize)
        }).collect();
        let mut stats = RasterStats { batches: plans.len() as u64, ..Default::default() };
        let align = ctx.limits().min_storage_buffer_offset_alignment.max(1) as usize;
        let mut records: Vec<DrawRecord> = Vec::new();
        let mut ranges: Vec<(usize, usize, usize)> = Vec::new(); // (chunk, first record, count)
        for (b, plan) in order.iter().map(|&i| &scene.batches[i as usize]).zip(&plans) {
            match plan {
                BatchPlan::Empty => {}
                BatchPlan::Culled => stats.batches_culled += 1,
                BatchPlan::Draw { precision, projection } => {
                    stats.batches_drawn += 1;
                    stats.points_by_precision[precision.words() - 1] += b.count as u64;
                    if ranges.last().is_none_or(|r| r.0 != b.chunk as usize) {
                        while records.len() * std::mem::size_of::<DrawRecord>() % align != 0 {
                            records.push(bytemuck::Zeroable::zeroed());
                        }
                        ranges.push((b.chunk as usize, records.len(), 0));
                    }
                    records.push(DrawRecord { projection: *projection, offset: b.offset, count: b.count, first_index: b.first_index, _pad: 0 });
                    ranges.last_mut().expect("pushed above").2 += 1;
                }
            }
        }
        let plan_seconds = start.elapsed().as_secs_f64();
        let record_size = std::mem::size_of::<DrawRecord>() as u64;
        if let Some(r) = ranges.iter().find(|r| r.2 as u64 * record_size > ctx.max_binding()) {
            return Err(GpuError::TooLarge { what: "one chunk's draw records", needed: r.2 as u64 * record_size, limit: ctx.max_binding() });
        }
        let needed = (records.len() as u64 * record_size).max(record_size);
        if self.records.as_ref().is_none_or(|b| b.size() < needed) {
            let size = needed.max(self.records.as_ref().map_or(0, |b| b.size() * 3 / 2)).min(ctx.limits().max_buffer_size);
            self.records = Some(storage(ctx, "draw records", size.max(needed), wgpu::BufferUsages::COPY_DST));
        }
        let records_buf = self.records.as_ref().expect("made above");
        if !records.is_empty() {
            ctx.queue.write_buffer(records_buf, 0, bytemuck::cast_slice(&records));
        }
        ctx.queue.write_buffer(&self.frame_uniforms, 0, bytemuck::bytes_of(&FrameUniforms::new(camera, ctx.division())));
        ctx.queue.write_buffer(&self.counters, 0, &[0u8; 8]);

        let dev = &ctx.device;
        let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        // Clear.
        {
            let targets: Vec<&wgpu::Buffer> = std::iter::once(&self.keys).chain(self.indices.as_ref()).collect();
            let groups: Vec<(wgpu::BindGroup, u32)> = targets
                .iter()
                .map(|buf| {
                    let layout = self.pipelines.clear.get_bind_group_layout(0);
                    let bg = dev.create_bind_group(&wgpu::BindGroupDescriptor { label: None, layout: &layout, entries: &[entry(0, buf.as_entire_binding())] });
                    (bg, (buf.size() / 4).div_ceil(256) as u32)
                })
                .collect();
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("clear"), timestamp_writes: self.timestamps(0) });
            pass.set_pipeline(&self.pipelines.clear);
            for (bg, n) in &groups {
                let (x, y) = ctx.split_dispatch(*n);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        // Draw: one pass per step (the 32-bit path's second step must see the first's depths).
        let steps = self.pipelines.draw.len();
        for (step, pipe) in self.pipelines.draw.iter().enumerate() {
            let layout0 = pipe.get_bind_group_layout(0);
            let mut e0 = vec![entry(0, self.frame_uniforms.as_entire_binding()), entry(1, self.keys.as_entire_binding())];
            // Every draw pass counts except the 32-bit path's first step.
            if self.path == AtomicPath::U64 || step == 1 {
                e0.push(entry(2, self.counters.as_entire_binding()));
            }
            if step == 1 {
                e0.push(entry(3, self.indices.as_ref().expect("32-bit path").as_entire_binding()));
            }
            let bg0 = dev.create_bind_group(&wgpu::BindGroupDescriptor { label: None, layout: &layout0, entries: &e0 });
            let layout1 = pipe.get_bind_group_layout(1);
            let groups1: Vec<(wgpu::BindGroup, u32)> = ranges
                .iter()
                .map(|&(chunk, first, count)| {
                    let c = &scene.chunks[chunk];
                    let rec = wgpu::BufferBinding { buffer: records_buf, offset: first as u64 * record_size, size: NonZeroU64::new(count as u64 * record_size) };
                    let bg = dev.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: None,
                        layout: &layout1,
                        entries: &[
                            entry(0, wgpu::BindingResource::Buffer(rec)),
                            entry(1, c.words[0].as_entire_binding()),
                            entry(2, c.words[1].as_entire_binding()),
                            entry(3, c.words[2].as_entire_binding()),
                        ],
                    });
                    (bg, count as u32)
                })
                .collect();
            let ts = self.queries.as_ref().map(|(set, _)| wgpu::ComputePassTimestampWrites {
                query_set: set,
                beginning_of_pass_write_index: (step == 0).then_some(2),
                end_of_pass_write_index: (step + 1 == steps).then_some(3),
            });
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(Pass::ALL[1 + step].file()), timestamp_writes: ts });
            pass.set_pipeline(pipe);
            pass.set_bind_group(0, &bg0, &[]);
            for (bg, n) in &groups1 {
                let (x, y) = ctx.split_dispatch(*n);
                pass.set_bind_group(1, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        // Resolve: one dispatch per chunk.
        if let Some(background) = resolve {
            let pixels = self.width as u64 * self.height as u64;
            if self.image.is_none() {
                self.image = Some(storage(ctx, "image", pixels * 4, wgpu::BufferUsages::COPY_SRC));
            }
            while self.resolve_uniforms.len() < scene.chunks.len().max(1) {
                self.resolve_uniforms.push(dev.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("resolve uniforms"),
                    size: std::mem::size_of::<ResolveUniforms>() as u64,
                    usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }));
            }
            let (index_buf, stride, depth_offset) = match &self.indices {
                None => (&self.keys, 2, 1),
                Some(ix) => (ix, 1, 0),
            };
            let layout = self.pipelines.resolve.get_bind_group_layout(0);
            let image = self.image.as_ref().expect("made above");
            let empty_colors;
            let mut groups = Vec::new();
            let chunk_list: Vec<(u32, u32, Option<&wgpu::Buffer>)> = if scene.chunks.is_empty() {
                empty_colors = storage(ctx, "no colours", 4, wgpu::BufferUsages::empty());
                vec![(0, 0, Some(&empty_colors))]
            } else {
                scene.chunks.iter().map(|c| (c.first_index, c.len, c.colors.as_ref())).collect()
            };
            for (i, (first_index, count, colors)) in chunk_list.into_iter().enumerate() {
                let u = ResolveUniforms {
                    width: self.width,
                    height: self.height,
                    key_stride: stride,
                    depth_offset,
                    first_index,
                    count,
                    background,
                    write_background: (i == 0) as u32,
                };
                ctx.queue.write_buffer(&self.resolve_uniforms[i], 0, bytemuck::bytes_of(&u));
                let colors = colors.expect("scene has colours");
                groups.push(dev.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: None,
                    layout: &layout,
                    entries: &[
                        entry(0, self.resolve_uniforms[i].as_entire_binding()),
                        entry(1, index_buf.as_entire_binding()),
                        entry(2, self.keys.as_entire_binding()),
                        entry(3, colors.as_entire_binding()),
                        entry(4, image.as_entire_binding()),
                    ],
                }));
            }
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some("resolve"), timestamp_writes: self.timestamps(4) });
            pass.set_pipeline(&self.pipelines.resolve);
            let (x, y) = ctx.split_dispatch(pixels.div_ceil(256) as u32);
            for bg in &groups {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        let counters_read = readback(ctx, &mut enc, &self.counters, 8);
        let times_read = self.queries.as_ref().map(|(set, buf)| {
            enc.resolve_query_set(set, 0..QUERIES, buf, 0);
            readback(ctx, &mut enc, buf, QUERIES as u64 * 8)
        });
        ctx.queue.submit([enc.finish()]);
        let counters = map_read(ctx, &counters_read)?;
        let c: &[u32] = bytemuck::cast_slice(&counters);
        stats.points_drawn = c[0] as u64 | (c[1] as u64) << 32;
        let timings = match times_read {
            Some(buf) => {
                let t = map_read(ctx, &buf)?;
                let t: Vec<u64> = t.chunks_exact(8).map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes"))).collect();
                let period = ctx.queue.get_timestamp_period() as f64 * 1e-6;
                let ms = |a: usize| t[a + 1].saturating_sub(t[a]) as f64 * period;
                Some(GpuTimings { clear_ms: ms(0), draw_ms: ms(2), resolve_ms: resolve.map(|_| ms(4)) })
            }
            None => None,
        };
        ctx.check()?;
        Ok(GpuFrame { stats, timings, plan_seconds, frame_seconds: start.elapsed().as_secs_f64() })
    }

    /// The framebuffer's keys as the CPU rasterizer writes them (`depth bits << 32 | index`,
    /// [`EMPTY_KEY`] for an empty pixel), row-major from the top-left pixel.
    pub fn read_keys(&self, ctx: &GpuContext) -> Result<Vec<u64>, GpuError> {
        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read keys") });
        let keys = readback(ctx, &mut enc, &self.keys, self.keys.size());
        let indices = self.indices.as_ref().map(|ix| readback(ctx, &mut enc, ix, ix.size()));
        ctx.queue.submit([enc.finish()]);
        let keys = map_read(ctx, &keys)?;
        let pixels = self.width as usize * self.height as usize;
        Ok(match indices {
            None => bytemuck::pod_collect_to_vec::<u8, u64>(&keys)[..pixels].to_vec(),
            Some(ix) => {
                let ix = map_read(ctx, &ix)?;
                let d: Vec<u32> = bytemuck::pod_collect_to_vec(&keys);
                let i: Vec<u32> = bytemuck::pod_collect_to_vec(&ix);
                (0..pixels).map(|p| if d[p] == u32::MAX { EMPTY_KEY } else { (d[p] as u64) << 32 | i[p] as u64 }).collect()
            }
        })
    }

    /// The resolved image (RGBA8 packed `r | g << 8 | b << 16 | a << 24`, row-major) of the last
    /// frame drawn with `resolve`.
    pub fn read_image(&self, ctx: &GpuContext) -> Result<Vec<u32>, GpuError> {
        let Some(image) = &self.image else { return Err(GpuError::Colors("no frame was resolved yet".into())) };
        read_image_buffer(ctx, image, self.width, self.height)
    }
}

/// The first `width * height` RGBA8 pixels of an image buffer (a resolve pass's output).
pub(crate) fn read_image_buffer(ctx: &GpuContext, image: &wgpu::Buffer, width: u32, height: u32) -> Result<Vec<u32>, GpuError> {
    let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read image") });
    let buf = readback(ctx, &mut enc, image, image.size());
    ctx.queue.submit([enc.finish()]);
    let bytes = map_read(ctx, &buf)?;
    Ok(bytemuck::pod_collect_to_vec::<u8, u32>(&bytes)[..width as usize * height as usize].to_vec())
}

/// A mappable copy of `size` bytes of `src`, recorded in `enc`.
pub(crate) fn readback(ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, src: &wgpu::Buffer, size: u64) -> wgpu::Buffer {
    let dst = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    enc.copy_buffer_to_buffer(src, 0, &dst, 0, size);
    dst
}

/// Maps a readback buffer (after its copy was submitted) and returns its bytes.
pub(crate) fn map_read(ctx: &GpuContext, buf: &wgpu::Buffer) -> Result<Vec<u8>, GpuError> {
    let (tx, rx) = mpsc::channel();
    buf.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    ctx.wait()?;
    match rx.recv() {
        Ok(Ok(())) => {}
        Ok(Err(e)) => return Err(GpuError::Device(format!("cannot read back: {e}"))),
        Err(_) => return Err(GpuError::Device("read back never completed".into())),
    }
    let bytes = buf.get_mapped_range(..).map_err(|e| GpuError::Device(format!("cannot read back: {e}")))?.to_vec();
    buf.unmap();
    Ok(bytes)
}
