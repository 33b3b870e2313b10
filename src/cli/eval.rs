//! `xscale eval --checkpoint FILE | --run RUN --scene DIR [--json FILE] [--out DIR]`: PSNR and
//! SSIM (SPEC §7), full image and masked, per held-out view and mean; a printed table; one
//! side-by-side PNG per view (prediction | ground truth | error heat map) when `--out` is given.

use super::common::{select_views, ModelArgs};
use crate::eval::protocol::{mean_score, score_view, table};
use crate::render::{heat_map, render_camera, side_by_side};
use crate::scene::image::write_png8;
use anyhow::{Context, Result};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    #[command(flatten)]
    pub model: ModelArgs,
    /// Views to score (default: the held-out ones).
    #[arg(long, default_value = "test")]
    pub views: String,
    /// Write per-view and mean scores as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write side-by-side images here.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(a: Args) -> Result<ExitCode> {
    let (ck_path, ck, s) = a.model.load()?;
    let views = select_views(&s.scene, &a.views)?;
    anyhow::ensure!(
        !views.is_empty(),
        "no views to evaluate (the scene has no held-out views; use --views)"
    );
    if let Some(d) = &a.out {
        std::fs::create_dir_all(d).with_context(|| format!("{}: cannot create", d.display()))?;
    }
    let mut scores = Vec::new();
    for &i in &views {
        let v = &s.scene.views[i];
        let r = render_camera(
            &ck.model,
            &ck.params,
            &s.tracer,
            &v.camera,
            ck.model.cfg.gamma,
            s.rows[i],
        )?;
        let gt = s.scene.load_image(i)?;
        let (sc, g) = score_view(&v.name, &r.image, &gt, &r.hit);
        if let Some(d) = &a.out {
            let heat = heat_map(&r.image, &g);
            write_png8(
                &d.join(Path::new(&v.name).with_extension("png")),
                &side_by_side(&[&r.image, &g, &heat]),
            )?;
        }
        scores.push(sc);
    }
    print!("{}", table(&scores));
    if let Some(j) = &a.json {
        let json = serde_json::json!({ "checkpoint": ck_path, "views": scores, "mean": mean_score(&scores) });
        std::fs::write(j, serde_json::to_string_pretty(&json)?)
            .with_context(|| format!("{}: cannot write", j.display()))?;
    }
    Ok(ExitCode::SUCCESS)
}
