//! A command that fails leaves no empty output folder behind: `train --scene /nonexistent --out
//! runs/x` used to leave `runs/x` (and `runs/`) created and empty, which the next command then
//! had to be pointed around. The folders an output path would create are noted before the command
//! runs; if it then fails (an error, or a stop with nothing saved), those of them that are empty
//! are removed again, deepest first. A folder that existed before, or that holds anything, stays.

use std::path::{Path, PathBuf};

/// The folders of an output path that do not exist yet, deepest first.
pub struct Created {
    dirs: Vec<PathBuf>,
}

impl Created {
    /// Note which of `out` and its ancestors do not exist now.
    pub fn before(out: &Path) -> Created {
        let mut dirs = Vec::new();
        let mut p = Some(out);
        while let Some(d) = p {
            if d.as_os_str().is_empty() || d.exists() {
                break;
            }
            dirs.push(d.to_path_buf());
            p = d.parent();
        }
        Created { dirs }
    }

    /// After a failure: remove the noted folders that are empty, deepest first, stopping at the
    /// first that is not (`remove_dir` never removes a folder that holds anything). `no_work`
    /// names files a command writes before its first result (e.g. `bench-quality`'s header-only
    /// `bench.csv`); it is asked about the deepest folder only and removes what it returns.
    pub fn clean_up(&self, no_work: &dyn Fn(&Path) -> Vec<PathBuf>) {
        if let Some(out) = self.dirs.first() {
            for f in no_work(out) {
                let _ = std::fs::remove_file(f);
            }
        }
        for d in &self.dirs {
            if std::fs::remove_dir(d).is_err() {
                break;
            }
        }
    }
}

/// `bench-quality`'s files when its `bench.csv` holds no measured row (only the header): the
/// record of the scene and budget and the empty table, written before the first configuration.
pub fn bench_quality_no_work(out: &Path) -> Vec<PathBuf> {
    let csv = out.join("bench.csv");
    match std::fs::read_to_string(&csv) {
        Ok(t) if t.lines().filter(|l| !l.trim().is_empty()).count() <= 1 => {
            vec![csv, out.join("bench.json")]
        }
        _ => Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn removes_only_the_empty_folders_it_noted() {
        let root = std::env::temp_dir().join(format!("xscale-out-dir-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(&root).unwrap();
        // Two new levels, both left empty: both go, the existing root stays.
        let out = root.join("runs/x");
        let c = Created::before(&out);
        std::fs::create_dir_all(&out).unwrap();
        c.clean_up(&|_| Vec::new());
        assert!(!root.join("runs").exists() && root.is_dir());
        // A folder that holds a file stays, and so do its ancestors.
        let c = Created::before(&out);
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(out.join("keep.txt"), "x").unwrap();
        c.clean_up(&|_| Vec::new());
        assert!(out.join("keep.txt").is_file());
        // A folder that existed before is never removed, even empty.
        std::fs::remove_file(out.join("keep.txt")).unwrap();
        let c = Created::before(&out);
        c.clean_up(&|_| Vec::new());
        assert!(out.is_dir());
        // bench-quality's header-only table goes with its record; a measured row keeps both.
        std::fs::remove_dir_all(root.join("runs")).unwrap();
        let c = Created::before(&out);
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(out.join("bench.csv"), "config,wall_s\n").unwrap();
        std::fs::write(out.join("bench.json"), "{}").unwrap();
        c.clean_up(&bench_quality_no_work);
        assert!(!root.join("runs").exists());
        let c = Created::before(&out);
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(out.join("bench.csv"), "config,wall_s\ncpu,1.0\n").unwrap();
        std::fs::write(out.join("bench.json"), "{}").unwrap();
        c.clean_up(&bench_quality_no_work);
        assert!(out.join("bench.csv").is_file() && out.join("bench.json").is_file());
        std::fs::remove_dir_all(&root).unwrap();
    }
}
