//! `flowram tune`: a step response of a controller profile, with its figures and a plot of
//! response vs reference per axis.
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use flowram::control::tuning::{Step, StepRun, step_response};
use plotters::prelude::*;
use serde::Serialize;

#[derive(Debug, Args)]
pub struct TuneArgs {
    /// Controller profile (TOML); default controllers/osc.toml.
    #[arg(long)]
    config: Option<PathBuf>,
    /// The step from the home pose: dx,dy,dz[,rx,ry,rz] in metres and radians (base frame).
    #[arg(long, allow_hyphen_values = true)]
    step: Step,
    /// Move the reference through the jerk-limited trajectory instead of a raw step.
    #[arg(long)]
    smooth: bool,
    /// Seconds recorded after the step.
    #[arg(long, default_value_t = 2.0)]
    duration: f64,
    /// Write a PNG plot of response vs reference per axis.
    #[arg(long)]
    plot: Option<PathBuf>,
    #[arg(long, default_value = "default")]
    scene: String,
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct TuneReport<'a> {
    config: &'a str,
    step: [f64; 6],
    smooth: bool,
    #[serde(flatten)]
    metrics: &'a flowram::control::tuning::StepMetrics,
}

pub fn run(args: TuneArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.duration > 0.0 && args.duration <= 60.0, "--duration must be in (0, 60] seconds");
    let config = flowram::rollout::stack::load_controller_config(args.config.as_deref())?;
    let config_name =
        args.config.as_deref().map_or_else(|| "controllers/osc.toml".to_string(), |p| p.display().to_string());
    let (mut world, mut runner) = flowram::rollout::stack::simulated_stack(&args.scene, config)?;
    let result = step_response(&mut world, &mut runner, &args.step, args.smooth, args.duration)?;
    if let Some(path) = &args.plot {
        plot(&result, path).with_context(|| format!("writing the plot {}", path.display()))?;
    }
    let s = &args.step;
    let report = TuneReport {
        config: &config_name,
        step: [s.translation.x, s.translation.y, s.translation.z, s.rotation.x, s.rotation.y, s.rotation.z],
        smooth: args.smooth,
        metrics: &result.metrics,
    };
    if args.json {
        return super::print_json(&report);
    }
    let m = &result.metrics;
    let opt = |v: Option<f64>| v.map_or("never".to_string(), |x| format!("{x:.3} s"));
    println!("rise time (10-90 %): {}", opt(m.rise_time_s));
    println!("overshoot: {:.2} %", m.overshoot_pct);
    println!("settling time (2 %): {}", opt(m.settling_time_s));
    println!("steady-state error: {:.4} mm, {:.4} deg", m.steady_state_error_mm, m.steady_state_error_deg);
    println!("peak torque: {:.0} % of the limit; QP fallbacks: {}", m.peak_torque_ratio * 100.0, m.qp_fallbacks);
    Ok(())
}

/// Six panels (x, y, z in mm; rx, ry, rz in deg): response and reference against time.
fn plot(run: &StepRun, path: &Path) -> anyhow::Result<()> {
    register_font()?;
    let tmp = path.with_extension("tmp.png");
    {
        let root = BitMapBackend::new(&tmp, (1200, 800)).into_drawing_area();
        root.fill(&WHITE)?;
        let title = if run.smooth { "step response (smooth reference)" } else { "step response (raw step)" };
        let root = root.titled(title, ("sans-serif", 22))?;
        let panels = root.split_evenly((2, 3));
        let names = ["x (mm)", "y (mm)", "z (mm)", "rx (deg)", "ry (deg)", "rz (deg)"];
        let t_end = run.t.last().copied().unwrap_or(1.0);
        for (axis, panel) in panels.iter().enumerate() {
            let scale = if axis < 3 { 1e3 } else { 180.0 / std::f64::consts::PI };
            let series = |v: &[[f64; 6]]| v.iter().zip(&run.t).map(|(x, &t)| (t, x[axis] * scale)).collect::<Vec<_>>();
            let (response, reference) = (series(&run.response), series(&run.reference));
            let (lo, hi) =
                response.iter().chain(&reference).fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
            let pad = ((hi - lo) * 0.1).max(0.05);
            let mut chart = ChartBuilder::on(panel)
                .caption(names[axis], ("sans-serif", 16))
                .margin(8)
                .x_label_area_size(30)
                .y_label_area_size(50)
                .build_cartesian_2d(0.0..t_end, (lo - pad)..(hi + pad))?;
            chart.configure_mesh().x_desc("t (s)").label_style(("sans-serif", 12)).draw()?;
            chart
                .draw_series(LineSeries::new(reference, &BLUE))?
                .label("reference")
                .legend(|(x, y)| PathElement::new([(x, y), (x + 15, y)], BLUE));
            chart
                .draw_series(LineSeries::new(response, &RED))?
                .label("TCP")
                .legend(|(x, y)| PathElement::new([(x, y), (x + 15, y)], RED));
            chart
                .configure_series_labels()
                .label_font(("sans-serif", 12))
                .border_style(BLACK)
                .background_style(WHITE)
                .draw()?;
        }
        root.present()?;
    }
    std::fs::rename(&tmp, path)?;
    Ok(())
}

/// plotters finds "sans-serif" through fontconfig (DejaVu Sans from Debian's
/// fonts-dejavu-core on these machines); say so if it is missing rather than fail obscurely.
fn register_font() -> anyhow::Result<()> {
    let probe = ("sans-serif", 12).into_font();
    probe.box_size("x").map(|_| ()).map_err(|e| {
        anyhow::anyhow!("plots need a sans-serif font through fontconfig ({e:?}); install Debian's fonts-dejavu-core")
    })
}
