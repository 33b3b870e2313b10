//! `xscale render --run RUN | --checkpoint FILE --scene DIR --out DIR [--views test|all|LIST]
//! [--path A,B --frames N] [--format png|exr] [--gamma G] [--mask] [--footprint]`; with
//! `--method ulr`, `--scene DIR` alone is enough (as for `eval`).
//!
//! `--gamma` is the multisampling factor γ used for rendering (default: the model's, for ULR
//! without a model the `cpu` preset's); pixels whose rays all miss get the background colour.

use super::common::{select_views, Method, ModelArgs};
use crate::eval::protocol::output_name;
use crate::render::ulr::{render_ulr, training_sources, Source};
use crate::render::{fly_camera, footprint_image, look_at_point, mask_image, ModelRenderer};
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
    /// Folder for the frames (created; one file per view, or frame_NNNN for a path).
    #[arg(long)]
    pub out: PathBuf,
    /// test, train, all, or a comma-separated list of view names / indices (each once).
    #[arg(long, default_value = "test")]
    pub views: String,
    /// Render a camera path from view A to view B instead of --views (names or indices).
    #[arg(long, value_parser = super::common::parse_view_pair, conflicts_with = "views")]
    pub path: Option<String>,
    /// Frames on the path (both ends included; at least 1).
    #[arg(long, default_value_t = 30, value_parser = super::common::parse_positive)]
    pub frames: usize,
    /// What renders: the trained model, or `ulr` (the no-learning baseline: unstructured lumigraph
    /// rendering of the training photos on the mesh, the 4 best by angle and footprint; it needs no model:
    /// `--scene DIR` alone, or a run for its scene, split, mesh and γ).
    #[arg(long, value_enum, default_value = "model")]
    pub method: Method,
    /// The appearance code of a view that has none of its own (a held-out view, a new camera):
    /// `neighbours` blends the codes of the training views nearest in pose (their exposure and
    /// white balance), `mean` takes the mean of all codes (spec §4.6). Only the camera is used,
    /// never the view's photo.
    #[arg(long, value_enum, default_value = "neighbours")]
    pub appearance: crate::render::appearance::NewViewCode,
    /// Image format: 8-bit PNG, or 32-bit float EXR (the same values, not quantised).
    #[arg(long, value_enum, default_value = "png")]
    pub format: Format,
    /// Multisampling factor for rendering (default: the model's γ; ULR without a model: the
    /// `cpu` preset's).
    #[arg(long, value_parser = super::common::parse_gamma)]
    pub gamma: Option<u32>,
    /// Render at this multiple of each view's resolution (e.g. 4: a 1024×768 view as
    /// 4096×3072; the field of view is unchanged). Frames are cast and shaded in bands of rows,
    /// so large frames need no more memory than the image itself.
    #[arg(long, default_value_t = 1.0, value_parser = super::common::parse_positive_number, allow_negative_numbers = true)]
    pub scale: f64,
    /// Also write NAME_mask.png (white where the rays hit the mesh).
    #[arg(long)]
    pub mask: bool,
    /// Also write NAME_footprint.png (log pixel footprint on the surface: finest black, coarsest
    /// white; pixels whose rays all miss red).
    #[arg(long)]
    pub footprint: bool,
    /// Only errors (no line per frame, no summary).
    #[arg(long, short)]
    pub quiet: bool,
    /// Colour of pixels whose rays miss the mesh, `R,G,B` in [0, 1] or `white`/`black`
    /// (default: the scene's `background` in scene.toml, else white).
    #[arg(long, value_parser = super::common::parse_background)]
    pub background: Option<[f32; 3]>,
}

/// `base` + `suffix` (appended: a base such as `img.v2` keeps its dot).
fn suffixed(base: &Path, suffix: &str) -> PathBuf {
    let mut p = base.as_os_str().to_owned();
    p.push(suffix);
    PathBuf::from(p)
}

impl Format {
    /// The file name suffix of a frame.
    fn suffix(self) -> &'static str {
        match self {
            Format::Png => ".png",
            Format::Exr => ".exr",
        }
    }
}

/// Write `img` at `base` + `.png` / `.exr`.
fn write(base: &Path, img: &Image, format: Format) -> Result<()> {
    let p = suffixed(base, format.suffix());
    match format {
        Format::Png => write_png8(&p, img),
        Format::Exr => write_exr(&p, img),
    }
}

/// Refuse, before any frame is allocated, a `--scale` that leaves a frame empty, or one that
/// cannot fit in memory: a frame holds its colours (f32), hit mask, footprints (f32) and the
/// written copy, at most 32 bytes per pixel (an allocation failure aborts the process with no
/// word about --scale). Sizes are judged in f64 from the unscaled cameras: `Camera::scaled`
/// saturates a side at u32::MAX and a frame's bytes overflow u64 (`--scale 1e9` was reported
/// as 4294967295×4294967295 pixels, and `--scale 33554432` wrapped to 0 bytes, passed, and
/// panicked allocating).
fn check_frame_sizes(jobs: &[(PathBuf, Camera, i32)], scale: f64) -> Result<()> {
    const FRAME_BYTES_PER_PIXEL: f64 = 32.0;
    let sizes: Vec<(&PathBuf, f64, f64)> = (jobs.iter())
        .map(|(p, c, _)| {
            let (w, h) = c.scaled_size(scale);
            (p, w, h)
        })
        .collect();
    if let Some((_, w, h)) = sizes.iter().find(|(_, w, h)| *w == 0.0 || *h == 0.0) {
        bail!("--scale {scale} leaves a {w}×{h} image");
    }
    let largest = (sizes.iter()).max_by(|a, b| (a.1 * a.2).total_cmp(&(b.1 * b.2)));
    let Some(&(p, w, h)) = largest else {
        return Ok(());
    };
    crate::sysmem::check_fits(
        w * h * FRAME_BYTES_PER_PIXEL,
        &format!("--scale {scale}: {}, {w}×{h} pixels,", p.display()),
        "use a smaller --scale",
    )?;
    // Only where the system gives no memory reading can a frame that passed have a side a
    // camera cannot hold.
    if w.max(h) > u32::MAX as f64 {
        bail!(
            "--scale {scale}: {}, {w}×{h} pixels: a side of at most {} pixels is possible; use a smaller --scale",
            p.display(),
            u32::MAX
        );
    }
    Ok(())
}

pub fn run(a: Args) -> Result<ExitCode> {
    let loaded = a.model.load_for(a.method)?;
    let gamma = a.gamma.unwrap_or(loaded.gamma());
    let s = &loaded.s;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create", a.out.display()))?;
    // Frames' temp files left by a render killed mid-write (not those of one still running;
    // not below: --out may be a folder of anything).
    let dead = |pid: Option<u32>| pid.is_none_or(|p| !crate::run::run_dir::process_alive(p));
    crate::io::atomic::remove_temp_files(&a.out, false, &dead);
    let background = a.background.unwrap_or(s.scene.background);
    // (output path without extension, camera, appearance row)
    let jobs: Vec<(PathBuf, Camera, i32)> = match &a.path {
        Some(p) => {
            // Two views: `parse_view_pair` took only `A,B`.
            let ends = select_views(&s.scene, p, "--path")?;
            let (va, vb) = (&s.scene.views[ends[0]], &s.scene.views[ends[1]]);
            let ta = look_at_point(&s.tracer, &s.scene.mesh, &va.camera);
            let tb = look_at_point(&s.tracer, &s.scene.mesh, &vb.camera);
            (0..a.frames)
                .map(|i| {
                    (
                        PathBuf::from(format!("frame_{i:04}")),
                        fly_camera(&va.camera, &vb.camera, ta, tb, i, a.frames),
                        -1,
                    )
                })
                .collect()
        }
        None => select_views(&s.scene, &a.views, "--views")?
            .into_iter()
            .map(|i| {
                let v = &s.scene.views[i];
                // The view's name with its folders (`a/0000.png` → `a/0000`), so views in
                // different folders do not overwrite each other.
                (output_name(&v.name, ""), v.camera.clone(), s.rows[i])
            })
            .collect(),
    };
    check_frame_sizes(&jobs, a.scale)?;
    let jobs: Vec<(PathBuf, Camera, i32)> = jobs
        .into_iter()
        .map(|(p, c, r)| (p, c.scaled(a.scale), r))
        .collect();
    // Every file this command will write, none of which may be one it reads.
    let suffixes = [
        Some(a.format.suffix()),
        a.mask.then_some("_mask.png"),
        a.footprint.then_some("_footprint.png"),
    ];
    let mut outputs: Vec<PathBuf> = Vec::new();
    for (stem, _, _) in &jobs {
        let base = a.out.join(stem);
        outputs.extend(suffixes.iter().flatten().map(|x| suffixed(&base, x)));
    }
    super::common::refuse_overwriting_inputs(
        &outputs,
        "--out",
        &s.scene,
        loaded.checkpoint.as_deref(),
    )?;
    let sources: Vec<Source> = if a.method == Method::Ulr {
        training_sources(&s.scene)?
    } else {
        Vec::new()
    };
    let looks =
        (loaded.ck.as_ref()).map(|ck| s.new_view_codes(&ck.model, &ck.params, a.appearance));
    let t0 = std::time::Instant::now();
    for (k, (stem, cam, row)) in jobs.iter().enumerate() {
        let r = match a.method {
            Method::Model => {
                let ck = (loaded.ck.as_ref()).expect("a model is loaded for --method model");
                let renderer = ModelRenderer {
                    model: &ck.model,
                    params: &ck.params,
                    tracer: &s.tracer,
                    gamma,
                    background,
                };
                let look = (looks.as_ref())
                    .expect("with the model")
                    .appearance(*row, cam);
                renderer.render(cam, &look)?
            }
            Method::Ulr => render_ulr(&s.tracer, &sources, cam, gamma, background)?,
        };
        let base = a.out.join(stem);
        if let Some(parent) = base.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("{}: cannot create", parent.display()))?;
        }
        write(&base, &r.image, a.format)?;
        if a.mask {
            write_png8(
                &suffixed(&base, "_mask.png"),
                &mask_image(&r.hit, cam.width, cam.height),
            )?;
        }
        if a.footprint {
            write_png8(
                &suffixed(&base, "_footprint.png"),
                &footprint_image(&r.footprint, &r.hit, cam.width, cam.height),
            )?;
        }
        if a.quiet {
            continue;
        }
        eprintln!(
            "[{}/{}] {} ({}×{})",
            k + 1,
            jobs.len(),
            stem.display(),
            cam.width,
            cam.height
        );
    }
    if a.quiet {
        return Ok(ExitCode::SUCCESS);
    }
    eprintln!(
        "rendered {} images into {} in {:.1} s",
        jobs.len(),
        a.out.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}
