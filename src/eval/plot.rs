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

/// The run-time-against-error plot: PSNR against wall-clock seconds (log scale), one curve per
/// configuration, the Pareto front circled. A curve with no training time (every point at 0 s:
/// ULR) cannot sit on the log axis: it is drawn as a level across the plot, `NAME (no training)`,
/// and a point at 0 s on the front is circled at the axis' left end.
pub fn pareto_png(path: &Path, title: &str, curves: &[Curve]) -> Result<()> {
    let timed = || {
        (curves.iter())
            .flat_map(|c| c.points.iter().map(|p| p.0))
            .filter(|&t| t > 0.0)
    };
    let (lo, hi) = timed().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), t| {
        (a.min(t), b.max(t))
    });
    // No timed point at all (only ULR): a nominal axis from 0.1 to 10 s.
    let (left, right) = if lo.is_finite() {
        (lo * 0.5, hi)
    } else {
        (0.1, 10.0)
    };
    let at_left = |(t, p): (f64, f64)| (if t > 0.0 { t } else { left }, p);
    let drawn: Vec<Curve> = curves
        .iter()
        .map(|c| match c.points.last() {
            Some(&(_, p)) if c.points.iter().all(|q| q.0 <= 0.0) => Curve {
                name: format!("{} (no training)", c.name),
                points: vec![(left, p), (right.max(left * 4.0), p)],
            },
            _ => Curve {
                name: c.name.clone(),
                points: c.points.iter().map(|&q| at_left(q)).collect(),
            },
        })
        .collect();
    let front: Vec<(f64, f64)> = pareto_front(curves)
        .iter()
        .map(|(t, p, _)| at_left((*t, *p)))
        .collect();
    lines_png(
        path,
        &Axes {
            title,
            x_desc: "wall-clock seconds of training (log scale)",
            y_desc: "held-out masked PSNR (dB)",
            log_x: true,
        },
        &drawn,
        &front,
        "Pareto front",
    )
}

/// Titles and scale of a [`lines_png`] plot.
pub struct Axes<'a> {
    pub title: &'a str,
    pub x_desc: &'a str,
    pub y_desc: &'a str,
    /// Logarithmic x axis (all x > 0).
    pub log_x: bool,
}

/// Curves of (x, y) points with dots, plus `marks` circled in black under the legend entry
/// `marks_label` (none if empty). Non-finite y values are left out.
pub fn lines_png(
    path: &Path,
    axes: &Axes,
    curves: &[Curve],
    marks: &[(f64, f64)],
    marks_label: &str,
) -> Result<()> {
    register_font();
    let pts = || curves.iter().flat_map(|c| c.points.iter().copied());
    let (tmin, tmax) = pts().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), (t, _)| {
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
    let (pmin, pmax) = (pmin.floor() - 0.5, pmax.ceil() + 0.5);
    let root = BitMapBackend::new(path, (1000, 650)).into_drawing_area();
    let e = |e: &dyn std::fmt::Display| anyhow!("{}: plot: {e}", path.display());
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let mut builder = ChartBuilder::on(&root);
    builder
        .caption(axes.title, ("sans-serif", 22))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60);
    if axes.log_x {
        let (tmin, tmax) = ((tmin * 0.8).max(1e-3), tmax * 1.25);
        let chart = builder
            .build_cartesian_2d((tmin..tmax).log_scale(), pmin..pmax)
            .map_err(|x| e(&x))?;
        draw_lines(chart, axes, curves, marks, marks_label).map_err(|x| e(&x))?;
    } else {
        let pad = 0.05 * (tmax - tmin).max(1e-9);
        let chart = builder
            .build_cartesian_2d(tmin - pad..tmax + pad, pmin..pmax)
            .map_err(|x| e(&x))?;
        draw_lines(chart, axes, curves, marks, marks_label).map_err(|x| e(&x))?;
    }
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

/// A log axis gets a tick at every 1…9 × 10^k; labelling only 1, 2, 3 and 5 × 10^k keeps the
/// labels from running into each other near the end of each decade.
fn log_tick_label(v: &f64) -> String {
    if v.is_nan() || *v <= 0.0 {
        return String::new();
    }
    let decade = 10f64.powf(v.log10().floor());
    let m = v / decade;
    if [1.0, 2.0, 3.0, 5.0, 10.0]
        .iter()
        .any(|k| (m - k).abs() < 1e-6 * k)
    {
        let r = m.round() * decade;
        // As many decimals as the decade needs (`{r}` printed 3 × 0.1 as 0.30000000000000004).
        let digits = (-decade.log10().round()).max(0.0) as usize;
        format!("{r:.digits$}")
    } else {
        String::new()
    }
}

type PlotResult = std::result::Result<(), Box<dyn std::error::Error>>;

fn draw_lines<'a, X>(
    mut chart: ChartContext<
        'a,
        BitMapBackend<'a>,
        Cartesian2d<X, plotters::coord::types::RangedCoordf64>,
    >,
    axes: &Axes,
    curves: &[Curve],
    marks: &[(f64, f64)],
    marks_label: &str,
) -> PlotResult
where
    X: Ranged<ValueType = f64> + plotters::coord::ranged1d::ValueFormatter<f64>,
{
    let mut mesh = chart.configure_mesh();
    mesh.x_desc(axes.x_desc)
        .y_desc(axes.y_desc)
        .label_style(("sans-serif", 15));
    if axes.log_x {
        mesh.x_label_formatter(&log_tick_label);
    }
    mesh.draw()?;
    for (i, c) in curves.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let p: Vec<(f64, f64)> = c
            .points
            .iter()
            .copied()
            .filter(|(_, y)| y.is_finite())
            .collect();
        chart
            .draw_series(LineSeries::new(p.clone(), color.stroke_width(2)))?
            .label(c.name.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
        chart.draw_series(p.iter().map(|&q| Circle::new(q, 3, color.filled())))?;
    }
    if !marks.is_empty() {
        chart
            .draw_series(
                marks
                    .iter()
                    .map(|&(t, p)| Circle::new((t, p), 8, BLACK.stroke_width(2))),
            )?
            .label(marks_label.to_string())
            .legend(|(x, y)| Circle::new((x + 9, y), 6, BLACK.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 15))
        .draw()?;
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

    /// Labels below 1 keep the decade's decimals only (0.3 was printed 0.30000000000000004).
    #[test]
    fn log_tick_labels_are_short() {
        let labels: Vec<String> = [0.03, 0.3, 0.5, 0.4, 2.0, 30.0]
            .iter()
            .map(log_tick_label)
            .collect();
        assert_eq!(labels, ["0.03", "0.3", "0.5", "", "2", "30"]);
    }

    /// A curve with no training time (ULR: its point at 0 s) is plotted (a level across the
    /// log axis; 0 has no place on it) and leads the front until a point beats it.
    #[test]
    fn a_curve_at_zero_seconds_is_plotted_and_on_the_front() {
        let curves = [
            Curve {
                name: "a".into(),
                points: vec![(1.0, 20.0), (2.0, 25.0)],
            },
            Curve {
                name: "ulr".into(),
                points: vec![(0.0, 23.0)],
            },
        ];
        let f: Vec<(f64, f64)> = pareto_front(&curves).iter().map(|x| (x.0, x.1)).collect();
        assert_eq!(f, vec![(0.0, 23.0), (2.0, 25.0)]);
        let png = std::env::temp_dir().join(format!("xscale-plot0-{}.png", std::process::id()));
        pareto_png(&png, "test", &curves).unwrap();
        assert!(std::fs::metadata(&png).unwrap().len() > 1000);
        let _ = std::fs::remove_file(&png);
    }
}
