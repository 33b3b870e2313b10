//! Where is a refined mesh still wrong? (docs/geometry.md §4)
//!
//! For meshes with the true surface's vertices (the synthetic proxies and their `refined.ply`),
//! prints the RMS of `|v − v_true|` over the vertices binned by their horizontal distance from the
//! scene's origin (20 m rings; the `small` scene's cameras look at its central 40–60 m, the terrain
//! runs out to ±100 m), so an error the photos cannot see (the outskirts) is told apart from one
//! they can.
//!
//! ```text
//! cargo run --release --example vertex_error_by_radius -- TRUTH.ply MESH.ply [MESH.ply ...]
//! ```

use xscale::scene::mesh::load_mesh;

const RING: f64 = 20.0;
const RINGS: usize = 6;

/// The ring of a (true) vertex: its horizontal distance from the origin in `RING`s, the last ring
/// open-ended.
fn ring(t: glam::DVec3) -> usize {
    (((t.x * t.x + t.y * t.y).sqrt() / RING) as usize).min(RINGS - 1)
}

fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    anyhow::ensure!(
        a.len() >= 3,
        "usage: vertex_error_by_radius TRUTH.ply MESH.ply [MESH.ply ...]"
    );
    let truth = load_mesh(std::path::Path::new(&a[1]))?.0;
    print!("{:<48}", "mesh");
    for i in 0..RINGS {
        let label = if i + 1 < RINGS {
            format!("r < {:.0} m", RING * (i + 1) as f64)
        } else {
            format!("r ≥ {:.0} m", RING * i as f64)
        };
        print!(" {label:>11}");
    }
    println!();
    for p in &a[2..] {
        let m = load_mesh(std::path::Path::new(p))?.0;
        anyhow::ensure!(
            m.vertices.len() == truth.vertices.len(),
            "{p}: {} vertices, the truth has {}",
            m.vertices.len(),
            truth.vertices.len()
        );
        let mut bins = [(0.0f64, 0usize); RINGS];
        for (v, t) in m.vertices.iter().zip(&truth.vertices) {
            let b = ring(*t);
            bins[b].0 += (*v - *t).length_squared();
            bins[b].1 += 1;
        }
        print!("{p:<48}");
        for (s, n) in bins {
            print!(" {:>11.4}", (s / n.max(1) as f64).sqrt());
        }
        println!();
    }
    print!("{:<48}", "vertices");
    let mut counts = [0usize; RINGS];
    for t in &truth.vertices {
        counts[ring(*t)] += 1;
    }
    for n in counts {
        print!(" {n:>11}");
    }
    println!();
    Ok(())
}
