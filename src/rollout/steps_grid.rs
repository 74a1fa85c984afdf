//! The Table C analogue: closed-loop success and inference latency against the number of Euler
//! steps, for one or more arms (a checkpoint, sampled with DRS or with global geometric tokens),
//! gathered from the results files of `flowram bench success --steps N [--no-drs] --out FILE`
//! ([`steps_grid`]), and drawn as a PNG ([`plot_steps_grid`]): success with its 95 % Wilson
//! interval on the left, the median inference latency on the right, both against the steps on a
//! log2 axis.
//!
//! Every cell must be a whole, complete evaluation of the same tasks, seeds, keyframe limit,
//! cameras, samples per observation, consensus rule and pointer temperature, so the cells differ
//! only in the checkpoint, the steps
//! and DRS: the comparison is paired on seeds.
use std::path::{Path, PathBuf};

use plotters::prelude::*;
use serde::Serialize;

use super::RolloutError;
use super::evaluation::SuccessRecord;
use crate::stats::{median, wilson_interval};

/// One task's successes in a cell.
#[derive(Debug, Clone, Serialize)]
pub struct TaskCount {
    pub task: String,
    pub successes: usize,
    pub episodes: usize,
}

/// One cell of the grid: an arm sampled with a number of Euler steps.
#[derive(Debug, Clone, Serialize)]
pub struct GridCell {
    /// The checkpoint's run or folder name, with ", global tokens" when it was sampled without DRS.
    pub arm: String,
    pub checkpoint: String,
    pub checkpoint_digest: String,
    pub drs: bool,
    pub steps: usize,
    /// Episodes over all tasks, and how many succeeded.
    pub episodes: usize,
    pub successes: usize,
    pub success_rate: f64,
    pub success_ci95: [f64; 2],
    pub tasks: Vec<TaskCount>,
    /// Median over the episodes of each episode's median inference time (observation to
    /// keyframe, all samples of the consensus), ms.
    pub inference_ms_median: f64,
    /// The results file the cell was read from.
    pub results: String,
}

/// The cells of the results files `records` (path, record), sorted by arm, then steps.
pub fn steps_grid(records: &[(PathBuf, SuccessRecord)]) -> Result<Vec<GridCell>, RolloutError> {
    let grid_error = |problem: String| RolloutError::Grid { problem };
    let Some((first_path, first)) = records.first() else {
        return Err(grid_error("no results files to tabulate (give the `bench success --out` files)".into()));
    };
    let mut cells: Vec<GridCell> = Vec::with_capacity(records.len());
    for (path, record) in records {
        if !record.shard.is_whole()
            || !record.complete()
            || record.outcomes.len() != record.tasks.len() * record.episodes
        {
            return Err(grid_error(format!(
                "{} is an incomplete or single-shard results file, or one with extra outcomes; finish it (re-run the same `bench success`) or \
                 `flowram merge` its shards first",
                path.display()
            )));
        }
        let setting = |r: &SuccessRecord| {
            let sampling = (
                r.samples,
                r.consensus,
                r.pointer_temperature.to_bits(),
                r.pointer_posterior,
                r.pointer_posterior_width.to_bits(),
                r.pointer_guidance.to_bits(),
            );
            (
                r.tasks.clone(),
                r.seed,
                r.episodes,
                r.max_keyframes,
                r.cameras.clone(),
                sampling,
                r.expert_versions.clone(),
            )
        };
        if setting(record) != setting(first) {
            return Err(grid_error(format!(
                "{} and {} are not on the same episodes and sampling: tasks {:?}, seeds {}+{}, max keyframes {}, \
                 cameras {:?}, samples {} ({}, pointer temperature {}, posterior {} width {} m, guidance {}), expert versions {} \
                 against tasks {:?}, seeds {}+{}, max keyframes {}, cameras {:?}, samples {} ({}, pointer temperature {}, \
                 posterior {} width {} m, guidance {}), expert versions {}",
                path.display(),
                first_path.display(),
                record.tasks,
                record.seed,
                record.episodes,
                record.max_keyframes,
                record.cameras,
                record.samples,
                record.consensus.name(),
                record.pointer_temperature,
                record.pointer_posterior,
                record.pointer_posterior_width,
                record.pointer_guidance,
                record.expert_versions_text(),
                first.tasks,
                first.seed,
                first.episodes,
                first.max_keyframes,
                first.cameras,
                first.samples,
                first.consensus.name(),
                first.pointer_temperature,
                first.pointer_posterior,
                first.pointer_posterior_width,
                first.pointer_guidance,
                first.expert_versions_text()
            )));
        }
        if let Some(twin) = cells.iter().find(|c| {
            (c.checkpoint_digest.as_str(), c.drs, c.steps)
                == (record.checkpoint_digest.as_str(), record.drs, record.steps)
        }) {
            return Err(grid_error(format!(
                "{} and {} are the same cell ({}, {} steps, DRS {}): give each once",
                path.display(),
                twin.results,
                record.checkpoint,
                record.steps,
                record.drs
            )));
        }
        let table = record.table();
        let successes: usize = table.iter().map(|t| t.successes).sum();
        let episodes: usize = table.iter().map(|t| t.episodes).sum();
        let inference: Vec<f64> = record.outcomes.iter().map(|o| o.outcome.inference_ms).collect();
        let mut arm = arm_name(&record.checkpoint);
        if !record.drs {
            arm.push_str(", global tokens");
        }
        cells.push(GridCell {
            arm,
            checkpoint: record.checkpoint.clone(),
            checkpoint_digest: record.checkpoint_digest.clone(),
            drs: record.drs,
            steps: record.steps,
            episodes,
            successes,
            success_rate: successes as f64 / episodes.max(1) as f64,
            success_ci95: wilson_interval(successes, episodes),
            tasks: table
                .iter()
                .map(|t| TaskCount { task: t.task.clone(), successes: t.successes, episodes: t.episodes })
                .collect(),
            inference_ms_median: median(&inference),
            results: path.display().to_string(),
        });
    }
    let arms: Vec<(String, String)> = cells.iter().map(|c| (c.arm.clone(), c.checkpoint_digest.clone())).collect();
    for (i, (arm, digest)) in arms.iter().enumerate() {
        if let Some((_, other)) = arms[..i].iter().find(|(a, d)| a == arm && d != digest) {
            return Err(grid_error(format!(
                "two different checkpoints (weights {digest} and {other}) are both named {arm:?} (their run's or \
                 folder's name): copy one run or checkpoint folder to another name and evaluate it there"
            )));
        }
    }
    cells.sort_by(|a, b| (a.arm.as_str(), a.steps).cmp(&(b.arm.as_str(), b.steps)));
    Ok(cells)
}

/// The name of a checkpoint folder: the run's (`runs/NAME/checkpoints/step-N` is `NAME`), or
/// the folder's own.
fn arm_name(checkpoint: &str) -> String {
    let path = Path::new(checkpoint);
    let run = path
        .parent()
        .filter(|p| p.file_name().is_some_and(|n| n == "checkpoints"))
        .and_then(Path::parent)
        .and_then(Path::file_name);
    match run.or(path.file_name()) {
        Some(name) => name.to_string_lossy().into_owned(),
        None => checkpoint.to_string(),
    }
}

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
    RGBColor(23, 190, 207),
];

/// Draws the grid to a PNG of `width` x `height` pixels at `path`, atomically: success (%, with
/// its 95 % interval) and median inference latency (ms) against Euler steps, one line per arm.
/// When no font can be loaded the plot is drawn without text rather than failing.
pub fn plot_steps_grid(cells: &[GridCell], path: &Path, width: u32, height: u32) -> Result<(), RolloutError> {
    let plot_error = |problem: String| RolloutError::Plot { path: path.to_path_buf(), problem };
    if cells.is_empty() {
        return Err(plot_error("no cells to plot".into()));
    }
    if path.extension().is_none_or(|e| !e.eq_ignore_ascii_case("png")) {
        return Err(plot_error("the plot is a PNG: give a path ending in .png".into()));
    }
    if width < 256 || height < 128 {
        return Err(plot_error(format!("{width}x{height} px is too small for two panels (at least 256x128)")));
    }
    let write = |text: bool| {
        crate::files::write_atomic_or(
            path,
            |tmp| draw(cells, tmp, width, height, text),
            |e| plot_error(format!("cannot write: {e}")),
        )
    };
    match write(true) {
        Ok(()) => Ok(()),
        Err(first) => write(false).map_err(|second| plot_error(format!("{first}; without text: {second}"))),
    }
}

fn draw(cells: &[GridCell], path: &Path, width: u32, height: u32, text: bool) -> Result<(), RolloutError> {
    let plot_error = |e: String| RolloutError::Plot { path: path.to_path_buf(), problem: e };
    let mut arms: Vec<&str> = Vec::new();
    for c in cells {
        if !arms.contains(&c.arm.as_str()) {
            arms.push(&c.arm);
        }
    }
    // The x axis is log2(steps), labelled with the steps themselves (2, 4, 8, 16).
    let log2 = |steps: usize| (steps.max(1) as f64).log2();
    let x_min = cells.iter().map(|c| log2(c.steps)).fold(f64::INFINITY, f64::min);
    let x_max = cells.iter().map(|c| log2(c.steps)).fold(f64::NEG_INFINITY, f64::max);
    let x_range = (x_min - 0.5)..(x_max + 0.5);
    // Ticks at the powers of two (steps such as 3 or 12 are drawn, not labelled).
    let ticks = (x_max - x_min).round() as usize + 1;
    let x_label = |v: &f64| {
        if (v - v.round()).abs() < 1e-6 { format!("{}", 2f64.powf(v.round()).round() as i64) } else { String::new() }
    };
    let latency_max = cells.iter().map(|c| c.inference_ms_median).filter(|v| v.is_finite()).fold(1.0f64, f64::max);

    let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| plot_error(e.to_string()))?;
    let (left, right) = root.split_horizontally(width / 2);

    // Left: success with its interval.
    let mut builder = ChartBuilder::on(&left);
    builder.margin(12);
    if text {
        builder.caption("closed-loop success", ("sans-serif", 18)).x_label_area_size(36).y_label_area_size(48);
    }
    let mut chart =
        builder.build_cartesian_2d(x_range.clone(), 0.0f64..100.0).map_err(|e| plot_error(e.to_string()))?;
    let mut mesh = chart.configure_mesh();
    if text {
        mesh.x_desc("Euler steps").y_desc("success (%)").x_labels(ticks).x_label_formatter(&x_label);
    } else {
        mesh.disable_x_axis().disable_y_axis();
    }
    mesh.draw().map_err(|e| plot_error(e.to_string()))?;
    for (k, arm) in arms.iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        let mine: Vec<&GridCell> = cells.iter().filter(|c| c.arm == *arm).collect();
        // Arms side by side around each step count, so that their intervals do not overlap.
        let dodge = 0.04 * (k as f64 - (arms.len() - 1) as f64 / 2.0);
        let points: Vec<(f64, f64)> = mine.iter().map(|c| (log2(c.steps) + dodge, 100.0 * c.success_rate)).collect();
        let drawn = chart
            .draw_series(LineSeries::new(points.clone(), color.stroke_width(2)))
            .map_err(|e| plot_error(e.to_string()))?;
        if text {
            drawn.label(*arm).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        }
        chart
            .draw_series(points.iter().map(|&p| Circle::new(p, 3, color.filled())))
            .map_err(|e| plot_error(e.to_string()))?;
        chart
            .draw_series(mine.iter().map(|c| {
                let x = log2(c.steps) + dodge;
                PathElement::new(vec![(x, 100.0 * c.success_ci95[0]), (x, 100.0 * c.success_ci95[1])], color)
            }))
            .map_err(|e| plot_error(e.to_string()))?;
    }
    if text {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| plot_error(e.to_string()))?;
    }

    // Right: latency.
    let mut builder = ChartBuilder::on(&right);
    builder.margin(12);
    if text {
        builder.caption("inference latency (median)", ("sans-serif", 18)).x_label_area_size(36).y_label_area_size(48);
    }
    let mut chart =
        builder.build_cartesian_2d(x_range, 0.0f64..latency_max * 1.15).map_err(|e| plot_error(e.to_string()))?;
    let mut mesh = chart.configure_mesh();
    if text {
        mesh.x_desc("Euler steps").y_desc("ms").x_labels(ticks).x_label_formatter(&x_label);
    } else {
        mesh.disable_x_axis().disable_y_axis();
    }
    mesh.draw().map_err(|e| plot_error(e.to_string()))?;
    for (k, arm) in arms.iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        let points: Vec<(f64, f64)> = cells
            .iter()
            .filter(|c| c.arm == *arm && c.inference_ms_median.is_finite())
            .map(|c| (log2(c.steps), c.inference_ms_median))
            .collect();
        chart
            .draw_series(LineSeries::new(points.clone(), color.stroke_width(2)))
            .map_err(|e| plot_error(e.to_string()))?;
        chart
            .draw_series(points.iter().map(|&p| Circle::new(p, 3, color.filled())))
            .map_err(|e| plot_error(e.to_string()))?;
    }
    root.present().map_err(|e| plot_error(e.to_string()))?;
    drop(chart);
    drop(left);
    drop(right);
    drop(root);
    if !std::fs::metadata(path).map(|m| m.len() > 0).unwrap_or(false) {
        return Err(plot_error("the PNG backend wrote nothing".into()));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::config::Consensus;
    use crate::rollout::evaluation::{RecordedOutcome, SUCCESS_FORMAT, SeedOutcome};
    use crate::rollout::shard::Shard;

    /// A whole record of `checkpoint` at `steps`: two tasks, four seeds each; seed i of task t
    /// succeeds when `solved(t, i)`, inferring in `ms` ms.
    fn record(
        checkpoint: &str,
        steps: usize,
        drs: bool,
        ms: f64,
        solved: impl Fn(usize, u64) -> bool,
    ) -> SuccessRecord {
        let outcomes = (0..2)
            .flat_map(|task| (0..4u64).map(move |i| (task, i)))
            .map(|(task, i)| RecordedOutcome {
                task,
                outcome: SeedOutcome {
                    seed: 1000 + i,
                    variation: i as usize,
                    success: solved(task, i),
                    keyframes: 3,
                    reached: 3,
                    inference_ms: ms + i as f64,
                },
            })
            .collect();
        SuccessRecord {
            format: SUCCESS_FORMAT.into(),
            revision: "test".into(),
            checkpoint: checkpoint.into(),
            checkpoint_digest: format!("digest of {checkpoint}"),
            tasks: vec!["open_drawer".into(), "push_buttons".into()],
            episodes: 4,
            seed: 1000,
            max_keyframes: 25,
            steps,
            samples: 8,
            consensus: Consensus::Medoid,
            pointer_temperature: 1.0,
            pointer_posterior: false,
            pointer_posterior_width: 0.0,
            pointer_guidance: 1.0,
            drs,
            cameras: vec!["front".into()],
            expert_versions: vec![1, 2],
            shard: Shard::WHOLE,
            outcomes,
        }
    }

    fn entry(name: &str, r: SuccessRecord) -> (PathBuf, SuccessRecord) {
        (PathBuf::from(name), r)
    }

    #[test]
    fn cells_count_every_task_and_sort_by_arm_then_steps() {
        let records = vec![
            entry("d8.json", record("runs/drs", 8, true, 100.0, |_, i| i < 3)),
            entry("d2.json", record("runs/drs", 2, true, 40.0, |t, i| t == 0 && i == 0)),
            entry("g8.json", record("runs/drs", 8, false, 90.0, |_, _| true)),
            entry("o4.json", record("runs/other", 4, true, 60.0, |_, _| false)),
        ];
        let cells = steps_grid(&records).unwrap();
        let keys: Vec<(&str, usize)> = cells.iter().map(|c| (c.arm.as_str(), c.steps)).collect();
        assert_eq!(keys, [("drs", 2), ("drs", 8), ("drs, global tokens", 8), ("other", 4)]);
        let d8 = &cells[1];
        assert_eq!((d8.successes, d8.episodes), (6, 8));
        assert_eq!(d8.success_ci95, wilson_interval(6, 8));
        assert_eq!(d8.tasks.iter().map(|t| t.successes).collect::<Vec<_>>(), [3, 3]);
        assert_eq!(d8.inference_ms_median, 101.5); // 100..103 twice
        assert_eq!(d8.results, "d8.json");
        assert_eq!((cells[0].successes, cells[2].successes, cells[3].successes), (1, 8, 0));
    }

    #[test]
    fn arms_are_named_after_their_run() {
        assert_eq!(arm_name("runs/five-tasks-fw/checkpoints/step-000014000"), "five-tasks-fw");
        assert_eq!(arm_name("models/policy/pretrained/five-tasks"), "five-tasks");
        assert_eq!(arm_name("checkpoints/step-1"), "step-1");
        assert_eq!(arm_name("/"), "/");
    }

    #[test]
    fn cells_that_are_not_comparable_are_refused() {
        let base = || entry("a.json", record("runs/drs", 8, true, 100.0, |_, _| true));
        let message = |records: Vec<(PathBuf, SuccessRecord)>| steps_grid(&records).unwrap_err().to_string();
        assert!(message(vec![]).contains("no results files"));
        let mut other_seeds = record("runs/drs", 4, true, 100.0, |_, _| true);
        other_seeds.seed = 2000;
        other_seeds.outcomes.iter_mut().for_each(|o| o.outcome.seed += 1000);
        assert!(message(vec![base(), entry("b.json", other_seeds)]).contains("not on the same episodes"));
        let mut other_samples = record("runs/drs", 4, true, 100.0, |_, _| true);
        other_samples.samples = 1;
        assert!(message(vec![base(), entry("b.json", other_samples)]).contains("samples 1"));
        let mut other_rule = record("runs/drs", 4, true, 100.0, |_, _| true);
        other_rule.consensus = Consensus::Mode;
        assert!(message(vec![base(), entry("b.json", other_rule)]).contains("samples 8 (mode"));
        let mut sharpened = record("runs/drs", 4, true, 100.0, |_, _| true);
        sharpened.pointer_temperature = 0.1;
        assert!(message(vec![base(), entry("b.json", sharpened)]).contains("pointer temperature 0.1"));
        let twice = message(vec![base(), entry("b.json", record("runs/drs", 8, true, 50.0, |_, _| false))]);
        assert!(twice.contains("same cell") && twice.contains("a.json"), "{twice}");
        let mut incomplete = record("runs/drs", 4, true, 100.0, |_, _| true);
        incomplete.outcomes.pop();
        assert!(message(vec![base(), entry("b.json", incomplete)]).contains("incomplete"));
        let mut shard = record("runs/drs", 4, true, 100.0, |_, _| true);
        shard.shard = Shard { index: 0, count: 2 };
        assert!(message(vec![base(), entry("b.json", shard)]).contains("single-shard"));
        let mut namesake = record("elsewhere/drs", 4, true, 100.0, |_, _| true);
        namesake.checkpoint_digest = "other weights".into();
        assert!(message(vec![base(), entry("b.json", namesake)]).contains("both named"));
    }

    #[test]
    fn the_plot_is_a_decodable_png_with_both_panels_drawn() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("grid.png");
        let records: Vec<_> = [2, 4, 8, 16]
            .into_iter()
            .flat_map(|s| {
                [
                    entry("d", record("runs/drs", s, true, 10.0 * s as f64, move |_, i| i < (s as u64).min(4))),
                    entry("g", record("runs/drs", s, false, 8.0 * s as f64, |_, i| i < 2)),
                ]
            })
            .collect();
        let cells = steps_grid(&records).unwrap();
        plot_steps_grid(&cells, &path, 960, 400).unwrap();
        let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (960, 400));
        let samples = info.color_type.samples();
        let coloured_in = |x0: usize, x1: usize| {
            buf[..info.buffer_size()]
                .chunks(samples)
                .enumerate()
                .filter(|(k, p)| {
                    (x0..x1).contains(&(k % 960)) && p.len() >= 3 && (p[0] as i32 - p[2] as i32).abs() > 60
                })
                .count()
        };
        assert!(coloured_in(0, 480) > 100 && coloured_in(480, 960) > 100, "both panels hold curves");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, ["grid.png"], "no temporary files left");
        assert!(plot_steps_grid(&[], &path, 960, 400).is_err());
        assert!(plot_steps_grid(&cells, &path, 100, 100).is_err());
        let not_png = plot_steps_grid(&cells, &dir.path().join("grid"), 960, 400).unwrap_err().to_string();
        assert!(not_png.contains(".png"), "{not_png}");
    }
}
