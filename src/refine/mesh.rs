//! The refined mesh a model renders: the training mesh with a checkpoint's offsets
//! (`refine.offsets`), the BVH a refining state is evaluated with, and `RUN/refined.ply`.

use crate::raycast::Tracer;
use crate::refine::field::RefineGeom;
use crate::scene::mesh::write_ply;
use crate::scene::{Mesh, Normalization};
use crate::train::setup::Prepared;
use crate::train::state::TrainState;
use anyhow::{ensure, Result};
use std::path::Path;

/// The base mesh with the checkpoint's offsets applied (eval/render), checking the vertex count.
pub fn refined_mesh(mesh: &Mesh, norm: &Normalization, offsets: &[f32]) -> Result<Mesh> {
    ensure!(
        offsets.len() == mesh.vertices.len(),
        "the model refines a mesh of {} vertices, but the scene's mesh has {}: pass the training mesh with --mesh",
        offsets.len(),
        mesh.vertices.len()
    );
    let geom = RefineGeom::new(mesh, norm);
    let theta: Vec<f64> = offsets.iter().map(|&t| t as f64).collect();
    Ok(geom.mesh_with(&theta))
}

/// The BVH to evaluate a state with: the refined mesh's when it refines one, else `None`.
pub fn eval_tracer(state: &TrainState, prepared: &Prepared) -> Result<Option<Tracer>> {
    match &state.ckpt.refine {
        Some(p) => {
            let m = refined_mesh(&prepared.scene.mesh, &state.ckpt.normalization, &p.offsets)?;
            let t = Tracer::new(&m, &state.ckpt.normalization)?;
            if state.cfg.model.refine.anchored {
                return Ok(Some(t.anchored(&prepared.scene.mesh)?));
            }
            Ok(Some(t))
        }
        None => Ok(None),
    }
}

/// `RUN/refined.ply`: the training mesh with the offsets of `state` (written at the end of a run
/// that refines the mesh; nothing otherwise). Returns the line that tells the user where it is
/// and how far its vertices moved (scene units, and as a share of the mesh's diagonal).
pub fn write_refined(
    state: &TrainState,
    prepared: &Prepared,
    run_dir: &Path,
) -> Result<Option<String>> {
    let Some(p) = &state.ckpt.refine else {
        return Ok(None);
    };
    let base = &prepared.scene.mesh;
    let m = refined_mesh(base, &state.ckpt.normalization, &p.offsets)?;
    let path = run_dir.join("refined.ply");
    write_ply(&path, &m)?;
    let moved: Vec<f64> = base
        .vertices
        .iter()
        .zip(&m.vertices)
        .map(|(a, b)| (*a - *b).length())
        .collect();
    let n = moved.len().max(1) as f64;
    let rms = (moved.iter().map(|d| d * d).sum::<f64>() / n).sqrt();
    let max = moved.iter().copied().fold(0.0, f64::max);
    let diag = base.diagonal().max(f64::MIN_POSITIVE);
    Ok(Some(format!(
        "refined mesh written to {}: its vertices moved {rms:.3e} RMS, {max:.3e} at most ({:.3} % and {:.3} % of the mesh's diagonal)",
        path.display(),
        100.0 * rms / diag,
        100.0 * max / diag
    )))
}
