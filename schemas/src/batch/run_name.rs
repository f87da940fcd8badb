//! The run name a batch carries: checked where a batch is written and where it is read.

use super::error::BatchError;
use super::format::RUN_NAME_LEN;

/// Checks a run name: printable ASCII without `/`, shorter than [`RUN_NAME_LEN`].
pub fn validate_run_name(run: &str) -> Result<(), BatchError> {
    let fail = |reason| {
        Err(BatchError::BadRunName {
            name: run.to_string(),
            reason,
        })
    };
    if run.is_empty() {
        return fail("empty");
    }
    if run.len() >= RUN_NAME_LEN {
        return fail("longer than 63 bytes");
    }
    if !run
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b))
    {
        return fail("only ASCII letters, digits, '-', '_' and '.' are allowed");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn run_names_are_printable_and_short() {
        assert!(validate_run_name("ablation-3.a_b").is_ok());
        assert!(validate_run_name("a/b").is_err());
        assert!(validate_run_name("").is_err());
        assert!(validate_run_name(&"x".repeat(64)).is_err());
    }
}
