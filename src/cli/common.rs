//! Pieces shared by several subcommands: choosing a checkpoint, loading a scene for a model.

use crate::model::checkpoint::Checkpoint;
use crate::run::model::{load_model_and_scene, scene_without_model, SceneForModel};
use crate::run::run_dir::run_checkpoint;
use crate::scene::{LoadOptions, Scene};
use crate::train::config::RunConfig;
use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};

/// A run configuration from the command line: preset, TOML overrides, and the most common
/// fields (`--steps`, `--batch`, `--seed`) on top.
#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// Preset: tiny (CI and tests), cpu (small scenes on a CPU) or paper (the official code's
    /// grid) [default: cpu].
    #[arg(long, value_parser = ["tiny", "cpu", "paper"])]
    pub preset: Option<String>,
    /// TOML file overriding any field of the preset (`[model]`, `[train]` tables).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Number of steps (overrides the config and the `cpu` preset's automatic budget, which
    /// chooses them from the scene's training pixels).
    #[arg(long)]
    pub steps: Option<u64>,
    /// Pixels per batch (overrides the config; at least 1).
    #[arg(long, value_parser = parse_positive)]
    pub batch: Option<usize>,
    /// Seed (overrides the config).
    #[arg(long)]
    pub seed: Option<u64>,
}

impl RunArgs {
    /// The preset, the file's overrides, then the flags (not yet validated).
    pub fn resolve(&self) -> Result<RunConfig> {
        let mut cfg = resolve_config(self.preset.as_deref(), self.config.as_deref())?;
        if let Some(s) = self.steps {
            cfg.train.steps = s;
            cfg.train.budget = crate::train::config::StepBudget::Fixed;
        }
        if let Some(b) = self.batch {
            cfg.train.batch_pixels = b;
        }
        if let Some(s) = self.seed {
            cfg.train.seed = s;
        }
        Ok(cfg)
    }
}

/// `--preset` (default `cpu`) with a `--config` file's overrides (`train`, `init`, `batch`). A
/// `--preset` given that the file's `preset = "..."` contradicts is an error: which one was
/// meant cannot be told.
pub fn resolve_config(preset: Option<&str>, config: Option<&Path>) -> Result<RunConfig> {
    if let (Some(p), Some(file)) = (preset, config) {
        if let Some(q) = config_file_preset(file)? {
            if q != p {
                bail!(
                    "--preset {p} conflicts with `preset = \"{q}\"` in {}: give the preset in one place",
                    file.display()
                );
            }
        }
    }
    RunConfig::resolve(preset.unwrap_or("cpu"), config)
}

/// The `preset` key of a `--config` file, if it has one.
pub fn config_file_preset(file: &Path) -> Result<Option<String>> {
    let text = crate::io::text::read(file)?;
    let v: toml::Value =
        toml::from_str(&text).with_context(|| format!("{}: not valid TOML", file.display()))?;
    Ok(v.get("preset").and_then(|p| p.as_str()).map(str::to_string))
}

/// A trained model and the scene to use it on (`--run RUN | --checkpoint FILE --scene DIR`).
#[derive(clap::Args, Debug)]
pub struct ModelArgs {
    /// Run folder (uses RUN/checkpoint.safetensors).
    #[arg(long)]
    pub run: Option<PathBuf>,
    /// A checkpoint file instead of a run folder.
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Scene directory (default with --run: the scene the run was trained on, from RUN/scene.json).
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Integer image downsample factor (default: the run's).
    #[arg(long, value_parser = parse_downsample)]
    pub downsample: Option<u32>,
    /// Mesh file instead of the scene's (default: the run's `train.mesh`, else the scene's own).
    #[arg(long)]
    pub mesh: Option<PathBuf>,
}

impl ModelArgs {
    /// The checkpoint path, the model, its run configuration (if any) and the scene for it.
    pub fn load(&self) -> Result<(PathBuf, Checkpoint, SceneForModel)> {
        let path = checkpoint_path(&self.run, &self.checkpoint)?;
        let (ck, cfg, dir, s) = load_model_and_scene(
            &path,
            || self.scene_dir(),
            self.downsample,
            self.mesh.as_deref(),
        )?;
        // Scores on other views than the run learned would read as its quality: say so. (At
        // another --downsample the cameras differ by design; a --mesh may differ on purpose.)
        let same_downsample = match (self.downsample, &cfg) {
            (Some(d), Some(c)) => d == c.train.downsample,
            (Some(_), None) => false,
            (None, _) => true,
        };
        if let (Some(run), true) = (&self.run, same_downsample) {
            if let Some(w) = scene_changed_warning(run, &dir, &s.scene)? {
                eprintln!("{w}");
            }
        }
        Ok((path, ck, s))
    }
}

/// A warning when `scene`'s cameras or train/test split are not those `run` was trained on
/// (`RUN/scene.json`; `None` too for a run without one).
pub fn scene_changed_warning(run: &Path, dir: &Path, scene: &Scene) -> Result<Option<String>> {
    let Some(then) = crate::run::run_dir::SceneFingerprint::read(run)? else {
        return Ok(None);
    };
    let now = crate::run::run_dir::SceneFingerprint::of(dir, scene);
    // The mesh is left out: `--mesh` may differ on purpose.
    let mut what = then.changed(&now);
    what.retain(|w| *w != "mesh");
    let what = what.join(" and ");
    let (dir_now, run) = (now.scene.display(), run.display());
    Ok((!what.is_empty()).then(|| {
        let how = if now.scene == then.scene {
            format!("its {what} changed since the run {run} was trained on it")
        } else {
            format!(
                "its {what} differ from those of {}, which the run {run} was trained on",
                then.scene.display()
            )
        };
        format!("warning: the scene {dir_now}: {how}: its views are not the ones the model learned or was held out from")
    }))
}

/// What renders the views of `eval` and `render`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Method {
    Model,
    Ulr,
}

impl Method {
    /// The name on the command line (and in `eval --json`'s `method`).
    pub fn name(self) -> &'static str {
        match self {
            Method::Model => "model",
            Method::Ulr => "ulr",
        }
    }
}

/// What `eval` and `render` work with: the model (its checkpoint path and checkpoint; `None` for
/// ULR given only `--scene`) and the scene.
pub struct Loaded {
    pub checkpoint: Option<PathBuf>,
    pub ck: Option<Checkpoint>,
    pub s: SceneForModel,
}

impl Loaded {
    /// The multisampling factor the views are cast with: the model's γ, else (ULR without a
    /// model) the `cpu` preset's, as ULR casts its pixels as the model does.
    pub fn gamma(&self) -> u32 {
        self.ck
            .as_ref()
            .map_or(crate::model::ModelConfig::cpu().gamma, |c| {
                c.model.cfg.gamma
            })
    }
}

impl ModelArgs {
    /// Whether a model was given (`--run` or `--checkpoint`).
    pub fn has_model(&self) -> bool {
        self.run.is_some() || self.checkpoint.is_some()
    }

    /// The model and scene `method` needs: ULR needs no model, so `--scene DIR` alone is enough
    /// (a run still gives its scene, split, mesh and γ); the model needs `--run` or `--checkpoint`.
    pub fn load_for(&self, method: Method) -> Result<Loaded> {
        if method == Method::Ulr && !self.has_model() {
            return Ok(Loaded {
                checkpoint: None,
                ck: None,
                s: self.scene_only()?,
            });
        }
        let (p, ck, s) = self.load()?;
        Ok(Loaded {
            checkpoint: Some(p),
            ck: Some(ck),
            s,
        })
    }

    /// The scene alone, for renderers that need no model (ULR): `--scene` with its own
    /// normalisation, `--downsample`, `--mesh`; every view without an appearance row.
    pub fn scene_only(&self) -> Result<SceneForModel> {
        let dir = self.scene_dir()?;
        let opts = LoadOptions {
            downsample: self.downsample.unwrap_or(1),
            mesh: self.mesh.clone(),
            ..LoadOptions::default()
        };
        scene_without_model(&dir, &opts)
    }

    /// `--scene`, else the scene recorded in `RUN/scene.json` by `xscale train`.
    pub fn scene_dir(&self) -> Result<PathBuf> {
        if let Some(s) = &self.scene {
            return Ok(s.clone());
        }
        let Some(run) = &self.run else {
            bail!(
                "give --scene DIR (a --checkpoint file does not say which scene it was trained on)"
            );
        };
        match crate::run::run_dir::SceneFingerprint::read(run)? {
            Some(f) if f.scene.is_dir() => Ok(f.scene),
            Some(f) => bail!(
                "{}: the run's scene {} no longer exists; give --scene DIR",
                run.display(),
                f.scene.display()
            ),
            None => bail!(
                "{}: the run does not record its scene (made by an older xscale); give --scene DIR",
                run.display()
            ),
        }
    }
}

/// `--run RUN` or `--checkpoint FILE` (exactly one).
pub fn checkpoint_path(run: &Option<PathBuf>, checkpoint: &Option<PathBuf>) -> Result<PathBuf> {
    match (run, checkpoint) {
        (Some(r), None) => Ok(run_checkpoint(r)),
        (None, Some(c)) => Ok(c.clone()),
        (Some(_), Some(_)) => bail!("give either --run or --checkpoint, not both"),
        (None, None) => bail!("give --run RUN or --checkpoint FILE"),
    }
}

/// A `--mesh` path made absolute: as given if it exists, else relative to the scene dir (as
/// `LoadOptions::mesh` resolves it), so a run config keeps pointing at the same file.
pub fn absolute_mesh_path(mesh: &Path, scene: &Path) -> PathBuf {
    let p = if mesh.exists() || mesh.is_absolute() {
        mesh.to_path_buf()
    } else {
        scene.join(mesh)
    };
    std::fs::canonicalize(&p).unwrap_or(p)
}

/// An error when one of `outputs` (written under `flag`) is a file the command reads: a view's
/// photo or mask file, or the checkpoint (`render --views all --out SCENE/images` used to replace
/// the photos by renders). Checked before the work, so nothing is written.
pub fn refuse_overwriting_inputs(
    outputs: &[PathBuf],
    flag: &str,
    scene: &Scene,
    checkpoint: Option<&Path>,
) -> Result<()> {
    // Only an output that exists can be an input: most are new, and cost one failed stat.
    let existing: Vec<&PathBuf> = outputs.iter().filter(|o| o.exists()).collect();
    if existing.is_empty() {
        return Ok(());
    }
    let mut inputs: Vec<(&Path, String)> = Vec::new();
    for (v, m) in scene.views.iter().zip(&scene.masks) {
        inputs.push((&v.image_path, format!("the photo of view {}", v.name)));
        if let crate::scene::mask::MaskSource::File(f) = m {
            inputs.push((f, format!("the mask of view {}", v.name)));
        }
    }
    if let Some(c) = checkpoint {
        inputs.push((c, "the checkpoint".to_string()));
    }
    let inputs: Vec<(&str, &Path)> = inputs.iter().map(|(p, w)| (w.as_str(), *p)).collect();
    for out in existing {
        crate::io::atomic::not_an_input(out, flag, &inputs)?;
    }
    Ok(())
}

/// Views named by `test`, `all`, `train`, or a comma-separated list of names or indices; `flag`
/// (`--views`, `--path`) names the option in errors. A view named twice (`0,0`, or `0` and
/// `0000.png`) is an error: it would be rendered twice and counted twice in a mean.
pub fn select_views(scene: &Scene, spec: &str, flag: &str) -> Result<Vec<usize>> {
    match spec {
        "test" => Ok(scene.test.clone()),
        "train" => Ok(scene.train()),
        "all" => Ok((0..scene.views.len()).collect()),
        list => {
            let mut out: Vec<(usize, &str)> = Vec::new();
            for s in list.split(',').map(str::trim) {
                let i = select_view(scene, s, flag)?;
                if let Some((_, first)) = out.iter().find(|(j, _)| *j == i) {
                    bail!(
                        "{flag}: view {} is named twice ({first:?} and {s:?}): give each view once",
                        scene.views[i].name
                    );
                }
                out.push((i, s));
            }
            Ok(out.into_iter().map(|(i, _)| i).collect())
        }
    }
}

/// The view `s` names: its whole name, its file stem (when one view has it) or its index.
fn select_view(scene: &Scene, s: &str, flag: &str) -> Result<usize> {
    if let Some(i) = scene.views.iter().position(|v| v.name == s) {
        return Ok(i);
    }
    // By file stem: `0001` for `0001.png`, or for `cam1/0001.jpg` — which must then be the only
    // view with that stem.
    let by_stem: Vec<usize> = (0..scene.views.len())
        .filter(|&i| {
            Path::new(&scene.views[i].name)
                .file_stem()
                .is_some_and(|x| x == s)
        })
        .collect();
    match by_stem[..] {
        [i] => return Ok(i),
        [_, _, ..] => bail!(
            "{flag}: {s:?} names {} views ({}): give the whole name",
            by_stem.len(),
            by_stem
                .iter()
                .map(|&i| scene.views[i].name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ),
        [] => {}
    }
    match s.parse::<usize>() {
        Ok(i) if i < scene.views.len() => Ok(i),
        _ => bail!(
            "{flag}: no view named or numbered {s:?} (the scene has {} views)",
            scene.views.len()
        ),
    }
}

/// A count that must be at least 1 (`--batch`, `--frames`, `--samples`): 0 is a usage error (exit 64).
pub fn parse_positive(s: &str) -> std::result::Result<usize, String> {
    parse_whole_in(s, 1, usize::MAX as u64, "").map(|n| n as usize)
}

/// An integer downsample factor (`--downsample`): at least 1.
pub fn parse_downsample(s: &str) -> std::result::Result<u32, String> {
    parse_whole_in(s, 1, u32::MAX.into(), "").map(|n| n as u32)
}

/// A multisampling factor γ (`--gamma`: γ×γ rays per pixel), 1 to 4 as `model.gamma`.
pub fn parse_gamma(s: &str) -> std::result::Result<u32, String> {
    let max = crate::raycast::cast::MAX_GAMMA.into();
    parse_whole_in(s, 1, max, " (γ×γ rays per pixel)").map(|n| n as u32)
}

/// Rounds of 1→4 subdivision (`subdivide --levels`, `ablate --subdivide`): at most 6.
pub fn parse_levels(s: &str) -> std::result::Result<u32, String> {
    parse_whole_in(s, 0, 6, " (× 4^levels faces: 6 is × 4096)").map(|n| n as u32)
}

/// A whole number in `lo..=hi` (`why` follows a range with an upper end in the error).
fn parse_whole_in(s: &str, lo: u64, hi: u64, why: &str) -> std::result::Result<u64, String> {
    let bounded = hi < u32::MAX.into();
    match s.trim().parse::<u64>() {
        Ok(n) if (lo..=hi).contains(&n) => Ok(n),
        Ok(_) if bounded => Err(format!("must be {lo} to {hi}{why}")),
        Ok(n) if n < lo => Err(format!("must be at least {lo}")),
        Ok(_) => Err(format!("must be at most {hi}")),
        Err(e) if bounded => Err(format!("expected a whole number from {lo} to {hi} ({e})")),
        Err(e) => Err(format!("expected a whole number ≥ {lo} ({e})")),
    }
}

/// A positive finite number (`--minutes`, `render --scale`).
pub fn parse_positive_number(s: &str) -> std::result::Result<f64, String> {
    parse_number(s, |x| x > 0.0 && x.is_finite(), "a positive number")
}

/// A number ≥ 0 (`bench-geometry --rms`).
pub fn parse_non_negative(s: &str) -> std::result::Result<f64, String> {
    parse_number(s, |x| x >= 0.0 && x.is_finite(), "a number ≥ 0")
}

/// A fraction of faces to keep, in (0, 1] (`decimate --ratio`, `ablate --ratio`).
pub fn parse_fraction(s: &str) -> std::result::Result<f64, String> {
    parse_number(s, |x| x > 0.0 && x <= 1.0, "a fraction in (0, 1]")
}

/// [`parse_fraction`] or 0 for none (`bench-geometry --decimate`).
pub fn parse_fraction_or_zero(s: &str) -> std::result::Result<f64, String> {
    parse_number(s, |x| (0.0..=1.0).contains(&x), "in [0, 1] (0: none)")
}

/// A number for which `ok` holds (NaN never does), else an error saying it must be `need`.
fn parse_number(s: &str, ok: fn(f64) -> bool, need: &str) -> std::result::Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(x) if ok(x) => Ok(x),
        Ok(_) => Err(format!("must be {need}")),
        Err(e) => Err(format!("expected {need} ({e})")),
    }
}

/// `--path A,B`: two views (names or indices; whether the scene has them is checked once it is
/// loaded).
pub fn parse_view_pair(s: &str) -> std::result::Result<String, String> {
    match s.split(',').map(str::trim).collect::<Vec<_>>()[..] {
        [a, b] if !a.is_empty() && !b.is_empty() => Ok(s.to_string()),
        _ => Err("expected two views A,B (names or indices)".into()),
    }
}

/// `--background`: `R,G,B` with values in [0, 1], or `white` / `black`.
pub fn parse_background(s: &str) -> std::result::Result<[f32; 3], String> {
    match s.trim().to_ascii_lowercase().as_str() {
        "white" => return Ok([1.0; 3]),
        "black" => return Ok([0.0; 3]),
        _ => {}
    }
    let v: Vec<f32> = s
        .split(',')
        .map(|x| x.trim().parse::<f32>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| format!("{s:?}: expected R,G,B (e.g. 1,1,1), white or black: {e}"))?;
    match v[..] {
        [r, g, b] if v.iter().all(|c| (0.0..=1.0).contains(c)) => Ok([r, g, b]),
        _ => Err(format!(
            "{s:?}: expected three values in [0, 1] (R,G,B), white or black"
        )),
    }
}

/// Set by the first Ctrl-C, SIGTERM or SIGHUP (`ctrlc`'s `termination` feature) once
/// [`on_interrupt`] installed the handler.
static INTERRUPTED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Exit status of a command stopped by a signal that saved its work (a run's checkpoint).
pub const EXIT_STOPPED: u8 = 130;

/// Exit status of a command stopped by a signal with nothing saved: before training began, or
/// aborted by a second signal (docs/runs.md, "Exit codes").
pub const EXIT_STOPPED_UNSAVED: u8 = 3;

/// Signals this close after the first are copies of it, not a second one: `timeout` sends its
/// signal to the process and then to its process group, a terminal's Ctrl-C reaches every
/// process of the job, a batch scheduler may repeat it.
const COPY_WINDOW: std::time::Duration = std::time::Duration::from_secs(1);

/// Install the process's interrupt handler and return its flag: the first signal sets it and
/// says `interrupt: WHAT`; copies of it within [`COPY_WINDOW`] are ignored; a later one aborts
/// at once: the run locks this process holds are removed, and it exits with
/// [`EXIT_STOPPED_UNSAVED`] saying nothing more was saved.
pub fn on_interrupt(what: &'static str) -> &'static std::sync::atomic::AtomicBool {
    use std::sync::atomic::Ordering;
    static FIRST: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
    let _ = ctrlc::set_handler(move || {
        let first = *FIRST.get_or_init(std::time::Instant::now);
        if INTERRUPTED.swap(true, Ordering::SeqCst) {
            if first.elapsed() < COPY_WINDOW {
                return;
            }
            crate::run::run_dir::release_locks();
            eprintln!(
                "\naborted: nothing more was saved (a run folder keeps its last checkpoint, if it has one: --resume continues from it)"
            );
            std::process::exit(EXIT_STOPPED_UNSAVED.into());
        }
        eprintln!("\ninterrupt: {what} (Ctrl-C again, a second later, to abort)");
    });
    &INTERRUPTED
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The flag value parsers take what the flag takes and name what it needs otherwise.
    #[test]
    fn flag_value_parsers() {
        assert_eq!(parse_positive("3"), Ok(3));
        assert_eq!(parse_positive("0").unwrap_err(), "must be at least 1");
        assert_eq!(parse_downsample("2"), Ok(2));
        assert!(parse_downsample("0").is_err() && parse_downsample("5000000000").is_err());
        assert_eq!(parse_gamma("4"), Ok(4));
        assert_eq!(
            parse_gamma("9").unwrap_err(),
            "must be 1 to 4 (γ×γ rays per pixel)"
        );
        assert_eq!(parse_levels("0"), Ok(0));
        assert!(parse_levels("7").unwrap_err().starts_with("must be 0 to 6"));
        assert_eq!(parse_fraction("1"), Ok(1.0));
        for bad in ["0", "1.5", "nan", "-0.1", "x"] {
            assert!(parse_fraction(bad).is_err(), "{bad}");
        }
        assert_eq!(parse_fraction_or_zero("0"), Ok(0.0));
        assert!(parse_fraction_or_zero("2").is_err());
        assert_eq!(parse_non_negative("0"), Ok(0.0));
        assert!(parse_non_negative("-1").is_err() && parse_non_negative("inf").is_err());
        assert_eq!(parse_positive_number("0.5"), Ok(0.5));
        for bad in ["0", "-2", "inf", "nan"] {
            assert!(parse_positive_number(bad).is_err(), "{bad}");
        }
        assert_eq!(parse_view_pair("0, b.png").as_deref(), Ok("0, b.png"));
        for bad in ["0", "0,", "a,b,c"] {
            assert!(parse_view_pair(bad).is_err(), "{bad}");
        }
    }
    use crate::scene::{LoadOptions, Scene};

    /// Views are chosen by whole name, by file stem when one view has it, or by index; a stem
    /// two views share (`cam1/0001.png`, `cam2/0001.png`) is an error naming both, not the first.
    #[test]
    fn views_by_name_stem_or_index() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
        let mut scene = Scene::load(&dir, &LoadOptions::default()).unwrap();
        let sel = |spec: &str, scene: &Scene| select_views(scene, spec, "--views");
        assert_eq!(sel("0003.png,0004, 5", &scene).unwrap(), [3, 4, 5]);
        assert_eq!(sel("test", &scene).unwrap(), scene.test);
        scene.views[1].name = "cam1/0001.png".into();
        scene.views[2].name = "cam2/0001.png".into();
        assert_eq!(sel("cam2/0001.png", &scene).unwrap(), [2]);
        let e = sel("0001", &scene).unwrap_err().to_string();
        assert!(
            e.contains("names 2 views (cam1/0001.png, cam2/0001.png)"),
            "{e}"
        );
        let e = sel("0009", &scene).unwrap_err().to_string();
        assert!(e.contains("no view named or numbered \"0009\""), "{e}");
        // The flag the list came from is the one named.
        let e = select_views(&scene, "0,99", "--path")
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("--path: no view named or numbered \"99\""),
            "{e}"
        );
    }

    /// A view named twice, by the same word or by two (index and name), is refused: it would be
    /// scored twice and weigh twice in the mean (`eval --views 0,0` did).
    #[test]
    fn a_view_named_twice_is_refused() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
        let scene = Scene::load(&dir, &LoadOptions::default()).unwrap();
        for spec in ["0,0", "3,0003.png", "0004, 4"] {
            let e = select_views(&scene, spec, "--views")
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("--views: view") && e.contains("named twice"),
                "{spec}: {e}"
            );
        }
        let e = select_views(&scene, "1,1", "--path")
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("--path: view 0001.png is named twice"), "{e}");
        assert_eq!(select_views(&scene, "1,0", "--views").unwrap(), [1, 0]);
    }
}
