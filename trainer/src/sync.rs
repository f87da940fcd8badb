//! What data-parallel ranks exchange, independent of the transport: a module's gradients
//! flattened into one host buffer in the module's fixed visitor order, the same buffer
//! put back as gradients, and a hash of the parameters to compare replicas.
//!
//! burn 0.22 has no cross-process collective, so gradients go through host memory: every
//! rank flattens its gradients into a [`GradientBuffer`] (each gradient multiplied by the
//! rank's sample count, zeros where a parameter got none, one "had a gradient" flag per
//! parameter, then the sample count and the step's scalars), the transport sums the
//! buffers elementwise over the ranks ([`crate::ddp`] does it with one `MPI_Allreduce`),
//! and [`GradientBuffer::into_gradients`] divides by the total sample count and registers
//! the mean gradients back. With equal batches that is the plain mean of the ranks'
//! gradients (PyTorch DDP's); a short last batch weighs by its samples. A parameter no
//! rank produced a gradient for stays without one, as on a single process.
//!
//! Buffers (BatchNorm's running statistics: float state that takes no gradient) ride in
//! the same buffer unweighted and are replaced by their mean over the ranks after the
//! step ([`GradientBuffer::average_buffers`]), so the replicas hold the same whole model
//! — checkpoints included — and the statistics see every rank's data.

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::{Device, Tensor, TensorData};
use std::hash::Hasher as _;

/// The summable form of one rank's step: weighted gradients, flags, buffers, scalars.
#[derive(Debug, Clone, PartialEq)]
pub struct GradientBuffer {
    /// `[gradients (Σ trainable parameter sizes) | had-gradient flag per trainable
    /// parameter | buffers (Σ buffer sizes) | samples | ranks (1 per rank) | scalars]`.
    pub values: Vec<f32>,
    /// Elements of every trainable parameter, in visitor order.
    sizes: Vec<usize>,
    /// Elements of all buffers together.
    buffer_len: usize,
    /// Step scalars carried at the end (losses…).
    scalars: usize,
}

impl GradientBuffer {
    /// Flattens `grads` of `module` (taken out of `grads`), each multiplied by `samples`,
    /// and the module's buffers; `scalars` are appended as given (already weighted as the
    /// caller wants them summed).
    pub fn from_gradients<M: Module>(
        module: &M,
        grads: &mut GradientsParams,
        samples: usize,
        scalars: &[f32],
    ) -> Self {
        let mut flatten = Flatten {
            grads,
            weight: samples as f32,
            values: Vec::with_capacity(module.num_params() + 64),
            sizes: Vec::new(),
            had: Vec::new(),
            buffers: Vec::new(),
        };
        module.visit(&mut flatten);
        let Flatten {
            mut values,
            sizes,
            had,
            buffers,
            ..
        } = flatten;
        values.extend(had);
        let buffer_len = buffers.len();
        values.extend(buffers);
        values.push(samples as f32);
        values.push(1.0);
        values.extend_from_slice(scalars);
        Self {
            values,
            sizes,
            buffer_len,
            scalars: scalars.len(),
        }
    }

    /// Total elements of the gradients.
    fn gradient_len(&self) -> usize {
        self.sizes.iter().sum()
    }

    /// Where the buffers start.
    fn buffers_at(&self) -> usize {
        self.gradient_len() + self.sizes.len()
    }

    /// The summed sample count (after the reduction: over all ranks).
    pub fn samples(&self) -> f32 {
        self.values[self.buffers_at() + self.buffer_len]
    }

    /// Ranks that added their buffer (after the reduction: the world size).
    pub fn ranks(&self) -> f32 {
        self.values[self.buffers_at() + self.buffer_len + 1]
    }

    /// The summed scalars.
    pub fn scalars(&self) -> &[f32] {
        let start = self.values.len() - self.scalars;
        &self.values[start..]
    }

    /// Bytes of the buffer (what one all-reduce moves per rank).
    pub fn bytes(&self) -> usize {
        self.values.len() * size_of::<f32>()
    }

    /// The mean gradients (summed values ÷ summed samples) of `module`'s parameters that
    /// had a gradient on some rank, on `device` (the gradients' device: the training
    /// device without autodiff).
    pub fn into_gradients<M: Module>(&self, module: &M, device: &Device) -> GradientsParams {
        let samples = self.samples().max(1.0);
        let flags_at = self.gradient_len();
        let mut register = Register {
            values: &self.values,
            flags: &self.values[flags_at..flags_at + self.sizes.len()],
            scale: 1.0 / samples,
            offset: 0,
            index: 0,
            device,
            grads: GradientsParams::new(),
        };
        module.visit(&mut register);
        register.grads
    }

    /// `module` with every buffer replaced by its mean over the ranks (summed values ÷
    /// ranks).
    pub fn average_buffers<M: Module>(&self, module: M) -> M {
        let start = self.buffers_at();
        let mut average = AverageBuffers {
            values: &self.values[start..start + self.buffer_len],
            scale: 1.0 / self.ranks().max(1.0),
            offset: 0,
        };
        module.map(&mut average)
    }
}

/// Whether a float "parameter" is trainable (a buffer such as a running statistic takes
/// no gradient).
fn trainable<const D: usize>(param: &Param<Tensor<D>>) -> bool {
    param.val().is_require_grad()
}

/// A tensor's values as `f32`.
fn values_of<const D: usize>(tensor: Tensor<D>) -> Vec<f32> {
    tensor
        .into_data()
        .convert::<f32>()
        .try_into_vec::<f32>()
        .expect("converted to f32")
}

struct Flatten<'a> {
    grads: &'a mut GradientsParams,
    weight: f32,
    values: Vec<f32>,
    sizes: Vec<usize>,
    had: Vec<f32>,
    buffers: Vec<f32>,
}

impl ModuleVisitor for Flatten<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if !trainable(param) {
            self.buffers.extend(values_of(param.val()));
            return;
        }
        let n = param.shape().num_elements();
        self.sizes.push(n);
        match self.grads.remove::<D>(param.id) {
            Some(grad) => {
                let values = values_of(grad);
                debug_assert_eq!(values.len(), n, "a gradient has its parameter's shape");
                self.values.extend(values.iter().map(|v| v * self.weight));
                self.had.push(1.0);
            }
            None => {
                self.values.resize(self.values.len() + n, 0.0);
                self.had.push(0.0);
            }
        }
    }
}

struct Register<'a> {
    values: &'a [f32],
    flags: &'a [f32],
    scale: f32,
    offset: usize,
    index: usize,
    device: &'a Device,
    grads: GradientsParams,
}

impl ModuleVisitor for Register<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        if !trainable(param) {
            return;
        }
        let shape = param.shape();
        let n = shape.num_elements();
        let values = &self.values[self.offset..self.offset + n];
        self.offset += n;
        let had = self.flags[self.index] > 0.0;
        self.index += 1;
        if had {
            let mean: Vec<f32> = values.iter().map(|v| v * self.scale).collect();
            let grad = Tensor::<D>::from_data(TensorData::new(mean, shape), self.device);
            self.grads.register(param.id, grad);
        }
    }
}

struct AverageBuffers<'a> {
    values: &'a [f32],
    scale: f32,
    offset: usize,
}

impl ModuleMapper for AverageBuffers<'_> {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        if trainable(&param) {
            return param;
        }
        let value = param.val();
        let shape = value.shape();
        let n = shape.num_elements();
        let mean: Vec<f32> = self.values[self.offset..self.offset + n]
            .iter()
            .map(|v| v * self.scale)
            .collect();
        self.offset += n;
        let averaged = Tensor::<D>::from_data(TensorData::new(mean, shape), &value.device());
        Param::initialized(param.id, averaged)
    }
}

/// A 64-bit hash of the bytes of every float parameter and buffer, in visitor order
/// (`params_hash` of the metrics): replicas that hold the same model have the same hash.
pub fn params_hash<M: Module>(module: &M) -> u64 {
    struct Hash(rustc_hash::FxHasher);
    impl ModuleVisitor for Hash {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let data = param.val().into_data().convert::<f32>();
            self.0.write(data.as_bytes());
        }
    }
    let mut hash = Hash(rustc_hash::FxHasher::default());
    module.visit(&mut hash);
    hash.0.finish()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use burn::nn::{Linear, LinearConfig};

    #[derive(Module, Debug)]
    struct Toy {
        a: Linear,
        b: Linear,
    }

    fn toy(device: &Device) -> Toy {
        Toy {
            a: LinearConfig::new(3, 2).init(device),
            b: LinearConfig::new(2, 1).init(device),
        }
    }

    #[test]
    fn flatten_then_register_gives_the_gradients_back_divided_by_the_samples() {
        let device = Device::flex().autodiff();
        let model = toy(&device);
        let x = Tensor::<2>::from_data(
            TensorData::new(vec![1.0f32, 2., 3., 4., 5., 6.], [2, 3]),
            &device,
        );
        // `b` is not used: it gets no gradient.
        let loss = model.a.forward(x).powi_scalar(2).sum();
        let mut grads = GradientsParams::from_grads(loss.backward(), &model);
        let expected = grads
            .get::<2>(model.a.weight.id)
            .expect("a.weight has a gradient")
            .into_data()
            .try_to_vec::<f32>()
            .unwrap();
        let buffer = GradientBuffer::from_gradients(&model, &mut grads, 4, &[2.5]);
        assert_eq!(buffer.samples(), 4.0);
        assert_eq!(buffer.scalars(), &[2.5]);
        // 3·2 + 2 (a) + 2·1 + 1 (b) gradient values, 4 flags, no buffers, samples,
        // ranks, one scalar.
        assert_eq!(buffer.values.len(), 11 + 4 + 2 + 1);
        assert_eq!(buffer.ranks(), 1.0);
        let mut summed = buffer.clone();
        for (s, v) in summed.values.iter_mut().zip(&buffer.values) {
            *s += v; // two identical ranks
        }
        assert_eq!(summed.ranks(), 2.0);
        let back = summed.into_gradients(&model, &device.clone().inner());
        let got = back
            .get::<2>(model.a.weight.id)
            .unwrap()
            .into_data()
            .try_to_vec::<f32>()
            .unwrap();
        for (g, e) in got.iter().zip(&expected) {
            assert!((g - e).abs() <= 1e-6 * e.abs().max(1.0), "{g} vs {e}");
        }
        assert!(back.get::<2>(model.b.weight.id).is_none());
        assert_eq!(back.len(), 2);
    }

    #[test]
    fn the_hash_changes_with_any_parameter() {
        let device = Device::flex();
        let model = toy(&device);
        let same = model.clone();
        assert_eq!(params_hash(&model), params_hash(&same));
        let other = Toy {
            b: LinearConfig::new(2, 1).init(&device),
            ..model.clone()
        };
        assert_ne!(params_hash(&model), params_hash(&other));
    }
}
