//! [`LabelConfig`]: the `[labels]` section of `pipeline.toml`, checked into a [`LabelMap`].

use super::map::LabelMap;
use crate::decode::points::LabelFieldSpec;
use rustc_hash::FxHashMap;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use superflow_common::InvalidSetting;

/// The `[labels]` section of `pipeline.toml`: how per-point labels are read and turned
/// into training classes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LabelConfig {
    /// The label field, matched regardless of case; by default the first of `label`,
    /// `class`, `semantic`, `semantic_label`, `lidarseg` present (a sidecar's only field
    /// also serves).
    pub field: Option<String>,
    /// Bits of the stored value that are the class (SemanticKITTI: `0xFFFF`, the instance
    /// being in the upper 16 bits); by default the whole value.
    pub label_mask: Option<u32>,
    /// Raw id → training class (nuScenes-lidarseg: its 32 raw classes to the 16 training
    /// classes). Keys are decimal (or `0x` hex) raw ids; a raw id not listed becomes
    /// `ignore_index`. Empty (the default): raw ids are the training classes.
    pub mapping: BTreeMap<String, u8>,
    /// The training class of unlabelled or unmapped points (255).
    pub ignore_index: u8,
    /// Names of the training classes, in id order, for reports; with them, a raw id of at
    /// least their number is an error when there is no mapping. Empty by default.
    pub classes: Vec<String>,
}

impl Default for LabelConfig {
    fn default() -> Self {
        Self {
            field: None,
            label_mask: None,
            mapping: BTreeMap::new(),
            ignore_index: 255,
            classes: Vec::new(),
        }
    }
}

impl LabelConfig {
    /// Checks the settings ([`LabelConfig::label_map`] without the map).
    pub fn validate(&self) -> Result<(), InvalidSetting> {
        self.label_map().map(|_| ())
    }

    /// Which field to read and which bits of it.
    pub fn field_spec(&self) -> LabelFieldSpec {
        LabelFieldSpec {
            name: self.field.clone(),
            mask: self.label_mask,
        }
    }

    /// The checked raw id → training class map: mapping keys are raw ids, a mask is not
    /// 0, `ignore_index` is not a named class, and every mapped class is a named class
    /// (when classes are named) or `ignore_index`.
    pub fn label_map(&self) -> Result<LabelMap, InvalidSetting> {
        if self.field.as_deref().is_some_and(str::is_empty) {
            return Err(InvalidSetting::new(
                "labels.field",
                "\"\"",
                "must name a field",
            ));
        }
        if self.label_mask == Some(0) {
            return Err(InvalidSetting::new(
                "labels.label_mask",
                0,
                "must keep at least one bit",
            ));
        }
        let class_count = self.classes.len();
        if class_count > usize::from(self.ignore_index) {
            return Err(InvalidSetting::new(
                "labels.ignore_index",
                self.ignore_index,
                format!(
                    "must not be a class id: labels.classes names {class_count} classes (0..{class_count})"
                ),
            ));
        }
        let table = (!self.mapping.is_empty())
            .then(|| {
                self.mapping
                    .iter()
                    .map(|(key, &class)| {
                        let setting = format!("labels.mapping.{key}");
                        let raw = parse_raw_id(key).ok_or_else(|| {
                            InvalidSetting::new(
                                &setting,
                                class,
                                "has a key that is not a raw id (a decimal or 0x hex u32)",
                            )
                        })?;
                        if class_count > 0
                            && usize::from(class) >= class_count
                            && class != self.ignore_index
                        {
                            return Err(InvalidSetting::new(
                                setting,
                                class,
                                format!(
                                    "is neither one of the {class_count} labels.classes nor labels.ignore_index ({})",
                                    self.ignore_index
                                ),
                            ));
                        }
                        Ok((raw, class))
                    })
                    .collect::<Result<FxHashMap<u32, u8>, _>>()
            })
            .transpose()?;
        Ok(LabelMap {
            table,
            ignore_index: self.ignore_index,
            class_count,
        })
    }
}

/// A raw id written as a TOML key: decimal or `0x` hex.
fn parse_raw_id(key: &str) -> Option<u32> {
    let key = key.trim();
    match key.strip_prefix("0x").or_else(|| key.strip_prefix("0X")) {
        Some(hex) => u32::from_str_radix(hex, 16).ok(),
        None => key.parse().ok(),
    }
}
