//! Flex tensors read in place by the native kernels: a custom op's inputs are usually
//! clones of tensors the solver keeps (`P f_k`, `φ_k`, a narrowed channel block), and
//! `FlexTensor::into_data` copies a shared buffer, so reading inputs that way cost a full
//! copy (and fresh, page-faulted memory) per call. A [`HostView`] borrows the values where
//! they already lie contiguously in their buffer, shared or not, and copies only strided
//! views.

use burn::backend::flex::FlexTensor;
use burn::tensor::DType;

/// A flex tensor's values as one contiguous host slice.
pub(crate) struct HostView {
    tensor: FlexTensor,
}

impl HostView {
    /// The view of `tensor` (copied once if its layout is strided).
    pub(crate) fn new(tensor: FlexTensor) -> Self {
        let tensor = if tensor.is_contiguous() {
            tensor
        } else {
            tensor.to_contiguous()
        };
        Self { tensor }
    }

    /// The views of two tensors of one shape and dtype, for the kernel `what`.
    ///
    /// # Panics
    ///
    /// If their shapes or dtypes differ.
    pub(crate) fn pair(a: FlexTensor, b: FlexTensor, what: &str) -> (Self, Self) {
        let (a, b) = (Self::new(a), Self::new(b));
        assert!(
            a.shape() == b.shape() && a.dtype() == b.dtype(),
            "{what}: {:?} {:?} against {:?} {:?}",
            a.shape(),
            a.dtype(),
            b.shape(),
            b.dtype()
        );
        (a, b)
    }

    /// The shape.
    pub(crate) fn shape(&self) -> Vec<usize> {
        self.tensor.layout().shape().to_vec()
    }

    /// The element type.
    pub(crate) fn dtype(&self) -> DType {
        self.tensor.dtype()
    }

    /// The values, row-major.
    ///
    /// # Panics
    ///
    /// If `T` is not the tensor's element type.
    pub(crate) fn values<T: bytemuck::Pod + burn::tensor::Element>(&self) -> &[T] {
        let layout = self.tensor.layout();
        let start = layout.start_offset();
        &self.tensor.storage::<T>()[start..start + layout.num_elements()]
    }
}
