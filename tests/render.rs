//! Rendering at size (`src/render/mod.rs`): a frame is cast and shaded in bands of rows, so a
//! 12-megapixel frame never holds its whole cast. The bands must not show: a frame rendered in
//! one-row bands, in uneven bands and whole is the same bits (and the same with 1 and 2 threads);
//! `xscale render --scale` writes the larger frame.

use std::path::Path;
use xscale::model::{Hfm, ModelConfig};
use xscale::raycast::Tracer;
use xscale::render::{Appearance, ModelRenderer, Rendered, WHITE};
use xscale::scene::{LoadOptions, Scene};

#[path = "common/pool.rs"]
mod pool;
use pool::in_pool;

fn bits(r: &Rendered) -> (Vec<u32>, Vec<bool>, Vec<u32>) {
    (
        r.image.data.iter().map(|v| v.to_bits()).collect(),
        r.hit.clone(),
        r.footprint.iter().map(|v| v.to_bits()).collect(),
    )
}

/// A renderer of `model` on a white background.
fn on_white<'a>(
    model: &'a Hfm,
    params: &'a [f32],
    tracer: &'a Tracer,
    gamma: u32,
) -> ModelRenderer<'a> {
    ModelRenderer {
        model,
        params,
        tracer,
        gamma,
        background: WHITE,
    }
}

/// The `tiny` fixture and a BVH of its mesh.
fn tiny_scene() -> (Scene, Tracer) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
    let scene = Scene::load(&root, &LoadOptions::default()).unwrap();
    let tracer = Tracer::new(&scene.mesh, &scene.normalization).unwrap();
    (scene, tracer)
}

#[test]
fn bands_do_not_show_in_the_frame() {
    let (scene, tracer) = tiny_scene();
    let mut cfg = ModelConfig::tiny();
    cfg.appearance_views = 6;
    let model = Hfm::new(&cfg).unwrap();
    let params = model.init_params(7);
    // A held-out view at 2.5× its size (160×120).
    let cam = scene.views[scene.test[0]].camera.scaled(2.5);
    let g = cfg.gamma;
    let per_row = (cam.width * g * g) as usize;
    let r = ModelRenderer {
        model: &model,
        params: &params,
        tracer: &tracer,
        gamma: g,
        background: WHITE,
    };
    let whole = r
        .render_in_bands(&cam, &Appearance::Row(-1), usize::MAX)
        .unwrap();
    assert_eq!(whole.image.width, 160);
    assert!(whole.hit.iter().filter(|&&h| h).count() > 1000);
    let reference = bits(&whole);
    // One row per band; 7 rows (120 = 17·7 + 1: a short last band); the default.
    for samples in [1, 7 * per_row, 7 * per_row + 3] {
        let frame = r
            .render_in_bands(&cam, &Appearance::Row(-1), samples)
            .unwrap();
        assert!(
            bits(&frame) == reference,
            "bands of {samples} sub-samples change the frame"
        );
    }
    let dflt = in_pool(1, || r.render(&cam, &Appearance::Row(-1)).unwrap());
    assert!(bits(&dflt) == reference);
    let two = in_pool(2, || {
        r.render_in_bands(&cam, &Appearance::Row(-1), per_row)
            .unwrap()
    });
    assert!(bits(&two) == reference, "thread count changes the frame");
}

/// The renderer builds the model's input straight from the cast (`Hfm::infer_pixels`, no
/// batch): every hit pixel's colour is the same bits as the forward of the batch the cast
/// makes (`Batch { positions, valid, dirs, footprint, .. }`, the path rendering took before),
/// for the hash model with ξ and the footprint level weighting, with a view's row and with
/// the mean code, and for the vertex featurization (triangles and barycentrics from the cast).
#[test]
fn the_frame_is_the_forward_of_the_batch_its_cast_makes() {
    use xscale::model::config::{Featurization, LevelWeight};
    use xscale::model::Batch;
    let (scene, tracer) = tiny_scene();
    let cam = scene.views[scene.test[0]].camera.scaled(1.5);
    let mut hashed = ModelConfig::tiny();
    hashed.appearance_views = 4;
    hashed.level_weight = LevelWeight::Footprint;
    let mut vertex = ModelConfig::tiny();
    vertex.featurization = Featurization::Vertex;
    vertex.vertex_features = 6;
    vertex.appearance_views = 4;
    vertex.vertex_count = scene.mesh.vertices.len() as u32;
    vertex.deform.enabled = false;
    for cfg in [hashed, vertex] {
        let model = match cfg.featurization {
            Featurization::Vertex => {
                Hfm::with_vertex(&cfg, scene.mesh.triangles.clone().into()).unwrap()
            }
            _ => Hfm::new(&cfg).unwrap(),
        };
        let mut params = model.init_params(11);
        // Non-zero deformation and shader weights beyond the initial ones, and distinct codes.
        for (k, v) in params.iter_mut().enumerate() {
            *v += 0.01 * ((k * 7919 % 201) as f32 - 100.0) / 100.0;
        }
        let g = cfg.gamma;
        let r = on_white(&model, &params, &tracer, g);
        let cast = xscale::raycast::cast_view(&tracer, &cam, g).unwrap();
        let s = (g * g) as usize;
        let hits: Vec<usize> = (0..cast.pixels.len())
            .filter(|&i| cast.pixels[i].valid != 0)
            .collect();
        assert!(hits.len() > 1000);
        let subs = |i: usize| &cast.subs[i * s..(i + 1) * s];
        for row in [-1, 2] {
            let frame = r.render(&cam, &Appearance::Row(row)).unwrap();
            let mut b = Batch {
                positions: (hits.iter())
                    .flat_map(|&i| subs(i).iter().map(|x| x.position.to_array()))
                    .collect(),
                valid: (hits.iter())
                    .flat_map(|&i| subs(i).iter().map(|x| x.hit() as u8))
                    .collect(),
                dirs: (hits.iter())
                    .map(|&i| cast.pixels[i].dir.as_vec3().to_array())
                    .collect(),
                view: vec![row; hits.len()],
                target: vec![[0.0; 3]; hits.len()],
                footprint: (hits.iter())
                    .map(|&i| cast.pixels[i].footprint as f32)
                    .collect(),
                ..Batch::default()
            };
            if model.vertex.is_some() {
                b.triangle = (hits.iter())
                    .flat_map(|&i| subs(i).iter().map(|x| x.triangle))
                    .collect();
                b.bary = (hits.iter())
                    .flat_map(|&i| {
                        (subs(i).iter()).map(|x| if x.hit() { [x.u, x.v] } else { [0.0; 2] })
                    })
                    .collect();
            }
            let fwd = model.forward(&params, &b).unwrap();
            let want = fwd.chunks.iter().flat_map(|c| c.rgb.iter().copied());
            let mut differ = 0;
            for (&i, w) in hits.iter().zip(want.collect::<Vec<f32>>().chunks_exact(3)) {
                let got = &frame.image.data[i * 3..i * 3 + 3];
                differ += (got.iter().zip(w)).any(|(a, b)| a.to_bits() != b.to_bits()) as usize;
            }
            assert_eq!(
                differ, 0,
                "{:?}, row {row}: pixels differ from the batch's forward",
                cfg.featurization
            );
        }
    }
}

/// A view rendered with a code of its own (`Appearance::Code`, what a held-out view gets from
/// its neighbours) is the same bits as with the row holding that code, and with the mean code
/// the same as row −1; a different code changes the frame.
#[test]
fn a_code_of_its_own_renders_as_the_row_that_holds_it() {
    let (scene, tracer) = tiny_scene();
    let mut cfg = ModelConfig::tiny();
    cfg.appearance_views = 3;
    let model = Hfm::new(&cfg).unwrap();
    let mut params = model.init_params(7);
    let codes = model.layout.view_mut(&mut params, "appearance.codes");
    for (k, c) in codes.iter_mut().enumerate() {
        *c = 0.5 * (k as f32 - 2.5);
    }
    let cam = scene.views[scene.test[0]].camera.clone();
    let g = cfg.gamma;
    let r = ModelRenderer {
        model: &model,
        params: &params,
        tracer: &tracer,
        gamma: g,
        background: WHITE,
    };
    let render = |look: &Appearance| bits(&r.render(&cam, look).unwrap());
    let a = cfg.appearance_dim as usize;
    let row1 = model.codes(&params)[a..2 * a].to_vec();
    assert!(render(&Appearance::Code(row1)) == render(&Appearance::Row(1)));
    let all = model.codes(&params);
    let mean: Vec<f32> = (0..a)
        .map(|i| (all[i] + all[a + i] + all[2 * a + i]) / 3.0)
        .collect();
    assert!(render(&Appearance::Code(mean)) == render(&Appearance::Row(-1)));
    assert!(render(&Appearance::Row(0)) != render(&Appearance::Row(-1)));
}

#[test]
fn render_scale_writes_the_larger_frame() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
    let dir = std::env::temp_dir().join(format!("xscale-test-render-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let run = dir.join("run");
    let xs = |args: &[&str]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(args)
            .output()
            .unwrap();
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let (code, err) = xs(&[
        "train",
        "--scene",
        root.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
        "--preset",
        "tiny",
        "--steps",
        "5",
        "--no-eval",
        "-q",
    ]);
    assert_eq!(code, Some(0), "{err}");
    let out = dir.join("frames");
    let (r, o) = (run.to_str().unwrap(), out.to_str().unwrap());
    let render = |scale: &str| {
        xs(&[
            "render", "--run", r, "--out", o, "--views", "0", "--scale", scale,
        ])
    };
    let (code, err) = render("3");
    assert_eq!(code, Some(0), "{err}");
    let img = image::open(out.join("0000.png")).unwrap();
    assert_eq!((img.width(), img.height()), (192, 144));
    assert!(err.contains("rendered 1 images"), "{err}");
    // -q, as train takes it: the frame, and nothing on stderr.
    std::fs::remove_file(out.join("0000.png")).unwrap();
    let (code, err) = xs(&["render", "--run", r, "--out", o, "--views", "0", "-q"]);
    assert_eq!((code, err.as_str()), (Some(0), ""));
    assert!(out.join("0000.png").exists());
    // A scale that leaves no pixel, one that is not a number, and (where the system reports its
    // available memory) a frame of 6.4M×4.8M pixels are errors, not panics or an abort.
    let mut bads = vec!["0.001", "-2", "x"];
    if cfg!(target_os = "linux") {
        bads.push("100000");
    }
    for bad in bads {
        let (code, err) = render(bad);
        assert!(
            matches!(code, Some(2) | Some(64)),
            "--scale {bad}: {code:?} {err}"
        );
        assert!(err.contains("--scale") || err.contains("scale"), "{err}");
    }
    // Outputs that are inputs are refused before anything is written (`render --out
    // SCENE/images` replaced the photos by renders; `eval --json` could replace the checkpoint).
    let scene = dir.join("scene");
    let cp = std::process::Command::new("cp")
        .args(["-r", root.to_str().unwrap(), scene.to_str().unwrap()])
        .status()
        .unwrap();
    assert!(cp.success());
    let photo = scene.join("images/0000.png");
    let before = std::fs::read(&photo).unwrap();
    let (s, images) = (scene.to_str().unwrap(), scene.join("images"));
    let o = images.to_str().unwrap();
    for cmd in ["render", "eval"] {
        let (code, err) = xs(&[cmd, "--run", r, "--scene", s, "--out", o, "--views", "0"]);
        assert_eq!(code, Some(2), "{cmd}: {err}");
        assert!(
            err.contains("--out is the photo of view 0000.png"),
            "{cmd}: {err}"
        );
    }
    assert_eq!(std::fs::read(&photo).unwrap(), before);
    let ck = run.join("checkpoint.safetensors");
    let ck_before = std::fs::read(&ck).unwrap();
    let (code, err) = xs(&["eval", "--run", r, "--json", ck.to_str().unwrap()]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--json is the checkpoint"), "{err}");
    assert_eq!(std::fs::read(&ck).unwrap(), ck_before);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A `--scale` whose frame cannot fit is refused with the size asked for: the frame size was
/// printed clamped at 4294967295 a side with a wrapped byte count, and a scale whose byte count
/// wrapped to 0 (2147483648×1610612736 pixels × 32 bytes = 3·2⁶⁵) passed the check and panicked
/// allocating (exit 101).
#[test]
#[cfg(target_os = "linux")]
fn an_oversized_scale_is_refused_with_its_true_size() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
    let out = std::env::temp_dir().join(format!("xscale-test-render-big-{}", std::process::id()));
    let (s, o) = (root.to_str().unwrap(), out.to_str().unwrap());
    // View 0 is 64×48.
    for (scale, shown, frame, bytes) in [
        (
            "1e9",
            "1000000000",
            "64000000000×48000000000 pixels",
            "98304000000000.00 GB",
        ),
        (
            "33554432",
            "33554432",
            "2147483648×1610612736 pixels",
            "110680464442.26 GB",
        ),
    ] {
        let args = [
            "render", "--method", "ulr", "--scene", s, "--out", o, "--views", "0", "--scale", scale,
        ];
        let r = std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "--scale {scale}: {err}");
        assert!(
            err.contains(&format!(
                "--scale {shown}: 0000, {frame}, would take about {bytes} in memory"
            )) && err.contains("use a smaller --scale"),
            "--scale {scale}: {err}"
        );
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// `render --method ulr` needs no model: `--scene DIR` alone, as for `eval` (it used to say
/// `give --run RUN or --checkpoint FILE`). Its `--footprint` image paints misses in a colour off
/// the grey ramp, so they are not taken for the finest footprint (black; both were 0). `--path`
/// names itself in its errors and cannot be given with `--views` (exit 64: it ignored them).
#[test]
fn render_ulr_from_a_scene_alone_and_footprint_misses_apart() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
    let dir = std::env::temp_dir().join(format!("xscale-test-render-ulr-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (scene, o) = (root.to_str().unwrap(), dir.to_str().unwrap());
    let xs = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_xscale"))
            .args(["render", "--scene", scene, "--out", o])
            .args(args)
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (code, err) = xs(&["--method", "ulr", "--views", "4", "--footprint", "--mask"]);
    assert_eq!(code, Some(0), "{err}");
    let img = image::open(dir.join("0004.png")).unwrap().to_rgb8();
    let mask = image::open(dir.join("0004_mask.png")).unwrap().to_rgb8();
    let fp = image::open(dir.join("0004_footprint.png"))
        .unwrap()
        .to_rgb8();
    assert_eq!(img.dimensions(), fp.dimensions());
    let (mut misses, mut hits, mut finest) = (0, 0, 0);
    for (m, f) in mask.pixels().zip(fp.pixels()) {
        if m[0] == 0 {
            misses += 1;
            assert_eq!(f.0, [255, 0, 0], "a miss is red");
        } else {
            hits += 1;
            assert!(f[0] == f[1] && f[1] == f[2], "a hit is grey: {f:?}");
            finest += (f.0 == [0, 0, 0]) as usize;
        }
    }
    assert!(
        misses > 0 && hits > 0 && finest > 0,
        "{misses} {hits} {finest}"
    );
    // The model still needs one.
    let (code, err) = xs(&["--views", "0"]);
    assert!(code == Some(2) && err.contains("--run"), "{code:?} {err}");
    let (code, err) = xs(&["--method", "ulr", "--path", "0,99", "--frames", "2"]);
    assert!(
        code == Some(2) && err.contains("--path: no view named or numbered \"99\""),
        "{code:?} {err}"
    );
    let (code, err) = xs(&["--method", "ulr", "--path", "0,1", "--views", "all"]);
    assert!(
        code == Some(64) && err.contains("--views"),
        "{code:?} {err}"
    );
    let (code, err) = xs(&["--method", "ulr", "--views", "1,0001"]);
    assert!(
        code == Some(2) && err.contains("named twice"),
        "{code:?} {err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `footprint_image` on its own: the finest hit pixel black, the coarsest white, misses
/// `FOOTPRINT_MISS` whatever their footprint value.
#[test]
fn footprint_image_keeps_misses_off_the_ramp() {
    use xscale::render::{footprint_image, FOOTPRINT_MISS};
    let fp = [0.5f32, 2.0, 0.0, 8.0];
    let hit = [true, true, false, true];
    let img = footprint_image(&fp, &hit, 4, 1);
    let px = |i: usize| [img.data[3 * i], img.data[3 * i + 1], img.data[3 * i + 2]];
    assert_eq!(px(0), [0.0; 3]);
    assert_eq!(px(1), [0.5; 3]);
    assert_eq!(px(2), FOOTPRINT_MISS);
    assert_eq!(px(3), [1.0; 3]);
    assert!(FOOTPRINT_MISS.iter().any(|&c| c != FOOTPRINT_MISS[0]));
}

/// `render` and `eval` load the scene and build its BVH while the checkpoint's tables are read
/// (`load_model_and_scene`): the same parameters, scene, appearance rows and frame as the
/// checkpoint loaded first and the scene after; a checkpoint that cannot be read is reported
/// as such, not as the scene's error.
#[test]
fn the_scene_loaded_while_the_tables_are_read_is_the_one_loaded_after() {
    use xscale::model::checkpoint::Checkpoint;
    use xscale::run::model::{load_model, load_model_and_scene, scene_for_model};
    let (scene, _) = tiny_scene();
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
    let mut cfg = ModelConfig::tiny();
    cfg.appearance_views = scene.train().len() as u32;
    let model = Hfm::new(&cfg).unwrap();
    let params = model.init_params(3);
    let ck = Checkpoint {
        model,
        params,
        normalization: scene.normalization,
        refine: None,
    };
    let dir = std::env::temp_dir().join(format!("xscale-test-render-load-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("checkpoint.safetensors");
    ck.save(&path).unwrap();
    let (a, acfg) = load_model(&path).unwrap();
    let sa = scene_for_model(&fixture, &a, acfg.as_ref(), None, None).unwrap();
    let (b, _, bdir, sb) = load_model_and_scene(&path, || Ok(fixture.clone()), None, None).unwrap();
    assert_eq!(bdir, fixture);
    let bits32 = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert!(bits32(&a.params) == bits32(&b.params) && bits32(&b.params) == bits32(&ck.params));
    assert_eq!(sa.rows, sb.rows);
    assert!(sb.rows.iter().any(|&r| r >= 0));
    assert_eq!(sa.scene.views.len(), sb.scene.views.len());
    let cam = &sa.scene.views[sa.scene.test[0]].camera;
    let frame = |ck: &Checkpoint, s: &xscale::run::model::SceneForModel| {
        let r = on_white(&ck.model, &ck.params, &s.tracer, 2);
        bits(&r.render(cam, &Appearance::Row(1)).unwrap())
    };
    assert!(frame(&a, &sa) == frame(&b, &sb));
    // A missing checkpoint is the error, whatever the scene's.
    let err = load_model_and_scene(
        &dir.join("none.safetensors"),
        || Ok(fixture.clone()),
        None,
        None,
    )
    .err()
    .unwrap();
    assert!(format!("{err:#}").contains("none.safetensors"), "{err:#}");
    // A scene that cannot be found is reported (after a checkpoint that reads).
    let err = load_model_and_scene(&path, || Ok(dir.join("no-scene")), None, None)
        .err()
        .unwrap();
    assert!(format!("{err:#}").contains("no-scene"), "{err:#}");
    let _ = std::fs::remove_dir_all(&dir);
}
