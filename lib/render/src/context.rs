//! Device setup: picks an adapter without any window or display ([`GpuContext::new`]), or one that
//! can also present to a window ([`GpuContext::for_window`]), asks for its real limits and for
//! 64-bit atomics (SHADER_INT64 + SHADER_INT64_ATOMIC_MIN_MAX) and GPU timestamps where present,
//! and chooses the atomic path at run time: 64-bit keys where the features exist, the 32-bit
//! two-pass path where they do not (GL backend, older GPUs) or where the caller asks for it.

use std::sync::{Arc, Mutex};

/// Which atomics the draw pass uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum AtomicPath {
    /// One pass, `atomicMin` on 64-bit depth|index keys (paper 003 Listing 1).
    U64,
    /// Two passes with 32-bit atomics: nearest depth, then the smallest index at that depth.
    TwoPass32,
}

impl AtomicPath {
    /// A short name: "64" or "32".
    pub fn name(self) -> &'static str {
        match self {
            AtomicPath::U64 => "64",
            AtomicPath::TwoPass32 => "32",
        }
    }
}

/// What the caller wants of the device.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub struct GpuOptions {
    /// Force an atomic path (`None`: 64-bit where the adapter has it).
    pub atomics: Option<AtomicPath>,
    /// Accept a software adapter (a CPU Vulkan such as lavapipe) when no hardware GPU exists.
    pub allow_software: bool,
    /// Split dispatches at this many workgroups per dimension instead of the device's limit
    /// (65,535 on most); small values exercise the split in tests.
    pub max_workgroups_per_dimension: Option<u32>,
}

/// Why the GPU rasterizer cannot run or failed.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No suitable adapter.
    #[error("no GPU adapter with compute shaders found{0}")]
    NoAdapter(String),
    /// 64-bit atomics were asked for but the adapter lacks them.
    #[error("{adapter}: no 64-bit atomics (SHADER_INT64 + SHADER_INT64_ATOMIC_MIN_MAX); use the 32-bit path")]
    NoInt64Atomics {
        /// The adapter's name.
        adapter: String,
    },
    /// The device could not be created.
    #[error("{adapter}: cannot create a device: {message}")]
    RequestDevice {
        /// The adapter's name.
        adapter: String,
        /// What wgpu said.
        message: String,
    },
    /// wgpu reported an error (validation, out of memory, lost device).
    #[error("GPU error: {0}")]
    Device(String),
    /// Something does not fit the device's limits.
    #[error("{what} needs {needed} bytes but the device allows {limit}")]
    TooLarge {
        /// What was too large.
        what: &'static str,
        /// Bytes needed.
        needed: u64,
        /// The device's limit.
        limit: u64,
    },
    /// The view or the batches are not drawable.
    #[error(transparent)]
    Raster(#[from] mortar_core::render::RasterError),
    /// Batches must be added with consecutive point indices.
    #[error("batch with first point index {got} added where {expected} was expected (indices must be consecutive from 0)")]
    FirstIndex {
        /// The next index of the scene.
        expected: u64,
        /// The batch's first index.
        got: u32,
    },
    /// Colours given for some batches but not others, or of the wrong length.
    #[error("colours: {0}")]
    Colors(String),
    /// A selection names batches the scene does not hold.
    #[error("selection: {0}")]
    Selection(String),
    /// The window's surface cannot be created or presented to.
    #[error("window surface: {0}")]
    Surface(String),
}

/// Mesa's device-select layer probes for a Wayland display and prints an error without one;
/// mortar enumerates and ranks the adapters itself, so the layer is switched off (unless the user
/// set NODEVICE_SELECT). Called before any GPU thread exists.
fn quiet_device_select() {
    if std::env::var_os("NODEVICE_SELECT").is_none() {
        std::env::set_var("NODEVICE_SELECT", "1");
    }
}

/// A description of the adapter in use, for reports.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AdapterSummary {
    /// Device name.
    pub name: String,
    /// Backend (Vulkan, Metal, Dx12, Gl).
    pub backend: String,
    /// Discrete, integrated, virtual, CPU or other.
    pub device_type: String,
    /// Driver name and version as reported.
    pub driver: String,
}

/// The device, its queue and what it can do.
pub struct GpuContext {
    /// The wgpu device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    adapter: wgpu::Adapter,
    summary: AdapterSummary,
    path: AtomicPath,
    timestamps: bool,
    software: bool,
    limits: wgpu::Limits,
    dispatch_x: u32,
    errors: Arc<Mutex<Vec<String>>>,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext")
            .field("adapter", &self.summary)
            .field("path", &self.path)
            .finish()
    }
}

/// The 64-bit atomic features the one-pass path needs.
pub const INT64_ATOMICS: wgpu::Features =
    wgpu::Features::SHADER_INT64.union(wgpu::Features::SHADER_INT64_ATOMIC_MIN_MAX);

fn rank(t: wgpu::DeviceType) -> u32 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 4,
        wgpu::DeviceType::IntegratedGpu => 3,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 1,
        wgpu::DeviceType::Cpu => 0,
    }
}

impl GpuContext {
    /// Opens the best adapter (discrete before integrated before virtual; software ones only with
    /// `allow_software`), headless. `WGPU_BACKEND` (e.g. `vulkan`, `gl`) restricts the backends.
    pub fn new(options: &GpuOptions) -> Result<GpuContext, GpuError> {
        // Vulkan, Metal and DX12 first; the GL backend (EGL probing, noisy on headless machines)
        // only when none of them has an adapter. WGPU_BACKEND overrides both.
        quiet_device_select();
        let from_env = wgpu::Backends::from_env();
        let mut adapters = Vec::new();
        for backends in [from_env.unwrap_or(wgpu::Backends::PRIMARY), wgpu::Backends::GL] {
            let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
                backends,
                ..wgpu::InstanceDescriptor::new_without_display_handle()
            });
            adapters = pollster::block_on(instance.enumerate_adapters(backends));
            if !adapters.is_empty() || from_env.is_some() {
                break;
            }
        }
        GpuContext::open(adapters, options, None)
    }

    /// Opens the best adapter that can also present to `window` (ranked as [`GpuContext::new`]
    /// does), and the window's surface on it. The surface is not configured yet (see
    /// [`crate::present::WindowSurface`]). Vulkan, Metal and DX12 are tried first, GL only when
    /// none of their adapters can present; `WGPU_BACKEND` restricts the backends.
    pub fn for_window<W>(
        options: &GpuOptions,
        window: W,
    ) -> Result<(GpuContext, wgpu::Surface<'static>), GpuError>
    where
        W: wgpu::WindowHandle
            + wgpu::rwh::HasDisplayHandle
            + std::fmt::Debug
            + Clone
            + Send
            + Sync
            + 'static,
    {
        quiet_device_select();
        let from_env = wgpu::Backends::from_env();
        let attempts: &[wgpu::Backends] = match from_env {
            Some(b) => &[b][..],
            None => &[wgpu::Backends::PRIMARY, wgpu::Backends::GL][..],
        };
        let mut last = GpuError::NoAdapter(String::new());
        for &backends in attempts {
            // The display handle matters to GL (EGL) only; Vulkan, Metal and DX12 ignore it.
            let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
                backends,
                display: Some(Box::new(window.clone())),
                ..wgpu::InstanceDescriptor::new_without_display_handle()
            });
            let surface = match instance.create_surface(window.clone()) {
                Ok(s) => s,
                Err(e) => {
                    last = GpuError::Surface(e.to_string());
                    continue;
                }
            };
            let adapters = pollster::block_on(instance.enumerate_adapters(backends));
            match GpuContext::open(adapters, options, Some(&surface)) {
                Ok(ctx) => return Ok((ctx, surface)),
                Err(e @ GpuError::NoAdapter(_)) => last = e,
                Err(e) => return Err(e),
            }
        }
        Err(last)
    }

    /// Ranks `adapters`, keeps those that can present to `surface` (when given), and opens the
    /// best one.
    fn open(
        adapters: Vec<wgpu::Adapter>,
        options: &GpuOptions,
        surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<GpuContext, GpuError> {
        let mut seen = Vec::new();
        let mut best: Option<(u32, bool, wgpu::Adapter)> = None;
        for a in adapters {
            let info = a.get_info();
            let presents = surface.is_none_or(|s| a.is_surface_supported(s));
            seen.push(format!(
                "{} ({:?}, {:?}{})",
                info.name,
                info.backend,
                info.device_type,
                if presents { "" } else { ", cannot present to the window" }
            ));
            if !presents
                || !a
                    .get_downlevel_capabilities()
                    .flags
                    .contains(wgpu::DownlevelFlags::COMPUTE_SHADERS)
            {
                continue;
            }
            if info.device_type == wgpu::DeviceType::Cpu && !options.allow_software {
                continue;
            }
            // Prefer the device type, then 64-bit atomics, then Vulkan over GL.
            let score = rank(info.device_type) * 4
                + 2 * a.features().contains(INT64_ATOMICS) as u32
                + (info.backend != wgpu::Backend::Gl) as u32;
            if best.as_ref().is_none_or(|b| score > b.0) {
                best = Some((score, info.device_type == wgpu::DeviceType::Cpu, a));
            }
        }
        let Some((_, software, adapter)) = best else {
            let what = if seen.is_empty() {
                String::new()
            } else {
                format!(
                    " (seen: {}{})",
                    seen.join(", "),
                    if options.allow_software {
                        ""
                    } else {
                        "; software adapters are not used here"
                    }
                )
            };
            return Err(GpuError::NoAdapter(what));
        };
        let info = adapter.get_info();
        let have = adapter.features();
        let path = match options.atomics {
            Some(AtomicPath::U64) if !have.contains(INT64_ATOMICS) => {
                return Err(GpuError::NoInt64Atomics { adapter: info.name })
            }
            Some(p) => p,
            None if have.contains(INT64_ATOMICS) => AtomicPath::U64,
            None => AtomicPath::TwoPass32,
        };
        let mut features = wgpu::Features::empty();
        if path == AtomicPath::U64 {
            features |= INT64_ATOMICS;
        }
        let timestamps = have.contains(wgpu::Features::TIMESTAMP_QUERY);
        if timestamps {
            features |= wgpu::Features::TIMESTAMP_QUERY;
        }
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("mortar"),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::RequestDevice {
            adapter: info.name.clone(),
            message: e.to_string(),
        })?;
        let errors = Arc::new(Mutex::new(Vec::new()));
        let sink = errors.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut v) = sink.lock() {
                v.push(e.to_string());
            }
        }));
        let summary = AdapterSummary {
            name: info.name.clone(),
            backend: format!("{:?}", info.backend),
            device_type: format!("{:?}", info.device_type),
            driver: format!("{} {}", info.driver, info.driver_info).trim().to_string(),
        };
        let dispatch_x = options
            .max_workgroups_per_dimension
            .unwrap_or(u32::MAX)
            .min(limits.max_compute_workgroups_per_dimension)
            .max(1);
        Ok(GpuContext {
            device,
            queue,
            adapter,
            summary,
            path,
            timestamps,
            software,
            limits,
            dispatch_x,
            errors,
        })
    }

    /// The adapter in use.
    pub fn adapter(&self) -> &AdapterSummary {
        &self.summary
    }

    /// The wgpu adapter itself (surface capabilities need it).
    pub fn wgpu_adapter(&self) -> &wgpu::Adapter {
        &self.adapter
    }

    /// The atomic path of the draw pass.
    pub fn atomic_path(&self) -> AtomicPath {
        self.path
    }

    /// Whether GPU timestamps are available.
    pub fn has_timestamps(&self) -> bool {
        self.timestamps
    }

    /// Whether the adapter is a software one (a CPU Vulkan).
    pub fn is_software(&self) -> bool {
        self.software
    }

    /// The device's limits (the adapter's own).
    pub fn limits(&self) -> &wgpu::Limits {
        &self.limits
    }

    /// How the draw passes divide (`mortar_core::render::gpu::DIVISION_*`): a software adapter
    /// (lavapipe, LLVM on the CPU) divides correctly rounded with WGSL's `/` and gives keys equal
    /// to the CPU's with it (tested in CI), while its `div_rn` sequence differed in 2 of 60,844
    /// pixels of one test view (its `fma` appears not to be fused); a hardware GPU may divide with
    /// 2.5 ULP of error, and on the H100 the refined division gave keys equal to the CPU's in every
    /// test and benchmark view (plain `/`: 1-2 pixels differed in some views there).
    pub fn division(&self) -> u32 {
        if self.software {
            mortar_core::render::gpu::DIVISION_PLAIN
        } else {
            mortar_core::render::gpu::DIVISION_REFINED
        }
    }

    /// The device memory the adapter's driver reports, in bytes: on Vulkan the largest heap
    /// flagged device-local (a discrete GPU's memory; a software or integrated adapter's is host
    /// memory). `None` where the backend does not say (wgpu has no portable query; other
    /// backends than Vulkan are not asked).
    pub fn device_memory(&self) -> Option<u64> {
        #[cfg(any(target_os = "linux", target_os = "windows", target_os = "android"))]
        {
            // SAFETY: the hal adapter is only read (its instance and physical device handles,
            // for one query of memory properties), never destroyed or used for GPU work.
            let hal = unsafe { self.adapter.as_hal::<wgpu::hal::api::Vulkan>() }?;
            let instance = hal.shared_instance().raw_instance();
            // SAFETY: the physical device belongs to this instance, which outlives the call.
            let props = unsafe {
                instance.get_physical_device_memory_properties(hal.raw_physical_device())
            };
            let heaps = &props.memory_heaps[..(props.memory_heap_count as usize).min(16)];
            // VK_MEMORY_HEAP_DEVICE_LOCAL_BIT is bit 0.
            heaps.iter().filter(|h| h.flags.as_raw() & 1 != 0).map(|h| h.size).max()
        }
        #[cfg(not(any(target_os = "linux", target_os = "windows", target_os = "android")))]
        {
            None
        }
    }

    /// The largest storage binding: what one chunk of points or one framebuffer may occupy.
    pub fn max_binding(&self) -> u64 {
        self.limits.max_storage_buffer_binding_size.min(self.limits.max_buffer_size)
    }

    /// Fails with the first error wgpu reported since the last call, if any.
    pub fn check(&self) -> Result<(), GpuError> {
        let mut v =
            self.errors.lock().map_err(|_| GpuError::Device("error log poisoned".into()))?;
        if v.is_empty() {
            return Ok(());
        }
        let first = v.remove(0);
        let more = v.len();
        v.clear();
        Err(GpuError::Device(if more > 0 { format!("{first} (and {more} more)") } else { first }))
    }

    /// Waits until the GPU has finished all submitted work.
    pub fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Device(e.to_string()))?;
        self.check()
    }

    /// Workgroup counts `(x, y)` covering `n` workgroups, with at most the device's maximum per
    /// dimension (65,535 on most) in x; the shaders linearize `y * groups_x + x` and skip the
    /// excess.
    pub fn split_dispatch(&self, n: u32) -> (u32, u32) {
        split_dispatch(n, self.dispatch_x)
    }
}

/// `(x, y)` with `x <= max_x` and `x * y >= n` (and `x * y - n < x`).
pub fn split_dispatch(n: u32, max_x: u32) -> (u32, u32) {
    let max_x = max_x.max(1);
    if n <= max_x {
        return (n, 1);
    }
    (max_x, n.div_ceil(max_x))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dispatch_split() {
        assert_eq!(split_dispatch(0, 65_535), (0, 1));
        assert_eq!(split_dispatch(65_535, 65_535), (65_535, 1));
        assert_eq!(split_dispatch(65_536, 65_535), (65_535, 2));
        assert_eq!(split_dispatch(293_000, 65_535), (65_535, 5));
        for n in [1u32, 7, 64, 1000, 4_000_000] {
            let (x, y) = split_dispatch(n, 5);
            assert!(x <= 5 && x * y >= n && x * y - n < x, "{n}");
        }
    }
}
