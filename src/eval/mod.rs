//! Evaluation: image metrics (SPEC §7) and the held-out protocol.

pub mod metrics;
pub mod plot;
pub mod protocol;
