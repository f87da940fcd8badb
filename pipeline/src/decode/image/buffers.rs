//! Reused pixel buffers. A sample decodes nine camera images and nine class maps at full
//! size only to resize them a moment later; a fresh `vec![0; n]` for each costs a
//! `memset` of the whole image and hands the decoder cold memory. Decoders take their
//! output buffer from this thread's pool ([`take`]), and whoever is done with a decoded
//! image may give its buffer back ([`give_back`]), still warm in the cache. A buffer
//! that is never given back is simply freed.

use std::cell::RefCell;

/// Buffers kept per thread (a sample's three images per frame are decoded one after
/// another on each thread; a few more cover the class maps).
const KEPT: usize = 4;

thread_local! {
    static POOL: RefCell<Vec<Vec<u8>>> = const { RefCell::new(Vec::new()) };
}

/// A buffer of exactly `len` bytes for a decoder to overwrite entirely: the smallest
/// kept buffer at least that long (its old contents are not cleared), else a zeroed one.
pub(crate) fn take(len: usize) -> Vec<u8> {
    let kept = POOL.with(|pool| {
        let mut pool = pool.borrow_mut();
        let (at, _) = pool
            .iter()
            .enumerate()
            .filter(|(_, b)| b.len() >= len)
            .min_by_key(|(_, b)| b.len())?;
        Some(pool.swap_remove(at))
    });
    match kept {
        Some(mut buffer) => {
            buffer.truncate(len);
            buffer
        }
        None => vec![0u8; len],
    }
}

/// Keeps `buffer` (at its length) for a later [`take`] on this thread; when the pool is
/// full it replaces the shortest kept buffer if it is longer.
pub fn give_back(buffer: Vec<u8>) {
    let len = buffer.len();
    if len == 0 {
        return;
    }
    POOL.with(|pool| {
        let mut pool = pool.borrow_mut();
        if pool.len() < KEPT {
            pool.push(buffer);
        } else if let Some(shortest) = pool
            .iter_mut()
            .min_by_key(|b| b.len())
            .filter(|b| b.len() < len)
        {
            *shortest = buffer;
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buffers_come_back_with_the_asked_length() {
        let mut a = take(1000);
        assert_eq!(a.len(), 1000);
        assert!(a.iter().all(|&b| b == 0), "a fresh buffer is zeroed");
        a.fill(7);
        let address = a.as_ptr();
        give_back(a);
        let b = take(600);
        assert_eq!(b.len(), 600);
        assert_eq!(b.as_ptr(), address, "the kept buffer is reused");
        assert!(b.iter().all(|&v| v == 7), "and not cleared");
        let c = take(5000);
        assert_eq!(c.len(), 5000);
        assert_ne!(c.as_ptr(), address);
        let long = c.as_ptr();
        give_back(b);
        give_back(c);
        // The shortest adequate buffer serves a request: the long one stays for long ones.
        let e = take(500);
        assert_eq!(e.as_ptr(), address);
        for _ in 0..2 * KEPT {
            give_back(vec![1u8; 10]);
        }
        let d = take(4000);
        assert_eq!(d.len(), 4000);
        assert_eq!(
            d.as_ptr(),
            long,
            "shorter buffers do not displace a longer one"
        );
    }
}
