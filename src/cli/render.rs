//! `xscale render --run RUN | --checkpoint FILE --scene DIR --out DIR [--views test|all|LIST]
//! [--path A,B --frames N] [--format png|exr] [--gamma G] [--mask] [--footprint]`.
//!
//! `--gamma` is the multisampling factor γ used for rendering (default: the model's); pixels
//! whose rays all miss are white.

use super::common::{select_views, ModelArgs};
use crate::render::{footprint_image, interpolate_camera, mask_image, render_camera};
use crate::scene::image::{write_exr, write_png8};
use crate::scene::{Camera, Image};
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    Png,
    Exr,
}

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub model: ModelArgs,
    #[arg(long)]
    pub out: PathBuf,
    /// test, train, all, or a comma-separated list of view names / indices.
    #[arg(long, default_value = "test")]
    pub views: String,
    /// Render a camera path from view A to view B instead (names or indices).
    #[arg(long)]
    pub path: Option<String>,
    /// Frames on the path (both ends included).
    #[arg(long, default_value_t = 30)]
    pub frames: usize,
    #[arg(long, value_enum, default_value = "png")]
    pub format: Format,
    /// Multisampling factor for rendering (default: the model's γ).
    #[arg(long)]
    pub gamma: Option<u32>,
    /// Also write NAME_mask.png (white where the rays hit the mesh).
    #[arg(long)]
    pub mask: bool,
    /// Also write NAME_footprint.png (log pixel footprint on the surface).
    #[arg(long)]
    pub footprint: bool,
}

fn write(path: &Path, img: &Image, format: Format) -> Result<()> {
    match format {
        Format::Png => write_png8(&path.with_extension("png"), img),
        Format::Exr => write_exr(&path.with_extension("exr"), img),
    }
}

pub fn run(a: Args) -> Result<ExitCode> {
    let (_, ck, s) = a.model.load()?;
    let gamma = a.gamma.unwrap_or(ck.model.cfg.gamma);
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create", a.out.display()))?;
    // (file stem, camera, appearance row)
    let jobs: Vec<(String, Camera, i32)> = match &a.path {
        Some(p) => {
            let ends = select_views(&s.scene, p)?;
            if ends.len() != 2 {
                bail!("--path takes two views A,B, got {p:?}");
            }
            let (va, vb) = (&s.scene.views[ends[0]], &s.scene.views[ends[1]]);
            (0..a.frames.max(1))
                .map(|i| {
                    (
                        format!("frame_{i:04}"),
                        interpolate_camera(&va.camera, &vb.camera, i, a.frames.max(1)),
                        -1,
                    )
                })
                .collect()
        }
        None => select_views(&s.scene, &a.views)?
            .into_iter()
            .map(|i| {
                let v = &s.scene.views[i];
                let stem = Path::new(&v.name)
                    .file_stem()
                    .map_or(v.name.clone(), |x| x.to_string_lossy().into());
                (stem, v.camera.clone(), s.rows[i])
            })
            .collect(),
    };
    let t0 = std::time::Instant::now();
    for (k, (stem, cam, row)) in jobs.iter().enumerate() {
        let r = render_camera(&ck.model, &ck.params, &s.tracer, cam, gamma, *row)?;
        write(&a.out.join(stem), &r.image, a.format)?;
        if a.mask {
            write_png8(
                &a.out.join(format!("{stem}_mask.png")),
                &mask_image(&r.hit, cam.width, cam.height),
            )?;
        }
        if a.footprint {
            write_png8(
                &a.out.join(format!("{stem}_footprint.png")),
                &footprint_image(&r.footprint, cam.width, cam.height),
            )?;
        }
        eprintln!(
            "[{}/{}] {stem} ({}×{})",
            k + 1,
            jobs.len(),
            cam.width,
            cam.height
        );
    }
    eprintln!(
        "rendered {} images into {} in {:.1} s",
        jobs.len(),
        a.out.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}
