//! The ray stream (`raycast/stream.rs`): rays cast as batches are drawn give the same batches,
//! bit for bit, as the sample cache, for every γ, with and without triangle ids, on any thread
//! count; the hit map's kept-pixel numbering; exact photo storage; whole training runs in both
//! modes write the same checkpoint.

// Index loops mirror the formulas (i over entries, c over channels).
#![allow(clippy::needless_range_loop)]

use std::path::{Path, PathBuf};
use xscale::raycast::stream::HitMap;
use xscale::raycast::{RayStream, SampleCache, Targets, Tracer};
use xscale::rng::{below, uniform_f32, Purpose};
use xscale::run::trainer::{train, TrainOptions};
use xscale::scene::{Camera, Image, LoadOptions, Scene};
use xscale::train::config::RunConfig;
use xscale::train::sampler::{
    batch_from_pixels, batch_pixels, draw_batch, patch_pixels, SampleMode, Samples,
};

#[path = "common/pool.rs"]
mod pool;
use pool::in_pool;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny")
}

/// The tiny scene, its tracer and its training views' photos.
fn tiny_training() -> (Scene, Tracer, Vec<Image>) {
    let scene = Scene::load(&fixture(), &LoadOptions::default()).unwrap();
    let tracer = Tracer::new(&scene.mesh, &scene.normalization).unwrap();
    let images = scene
        .train()
        .iter()
        .map(|&i| scene.load_image(i).unwrap())
        .collect();
    (scene, tracer, images)
}

/// The training views as the sample sources take them: (camera, photo), in training order.
fn training_views<'a>(
    scene: &'a Scene,
    images: &'a [Image],
) -> Vec<(&'a Camera, Option<&'a Image>)> {
    scene
        .train()
        .iter()
        .zip(images)
        .map(|(&i, img)| (&scene.views[i].camera, Some(img)))
        .collect()
}

/// Every kept pixel of the tiny scene, for γ = 1..4, hash (positions only) and vertex
/// (triangle ids + barycentrics) batches: the stream's batch equals the cache's, and is the same
/// with 1 and 2 threads.
#[test]
fn stream_batches_equal_cache_batches() {
    let (scene, tracer, images) = tiny_training();
    let views = training_views(&scene, &images);
    for gamma in 1..=4 {
        for tri in [false, true] {
            let cache = SampleCache::build(&tracer, &views, gamma, tri, &mut |_| {}).unwrap();
            let stream = RayStream::build(&tracer, &views, gamma, tri, &mut |_| {}).unwrap();
            assert_eq!(stream.len(), cache.len(), "γ={gamma}");
            assert_eq!(stream.dropped, cache.dropped);
            assert_eq!(stream.footprint_min(), cache.footprint_min());
            // All pixels in order, and a random batch with repeats.
            let all: Vec<usize> = (0..cache.len()).collect();
            let drawn = batch_pixels(cache.len(), 7, 3, 3000);
            for pixels in [&all, &drawn] {
                let want = batch_from_pixels(&cache, pixels);
                let one = in_pool(1, || stream.batch(&tracer, pixels));
                let two = in_pool(2, || stream.batch(&tracer, pixels));
                assert!(one == want, "γ={gamma} triangles={tri}: stream ≠ cache");
                assert!(two == one, "γ={gamma} triangles={tri}: 1 vs 2 threads");
                want.validate().unwrap();
            }
        }
    }
}

/// Patch batches (`train/sampler.rs`): the stream and the cache give the same kept pixels,
/// masks and batches; every whole patch is k×k neighbouring pixels of one view in row-major
/// order; a patch with a masked slot is one that no try could find whole, its masked rows
/// filled with its origin; the batch is a pure function of (seed, step).
#[test]
fn patch_batches_are_neighbours_and_the_same_streamed_or_cached() {
    let (scene, tracer, images) = tiny_training();
    let views = training_views(&scene, &images);
    let cache = SampleCache::build(&tracer, &views, 2, false, &mut |_| {}).unwrap();
    let stream = RayStream::build(&tracer, &views, 2, false, &mut |_| {}).unwrap();
    let pix: Vec<([u32; 2], usize)> = (0..cache.len())
        .map(|i| (cache.pixel(i), cache.view_index(i)))
        .collect();
    let (cache, stream) = (Samples::Cache(Box::new(cache)), Samples::Stream(stream));
    let mut saw_masked = false;
    for (k, size, patched) in [
        (4usize, 512usize, 512usize),
        (8, 512, 512),
        (16, 512, 512),
        (4, 500, 128),
    ] {
        for step in 0..4 {
            let (pc, mc) = patch_pixels(&cache, 3, step, size, k, patched);
            let (ps, ms) = patch_pixels(&stream, 3, step, size, k, patched);
            assert_eq!((&pc, &mc), (&ps, &ms), "k {k} step {step}: stream ≠ cache");
            assert_eq!(pc.len(), size);
            assert_eq!(
                patch_pixels(&cache, 3, step, size, k, patched),
                (pc.clone(), mc.clone())
            );
            // The independent rows after the patches: the single-pixel draw's first slots.
            let rest = batch_pixels(pix.len(), 3, step, size - patched);
            assert_eq!(&pc[patched..], &rest[..]);
            assert!(mc.len() == size || patched == size);
            assert!(mc.get(patched..).unwrap_or(&[]).iter().all(|&m| m == 0));
            for (j, rows) in pc[..patched].chunks(k * k).enumerate() {
                let masked = |r: usize| mc.get(j * k * k + r) == Some(&0);
                let o = pix[rows[0]];
                for (r, &i) in rows.iter().enumerate() {
                    if masked(r) {
                        saw_masked = true;
                        assert_eq!(i, rows[0], "k {k}: a masked row holds the origin");
                        continue;
                    }
                    let (dx, dy) = ((r % k) as u32, (r / k) as u32);
                    assert_eq!(pix[i].1, o.1, "k {k} patch {j}: one view");
                    assert_eq!(
                        pix[i].0,
                        [o.0[0] + dx, o.0[1] + dy],
                        "k {k} patch {j} row {r}"
                    );
                }
            }
            let bc = draw_batch(&cache, &tracer, 3, step, size, k as u32, patched);
            let bs = in_pool(2, || {
                draw_batch(&stream, &tracer, 3, step, size, k as u32, patched)
            });
            assert!(bc == bs, "k {k} step {step}: batches differ");
            assert_eq!(bc.patch, k);
            bc.validate().unwrap();
        }
    }
    // The tiny fixture's views are 64×48 with the object in part of them: 16×16 patches
    // cannot always be found whole, so the masked fallback is exercised.
    assert!(saw_masked);
}

/// `HitMap::locate` is the k-th set bit in row-major order, against a brute-force list, on
/// widths around multiples of 64, empty rows, full rows and an empty map.
#[test]
fn hit_map_numbering() {
    for (case, &(w, h, density)) in [
        (1u32, 1u32, 1.0f32),
        (63, 5, 0.5),
        (64, 4, 0.3),
        (65, 7, 0.9),
        (130, 9, 0.02),
        (200, 3, 1.0),
        (17, 6, 0.0),
    ]
    .iter()
    .enumerate()
    {
        let wpr = (w as usize).div_ceil(64);
        let mut bits = vec![0u64; wpr * h as usize];
        let mut want = Vec::new();
        for v in 0..h {
            // Row 1 always empty.
            for u in 0..w {
                let on =
                    v != 1 && uniform_f32(case as u64, Purpose::Test, v as u64, u as u64) < density;
                if on {
                    bits[v as usize * wpr + u as usize / 64] |= 1 << (u % 64);
                    want.push((u, v));
                }
            }
        }
        let m = HitMap::from_bits(w, h, bits);
        assert_eq!(m.len(), want.len(), "case {case}");
        for (k, &p) in want.iter().enumerate() {
            assert_eq!(m.locate(k), p, "case {case}, kept pixel {k}");
            assert!(m.get(p.0, p.1));
        }
        // index_of inverts locate, and is None off the mesh and outside the image.
        for v in 0..h + 1 {
            for u in 0..w + 1 {
                let k = want.iter().position(|&p| p == (u, v));
                assert_eq!(m.index_of(u, v), k, "case {case}, pixel ({u}, {v})");
            }
        }
    }
}

/// 8-bit and 16-bit photos are stored narrow and read back bit for bit; anything else stays f32.
#[test]
fn photos_are_stored_exactly() {
    let mk = |f: &dyn Fn(u64) -> f32| Image {
        width: 5,
        height: 3,
        data: (0..45).map(|i| f(i as u64)).collect(),
    };
    let i8 = mk(&|i| below(1, Purpose::Test, 0, i, 256) as f32 / 255.0);
    let i16 = mk(&|i| below(1, Purpose::Test, 1, i, 65536) as f32 / 65535.0);
    let f = mk(&|i| uniform_f32(1, Purpose::Test, 2, i) * 1.7 - 0.2);
    for (img, kind) in [(&i8, "u8"), (&i16, "u16"), (&f, "f32")] {
        let t = Targets::from_image(img);
        let got = match &t {
            Targets::U8(_) => "u8",
            Targets::U16(_) => "u16",
            Targets::F32(_) => "f32",
            Targets::None => "none",
        };
        assert_eq!(got, kind);
        for o in (0..45).step_by(3) {
            let back = t.rgb(o);
            for c in 0..3 {
                assert_eq!(
                    back[c].to_bits(),
                    img.data[o + c].to_bits(),
                    "{kind} at {o}"
                );
            }
        }
    }
}

/// A short training run writes the same checkpoint bytes with streamed and cached samples.
#[test]
fn training_is_identical_in_both_modes() {
    let mut bytes = Vec::new();
    for mode in [SampleMode::Stream, SampleMode::Cache] {
        let mut c = RunConfig::preset("tiny").unwrap();
        c.train.steps = 40;
        c.train.batch_pixels = 512;
        c.train.samples = mode;
        let run = std::env::temp_dir().join(format!(
            "xscale-test-stream-{}-{mode:?}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&run);
        let opts = TrainOptions {
            no_final_eval: true,
            quiet: true,
            ..Default::default()
        };
        train(&fixture(), &run, c, &opts).unwrap();
        let ck = std::fs::read(run.join("checkpoint.safetensors")).unwrap();
        let _ = std::fs::remove_dir_all(&run);
        bytes.push(ck);
    }
    // The run config (saved in the checkpoint) names the mode, so compare the tensors.
    let a = safetensors::SafeTensors::deserialize(&bytes[0]).unwrap();
    let b = safetensors::SafeTensors::deserialize(&bytes[1]).unwrap();
    let mut names: Vec<&str> = a.names();
    names.sort();
    assert!(!names.is_empty());
    for n in &names {
        assert_eq!(
            a.tensor(n).unwrap().data(),
            b.tensor(n).unwrap().data(),
            "tensor {n} differs between stream and cache"
        );
    }
}

/// `train.samples` and `train.memory_gb` change speed and memory, never results, so a resume may
/// change them: a run cached and told it no longer fits ("To fit: stream the rays instead of
/// caching them ([train] samples = \"stream\")") continues streamed, and writes the tensors an
/// uninterrupted cached run writes. `--resume` used to refuse them as differences from the run,
/// which left such a run no way to continue; other keys still are refused.
#[test]
fn a_resume_may_switch_between_cache_and_stream() {
    let dir =
        std::env::temp_dir().join(format!("xscale-test-stream-resume-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let conf = |name: &str, text: &str| {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p.to_str().unwrap().to_string()
    };
    let cache = conf("cache.toml", "[train]\nsamples = \"cache\"\n");
    let stream = conf(
        "stream.toml",
        "[train]\nsamples = \"stream\"\nmemory_gb = 4\n",
    );
    let seed = conf("seed.toml", "[train]\nsamples = \"stream\"\nseed = 3\n");
    let scene = fixture();
    let xs = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args([
                "train",
                "--scene",
                scene.to_str().unwrap(),
                "--preset",
                "tiny",
            ])
            .args(["--no-eval", "-q", "--batch", "256"])
            .args(args)
            .output()
            .unwrap()
    };
    let run = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let (whole, part) = (run("whole"), run("part"));
    assert!(xs(&["--out", &whole, "--steps", "8", "--config", &cache])
        .status
        .success());
    assert!(xs(&["--out", &part, "--steps", "4", "--config", &cache])
        .status
        .success());
    let o = xs(&[
        "--out", &part, "--resume", "--steps", "8", "--config", &stream,
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let saved = std::fs::read_to_string(dir.join("part/config.toml")).unwrap();
    assert!(saved.contains("samples = \"stream\""), "{saved}");
    let load = |r: &str| {
        xscale::io::tensors::TensorFile::read(Path::new(r).join("checkpoint.safetensors")).unwrap()
    };
    let (a, b) = (load(&whole), load(&part));
    assert!(!a.tensors.is_empty());
    assert_eq!(
        a.tensors, b.tensors,
        "streamed after a cached start: other tensors"
    );
    // A key that changes results is still refused.
    let o = xs(&[
        "--out", &part, "--resume", "--steps", "12", "--config", &seed,
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("train.seed = 3") && !err.contains("train.samples"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
