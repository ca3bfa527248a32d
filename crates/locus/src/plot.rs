//! Line plots as SVG (plotters), the one drawing routine behind every
//! figure locus writes: the quality and locality benchmarks and the
//! radiosity convergence report.

use anyhow::{Result, bail};
use std::path::Path;

/// One line of a plot, with a marker at each point.
pub struct Series {
    pub label: String,
    pub points: Vec<(f64, f64)>,
    /// Thicker lines and filled markers stand out from the rest.
    pub bold: bool,
}

/// Points gathered into one series per label, in order of first
/// appearance; a series is bold if its first point says so.
pub fn group(points: impl IntoIterator<Item = (String, (f64, f64), bool)>) -> Vec<Series> {
    let mut series: Vec<Series> = Vec::new();
    for (label, point, bold) in points {
        match series.iter_mut().find(|s| s.label == label) {
            Some(s) => s.points.push(point),
            None => series.push(Series {
                label,
                points: vec![point],
                bold,
            }),
        }
    }
    series
}

/// The axes: descriptions and whether each is logarithmic.
pub struct Axes<'a> {
    pub x: &'a str,
    pub y: &'a str,
    pub log_x: bool,
    pub log_y: bool,
}

fn range(values: impl Iterator<Item = f64>, log: bool) -> (f64, f64) {
    let (lo, hi) = values
        .map(|v| if log { v.max(1e-12) } else { v })
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if log {
        (lo * 0.8, hi * 1.25)
    } else {
        (lo.min(0.0), (hi * 1.1).max(1e-6))
    }
}

/// Draws `series` on `axes` as a 900x600 SVG at `path`.
pub fn lines(path: &Path, title: &str, axes: &Axes, series: &[Series]) -> Result<()> {
    use plotters::coord::Shift;
    use plotters::prelude::*;
    if series.iter().all(|s| s.points.is_empty()) {
        bail!("{}: nothing to plot", path.display());
    }
    let err = |e: &dyn std::fmt::Display| anyhow::anyhow!("plotting {}: {e}", path.display());
    let all = || series.iter().flat_map(|s| s.points.iter());
    let (x0, x1) = range(all().map(|p| p.0), axes.log_x);
    let (y0, y1) = range(all().map(|p| p.1), axes.log_y);
    let root: DrawingArea<SVGBackend, Shift> =
        SVGBackend::new(path, (900, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let mut builder = ChartBuilder::on(&root);
    builder
        .caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70);
    // plotters types linear and log axes apart, so the drawing is generic
    // over the coordinate system and instantiated for each combination.
    macro_rules! draw {
        ($xr:expr, $yr:expr) => {{
            let mut chart = builder.build_cartesian_2d($xr, $yr).map_err(|e| err(&e))?;
            let mut mesh = chart.configure_mesh();
            mesh.x_desc(axes.x).y_desc(axes.y);
            if axes.log_y {
                mesh.y_label_formatter(&|v| format!("{v:.0e}"));
            }
            mesh.draw().map_err(|e| err(&e))?;
            let pos = |p: &(f64, f64)| {
                (
                    if axes.log_x { p.0.max(1e-12) } else { p.0 },
                    if axes.log_y { p.1.max(1e-12) } else { p.1 },
                )
            };
            for (i, s) in series.iter().enumerate() {
                let pts: Vec<(f64, f64)> = s.points.iter().map(pos).collect();
                let color = Palette99::pick(i).to_rgba();
                let style = color.stroke_width(if s.bold { 2 } else { 1 });
                chart
                    .draw_series(LineSeries::new(pts.clone(), style))
                    .map_err(|e| err(&e))?
                    .label(s.label.clone())
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
                let marker = if s.bold {
                    color.filled()
                } else {
                    color.stroke_width(1)
                };
                chart
                    .draw_series(pts.into_iter().map(|p| Circle::new(p, 3, marker)))
                    .map_err(|e| err(&e))?;
            }
            chart
                .configure_series_labels()
                .border_style(BLACK)
                .background_style(WHITE.mix(0.8))
                .draw()
                .map_err(|e| err(&e))?;
        }};
    }
    match (axes.log_x, axes.log_y) {
        (true, true) => draw!((x0..x1).log_scale(), (y0..y1).log_scale()),
        (true, false) => draw!((x0..x1).log_scale(), y0..y1),
        (false, true) => draw!(x0..x1, (y0..y1).log_scale()),
        (false, false) => draw!(x0..x1, y0..y1),
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_every_series_on_every_axis_kind() {
        let dir = std::env::temp_dir().join(format!("locus-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (k, (log_x, log_y)) in [(false, false), (true, false), (false, true), (true, true)]
            .into_iter()
            .enumerate()
        {
            let path = dir.join(format!("p{k}.svg"));
            let series = [
                Series {
                    label: "first line".into(),
                    points: vec![(1.0, 2.0), (10.0, 0.5)],
                    bold: true,
                },
                Series {
                    label: "second line".into(),
                    points: vec![(2.0, 1.0)],
                    bold: false,
                },
            ];
            let axes = Axes {
                x: "x",
                y: "y",
                log_x,
                log_y,
            };
            lines(&path, "t", &axes, &series).unwrap();
            let text = std::fs::read_to_string(&path).unwrap();
            assert!(
                text.contains("<svg")
                    && text.contains("first line")
                    && text.contains("second line")
            );
        }
        let empty = lines(
            &dir.join("e.svg"),
            "t",
            &Axes {
                x: "",
                y: "",
                log_x: false,
                log_y: false,
            },
            &[],
        );
        assert!(empty.is_err());
        std::fs::remove_dir_all(&dir).ok();
    }
}
