//! The loss curve of a training run: total loss, L_CFM and L_open against step on a
//! logarithmic axis, as a PNG written atomically (`loss.png` beside `metrics.csv`).
use std::fs;
use std::path::Path;

use plotters::prelude::*;

use crate::policy::error::{PolicyError, Result};
use crate::policy::training::metrics::MetricsRow;

/// Draws the loss curve (total loss, L_CFM and L_open against step, log-scale
/// y) to a PNG of `width` x `height` pixels at `path`, atomically. Rows with
/// non-positive or non-finite values are left out of their series. When no
/// font can be loaded the plot is drawn without text rather than failing.
pub fn plot_loss_curve(rows: &[MetricsRow], path: &Path, width: u32, height: u32) -> Result<()> {
    if rows.is_empty() {
        return Err(PolicyError::Invalid("plot_loss_curve: no metrics rows to plot".into()));
    }
    if width < 64 || height < 64 {
        return Err(PolicyError::Invalid(format!(
            "plot_loss_curve: {width}x{height} px is too small (at least 64x64)"
        )));
    }
    let file_error = |m: String| PolicyError::File { path: path.to_path_buf(), message: m };
    let with_text = crate::files::write_atomic_or(
        path,
        |tmp| draw_loss_curve(rows, tmp, width, height, true),
        |e| PolicyError::io(path, "write", e),
    );
    match with_text {
        Ok(()) => Ok(()),
        Err(first) => crate::files::write_atomic_or(
            path,
            |tmp| draw_loss_curve(rows, tmp, width, height, false),
            |e| PolicyError::io(path, "write", e),
        )
        .map_err(|second| file_error(format!("cannot draw the loss curve: {first}; without text: {second}"))),
    }
}

/// A log-axis tick label: `100`, `0.1`, `1e-5` (not `9.999999999e-5`).
fn log_label(v: f64) -> String {
    if v.is_nan() || v <= 0.0 {
        return format!("{v}");
    }
    let exponent = v.log10().round() as i32;
    if (v / 10f64.powi(exponent) - 1.0).abs() > 1e-6 {
        return format!("{v:.2e}");
    }
    match exponent {
        0..=3 => format!("{}", 10i32.pow(exponent as u32)),
        -3..0 => format!("{:.*}", exponent.unsigned_abs() as usize, 10f64.powi(exponent)),
        _ => format!("1e{exponent}"),
    }
}

fn draw_loss_curve(rows: &[MetricsRow], path: &Path, width: u32, height: u32, text: bool) -> Result<()> {
    let plot_error = |e: String| PolicyError::File { path: path.to_path_buf(), message: e };
    type Series = (&'static str, RGBColor, fn(&MetricsRow) -> f64);
    let series: [Series; 3] = [
        ("loss (total)", RGBColor(31, 119, 180), |r| r.loss),
        ("L_CFM", RGBColor(214, 39, 40), |r| r.cfm),
        ("L_open", RGBColor(44, 160, 44), |r| r.bce),
    ];
    let positive = |v: f64| v.is_finite() && v > 0.0;
    let values = rows.iter().flat_map(|r| series.iter().map(move |(_, _, f)| f(r))).filter(|&v| positive(v));
    let (mut y_min, mut y_max) = values.fold((f64::INFINITY, 0.0f64), |(lo, hi), v| (lo.min(v), hi.max(v)));
    if !y_min.is_finite() {
        (y_min, y_max) = (1e-3, 1.0);
    }
    let (y_min, y_max) = (y_min * 0.8, y_max * 1.25);
    let x_min = rows.iter().map(|r| r.step).min().unwrap_or(0);
    let x_max = rows.iter().map(|r| r.step).max().unwrap_or(1).max(x_min + 1);

    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| plot_error(e.to_string()))?;
    let mut builder = ChartBuilder::on(&root);
    builder.margin(12);
    if text {
        builder.caption("FlowRAM training loss", ("sans-serif", 20)).x_label_area_size(36).y_label_area_size(64);
    }
    let mut chart =
        builder.build_cartesian_2d(x_min..x_max, (y_min..y_max).log_scale()).map_err(|e| plot_error(e.to_string()))?;
    let mut mesh = chart.configure_mesh();
    if text {
        mesh.x_desc("step").y_desc("loss (log)").y_label_formatter(&|v| log_label(*v));
    } else {
        mesh.disable_x_axis().disable_y_axis();
    }
    mesh.draw().map_err(|e| plot_error(e.to_string()))?;
    for (label, color, value) in series {
        let points: Vec<(u64, f64)> = rows.iter().map(|r| (r.step, value(r))).filter(|&(_, v)| positive(v)).collect();
        let drawn =
            chart.draw_series(LineSeries::new(points, color.stroke_width(2))).map_err(|e| plot_error(e.to_string()))?;
        if text {
            drawn.label(label).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        }
    }
    if text {
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| plot_error(e.to_string()))?;
    }
    root.present().map_err(|e| plot_error(e.to_string()))?;
    drop(chart);
    drop(root);
    // The backend writes on present(); make sure the file exists.
    if !fs::metadata(path).map(|m| m.len() > 0).unwrap_or(false) {
        return Err(plot_error("the PNG backend wrote nothing".into()));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::training::test_support::{metrics_row as row, tmp_dir};
    use std::fs::{self, File};

    #[test]
    fn log_axis_labels_are_short() {
        let labels: Vec<String> =
            [1e-6, 9.99999999e-6, 1e-3, 0.1, 1.0, 100.0, 1e4, 0.05].into_iter().map(log_label).collect();
        assert_eq!(labels, ["1e-6", "1e-5", "0.001", "0.1", "1", "100", "1e4", "5.00e-2"]);
    }

    #[test]
    fn loss_curve_png_is_written_and_decodable() {
        let dir = tmp_dir("png");
        let path = dir.join("loss.png");
        let mut rows: Vec<MetricsRow> = (1..=200).map(row).collect();
        rows[5].bce = 0.0; // left out of the log plot, not an error
        plot_loss_curve(&rows, &path, 640, 400).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (640, 400));
        // Not blank: some pixels are neither white nor grey (the curves).
        let colored = buf[..info.buffer_size()]
            .chunks(info.color_type.samples())
            .filter(|p| p.len() >= 3 && (p[0] as i32 - p[1] as i32).abs() > 60)
            .count();
        assert!(colored > 100, "only {colored} coloured pixels");
        let names: Vec<String> =
            fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        assert_eq!(names, vec!["loss.png".to_string()], "no temporary files left");
        assert!(plot_loss_curve(&[], &path, 640, 400).is_err());
        fs::remove_dir_all(&dir).ok();
    }
}
