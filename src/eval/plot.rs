//! The run-time-against-error plot of `xscale bench-quality` (`plotters`, PNG). Text uses the
//! embedded DejaVu Sans subset (`assets/fonts/`, license beside it), so no system font is needed.

use anyhow::{anyhow, Result};
use plotters::prelude::*;
use std::path::Path;

static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans-subset.ttf");

fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// One curve: a name and its (seconds, PSNR) points in time order.
pub struct Curve {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// The points no other point beats (less or equal time and more PSNR), in time order.
pub fn pareto_front(curves: &[Curve]) -> Vec<(f64, f64, String)> {
    let mut all: Vec<(f64, f64, String)> = curves
        .iter()
        .flat_map(|c| c.points.iter().map(|&(t, p)| (t, p, c.name.clone())))
        .filter(|(t, p, _)| t.is_finite() && p.is_finite())
        .collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0).then(b.1.total_cmp(&a.1)));
    let mut front = Vec::new();
    let mut best = f64::NEG_INFINITY;
    for p in all {
        if p.1 > best {
            best = p.1;
            front.push(p);
        }
    }
    front
}

/// Held-out masked PSNR against wall-clock seconds (log scale), one line per curve, the Pareto
/// front marked with circles.
pub fn pareto_png(path: &Path, title: &str, curves: &[Curve]) -> Result<()> {
    register_font();
    let pts = || curves.iter().flat_map(|c| c.points.iter().copied());
    let (tmin, tmax) = pts().fold((f64::INFINITY, 0.0f64), |(a, b), (t, _)| {
        (a.min(t), b.max(t))
    });
    let (pmin, pmax) = pts()
        .filter(|(_, p)| p.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), (_, p)| {
            (a.min(p), b.max(p))
        });
    if !(tmin.is_finite() && pmin.is_finite()) {
        return Err(anyhow!("nothing to plot"));
    }
    let (tmin, tmax) = ((tmin * 0.8).max(1e-3), tmax * 1.25);
    let (pmin, pmax) = (pmin.floor() - 0.5, pmax.ceil() + 0.5);
    let root = BitMapBackend::new(path, (1000, 650)).into_drawing_area();
    let e = |e: &dyn std::fmt::Display| anyhow!("{}: plot: {e}", path.display());
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d((tmin..tmax).log_scale(), pmin..pmax)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc("wall-clock seconds of training (log scale)")
        .y_desc("held-out masked PSNR (dB)")
        .label_style(("sans-serif", 15))
        .draw()
        .map_err(|x| e(&x))?;
    for (i, c) in curves.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let p: Vec<(f64, f64)> = c
            .points
            .iter()
            .copied()
            .filter(|(_, y)| y.is_finite())
            .collect();
        chart
            .draw_series(LineSeries::new(p.clone(), color.stroke_width(2)))
            .map_err(|x| e(&x))?
            .label(c.name.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
        chart
            .draw_series(p.iter().map(|&q| Circle::new(q, 3, color.filled())))
            .map_err(|x| e(&x))?;
    }
    let front = pareto_front(curves);
    chart
        .draw_series(
            front
                .iter()
                .map(|(t, p, _)| Circle::new((*t, *p), 8, BLACK.stroke_width(2))),
        )
        .map_err(|x| e(&x))?
        .label("Pareto front")
        .legend(|(x, y)| Circle::new((x + 9, y), 6, BLACK.stroke_width(2)));
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 15))
        .draw()
        .map_err(|x| e(&x))?;
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_front_keeps_only_unbeaten_points() {
        let c = |n: &str, p: &[(f64, f64)]| Curve {
            name: n.into(),
            points: p.to_vec(),
        };
        let curves = [
            c("a", &[(1.0, 20.0), (2.0, 25.0), (4.0, 26.0)]),
            c("b", &[(1.5, 22.0), (3.0, 24.0), (8.0, 30.0)]),
        ];
        let f: Vec<(f64, f64)> = pareto_front(&curves).iter().map(|x| (x.0, x.1)).collect();
        assert_eq!(
            f,
            vec![
                (1.0, 20.0),
                (1.5, 22.0),
                (2.0, 25.0),
                (4.0, 26.0),
                (8.0, 30.0)
            ]
        );
        let dir = std::env::temp_dir().join(format!("xscale-plot-{}.png", std::process::id()));
        pareto_png(&dir, "test", &curves).unwrap();
        assert!(std::fs::metadata(&dir).unwrap().len() > 1000);
        let _ = std::fs::remove_file(&dir);
    }
}
