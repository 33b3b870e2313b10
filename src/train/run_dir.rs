//! A run folder's protection and identity (docs/runs.md):
//! - [`RunLock`]: `RUN/.lock` holds the training process's pid while it runs, so two runs
//!   into one folder cannot both proceed (a lock whose process is gone is taken over).
//! - [`prepare_run_dir`]: a folder that already holds a run is refused unless the caller
//!   resumes it or asks to overwrite it; leftover temporary checkpoint files are removed.
//! - [`SceneFingerprint`]: hashes of the cameras (names, sizes, intrinsics, poses), the split and
//!   the mesh, stored in `RUN/scene.json` with the scene's path, so a resume on another scene is
//!   an error and `eval`/`render --run` can find the scene.
//! - [`Existing`]: what a command that fills an output folder (`bench-quality`, `ablate`) does
//!   with the results an earlier run left there.
//! - [`stopped_run_of`]: a run folder a tool trains (`ablate`, `bench-geometry`) is continued
//!   when it holds the same settings' run stopped halfway, else started afresh.

use crate::scene::Scene;
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Files and folders a run writes (what `--overwrite` removes; nothing else is touched).
pub const RUN_FILES: [&str; 10] = [
    "checkpoint.safetensors",
    "checkpoint-diverged.safetensors",
    "metrics.jsonl",
    "config.toml",
    "eval.json",
    "scene.json",
    "render",
    "eval",
    "refined.ply",
    // A tool's settings for the run (`stopped_run_of`): replaced with the run it describes.
    SETTINGS_FILE,
];

/// What to do with the results an earlier run left in an output folder (`bench-quality`'s
/// `bench.csv`, `ablate`'s `ablation.json`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Existing {
    /// Refuse to start (the default: earlier results are not thrown away unasked).
    #[default]
    Refuse,
    /// Keep them, except those of what this run does again (a configuration or variant run
    /// again replaces its earlier results, e.g. one cut short by Ctrl-C), and report them all.
    Append,
    /// Start afresh.
    Overwrite,
}

impl Existing {
    /// From a command's `--append` / `--overwrite` flags (clap keeps them exclusive).
    pub fn from_flags(append: bool, overwrite: bool) -> Existing {
        match (append, overwrite) {
            (true, _) => Existing::Append,
            (_, true) => Existing::Overwrite,
            _ => Existing::Refuse,
        }
    }
}

/// Holds `RUN/.lock` (our pid) until dropped.
pub struct RunLock {
    path: PathBuf,
}

impl RunLock {
    /// The pid of a live process holding `run_dir`'s lock, if any.
    pub fn holder(run_dir: &Path) -> Option<u32> {
        let text = std::fs::read_to_string(run_dir.join(".lock")).ok()?;
        text.trim()
            .parse()
            .ok()
            .filter(|&p| p != std::process::id() && process_alive(p))
    }

    /// Take the lock of `run_dir` (which must exist).
    pub fn acquire(run_dir: &Path) -> Result<RunLock> {
        let path = run_dir.join(".lock");
        for _ in 0..2 {
            match std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&path)
            {
                Ok(mut f) => {
                    use std::io::Write;
                    writeln!(f, "{}", std::process::id())
                        .with_context(|| format!("{}: cannot write", path.display()))?;
                    return Ok(RunLock { path });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let text = std::fs::read_to_string(&path).unwrap_or_default();
                    let pid: Option<u32> = text.trim().parse().ok();
                    if let Some(p) = pid.filter(|&p| process_alive(p)) {
                        bail!(
                            "{}: another xscale process (pid {p}) is training into this run folder; wait for it, stop it, or choose another --out",
                            run_dir.display()
                        );
                    }
                    // Stale: its process is gone (killed). Take it over.
                    std::fs::remove_file(&path)
                        .with_context(|| format!("{}: cannot remove stale lock", path.display()))?;
                }
                Err(e) => {
                    return Err(e).with_context(|| format!("{}: cannot create", path.display()))
                }
            }
        }
        bail!("{}: could not take the run lock", path.display())
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Whether process `pid` is running (Linux: `/proc/<pid>/stat`; elsewhere assumed alive, so a
/// stale lock must be removed by hand). A killed process stays in `/proc` as a zombie (state `Z`)
/// until its parent reaps it, which can take a while when the parent is a shell that has
/// moved on: it counts as gone, or a run killed by SIGKILL would block the command that
/// continues it ("another xscale process (pid N) is training into this run folder").
fn process_alive(pid: u32) -> bool {
    let proc = Path::new("/proc");
    if !proc.is_dir() {
        return true;
    }
    if pid == std::process::id() {
        return true;
    }
    match std::fs::read_to_string(proc.join(pid.to_string()).join("stat")) {
        Ok(stat) => !matches!(stat_state(&stat), Some('Z' | 'X' | 'x')),
        Err(_) => false,
    }
}

/// The state letter of a `/proc/<pid>/stat` line: the first field after the command name, which
/// is in parentheses and may itself hold spaces and parentheses (so: after the last `)`).
fn stat_state(stat: &str) -> Option<char> {
    stat[stat.rfind(')')? + 1..].trim_start().chars().next()
}

/// Make `run_dir` ready for a run: create it; refuse one that holds a run unless `resume`
/// (then it must hold a checkpoint) or `overwrite` (then the run's files are removed); remove
/// temporary checkpoint files left by killed runs. Call with the lock held.
pub fn prepare_run_dir(run_dir: &Path, resume: bool, overwrite: bool) -> Result<()> {
    if resume && overwrite {
        bail!("give either --resume or --overwrite, not both");
    }
    let mut leftovers = 0u64;
    for e in std::fs::read_dir(run_dir)
        .with_context(|| format!("{}: cannot list", run_dir.display()))?
        .flatten()
    {
        let name = e.file_name().to_string_lossy().to_string();
        if crate::io::atomic::is_temp_name(&name) {
            leftovers += e.metadata().map(|m| m.len()).unwrap_or(0);
            let _ = std::fs::remove_file(e.path());
        }
    }
    if leftovers > 0 {
        eprintln!(
            "removed temporary checkpoint files left by an interrupted write ({:.1} MB)",
            leftovers as f64 / 1e6
        );
    }
    let existing: Vec<&str> = RUN_FILES
        .iter()
        .copied()
        .filter(|f| run_dir.join(f).exists())
        .collect();
    if resume || existing.is_empty() {
        return Ok(());
    }
    if !overwrite {
        bail!(
            "{}: this folder already holds a run ({}); continue it with --resume, replace it with --overwrite, or choose another --out",
            run_dir.display(),
            existing.join(", ")
        );
    }
    remove_listed(run_dir, &existing)
}

/// The settings a tool that trains run folders itself (`ablate`, `bench-geometry`) started a
/// run with: its unresolved configuration ([`crate::train::config::RunConfig::results_toml`]),
/// written by the trainer when the run starts (`TrainOptions::settings`). Listed in
/// [`RUN_FILES`], so it goes with the run it describes.
pub const SETTINGS_FILE: &str = "variant.toml";

/// Whether `run_dir` holds a run a tool started with exactly the settings `cfg` (its checkpoint
/// interval aside) that stopped before its last step (Ctrl-C, SIGTERM, a kill after a periodic
/// checkpoint), or at its last step before its final evaluation wrote `eval.json`: the tool then
/// trains it with `resume`, which gives the bits of an uninterrupted run (and, at the last step,
/// only evaluates). A finished and evaluated run, or one of other settings, is not (the tool
/// trains afresh, replacing it).
pub fn stopped_run_of(run_dir: &Path, cfg: &crate::train::config::RunConfig) -> bool {
    std::fs::read_to_string(run_dir.join(SETTINGS_FILE)).is_ok_and(|t| t == cfg.results_toml())
        && checkpoint_step(&run_dir.join("checkpoint.safetensors")).is_some_and(|k| {
            k < cfg.train.steps || (k == cfg.train.steps && !run_dir.join("eval.json").is_file())
        })
}

/// The step a training checkpoint holds, from its header alone (no tensor is read); `None` when
/// the file is missing or unreadable.
pub fn checkpoint_step(ckpt: &Path) -> Option<u64> {
    let f = crate::io::tensors::TensorFile::read_only(ckpt, |_| false).ok()?;
    f.meta("step").ok()?.parse().ok()
}

/// Remove the files and folders of `dir` named in `names` that exist (what `--overwrite`
/// replaces); nothing else in `dir` is touched.
pub fn remove_listed(dir: &Path, names: &[&str]) -> Result<()> {
    for name in names {
        let p = dir.join(name);
        let r = if p.is_dir() {
            std::fs::remove_dir_all(&p)
        } else if p.exists() {
            std::fs::remove_file(&p)
        } else {
            Ok(())
        };
        r.with_context(|| format!("{}: cannot remove (--overwrite)", p.display()))?;
    }
    Ok(())
}

/// `RUN/scene.json`: where the scene was and what it held.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SceneFingerprint {
    /// The scene directory (absolute when it could be resolved).
    pub scene: PathBuf,
    /// Hash of every view's name, image size, intrinsics, distortion and pose (hex).
    pub cameras: String,
    /// Hash of the held-out view indices.
    pub split: String,
    /// Hash of the mesh's vertices and triangles.
    pub mesh: String,
}

/// 64-bit FNV-1a, fed with exact bit patterns (so any change of any value changes the hash
/// with overwhelming probability; not a cryptographic hash).
struct Fnv(u64);

impl Fnv {
    fn new() -> Fnv {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
    fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 = (self.0 ^ x as u64).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    fn f64(&mut self, x: f64) {
        self.bytes(&x.to_bits().to_le_bytes());
    }
    fn u64(&mut self, x: u64) {
        self.bytes(&x.to_le_bytes());
    }
    fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }
}

impl SceneFingerprint {
    /// The fingerprint of a loaded scene (cameras after downsampling, as trained on).
    pub fn of(dir: &Path, scene: &Scene) -> SceneFingerprint {
        let mut cams = Fnv::new();
        for v in &scene.views {
            cams.bytes(v.name.as_bytes());
            cams.u64(0xff);
            let c = &v.camera;
            cams.u64(c.width as u64);
            cams.u64(c.height as u64);
            for x in [c.fx, c.fy, c.cx, c.cy] {
                cams.f64(x);
            }
            cams.bytes(format!("{:?}", c.distortion).as_bytes());
            for x in c.rotation.to_cols_array() {
                cams.f64(x);
            }
            for x in c.translation.to_array() {
                cams.f64(x);
            }
        }
        let mut split = Fnv::new();
        for &t in &scene.test {
            split.u64(t as u64);
        }
        let mut mesh = Fnv::new();
        mesh.u64(scene.mesh.vertices.len() as u64);
        for v in &scene.mesh.vertices {
            for x in v.to_array() {
                mesh.f64(x);
            }
        }
        for t in &scene.mesh.triangles {
            for &i in t {
                mesh.u64(i as u64);
            }
        }
        SceneFingerprint {
            scene: std::fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf()),
            cameras: cams.hex(),
            split: split.hex(),
            mesh: mesh.hex(),
        }
    }

    pub fn path(run_dir: &Path) -> PathBuf {
        run_dir.join("scene.json")
    }

    /// `RUN/scene.json`, `None` if the run has none (made before fingerprints existed).
    pub fn read(run_dir: &Path) -> Result<Option<SceneFingerprint>> {
        let p = SceneFingerprint::path(run_dir);
        if !p.is_file() {
            return Ok(None);
        }
        let text =
            std::fs::read_to_string(&p).with_context(|| format!("{}: cannot read", p.display()))?;
        Ok(Some(serde_json::from_str(&text).with_context(|| {
            format!("{}: not a scene fingerprint", p.display())
        })?))
    }

    pub fn write(&self, run_dir: &Path) -> Result<()> {
        let p = SceneFingerprint::path(run_dir);
        crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(self)?)
    }

    /// What differs between this fingerprint and `now`: `"cameras"`, `"train/test split"`,
    /// `"mesh"`, in that order.
    pub fn changed(&self, now: &SceneFingerprint) -> Vec<&'static str> {
        [
            (self.cameras != now.cameras, "cameras"),
            (self.split != now.split, "train/test split"),
            (self.mesh != now.mesh, "mesh"),
        ]
        .into_iter()
        .filter_map(|(differs, what)| differs.then_some(what))
        .collect()
    }

    /// An error naming what differs when `now` is not the scene this run was trained on.
    pub fn check_same(&self, now: &SceneFingerprint) -> Result<()> {
        let diff = self.changed(now);
        if !diff.is_empty() {
            // Since 2026-11-27 a transforms.json's applied_transform is undone: a run trained on
            // one before reads its cameras in another frame now.
            let applied = diff.contains(&"cameras")
                && std::fs::read_to_string(now.scene.join("transforms.json"))
                    .is_ok_and(|t| t.contains("\"applied_transform\""));
            bail!(
                "--resume: the scene {} differs from the one this run was trained on ({}): its {} changed; resume on the same scene, or start a new run{}",
                now.scene.display(),
                self.scene.display(),
                diff.join(" and "),
                if applied {
                    " (its transforms.json has an applied_transform, which xscale undoes since 2026-11-27: for a run trained before, set applied_transform = \"keep\" in scene.toml)"
                } else {
                    ""
                }
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stat_state_is_read_after_the_command_name() {
        assert_eq!(stat_state("42 (xscale) R 1 42 42 0"), Some('R'));
        assert_eq!(stat_state("42 (a) b) (c) Z 1 42"), Some('Z'));
        assert_eq!(stat_state("42 (xscale"), None);
    }

    /// A lock held by a live process is refused; one held by a killed process that its parent
    /// has not reaped yet (a zombie, as after `kill -9` of a job a shell started with `&`) is
    /// taken over.
    #[cfg(target_os = "linux")]
    #[test]
    fn a_zombie_does_not_hold_the_lock() {
        let dir = std::env::temp_dir().join(format!("xscale-lock-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let lock_of = |pid: u32| std::fs::write(dir.join(".lock"), format!("{pid}\n")).unwrap();
        let mut live = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        lock_of(live.id());
        let e = RunLock::acquire(&dir)
            .err()
            .expect("a live holder is refused");
        assert!(format!("{e:#}").contains("another xscale process"), "{e:#}");
        live.kill().unwrap();
        // Not reaped yet: a zombie.
        let t0 = std::time::Instant::now();
        let stat = Path::new("/proc").join(live.id().to_string()).join("stat");
        while stat_state(&std::fs::read_to_string(&stat).unwrap()) != Some('Z') {
            assert!(t0.elapsed().as_secs() < 10, "never became a zombie");
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        let lock = RunLock::acquire(&dir).expect("a zombie's lock is taken over");
        assert_eq!(
            std::fs::read_to_string(dir.join(".lock")).unwrap().trim(),
            std::process::id().to_string()
        );
        drop(lock);
        live.wait().unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }
}
