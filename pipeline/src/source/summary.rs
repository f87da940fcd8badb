//! The summary section: its framing checked before mcap's `SummaryReader` reads it, then
//! what the scan takes from it (schemas, channels, where chunks start, message counts).

use super::damage::Damage;
use super::error::SourceError;
use super::file::McapFile;
use super::framing::{FramingError, MAX_RECORD_BYTES, check_framing};
use mcap::records::op;

/// Why a file's summary section cannot be used.
#[derive(Debug, thiserror::Error)]
pub(super) enum SummaryError {
    /// The footer points outside the file.
    #[error("the footer's summary start, byte {start}, is outside the file's data")]
    StartOutside {
        /// The footer's summary start.
        start: u64,
    },
    /// The section could not be read.
    #[error(transparent)]
    Read(#[from] SourceError),
    /// The section is not a run of whole summary records.
    #[error("malformed summary section at byte {offset}: {source}")]
    Malformed {
        /// File offset of the offending record.
        offset: u64,
        /// What is wrong with it.
        source: FramingError,
    },
    /// No footer or summary, or mcap could not read it.
    #[error("the summary section is missing or unreadable")]
    Unreadable,
}

impl McapFile {
    /// The summary, read by mcap after `check_summary_framing`.
    pub(super) fn checked_summary(&self) -> Result<mcap::Summary, SummaryError> {
        self.check_summary_framing()?;
        self.read_summary().ok_or(SummaryError::Unreadable)
    }

    /// Checks the framing of the summary section (from the footer's summary start to the
    /// footer) before mcap's `SummaryReader` reads it: every record within the section and
    /// none of a kind that belongs in the data section (a chunk there made mcap overflow a
    /// subtraction: found by the fuzz target). Without a footer or summary there is nothing
    /// to check; the error names the byte offset of the offending record.
    fn check_summary_framing(&self) -> Result<(), SummaryError> {
        // Footer: opcode, length, summary start, summary offset start, CRC; then the magic.
        let footer_len = 9 + 20 + 8;
        let Some(footer_start) = self.len.checked_sub(footer_len).filter(|&f| f >= 8) else {
            return Ok(());
        };
        let Ok(footer) = self.read_exact_at(footer_start, footer_len) else {
            return Ok(());
        };
        let mut start = [0u8; 8];
        start.copy_from_slice(&footer[9..17]);
        let summary_start = u64::from_le_bytes(start);
        if footer[0] != op::FOOTER || summary_start == 0 {
            return Ok(());
        }
        if !(8..=footer_start).contains(&summary_start)
            || footer_start - summary_start > MAX_RECORD_BYTES
        {
            return Err(SummaryError::StartOutside {
                start: summary_start,
            });
        }
        let section = self.read_exact_at(summary_start, footer_start - summary_start)?;
        check_framing(&section, |opcode| {
            !matches!(
                opcode,
                op::HEADER
                    | op::FOOTER
                    | op::MESSAGE
                    | op::CHUNK
                    | op::MESSAGE_INDEX
                    | op::ATTACHMENT
                    | op::METADATA
                    | op::DATA_END
            )
        })
        .map_err(|source| SummaryError::Malformed {
            offset: summary_start + source.at() as u64,
            source,
        })
    }

    fn read_summary(&self) -> Option<mcap::Summary> {
        use mcap::sans_io::summary_reader::{
            SummaryReadEvent, SummaryReader, SummaryReaderOptions,
        };
        let mut reader = SummaryReader::new_with_options(
            SummaryReaderOptions::default()
                .with_file_size(self.len)
                .with_record_length_limit(MAX_RECORD_BYTES as usize),
        );
        let mut pos = 0u64;
        while let Some(event) = reader.next_event() {
            match event.ok()? {
                SummaryReadEvent::ReadRequest(need) => {
                    let buf = reader.insert(need);
                    let n = buf.len().min(self.len.saturating_sub(pos) as usize);
                    self.read_into(&mut buf[..n], pos).ok()?;
                    pos += n as u64;
                    reader.notify_read(n);
                }
                SummaryReadEvent::SeekRequest(to) => {
                    pos = match to {
                        std::io::SeekFrom::Start(p) => p,
                        std::io::SeekFrom::End(d) => self.len.checked_add_signed(d)?,
                        std::io::SeekFrom::Current(d) => pos.checked_add_signed(d)?,
                    };
                    reader.notify_seeked(pos);
                }
            }
        }
        reader.finish()
    }

    /// Registers the summary's schemas and channels; returns the chunk offsets of its
    /// index, sorted: where to resume after a corrupt record. Only offsets inside the
    /// file (a corrupt index pointing past its end made the scan compute `len - pos` with
    /// `pos > len`: found by the fuzz target).
    pub(super) fn take_summary(&mut self, summary: &mcap::Summary) -> Vec<u64> {
        for schema in summary.schemas.values() {
            self.add_schema(schema.id, &schema.name, &schema.encoding, &schema.data);
        }
        for channel in summary.channels.values() {
            self.add_channel(
                channel.id,
                channel.schema.as_ref().map_or(0, |s| s.id),
                &channel.topic,
                &channel.message_encoding,
                &channel.metadata,
            );
        }
        let mut indexed_chunks: Vec<u64> = summary
            .chunk_indexes
            .iter()
            .map(|c| c.chunk_start_offset)
            .filter(|offset| (8..self.len).contains(offset))
            .collect();
        indexed_chunks.sort_unstable();
        indexed_chunks
    }

    /// Notes the channels with fewer messages read than the summary's statistics state.
    pub(super) fn count_missing_messages(&mut self, summary: &mcap::Summary) {
        let Some(stats) = &summary.stats else {
            return;
        };
        for (id, expected) in &stats.channel_message_counts {
            let found = self.message_counts.get(id).copied().unwrap_or(0);
            if found < *expected {
                let topic = self
                    .channels
                    .get(id)
                    .map_or_else(|| format!("channel {id}"), |c| c.topic.clone());
                self.damage.push(Damage::MissingMessages {
                    topic,
                    expected: *expected,
                    found,
                });
            }
        }
    }
}
