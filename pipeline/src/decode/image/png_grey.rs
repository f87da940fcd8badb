//! A fast path for the commonest class-map PNG: 8-bit grey, not interlaced, read as
//! `Mono8`. The `png` crate unfilters Paeth rows of one-byte pixels byte by byte (each
//! byte waits for its left neighbour): 0.3 ms for an 800×450 map, 1.2 ms at 1600×900,
//! most of a class map's decoding. Label maps are piecewise constant, and where the row
//! above is constant and the filtered bytes are zero, Paeth predicts the left neighbour
//! and every byte equals it: such spans are filled sixteen bytes at a time, and only the
//! bytes near a label boundary take the byte-by-byte rule. The other filters (None, Sub,
//! Up, Average) are unfiltered as the PNG specification says.
//!
//! The chunks are walked here (CRCs checked), the image data inflated with `fdeflate`
//! (the `png` crate's own inflater) straight into the output's row buffer. Anything this
//! path does not expect — another layout, a damaged file, a missing chunk — makes it
//! return `None`, and the caller decodes with the `png` crate, whose errors name what
//! is wrong. The result is byte for byte the `png` crate's (tested on every filter and on
//! the encoder's adaptive choice).

use super::buffers;

/// Bytes per fast-path span (one SSE register's worth).
const SPAN: usize = 16;

/// The PNG signature.
const SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];

/// An 8-bit grey, non-interlaced PNG decoded into its `width × height` bytes; `None` when
/// `data` is anything else or anything in it is unexpected (the `png` crate then
/// decodes it and reports). `max_bytes` bounds the image.
pub(super) fn decode_grey8(data: &[u8], max_bytes: u64) -> Option<Vec<u8>> {
    let rest = data.strip_prefix(&SIGNATURE)?;
    let mut chunks = Chunks { rest };
    let (kind, ihdr) = chunks.next()?;
    if kind != *b"IHDR" || ihdr.len() != 13 {
        return None;
    }
    let width = u32::from_be_bytes(ihdr[0..4].try_into().ok()?);
    let height = u32::from_be_bytes(ihdr[4..8].try_into().ok()?);
    // Bit depth 8, colour type 0 (grey), compression 0, filter method 0, no interlace.
    if ihdr[8..13] != [8, 0, 0, 0, 0] || width == 0 || height == 0 {
        return None;
    }
    let (w, h) = (width as usize, height as usize);
    let line = w.checked_add(1)?;
    let filtered_len = line.checked_mul(h)?;
    if filtered_len as u64 > max_bytes {
        return None;
    }
    let mut filtered = buffers::take(filtered_len);
    let mut inflater = fdeflate::Decompressor::new();
    let mut written = 0;
    let (mut seen_data, mut data_done, mut ended) = (false, false, false);
    while let Some((kind, body)) = chunks.next() {
        match &kind {
            b"IDAT" if data_done => return None,
            b"IDAT" => {
                seen_data = true;
                let mut input = body;
                while !input.is_empty() && !inflater.is_done() {
                    let (used, made) = inflater.read(input, &mut filtered, written, false).ok()?;
                    input = &input[used..];
                    written += made;
                    if used == 0 && made == 0 {
                        return None;
                    }
                }
            }
            b"IEND" => {
                ended = true;
                break;
            }
            // A palette, or a second header: not the simple layout this path is for.
            b"PLTE" | b"IHDR" => return None,
            // Ancillary chunks; the image data must be one run of IDAT chunks.
            _ => data_done = seen_data,
        }
    }
    if !ended || !inflater.is_done() || written != filtered_len {
        return None;
    }
    let mut out = buffers::take(w * h);
    for (r, filtered_row) in filtered.chunks_exact(line).enumerate() {
        let (filter, bytes) = filtered_row.split_first()?;
        let (done, rest) = out.split_at_mut(r * w);
        let previous = done.get(done.len().saturating_sub(w)..).unwrap_or_default();
        unfilter_row(*filter, bytes, previous, &mut rest[..w])?;
    }
    buffers::give_back(filtered);
    Some(out)
}

/// The chunks of a PNG after its signature: `(type, data)` with the CRC checked; ends
/// at the end of the data or at the first malformed chunk.
struct Chunks<'a> {
    rest: &'a [u8],
}

impl<'a> Chunks<'a> {
    fn next(&mut self) -> Option<([u8; 4], &'a [u8])> {
        let len = u32::from_be_bytes(self.rest.get(0..4)?.try_into().ok()?) as usize;
        let kind: [u8; 4] = self.rest.get(4..8)?.try_into().ok()?;
        let body = self.rest.get(8..8usize.checked_add(len)?)?;
        let crc = u32::from_be_bytes(self.rest.get(8 + len..12 + len)?.try_into().ok()?);
        let mut hasher = crc32fast::Hasher::new();
        hasher.update(&kind);
        hasher.update(body);
        if hasher.finalize() != crc {
            self.rest = &[];
            return None;
        }
        self.rest = &self.rest[12 + len..];
        Some((kind, body))
    }
}

/// Unfilters one row of one-byte pixels into `out` (`previous`: the row above,
/// unfiltered; empty for the first row). `None` for an unknown filter type.
fn unfilter_row(filter: u8, row: &[u8], previous: &[u8], out: &mut [u8]) -> Option<()> {
    let up = |i: usize| previous.get(i).copied().unwrap_or(0);
    match filter {
        0 => out.copy_from_slice(row),
        1 => {
            let mut left = 0u8;
            for (o, &f) in out.iter_mut().zip(row) {
                left = left.wrapping_add(f);
                *o = left;
            }
        }
        2 if previous.is_empty() => out.copy_from_slice(row),
        2 => {
            for ((o, &f), &b) in out.iter_mut().zip(row).zip(previous) {
                *o = f.wrapping_add(b);
            }
        }
        3 => {
            let mut left = 0u8;
            for (i, (o, &f)) in out.iter_mut().zip(row).enumerate() {
                let average = ((u16::from(left) + u16::from(up(i))) / 2) as u8;
                left = f.wrapping_add(average);
                *o = left;
            }
        }
        4 if previous.is_empty() => {
            // Without a row above Paeth predicts the left neighbour (Sub).
            return unfilter_row(1, row, previous, out);
        }
        4 => paeth_row(row, previous, out),
        _ => return None,
    }
    Some(())
}

/// Paeth's predictor (PNG specification, 9.4).
#[inline(always)]
fn paeth(a: u8, b: u8, c: u8) -> u8 {
    let (ia, ib, ic) = (i16::from(a), i16::from(b), i16::from(c));
    let p = ia + ib - ic;
    let (pa, pb, pc) = ((p - ia).abs(), (p - ib).abs(), (p - ic).abs());
    if pa <= pb && pa <= pc {
        a
    } else if pb <= pc {
        b
    } else {
        c
    }
}

/// A Paeth row of one-byte pixels with a row above (`previous.len() == row.len()`).
///
/// Where the row above is constant over a span (and its left neighbour) and the span's
/// filtered bytes are zero, every byte of the span predicts its left neighbour (`b = c`
/// makes `pa = 0`) and adds nothing: the span is the left neighbour repeated.
fn paeth_row(row: &[u8], previous: &[u8], out: &mut [u8]) {
    let n = row.len();
    // The first byte: no left or upper-left neighbour (both 0).
    out[0] = row[0].wrapping_add(paeth(0, previous[0], 0));
    // The last byte written, kept in a register: read back from `out`, each plain span
    // waited for the store of the one before it.
    let mut left = out[0];
    let mut i = 1;
    while i < n {
        if i + SPAN <= n {
            let f = &row[i..i + SPAN];
            let b = &previous[i..i + SPAN];
            let c = &previous[i - 1..i - 1 + SPAN];
            // One OR-reduction in vector lanes: zero when the span is plain.
            let busy = f
                .iter()
                .zip(b.iter().zip(c))
                .fold(0u8, |acc, (&f, (&b, &c))| acc | f | (b ^ c));
            if busy == 0 {
                out[i..i + SPAN].fill(left);
                i += SPAN;
                continue;
            }
        }
        // Byte by byte to the end of this span (or of the row).
        let end = (i + SPAN).min(n);
        while i < end {
            left = row[i].wrapping_add(paeth(left, previous[i], previous[i - 1]));
            out[i] = left;
            i += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Encodes `pixels` (8-bit grey) with `filter`, in several IDAT chunks.
    fn encode(pixels: &[u8], w: u32, h: u32, filter: png::Filter) -> Vec<u8> {
        let mut out = Vec::new();
        {
            let mut encoder = png::Encoder::new(&mut out, w, h);
            encoder.set_color(png::ColorType::Grayscale);
            encoder.set_depth(png::BitDepth::Eight);
            encoder.set_filter(filter);
            let mut writer = encoder.write_header().unwrap();
            let mut stream = writer.stream_writer_with_size(1000).unwrap();
            std::io::Write::write_all(&mut stream, pixels).unwrap();
            stream.finish().unwrap();
        }
        out
    }

    fn png_crate(data: &[u8]) -> Vec<u8> {
        let mut decoder = png::Decoder::new(std::io::Cursor::new(data));
        decoder.set_transformations(png::Transformations::IDENTITY);
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut buf).unwrap();
        buf
    }

    /// A label map: rectangles and discs of classes over a background, with a noisy
    /// band (so that every filter and every Paeth case occurs).
    fn label_map(w: usize, h: usize, seed: u32) -> Vec<u8> {
        let mut state = seed.wrapping_mul(2_654_435_761).max(1);
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            state
        };
        let mut map = vec![0u8; w * h];
        for _ in 0..12 {
            let (x0, y0) = (next() as usize % w, next() as usize % h);
            let (rw, rh) = (
                1 + next() as usize % w.div_ceil(2),
                1 + next() as usize % h.div_ceil(2),
            );
            let class = (next() % 17) as u8;
            for y in y0..(y0 + rh).min(h) {
                for x in x0..(x0 + rw).min(w) {
                    map[y * w + x] = class;
                }
            }
        }
        for y in h / 3..(h / 3 + 3).min(h) {
            for x in 0..w {
                map[y * w + x] = (next() % 256) as u8;
            }
        }
        map
    }

    #[test]
    fn equals_the_png_crate_for_every_filter() {
        use png::Filter;
        for (w, h) in [
            (1usize, 1usize),
            (15, 4),
            (16, 3),
            (17, 9),
            (200, 61),
            (448, 224),
        ] {
            for seed in 1..4 {
                let map = label_map(w, h, seed);
                for filter in [
                    Filter::NoFilter,
                    Filter::Sub,
                    Filter::Up,
                    Filter::Avg,
                    Filter::Paeth,
                    Filter::Adaptive,
                ] {
                    let data = encode(&map, w as u32, h as u32, filter);
                    let fast = decode_grey8(&data, u64::MAX).expect("fast path");
                    assert_eq!(fast.len(), w * h);
                    assert_eq!(fast, map, "{w}x{h} seed {seed} {filter:?}");
                    assert_eq!(fast, png_crate(&data));
                }
            }
        }
    }

    #[test]
    fn anything_unexpected_is_left_to_the_png_crate() {
        let map = label_map(40, 30, 7);
        let good = encode(&map, 40, 30, png::Filter::Paeth);
        assert!(decode_grey8(&good, u64::MAX).is_some());
        // Too large for the bound; cut short; a flipped bit (CRC); not a PNG.
        assert!(decode_grey8(&good, 100).is_none());
        for cut in [good.len() - 12, good.len() / 2, 40, 8] {
            assert!(
                decode_grey8(&good[..cut], u64::MAX).is_none(),
                "cut at {cut}"
            );
        }
        let mut flipped = good.clone();
        let at = flipped.len() / 2;
        flipped[at] ^= 0x10;
        assert!(decode_grey8(&flipped, u64::MAX).is_none());
        assert!(decode_grey8(b"not a png", u64::MAX).is_none());
        // RGB and 16-bit grey are other layouts.
        let mut rgb = Vec::new();
        {
            let mut encoder = png::Encoder::new(&mut rgb, 2, 2);
            encoder.set_color(png::ColorType::Rgb);
            encoder.set_depth(png::BitDepth::Eight);
            let mut writer = encoder.write_header().unwrap();
            writer.write_image_data(&[0u8; 12]).unwrap();
        }
        assert!(decode_grey8(&rgb, u64::MAX).is_none());
    }
}
