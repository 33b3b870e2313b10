//! Files that are whole or absent: written to a temp file next to the target, then renamed over it,
//! so a crash, a kill or a full disk mid-write never leaves a truncated checkpoint, render or dump.

use anyhow::{bail, Context, Result};
use std::path::{Path, PathBuf};

/// The folder a file `path` will be written into, if it exists (an error naming the user's
/// path otherwise). Commands call it before their work, so a typo in an output path costs no
/// computation; [`write_atomic`] calls it again.
pub fn writable_folder(path: &Path) -> Result<PathBuf> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if path.file_name().is_none() {
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
/// inode on Unix, so a hard link or another spelling of the path counts too): writing it would
/// replace the input the command read. `inputs` are `(what, flag, path)`, e.g.
/// `("checkpoint", "--checkpoint", path)`; `out_flag` names the output's flag.
pub fn not_an_input(out: &Path, out_flag: &str, inputs: &[(&str, &str, &Path)]) -> Result<()> {
    for (what, flag, input) in inputs {
        if same_file(out, input) {
            bail!(
                "{}: {out_flag} is the {what} ({flag}, the same file): writing it would replace the command's own input; write to another file",
                out.display()
            );
        }
    }
    Ok(())
}

/// Whether `a` and `b` name one existing file.
fn same_file(a: &Path, b: &Path) -> bool {
    let (Ok(ma), Ok(mb)) = (std::fs::metadata(a), std::fs::metadata(b)) else {
        return false;
    };
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        ma.dev() == mb.dev() && ma.ino() == mb.ino()
    }
    #[cfg(not(unix))]
    {
        let _ = (ma, mb);
        matches!((a.canonicalize(), b.canonicalize()), (Ok(x), Ok(y)) if x == y)
    }
}

/// Write `path` through `write`, which must write the whole file at the temp path it is given:
/// on success the temp file (`.NAME.tmp.PID.N` in the same directory, so the rename stays on one
/// file system) is renamed over `path`; on error it is removed and `path` is untouched. `durable`
/// also fsyncs the file before the rename and the directory after it (checkpoints); without it
/// the file is still whole or absent, but may be lost by a power cut (images, which a rerun
/// recreates).
pub fn write_atomic(
    path: &Path,
    durable: bool,
    write: impl FnOnce(&Path) -> Result<()>,
) -> Result<()> {
    let dir = writable_folder(path)?;
    let fname = path.file_name().expect("checked by writable_folder");
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
        std::fs::rename(&tmp, path).with_context(|| {
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
    // Persist the rename itself (best effort: not every platform can fsync a directory).
    #[cfg(unix)]
    if durable {
        if let Ok(d) = std::fs::File::open(&dir) {
            let _ = d.sync_all();
        }
    }
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
}
