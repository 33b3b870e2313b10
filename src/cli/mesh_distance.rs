//! `xscale mesh-distance --mesh A --truth B [--samples N]`: mean / RMS / max point-to-surface
//! distance of area samples of A to B, and of B to A (`scene/distance.rs`).

use crate::scene::distance::{surface_distance, SurfaceIndex};
use crate::scene::mesh::load_mesh;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The mesh to measure (PLY or OBJ).
    #[arg(long)]
    pub mesh: PathBuf,
    /// The reference surface (PLY or OBJ), e.g. a synthetic scene's truth.ply.
    #[arg(long)]
    pub truth: PathBuf,
    /// Area samples on each mesh.
    #[arg(long, default_value_t = crate::experiments::bench_geometry::DISTANCE_SAMPLES, value_parser = super::common::parse_positive)]
    pub samples: usize,
}

pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    let (m, _) = load_mesh(&a.mesh)?;
    let (t, _) = load_mesh(&a.truth)?;
    // Per direction: the samples (f64 points) and their distances; the area sums of the mesh.
    let faces = m.triangles.len().max(t.triangles.len()) as f64;
    let need = a.samples as f64 * 32.0 + 8.0 * faces;
    crate::sysmem::check_fits(
        need,
        &format!("--samples {}", a.samples),
        "use fewer --samples",
    )?;
    let diag = t.diagonal();
    let ratio = m.diagonal() / diag;
    if !(0.1..=10.0).contains(&ratio) {
        eprintln!(
            "warning: the mesh's bounding box is {ratio:.3e} times the size of the truth's: are the two in the same units and frame?"
        );
    }
    let to = surface_distance(&m, &SurfaceIndex::new(&t), a.samples);
    let from = surface_distance(&t, &SurfaceIndex::new(&m), a.samples);
    for (what, d) in [("mesh → truth", to), ("truth → mesh", from)] {
        println!(
            "{what}: mean {:.5}  RMS {:.5} ({:.4} % of the truth's diagonal {diag:.3})  max {:.5}  ({} sample{})",
            d.mean,
            d.rms,
            100.0 * d.rms / diag,
            d.max,
            d.samples,
            if d.samples == 1 { "" } else { "s" }
        );
    }
    Ok(ExitCode::SUCCESS)
}
