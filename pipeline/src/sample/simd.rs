//! Runtime choice of the vector code for the sample builder's hot loops.
//!
//! The crate is built for baseline x86-64 (SSE2), which leaves most of the vector width
//! of current CPUs unused. The hot loops (bilinear resize, cylindrical cells and their
//! ranges, the projection's cone test, SLIC) are therefore also compiled with AVX2, most
//! of them with AVX-512 too (`#[target_feature]` copies of functions whose bodies are
//! `#[inline(always)]`), and the widest copy the CPU runs is chosen at run time. FMA is
//! never used for contraction (Rust never contracts `a * b + c`): every copy performs the
//! same IEEE operations in the same order, so all give identical results.

/// Whether the CPU runs AVX2 code.
#[cfg(target_arch = "x86_64")]
#[inline]
pub(crate) fn has_avx2() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
}

/// Whether the AVX-512 copies run: the CPU has AVX-512 F and BW (AMD Zen 4 and later,
/// Intel server cores since Skylake-SP) and `SUPERFLOW_NO_AVX512` is not set. Every copy
/// gives the same results; the variable is for CPUs that lower their clock for 512-bit
/// code (Skylake-SP, Cascade Lake), where the AVX2 copies may be faster overall.
#[cfg(target_arch = "x86_64")]
pub(crate) fn has_avx512() -> bool {
    static CHOSEN: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *CHOSEN.get_or_init(|| {
        std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::env::var_os("SUPERFLOW_NO_AVX512").is_none()
    })
}
