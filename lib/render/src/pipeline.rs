//! The long-lived GPU state of the renderers, built once when a renderer is made (the re_renderer
//! manner): each pass's compute pipeline with explicit bind-group layouts made from its binding
//! table in [`crate::shaders`], and the helpers that make bind groups and buffers from the same
//! tables. Nothing here changes from frame to frame.

use crate::context::GpuContext;
use crate::shaders::{binding, Binding, BindingKind, Pass};

/// The layout of bind group `group` from the entries of `bindings` in that group.
pub(crate) fn bind_group_layout(
    ctx: &GpuContext,
    label: &str,
    bindings: &[Binding],
    group: u32,
    visibility: wgpu::ShaderStages,
) -> wgpu::BindGroupLayout {
    let entries: Vec<wgpu::BindGroupLayoutEntry> = bindings
        .iter()
        .filter(|b| b.group == group)
        .map(|b| wgpu::BindGroupLayoutEntry {
            binding: b.binding,
            visibility,
            ty: wgpu::BindingType::Buffer {
                ty: match b.kind {
                    BindingKind::Uniform => wgpu::BufferBindingType::Uniform,
                    BindingKind::StorageRead => {
                        wgpu::BufferBindingType::Storage { read_only: true }
                    }
                    BindingKind::StorageReadWrite => {
                        wgpu::BufferBindingType::Storage { read_only: false }
                    }
                },
                has_dynamic_offset: false,
                // Checked against the shader's types when a pass runs.
                min_binding_size: None,
            },
            count: None,
        })
        .collect();
    ctx.device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(label),
        entries: &entries,
    })
}

/// The compute passes `passes` over one bind group (group 0, from `bindings`), sharing its
/// layout: the GPU octree builder's passes and the radix sort's, which bind one set of buffers to
/// every pass they run. Returns the layout and each pass's pipeline.
pub(crate) fn one_group_pipelines(
    ctx: &GpuContext,
    label: &str,
    bindings: &[Binding],
    passes: impl Iterator<Item = Pass>,
) -> (wgpu::BindGroupLayout, Vec<(Pass, wgpu::ComputePipeline)>) {
    let layout = bind_group_layout(ctx, label, bindings, 0, wgpu::ShaderStages::COMPUTE);
    let pl = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: Some(label),
        bind_group_layouts: &[Some(&layout)],
        immediate_size: 0,
    });
    let pipelines = passes
        .map(|pass| {
            let module = ctx.device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(pass.file()),
                source: wgpu::ShaderSource::Wgsl(pass.source().into()),
            });
            let p = ctx.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(pass.file()),
                layout: Some(&pl),
                module: &module,
                entry_point: Some("main"),
                compilation_options: Default::default(),
                cache: None,
            });
            (pass, p)
        })
        .collect();
    (layout, pipelines)
}

/// Bind-group layouts several pipelines share, so that one bind group serves all of them.
pub(crate) struct SharedLayouts {
    /// Group 1 of every draw pass ([`binding::BATCHES`]: one chunk's records and words).
    batches: wgpu::BindGroupLayout,
}

impl SharedLayouts {
    pub(crate) fn new(ctx: &GpuContext) -> SharedLayouts {
        SharedLayouts {
            batches: bind_group_layout(
                ctx,
                "batches",
                &binding::BATCHES,
                1,
                wgpu::ShaderStages::COMPUTE,
            ),
        }
    }

    /// The layout of group 1 of the draw passes.
    pub(crate) fn batches(&self) -> &wgpu::BindGroupLayout {
        &self.batches
    }
}

/// One compute pass: its pipeline and the layouts of its bind groups (index = `@group`).
pub(crate) struct PassPipeline {
    pass: Pass,
    pipeline: wgpu::ComputePipeline,
    layouts: Vec<wgpu::BindGroupLayout>,
}

impl PassPipeline {
    /// Compiles `pass` with layouts from [`Pass::bindings`] (group 1 of the draw passes from
    /// `shared`).
    pub(crate) fn new(ctx: &GpuContext, pass: Pass, shared: &SharedLayouts) -> PassPipeline {
        PassPipeline::with_constants(ctx, pass, shared, &[])
    }

    /// [`new`](Self::new) with values for the WGSL module's `override` constants (name, value).
    pub(crate) fn with_constants(
        ctx: &GpuContext,
        pass: Pass,
        shared: &SharedLayouts,
        constants: &[(&str, f64)],
    ) -> PassPipeline {
        let bindings = pass.bindings();
        let groups = bindings.iter().map(|b| b.group + 1).max().unwrap_or(0);
        let layouts: Vec<wgpu::BindGroupLayout> = (0..groups)
            .map(|g| {
                if g == 1 && pass.draws_batches() {
                    shared.batches.clone()
                } else {
                    bind_group_layout(ctx, pass.file(), bindings, g, wgpu::ShaderStages::COMPUTE)
                }
            })
            .collect();
        let layout_refs: Vec<Option<&wgpu::BindGroupLayout>> = layouts.iter().map(Some).collect();
        let layout = ctx.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some(pass.file()),
            bind_group_layouts: &layout_refs,
            immediate_size: 0,
        });
        let module = ctx.device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(pass.file()),
            source: wgpu::ShaderSource::Wgsl(pass.source().into()),
        });
        let pipeline = ctx.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(pass.file()),
            layout: Some(&layout),
            module: &module,
            entry_point: Some("main"),
            // The passes initialise the little workgroup memory they use (common/counters.wgsl).
            compilation_options: wgpu::PipelineCompilationOptions {
                constants,
                zero_initialize_workgroup_memory: false,
            },
            cache: None,
        });
        PassPipeline { pass, pipeline, layouts }
    }

    /// The pass.
    pub(crate) fn pass(&self) -> Pass {
        self.pass
    }

    /// The compute pipeline.
    pub(crate) fn pipeline(&self) -> &wgpu::ComputePipeline {
        &self.pipeline
    }

    /// A bind group of group `group` from `entries` (made with [`entry`] from the pass's
    /// bindings).
    pub(crate) fn bind_group(
        &self,
        ctx: &GpuContext,
        group: u32,
        entries: &[wgpu::BindGroupEntry<'_>],
    ) -> wgpu::BindGroup {
        ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(self.pass.file()),
            layout: &self.layouts[group as usize],
            entries,
        })
    }
}

/// A bind-group entry for `binding` (one of [`crate::shaders::binding`]).
pub(crate) fn entry(
    binding: Binding,
    resource: wgpu::BindingResource<'_>,
) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry { binding: binding.binding, resource }
}

/// A batches bind group (group 1 of the draw passes) over `records` and one chunk's words.
pub(crate) fn batches_group(
    ctx: &GpuContext,
    shared: &SharedLayouts,
    records: wgpu::BufferBinding<'_>,
    words: &[wgpu::Buffer; 3],
) -> wgpu::BindGroup {
    ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("batches"),
        layout: shared.batches(),
        entries: &[
            entry(binding::RECORDS, wgpu::BindingResource::Buffer(records)),
            entry(binding::COARSE, words[0].as_entire_binding()),
            entry(binding::MEDIUM, words[1].as_entire_binding()),
            entry(binding::FINE, words[2].as_entire_binding()),
        ],
    })
}

/// A storage buffer of `size` bytes (at least 4) with the `extra` usages.
pub(crate) fn storage(
    ctx: &GpuContext,
    label: &str,
    size: u64,
    extra: wgpu::BufferUsages,
) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: size.max(4),
        usage: wgpu::BufferUsages::STORAGE | extra,
        mapped_at_creation: false,
    })
}

/// A uniform buffer holding one `T`, written with `queue.write_buffer`.
pub(crate) fn uniform<T: bytemuck::Pod>(ctx: &GpuContext, label: &str) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: std::mem::size_of::<T>() as u64,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// Timestamp queries of one renderer: the query set and the buffer it is resolved into.
pub(crate) struct Timestamps {
    pub(crate) set: wgpu::QuerySet,
    pub(crate) buffer: wgpu::Buffer,
}

impl Timestamps {
    pub(crate) fn new(ctx: &GpuContext, label: &str, count: u32) -> Timestamps {
        let set = ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some(label),
            ty: wgpu::QueryType::Timestamp,
            count,
        });
        let buffer = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: count as u64 * 8,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        Timestamps { set, buffer }
    }

    /// The writes of a pass: slot `begin` at its start, `end` at its end (either may be absent).
    pub(crate) fn writes(
        &self,
        begin: Option<u32>,
        end: Option<u32>,
    ) -> wgpu::ComputePassTimestampWrites<'_> {
        wgpu::ComputePassTimestampWrites {
            query_set: &self.set,
            beginning_of_pass_write_index: begin,
            end_of_pass_write_index: end,
        }
    }
}
