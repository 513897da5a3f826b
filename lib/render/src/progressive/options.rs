//! The choices a [`GpuProgressive`](super::GpuProgressive) is made with ([`ProgressiveOptions`]).

/// Choices of a [`GpuProgressive`](super::GpuProgressive).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct ProgressiveOptions {
    /// Slots per chunk (`None`: as many as the device's largest binding holds, at most
    /// [`MAX_CHUNK_POINTS`](crate::scene::MAX_CHUNK_POINTS)). Small values exercise the chunking
    /// in tests.
    pub chunk_slots: Option<u32>,
    /// Whether points come with RGBA8 colours (for the GPU resolve and
    /// [`GpuProgressive::image_buffer`](super::GpuProgressive::image_buffer)).
    pub colors: bool,
    /// Whether points come with a 64-bit payload kept on the host by slot
    /// ([`GpuProgressive::payload`](super::GpuProgressive::payload), as the CPU renderer keeps it),
    /// for colour rules resolved on the host.
    pub payloads: bool,
    /// Time the passes with the host's clock
    /// ([`BudgetTiming::HostClock`](super::BudgetTiming::HostClock)) even where the device has
    /// timestamps (what a device without them does; tests use it).
    pub host_clock: bool,
}
