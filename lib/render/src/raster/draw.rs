//! One frame: the batches planned (on the GPU by the plan pass, or on the host with the same
//! [`Planner`]) into draw records, then the clear and draw passes, the resolve when asked, and
//! the counters and pass times read back.

use super::report::{resolve_timings, GpuFrame, GpuTimings, PLAN_QUERIES, QUERIES};
use super::tuning::RecordOrder;
use super::GpuRasterizer;
use crate::buffers::{grown_size, map_read, readback};
use crate::context::{GpuContext, GpuError};
use crate::pipeline::{batches_group, entry, storage};
use crate::scene::GpuScene;
use crate::shaders::binding;
use mortar_core::render::gpu::{plan_counter, DrawRecord, FrameUniforms, PlanUniforms};
use mortar_core::render::resolve::ResolveOptions;
use mortar_core::render::{BatchPlan, Camera, Planner, RasterError, RasterOptions, RasterStats};
use rayon::prelude::*;
use std::num::NonZeroU64;
use std::time::Instant;

/// Batches from which the host plans them in parallel.
const PARALLEL_PLAN_MIN: usize = 4096;

impl GpuRasterizer {
    /// Draws the scene for `camera` into a cleared framebuffer; with `resolve` also resolves the
    /// image from the scene's colours as [`mortar_core::render::resolve::resolve`] does (hole
    /// filling, colours, eye-dome lighting, background). Waits for the GPU.
    pub fn draw(
        &mut self,
        ctx: &GpuContext,
        scene: &mut GpuScene,
        camera: &Camera,
        options: &RasterOptions,
        resolve: Option<&ResolveOptions>,
    ) -> Result<GpuFrame, GpuError> {
        self.draw_selected(ctx, scene, None, camera, options, resolve)
    }

    /// [`draw`](Self::draw) of only the scene's batches listed in `selected` (positions in
    /// [`GpuScene::batches`], any order, each at most once; `None`: every batch). The framebuffer
    /// holds the scene's point indices as usual, so the resolve needs no change: this is how a
    /// level-of-detail selection is drawn from a scene holding every node once.
    pub fn draw_selected(
        &mut self,
        ctx: &GpuContext,
        scene: &mut GpuScene,
        selected: Option<&[u32]>,
        camera: &Camera,
        options: &RasterOptions,
        resolve: Option<&ResolveOptions>,
    ) -> Result<GpuFrame, GpuError> {
        let start = Instant::now();
        let (width, height) = self.size();
        if camera.width != width || camera.height != height {
            return Err(RasterError::Viewport {
                fb_width: width,
                fb_height: height,
                width: camera.width,
                height: camera.height,
            }
            .into());
        }
        if let Some(r) = resolve {
            self.check_resolve(ctx, scene, r)?;
        }
        scene.flush(ctx)?;
        let record_size = std::mem::size_of::<DrawRecord>() as u64;
        let mut stats = RasterStats::default();
        // Every batch planned on the GPU (the plan pass writes the records) or, for a selection or
        // when asked, on the host with the same plan.
        let on_gpu = selected.is_none() && self.tuning.plan_on_gpu && !scene.batches.is_empty();
        let ranges: Vec<(usize, usize, usize)> = if on_gpu {
            Planner::new(camera, scene.grid(), options)?;
            let f = &mut self.per_frame;
            let needed = (scene.records_total as u64 * record_size).max(record_size);
            if f.records.size() < needed {
                let size = grown_size(ctx, f.records.size(), needed);
                f.records = storage(ctx, "draw records", size, wgpu::BufferUsages::COPY_DST);
            }
            let mut u = PlanUniforms::new(
                camera,
                scene.grid(),
                options,
                self.tuning.division.unwrap_or(ctx.division()),
            );
            u.batches = scene.batches.len() as u32;
            ctx.queue.write_buffer(&f.plan_uniforms, 0, bytemuck::bytes_of(&u));
            ctx.queue.write_buffer(&f.plan_counters, 0, &[0u8; 4 * plan_counter::WORDS]);
            stats.batches = scene.batches.len() as u64;
            scene
                .record_ranges
                .iter()
                .enumerate()
                .filter(|r| r.1 .1 > 0)
                .map(|(chunk, &(first, count))| (chunk, first as usize, count as usize))
                .collect()
        } else {
            self.plan_on_host(ctx, scene, selected, camera, options, &mut stats)?
        };
        let plan_seconds = start.elapsed().as_secs_f64();
        if let Some(r) = ranges.iter().find(|r| r.2 as u64 * record_size > ctx.max_binding()) {
            return Err(GpuError::TooLarge {
                what: "one chunk's draw records",
                needed: r.2 as u64 * record_size,
                limit: ctx.max_binding(),
            });
        }
        let f = &mut self.per_frame;
        ctx.queue.write_buffer(
            &f.frame_uniforms,
            0,
            bytemuck::bytes_of(&FrameUniforms::new(
                camera,
                self.tuning.division.unwrap_or(ctx.division()),
            )),
        );
        ctx.queue.write_buffer(&f.counters, 0, &[0u8; 8]);
        let f = &self.per_frame;
        let t = &self.target;
        let passes = &self.passes;
        let queries = self.queries.as_ref();

        let dev = &ctx.device;
        let mut enc =
            dev.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        if on_gpu {
            let Some(plan_batches) = &scene.plan_buffer else {
                return Err(GpuError::Device("the scene's plan batches were not written".into()));
            };
            let group = passes.plan.bind_group(
                ctx,
                0,
                &[
                    entry(binding::PLAN_PARAMS, f.plan_uniforms.as_entire_binding()),
                    entry(binding::PLAN_BATCHES, plan_batches.as_entire_binding()),
                    entry(binding::PLAN_RECORDS, f.records.as_entire_binding()),
                    entry(binding::PLAN_COUNTERS, f.plan_counters.as_entire_binding()),
                ],
            );
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("plan"),
                timestamp_writes: queries
                    .map(|q| q.writes(Some(PLAN_QUERIES), Some(PLAN_QUERIES + 1))),
            });
            pass.set_pipeline(passes.plan.pipeline());
            pass.set_bind_group(0, &group, &[]);
            let (x, y) = ctx.split_dispatch((scene.batches.len() as u32).div_ceil(256));
            pass.dispatch_workgroups(x, y, 1);
        }
        // Clear.
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("clear"),
                timestamp_writes: queries.map(|q| q.writes(Some(0), Some(1))),
            });
            pass.set_pipeline(passes.clear.pipeline());
            for (bg, n) in &t.clear_groups {
                let (x, y) = ctx.split_dispatch(*n);
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        // Draw: one pass per step (the 32-bit path's second step must see the first's depths),
        // every step with the same batches bind groups (one per chunk).
        let batches: Vec<(wgpu::BindGroup, u32)> = ranges
            .iter()
            .map(|&(chunk, first, count)| {
                let rec = wgpu::BufferBinding {
                    buffer: &f.records,
                    offset: first as u64 * record_size,
                    size: NonZeroU64::new(count as u64 * record_size),
                };
                (batches_group(ctx, &passes.shared, rec, &scene.chunks[chunk].words), count as u32)
            })
            .collect();
        let steps = passes.draw.steps();
        for (step, (pipe, group0)) in steps.iter().zip(&t.draw_groups).enumerate() {
            let ts = queries.map(|q| {
                q.writes((step == 0).then_some(2), (step + 1 == steps.len()).then_some(3))
            });
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some(pipe.pass().file()),
                timestamp_writes: ts,
            });
            pass.set_pipeline(pipe.pipeline());
            pass.set_bind_group(0, group0, &[]);
            for (bg, n) in &batches {
                let (x, y) = ctx.split_dispatch(*n);
                pass.set_bind_group(1, bg, &[]);
                pass.dispatch_workgroups(x, y, 1);
            }
        }
        if let Some(r) = resolve {
            self.encode_resolve(ctx, &mut enc, scene, r)?;
        }
        let counters_read = readback(ctx, &mut enc, &self.per_frame.counters, 8);
        let plan_read = on_gpu.then(|| {
            readback(ctx, &mut enc, &self.per_frame.plan_counters, 4 * plan_counter::WORDS as u64)
        });
        let times_read = self.queries.as_ref().map(|q| {
            enc.resolve_query_set(&q.set, 0..QUERIES, &q.buffer, 0);
            readback(ctx, &mut enc, &q.buffer, QUERIES as u64 * 8)
        });
        ctx.queue.submit([enc.finish()]);
        let counters = map_read(ctx, &counters_read)?;
        let c: &[u32] = bytemuck::cast_slice(&counters);
        stats.points_drawn = c[0] as u64 | (c[1] as u64) << 32;
        if let Some(buf) = plan_read {
            let pc: Vec<u32> = bytemuck::pod_collect_to_vec(&map_read(ctx, &buf)?);
            stats.batches_culled = pc[plan_counter::CULLED] as u64;
            stats.batches_drawn = pc[plan_counter::DRAWN] as u64;
            for w in 0..3 {
                stats.points_by_precision[w] = pc[plan_counter::POINTS_BY_WORDS + w] as u64;
            }
        }
        let timings = match times_read {
            Some(buf) => {
                let t: Vec<u64> = bytemuck::pod_collect_to_vec(&map_read(ctx, &buf)?);
                let period = ctx.queue.get_timestamp_period() as f64 * 1e-6;
                let ms = |a: usize| t[a + 1].saturating_sub(t[a]) as f64 * period;
                let post = resolve.map(|r| resolve_timings(&t, period, r));
                Some(GpuTimings {
                    clear_ms: ms(0),
                    draw_ms: ms(2),
                    resolve_ms: post.map(|p| p.1),
                    hole_fill_ms: post.and_then(|p| p.0),
                    eye_dome_ms: post.and_then(|p| p.2),
                    plan_ms: on_gpu.then(|| ms(PLAN_QUERIES as usize)),
                })
            }
            None => None,
        };
        ctx.check()?;
        Ok(GpuFrame { stats, timings, plan_seconds, frame_seconds: start.elapsed().as_secs_f64() })
    }

    /// Plans the batches (all, or those `selected`) on the host, writes their records per chunk
    /// (each chunk's records starting at a storage-offset boundary; padding records have no
    /// points) and returns the chunks' record ranges `(chunk, first record, count)`.
    fn plan_on_host(
        &mut self,
        ctx: &GpuContext,
        scene: &GpuScene,
        selected: Option<&[u32]>,
        camera: &Camera,
        options: &RasterOptions,
        stats: &mut RasterStats,
    ) -> Result<Vec<(usize, usize, usize)>, GpuError> {
        let planner = Planner::new(camera, scene.grid(), options)?;
        // The batches to draw, in scene order (so that each chunk's records are contiguous).
        let order: Vec<u32> = match selected {
            None => (0..scene.batches.len() as u32).collect(),
            Some(ids) => {
                let mut v = ids.to_vec();
                v.sort_unstable();
                v.dedup();
                if let Some(&bad) = v.iter().find(|&&i| i as usize >= scene.batches.len()) {
                    return Err(GpuError::Selection(format!(
                        "batch {bad} selected, but the scene holds {}",
                        scene.batches.len()
                    )));
                }
                v
            }
        };
        let plan = |&i: &u32| {
            let b = &scene.batches[i as usize];
            planner.plan(&b.grid, &b.bounds, b.count as usize)
        };
        // A batch's plan is a few dozen arithmetic operations: below a few thousand batches it
        // costs less than waking rayon's threads, which a build beside the view (`build
        // --preview`) keeps busy (frames then waited for the build's jobs: issue 29).
        let plans: Vec<BatchPlan> = if order.len() < PARALLEL_PLAN_MIN {
            order.iter().map(plan).collect()
        } else {
            order.par_iter().map(plan).collect()
        };
        stats.batches = plans.len() as u64;
        let align = ctx.limits().min_storage_buffer_offset_alignment.max(1) as usize;
        let mut records: Vec<DrawRecord> = Vec::new();
        let mut ranges: Vec<(usize, usize, usize)> = Vec::new();
        for (b, plan) in order.iter().map(|&i| &scene.batches[i as usize]).zip(&plans) {
            match plan {
                BatchPlan::Empty => {}
                BatchPlan::Culled => stats.batches_culled += 1,
                BatchPlan::Draw { precision, projection } => {
                    stats.batches_drawn += 1;
                    stats.points_by_precision[precision.words() - 1] += b.count as u64;
                    match ranges.last_mut() {
                        Some(r) if r.0 == b.chunk as usize => r.2 += 1,
                        _ => {
                            while !(records.len() * std::mem::size_of::<DrawRecord>())
                                .is_multiple_of(align)
                            {
                                records.push(bytemuck::Zeroable::zeroed());
                            }
                            ranges.push((b.chunk as usize, records.len(), 1));
                        }
                    }
                    records.push(DrawRecord {
                        projection: *projection,
                        offset: b.offset,
                        count: b.count,
                        first_index: b.first_index,
                        _pad: 0,
                    });
                }
            }
        }
        if self.tuning.order != RecordOrder::Scene {
            for &(_, first, count) in &ranges {
                let part = records[first..first + count].to_vec();
                for (dst, src) in self.tuning.order.permutation(count).into_iter().enumerate() {
                    records[first + dst] = part[src];
                }
            }
        }
        let record_size = std::mem::size_of::<DrawRecord>() as u64;
        let f = &mut self.per_frame;
        let needed = (records.len() as u64 * record_size).max(record_size);
        if f.records.size() < needed {
            let size = grown_size(ctx, f.records.size(), needed);
            f.records = storage(ctx, "draw records", size, wgpu::BufferUsages::COPY_DST);
        }
        if !records.is_empty() {
            ctx.queue.write_buffer(&f.records, 0, bytemuck::cast_slice(&records));
        }
        Ok(ranges)
    }
}
