//! `xscale align-mesh --in MESH --dataparser-transforms FILE --scene DIR --out MESH`: bring a mesh
//! exported by nerfstudio (`ns-export tsdf` / `poisson`, which stand in its dataparser's
//! normalised frame) into the frame the scene's cameras are read in, then check it against the
//! scene's reconstruction points as every load does (docs/spec.md §3.9).

use super::decimate::write_mesh;
use crate::scene::load::nerfstudio_original_to_cameras;
use crate::scene::mesh::load_mesh;
use crate::scene::transforms::DataparserTransform;
use crate::scene::{LoadOptions, Scene};
use anyhow::{bail, Result};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// The mesh nerfstudio exported (PLY or OBJ).
    #[arg(long = "in")]
    pub input: PathBuf,
    /// The trained model's `dataparser_transforms.json` (beside its `config.yml`).
    #[arg(long)]
    pub dataparser_transforms: PathBuf,
    /// The scene folder nerfstudio trained on (its `transforms.json`, or COLMAP model).
    #[arg(long)]
    pub scene: PathBuf,
    /// Output mesh (.ply or .obj); e.g. `SCENE/mesh.ply`, where the scene looks for its mesh.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: Args) -> Result<ExitCode> {
    crate::io::atomic::not_an_input(&a.out, "--out", &[("the input mesh (--in)", &a.input)])?;
    let ext = a
        .out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    if !matches!(ext.as_deref(), Some("ply" | "obj")) {
        bail!("{}: the output must end in .ply or .obj", a.out.display());
    }
    let t = DataparserTransform::read(&a.dataparser_transforms)?;
    let to_cameras = nerfstudio_original_to_cameras(&a.scene)?;
    let (mut mesh, _) = load_mesh(&a.input)?;
    t.to_original(&mut mesh.vertices);
    if let Some((r, off)) = to_cameras {
        for v in &mut mesh.vertices {
            *v = r * *v + off;
        }
    }
    write_mesh(&a.out, &mesh)?;
    println!(
        "align-mesh: {} vertices moved out of nerfstudio's dataparser frame (scale {}){}; wrote {}",
        mesh.vertices.len(),
        t.scale,
        if to_cameras.is_some() {
            " and into the transforms file's own frame, where the scene's cameras are read"
        } else {
            ""
        },
        a.out.display()
    );
    // The check every load makes, on the mesh just written.
    let opts = LoadOptions {
        mesh: Some(std::fs::canonicalize(&a.out)?),
        ..LoadOptions::default()
    };
    let (_, report) = Scene::load_report(&a.scene, &opts)?;
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    match &report.frame_check {
        Some((source, ag)) if ag.agrees() => println!(
            "checked against {}: {:.0} % of its points inside the mesh's bounds lie on it, {:.0} % of the mesh has a point near it",
            source.display(),
            100.0 * ag.share(),
            100.0 * ag.cover()
        ),
        Some((_, ag)) if ag.disagrees() => {}
        Some((source, _)) => println!(
            "{}: too few points to check the mesh against",
            source.display()
        ),
        None => println!("the scene has no reconstruction points to check the mesh against"),
    }
    Ok(ExitCode::SUCCESS)
}
