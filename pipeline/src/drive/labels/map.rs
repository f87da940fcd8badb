//! [`LabelMap`]: raw ids to training classes.

use rustc_hash::FxHashMap;

/// Raw ids → training classes ([`LabelConfig::label_map`](super::LabelConfig::label_map)).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LabelMap {
    /// Raw id → class; `None`: the raw id is the class.
    pub(super) table: Option<FxHashMap<u32, u8>>,
    pub(super) ignore_index: u8,
    /// Named classes (0: none named).
    pub(super) class_count: usize,
}

impl LabelMap {
    /// The training class of raw id `raw`: mapped (`ignore_index` when unlisted), or
    /// without a mapping the id itself — `Err(raw)` when it is not below the number of
    /// named classes (or 256).
    #[inline]
    pub fn class_of(&self, raw: u32) -> Result<u8, u32> {
        match &self.table {
            Some(table) => Ok(table.get(&raw).copied().unwrap_or(self.ignore_index)),
            None => u8::try_from(raw)
                .ok()
                .filter(|c| self.class_count == 0 || usize::from(*c) < self.class_count)
                .ok_or(raw),
        }
    }

    /// The training classes of `raw` ids; `Err` with the first id that has none.
    pub fn classes_of(&self, raw: &[u32]) -> Result<Vec<u8>, u32> {
        raw.iter().map(|&r| self.class_of(r)).collect()
    }

    /// The class of unlabelled and unmapped points.
    pub fn ignore_index(&self) -> u8 {
        self.ignore_index
    }

    /// Whether raw ids go through a mapping.
    pub fn has_mapping(&self) -> bool {
        self.table.is_some()
    }

    /// Why a raw id has no class without a mapping, for errors.
    pub(super) fn limit(&self) -> String {
        if self.class_count > 0 {
            format!(
                "labels.classes names {} classes (ids 0..{})",
                self.class_count, self.class_count
            )
        } else {
            "training classes are u8 ids below 256".to_string()
        }
    }
}
