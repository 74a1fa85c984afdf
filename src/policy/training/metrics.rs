//! Training metrics on disk: `metrics.csv` (one row per logged step, header
//! once, rows after the resumed step dropped on `--resume`) written
//! atomically.

use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use crate::files::write_atomic;
use crate::policy::error::{PolicyError, Result};

/// The CSV header, in column order.
pub const METRICS_HEADER: &str = "step,loss,cfm,bce,lr,seconds";

/// One logged training step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MetricsRow {
    /// Optimiser step (1-based).
    pub step: u64,
    /// Total weighted loss (`100 * cfm + 10 * bce` by default).
    pub loss: f64,
    /// Velocity MSE (L_CFM, unweighted).
    pub cfm: f64,
    /// Gripper-open BCE (L_open, unweighted).
    pub bce: f64,
    /// Learning rate used for the step.
    pub lr: f64,
    /// Wall-clock seconds of training up to this step (summed over resumes).
    pub seconds: f64,
}

impl MetricsRow {
    fn to_csv(self) -> String {
        format!("{},{},{},{},{},{:.3}", self.step, self.loss, self.cfm, self.bce, self.lr, self.seconds)
    }

    fn parse(line: &str) -> std::result::Result<Self, String> {
        let fields: Vec<&str> = line.trim().split(',').collect();
        if fields.len() != 6 {
            return Err(format!("expected 6 comma-separated fields ({METRICS_HEADER}), found {}", fields.len()));
        }
        let num = |i: usize| -> std::result::Result<f64, String> {
            fields[i].parse::<f64>().map_err(|e| format!("field {} '{}': {e}", i + 1, fields[i]))
        };
        Ok(MetricsRow {
            step: fields[0].parse().map_err(|e| format!("step '{}': {e}", fields[0]))?,
            loss: num(1)?,
            cfm: num(2)?,
            bce: num(3)?,
            lr: num(4)?,
            seconds: num(5)?,
        })
    }
}

/// Reads every row of a metrics CSV (the header is checked and skipped).
pub fn read_metrics(path: &Path) -> Result<Vec<MetricsRow>> {
    let file = File::open(path)
        .map_err(|e| PolicyError::File { path: path.to_path_buf(), message: format!("cannot open: {e}") })?;
    let mut rows = Vec::new();
    for (i, line) in BufReader::new(file).lines().enumerate() {
        let line = line.map_err(|e| PolicyError::File {
            path: path.to_path_buf(),
            message: format!("cannot read line {}: {e}", i + 1),
        })?;
        if i == 0 {
            if line.trim() != METRICS_HEADER {
                return Err(PolicyError::File {
                    path: path.to_path_buf(),
                    message: format!("header is '{}', expected '{METRICS_HEADER}'", line.trim()),
                });
            }
            continue;
        }
        if line.trim().is_empty() {
            continue;
        }
        rows.push(
            MetricsRow::parse(&line)
                .map_err(|m| PolicyError::File { path: path.to_path_buf(), message: format!("line {}: {m}", i + 1) })?,
        );
    }
    Ok(rows)
}

/// Appends rows to `metrics.csv`, flushing each.
pub struct MetricsLog {
    path: PathBuf,
    file: File,
}

impl MetricsLog {
    /// Starts a fresh log at `path` (replacing any old one) with the header.
    pub fn create(path: &Path) -> Result<Self> {
        write_atomic(path, format!("{METRICS_HEADER}\n").as_bytes()).map_err(|e| PolicyError::io(path, "write", e))?;
        Self::open_append(path)
    }

    /// Continues the log of a run resumed after step `resumed_step`: keeps the
    /// rows with `step <= resumed_step`, drops later ones (logged after the
    /// checkpoint, they will be logged again), and appends from there. A
    /// missing file starts a fresh log.
    pub fn resume(path: &Path, resumed_step: u64) -> Result<Self> {
        if !path.exists() {
            return Self::create(path);
        }
        let kept: Vec<MetricsRow> = read_metrics(path)?.into_iter().filter(|r| r.step <= resumed_step).collect();
        let mut text = format!("{METRICS_HEADER}\n");
        for row in kept {
            text.push_str(&row.to_csv());
            text.push('\n');
        }
        write_atomic(path, text.as_bytes()).map_err(|e| PolicyError::io(path, "write", e))?;
        Self::open_append(path)
    }

    fn open_append(path: &Path) -> Result<Self> {
        let file = OpenOptions::new().append(true).open(path).map_err(|e| PolicyError::File {
            path: path.to_path_buf(),
            message: format!("cannot open for appending: {e}"),
        })?;
        Ok(Self { path: path.to_path_buf(), file })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Appends one row and flushes it to the OS.
    pub fn append(&mut self, row: &MetricsRow) -> Result<()> {
        writeln!(self.file, "{}", row.to_csv())
            .and_then(|_| self.file.flush())
            .map_err(|e| PolicyError::File { path: self.path.clone(), message: format!("cannot append: {e}") })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::training::test_support::{metrics_row as row, tmp_dir};
    use std::fs;

    #[test]
    fn csv_resume_drops_rows_after_the_checkpoint() {
        let dir = tmp_dir("csv");
        let path = dir.join("metrics.csv");
        let mut log = MetricsLog::create(&path).unwrap();
        for s in 1..=10 {
            log.append(&row(s)).unwrap();
        }
        drop(log);
        // Crash after step 10; the last checkpoint was at step 6.
        let mut log = MetricsLog::resume(&path, 6).unwrap();
        for s in 7..=8 {
            log.append(&row(s)).unwrap();
        }
        drop(log);
        let rows = read_metrics(&path).unwrap();
        let steps: Vec<u64> = rows.iter().map(|r| r.step).collect();
        assert_eq!(steps, (1..=8).collect::<Vec<_>>());
        assert_eq!(rows[3], row(4));
        let text = fs::read_to_string(&path).unwrap();
        assert_eq!(text.matches(METRICS_HEADER).count(), 1, "header once:\n{text}");
        // A fresh create starts over; resume on a missing file creates it.
        MetricsLog::create(&path).unwrap();
        assert!(read_metrics(&path).unwrap().is_empty());
        let other = dir.join("new.csv");
        MetricsLog::resume(&other, 5).unwrap();
        assert!(read_metrics(&other).unwrap().is_empty());
        fs::write(&other, "step,loss\n1,2\n").unwrap();
        assert!(matches!(read_metrics(&other), Err(PolicyError::File { .. })));
        fs::remove_dir_all(&dir).ok();
    }
}
