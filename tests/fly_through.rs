//! `render --path A,B` from an aerial view to a close-up keeps the scene in view: every frame's
//! optical axis hits the mesh (the straight interpolation of the poses looks past it in the
//! middle), the ends are the views themselves, and the distance to the scene falls geometrically.

use std::path::Path;
use xscale::raycast::Tracer;
use xscale::render::{fly_camera, interpolate_camera, look_at_point};
use xscale::scene::{LoadOptions, Scene};

#[test]
fn a_fly_through_keeps_the_scene_in_view() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/tiny");
    let scene = Scene::load(&root, &LoadOptions::default()).unwrap();
    let tracer = Tracer::new(&scene.mesh, &scene.normalization).unwrap();
    // View 0 is aerial, view 5 a close-up (footprints ~25x apart in this fixture).
    let (a, b) = (&scene.views[0].camera, &scene.views[5].camera);
    let (ta, tb) = (
        look_at_point(&tracer, &scene.mesh, a),
        look_at_point(&tracer, &scene.mesh, b),
    );
    let n = 30;
    let axis_hits = |c: &xscale::scene::Camera| {
        let d = (c.rotation.transpose() * glam::DVec3::Z).normalize();
        tracer.closest_hit(c.center(), d).is_some()
    };
    let mut dists = Vec::new();
    for i in 0..n {
        let c = fly_camera(a, b, ta, tb, i, n);
        assert!(
            axis_hits(&c),
            "frame {i}: the optical axis misses the scene"
        );
        let target = ta.lerp(tb, i as f64 / (n - 1) as f64);
        dists.push((target - c.center()).length());
    }
    // Ends reproduce the views.
    for (c, v) in [
        (fly_camera(a, b, ta, tb, 0, n), a),
        (fly_camera(a, b, ta, tb, n - 1, n), b),
    ] {
        assert!((c.center() - v.center()).length() < 1e-9 * (1.0 + v.center().length()));
        assert!((c.rotation - v.rotation)
            .to_cols_array()
            .iter()
            .all(|x| x.abs() < 1e-9));
    }
    // Geometric distance: constant ratio between frames.
    let r0 = dists[1] / dists[0];
    for w in dists.windows(2) {
        assert!((w[1] / w[0] - r0).abs() < 1e-9, "{dists:?}");
    }
    // Every frame looks at the moving look-at point (it projects to the principal point); the
    // straight interpolation of the poses lets it drift far off-centre, out of the frame.
    let off = |c: &xscale::scene::Camera, p: glam::DVec3| {
        c.project(p).map_or(f64::INFINITY, |(x, y)| {
            (x - c.cx).hypot(y - c.cy) / c.width as f64
        })
    };
    let mut straight_worst = 0.0f64;
    for i in 0..n {
        let target = ta.lerp(tb, i as f64 / (n - 1) as f64);
        let c = fly_camera(a, b, ta, tb, i, n);
        assert!(off(&c, target) < 1e-6, "frame {i}: {}", off(&c, target));
        straight_worst = straight_worst.max(off(&interpolate_camera(a, b, i, n), target));
    }
    assert!(
        straight_worst > 0.5,
        "straight path: worst offset {straight_worst} image widths"
    );
}
