//! `xscale prepare`'s stages, from a folder of photos to a scene folder xscale reads:
//!
//! | stage | what | writes |
//! |---|---|---|
//! | photos | list the photos, match them to known poses, copy (or downsample) them | `OUT/images/` |
//! | features | `colmap feature_extractor` (CPU SIFT) | `OUT/.prepare/database.db` |
//! | matches | `colmap exhaustive_matcher`, `sequential_matcher`, or `matches_importer` with pairs of nearby known poses | the database |
//! | sparse | `colmap point_triangulator` with the known poses, or `colmap mapper` | `OUT/sparse/0/` |
//! | undistort | `colmap image_undistorter` (asked for only) | `OUT/dense/` |
//! | mesh | the Delaunay graph cut of the points (`mesher.rs`), a report | `OUT/mesh.ply`, `OUT/prepare.json` |
//!
//! A stage's output appears under its final name only when the stage is done (COLMAP writes
//! into `OUT/.prepare/` and the folder is renamed; the mesh is written last), and
//! `OUT/.prepare/state.json` lists the stages done with the inputs they were made from. So a run
//! stopped anywhere leaves no `mesh.ply` a later command would take as a finished scene, and the
//! same command again goes on from the first stage not done (COLMAP itself skips photos and
//! pairs its database already has); run on a finished folder it only prints the report. Other
//! photos or settings than those recorded are refused (`--force` starts over).

use super::colmap_run::{Colmap, Step, INSTALL_HINT};
use super::mesher::{self, Track};
use super::sparse::{Model, Reprojection};
use crate::scene::{self, colmap, CameraFormat, View};
use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

/// How image pairs are chosen for matching.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Matcher {
    /// Known poses: pairs of nearby views; otherwise exhaustive up to 100 photos, sequential beyond.
    Auto,
    /// Every pair (`colmap exhaustive_matcher`).
    Exhaustive,
    /// Each photo with the next 10 in name order (`colmap sequential_matcher`): videos.
    Sequential,
    /// Each view with its [`PAIR_NEIGHBOURS`] nearest known poses (`colmap matches_importer`).
    Pairs,
}

/// Views each view is matched with under [`Matcher::Pairs`].
pub const PAIR_NEIGHBOURS: usize = 20;
/// Beyond this many photos, [`Matcher::Auto`] without poses matches sequentially.
pub const EXHAUSTIVE_MAX: usize = 100;

/// Everything `xscale prepare` is told.
#[derive(Clone, Debug)]
pub struct Options {
    /// Folder of photos.
    pub photos: Option<PathBuf>,
    /// A scene folder with known poses (any camera layout xscale reads).
    pub poses: Option<PathBuf>,
    /// An existing COLMAP sparse model to mesh (no COLMAP run).
    pub sparse: Option<PathBuf>,
    pub out: PathBuf,
    pub downsample: u32,
    pub matcher: Matcher,
    /// SIFT features per photo at most (COLMAP's default 8192 when `None`).
    pub max_features: Option<u32>,
    pub undistort: bool,
    pub force: bool,
    pub dry_run: bool,
    pub colmap: Option<PathBuf>,
    /// Threads COLMAP uses.
    pub threads: usize,
    pub mesher: mesher::Options,
}

/// The inputs and settings the COLMAP stages depend on: a folder made from others is refused.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Inputs {
    photos: Vec<(String, u64)>,
    poses: Option<String>,
    sparse: Option<String>,
    downsample: u32,
    matcher: Matcher,
    max_features: Option<u32>,
    undistort: bool,
}

/// `OUT/.prepare/state.json`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
struct State {
    inputs: Option<Inputs>,
    /// The mesher settings the mesh was made with (other ones redo only the mesh).
    #[serde(default)]
    mesher: Option<String>,
    done: Vec<String>,
    seconds: Vec<(String, f64)>,
}

/// Per view in the report.
#[derive(Clone, Debug, Serialize)]
pub struct ViewReport {
    pub name: String,
    /// Keypoints of the photo that belong to a 3-D point.
    pub observations: usize,
    /// Share of the view's pixels whose ray meets the mesh (cast at a reduced resolution).
    pub hit: f64,
}

/// `OUT/prepare.json`.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub photos: usize,
    pub views: usize,
    pub points: usize,
    /// Through xscale's cameras (with their distortion), every observation.
    pub reprojection: Reprojection,
    /// COLMAP's own per-point errors, averaged.
    pub colmap_mean_error: f64,
    pub mesh_vertices: usize,
    pub mesh_triangles: usize,
    pub mesher: mesher::Stats,
    pub mean_hit: f64,
    pub per_view: Vec<ViewReport>,
    /// Seconds per stage, in order.
    pub seconds: Vec<(String, f64)>,
    pub notes: Vec<String>,
}

const PHOTO_EXTS: [&str; 6] = ["jpg", "jpeg", "png", "tif", "tiff", "bmp"];

struct Ctx<'a> {
    work: PathBuf,
    state: State,
    stop: &'a AtomicBool,
    notes: Vec<String>,
}

fn say(msg: impl AsRef<str>) {
    eprintln!("{}", msg.as_ref());
}

impl Ctx<'_> {
    fn done(&self, stage: &str) -> bool {
        self.state.done.iter().any(|s| s == stage)
    }

    fn finish(&mut self, stage: &str, secs: f64) -> Result<()> {
        self.state.done.retain(|s| s != stage);
        self.state.done.push(stage.to_string());
        self.state.seconds.retain(|(s, _)| s != stage);
        self.state.seconds.push((stage.to_string(), secs));
        self.save()
    }

    fn save(&self) -> Result<()> {
        let text = serde_json::to_string_pretty(&self.state)?;
        crate::io::atomic::write_bytes(&self.work.join("state.json"), text)
    }

    fn check_stop(&self) -> Result<()> {
        if self.stop.load(std::sync::atomic::Ordering::SeqCst) {
            bail!("interrupted");
        }
        Ok(())
    }
}

/// The photos of a folder (by extension, case-insensitive), sorted by name.
pub fn list_photos(dir: &Path) -> Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        bail!("{}: photo folder not found", dir.display());
    }
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("{}: cannot list", dir.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| PHOTO_EXTS.iter().any(|x| e.eq_ignore_ascii_case(x)))
        })
        .collect();
    out.sort();
    if out.is_empty() {
        bail!(
            "{}: no photos ({} files) in the folder",
            dir.display(),
            PHOTO_EXTS.join(", ")
        );
    }
    Ok(out)
}

fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_default()
}

/// Known poses from a scene folder, matched to the photos by file name (or stem): the views
/// kept (named as their photos, cameras as the photos are), and notes on what was left out.
fn load_poses(dir: &Path, photos: &[PathBuf], work: &Path) -> Result<(Vec<View>, Vec<String>)> {
    let format = one_format(dir)?;
    let mut notes = Vec::new();
    let views = match format {
        CameraFormat::Transforms => transforms_with_photos(dir, photos, work, &mut notes)?,
        CameraFormat::Colmap => {
            let l = colmap::find_layout(dir)
                .ok_or_else(|| anyhow!("{}: no COLMAP model", dir.display()))?;
            colmap::load(&l.model, &l.images)?
        }
        CameraFormat::MvsNet => {
            let l = scene::mvsnet::find_layouts(dir)
                .into_iter()
                .next()
                .ok_or_else(|| anyhow!("{}: no cams_<dsp>/", dir.display()))?;
            scene::mvsnet::load(&l)?
        }
        CameraFormat::Metashape => {
            let xml = scene::metashape::find(dir)
                .ok_or_else(|| anyhow!("{}: no cameras.xml", dir.display()))?;
            let loaded = scene::metashape::load(&xml, &dir.join("images"))?;
            notes.extend(loaded.notes);
            loaded.views
        }
    };
    let mut kept = Vec::new();
    let mut missing = Vec::new();
    for v in views {
        match photo_named(photos, &v.name) {
            Some(p) => {
                let (w, h) = scene::image::dimensions(p)?;
                if (w, h) != (v.camera.width, v.camera.height) {
                    bail!(
                        "{}: the photo is {w}x{h} but the known camera of '{}' ({}) is {}x{}",
                        p.display(),
                        v.name,
                        format.name(),
                        v.camera.width,
                        v.camera.height
                    );
                }
                kept.push(View {
                    name: file_name(p),
                    camera: v.camera,
                    image_path: p.clone(),
                });
            }
            None => missing.push(v.name),
        }
    }
    if !missing.is_empty() && format != CameraFormat::Transforms {
        notes.push(format!(
            "{} of the known views have no photo and are left out: {}",
            missing.len(),
            first_names(&missing)
        ));
    }
    let unposed = photos.len() - kept.len();
    if unposed > 0 {
        notes.push(format!(
            "{unposed} photos have no known pose and are not used"
        ));
    }
    kept.sort_by(|a, b| a.name.cmp(&b.name));
    if kept.len() < 2 {
        bail!(
            "{}: only {} known views have a photo: two at least are needed",
            dir.display(),
            kept.len()
        );
    }
    Ok((kept, notes))
}

/// The first eight of `names`, then "…" if there are more.
fn first_names(names: &[String]) -> String {
    let mut s = names[..names.len().min(8)].join(", ");
    if names.len() > 8 {
        s += ", …";
    }
    s
}

/// The one camera layout of a `--poses` folder (none or several is an error).
fn one_format(dir: &Path) -> Result<CameraFormat> {
    let formats = scene::detect_formats(dir);
    match formats.as_slice() {
        [f] => Ok(*f),
        [] => bail!(
            "{}: no cameras found for --poses (transforms.json, a COLMAP model, MVSNet cams_<dsp>/, Metashape cameras.xml)",
            dir.display()
        ),
        many => bail!(
            "{}: several camera layouts ({}): give --poses a folder with one",
            dir.display(),
            many.iter().map(|f| f.name()).collect::<Vec<_>>().join(", ")
        ),
    }
}

/// The photo a view named `n` shows: the one with its file name, else the only one with its stem.
fn photo_named<'a>(photos: &'a [PathBuf], n: &str) -> Option<&'a PathBuf> {
    let base = Path::new(n)
        .file_name()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_default();
    let stem = Path::new(&base)
        .file_stem()
        .map(|s| s.to_string_lossy().to_string());
    photos.iter().find(|p| file_name(p) == base).or_else(|| {
        let matches: Vec<&PathBuf> = photos
            .iter()
            .filter(|p| p.file_stem().map(|s| s.to_string_lossy().to_string()) == stem)
            .collect();
        (matches.len() == 1).then(|| matches[0])
    })
}

/// `p` made absolute (against the working folder), as a JSON string.
fn absolute_text(p: &Path) -> serde_json::Value {
    let a = std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    serde_json::Value::String(a.to_string_lossy().to_string())
}

/// The views of `dir/transforms.json` whose frames have a photo (a trimmed public capture lists
/// more than it ships), read from a copy in `work` that names the photos.
fn transforms_with_photos(
    dir: &Path,
    photos: &[PathBuf],
    work: &Path,
    notes: &mut Vec<String>,
) -> Result<Vec<View>> {
    let file = dir.join("transforms.json");
    if !file.is_file() {
        bail!(
            "{}: --poses reads transforms.json (not the NeRF-synthetic split files)",
            dir.display()
        );
    }
    let mut root: serde_json::Value = serde_json::from_str(&crate::io::text::read(&file)?)
        .map_err(|e| anyhow!("{}: {e}", file.display()))?;
    let frames = root
        .get_mut("frames")
        .and_then(|f| f.as_array_mut())
        .ok_or_else(|| anyhow!("{}: no 'frames' array", file.display()))?;
    let total = frames.len();
    let mut missing = Vec::new();
    frames.retain_mut(|f| {
        let Some(fp) = f
            .get("file_path")
            .and_then(|v| v.as_str())
            .map(str::to_string)
        else {
            return true; // the loader names it
        };
        match photo_named(photos, &fp) {
            Some(p) => {
                // The copy stands in another folder: its paths are absolute.
                f["file_path"] = absolute_text(p);
                let mask = f
                    .get("mask_path")
                    .and_then(|v| v.as_str())
                    .map(|m| absolute_text(&dir.join(m.strip_prefix("./").unwrap_or(m))));
                if let Some(m) = mask {
                    f["mask_path"] = m;
                }
                true
            }
            None => {
                missing.push(fp);
                false
            }
        }
    });
    if !missing.is_empty() {
        notes.push(format!(
            "{}: {} of {total} frames have no photo in the photo folder and are left out: {}",
            file.display(),
            missing.len(),
            first_names(&missing)
        ));
    }
    let copy = work.join("poses-transforms.json");
    crate::io::atomic::write_bytes(&copy, serde_json::to_string_pretty(&root)?)?;
    Ok(
        scene::transforms::load_full(&copy, scene::transforms::AppliedTransform::Undo)
            .map_err(|e| {
                anyhow!(
                    "{} (read from the frames of {} that have photos): {e:#}",
                    copy.display(),
                    file.display()
                )
            })?
            .views,
    )
}

/// Pairs of views to match: each view with its `k` nearest by the angle between optical axes
/// (those facing away by more than 90° are never paired), then by centre distance.
pub fn pose_pairs(views: &[View], k: usize) -> Vec<(usize, usize)> {
    let axis = |v: &View| v.camera.rotation.transpose() * glam::DVec3::Z;
    let mut pairs = std::collections::BTreeSet::new();
    for (i, a) in views.iter().enumerate() {
        let mut cand: Vec<(f64, f64, usize)> = views
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != i)
            .filter_map(|(j, b)| {
                let c = axis(a).dot(axis(b));
                (c > 0.0).then(|| (-c, (a.camera.center() - b.camera.center()).length(), j))
            })
            .collect();
        cand.sort_by(|x, y| {
            x.0.total_cmp(&y.0)
                .then(x.1.total_cmp(&y.1))
                .then(x.2.cmp(&y.2))
        });
        for &(_, _, j) in cand.iter().take(k) {
            pairs.insert((i.min(j), i.max(j)));
        }
    }
    pairs.into_iter().collect()
}

/// Copy a photo to `dst`, or write it downsampled by `s` (block average, as xscale's own
/// `--downsample`; JPEG at quality 95, anything else as 8-bit PNG under the same name).
fn copy_photo(src: &Path, dst: &Path, s: u32) -> Result<()> {
    if s <= 1 {
        if std::fs::hard_link(src, dst).is_err() {
            std::fs::copy(src, dst)
                .with_context(|| format!("{}: cannot copy to {}", src.display(), dst.display()))?;
        }
        return Ok(());
    }
    let img = scene::image::load_rgb(src)?;
    let small = scene::image::downsample(&img, s);
    let ext = dst
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    if ext == "jpg" || ext == "jpeg" {
        let bytes: Vec<u8> = small
            .data
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        crate::io::atomic::write_atomic(dst, false, |tmp| {
            let f = std::fs::File::create(tmp)?;
            let mut enc = ::image::codecs::jpeg::JpegEncoder::new_with_quality(
                std::io::BufWriter::new(f),
                95,
            );
            enc.encode(
                &bytes,
                small.width,
                small.height,
                ::image::ExtendedColorType::Rgb8,
            )
            .map_err(|e| anyhow!("{}: cannot encode JPEG: {e}", dst.display()))
        })
    } else {
        scene::image::write_png8(dst, &small)
    }
}

/// COLMAP's camera model name and parameters for a view's camera.
fn colmap_camera(v: &View) -> Result<(&'static str, Vec<f64>)> {
    let (m, p) = colmap::model_of(v)?;
    Ok((colmap::MODELS[m].0, p))
}

/// The COLMAP commands of the run, in order (the sparse stage's depend on whether poses are known).
fn colmap_steps(
    o: &Options,
    work: &Path,
    views: Option<&[View]>,
    n_photos: usize,
) -> Result<Vec<(&'static str, Step)>> {
    let db = work.join("database.db");
    let images = o.out.join("images");
    let t = o.threads.max(1);
    let mut fe = Step::new("feature_extractor")
        .arg("database_path", db.display())
        .arg("image_path", images.display())
        .arg("SiftExtraction.use_gpu", 0)
        .arg("SiftExtraction.num_threads", t);
    if let Some(n) = o.max_features {
        fe = fe.arg("SiftExtraction.max_num_features", n);
    }
    if let Some(vs) = views {
        // One COLMAP camera when every view shares the intrinsics (it helps the matcher's
        // geometric verification; triangulation uses the known cameras either way).
        let first = colmap_camera(&vs[0])?;
        let shared = vs
            .iter()
            .all(|v| colmap_camera(v).map(|c| c == first).unwrap_or(false));
        if shared {
            fe = fe
                .arg("ImageReader.single_camera", 1)
                .arg("ImageReader.camera_model", first.0)
                .arg(
                    "ImageReader.camera_params",
                    first
                        .1
                        .iter()
                        .map(|x| format!("{x}"))
                        .collect::<Vec<_>>()
                        .join(","),
                );
        }
    } else {
        fe = fe.arg("ImageReader.single_camera", 1);
    }
    let matcher = match (o.matcher, views.is_some()) {
        (Matcher::Auto, true) => Matcher::Pairs,
        (Matcher::Auto, false) if n_photos <= EXHAUSTIVE_MAX => Matcher::Exhaustive,
        (Matcher::Auto, false) => Matcher::Sequential,
        (Matcher::Pairs, false) => bail!("--matcher pairs needs known poses (--poses)"),
        (m, _) => m,
    };
    let mt = match matcher {
        Matcher::Exhaustive => Step::new("exhaustive_matcher"),
        Matcher::Sequential => {
            Step::new("sequential_matcher").arg("SequentialMatching.overlap", 10)
        }
        _ => Step::new("matches_importer")
            .arg("match_list_path", work.join("pairs.txt").display())
            .arg("match_type", "pairs"),
    }
    .arg("database_path", db.display())
    .arg("SiftMatching.use_gpu", 0)
    .arg("SiftMatching.num_threads", t);
    let sfm = if views.is_some() {
        Step::new("point_triangulator")
            .arg("database_path", db.display())
            .arg("image_path", images.display())
            .arg("input_path", work.join("known").display())
            .arg("output_path", work.join("sparse-new").display())
            .arg("clear_points", 1)
            .arg("Mapper.ba_refine_focal_length", 0)
            .arg("Mapper.ba_refine_principal_point", 0)
            .arg("Mapper.ba_refine_extra_params", 0)
    } else {
        Step::new("mapper")
            .arg("database_path", db.display())
            .arg("image_path", images.display())
            .arg("output_path", work.join("sparse-new").display())
            .arg("Mapper.num_threads", t)
    };
    let mut steps = vec![("features", fe), ("matches", mt), ("sparse", sfm)];
    if o.undistort {
        steps.push((
            "undistort",
            Step::new("image_undistorter")
                .arg("image_path", images.display())
                .arg("input_path", o.out.join("sparse").join("0").display())
                .arg("output_path", work.join("dense-new").display())
                .arg("output_type", "COLMAP"),
        ));
    }
    Ok(steps)
}

/// The folders and files `prepare` makes in OUT (what `--force` removes).
const MADE: [&str; 5] = ["images", "sparse", "dense", "mesh.ply", "prepare.json"];

/// Run `xscale prepare`. Returns the report (also written to `OUT/prepare.json`), or `None` for
/// a dry run.
pub fn run(o: &Options, stop: &AtomicBool) -> Result<Option<Report>> {
    let out = &o.out;
    let work = out.join(".prepare");
    if o.downsample == 0 {
        bail!("--downsample must be at least 1");
    }
    if o.sparse.is_some() && (o.poses.is_some() || o.downsample > 1 || o.undistort) {
        bail!("--sparse meshes an existing model as it is: it takes no --poses, --downsample or --undistort");
    }
    // Inputs.
    let photo_dir = photo_dir(o)?;
    let photos = list_photos(&photo_dir)?;
    let inputs = inputs_of(o, &photos);
    let mut ctx = Ctx {
        work: work.clone(),
        state: open_out(o, &work, &inputs)?,
        stop,
        notes: Vec::new(),
    };
    // Known poses, matched to the photos.
    let colmap_exe = Colmap::find(o.colmap.as_deref());
    // Nothing is written by a dry run, nor when COLMAP is missing and needed.
    let writes = !o.dry_run && (colmap_exe.is_some() || o.sparse.is_some());
    if writes {
        std::fs::create_dir_all(&work)
            .with_context(|| format!("{}: cannot create", work.display()))?;
    }
    let views = known_views(o, &photos, writes, &mut ctx.notes)?;
    let used: Vec<PathBuf> = match &views {
        Some(v) => v.iter().map(|x| x.image_path.clone()).collect(),
        None => photos.clone(),
    };
    let steps = if o.sparse.is_none() {
        colmap_steps(o, &work, views.as_deref(), used.len())?
    } else {
        Vec::new()
    };
    let plan = Plan {
        photos: photos.len(),
        used,
        views,
        steps,
        images: out.join("images"),
    };
    if o.dry_run || (colmap_exe.is_none() && o.sparse.is_none()) {
        let exe = colmap_exe
            .as_ref()
            .map(|c| c.exe.display().to_string())
            .unwrap_or_else(|| "colmap".into());
        print_plan(o, &plan, &photo_dir, &work, &exe);
        if colmap_exe.is_none() && !o.dry_run {
            bail!("{INSTALL_HINT}\nThe commands above are what would have run.");
        }
        return Ok(None);
    }
    if ctx.state.inputs.is_none() {
        ctx.state.inputs = Some(inputs.clone());
        ctx.save()?;
    }
    let mesher_key = format!("{:?}", o.mesher);
    if ctx.done("mesh") && ctx.state.mesher.as_deref() != Some(mesher_key.as_str()) {
        say("note: other mesher settings than the mesh was made with: meshing again");
        ctx.state.done.retain(|s| s != "mesh");
    }
    let all_done =
        ["photos", "sparse", "mesh"].iter().all(|s| ctx.done(s)) && out.join("mesh.ply").is_file();
    if all_done && (!o.undistort || ctx.done("undistort")) {
        let text = crate::io::text::read(&out.join("prepare.json")).unwrap_or_default();
        say(format!(
            "{} is already prepared from these photos and settings (its report: {}); --force redoes it",
            out.display(),
            out.join("prepare.json").display()
        ));
        if !text.is_empty() {
            println!("{}", summary_of_json(&text));
        }
        return Ok(None);
    }
    let mut header = Headers {
        k: 0,
        n: if o.sparse.is_some() {
            2
        } else {
            4 + o.undistort as usize + 1
        },
    };
    stage_photos(o, &mut ctx, &plan, &mut header)?;
    if o.sparse.is_some() {
        ctx.finish("sparse", 0.0)?;
    }
    if o.sparse.is_none() {
        let colmap_exe = colmap_exe.unwrap_or(Colmap {
            exe: "colmap".into(),
        });
        colmap_stages(o, &mut ctx, &plan, &colmap_exe, &mut header)?;
    }
    stage_mesh(o, &mut ctx, &plan, &mut header, mesher_key).map(Some)
}

/// What a run works on once its inputs are read.
struct Plan {
    /// Photos in the photo folder.
    photos: usize,
    /// The photos used (those with a known pose, when poses are given).
    used: Vec<PathBuf>,
    /// Known poses (`--poses`).
    views: Option<Vec<View>>,
    /// The COLMAP commands, by stage ([`colmap_steps`]; none with `--sparse`).
    steps: Vec<(&'static str, Step)>,
    /// `OUT/images`.
    images: PathBuf,
}

/// Numbered stage headers: `[k/n] name: what`.
struct Headers {
    k: usize,
    n: usize,
}

impl Headers {
    fn say(&mut self, name: &str, what: String) {
        self.k += 1;
        say(format!("[{}/{}] {name}: {what}", self.k, self.n));
    }
}

/// The photo folder: `--photos`, else the `images/` of `--poses`, else the images of the
/// `--sparse` model's layout.
fn photo_dir(o: &Options) -> Result<PathBuf> {
    Ok(match (&o.photos, &o.poses, &o.sparse) {
        (Some(p), _, _) => p.clone(),
        (None, Some(p), _) => {
            let i = p.join("images");
            if !i.is_dir() {
                bail!(
                    "--poses {} has no images/ folder: name the photos with --photos DIR",
                    p.display()
                );
            }
            i
        }
        (None, None, Some(s)) => {
            // The layout's images/, else those of the COLMAP workspace the model stands in
            // (WS/sparse/0 or WS/sparse beside WS/images).
            let layout = colmap::find_layout(s).map(|l| l.images);
            let beside = [
                s.join("..").join("images"),
                s.join("..").join("..").join("images"),
            ];
            let first = layout.clone().unwrap_or_else(|| beside[1].clone());
            layout
                .into_iter()
                .chain(beside)
                .find(|d| d.is_dir())
                .unwrap_or(first)
        }
        (None, None, None) => {
            bail!("give the photos (--photos DIR), or a COLMAP model to mesh (--sparse DIR)")
        }
    })
}

fn inputs_of(o: &Options, photos: &[PathBuf]) -> Inputs {
    Inputs {
        photos: photos
            .iter()
            .map(|p| (file_name(p), p.metadata().map(|m| m.len()).unwrap_or(0)))
            .collect(),
        poses: o.poses.as_ref().map(|p| p.display().to_string()),
        sparse: o.sparse.as_ref().map(|p| p.display().to_string()),
        downsample: o.downsample,
        matcher: o.matcher,
        max_features: o.max_features,
        undistort: o.undistort,
    }
}

/// The output folder's state: new, ours (resumed or finished), emptied by `--force`, or refused
/// (another folder, or one made from other inputs).
fn open_out(o: &Options, work: &Path, inputs: &Inputs) -> Result<State> {
    let out = &o.out;
    let state_path = work.join("state.json");
    let state = if state_path.is_file() {
        serde_json::from_str::<State>(&crate::io::text::read(&state_path)?).map_err(|e| {
            anyhow!(
                "{}: {e} (remove {} to start over)",
                state_path.display(),
                work.display()
            )
        })?
    } else {
        State::default()
    };
    if o.force && !o.dry_run {
        for m in MADE {
            let p = out.join(m);
            if p.is_dir() {
                std::fs::remove_dir_all(&p)
                    .with_context(|| format!("{}: cannot remove", p.display()))?;
            } else if p.exists() {
                std::fs::remove_file(&p)
                    .with_context(|| format!("{}: cannot remove", p.display()))?;
            }
        }
        if work.exists() {
            std::fs::remove_dir_all(work)
                .with_context(|| format!("{}: cannot remove", work.display()))?;
        }
        return Ok(State::default());
    }
    if out.is_dir() && !work.is_dir() && std::fs::read_dir(out)?.next().is_some() {
        bail!(
            "{}: the folder exists and was not made by `xscale prepare`: give a new or empty --out folder",
            out.display()
        );
    }
    if let Some(prev) = &state.inputs {
        if prev != inputs {
            bail!(
                "{}: prepared from other photos or settings than these ({}); add --force to start over there, or give another --out",
                out.display(),
                describe_change(prev, inputs)
            );
        }
    }
    Ok(state)
}

/// The known poses of `--poses` (cameras downsampled as the photos will be), their notes said
/// and kept; `None` without `--poses`.
fn known_views(
    o: &Options,
    photos: &[PathBuf],
    writes: bool,
    notes: &mut Vec<String>,
) -> Result<Option<Vec<View>>> {
    let Some(p) = &o.poses else {
        return Ok(None);
    };
    let scratch = if writes {
        o.out.join(".prepare")
    } else {
        std::env::temp_dir()
    };
    let (mut v, found) = load_poses(p, photos, &scratch)?;
    for n in found {
        say(format!("note: {n}"));
        notes.push(n);
    }
    if o.downsample > 1 {
        for x in v.iter_mut() {
            x.camera = x.camera.downsampled(o.downsample);
        }
    }
    Ok(Some(v))
}

/// What a run would do, as shell commands (a dry run, or COLMAP missing).
fn print_plan(o: &Options, plan: &Plan, photo_dir: &Path, work: &Path, exe: &str) {
    println!(
        "# photos: {} from {} into {}",
        plan.used.len(),
        photo_dir.display(),
        plan.images.display()
    );
    for (stage, s) in &plan.steps {
        if *stage == "matches" && s.command == "matches_importer" {
            println!("# pairs.txt: each view with its {PAIR_NEIGHBOURS} nearest known poses");
        }
        if *stage == "sparse" && plan.views.is_some() {
            println!(
                "# {}: the known poses as a COLMAP model",
                work.join("known").display()
            );
        }
        println!("{}", s.shell(exe));
    }
    println!(
        "# then: the Delaunay graph-cut mesh of the points → {}",
        o.out.join("mesh.ply").display()
    );
}

/// Stage: the photos copied (or downsampled) to `OUT/images`, and a `--sparse` model to
/// `OUT/sparse/0`.
fn stage_photos(o: &Options, ctx: &mut Ctx, plan: &Plan, header: &mut Headers) -> Result<()> {
    let (images, used) = (&plan.images, &plan.used);
    if ctx.done("photos") {
        header.say("photos", "done before".into());
        return Ok(());
    }
    header.say(
        "photos",
        format!(
            "{} photos → {}{}",
            used.len(),
            images.display(),
            if o.downsample > 1 {
                format!(" (downsampled {}×)", o.downsample)
            } else {
                String::new()
            }
        ),
    );
    let t = Instant::now();
    std::fs::create_dir_all(images)
        .with_context(|| format!("{}: cannot create", images.display()))?;
    for (i, p) in used.iter().enumerate() {
        ctx.check_stop()?;
        copy_photo(p, &images.join(file_name(p)), o.downsample)?;
        if i % 10 == 9 {
            say(format!("  {}/{}", i + 1, used.len()));
        }
    }
    if let Some(s) = &o.sparse {
        let l = colmap::find_layout(s);
        let model = l.map(|l| l.model).unwrap_or_else(|| s.clone());
        let dst = o.out.join("sparse").join("0");
        std::fs::create_dir_all(&dst)?;
        for f in ["cameras", "images", "points3D"] {
            for ext in ["txt", "bin"] {
                let src = model.join(format!("{f}.{ext}"));
                if src.is_file() {
                    std::fs::copy(&src, dst.join(format!("{f}.{ext}")))?;
                }
            }
        }
    }
    ctx.finish("photos", t.elapsed().as_secs_f64())
}

/// The COLMAP stages not done yet, each run into `OUT/.prepare` and moved to its final name
/// when done.
fn colmap_stages(
    o: &Options,
    ctx: &mut Ctx,
    plan: &Plan,
    colmap_exe: &Colmap,
    header: &mut Headers,
) -> Result<()> {
    let work = ctx.work.clone();
    if ctx.state.done.len() == 1 {
        if let Some(v) = colmap_exe.version() {
            say(format!("  using {v} ({})", colmap_exe.exe.display()));
        }
    }
    let logs = work.join("logs");
    std::fs::create_dir_all(&logs)?;
    for (stage, step) in &plan.steps {
        if ctx.done(stage) {
            header.say(stage, "done before".into());
            continue;
        }
        header.say(stage, format!("colmap {}", step.command));
        let t = Instant::now();
        before_colmap(stage, step, &work, plan.views.as_deref())?;
        let log = logs.join(format!("{stage}.log"));
        colmap_exe.run(step, &log, ctx.stop, &mut |p| say(format!("  {p}")))?;
        match *stage {
            "sparse" => {
                let new = work.join("sparse-new");
                // The mapper writes one model per connected part (0, 1, …): the largest.
                let model = if plan.views.is_some() {
                    new.clone()
                } else {
                    largest_model(&new, &plan.images, plan.used.len(), &mut ctx.notes)?
                };
                let dst = o.out.join("sparse").join("0");
                if dst.exists() {
                    std::fs::remove_dir_all(&dst)?;
                }
                std::fs::create_dir_all(o.out.join("sparse"))?;
                std::fs::rename(&model, &dst).with_context(|| {
                    format!("{}: cannot move to {}", model.display(), dst.display())
                })?;
            }
            "undistort" => {
                let dst = o.out.join("dense");
                if dst.exists() {
                    std::fs::remove_dir_all(&dst)?;
                }
                std::fs::rename(work.join("dense-new"), &dst)?;
            }
            _ => {}
        }
        let secs = t.elapsed().as_secs_f64();
        say(format!("  {stage}: {secs:.1} s"));
        ctx.finish(stage, secs)?;
    }
    Ok(())
}

/// What a COLMAP stage needs in `work` before it runs: the pairs of nearby views, an empty
/// output folder, the known poses as a COLMAP model.
fn before_colmap(stage: &str, step: &Step, work: &Path, views: Option<&[View]>) -> Result<()> {
    match stage {
        "matches" if step.command == "matches_importer" => {
            let v = views.unwrap();
            let pairs = pose_pairs(v, PAIR_NEIGHBOURS);
            let text: String = pairs
                .iter()
                .map(|&(a, b)| format!("{} {}\n", v[a].name, v[b].name))
                .collect();
            crate::io::atomic::write_bytes(&work.join("pairs.txt"), text)?;
            say(format!(
                "  {} pairs of nearby views (of {} in all)",
                pairs.len(),
                v.len() * (v.len() - 1) / 2
            ));
        }
        "sparse" => {
            let new = work.join("sparse-new");
            if new.exists() {
                std::fs::remove_dir_all(&new)?;
            }
            std::fs::create_dir_all(&new)?;
            if let Some(v) = views {
                colmap::write_text(&work.join("known"), v)?;
            }
        }
        "undistort" => {
            let new = work.join("dense-new");
            if new.exists() {
                std::fs::remove_dir_all(&new)?;
            }
        }
        _ => {}
    }
    Ok(())
}

/// Stage: the mesh of the sparse points and the report, written to `OUT/prepare.json`, the mesh
/// last (under its final name it makes the folder a scene); the state records `mesher_key`, the
/// mesher settings.
fn stage_mesh(
    o: &Options,
    ctx: &mut Ctx,
    plan: &Plan,
    header: &mut Headers,
    mesher_key: String,
) -> Result<Report> {
    let out = &o.out;
    header.say("mesh", "Delaunay graph cut of the sparse points".into());
    let t = Instant::now();
    let model = Model::read(&out.join("sparse").join("0"), &plan.images)?;
    let (mesh, mstats) = mesh_model(&model, &o.mesher, ctx.stop)?;
    if mesh.triangles.is_empty() {
        bail!("the graph cut found no surface (every cell on one side): too few points or views");
    }
    let tmp_mesh = ctx.work.join("mesh.ply");
    scene::mesh::write_ply(&tmp_mesh, &mesh)?;
    ctx.check_stop()?;
    let per_view = hit_fractions(&model, &mesh)?;
    let secs = t.elapsed().as_secs_f64();
    ctx.state.seconds.retain(|(s, _)| s != "mesh");
    ctx.state.seconds.push(("mesh".into(), secs));
    let reprojection = model.reprojection();
    let report = Report {
        photos: plan.photos,
        views: model.views.len(),
        points: model.points.len(),
        reprojection,
        colmap_mean_error: model.points.iter().map(|p| p.error).sum::<f64>()
            / model.points.len().max(1) as f64,
        mesh_vertices: mesh.vertices.len(),
        mesh_triangles: mesh.triangles.len(),
        mesher: mstats,
        mean_hit: per_view.iter().map(|v| v.hit).sum::<f64>() / per_view.len().max(1) as f64,
        per_view,
        seconds: ctx.state.seconds.clone(),
        notes: ctx.notes.clone(),
    };
    let json = serde_json::to_string_pretty(&report)?;
    crate::io::atomic::write_bytes(&out.join("prepare.json"), &json)?;
    std::fs::rename(&tmp_mesh, out.join("mesh.ply"))
        .with_context(|| format!("{}: cannot move", tmp_mesh.display()))?;
    ctx.state.mesher = Some(mesher_key);
    ctx.finish("mesh", secs)?;
    println!("{}", summary_of_json(&json));
    println!("scene ready: xscale train --scene {}", out.display());
    Ok(report)
}

/// The mesher run on a sparse model's points and cameras, its progress said every 2 s.
fn mesh_model(
    model: &Model,
    opts: &mesher::Options,
    stop: &AtomicBool,
) -> Result<(scene::Mesh, mesher::Stats)> {
    let cams: Vec<glam::DVec3> = model.views.iter().map(|v| v.camera.center()).collect();
    let tracks: Vec<Track> = model
        .points
        .iter()
        .map(|p| {
            let mut c: Vec<u32> = p.track.iter().map(|t| t.0).collect();
            c.sort_unstable();
            c.dedup();
            Track {
                xyz: p.xyz,
                cameras: c,
            }
        })
        .collect();
    let last = std::sync::Mutex::new(Instant::now());
    let progress = |stage: &str, done: usize, total: usize| {
        let mut l = last.lock().unwrap();
        if l.elapsed().as_secs_f64() >= 2.0 || done == total {
            say(format!("  {stage}: {done}/{total}"));
            *l = Instant::now();
        }
    };
    let stop_fn = || stop.load(std::sync::atomic::Ordering::SeqCst);
    let (mesh, mstats) = mesher::mesh(&tracks, &cams, opts, &progress, &stop_fn)?;
    say(format!(
        "  {} points ({} used), {} cells, {} lines of sight; {} triangles ({} long ones dropped)",
        mstats.points,
        mstats.points_used,
        mstats.cells,
        mstats.rays,
        mstats.triangles,
        mstats.dropped_long
    ));
    Ok((mesh, mstats))
}

/// The mapper's largest model in `dir` (subfolders 0, 1, …), noting when there are several.
fn largest_model(
    dir: &Path,
    images: &Path,
    photos: usize,
    notes: &mut Vec<String>,
) -> Result<PathBuf> {
    let mut models: Vec<(usize, PathBuf)> = std::fs::read_dir(dir)?
        .flatten()
        .map(|e| e.path())
        .filter(|p| colmap::is_model_dir(p))
        .map(|p| (colmap::load(&p, images).map(|v| v.len()).unwrap_or(0), p))
        .collect();
    models.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
    let Some((n, best)) = models.first().cloned() else {
        bail!(
            "COLMAP's mapper registered no model from the {photos} photos (too little overlap or texture?); its log is in {}",
            dir.parent().unwrap_or(dir).join("logs").join("sparse.log").display()
        );
    };
    if models.len() > 1 || n < photos {
        let msg = format!(
            "COLMAP's mapper registered {n} of {photos} photos{}",
            if models.len() > 1 {
                format!(
                    " in its largest of {} models; the others are left out",
                    models.len()
                )
            } else {
                String::new()
            }
        );
        say(format!("note: {msg}"));
        notes.push(msg);
    }
    Ok(best)
}

/// Share of each view's pixels whose ray meets the mesh, cast with xscale's ray caster at a
/// resolution at most 320 pixels wide.
fn hit_fractions(model: &Model, mesh: &scene::Mesh) -> Result<Vec<ViewReport>> {
    let norm = scene::Normalization::from_mesh(mesh, scene::NormalizeMode::PerAxis);
    let tracer = crate::raycast::Tracer::new(mesh, &norm)?;
    let mut out = Vec::new();
    for (i, v) in model.views.iter().enumerate() {
        let s = v.camera.width.div_ceil(320).max(1);
        let cam = v.camera.downsampled(s);
        let cast = crate::raycast::cast::cast_view(&tracer, &cam, 1)?;
        let hits = cast.pixels.iter().filter(|p| p.valid != 0).count();
        let observations = model
            .points
            .iter()
            .map(|p| p.track.iter().filter(|t| t.0 as usize == i).count())
            .sum();
        out.push(ViewReport {
            name: v.name.clone(),
            observations,
            hit: hits as f64 / cast.pixels.len().max(1) as f64,
        });
    }
    Ok(out)
}

/// What changed between two runs' inputs, for the refusal.
fn describe_change(a: &Inputs, b: &Inputs) -> String {
    let mut d = Vec::new();
    if a.photos != b.photos {
        d.push(format!(
            "photos: {} then, {} now",
            a.photos.len(),
            b.photos.len()
        ));
    }
    if a.poses != b.poses {
        d.push("--poses".into());
    }
    if a.sparse != b.sparse {
        d.push("--sparse".into());
    }
    if a.downsample != b.downsample {
        d.push(format!(
            "--downsample {} then, {} now",
            a.downsample, b.downsample
        ));
    }
    if a.matcher != b.matcher {
        d.push("--matcher".into());
    }
    if a.max_features != b.max_features {
        d.push("--max-features".into());
    }
    if a.undistort != b.undistort {
        d.push("--undistort".into());
    }
    d.join("; ")
}

/// A short text summary of a `prepare.json`.
pub fn summary_of_json(json: &str) -> String {
    let Ok(v) = serde_json::from_str::<serde_json::Value>(json) else {
        return String::new();
    };
    let f = |k: &str| v.get(k).and_then(|x| x.as_f64()).unwrap_or(f64::NAN);
    let mut s = format!(
        "views {}  points {}  reprojection error {:.3} px mean ({:.3} RMS, COLMAP's {:.3})  mesh {} triangles  pixels hitting the mesh {:.1} % (mean over views)",
        f("views"),
        f("points"),
        v["reprojection"]["mean"].as_f64().unwrap_or(f64::NAN),
        v["reprojection"]["rms"].as_f64().unwrap_or(f64::NAN),
        f("colmap_mean_error"),
        f("mesh_triangles"),
        100.0 * f("mean_hit")
    );
    if let Some(views) = v["per_view"].as_array() {
        let mut worst: Vec<(f64, String)> = views
            .iter()
            .map(|x| {
                (
                    x["hit"].as_f64().unwrap_or(0.0),
                    x["name"].as_str().unwrap_or("").to_string(),
                )
            })
            .collect();
        worst.sort_by(|a, b| a.0.total_cmp(&b.0));
        s += &format!(
            "\nfewest hits: {}",
            worst
                .iter()
                .take(3)
                .map(|(h, n)| format!("{n} {:.1} %", 100.0 * h))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    if let Some(secs) = v["seconds"].as_array() {
        s += "\nseconds per stage: ";
        s += &secs
            .iter()
            .filter_map(|x| Some(format!("{} {:.1}", x[0].as_str()?, x[1].as_f64()?)))
            .collect::<Vec<_>>()
            .join(", ");
    }
    s
}
