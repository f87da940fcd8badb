//! Validated, typed, zero-copy views of a received batch.

use super::error::BatchError;
use super::format::{
    BATCH_FORMAT_VERSION, BATCH_LOST, BATCH_MAGIC, BatchHeader, BatchMeta, DType, Element,
    MAX_DIMS, MAX_SECTIONS, SECTION_ALIGN, SectionDesc, nul_padded_str,
};
use super::run_name::validate_run_name;
use super::sections::Section;

/// A typed view of one section: its elements and shape, borrowed from the payload.
#[derive(Debug, Clone, Copy)]
pub struct TensorView<'a, T> {
    /// The section's name.
    pub name: &'a str,
    /// The elements, row-major.
    pub data: &'a [T],
    dims: [usize; MAX_DIMS],
    ndim: usize,
}

impl<T> TensorView<'_, T> {
    /// The shape, outermost dimension first.
    pub fn shape(&self) -> &[usize] {
        &self.dims[..self.ndim]
    }
}

/// One validated entry of the section table.
#[derive(Debug, Clone)]
struct Entry<'a> {
    name: &'a str,
    dtype: DType,
    dims: [usize; MAX_DIMS],
    ndim: usize,
    bytes: &'a [u8],
}

/// A received batch whose header and payload were checked: magic, version, header size,
/// flags, section names, dtypes, shapes against lengths, bounds, alignment and overlaps.
/// After [`BatchView::new`] succeeds, reading a section of the right dtype cannot fail
/// (a lost batch, [`BatchView::is_lost`], has no section to read).
#[derive(Debug, Clone)]
pub struct BatchView<'a> {
    meta: BatchMeta,
    sections: Vec<Entry<'a>>,
}

impl<'a> BatchView<'a> {
    /// Validates `header` against `payload` (the received slice, possibly longer than
    /// the header's `payload_len`).
    pub fn new(header: &'a BatchHeader, payload: &'a [u8]) -> Result<Self, BatchError> {
        let count = check_header(header)?;
        let payload_len = usize::try_from(header.payload_len)
            .ok()
            .filter(|len| *len <= payload.len())
            .ok_or(BatchError::PayloadTooShort {
                declared: header.payload_len,
                actual: payload.len(),
            })?;
        let payload = &payload[..payload_len];
        let mut sections: Vec<Entry<'a>> = Vec::with_capacity(count);
        for (index, desc) in header.sections[..count].iter().enumerate() {
            let name = entry_name(index, desc, &sections)?;
            sections.push(entry(name, desc, payload)?);
        }
        check_overlaps(&sections)?;
        Ok(Self {
            meta: header.meta(),
            sections,
        })
    }

    /// Run, epoch, step, seed and the other stream fields of the header.
    pub fn meta(&self) -> &BatchMeta {
        &self.meta
    }

    /// Whether the batch is lost ([`BATCH_LOST`]): every sample failed in the pipeline.
    /// It counts as the batch at its position (its epoch still ends after it) but has no
    /// section and no sample.
    pub fn is_lost(&self) -> bool {
        self.meta.lost()
    }

    /// Section names in table order.
    pub fn section_names(&self) -> impl Iterator<Item = &'a str> + '_ {
        self.sections.iter().map(|s| s.name)
    }

    /// The dtype and shape of a section.
    pub fn describe(&self, name: &str) -> Result<(DType, &[usize]), BatchError> {
        let section = self.find(name)?;
        Ok((section.dtype, &section.dims[..section.ndim]))
    }

    /// The raw bytes of a section.
    pub fn bytes(&self, name: &str) -> Result<&'a [u8], BatchError> {
        Ok(self.find(name)?.bytes)
    }

    /// A typed view of a section; an error if the name is absent or the dtype differs.
    pub fn get<T: Element>(&self, name: &str) -> Result<TensorView<'a, T>, BatchError> {
        let section = self.find(name)?;
        if section.dtype != T::DTYPE {
            return Err(BatchError::WrongDType {
                name: name.to_string(),
                actual: section.dtype,
                requested: T::DTYPE,
            });
        }
        let data = bytemuck::try_cast_slice(section.bytes).map_err(|e| BatchError::BadSection {
            name: name.to_string(),
            reason: e.to_string(),
        })?;
        Ok(TensorView {
            name: section.name,
            data,
            dims: section.dims,
            ndim: section.ndim,
        })
    }

    /// A typed view of a section of the section table, which must declare it as `T`.
    pub fn section<T: Element>(&self, section: Section) -> Result<TensorView<'a, T>, BatchError> {
        section.check::<T>()?;
        self.get(&section.name())
    }

    /// Whether the batch holds `section`.
    pub fn has(&self, section: Section) -> bool {
        self.find(&section.name()).is_ok()
    }

    fn find(&self, name: &str) -> Result<&Entry<'a>, BatchError> {
        self.sections
            .iter()
            .find(|s| s.name == name)
            .ok_or_else(|| BatchError::Missing {
                name: name.to_string(),
            })
    }
}

/// Rule 1 and the header fields: magic, version, header size, section count, flags (a
/// lost batch: nothing in it), run name and zero unused table entries. Returns the
/// section count.
fn check_header(header: &BatchHeader) -> Result<usize, BatchError> {
    if header.magic != BATCH_MAGIC {
        return Err(BatchError::BadMagic {
            found: header.magic,
        });
    }
    if header.version != BATCH_FORMAT_VERSION {
        return Err(BatchError::Version {
            found: header.version,
        });
    }
    if header.header_size as usize != BatchHeader::SIZE {
        return Err(BatchError::HeaderSize {
            found: header.header_size,
            expected: BatchHeader::SIZE as u32,
        });
    }
    let count = header.section_count as usize;
    if count > MAX_SECTIONS {
        return Err(BatchError::TooManySections { count });
    }
    match header.flags {
        0 => {}
        // A lost batch holds nothing: what it declares otherwise would be read as data.
        BATCH_LOST => {
            if header.section_count != 0 || header.sample_count != 0 || header.payload_len != 0 {
                return Err(BatchError::LostWithContent {
                    sections: header.section_count,
                    samples: header.sample_count,
                    payload_len: header.payload_len,
                });
            }
        }
        found => return Err(BatchError::Flags { found }),
    }
    let run = nul_padded_str(&header.run).ok_or_else(|| BatchError::BadRunName {
        name: String::from_utf8_lossy(&header.run).into_owned(),
        reason: "not NUL-padded ASCII",
    })?;
    validate_run_name(run)?;
    if let Some(index) = header.sections[count..]
        .iter()
        .position(|s| bytemuck::bytes_of(s).iter().any(|b| *b != 0))
    {
        return Err(BatchError::BadSection {
            name: format!("#{}", count + index),
            reason: "an unused table entry is not zero".into(),
        });
    }
    Ok(count)
}

/// Rule 2 for the name of entry `index`: NUL-padded UTF-8, non-empty, NUL-terminated and
/// not among the entries before it.
fn entry_name<'a>(
    index: usize,
    desc: &'a SectionDesc,
    before: &[Entry<'a>],
) -> Result<&'a str, BatchError> {
    let name = nul_padded_str(&desc.name).ok_or_else(|| BatchError::BadName {
        index,
        name: String::from_utf8_lossy(&desc.name).into_owned(),
        reason: "not NUL-padded UTF-8",
    })?;
    let bad_name = |reason| BatchError::BadName {
        index,
        name: name.to_string(),
        reason,
    };
    if name.is_empty() {
        return Err(bad_name("empty"));
    }
    if desc.name[desc.name.len() - 1] != 0 {
        return Err(bad_name("not NUL-terminated"));
    }
    if before.iter().any(|s| s.name == name) {
        return Err(bad_name("used twice"));
    }
    Ok(name)
}

/// Rules 2 and 3 for one entry: dtype, shape against length, offset, bounds within
/// `payload` (cut to `payload_len`) and alignment in memory.
fn entry<'a>(
    name: &'a str,
    desc: &SectionDesc,
    payload: &'a [u8],
) -> Result<Entry<'a>, BatchError> {
    let bad = |reason: String| BatchError::BadSection {
        name: name.to_string(),
        reason,
    };
    let dtype = DType::from_code(desc.dtype).ok_or_else(|| BatchError::UnknownDType {
        name: name.to_string(),
        code: desc.dtype,
    })?;
    let ndim = desc.ndim as usize;
    if !(1..=MAX_DIMS).contains(&ndim) {
        return Err(bad(format!("ndim {ndim} is not in 1..={MAX_DIMS}")));
    }
    if desc.shape[ndim..].iter().any(|d| *d != 0) {
        return Err(bad("unused shape entries are not zero".into()));
    }
    let mut dims = [0usize; MAX_DIMS];
    for (slot, d) in dims.iter_mut().zip(&desc.shape[..ndim]) {
        *slot = usize::try_from(*d).map_err(|_| bad(format!("dimension {d} too large")))?;
    }
    let expected = dims[..ndim]
        .iter()
        .try_fold(dtype.size(), |acc, d| acc.checked_mul(*d))
        .ok_or_else(|| bad(format!("shape {:?} overflows", &dims[..ndim])))?;
    if desc.len_bytes != expected as u64 {
        return Err(bad(format!(
            "{} bytes for shape {:?} of {dtype:?} ({expected} expected)",
            desc.len_bytes,
            &dims[..ndim]
        )));
    }
    if !desc.offset.is_multiple_of(SECTION_ALIGN as u64) {
        return Err(bad(format!(
            "offset {} is not a multiple of {SECTION_ALIGN}",
            desc.offset
        )));
    }
    let payload_len = payload.len();
    let start = usize::try_from(desc.offset).unwrap_or(usize::MAX);
    let end = start
        .checked_add(expected)
        .filter(|end| *end <= payload_len)
        .ok_or_else(|| {
            bad(format!(
                "bytes {}..{}+{expected} lie outside the payload of {payload_len} bytes",
                desc.offset, desc.offset
            ))
        })?;
    let bytes = &payload[start..end];
    if !(bytes.as_ptr() as usize).is_multiple_of(dtype.size()) {
        let address = bytes.as_ptr() as usize;
        return Err(BatchError::Misaligned {
            found: 1 << address.trailing_zeros().min(12),
            needed: dtype.size(),
        });
    }
    Ok(Entry {
        name,
        dtype,
        dims,
        ndim,
        bytes,
    })
}

/// Rule 3: non-empty sections do not share bytes.
fn check_overlaps(sections: &[Entry<'_>]) -> Result<(), BatchError> {
    let mut by_offset: Vec<&Entry<'_>> = sections.iter().filter(|s| !s.bytes.is_empty()).collect();
    by_offset.sort_by_key(|s| s.bytes.as_ptr() as usize);
    for pair in by_offset.windows(2) {
        let first_end = pair[0].bytes.as_ptr() as usize + pair[0].bytes.len();
        if (pair[1].bytes.as_ptr() as usize) < first_end {
            return Err(BatchError::Overlap {
                first: pair[0].name.to_string(),
                second: pair[1].name.to_string(),
            });
        }
    }
    Ok(())
}
