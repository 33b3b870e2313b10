//! What a run folder's `metrics.jsonl` recorded (docs/runs.md).

use std::path::Path;

/// Every line, parsed.
pub fn lines(run: &Path) -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    text.lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{l}: {e}")))
        .collect()
}

/// The steps whose checkpoints were written (`"checkpoint": true` lines), in order.
pub fn checkpoints(run: &Path) -> Vec<u64> {
    lines(run)
        .iter()
        .filter(|j| j["checkpoint"] == true)
        .map(|j| j["step"].as_u64().unwrap())
        .collect()
}

/// Whether the run's `elapsed_s` never goes back, over at least `min` lines that carry it.
pub fn elapsed_runs_on(run: &Path, min: usize) -> bool {
    let t: Vec<f64> = lines(run)
        .iter()
        .filter_map(|j| j["elapsed_s"].as_f64())
        .collect();
    t.len() >= min && t.windows(2).all(|w| w[0] <= w[1])
}
