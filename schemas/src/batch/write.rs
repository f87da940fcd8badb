//! Planning a batch ([`BatchLayout`]) and filling it in place ([`BatchWriter`]).

use super::error::BatchError;
use super::format::{
    BATCH_FORMAT_VERSION, BATCH_LOST, BATCH_MAGIC, BatchHeader, BatchMeta, DType, Element,
    MAX_DIMS, MAX_SECTIONS, SECTION_ALIGN, SectionDesc, nul_padded_str, write_nul_padded,
};
use super::run_name::validate_run_name;
use super::sections::Section;
use bytemuck::Zeroable;

/// Handle of a section planned in a [`BatchLayout`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SectionId(usize);

/// The plan of a batch: every section's name, dtype, shape and aligned offset.
///
/// ```
/// use superflow_schemas::batch::{BatchLayout, BatchMeta, BatchView, BatchWriter};
///
/// let mut layout = BatchLayout::new();
/// let points = layout.add::<f32>("points", &[3, 4])?;
/// let ids = layout.add::<u32>("sample_ids", &[2])?;
/// let header = layout.header(&BatchMeta { run: "demo".into(), sample_count: 2, ..Default::default() })?;
///
/// let mut payload = vec![0u64; layout.payload_len().div_ceil(8)]; // 8-byte aligned storage
/// let payload: &mut [u8] = bytemuck::cast_slice_mut(&mut payload);
/// let mut writer = BatchWriter::new(&layout, payload)?;
/// writer.take::<f32>(points)?.iter_mut().enumerate().for_each(|(i, v)| *v = i as f32);
/// writer.write(ids, &[7u32, 9])?;
///
/// let view = BatchView::new(&header, payload)?;
/// let points = view.get::<f32>("points")?;
/// assert_eq!(points.shape(), &[3, 4]);
/// assert_eq!(points.data[5], 5.0);
/// assert_eq!(view.get::<u32>("sample_ids")?.data, &[7, 9]);
/// # Ok::<(), superflow_schemas::batch::BatchError>(())
/// ```
#[derive(Debug, Clone, Default)]
pub struct BatchLayout {
    sections: Vec<SectionDesc>,
    names: Vec<String>,
    payload_len: usize,
}

impl BatchLayout {
    /// An empty layout.
    pub fn new() -> Self {
        Self::default()
    }

    /// Plans a section of element type `T` and the given shape (row-major).
    pub fn add<T: Element>(
        &mut self,
        name: &str,
        shape: &[usize],
    ) -> Result<SectionId, BatchError> {
        self.add_dtype(name, T::DTYPE, shape)
    }

    /// Plans a section of a dtype chosen at run time.
    pub fn add_dtype(
        &mut self,
        name: &str,
        dtype: DType,
        shape: &[usize],
    ) -> Result<SectionId, BatchError> {
        let index = self.sections.len();
        if index >= MAX_SECTIONS {
            return Err(BatchError::TooManySections { count: index + 1 });
        }
        let bad_name = |reason| BatchError::BadName {
            index,
            name: name.to_string(),
            reason,
        };
        if name.is_empty() {
            return Err(bad_name("empty"));
        }
        if self.names.iter().any(|n| n == name) {
            return Err(bad_name("used twice"));
        }
        let mut desc = SectionDesc::zeroed();
        if !write_nul_padded(&mut desc.name, name) {
            return Err(bad_name("longer than 31 bytes or contains NUL"));
        }
        let bad_section = |reason: String| BatchError::BadSection {
            name: name.to_string(),
            reason,
        };
        if shape.is_empty() || shape.len() > MAX_DIMS {
            return Err(bad_section(format!(
                "{} dimensions, 1 to {MAX_DIMS} supported",
                shape.len()
            )));
        }
        let len_bytes = shape
            .iter()
            .try_fold(dtype.size(), |acc, d| acc.checked_mul(*d))
            .ok_or_else(|| bad_section(format!("shape {shape:?} overflows")))?;
        let offset = self.payload_len.next_multiple_of(SECTION_ALIGN);
        let end = offset
            .checked_add(len_bytes)
            .ok_or_else(|| bad_section("payload length overflows".into()))?;
        desc.dtype = dtype.code();
        desc.ndim = shape.len() as u32;
        for (slot, d) in desc.shape.iter_mut().zip(shape) {
            *slot = *d as u64;
        }
        desc.offset = offset as u64;
        desc.len_bytes = len_bytes as u64;
        self.sections.push(desc);
        self.names.push(name.to_string());
        self.payload_len = end;
        Ok(SectionId(index))
    }

    /// Plans a section of the section table, with the table's dtype; `shape` must have
    /// the table's rank and fixed sizes.
    pub fn add_section(
        &mut self,
        section: Section,
        shape: &[usize],
    ) -> Result<SectionId, BatchError> {
        section.check_shape(shape)?;
        self.add_dtype(&section.name(), section.spec().dtype, shape)
    }

    /// The planned section of that name, if any.
    pub fn find(&self, name: &str) -> Option<SectionId> {
        self.names.iter().position(|n| n == name).map(SectionId)
    }

    /// Bytes of payload the batch needs (the size to loan).
    pub fn payload_len(&self) -> usize {
        self.payload_len
    }

    /// The planned sections, in payload order.
    pub fn sections(&self) -> &[SectionDesc] {
        &self.sections
    }

    /// The header describing this layout, stamped with `meta`. `meta.flags` is 0, or
    /// [`BATCH_LOST`] for an empty layout and no sample (see [`BatchHeader::lost`]).
    pub fn header(&self, meta: &BatchMeta) -> Result<BatchHeader, BatchError> {
        validate_run_name(&meta.run)?;
        match meta.flags {
            0 => {}
            BATCH_LOST => {
                if !self.sections.is_empty() || meta.sample_count != 0 || self.payload_len != 0 {
                    return Err(BatchError::LostWithContent {
                        sections: self.sections.len() as u32,
                        samples: meta.sample_count,
                        payload_len: self.payload_len as u64,
                    });
                }
            }
            found => return Err(BatchError::Flags { found }),
        }
        let mut header = BatchHeader::zeroed();
        header.magic = BATCH_MAGIC;
        header.version = BATCH_FORMAT_VERSION;
        header.header_size = BatchHeader::SIZE as u32;
        header.section_count = self.sections.len() as u32;
        header.payload_len = self.payload_len as u64;
        header.epoch = meta.epoch;
        header.step = meta.step;
        header.seed = meta.seed;
        header.sequence = meta.sequence;
        header.created_unix_nanos = meta.created_unix_nanos;
        header.sample_count = meta.sample_count;
        header.flags = meta.flags;
        write_nul_padded(&mut header.run, &meta.run);
        header.sections[..self.sections.len()].copy_from_slice(&self.sections);
        Ok(header)
    }

    fn name(&self, id: SectionId) -> &str {
        self.sections
            .get(id.0)
            .and_then(|s| nul_padded_str(&s.name))
            .unwrap_or("?")
    }
}

impl BatchHeader {
    /// The header of a lost batch at `meta`'s place in the stream (run, epoch, step,
    /// seed, sequence, time): [`BATCH_LOST`], no section, no sample, `payload_len` 0.
    /// `meta`'s `sample_count` and `flags` are not used.
    pub fn lost(meta: &BatchMeta) -> Result<Self, BatchError> {
        BatchLayout::new().header(&BatchMeta {
            sample_count: 0,
            flags: BATCH_LOST,
            ..meta.clone()
        })
    }
}

/// Hands out the mutable slice of every section of a payload buffer, so that each
/// section is written exactly once, in place (for example by several rayon tasks at
/// once: each [`BatchWriter::take`] borrows a disjoint part of the buffer).
///
/// [`BatchWriter::new`] zeroes the payload first, so padding and any section left
/// unwritten are zero: two batches built from the same samples are bit-identical.
#[derive(Debug)]
pub struct BatchWriter<'a> {
    layout: &'a BatchLayout,
    slices: Vec<Option<&'a mut [u8]>>,
}

impl<'a> BatchWriter<'a> {
    /// Splits `payload` (at least [`BatchLayout::payload_len`] bytes, 8-byte aligned)
    /// into the layout's sections.
    pub fn new(layout: &'a BatchLayout, payload: &'a mut [u8]) -> Result<Self, BatchError> {
        Self::split(layout, payload, true)
    }

    /// Like [`BatchWriter::new`] for a payload the caller has just zeroed (an iceoryx2
    /// slice loaned with `write_from_fn(|_| 0)`): skips the second zeroing pass. Bytes
    /// that are not zero break rule 4 (identical batches are bit-identical), nothing
    /// else.
    pub fn over_zeroed(layout: &'a BatchLayout, payload: &'a mut [u8]) -> Result<Self, BatchError> {
        Self::split(layout, payload, false)
    }

    fn split(
        layout: &'a BatchLayout,
        payload: &'a mut [u8],
        zero: bool,
    ) -> Result<Self, BatchError> {
        if payload.len() < layout.payload_len {
            return Err(BatchError::BufferTooSmall {
                needed: layout.payload_len as u64,
                actual: payload.len(),
            });
        }
        let needed = layout
            .sections
            .iter()
            .filter_map(|s| DType::from_code(s.dtype))
            .map(DType::size)
            .max()
            .unwrap_or(1);
        let address = payload.as_ptr() as usize;
        if !address.is_multiple_of(needed) {
            return Err(BatchError::Misaligned {
                found: 1 << address.trailing_zeros().min(12),
                needed,
            });
        }
        let (used, _) = payload.split_at_mut(layout.payload_len);
        if zero {
            used.fill(0);
        }
        let mut rest = used;
        let mut consumed = 0usize;
        let mut slices = Vec::with_capacity(layout.sections.len());
        for section in &layout.sections {
            let (_, after_gap) = rest.split_at_mut(section.offset as usize - consumed);
            let (slice, after) = after_gap.split_at_mut(section.len_bytes as usize);
            slices.push(Some(slice));
            rest = after;
            consumed = (section.offset + section.len_bytes) as usize;
        }
        Ok(Self { layout, slices })
    }

    /// The section's elements, to be written in place. Each section can be taken once.
    pub fn take<T: Element>(&mut self, id: SectionId) -> Result<&'a mut [T], BatchError> {
        let name = || self.layout.name(id).to_string();
        let desc = self
            .layout
            .sections
            .get(id.0)
            .ok_or_else(|| BatchError::Missing {
                name: format!("#{}", id.0),
            })?;
        let actual = DType::from_code(desc.dtype).ok_or_else(|| BatchError::UnknownDType {
            name: name(),
            code: desc.dtype,
        })?;
        if actual != T::DTYPE {
            return Err(BatchError::WrongDType {
                name: name(),
                actual,
                requested: T::DTYPE,
            });
        }
        let bytes = self.slices[id.0]
            .take()
            .ok_or_else(|| BatchError::AlreadyTaken { name: name() })?;
        bytemuck::try_cast_slice_mut(bytes).map_err(|e| BatchError::BadSection {
            name: name(),
            reason: e.to_string(),
        })
    }

    /// [`BatchWriter::take`] of a section of the table, which must declare it as `T`.
    pub fn take_section<T: Element>(
        &mut self,
        section: Section,
    ) -> Result<&'a mut [T], BatchError> {
        let id = self.id_of::<T>(section)?;
        self.take(id)
    }

    /// [`BatchWriter::write`] of a section of the table, which must declare it as `T`.
    pub fn write_section<T: Element>(
        &mut self,
        section: Section,
        data: &[T],
    ) -> Result<(), BatchError> {
        let id = self.id_of::<T>(section)?;
        self.write(id, data)
    }

    fn id_of<T: Element>(&self, section: Section) -> Result<SectionId, BatchError> {
        section.check::<T>()?;
        let name = section.name();
        self.layout.find(&name).ok_or_else(|| BatchError::Missing {
            name: name.into_owned(),
        })
    }

    /// Copies `data` into the section; its length must equal the section's element count.
    pub fn write<T: Element>(&mut self, id: SectionId, data: &[T]) -> Result<(), BatchError> {
        let target = self.take::<T>(id)?;
        if target.len() != data.len() {
            return Err(BatchError::BadSection {
                name: self.layout.name(id).to_string(),
                reason: format!("{} elements written into {}", data.len(), target.len()),
            });
        }
        target.copy_from_slice(data);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sections_are_aligned_and_packed_in_order() {
        let mut layout = BatchLayout::new();
        let a = layout.add::<u8>("a", &[3]).unwrap();
        let b = layout.add::<f64>("b", &[2, 2]).unwrap();
        let c = layout.add::<u16>("c", &[1, 1, 1, 5]).unwrap();
        assert_eq!((a, b, c), (SectionId(0), SectionId(1), SectionId(2)));
        let offsets: Vec<u64> = layout.sections().iter().map(|s| s.offset).collect();
        assert_eq!(offsets, [0, 64, 128]);
        assert_eq!(layout.payload_len(), 128 + 10);
    }

    #[test]
    fn invalid_plans_are_errors() {
        let mut layout = BatchLayout::new();
        layout.add::<u8>("x", &[1]).unwrap();
        assert!(matches!(
            layout.add::<u8>("x", &[1]),
            Err(BatchError::BadName { .. })
        ));
        assert!(layout.add::<u8>("", &[1]).is_err());
        assert!(layout.add::<u8>(&"n".repeat(32), &[1]).is_err());
        assert!(layout.add::<u8>("ok", &[]).is_err());
        assert!(layout.add::<u8>("five", &[1, 1, 1, 1, 1]).is_err());
        assert!(layout.add::<f32>("huge", &[usize::MAX / 2, 3]).is_err());
        for i in 1..MAX_SECTIONS {
            layout.add::<u8>(&format!("s{i}"), &[1]).unwrap();
        }
        assert!(matches!(
            layout.add::<u8>("one_more", &[1]),
            Err(BatchError::TooManySections { .. })
        ));
        let meta = BatchMeta {
            run: "has space".into(),
            ..Default::default()
        };
        assert!(matches!(
            layout.header(&meta),
            Err(BatchError::BadRunName { .. })
        ));
    }

    #[test]
    fn writer_checks_buffer_dtype_and_single_take() {
        let mut layout = BatchLayout::new();
        let f = layout.add::<f32>("f", &[4]).unwrap();
        let mut storage = vec![0u64; 4];
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut storage);
        assert!(matches!(
            BatchWriter::new(&layout, &mut bytes[..8]),
            Err(BatchError::BufferTooSmall { .. })
        ));
        assert!(matches!(
            BatchWriter::new(&layout, &mut bytes[1..]),
            Err(BatchError::Misaligned { .. })
        ));
        let mut writer = BatchWriter::new(&layout, bytes).unwrap();
        assert!(matches!(
            writer.take::<u32>(f),
            Err(BatchError::WrongDType { .. })
        ));
        assert!(matches!(
            writer.write(f, &[1.0f32; 3]),
            Err(BatchError::BadSection { .. })
        ));
        assert!(matches!(
            writer.take::<f32>(f),
            Err(BatchError::AlreadyTaken { .. })
        ));
    }

    #[test]
    fn writer_zeroes_stale_bytes() {
        let mut layout = BatchLayout::new();
        layout.add::<u8>("a", &[1]).unwrap();
        let b = layout.add::<u8>("b", &[1]).unwrap();
        let mut storage = vec![0xFFu8; 65];
        let mut writer = BatchWriter::new(&layout, &mut storage).unwrap();
        writer.write(b, &[5u8]).unwrap();
        let mut expected = vec![0u8; 65];
        expected[64] = 5;
        assert_eq!(storage, expected);
    }
}
