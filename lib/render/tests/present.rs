//! The window's side of the GPU renderer without a window: the present pass validates and shares
//! its uniform layout with Rust, and a colour-mode switch ([`GpuScene::set_colors`]) changes what
//! the resolve pass writes without uploading the points again.
//!
//! The window itself (surface, present, read-back) is tested end to end under Xvfb in the
//! `mortar` package's `tests/window.rs`.

use mortar_core::grid::Grid;
use mortar_core::render::resolve::{resolve_with_colors, ResolveOptions};
use mortar_core::render::testutil::Scene;
use mortar_core::render::{rasterize, Camera, Framebuffer, RasterOptions, ViewPreset};
use mortar_render::present::PresentUniforms;
use mortar_render::{AtomicPath, GpuError, GpuRasterizer, GpuScene, SceneOptions};
use naga::valid::{Capabilities, ValidationFlags, Validator};
use std::mem::{offset_of, size_of};

#[test]
fn present_pass_validates_and_matches_its_rust_uniforms() {
    let src = mortar_render::shaders::PRESENT;
    let module = naga::front::wgsl::parse_str(src)
        .unwrap_or_else(|e| panic!("present.wgsl: {}", e.emit_to_string(src)));
    Validator::new(ValidationFlags::all(), Capabilities::empty())
        .validate(&module)
        .unwrap_or_else(|e| panic!("present.wgsl: {}", e.emit_to_string(src)));
    let stages: Vec<(&str, naga::ShaderStage)> =
        module.entry_points.iter().map(|e| (e.name.as_str(), e.stage)).collect();
    assert!(
        stages.contains(&("vs_main", naga::ShaderStage::Vertex))
            && stages.contains(&("fs_main", naga::ShaderStage::Fragment)),
        "{stages:?}"
    );

    let mut layouter = naga::proc::Layouter::default();
    layouter.update(module.to_ctx()).unwrap();
    let (handle, members, span) = module
        .types
        .iter()
        .find_map(|(h, t)| match &t.inner {
            naga::TypeInner::Struct { members, span }
                if t.name.as_deref() == Some("PresentUniforms") =>
            {
                Some((h, members.clone(), *span))
            }
            _ => None,
        })
        .expect("struct PresentUniforms in present.wgsl");
    assert_eq!(layouter[handle].size, span);
    assert_eq!(span as usize, size_of::<PresentUniforms>());
    let rust = [
        ("width", offset_of!(PresentUniforms, width)),
        ("height", offset_of!(PresentUniforms, height)),
        ("overlay_width", offset_of!(PresentUniforms, overlay_width)),
        ("overlay_height", offset_of!(PresentUniforms, overlay_height)),
        ("srgb_target", offset_of!(PresentUniforms, srgb_target)),
        ("_pad0", offset_of!(PresentUniforms, _pad0)),
        ("_pad1", offset_of!(PresentUniforms, _pad1)),
        ("_pad2", offset_of!(PresentUniforms, _pad2)),
    ];
    let wgsl: Vec<(String, usize)> =
        members.iter().map(|m| (m.name.clone().unwrap_or_default(), m.offset as usize)).collect();
    let rust: Vec<(String, usize)> = rust.iter().map(|(n, o)| (n.to_string(), *o)).collect();
    assert_eq!(wgsl, rust);
}

#[test]
fn set_colors_recolours_the_resolved_image() {
    let Some(ctx) = mortar_render::testing::context_or_skip(AtomicPath::TwoPass32, None) else {
        return;
    };
    let scene = Scene::terrain(30_000, 11, Grid { scale: [0.01; 3], offset: [0.0; 3] });
    // Small chunks: the new colours must land in every chunk at the right offset.
    let mut gs = GpuScene::new(
        &ctx,
        scene.grid,
        scene.points.len() as u64,
        SceneOptions { chunk_points: Some(10_240 * 2), colors: true },
    )
    .unwrap();
    for b in scene.refs() {
        let s = b.first_index as usize;
        gs.push(&ctx, &b, Some(&scene.colors[s..s + b.len()])).unwrap();
    }
    assert!(gs.chunk_count() > 1);
    let cam = Camera::frame_perspective(&scene.bounds, ViewPreset::Iso, 0.8, 200, 150).unwrap();
    let opts = RasterOptions::default();
    let bg = 0xff20_1008;
    let fb = Framebuffer::new(cam.width, cam.height);
    rasterize(&fb, &scene.refs(), &scene.grid, &cam, &opts).unwrap();
    let keys = fb.into_keys();
    let resolve_opts = ResolveOptions { background: bg, ..Default::default() };

    let mut gr = GpuRasterizer::new(&ctx, cam.width, cam.height).unwrap();
    gr.draw(&ctx, &mut gs, &cam, &opts, Some(&resolve_opts)).unwrap();
    assert_eq!(
        gr.read_image(&ctx).unwrap(),
        resolve_with_colors(&keys, cam.width, cam.height, &scene.colors, &resolve_opts)
    );

    // Another colour per point (a hash of its index): the image follows, the keys do not move.
    let other: Vec<u32> =
        (0..scene.points.len() as u32).map(|i| i.wrapping_mul(0x9e37_79b9) | 0xff00_0000).collect();
    gs.set_colors(&ctx, &other).unwrap();
    gr.draw(&ctx, &mut gs, &cam, &opts, Some(&resolve_opts)).unwrap();
    let image = gr.read_image(&ctx).unwrap();
    assert_eq!(image, resolve_with_colors(&keys, cam.width, cam.height, &other, &resolve_opts));
    assert_ne!(
        image,
        resolve_with_colors(&keys, cam.width, cam.height, &scene.colors, &resolve_opts)
    );

    // Resizing keeps the scene and the pipelines; the next frame has the new size.
    gr.resize(&ctx, 120, 90).unwrap();
    assert_eq!(gr.size(), (120, 90));
    assert!(gr.image_buffer().is_none(), "the old image is gone with the old size");
    let small = Camera { width: 120, height: 90, ..cam };
    gr.draw(&ctx, &mut gs, &small, &opts, Some(&resolve_opts)).unwrap();
    let fb = Framebuffer::new(120, 90);
    rasterize(&fb, &scene.refs(), &scene.grid, &small, &opts).unwrap();
    assert_eq!(
        gr.read_image(&ctx).unwrap(),
        resolve_with_colors(&fb.into_keys(), 120, 90, &other, &resolve_opts)
    );

    // Wrong lengths are errors, not panics.
    assert!(matches!(gs.set_colors(&ctx, &other[1..]), Err(GpuError::Colors(_))));
    let mut plain = GpuScene::new(&ctx, scene.grid, 0, SceneOptions::default()).unwrap();
    assert!(matches!(plain.set_colors(&ctx, &[]), Err(GpuError::Colors(_))));
}
