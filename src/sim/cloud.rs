//! World-frame point clouds from RGB-D frames: back-projection of depth through the camera's
//! pinhole model and pose, optional cropping to a workspace box, and merging across cameras.
use nalgebra::{Point3, Vector3};

use super::camera::RgbdFrame;

/// An axis-aligned box in the world frame (metres).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Workspace {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl Workspace {
    /// The region in front of the robot of flowram's scenes: the table top from the robot's base
    /// to its far edge, and up to 0.65 m above it.
    pub const TABLE: Workspace = Workspace { min: [-0.25, -0.65, 0.74], max: [0.9, 0.65, 1.4] };

    pub fn contains(&self, p: &Point3<f64>) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }
}

/// Points in the world frame with one RGB colour each.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    pub points: Vec<Point3<f32>>,
    pub colors: Vec<[u8; 3]>,
}

impl PointCloud {
    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Back-projects every pixel with depth > 0 into the world frame, keeping those inside
    /// `crop` when one is given.
    pub fn from_frame(frame: &RgbdFrame, crop: Option<&Workspace>) -> Self {
        let mut cloud = Self::default();
        cloud.extend_from_frame(frame, crop);
        cloud
    }

    /// Appends the points of another frame (for a merged multi-camera cloud).
    pub fn extend_from_frame(&mut self, frame: &RgbdFrame, crop: Option<&Workspace>) {
        let k = &frame.intrinsics;
        let pose = frame.extrinsics.to_homogeneous();
        let r = pose.fixed_view::<3, 3>(0, 0).into_owned();
        let t = Vector3::new(pose[(0, 3)], pose[(1, 3)], pose[(2, 3)]);
        for v in 0..k.height {
            for u in 0..k.width {
                let i = v * k.width + u;
                let z = frame.depth[i] as f64;
                if z <= 0.0 {
                    continue;
                }
                let cam = Vector3::new((u as f64 - k.cx) * z / k.fx, (v as f64 - k.cy) * z / k.fy, z);
                let p = Point3::from(r * cam + t);
                if crop.is_some_and(|w| !w.contains(&p)) {
                    continue;
                }
                self.points.push(p.cast());
                self.colors.push([frame.rgb[3 * i], frame.rgb[3 * i + 1], frame.rgb[3 * i + 2]]);
            }
        }
    }

    /// Binary little-endian PLY (x, y, z float; red, green, blue uchar): opens in MeshLab,
    /// Open3D, CloudCompare.
    pub fn to_ply(&self) -> Vec<u8> {
        let header = format!(
            "ply\nformat binary_little_endian 1.0\ncomment flowram point cloud, world frame, metres\n\
             element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
             property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
            self.points.len()
        );
        let mut out = Vec::with_capacity(header.len() + self.points.len() * 15);
        out.extend_from_slice(header.as_bytes());
        for (p, c) in self.points.iter().zip(&self.colors) {
            for x in [p.x, p.y, p.z] {
                out.extend_from_slice(&x.to_le_bytes());
            }
            out.extend_from_slice(c);
        }
        out
    }
}
