//! Runtime choice of AVX2 code for SLIC's hot loops.
//!
//! The crate is built for baseline x86-64 (SSE2), which leaves half of the vector width
//! of current CPUs unused. The hot loops are therefore also compiled with AVX2 enabled
//! (`#[target_feature]` copies of functions whose bodies are `#[inline(always)]`) and
//! chosen at run time when the CPU has it. Only AVX2 is enabled, not FMA: the arithmetic
//! stays the same IEEE operations in the same order (Rust never contracts `a * b + c`),
//! so both copies give identical results.

/// Whether the CPU runs AVX2 code.
#[cfg(target_arch = "x86_64")]
#[inline]
pub(super) fn has_avx2() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
}
