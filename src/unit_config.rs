//! Unit-carrying TOML configuration files (`controllers/*.toml`), read with validation.
//!
//! Physical quantities are written with their unit, so a file says what it means:
//! `velocity = { values = [2.175, ...], unit = "rad/s" }` or `time = { value = 0.5, unit = "s" }`.
//! Values are converted to SI on read. A missing field, a wrong unit, a value of the wrong sign
//! or length, or an unknown key gives a [`ConfigError`] that names the file and the field.
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// A configuration file that could not be read or is invalid.
#[derive(Debug, thiserror::Error)]
#[error("{file}: {field}: {message}")]
pub struct ConfigError {
    pub file: PathBuf,
    /// Dotted path of the offending field (`task.position.stiffness`), or `-` for the file.
    pub field: String,
    pub message: String,
}

/// The physical kind of a configured value, with the units accepted for it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantity {
    Angle,
    AngularVelocity,
    AngularAcceleration,
    AngularJerk,
    Length,
    Velocity,
    Acceleration,
    Torque,
    TorqueRate,
    Force,
    /// Joint damping (torque per joint velocity).
    JointDamping,
    Time,
    /// Gain on an error, per second squared: stiffness of an inertia-decoupled task (= w_n^2).
    PerSecondSquared,
    /// Gain per second (velocity per unit error).
    PerSecond,
    /// Gain per second cubed: integral gain of an inertia-decoupled task.
    PerSecondCubed,
    Dimensionless,
}

impl Quantity {
    /// (unit spelling, factor to SI) pairs; the first is the canonical unit.
    fn units(self) -> &'static [(&'static str, f64)] {
        const DEG: f64 = std::f64::consts::PI / 180.0;
        match self {
            Quantity::Angle => &[("rad", 1.0), ("deg", DEG)],
            Quantity::AngularVelocity => &[("rad/s", 1.0), ("deg/s", DEG)],
            Quantity::AngularAcceleration => &[("rad/s^2", 1.0), ("deg/s^2", DEG)],
            Quantity::AngularJerk => &[("rad/s^3", 1.0), ("deg/s^3", DEG)],
            Quantity::Length => &[("m", 1.0), ("cm", 0.01), ("mm", 0.001)],
            Quantity::Velocity => &[("m/s", 1.0), ("mm/s", 0.001)],
            Quantity::Acceleration => &[("m/s^2", 1.0)],
            Quantity::Torque => &[("Nm", 1.0), ("N*m", 1.0)],
            Quantity::JointDamping => &[("Nm*s/rad", 1.0)],
            Quantity::TorqueRate => &[("Nm/s", 1.0), ("N*m/s", 1.0)],
            Quantity::Force => &[("N", 1.0)],
            Quantity::Time => &[("s", 1.0), ("ms", 0.001), ("us", 1e-6)],
            Quantity::PerSecondSquared => &[("1/s^2", 1.0)],
            Quantity::PerSecond => &[("1/s", 1.0)],
            Quantity::PerSecondCubed => &[("1/s^3", 1.0)],
            Quantity::Dimensionless => &[("1", 1.0)],
        }
    }

    fn describe(self) -> String {
        self.units().iter().map(|(u, _)| format!("\"{u}\"")).collect::<Vec<_>>().join(" or ")
    }
}

/// Which values a field accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sign {
    Any,
    NonNegative,
    Positive,
}

/// A parsed TOML file, read field by field; remembers which keys were used so that unknown
/// (misspelt) keys are reported by [`ConfigFile::finish`].
pub struct ConfigFile {
    path: PathBuf,
    root: toml::Table,
    used: BTreeSet<String>,
}

impl ConfigFile {
    pub fn open(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|e| ConfigError {
            file: path.to_path_buf(),
            field: "-".into(),
            message: format!("cannot read the file: {e}"),
        })?;
        Self::parse(path, &text)
    }

    pub fn parse(path: &Path, text: &str) -> Result<Self, ConfigError> {
        let root: toml::Table = text.parse().map_err(|e: toml::de::Error| {
            // Where: the line number and the line itself (it names the field).
            let at = e.span().map(|span| {
                let start = span.start.min(text.len());
                let line = text[..start].matches('\n').count() + 1;
                let content = text.lines().nth(line - 1).unwrap_or("").trim();
                format!(" at line {line} (`{content}`)")
            });
            ConfigError {
                file: path.to_path_buf(),
                field: "-".into(),
                message: format!("not valid TOML{}: {}", at.unwrap_or_default(), e.message()),
            }
        })?;
        Ok(Self { path: path.to_path_buf(), root, used: BTreeSet::new() })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn error(&self, field: &str, message: impl Into<String>) -> ConfigError {
        ConfigError { file: self.path.clone(), field: field.into(), message: message.into() }
    }

    fn lookup(&mut self, field: &str) -> Result<&toml::Value, ConfigError> {
        let mut parts = field.split('.');
        let first = parts.next().unwrap_or_default();
        let mut prefix = first.to_string();
        self.used.insert(prefix.clone());
        let mut value = self.root.get(first);
        for part in parts {
            prefix = format!("{prefix}.{part}");
            self.used.insert(prefix.clone());
            value = value.and_then(|v| v.as_table()).and_then(|t| t.get(part));
        }
        value.ok_or_else(|| ConfigError { file: self.path.clone(), field: field.into(), message: "missing".into() })
    }

    /// Whether a field is present (for optional sections).
    pub fn has(&self, field: &str) -> bool {
        let mut value: Option<&toml::Value> = None;
        for (i, part) in field.split('.').enumerate() {
            value =
                if i == 0 { self.root.get(part) } else { value.and_then(|v| v.as_table()).and_then(|t| t.get(part)) };
        }
        value.is_some()
    }

    /// `field = { values = [..N numbers..], unit = "..." }`, converted to SI.
    pub fn quantities<const N: usize>(
        &mut self,
        field: &str,
        kind: Quantity,
        sign: Sign,
    ) -> Result<[f64; N], ConfigError> {
        let (values, scale) = self.with_unit(field, "values", kind)?;
        let array =
            values.as_array().ok_or_else(|| self.error(field, format!("`values` must be an array of {N} numbers")))?;
        if array.len() != N {
            return Err(self.error(field, format!("expected {N} values, found {}", array.len())));
        }
        let mut out = [0.0; N];
        for (i, v) in array.iter().enumerate() {
            out[i] = self.number(field, v)? * scale;
            self.check_sign(field, out[i], sign)?;
        }
        Ok(out)
    }

    /// `field = { value = x, unit = "..." }`, converted to SI.
    pub fn quantity(&mut self, field: &str, kind: Quantity, sign: Sign) -> Result<f64, ConfigError> {
        let (value, scale) = self.with_unit(field, "value", kind)?;
        let x = self.number(field, &value)? * scale;
        self.check_sign(field, x, sign)?;
        Ok(x)
    }

    /// A plain dimensionless number.
    pub fn number_field(&mut self, field: &str, sign: Sign) -> Result<f64, ConfigError> {
        let value = self.lookup(field)?.clone();
        let x = self.number(field, &value)?;
        self.check_sign(field, x, sign)?;
        Ok(x)
    }

    /// A boolean (`true` / `false`).
    pub fn flag(&mut self, field: &str) -> Result<bool, ConfigError> {
        let value = self.lookup(field)?.clone();
        value.as_bool().ok_or_else(|| self.error(field, format!("expected true or false, found {value}")))
    }

    /// A plain array of N dimensionless numbers.
    pub fn numbers<const N: usize>(&mut self, field: &str, sign: Sign) -> Result<[f64; N], ConfigError> {
        let value = self.lookup(field)?.clone();
        let array = value.as_array().ok_or_else(|| self.error(field, format!("expected an array of {N} numbers")))?;
        if array.len() != N {
            return Err(self.error(field, format!("expected {N} values, found {}", array.len())));
        }
        let mut out = [0.0; N];
        for (i, v) in array.iter().enumerate() {
            out[i] = self.number(field, v)?;
            self.check_sign(field, out[i], sign)?;
        }
        Ok(out)
    }

    /// Reports keys of the file that no reader asked for (typos, fields of another version).
    pub fn finish(self) -> Result<(), ConfigError> {
        fn walk(table: &toml::Table, prefix: &str, out: &mut Vec<String>) {
            for (k, v) in table {
                let path = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                out.push(path.clone());
                if let Some(t) = v.as_table() {
                    // A quantity table's own keys are its value(s) and unit, not sections.
                    if !(t.contains_key("unit") || t.contains_key("value") || t.contains_key("values")) {
                        walk(t, &path, out);
                    }
                }
            }
        }
        let mut all = Vec::new();
        walk(&self.root, "", &mut all);
        match all.into_iter().find(|k| !self.used.contains(k)) {
            None => Ok(()),
            Some(k) => Err(self.error(&k, "unknown field (misspelt, or not used by this version of flowram)")),
        }
    }

    fn with_unit(&mut self, field: &str, key: &str, kind: Quantity) -> Result<(toml::Value, f64), ConfigError> {
        let table = self
            .lookup(field)?
            .as_table()
            .cloned()
            .ok_or_else(|| self.error(field, format!("expected {{ {key} = ..., unit = {} }}", kind.describe())))?;
        if let Some(extra) = table.keys().find(|k| *k != key && *k != "unit") {
            return Err(self.error(field, format!("unexpected key `{extra}` (expected `{key}` and `unit`)")));
        }
        let value = table.get(key).cloned().ok_or_else(|| self.error(field, format!("missing `{key}`")))?;
        let unit = match (table.get("unit"), kind) {
            (None, Quantity::Dimensionless) => "1".to_string(),
            (None, _) => return Err(self.error(field, format!("missing `unit` (expected {})", kind.describe()))),
            (Some(u), _) => u.as_str().ok_or_else(|| self.error(field, "`unit` must be a string"))?.trim().to_string(),
        };
        let scale = kind
            .units()
            .iter()
            .find(|(u, _)| *u == unit)
            .map(|(_, s)| *s)
            .ok_or_else(|| self.error(field, format!("wrong unit \"{unit}\": expected {}", kind.describe())))?;
        Ok((value, scale))
    }

    fn number(&self, field: &str, v: &toml::Value) -> Result<f64, ConfigError> {
        let x = match v {
            toml::Value::Float(f) => *f,
            toml::Value::Integer(i) => *i as f64,
            other => return Err(self.error(field, format!("expected a number, found {}", other.type_str()))),
        };
        if x.is_finite() { Ok(x) } else { Err(self.error(field, format!("{x} is not a finite number"))) }
    }

    fn check_sign(&self, field: &str, x: f64, sign: Sign) -> Result<(), ConfigError> {
        match sign {
            Sign::Any => Ok(()),
            Sign::NonNegative if x >= 0.0 => Ok(()),
            Sign::Positive if x > 0.0 => Ok(()),
            Sign::NonNegative => Err(self.error(field, format!("{x} is negative; it must be >= 0"))),
            Sign::Positive => Err(self.error(field, format!("{x} must be > 0"))),
        }
    }
}
