//! The geometry of the FlowRAM policy: rotation representations of the action, lifting depth
//! pixels to world points, the workspace normalisation, exact farthest point sampling, the
//! Dynamic Radius Schedule (DRS) that picks the geometric tokens around the current noisy action
//! position, and the 3D sinusoidal positional encoding of token positions.
//!
//! Conventions:
//! - Rotation matrices are `[[f32; 3]; 3]` indexed `m[row][col]`, mapping body to world
//!   (columns are the body axes in the world frame). Quaternions are `[w, x, y, z]`, unit,
//!   canonical with `w >= 0`.
//! - The 6D rotation (Zhou et al., CVPR 2019) is the first two columns of the matrix,
//!   `[m00, m10, m20, m01, m11, m21]`, as in 3D Diffuser Actor.
//! - Cameras: OpenCV axes (x right, y down, z forward), z-depth in metres, intrinsics
//!   `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]` in pixels with pixel centres at integer
//!   coordinates (pixel `(u, v)` = column u, row v is centred at `(u, v)`), as `sim::camera`.
//! - Normalised workspace coordinates: each axis of the workspace box mapped to [-1, 1]. Radii of
//!   the DRS are in these units.
use std::f32::consts::PI;

use candle_core::{D, DType, Tensor};
use serde::{Deserialize, Serialize};

use crate::policy::error::{PolicyError, Result};

// ---------------------------------------------------------------------------------------------
// Rotations
// ---------------------------------------------------------------------------------------------

/// A rotation matrix, `m[row][col]`.
pub type RotationMatrix = [[f32; 3]; 3];

/// Rotation matrix of the quaternion `q = [w, x, y, z]` (normalised first, so any non-zero
/// scaling of a unit quaternion gives the same rotation).
///
/// Errors: [`PolicyError::Invalid`] when `q` has a non-finite entry or (nearly) zero norm.
pub fn matrix_from_quaternion(q: [f32; 4]) -> Result<RotationMatrix> {
    let q64 = q.map(f64::from);
    let norm = q64.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !norm.is_finite() || norm < 1e-12 {
        return Err(PolicyError::Invalid(format!(
            "quaternion [w, x, y, z] = {q:?} has norm {norm}: expected a finite, non-zero quaternion"
        )));
    }
    let [w, x, y, z] = q64.map(|v| v / norm);
    let m = [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ];
    Ok(m.map(|row| row.map(|v| v as f32)))
}

/// Canonical unit quaternion `[w, x, y, z]` (`w >= 0`; when `w == 0`, the first non-zero of
/// x, y, z is positive) of a rotation matrix (Shepperd's method). `m` should be a rotation; pass
/// anything else through [`rotation_from_6d`] first. Never returns NaN for finite input.
pub fn quaternion_from_matrix(m: &RotationMatrix) -> [f32; 4] {
    let m = m.map(|row| row.map(f64::from));
    let trace = m[0][0] + m[1][1] + m[2][2];
    let q = if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0; // 4w
        [0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).max(1e-300).sqrt() * 2.0; // 4x
        [(m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).max(1e-300).sqrt() * 2.0; // 4y
        [(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).max(1e-300).sqrt() * 2.0; // 4z
        [(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s]
    };
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !norm.is_finite() || norm == 0.0 {
        return [1.0, 0.0, 0.0, 0.0];
    }
    let mut q = q.map(|v| v / norm);
    let first_nonzero = q.iter().copied().find(|v| *v != 0.0).unwrap_or(1.0);
    if first_nonzero < 0.0 {
        q = q.map(|v| -v);
    }
    q.map(|v| v as f32)
}

/// The 6D representation: first column then second column of `m`,
/// `[m00, m10, m20, m01, m11, m21]`.
pub fn rotation_to_6d(m: &RotationMatrix) -> [f32; 6] {
    [m[0][0], m[1][0], m[2][0], m[0][1], m[1][1], m[2][1]]
}

/// A proper rotation from any 6D vector by Gram-Schmidt (Zhou et al.): `b1 = a1 / |a1|`,
/// `b2 = normalise(a2 - (b1 . a2) b1)`, `b3 = b1 x b2`, columns `[b1 b2 b3]`. Computed in f64.
///
/// Never returns NaN; always orthonormal with det = +1. Deterministic fallbacks for degenerate
/// input (non-finite entries are first replaced by 0):
/// - `|a1| <= 1e-12`: `b1 = e_x`;
/// - `a2` (nearly) parallel to `b1` or zero (`|a2 - (b1 . a2) b1| <= 1e-6 |a2|` or `<= 1e-12`):
///   `b2` is Gram-Schmidt of the world axis `e_k` least aligned with `b1` (smallest `|b1_k|`,
///   lowest k on ties).
///
/// So all zeros give the identity, and `[1, 0, 0, 1, 0, 0]` gives the identity too.
pub fn rotation_from_6d(r: [f32; 6]) -> RotationMatrix {
    let clean = r.map(|v| if v.is_finite() { f64::from(v) } else { 0.0 });
    let a1 = [clean[0], clean[1], clean[2]];
    let a2 = [clean[3], clean[4], clean[5]];
    // f32 inputs cannot overflow or underflow squared in f64, so no rescaling is needed.
    let b1 = normalised(a1).unwrap_or([1.0, 0.0, 0.0]);
    let b2 = {
        let residual = sub64(a2, scale64(b1, dot64(b1, a2)));
        match normalised(residual) {
            Some(b2) if norm64(residual) > 1e-6 * norm64(a2) => b2,
            _ => {
                let k = (0..3).min_by(|&i, &j| b1[i].abs().total_cmp(&b1[j].abs())).unwrap_or(0);
                let mut axis = [0.0; 3];
                axis[k] = 1.0;
                // |b1_k| <= 1/sqrt(3), so this residual has norm >= sqrt(2/3).
                normalised(sub64(axis, scale64(b1, b1[k]))).unwrap_or([0.0, 1.0, 0.0])
            }
        }
    };
    let b3 = normalised(cross64(b1, b2)).unwrap_or([0.0, 0.0, 1.0]);
    let m = [[b1[0], b2[0], b3[0]], [b1[1], b2[1], b3[1]], [b1[2], b2[2], b3[2]]];
    m.map(|row| row.map(|v| v as f32))
}

/// `rotation_to_6d(matrix_from_quaternion(q))`.
pub fn quaternion_to_6d(q: [f32; 4]) -> Result<[f32; 6]> {
    Ok(rotation_to_6d(&matrix_from_quaternion(q)?))
}

/// `quaternion_from_matrix(rotation_from_6d(r))`: canonical quaternion of any 6D vector.
pub fn quaternion_from_6d(r: [f32; 6]) -> [f32; 4] {
    quaternion_from_matrix(&rotation_from_6d(r))
}

fn dot64(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn sub64(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale64(a: [f64; 3], s: f64) -> [f64; 3] {
    a.map(|v| v * s)
}
fn cross64(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn norm64(a: [f64; 3]) -> f64 {
    dot64(a, a).sqrt()
}
/// `a / |a|`, or None when `|a| <= 1e-12`.
fn normalised(a: [f64; 3]) -> Option<[f64; 3]> {
    let n = norm64(a);
    if n > 1e-12 && n.is_finite() { Some(a.map(|v| v / n)) } else { None }
}

// ---------------------------------------------------------------------------------------------
// Lifting depth to world points, workspace normalisation
// ---------------------------------------------------------------------------------------------

/// World xyz (metres) of the feature-grid cells of one depth image.
///
/// - `depth`: `height * width` z-depths in metres, row-major, row 0 at the top; values `<= 0` or
///   non-finite mean "no surface" (MuJoCo renders 0 beyond the far plane).
/// - `intrinsics`: `K` (pixels, pixel centres at integer coordinates), `camera_to_world`: the
///   4x4 pose of the OpenCV camera frame in the world (`[row][col]`, last row `[0, 0, 0, 1]`).
/// - `stride`: the feature grid has `(height / stride) x (width / stride)` cells, each covering a
///   `stride x stride` block of pixels. Cell `(r, c)` is represented by the pixel nearest its
///   centre, `(u, v) = (stride * c + stride / 2, stride * r + stride / 2)` (integer division: the
///   exact centre for odd strides, the lower-right of the four central pixels for even ones), and
///   its point is that pixel's back-projection `R (z (u - cx) / fx, z (v - cy) / fy, z) + t`, a
///   true surface point (no depth interpolation across edges).
///
/// Returns the row-major cells, `None` where the depth is invalid.
///
/// Errors: [`PolicyError::Invalid`] when `depth.len() != height * width`, `stride` is 0 or does
/// not divide both sizes, or `fx`, `fy` are not positive and finite.
pub fn lift_depth(
    depth: &[f32],
    height: usize,
    width: usize,
    intrinsics: &[[f32; 3]; 3],
    camera_to_world: &[[f32; 4]; 4],
    stride: usize,
) -> Result<Vec<Option<[f32; 3]>>> {
    if depth.len() != height * width {
        return Err(PolicyError::Invalid(format!(
            "depth image has {} values, expected height * width = {height} * {width}",
            depth.len()
        )));
    }
    if stride == 0 || !height.is_multiple_of(stride) || !width.is_multiple_of(stride) {
        return Err(PolicyError::Invalid(format!(
            "feature stride {stride} must be positive and divide the image size {height}x{width}"
        )));
    }
    let (fx, fy, cx, cy) = (intrinsics[0][0], intrinsics[1][1], intrinsics[0][2], intrinsics[1][2]);
    if !(fx > 0.0 && fy > 0.0 && fx.is_finite() && fy.is_finite() && cx.is_finite() && cy.is_finite()) {
        return Err(PolicyError::Invalid(format!(
            "intrinsics need finite fx, fy > 0 and finite cx, cy; got fx {fx}, fy {fy}, cx {cx}, cy {cy}"
        )));
    }
    let pose = camera_to_world;
    let (rows, cols) = (height / stride, width / stride);
    let mut cells = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        let v = stride * r + stride / 2;
        for c in 0..cols {
            let u = stride * c + stride / 2;
            let z = depth[v * width + u];
            if !(z > 0.0 && z.is_finite()) {
                cells.push(None);
                continue;
            }
            let cam = [(u as f32 - cx) * z / fx, (v as f32 - cy) * z / fy, z];
            let world: [f32; 3] =
                std::array::from_fn(|i| pose[i][0] * cam[0] + pose[i][1] * cam[1] + pose[i][2] * cam[2] + pose[i][3]);
            cells.push(Some(world));
        }
    }
    Ok(cells)
}

/// Pixel coordinates `(u, v)` (integer = pixel centre, see [`lift_depth`]) and z-depth of a
/// world point, or None when it is not in front of the camera. The inverse of the
/// back-projection in [`lift_depth`].
pub fn project_to_pixel(
    point: [f32; 3],
    intrinsics: &[[f32; 3]; 3],
    camera_to_world: &[[f32; 4]; 4],
) -> Option<([f32; 2], f32)> {
    let pose = camera_to_world;
    let d = [point[0] - pose[0][3], point[1] - pose[1][3], point[2] - pose[2][3]];
    // R^T d: camera coordinates.
    let cam: [f32; 3] = std::array::from_fn(|j| pose[0][j] * d[0] + pose[1][j] * d[1] + pose[2][j] * d[2]);
    if cam[2].is_nan() || cam[2] <= 0.0 {
        return None;
    }
    let u = intrinsics[0][0] * cam[0] / cam[2] + intrinsics[0][2];
    let v = intrinsics[1][1] * cam[1] / cam[2] + intrinsics[1][2];
    Some(([u, v], cam[2]))
}

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

// ---------------------------------------------------------------------------------------------
// Farthest point sampling
// ---------------------------------------------------------------------------------------------

/// SIMD width the leaf kernel is written for (16 f32 = one AVX-512 register, two AVX2).
const LANES: usize = 16;
/// Points per kd-tree leaf (about; leaves are padded to a multiple of [`LANES`]).
const LEAF_POINTS: usize = 64;
/// Subtrees at least this large are built in parallel (rayon::join on the two halves).
const PARALLEL_BUILD_MIN_POINTS: usize = 1 << 15;

/// Exact farthest point sampling: starting from `points[first]`, repeatedly picks the point whose
/// squared distance to the nearest already-picked point is largest (ties: the lowest index).
/// Returns `n` indices in pick order, `first` first. When `n >= points.len()`, returns all
/// indices `0..points.len()` in index order (no sampling needed); an empty cloud gives an empty
/// list.
///
/// The result is identical to the textbook O(N n) loop (same f32 arithmetic, same tie rule);
/// it is computed on a kd-tree of leaves (structure of arrays, a vectorised 16-lane kernel) where
/// a whole subtree is skipped when the new pick is no closer to its bounding box than its
/// current largest distance. The tree build (median splits over contiguous point records) is
/// rayon-parallel for subtrees of 2^15 points and more; the pick loop is serial (see the
/// module's benchmark: per-pick synchronisation of threads costs more than it saves). Several
/// clouds (a batch) are best sampled in parallel by the caller.
///
/// Errors: [`PolicyError::Invalid`] when `first >= points.len()` (non-empty cloud) or a
/// coordinate is not finite.
pub fn farthest_point_sample(points: &[[f32; 3]], n: usize, first: usize) -> Result<Vec<usize>> {
    if points.is_empty() || n == 0 {
        return Ok(Vec::new());
    }
    if first >= points.len() {
        return Err(PolicyError::Invalid(format!(
            "farthest point sampling starts at index {first}, but the cloud has {} points",
            points.len()
        )));
    }
    if let Some(bad) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(PolicyError::Invalid(format!(
            "point {bad} of the cloud is {:?}: farthest point sampling needs finite coordinates",
            points[bad]
        )));
    }
    if n >= points.len() {
        return Ok((0..points.len()).collect());
    }
    Ok(fps_dispatch(points, n, first))
}

fn fps_dispatch(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports AVX-512F (checked just above).
            return unsafe { fps_avx512(points, n, first) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            return unsafe { fps_avx2(points, n, first) };
        }
    }
    fps_generic(points, n, first)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn fps_avx512(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
    fps_generic(points, n, first)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn fps_avx2(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
    fps_generic(points, n, first)
}

/// The pick loop; compiled once per instruction set by the wrappers above.
#[inline(always)]
fn fps_generic(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
    let mut tree = FpsTree::build(points);
    let mut picks = Vec::with_capacity(n);
    picks.push(first);
    let mut last = points[first];
    for _ in 1..n {
        tree.update(1, last);
        let pick = tree.lowest_id_at(1, tree.node_max[1]) as usize;
        picks.push(pick);
        last = points[pick];
    }
    picks
}

/// One point of the cloud with its index, moved around while the tree is built.
#[derive(Clone, Copy)]
struct PointRecord {
    p: [f32; 3],
    id: u32,
}

fn bounding_box(records: &[PointRecord]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for r in records {
        for a in 0..3 {
            lo[a] = lo[a].min(r.p[a]);
            hi[a] = hi[a].max(r.p[a]);
        }
    }
    (lo, hi)
}

/// Orders `records` into `2^depth` spatially compact leaves: split at the middle position
/// (`len / 2`) along the widest axis of the bounding box, recursively. The leaf boundaries
/// depend only on the length, see [`leaf_bounds`].
fn kd_partition(records: &mut [PointRecord], depth: usize) {
    if depth == 0 || records.len() < 2 {
        return;
    }
    let (lo, hi) = bounding_box(records);
    let axis = (0..3).max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b]))).unwrap_or(0);
    let mid = records.len() / 2;
    records.select_nth_unstable_by(mid, |a, b| a.p[axis].total_cmp(&b.p[axis]).then(a.id.cmp(&b.id)));
    let (left, right) = records.split_at_mut(mid);
    if left.len() + right.len() >= PARALLEL_BUILD_MIN_POINTS {
        rayon::join(|| kd_partition(left, depth - 1), || kd_partition(right, depth - 1));
    } else {
        kd_partition(left, depth - 1);
        kd_partition(right, depth - 1);
    }
}

/// Start positions of the `2^depth` leaves of [`kd_partition`] over `len` records, plus `len`.
fn leaf_bounds(len: usize, depth: usize) -> Vec<usize> {
    let mut bounds = vec![0, len];
    for _ in 0..depth {
        let mut next = Vec::with_capacity(bounds.len() * 2);
        for w in bounds.windows(2) {
            next.extend([w[0], w[0] + (w[1] - w[0]) / 2]);
        }
        next.push(len);
        bounds = next;
    }
    bounds
}

/// A complete binary kd-tree (heap layout: node 1 is the root, node k has children 2k, 2k+1,
/// leaves are nodes `first_leaf..2 * first_leaf`). Points are stored leaf by leaf as structure
/// of arrays, each leaf padded to a multiple of [`LANES`] with copies of its first point whose
/// distance is -inf (never picked, never changed).
struct FpsTree {
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    /// Squared distance of each point to its nearest pick so far (+inf before the first).
    dist: Vec<f32>,
    ids: Vec<u32>,
    /// `leaf_range[l] .. leaf_range[l + 1]` are leaf l's (padded) slots.
    leaf_range: Vec<usize>,
    first_leaf: usize,
    node_lo: Vec<[f32; 3]>,
    node_hi: Vec<[f32; 3]>,
    /// Largest `dist` in each node's subtree.
    node_max: Vec<f32>,
}

impl FpsTree {
    fn build(points: &[[f32; 3]]) -> Self {
        let mut depth = 0;
        while points.len() > LEAF_POINTS << depth {
            depth += 1;
        }
        let first_leaf = 1usize << depth;
        let mut records: Vec<PointRecord> =
            points.iter().enumerate().map(|(i, &p)| PointRecord { p, id: i as u32 }).collect();
        kd_partition(&mut records, depth);
        let bounds = leaf_bounds(records.len(), depth);
        let padded_len: usize = bounds.windows(2).map(|w| (w[1] - w[0]).div_ceil(LANES) * LANES).sum();
        let mut tree = Self {
            xs: Vec::with_capacity(padded_len),
            ys: Vec::with_capacity(padded_len),
            zs: Vec::with_capacity(padded_len),
            dist: Vec::with_capacity(padded_len),
            ids: Vec::with_capacity(padded_len),
            leaf_range: Vec::with_capacity(first_leaf + 1),
            first_leaf,
            node_lo: vec![[f32::INFINITY; 3]; 2 * first_leaf],
            node_hi: vec![[f32::NEG_INFINITY; 3]; 2 * first_leaf],
            node_max: vec![f32::INFINITY; 2 * first_leaf],
        };
        for (leaf, w) in bounds.windows(2).enumerate() {
            tree.leaf_range.push(tree.xs.len());
            let leaf_records = &records[w[0]..w[1]];
            let padded = leaf_records.len().div_ceil(LANES) * LANES;
            for k in 0..padded {
                let real = leaf_records.get(k);
                let r = real.or(leaf_records.first()).copied().unwrap_or(PointRecord { p: [0.0; 3], id: u32::MAX });
                tree.xs.push(r.p[0]);
                tree.ys.push(r.p[1]);
                tree.zs.push(r.p[2]);
                tree.dist.push(if real.is_some() { f32::INFINITY } else { f32::NEG_INFINITY });
                tree.ids.push(if real.is_some() { r.id } else { u32::MAX });
            }
            let (lo, hi) = bounding_box(leaf_records);
            tree.node_lo[first_leaf + leaf] = lo;
            tree.node_hi[first_leaf + leaf] = hi;
            if leaf_records.is_empty() {
                tree.node_max[first_leaf + leaf] = f32::NEG_INFINITY;
            }
        }
        tree.leaf_range.push(tree.xs.len());
        for node in (1..first_leaf).rev() {
            for a in 0..3 {
                tree.node_lo[node][a] = tree.node_lo[2 * node][a].min(tree.node_lo[2 * node + 1][a]);
                tree.node_hi[node][a] = tree.node_hi[2 * node][a].max(tree.node_hi[2 * node + 1][a]);
            }
            tree.node_max[node] = tree.node_max[2 * node].max(tree.node_max[2 * node + 1]);
        }
        tree
    }

    /// Folds the pick `p` into the distances of `node`'s subtree.
    ///
    /// Skip rule: the subtree is untouched when its largest distance is <= the squared distance
    /// from `p` to its bounding box. Exact (not approximate): rounding is monotone, so every
    /// point's computed squared distance to `p` is >= the box's, computed the same way.
    #[inline(always)]
    fn update(&mut self, node: usize, p: [f32; 3]) {
        if self.node_max[node] <= box_distance2(p, self.node_lo[node], self.node_hi[node]) {
            return;
        }
        if node >= self.first_leaf {
            let leaf = node - self.first_leaf;
            let range = self.leaf_range[leaf]..self.leaf_range[leaf + 1];
            self.node_max[node] = update_leaf(
                &self.xs[range.clone()],
                &self.ys[range.clone()],
                &self.zs[range.clone()],
                &mut self.dist[range],
                p,
            );
        } else {
            self.update(2 * node, p);
            self.update(2 * node + 1, p);
            self.node_max[node] = self.node_max[2 * node].max(self.node_max[2 * node + 1]);
        }
    }

    /// Lowest point id in `node`'s subtree whose distance equals `best` (u32::MAX if none).
    fn lowest_id_at(&self, node: usize, best: f32) -> u32 {
        if self.node_max[node] != best {
            return u32::MAX;
        }
        if node >= self.first_leaf {
            let leaf = node - self.first_leaf;
            let range = self.leaf_range[leaf]..self.leaf_range[leaf + 1];
            return self.dist[range.clone()]
                .iter()
                .zip(&self.ids[range])
                .filter(|(d, _)| **d == best)
                .map(|(_, id)| *id)
                .min()
                .unwrap_or(u32::MAX);
        }
        self.lowest_id_at(2 * node, best).min(self.lowest_id_at(2 * node + 1, best))
    }
}

/// Squared distance from `p` to the box `[lo, hi]` (0 inside), computed like the point
/// distances in [`update_leaf`].
#[inline(always)]
fn box_distance2(p: [f32; 3], lo: [f32; 3], hi: [f32; 3]) -> f32 {
    let gap = |a: usize| {
        if p[a] < lo[a] {
            lo[a] - p[a]
        } else if p[a] > hi[a] {
            p[a] - hi[a]
        } else {
            0.0
        }
    };
    let (gx, gy, gz) = (gap(0), gap(1), gap(2));
    gx * gx + gy * gy + gz * gz
}

/// `dist[i] = min(dist[i], |x_i - p|^2)` over one leaf (length a multiple of [`LANES`]);
/// returns the new largest `dist`. Written lane-wise so it compiles to vector min/max.
#[inline(always)]
fn update_leaf(xs: &[f32], ys: &[f32], zs: &[f32], dist: &mut [f32], p: [f32; 3]) -> f32 {
    let mut lane_max = [f32::NEG_INFINITY; LANES];
    for (((x, y), z), d) in
        xs.chunks_exact(LANES).zip(ys.chunks_exact(LANES)).zip(zs.chunks_exact(LANES)).zip(dist.chunks_exact_mut(LANES))
    {
        for l in 0..LANES {
            let dx = x[l] - p[0];
            let dy = y[l] - p[1];
            let dz = z[l] - p[2];
            let candidate = dx * dx + dy * dy + dz * dz;
            let nearest = if candidate < d[l] { candidate } else { d[l] };
            d[l] = nearest;
            lane_max[l] = if nearest > lane_max[l] { nearest } else { lane_max[l] };
        }
    }
    lane_max.iter().fold(f32::NEG_INFINITY, |m, &v| if v > m { v } else { m })
}

// ---------------------------------------------------------------------------------------------
// Dynamic Radius Schedule and geometric tokens
// ---------------------------------------------------------------------------------------------

/// Distance between opposite corners of the normalised workspace [-1, 1]^3: a ball of this
/// radius around any point of the box covers the whole box.
pub const GLOBAL_RADIUS: f32 = 3.464_101_6; // 2 * sqrt(3)

/// A suggested `min_inside` for [`select_geometric_tokens`]: with fewer points near the action
/// the local region says little, and global sampling is used instead.
pub const DEFAULT_MIN_INSIDE: usize = 64;

/// Raw form of [`RadiusSchedule`] for deserialisation (validated on conversion).
#[derive(Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
enum RadiusScheduleSpec {
    Dynamic { r_min: f32, r_max: f32, power: f32 },
    Global,
}

/// The Dynamic Radius Schedule: radius `r(t)` (normalised workspace units) of the region around
/// the current noisy action position from which geometric tokens are sampled, for flow time `t`
/// (0 = noise, 1 = data).
///
/// JSON: `{"kind": "dynamic", "r_min": 0.4, "r_max": 3.4641016, "power": 1.0}` or
/// `{"kind": "global"}`; deserialisation validates like [`RadiusSchedule::dynamic`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RadiusScheduleSpec", tag = "kind", rename_all = "snake_case")]
pub enum RadiusSchedule {
    /// `r(t) = r_min + (r_max - r_min) (1 - t)^power`: `r_max` (global, >= 2 sqrt(3)) at t = 0,
    /// shrinking monotonically to `r_min` at t = 1.
    Dynamic { r_min: f32, r_max: f32, power: f32 },
    /// The "w/o DRS" ablation: global sampling at every step.
    Global,
}

impl TryFrom<RadiusScheduleSpec> for RadiusSchedule {
    type Error = PolicyError;
    fn try_from(spec: RadiusScheduleSpec) -> Result<Self> {
        match spec {
            RadiusScheduleSpec::Dynamic { r_min, r_max, power } => Self::dynamic(r_min, r_max, power),
            RadiusScheduleSpec::Global => Ok(Self::Global),
        }
    }
}

impl Default for RadiusSchedule {
    /// `r_min = 0.4, r_max = 2 sqrt(3), power = 1` (see [`RadiusSchedule::DEFAULT_R_MIN`],
    /// [`RadiusSchedule::DEFAULT_POWER`]).
    fn default() -> Self {
        Self::Dynamic { r_min: Self::DEFAULT_R_MIN, r_max: GLOBAL_RADIUS, power: Self::DEFAULT_POWER }
    }
}

impl RadiusSchedule {
    /// Radius at t = 1 (normalised units). On flowram's table workspace (1.15 x 1.3 x 0.66 m)
    /// that is about 23 x 26 x 13 cm: the gripper and what it is about to touch. The code
    /// release uses a fixed 1.2 once out of the noisiest 10 % of the flow; 0.4 is reached only
    /// at the end, when the action estimate is precise.
    pub const DEFAULT_R_MIN: f32 = 0.4;
    /// Linear shrinking: the noisy position is `a_t = t a1 + (1 - t) a0`, so its distance to the
    /// target position is `(1 - t) |a1 - a0|`, linear in t (clamping the centre to the box only
    /// brings it closer). With power 1 the region contains the target at every t whenever
    /// `|a1 - a0| <= r_max - r_min` (3.06 with the defaults): about 97 % of the 3D Gaussian
    /// noise draws for a target at the workspace centre, about 80 % at a corner.
    pub const DEFAULT_POWER: f32 = 1.0;

    /// A validated dynamic schedule. Errors: [`PolicyError::Invalid`] unless all values are
    /// finite, `0 < r_min <= r_max`, `r_max >= 2 sqrt(3)` (global at t = 0) and `power > 0`.
    pub fn dynamic(r_min: f32, r_max: f32, power: f32) -> Result<Self> {
        if !(r_min.is_finite() && r_max.is_finite() && power.is_finite()) {
            return Err(PolicyError::Invalid(format!(
                "radius schedule needs finite values; got r_min {r_min}, r_max {r_max}, power {power}"
            )));
        }
        if !(r_min > 0.0 && r_min <= r_max) {
            return Err(PolicyError::Invalid(format!(
                "radius schedule needs 0 < r_min <= r_max (normalised workspace units); got r_min {r_min}, r_max {r_max}"
            )));
        }
        if r_max < GLOBAL_RADIUS {
            return Err(PolicyError::Invalid(format!(
                "radius schedule r_max {r_max} must be >= 2 sqrt(3) = {GLOBAL_RADIUS} so that sampling is global at t = 0"
            )));
        }
        if power <= 0.0 {
            return Err(PolicyError::Invalid(format!("radius schedule power must be > 0; got {power}")));
        }
        Ok(Self::Dynamic { r_min, r_max, power })
    }

    /// Checks a schedule built by hand (the enum fields are public).
    pub fn validate(&self) -> Result<()> {
        match *self {
            Self::Dynamic { r_min, r_max, power } => Self::dynamic(r_min, r_max, power).map(|_| ()),
            Self::Global => Ok(()),
        }
    }

    /// `r(t)` in normalised workspace units, `t` clamped to [0, 1]; infinite for `Global`.
    /// Continuous and non-increasing in t.
    pub fn radius(&self, t: f32) -> f32 {
        match *self {
            Self::Dynamic { r_min, r_max, power } => {
                let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
                r_min + (r_max - r_min) * (1.0 - t).powf(power)
            }
            Self::Global => f32::INFINITY,
        }
    }
}

/// Which points become geometric tokens at one flow step.
#[derive(Debug, Clone, PartialEq)]
pub struct GeometricSelection {
    /// Exactly `n2` indices into the cloud (fewer only when the cloud itself is smaller; see
    /// [`select_geometric_tokens`]).
    pub indices: Vec<usize>,
    /// The radius `r(t)` used (normalised units; infinite for the global schedule).
    pub radius: f32,
    /// True when fewer than `min_inside` points lay within the radius and global sampling was
    /// used instead.
    pub fell_back: bool,
}

/// Picks `n2` geometric tokens from `points_norm` (normalised workspace coordinates, [-1, 1]^3)
/// around `center` (the current noisy action position, normalised) at flow time `t` in [0, 1]:
///
/// 1. `center` is clamped to [-1, 1]^3 (early in the flow the noisy position can lie outside
///    the workspace; the gripper's target cannot), and `r = schedule.radius(t)`.
/// 2. If `r >= 2 sqrt(3)` (always at t = 0, and always for [`RadiusSchedule::Global`]), every
///    point is a candidate: global sampling.
/// 3. Otherwise the candidates are the points with `|p - center| <= r`, in index order.
///    - at least `n2` of them: farthest point sampling over them to `n2`, starting from the
///      lowest index;
///    - between `min_inside` and `n2 - 1`: all of them, repeated cyclically to `n2`
///      (`c0 c1 .. ck c0 c1 ..`), so that the token count is fixed;
///    - fewer than `min_inside`: global sampling, `fell_back = true`.
/// 4. Global sampling is farthest point sampling from index 0 over the whole cloud (so at t = 0
///    the selection equals `farthest_point_sample(points_norm, n2, 0)`), or every index repeated
///    cyclically when the cloud has fewer than `n2` points.
///
/// Deterministic. Errors: [`PolicyError::Invalid`] for an empty cloud, `n2 == 0`,
/// `min_inside == 0`, a non-finite `center` or `t` outside [0, 1], non-finite points, or an
/// invalid schedule.
pub fn select_geometric_tokens(
    points_norm: &[[f32; 3]],
    center: [f32; 3],
    t: f32,
    n2: usize,
    min_inside: usize,
    schedule: &RadiusSchedule,
) -> Result<GeometricSelection> {
    select_geometric_tokens_cached(points_norm, None, center, t, n2, min_inside, schedule)
}

/// [`select_geometric_tokens`] with the global selection of these points computed once
/// ([`global_geometric_tokens`] with the same `n2`; inference reuses it at every step that
/// samples globally: t = 0, the w/o-DRS ablation, the fallback, and radii that hold every point).
/// The result is identical to [`select_geometric_tokens`]'s. A `global` of another length than
/// `n2` is ignored.
pub fn select_geometric_tokens_cached(
    points_norm: &[[f32; 3]],
    global: Option<&[usize]>,
    center: [f32; 3],
    t: f32,
    n2: usize,
    min_inside: usize,
    schedule: &RadiusSchedule,
) -> Result<GeometricSelection> {
    let global_indices = || match global {
        Some(g) if g.len() == n2 => Ok(g.to_vec()),
        _ => global_geometric_tokens(points_norm, n2),
    };
    if points_norm.is_empty() {
        return Err(PolicyError::Invalid("geometric tokens need a non-empty point cloud".into()));
    }
    if n2 == 0 || min_inside == 0 {
        return Err(PolicyError::Invalid(format!(
            "geometric token count n2 ({n2}) and min_inside ({min_inside}) must be positive"
        )));
    }
    if !center.iter().all(|v| v.is_finite()) {
        return Err(PolicyError::Invalid(format!("action position {center:?} is not finite")));
    }
    if !(0.0..=1.0).contains(&t) {
        return Err(PolicyError::Invalid(format!("flow time t = {t} must lie in [0, 1]")));
    }
    schedule.validate()?;
    let radius = schedule.radius(t);
    if radius >= GLOBAL_RADIUS {
        return Ok(GeometricSelection { indices: global_indices()?, radius, fell_back: false });
    }

    let center = center.map(|v| v.clamp(-1.0, 1.0));
    let radius2 = radius * radius;
    let inside: Vec<usize> = (0..points_norm.len())
        .filter(|&i| {
            let p = points_norm[i];
            let d = [p[0] - center[0], p[1] - center[1], p[2] - center[2]];
            d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= radius2
        })
        .collect();

    if inside.len() < min_inside {
        return Ok(GeometricSelection { indices: global_indices()?, radius, fell_back: true });
    }
    let indices = if inside.len() == points_norm.len() {
        // every point inside: FPS over the same candidates from the same start
        global_indices()?
    } else if inside.len() >= n2 {
        let local: Vec<[f32; 3]> = inside.iter().map(|&i| points_norm[i]).collect();
        farthest_point_sample(&local, n2, 0)?.into_iter().map(|k| inside[k]).collect()
    } else {
        inside.iter().copied().cycle().take(n2).collect()
    };
    Ok(GeometricSelection { indices, radius, fell_back: false })
}

/// `n2` indices sampled over the whole cloud: farthest point sampling from index 0 (cyclic
/// repetition when the cloud is smaller than `n2`). The geometric tokens at t = 0.
pub fn global_geometric_tokens(points_norm: &[[f32; 3]], n2: usize) -> Result<Vec<usize>> {
    if points_norm.len() >= n2 {
        farthest_point_sample(points_norm, n2, 0)
    } else {
        Ok((0..points_norm.len()).cycle().take(n2).collect())
    }
}

// ---------------------------------------------------------------------------------------------
// 3D positional encoding
// ---------------------------------------------------------------------------------------------

/// Octaves spanned by the positional encoding's frequencies: from pi/2 (half a period over the
/// whole [-1, 1] axis) to 2^5 pi (a period of 1/16 normalised unit, about 3.6 cm on flowram's
/// 1.15 m x axis).
pub const POSITIONAL_OCTAVES: f32 = 6.0;

/// The frequencies (radians per normalised unit) of [`positional_encoding`] for `per_axis`
/// frequencies: `omega_k = pi * 2^(k * 6 / (F - 1) - 1)`, k = 0..F-1, geometric from pi/2 to
/// 32 pi (`[pi / 2]` when F = 1).
pub fn positional_frequencies(per_axis: usize) -> Vec<f32> {
    (0..per_axis)
        .map(|k| {
            let step = if per_axis > 1 { POSITIONAL_OCTAVES / (per_axis - 1) as f32 } else { 0.0 };
            PI * (k as f32 * step - 1.0).exp2()
        })
        .collect()
}

/// Sinusoidal (Fourier-feature) encoding of normalised positions: `xyz` `[.., 3]` ->
/// `[.., channels]`, same dtype and device.
///
/// Channel layout: `channels = 6 F` (F = channels / 6 frequencies per axis, 20 for C = 120),
/// three blocks of `2 F` for x, y, z; each block is `sin(omega_0 a) .. sin(omega_{F-1} a)`
/// then `cos(omega_0 a) .. cos(omega_{F-1} a)` with the frequencies of
/// [`positional_frequencies`].
///
/// Positions are data (point cloud, noisy action), so no gradient flows back to `xyz` (it is
/// detached). CPU f32 tensors take a fused kernel (branch-free sin/cos, accurate to about 1e-6
/// for |x| <= 100, where it switches to the standard library); other dtypes and devices use
/// candle ops.
///
/// Errors: [`PolicyError::Invalid`] when the last dimension is not 3 or `channels` is not a
/// positive multiple of 6.
pub fn positional_encoding(xyz: &Tensor, channels: usize) -> Result<Tensor> {
    if xyz.dims().last() != Some(&3) {
        return Err(PolicyError::Invalid(format!(
            "positional encoding expects positions [.., 3], got shape {:?}",
            xyz.dims()
        )));
    }
    if channels == 0 || !channels.is_multiple_of(6) {
        return Err(PolicyError::Invalid(format!(
            "positional encoding channels must be a positive multiple of 6 (sin and cos per axis); got {channels}"
        )));
    }
    let per_axis = channels / 6;
    let xyz = xyz.detach();
    if xyz.device().is_cpu() && xyz.dtype() == DType::F32 {
        let positions = xyz.flatten_all()?.to_vec1::<f32>()?;
        let mut shape = xyz.dims().to_vec();
        if let Some(last) = shape.last_mut() {
            *last = channels;
        }
        let encoded = encode_positions(&positions, per_axis);
        return Ok(Tensor::from_vec(encoded, shape, xyz.device())?);
    }
    let freqs = Tensor::new(positional_frequencies(per_axis), xyz.device())?.to_dtype(xyz.dtype())?;
    let angles = xyz.unsqueeze(D::Minus1)?.broadcast_mul(&freqs)?; // [.., 3, F]
    let features = Tensor::cat(&[angles.sin()?, angles.cos()?], D::Minus1)?; // [.., 3, 2F]
    Ok(features.flatten_from(features.rank() - 2)?)
}

/// The CPU kernel of [`positional_encoding`]: `positions` (3 per point) -> `6 F` per point.
fn encode_positions(positions: &[f32], per_axis: usize) -> Vec<f32> {
    let freqs = positional_frequencies(per_axis);
    let width = 2 * per_axis; // one axis block: F sines, F cosines
    let mut out = vec![0.0f32; positions.len() * width];
    let largest = positions.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let fast = largest <= 100.0; // |angle| <= 100 * 32 pi: the reduction below stays exact enough
    let encode_block = |(block, &x): (&mut [f32], &f32)| {
        let (sines, cosines) = block.split_at_mut(per_axis);
        for ((s, c), w) in sines.iter_mut().zip(cosines.iter_mut()).zip(&freqs) {
            (*s, *c) = if fast { sin_cos(w * x) } else { (w * x).sin_cos() };
        }
    };
    const PARALLEL_MIN_VALUES: usize = 1 << 18;
    if out.len() >= PARALLEL_MIN_VALUES {
        use rayon::prelude::*;
        out.par_chunks_mut(width).zip(positions.par_iter()).with_min_len(1024).for_each(encode_block);
    } else {
        out.chunks_mut(width).zip(positions.iter()).for_each(encode_block);
    }
    out
}

/// `(sin a, cos a)` without branches (vectorisable): reduction by pi/2 (Cody-Waite, three
/// parts) and Cephes' single-precision polynomials on [-pi/4, pi/4]. Absolute error about 1e-7
/// for |a| up to a few thousand.
#[inline(always)]
fn sin_cos(a: f32) -> (f32, f32) {
    const FRAC_2_PI: f32 = std::f32::consts::FRAC_2_PI;
    const ROUND: f32 = 12_582_912.0; // 1.5 * 2^23: (v + ROUND) - ROUND rounds v to an integer
    let q = (a * FRAC_2_PI + ROUND) - ROUND;
    let r = ((a - q * 1.570_312_5) - q * 4.837_513e-4) - q * 7.549_79e-8;
    let r2 = r * r;
    let s = r + r * r2 * (-1.666_665_5e-1 + r2 * (8.332_161e-3 + r2 * -1.951_529_6e-4));
    let c = 1.0 - 0.5 * r2 + r2 * r2 * (4.166_664_6e-2 + r2 * (-1.388_731_6e-3 + r2 * 2.443_315_7e-5));
    let quadrant = (q as i32) & 3;
    let (s, c) = if quadrant & 1 != 0 { (c, s) } else { (s, c) };
    let sin = if quadrant & 2 != 0 { -s } else { s };
    let cos = if (quadrant + 1) & 2 != 0 { -c } else { c };
    (sin, cos)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_quaternion(rng: &mut ChaCha8Rng) -> [f32; 4] {
        loop {
            let q: [f32; 4] = std::array::from_fn(|_| rng.random_range(-1.0f32..1.0));
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            if n > 0.1 && n <= 1.0 {
                return q.map(|v| v / n);
            }
        }
    }

    fn canonical(q: [f32; 4]) -> [f32; 4] {
        if q[0] < 0.0 { q.map(|v| -v) } else { q }
    }

    fn assert_close<const N: usize>(a: [f32; N], b: [f32; N], tol: f32, what: &str) {
        for i in 0..N {
            assert!((a[i] - b[i]).abs() <= tol, "{what}: {a:?} vs {b:?}");
        }
    }

    fn assert_proper_rotation(m: &RotationMatrix, what: &str) {
        for i in 0..3 {
            for j in 0..3 {
                assert!(m[i][j].is_finite(), "{what}: NaN/inf in {m:?}");
                let dot: f32 = (0..3).map(|k| m[k][i] * m[k][j]).sum();
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((dot - want).abs() < 1e-5, "{what}: columns {i},{j} dot {dot} in {m:?}");
            }
        }
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        assert!((det - 1.0).abs() < 1e-5, "{what}: det {det} of {m:?}");
    }

    #[test]
    fn rotation_round_trips() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut quaternions: Vec<[f32; 4]> = (0..2000).map(|_| random_quaternion(&mut rng)).collect();
        // Half-turns and near half-turns exercise every branch of Shepperd's method.
        quaternions.extend([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0], [1e-4, 0.7, 0.7, 0.1]]);
        for q in quaternions {
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            let q = q.map(|v| v / n);
            let m = matrix_from_quaternion(q).unwrap();
            assert_proper_rotation(&m, "from quaternion");
            let back = quaternion_from_matrix(&m);
            assert!(back[0] >= 0.0);
            // q and -q are the same rotation; compare the canonical forms (w = 0 ties aside).
            let same = (0..4).all(|i| (back[i] - canonical(q)[i]).abs() < 1e-5)
                || (q[0].abs() < 1e-5 && (0..4).all(|i| (back[i] + canonical(q)[i]).abs() < 1e-5));
            assert!(same, "quaternion {q:?} -> {back:?}");
            let m6 = rotation_from_6d(rotation_to_6d(&m));
            for r in 0..3 {
                assert_close(m6[r], m[r], 1e-5, "matrix -> 6D -> matrix");
            }
            let q6 = quaternion_from_6d(quaternion_to_6d(q).unwrap());
            assert_close(
                rotation_to_6d(&matrix_from_quaternion(q6).unwrap()),
                rotation_to_6d(&m),
                1e-5,
                "q -> 6D -> q",
            );
        }
    }

    #[test]
    fn known_rotation_and_6d_layout() {
        let h = 0.5f32.sqrt();
        let m = matrix_from_quaternion([h, 0.0, 0.0, h]).unwrap(); // +90 deg about z
        let want = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        for r in 0..3 {
            assert_close(m[r], want[r], 1e-6, "90 deg about z");
        }
        assert_close(rotation_to_6d(&m), [0.0, 1.0, 0.0, -1.0, 0.0, 0.0], 1e-6, "6D = first two columns");
        assert_close(quaternion_from_matrix(&m), [h, 0.0, 0.0, h], 1e-6, "back");
        // Scaling does not matter; zero and NaN quaternions are refused.
        assert_close(matrix_from_quaternion([2.0 * h, 0.0, 0.0, 2.0 * h]).unwrap()[0], want[0], 1e-6, "scaled");
        assert!(matrix_from_quaternion([0.0; 4]).is_err());
        assert!(matrix_from_quaternion([f32::NAN, 0.0, 0.0, 1.0]).is_err());
    }

    #[test]
    fn gram_schmidt_of_noisy_6d_keeps_the_first_column_direction() {
        let m = rotation_from_6d([2.0, 0.0, 0.0, 0.5, 3.0, 0.0]);
        assert_close(rotation_to_6d(&m), [1.0, 0.0, 0.0, 0.0, 1.0, 0.0], 1e-6, "gram-schmidt");
        let m = rotation_from_6d([0.0, 0.0, 1.0, 1.0, 0.0, 0.2]);
        assert_close([m[0][0], m[1][0], m[2][0]], [0.0, 0.0, 1.0], 1e-6, "b1");
        assert_close([m[0][1], m[1][1], m[2][1]], [1.0, 0.0, 0.0], 1e-6, "b2");
    }

    #[test]
    fn degenerate_6d_gives_proper_rotations() {
        let big = 3.0e38f32;
        let cases: [[f32; 6]; 12] = [
            [0.0; 6],
            [1.0, 2.0, 3.0, 2.0, 4.0, 6.0],      // parallel
            [1.0, 2.0, 3.0, -1.0, -2.0, -3.0],   // antiparallel
            [0.0, 0.0, 0.0, 0.3, -0.2, 0.9],     // zero first column
            [0.3, -0.2, 0.9, 0.0, 0.0, 0.0],     // zero second column
            [f32::NAN, 1.0, 0.0, 0.0, 1.0, 0.0], // NaN
            [f32::INFINITY, 0.0, 0.0, f32::NEG_INFINITY, 1.0, f32::NAN],
            [big, big, big, big, big, -big],    // huge
            [1e-30, 0.0, 0.0, 0.0, 1e-30, 0.0], // tiny
            [1.0, 1e-8, 0.0, 1.0, 0.0, 0.0],    // nearly parallel
            [0.0, 0.0, 1.0, 0.0, 0.0, 1.0],     // parallel to e_z
            [0.577, 0.577, 0.577, 0.577, 0.577, 0.577],
        ];
        for r in cases {
            assert_proper_rotation(&rotation_from_6d(r), &format!("6D {r:?}"));
            let q = quaternion_from_6d(r);
            assert!(q.iter().all(|v| v.is_finite()) && q[0] >= 0.0, "{r:?} -> {q:?}");
        }
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(rotation_from_6d([0.0; 6]), identity);
        assert_eq!(rotation_from_6d([1.0, 0.0, 0.0, 3.0, 0.0, 0.0]), identity);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..2000 {
            let r: [f32; 6] = std::array::from_fn(|_| rng.random_range(-1.0f32..1.0));
            assert_proper_rotation(&rotation_from_6d(r), "random 6D");
        }
    }

    /// A 128x128 camera with fovy 60 deg looking down at a table plane z = 0.75 m from 1.6 m up,
    /// tilted; depth rendered analytically; a band of pixels sees nothing.
    /// Intrinsics, camera-to-world pose, depth image, image size.
    type SyntheticCamera = ([[f32; 3]; 3], [[f32; 4]; 4], Vec<f32>, usize);

    fn synthetic_camera() -> SyntheticCamera {
        let size = 128usize;
        let f = 0.5 * size as f32 / (30f32.to_radians()).tan();
        let c = (size as f32 - 1.0) / 2.0;
        let k = [[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]];
        // Camera z (forward) points down and forward, x right.
        let tilt = 0.4f32;
        let z_axis = [0.0, tilt.sin(), -tilt.cos()];
        let x_axis = [1.0, 0.0, 0.0];
        let y_axis = [
            z_axis[1] * x_axis[2] - z_axis[2] * x_axis[1],
            z_axis[2] * x_axis[0] - z_axis[0] * x_axis[2],
            z_axis[0] * x_axis[1] - z_axis[1] * x_axis[0],
        ];
        let t = [0.3, -0.2, 1.6];
        let pose = [
            [x_axis[0], y_axis[0], z_axis[0], t[0]],
            [x_axis[1], y_axis[1], z_axis[1], t[1]],
            [x_axis[2], y_axis[2], z_axis[2], t[2]],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let mut depth = vec![0.0; size * size];
        for v in 0..size {
            for u in 0..size {
                if (40..44).contains(&v) {
                    continue; // no surface
                }
                let ray = [(u as f32 - c) / f, (v as f32 - c) / f, 1.0];
                let ray_z = pose[2][0] * ray[0] + pose[2][1] * ray[1] + pose[2][2] * ray[2];
                depth[v * size + u] = (0.75 - t[2]) / ray_z;
            }
        }
        (k, pose, depth, size)
    }

    #[test]
    fn lifting_inverts_the_pinhole_projection() {
        let (k, pose, depth, size) = synthetic_camera();
        for stride in [1usize, 2, 4, 8] {
            let cells = lift_depth(&depth, size, size, &k, &pose, stride).unwrap();
            let grid = size / stride;
            assert_eq!(cells.len(), grid * grid);
            for r in 0..grid {
                for c in 0..grid {
                    let (u, v) = (stride * c + stride / 2, stride * r + stride / 2);
                    let cell = cells[r * grid + c];
                    if (40..44).contains(&v) {
                        assert!(cell.is_none(), "pixel row {v} has no depth");
                        continue;
                    }
                    let p = cell.expect("valid depth gives a point");
                    assert!((p[2] - 0.75).abs() < 1e-4, "point {p:?} is off the table plane");
                    let ([pu, pv], z) = project_to_pixel(p, &k, &pose).unwrap();
                    assert!(
                        (pu - u as f32).abs() < 1e-3 && (pv - v as f32).abs() < 1e-3,
                        "{p:?} -> ({pu}, {pv}) not ({u}, {v})"
                    );
                    assert!((z - depth[v * size + u]).abs() < 1e-4);
                }
            }
        }
        assert!(lift_depth(&depth, size, size, &k, &pose, 3).is_err(), "3 does not divide 128");
        assert!(lift_depth(&depth, size, size, &k, &pose, 0).is_err());
        assert!(lift_depth(&depth[1..], size, size, &k, &pose, 1).is_err());
        let mut bad_k = k;
        bad_k[0][0] = 0.0;
        assert!(lift_depth(&depth, size, size, &bad_k, &pose, 1).is_err());
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

    /// The textbook O(N n) loop, lowest index on ties.
    fn reference_fps(points: &[[f32; 3]], n: usize, first: usize) -> Vec<usize> {
        let mut dist = vec![f32::INFINITY; points.len()];
        let mut picks = vec![first];
        let mut last = first;
        while picks.len() < n {
            let p = points[last];
            let mut best = (f32::NEG_INFINITY, 0);
            for (i, q) in points.iter().enumerate() {
                let (dx, dy, dz) = (q[0] - p[0], q[1] - p[1], q[2] - p[2]);
                let d = dx * dx + dy * dy + dz * dz;
                if d < dist[i] {
                    dist[i] = d;
                }
                if dist[i] > best.0 {
                    best = (dist[i], i);
                }
            }
            last = best.1;
            picks.push(last);
        }
        picks
    }

    fn random_cloud(rng: &mut ChaCha8Rng, n: usize) -> Vec<[f32; 3]> {
        (0..n).map(|_| std::array::from_fn(|_| rng.random_range(-1.0f32..1.0))).collect()
    }

    #[test]
    fn fps_matches_the_reference_loop() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for (size, n) in [(2usize, 1usize), (3, 2), (17, 9), (100, 50), (1000, 300), (5000, 1024), (4096, 1024)] {
            let cloud = random_cloud(&mut rng, size);
            let first = rng.random_range(0..size);
            assert_eq!(
                farthest_point_sample(&cloud, n, first).unwrap(),
                reference_fps(&cloud, n, first),
                "{size} -> {n}"
            );
        }
        // Clustered and anisotropic clouds.
        let mut cloud: Vec<[f32; 3]> = (0..3000)
            .map(|i| {
                let c = (i % 5) as f32 * 0.4 - 0.8;
                [
                    c + rng.random_range(-0.01f32..0.01),
                    rng.random_range(-1.0f32..1.0) * 0.01,
                    rng.random_range(0.0f32..0.05),
                ]
            })
            .collect();
        cloud.extend(random_cloud(&mut rng, 200));
        assert_eq!(farthest_point_sample(&cloud, 700, 5).unwrap(), reference_fps(&cloud, 700, 5));
    }

    #[test]
    fn fps_ties_and_duplicates_pick_the_lowest_index() {
        // A coarse integer grid, every point three times: distances tie all the time.
        let mut cloud = Vec::new();
        for _ in 0..3 {
            for x in 0..6 {
                for y in 0..5 {
                    for z in 0..4 {
                        cloud.push([x as f32, y as f32, z as f32]);
                    }
                }
            }
        }
        for n in [10, 120, 200, 359] {
            assert_eq!(farthest_point_sample(&cloud, n, 7).unwrap(), reference_fps(&cloud, n, 7), "n = {n}");
        }
        let same = vec![[0.5f32; 3]; 50];
        assert_eq!(farthest_point_sample(&same, 4, 3).unwrap(), vec![3, 0, 0, 0]);
    }

    #[test]
    fn fps_with_a_parallel_build_matches_the_reference() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let cloud = random_cloud(&mut rng, 4 * PARALLEL_BUILD_MIN_POINTS + 999);
        assert_eq!(farthest_point_sample(&cloud, 64, 42).unwrap(), reference_fps(&cloud, 64, 42));
    }

    #[test]
    fn fps_edge_cases() {
        let cloud = [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]];
        assert_eq!(farthest_point_sample(&cloud, 3, 1).unwrap(), vec![0, 1, 2], "n >= len gives all indices");
        assert_eq!(farthest_point_sample(&cloud, 10, 0).unwrap(), vec![0, 1, 2]);
        assert_eq!(farthest_point_sample(&cloud, 2, 1).unwrap(), vec![1, 2]);
        assert!(farthest_point_sample(&[], 4, 0).unwrap().is_empty());
        assert!(farthest_point_sample(&cloud, 2, 3).is_err());
        assert!(farthest_point_sample(&[[0.0, f32::NAN, 0.0], [1.0; 3], [2.0; 3]], 2, 0).is_err());
    }

    #[test]
    fn radius_schedule_is_global_then_shrinks_monotonically() {
        let schedule = RadiusSchedule::default();
        schedule.validate().unwrap();
        assert!(schedule.radius(0.0) >= GLOBAL_RADIUS);
        assert!((schedule.radius(1.0) - RadiusSchedule::DEFAULT_R_MIN).abs() < 1e-6);
        let mut previous = f32::INFINITY;
        for k in 0..=1000 {
            let r = schedule.radius(k as f32 / 1000.0);
            assert!(r <= previous, "r(t) must not increase");
            assert!(previous == f32::INFINITY || previous - r < 0.01, "r(t) must be continuous");
            previous = r;
        }
        let quadratic = RadiusSchedule::dynamic(0.2, 4.0, 2.0).unwrap();
        assert!((quadratic.radius(0.5) - (0.2 + 3.8 * 0.25)).abs() < 1e-6);
        assert_eq!(RadiusSchedule::Global.radius(0.9), f32::INFINITY);
        for (r_min, r_max, power) in
            [(0.0, 4.0, 1.0), (0.5, 3.0, 1.0), (5.0, 4.0, 1.0), (0.5, 4.0, 0.0), (f32::NAN, 4.0, 1.0)]
        {
            assert!(RadiusSchedule::dynamic(r_min, r_max, power).is_err(), "{r_min} {r_max} {power}");
        }
        let json = serde_json::to_string(&schedule).unwrap();
        assert_eq!(serde_json::from_str::<RadiusSchedule>(&json).unwrap(), schedule);
        assert_eq!(serde_json::from_str::<RadiusSchedule>(r#"{"kind":"global"}"#).unwrap(), RadiusSchedule::Global);
        assert!(
            serde_json::from_str::<RadiusSchedule>(r#"{"kind":"dynamic","r_min":0.4,"r_max":1.0,"power":1}"#).is_err()
        );
    }

    #[test]
    fn cached_global_selection_gives_the_same_tokens() {
        let mut rng = ChaCha8Rng::seed_from_u64(23);
        let cloud = random_cloud(&mut rng, 3000);
        let global = global_geometric_tokens(&cloud, 256).unwrap();
        let wrong_length = global_geometric_tokens(&cloud, 100).unwrap();
        for schedule in [RadiusSchedule::default(), RadiusSchedule::Global] {
            // t = 0 (global), every point inside (r ~ 3.3), a local ball, the fallback (far centre)
            for (center, t) in
                [([0.1, 0.2, -0.3], 0.0), ([0.0, 0.0, 0.0], 0.05), ([0.2, -0.3, 0.1], 0.7), ([3.0, 3.0, 3.0], 1.0)]
            {
                let plain = select_geometric_tokens(&cloud, center, t, 256, 32, &schedule).unwrap();
                for g in [&global, &wrong_length] {
                    let cached =
                        select_geometric_tokens_cached(&cloud, Some(g), center, t, 256, 32, &schedule).unwrap();
                    assert_eq!(cached, plain, "t {t}, centre {center:?}, {schedule:?}");
                }
            }
        }
    }

    #[test]
    fn geometric_tokens_lie_within_the_radius() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let cloud = random_cloud(&mut rng, 4096);
        let schedule = RadiusSchedule::default();
        let center = [0.2, -0.3, 0.1];
        for t in [0.5f32, 0.7, 0.8] {
            let selection = select_geometric_tokens(&cloud, center, t, 256, 32, &schedule).unwrap();
            assert!(!selection.fell_back);
            assert_eq!(selection.indices.len(), 256);
            assert!((selection.radius - schedule.radius(t)).abs() < 1e-6);
            let mut unique = selection.indices.clone();
            unique.sort_unstable();
            unique.dedup();
            assert_eq!(unique.len(), 256, "enough points inside: no repetition");
            for &i in &selection.indices {
                let p = cloud[i];
                let d = ((p[0] - center[0]).powi(2) + (p[1] - center[1]).powi(2) + (p[2] - center[2]).powi(2)).sqrt();
                assert!(d <= selection.radius + 1e-6, "token {i} at distance {d} > r = {}", selection.radius);
            }
            assert_eq!(
                select_geometric_tokens(&cloud, center, t, 256, 32, &schedule).unwrap(),
                selection,
                "deterministic"
            );
        }
    }

    #[test]
    fn geometric_tokens_are_global_fps_at_t0_and_without_drs() {
        let mut rng = ChaCha8Rng::seed_from_u64(22);
        let cloud = random_cloud(&mut rng, 3000);
        let global = farthest_point_sample(&cloud, 512, 0).unwrap();
        for center in [[0.0f32; 3], [0.9, -0.9, 0.9], [5.0, 5.0, -7.0]] {
            let at_noise = select_geometric_tokens(&cloud, center, 0.0, 512, 16, &RadiusSchedule::default()).unwrap();
            assert_eq!(at_noise.indices, global);
            assert!(!at_noise.fell_back);
            let without_drs = select_geometric_tokens(&cloud, center, 0.95, 512, 16, &RadiusSchedule::Global).unwrap();
            assert_eq!(without_drs.indices, global);
        }
    }

    #[test]
    fn geometric_tokens_clamp_the_centre_and_stay_global_for_uncropped_points() {
        let mut rng = ChaCha8Rng::seed_from_u64(24);
        let mut cloud = random_cloud(&mut rng, 3000);
        // A noisy action far outside the workspace samples around the nearest box corner.
        let schedule = RadiusSchedule::default();
        let far = select_geometric_tokens(&cloud, [3.0, 3.0, 3.0], 0.5, 256, 16, &schedule).unwrap();
        let corner = select_geometric_tokens(&cloud, [1.0, 1.0, 1.0], 0.5, 256, 16, &schedule).unwrap();
        assert!(!far.fell_back);
        assert_eq!(far, corner);
        // Points outside [-1, 1]^3 (a caller that did not crop) still count at t = 0.
        cloud.extend([[-1.6f32, -1.6, -1.6], [1.7, 1.7, -1.7]]);
        let global = farthest_point_sample(&cloud, 256, 0).unwrap();
        let at_noise = select_geometric_tokens(&cloud, [0.9, 0.9, 0.9], 0.0, 256, 16, &schedule).unwrap();
        assert_eq!(at_noise.indices, global);
        assert!(global.contains(&3000) && global.contains(&3001));
    }

    #[test]
    fn geometric_tokens_fall_back_or_repeat_when_few_points_are_near() {
        let mut rng = ChaCha8Rng::seed_from_u64(23);
        // Most points in a blob around (-0.8, -0.8, -0.8), 20 around (0.8, 0.8, 0.8).
        let mut cloud: Vec<[f32; 3]> =
            (0..2000).map(|_| std::array::from_fn(|_| -0.8 + rng.random_range(-0.1f32..0.1))).collect();
        cloud.extend((0..20).map(|_| std::array::from_fn::<f32, 3, _>(|_| 0.8 + rng.random_range(-0.05f32..0.05))));
        let schedule = RadiusSchedule::default();
        let far = [0.8, 0.8, 0.8];
        // 20 points inside, min_inside 32: fall back to global FPS.
        let fallback = select_geometric_tokens(&cloud, far, 1.0, 256, 32, &schedule).unwrap();
        assert!(fallback.fell_back);
        assert_eq!(fallback.indices, farthest_point_sample(&cloud, 256, 0).unwrap());
        // min_inside 10: the 20 points repeated cyclically to 256.
        let padded = select_geometric_tokens(&cloud, far, 1.0, 256, 10, &schedule).unwrap();
        assert!(!padded.fell_back);
        assert_eq!(padded.indices.len(), 256);
        let inside: Vec<usize> = (2000..2020).collect();
        assert_eq!(&padded.indices[..20], &inside[..]);
        assert_eq!(&padded.indices[20..40], &inside[..]);
        // Exact count n2 for any centre and time.
        for _ in 0..50 {
            let center: [f32; 3] = std::array::from_fn(|_| rng.random_range(-2.0f32..2.0));
            let t = rng.random_range(0.0f32..=1.0);
            let s = select_geometric_tokens(&cloud, center, t, 300, 8, &schedule).unwrap();
            assert_eq!(s.indices.len(), 300);
        }
        // A cloud smaller than n2 is repeated; bad arguments are refused.
        assert_eq!(select_geometric_tokens(&cloud[..5], far, 0.0, 12, 1, &schedule).unwrap().indices.len(), 12);
        assert!(select_geometric_tokens(&[], far, 0.5, 12, 1, &schedule).is_err());
        assert!(select_geometric_tokens(&cloud, far, 1.5, 12, 1, &schedule).is_err());
        assert!(select_geometric_tokens(&cloud, [f32::NAN; 3], 0.5, 12, 1, &schedule).is_err());
        assert!(select_geometric_tokens(&cloud, far, 0.5, 0, 1, &schedule).is_err());
        let bad = RadiusSchedule::Dynamic { r_min: 0.4, r_max: 1.0, power: 1.0 };
        assert!(select_geometric_tokens(&cloud, far, 0.5, 12, 1, &bad).is_err());
    }

    #[test]
    fn branch_free_sin_cos_is_accurate() {
        let mut worst = 0.0f32;
        for k in -400_000..=400_000 {
            let a = k as f32 * 0.01 + 0.003; // [-4000, 4000]
            let (s, c) = sin_cos(a);
            let (s64, c64) = (a as f64).sin_cos();
            worst = worst.max((s as f64 - s64).abs() as f32).max((c as f64 - c64).abs() as f32);
        }
        assert!(worst < 1e-6, "largest error {worst}");
    }

    #[test]
    fn positional_encoding_layout() {
        let device = Device::Cpu;
        let xyz = Tensor::new(&[[[0.1f32, -0.5, 0.9], [1.0, 0.0, -1.0]], [[0.3, 0.3, 0.3], [-0.2, 0.7, 0.0]]], &device)
            .unwrap();
        let encoded = positional_encoding(&xyz, 120).unwrap();
        assert_eq!(encoded.dims(), &[2, 2, 120]);
        let values = encoded.to_vec3::<f32>().unwrap();
        let freqs = positional_frequencies(20);
        assert!((freqs[0] - PI / 2.0).abs() < 1e-6 && (freqs[19] - 32.0 * PI).abs() < 1e-4);
        let position = [0.1f32, -0.5, 0.9];
        for axis in 0..3 {
            for (k, w) in freqs.iter().enumerate() {
                let sin = values[0][0][axis * 40 + k];
                let cos = values[0][0][axis * 40 + 20 + k];
                assert!((sin - (w * position[axis]).sin()).abs() < 1e-5, "axis {axis} sin {k}");
                assert!((cos - (w * position[axis]).cos()).abs() < 1e-5, "axis {axis} cos {k}");
            }
        }
        assert_eq!(positional_encoding(&xyz, 6).unwrap().dims(), &[2, 2, 6]);
        // The fused CPU f32 kernel agrees with the candle-op path (taken for f64).
        let ops = positional_encoding(&xyz.to_dtype(candle_core::DType::F64).unwrap(), 120).unwrap();
        let diff = (ops.to_dtype(candle_core::DType::F32).unwrap() - &encoded).unwrap().abs().unwrap();
        let diff = diff.max_all().unwrap().to_scalar::<f32>().unwrap();
        // Rounding the angle w * x (up to 32 pi) in f32 rather than f64 alone costs a few 1e-6.
        assert!(diff < 1e-5, "fused kernel vs candle ops: {diff}");
        // Large coordinates take the standard library's sin/cos.
        let far = Tensor::new(&[[150.0f32, -1.0, 0.0]], &device).unwrap();
        let far_encoded = positional_encoding(&far, 12).unwrap().to_vec2::<f32>().unwrap();
        assert!((far_encoded[0][1] - (positional_frequencies(2)[1] * 150.0).sin()).abs() < 1e-6);
        assert!(positional_encoding(&xyz, 100).is_err());
        assert!(positional_encoding(&Tensor::zeros((4, 2), candle_core::DType::F32, &device).unwrap(), 120).is_err());
    }
}
