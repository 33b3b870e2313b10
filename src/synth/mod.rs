//! Cross-scale synthetic scenes whose ground truth does not come from the model (`xscale synth`).
