//! Shader checks that need no GPU: naga parses and validates every pass exactly as the pipelines
//! assemble it (with 64-bit capabilities only where the pass needs them), and every struct shared
//! with WGSL has the same size and member offsets as its `#[repr(C)]` Rust twin.

use mortar_core::render::gpu::{BatchProjection, DrawRecord, FrameUniforms, PrepareUniforms, ResolveUniforms, ScatterUniforms};
use mortar_core::render::progressive::UNLOADED;
use mortar_render::progressive::SLOTS_PER_THREAD;
use mortar_render::shaders::Pass;
use naga::valid::{Capabilities, ValidationFlags, Validator};
use std::mem::{offset_of, size_of};

fn parse(pass: Pass) -> naga::Module {
    let src = pass.source();
    naga::front::wgsl::parse_str(&src).unwrap_or_else(|e| panic!("{}: {}", pass.file(), e.emit_to_string(&src)))
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
    assert!(Validator::new(ValidationFlags::all(), Capabilities::SHADER_INT64).validate(&module).is_err(), "atomicMin on u64 needs SHADER_INT64_ATOMIC_MIN_MAX");
}

/// Size and member offsets (by name) of the WGSL struct `name`.
fn wgsl_layout(module: &naga::Module, name: &str) -> (u32, Vec<(String, u32)>) {
    let mut layouter = naga::proc::Layouter::default();
    layouter.update(module.to_ctx()).unwrap();
    for (handle, ty) in module.types.iter() {
        if ty.name.as_deref() == Some(name) {
            if let naga::TypeInner::Struct { members, span } = &ty.inner {
                assert_eq!(layouter[handle].size, *span);
                return (*span, members.iter().map(|m| (m.name.clone().unwrap_or_default(), m.offset)).collect());
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
    let scatter = parse(Pass::ProgressiveScatter);
    let prepare = parse(Pass::ProgressivePrepare);
    let cases: Vec<(&str, &naga::Module, usize, Vec<(&str, usize)>)> = vec![
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
            "ScatterUniforms",
            &scatter,
            size_of::<ScatterUniforms>(),
            vec![
                ("colors", offset_of!(ScatterUniforms, colors)),
                ("colors_only", offset_of!(ScatterUniforms, colors_only)),
                ("_pad1", offset_of!(ScatterUniforms, _pad1)),
                ("_pad2", offset_of!(ScatterUniforms, _pad2)),
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
    let c = module.constants.iter().find(|(_, c)| c.name.as_deref() == Some(name)).unwrap_or_else(|| panic!("constant {name} not found in the WGSL")).1;
    match module.global_expressions[c.init] {
        naga::Expression::Literal(naga::Literal::U32(v)) => v,
        ref e => panic!("constant {name}: {e:?} is not a u32 literal"),
    }
}

#[test]
fn progressive_constants_have_the_rust_values() {
    // The progressive passes share progressive_types.wgsl; Fill uses both constants.
    let fill = parse(Pass::ProgressiveFill);
    assert_eq!(wgsl_u32_constant(&fill, "UNLOADED"), UNLOADED, "UNLOADED: WGSL and mortar_core differ");
    assert_eq!(wgsl_u32_constant(&fill, "SLOTS_PER_THREAD"), SLOTS_PER_THREAD, "SLOTS_PER_THREAD: WGSL and Rust differ");
    let unload = parse(Pass::ProgressiveUnload);
    assert_eq!(wgsl_u32_constant(&unload, "UNLOADED"), UNLOADED);
}
