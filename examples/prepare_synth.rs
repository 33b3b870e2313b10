//! The mesher of `xscale prepare` on a synthetic scene, for its distance to the true surface
//! (docs/prepare.md): writes OUT/truth.ply (the true surface), OUT/mesh.ply (the Delaunay graph
//! cut of the sparse points) and OUT/points.ply (the points with normals fitted to their 12
//! nearest neighbours and turned towards their cameras: what COLMAP's `poisson_mesher` reads).
//! Then `xscale mesh-distance --mesh OUT/mesh.ply --truth OUT/truth.ply`. The distances of
//! OUT/mesh.ply and, when present, OUT/meshed-poisson.ply (COLMAP's `poisson_mesher` on
//! OUT/points.ply) to the true surface are printed and written to OUT/distances.json.
//!
//! cargo run --release --example prepare_synth -- OUT [PRESET small] [POINTS_PER_VIEW 400]
//!     [NOISE 0.001] [OUTLIERS 0.02] [SEED 1] [QUALITY 1] [MAX_SIDE 25]

use glam::{DMat3, DVec3};
use rayon::prelude::*;
use std::io::Write;
use xscale::prepare::mesher::{self, Options};
use xscale::prepare::synthetic;

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let out = std::path::PathBuf::from(a.first().map(String::as_str).unwrap_or("prepare-synth"));
    let preset = match a.get(1).map(String::as_str).unwrap_or("small") {
        "tiny" => xscale::synth::Preset::Tiny,
        "cross" => xscale::synth::Preset::Cross,
        _ => xscale::synth::Preset::Small,
    };
    let per_view: usize = a.get(2).map_or(Ok(400), |s| s.parse())?;
    let noise: f64 = a.get(3).map_or(Ok(0.001), |s| s.parse())?;
    let outliers: f64 = a.get(4).map_or(Ok(0.02), |s| s.parse())?;
    let seed: u64 = a.get(5).map_or(Ok(1), |s| s.parse())?;
    let mut opts = Options::default();
    if let Some(q) = a.get(6) {
        opts.quality = q.parse()?;
    }
    if let Some(q) = a.get(7) {
        opts.max_side_factor = q.parse()?;
    }
    std::fs::create_dir_all(&out)?;
    let s = xscale::synth::build(preset, 7);
    let pts = synthetic::points(&s, per_view, noise, outliers, seed);
    eprintln!(
        "{} points from {} cameras",
        pts.tracks.len(),
        pts.cameras.len()
    );
    xscale::scene::mesh::write_ply(&out.join("truth.ply"), &s.truth.to_mesh())?;
    let t = std::time::Instant::now();
    let (m, stats) = mesher::mesh(&pts.tracks, &pts.cameras, &opts, &|_, _, _| {}, &|| false)?;
    let mesher_s = t.elapsed().as_secs_f64();
    eprintln!("mesher: {mesher_s:.2} s, {stats:?}");
    xscale::scene::mesh::write_ply(&out.join("mesh.ply"), &m)?;
    // Normals: the smallest principal axis of the 12 nearest points, towards the cameras.
    let xyz: Vec<DVec3> = pts.tracks.iter().map(|t| t.xyz).collect();
    let normals: Vec<DVec3> = (0..xyz.len())
        .into_par_iter()
        .map(|i| {
            let mut d: Vec<(f64, usize)> = xyz
                .iter()
                .enumerate()
                .map(|(j, q)| ((*q - xyz[i]).length_squared(), j))
                .collect();
            d.select_nth_unstable_by(12, |a, b| a.0.total_cmp(&b.0));
            let nb: Vec<DVec3> = d[..13].iter().map(|x| xyz[x.1]).collect();
            let c = nb.iter().copied().sum::<DVec3>() / nb.len() as f64;
            let mut cov = DMat3::ZERO;
            for q in &nb {
                let r = *q - c;
                cov += DMat3::from_cols(r * r.x, r * r.y, r * r.z);
            }
            // Smallest eigenvector by inverse power iteration on the shifted matrix.
            let shift = DMat3::from_diagonal(DVec3::splat(
                1e-12 * (cov.x_axis.x + cov.y_axis.y + cov.z_axis.z),
            ));
            let inv = (cov + shift).inverse();
            let mut n = DVec3::new(0.3, 0.5, 0.8).normalize();
            for _ in 0..30 {
                n = (inv * n).normalize();
            }
            let towards: DVec3 = pts.tracks[i]
                .cameras
                .iter()
                .map(|&c| (pts.cameras[c as usize] - xyz[i]).normalize())
                .sum();
            if n.dot(towards) < 0.0 {
                -n
            } else {
                n
            }
        })
        .collect();
    let mut f = std::io::BufWriter::new(std::fs::File::create(out.join("points.ply"))?);
    writeln!(f, "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header", xyz.len())?;
    for (p, n) in xyz.iter().zip(&normals) {
        // COLMAP's poisson_mesher refuses points without colours.
        writeln!(
            f,
            "{} {} {} {} {} {} 128 128 128",
            p.x, p.y, p.z, n.x, n.y, n.z
        )?;
    }
    drop(f);
    // Accuracy (mesh → truth) and completeness (the truth that two cameras see → mesh).
    let truth = s.truth.to_mesh();
    let diag = truth.diagonal();
    let seen = synthetic::seen_samples(&s, 50_000);
    println!(
        "scene diagonal {diag:.3}; {} seen samples of the truth",
        seen.len()
    );
    let mut rows = Vec::new();
    for name in ["mesh.ply", "meshed-poisson.ply"] {
        let p = out.join(name);
        if !p.is_file() {
            continue;
        }
        let (mesh, _) = xscale::scene::mesh::load_mesh(&p)?;
        let (acc, comp) = synthetic::distances(&s, &mesh, &seen, 50_000);
        println!(
            "{name}: {} triangles; (distances capped at 10 % of the diagonal) accuracy mean {:.4} RMS {:.4} ({:.3} % of the diagonal); completeness mean {:.4} RMS {:.4} ({:.3} %)",
            mesh.triangles.len(), acc.0, acc.1, 100.0 * acc.1 / diag, comp.0, comp.1, 100.0 * comp.1 / diag
        );
        rows.push(serde_json::json!({
            "mesh": name, "triangles": mesh.triangles.len(),
            "accuracy_mean": acc.0, "accuracy_rms": acc.1,
            "completeness_mean": comp.0, "completeness_rms": comp.1,
        }));
    }
    let json = serde_json::json!({
        "points": pts.tracks.len(), "cameras": pts.cameras.len(),
        "lines_of_sight": pts.tracks.iter().map(|t| t.cameras.len()).sum::<usize>(),
        "noise": noise, "outliers": outliers, "max_side": opts.max_side_factor,
        "quality": opts.quality, "diagonal": diag, "seen_samples": seen.len(),
        "mesher_s": mesher_s, "meshes": rows,
    });
    std::fs::write(
        out.join("distances.json"),
        serde_json::to_string_pretty(&json)?,
    )?;
    Ok(())
}
