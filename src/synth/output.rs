//! Writing a synthetic scene directory. Layout (one dir):
//!
//! ```text
//! mesh.ply, mesh.obj          the proxy mesh (what training gets)
//! truth.ply                   the fine true surface (only with write_truth: it is large)
//! images/NAME.png             ground truth, 8-bit sRGB-encoded values
//! sparse/0/{cameras,images,points3D}.txt   COLMAP text model
//! images_1/NAME.png + cams_1/NAME_cam.txt  MVSNet layout (same images; not for `large` or a
//!                             distorted `--lens`, which MVSNet cannot describe)
//! transforms.json             instant-ngp / nerfstudio (file_path = images/NAME.png)
//! synth.toml                  preset, seed, every parameter, per-view kind, summary
//! scene.toml                  `format = "colmap"`: which of the three layouts a plain load uses
//! ```
//! All writers are the `scene` module's; every file is a pure function of (preset, seed).

use super::{Params, Preset, Summary, Synth};
use crate::scene::{self, Image, View};
use anyhow::{Context, Result};
use std::fs;
use std::path::Path;

/// The `View` records of a synthetic scene (image paths under `dir/images/`).
pub fn views(s: &Synth, dir: &Path) -> Vec<View> {
    s.views
        .iter()
        .zip(&s.names)
        .map(|(v, name)| View {
            name: name.clone(),
            camera: v.camera.clone(),
            image_path: dir.join("images").join(name),
        })
        .collect()
}

#[derive(serde::Serialize)]
struct ViewRecord<'a> {
    name: &'a str,
    kind: super::cameras::ViewKind,
    /// Eye–target distance (m).
    distance: f64,
    target: [f64; 3],
}

#[derive(serde::Serialize)]
struct Record<'a> {
    /// Regenerate with `xscale synth --preset <preset> --seed <seed>`.
    generator: &'static str,
    preset: Preset,
    seed: u64,
    params: &'a Params,
    buildings: &'a [super::surface::Building],
    summary: &'a Summary,
    views: Vec<ViewRecord<'a>>,
}

/// Write the whole scene into `dir` (created if needed). `images` are the rendered views in
/// order (from [`Synth::render`]).
pub fn write(
    s: &Synth,
    images: &[Image],
    summary: &Summary,
    dir: &Path,
    write_truth: bool,
) -> Result<()> {
    assert_eq!(images.len(), s.views.len());
    write_with(
        s,
        &mut |i| images[i].clone(),
        summary,
        dir,
        write_truth,
        &mut |_| Ok(()),
    )
}

/// [`write()`] with each view rendered by `image(i)` just before it is written (one image in
/// memory at a time); `progress(i)` after view i is written (an error from it stops the writing
/// there and is returned). The `large` preset writes no MVSNet copy of its images.
pub fn write_with(
    s: &Synth,
    image: &mut dyn FnMut(usize) -> Image,
    summary: &Summary,
    dir: &Path,
    write_truth: bool,
    progress: &mut dyn FnMut(usize) -> Result<()>,
) -> Result<()> {
    fs::create_dir_all(dir.join("images"))
        .with_context(|| format!("{}: cannot create", dir.display()))?;
    let vs = views(s, dir);
    // The record first: a folder an interrupted synth left behind is still known as its output
    // (`xscale synth` writes into such a folder again only with the same preset and seed).
    let record = Record {
        generator: "xscale synth",
        preset: s.preset,
        seed: s.seed,
        params: &s.params,
        buildings: &s.truth.buildings,
        summary,
        views: s
            .views
            .iter()
            .zip(&s.names)
            .map(|(v, n)| ViewRecord {
                name: n,
                kind: v.kind,
                distance: v.distance,
                target: v.target.to_array(),
            })
            .collect(),
    };
    let text = toml::to_string(&record).context("synth.toml: cannot serialise")?;
    let path = dir.join("synth.toml");
    fs::write(&path, text).with_context(|| format!("{}: cannot write", path.display()))?;
    scene::mesh::write_ply(&dir.join("mesh.ply"), &s.proxy)?;
    scene::mesh::write_obj(&dir.join("mesh.obj"), &s.proxy)?;
    if write_truth {
        scene::mesh::write_ply(&dir.join("truth.ply"), &s.truth.to_mesh())?;
    }
    for (i, v) in vs.iter().enumerate() {
        scene::image::write_png8(&v.image_path, &image(i))?;
        progress(i)?;
    }
    scene::colmap::write_text(&dir.join("sparse").join("0"), &vs)?;
    // MVSNet's layout has no lens distortion: not written for `--lens` other than pinhole.
    let mvsnet = s.preset != Preset::Large && s.params.lens.is_pinhole();
    if mvsnet {
        scene::mvsnet::write(dir, &vs, 1)?;
        for v in &vs {
            let dst = dir.join("images_1").join(&v.name);
            fs::copy(&v.image_path, &dst)
                .with_context(|| format!("{}: cannot write", dst.display()))?;
        }
    }
    scene::transforms::write(&dir.join("transforms.json"), &vs, "images/")?;
    // All three layouts describe the same cameras (tests/synth.rs checks it); a plain
    // `Scene::load` needs to be told which to read.
    let path = dir.join("scene.toml");
    let text = if !mvsnet {
        "# The cameras are written in two layouts (COLMAP, transforms.json); they agree to 1e-9.\n\
         # Load the COLMAP one unless told otherwise.\n\
         format = \"colmap\"\n"
    } else {
        "# The cameras are written in three layouts (COLMAP, MVSNet, transforms.json);\n\
         # they agree to 1e-9. Load the COLMAP one unless told otherwise.\n\
         format = \"colmap\"\n"
    };
    fs::write(&path, text).with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}
