//! Line plots the benchmarks write as PNG files beside `BENCHMARKS.md` (`docs/bench/`).

#![allow(dead_code)] // each benchmark uses its own subset

use std::path::{Path, PathBuf};

use plotters::coord::ranged1d::ValueFormatter;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

/// Where the plots go: `docs/bench/` of this tree.
pub fn dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/bench")
}

/// Text needs a font: DejaVu Sans, as Debian installs it (`fonts-dejavu-core`).
const FONT: &str = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf";

/// Registers [`FONT`] with plotters, once per process.
fn font() -> Result<(), String> {
    static REGISTERED: std::sync::OnceLock<Result<(), String>> = std::sync::OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            let font = std::fs::read(FONT)
                .map_err(|e| format!("{FONT}: {e} (install fonts-dejavu-core to get the plots)"))?;
            register_font(
                "sans-serif",
                FontStyle::Normal,
                Box::leak(font.into_boxed_slice()),
            )
            .map_err(|_| format!("{FONT} is not a font plotters can read"))
        })
        .clone()
}

/// One line of a plot.
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// A plot of `series` against a logarithmic x axis (and y axis when `log_y`: values across
/// orders of magnitude), written as `name`.png in [`dir`]; returns the path, or why it could not
/// be written (the benchmark's tables stand without it).
pub fn log_x(
    name: &str,
    title: &str,
    (x_label, y_label): (&str, &str),
    series: &[Series],
    log_y: bool,
) -> Result<PathBuf, String> {
    font()?;
    std::fs::create_dir_all(dir()).map_err(|e| format!("{}: {e}", dir().display()))?;
    let path = dir().join(format!("{name}.png"));
    let (w, h) = (800u32, 480u32);
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let points = series.iter().flat_map(|s| s.points.iter());
        let (x_min, x_max) = points
            .clone()
            .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
        let (y_min, y_max) =
            points.fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let x = (x_min * 0.8..x_max * 1.25).log_scale();
        if log_y {
            let mut chart = ChartBuilder::on(&root)
                .caption(title, ("sans-serif", 22))
                .margin(16)
                .x_label_area_size(44)
                .y_label_area_size(70)
                .build_cartesian_2d(x, (y_min.max(1e-9) * 0.5..y_max * 2.0).log_scale())
                .map_err(|e| e.to_string())?;
            draw(&mut chart, (x_label, y_label), series)?;
        } else {
            let mut chart = ChartBuilder::on(&root)
                .caption(title, ("sans-serif", 22))
                .margin(16)
                .x_label_area_size(44)
                .y_label_area_size(70)
                .build_cartesian_2d(x, 0.0..(y_max * 1.15).max(1e-9))
                .map_err(|e| e.to_string())?;
            draw(&mut chart, (x_label, y_label), series)?;
        }
        root.present().map_err(|e| e.to_string())?;
    }
    save(path, (w, h), &rgb)
}

/// A chart with linear axes, y from a little below the lowest point (growth shows).
pub fn linear(
    name: &str,
    title: &str,
    (x_label, y_label): (&str, &str),
    series: &[Series],
) -> Result<PathBuf, String> {
    font()?;
    std::fs::create_dir_all(dir()).map_err(|e| format!("{}: {e}", dir().display()))?;
    let path = dir().join(format!("{name}.png"));
    let (w, h) = (800u32, 480u32);
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let points = series.iter().flat_map(|s| s.points.iter());
        let (x_min, x_max) = points
            .clone()
            .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
        let (y_min, y_max) =
            points.fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
        let pad = ((y_max - y_min) * 0.1).max(y_max.abs() * 0.02).max(1e-9);
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(16)
            .x_label_area_size(44)
            .y_label_area_size(70)
            .build_cartesian_2d(x_min..x_max.max(x_min + 1e-9), (y_min - pad)..(y_max + pad))
            .map_err(|e| e.to_string())?;
        draw(&mut chart, (x_label, y_label), series)?;
        root.present().map_err(|e| e.to_string())?;
    }
    save(path, (w, h), &rgb)
}

/// Writes an RGB image of `w` × `h` as a PNG file at `path`.
fn save(path: PathBuf, (w, h): (u32, u32), rgb: &[u8]) -> Result<PathBuf, String> {
    let file = std::fs::File::create(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), w, h);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder
        .write_header()
        .and_then(|mut writer| writer.write_image_data(rgb))
        .map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(path)
}

/// The axes, lines, points and legend of a chart.
fn draw<'a, X, Y>(
    chart: &mut ChartContext<'a, BitMapBackend<'a>, Cartesian2d<X, Y>>,
    (x_label, y_label): (&str, &str),
    series: &[Series],
) -> Result<(), String>
where
    X: Ranged<ValueType = f64> + ValueFormatter<f64>,
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_label)
        .x_labels(6)
        .y_labels(8)
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| {
            if v.abs() >= 10.0 {
                format!("{v:.0}")
            } else {
                format!("{v:.2}")
            }
        })
        .label_style(("sans-serif", 14))
        .draw()
        .map_err(|e| e.to_string())?;
    // Dark enough to read on white, told apart without colour vision too (order is the legend's).
    const COLORS: [RGBColor; 5] = [
        RGBColor(0, 90, 181),
        RGBColor(220, 50, 32),
        RGBColor(0, 140, 70),
        RGBColor(120, 60, 160),
        RGBColor(60, 60, 60),
    ];
    for (i, s) in series.iter().enumerate() {
        let color = COLORS[i % COLORS.len()].to_rgba();
        chart
            .draw_series(LineSeries::new(s.points.clone(), color.stroke_width(2)))
            .map_err(|e| e.to_string())?
            .label(s.name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color));
        chart
            .draw_series(s.points.iter().map(|&p| Circle::new(p, 4, color.filled())))
            .map_err(|e| e.to_string())?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .map_err(|e| e.to_string())?;
    Ok(())
}
