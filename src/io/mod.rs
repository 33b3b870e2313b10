//! Tensor exchange (SPEC §6): safetensors checkpoints, batches and dumps, and `compare`.
