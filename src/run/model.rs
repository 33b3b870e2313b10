//! A run's model and the scene to use it on (`xscale eval`, `render`, and tests): the checkpoint
//! with the run configuration it was trained with, and the scene loaded for it — the model's
//! normalisation, the refined mesh when the model refines it (and the BVH anchored to the
//! training mesh when its features are), the appearance row of each view.

use crate::model::checkpoint::Checkpoint;
use crate::raycast::Tracer;
use crate::refine::mesh::refined_mesh;
use crate::scene::{LoadOptions, Scene};
use crate::train::config::RunConfig;
use anyhow::{bail, Context, Result};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A model checkpoint and, when it has one, the run configuration it was trained with.
pub fn load_model(path: &Path) -> Result<(Checkpoint, Option<RunConfig>)> {
    let (ckpt, metadata) = Checkpoint::read_model(path)?;
    Ok((ckpt, run_config(&metadata, path)?))
}

/// The run configuration stored in a checkpoint's metadata, if any.
fn run_config(metadata: &BTreeMap<String, String>, path: &Path) -> Result<Option<RunConfig>> {
    (metadata.get("run_config"))
        .map(|text| RunConfig::from_stored_toml(text, &path.display().to_string()))
        .transpose()
}

/// [`load_model`] and [`scene_for_model`] (the scene folder from `dir`, asked once the
/// checkpoint's header is read), with the scene loaded and its BVH built on a thread of their
/// own while the checkpoint's hash tables are copied (`Checkpoint::read_model_while`): the same
/// model and scene, in the time of the longer of the two rather than their sum. Returns the
/// scene folder too. A checkpoint's error is reported before the scene's.
pub fn load_model_and_scene(
    path: &Path,
    dir: impl FnOnce() -> Result<PathBuf> + Send,
    downsample: Option<u32>,
    mesh: Option<&Path>,
) -> Result<(Checkpoint, Option<RunConfig>, PathBuf, SceneForModel)> {
    let (ckpt, _, early) = Checkpoint::read_model_while(path, |head, metadata| {
        let cfg = run_config(metadata, path)?;
        let dir = dir()?;
        let opts = scene_options(cfg.as_ref(), downsample, mesh)?;
        let scene = load_warning(&dir, &opts)?;
        // A model that refines its mesh is cast against the refined one, made from its
        // parameters: that BVH is built once they are read.
        let tracer = (!head.cfg.refine.enabled)
            .then(|| Tracer::new(&scene.mesh, &head.normalization).context("building the BVH"))
            .transpose()?;
        anyhow::Ok((cfg, dir, scene, tracer))
    })?;
    let (cfg, dir, scene, tracer) = early?;
    let s = finish_scene(scene, tracer, &ckpt, cfg.as_ref())?;
    Ok((ckpt, cfg, dir, s))
}

/// A scene loaded for a model: the model's normalisation (not the scene mesh's own, so a
/// decimated or edited mesh still maps into the trained grid), its BVH, and the appearance row
/// of each view (training views in order; held-out views −1).
pub struct SceneForModel {
    pub scene: Scene,
    pub tracer: Tracer,
    pub rows: Vec<i32>,
}

impl SceneForModel {
    /// The appearances views are rendered in with `model` and `params`: a view's own row (≥ 0)
    /// or, for a view without one, the code `rule` gives (`render::appearance`), from the
    /// training cameras.
    pub fn new_view_codes<'a>(
        &'a self,
        model: &'a crate::model::hfm::Hfm,
        params: &'a [f32],
        rule: crate::render::appearance::NewViewCode,
    ) -> crate::render::appearance::NewViewCodes<'a> {
        let train: Vec<&crate::scene::Camera> = (self.scene.train().iter())
            .map(|&j| &self.scene.views[j].camera)
            .collect();
        crate::render::appearance::NewViewCodes::new(model, params, rule, train)
    }
}

/// `mesh`: a mesh file overriding the scene's (default: the run config's `train.mesh`, else the
/// scene's own). A vertex-featurization model checks that the mesh's triangles are the ones it
/// was trained on (its table is indexed by them).
pub fn scene_for_model(
    dir: &Path,
    ckpt: &Checkpoint,
    cfg: Option<&RunConfig>,
    downsample: Option<u32>,
    mesh: Option<&Path>,
) -> Result<SceneForModel> {
    let opts = scene_options(cfg, downsample, mesh)?;
    let scene = load_warning(dir, &opts)?;
    finish_scene(scene, None, ckpt, cfg)
}

/// How [`scene_for_model`] loads the scene: the run's downsampling, normalisation and mesh
/// unless given (a run's mesh that no longer exists is an error).
fn scene_options(
    cfg: Option<&RunConfig>,
    downsample: Option<u32>,
    mesh: Option<&Path>,
) -> Result<LoadOptions> {
    let opts = LoadOptions {
        downsample: downsample.or(cfg.map(|c| c.train.downsample)).unwrap_or(1),
        normalize: cfg.map(|c| c.train.normalize).unwrap_or_default(),
        mesh: mesh
            .map(Path::to_path_buf)
            .or_else(|| cfg.and_then(|c| c.train.mesh.clone())),
        ..LoadOptions::default()
    };
    if let (None, Some(m)) = (mesh, &opts.mesh) {
        if !m.exists() {
            bail!(
                "{}: the mesh this model was trained on (train.mesh of its run configuration) no longer exists; give it with --mesh FILE",
                m.display()
            );
        }
    }
    Ok(opts)
}

/// [`scene_for_model`] once the scene is loaded: the model's normalisation, the vertex model's
/// mesh checked, the refined mesh, the BVH (`tracer`, when already built on the unrefined
/// mesh with the model's normalisation, is used as it is), the appearance rows.
fn finish_scene(
    mut scene: Scene,
    tracer: Option<Tracer>,
    ckpt: &Checkpoint,
    cfg: Option<&RunConfig>,
) -> Result<SceneForModel> {
    if let Some(vt) = &ckpt.model.vertex {
        if scene.mesh.vertices.len() != vt.n_vertices || scene.mesh.triangles[..] != vt.faces[..] {
            bail!(
                "the model has vertex features for a mesh of {} vertices / {} triangles, but the scene's mesh has {} / {} (or other triangles): pass the training mesh with --mesh",
                vt.n_vertices,
                vt.faces.len(),
                scene.mesh.vertices.len(),
                scene.mesh.triangles.len()
            );
        }
    }
    scene.normalization = ckpt.normalization;
    let mut anchor = None;
    if let Some(r) = &ckpt.refine {
        // The model refined its training mesh (`[model.refine]`): render on the refined one.
        let refined = refined_mesh(&scene.mesh, &scene.normalization, &r.offsets)?;
        let base = std::mem::replace(&mut scene.mesh, refined);
        // `anchored`: the features are queried on the training mesh.
        if cfg.is_some_and(|c| c.model.refine.anchored) {
            anchor = Some(base);
        }
    }
    let mut tracer = match tracer {
        Some(t) if ckpt.refine.is_none() => t,
        _ => Tracer::new(&scene.mesh, &scene.normalization).context("building the BVH")?,
    };
    if let Some(base) = &anchor {
        tracer = tracer.anchored(base)?;
    }
    let train = scene.train();
    let mut rows = vec![-1; scene.views.len()];
    if ckpt.model.appearance_dim() > 0 {
        if train.len() != ckpt.model.appearance_views() {
            eprintln!(
                "warning: the scene has {} training views but the model has {} appearance codes; every view uses the mean code",
                train.len(),
                ckpt.model.appearance_views()
            );
        } else {
            for (r, &i) in train.iter().enumerate() {
                rows[i] = r as i32;
            }
        }
    }
    Ok(SceneForModel {
        scene,
        tracer,
        rows,
    })
}

/// [`Scene::load`], printing the loader's warnings (a mesh in other units or another frame than
/// the cameras, docs/spec.md §3.9) as `train` and `cast` do: `eval` and `render` would otherwise
/// score or draw such a scene without a word.
pub fn load_warning(dir: &Path, opts: &LoadOptions) -> Result<Scene> {
    let (scene, report) = Scene::load_report(dir, opts)?;
    for w in &report.warnings {
        eprintln!("warning: {w}");
    }
    if report.left_out > 0 {
        eprintln!(
            "note: {} views of {} have no photo on disk and are left out (skip_missing = true in its scene.toml)",
            report.left_out,
            dir.display()
        );
    }
    Ok(scene)
}

/// The scene alone, for renderers that need no model (ULR): its own normalisation, its BVH, every
/// view without an appearance row.
pub fn scene_without_model(dir: &Path, opts: &LoadOptions) -> Result<SceneForModel> {
    let scene = load_warning(dir, opts)?;
    let tracer = Tracer::new(&scene.mesh, &scene.normalization).context("building the BVH")?;
    let rows = vec![-1; scene.views.len()];
    Ok(SceneForModel {
        scene,
        tracer,
        rows,
    })
}
