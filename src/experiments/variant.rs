//! What the experiments share: the runs of their variants (the base configuration each variant
//! changes, and training one into its own run folder that a stopped experiment continues) and the
//! no-learning baseline's scores (ULR on the held-out views).

use crate::eval::protocol::{score_rendered, ViewScore};
use crate::raycast::Tracer;
use crate::render::ulr::{render_ulr, Source};
use crate::run::trainer::{train, TrainOptions, TrainSummary};
use crate::scene::Scene;
use crate::train::config::RunConfig;
use anyhow::Result;
use std::path::Path;
use std::sync::atomic::AtomicBool;

/// How an experiment trains its variants.
#[derive(Clone, Debug)]
pub struct Runs {
    /// Base configuration (preset, overrides, steps, seed) every variant is derived from.
    pub base: RunConfig,
    /// Only errors and the final table: no progress lines, no progress bar.
    pub quiet: bool,
    /// Set by a Ctrl-C / SIGTERM handler: the run in training stops at its next step with a
    /// checkpoint, and the experiment ends with what it finished; the same command continues it.
    pub interrupt: Option<&'static AtomicBool>,
}

impl Runs {
    /// Train variant `cfg` on `scene` into `dir`: with `resume`, the run this experiment stopped
    /// there continues from its checkpoint (`run_dir::stopped_run_of`); otherwise a run the folder
    /// holds is replaced. The variant's settings are recorded in the run (`RUN/variant.toml`).
    pub fn train(
        &self,
        scene: &Path,
        dir: &Path,
        cfg: &RunConfig,
        resume: bool,
    ) -> Result<TrainSummary> {
        train(
            scene,
            dir,
            cfg.clone(),
            &TrainOptions {
                quiet: true,
                resume,
                overwrite: !resume,
                interrupt: self.interrupt,
                settings: Some(cfg.results_toml()),
                bar: !self.quiet,
                ..TrainOptions::default()
            },
        )
    }
}

/// The ULR baseline's scores of `scene`'s held-out views: each rendered from the training photos
/// `sources` on the mesh `tracer` casts against, with γ×γ rays per pixel.
pub fn ulr_scores(
    scene: &Scene,
    tracer: &Tracer,
    sources: &[Source],
    gamma: u32,
) -> Result<Vec<ViewScore>> {
    let mut views = Vec::new();
    for &i in &scene.test {
        let r = render_ulr(
            tracer,
            sources,
            &scene.views[i].camera,
            gamma,
            scene.background,
        )?;
        views.push(score_rendered(scene, i, r, scene.background)?.scored.score);
    }
    Ok(views)
}
