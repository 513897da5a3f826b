//! Shader checks that need no GPU: naga parses and validates every pass exactly as the pipelines
//! assemble it (with 64-bit capabilities only where the pass needs them), every pass declares
//! exactly the bindings of its Rust table (the one the pipelines build their bind-group layouts
//! from), and every struct shared with WGSL has the same size and member offsets as its
//! `#[repr(C)]` Rust twin.

use mortar_core::render::gpu::{
    BatchProjection, DrawRecord, EyeDomeUniforms, FrameUniforms, HoleFillUniforms, OctreeNode,
    OctreeUniforms, PlanBatch, PlanUniforms, PrepareUniforms, ReframeUniforms, ResolveUniforms,
    ScatterUniforms, SortUniforms,
};
use mortar_core::render::progressive::UNLOADED;
use mortar_core::render::resolve::{EDL_EXP2_COEFFS, EDL_LOG2_COEFFS};
use mortar_render::progressive::SLOTS_PER_THREAD;
use mortar_render::shaders::{binding, Binding, BindingKind, Pass, PRESENT, PRESENT_BINDINGS};
use naga::valid::{Capabilities, ValidationFlags, Validator};
use std::mem::{offset_of, size_of};

fn parse(pass: Pass) -> naga::Module {
    let src = pass.source();
    naga::front::wgsl::parse_str(&src)
        .unwrap_or_else(|e| panic!("{}: {}", pass.file(), e.emit_to_string(&src)))
}

#[test]
fn every_pass_validates_with_the_capabilities_it_is_given() {
    for pass in Pass::ALL {
        let module = parse(pass);
        let caps = if pass.needs_int64() {
            Capabilities::SHADER_INT64 | Capabilities::SHADER_INT64_ATOMIC_MIN_MAX
        } else {
            Capabilities::empty()
        };
        let src = pass.source();
        Validator::new(ValidationFlags::all(), caps)
            .validate(&module)
            .unwrap_or_else(|e| panic!("{}: {}", pass.file(), e.emit_to_string(&src)));
        assert!(module.entry_points.iter().any(|e| e.name == "main"), "{}: no main", pass.file());
    }
    // The 64-bit pass really needs the capabilities: without them naga refuses it, so the
    // check above would notice a pass that silently stopped using 64-bit atomics.
    let module = parse(Pass::Draw64);
    assert!(
        Validator::new(ValidationFlags::all(), Capabilities::SHADER_INT64)
            .validate(&module)
            .is_err(),
        "atomicMin on u64 needs SHADER_INT64_ATOMIC_MIN_MAX"
    );
}

/// What a WGSL resource variable is, as wgpu's bind-group layouts distinguish them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Kind {
    Uniform,
    StorageRead,
    StorageReadWrite,
    Texture,
    StorageTexture,
    Sampler,
    /// Anything else with a binding (push constants, ...): never in a Rust table.
    Other,
}

impl From<BindingKind> for Kind {
    fn from(k: BindingKind) -> Kind {
        match k {
            BindingKind::Uniform => Kind::Uniform,
            BindingKind::StorageRead => Kind::StorageRead,
            BindingKind::StorageReadWrite => Kind::StorageReadWrite,
        }
    }
}

/// Every `@group(g) @binding(b)` the module declares: (group, binding, kind, name), sorted.
fn declared_bindings(module: &naga::Module) -> Vec<(u32, u32, Kind, String)> {
    let mut out: Vec<(u32, u32, Kind, String)> = module
        .global_variables
        .iter()
        .filter_map(|(_, var)| {
            let rb = var.binding.as_ref()?;
            let kind = match var.space {
                naga::AddressSpace::Uniform => Kind::Uniform,
                naga::AddressSpace::Storage { access }
                    if access.contains(naga::StorageAccess::STORE) =>
                {
                    Kind::StorageReadWrite
                }
                naga::AddressSpace::Storage { .. } => Kind::StorageRead,
                naga::AddressSpace::Handle => match module.types[var.ty].inner {
                    naga::TypeInner::Image { class: naga::ImageClass::Storage { .. }, .. } => {
                        Kind::StorageTexture
                    }
                    naga::TypeInner::Image { .. } => Kind::Texture,
                    naga::TypeInner::Sampler { .. } => Kind::Sampler,
                    _ => Kind::Other,
                },
                _ => Kind::Other,
            };
            Some((rb.group, rb.binding, kind, var.name.clone().unwrap_or_default()))
        })
        .collect();
    out.sort();
    out
}

/// The differences between what `module` declares and the Rust table `bindings` (empty: they
/// agree on every group, binding number, kind and variable name, and neither has an entry the
/// other lacks).
fn binding_mismatches(module: &naga::Module, bindings: &[Binding]) -> Vec<String> {
    let wgsl = declared_bindings(module);
    let mut rust: Vec<(u32, u32, Kind, String)> = bindings
        .iter()
        .map(|b| (b.group, b.binding, Kind::from(b.kind), b.name.to_string()))
        .collect();
    rust.sort();
    let mut out = Vec::new();
    for w in rust.windows(2) {
        if (w[0].0, w[0].1) == (w[1].0, w[1].1) {
            out.push(format!(
                "Rust lists @group({}) @binding({}) twice ({} and {})",
                w[0].0, w[0].1, w[0].3, w[1].3
            ));
        }
    }
    for r in &rust {
        match wgsl.iter().find(|w| (w.0, w.1) == (r.0, r.1)) {
            None => out.push(format!(
                "Rust has @group({}) @binding({}) {} ({:?}) that the WGSL does not declare",
                r.0, r.1, r.3, r.2
            )),
            Some(w) if w != r => out.push(format!(
                "@group({}) @binding({}): WGSL {} ({:?}), Rust {} ({:?})",
                r.0, r.1, w.3, w.2, r.3, r.2
            )),
            Some(_) => {}
        }
    }
    for w in &wgsl {
        if !rust.iter().any(|r| (r.0, r.1) == (w.0, w.1)) {
            out.push(format!(
                "the WGSL declares @group({}) @binding({}) {} ({:?}) that Rust does not list",
                w.0, w.1, w.3, w.2
            ));
        }
    }
    out
}

#[test]
fn every_pass_declares_exactly_its_rust_bindings() {
    for pass in Pass::ALL {
        let problems = binding_mismatches(&parse(pass), pass.bindings());
        assert!(
            problems.is_empty(),
            "{}: bindings differ from Pass::bindings():\n  {}",
            pass.file(),
            problems.join("\n  ")
        );
        // The draw passes share one group-1 layout (binding::BATCHES) and so one bind group.
        let group1: Vec<Binding> =
            pass.bindings().iter().copied().filter(|b| b.group == 1).collect();
        assert_eq!(
            pass.draws_batches(),
            !group1.is_empty(),
            "{}: draws_batches() and the table disagree",
            pass.file()
        );
        if pass.draws_batches() {
            assert_eq!(
                group1,
                binding::BATCHES,
                "{}: group 1 is not binding::BATCHES",
                pass.file()
            );
        }
    }
    let present = naga::front::wgsl::parse_str(PRESENT).unwrap();
    let problems = binding_mismatches(&present, PRESENT_BINDINGS);
    assert!(
        problems.is_empty(),
        "present.wgsl: bindings differ from PRESENT_BINDINGS:\n  {}",
        problems.join("\n  ")
    );
}

#[test]
fn a_wrong_binding_table_is_noticed() {
    // The check above must be able to fail: a changed number, kind or name, a missing entry and
    // an extra entry are each reported.
    let module = parse(Pass::Draw64);
    let good = Pass::Draw64.bindings();
    assert!(binding_mismatches(&module, good).is_empty());
    type Edit = fn(&mut Vec<Binding>);
    let edits: [(&str, Edit); 5] = [
        ("number", |t| t[2].binding = 5),
        ("kind", |t| t[1].kind = BindingKind::StorageRead),
        ("name", |t| t[0].name = "camera"),
        ("missing", |t| {
            t.pop();
        }),
        ("extra", |t| {
            t.push(Binding { group: 0, binding: 7, kind: BindingKind::Uniform, name: "extra" })
        }),
    ];
    for (what, edit) in edits {
        let mut bad = good.to_vec();
        edit(&mut bad);
        assert!(
            !binding_mismatches(&module, &bad).is_empty(),
            "a table with a wrong {what} passed"
        );
    }
    let mut twice = good.to_vec();
    twice.push(binding::COUNTERS);
    assert!(
        !binding_mismatches(&module, &twice).is_empty(),
        "a table listing a binding twice passed"
    );
}

/// Size and member offsets (by name) of the WGSL struct `name`.
fn wgsl_layout(module: &naga::Module, name: &str) -> (u32, Vec<(String, u32)>) {
    let mut layouter = naga::proc::Layouter::default();
    layouter.update(module.to_ctx()).unwrap();
    for (handle, ty) in module.types.iter() {
        if ty.name.as_deref() == Some(name) {
            if let naga::TypeInner::Struct { members, span } = &ty.inner {
                assert_eq!(layouter[handle].size, *span);
                return (
                    *span,
                    members
                        .iter()
                        .map(|m| (m.name.clone().unwrap_or_default(), m.offset))
                        .collect(),
                );
            }
        }
    }
    panic!("struct {name} not found in the WGSL");
}

#[test]
fn shared_structs_have_the_rust_layout() {
    // draw.wgsl and resolve.wgsl together contain every shared struct (types.wgsl is in both).
    let draw = parse(Pass::Draw64);
    let resolve = parse(Pass::Resolve);
    let fill = parse(Pass::HoleFill);
    let eye_dome = parse(Pass::EyeDome);
    let scatter = parse(Pass::ProgressiveScatter);
    let prepare = parse(Pass::ProgressivePrepare);
    let reframe = parse(Pass::ProgressiveReframe);
    let plan = parse(Pass::Plan);
    let octree = parse(Pass::OctreeVoxels);
    let sort = parse(Pass::SortScatter);
    // (struct, module holding it, Rust size, Rust members with their offsets)
    type Case<'a> = (&'a str, &'a naga::Module, usize, Vec<(&'a str, usize)>);
    let cases: Vec<Case<'_>> = vec![
        (
            "BatchProjection",
            &draw,
            size_of::<BatchProjection>(),
            vec![
                ("pixel_from_local", offset_of!(BatchProjection, pixel_from_local)),
                ("anchor", offset_of!(BatchProjection, anchor)),
                ("words", offset_of!(BatchProjection, words)),
                ("shift", offset_of!(BatchProjection, shift)),
                ("_pad0", offset_of!(BatchProjection, _pad0)),
                ("pixel_origin", offset_of!(BatchProjection, pixel_origin)),
                ("_pad1", offset_of!(BatchProjection, _pad1)),
            ],
        ),
        (
            "DrawRecord",
            &draw,
            size_of::<DrawRecord>(),
            vec![
                ("projection", offset_of!(DrawRecord, projection)),
                ("offset", offset_of!(DrawRecord, offset)),
                ("count", offset_of!(DrawRecord, count)),
                ("first_index", offset_of!(DrawRecord, first_index)),
                ("_pad", offset_of!(DrawRecord, _pad)),
            ],
        ),
        (
            "FrameUniforms",
            &draw,
            size_of::<FrameUniforms>(),
            vec![
                ("width", offset_of!(FrameUniforms, width)),
                ("height", offset_of!(FrameUniforms, height)),
                ("near", offset_of!(FrameUniforms, near)),
                ("far", offset_of!(FrameUniforms, far)),
                ("perspective", offset_of!(FrameUniforms, perspective)),
                ("zero", offset_of!(FrameUniforms, zero)),
                ("division", offset_of!(FrameUniforms, division)),
                ("_pad", offset_of!(FrameUniforms, _pad)),
            ],
        ),
        (
            "ResolveUniforms",
            &resolve,
            size_of::<ResolveUniforms>(),
            vec![
                ("width", offset_of!(ResolveUniforms, width)),
                ("height", offset_of!(ResolveUniforms, height)),
                ("key_stride", offset_of!(ResolveUniforms, key_stride)),
                ("depth_offset", offset_of!(ResolveUniforms, depth_offset)),
                ("first_index", offset_of!(ResolveUniforms, first_index)),
                ("count", offset_of!(ResolveUniforms, count)),
                ("background", offset_of!(ResolveUniforms, background)),
                ("write_background", offset_of!(ResolveUniforms, write_background)),
            ],
        ),
        (
            "PlanBatch",
            &plan,
            size_of::<PlanBatch>(),
            vec![
                ("min", offset_of!(PlanBatch, min)),
                ("record", offset_of!(PlanBatch, record)),
                ("lo", offset_of!(PlanBatch, lo)),
                ("offset", offset_of!(PlanBatch, offset)),
                ("hi", offset_of!(PlanBatch, hi)),
                ("count", offset_of!(PlanBatch, count)),
                ("bits", offset_of!(PlanBatch, bits)),
                ("first_index", offset_of!(PlanBatch, first_index)),
            ],
        ),
        (
            "PlanUniforms",
            &plan,
            size_of::<PlanUniforms>(),
            vec![
                ("eye_int", offset_of!(PlanUniforms, eye_int)),
                ("perspective", offset_of!(PlanUniforms, perspective)),
                ("eye_frac", offset_of!(PlanUniforms, eye_frac)),
                ("batches", offset_of!(PlanUniforms, batches)),
                ("right", offset_of!(PlanUniforms, right)),
                ("up", offset_of!(PlanUniforms, up)),
                ("forward", offset_of!(PlanUniforms, forward)),
                ("scale", offset_of!(PlanUniforms, scale)),
                ("sx", offset_of!(PlanUniforms, sx)),
                ("sy", offset_of!(PlanUniforms, sy)),
                ("cx", offset_of!(PlanUniforms, cx)),
                ("cy", offset_of!(PlanUniforms, cy)),
                ("near", offset_of!(PlanUniforms, near)),
                ("far", offset_of!(PlanUniforms, far)),
                ("width", offset_of!(PlanUniforms, width)),
                ("height", offset_of!(PlanUniforms, height)),
                ("words", offset_of!(PlanUniforms, words)),
                ("cull", offset_of!(PlanUniforms, cull)),
                ("division", offset_of!(PlanUniforms, division)),
                ("zero", offset_of!(PlanUniforms, zero)),
                ("margin_px", offset_of!(PlanUniforms, margin_px)),
                ("slack", offset_of!(PlanUniforms, slack)),
                ("max_error_px", offset_of!(PlanUniforms, max_error_px)),
                ("_pad", offset_of!(PlanUniforms, _pad)),
            ],
        ),
        (
            "HoleFillUniforms",
            &fill,
            size_of::<HoleFillUniforms>(),
            vec![
                ("width", offset_of!(HoleFillUniforms, width)),
                ("height", offset_of!(HoleFillUniforms, height)),
                ("key_stride", offset_of!(HoleFillUniforms, key_stride)),
                ("depth_offset", offset_of!(HoleFillUniforms, depth_offset)),
                ("min_neighbors", offset_of!(HoleFillUniforms, min_neighbors)),
                ("_pad0", offset_of!(HoleFillUniforms, _pad0)),
                ("_pad1", offset_of!(HoleFillUniforms, _pad1)),
                ("_pad2", offset_of!(HoleFillUniforms, _pad2)),
            ],
        ),
        (
            "EyeDomeUniforms",
            &eye_dome,
            size_of::<EyeDomeUniforms>(),
            vec![
                ("width", offset_of!(EyeDomeUniforms, width)),
                ("height", offset_of!(EyeDomeUniforms, height)),
                ("key_stride", offset_of!(EyeDomeUniforms, key_stride)),
                ("depth_offset", offset_of!(EyeDomeUniforms, depth_offset)),
                ("scale", offset_of!(EyeDomeUniforms, scale)),
                ("zero", offset_of!(EyeDomeUniforms, zero)),
                ("_pad0", offset_of!(EyeDomeUniforms, _pad0)),
                ("_pad1", offset_of!(EyeDomeUniforms, _pad1)),
                ("offsets", offset_of!(EyeDomeUniforms, offsets)),
                ("log2_coeffs", offset_of!(EyeDomeUniforms, log2_coeffs)),
                ("exp2_coeffs", offset_of!(EyeDomeUniforms, exp2_coeffs)),
            ],
        ),
        (
            "ScatterUniforms",
            &scatter,
            size_of::<ScatterUniforms>(),
            vec![
                ("colors", offset_of!(ScatterUniforms, colors)),
                ("colors_only", offset_of!(ScatterUniforms, colors_only)),
                ("prime", offset_of!(ScatterUniforms, prime)),
                ("first", offset_of!(ScatterUniforms, first)),
                ("chunk_first", offset_of!(ScatterUniforms, chunk_first)),
                ("chunk_len", offset_of!(ScatterUniforms, chunk_len)),
                ("count", offset_of!(ScatterUniforms, count)),
                ("_pad", offset_of!(ScatterUniforms, _pad)),
            ],
        ),
        (
            "PrepareUniforms",
            &prepare,
            size_of::<PrepareUniforms>(),
            vec![
                ("pixels", offset_of!(PrepareUniforms, pixels)),
                ("chunk_slots", offset_of!(PrepareUniforms, chunk_slots)),
                ("list_stride", offset_of!(PrepareUniforms, list_stride)),
                ("chunks", offset_of!(PrepareUniforms, chunks)),
            ],
        ),
        (
            "ReframeUniforms",
            &reframe,
            size_of::<ReframeUniforms>(),
            vec![
                ("from_min", offset_of!(ReframeUniforms, from_min)),
                ("count", offset_of!(ReframeUniforms, count)),
                ("to_min", offset_of!(ReframeUniforms, to_min)),
                ("_pad0", offset_of!(ReframeUniforms, _pad0)),
                ("from_shift", offset_of!(ReframeUniforms, from_shift)),
                ("_pad1", offset_of!(ReframeUniforms, _pad1)),
                ("to_shift", offset_of!(ReframeUniforms, to_shift)),
                ("_pad2", offset_of!(ReframeUniforms, _pad2)),
            ],
        ),
        (
            "OctreeUniforms",
            &octree,
            size_of::<OctreeUniforms>(),
            vec![
                ("first", offset_of!(OctreeUniforms, first)),
                ("count", offset_of!(OctreeUniforms, count)),
                ("capacity", offset_of!(OctreeUniforms, capacity)),
                ("max_level", offset_of!(OctreeUniforms, max_level)),
                ("node_capacity", offset_of!(OctreeUniforms, node_capacity)),
                ("grid_first", offset_of!(OctreeUniforms, grid_first)),
                ("grid_count", offset_of!(OctreeUniforms, grid_count)),
                ("groups_x", offset_of!(OctreeUniforms, groups_x)),
                ("mode", offset_of!(OctreeUniforms, mode)),
                ("base", offset_of!(OctreeUniforms, base)),
                ("_pad", offset_of!(OctreeUniforms, _pad)),
            ],
        ),
        (
            "SortUniforms",
            &sort,
            size_of::<SortUniforms>(),
            vec![
                ("count", offset_of!(SortUniforms, count)),
                ("bit", offset_of!(SortUniforms, bit)),
                ("tiles", offset_of!(SortUniforms, tiles)),
                ("groups_x", offset_of!(SortUniforms, groups_x)),
                ("base", offset_of!(SortUniforms, base)),
                ("blocks", offset_of!(SortUniforms, blocks)),
                ("entries", offset_of!(SortUniforms, entries)),
                ("_pad", offset_of!(SortUniforms, _pad)),
            ],
        ),
        (
            "Node",
            &octree,
            size_of::<OctreeNode>(),
            vec![
                ("count", offset_of!(OctreeNode, count)),
                ("child", offset_of!(OctreeNode, child)),
                ("min", offset_of!(OctreeNode, min)),
                ("size_level", offset_of!(OctreeNode, size_level)),
                ("grid", offset_of!(OctreeNode, grid)),
                ("cursor", offset_of!(OctreeNode, cursor)),
            ],
        ),
    ];
    for (name, module, rust_size, rust_members) in cases {
        let (size, members) = wgsl_layout(module, name);
        assert_eq!(size as usize, rust_size, "{name}: WGSL size {size}, Rust {rust_size}");
        let names: Vec<&str> = members.iter().map(|m| m.0.as_str()).collect();
        let rust_names: Vec<&str> = rust_members.iter().map(|m| m.0).collect();
        assert_eq!(names, rust_names, "{name}: members differ");
        for ((n, off), (_, rust_off)) in members.iter().zip(&rust_members) {
            assert_eq!(*off as usize, *rust_off, "{name}.{n}: WGSL offset {off}, Rust {rust_off}");
        }
    }
}

/// The value of the WGSL `u32` constant `name` of `module`.
fn wgsl_u32_constant(module: &naga::Module, name: &str) -> u32 {
    let c = module
        .constants
        .iter()
        .find(|(_, c)| c.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("constant {name} not found in the WGSL"))
        .1;
    match module.global_expressions[c.init] {
        naga::Expression::Literal(naga::Literal::U32(v)) => v,
        ref e => panic!("constant {name}: {e:?} is not a u32 literal"),
    }
}

/// The value of the WGSL `f32` constant `name` of `module`.
fn wgsl_f32_constant(module: &naga::Module, name: &str) -> f32 {
    let c = module
        .constants
        .iter()
        .find(|(_, c)| c.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("constant {name} not found in the WGSL"))
        .1;
    match module.global_expressions[c.init] {
        naga::Expression::Literal(naga::Literal::F32(v)) => v,
        ref e => panic!("constant {name}: {e:?} is not an f32 literal"),
    }
}

#[test]
fn plan_constants_have_the_rust_values() {
    let plan = parse(Pass::Plan);
    assert_eq!(
        wgsl_f32_constant(&plan, "FAR_UNITS"),
        mortar_core::render::plan::FAR_UNITS,
        "FAR_UNITS: WGSL and mortar_core differ"
    );
}

#[test]
fn progressive_constants_have_the_rust_values() {
    // The progressive passes share progressive_types.wgsl; Fill uses both constants.
    let fill = parse(Pass::ProgressiveFill);
    assert_eq!(
        wgsl_u32_constant(&fill, "UNLOADED"),
        UNLOADED,
        "UNLOADED: WGSL and mortar_core differ"
    );
    assert_eq!(
        wgsl_u32_constant(&fill, "SLOTS_PER_THREAD"),
        SLOTS_PER_THREAD,
        "SLOTS_PER_THREAD: WGSL and Rust differ"
    );
    let unload = parse(Pass::ProgressiveUnload);
    assert_eq!(wgsl_u32_constant(&unload, "UNLOADED"), UNLOADED);
}

#[test]
fn eye_dome_polynomial_lengths_have_the_rust_values() {
    // The coefficients themselves travel in EyeDomeUniforms (one definition, in Rust); the WGSL
    // loops over as many terms as Rust has, and the uniform arrays hold them.
    let edl = parse(Pass::EyeDome);
    assert_eq!(wgsl_u32_constant(&edl, "LOG2_TERMS") as usize, EDL_LOG2_COEFFS.len());
    assert_eq!(wgsl_u32_constant(&edl, "EXP2_TERMS") as usize, EDL_EXP2_COEFFS.len());
    assert!(EDL_LOG2_COEFFS.len() <= 4 * 3 && EDL_EXP2_COEFFS.len() <= 4 * 2);
}
