//! Seeded parameter initialization, generated on the host so that a run's initial
//! weights depend only on its seed — not on the backend, the device or thread count.
//! Resumed and uninterrupted runs start from the same weights, and the end-to-end test
//! compares their losses.

use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};

/// A SplitMix64 stream: small, fast and good enough for weight initialization.
#[derive(Debug, Clone)]
pub struct InitRng {
    state: u64,
}

impl InitRng {
    /// A stream for one named parameter of a run: the same (seed, name) always gives the
    /// same values.
    pub fn new(seed: u64, name: &str) -> Self {
        // FNV-1a of the name, mixed with the seed.
        let mut h = 0xcbf2_9ce4_8422_2325_u64;
        for b in name.bytes() {
            h ^= u64::from(b);
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
        Self {
            state: seed ^ h.rotate_left(17),
        }
    }

    fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in (0, 1).
    fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// `n` values, normal with standard deviation `std`.
    pub fn normals(&mut self, n: usize, std: f64) -> Vec<f32> {
        (0..n).map(|_| (self.normal() * std) as f32).collect()
    }
}

/// A trainable parameter of `shape` drawn from N(0, std²) by the stream (seed, name).
pub fn normal_param<const D: usize>(
    shape: [usize; D],
    std: f64,
    seed: u64,
    name: &str,
    device: &Device,
) -> Param<Tensor<D>> {
    let n = shape.iter().product();
    let values = InitRng::new(seed, name).normals(n, std);
    Param::from_tensor(Tensor::from_data(TensorData::new(values, shape), device))
}

/// A trainable parameter of `shape` filled with `value`.
pub fn constant_param<const D: usize>(
    shape: [usize; D],
    value: f32,
    device: &Device,
) -> Param<Tensor<D>> {
    Param::from_tensor(Tensor::full(shape, value, device))
}
