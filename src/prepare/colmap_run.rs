//! Running COLMAP's command-line program: finding it, the install hint when it is missing, and
//! one command run with its output logged to a file, a progress line on stderr, and a stop on
//! interrupt (the child is killed; COLMAP's database is SQLite, so what it wrote stays
//! consistent and a later run resumes: feature extraction and matching skip what is done).

use anyhow::{bail, Context, Result};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// What to install when no `colmap` is on the PATH.
pub const INSTALL_HINT: &str = "COLMAP is not installed (no `colmap` on the PATH). Install it: \
`sudo apt-get install colmap` on Debian/Ubuntu (as root: `apt-get update && apt-get install -y colmap`), \
`brew install colmap` on macOS, `conda install -c conda-forge colmap` elsewhere; or name the binary \
with --colmap PATH. Only COLMAP's CPU commands are used (no CUDA needed). Without COLMAP, \
`xscale prepare --sparse MODEL_DIR` meshes a sparse model made elsewhere.";

/// A `colmap` program.
#[derive(Clone, Debug)]
pub struct Colmap {
    pub exe: PathBuf,
}

/// One COLMAP command: its name (`feature_extractor`, …) and arguments.
#[derive(Clone, Debug, PartialEq)]
pub struct Step {
    pub command: String,
    pub args: Vec<String>,
}

impl Step {
    pub fn new(command: &str) -> Step {
        Step {
            command: command.to_string(),
            args: Vec::new(),
        }
    }

    /// Add `--name value`.
    pub fn arg(mut self, name: &str, value: impl ToString) -> Step {
        self.args.push(format!("--{name}"));
        self.args.push(value.to_string());
        self
    }

    /// The command as a shell line (arguments with spaces or quotes single-quoted).
    pub fn shell(&self, exe: &str) -> String {
        let quote = |s: &str| {
            if !s.is_empty()
                && s.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_./,:=+@".contains(c))
            {
                s.to_string()
            } else {
                format!("'{}'", s.replace('\'', "'\\''"))
            }
        };
        std::iter::once(quote(exe))
            .chain(std::iter::once(self.command.clone()))
            .chain(self.args.iter().map(|a| quote(a)))
            .collect::<Vec<_>>()
            .join(" ")
    }
}

impl Colmap {
    /// `explicit`, else the first `colmap` on the PATH; `None` when there is none.
    pub fn find(explicit: Option<&Path>) -> Option<Colmap> {
        if let Some(p) = explicit {
            return p.is_file().then(|| Colmap {
                exe: p.to_path_buf(),
            });
        }
        let path = std::env::var_os("PATH")?;
        std::env::split_paths(&path)
            .map(|d| d.join("colmap"))
            .find(|p| is_executable(p))
            .map(|exe| Colmap { exe })
    }

    /// COLMAP's version line (`COLMAP 3.8 -- …`), if `colmap help` prints one.
    pub fn version(&self) -> Option<String> {
        let out = Command::new(&self.exe).arg("help").output().ok()?;
        let text = String::from_utf8_lossy(&out.stdout).to_string();
        text.lines()
            .find(|l| l.starts_with("COLMAP"))
            .map(|l| l.trim().to_string())
    }

    /// Run `step`, its output appended to `log`; `progress(line)` gets COLMAP's progress lines
    /// (at most every 2 s). Stops (killing COLMAP) when `stop` is set, with an error saying so.
    pub fn run(
        &self,
        step: &Step,
        log: &Path,
        stop: &AtomicBool,
        progress: &mut dyn FnMut(&str),
    ) -> Result<Duration> {
        let t0 = Instant::now();
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log)
            .with_context(|| format!("{}: cannot open the log", log.display()))?;
        use std::io::Write;
        writeln!(file, "$ {}", step.shell(&self.exe.to_string_lossy()))?;
        let mut child = Command::new(&self.exe)
            .arg(&step.command)
            .args(&step.args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .with_context(|| format!("{}: cannot start", self.exe.display()))?;
        // Both streams into one channel, line by line.
        let (tx, rx) = std::sync::mpsc::channel::<String>();
        let mut readers = Vec::new();
        let out = child.stdout.take().unwrap();
        let err = child.stderr.take().unwrap();
        for stream in [
            Box::new(out) as Box<dyn std::io::Read + Send>,
            Box::new(err),
        ] {
            let tx = tx.clone();
            readers.push(std::thread::spawn(move || {
                for line in BufReader::new(stream).lines().map_while(|l| l.ok()) {
                    if tx.send(line).is_err() {
                        break;
                    }
                }
            }));
        }
        drop(tx);
        let mut last = Instant::now() - Duration::from_secs(10);
        let mut tail: Vec<String> = Vec::new();
        let status = loop {
            while let Ok(line) = rx.recv_timeout(Duration::from_millis(200)) {
                writeln!(file, "{line}").ok();
                if let Some(p) = progress_of(&line) {
                    if last.elapsed() >= Duration::from_secs(2) {
                        progress(&p);
                        last = Instant::now();
                    }
                }
                tail.push(line);
                if tail.len() > 12 {
                    tail.remove(0);
                }
                if stop.load(Ordering::SeqCst) {
                    break;
                }
            }
            if stop.load(Ordering::SeqCst) {
                let _ = child.kill();
                let _ = child.wait();
                writeln!(file, "(stopped by an interrupt)").ok();
                bail!("interrupted during `colmap {}`", step.command);
            }
            if let Some(s) = child.try_wait()? {
                // Drain what is left.
                for line in rx.try_iter() {
                    writeln!(file, "{line}").ok();
                    tail.push(line);
                }
                break s;
            }
        };
        for r in readers {
            let _ = r.join();
        }
        if !status.success() {
            let last_lines: Vec<&String> = tail
                .iter()
                .rev()
                .take(6)
                .collect::<Vec<_>>()
                .into_iter()
                .rev()
                .collect();
            bail!(
                "`colmap {}` failed ({status}); its output is in {}; it ended:\n  {}",
                step.command,
                log.display(),
                last_lines
                    .iter()
                    .map(|s| s.as_str())
                    .collect::<Vec<_>>()
                    .join("\n  ")
            );
        }
        Ok(t0.elapsed())
    }
}

fn is_executable(p: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        p.metadata()
            .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
    }
    #[cfg(not(unix))]
    {
        p.is_file()
    }
}

/// The progress lines COLMAP prints, shortened: `Processed file [3/50]`, `Matching block
/// [1/4, 2/4]`, `Registering image #12 (7)`, `Triangulating image #4 (3)`.
fn progress_of(line: &str) -> Option<String> {
    let l = line.trim();
    for key in [
        "Processed file",
        "Matching block",
        "Registering image",
        "Triangulating image",
        "Undistorting image",
        "Importing matches",
    ] {
        if let Some(k) = l.find(key) {
            let rest = &l[k..];
            let end = rest.find(" in ").unwrap_or(rest.len());
            return Some(rest[..end].to_string());
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shell_lines_quote_what_needs_it() {
        let s = Step::new("feature_extractor")
            .arg("database_path", "/tmp/a b/db.db")
            .arg("ImageReader.camera_params", "1.5,2,3");
        assert_eq!(
            s.shell("colmap"),
            "colmap feature_extractor --database_path '/tmp/a b/db.db' --ImageReader.camera_params 1.5,2,3"
        );
    }

    #[test]
    fn progress_lines() {
        assert_eq!(
            progress_of("Processed file [3/50]").as_deref(),
            Some("Processed file [3/50]")
        );
        assert_eq!(
            progress_of("Matching block [1/2, 2/2] in 12.3s").as_deref(),
            Some("Matching block [1/2, 2/2]")
        );
        assert_eq!(progress_of("  Name: 0001.jpg"), None);
    }

    /// A missing binary is `None`; a failing command is an error naming its log and its last
    /// lines; an interrupt kills it.
    #[test]
    fn runs_and_fails_and_stops() {
        assert!(Colmap::find(Some(Path::new("/nonexistent/colmap"))).is_none());
        let dir = std::env::temp_dir().join(format!("xscale-colmap-run-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let fake = dir.join("colmap");
        std::fs::write(
            &fake,
            "#!/bin/sh\nif [ \"$1\" = slow ]; then sleep 30; fi\necho 'Processed file [1/2]'\necho \"args: $*\"\n[ \"$1\" = fail ] && { echo 'ERROR: broken' >&2; exit 3; }\nexit 0\n",
        )
        .unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
        }
        let c = Colmap::find(Some(&fake)).unwrap();
        let log = dir.join("log.txt");
        let stop = AtomicBool::new(false);
        let mut seen = Vec::new();
        c.run(&Step::new("ok").arg("x", 1), &log, &stop, &mut |p| {
            seen.push(p.to_string())
        })
        .unwrap();
        assert_eq!(seen, ["Processed file [1/2]"]);
        let logged = std::fs::read_to_string(&log).unwrap();
        assert!(logged.contains("args: ok --x 1"), "{logged}");
        let e = c
            .run(&Step::new("fail"), &log, &stop, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`colmap fail` failed") && e.contains("ERROR: broken"),
            "{e}"
        );
        stop.store(true, Ordering::SeqCst);
        let t = Instant::now();
        let e = c
            .run(&Step::new("slow"), &log, &stop, &mut |_| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("interrupted"), "{e}");
        assert!(t.elapsed() < Duration::from_secs(10));
        std::fs::remove_dir_all(&dir).ok();
    }
}
