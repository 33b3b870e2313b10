//! From a scene directory to what training needs (SPEC §1, §8): load the scene, build the BVH,
//! cast every training view once into the sample cache, and drop hash levels no view resolves.

use crate::model::config::GridConfig;
use crate::model::hashgrid::tcnn_scales;
use crate::model::ModelConfig;
use crate::raycast::{CacheEvent, SampleCache, Tracer};
use crate::scene::{Image, LoadOptions, Scene};
use crate::train::config::RunConfig;
use anyhow::{bail, Context, Result};
use std::path::Path;

/// A scene prepared for training or evaluation.
pub struct Prepared {
    pub scene: Scene,
    pub tracer: Tracer,
    /// Scene indices of the training views; the position in this list is the view's
    /// appearance-code row.
    pub train_views: Vec<usize>,
    /// Samples of the training views (input index = position in `train_views`).
    pub cache: SampleCache,
}

impl Prepared {
    /// Appearance row of a scene view, or -1 (held-out / unknown view: mean code).
    pub fn appearance_row(&self, scene_view: usize) -> i32 {
        self.train_views
            .iter()
            .position(|&v| v == scene_view)
            .map_or(-1, |r| r as i32)
    }
}

/// Load `dir`, cast the training views with γ = `gamma`; with `with_images`, targets come from
/// the photos (else they are zero — enough for `init`). Messages go to `log`.
pub fn prepare(
    dir: &Path,
    cfg: &RunConfig,
    with_images: bool,
    log: &mut dyn FnMut(String),
) -> Result<Prepared> {
    let opts = LoadOptions {
        downsample: cfg.train.downsample,
        normalize: cfg.train.normalize,
        mesh: cfg.train.mesh.clone(),
        ..LoadOptions::default()
    };
    let (scene, report) = Scene::load_report(dir, &opts)?;
    let train_views = scene.train();
    log(format!(
        "scene {}: {} views ({} train, {} held out), {} format, mesh {} ({} triangles, {} degenerate dropped)",
        dir.display(),
        scene.views.len(),
        train_views.len(),
        scene.test.len(),
        report.format.name(),
        report.mesh_path.display(),
        scene.mesh.triangles.len(),
        report.mesh_stats.dropped_degenerate
    ));
    if train_views.is_empty() {
        bail!(
            "{}: no training views (all {} are held out)",
            dir.display(),
            scene.views.len()
        );
    }
    let tracer = Tracer::new(&scene.mesh, &scene.normalization).context("building the BVH")?;
    let images: Vec<Option<Image>> = if with_images {
        train_views
            .iter()
            .map(|&i| scene.load_image(i).map(Some))
            .collect::<Result<_>>()?
    } else {
        vec![None; train_views.len()]
    };
    let views: Vec<_> = train_views
        .iter()
        .zip(&images)
        .map(|(&i, img)| (&scene.views[i].camera, img.as_ref()))
        .collect();
    let t0 = std::time::Instant::now();
    let mut on_event = |e| {
        if let CacheEvent::ViewDropped { view } = e {
            log(format!(
                "warning: view {} ({}) sees no part of the mesh: dropped",
                train_views[view], scene.views[train_views[view]].name
            ));
        }
    };
    // The vertex featurization needs each sub-sample's triangle and barycentrics.
    let cache = if cfg.model.featurization.is_hash() {
        SampleCache::build(&tracer, &views, cfg.model.gamma, &mut on_event)?
    } else {
        SampleCache::build_with_triangles(&tracer, &views, cfg.model.gamma, &mut on_event)?
    };
    if cache.is_empty() {
        bail!(
            "{}: no training pixel sees the mesh (check the cameras' convention)",
            dir.display()
        );
    }
    log(format!(
        "cast {} training views with γ={} in {:.2} s: {} pixels kept, {:.1} MB",
        train_views.len(),
        cfg.model.gamma,
        t0.elapsed().as_secs_f64(),
        cache.len(),
        cache.bytes() as f64 / 1e6
    ));
    Ok(Prepared {
        scene,
        tracer,
        train_views,
        cache,
    })
}

/// Number of levels of `grid` whose cells are not finer than `footprint` (normalised units):
/// level l is kept while `1 / scale_l ≥ footprint`; at least one level is kept (SPEC §8).
pub fn levels_resolved(grid: &GridConfig, footprint: f64) -> u32 {
    let scales = tcnn_scales(grid);
    let kept = scales
        .iter()
        .take_while(|&&s| 1.0 / (s as f64) >= footprint)
        .count();
    kept.max(1) as u32
}

/// Apply SPEC §8 to a model config: drop grid-H levels finer than the finest footprint seen in
/// any training view. Returns a message saying what was dropped and why, if anything was.
pub fn drop_fine_levels(model: &mut ModelConfig, footprint_min: f64) -> Option<String> {
    let all = model.grid_h.levels;
    let kept = levels_resolved(&model.grid_h, footprint_min).min(all);
    if kept == all {
        return None;
    }
    let scales = tcnn_scales(&model.grid_h);
    model.grid_h.levels = kept;
    Some(format!(
        "grid H: keeping {kept} of {all} levels; levels {kept}..{} have cells of {:.3e}..{:.3e} (normalised), finer than the finest pixel footprint {:.3e} of any training view",
        all - 1,
        1.0 / scales[kept as usize] as f64,
        1.0 / scales[all as usize - 1] as f64,
        footprint_min
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_dropping() {
        let mut m = ModelConfig::cpu();
        // Footprint larger than every cell: only level 0 survives.
        assert_eq!(levels_resolved(&m.grid_h, 1.0), 1);
        // Tiny footprint: every level is resolved.
        assert_eq!(levels_resolved(&m.grid_h, 1e-9), 16);
        // Cells of level l are 1/scale_l; with a footprint between two levels' cells the finer is dropped.
        let scales = tcnn_scales(&m.grid_h);
        let fp = 0.5 * (1.0 / scales[9] as f64 + 1.0 / scales[10] as f64);
        assert_eq!(levels_resolved(&m.grid_h, fp), 10);
        let msg = drop_fine_levels(&mut m, fp).unwrap();
        assert_eq!(m.grid_h.levels, 10);
        assert!(msg.contains("10 of 16"), "{msg}");
        assert!(drop_fine_levels(&mut m, fp).is_none());
    }
}
