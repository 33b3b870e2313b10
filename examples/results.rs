//! Regenerates `docs/results.md`, the one page of measured figures the README and the docs link
//! to. Every figure on it comes from a workload this program runs itself, with the host (CPU
//! model, cores), the date, the commit and the exact command beside it.
//!
//! ```text
//! cargo run --release --example results                      # every section (long: see --list)
//! cargo run --release --example results -- --only small,render   # these sections again
//! cargo run --release --example results -- --render-only     # rewrite the page from the JSON
//! cargo run --release --example results -- --list            # the sections and what they cost
//! ```
//!
//! Each section writes its rows to `docs/results/<section>.json` (machine-readable: the raw
//! numbers, the commands, host, date, commit) and the page is rendered from all such files, so a
//! section is rerun alone without redoing the others, and a section added by another program
//! (any `docs/results/*.json` with the same fields) appears on the page too. Scratch runs go to
//! `target/results/`. The workloads call the `xscale` binary built next to this example
//! (`target/release/xscale`, rebuilt first with `cargo build --release --locked`) and the
//! project's benches (`cargo bench --bench NAME`, which write their rows where
//! `XSCALE_BENCH_JSON` says).

use anyhow::{anyhow, bail, Context, Result};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// One section: its file name, title, what it measures, and how to run it.
struct Spec {
    name: &'static str,
    title: &'static str,
    measures: &'static str,
    cost: &'static str,
    run: fn(&Ctx) -> Result<Section>,
}

const SECTIONS: &[Spec] = &[
    Spec {
        name: "tiny",
        title: "The bundled tiny scene",
        measures: "The README's first command, as a user runs it: 300 steps of the `tiny` preset on `fixtures/tiny` (8 views of 64×48, 2 held out), the whole command timed (setup, training, final evaluation). A smoke test of the install, not a quality benchmark.",
        cost: "seconds",
        run: tiny,
    },
    Spec {
        name: "small",
        title: "Training `synth --preset small` with the default `cpu` preset",
        measures: "Quality against training steps on the project's synthetic cross-scale scene (40 views of 200×150, an aerial ring at 120 m and close-up clusters at 4 m; 6 views held out): one run of the default configuration stopped and resumed at each step count (a resumed run is bit-identical to an uninterrupted one), scored on the held-out views after each. Masked = pixels whose rays hit the mesh; full = every pixel; close-ups and aerial views split as `eval.json`'s `near_far`. The last rows are the no-learning ULR baseline on the same views and the training loop's own speed between steps 50 and 250 of the first leg.",
        cost: "a few minutes",
        run: small,
    },
    Spec {
        name: "train_loop",
        title: "Where a training step's time goes (`cargo bench --bench train_loop`)",
        measures: "The whole training loop at the `cpu` preset on `small` (4,096-pixel batches from the sample cache, γ = 2, the automatic level range), setup excluded: pixels per second and milliseconds per step by phase, with 1 and 2 threads alternated in rounds (best round of each). The 2-thread / 1-thread ratio is measured in the same run.",
        cost: "a minute or two (plus building the bench)",
        run: train_loop,
    },
    Spec {
        name: "skips",
        title: "What each skip and switch saves (`cargo bench --bench skips`)",
        measures: "Milliseconds per training step of the default `cpu` run on `small` with one thing changed (2 threads, 4,096-pixel batches, best of alternating rounds): level dropping, footprint level weighting, the automatic level range, deformation, multisampling, compaction of invalid sub-samples, and the sample cache against rays cast per batch.",
        cost: "a few minutes",
        run: skips,
    },
    Spec {
        name: "torch_peer",
        title: "Against PyTorch (`cargo bench --bench torch_peer`)",
        measures: "One training step of the same model, checkpoint and 16,384-pixel batch on 2 threads in xscale and in a PyTorch peer (`reference/bench_torch.py`) run twice per round — its loss compiled with `torch.compile` and eager (uncompiled, the peer the project's earlier ratios were quoted against) — timed in alternating rounds after each peer reproduced xscale's loss. Needs `pip install torch numpy safetensors` for `python3` (or the interpreter `XSCALE_TORCH_PYTHON` names); without them the section keeps its earlier measurement, or says it was skipped.",
        cost: "a few minutes when torch is installed",
        run: torch_peer,
    },
    Spec {
        name: "oracle",
        title: "The oracle's dump: time against error (`cargo bench --bench oracle`)",
        measures: "Every precision mode of `xscale dump` on one workload (the golden `cpu-t10` checkpoint on a seeded batch of 4,096 pixels × 4 sub-samples, in memory), timed in alternating rounds (median), with each tensor family's error against the f64 dump: the largest `max abs / peak` of the family (what the tolerance files limit). The f32 dumps pass `tolerances-f32.toml` before they are timed.",
        cost: "about a minute",
        run: oracle,
    },
    Spec {
        name: "python",
        title: "The oracle from Python (`python/bench/bench_ops.py`)",
        measures: "What calling the oracle from Python costs, on the golden `cpu-t10` checkpoint and a seeded batch of 4,096 pixels × 4 sub-samples (10 % invalid), f32 and f64: every op of a whole step composed from the package's ops (`xscale.step_from_ops`) timed per call, split into the Rust computation and the binding's overhead (argument checks, array conversion, the GIL); their sum against the composed step; and the whole step in one call (`Model.step`) against the `xscale dump` command's round trip (the process, its files, loading the dump back), in alternating rounds (median). Before timing it checks that the composed step equals `Model.step` bit for bit and that the command's dump equals it tensor for tensor. Needs the package (`pip install ./python`) for `python3` or `XSCALE_PYTHON`; without it the section says it was skipped.",
        cost: "under a minute (the package built)",
        run: python,
    },
    Spec {
        name: "render",
        title: "Rendering a 1.08-megapixel frame",
        measures: "`xscale render --scale 6` of one held-out `small` view (1200×900, γ = 2) from the `small` section's checkpoint: the whole command (mapping the checkpoint, casting, shading, writing the PNG), median of 5 runs, and its peak memory.",
        cost: "under a minute",
        run: render,
    },
    Spec {
        name: "real",
        title: "Real photographs: the default against reprojection (ULR)",
        measures: "The default `cpu` preset trained on real captures and scored on their held-out views (every 7th) against the no-learning ULR baseline on the same pixels: masked PSNR, SSIM and ꟻLIP (lower is better), and the full-image PSNR (every pixel, the mesh's misses counted). The committed capture is `fixtures/prepare_skull` (10 photos of a skull, 709×473, CC BY 4.0; its COLMAP model meshed by `xscale prepare --sparse`, black background); scene folders listed in `XSCALE_REAL_SCENES` (colon-separated; their photos are not in the repository) are run the same way — on this page instant-ngp's `fox` (50 phone photos halved to 540×960, NVIDIA's non-commercial licence), prepared with `xscale prepare --photos fox/images --poses fox --downsample 2 --out fox_scene` (docs/prepare.md). The refinement row trains the same scene with photo-consistency mesh refinement on (`[model.refine] enabled = true`), which the `cpu` preset leaves off. The row `mean code` scores the same model with every held-out view given the mean appearance code (`eval --appearance mean`) instead of its pose neighbours' codes (the default, spec §4.6).",
        cost: "about 5 minutes, plus 10 per scene of XSCALE_REAL_SCENES",
        run: real,
    },
    Spec {
        name: "bench_quality",
        title: "Run time against error (`xscale bench-quality`)",
        measures: "Every configuration of `xscale bench-quality --list` trained for the same wall-clock budget on `small` and scored on the held-out views at the budget and at its halvings (evaluation time not counted); then the default, three of its variants (mesh refinement among them) and ULR on a real capture (the skull of section `real`). One seed per configuration: differences of a few tenths of a dB are within what two runs of one configuration differ by.",
        cost: "about 20 minutes",
        run: bench_quality,
    },
    Spec {
        name: "ablation",
        title: "Ablations and the vertex-feature baseline (`xscale ablate`)",
        measures: "The paper's Table 4 and 5 ablations and the Fig. 2b vertex-feature baseline on `small`, every variant with the same step budget and seed, scored on the held-out views, with the claims `xscale ablate` checks on the measured numbers.",
        cost: "about 10 minutes",
        run: ablation,
    },
    Spec {
        name: "cross",
        title: "Cross-scale reach on `synth --preset cross`",
        measures: "Held-out close-ups and aerial views of `synth --preset cross` (56 views of 200×150: aerial at 120 m, close-ups at 4 m, texture tied to the close-ups' pixels) after the default number of steps of the `cpu` preset, with its automatic level range and footprint level weighting, against the preset's fixed range, against no level weighting, and against the no-learning ULR baseline.",
        cost: "about 10 minutes",
        run: cross,
    },
    Spec {
        name: "geometry_cross",
        title: "A far-view mesh refined by the close-ups (`xscale bench-geometry` on `cross`)",
        measures: "`xscale bench-geometry` on `synth --preset cross` (seed 1) with the exact surface and a proxy displaced along its normals by a smooth field (wavelength 20 % of the diagonal) of RMS 0.36 % of the diagonal, about one and a half aerial pixel footprints (the note gives its ratio to the held-out aerial views' median): the error of a mesh made from the aerial views, tens of close-up pixels. Each trained for the same steps and seed with ξ on, with the mesh fixed, with the cross-scale refinement (`configs/refine-cross.toml`: image levels per view as deep as the footprints imply, neighbours chosen again at every rebuild, scale-band weights) and with the default refinement (`[model.refine] enabled = true`: image levels 2 → 0 for every view, neighbours chosen once). Held-out masked PSNR of the close-ups and aerial views (`eval.json`'s near/far split); the geometry error is the RMS distance of area samples of the mesh (the proxy, or `RUN/refined.ply`) to the true surface; recovered = the share of the close-ups' loss to the exact mesh that the refinement wins back.",
        cost: "about 25 minutes",
        run: geometry_cross,
    },
    Spec {
        name: "prepare",
        title: "From photos to a scene: `xscale prepare`",
        measures: "The mesher of `xscale prepare` against a true surface: `examples/prepare_synth.rs` on the `small` synthetic scene (400 points found per camera, exact or with noise of 0.1 % of the diagonal and 2 % wrong matches), its Delaunay graph cut at three `--max-side` settings and COLMAP's `poisson_mesher` on the same points (normals fitted to 12 neighbours, turned towards the cameras); accuracy = RMS distance of area samples of the mesh to the truth, completeness = RMS distance of samples of the truth that two cameras see to the mesh, both capped at 10 % of the diagonal and given as a share of it. Then a real capture from a folder of photos to a trained model, stage by stage (`prepare.json`'s seconds per stage), with its points, reprojection error through xscale's cameras, the share of pixels whose ray meets the mesh, and the trained model's held-out scores: the committed skull photos (`fixtures/prepare_skull`, 10 photos of 709×473, with the poses of its COLMAP model: COLMAP's mapper finds no good initial pair in these 10 small photos), and any capture named by `XSCALE_PREPARE_PHOTOS` (with `XSCALE_PREPARE_POSES` for known poses, `XSCALE_PREPARE_DOWNSAMPLE`, `XSCALE_PREPARE_STEPS`). Needs COLMAP on the PATH for Poisson and for the photos; without it those rows say they were skipped.",
        cost: "a minute or two on a quiet machine; about 15 minutes at a load of 18, where COLMAP's Poisson slows most",
        run: prepare,
    },
    Spec {
        name: "budget",
        title: "Training budget: the step count the cpu preset chooses",
        measures: "The `cpu` preset's training budget (`[train] budget = \"auto\"`: about 12 epochs over the kept training pixels, 1,000 to 12,000 steps, with the preset's learning-rate decays stretched to the chosen count) on `synth --preset small` and `cross` (seed 1) and on a real capture (the skull of section `real`), against fixed 2,000 steps (`--steps 2000`: the preset's schedule as written) and, on `cross` and the skull, a run 3× the rule's steps with the schedule stretched the same way. On the skull close-ups and aerial views do not apply (one scale). Held-out masked PSNR and SSIM, close-ups and aerial views apart; wall time of each `train` command (casting and the final evaluation included), one run after another on the same host.",
        cost: "about 20 minutes",
        run: budget,
    },
    Spec {
        name: "sizing",
        title: "Table sizes from the scene: parameters, checkpoints, quality, step time",
        measures: "The `cpu` preset's hash-table sizes chosen from the surface cells the training rays reach (`[model.grid_h] log2_table_size = \"auto\"`, the default: each level 8 entries per reached cell, 2^12..2^19, dense iff its dense grid fits that size, grid D never above its configured 2^17; the optimizer state, in its own file, leaves out the Adam state of entries no ray reached, and the checkpoint (the model) a table's rows no ray reached where leaving them out saves at least a quarter of its bytes) against fixed tables of 2^19 entries per level (`--config` with `[model.grid_h] log2_table_size = 19`, the preset before). `tiny`, `small`, `cross` and `large` (`synth --preset NAME --seed 1`): parameters of the model `xscale init` builds; each but `large` trained with the default budget (training seeds `XSCALE_SIZING_SEEDS`, default 0,1,2; `large` only with `XSCALE_SIZING_LARGE_SEEDS`): checkpoint and optimizer-state bytes and what fills them, held-out masked PSNR (close-ups and aerial views apart), wall time of the `train` command, the two configurations alternating seed by seed. Then `cargo bench --bench sizing`: milliseconds per training step on `small` and `cross`, 2 threads, 4,096- and 16,384-pixel batches, the two models alternating in rounds (best round).",
        cost: "about 10 minutes per seed (tiny, small, cross; 20 with load), plus the bench",
        run: sizing,
    },
    Spec {
        name: "sizing_render",
        title: "Rendering a 1.08-megapixel frame with tables from the scene",
        measures: "`xscale render --scale 6` of one held-out `small` view (1200×900, γ = 2) from the `sizing` section's seed-0 models of `small` (fixed 2^19 tables and tables from the scene): the whole command (mapping the checkpoint, building the BVH, casting, shading, writing the PNG), the two alternating, 5 runs each, median. Then, for the auto model, the same command at `--scale 0.05` (its fixed costs) against the full frame, and with `XSCALE_RENDER_BEFORE=<an older xscale binary>` that binary's full frame as well (checked to write the same PNG bytes), all alternating, 5 runs each.",
        cost: "under a minute (after the sizing section)",
        run: sizing_render,
    },
    Spec {
        name: "refine",
        title: "Mesh refinement on and off (`xscale bench-geometry`)",
        measures: "Photo-consistency mesh refinement (`[model.refine] enabled = true` with the section's defaults) on and off, `cpu` preset at `bench-geometry`'s fixed 2,000 steps (the same count for every run), deformation on, on `synth --preset small --write-truth` (seed 1): the exact mesh with training seeds 0, 1 and 2, and a proxy displaced by 0.3 % of the diagonal RMS (seed 0). Held-out masked PSNR and SSIM, close-ups and aerial views apart, training time of each run (one after another on the same host). The `cpu` preset keeps refinement off; this table is what that rule rests on.",
        cost: "about 30 minutes",
        run: refine,
    },
    Spec {
        name: "meshcheck",
        title: "The mesh check: a correct mesh against turned, moved and scaled ones",
        measures: "`xscale cast` on each scene with its own mesh and with that mesh turned a quarter about x, moved along z by 5 % of its bounding box's diagonal, along x by 3 %, and scaled by 1.1 (about the box's centre; the meshes `raycast::photo_check_neighbours_table` uses), and what its checks say (docs/spec.md §3.9): the photo check's correlation (a warning below 0.5), its neighbour check (the best of the 20 neighbours — the mesh moved by ± 4 % of the region the cameras see, turned by ± 5° and a quarter, scaled ×/÷ 1.1 — against the mesh as given, both scored by the correlation within cubes of a quarter of that region; a warning when it wins by more than 0.03 in the mean and in two thirds of the view pairs, or by more than 0.1), and the check against the reconstruction's points (tolerances in units of the region the cameras see). A correct mesh should stay silent, every other warn. Scenes: the `tiny` fixture, `synth --preset small --seed 1`, the committed real skull (section `real`), and any scene folder of `XSCALE_REAL_SCENES` (here instant-ngp's fox and the skull's full capture, /work/data/skull: 10 registered photos of 1418×946).",
        cost: "a few minutes, plus about a minute per scene of XSCALE_REAL_SCENES",
        run: meshcheck,
    },
];

/// What a section's run gives; the runner adds name, title, host, date, commit and duration.
#[derive(Default)]
struct Section {
    commands: Vec<String>,
    tables: Vec<Value>,
    notes: Vec<String>,
    images: Vec<(String, String)>,
    /// Why the whole section could not be measured on this host (a missing tool): the page then
    /// keeps the section's earlier measurement, if it has one, instead of a "not measured" note.
    skipped: Option<String>,
}

struct Ctx {
    root: PathBuf,
    work: PathBuf,
    bin: PathBuf,
    docs: PathBuf,
}

/// A finished child process: exit status, output, wall time, peak resident memory.
struct Ran {
    ok: bool,
    stderr: String,
    wall_s: f64,
    peak_mb: Option<f64>,
}

impl Ctx {
    /// `xscale ARGS` from the repository root; an error (with its stderr) unless it exits 0.
    fn xscale(&self, args: &[&str]) -> Result<Ran> {
        let r = run_measured(Command::new(&self.bin).args(args).current_dir(&self.root))?;
        if !r.ok {
            bail!("xscale {}: failed:\n{}", args.join(" "), tail(&r.stderr));
        }
        Ok(r)
    }

    /// `cargo bench --bench NAME`, its rows from `XSCALE_BENCH_JSON`.
    fn bench(&self, name: &str, env: &[(&str, &str)]) -> Result<Value> {
        let json = self.work.join(format!("bench-{name}.json"));
        let _ = std::fs::remove_file(&json);
        let mut c = Command::new("cargo");
        c.args(["bench", "--locked", "--bench", name])
            .current_dir(&self.root)
            .env("XSCALE_BENCH_JSON", &json);
        for (k, v) in env {
            c.env(k, v);
        }
        let r = run_measured(&mut c)?;
        if !r.ok {
            bail!("cargo bench --bench {name}: failed:\n{}", tail(&r.stderr));
        }
        let text = std::fs::read_to_string(&json)
            .with_context(|| format!("cargo bench --bench {name} wrote no {}", json.display()))?;
        Ok(serde_json::from_str(&text)?)
    }

    /// A scratch path under `target/results/`, relative to the repository root when it can be
    /// (so the commands on the page read as a user would type them).
    fn w(&self, name: &str) -> String {
        let p = self.work.join(name);
        p.strip_prefix(&self.root)
            .map(|r| r.display().to_string())
            .unwrap_or_else(|_| p.display().to_string())
    }
}

fn tail(s: &str) -> String {
    let lines: Vec<&str> = s.lines().collect();
    lines[lines.len().saturating_sub(15)..].join("\n")
}

/// Spawn, wait, and measure wall time and (Linux) the child's own peak resident set.
fn run_measured(c: &mut Command) -> Result<Ran> {
    use std::io::Read;
    let t0 = Instant::now();
    let mut child = c
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .with_context(|| format!("cannot start {c:?}"))?;
    let (mut out, mut err) = (child.stdout.take().unwrap(), child.stderr.take().unwrap());
    let t_err = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = err.read_to_string(&mut s);
        s
    });
    // Drained so a chatty child never blocks on a full pipe; the sections read files.
    let _ = std::io::copy(&mut out, &mut std::io::sink());
    let stderr = t_err.join().unwrap_or_default();
    let (ok, peak_mb) = wait_rusage(&mut child)?;
    Ok(Ran {
        ok,
        stderr,
        wall_s: t0.elapsed().as_secs_f64(),
        peak_mb,
    })
}

#[cfg(target_os = "linux")]
fn wait_rusage(child: &mut std::process::Child) -> Result<(bool, Option<f64>)> {
    let mut status = 0i32;
    // SAFETY: a zeroed rusage is a valid value of the plain C struct wait4 fills in.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: the pid is our own unreaped child; status and ru are valid for writes.
    let pid = unsafe { libc::wait4(child.id() as i32, &mut status, 0, &mut ru) };
    if pid < 0 {
        bail!("wait4: {}", std::io::Error::last_os_error());
    }
    let ok = libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0;
    // ru_maxrss is in KiB on Linux.
    Ok((ok, Some(ru.ru_maxrss as f64 / 1024.0)))
}

#[cfg(not(target_os = "linux"))]
fn wait_rusage(child: &mut std::process::Child) -> Result<(bool, Option<f64>)> {
    Ok((child.wait()?.success(), None))
}

// ---------------------------------------------------------------- tables

/// A table: caption, column names, and rows of raw values; `digits[c]` decimals for column c's
/// numbers on the page (the JSON keeps them whole).
fn table(caption: &str, columns: &[&str], digits: &[usize], rows: Vec<Vec<Value>>) -> Value {
    json!({"caption": caption, "columns": columns, "digits": digits, "rows": rows})
}

fn read_json(p: &Path) -> Result<Value> {
    let t = std::fs::read_to_string(p).with_context(|| format!("{}: cannot read", p.display()))?;
    serde_json::from_str(&t).with_context(|| format!("{}: not JSON", p.display()))
}

/// Mean masked / full scores and the close-up / aerial split of an `eval.json`.
fn scores(e: &Value) -> (Value, Value, Value, Value, Value) {
    let m = &e["mean"];
    let nf = &e["by_scale"]["near_far"];
    (
        m["psnr_masked"].clone(),
        m["ssim_masked"].clone(),
        m["psnr"].clone(),
        nf[1]["mean"]["psnr_masked"].clone(),
        nf[2]["mean"]["psnr_masked"].clone(),
    )
}

/// `metrics.jsonl` lines.
fn metrics(run: &Path) -> Result<Vec<Value>> {
    let p = run.join("metrics.jsonl");
    let t = std::fs::read_to_string(&p).with_context(|| format!("{}", p.display()))?;
    Ok(t.lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect())
}

/// The training time a run's `metrics.jsonl` records at its last checkpoint line.
fn trained_s(run: &Path) -> Result<f64> {
    metrics(run)?
        .iter()
        .rev()
        .find(|m| m["checkpoint"].as_bool() == Some(true))
        .and_then(|m| m["elapsed_s"].as_f64())
        .ok_or_else(|| anyhow!("{}: no checkpoint line in metrics.jsonl", run.display()))
}

fn peak_mb(run: &Path) -> Option<f64> {
    metrics(run)
        .ok()?
        .iter()
        .rev()
        .find_map(|m| m["peak_rss_bytes"].as_f64().map(|b| b / (1024.0 * 1024.0)))
}

/// grid-H levels and the finest resolution of a run's `config.toml`.
fn levels(run: &Path) -> Result<(i64, Option<f64>)> {
    let t = std::fs::read_to_string(run.join("config.toml"))?;
    let v: toml::Value = toml::from_str(&t)?;
    let g = &v["model"]["grid_h"];
    Ok((
        g["levels"].as_integer().unwrap_or(0),
        g.get("finest_resolution").and_then(|x| x.as_float()),
    ))
}

// ---------------------------------------------------------------- sections

fn tiny(c: &Ctx) -> Result<Section> {
    let out = c.w("tiny");
    let _ = std::fs::remove_dir_all(c.root.join(&out));
    let args = [
        "train",
        "--scene",
        "fixtures/tiny",
        "--out",
        &out,
        "--preset",
        "tiny",
    ];
    let r = c.xscale(&args)?;
    let run = c.root.join(&out);
    let e = read_json(&run.join("eval.json"))?;
    let (pm, sm, pf, _, _) = scores(&e);
    Ok(Section {
        commands: vec![format!("xscale {}", args.join(" "))],
        tables: vec![table(
            "",
            &[
                "steps",
                "whole command (s)",
                "training (s)",
                "held-out masked PSNR (dB)",
                "masked SSIM",
                "full PSNR (dB)",
                "peak memory (MB)",
            ],
            &[0, 2, 2, 2, 3, 2, 0],
            vec![vec![
                e["step"].clone(),
                json!(r.wall_s),
                json!(trained_s(&run)?),
                pm,
                sm,
                pf,
                json!(r.peak_mb),
            ]],
        )],
        ..Section::default()
    })
}

const SMALL_STEPS: [u64; 4] = [250, 500, 1000, 2000];

/// `synth --preset small --seed 1` into `target/results/small` (the same bytes every time).
fn small_scene(c: &Ctx, cmds: &mut Vec<String>) -> Result<(String, f64)> {
    let dir = c.w("small");
    let args = ["synth", "--preset", "small", "--seed", "1", "--out", &dir];
    let r = c.xscale(&args)?;
    cmds.push(format!("xscale {}", args.join(" ")));
    Ok((dir, r.wall_s))
}

fn small(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let (scene, synth_s) = small_scene(c, &mut s.commands)?;
    let out = c.w("small-run");
    let run = c.root.join(&out);
    let _ = std::fs::remove_dir_all(&run);
    let mut rows = Vec::new();
    for (i, steps) in SMALL_STEPS.iter().enumerate() {
        let st = steps.to_string();
        let args: Vec<&str> = if i == 0 {
            vec![
                "train", "--scene", &scene, "--out", &out, "--steps", &st, "-q",
            ]
        } else {
            vec!["train", "--out", &out, "--resume", "--steps", &st, "-q"]
        };
        c.xscale(&args)?;
        s.commands.push(format!("xscale {}", args.join(" ")));
        let e = read_json(&run.join("eval.json"))?;
        let (pm, sm, pf, near, far) = scores(&e);
        rows.push(vec![
            json!(steps),
            json!(trained_s(&run)?),
            pm,
            sm,
            pf,
            near,
            far,
            json!(peak_mb(&run)),
        ]);
    }
    let (lv, finest) = levels(&run)?;
    // The loop's own speed between steps 50 and 250 (the first leg; logs every 25 steps).
    let m = metrics(&run)?;
    let at = |k: u64| {
        m.iter()
            .find(|x| x["step"].as_u64() == Some(k) && x["loss"].is_number())
            .and_then(|x| x["elapsed_s"].as_f64())
    };
    let loop_ms = match (at(50), at(250)) {
        (Some(a), Some(b)) => Some(1e3 * (b - a) / 200.0),
        _ => None,
    };
    // The no-learning baseline on the same held-out views.
    let ulr = c.w("small-ulr.json");
    let args = [
        "eval", "--scene", &scene, "--method", "ulr", "--json", &ulr, "-q",
    ];
    c.xscale(&args)?;
    s.commands.push(format!("xscale {}", args.join(" ")));
    let e = read_json(&c.root.join(&ulr))?;
    let (pm, sm, pf, near, far) = scores(&e);
    rows.push(vec![
        json!("ULR (no training)"),
        json!(0.0),
        pm,
        sm,
        pf,
        near,
        far,
        Value::Null,
    ]);
    s.tables.push(table(
        "",
        &[
            "steps",
            "training (s)",
            "masked PSNR (dB)",
            "masked SSIM",
            "full PSNR (dB)",
            "close-ups (dB)",
            "aerial (dB)",
            "peak memory (MB)",
        ],
        &[0, 1, 2, 3, 2, 2, 2, 0],
        rows,
    ));
    s.tables.push(table(
        "The run",
        &[
            "grid-H levels (automatic range)",
            "finest resolution (cells)",
            "loop ms per step (steps 50–250)",
            "loop pixels/s",
            "synth (s)",
        ],
        &[0, 0, 1, 0, 1],
        vec![vec![
            json!(lv),
            json!(finest),
            json!(loop_ms),
            json!(loop_ms.map(|ms| 4096.0 / ms * 1e3)),
            json!(synth_s),
        ]],
    ));
    Ok(s)
}

/// A bench's `rows`, each as the values of `keys` in that order.
fn columns(v: &Value, bench: &str, keys: &[&str]) -> Result<Vec<Vec<Value>>> {
    Ok(v["rows"]
        .as_array()
        .ok_or_else(|| anyhow!("{bench}: no rows"))?
        .iter()
        .map(|r| keys.iter().map(|k| r[*k].clone()).collect())
        .collect())
}

fn train_loop(c: &Ctx) -> Result<Section> {
    let v = c.bench("train_loop", &[])?;
    let rows = columns(
        &v,
        "train_loop",
        &[
            "threads",
            "pixels_per_s",
            "ms_per_step",
            "batch_ms",
            "forward_ms",
            "backward_ms",
            "adam_ms",
        ],
    )?;
    Ok(Section {
        commands: vec!["cargo bench --bench train_loop".into()],
        tables: vec![
            table(
                &format!(
                    "batch {} pixels, {} grid-H levels, best of {} rounds of {} steps",
                    v["batch"], v["levels"], v["rounds"], v["steps"]
                ),
                &[
                    "threads",
                    "pixels/s",
                    "ms/step",
                    "batch (ms)",
                    "forward (ms)",
                    "backward (ms)",
                    "Adam (ms)",
                ],
                &[0, 0, 2, 2, 2, 2, 2],
                rows,
            ),
            table(
                "",
                &["2 threads against 1 (×)"],
                &[2],
                vec![vec![v["two_over_one"].clone()]],
            ),
        ],
        ..Section::default()
    })
}

fn skips(c: &Ctx) -> Result<Section> {
    let v = c.bench("skips", &[])?;
    let rows = columns(
        &v,
        "skips",
        &[
            "configuration",
            "ms_per_step",
            "vs_default",
            "sub_samples",
            "levels",
        ],
    )?;
    Ok(Section {
        commands: vec!["cargo bench --bench skips".into()],
        tables: vec![table(
            &format!(
                "best of {} rounds of {} steps; each line the default with one change",
                v["rounds"], v["steps"]
            ),
            &[
                "configuration",
                "ms/step",
                "time against the default (×)",
                "sub-samples per step",
                "grid-H levels",
            ],
            &[0, 2, 2, 0, 0],
            rows,
        )],
        ..Section::default()
    })
}

fn torch_peer(c: &Ctx) -> Result<Section> {
    let v = c.bench("torch_peer", &[])?;
    let mut s = Section {
        commands: vec!["cargo bench --bench torch_peer".into()],
        ..Section::default()
    };
    if let Some(why) = v["skipped"].as_str() {
        s.notes.push(format!("Not measured on this host: {why}."));
        s.skipped = Some(why.to_string());
        return Ok(s);
    }
    let rows = v["peers"]
        .as_array()
        .ok_or_else(|| anyhow!("torch_peer: no peers"))?
        .iter()
        .map(|p| {
            vec![
                p["mode"].clone(),
                v["xscale_ms"].clone(),
                p["torch_ms"].clone(),
                p["ratio"].clone(),
                p["ratio_min"].clone(),
                p["ratio_max"].clone(),
            ]
        })
        .collect();
    s.tables.push(table(
        &format!(
            "{} pixels, {} threads, median of {} alternating rounds of {} steps (xscale, then each peer)",
            v["batch"], v["threads"], v["rounds"], v["steps"]
        ),
        &[
            "PyTorch peer",
            "xscale (ms/step)",
            "PyTorch (ms/step)",
            "PyTorch / xscale (×)",
            "lowest round (×)",
            "highest round (×)",
        ],
        &[0, 1, 1, 2, 2, 2],
        rows,
    ));
    Ok(s)
}

fn oracle(c: &Ctx) -> Result<Section> {
    let v = c.bench("oracle", &[])?;
    let modes: Vec<String> = v["modes"]
        .as_array()
        .ok_or_else(|| anyhow!("oracle: no modes"))?
        .iter()
        .map(|m| m.as_str().unwrap_or("?").to_string())
        .collect();
    let mut cols = vec!["".to_string()];
    cols.extend(modes.iter().cloned());
    let cols: Vec<&str> = cols.iter().map(String::as_str).collect();
    let row = |label: &str, key: &str| {
        let mut r = vec![json!(label)];
        r.extend(v[key].as_array().cloned().unwrap_or_default());
        r
    };
    let mut err_rows = Vec::new();
    for f in v["families"].as_array().into_iter().flatten() {
        let mut r = vec![f["family"].clone()];
        for e in f["max_abs_over_peak"].as_array().into_iter().flatten() {
            r.push(json!(match e.as_f64() {
                Some(0.0) => "0".to_string(),
                Some(x) => format!("{x:.2e}"),
                None => "—".to_string(),
            }));
        }
        err_rows.push(r);
    }
    let mut digits = vec![0];
    digits.extend(std::iter::repeat_n(1, modes.len()));
    let mut d2 = vec![0];
    d2.extend(std::iter::repeat_n(2, modes.len()));
    Ok(Section {
        commands: vec!["cargo bench --bench oracle".into()],
        tables: vec![
            table(
                &format!(
                    "{} pixels, {} threads, median of {} rounds; {} kink pixels",
                    v["pixels"], v["threads"], v["rounds"], v["kink_pixels"]
                ),
                &cols,
                &digits,
                vec![
                    row("time per dump (ms)", "wall_ms"),
                    row("CPU time per dump (ms)", "cpu_ms"),
                ],
            ),
            table(
                "",
                &cols,
                &d2,
                vec![row("time against the f64 dump (×)", "over_f64")],
            ),
            table(
                "Error against the f64 dump (max abs / peak)",
                &cols,
                &digits,
                err_rows,
            ),
        ],
        ..Section::default()
    })
}

/// The Python package's call overhead (`python/bench/bench_ops.py --json`).
fn python(c: &Ctx) -> Result<Section> {
    let py = std::env::var("XSCALE_PYTHON").unwrap_or_else(|_| "python3".into());
    let cmd = format!("{py} python/bench/bench_ops.py --rounds 7");
    let mut s = Section {
        commands: vec![cmd],
        ..Section::default()
    };
    let probe = Command::new(&py)
        .args(["-c", "import xscale"])
        .current_dir(&c.root)
        .output();
    if !probe.is_ok_and(|o| o.status.success()) {
        let why = format!(
            "`{py}` cannot import the package (`pip install ./python`; \
             XSCALE_PYTHON names another interpreter)"
        );
        s.notes.push(format!("Not measured on this host: {why}."));
        s.skipped = Some(why);
        return Ok(s);
    }
    let json = c.work.join("python.json");
    let bin = c.bin.display().to_string();
    let r = run_measured(
        Command::new(&py)
            .args([
                "python/bench/bench_ops.py",
                "--rounds",
                "7",
                "--xscale",
                &bin,
                "--json",
            ])
            .arg(&json)
            .current_dir(&c.root),
    )?;
    if !r.ok {
        bail!("python/bench/bench_ops.py: failed:\n{}", tail(&r.stderr));
    }
    let v = read_json(&json)?;
    let mut rows = Vec::new();
    for (name, o) in v["ops"].as_object().into_iter().flatten() {
        let mut row = vec![json!(name), o["f64"]["calls_per_step"].clone()];
        for p in ["f32", "f64"] {
            row.push(o[p]["wall_us"].clone());
            row.push(o[p]["rust_us"].clone());
            row.push(o[p]["overhead_us"].clone());
        }
        rows.push(row);
    }
    s.tables.push(table(
        &format!(
            "{} pixels ({} valid sub-samples), {} threads, median of {} rounds; Python {}, numpy {}; per call",
            v["pixels"], v["valid_subsamples"], v["threads"], v["rounds"],
            v["python"].as_str().unwrap_or("?"), v["numpy"].as_str().unwrap_or("?")
        ),
        &[
            "op",
            "calls per step",
            "f32 call (µs)",
            "f32 Rust (µs)",
            "f32 overhead (µs)",
            "f64 call (µs)",
            "f64 Rust (µs)",
            "f64 overhead (µs)",
        ],
        &[0, 0, 0, 0, 1, 0, 0, 1],
        rows,
    ));
    let st = &v["steps"];
    let row = |label: &str, key: &str, scale: f64| {
        vec![
            json!(label),
            json!(st["f32"][key].as_f64().map(|x| x * scale)),
            json!(st["f64"][key].as_f64().map(|x| x * scale)),
        ]
    };
    s.tables.push(table(
        "The whole step",
        &["", "f32", "f64"],
        &[0, 2, 2],
        vec![
            row("composed from the ops (ms)", "composed", 1.0),
            row("of which op calls (ms)", "ops", 1.0),
            row("of which the ops' overhead (ms)", "overhead", 1.0),
            row("overhead / composed step (%)", "share", 100.0),
            row("Model.step, one call (ms)", "step", 1.0),
            row("xscale dump round trip (ms)", "cli", 1.0),
            row("round trip / Model.step (×)", "ratio", 1.0),
        ],
    ));
    Ok(s)
}

fn render(c: &Ctx) -> Result<Section> {
    let out = c.w("small-run");
    let run = c.root.join(&out);
    let mut s = Section::default();
    if !run.join("checkpoint.safetensors").is_file() {
        bail!("no {}: run the small section first", run.display());
    }
    let e = read_json(&run.join("eval.json"))?;
    let view = e["views"][0]["view"]
        .as_str()
        .ok_or_else(|| anyhow!("{}: no view", run.display()))?
        .to_string();
    let dir = c.w("render");
    let args = [
        "render", "--run", &out, "--views", &view, "--scale", "6", "--out", &dir, "-q",
    ];
    let mut walls = Vec::new();
    let mut peak: f64 = 0.0;
    for _ in 0..5 {
        let r = c.xscale(&args)?;
        walls.push(r.wall_s);
        peak = peak.max(r.peak_mb.unwrap_or(0.0));
    }
    walls.sort_by(f64::total_cmp);
    s.commands
        .push(format!("xscale {}   (5 times)", args.join(" ")));
    s.tables.push(table(
        &format!(
            "view {view} at 6× its size, the model after {} steps",
            e["step"]
        ),
        &[
            "median (s)",
            "fastest (s)",
            "slowest (s)",
            "peak memory (MB)",
        ],
        &[2, 2, 2, 0],
        vec![vec![
            json!(walls[2]),
            json!(walls[0]),
            json!(walls[4]),
            json!(peak),
        ]],
    ));
    Ok(s)
}

/// The skull of `fixtures/prepare_skull` meshed into `target/results/skull` (the same bytes every
/// time), with a black background (its photos' backdrop), and the commands.
fn skull_scene(c: &Ctx, cmds: &mut Vec<String>) -> Result<String> {
    let dir = c.w("skull");
    let _ = std::fs::remove_dir_all(c.root.join(&dir));
    let args = [
        "prepare",
        "--sparse",
        "fixtures/prepare_skull",
        "--out",
        &dir,
    ];
    c.xscale(&args)?;
    cmds.push(format!("xscale {}", args.join(" ")));
    let toml = "background = [0, 0, 0]\n";
    std::fs::write(c.root.join(&dir).join("scene.toml"), toml)?;
    cmds.push(format!("({dir}/scene.toml: {})", toml.trim()));
    Ok(dir)
}

fn real(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let mut scenes = vec![("skull".to_string(), skull_scene(c, &mut s.commands)?)];
    if let Ok(list) = std::env::var("XSCALE_REAL_SCENES") {
        for d in list.split(':').filter(|d| !d.is_empty()) {
            let p = Path::new(d);
            let name = p
                .file_name()
                .map_or("scene".into(), |n| n.to_string_lossy().into_owned());
            scenes.push((name, d.to_string()));
        }
    }
    let mut rows = Vec::new();
    let mut wins = Vec::new();
    for (name, scene) in &scenes {
        let out = c.w(&format!("real-{name}"));
        let _ = std::fs::remove_dir_all(c.root.join(&out));
        let args = ["train", "--scene", scene, "--out", &out, "-q"];
        c.xscale(&args)?;
        s.commands.push(format!("xscale {}", args.join(" ")));
        let run = c.root.join(&out);
        let trained = read_json(&run.join("eval.json"))?;
        let mean_json = c.w(&format!("real-{name}-mean.json"));
        let args = [
            "eval",
            "--run",
            &out,
            "--appearance",
            "mean",
            "--json",
            &mean_json,
            "-q",
        ];
        c.xscale(&args)?;
        s.commands.push(format!("xscale {}", args.join(" ")));
        let ulr_json = c.w(&format!("real-{name}-ulr.json"));
        let args = [
            "eval", "--scene", scene, "--method", "ulr", "--json", &ulr_json, "-q",
        ];
        c.xscale(&args)?;
        s.commands.push(format!("xscale {}", args.join(" ")));
        let ulr = read_json(&c.root.join(&ulr_json))?;
        let views = trained["views"].as_array().map_or(0, |v| v.len());
        let row = |what: &str, e: &Value, secs: Value| {
            let m = &e["mean"];
            vec![
                json!(name),
                json!(what),
                json!(views),
                secs,
                m["psnr_masked"].clone(),
                m["ssim_masked"].clone(),
                m["flip_masked"].clone(),
                m["psnr"].clone(),
            ]
        };
        rows.push(row(
            "xscale, the default (cpu preset)",
            &trained,
            json!(trained_s(&run)?),
        ));
        rows.push(row(
            "the same model, held-out views with the mean code",
            &read_json(&c.root.join(&mean_json))?,
            json!(trained_s(&run)?),
        ));
        // Mesh refinement on the same scene: what it does to a real, reconstructed mesh.
        let refined = c.w(&format!("real-{name}-refine"));
        let _ = std::fs::remove_dir_all(c.root.join(&refined));
        let cfg = c.w("real-refine.toml");
        let text = "[model.refine]\nenabled = true\n";
        std::fs::write(c.root.join(&cfg), text)?;
        let args = [
            "train", "--scene", scene, "--out", &refined, "--config", &cfg, "-q",
        ];
        c.xscale(&args)?;
        s.commands.push(format!(
            "xscale {}   ({cfg}: {})",
            args.join(" "),
            text.trim().replace('\n', " ")
        ));
        let run_r = c.root.join(&refined);
        rows.push(row(
            "xscale with mesh refinement (`[model.refine] enabled = true`)",
            &read_json(&run_r.join("eval.json"))?,
            json!(trained_s(&run_r)?),
        ));
        rows.push(row("ULR (no training)", &ulr, json!(0.0)));
        let (a, b) = (&trained["mean"], &ulr["mean"]);
        let ahead = |k: &str, lower: bool| {
            let (x, y) = (
                a[k].as_f64().unwrap_or(f64::NAN),
                b[k].as_f64().unwrap_or(f64::NAN),
            );
            if lower {
                x < y
            } else {
                x > y
            }
        };
        let n = [
            ahead("psnr_masked", false),
            ahead("ssim_masked", false),
            ahead("flip_masked", true),
        ]
        .iter()
        .filter(|&&w| w)
        .count();
        wins.push(format!(
            "{name}: the default is ahead of ULR on {n} of the 3 masked scores"
        ));
    }
    s.tables.push(table(
        "held-out views, means over views",
        &[
            "scene",
            "method",
            "held-out views",
            "training (s)",
            "masked PSNR (dB)",
            "masked SSIM",
            "masked ꟻLIP",
            "full PSNR (dB)",
        ],
        &[0, 0, 0, 1, 2, 3, 3, 2],
        rows,
    ));
    s.notes.push(wins.join("; ") + ".");
    Ok(s)
}

/// The `cpu` preset's decays (halvings at 1000, then every 250 up to 1750, of its 2,000 written
/// steps) stretched to `steps` as `budget = "auto"` does (`LrSchedule::stretched`), as a config.
fn stretched_config(steps: u64) -> String {
    let at = |k: u64| (k * steps + 1000) / 2000;
    let mut t = format!("[train]\nsteps = {steps}\n");
    for g in ["shader", "deform", "grid_h", "grid_d"] {
        t += &format!(
            "[train.adam.{g}.schedule]\ndecay_start = {}\ndecay_interval = {}\ndecay_base = 0.5\ndecay_end = {}\n",
            at(1000),
            at(250),
            at(1750)
        );
    }
    t
}

/// The meshes of section `meshcheck`: the scene's own, turned a quarter about x, moved along z
/// by 5 % and along x by 3 % of its bounding box's diagonal, scaled by 1.1 (about the box's
/// centre), as `raycast::photo_check_neighbours_table` makes them.
fn wrong_meshes(mesh: &xscale::scene::Mesh) -> Vec<(&'static str, xscale::scene::Mesh)> {
    use glam::{DMat3, DVec3};
    let (lo, hi) = mesh.bbox();
    let (mid, diag) = (0.5 * (lo + hi), (hi - lo).length());
    let moved = |f: &dyn Fn(DVec3) -> DVec3| xscale::scene::Mesh {
        vertices: mesh.vertices.iter().map(|&v| f(v)).collect(),
        triangles: mesh.triangles.clone(),
    };
    let quarter = DMat3::from_rotation_x(std::f64::consts::FRAC_PI_2);
    vec![
        ("correct", mesh.clone()),
        ("turned 90° about x", moved(&|v| mid + quarter * (v - mid))),
        (
            "moved +z by 5% of the diagonal",
            moved(&|v| v + DVec3::Z * 0.05 * diag),
        ),
        (
            "moved +x by 3% of the diagonal",
            moved(&|v| v + DVec3::X * 0.03 * diag),
        ),
        ("scaled 1.1×", moved(&|v| mid + 1.1 * (v - mid))),
    ]
}

/// Whether the scene's COLMAP model has any reconstruction points (the synthetic scenes write
/// an empty `points3D.txt`).
fn has_points(scene: &Path) -> bool {
    let model = scene.join("sparse/0");
    match std::fs::read_to_string(model.join("points3D.txt")) {
        Ok(t) => t
            .lines()
            .any(|l| !l.starts_with('#') && !l.trim().is_empty()),
        Err(_) => model.join("points3D.bin").is_file(),
    }
}

/// The number after `key` in `line` (up to the next character that cannot be part of it).
fn number_after(line: &str, key: &str) -> Option<f64> {
    let rest = &line[line.find(key)? + key.len()..];
    let end = rest
        .find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))
        .unwrap_or(rest.len());
    rest[..end].parse().ok()
}

fn meshcheck(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let (small, _) = small_scene(c, &mut s.commands)?;
    let mut scenes = vec![
        ("tiny".to_string(), "fixtures/tiny".to_string()),
        ("small".to_string(), small),
        (
            "skull (fixtures/prepare_skull)".to_string(),
            skull_scene(c, &mut s.commands)?,
        ),
    ];
    if let Ok(list) = std::env::var("XSCALE_REAL_SCENES") {
        scenes.extend(
            (list.split(':').filter(|d| !d.is_empty())).map(|d| (d.to_string(), d.to_string())),
        );
    }
    let mut rows = Vec::new();
    let mut right = 0;
    for (name, scene) in &scenes {
        let mesh_path = c.root.join(scene).join("mesh.ply");
        let (mesh, _) = xscale::scene::mesh::load_mesh(&mesh_path)?;
        let tag = name.replace(|ch: char| !ch.is_ascii_alphanumeric(), "_");
        for (k, (what, m)) in wrong_meshes(&mesh).into_iter().enumerate() {
            let file = c.w(&format!("meshcheck-{tag}-{k}.ply"));
            xscale::scene::mesh::write_ply(&c.root.join(&file), &m)?;
            let args = ["cast", "--scene", scene, "--mesh", &file, "--gamma", "1"];
            let r = c.xscale(&args)?;
            if k == 0 || k == 1 {
                s.commands.push(format!("xscale {}", args.join(" ")));
            }
            let lines: Vec<&str> = r.stderr.lines().collect();
            let find = |key: &str| lines.iter().find(|l| l.contains(key)).copied();
            let correlation = find("photos see at the same surface points correlate")
                .and_then(|l| number_after(l, "correlate "));
            let photo_warns = find("warning: the colours two photos see").is_some();
            let beaten = find("agrees better with the photos than the mesh as given");
            let silent = find("no neighbour of the mesh");
            let (best, best_score, given) = match (beaten, silent) {
                (Some(l), _) => (
                    l.split(" agrees better")
                        .next()
                        .unwrap_or("")
                        .trim_start_matches("warning: the mesh ")
                        .to_string(),
                    number_after(l, "local correlation "),
                    number_after(l, " against "),
                ),
                (None, Some(l)) => (
                    l.split("the best, ")
                        .nth(1)
                        .and_then(|t| t.split(':').next())
                        .unwrap_or("")
                        .to_string(),
                    number_after(l, "local correlation "),
                    number_after(l, " against "),
                ),
                _ => (String::new(), None, None),
            };
            let points = lines
                .iter()
                .any(|l| l.contains("points of") && l.contains("another frame"))
                || lines.iter().any(|l| l.contains("lie inside its bounds"));
            let has_points = has_points(&c.root.join(scene));
            let warns = photo_warns || beaten.is_some() || points;
            right += usize::from(warns == (what != "correct"));
            let wins = beaten.or(silent).and_then(|l| {
                let t = &l[l.find("higher in ")? + "higher in ".len()..];
                Some(t.split(" view pairs").next()?.to_string())
            });
            rows.push(vec![
                json!(name),
                json!(what),
                json!(correlation),
                json!(given),
                json!(best),
                json!(best_score),
                json!(wins),
                json!(if beaten.is_some() { "warns" } else { "silent" }),
                json!(if !has_points {
                    "no points"
                } else if points {
                    "warns"
                } else {
                    "silent"
                }),
                json!(if warns { "warns" } else { "silent" }),
                json!(r.wall_s),
            ]);
        }
    }
    s.notes.push(format!(
        "{right} of {} meshes judged as they should be (a correct mesh silent, every other warned of).",
        rows.len()
    ));
    s.tables.push(table(
        "what `xscale cast` says of each mesh",
        &[
            "scene",
            "mesh",
            "photo correlation",
            "local correlation as given",
            "best neighbour",
            "its local correlation",
            "view pairs it wins",
            "neighbour check",
            "points check",
            "verdict",
            "cast (s)",
        ],
        &[0, 0, 2, 3, 0, 3, 0, 0, 0, 0, 1],
        rows,
    ));
    Ok(s)
}

fn budget(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let mut rows = Vec::new();
    for preset in ["small", "cross", "skull"] {
        let scene = if preset == "skull" {
            // A real capture as the third scene (section real's skull).
            skull_scene(c, &mut s.commands)?
        } else {
            let scene = c.w(&format!("budget-{preset}"));
            let _ = std::fs::remove_dir_all(c.root.join(&scene));
            let args = ["synth", "--preset", preset, "--seed", "1", "--out", &scene];
            c.xscale(&args)?;
            s.commands.push(format!("xscale {}", args.join(" ")));
            scene
        };
        let mut train =
            |cmds: &mut Vec<String>, what: &str, extra: &[&str], tag: &str| -> Result<u64> {
                let out = c.w(&format!("budget-{preset}-{tag}"));
                let _ = std::fs::remove_dir_all(c.root.join(&out));
                let mut args = vec!["train", "--scene", &scene, "--out", &out, "-q"];
                args.extend_from_slice(extra);
                let r = c.xscale(&args)?;
                cmds.push(format!("xscale {}", args.join(" ")));
                let e = read_json(&c.root.join(&out).join("eval.json"))?;
                let steps = e["step"].as_u64().unwrap_or(0);
                let (psnr_m, ssim_m, _, near, far) = scores(&e);
                rows.push(vec![
                    json!(preset),
                    json!(what),
                    json!(steps),
                    json!(r.wall_s),
                    psnr_m,
                    ssim_m,
                    near,
                    far,
                ]);
                Ok(steps)
            };
        let chosen = train(&mut s.commands, "the rule (the default)", &[], "rule")?;
        train(
            &mut s.commands,
            "fixed 2,000 steps",
            &["--steps", "2000"],
            "2000",
        )?;
        if preset != "small" {
            let cfg = c.w(&format!("budget-{preset}-3x.toml"));
            std::fs::write(c.root.join(&cfg), stretched_config(3 * chosen))?;
            s.commands.push(format!(
                "({cfg}: [train] steps = 3 × the rule's, the four decaying groups' schedules stretched to it)"
            ));
            train(
                &mut s.commands,
                "3× the rule's steps",
                &["--config", &cfg],
                "3x",
            )?;
        }
    }
    s.tables.push(table(
        "held-out views (seed 1), means over views",
        &[
            "scene",
            "run",
            "steps",
            "wall (s)",
            "masked PSNR (dB)",
            "masked SSIM",
            "close-ups (dB)",
            "aerial (dB)",
        ],
        &[0, 0, 0, 0, 2, 4, 2, 2],
        rows,
    ));
    s.notes.push("Close-ups and aerial views: the held-out views below and above the near/far split of `eval.json` (`by_scale.near_far`); on `small` the split is by footprint too.".into());
    Ok(s)
}

/// The model's parameter count of a checkpoint (its layout's total).
fn ckpt_params(path: &Path) -> Result<usize> {
    Ok(xscale::model::checkpoint::Checkpoint::load(path)?
        .model
        .layout
        .total)
}

/// Bytes of a run's tensors by part, from the safetensors headers of its model file and, beside
/// it, its optimizer state (`optimizer.safetensors`, if any): grid H, grid D (each whole, or its
/// stepped rows and row mask), the MLPs and appearance codes, and the Adam state (`adam.*`, its
/// row masks included).
fn ckpt_parts(path: &Path) -> Result<[u64; 4]> {
    use std::io::Read;
    let mut parts = [0u64; 4];
    for path in [
        path.to_path_buf(),
        xscale::train::state::optimizer_path(path),
    ] {
        if !path.is_file() {
            continue;
        }
        let mut f = std::fs::File::open(&path).with_context(|| format!("{}", path.display()))?;
        let mut n = [0u8; 8];
        f.read_exact(&mut n)?;
        let mut head = vec![0u8; u64::from_le_bytes(n) as usize];
        f.read_exact(&mut head)?;
        let h: Value = serde_json::from_slice(&head)?;
        for (name, t) in h.as_object().into_iter().flatten() {
            let Some(o) = t["data_offsets"].as_array() else {
                continue; // __metadata__
            };
            let bytes = o[1].as_u64().unwrap_or(0) - o[0].as_u64().unwrap_or(0);
            let i = if name.starts_with("adam.") {
                3
            } else if name.starts_with("grid_h.table") {
                0
            } else if name.starts_with("grid_d.table") {
                1
            } else {
                2
            };
            parts[i] += bytes;
        }
    }
    Ok(parts)
}

/// Seeds from an environment variable (comma-separated), or `default`.
fn env_seeds(var: &str, default: &str) -> Vec<String> {
    std::env::var(var)
        .unwrap_or_else(|_| default.into())
        .split(',')
        .map(|x| x.trim().to_string())
        .filter(|x| !x.is_empty())
        .collect()
}

fn sizing(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let fixed = c.w("sizing-fixed19.toml");
    std::fs::write(
        c.root.join(&fixed),
        "[model.grid_h]\nlog2_table_size = 19\n",
    )?;
    s.commands
        .push(format!("({fixed}: [model.grid_h] log2_table_size = 19)"));
    let seeds = env_seeds("XSCALE_SIZING_SEEDS", "0,1,2");
    let large_seeds = env_seeds("XSCALE_SIZING_LARGE_SEEDS", "");
    let tag_name = |t: &str| if t == "fixed" { "fixed 2^19" } else { "auto" };
    let mut size_rows = Vec::new();
    let mut run_rows = Vec::new();
    let mut part_rows = Vec::new();
    // (scene, tables, PSNR, checkpoint MB, close-ups, aerial) per run.
    type Means = (String, String, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>);
    let mut means: Vec<Means> = Vec::new();
    for preset in ["tiny", "small", "cross", "large"] {
        let scene = c.w(&format!("sizing-{preset}"));
        let args = ["synth", "--preset", preset, "--seed", "1", "--out", &scene];
        c.xscale(&args)?;
        s.commands.push(format!("xscale {}", args.join(" ")));
        let mut params = [0usize; 2];
        for (i, tag) in ["fixed", "auto"].iter().enumerate() {
            let out = c.w(&format!("sizing-{preset}-{tag}-init.safetensors"));
            let mut args = vec!["init", "--scene", &scene, "--out", &out];
            if *tag == "fixed" {
                args.extend_from_slice(&["--config", &fixed]);
            }
            c.xscale(&args)?;
            s.commands.push(format!("xscale {}", args.join(" ")));
            params[i] = ckpt_params(&c.root.join(&out))?;
            let _ = std::fs::remove_file(c.root.join(&out));
        }
        size_rows.push(vec![
            json!(preset),
            json!(params[0]),
            json!(params[1]),
            json!(params[1] as f64 / params[0] as f64),
        ]);
        let seeds = if preset == "large" {
            large_seeds.clone()
        } else {
            seeds.clone()
        };
        if seeds.is_empty() {
            continue;
        }
        for tag in ["fixed", "auto"] {
            means.push((
                preset.into(),
                tag.into(),
                Vec::new(),
                Vec::new(),
                Vec::new(),
                Vec::new(),
            ));
        }
        let n = means.len();
        for seed in &seeds {
            for (i, tag) in ["fixed", "auto"].iter().enumerate() {
                let out = c.w(&format!("sizing-{preset}-{tag}-{seed}"));
                let _ = std::fs::remove_dir_all(c.root.join(&out));
                let mut args = vec![
                    "train", "--scene", &scene, "--out", &out, "--seed", seed, "-q",
                ];
                if *tag == "fixed" {
                    args.extend_from_slice(&["--config", &fixed]);
                }
                let r = c.xscale(&args)?;
                s.commands.push(format!("xscale {}", args.join(" ")));
                let run = c.root.join(&out);
                let e = read_json(&run.join("eval.json"))?;
                let ckpt = run.join("checkpoint.safetensors");
                let bytes = std::fs::metadata(&ckpt)?.len();
                let opt_bytes = std::fs::metadata(xscale::train::state::optimizer_path(&ckpt))
                    .map_or(0, |m| m.len());
                let (psnr, _, _, near, far) = scores(&e);
                let f = |v: &Value| v.as_f64().unwrap_or(f64::NAN);
                let m = &mut means[n - 2 + i];
                m.2.push(f(&psnr));
                m.3.push(bytes as f64 / 1e6);
                m.4.push(f(&near));
                m.5.push(f(&far));
                if seed == &seeds[0] {
                    let p = ckpt_parts(&ckpt)?;
                    let mut row = vec![json!(preset), json!(tag_name(tag))];
                    row.extend(p.iter().map(|&b| json!(b as f64 / 1e6)));
                    row.push(json!(bytes as f64 / 1e6));
                    row.push(json!(opt_bytes as f64 / 1e6));
                    part_rows.push(row);
                }
                run_rows.push(vec![
                    json!(preset),
                    json!(tag_name(tag)),
                    json!(seed),
                    e["step"].clone(),
                    json!(bytes as f64 / 1e6),
                    json!(opt_bytes as f64 / 1e6),
                    psnr,
                    near,
                    far,
                    json!(r.wall_s),
                    json!(peak_mb(&run)),
                ]);
            }
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let mean_rows = means
        .iter()
        .map(|(p, t, psnr, mb, near, far)| {
            vec![
                json!(p),
                json!(tag_name(t)),
                json!(psnr.len()),
                json!(mean(mb)),
                json!(mean(psnr)),
                json!(mean(near)),
                json!(mean(far)),
            ]
        })
        .collect();
    s.tables.push(table(
        "parameters of the model `xscale init` builds",
        &["scene", "fixed 2^19", "auto", "auto / fixed"],
        &[0, 0, 0, 3],
        size_rows,
    ));
    s.tables.push(table(
        "trained with the default budget, held-out views",
        &[
            "scene",
            "tables",
            "seed",
            "steps",
            "checkpoint (MB)",
            "optimizer state (MB)",
            "masked PSNR (dB)",
            "close-ups (dB)",
            "aerial (dB)",
            "wall (s)",
            "peak memory (MB)",
        ],
        &[0, 0, 0, 0, 1, 1, 2, 2, 2, 0, 0],
        run_rows,
    ));
    s.tables.push(table(
        "means over the seeds",
        &[
            "scene",
            "tables",
            "seeds",
            "checkpoint (MB)",
            "masked PSNR (dB)",
            "close-ups (dB)",
            "aerial (dB)",
        ],
        &[0, 0, 0, 1, 2, 2, 2],
        mean_rows,
    ));
    s.tables.push(table(
        "what the checkpoint holds (first seed's run, MB of tensor data)",
        &[
            "scene",
            "tables",
            "grid H",
            "grid D",
            "MLPs and codes",
            "Adam state",
            "checkpoint file",
            "optimizer file",
        ],
        &[0, 0, 2, 2, 3, 2, 2, 2],
        part_rows,
    ));
    s.notes.push("Close-ups and aerial views: the held-out views below and above the near/far split of `eval.json` (`by_scale.near_far`); on `tiny` and `small` the split is by footprint too. `large` is trained only with `XSCALE_SIZING_LARGE_SEEDS` set (its parameters are always counted).".into());
    let v = c.bench("sizing", &[])?;
    s.commands.push("cargo bench --bench sizing".into());
    s.tables.push(table(
        "a training step on `small` and `cross`, 2 threads (best of alternating rounds)",
        &[
            "scene",
            "batch (pixels)",
            "fixed 2^19 (ms)",
            "auto (ms)",
            "fixed / auto",
            "fixed parameters",
            "auto parameters",
        ],
        &[0, 0, 1, 1, 2, 0, 0],
        columns(
            &v,
            "sizing",
            &[
                "scene",
                "batch",
                "fixed_ms",
                "auto_ms",
                "fixed_over_auto",
                "fixed_params",
                "auto_params",
            ],
        )?,
    ));
    Ok(s)
}

fn sizing_render(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let runs = ["fixed", "auto"].map(|t| c.w(&format!("sizing-small-{t}-0")));
    for r in &runs {
        if !c.root.join(r).join("checkpoint.safetensors").is_file() {
            bail!("no {r}: run the sizing section first");
        }
    }
    let e = read_json(&c.root.join(&runs[1]).join("eval.json"))?;
    let view = e["views"][0]["view"]
        .as_str()
        .ok_or_else(|| anyhow!("{}: no view", runs[1]))?
        .to_string();
    let dir = c.w("sizing-render");
    let mut walls = [Vec::new(), Vec::new()];
    let mut peak = [0.0f64; 2];
    for _ in 0..5 {
        for (i, r) in runs.iter().enumerate() {
            let args = [
                "render", "--run", r, "--views", &view, "--scale", "6", "--out", &dir, "-q",
            ];
            let ran = c.xscale(&args)?;
            walls[i].push(ran.wall_s);
            peak[i] = peak[i].max(ran.peak_mb.unwrap_or(0.0));
        }
    }
    for (i, r) in runs.iter().enumerate() {
        s.commands.push(format!(
            "xscale render --run {r} --views {view} --scale 6 --out {dir} -q   (5 times, alternating)"
        ));
        walls[i].sort_by(f64::total_cmp);
    }
    let rows = (0..2)
        .map(|i| {
            vec![
                json!(["fixed 2^19", "auto"][i]),
                json!(walls[i][2]),
                json!(walls[i][0]),
                json!(walls[i][4]),
                json!(peak[i]),
            ]
        })
        .collect();
    s.tables.push(table(
        &format!("view {view} at 6× its size"),
        &[
            "tables",
            "median (s)",
            "fastest (s)",
            "slowest (s)",
            "peak memory (MB)",
        ],
        &[0, 2, 2, 2, 0],
        rows,
    ));
    s.notes.push(format!(
        "Fixed / auto (medians): {:.2}×.",
        walls[0][2] / walls[1][2]
    ));
    // Where the auto model's time goes: the same command at --scale 0.05 (a 40×30 frame: mapping
    // the checkpoint, loading the scene, building the BVH) against the full frame, alternating;
    // with XSCALE_RENDER_BEFORE=<an older xscale binary>, that binary's full frame too (its PNG
    // must be the same bytes), for a before/after ratio measured in one run.
    let before = std::env::var("XSCALE_RENDER_BEFORE").ok();
    let r = &runs[1];
    let png = c
        .root
        .join(&dir)
        .join(Path::new(&view).with_extension("png"));
    let mut cases: Vec<(String, PathBuf, &str)> = vec![
        (
            "this build, --scale 0.05 (load, scene, BVH)".into(),
            c.bin.clone(),
            "0.05",
        ),
        ("this build, --scale 6".into(), c.bin.clone(), "6"),
    ];
    if let Some(b) = &before {
        cases.push((format!("{b}, --scale 6"), PathBuf::from(b), "6"));
    }
    let mut times = vec![Vec::new(); cases.len()];
    let mut reference: Option<Vec<u8>> = None;
    for _ in 0..5 {
        for (k, (_, bin, scale)) in cases.iter().enumerate() {
            let args = [
                "render", "--run", r, "--views", &view, "--scale", scale, "--out", &dir, "-q",
            ];
            let ran = run_measured(Command::new(bin).args(args).current_dir(&c.root))?;
            if !ran.ok {
                bail!(
                    "{} {}: failed:\n{}",
                    bin.display(),
                    args.join(" "),
                    tail(&ran.stderr)
                );
            }
            times[k].push(ran.wall_s);
            if *scale == "6" {
                let bytes = std::fs::read(&png)
                    .with_context(|| format!("{}: cannot read", png.display()))?;
                match &reference {
                    None => reference = Some(bytes),
                    Some(b) if *b == bytes => {}
                    Some(_) => bail!("{}: not the same PNG bytes as this build's", bin.display()),
                }
            }
        }
    }
    for (label, _, scale) in &cases {
        s.commands.push(format!(
            "{label}: xscale render --run {r} --views {view} --scale {scale} --out {dir} -q   (5 times, alternating)"
        ));
    }
    for t in times.iter_mut() {
        t.sort_by(f64::total_cmp);
    }
    let mp = 1200.0 * 900.0 / 1e6;
    let rows = (cases.iter().zip(&times))
        .map(|((label, _, _), t)| vec![json!(label), json!(t[2]), json!(t[0]), json!(t[4])])
        .collect();
    s.tables.push(table(
        &format!("view {view}, auto tables: fixed costs against the frame"),
        &["command", "median (s)", "fastest (s)", "slowest (s)"],
        &[0, 2, 2, 2],
        rows,
    ));
    s.notes.push(format!(
        "This build: {:.2} s per megapixel for the whole command; {:.2} s of it fixed (load, scene, BVH), {:.2} s per megapixel for casting, shading and writing.",
        times[1][2] / mp,
        times[0][2],
        (times[1][2] - times[0][2]) / mp
    ));
    if before.is_some() {
        s.notes.push(format!(
            "Before / this build (medians of the full frame): {:.2}×; the same PNG bytes.",
            times[2][2] / times[1][2]
        ));
    }
    Ok(s)
}

const BQ_MINUTES: &str = "0.5";

/// The configurations `bench-quality` runs on the real capture (the default, the fastest step
/// and the largest batch of the `small` table, mesh refinement, and the no-learning baseline).
const BQ_REAL_CONFIGS: &str = "cpu,cpu-refine,cpu-gamma1,cpu-batch16k,ulr";

fn bench_quality(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let (scene, _) = small_scene(c, &mut s.commands)?;
    let out = c.w("bench-quality");
    let args = [
        "bench-quality",
        "--scene",
        &scene,
        "--out",
        &out,
        "--minutes",
        BQ_MINUTES,
        "--overwrite",
    ];
    c.xscale(&args)?;
    s.commands.push(format!("xscale {}", args.join(" ")));
    let (last, all) = bench_rows(&c.root.join(&out))?;
    let cols = [
        "configuration",
        "training (s)",
        "steps",
        "masked PSNR (dB)",
        "masked SSIM",
        "close-ups (dB)",
        "aerial (dB)",
    ];
    s.tables.push(table(
        &format!("At the full budget ({BQ_MINUTES} min), best first"),
        &cols,
        &[0, 1, 0, 2, 3, 2, 2],
        last,
    ));
    s.tables.push(table(
        "Every evaluation (the rows of bench.csv)",
        &cols,
        &[0, 1, 0, 2, 3, 2, 2],
        all,
    ));
    std::fs::copy(
        c.root.join(&out).join("pareto.png"),
        c.docs.join("results/bench-quality.png"),
    )?;
    s.images.push((
        "results/bench-quality.png".into(),
        "held-out masked PSNR against training seconds".into(),
    ));
    // A real capture: the skull of fixtures/prepare_skull (section real).
    let skull = skull_scene(c, &mut s.commands)?;
    let out = c.w("bench-quality-skull");
    let args = [
        "bench-quality",
        "--scene",
        &skull,
        "--out",
        &out,
        "--minutes",
        BQ_MINUTES,
        "--configs",
        BQ_REAL_CONFIGS,
        "--overwrite",
    ];
    c.xscale(&args)?;
    s.commands.push(format!("xscale {}", args.join(" ")));
    let (last, _) = bench_rows(&c.root.join(&out))?;
    // One scale: near/far are absent on this capture; drop the two columns.
    let last = last.into_iter().map(|r| r[..5].to_vec()).collect();
    s.tables.push(table(
        &format!(
            "On a real capture, the skull of `fixtures/prepare_skull` (2 held-out views), at the full budget ({BQ_MINUTES} min), best first"
        ),
        &cols[..5],
        &[0, 1, 0, 2, 3],
        last,
    ));
    Ok(s)
}

/// The rows of a `bench-quality` folder's `bench.csv`: the last evaluation of each configuration
/// (at the full budget), best masked PSNR first, and every evaluation, each as configuration,
/// wall seconds, step, masked PSNR, masked SSIM, close-ups and aerial PSNR.
type BenchRows = (Vec<Vec<Value>>, Vec<Vec<Value>>);

fn bench_rows(dir: &Path) -> Result<BenchRows> {
    let csv = std::fs::read_to_string(dir.join("bench.csv"))?;
    let mut lines = csv.lines();
    let head: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n);
    let (ci, wi, si, pi, qi, ni, fi) = (
        col("config"),
        col("wall_s"),
        col("step"),
        col("psnr_masked"),
        col("ssim_masked"),
        col("psnr_near"),
        col("psnr_far"),
    );
    let mut rows: Vec<Vec<String>> = lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect();
    let num = |r: &Vec<String>, i: Option<usize>| -> Value {
        i.and_then(|i| r.get(i))
            .and_then(|x| x.parse::<f64>().ok())
            .map_or(Value::Null, |x| json!(x))
    };
    let name = |r: &Vec<String>| ci.and_then(|i| r.get(i)).cloned().unwrap_or_default();
    // Every evaluation, and the last of each configuration (at the full budget).
    rows.sort_by(|a, b| {
        name(a).cmp(&name(b)).then(
            num(a, wi)
                .as_f64()
                .unwrap_or(0.0)
                .total_cmp(&num(b, wi).as_f64().unwrap_or(0.0)),
        )
    });
    let mut last: Vec<Vec<Value>> = Vec::new();
    let mut all: Vec<Vec<Value>> = Vec::new();
    for (k, r) in rows.iter().enumerate() {
        let v = vec![
            json!(name(r)),
            num(r, wi),
            num(r, si),
            num(r, pi),
            num(r, qi),
            num(r, ni),
            num(r, fi),
        ];
        if rows.get(k + 1).is_none_or(|n| name(n) != name(r)) {
            last.push(v.clone());
        }
        all.push(v);
    }
    last.sort_by(|a, b| {
        b[3].as_f64()
            .unwrap_or(0.0)
            .total_cmp(&a[3].as_f64().unwrap_or(0.0))
    });
    Ok((last, all))
}

const ABLATE_STEPS: &str = "1000";

fn ablation(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let (scene, _) = small_scene(c, &mut s.commands)?;
    let out = c.w("ablate");
    let args = [
        "ablate",
        "--scene",
        &scene,
        "--out",
        &out,
        "--steps",
        ABLATE_STEPS,
        "--overwrite",
    ];
    c.xscale(&args)?;
    s.commands.push(format!("xscale {}", args.join(" ")));
    let a = read_json(&c.root.join(&out).join("ablation.json"))?;
    let rows = a["results"]
        .as_array()
        .ok_or_else(|| anyhow!("ablation.json: no results"))?
        .iter()
        .map(|r| {
            vec![
                r["name"].clone(),
                r["featurization"].clone(),
                r["mesh_faces"].clone(),
                r["gamma"].clone(),
                json!(if r["deform"].as_bool() == Some(true) {
                    "on"
                } else {
                    "off"
                }),
                r["params"].clone(),
                r["mean"]["psnr_masked"].clone(),
                r["mean"]["ssim_masked"].clone(),
                r["mean"]["psnr"].clone(),
                r["train_seconds"].clone(),
            ]
        })
        .collect();
    s.tables.push(table(
        &format!(
            "preset `{}`, {} steps of {} pixels, seed {}",
            a["preset"].as_str().unwrap_or("?"),
            a["steps"],
            a["batch_pixels"],
            a["seed"]
        ),
        &[
            "variant",
            "featurization",
            "mesh faces",
            "γ",
            "ξ",
            "parameters",
            "masked PSNR (dB)",
            "masked SSIM",
            "full PSNR (dB)",
            "training (s)",
        ],
        &[0, 0, 0, 0, 0, 0, 2, 3, 2, 1],
        rows,
    ));
    let claims = a["claims"]
        .as_array()
        .map(|v| {
            v.iter()
                .map(|c| {
                    vec![
                        c["claim"].clone(),
                        json!(match c["holds"].as_bool() {
                            Some(true) => "holds",
                            Some(false) => "does not hold",
                            None => "not run",
                        }),
                        c["measured"].clone(),
                    ]
                })
                .collect()
        })
        .unwrap_or_default();
    s.tables.push(table(
        "The claims `xscale ablate` checks",
        &["claim", "verdict", "measured"],
        &[0, 0, 0],
        claims,
    ));
    Ok(s)
}

fn cross(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let scene = c.w("cross");
    let args = ["synth", "--preset", "cross", "--seed", "1", "--out", &scene];
    c.xscale(&args)?;
    s.commands.push(format!("xscale {}", args.join(" ")));
    let variants: [(&str, &str, Option<&str>); 3] = [
        (
            "automatic level range, footprint weighting (the `cpu` default)",
            "cross-auto",
            None,
        ),
        (
            "the preset's fixed range (`[train] level_range = \"fixed\"`)",
            "cross-fixed",
            Some("[train]\nlevel_range = \"fixed\"\n"),
        ),
        (
            "no level weighting (`[model] level_weight = \"none\"`)",
            "cross-noweight",
            Some("[model]\nlevel_weight = \"none\"\n"),
        ),
    ];
    let mut rows = Vec::new();
    for (what, name, cfg) in variants {
        let out = c.w(name);
        let _ = std::fs::remove_dir_all(c.root.join(&out));
        let mut args = vec!["train", "--scene", &scene, "--out", &out, "-q"];
        let cfg_path = c.w(&format!("{name}.toml"));
        if let Some(text) = cfg {
            std::fs::write(c.root.join(&cfg_path), text)?;
            args.extend(["--config", &cfg_path]);
        }
        c.xscale(&args)?;
        let mut cmd = format!("xscale {}", args.join(" "));
        if let Some(text) = cfg {
            cmd += &format!("   ({cfg_path}: {})", text.trim().replace('\n', " "));
        }
        s.commands.push(cmd);
        let run = c.root.join(&out);
        let e = read_json(&run.join("eval.json"))?;
        let (pm, _, _, near, far) = scores(&e);
        let (lv, finest) = levels(&run)?;
        rows.push(vec![
            json!(what),
            json!(lv),
            json!(finest),
            e["step"].clone(),
            json!(trained_s(&run)?),
            near,
            far,
            pm,
            json!(peak_mb(&run)),
        ]);
    }
    let ulr = c.w("cross-ulr.json");
    let args = [
        "eval", "--scene", &scene, "--method", "ulr", "--json", &ulr, "-q",
    ];
    c.xscale(&args)?;
    s.commands.push(format!("xscale {}", args.join(" ")));
    let e = read_json(&c.root.join(&ulr))?;
    let (pm, _, _, near, far) = scores(&e);
    rows.push(vec![
        json!("ULR (no training)"),
        Value::Null,
        Value::Null,
        Value::Null,
        json!(0.0),
        near,
        far,
        pm,
        Value::Null,
    ]);
    s.tables.push(table(
        "held-out masked PSNR",
        &[
            "configuration",
            "grid-H levels",
            "finest resolution (cells)",
            "steps",
            "training (s)",
            "close-ups (dB)",
            "aerial (dB)",
            "all (dB)",
            "peak memory (MB)",
        ],
        &[0, 0, 0, 0, 0, 2, 2, 2, 0],
        rows,
    ));
    Ok(s)
}

/// Steps of every run of section `geometry_cross`.
const GEO_CROSS_STEPS: &str = "1000";
/// The proxy of section `geometry_cross`: RMS in % of the diagonal.
const GEO_CROSS_RMS: &str = "0.36";

fn geometry_cross(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let out = c.w("geo-cross");
    let rms = format!("0,{GEO_CROSS_RMS}");
    let common = [
        "--steps",
        GEO_CROSS_STEPS,
        "--decimate",
        "0",
        "--deform",
        "on",
        "-q",
    ];
    let mut args = vec![
        "bench-geometry",
        "--scene-preset",
        "cross",
        "--out",
        &out,
        "--rms",
        &rms,
        "--refine",
        "off,on",
        "--config",
        "configs/refine-cross.toml",
    ];
    args.extend(common);
    c.xscale(&args)?;
    s.commands.push(format!("xscale {}", args.join(" ")));
    let before = c.w("geo-cross-before");
    let scene = format!("{out}/scene");
    let mut args = vec![
        "bench-geometry",
        "--scene",
        &scene,
        "--out",
        &before,
        "--rms",
        &rms,
        "--refine",
        "on",
    ];
    args.extend(common);
    c.xscale(&args)?;
    s.commands.push(format!("xscale {}", args.join(" ")));
    let now = read_json(&c.root.join(&out).join("geometry.json"))?;
    let was = read_json(&c.root.join(&before).join("geometry.json"))?;
    let variant = |rep: &Value, name: &str| -> Result<Value> {
        rep["variants"]
            .as_array()
            .and_then(|v| v.iter().find(|x| x["name"] == name))
            .cloned()
            .with_context(|| format!("geometry.json has no variant {name}"))
    };
    let proxy_name = format!("rms{GEO_CROSS_RMS}");
    let proxy_rms = now["proxies"]
        .as_array()
        .and_then(|v| v.iter().find(|p| p["name"] == proxy_name.as_str()))
        .map(|p| p["to_truth"]["rms"].clone())
        .unwrap_or(Value::Null);
    let exact = variant(&now, "exact_xi")?;
    let fixed = variant(&now, &format!("{proxy_name}_xi"))?;
    let near = |v: &Value| v["near"]["psnr_masked"].as_f64();
    let (e, f) = (near(&exact), near(&fixed));
    let recovered = |v: &Value| -> Value {
        match (e, f, near(v)) {
            (Some(e), Some(f), Some(r)) if e > f => json!(100.0 * (r - f) / (e - f)),
            _ => Value::Null,
        }
    };
    let mut rows = Vec::new();
    let rows_of: [(&str, &str, &Value, String); 6] = [
        ("exact", "fixed", &now, "exact_xi".into()),
        (
            "exact",
            "default (levels 2 → 0, pairs once)",
            &was,
            "exact_xi_refine".into(),
        ),
        (
            "exact",
            "cross-scale (`configs/refine-cross.toml`)",
            &now,
            "exact_xi_refine".into(),
        ),
        ("proxy", "fixed", &now, format!("{proxy_name}_xi")),
        (
            "proxy",
            "default (levels 2 → 0, pairs once)",
            &was,
            format!("{proxy_name}_xi_refine"),
        ),
        (
            "proxy",
            "cross-scale (`configs/refine-cross.toml`)",
            &now,
            format!("{proxy_name}_xi_refine"),
        ),
    ];
    for (mesh, how, rep, name) in rows_of {
        let v = variant(rep, &name)?;
        let geo = if v["refine"] == true {
            v["refined_to_truth"]["rms"].clone()
        } else if mesh == "exact" {
            json!(0.0)
        } else {
            proxy_rms.clone()
        };
        rows.push(vec![
            json!(mesh),
            json!(how),
            geo,
            v["near"]["psnr_masked"].clone(),
            v["far"]["psnr_masked"].clone(),
            v["all"]["psnr_masked"].clone(),
            if mesh == "proxy" && v["refine"] == true {
                recovered(&v)
            } else {
                Value::Null
            },
            v["train_seconds"].clone(),
        ]);
    }
    // The proxy's error in aerial pixel footprints: the held-out aerial views' median.
    let mut aerial: Vec<f64> = read_json(&c.root.join(&out).join("runs/exact_xi/eval.json"))?
        ["views"]
        .as_array()
        .map(|v| v.iter().filter_map(|x| x["footprint"].as_f64()).collect())
        .unwrap_or_default();
    aerial.sort_by(f64::total_cmp);
    let split = now["variants"][0]["far"]["views"].as_u64().unwrap_or(0) as usize;
    let far: Vec<f64> = aerial[aerial.len().saturating_sub(split)..].to_vec();
    if let (Some(r), Some(m)) = (proxy_rms.as_f64(), far.get(far.len() / 2)) {
        s.notes.push(format!(
            "The proxy's RMS error {r:.3} m is {:.2} median footprints of the held-out aerial views ({m:.3} m).",
            r / m
        ));
    }
    s.notes.push("Training times are those of the runs as trained, one after another while other builds loaded the host: compare them loosely. A reused run keeps its recorded time.".into());
    {}
    s.tables.push(table(
        &format!("held-out masked PSNR, {GEO_CROSS_STEPS} steps, ξ on"),
        &[
            "mesh",
            "refinement",
            "geometry error RMS (m)",
            "close-ups (dB)",
            "aerial (dB)",
            "all (dB)",
            "close-up loss recovered (%)",
            "training (s)",
        ],
        &[0, 0, 3, 2, 2, 2, 0, 0],
        rows,
    ));
    Ok(s)
}

/// Training seeds of section `refine` on the exact mesh (the proxy runs with the first).
const REFINE_SEEDS: [u64; 3] = [0, 1, 2];

fn refine(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let mut rows = Vec::new();
    // (mesh, refinement) → PSNR per seed, and training seconds.
    let mut by: std::collections::BTreeMap<(String, bool), Vec<(f64, f64)>> = Default::default();
    let first = c.w(&format!("refine-s{}", REFINE_SEEDS[0]));
    let scene = format!("{first}/scene");
    for seed in REFINE_SEEDS {
        let out = c.w(&format!("refine-s{seed}"));
        let _ = std::fs::remove_dir_all(c.root.join(&out));
        let seed_s = seed.to_string();
        let rms = if seed == REFINE_SEEDS[0] {
            "0,0.3"
        } else {
            "0"
        };
        let mut args = vec!["bench-geometry"];
        if seed == REFINE_SEEDS[0] {
            args.extend(["--scene-preset", "small", "--synth-seed", "1"]);
        } else {
            args.extend(["--scene", &scene]);
        }
        args.extend([
            "--out",
            &out,
            "--seed",
            &seed_s,
            "--rms",
            rms,
            "--decimate",
            "0",
            "--deform",
            "on",
            "--refine",
            "on,off",
            "-q",
        ]);
        c.xscale(&args)?;
        s.commands.push(format!("xscale {}", args.join(" ")));
        let rep = read_json(&c.root.join(&out).join("geometry.json"))?;
        for v in rep["variants"].as_array().into_iter().flatten() {
            let proxy = v["proxy"].as_str().unwrap_or("?").to_string();
            let on = v["refine"].as_bool().unwrap_or(false);
            let psnr = v["all"]["psnr_masked"].as_f64().unwrap_or(f64::NAN);
            let secs = v["train_seconds"].as_f64().unwrap_or(f64::NAN);
            by.entry((proxy.clone(), on))
                .or_default()
                .push((psnr, secs));
            rows.push(vec![
                json!(proxy),
                json!(seed),
                json!(if on { "on" } else { "off" }),
                v["steps"].clone(),
                v["all"]["psnr_masked"].clone(),
                v["all"]["ssim_masked"].clone(),
                v["near"]["psnr_masked"].clone(),
                v["far"]["psnr_masked"].clone(),
                v["train_seconds"].clone(),
            ]);
        }
    }
    s.tables.push(table(
        "every run: held-out masked scores",
        &[
            "mesh",
            "seed",
            "refinement",
            "steps",
            "PSNR (dB)",
            "SSIM",
            "close-ups (dB)",
            "aerial (dB)",
            "training (s)",
        ],
        &[0, 0, 0, 0, 2, 4, 2, 2, 0],
        rows,
    ));
    // Mean PSNR and mean training seconds of a group of runs.
    let mean = |v: &[(f64, f64)]| {
        let n = v.len() as f64;
        (
            v.iter().map(|p| p.0).sum::<f64>() / n,
            v.iter().map(|p| p.1).sum::<f64>() / n,
        )
    };
    let mut summary = Vec::new();
    for proxy in by
        .keys()
        .map(|k| k.0.clone())
        .collect::<std::collections::BTreeSet<_>>()
    {
        let (Some(on), Some(off)) = (
            by.get(&(proxy.clone(), true)),
            by.get(&(proxy.clone(), false)),
        ) else {
            continue;
        };
        let ((psnr_on, s_on), (psnr_off, s_off)) = (mean(on), mean(off));
        summary.push(vec![
            json!(proxy),
            json!(on.len().min(off.len())),
            json!(psnr_off),
            json!(psnr_on),
            json!(psnr_on - psnr_off),
            json!(s_on / s_off),
        ]);
    }
    s.tables.push(table(
        "means over seeds: what refinement gains (negative: costs) and its time",
        &[
            "mesh",
            "seeds",
            "off (dB)",
            "on (dB)",
            "on − off (dB)",
            "training time on / off",
        ],
        &[0, 0, 2, 2, 2, 2],
        summary,
    ));
    Ok(s)
}

// ---------------------------------------------------------------- host, date, commit

/// Whether `name` is an executable file on the PATH.
fn on_path(name: &str) -> bool {
    std::env::var_os("PATH")
        .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join(name).is_file()))
}

/// Steps of the `cpu` preset the `prepare` section trains each capture for.
const PREPARE_STEPS: u64 = 500;

fn prepare(c: &Ctx) -> Result<Section> {
    let mut s = Section::default();
    let colmap = on_path("colmap");
    // (a) The mesher against a true surface.
    let r = run_measured(
        Command::new("cargo")
            .args([
                "build",
                "--release",
                "--locked",
                "--example",
                "prepare_synth",
            ])
            .current_dir(&c.root),
    )?;
    if !r.ok {
        bail!(
            "cargo build --example prepare_synth: failed:\n{}",
            tail(&r.stderr)
        );
    }
    let synth_bin = c.root.join("target/release/examples/prepare_synth");
    let synth = |dir: &str,
                 noise: &str,
                 outliers: &str,
                 side: &str,
                 cmds: &mut Vec<String>|
     -> Result<Value> {
        let args = [dir, "small", "400", noise, outliers, "1", "1", side];
        let r = run_measured(Command::new(&synth_bin).args(args).current_dir(&c.root))?;
        if !r.ok {
            bail!(
                "prepare_synth {}: failed:\n{}",
                args.join(" "),
                tail(&r.stderr)
            );
        }
        cmds.push(format!(
            "cargo run --release --example prepare_synth -- {}",
            args.join(" ")
        ));
        read_json(&c.root.join(dir).join("distances.json"))
    };
    let mut rows = Vec::new();
    let mut diag = 0.0;
    for (label, key, noise, outliers) in [
        ("exact", "exact", "0", "0"),
        ("noise 0.1 % + 2 % wrong matches", "noisy", "0.001", "0.02"),
    ] {
        for side in ["25", "8", "5"] {
            let dir = c.w(&format!("prepare-synth/{key}-{side}"));
            let _ = std::fs::remove_dir_all(c.root.join(&dir));
            let v = synth(&dir, noise, outliers, side, &mut s.commands)?;
            diag = v["diagonal"].as_f64().unwrap_or(f64::NAN);
            let m = &v["meshes"][0];
            let pct = |k: &str| json!(100.0 * m[k].as_f64().unwrap_or(f64::NAN) / diag);
            let name = if side == "8" {
                format!("xscale, --max-side {side} (default)")
            } else {
                format!("xscale, --max-side {side}")
            };
            rows.push(vec![
                json!(label),
                v["points"].clone(),
                json!(name),
                m["triangles"].clone(),
                pct("accuracy_rms"),
                pct("completeness_rms"),
                v["mesher_s"].clone(),
            ]);
            if side != "25" {
                continue;
            }
            // COLMAP's Poisson mesher on the same points (they do not depend on --max-side).
            if !colmap {
                rows.push(vec![
                    json!(label),
                    v["points"].clone(),
                    json!("COLMAP poisson_mesher: skipped (no `colmap` on the PATH)"),
                    Value::Null,
                    Value::Null,
                    Value::Null,
                    Value::Null,
                ]);
                continue;
            }
            let ply = format!("{dir}/points.ply");
            let out = format!("{dir}/meshed-poisson.ply");
            let args = [
                "poisson_mesher",
                "--input_path",
                &ply,
                "--output_path",
                &out,
            ];
            let r = run_measured(Command::new("colmap").args(args).current_dir(&c.root))?;
            s.commands.push(format!("colmap {}", args.join(" ")));
            if !r.ok {
                rows.push(vec![
                    json!(label),
                    v["points"].clone(),
                    json!("COLMAP poisson_mesher: failed"),
                    Value::Null,
                    Value::Null,
                    Value::Null,
                    Value::Null,
                ]);
                s.notes.push(format!(
                    "`colmap poisson_mesher` failed on the {key} points:\n\n```\n{}\n```",
                    tail(&r.stderr)
                ));
                continue;
            }
            // Measured by the example when OUT/meshed-poisson.ply exists (the rest is the same run).
            let v = synth(&dir, noise, outliers, side, &mut s.commands)?;
            let m = &v["meshes"][1];
            let pct = |k: &str| json!(100.0 * m[k].as_f64().unwrap_or(f64::NAN) / diag);
            rows.push(vec![
                json!(label),
                v["points"].clone(),
                json!("COLMAP poisson_mesher (defaults)"),
                m["triangles"].clone(),
                pct("accuracy_rms"),
                pct("completeness_rms"),
                json!(r.wall_s),
            ]);
        }
    }
    s.tables.push(table(
        &format!("The `small` scene (40 cameras; diagonal {diag:.1} m): RMS distances as a share of the diagonal"),
        &["points", "point count", "mesher", "triangles", "accuracy RMS (%)", "completeness RMS (%)", "meshing (s)"],
        &[0, 0, 0, 0, 3, 3, 1],
        rows,
    ));
    s.notes.push(
        "COLMAP's `delaunay_mesher` (what xscale's mesher reimplements) is not compared: the COLMAP \
         Debian ships (3.8 here) is built without CGAL (\"Delaunay meshing requires CGAL\")."
            .into(),
    );
    // (b) Real captures, photos to a trained model.
    let mut captures: Vec<(String, String, Option<String>, String, u64)> = Vec::new();
    captures.push((
        "skull (fixtures/prepare_skull, 10 photos)".into(),
        "fixtures/prepare_skull/images".into(),
        Some("fixtures/prepare_skull".into()),
        "1".into(),
        PREPARE_STEPS,
    ));
    if let Ok(p) = std::env::var("XSCALE_PREPARE_PHOTOS") {
        let steps = std::env::var("XSCALE_PREPARE_STEPS")
            .ok()
            .and_then(|x| x.parse().ok())
            .unwrap_or(2000);
        captures.push((
            format!("`{p}`"),
            p,
            std::env::var("XSCALE_PREPARE_POSES").ok(),
            std::env::var("XSCALE_PREPARE_DOWNSAMPLE").unwrap_or_else(|_| "1".into()),
            steps,
        ));
    }
    let mut stages = Vec::new();
    let mut summary = Vec::new();
    for (k, (label, photos, poses, down, steps)) in captures.iter().enumerate() {
        if !colmap {
            s.notes.push(format!("{label}: not measured on this host: `xscale prepare` from photos needs `colmap` on the PATH."));
            continue;
        }
        let out = c.w(&format!("prepare-{k}"));
        let _ = std::fs::remove_dir_all(c.root.join(&out));
        let mut args = vec!["prepare", "--photos", photos.as_str()];
        if let Some(p) = poses {
            args.extend(["--poses", p.as_str()]);
        }
        args.extend(["--downsample", down.as_str(), "--out", &out]);
        let load0 = load();
        s.commands.push(format!("xscale {}", args.join(" ")));
        let r = match c.xscale(&args) {
            Ok(r) => r,
            Err(e) => {
                // A capture COLMAP cannot reconstruct is a result too: said, not hidden.
                s.notes.push(format!(
                    "{label}: `xscale prepare` failed:\n\n```\n{e:#}\n```"
                ));
                continue;
            }
        };
        let rep = read_json(&c.root.join(&out).join("prepare.json"))?;
        for st in rep["seconds"].as_array().into_iter().flatten() {
            stages.push(vec![json!(label), st[0].clone(), st[1].clone()]);
        }
        stages.push(vec![
            json!(label),
            json!(format!(
                "prepare in all (load average {} at the start)",
                load0.map_or("?".into(), |l| format!("{l:.1}"))
            )),
            json!(r.wall_s),
        ]);
        let run = c.w(&format!("prepare-{k}-run"));
        let _ = std::fs::remove_dir_all(c.root.join(&run));
        let st = steps.to_string();
        let targs = [
            "train", "--scene", &out, "--out", &run, "--steps", &st, "-q",
        ];
        let load0 = load();
        let r = c.xscale(&targs)?;
        s.commands.push(format!("xscale {}", targs.join(" ")));
        stages.push(vec![json!(label), json!(format!("train, `cpu` preset, {steps} steps, with the final evaluation (load average {} at the start)", load0.map_or("?".into(), |l| format!("{l:.1}")))), json!(r.wall_s)]);
        let e = read_json(&c.root.join(&run).join("eval.json"))?;
        let (pm, sm, pf, _, _) = scores(&e);
        let hits: Vec<f64> = rep["per_view"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|v| v["hit"].as_f64())
            .collect();
        let min_hit = hits.iter().copied().fold(f64::INFINITY, f64::min);
        summary.push(vec![
            json!(label),
            rep["photos"].clone(),
            rep["views"].clone(),
            rep["points"].clone(),
            rep["reprojection"]["mean"].clone(),
            rep["reprojection"]["rms"].clone(),
            rep["colmap_mean_error"].clone(),
            rep["mesh_triangles"].clone(),
            json!(100.0 * rep["mean_hit"].as_f64().unwrap_or(f64::NAN)),
            json!(if hits.is_empty() {
                f64::NAN
            } else {
                100.0 * min_hit
            }),
            json!(steps),
            e["views"]
                .as_array()
                .map_or(Value::Null, |v| json!(v.len())),
            pm,
            sm,
            pf,
        ]);
    }
    if !stages.is_empty() {
        s.tables.push(table(
            "Seconds per stage (`prepare.json`), then training",
            &["capture", "stage", "seconds"],
            &[0, 0, 1],
            stages,
        ));
        s.tables.push(table(
            "What came out: the report and the trained model's held-out scores",
            &[
                "capture",
                "photos",
                "views posed",
                "points",
                "reprojection mean (px)",
                "reprojection RMS (px)",
                "COLMAP's mean error (px)",
                "mesh triangles",
                "pixels hit, mean (%)",
                "pixels hit, lowest view (%)",
                "steps",
                "held-out views",
                "masked PSNR (dB)",
                "masked SSIM",
                "full PSNR (dB)",
            ],
            &[0, 0, 0, 0, 3, 3, 3, 0, 1, 1, 0, 0, 2, 3, 2],
            summary,
        ));
    }
    Ok(s)
}

fn host() -> Value {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    json!({"cpu": cpu, "cores": cores})
}

fn load() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

fn commit(root: &Path) -> String {
    let git = |args: &[&str]| {
        Command::new("git")
            .args(args)
            .current_dir(root)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    let head = git(&["rev-parse", "--short=10", "HEAD"]).unwrap_or_else(|| "unknown".into());
    // Changes to the code (not to the generated page) make the commit approximate.
    let dirty = git(&[
        "status",
        "--porcelain",
        "--",
        "src",
        "benches",
        "examples",
        "Cargo.toml",
    ])
    .is_some_and(|s| !s.is_empty());
    if dirty {
        format!("{head} + uncommitted changes")
    } else {
        head
    }
}

/// UTC date and time of now, `YYYY-MM-DD HH:MM`.
fn now_utc() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs()) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02} UTC",
        rem / 3600,
        rem % 3600 / 60
    )
}

// ---------------------------------------------------------------- the page

fn cell(v: &Value, digits: usize) -> String {
    match v {
        Value::Null => "—".into(),
        Value::Number(n) => match (n.as_i64(), n.as_f64()) {
            (Some(i), _) => i.to_string(),
            (None, Some(x)) if !x.is_finite() => x.to_string(),
            (None, Some(x)) => format!("{x:.digits$}"),
            _ => n.to_string(),
        },
        Value::String(s) => s.replace('|', "\\|"),
        Value::Bool(b) => b.to_string(),
        other => other.to_string(),
    }
}

fn render_section(v: &Value, md: &mut String) {
    let s = |k: &str| v[k].as_str().unwrap_or("").to_string();
    md.push_str(&format!("## {}\n\n", s("title")));
    md.push_str(&format!(
        "<a id=\"{}\"></a>{}\n\n",
        s("section"),
        s("measures")
    ));
    md.push_str(&format!(
        "Host: {}, {} cores; {}; commit {}; took {:.0} s (load average {} before).\n\n",
        v["host"]["cpu"].as_str().unwrap_or("?"),
        v["host"]["cores"],
        s("date"),
        s("commit"),
        v["seconds"].as_f64().unwrap_or(0.0),
        v["load_before"]
            .as_f64()
            .map_or("unknown".into(), |l| format!("{l:.1}")),
    ));
    md.push_str(&format!(
        "Regenerate: `cargo run --release --example results -- --only {}`. Commands run:\n\n```\n",
        s("section")
    ));
    for c in v["commands"].as_array().into_iter().flatten() {
        md.push_str(c.as_str().unwrap_or(""));
        md.push('\n');
    }
    md.push_str("```\n\n");
    for t in v["tables"].as_array().into_iter().flatten() {
        let cols: Vec<String> = t["columns"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|c| c.as_str().unwrap_or("").to_string())
            .collect();
        let digits: Vec<usize> = t["digits"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|d| d.as_u64().unwrap_or(2) as usize)
            .collect();
        if let Some(cap) = t["caption"].as_str().filter(|c| !c.is_empty()) {
            md.push_str(&format!("{cap}:\n\n"));
        }
        md.push_str(&format!("| {} |\n", cols.join(" | ")));
        md.push_str(&format!("|{}\n", "---|".repeat(cols.len())));
        for r in t["rows"].as_array().into_iter().flatten() {
            let cells: Vec<String> = r
                .as_array()
                .into_iter()
                .flatten()
                .enumerate()
                .map(|(i, x)| cell(x, digits.get(i).copied().unwrap_or(2)))
                .collect();
            md.push_str(&format!("| {} |\n", cells.join(" | ")));
        }
        md.push('\n');
    }
    for n in v["notes"].as_array().into_iter().flatten() {
        md.push_str(&format!("{}\n\n", n.as_str().unwrap_or("")));
    }
    for i in v["images"].as_array().into_iter().flatten() {
        md.push_str(&format!(
            "![{}]({})\n\n",
            i[1].as_str().unwrap_or(""),
            i[0].as_str().unwrap_or("")
        ));
    }
}

/// `docs/results.md` from every `docs/results/*.json`: the known sections in their order, then
/// any other in name order.
fn write_page(docs: &Path) -> Result<()> {
    let dir = docs.join("results");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .with_context(|| format!("{}", dir.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    let rank = |p: &PathBuf| {
        let stem = p
            .file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .to_string();
        (
            SECTIONS
                .iter()
                .position(|s| s.name == stem)
                .unwrap_or(SECTIONS.len()),
            stem,
        )
    };
    files.sort_by_key(rank);
    let mut md = String::from(
        "# Results\n\n\
         <!-- Generated by `cargo run --release --example results` from docs/results/*.json; do not edit: rerun it. -->\n\n\
         Every measured figure the project quotes, regenerated by the command that measures it: \
         `cargo run --release --example results` runs every section (`-- --list` says what each \
         costs), `-- --only NAME` one section, `-- --render-only` rewrites this page from the \
         stored rows (`docs/results/NAME.json`). Each section gives its host, date, commit and \
         commands. Timings depend on the host and on what else runs on it (the load average is \
         given); compare figures within one section, where they were measured side by side.\n\n",
    );
    md.push_str("Sections: ");
    let mut toc = Vec::new();
    let mut bodies = String::new();
    for f in &files {
        let v = read_json(f)?;
        toc.push(format!(
            "[{}](#{})",
            v["title"].as_str().unwrap_or("?").replace('`', ""),
            v["section"].as_str().unwrap_or("")
        ));
        render_section(&v, &mut bodies);
    }
    md.push_str(&toc.join(" · "));
    md.push_str("\n\n");
    md.push_str(&bodies);
    let page = docs.join("results.md");
    std::fs::write(&page, md.trim_end().to_string() + "\n")?;
    eprintln!("wrote {}", page.display());
    Ok(())
}

/// Whether a section's page file holds a measurement (a table), not just a "not measured" note.
fn measured_before(path: &Path) -> bool {
    read_json(path).is_ok_and(|v| v["tables"].as_array().is_some_and(|t| !t.is_empty()))
}

fn main() -> Result<()> {
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let docs = root.join("docs");
    if argv
        .iter()
        .any(|a| a == "--list" || a == "--help" || a == "-h")
    {
        println!("sections (cargo run --release --example results -- --only a,b):");
        for s in SECTIONS {
            println!("  {:<14} {} ({})", s.name, s.title.replace('`', ""), s.cost);
        }
        return Ok(());
    }
    if argv.iter().any(|a| a == "--render-only") {
        return write_page(&docs);
    }
    let only: Option<Vec<String>> = match argv.iter().position(|a| a == "--only") {
        Some(i) => Some(
            argv.get(i + 1)
                .ok_or_else(|| anyhow!("--only needs a list of sections (--list)"))?
                .split(',')
                .map(str::to_string)
                .collect(),
        ),
        None => None,
    };
    for a in &argv {
        if a.starts_with("--") && !["--only", "--render-only", "--list"].contains(&a.as_str()) {
            bail!("{a}: unknown option (--only A,B, --render-only, --list)");
        }
    }
    if let Some(names) = &only {
        for n in names {
            if !SECTIONS.iter().any(|s| s.name == n) {
                bail!(
                    "--only {n}: no such section (there are: {})",
                    SECTIONS
                        .iter()
                        .map(|s| s.name)
                        .collect::<Vec<_>>()
                        .join(", ")
                );
            }
        }
    }
    // The binary the sections run, built from this tree.
    let st = Command::new("cargo")
        .args(["build", "--release", "--locked", "--bin", "xscale"])
        .current_dir(&root)
        .status()?;
    if !st.success() {
        bail!("cargo build --release --bin xscale failed");
    }
    let exe = std::env::current_exe()?;
    let bin = exe
        .parent()
        .and_then(|p| p.parent())
        .map(|p| p.join("xscale"))
        .filter(|p| p.is_file())
        .unwrap_or_else(|| root.join("target/release/xscale"));
    let work = root.join("target/results");
    std::fs::create_dir_all(&work)?;
    std::fs::create_dir_all(docs.join("results"))?;
    let ctx = Ctx {
        root: root.clone(),
        work,
        bin,
        docs: docs.clone(),
    };
    let mut failed = Vec::new();
    let mut kept = Vec::new();
    for spec in SECTIONS {
        if only
            .as_ref()
            .is_some_and(|o| !o.iter().any(|n| n == spec.name))
        {
            continue;
        }
        eprintln!("== {} ({})", spec.name, spec.cost);
        let (date, load_before, t0) = (now_utc(), load(), Instant::now());
        let path = docs.join(format!("results/{}.json", spec.name));
        match (spec.run)(&ctx) {
            Ok(s) if s.skipped.is_some() && measured_before(&path) => {
                eprintln!(
                    "   {}: not measurable here ({}); kept the earlier measurement in {}",
                    spec.name,
                    s.skipped.as_deref().unwrap_or(""),
                    path.display()
                );
                kept.push(spec.name);
            }
            Ok(s) => {
                let v = json!({
                    "section": spec.name,
                    "title": spec.title,
                    "measures": spec.measures,
                    "host": host(),
                    "date": date,
                    "commit": commit(&root),
                    "seconds": t0.elapsed().as_secs_f64(),
                    "load_before": load_before,
                    "commands": s.commands,
                    "tables": s.tables,
                    "notes": s.notes,
                    "images": s.images.iter().map(|(p, c)| json!([p, c])).collect::<Vec<_>>(),
                });
                std::fs::write(&path, serde_json::to_string_pretty(&v)? + "\n")?;
                eprintln!(
                    "   {} in {:.0} s",
                    path.display(),
                    t0.elapsed().as_secs_f64()
                );
            }
            Err(e) => {
                eprintln!("   {}: FAILED: {e:#}", spec.name);
                failed.push(spec.name);
            }
        }
        // The page after every section, so an interrupted run keeps what it measured.
        write_page(&docs)?;
    }
    if !kept.is_empty() {
        eprintln!(
            "not measurable on this host, earlier measurements kept: {}",
            kept.join(", ")
        );
    }
    if !failed.is_empty() {
        bail!(
            "sections that failed (their earlier rows, if any, are kept): {}",
            failed.join(", ")
        );
    }
    Ok(())
}
