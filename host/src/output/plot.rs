//! Plots: the trajectory seen from above (with the ground truth overlaid when given) and an
//! error over time, as PNG or SVG (chosen by the file extension).
//!
//! PNG text is drawn with a subset of DejaVu Sans built into the binary
//! (`host/assets/DejaVuSans-subset.ttf`, licence beside it), so plots need no system fonts.
//! SVG text names the `sans-serif` family and is rendered by the viewer.

use std::fmt;
use std::path::Path;
use std::sync::Once;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;

static FONT: &[u8] = include_bytes!("../../assets/DejaVuSans-subset.ttf");
static REGISTER: Once = Once::new();

fn register_font() {
    REGISTER.call_once(|| {
        // The font is checked by a test; if it failed to load, PNG text would be missing but
        // the plot would still be drawn.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// A plot could not be written.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PlotError(pub String);

impl fmt::Display for PlotError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for PlotError {}

const SIZE: (u32, u32) = (1000, 850);
/// Most points drawn per series (longer series are decimated evenly, keeping the last point).
const MAX_POINTS: usize = 20_000;

fn decimate<T: Copy>(v: &[T]) -> Vec<T> {
    if v.len() <= MAX_POINTS {
        return v.to_vec();
    }
    let step = v.len().div_ceil(MAX_POINTS);
    let mut out: Vec<T> = v.iter().step_by(step).copied().collect();
    if let Some(&last) = v.last() {
        out.push(last);
    }
    out
}

enum Kind {
    Png,
    Svg,
}

fn kind_of(path: &Path) -> Result<Kind, PlotError> {
    match path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref() {
        Some("png") => Ok(Kind::Png),
        Some("svg") => Ok(Kind::Svg),
        _ => Err(PlotError(format!("plot {}: the file name must end in .png or .svg", path.display()))),
    }
}

/// The two axes of the top view: x and y, unless z spans more than one of them (a camera frame
/// with y down, as KITTI's), in which case the axis of least extent is dropped.
fn plane(points: &[[f64; 3]]) -> (usize, usize) {
    let mut ext = [0.0f64; 3];
    for (k, e) in ext.iter_mut().enumerate() {
        let (lo, hi) = points
            .iter()
            .map(|p| p[k])
            .filter(|v| v.is_finite())
            .fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
        *e = if hi >= lo { hi - lo } else { 0.0 };
    }
    if ext[2] <= ext[0].min(ext[1]) {
        (0, 1)
    } else if ext[0] < ext[1] {
        (1, 2)
    } else {
        (0, 2)
    }
}

fn top_view<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    est_label: &str,
    est: &[[f64; 3]],
    gt: Option<&[[f64; 3]]>,
) -> Result<(), String> {
    let e = |x: DrawingAreaErrorKind<DB::ErrorType>| x.to_string();
    root.fill(&WHITE).map_err(e)?;
    let (a, b) = plane(gt.unwrap_or(est));
    let finite_xy = |p: &&[f64; 3]| p[a].is_finite() && p[b].is_finite();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for p in est.iter().chain(gt.unwrap_or(&[])).filter(finite_xy) {
        x0 = x0.min(p[a]);
        x1 = x1.max(p[a]);
        y0 = y0.min(p[b]);
        y1 = y1.max(p[b]);
    }
    if x0 > x1 {
        (x0, x1, y0, y1) = (-1.0, 1.0, -1.0, 1.0);
    }
    // Equal scale on both axes: grow the narrower range to the plot area's aspect.
    let (pw, ph) = ((SIZE.0 - 110) as f64, (SIZE.1 - 130) as f64);
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let scale = ((x1 - x0) / pw).max((y1 - y0) / ph).max(1e-6) * 1.08;
    let (hx, hy) = (scale * pw / 2.0, scale * ph / 2.0);
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 26))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(65)
        .build_cartesian_2d(cx - hx..cx + hx, cy - hy..cy + hy)
        .map_err(e)?;
    let names = ["x [m]", "y [m]", "z [m]"];
    chart
        .configure_mesh()
        .x_desc(names[a])
        .y_desc(names[b])
        .label_style(("sans-serif", 16))
        .draw()
        .map_err(e)?;
    if let Some(gt) = gt {
        let pts: Vec<(f64, f64)> = decimate(gt).iter().filter(finite_xy).map(|p| (p[a], p[b])).collect();
        chart
            .draw_series(LineSeries::new(pts, ShapeStyle::from(&BLACK).stroke_width(2)))
            .map_err(e)?
            .label("ground truth")
            .legend(|(x, y)| {
                PathElement::new(vec![(x, y), (x + 25, y)], ShapeStyle::from(&BLACK).stroke_width(2))
            });
    }
    let pts: Vec<(f64, f64)> = decimate(est).iter().filter(finite_xy).map(|p| (p[a], p[b])).collect();
    let start = pts.first().copied();
    chart
        .draw_series(LineSeries::new(pts, ShapeStyle::from(&BLUE).stroke_width(2)))
        .map_err(e)?
        .label(est_label)
        .legend(|(x, y)| {
            PathElement::new(vec![(x, y), (x + 25, y)], ShapeStyle::from(&BLUE).stroke_width(2))
        });
    if let Some(s) = start {
        chart
            .draw_series(std::iter::once(Circle::new(s, 6, ShapeStyle::from(&RED).filled())))
            .map_err(e)?
            .label("start")
            .legend(|(x, y)| Circle::new((x + 12, y), 5, ShapeStyle::from(&RED).filled()));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .label_font(("sans-serif", 18))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(e)?;
    root.present().map_err(e)
}

fn error_series<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[(f64, f64)],
) -> Result<(), String> {
    let e = |x: DrawingAreaErrorKind<DB::ErrorType>| x.to_string();
    root.fill(&WHITE).map_err(e)?;
    let pts: Vec<(f64, f64)> =
        series.iter().copied().filter(|(t, v)| t.is_finite() && v.is_finite()).collect();
    let t0 = pts.first().map_or(0.0, |p| p.0);
    let pts: Vec<(f64, f64)> = decimate(&pts).into_iter().map(|(t, v)| (t - t0, v)).collect();
    let t1 = pts.iter().map(|p| p.0).fold(0.0f64, f64::max).max(1e-3);
    let vmax = pts.iter().map(|p| p.1).fold(0.0f64, f64::max).max(1e-9) * 1.1;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 26))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(75)
        .build_cartesian_2d(0.0..t1, 0.0..vmax)
        .map_err(e)?;
    chart.configure_mesh().x_desc(x_desc).y_desc(y_desc).label_style(("sans-serif", 16)).draw().map_err(e)?;
    chart.draw_series(LineSeries::new(pts, ShapeStyle::from(&BLUE).stroke_width(2))).map_err(e)?;
    root.present().map_err(e)
}

fn write_with(
    path: &Path,
    png: impl FnOnce(DrawingArea<BitMapBackend<'_>, Shift>) -> Result<(), String>,
    svg: impl FnOnce(DrawingArea<SVGBackend<'_>, Shift>) -> Result<(), String>,
) -> Result<(), PlotError> {
    let kind = kind_of(path)?;
    if let Some(dir) = path.parent()
        && !dir.as_os_str().is_empty()
    {
        std::fs::create_dir_all(dir).map_err(|e| PlotError(format!("plot {}: {e}", dir.display())))?;
    }
    register_font();
    let r = match kind {
        Kind::Png => png(BitMapBackend::new(path, SIZE).into_drawing_area()),
        Kind::Svg => svg(SVGBackend::new(path, SIZE).into_drawing_area()),
    };
    r.map_err(|e| PlotError(format!("plot {}: {}", path.display(), crate::diag::one_line(&e))))
}

/// Writes the trajectory seen from above (x right, y up, equal scale; x-z for a camera frame
/// whose z spans more than x or y), labelled `est_label`, with the ground truth in black when
/// given. Positions in metres.
pub fn plot_trajectory_top_view(
    path: &Path,
    title: &str,
    est_label: &str,
    est: &[[f64; 3]],
    gt: Option<&[[f64; 3]]>,
) -> Result<(), PlotError> {
    write_with(path, |a| top_view(a, title, est_label, est, gt), |a| top_view(a, title, est_label, est, gt))
}

/// Writes an error series: `series` holds (x, error) pairs, x shown from the first pair's
/// (seconds for a time axis, `x_desc` names it).
pub fn plot_error_over_time(
    path: &Path,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[(f64, f64)],
) -> Result<(), PlotError> {
    write_with(
        path,
        |a| error_series(a, title, x_desc, y_desc, series),
        |a| error_series(a, title, x_desc, y_desc, series),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bundled_font_loads() {
        assert!(FONT.len() < 16 * 1024, "keep the bundled font small");
        assert!(plotters::style::register_font("loglio-test", FontStyle::Normal, FONT).is_ok());
    }

    #[test]
    fn writes_png_and_svg() {
        let dir = std::env::temp_dir().join(format!("loglio-plot-{}", std::process::id()));
        let est: Vec<[f64; 3]> = (0..500)
            .map(|i| {
                let a = i as f64 * 0.02;
                [10.0 * a.cos(), 5.0 * a.sin(), 0.0]
            })
            .collect();
        let gt: Vec<[f64; 3]> = est.iter().map(|p| [p[0] + 0.3, p[1], 0.0]).collect();
        let png = dir.join("traj.png");
        plot_trajectory_top_view(&png, "top view", "estimate", &est, Some(&gt)).unwrap();
        // A camera-frame trajectory (y down, z forward) is drawn in x-z.
        let cam: Vec<[f64; 3]> = est.iter().map(|p| [p[0], 0.01 * p[1], p[1]]).collect();
        assert_eq!(plane(&cam), (0, 2));
        assert_eq!(plane(&est), (0, 1));
        let bytes = std::fs::read(&png).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
        let svg = dir.join("err.svg");
        let series: Vec<(f64, f64)> =
            (0..100).map(|i| (100.0 + i as f64 * 0.1, (i as f64 * 0.1).sin().abs())).collect();
        plot_error_over_time(&svg, "APE", "time since start [s]", "error [m]", &series).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.starts_with("<svg") && text.contains("time since start [s]"));
        assert_eq!(
            plot_error_over_time(&dir.join("x.jpg"), "t", "x", "y", &series).unwrap_err().0,
            format!("plot {}: the file name must end in .png or .svg", dir.join("x.jpg").display())
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
