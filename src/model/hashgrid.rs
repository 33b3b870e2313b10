//! Multi-resolution hash grid with tiny-cuda-nn semantics (SPEC §4.2, the paper's Eq. 2).
//!
//! API contract (the pipeline in `hfm.rs` codes against this; the bodies are being written):
//! - points are normalised positions `x_n ∈ [0,1]^3` as `[f64; 3]`;
//! - `out` is `[M, L*F]` row-major (point-major, then level, then feature);
//! - the table is `[entries, F]` (level-major, then entry, then feature), `offsets[l]` is the
//!   first entry of level l (`offsets[L]` = total entries);
//! - backward passes *accumulate* into their outputs.

use crate::model::config::{GridConfig, PositionMode};
use crate::model::Real;

/// Geometry of a grid: per-level scales (saved with the model), resolutions, sizes, dense flags.
#[derive(Clone, Debug, PartialEq)]
pub struct HashGrid {
    pub cfg: GridConfig,
    /// `scale_l` (f32), as saved in `grid_*.scales`.
    pub scales: Vec<f32>,
    /// `res_l = ceil(scale_l) + 1`.
    pub resolutions: Vec<u32>,
    /// First entry of each level, and the total at the end (`grid_*.offsets`, L+1 values).
    pub offsets: Vec<u32>,
    /// Whether level l is indexed densely (no hashing).
    pub dense: Vec<bool>,
}

/// The set of table entries a backward pass wrote to, so Adam and gradient zeroing cost what the
/// batch touched rather than the table size (SPEC §4.8, §8).
#[derive(Clone, Debug, Default)]
pub struct Touched {
    /// Entry indices (each entry is F floats), unique, in a deterministic order.
    pub entries: Vec<u32>,
}

impl HashGrid {
    /// Scales computed as tiny-cuda-nn does (log2(b) in f32).
    pub fn new(_cfg: &GridConfig) -> HashGrid {
        todo!("hashgrid")
    }
    /// From a saved scale table (a loader never recomputes scales).
    pub fn with_scales(_cfg: &GridConfig, _scales: Vec<f32>) -> anyhow::Result<HashGrid> {
        todo!("hashgrid")
    }
    /// Output width L*F.
    pub fn out_dim(&self) -> usize {
        (self.cfg.levels * self.cfg.features) as usize
    }
    /// Total entries over all levels.
    pub fn n_entries(&self) -> usize {
        *self.offsets.last().unwrap_or(&0) as usize
    }
    /// Parameter count: entries × F.
    pub fn n_params(&self) -> usize {
        self.n_entries() * self.cfg.features as usize
    }
    /// Initial table, U(-1e-4, 1e-4) from the counter-based generator.
    pub fn init_table(&self, _seed: u64, _tensor_id: u64) -> Vec<f32> {
        todo!("hashgrid")
    }
    /// Encode M points: `out[M, L*F]` (overwritten).
    pub fn forward<R: Real>(
        &self,
        _table: &[R],
        _points: &[[f64; 3]],
        _mode: PositionMode,
        _out: &mut [R],
    ) {
        todo!("hashgrid")
    }
    /// Accumulate `d_table += ∂L/∂table` from `d_out[M, L*F]`, and record touched entries.
    pub fn backward_table<R: Real>(
        &self,
        _points: &[[f64; 3]],
        _mode: PositionMode,
        _d_out: &[R],
        _d_table: &mut [R],
        _touched: &mut Touched,
    ) {
        todo!("hashgrid")
    }
    /// Accumulate `d_points[M, 3] += ∂L/∂x_n`.
    pub fn backward_points<R: Real>(
        &self,
        _table: &[R],
        _points: &[[f64; 3]],
        _mode: PositionMode,
        _d_out: &[R],
        _d_points: &mut [R],
    ) {
        todo!("hashgrid")
    }
}
