//! [`LabelForm`]: where a drive's labels are, a field of its clouds or a sidecar.

use serde::{Deserialize, Serialize};

/// Where a drive's labels are.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "form", rename_all = "snake_case")]
pub enum LabelForm {
    /// A field of the LiDAR's clouds.
    Field {
        /// The field's name as recorded.
        field: String,
    },
    /// Parallel clouds in a `<drive>.labels.mcap` sidecar.
    Sidecar {
        /// The sidecar file.
        file: String,
        /// Its label-cloud topic.
        topic: String,
    },
}

impl std::fmt::Display for LabelForm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LabelForm::Field { field } => write!(f, "field `{field}` of the LiDAR clouds"),
            LabelForm::Sidecar { file, topic } => write!(f, "sidecar {file}: {topic}"),
        }
    }
}
