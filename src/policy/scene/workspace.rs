//! The workspace box and its normalisation: each axis of the box mapped to [-1, 1] (the units of
//! the token positions and of the DRS radii), and cropping clouds to the box.
use serde::{Deserialize, Serialize};

use crate::policy::error::{PolicyError, Result};

/// Raw form of [`WorkspaceBounds`] for deserialisation (validated on conversion).
#[derive(Deserialize)]
struct WorkspaceBoundsSpec {
    min: [f32; 3],
    max: [f32; 3],
}

/// The axis-aligned workspace box in the world frame (metres); points inside are mapped to
/// [-1, 1] per axis: `p_norm = 2 (p - min) / (max - min) - 1`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "WorkspaceBoundsSpec")]
pub struct WorkspaceBounds {
    min: [f32; 3],
    max: [f32; 3],
}

impl TryFrom<WorkspaceBoundsSpec> for WorkspaceBounds {
    type Error = PolicyError;
    fn try_from(spec: WorkspaceBoundsSpec) -> Result<Self> {
        Self::new(spec.min, spec.max)
    }
}

/// Workspace points of a lifted grid: normalised positions and which grid cell each came from
/// (to gather that cell's image features).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CroppedCloud {
    /// Positions in normalised workspace coordinates, each in [-1, 1]^3.
    pub points_norm: Vec<[f32; 3]>,
    /// `cells[k]` is the index into the lifted grid of `points_norm[k]` (increasing).
    pub cells: Vec<usize>,
}

impl WorkspaceBounds {
    /// Errors: [`PolicyError::Invalid`] unless every bound is finite and `min < max` per axis.
    pub fn new(min: [f32; 3], max: [f32; 3]) -> Result<Self> {
        for axis in 0..3 {
            if !(min[axis].is_finite() && max[axis].is_finite() && min[axis] < max[axis]) {
                return Err(PolicyError::Invalid(format!(
                    "workspace bounds need finite min < max on every axis; axis {axis} has min {} max {}",
                    min[axis], max[axis]
                )));
            }
        }
        Ok(Self { min, max })
    }

    pub fn min(&self) -> [f32; 3] {
        self.min
    }

    pub fn max(&self) -> [f32; 3] {
        self.max
    }

    /// Whether `p` (metres) lies in the box (bounds included).
    pub fn contains(&self, p: [f32; 3]) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }

    /// Metres -> normalised coordinates (not clamped: points outside map outside [-1, 1]).
    pub fn normalize(&self, p: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|i| 2.0 * (p[i] - self.min[i]) / (self.max[i] - self.min[i]) - 1.0)
    }

    /// Normalised coordinates -> metres (inverse of [`Self::normalize`]).
    pub fn denormalize(&self, q: [f32; 3]) -> [f32; 3] {
        std::array::from_fn(|i| self.min[i] + 0.5 * (q[i] + 1.0) * (self.max[i] - self.min[i]))
    }

    /// Keeps the valid cells inside the box and normalises them.
    pub fn crop_and_normalize(&self, cells: &[Option<[f32; 3]>]) -> CroppedCloud {
        let mut cloud = CroppedCloud::default();
        for (index, cell) in cells.iter().enumerate() {
            if let Some(p) = cell
                && self.contains(*p)
            {
                cloud.points_norm.push(self.normalize(*p).map(|v| v.clamp(-1.0, 1.0)));
                cloud.cells.push(index);
            }
        }
        cloud
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn assert_close<const N: usize>(a: [f32; N], b: [f32; N], tol: f32, what: &str) {
        for i in 0..N {
            assert!((a[i] - b[i]).abs() <= tol, "{what}: {a:?} vs {b:?}");
        }
    }

    #[test]
    fn workspace_normalisation_and_crop() {
        let ws = WorkspaceBounds::new([-0.25, -0.65, 0.74], [0.9, 0.65, 1.4]).unwrap();
        assert_close(ws.normalize([-0.25, -0.65, 0.74]), [-1.0; 3], 1e-6, "min corner");
        assert_close(ws.normalize([0.9, 0.65, 1.4]), [1.0; 3], 1e-6, "max corner");
        let p = [0.3, 0.1, 0.9];
        assert_close(ws.denormalize(ws.normalize(p)), p, 1e-6, "round trip");
        let cells = vec![Some([0.0, 0.0, 1.0]), None, Some([0.0, 0.0, 0.5]), Some([0.9, 0.65, 1.4])];
        let cloud = ws.crop_and_normalize(&cells);
        assert_eq!(cloud.cells, vec![0, 3]);
        assert!(cloud.points_norm.iter().flatten().all(|v| (-1.0..=1.0).contains(v)));
        assert!(WorkspaceBounds::new([0.0; 3], [1.0, 0.0, 1.0]).is_err());
        assert!(WorkspaceBounds::new([f32::NAN, 0.0, 0.0], [1.0; 3]).is_err());
        let json = serde_json::to_string(&ws).unwrap();
        assert_eq!(serde_json::from_str::<WorkspaceBounds>(&json).unwrap(), ws);
        assert!(serde_json::from_str::<WorkspaceBounds>(r#"{"min":[1,0,0],"max":[0,1,1]}"#).is_err());
    }
}
