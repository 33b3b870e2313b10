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
pub const RUN_FILES: [&str; 15] = [
    "checkpoint.safetensors",
    "optimizer.safetensors",
    "optimizer.next.safetensors",
    "optimizer-diverged.safetensors",
    "optimizer-diverged.next.safetensors",
    TIME_FILE,
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

/// Holds `RUN/.lock` until dropped: the file holds our pid, and we hold an exclusive `flock` on
/// it, which the kernel releases when the process ends however it ends (so a lock nobody holds
/// is stale, whatever pid it names: a killed run's, or one since reused by another program).
pub struct RunLock {
    path: PathBuf,
    /// The lock file, open: its `flock` lasts as long as this does.
    _file: std::fs::File,
}

/// The locks this process holds, for [`release_locks`] (an abort exits without dropping them).
static HELD: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

/// Remove the `.lock` files this process holds: for an exit that skips destructors (a second
/// Ctrl-C aborting at once), so it never leaves a `.lock` behind.
pub fn release_locks() {
    if let Ok(held) = HELD.lock() {
        for p in held.iter() {
            let _ = std::fs::remove_file(p);
        }
    }
}

impl RunLock {
    /// The pid of a live process holding `run_dir`'s lock, if any.
    pub fn holder(run_dir: &Path) -> Option<u32> {
        let path = run_dir.join(".lock");
        let file = std::fs::File::open(&path).ok()?;
        live_holder(&file, &path)
    }

    /// Take the lock of `run_dir` (which must exist). Race-free: the lock file appears whole
    /// (written and locked under a temporary name, then hard-linked into place, which fails if
    /// a `.lock` exists), and a stale one is replaced by renaming ours over it while holding its
    /// `flock`, after checking it is still the file at `.lock` (so of two processes taking over
    /// the same stale lock, one wins and the other finds the winner's lock live).
    pub fn acquire(run_dir: &Path) -> Result<RunLock> {
        let path = run_dir.join(".lock");
        let cannot = |what: &str| format!("{}: cannot {what}", path.display());
        for _ in 0..20 {
            let (tmp, ours) = new_lock_file(run_dir)?;
            match std::fs::hard_link(&tmp, &path) {
                Ok(()) => {
                    let _ = std::fs::remove_file(&tmp);
                    return Ok(RunLock::held(path, ours));
                }
                // Removed by a run cleaning the folder's temp files: try again.
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
                Err(e) => {
                    let _ = std::fs::remove_file(&tmp);
                    return Err(e).with_context(|| cannot("create"));
                }
            }
            let theirs = match std::fs::File::open(&path) {
                Ok(f) => f,
                // Released meanwhile: try again.
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    let _ = std::fs::remove_file(&tmp);
                    continue;
                }
                Err(e) => {
                    let _ = std::fs::remove_file(&tmp);
                    return Err(e).with_context(|| cannot("open"));
                }
            };
            if let Some(p) = live_holder(&theirs, &path) {
                let _ = std::fs::remove_file(&tmp);
                bail!("{}", held_by(run_dir, p));
            }
            // Stale, and we hold its flock: replace it, unless it was replaced meanwhile.
            if !same_file(&theirs, &path) {
                let _ = std::fs::remove_file(&tmp);
                continue;
            }
            let renamed = std::fs::rename(&tmp, &path);
            drop(theirs);
            match renamed {
                Ok(()) => return Ok(RunLock::held(path, ours)),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => return Err(e).with_context(|| cannot("replace the stale lock")),
            }
        }
        bail!("{}: could not take the run lock", path.display())
    }

    fn held(path: PathBuf, file: std::fs::File) -> RunLock {
        if let Ok(mut held) = HELD.lock() {
            held.push(path.clone());
        }
        RunLock { path, _file: file }
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        if let Ok(mut held) = HELD.lock() {
            held.retain(|p| *p != self.path);
        }
        let _ = std::fs::remove_file(&self.path);
    }
}

/// The error of a run folder whose lock `pid` holds.
pub fn held_by(run_dir: &Path, pid: u32) -> String {
    format!(
        "{}: another xscale process (pid {pid}) is training into this run folder; wait for it, stop it, or choose another --out (if you are sure no xscale process trains there, remove {})",
        run_dir.display(),
        run_dir.join(".lock").display()
    )
}

/// A lock file for this process under a temporary name in `run_dir` (`.lock.tmp.PID.N`, a name
/// a run's start cleans up after a kill): our pid written, its `flock` held.
fn new_lock_file(run_dir: &Path) -> Result<(PathBuf, std::fs::File)> {
    use std::io::Write;
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = run_dir.join(format!(".lock.tmp.{}.{n}", std::process::id()));
    let written = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        writeln!(f, "{}", std::process::id())?;
        f.flush()?;
        if try_flock(&f)? {
            Ok(f)
        } else {
            Err(std::io::Error::other("a new file is locked"))
        }
    })();
    match written {
        Ok(f) => Ok((tmp, f)),
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            Err(e).with_context(|| format!("{}: cannot write", tmp.display()))
        }
    }
}

/// The pid of a live process holding the lock file `file` (open at `path`): one holding its
/// `flock`, or — for a lock without one (written by an xscale from before locks were
/// `flock`ed) — the live xscale process it names. A `None` leaves us holding the `flock`.
fn live_holder(file: &std::fs::File, path: &Path) -> Option<u32> {
    let pid: Option<u32> = std::fs::read_to_string(path)
        .ok()
        .and_then(|t| t.trim().parse().ok());
    let mine = |p: &u32| *p == std::process::id();
    match try_flock(file) {
        // Held (by another process, or by this one through another open file).
        Ok(false) => Some(pid.unwrap_or(0)),
        _ => pid.filter(|p| !mine(p) && process_alive(*p) && is_xscale(*p)),
    }
}

/// Take `f`'s exclusive `flock` without waiting: `Ok(false)` when another open file holds it.
/// (Without `flock`, not unix: always taken; liveness then rests on the pid alone.)
fn try_flock(f: &std::fs::File) -> std::io::Result<bool> {
    #[cfg(unix)]
    {
        use std::os::unix::io::AsRawFd;
        // SAFETY: flock on a file descriptor we own for the duration of the call.
        let r = unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if r == 0 {
            return Ok(true);
        }
        let e = std::io::Error::last_os_error();
        if e.raw_os_error() == Some(libc::EWOULDBLOCK) {
            return Ok(false);
        }
        Err(e)
    }
    #[cfg(not(unix))]
    {
        let _ = f;
        Ok(true)
    }
}

/// Whether the open `file` is the file now at `path` (not replaced or removed since it was
/// opened).
fn same_file(file: &std::fs::File, path: &Path) -> bool {
    match (file.metadata(), std::fs::metadata(path)) {
        (Ok(a), Ok(b)) => crate::io::atomic::same_identity(&a, &b).unwrap_or(true),
        _ => false,
    }
}

/// Whether process `pid` runs xscale (its command's file name starts with `xscale`, from
/// `/proc/<pid>/cmdline`). Where that cannot be read: no on unix, where the `flock` tells a live
/// run (so only a lock of an older build without one could be missed); yes elsewhere, where the
/// pid is all there is (a stale lock is then removed by hand, as the refusal says).
fn is_xscale(pid: u32) -> bool {
    match std::fs::read(Path::new("/proc").join(pid.to_string()).join("cmdline")) {
        Ok(cmd) => {
            let argv0 = cmd.split(|&b| b == 0).next().unwrap_or_default();
            Path::new(&*String::from_utf8_lossy(argv0))
                .file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("xscale"))
        }
        Err(_) => cfg!(not(unix)),
    }
}

/// Whether process `pid` is running (Linux: `/proc/<pid>/stat`; elsewhere assumed alive, so a
/// stale lock must be removed by hand). A killed process stays in `/proc` as a zombie (state `Z`)
/// until its parent reaps it, which can take a while when the parent is a shell that has
/// moved on: it counts as gone, or a run killed by SIGKILL would block the command that
/// continues it ("another xscale process (pid N) is training into this run folder").
pub fn process_alive(pid: u32) -> bool {
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

/// The folders of a run's images (`render/`, `eval/`): `--overwrite` removes the images in them
/// (and temp files), not other files a user put there.
const IMAGE_DIRS: [&str; 2] = ["render", "eval"];

/// Make `run_dir` ready for a run (call with the lock held): remove temp files left by killed
/// writes (also in `render/` and `eval/`), and refuse a folder that holds a run unless `resume`
/// (the caller then needs its checkpoint) or `overwrite`. Returns the earlier run's files that
/// the new run replaces — for [`remove_run`] once it is ready to start, so an error before that
/// (a bad scene, config or batch, a Ctrl-C during setup) leaves them as they were. A folder
/// whose run wrote no checkpoint (killed before its first) holds nothing worth keeping: it is
/// started afresh without `--overwrite`, with a line saying so.
pub fn prepare_run_dir(run_dir: &Path, resume: bool, overwrite: bool) -> Result<Vec<&'static str>> {
    if resume && overwrite {
        bail!("give either --resume or --overwrite, not both");
    }
    // Under the lock: every temp file here is a killed writer's.
    let all = |_: Option<u32>| true;
    let leftovers = crate::io::atomic::remove_temp_files(run_dir, false, &all)
        + IMAGE_DIRS
            .iter()
            .map(|d| crate::io::atomic::remove_temp_files(&run_dir.join(d), true, &all))
            .sum::<u64>();
    if leftovers > 0 {
        eprintln!(
            "removed temporary files left by an interrupted write ({:.1} MB)",
            leftovers as f64 / 1e6
        );
    }
    let existing: Vec<&str> = RUN_FILES
        .iter()
        .copied()
        .filter(|f| run_dir.join(f).exists())
        .collect();
    if resume || existing.is_empty() {
        return Ok(Vec::new());
    }
    if overwrite {
        return Ok(existing);
    }
    let resumable = run_dir.join("checkpoint.safetensors").is_file();
    // A diverged run's state is kept for a look, though it cannot be resumed.
    if !resumable && !run_dir.join("checkpoint-diverged.safetensors").is_file() {
        eprintln!(
            "{}: the run there wrote no checkpoint (it was stopped before its first): starting afresh in its place",
            run_dir.display()
        );
        return Ok(existing);
    }
    bail!(
        "{}: this folder already holds a run ({}); {}replace it with --overwrite, or choose another --out",
        run_dir.display(),
        existing.join(", "),
        if resumable {
            "continue it with --resume, "
        } else {
            ""
        }
    )
}

/// Remove an earlier run's files `names` from `run_dir` (what [`prepare_run_dir`] returned):
/// files and folders as [`remove_listed`], except `render/` and `eval/`, of which only the images
/// go (and the folders, when that empties them).
pub fn remove_run(run_dir: &Path, names: &[&str]) -> Result<()> {
    let (images, rest): (Vec<&str>, Vec<&str>) = names.iter().partition(|n| IMAGE_DIRS.contains(n));
    remove_listed(run_dir, &rest)?;
    for d in images {
        remove_images(&run_dir.join(d))?;
    }
    Ok(())
}

/// Remove the images (`.png`, `.exr`) in `dir` and below, then the folders left empty.
fn remove_images(dir: &Path) -> Result<()> {
    let list = std::fs::read_dir(dir).with_context(|| format!("{}: cannot list", dir.display()))?;
    for e in list.flatten() {
        let p = e.path();
        let image = p
            .extension()
            .is_some_and(|x| x.eq_ignore_ascii_case("png") || x.eq_ignore_ascii_case("exr"));
        if e.file_type().is_ok_and(|t| t.is_dir()) {
            remove_images(&p)?;
        } else if image {
            std::fs::remove_file(&p)
                .with_context(|| format!("{}: cannot remove (--overwrite)", p.display()))?;
        }
    }
    // Kept when it holds other files.
    let _ = std::fs::remove_dir(dir);
    Ok(())
}

/// The run's training time when its checkpoint was written, `{"step": K, "elapsed_s": T}`
/// ([`crate::run::report::elapsed_at`]). Not in the checkpoint, whose bytes must not depend on
/// wall time (a resumed run writes the same bytes as one never stopped), nor only in
/// `metrics.jsonl`, a log a user may trim or delete (the resumed run's time then restarted at
/// 0).
pub const TIME_FILE: &str = "checkpoint-time.json";

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

/// `RUN/checkpoint.safetensors` of a run folder.
pub fn run_checkpoint(run: &Path) -> PathBuf {
    run.join("checkpoint.safetensors")
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

    /// A lock held by a live run (here: this process, through another open file) is refused
    /// and named; one whose pid is a live process that is no xscale (`sleep`, standing for a
    /// killed run's pid reused), or a killed process its parent has not reaped yet (a zombie,
    /// as after `kill -9` of a job a shell started with `&`), is taken over. (A live pid used
    /// to hold the folder whatever it ran.)
    #[cfg(target_os = "linux")]
    #[test]
    fn only_a_live_xscale_run_holds_the_lock() {
        let dir = std::env::temp_dir().join(format!("xscale-lock-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let held = RunLock::acquire(&dir).unwrap();
        let e = RunLock::acquire(&dir)
            .err()
            .expect("a live holder is refused");
        let e = format!("{e:#}");
        assert!(
            e.contains(&format!(
                "another xscale process (pid {})",
                std::process::id()
            )),
            "{e}"
        );
        assert_eq!(RunLock::holder(&dir), Some(std::process::id()));
        drop(held);
        assert!(!dir.join(".lock").exists() && RunLock::holder(&dir).is_none());
        let lock_of = |pid: u32| std::fs::write(dir.join(".lock"), format!("{pid}\n")).unwrap();
        let mut live = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        lock_of(live.id());
        drop(RunLock::acquire(&dir).expect("a live process that is no xscale holds no lock"));
        lock_of(live.id());
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

    /// Takers racing for a free folder, or for one whose lock is stale, never both get it, and
    /// never see a lock file without its pid. (Creating the file and writing the pid afterwards
    /// let a second process read it empty, call it stale and take it too.)
    #[cfg(unix)]
    #[test]
    fn racing_takers_never_share_the_lock() {
        let dir = std::env::temp_dir().join(format!("xscale-lock-race-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for round in 0..40 {
            if round % 2 == 1 {
                std::fs::write(dir.join(".lock"), "4000000000\n").unwrap();
            }
            let barrier = std::sync::Barrier::new(6);
            let won = std::sync::atomic::AtomicUsize::new(0);
            std::thread::scope(|s| {
                for _ in 0..6 {
                    s.spawn(|| {
                        barrier.wait();
                        if let Ok(lock) = RunLock::acquire(&dir) {
                            won.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                            let pid = std::fs::read_to_string(dir.join(".lock")).unwrap();
                            assert_eq!(pid.trim(), std::process::id().to_string());
                            // Held until every taker has tried.
                            barrier.wait();
                            drop(lock);
                        } else {
                            barrier.wait();
                        }
                    });
                }
            });
            assert_eq!(won.into_inner(), 1, "round {round}");
            assert!(!dir.join(".lock").exists());
        }
        let left: Vec<_> = std::fs::read_dir(&dir).unwrap().flatten().collect();
        assert!(left.is_empty(), "{left:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
