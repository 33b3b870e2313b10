//! `xscale cast --scene DIR [--gamma G] [--downsample S]`: load a scene, build the BVH, cast
//! γ×γ rays per pixel of every training view once, and report what the sample cache holds
//! (kept pixels per view, dropped views, footprints, memory, speed). Progress and warnings go
//! to stderr, the summary to stdout.

use crate::raycast::consistency::PhotoCheck;
use crate::raycast::{BuildPreset, CacheEvent, SampleCache, Tracer};
use crate::scene::Camera;
use crate::scene::{CameraFormat, LoadOptions, NormalizeMode, Scene};
use crate::train::sampler::Samples;
use crate::train::setup::CastViews;
use anyhow::{bail, Context, Result};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Which {
    /// Training views (the default: what training casts).
    Train,
    /// Held-out views.
    Test,
    /// Every view.
    All,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Bvh {
    Fast,
    Medium,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Normalize {
    /// Each axis of the bounding box on its own (the default, as the official code; `per-axis`
    /// is accepted too).
    #[value(name = "peraxis", alias = "per-axis")]
    PerAxis,
    /// The largest axis for all three.
    Isotropic,
}

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scene directory (COLMAP, MVSNet, transforms.json or Metashape cameras.xml layout, plus a
    /// mesh).
    #[arg(long)]
    pub scene: PathBuf,
    /// Multisampling factor γ: γ×γ rays per pixel (1..=4).
    #[arg(long, default_value_t = 2, value_parser = super::common::parse_gamma)]
    pub gamma: u32,
    /// Integer image downsample factor.
    #[arg(long, default_value_t = 1, value_parser = super::common::parse_downsample)]
    pub downsample: u32,
    /// Mesh file (default: found in the scene directory).
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// Camera format (default: auto-detect): colmap, mvsnet, transforms, metashape.
    #[arg(long)]
    pub format: Option<CameraFormat>,
    /// Normalisation of the bounding box to `[0,1]^3`.
    #[arg(long, value_enum, default_value_t = Normalize::PerAxis)]
    pub normalize: Normalize,
    /// Which views to cast.
    #[arg(long, value_enum, default_value_t = Which::Train)]
    pub views: Which,
    /// BVH build preset (obvhs); hits do not depend on it.
    #[arg(long, value_enum, default_value_t = Bvh::Medium)]
    pub bvh: Bvh,
    /// Do not load the images' pixels (cast only; targets are zero, the photo check is skipped
    /// and alpha-channel masks are not applied). Their headers are still read, so an image
    /// whose size differs from its camera's is refused as without this flag.
    #[arg(long)]
    pub no_images: bool,
}

pub fn run(args: Args) -> Result<ExitCode> {
    crate::raycast::cast::check_gamma(args.gamma)?;
    let t0 = Instant::now();
    let opts = LoadOptions {
        format: args.format,
        downsample: args.downsample,
        normalize: match args.normalize {
            Normalize::PerAxis => NormalizeMode::PerAxis,
            Normalize::Isotropic => NormalizeMode::Isotropic,
        },
        mesh: args.mesh.clone(),
        // The size check reads headers only, so --no-images keeps it: without it a camera that
        // disagrees with its photo was cast at the camera's size and reported as fine.
        ..LoadOptions::default()
    };
    let (scene, report) = Scene::load_report(&args.scene, &opts)?;
    let tracer = build_tracer(&args, &scene, &report, t0)?;
    let indices: Vec<usize> = match args.views {
        Which::Train => scene.train(),
        Which::Test => scene.test.clone(),
        Which::All => (0..scene.views.len()).collect(),
    };
    if indices.is_empty() {
        bail!("{}: no views to cast", args.scene.display());
    }
    let (cache, rays, cast_s) = cast_views(&args, &scene, &tracer, &indices)?;
    print_report(&args, &scene, &cache, &indices, rays, cast_s);
    if cache.is_empty() {
        eprintln!("error: no view sees the mesh");
        return Ok(ExitCode::from(1));
    }
    Ok(ExitCode::SUCCESS)
}

/// Report the loaded scene, build the BVH and report it.
fn build_tracer(
    args: &Args,
    scene: &Scene,
    report: &crate::scene::LoadReport,
    t0: Instant,
) -> Result<Tracer> {
    eprintln!(
        "scene {}: {} views ({} test), cameras {:?}, mesh {} ({} vertices, {} triangles, {} degenerate dropped), loaded in {:.2} s",
        args.scene.display(),
        scene.views.len(),
        scene.test.len(),
        report.format,
        report.mesh_path.display(),
        scene.mesh.vertices.len(),
        scene.mesh.triangles.len(),
        report.mesh_stats.dropped_degenerate,
        t0.elapsed().as_secs_f64()
    );
    for n in &report.notes {
        eprintln!("{n}");
    }
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    let preset = match args.bvh {
        Bvh::Fast => BuildPreset::Fast,
        Bvh::Medium => BuildPreset::Medium,
    };
    let tracer = Tracer::with_preset(&scene.mesh, &scene.normalization, preset)
        .with_context(|| format!("{}: building the BVH", report.mesh_path.display()))?;
    eprintln!(
        "BVH ({} preset): {} nodes in {:.2} s; traversal: {}",
        preset.name(),
        tracer.node_count(),
        tracer.build_time().as_secs_f64(),
        if tracer.avx() {
            "AVX, 8 rays per packet"
        } else {
            "SSE, 4 rays per packet"
        }
    );
    Ok(tracer)
}

/// Cast every view of `indices` into a sample cache (input index = position in `indices`), as
/// `train`'s setup casts them: (cache, rays cast, seconds casting).
fn cast_views(
    args: &Args,
    scene: &Scene,
    tracer: &Tracer,
    indices: &[usize],
) -> Result<(SampleCache, u64, f64)> {
    let mut samples = Samples::Cache(Box::new(SampleCache::new(args.gamma, false)?));
    // The photos against the mesh, as `train` checks them (`raycast/consistency.rs`).
    let mut photo_check = (!args.no_images).then(|| {
        let cams: Vec<&Camera> = indices.iter().map(|&i| &scene.views[i].camera).collect();
        PhotoCheck::plan(&scene.mesh, tracer, &cams)
    });
    let cast = CastViews {
        scene,
        tracer,
        views: indices,
        images: !args.no_images,
        alpha_without_images: false,
    }
    .into_samples(
        &mut samples,
        photo_check.as_mut(),
        &|| false,
        &mut |i, mask, e| match e {
            CacheEvent::ViewCast { view, kept, pixels } => {
                eprintln!(
                    "[{}/{}] view {i} '{}': {kept} of {pixels} pixels see the mesh ({:.1}%)",
                    view + 1,
                    indices.len(),
                    scene.views[i].name,
                    100.0 * kept as f64 / pixels.max(1) as f64
                )
            }
            CacheEvent::ViewDropped { .. } => {
                eprintln!(
                    "warning: view {i} '{}' {}; dropped",
                    scene.views[i].name,
                    crate::scene::mask::drop_reason(mask)
                )
            }
        },
    )?;
    let cast_s = cast.cast_seconds;
    let rays = indices
        .iter()
        .map(|&i| {
            let c = &scene.views[i].camera;
            (c.width * c.height * args.gamma * args.gamma) as u64
        })
        .sum();
    if let Some(c) = &photo_check {
        let name = |k: usize| scene.views[indices[k]].name.clone();
        for m in c.result().messages(&name) {
            eprintln!("{m}");
        }
    }
    let Samples::Cache(cache) = samples else {
        unreachable!("cast into a cache")
    };
    Ok((*cache, rays, cast_s))
}

/// What the cache holds, on stdout.
fn print_report(
    args: &Args,
    scene: &Scene,
    cache: &SampleCache,
    indices: &[usize],
    rays: u64,
    cast_s: f64,
) {
    let n_cast = indices.len();
    let g2 = cache.samples_per_pixel();
    let valid: u64 = (0..cache.len())
        .map(|i| cache.valid(i).count_ones() as u64)
        .sum();
    println!("views cast:        {n_cast}");
    println!("views kept:        {}", cache.views.len());
    if !cache.dropped.is_empty() {
        let names: Vec<&str> = cache
            .dropped
            .iter()
            .map(|&k| scene.views[indices[k]].name.as_str())
            .collect();
        println!(
            "views dropped:     {} ({})",
            cache.dropped.len(),
            names.join(", ")
        );
    }
    println!("gamma:             {} ({} rays per pixel)", args.gamma, g2);
    println!("rays cast:         {rays}");
    println!(
        "pixels kept:       {} ({} valid sub-samples of {})",
        cache.len(),
        valid,
        cache.len() * g2
    );
    println!(
        "cache memory:      {:.1} MiB ({} bytes per kept pixel)",
        cache.bytes() as f64 / (1 << 20) as f64,
        12 * g2 + 42
    );
    if let Some(f) = cache.footprint_min() {
        let e = scene.normalization.extent.max_element();
        println!(
            "finest footprint:  {f:.3e} (normalised; {:.3e} scene units) — hash levels with cells below this carry no signal",
            f as f64 * e
        );
        for v in &cache.views {
            println!(
                "  view {:>4} '{}': {} pixels, min footprint {:.3e}",
                indices[v.view], scene.views[indices[v.view]].name, v.len, v.footprint_min
            );
        }
    }
    println!(
        "cast time:         {:.2} s ({:.2} Mrays/s)",
        cast_s,
        rays as f64 / cast_s.max(1e-9) / 1e6
    );
}
