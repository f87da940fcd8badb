//! What indexing skipped: [`SkipReport`] counts skips by kind and spells out the first
//! of each; [`DamageKind`] names the kinds that file damage causes.

use crate::source::Damage;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Counted skips, one entry per kind, with the first occurrence spelled out.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SkipReport {
    /// Kind → count and first example (`file: topic at stamp: error`).
    pub entries: BTreeMap<String, SkipEntry>,
}

/// One kind of skip.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SkipEntry {
    /// How many.
    pub count: u64,
    /// The first one, in words.
    pub first: String,
}

impl SkipReport {
    /// Counts one skip of `kind`; `detail` is kept for the first.
    pub fn add(&mut self, kind: impl Into<String>, detail: impl FnOnce() -> String) {
        self.entries
            .entry(kind.into())
            .and_modify(|e| e.count += 1)
            .or_insert_with(|| SkipEntry {
                count: 1,
                first: detail(),
            });
    }

    /// Total skips.
    pub fn total(&self) -> u64 {
        self.entries.values().map(|e| e.count).sum()
    }
}

/// The skip kind of each [`Damage`] of a file: the key of its [`SkipReport`] entry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DamageKind {
    /// [`Damage::Truncated`].
    Truncated,
    /// [`Damage::NoSummary`].
    NoSummary,
    /// [`Damage::BadChunk`].
    BadChunk,
    /// [`Damage::BadRecord`].
    BadRecord,
    /// [`Damage::MissingMessages`].
    MissingMessages,
}

impl DamageKind {
    /// Every kind.
    pub const ALL: [DamageKind; 5] = [
        DamageKind::Truncated,
        DamageKind::NoSummary,
        DamageKind::BadChunk,
        DamageKind::BadRecord,
        DamageKind::MissingMessages,
    ];

    /// The kind of `damage`.
    pub fn of(damage: &Damage) -> DamageKind {
        match damage {
            Damage::Truncated { .. } => DamageKind::Truncated,
            Damage::NoSummary { .. } => DamageKind::NoSummary,
            Damage::BadChunk { .. } => DamageKind::BadChunk,
            Damage::BadRecord { .. } => DamageKind::BadRecord,
            Damage::MissingMessages { .. } => DamageKind::MissingMessages,
        }
    }

    /// The kind in words, as the report keys it.
    pub fn as_str(self) -> &'static str {
        match self {
            DamageKind::Truncated => "file truncated",
            DamageKind::NoSummary => "file without summary",
            DamageKind::BadChunk => "unreadable chunk",
            DamageKind::BadRecord => "corrupt record",
            DamageKind::MissingMessages => "messages lost to damage",
        }
    }

    /// Whether messages were lost (a file without summary loses none: it only cannot be
    /// cross-checked).
    pub fn loses_data(self) -> bool {
        self != DamageKind::NoSummary
    }

    /// Whether the report key `kind` is a kind of damage that lost messages.
    pub fn is_data_loss(kind: &str) -> bool {
        Self::ALL
            .iter()
            .any(|k| k.loses_data() && k.as_str() == kind)
    }
}
