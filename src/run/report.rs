//! What a training run tells its user and writes down: the terminal (progress bar or lines),
//! `RUN/metrics.jsonl`, and the final `RUN/eval.json`. Nothing here affects the numbers.

use crate::eval::protocol::{mean_score, scale_summary, scale_table, table, ViewScore};
use crate::train::state::{StepStats, TrainState};
use anyhow::{Context, Result};
use std::fs::File;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The terminal and `metrics.jsonl` of one run.
pub struct Reporter {
    quiet: bool,
    bar: Option<indicatif::ProgressBar>,
    metrics: File,
    /// `RUN/checkpoint-time.json` ([`crate::run::run_dir::TIME_FILE`]).
    time_path: PathBuf,
    steps: u64,
    t0: Instant,
    /// Seconds the run had trained before this process (a resumed run; 0 for a fresh one).
    offset: f64,
    /// Running mean squared error (exponential, 0.9) for the logged PSNR.
    ema_mse: Option<f64>,
    /// Since the last log line: start, valid sub-samples, pixels.
    window: (Instant, usize, usize),
}

/// `-10 log10(mse)`.
pub fn psnr_of(mse: f64) -> f64 {
    -10.0 * mse.log10()
}

impl Reporter {
    /// Append to `run_dir`'s `metrics.jsonl`; a progress bar on a terminal unless `quiet` (or,
    /// with `bar`, even then: a tool's run shows its progress but none of its messages).
    /// `offset`: the seconds the run had already trained (a resumed run, [`elapsed_at`]), so
    /// `elapsed_s` runs on across resumes.
    pub fn open(
        run_dir: &Path,
        quiet: bool,
        bar: bool,
        steps: u64,
        first_step: u64,
        offset: f64,
    ) -> Result<Reporter> {
        let metrics_path = run_dir.join("metrics.jsonl");
        let metrics = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&metrics_path)
            .with_context(|| format!("{}: cannot open", metrics_path.display()))?;
        let bar = ((!quiet || bar) && std::io::stderr().is_terminal()).then(|| {
            let b = indicatif::ProgressBar::new(steps);
            b.set_style(
                indicatif::ProgressStyle::with_template(
                    "{bar:30} {pos}/{len} [{elapsed_precise} < {eta_precise}] {msg}",
                )
                .expect("valid template"),
            );
            b.set_position(first_step);
            b
        });
        Ok(Reporter {
            quiet,
            bar,
            metrics,
            time_path: run_dir.join(crate::run::run_dir::TIME_FILE),
            steps,
            t0: Instant::now(),
            offset,
            ema_mse: None,
            window: (Instant::now(), 0, 0),
        })
    }

    /// A line for the user (above the bar when there is one).
    pub fn say(&self, msg: String) {
        if self.quiet && !msg.starts_with("warning:") {
            return;
        }
        match &self.bar {
            Some(b) => b.println(msg),
            None => eprintln!("{msg}"),
        }
    }

    /// The run's wall time: seconds since the reporter was opened, plus what the run had
    /// trained before a resume.
    pub fn elapsed(&self) -> f64 {
        self.offset + self.t0.elapsed().as_secs_f64()
    }

    /// A checkpoint of step `k` was written: a metrics line with the time, and the time beside
    /// the checkpoint, which a resume from it continues from ([`elapsed_at`]).
    pub fn checkpointed(&mut self, k: u64) -> Result<()> {
        let t = self.elapsed();
        writeln!(
            self.metrics,
            "{}",
            serde_json::json!({"step": k, "checkpoint": true, "elapsed_s": t})
        )?;
        let record = serde_json::json!({"step": k, "elapsed_s": t});
        crate::io::atomic::write_bytes(&self.time_path, format!("{record}\n"))
    }

    /// The model and the run's shape, once at the start.
    pub fn model(&self, state: &TrainState) {
        let feat = match &state.ckpt.model.vertex {
            Some(vt) => format!(
                "vertex features Z={} on {} vertices",
                vt.features, vt.n_vertices
            ),
            None => format!("{} grid H levels", state.cfg.model.grid_h.levels),
        };
        let deform = if state.cfg.model.deform.enabled {
            "on"
        } else {
            "off"
        };
        self.say(format!(
            "model: {} parameters ({feat}, deformation {deform}, γ={}, A={}); {} steps of {} pixels",
            state.ckpt.model.layout.total,
            state.cfg.model.gamma,
            state.cfg.model.appearance_dim,
            self.steps,
            state.cfg.train.batch_pixels
        ));
    }

    /// After step `k` (1-based count of steps done): the running PSNR, and every `log_every`
    /// steps a metrics line and a progress message.
    pub fn step(&mut self, k: u64, st: &StepStats, pixels: usize, log_every: u64) -> Result<()> {
        let ema = self.ema_mse.map_or(st.mse, |e| 0.9 * e + 0.1 * st.mse);
        self.ema_mse = Some(ema);
        self.window.1 += st.samples;
        self.window.2 += pixels;
        if k % log_every.max(1) == 0 || k == self.steps {
            let dt = self.window.0.elapsed().as_secs_f64().max(1e-9);
            let px_s = self.window.2 as f64 / dt;
            let line = serde_json::json!({
                "step": k, "loss": st.loss, "psnr": psnr_of(ema),
                "pixels_per_s": px_s, "samples_per_s": self.window.1 as f64 / dt,
                "elapsed_s": self.elapsed(),
            });
            writeln!(self.metrics, "{line}")?;
            let msg = format!(
                "loss {:.4}  psnr {:.2}  {px_s:.0} px/s",
                st.loss,
                psnr_of(ema)
            );
            match &self.bar {
                Some(b) => b.set_message(msg),
                None => self.say(format!("step {k}/{}  {msg}", self.steps)),
            }
            self.window = (Instant::now(), 0, 0);
        }
        if let Some(b) = &self.bar {
            b.set_position(k);
        }
        Ok(())
    }

    /// A periodic evaluation at step `k`.
    pub fn eval(&mut self, k: u64, scores: &[ViewScore]) -> Result<()> {
        let m = mean_score(scores);
        writeln!(
            self.metrics,
            "{}",
            serde_json::json!({"step": k, "eval": m, "elapsed_s": self.elapsed()})
        )?;
        self.say(format!(
            "eval @ {k}: PSNR {:.2} (masked {:.2}), SSIM {:.4} (masked {:.4}) on {} views",
            m.psnr,
            m.psnr_masked,
            m.ssim,
            m.ssim_masked,
            scores.len()
        ));
        Ok(())
    }

    /// The loop is over: remove the bar.
    pub fn loop_done(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
    }

    /// A completed run: its time, checkpoint and peak memory (also in `metrics.jsonl`).
    pub fn trained(&mut self, step: u64, seconds: f64, ckpt_path: &Path) -> Result<()> {
        let peak = crate::sysmem::peak_rss_bytes();
        self.say(format!(
            "trained {step} steps in {seconds:.1} s; checkpoint {}{}",
            ckpt_path.display(),
            peak.map_or(String::new(), |b| format!(
                "; peak memory {:.2} GB",
                b as f64 / 1e9
            ))
        ));
        if let Some(b) = peak {
            writeln!(
                self.metrics,
                "{}",
                serde_json::json!({"step": step, "peak_rss_bytes": b})
            )?;
        }
        Ok(())
    }

    /// The final evaluation: the table, a metrics line and `RUN/eval.json`; returns the mean.
    pub fn final_eval(
        &mut self,
        step: u64,
        scores: &[ViewScore],
        run_dir: &Path,
    ) -> Result<ViewScore> {
        let m = mean_score(scores);
        self.say(table(scores) + &scale_table(scores));
        writeln!(
            self.metrics,
            "{}",
            serde_json::json!({"step": step, "eval": m, "final": true, "elapsed_s": self.elapsed()})
        )?;
        let json = serde_json::json!({
            "views": scores, "mean": m, "by_scale": scale_summary(scores), "step": step
        });
        crate::io::atomic::write_bytes(
            &run_dir.join("eval.json"),
            serde_json::to_string_pretty(&json)?,
        )?;
        self.say(format!(
            "renders in {}, side-by-sides in {}",
            run_dir.join("render").display(),
            run_dir.join("eval").display()
        ));
        Ok(m)
    }
}

/// The training time of `run_dir`'s run at its checkpoint's `step`: from
/// [`crate::run::run_dir::TIME_FILE`] when it holds that step, else (a run from an older xscale,
/// or one killed between writing its checkpoint and that file) as `metrics.jsonl` records it
/// ([`elapsed_recorded`]; the resume has cut it back to the checkpoint's step).
pub fn elapsed_at(run_dir: &Path, step: u64) -> Option<f64> {
    let recorded = std::fs::read_to_string(run_dir.join(crate::run::run_dir::TIME_FILE))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .filter(|j| j.get("step").and_then(|s| s.as_u64()) == Some(step))
        .and_then(|j| j.get("elapsed_s").and_then(|e| e.as_f64()))
        .filter(|e| e.is_finite() && *e >= 0.0);
    recorded.or_else(|| elapsed_recorded(&run_dir.join("metrics.jsonl")))
}

/// The run's training time as its metrics file records it: the last `elapsed_s` outside a
/// final-evaluation line (whose time is not training) — for a file cut back to a resumed
/// checkpoint's step, that checkpoint's own line when it has one; `None` without any.
pub fn elapsed_recorded(metrics_path: &Path) -> Option<f64> {
    let text = std::fs::read_to_string(metrics_path).ok()?;
    text.lines()
        .rev()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|j| j.get("final").is_none())
        .filter_map(|j| j.get("elapsed_s").and_then(|e| e.as_f64()))
        .find(|e| e.is_finite() && *e >= 0.0)
}
