//! The compute device a backend name (`--backend`) stands for.

use burn::tensor::Device;

/// A compute backend (`--backend`, `--backends`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum Backend {
    /// burn's CPU backend.
    #[default]
    Flex,
    /// wgpu: Vulkan, Metal or DX12 (build with `--features wgpu`).
    Wgpu,
    /// CUDA (build with `--features cuda`).
    Cuda,
}

impl Backend {
    /// Its name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Flex => "flex",
            Backend::Wgpu => "wgpu",
            Backend::Cuda => "cuda",
        }
    }
}

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A `--backend` this build or machine cannot run.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BackendError {
    /// A GPU backend whose cargo feature this build was made without.
    #[error("backend {0} is not compiled in: build with `--features {0}`")]
    NotCompiledIn(&'static str),
    /// A GPU backend this machine has no device for (no driver, no adapter).
    // The runtime's reason sits inside the message, in parentheses: not a source, so a
    // printer of the chain does not repeat it.
    #[cfg(feature = "wgpu")]
    #[error("backend {backend}: no device on this machine ({error})")]
    NoDevice {
        /// The backend asked for.
        backend: &'static str,
        /// What the runtime said.
        error: burn::cubecl::device::DeviceUnavailable,
    },
    /// A GPU backend whose runtime answered with a device of another runtime.
    #[cfg(feature = "wgpu")]
    #[error(
        "backend {backend}: no device on this machine (the runtime answered with a device of another runtime)"
    )]
    OtherRuntime {
        /// The backend asked for.
        backend: &'static str,
    },
}

/// What the trainer needs to know of a GPU device it opened.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GpuInfo {
    /// The adapter as it names itself (`llvmpipe (LLVM 15.0.6, 256 bits)`, `NVIDIA H200`).
    pub name: String,
    /// The adapter's limit on workgroups per dispatch dimension (Vulkan's
    /// `maxComputeWorkGroupCount`, wgpu's `max_compute_workgroups_per_dimension`).
    pub max_workgroups_per_dimension: u32,
    /// No card behind it: a software rasterizer (llvmpipe, lavapipe) or a CPU.
    pub software: bool,
}

impl std::fmt::Display for GpuInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}, at most {} workgroups per dimension)",
            self.name,
            if self.software {
                "software"
            } else {
                "hardware"
            },
            self.max_workgroups_per_dimension
        )
    }
}

/// The device of `backend`: `flex` (CPU), `wgpu` (the best adapter; set
/// `CUBECL_WGPU_DEFAULT_DEVICE` to choose another) or `cuda` (GPU `index`).
#[cfg_attr(not(feature = "cuda"), allow(unused_variables))]
pub fn select(backend: Backend, index: usize) -> Result<Device, BackendError> {
    match backend {
        Backend::Flex => Ok(Device::flex()),
        #[cfg(feature = "wgpu")]
        Backend::Wgpu => wgpu::open().map(|(device, _)| device),
        #[cfg(feature = "cuda")]
        Backend::Cuda => Ok(Device::cuda(index)),
        #[cfg(not(feature = "wgpu"))]
        Backend::Wgpu => Err(BackendError::NotCompiledIn("wgpu")),
        #[cfg(not(feature = "cuda"))]
        Backend::Cuda => Err(BackendError::NotCompiledIn("cuda")),
    }
}

/// Waits until the work queued on `device` has run. A GPU runtime compiles and runs
/// kernels on threads of its own, and a step's last kernels (the optimizer's update, the
/// frees of dropped tensors) are still queued when the host has its loss; a process that
/// exits then tears the driver's globals down under a thread that is inside its compiler
/// (seen with Mesa's lavapipe: SIGSEGV in LLVM after the run had succeeded). Every command
/// settles its device before it returns. An error is logged, not returned: the work
/// that counted has already been read back.
pub fn settle(device: &Device) {
    if let Err(e) = device.sync() {
        tracing::warn!(
            ?device,
            "the device failed while finishing its queued work: {e}"
        );
    }
}

/// The largest number of index rows one gather or scatter-add may take on `device`: the
/// adapter's workgroup limit on wgpu, past which burn's scatter-add and row sums were seen
/// wrong (see `pipeline/docs/FIELD_NOTES.md`); `None` (no limit) elsewhere. Known for the wgpu devices
/// [`select`] opened.
pub fn index_rows_limit(device: &Device) -> Option<usize> {
    #[cfg(feature = "wgpu")]
    {
        wgpu::info(device).map(|info| info.max_workgroups_per_dimension as usize)
    }
    #[cfg(not(feature = "wgpu"))]
    {
        let _ = device;
        None
    }
}

/// What [`select`] learned of `device` if it is a GPU it opened.
pub fn gpu_info(device: &Device) -> Option<GpuInfo> {
    #[cfg(feature = "wgpu")]
    {
        wgpu::info(device)
    }
    #[cfg(not(feature = "wgpu"))]
    {
        let _ = device;
        None
    }
}

#[cfg(feature = "wgpu")]
mod wgpu {
    use super::{BackendError, GpuInfo};
    use burn::cubecl::wgpu::WgpuDeviceKind;
    use burn::tensor::Device;
    use std::sync::{Mutex, PoisonError};

    /// The wgpu devices opened so far, with what their adapters report.
    static OPENED: Mutex<Vec<(Device, GpuInfo)>> = Mutex::new(Vec::new());

    /// The default adapter (the best one; `CUBECL_WGPU_DEFAULT_DEVICE` chooses another)
    /// as a burn device, with its name and limits.
    pub(super) fn open() -> Result<(Device, GpuInfo), BackendError> {
        let cube = burn::cubecl::Device::wgpu(WgpuDeviceKind::DefaultDevice).map_err(|error| {
            BackendError::NoDevice {
                backend: "wgpu",
                error,
            }
        })?;
        let client = cube.client();
        let properties = client.properties();
        let (x, y, z) = properties.hardware.max_cube_count;
        let info = GpuInfo {
            name: properties.identity.name.clone(),
            max_workgroups_per_dimension: x.min(y).min(z),
            software: properties.identity.physical.is_none(),
        };
        let burn::cubecl::Device::Wgpu(wgpu) = cube else {
            return Err(BackendError::OtherRuntime { backend: "wgpu" });
        };
        let device = Device::new(wgpu);
        let mut opened = OPENED.lock().unwrap_or_else(PoisonError::into_inner);
        if !opened.iter().any(|(d, _)| *d == device) {
            opened.push((device.clone(), info.clone()));
        }
        Ok((device, info))
    }

    pub(super) fn info(device: &Device) -> Option<GpuInfo> {
        let opened = OPENED.lock().unwrap_or_else(PoisonError::into_inner);
        if opened.is_empty() {
            return None;
        }
        opened
            .iter()
            .find(|(d, _)| d == device)
            .map(|(_, info)| info.clone())
    }
}

/// The wgpu device with what its adapter reports (`None` in a build without `wgpu`).
pub fn open_wgpu() -> Result<(Device, GpuInfo), BackendError> {
    #[cfg(feature = "wgpu")]
    {
        wgpu::open()
    }
    #[cfg(not(feature = "wgpu"))]
    {
        Err(BackendError::NotCompiledIn("wgpu"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flex_is_always_there_and_a_backend_not_built_is_an_error() {
        use clap::ValueEnum as _;
        assert!(select(Backend::Flex, 0).is_ok());
        for backend in Backend::value_variants() {
            assert_eq!(Backend::from_str(backend.name(), false), Ok(*backend));
        }
        #[cfg(not(feature = "cuda"))]
        assert_eq!(
            select(Backend::Cuda, 0).expect_err("not built").to_string(),
            "backend cuda is not compiled in: build with `--features cuda`"
        );
    }
}
