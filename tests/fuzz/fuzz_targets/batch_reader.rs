//! Arbitrary bytes as a batch file (what `superflow-pipeline batch` writes: the
//! `BatchHeader` bytes, then the payload) through the validating `BatchView`.
//!
//! The payload is read from aligned storage, as a subscriber receives it from
//! iceoryx2, and again shifted by 1, 2 and 4 bytes (a misaligned slice must be an
//! error, not a bad read). Once a view validates, every section it lists must read back
//! with its own dtype at its declared shape, and with any other dtype fail cleanly.
#![no_main]

use libfuzzer_sys::fuzz_target;
use superflow_schemas::batch::{BatchHeader, BatchView, DType, Element};

fn read_as<T: Element>(view: &BatchView<'_>, name: &str, own: DType) {
    match view.get::<T>(name) {
        Ok(tensor) => {
            assert_eq!(own, T::DTYPE, "{name}: read as another dtype");
            let elements: usize = tensor.shape().iter().product();
            assert_eq!(tensor.data.len(), elements, "{name}: length against shape");
            // Touch the first and last element.
            let _ = (tensor.data.first().copied(), tensor.data.last().copied());
        }
        Err(e) => assert_ne!(
            own,
            T::DTYPE,
            "{name}: a validated section failed to read: {e}"
        ),
    }
}

fn check(header: &BatchHeader, payload: &[u8]) {
    let Ok(view) = BatchView::new(header, payload) else {
        return;
    };
    let _ = view.meta();
    let names: Vec<&str> = view.section_names().collect();
    for name in names {
        let (dtype, shape) = view.describe(name).expect("a listed section is described");
        let bytes = view.bytes(name).expect("a listed section has bytes");
        let elements: usize = shape.iter().product();
        assert_eq!(
            bytes.len(),
            elements * dtype.size(),
            "{name}: bytes against shape"
        );
        read_as::<u8>(&view, name, dtype);
        read_as::<u16>(&view, name, dtype);
        read_as::<i32>(&view, name, dtype);
        read_as::<u32>(&view, name, dtype);
        read_as::<i64>(&view, name, dtype);
        read_as::<u64>(&view, name, dtype);
        read_as::<f32>(&view, name, dtype);
        read_as::<f64>(&view, name, dtype);
    }
    assert!(view.get::<u8>("").is_err());
}

fuzz_target!(|data: &[u8]| {
    let Some(header) = BatchHeader::from_bytes(data) else {
        return;
    };
    let payload = &data[BatchHeader::SIZE..];
    // 64-byte aligned storage with room for a shift of up to 4 bytes.
    let mut storage = vec![[0u64; 8]; (payload.len() + 4).div_ceil(64)];
    let bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut storage);
    for shift in [0usize, 1, 2, 4] {
        bytes[shift..shift + payload.len()].copy_from_slice(payload);
        check(&header, &bytes[shift..shift + payload.len()]);
    }
});
