//! mortar-render: the wgpu compute rasterizer and the preview window.
//!
//! Not built yet: this crate exists so the crate graph of `ARCHITECTURE.md` is in place from the
//! start (`bins -> {io, render} -> core`). The GPU renderer arrives with the "shared renderer,
//! part 2" issue; until then `mortar` has no GPU code.
