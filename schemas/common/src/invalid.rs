//! The one error every `validate` of a configuration returns, the pipeline's and the
//! trainer's alike.

use std::fmt;

/// A setting out of range: which one (its TOML path, e.g. `sample.temporal_frames` or
/// `optim.steps`),
/// the value found and the rule it breaks.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{setting} = {value} {rule}")]
pub struct InvalidSetting {
    /// The setting's TOML path.
    pub setting: String,
    /// The value found, as written.
    pub value: String,
    /// What it must be.
    pub rule: String,
}

impl InvalidSetting {
    /// `setting = value rule`, e.g. `("sample.cameras", 0, "must be 1..=255")`.
    pub fn new(
        setting: impl Into<String>,
        value: impl fmt::Display,
        rule: impl Into<String>,
    ) -> Self {
        Self {
            setting: setting.into(),
            value: value.to_string(),
            rule: rule.into(),
        }
    }
}
