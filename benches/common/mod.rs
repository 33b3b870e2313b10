//! Shared by the benches: environment knobs and the `small` synthetic scene.

use std::path::PathBuf;

/// `name` from the environment as a number, else `default`.
pub fn env(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// `xscale synth --preset small --seed 1`, generated into `target/bench-scenes/small` on first use.
pub fn small_scene() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/bench-scenes/small");
    if !dir.join("scene.toml").is_file() {
        eprintln!("generating the small scene into {}", dir.display());
        let s = xscale::synth::build(xscale::synth::Preset::Small, 1);
        let summary = s.summary();
        let images = s.render();
        xscale::synth::output::write(&s, &images, &summary, &dir, false).unwrap();
    }
    dir
}
