//! The compute device a backend name (`--backend`) stands for.

use burn::tensor::Device;

/// A `--backend` this build cannot run.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BackendError {
    /// Not one of flex, wgpu, cuda.
    #[error("unknown backend {0:?} (flex, wgpu, cuda)")]
    Unknown(String),
    /// A GPU backend whose cargo feature this build was made without.
    #[error("backend {0} is not compiled in: build with `--features {0}`")]
    NotCompiledIn(&'static str),
}

/// The device of `backend`: `flex` (CPU), `wgpu` (the best adapter; set
/// `CUBECL_WGPU_DEFAULT_DEVICE` to choose another) or `cuda` (GPU `index`).
#[cfg_attr(not(feature = "cuda"), allow(unused_variables))]
pub fn select(backend: &str, index: usize) -> Result<Device, BackendError> {
    match backend {
        "flex" => Ok(Device::flex()),
        #[cfg(feature = "wgpu")]
        "wgpu" => Ok(Device::wgpu(burn::tensor::DeviceKind::DefaultDevice)),
        #[cfg(feature = "cuda")]
        "cuda" => Ok(Device::cuda(index)),
        #[cfg(not(feature = "wgpu"))]
        "wgpu" => Err(BackendError::NotCompiledIn("wgpu")),
        #[cfg(not(feature = "cuda"))]
        "cuda" => Err(BackendError::NotCompiledIn("cuda")),
        other => Err(BackendError::Unknown(other.to_string())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flex_is_always_there_and_unknown_names_are_errors() {
        assert!(select("flex", 0).is_ok());
        assert_eq!(
            select("tpu", 0).expect_err("unknown").to_string(),
            "unknown backend \"tpu\" (flex, wgpu, cuda)"
        );
        #[cfg(not(feature = "cuda"))]
        assert_eq!(
            select("cuda", 0).expect_err("not built").to_string(),
            "backend cuda is not compiled in: build with `--features cuda`"
        );
    }
}
