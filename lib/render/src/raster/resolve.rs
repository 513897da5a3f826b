//! The resolve's passes on the GPU, as [`mortar_core::render::resolve::resolve`] does on the
//! host: hole filling into the filled keys, one colour dispatch per chunk, eye-dome lighting of
//! the image; recorded into a frame's encoder or run again on the last frame's keys.

use super::report::{resolve_timings, GpuTimings, QUERIES, RESOLVE_QUERIES};
use super::GpuRasterizer;
use crate::buffers::{map_read, readback};
use crate::context::{GpuContext, GpuError};
use crate::pipeline::{entry, uniform};
use crate::scene::GpuScene;
use crate::shaders::binding;
use mortar_core::render::gpu::{EyeDomeUniforms, HoleFillUniforms, ResolveUniforms};
use mortar_core::render::resolve::ResolveOptions;

impl GpuRasterizer {
    /// Resolves the framebuffer as it is (the last frame drawn) again, with `options` and the
    /// scene's colours as they are now: for callers that choose colours after seeing the keys
    /// (`mortar render` colours scalar modes by the visible points' percentiles), then
    /// [`GpuScene::set_colors`]. Waits for the GPU; returns the passes' times (hole fill,
    /// resolve, eye-dome lighting) where the device has timestamps.
    pub fn resolve(
        &mut self,
        ctx: &GpuContext,
        scene: &mut GpuScene,
        options: &ResolveOptions,
    ) -> Result<Option<GpuTimings>, GpuError> {
        self.check_resolve(ctx, scene, options)?;
        scene.flush(ctx)?;
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("resolve") });
        self.encode_resolve(ctx, &mut enc, scene, options)?;
        let times_read = self.queries.as_ref().map(|q| {
            enc.resolve_query_set(&q.set, 0..QUERIES, &q.buffer, 0);
            readback(ctx, &mut enc, &q.buffer, QUERIES as u64 * 8)
        });
        ctx.queue.submit([enc.finish()]);
        let timings = match times_read {
            Some(buf) => {
                let t: Vec<u64> = bytemuck::pod_collect_to_vec(&map_read(ctx, &buf)?);
                let period = ctx.queue.get_timestamp_period() as f64 * 1e-6;
                let (hole_fill_ms, resolve_ms, eye_dome_ms) = resolve_timings(&t, period, options);
                Some(GpuTimings {
                    clear_ms: 0.0,
                    draw_ms: 0.0,
                    resolve_ms: Some(resolve_ms),
                    hole_fill_ms,
                    eye_dome_ms,
                    plan_ms: None,
                })
            }
            None => {
                ctx.wait()?;
                None
            }
        };
        ctx.check()?;
        Ok(timings)
    }

    /// Whether `scene` and this rasterizer can resolve with `options`.
    pub(super) fn check_resolve(
        &self,
        ctx: &GpuContext,
        scene: &GpuScene,
        options: &ResolveOptions,
    ) -> Result<(), GpuError> {
        if !scene.has_colors() {
            return Err(GpuError::Colors("resolve asked for but the scene has no colours".into()));
        }
        if options.hole_fill.is_some() && self.target.filled.is_none() {
            let needed = self.target.width as u64 * self.target.height as u64 * 8;
            return Err(GpuError::TooLarge {
                what: "the hole-filled keys",
                needed,
                limit: ctx.max_binding(),
            });
        }
        Ok(())
    }

    /// Records the resolve's passes into `enc`: hole filling (the framebuffer into the filled
    /// keys), one colour dispatch per chunk from the filled keys or the framebuffer, eye-dome
    /// lighting of the image from the same keys' depths.
    pub(super) fn encode_resolve(
        &mut self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        scene: &GpuScene,
        options: &ResolveOptions,
    ) -> Result<(), GpuError> {
        let (width, height) = self.size();
        let pixels = width as u64 * height as u64;
        let t = &mut self.target;
        let passes = &self.passes;
        let queries = self.queries.as_ref();
        let f = &mut self.per_frame;
        let (split_x, split_y) = ctx.split_dispatch(pixels.div_ceil(256) as u32);
        let (index_words, depth_words, stride, depth_offset) = t.keys.words();
        // Where the colours and the eye-dome depths are read from.
        let (index_buf, depth_buf, stride, depth_offset, eye_dome_group) =
            match (&options.hole_fill, &t.filled) {
                (Some(fill), Some((filled, fill_group, edl_group))) => {
                    let u = HoleFillUniforms::new(fill, width, height, stride, depth_offset);
                    ctx.queue.write_buffer(&f.fill_uniforms, 0, bytemuck::bytes_of(&u));
                    let slots = (Some(RESOLVE_QUERIES), Some(RESOLVE_QUERIES + 1));
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("hole fill"),
                        timestamp_writes: queries.map(|q| q.writes(slots.0, slots.1)),
                    });
                    pass.set_pipeline(passes.hole_fill.pipeline());
                    pass.set_bind_group(0, fill_group, &[]);
                    pass.dispatch_workgroups(split_x, split_y, 1);
                    (filled, filled, 2, 1, edl_group)
                }
                (Some(_), None) => {
                    return Err(GpuError::TooLarge {
                        what: "the hole-filled keys",
                        needed: pixels * 8,
                        limit: ctx.max_binding(),
                    })
                }
                (None, _) => (index_words, depth_words, stride, depth_offset, &t.eye_dome_group),
            };
        // Colours: one dispatch per chunk.
        while f.resolve_uniforms.len() < scene.chunks.len().max(1) {
            f.resolve_uniforms.push(uniform::<ResolveUniforms>(ctx, "resolve uniforms"));
        }
        let chunk_list: Vec<(u32, u32, Option<&wgpu::Buffer>)> = if scene.chunks.is_empty() {
            vec![(0, 0, Some(&self.no_colors))]
        } else {
            scene.chunks.iter().map(|c| (c.first_index, c.len, c.colors.as_ref())).collect()
        };
        let mut groups = Vec::with_capacity(chunk_list.len());
        for (i, (first_index, count, colors)) in chunk_list.into_iter().enumerate() {
            // Checked by check_resolve: a scene with colours has them in every chunk.
            let Some(colors) = colors else {
                return Err(GpuError::Colors("a chunk of the scene has no colours".into()));
            };
            let u = ResolveUniforms {
                width,
                height,
                key_stride: stride,
                depth_offset,
                first_index,
                count,
                background: options.background,
                write_background: (i == 0) as u32,
            };
            ctx.queue.write_buffer(&f.resolve_uniforms[i], 0, bytemuck::bytes_of(&u));
            groups.push(passes.resolve.bind_group(
                ctx,
                0,
                &[
                    entry(binding::RESOLVE_PARAMS, f.resolve_uniforms[i].as_entire_binding()),
                    entry(binding::RESOLVE_INDEX_WORDS, index_buf.as_entire_binding()),
                    entry(binding::RESOLVE_DEPTH_WORDS, depth_buf.as_entire_binding()),
                    entry(binding::RESOLVE_COLORS, colors.as_entire_binding()),
                    entry(binding::RESOLVE_IMAGE, t.image.as_entire_binding()),
                ],
            ));
        }
        {
            let slots = (Some(RESOLVE_QUERIES + 2), Some(RESOLVE_QUERIES + 3));
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("resolve"),
                timestamp_writes: queries.map(|q| q.writes(slots.0, slots.1)),
            });
            pass.set_pipeline(passes.resolve.pipeline());
            for bg in &groups {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(split_x, split_y, 1);
            }
        }
        if let Some(edl) = &options.eye_dome {
            let u = EyeDomeUniforms::new(edl, width, height, stride, depth_offset);
            ctx.queue.write_buffer(&f.eye_dome_uniforms, 0, bytemuck::bytes_of(&u));
            let slots = (Some(RESOLVE_QUERIES + 4), Some(RESOLVE_QUERIES + 5));
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("eye-dome lighting"),
                timestamp_writes: queries.map(|q| q.writes(slots.0, slots.1)),
            });
            pass.set_pipeline(passes.eye_dome.pipeline());
            pass.set_bind_group(0, eye_dome_group, &[]);
            pass.dispatch_workgroups(split_x, split_y, 1);
        }
        t.resolved = true;
        Ok(())
    }
}
