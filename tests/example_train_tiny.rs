//! `examples/train_tiny.rs` (the library used without the CLI) runs and learns: the loss falls
//! and the held-out score matches what `xscale train` reaches with the same preset and steps.

#[path = "../examples/train_tiny.rs"]
mod train_tiny;

use std::path::Path;

#[test]
fn the_library_example_trains_like_the_cli() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = train_tiny::run(&root.join("fixtures/tiny"), 300, false).unwrap();
    assert_eq!(out.state.step, 300);
    assert!(
        out.last_loss < 0.5 * out.first_loss,
        "loss {} -> {}",
        out.first_loss,
        out.last_loss
    );
    // The same run through the trainer gives the same parameters bit for bit (the loop is
    // deterministic), hence the same score.
    let dir = std::env::temp_dir().join(format!("xscale-example-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut cfg = xscale::train::config::RunConfig::preset("tiny").unwrap();
    cfg.train.steps = 300;
    let s = xscale::run::trainer::train(
        &root.join("fixtures/tiny"),
        &dir,
        cfg,
        &xscale::run::trainer::TrainOptions {
            quiet: true,
            ..Default::default()
        },
    )
    .unwrap();
    let cli = s.final_scores.unwrap().psnr_masked;
    assert_eq!(
        out.psnr_masked.to_bits(),
        cli.to_bits(),
        "example {} dB, trainer {cli} dB",
        out.psnr_masked
    );
    let _ = std::fs::remove_dir_all(&dir);
}
