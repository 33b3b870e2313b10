//! `xscale eval --checkpoint FILE | --run RUN --scene DIR [--json FILE] [--out DIR]`: PSNR, SSIM
//! and ꟻLIP (SPEC §7), full image and masked, per held-out view and mean; a printed table; one
//! side-by-side PNG per view (render | photo | error heat map | ꟻLIP) when `--out` is given.

use super::common::Method;
use super::common::{select_views, ModelArgs};
use crate::eval::protocol::{
    evaluate_view, mean_score, output_name, scale_summary, scale_table, score_rendered, table,
    write_evaluated,
};
use crate::render::ulr::{render_ulr, training_sources, Source};
use crate::render::ModelRenderer;
use anyhow::{Context, Result};
use std::path::PathBuf;
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
    /// Write side-by-side images here (render | photo | error | ꟻLIP), under each view's name.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Colour of pixels whose rays miss the mesh, `R,G,B` in [0, 1] or `white`/`black`
    /// (default: the scene's `background` in scene.toml, else white).
    #[arg(long, value_parser = super::common::parse_background)]
    pub background: Option<[f32; 3]>,
    /// What renders the views: the trained model, or `ulr` (unstructured lumigraph rendering of
    /// the training photos on the mesh: a no-learning baseline: the 4 best photos by angle and footprint blended; it needs
    /// no model: `--scene DIR` alone, or a run for its scene, split and mesh).
    #[arg(long, value_enum, default_value = "model")]
    pub method: Method,
    /// The appearance code of a view that has none of its own (a held-out view, a new camera):
    /// `neighbours` blends the codes of the training views nearest in pose (their exposure and
    /// white balance), `mean` takes the mean of all codes (spec §4.6). Only the camera is used,
    /// never the view's photo.
    #[arg(long, value_enum, default_value = "neighbours")]
    pub appearance: crate::render::appearance::NewViewCode,
    /// No progress lines (one per view scored, on stderr); the table, notes and errors remain.
    #[arg(long, short)]
    pub quiet: bool,
}

pub fn run(a: Args) -> Result<ExitCode> {
    if let Some(j) = &a.json {
        crate::io::atomic::writable_folder(j)?;
    }
    // ULR needs no model: `--scene` alone is enough.
    let loaded = a.model.load_for(a.method)?;
    let ulr_gamma = loaded.gamma();
    let (ck, s) = (&loaded.ck, &loaded.s);
    let views = select_views(&s.scene, &a.views, "--views")?;
    anyhow::ensure!(
        !views.is_empty(),
        "no views to evaluate (the scene has no held-out views; use --views)"
    );
    // None of the files written may be one this command reads (a photo, a mask, the checkpoint).
    let (ck_read, refuse) = (
        loaded.checkpoint.as_deref(),
        super::common::refuse_overwriting_inputs,
    );
    if let Some(j) = &a.json {
        refuse(std::slice::from_ref(j), "--json", &s.scene, ck_read)?;
    }
    if let Some(d) = &a.out {
        let names = views.iter().map(|&i| &s.scene.views[i].name);
        let pngs: Vec<PathBuf> = names.map(|n| d.join(output_name(n, "png"))).collect();
        refuse(&pngs, "--out", &s.scene, ck_read)?;
    }
    if let Some(d) = &a.out {
        std::fs::create_dir_all(d).with_context(|| format!("{}: cannot create", d.display()))?;
    }
    let background = a.background.unwrap_or(s.scene.background);
    let sources: Vec<Source> = if a.method == Method::Ulr {
        if !a.quiet {
            eprintln!(
                "ULR baseline: blending the {} training photos (k = {})",
                s.scene.train().len(),
                crate::render::ulr::K
            );
        }
        training_sources(&s.scene)?
    } else {
        Vec::new()
    };
    let looks = (ck.as_ref()).map(|ck| s.new_view_codes(&ck.model, &ck.params, a.appearance));
    let mut scores = Vec::new();
    for (k, &i) in views.iter().enumerate() {
        let e = match a.method {
            Method::Model => {
                let ck = ck.as_ref().expect("a model is loaded for --method model");
                let renderer = ModelRenderer {
                    model: &ck.model,
                    params: &ck.params,
                    tracer: &s.tracer,
                    gamma: ck.model.cfg.gamma,
                    background,
                };
                let looks = looks.as_ref().expect("with the model");
                let look = looks.appearance(s.rows[i], &s.scene.views[i].camera);
                evaluate_view(&renderer, &s.scene, i, &look)?
            }
            Method::Ulr => {
                let camera = &s.scene.views[i].camera;
                let r = render_ulr(&s.tracer, &sources, camera, ulr_gamma, background)?;
                score_rendered(&s.scene, i, r, background)?
            }
        };
        if let Some(d) = &a.out {
            write_evaluated(&e, &s.scene.views[i].name, None, Some(d))?;
        }
        if !a.quiet {
            eprintln!(
                "scored {}/{}: {} (PSNR {:.2})",
                k + 1,
                views.len(),
                s.scene.views[i].name,
                e.scored.score.psnr
            );
        }
        scores.push(e.scored.score);
    }
    print!("{}{}", table(&scores), scale_table(&scores));
    let seen = training_views(&s.scene, &views);
    if let Some(w) = training_views_note(&seen, views.len()) {
        eprintln!("{w}");
    }
    if let Some(j) = &a.json {
        let mut json = serde_json::json!({
            "method": a.method.name(), "views": scores, "mean": mean_score(&scores),
            "by_scale": scale_summary(&scores), "training_views": seen
        });
        // The checkpoint scored; ULR uses none (a run given with it lends only its scene,
        // split, mesh and γ).
        if let (Method::Model, Some(p)) = (a.method, &loaded.checkpoint) {
            json["checkpoint"] = serde_json::json!(p);
        }
        crate::io::atomic::write_bytes(j, serde_json::to_string_pretty(&json)?)?;
    }
    Ok(ExitCode::SUCCESS)
}

/// The names of the scored `views` that are training views of `scene` (not held out).
fn training_views<'a>(scene: &'a crate::scene::Scene, views: &[usize]) -> Vec<&'a str> {
    (views.iter())
        .filter(|i| !scene.test.contains(i))
        .map(|&i| scene.views[i].name.as_str())
        .collect()
}

/// A word when training views are among the `scored` ones: the model (or ULR, which blends
/// their own photos) has seen them, so their scores measure fitting, not novel views.
fn training_views_note(seen: &[&str], scored: usize) -> Option<String> {
    if seen.is_empty() {
        return None;
    }
    let names = match seen {
        [a, b, c, _, ..] => format!("{a}, {b}, {c}, …"),
        _ => seen.join(", "),
    };
    let which = if seen.len() == scored {
        format!("all {scored} scored views are training views ({names})")
    } else {
        format!(
            "{} of the {scored} scored views are training views ({names}), and the mean mixes them with held-out ones",
            seen.len()
        )
    };
    Some(format!(
        "note: {which}: the model learned from these photos, so their scores measure how well it fits them, not novel-view synthesis (--views test scores the held-out views)"
    ))
}

#[cfg(test)]
mod tests {
    use super::training_views_note;

    #[test]
    fn training_views_are_named_with_what_they_mean() {
        assert_eq!(training_views_note(&[], 3), None);
        let some = training_views_note(&["a.png"], 2).unwrap();
        assert!(
            some.contains("1 of the 2 scored views") && some.contains("mixes"),
            "{some}"
        );
        let all = training_views_note(&["a", "b", "c", "d", "e"], 5).unwrap();
        assert!(
            all.contains("all 5 scored views") && all.contains("(a, b, c, …)"),
            "{all}"
        );
    }
}
