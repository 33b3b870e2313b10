//! Files that are whole or absent: written to a temp file next to the target, then renamed over it,
//! so a crash, a kill or a full disk mid-write never leaves a truncated checkpoint, render or dump.
//!
//! What the user named is what gets written: a symlink is followed and the file it points to is
//! replaced (the link stays a link); a FIFO, a character or block device or any other file that
//! is not a regular file is written through directly (no temp file, no rename: renaming over it
//! would replace the pipe or device by a regular file), and a failed write there is an error.

use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};

/// Where a write to a path lands.
#[derive(Debug, PartialEq)]
enum Target {
    /// A regular file, or none yet: written to a temp file in its folder and renamed over it.
    Replace(PathBuf),
    /// A FIFO, a device, a socket: opened and written in place.
    Through(PathBuf),
}

/// Where writing `path` lands: symlinks followed to the file they name (which need not exist
/// yet), then [`Target::Replace`] for a regular file or nothing, [`Target::Through`] for anything
/// else but a folder (an error).
fn target(path: &Path) -> Result<Target> {
    let mut p = path.to_path_buf();
    // As the kernel's own limit on links followed in one lookup (ELOOP).
    for _ in 0..40 {
        let meta = match std::fs::symlink_metadata(&p) {
            Ok(m) => m,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Target::Replace(p)),
            Err(e) => return Err(e).with_context(|| format!("{}: cannot write", path.display())),
        };
        let kind = meta.file_type();
        if kind.is_symlink() {
            let to = std::fs::read_link(&p)
                .with_context(|| format!("{}: cannot read the link", p.display()))?;
            p = match p.parent() {
                Some(d) if to.is_relative() => d.join(to),
                _ => to,
            };
        } else if kind.is_file() {
            return Ok(Target::Replace(p));
        } else if kind.is_dir() {
            bail!("{}: is a folder, not a file", path.display());
        } else {
            return Ok(Target::Through(p));
        }
    }
    bail!(
        "{}: cannot write: too many levels of symbolic links",
        path.display()
    )
}

/// The folder a file `path` will be written into, if it exists (an error naming the user's
/// path otherwise); for a symlink, the folder of the file it points to. Commands call it before
/// their work, so a typo in an output path costs no computation; [`write_atomic`] calls it again.
pub fn writable_folder(path: &Path) -> Result<PathBuf> {
    if path.file_name().is_none() {
        bail!("{}: not a file path", path.display());
    }
    match target(path)? {
        Target::Replace(p) => folder_of(path, &p),
        Target::Through(p) => Ok(p.parent().map_or(PathBuf::from("."), Path::to_path_buf)),
    }
}

/// The folder `file` (`path`, or the file its links point to) is in, which must exist.
fn folder_of(path: &Path, file: &Path) -> Result<PathBuf> {
    let dir = match file.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if file.file_name().is_none() {
        bail!("{}: not a file path", path.display());
    }
    // Said here, naming the user's path: the temp file's "cannot create" would name only itself.
    if !dir.is_dir() {
        bail!(
            "{}: cannot write: the folder {} does not exist",
            path.display(),
            dir.display()
        );
    }
    Ok(dir)
}

/// Refuse an output path that is one of the command's inputs (the same file: by device and
/// inode on Unix, so a link, a hard link or another spelling of the path counts too): writing it
/// would replace the input the command read. Checked before the work, so nothing is written.
/// `inputs` are `(what, path)`, `what` a phrase such as `the input mesh (--in)`; `out_flag` names
/// the output's flag. (`decimate --in m.ply --out m.ply` and `dump --out` onto its checkpoint
/// used to replace their input silently.)
pub fn not_an_input(out: &Path, out_flag: &str, inputs: &[(&str, &Path)]) -> Result<()> {
    for (what, input) in inputs {
        if same_file(out, input) {
            bail!(
                "{}: {out_flag} is {what} (the same file as {}): writing it would replace the command's own input; write to another file",
                out.display(),
                input.display()
            );
        }
    }
    Ok(())
}

/// Whether `a` and `b` name one existing file (through links, other spellings of the path, hard
/// links).
pub fn same_file(a: &Path, b: &Path) -> bool {
    let (Ok(ma), Ok(mb)) = (std::fs::metadata(a), std::fs::metadata(b)) else {
        return false;
    };
    same_identity(&ma, &mb)
        .unwrap_or_else(|| matches!((a.canonicalize(), b.canonicalize()), (Ok(x), Ok(y)) if x == y))
}

/// Whether two files' metadata are of one file (device and inode); `None` where the system
/// gives no such identity (not unix).
pub fn same_identity(a: &std::fs::Metadata, b: &std::fs::Metadata) -> Option<bool> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        Some((a.dev(), a.ino()) == (b.dev(), b.ino()))
    }
    #[cfg(not(unix))]
    {
        let _ = (a, b);
        None
    }
}

/// Write `path` through `write`, which must write the whole file at the temp path it is given:
/// on success the temp file (`.NAME.tmp.PID.N` in the same directory, so the rename stays on one
/// file system) is renamed over `path`; on error it is removed and `path` is untouched. `durable`
/// also fsyncs the file before the rename and the directory after it (checkpoints); without it
/// the file is still whole or absent, but may be lost by a power cut (images, which a rerun
/// recreates). A symlink `path` is followed: the file it points to is replaced, the link kept; a
/// FIFO or device is written through by `write` itself (module docs).
pub fn write_atomic(
    path: &Path,
    durable: bool,
    write: impl FnOnce(&Path) -> Result<()>,
) -> Result<()> {
    if path.file_name().is_none() {
        bail!("{}: not a file path", path.display());
    }
    let file = match target(path)? {
        Target::Replace(file) => file,
        // Nothing to rename over and nothing to fsync (a pipe cannot be; a device need not).
        Target::Through(file) => return write(&file),
    };
    let dir = folder_of(path, &file)?;
    let fname = file.file_name().expect("checked by folder_of");
    // Unique per process and per call, so concurrent writers never share a temp file.
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let tmp = dir.join(format!(
        ".{}.tmp.{}.{}",
        fname.to_string_lossy(),
        std::process::id(),
        COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed)
    ));
    let result = (|| -> Result<()> {
        write(&tmp)?;
        if durable {
            std::fs::File::open(&tmp)
                .and_then(|f| f.sync_all())
                .with_context(|| format!("{}: fsync failed", tmp.display()))?;
        }
        std::fs::rename(&tmp, &file).with_context(|| {
            format!(
                "{}: cannot rename {} over it",
                path.display(),
                tmp.display()
            )
        })
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
        return result;
    }
    if durable {
        sync_dir(&dir);
    }
    Ok(())
}

/// Persist a rename in folder `dir` (best effort: not every platform can fsync a directory).
fn sync_dir(dir: &Path) {
    #[cfg(unix)]
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
    #[cfg(not(unix))]
    let _ = dir;
}

/// Rename `from` over `to` and persist the rename (the folder fsynced, as [`write_atomic`]
/// does): the commit of a write spread over two files (`train/state.rs`: a run's optimizer
/// state after its model).
pub fn rename_durable(from: &Path, to: &Path) -> Result<()> {
    std::fs::rename(from, to)
        .with_context(|| format!("{}: cannot rename {} over it", to.display(), from.display()))?;
    let dir = match to.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    sync_dir(dir);
    Ok(())
}

/// Write `data` to `path`, whole or not at all (not durable: see [`write_atomic`]).
pub fn write_bytes(path: &Path, data: impl AsRef<[u8]>) -> Result<()> {
    write_atomic(path, false, |tmp| {
        std::fs::write(tmp, data.as_ref())
            .with_context(|| format!("{}: cannot write", path.display()))
    })
}

/// Whether `name` is a temp file [`write_atomic`] leaves behind when its process is killed.
pub fn is_temp_name(name: &str) -> bool {
    name.starts_with('.') && name.contains(".tmp.")
}

/// Remove the temp files [`write_atomic`] left in `dir` — and with `deep` in every folder below it —
/// for which `stale` holds (given the pid in the name, `.NAME.tmp.PID.N`, if it has one); their
/// bytes. A folder that cannot be listed (or does not exist) holds none.
pub fn remove_temp_files(dir: &Path, deep: bool, stale: &dyn Fn(Option<u32>) -> bool) -> u64 {
    let Ok(list) = std::fs::read_dir(dir) else {
        return 0;
    };
    let mut bytes = 0;
    for e in list.flatten() {
        let Ok(kind) = e.file_type() else { continue };
        let name = e.file_name().to_string_lossy().to_string();
        if kind.is_dir() && deep {
            bytes += remove_temp_files(&e.path(), deep, stale);
        } else if kind.is_file() && is_temp_name(&name) && stale(temp_pid(&name)) {
            bytes += e.metadata().map(|m| m.len()).unwrap_or(0);
            let _ = std::fs::remove_file(e.path());
        }
    }
    bytes
}

/// The pid of the process that made the temp file `name` (`.NAME.tmp.PID.N`).
fn temp_pid(name: &str) -> Option<u32> {
    let rest = &name[name.rfind(".tmp.")? + 5..];
    rest.split('.').next()?.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_write_leaves_the_old_file_and_no_temp() {
        let dir = std::env::temp_dir().join(format!("xscale-atomic-img-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("0000.png");
        std::fs::write(&p, b"old").unwrap();
        let err = write_atomic(&p, false, |tmp| {
            std::fs::write(tmp, b"half")?;
            anyhow::bail!("disk full")
        })
        .unwrap_err();
        assert!(format!("{err:#}").contains("disk full"));
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        write_atomic(&p, false, |tmp| Ok(std::fs::write(tmp, b"new")?)).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new");
        let names: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, vec!["0000.png".to_string()]);
        assert!(is_temp_name(".0000.png.tmp.12.0") && !is_temp_name("0000.png"));
        assert_eq!(temp_pid(".a.tmp.b.png.tmp.12.0"), Some(12));
        let absent = dir.join("no-such-folder").join("dump.safetensors");
        let err = format!("{:#}", write_bytes(&absent, b"x").unwrap_err());
        assert!(
            err.contains("dump.safetensors: cannot write: the folder")
                && err.contains("does not exist"),
            "{err}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A symlink is followed (the file it points to replaced, also one not there yet, the link
    /// kept); a FIFO is written through, not replaced by a regular file, and a write it refuses
    /// is an error. (Each used to be replaced by a regular file at the link's or FIFO's path.)
    #[cfg(unix)]
    #[test]
    fn links_are_followed_and_fifos_written_through() {
        let dir = std::env::temp_dir().join(format!("xscale-atomic-link-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        let (file, link) = (dir.join("sub/target.json"), dir.join("link.json"));
        std::fs::write(&file, b"old").unwrap();
        std::os::unix::fs::symlink("sub/target.json", &link).unwrap();
        write_bytes(&link, b"new").unwrap();
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::read(&file).unwrap(), b"new");
        // A link to a link to a file not there yet: the file is made where the links end.
        let link2 = dir.join("link2.json");
        std::os::unix::fs::symlink(dir.join("sub/dangling.json"), dir.join("sub/dangling"))
            .unwrap();
        std::os::unix::fs::symlink("sub/dangling", &link2).unwrap();
        write_bytes(&link2, b"x").unwrap();
        assert_eq!(std::fs::read(dir.join("sub/dangling.json")).unwrap(), b"x");
        // A link into a folder that does not exist names the user's path.
        let bad = dir.join("bad.json");
        std::os::unix::fs::symlink("no-such/t.json", &bad).unwrap();
        let err = format!("{:#}", writable_folder(&bad).unwrap_err());
        assert!(err.contains("bad.json: cannot write: the folder"), "{err}");
        // A FIFO: its reader gets the bytes; it stays a FIFO.
        let fifo = dir.join("fifo");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let reader = {
            let fifo = fifo.clone();
            std::thread::spawn(move || std::fs::read(fifo).unwrap())
        };
        write_bytes(&fifo, b"through").unwrap();
        assert_eq!(reader.join().unwrap(), b"through");
        use std::os::unix::fs::FileTypeExt;
        assert!(std::fs::symlink_metadata(&fifo)
            .unwrap()
            .file_type()
            .is_fifo());
        // A reader that goes away: the write fails (EPIPE), an error, not a silent success.
        let reader = {
            let fifo = fifo.clone();
            std::thread::spawn(move || drop(std::fs::File::open(fifo).unwrap()))
        };
        let err = write_bytes(&fifo, vec![0u8; 4 << 20]).unwrap_err();
        reader.join().unwrap();
        assert!(format!("{err:#}").contains("fifo: cannot write"), "{err:#}");
        assert!(std::fs::symlink_metadata(&fifo)
            .unwrap()
            .file_type()
            .is_fifo());
        // A folder is not a file.
        let err = format!("{:#}", write_bytes(&dir.join("sub"), b"x").unwrap_err());
        assert!(err.contains("is a folder"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
