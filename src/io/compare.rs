//! Tensor-by-tensor comparison (in progress).
