//! xscale — a pure-CPU, deterministic Rust implementation of XScale-NVS, the hash featurized
//! manifold for cross-scale novel view synthesis (CVPR 2024).
//!
//! The modules follow the data flow of SPEC §1:
//!
//! | stage | module |
//! |---|---|
//! | scene dir → mesh, cameras, images, split, normalisation | [`scene`] |
//! | BVH, γ² rays per pixel, sample cache | [`raycast`] |
//! | synthetic cross-scale scenes with independent ground truth | [`synth`] |
//! | hash grids, SH, MLPs, deformation ξ, pooling, shader, loss (forward + backward) | [`model`] |
//! | run configuration, batches, Adam, the training state and its step | [`train`] |
//! | mesh refinement (beyond the paper): the offset field, its gradients, the photo term | [`refine`] |
//! | a run: the training loop, run folder, checkpoints, exact resume, progress | [`run`] |
//! | experiments over many runs: ablations, run time against error, geometry sensitivity | [`experiments`] |
//! | rendering any camera, camera paths, error images | [`render`] |
//! | PSNR / SSIM, the held-out protocol | [`eval`] |
//! | photos → a scene: COLMAP's CPU pipeline, a Delaunay graph-cut mesh of its points | [`prepare`] |
//! | safetensors checkpoints, batches, dumps, `compare` | [`io`] |
//! | counter-based random numbers (SPEC §5) | [`rng`] |
//! | the machine's memory: what is available, refusing what cannot fit; huge-page hints | [`sysmem`], [`memhint`] |
//! | command-line front end | [`cli`] |

// No library function longer than clippy.toml's threshold (120 lines of code) but the
// hand-written forward/backward kernels, which say so where they stand. (Tests, benches and
// examples may run longer: a scenario reads best in one piece.)
#![warn(clippy::too_many_lines)]

// Output to a closed pipe (`xscale train … 2>&1 | head -2`) is dropped, not a panic: std's
// `println!`/`eprintln!` panic when the write fails ("failed printing to stderr: Broken pipe",
// exit 101, the run lost mid-step). These shadow them in every module below (macro_rules are
// in scope textually), so the work goes on to its end and the command exits as it would have.
// `print!`/`eprint!` likewise.
macro_rules! println {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($t)*);
    }};
}
macro_rules! eprintln {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($t)*);
    }};
}
macro_rules! print {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stdout(), $($t)*);
    }};
}

pub mod cli;
pub mod eval;
pub mod experiments;
pub mod io;
pub mod memhint;
pub mod model;
pub mod prepare;
pub mod raycast;
pub mod refine;
pub mod render;
pub mod rng;
pub mod run;
pub mod scene;
pub mod synth;
pub mod sysmem;
pub mod train;
