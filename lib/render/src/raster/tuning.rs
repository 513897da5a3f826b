//! Variants of the 64-bit draw pass for measurements ([`DrawTuning`]) and the order of a chunk's
//! draw records ([`RecordOrder`]).

/// Variants of the 64-bit draw pass for measuring where its time goes (issue 17; the bench
/// `mortar-bench-gpu --kernels --workgroups --orders`). The renderer draws with the default,
/// which every test checks; the others are diagnostics (kernel 3 leaves no image at all).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct DrawTuning {
    /// `draw.wgsl`'s `KERNEL`: 0 the renderer (atomicLoad early test), 1 early test from a plain
    /// load of the depth word, 2 no early test, 3 no framebuffer access, 4 kernel 0 with four
    /// points' words loaded before any is projected (the paper's prefetch, §3.4).
    pub kernel: u32,
    /// Threads per workgroup (`WG`; one workgroup per batch whatever the size).
    pub workgroup: u32,
    /// Order of a chunk's draw records, i.e. of the workgroups (host planning only).
    pub order: RecordOrder,
    /// Plan every batch on the GPU (the plan pass); `false` plans on the host (as a selection
    /// always is), with the same plan.
    pub plan_on_gpu: bool,
    /// The division of the draw and plan passes instead of the context's
    /// ([`GpuContext::division`]): `Some(DIVISION_PLAIN)` on a GPU whose `/` is not correctly
    /// rounded measures what the exact division costs (its keys may then differ from the CPU's).
    ///
    /// [`GpuContext::division`]: crate::GpuContext::division
    pub division: Option<u32>,
}

impl Default for DrawTuning {
    fn default() -> Self {
        DrawTuning {
            kernel: 0,
            workgroup: 128,
            order: RecordOrder::Scene,
            plan_on_gpu: true,
            division: None,
        }
    }
}

/// The order in which a chunk's batches are handed to workgroups.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RecordOrder {
    /// Scene (Morton) order: workgroups that run together draw neighbouring batches.
    Scene,
    /// Records `k, k + s, k + 2s, ...` for `k` in `0..s`: workgroups that run together draw
    /// batches `s` apart, in other places of the screen.
    Strided(u32),
}

impl RecordOrder {
    /// The permutation of `n` records.
    pub(super) fn permutation(self, n: usize) -> Vec<usize> {
        match self {
            RecordOrder::Scene => (0..n).collect(),
            RecordOrder::Strided(s) => {
                let s = (s as usize).max(1);
                (0..s).flat_map(|k| (k..n).step_by(s)).collect()
            }
        }
    }
}
