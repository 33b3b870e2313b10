//! `xscale bench-quality` on the bundled fixture: a row per evaluation (budget·2^-k, k = 5..0)
//! with growing wall time, the ULR row, the plot, and a clear error for an unknown configuration.

use std::path::Path;
use xscale::train::bench_quality::bench_quality;

#[test]
fn bench_quality_writes_rows_and_the_plot() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = std::env::temp_dir().join(format!("xscale-bq-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let configs = vec!["tiny".to_string(), "ulr".to_string()];
    let rows = bench_quality(
        &root.join("fixtures/tiny"),
        &out,
        &configs,
        0.01,
        &mut |_| {},
    )
    .unwrap();
    let tiny: Vec<_> = rows.iter().filter(|r| r.config == "tiny").collect();
    assert_eq!(tiny.len(), 6);
    assert!(tiny
        .windows(2)
        .all(|w| w[1].wall_s > w[0].wall_s && w[1].step > w[0].step));
    assert!(tiny
        .iter()
        .all(|r| r.psnr_masked.is_finite() && r.psnr_masked > 10.0));
    assert_eq!(rows.iter().filter(|r| r.config == "ulr").count(), 1);
    let csv = std::fs::read_to_string(out.join("bench.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 7);
    assert!(csv.starts_with("config,setup_s,wall_s,step,psnr_masked,ssim_masked"));
    assert!(std::fs::metadata(out.join("pareto.png")).unwrap().len() > 1000);
    let e = bench_quality(
        &root.join("fixtures/tiny"),
        &out,
        &["cpux".into()],
        0.01,
        &mut |_| {},
    )
    .unwrap_err();
    assert!(
        format!("{e:#}").contains("unknown configuration \"cpux\""),
        "{e:#}"
    );
    let _ = std::fs::remove_dir_all(&out);
}
