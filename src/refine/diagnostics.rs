//! The refinement's update-by-update diagnostics (`XSCALE_REFINE_LOG`, `XSCALE_REFINE_TRUTH`;
//! docs/geometry.md): nothing a run computes depends on them.

use crate::refine::field::RefineGeom;
use crate::refine::photo_term::{PhotoStats, PhotoTerm};
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

    /// One line of per-view figures (`XSCALE_REFINE_LOG` with the photo term): each training
    /// view's footprint, deepest and current image level, weight, neighbours (appearance rows),
    /// its patches since the last update (drawn, valid, mean energy) and, given the truth, the
    /// RMS normal error of the vertices its probe rays hit; and those means over the close-up and
    /// far views (split at the geometric mean of the finest and coarsest footprints).
    pub fn views(
        &self,
        step: u64,
        geom: &RefineGeom,
        theta: &[f64],
        term: &PhotoTerm,
        stats: &[PhotoStats],
    ) -> Result<()> {
        let err = |tris: &[u32]| -> Option<f64> {
            let tv = self.truth.as_ref()?;
            let mut vs: Vec<u32> = tris
                .iter()
                .flat_map(|&t| geom.triangles[t as usize])
                .collect();
            vs.sort_unstable();
            vs.dedup();
            let e2: f64 = vs
                .iter()
                .map(|&i| {
                    let i = i as usize;
                    let v = geom.position(i, theta[i]) + geom.norm.center;
                    (v - tv[i]).dot(geom.normals[i]).powi(2)
                })
                .sum();
            Some((e2 / vs.len().max(1) as f64).sqrt())
        };
        let fps: Vec<f64> = term
            .views
            .iter()
            .filter(|v| v.active && v.footprint.is_finite())
            .map(|v| v.footprint)
            .collect();
        let lo = fps.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = fps.iter().copied().fold(0.0f64, f64::max);
        let split = (lo * hi).sqrt();
        let mut rows = Vec::new();
        // [near, far]: (views, Σ err², patches valid, drawn, Σ energy)
        let mut groups = [(0usize, 0.0f64, 0u64, 0u64, 0.0f64); 2];
        for (slot, v) in term.views.iter().enumerate() {
            if !v.active {
                continue;
            }
            let st = stats.get(slot).copied().unwrap_or_default();
            let e = err(&v.probe_triangles);
            let g = &mut groups[(v.footprint >= split) as usize];
            g.0 += 1;
            g.1 += e.unwrap_or(0.0).powi(2);
            g.2 += st.valid;
            g.3 += st.drawn;
            g.4 += st.energy;
            rows.push(
                serde_json::json!({"row": v.row, "footprint": v.footprint, "top": v.top,
                "level": term.level(slot, step.saturating_sub(1)), "weight": v.weight,
                "neighbours": v.neighbours.iter().map(|&j| term.views[j].row).collect::<Vec<_>>(),
                "drawn": st.drawn, "valid": st.valid,
                "energy_mean": st.energy / st.valid.max(1) as f64, "error_rms": e}),
            );
        }
        let group = |g: (usize, f64, u64, u64, f64)| {
            serde_json::json!({"views": g.0, "error_rms": (g.1 / g.0.max(1) as f64).sqrt(),
                "drawn": g.3, "valid": g.2, "energy_mean": g.4 / g.2.max(1) as f64})
        };
        self.line(
            serde_json::json!({"step": step, "close_up": group(groups[0]),
            "far": group(groups[1]), "views": rows}),
        )
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
