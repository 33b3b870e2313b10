//! The parsers under fuzzing and what each case must satisfy, shared by the mutation harness
//! (`tests/fuzz_parsers.rs`) and the coverage-guided targets (`fuzz/`, `cargo fuzz`), so both
//! test the same functions with the same seeds and the same verdict (docs/bad-input.md):
//!   * no panic (the caller catches it), and
//!   * a failure names the file it read, and
//!   * an accepted input is finite with indices in range (else it is a silent wrong answer).

#![allow(dead_code)] // each includer uses part of it

use std::path::Path;

use xscale::io::TensorFile;
use xscale::model::checkpoint::Checkpoint;
use xscale::model::Batch;
use xscale::scene::{colmap, mesh, metashape, mvsnet, transforms, LoadOptions, Scene};
use xscale::train::config::RunConfig;

/// Parse `bytes` (written into the work dir); returns the path errors must name, and the result.
pub type RunFn = dyn Fn(&[u8], &Path) -> (String, anyhow::Result<()>) + Send + Sync;

/// One parser under test: seed files (all of the same kind), whether the format is text, and a
/// function that writes the mutated bytes where the parser reads them and runs it.
pub struct Target {
    pub name: &'static str,
    pub seeds: Vec<Vec<u8>>,
    pub text: bool,
    /// Cases in the default run.
    pub quick: usize,
    /// Writes `bytes` into the work dir and parses; returns the path that errors must name.
    pub run: Box<RunFn>,
}

pub fn read(p: impl AsRef<Path>) -> Vec<u8> {
    let p = p.as_ref();
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let p = e.path();
        if p.is_dir() {
            copy_dir(&p, &to.join(e.file_name()));
        } else {
            std::fs::copy(&p, to.join(e.file_name())).unwrap();
        }
    }
}

pub fn disp(p: &Path) -> String {
    p.display().to_string()
}

/// Mutate one file of a multi-file input: the seed is `name\0bytes`; the harness mutates the
/// bytes part only (a seed per file keeps the others intact).
pub fn split_named(b: &[u8]) -> (&str, &[u8]) {
    match b.iter().position(|&c| c == 0) {
        Some(z) => (std::str::from_utf8(&b[..z]).unwrap_or(""), &b[z + 1..]),
        None => ("", b),
    }
}

/// A parsed mesh must be finite with indices in range (else it is a silent wrong answer).
pub fn check_mesh(m: &xscale::scene::Mesh) -> anyhow::Result<()> {
    anyhow::ensure!(
        m.vertices.iter().all(|v| v.is_finite()),
        "ACCEPTED a non-finite vertex"
    );
    let n = m.vertices.len() as u32;
    anyhow::ensure!(
        m.triangles.iter().flatten().all(|&i| i < n),
        "ACCEPTED an index out of range"
    );
    Ok(())
}

/// Parsed cameras must be finite with a positive size and focal length.
pub fn check_views(vs: &[xscale::scene::view::View]) -> anyhow::Result<()> {
    for v in vs {
        let c = &v.camera;
        anyhow::ensure!(
            [c.fx, c.fy, c.cx, c.cy].iter().all(|x| x.is_finite())
                && c.fx > 0.0
                && c.fy > 0.0
                && c.width > 0
                && c.height > 0
                && c.rotation.is_finite()
                && c.translation.is_finite(),
            "ACCEPTED a bad camera for {}: {c:?}",
            v.name
        );
    }
    Ok(())
}

/// Every parser, its seeds from `fx` (the repository's `fixtures/`), writing into `work`.
/// A transforms.json with the keys nerfstudio adds: a top-level `applied_transform` and each
/// frame's `mask_path` (naming the frame's own image, which exists next to the file). Plain text
/// edits, as the cargo-fuzz crate that shares this file has no JSON library.
fn nerfstudio_keys(json: &[u8]) -> Vec<u8> {
    let text = std::str::from_utf8(json).unwrap();
    let open = text.find('{').unwrap() + 1;
    let mut out = format!(
        "{}\n  \"applied_transform\": [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]],{}",
        &text[..open],
        &text[open..]
    );
    // `"file_path": "P",` → `"file_path": "P", "mask_path": "P",`
    let key = "\"file_path\": ";
    let mut at = 0;
    while let Some(k) = out[at..].find(key) {
        let start = at + k + key.len();
        let end = start + 1 + out[start + 1..].find('"').unwrap() + 1;
        let value = out[start..end].to_string();
        let insert = format!(", \"mask_path\": {value}");
        out.insert_str(end, &insert);
        at = end + insert.len();
    }
    assert!(out.contains("mask_path"), "no file_path in the seed");
    out.into_bytes()
}

pub fn targets(fx: &Path, work: &Path) -> Vec<Target> {
    let fx = fx.to_path_buf();
    let mut ts = Vec::new();

    // PLY, ASCII and binary (float, double, big-endian), and OBJ.
    let plys: Vec<Vec<u8>> = [
        "formats/mesh/cube_ascii.ply",
        "formats/mesh/cube_be.ply",
        "formats/mesh/cube_double.ply",
        "formats/mesh/cube_float.ply",
        "formats/mesh/degenerate.ply",
    ]
    .iter()
    .map(|p| read(fx.join(p)))
    .collect();
    let mut ascii_ply = vec![plys[0].clone()];
    ascii_ply.push(read(fx.join("tiny/mesh.ply")));
    let bin_ply: Vec<Vec<u8>> = plys[1..4].to_vec();
    for (name, seeds, text) in [
        ("ply_ascii", ascii_ply, true),
        ("ply_binary", bin_ply, false),
    ] {
        ts.push(Target {
            name,
            seeds,
            text,
            quick: 2000,
            run: Box::new(|b, w| {
                let p = w.join("mesh.ply");
                std::fs::write(&p, b).unwrap();
                (
                    disp(&p),
                    mesh::load_mesh(&p).and_then(|(m, _)| check_mesh(&m)),
                )
            }),
        });
    }
    ts.push(Target {
        name: "obj",
        seeds: vec![read(fx.join("formats/mesh/cube.obj"))],
        text: true,
        quick: 2000,
        run: Box::new(|b, w| {
            let p = w.join("mesh.obj");
            std::fs::write(&p, b).unwrap();
            (
                disp(&p),
                mesh::load_mesh(&p).and_then(|(m, _)| check_mesh(&m)),
            )
        }),
    });

    // COLMAP text and binary: one seed per file of the model, the others left intact.
    for (name, src, files, text) in [
        (
            "colmap_text",
            "formats/colmap/sparse/0",
            &["cameras.txt", "images.txt"][..],
            true,
        ),
        (
            "colmap_binary",
            "formats/colmap_bin/sparse/0",
            &["cameras.bin", "images.bin"][..],
            false,
        ),
    ] {
        let model = work.join(name);
        copy_dir(&fx.join(src), &model);
        let seeds = files
            .iter()
            .map(|f| {
                let mut s = f.as_bytes().to_vec();
                s.push(0);
                s.extend(read(fx.join(src).join(f)));
                s
            })
            .collect();
        let orig: Vec<(String, Vec<u8>)> = files
            .iter()
            .map(|f| (f.to_string(), read(fx.join(src).join(f))))
            .collect();
        let images = fx.join("formats/colmap/images");
        ts.push(Target {
            name,
            seeds,
            text,
            quick: 2500,
            run: Box::new(move |b, _| {
                for (f, o) in &orig {
                    std::fs::write(model.join(f), o).unwrap();
                }
                let (f, body) = split_named(b);
                if f.is_empty() || !orig.iter().any(|(n, _)| n == f) {
                    return (String::new(), Ok(())); // the mutation hit the file name
                }
                std::fs::write(model.join(f), body).unwrap();
                let r = if text {
                    colmap::read_text(&model, &images)
                } else {
                    colmap::read_binary(&model, &images)
                };
                // Errors may name either file of the model: require the model folder.
                (disp(&model), r.and_then(|v| check_views(&v)))
            }),
        });
    }

    // COLMAP `points3D` (read for the mesh-frame check, `scene/points.rs`). Seeds written here:
    // the fixtures' models have no points.
    let points: Vec<([f64; 3], u32)> = vec![
        ([1.5, -2.25, 3.0], 3),
        ([0.0, 1e-3, -7.5], 2),
        ([123456.789, 4512345.6, 12.0], 5),
    ];
    let mut text = b"# 3D point list with one line of data per point:\n".to_vec();
    let mut binary = (points.len() as u64).to_le_bytes().to_vec();
    for (k, (p, track)) in points.iter().enumerate() {
        let obs: String = (0..*track)
            .map(|i| format!(" {} {}", i + 1, 7 * i))
            .collect();
        text.extend(format!("{} {} {} {} 10 20 30 0.5{obs}\n", k + 1, p[0], p[1], p[2]).bytes());
        binary.extend((k as u64 + 1).to_le_bytes());
        p.iter().for_each(|x| binary.extend(x.to_le_bytes()));
        binary.extend([10u8, 20, 30]);
        binary.extend(0.5f64.to_le_bytes());
        binary.extend((*track as u64).to_le_bytes());
        (0..*track)
            .for_each(|i| binary.extend([(i + 1).to_le_bytes(), (7 * i).to_le_bytes()].concat()));
    }
    for (name, file, seed, is_text) in [
        ("colmap_points_text", "points3D.txt", text, true),
        ("colmap_points_binary", "points3D.bin", binary, false),
    ] {
        ts.push(Target {
            name,
            seeds: vec![seed],
            text: is_text,
            quick: 2500,
            run: Box::new(move |b, w| {
                let p = w.join(file);
                std::fs::write(&p, b).unwrap();
                let r = colmap::read_points(w).and_then(|pts| {
                    let (_, pts) = pts.ok_or_else(|| anyhow::anyhow!("ACCEPTED no file"))?;
                    anyhow::ensure!(
                        pts.iter().all(|(x, _)| x.is_finite()),
                        "ACCEPTED a non-finite point"
                    );
                    Ok(())
                });
                (disp(&p), r)
            }),
        });
    }

    // MVSNet `*_cam.txt`.
    ts.push(Target {
        name: "mvsnet_cam",
        seeds: vec![
            read(fx.join("formats/mvsnet/cams_1/0000_cam.txt")),
            read(fx.join("tiny/cams_1/0001_cam.txt")),
        ],
        text: true,
        quick: 2500,
        run: Box::new(|b, w| {
            let p = w.join("0000_cam.txt");
            std::fs::write(&p, b).unwrap();
            let r = mvsnet::parse_cam(&p).and_then(|(r, t, k)| {
                anyhow::ensure!(
                    r.is_finite() && t.is_finite() && k.iter().all(|x| x.is_finite()),
                    "ACCEPTED a non-finite camera"
                );
                Ok(())
            });
            (disp(&p), r)
        }),
    });

    // Metashape's cameras.xml (the `tiny` photos beside it). Seeds: the `tiny` cameras as a
    // Metashape 2 export and one camera with every lens term, as `scene_formats`'s
    // `metashape_tiny` and `metashape_lens_models_follow_the_manual` write them.
    let mdir = work.join("metashape");
    copy_dir(&fx.join("tiny/images"), &mdir.join("images"));
    ts.push(Target {
        name: "metashape_xml",
        seeds: vec![
            read(fx.join("formats/metashape/cameras.xml")),
            read(fx.join("formats/metashape/lens.xml")),
        ],
        text: true,
        quick: 2500,
        run: Box::new(move |b, _| {
            let p = mdir.join("cameras.xml");
            std::fs::write(&p, b).unwrap();
            let r = metashape::load(&p, &mdir.join("images")).and_then(|l| check_views(&l.views));
            (disp(&p), r)
        }),
    });

    // transforms.json (images copied next to it so that paths resolve).
    let tdir = work.join("transforms");
    copy_dir(&fx.join("formats/transforms"), &tdir);
    copy_dir(&fx.join("tiny/images"), &tdir.join("images"));
    ts.push(Target {
        name: "transforms_json",
        seeds: vec![
            read(fx.join("formats/transforms/transforms.json")),
            read(fx.join("tiny/transforms.json")),
            nerfstudio_keys(&read(fx.join("tiny/transforms.json"))),
        ],
        text: true,
        quick: 2500,
        run: Box::new(move |b, _| {
            let p = tdir.join("transforms.json");
            std::fs::write(&p, b).unwrap();
            (disp(&p), transforms::load(&p).and_then(|v| check_views(&v)))
        }),
    });

    // scene.toml, through the whole scene loader (slower: images are read).
    let sdir = work.join("scene");
    copy_dir(&fx.join("formats/colmap"), &sdir);
    ts.push(Target {
        name: "scene_toml",
        seeds: vec![
            b"holdout_every = 2\nbackground = [0.0, 0.5, 1.0]\nformat = \"colmap\"\n".to_vec(),
            b"test_views = [\"a.png\"]\n".to_vec(),
            b"applied_transform = \"keep\"\nformat = \"colmap\"\n".to_vec(),
        ],
        text: true,
        quick: 1500,
        run: Box::new(move |b, _| {
            let p = sdir.join("scene.toml");
            std::fs::write(&p, b).unwrap();
            let r = Scene::load(&sdir, &LoadOptions::default());
            // A valid scene.toml can still make an invalid split (for instance a test view
            // list naming every view); those errors name the scene folder.
            (disp(&sdir), r.map(|_| ()))
        }),
    });

    // Run configuration TOML (`--config`), parsed from text with the file named as origin.
    let mut cfgs = Vec::new();
    for d in ["tiny-f64-linear", "cpu-t10", "tiny-tcnn-smoothstep"] {
        cfgs.push(read(fx.join("golden").join(d).join("config.toml")));
    }
    ts.push(Target {
        name: "config_toml",
        seeds: cfgs,
        text: true,
        quick: 2500,
        run: Box::new(|b, w| {
            let p = w.join("config.toml");
            let text = String::from_utf8_lossy(b);
            let origin = disp(&p);
            let r = RunConfig::from_toml_str(&text, "tiny", &origin);
            (origin, r.map(|_| ()))
        }),
    });

    // A run configuration as a checkpoint stores it (`run_config` metadata), read as written
    // (`RunConfig::from_stored_toml`, not laid over a preset): seeds from the golden checkpoints.
    let stored: Vec<Vec<u8>> = ["tiny-f64-linear", "cpu-t10", "tiny-tcnn-smoothstep"]
        .iter()
        .map(|d| {
            let ck = fx.join("golden").join(d).join("checkpoint.safetensors");
            let f = xscale::model::checkpoint::Checkpoint::read_model_tensors(&ck).unwrap();
            f.meta("run_config").unwrap().as_bytes().to_vec()
        })
        .collect();
    ts.push(Target {
        name: "stored_config",
        seeds: stored,
        text: true,
        quick: 1500,
        run: Box::new(|b, w| {
            let origin = disp(&w.join("checkpoint.safetensors"));
            let text = String::from_utf8_lossy(b);
            (
                origin.clone(),
                RunConfig::from_stored_toml(&text, &origin).map(|_| ()),
            )
        }),
    });

    // safetensors checkpoints and batches, read from disk as the CLI does.
    ts.push(Target {
        name: "checkpoint",
        seeds: vec![
            read(fx.join("golden/tiny-f64-smoothstep-g1/checkpoint.safetensors")),
            read(fx.join("golden/tiny-f64-linear/checkpoint.safetensors")),
        ],
        text: false,
        quick: 1000,
        run: Box::new(|b, w| {
            let p = w.join("checkpoint.safetensors");
            std::fs::write(&p, b).unwrap();
            (disp(&p), Checkpoint::load(&p).map(|_| ()))
        }),
    });
    ts.push(Target {
        name: "batch",
        seeds: vec![
            read(fx.join("golden/tiny-f64-smoothstep-g1/batch.safetensors")),
            read(fx.join("golden/cpu-t10/batch.safetensors")),
        ],
        text: false,
        quick: 1500,
        run: Box::new(|b, w| {
            let p = w.join("batch.safetensors");
            std::fs::write(&p, b).unwrap();
            (disp(&p), Batch::load(&p).map(|_| ()))
        }),
    });
    // Tensor files with no expectation about their content (`compare`, `dump` inputs).
    ts.push(Target {
        name: "tensor_file",
        seeds: vec![read(
            fx.join("golden/tiny-f64-smoothstep-g1/ref_grid_f32.safetensors"),
        )],
        text: false,
        quick: 1500,
        run: Box::new(|b, w| {
            let p = w.join("t.safetensors");
            std::fs::write(&p, b).unwrap();
            (disp(&p), TensorFile::read(&p).map(|_| ()))
        }),
    });
    ts
}

/// The verdict on one case that did not panic: `Err` explains why the case fails the contract.
/// `seed` marks an unmutated seed, which must parse.
pub fn judge(path: &str, r: &anyhow::Result<()>, seed: bool) -> Result<(), String> {
    let Err(e) = r else { return Ok(()) };
    let msg = format!("{e:#}");
    if seed {
        return Err(format!("unmutated seed fails: {msg}"));
    }
    if msg.contains("ACCEPTED") {
        return Err(msg);
    }
    if !msg.contains(path) {
        return Err(format!("error does not name '{path}': {msg}"));
    }
    Ok(())
}
