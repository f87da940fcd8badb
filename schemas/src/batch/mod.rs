//! The batch on the wire: a fixed `#[repr(C)]` [`BatchHeader`] (the iceoryx2 user header)
//! and a byte payload of typed, aligned sections described by the header's section table.
//!
//! The layout is specified byte for byte in `schemas/BATCH_FORMAT.md`. The producer plans
//! the sections with a [`BatchLayout`], loans a payload of [`BatchLayout::payload_len`]
//! bytes and fills every section in place through [`BatchWriter`]; a consumer wraps the
//! received header and payload in a [`BatchView`], which validates everything before
//! handing out typed slices.
//!
//! Which sections a SuperFlow batch holds is the table of [`sections`]: the pipeline
//! plans and fills a batch by [`Section`] ([`BatchLayout::add_section`],
//! [`BatchWriter::take_section`]) and the trainer reads by [`Section`]
//! ([`BatchView::section`]), each access checked against the table's dtype.

mod error;
mod format;
mod read;
mod run_name;
pub mod sections;
mod write;

pub use error::BatchError;
pub use format::{
    BATCH_FORMAT_VERSION, BATCH_LOST, BATCH_MAGIC, BatchHeader, BatchMeta, DType, Element,
    MAX_DIMS, MAX_SECTIONS, RUN_NAME_LEN, SECTION_ALIGN, SECTION_NAME_LEN, SectionDesc,
};
pub use read::{BatchView, TensorView};
pub use run_name::validate_run_name;
pub use sections::{Dims, LevelDims, Section, SectionSpec};
pub use write::{BatchLayout, BatchWriter, SectionId};
