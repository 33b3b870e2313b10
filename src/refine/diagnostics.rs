//! The refinement's update-by-update diagnostics (`XSCALE_REFINE_LOG`, `XSCALE_REFINE_TRUTH`;
//! docs/geometry.md): nothing a run computes depends on them.

use crate::refine::field::RefineGeom;
use crate::refine::photo_term::PhotoStats;
use anyhow::{ensure, Context, Result};
use glam::DVec3;

/// Update-by-update diagnostics (`XSCALE_REFINE_LOG`, `XSCALE_REFINE_TRUTH`): one JSON line per
/// update with the RMS / largest offset and the RMS change of this update (scene units), and, given
/// a truth mesh with the same vertices, the RMS distance along the vertex normals to it.
pub struct Diagnostics {
    log: std::path::PathBuf,
    truth: Option<Vec<DVec3>>,
    /// Vertices the photo term has used so far (its error is also logged over them).
    pub seen: Vec<bool>,
}

impl Diagnostics {
    pub fn from_env(n_vertices: usize) -> Result<Option<Diagnostics>> {
        let Some(log) = std::env::var_os("XSCALE_REFINE_LOG") else {
            return Ok(None);
        };
        let truth = match std::env::var_os("XSCALE_REFINE_TRUTH") {
            Some(p) => {
                let m = crate::scene::mesh::load_mesh(std::path::Path::new(&p))?.0;
                ensure!(
                    m.vertices.len() == n_vertices,
                    "XSCALE_REFINE_TRUTH: {} vertices, the training mesh has {n_vertices}",
                    m.vertices.len()
                );
                Some(m.vertices)
            }
            None => None,
        };
        Ok(Some(Diagnostics {
            log: log.into(),
            truth,
            seen: Vec::new(),
        }))
    }

    pub fn record(
        &self,
        step: u64,
        geom: &RefineGeom,
        theta: &[f64],
        before: &[f32],
        grad_rms: &[f64],
        photo: Option<PhotoStats>,
    ) -> Result<()> {
        let n = theta.len().max(1) as f64;
        let s = geom.scale;
        let rms = (theta.iter().map(|t| t * t).sum::<f64>() / n).sqrt() * s;
        let max = theta.iter().fold(0.0f64, |m, t| m.max(t.abs())) * s;
        let change = (theta
            .iter()
            .zip(before)
            .map(|(a, &b)| (a - b as f64).powi(2))
            .sum::<f64>()
            / n)
            .sqrt()
            * s;
        let err = self.truth.as_ref().map(|tv| {
            let (mut e2, mut s2, mut ns) = (0.0, 0.0, 0usize);
            for i in 0..theta.len() {
                let v = geom.position(i, theta[i]) + geom.norm.center;
                let e = (v - tv[i]).dot(geom.normals[i]).powi(2);
                e2 += e;
                if self.seen.get(i) == Some(&true) {
                    s2 += e;
                    ns += 1;
                }
            }
            ((e2 / n).sqrt(), (s2 / ns.max(1) as f64).sqrt(), ns)
        });
        let mut line = serde_json::json!({"step": step, "offset_rms": rms, "offset_max": max,
            "update_rms": change, "normal_error_rms": err.map(|e| e.0), "grad_rms": grad_rms});
        if let (Some(e), false) = (err, self.seen.is_empty()) {
            line["normal_error_rms_seen"] = serde_json::json!(e.1);
            line["seen"] = serde_json::json!(e.2);
        }
        if let Some(p) = photo {
            line["photo"] = serde_json::json!({"drawn": p.drawn, "valid": p.valid,
                "energy_mean": p.energy / p.valid.max(1) as f64});
        }
        self.line(line)
    }

    pub fn line(&self, line: serde_json::Value) -> Result<()> {
        use std::io::Write;
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)
            .with_context(|| format!("{}: cannot append", self.log.display()))?;
        writeln!(f, "{line}").with_context(|| format!("{}: cannot write", self.log.display()))
    }
}
