//! Ray-casting throughput (`cargo bench --bench raycast`).
//!
//! Scene: a displaced icosphere with 1,310,720 triangles; one 1024×768 camera, γ = 2
//! (3,145,728 primary rays). First validates 2,000 of the view's rays against brute force over
//! all triangles (bit-exact against the f32 watertight brute force, and the same triangle as the
//! f64 Möller–Trumbore brute force; aborts on any difference), then reports Mrays/s, for each
//! build preset, of
//! - `SampleCache::build`, the production path (ray generation, packet traversal, f64
//!   refinement, footprints, compaction into the cache), on 1 and 2 threads and per core;
//! - `cast_view` (the same up to full per-sub-sample records, as rendering uses), likewise;
//! - the traversal alone (`Tracer::trace` on prebuilt packets, one thread);
//!
//! and obvhs's own single-ray BVH2 traversal (with our watertight closure) on the same rays as a
//! reference point. Every timed run is checked against the validated cast.
//!
//! Environment: XSCALE_BENCH_LEVEL (icosphere subdivision, default 8), XSCALE_BENCH_REPS (rounds,
//! default 5), XSCALE_BENCH_VALIDATE (rays checked, default 2000), XSCALE_BENCH_ONLY=cache (only
//! SampleCache::build, for profiling; of the preset XSCALE_BENCH_PRESET, default medium),
//! XSCALE_BENCH_NO_AVX=1 (the SSE traversal, as on a CPU without AVX).

mod common;
use common::{env, env_count};
use glam::{DVec3, Vec3A};
use rayon::prelude::*;
use std::time::Instant;
use xscale::raycast::meshes::displaced_icosphere;
use xscale::raycast::triangle::{intersect, WatertightRay};
use xscale::raycast::{
    brute_force_closest_hit, cast_view, BuildPreset, Packet, SampleCache, Tracer, MAX_LANES,
};
use xscale::scene::{Camera, Distortion, Normalization, NormalizeMode};

fn camera() -> Camera {
    // At (0.4, -3.0, 0.9) looking at the origin.
    let center = DVec3::new(0.4, -3.0, 0.9);
    let z = (-center).normalize();
    let x = z.cross(DVec3::Z).normalize();
    let y = z.cross(x);
    let rotation = glam::DMat3::from_cols(x, y, z).transpose();
    Camera {
        width: 1024,
        height: 768,
        fx: 1100.0,
        fy: 1100.0,
        cx: 512.0,
        cy: 384.0,
        distortion: Distortion::None,
        rotation,
        translation: -(rotation * center),
    }
}

/// CPU seconds of this thread (from /proc; ns resolution).
fn thread_cpu() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .map_or(f64::NAN, |ns| ns * 1e-9)
}

/// CPU seconds of the whole process (utime + stime, 10 ms ticks).
fn process_cpu() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let rest = s.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| {
        f.get(i)
            .and_then(|x| x.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    (tick(11) + tick(12)) / 100.0
}

fn brute_force_f32(tris: &[[[f32; 3]; 3]], o: [f32; 3], d: [f32; 3]) -> Option<(u32, f32)> {
    let r = WatertightRay::new(o, d)?;
    let mut best: Option<(u32, f32)> = None;
    for (i, v) in tris.iter().enumerate() {
        if let Some(h) = intersect(&r, v) {
            if best.is_none_or(|(bi, bt)| h.t < bt || (h.t == bt && (i as u32) < bi)) {
                best = Some((i as u32, h.t));
            }
        }
    }
    best
}

fn main() {
    println!(
        "load average at the start: {}",
        std::fs::read_to_string("/proc/loadavg")
            .unwrap_or_default()
            .trim()
    );
    let level = env("XSCALE_BENCH_LEVEL", 8) as u32;
    let reps = env_count("XSCALE_BENCH_REPS", 5);
    let t0 = Instant::now();
    let mesh = displaced_icosphere(level, 0.03);
    let n = Normalization::from_mesh(&mesh, NormalizeMode::PerAxis);
    println!(
        "mesh: displaced icosphere level {level}, {} triangles ({:.2} s to generate)",
        mesh.triangles.len(),
        t0.elapsed().as_secs_f64()
    );
    let cam = camera();
    let gamma = 2;
    let rays = (cam.width * cam.height * gamma * gamma) as f64;

    let mut tracers = Vec::new();
    let only_cache = std::env::var("XSCALE_BENCH_ONLY").as_deref() == Ok("cache");
    for preset in BuildPreset::ALL {
        let only = std::env::var("XSCALE_BENCH_PRESET").unwrap_or_else(|_| "medium".into());
        if only_cache && preset.name() != only {
            continue;
        }
        let mut t = Tracer::with_preset(&mesh, &n, preset).unwrap();
        if std::env::var_os("XSCALE_BENCH_NO_AVX").is_some() {
            t.set_avx(false);
        }
        println!(
            "build {:>6}: {:.2} s, {} 8-wide nodes",
            preset.name(),
            t.build_time().as_secs_f64(),
            t.node_count()
        );
        tracers.push(t);
    }

    // ---- validation: 2,000 of the view's rays against brute force ----
    let vc = cast_view(&tracers[0], &cam, gamma).unwrap();
    let hit_frac = vc.subs.iter().filter(|s| s.hit()).count() as f64 / rays;
    println!(
        "view: {}×{} γ={gamma}, {rays} rays, {:.1}% hit",
        cam.width,
        cam.height,
        100.0 * hit_frac
    );
    let o = cam.center() - n.center;
    let tris32: Vec<[[f32; 3]; 3]> = mesh
        .triangles
        .iter()
        .map(|t| t.map(|k| (mesh.vertices[k as usize] - n.center).as_vec3().to_array()))
        .collect();
    let nval = env("XSCALE_BENCH_VALIDATE", 2000);
    let stride = vc.subs.len() / nval;
    let idx: Vec<usize> = (0..nval)
        .map(|k| k * stride + (k * 7919) % stride)
        .collect();
    let t0 = Instant::now();
    let bad: Vec<String> = idx
        .par_iter()
        .filter_map(|&i| {
            let s = &vc.subs[i];
            let (o32, d32) = (o.as_vec3().to_array(), s.dir.as_vec3().to_array());
            let want = brute_force_f32(&tris32, o32, d32);
            let got = s.hit().then_some(s.triangle);
            let mut msgs = Vec::new();
            if got != want.map(|w| w.0) {
                msgs.push(format!("ray {i}: f32 brute force {want:?}, cast {got:?}"));
            }
            for t in &tracers {
                let mut sc = t.scratch();
                let mut p = Packet::default();
                p.set(0, o32, d32);
                if t.trace(&p, &mut sc)[0] != want {
                    msgs.push(format!(
                        "ray {i}: preset {:?} differs from f32 brute force",
                        t.preset()
                    ));
                }
            }
            let bf = brute_force_closest_hit(&mesh, cam.center(), s.dir);
            if bf.map(|h| h.triangle) != got {
                msgs.push(format!("ray {i}: f64 brute force {bf:?}, cast {got:?}"));
            }
            if let (Some(b), true) = (bf, s.hit()) {
                if (b.t - s.t).abs() > 1e-9 * b.t {
                    msgs.push(format!("ray {i}: distance {} vs brute force {}", s.t, b.t));
                }
            }
            (!msgs.is_empty()).then(|| msgs.join("; "))
        })
        .collect();
    if !bad.is_empty() {
        for b in bad.iter().take(10) {
            eprintln!("{b}");
        }
        eprintln!("validation FAILED: {} of {nval} rays differ", bad.len());
        std::process::exit(1);
    }
    println!(
        "validation: {nval} rays equal brute force (f32 watertight bit-exact, f64 Möller–Trumbore triangle and distance) ({:.1} s)",
        t0.elapsed().as_secs_f64()
    );

    // ---- timing ----
    // `reps` rounds, each timing 1 then 2 threads back to back (so both see the same machine
    // state; this VM's speed drifts by ±30% over tens of seconds); per thread count the best
    // wall time and the CPU time of that run.
    let pools: Vec<rayon::ThreadPool> = [1, 2]
        .iter()
        .map(|&n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        })
        .collect();
    let time_both = |run: &(dyn Fn() -> usize + Sync), want: usize| {
        let mut best = [(f64::INFINITY, f64::INFINITY); 2];
        for _ in 0..reps {
            for (b, pool) in best.iter_mut().zip(&pools) {
                let (s, c) = (Instant::now(), process_cpu());
                let got = pool.install(run);
                let (w, c) = (s.elapsed().as_secs_f64(), process_cpu() - c);
                assert_eq!(got, want, "timed run differs from the validated one");
                if w < b.0 {
                    *b = (w, c);
                }
            }
        }
        best.map(|(w, c)| (rays / w / 1e6, rays / c / 1e6))
    };
    let hits = vc.subs.iter().filter(|s| s.hit()).count();
    let kept = vc.pixels.iter().filter(|p| p.valid != 0).count();
    // cast_view: checks every sub-sample's triangle against the validated cast.
    let time_cast = |t: &Tracer| {
        time_both(
            &|| {
                let v = cast_view(t, &cam, gamma).unwrap();
                v.subs
                    .iter()
                    .zip(&vc.subs)
                    .filter(|(a, b)| a.hit() && a.triangle == b.triangle)
                    .count()
            },
            hits,
        )
    };
    // The production path: SampleCache::build (cast + compaction into the cache).
    let time_cache = |t: &Tracer| {
        time_both(
            &|| {
                SampleCache::build(t, &[(&cam, None)], gamma, false, &mut |_| {})
                    .unwrap()
                    .len()
            },
            kept,
        )
    };
    if only_cache {
        let [(m1, c1), (m2, c2)] = time_cache(&tracers[0]);
        println!(
            "SampleCache::build: 1 thread {m1:.2} Mrays/s, 2 threads {m2:.2} Mrays/s ({:.2} per core); per CPU-second {c1:.2}, {c2:.2}",
            m2 / 2.0
        );
        return;
    }
    for t in &tracers {
        let [(m1, c1), (m2, c2)] = time_cache(t);
        println!(
            "SampleCache::build [{:>6}]: 1 thread {m1:.2} Mrays/s, 2 threads {m2:.2} Mrays/s ({:.2} Mrays/s per core), scaling {:.2}×; per CPU-second: {c1:.2} (1 thread), {c2:.2} (2 threads) Mrays",
            t.preset().name(),
            m2 / 2.0,
            m2 / m1
        );
        let [(m1, c1), (m2, c2)] = time_cast(t);
        println!(
            "cast_view [{:>6}]: 1 thread {m1:.2} Mrays/s, 2 threads {m2:.2} Mrays/s ({:.2} Mrays/s per core), scaling {:.2}×; per CPU-second: {c1:.2} (1 thread), {c2:.2} (2 threads) Mrays",
            t.preset().name(),
            m2 / 2.0,
            m2 / m1
        );
        // Traversal alone (the packets cast_view traces: 4×4 sub-samples = 2×2 pixels), this
        // thread.
        let mut sc = t.scratch();
        let o32 = o.as_vec3().to_array();
        let (w, h) = (cam.width as usize, cam.height as usize);
        let packets: Vec<Packet> = (0..h / 2)
            .flat_map(|v2| (0..w / 2).map(move |u2| (u2, v2)))
            .map(|(u2, v2)| {
                let mut p = Packet::default();
                for l in 0..MAX_LANES {
                    let (sx, sy) = (l % 4, l / 4);
                    let (pu, pv) = (2 * u2 + sx / 2, 2 * v2 + sy / 2);
                    let j = (sy % 2) * 2 + sx % 2;
                    p.set(
                        l,
                        o32,
                        vc.subs[(pv * w + pu) * 4 + j].dir.as_vec3().to_array(),
                    );
                }
                p
            })
            .collect();
        // Best of `reps`.
        let (mut w, mut c) = (f64::INFINITY, f64::INFINITY);
        for _ in 0..reps {
            let (s, c0) = (Instant::now(), thread_cpu());
            let mut nhit = 0usize;
            for p in &packets {
                nhit += t.trace(p, &mut sc).iter().filter(|h| h.is_some()).count();
            }
            let (w1, c1) = (s.elapsed().as_secs_f64(), thread_cpu() - c0);
            assert_eq!(nhit, hits);
            if w1 < w {
                (w, c) = (w1, c1);
            }
        }
        println!(
            "trace only [{:>6}, {}]: 1 thread {:.2} Mrays/s wall, {:.2} Mrays per CPU-second",
            t.preset().name(),
            if t.avx() {
                "AVX: 8-wide node tests, 8-lane triangle chunks"
            } else {
                "SSE: node tests in halves, 4-lane triangle chunks"
            },
            rays / w / 1e6,
            rays / c / 1e6
        );
    }

    // ---- reference: obvhs single-ray BVH2 traversal with our watertight test ----
    let otris: Vec<obvhs::triangle::Triangle> = tris32
        .iter()
        .map(|t| obvhs::triangle::Triangle {
            v0: Vec3A::from_array(t[0]),
            v1: Vec3A::from_array(t[1]),
            v2: Vec3A::from_array(t[2]),
        })
        .collect();
    let bvh2 = obvhs::bvh2::builder::build_bvh2_from_tris(
        &otris,
        BuildPreset::Medium.params(),
        &mut std::time::Duration::default(),
    );
    let o32 = o.as_vec3();
    let dirs: Vec<[f32; 3]> = vc.subs.iter().map(|s| s.dir.as_vec3().to_array()).collect();
    let (s, c) = (Instant::now(), thread_cpu());
    let mut hits = 0usize;
    for d in &dirs {
        let wr = WatertightRay::new(o32.to_array(), *d).unwrap();
        let ray = obvhs::ray::Ray::new_inf(o32.into(), Vec3A::from_array(*d));
        let mut hit = obvhs::ray::RayHit::none();
        if bvh2.ray_traverse(ray, &mut hit, |_, k| {
            intersect(&wr, &tris32[bvh2.primitive_indices[k] as usize])
                .map_or(f32::INFINITY, |h| h.t)
        }) {
            hits += 1;
        }
    }
    let mo = rays / s.elapsed().as_secs_f64() / 1e6;
    let mc = rays / (thread_cpu() - c) / 1e6;
    println!(
        "reference: obvhs Bvh2::ray_traverse + watertight closure, 1 thread: {mo:.2} Mrays/s wall, {mc:.2} Mrays per CPU-second (trace only, {:.1}% hit)",
        100.0 * hits as f64 / rays
    );
    println!(
        "load average at the end: {}",
        std::fs::read_to_string("/proc/loadavg")
            .unwrap_or_default()
            .trim()
    );
}
