//! `xscale decimate --in MESH --ratio R --out MESH`: quadric-error decimation to about `R` of
//! the faces (paper Table 5; `scene::mesh::decimate`, meshoptimizer). `xscale subdivide` does
//! the opposite (midpoint 1→4 subdivision). The output format follows `--out`'s extension
//! (`.ply` binary double, `.obj`).

use crate::scene::mesh::{decimate_report, load_mesh, subdivide, write_obj, write_ply};
use crate::scene::Mesh;
use anyhow::{bail, Result};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Input mesh (PLY or OBJ).
    #[arg(long = "in")]
    pub input: PathBuf,
    /// Fraction of the faces to keep, in (0, 1].
    #[arg(long, value_parser = super::common::parse_fraction, allow_negative_numbers = true)]
    pub ratio: f64,
    /// Output mesh (.ply or .obj).
    #[arg(long)]
    pub out: PathBuf,
}

/// Write `mesh` as PLY or OBJ by the extension of `path`.
pub fn write_mesh(path: &Path, mesh: &Mesh) -> Result<()> {
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .as_deref()
    {
        Some("ply") => write_ply(path, mesh),
        Some("obj") => write_obj(path, mesh),
        _ => bail!("{}: the output must end in .ply or .obj", path.display()),
    }
}

pub fn run(a: Args) -> Result<ExitCode> {
    crate::io::atomic::not_an_input(&a.out, "--out", &[("the input mesh (--in)", &a.input)])?;
    let (mesh, _) = load_mesh(&a.input)?;
    let (out, r) = decimate_report(&mesh, a.ratio)?;
    write_mesh(&a.out, &out)?;
    println!(
        "decimate: {} → {} faces (target {}), {} → {} vertices, relative error {:.2e}; wrote {}",
        r.faces_in,
        r.faces_out,
        r.faces_target,
        mesh.vertices.len(),
        r.vertices_out,
        r.relative_error,
        a.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// `xscale subdivide --in MESH --levels N --out MESH`.
#[derive(clap::Args, Debug)]
pub struct SubdivideArgs {
    /// Input mesh (PLY or OBJ).
    #[arg(long = "in")]
    pub input: PathBuf,
    /// Rounds of 1→4 midpoint subdivision (faces × 4^N; at most 6).
    #[arg(long, value_parser = super::common::parse_levels)]
    pub levels: u32,
    /// Output mesh (.ply or .obj).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run_subdivide(a: SubdivideArgs) -> Result<ExitCode> {
    crate::io::atomic::not_an_input(&a.out, "--out", &[("the input mesh (--in)", &a.input)])?;
    let (mesh, _) = load_mesh(&a.input)?;
    crate::scene::remesh::check_subdivide(
        &mesh,
        a.levels,
        &format!("subdivide --levels {}", a.levels),
        "use fewer --levels",
    )?;
    let out = subdivide(&mesh, a.levels)?;
    write_mesh(&a.out, &out)?;
    println!(
        "subdivide: {} → {} faces, {} → {} vertices; wrote {}",
        mesh.triangles.len(),
        out.triangles.len(),
        mesh.vertices.len(),
        out.vertices.len(),
        a.out.display()
    );
    Ok(ExitCode::SUCCESS)
}
