//! `xscale prepare --photos DIR --out OUT [--poses SCENE]`: photos to a scene folder on a CPU —
//! COLMAP's CPU structure-from-motion (feature extraction, matching, mapping or triangulation
//! with known poses, undistortion if asked), then a mesh of its sparse points by the
//! visibility Delaunay graph cut (`prepare/`). `--sparse MODEL` meshes a model made elsewhere,
//! without COLMAP. docs/prepare.md has the walk-through.

use crate::prepare::mesher;
use crate::prepare::pipeline::{self, Matcher};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Folder of photos (JPEG, PNG, TIFF).
    #[arg(long)]
    pub photos: Option<PathBuf>,
    /// Scene folder whose cameras are known (transforms.json, COLMAP, MVSNet or Metashape
    /// layout): the points are triangulated with these poses instead of COLMAP's mapper. Its
    /// views are matched to the photos by file name.
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Mesh this COLMAP sparse model (a model folder, or a scene folder holding sparse/0 and
    /// images/) as it is: no COLMAP run.
    #[arg(long, conflicts_with = "poses")]
    pub sparse: Option<PathBuf>,
    /// Output scene folder (created; a folder this command made is resumed).
    #[arg(long)]
    pub out: PathBuf,
    /// Downsample the photos by this integer factor first (block average; known cameras follow).
    #[arg(long, default_value_t = 1, value_parser = super::common::parse_downsample)]
    pub downsample: u32,
    /// Which image pairs COLMAP matches.
    #[arg(long, value_enum, default_value_t = Matcher::Auto)]
    pub matcher: Matcher,
    /// SIFT features per photo at most (default: COLMAP's, 8192). Matching time grows with its
    /// square.
    #[arg(long, value_parser = clap::value_parser!(u32).range(100..))]
    pub max_features: Option<u32>,
    /// Also write undistorted (pinhole) photos and cameras with `colmap image_undistorter`
    /// (into OUT/dense/, which xscale then reads).
    #[arg(long)]
    pub undistort: bool,
    /// Start over in an OUT made from other photos or settings (removes what prepare wrote there).
    #[arg(long)]
    pub force: bool,
    /// Print the COLMAP commands and stop.
    #[arg(long)]
    pub dry_run: bool,
    /// The COLMAP binary (default: `colmap` on the PATH).
    #[arg(long)]
    pub colmap: Option<PathBuf>,
    /// Mesher: weight of the surface-quality term, in lines of sight.
    #[arg(long, default_value_t = mesher::Options::default().quality, value_parser = super::common::parse_non_negative)]
    pub quality: f64,
    /// Mesher: drop triangles with a side longer than this many times the 95th percentile
    /// side (0 keeps all).
    #[arg(long, default_value_t = mesher::Options::default().max_side_factor, value_parser = super::common::parse_non_negative)]
    pub max_side: f64,
    /// Mesher: points seen by fewer photos are left out.
    #[arg(long, default_value_t = mesher::Options::default().min_track, value_parser = super::common::parse_positive)]
    pub min_track: usize,
}

pub fn run(a: Args) -> anyhow::Result<ExitCode> {
    let stop = super::common::on_interrupt(
        "stopping prepare; the same command again resumes where it stopped",
    );
    let threads = rayon::current_num_threads();
    let o = pipeline::Options {
        photos: a.photos,
        poses: a.poses,
        sparse: a.sparse,
        out: a.out,
        downsample: a.downsample,
        matcher: a.matcher,
        max_features: a.max_features,
        undistort: a.undistort,
        force: a.force,
        dry_run: a.dry_run,
        colmap: a.colmap,
        threads,
        mesher: mesher::Options {
            quality: a.quality,
            max_side_factor: a.max_side,
            min_track: a.min_track,
            ..mesher::Options::default()
        },
    };
    match pipeline::run(&o, stop) {
        Ok(_) => Ok(ExitCode::SUCCESS),
        Err(e) if stop.load(std::sync::atomic::Ordering::SeqCst) => {
            eprintln!("stopped ({e:#}): nothing half-written is left as finished; the same command resumes");
            Ok(ExitCode::from(super::common::EXIT_STOPPED_UNSAVED))
        }
        Err(e) => Err(e),
    }
}
