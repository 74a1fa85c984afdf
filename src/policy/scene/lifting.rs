//! Lifting depth pixels to world points, and projecting world points back to pixels.
//!
//! Cameras: OpenCV axes (x right, y down, z forward), z-depth in metres, intrinsics
//! `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]` in pixels with pixel centres at integer
//! coordinates (pixel `(u, v)` = column u, row v is centred at `(u, v)`), as `sim::camera`.
use crate::policy::error::{PolicyError, Result};

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

#[cfg(test)]
mod tests {
    use super::*;

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
}
