//! Offscreen RGB-D cameras: EGL rendering through MuJoCo (Mesa llvmpipe on these machines),
//! the pinhole model of each camera, and its pose.
//!
//! Conventions (also in the README):
//! - images are row-major, row 0 at the top; RGB u8; depth f32 in metres along the optical axis
//!   (z-depth, not ray length); pixels that see nothing (beyond the far plane) have depth 0;
//! - intrinsics `K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]` with pixel centres at integer
//!   coordinates (OpenCV), from the camera's vertical field of view `fovy` and square pixels;
//! - extrinsics are camera-to-world in the OpenCV camera convention (x right, y down, z forward).
//!   MuJoCo's own camera frame looks along -z with y up; the conversion is
//!   `R_world_cv = R_world_mujoco * diag(1, -1, -1)`.
use std::mem::ManuallyDrop;
use std::sync::{Mutex, MutexGuard, PoisonError};

use mujoco_rs::prelude::*;
use mujoco_rs::renderer::MjRenderer;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};

use super::SimError;
use super::world::World;

/// The default image size (pixels, square), as in the paper and RLBench's 128x128 setting.
pub const DEFAULT_IMAGE_SIZE: usize = 128;

/// Pinhole intrinsics of one camera at one image size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub width: usize,
    pub height: usize,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// From MuJoCo's vertical field of view (degrees) and the image size.
    pub fn from_fovy(fovy_deg: f64, width: usize, height: usize) -> Self {
        let f = 0.5 * height as f64 / (0.5 * fovy_deg.to_radians()).tan();
        Self { width, height, fx: f, fy: f, cx: (width as f64 - 1.0) / 2.0, cy: (height as f64 - 1.0) / 2.0 }
    }

    /// The 3x3 camera matrix K.
    pub fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }
}

/// What the renderer draws for the robot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Visuals {
    /// The Panda's full visual meshes (about 135k faces): what the paper's images look like.
    #[default]
    Full,
    /// Collision meshes as their convex hulls (a few hundred faces per link): several times
    /// faster on a software renderer, coarser arm silhouettes, identical everything else.
    Fast,
}

/// One rendered RGB-D frame with its camera model.
#[derive(Debug, Clone)]
pub struct RgbdFrame {
    pub camera: String,
    pub intrinsics: Intrinsics,
    /// Camera-to-world, OpenCV camera axes.
    pub extrinsics: Isometry3<f64>,
    /// `height * width * 3` bytes, row 0 at the top.
    pub rgb: Vec<u8>,
    /// `height * width` metres; 0 where nothing was hit.
    pub depth: Vec<f32>,
}

/// Held while an offscreen GL context is made or destroyed. Every rig opens a context on the
/// same EGL display (one Mesa driver instance per process); MuJoCo-rs serialises only
/// `mjr_makeContext` / `mjr_freeContext`, not the EGL context's and surface's creation and
/// destruction around them. Rigs made and dropped on several threads at once (the test harness
/// runs tests that way) are the one place that could race: the CI run of stop 53 (session 42)
/// died once with SIGSEGV there, not reproduced here. Rendering itself stays concurrent. Never
/// taken in the control tick (a rig is made before a run starts).
static GL_CONTEXTS: Mutex<()> = Mutex::new(());

fn gl_contexts() -> MutexGuard<'static, ()> {
    GL_CONTEXTS.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The scene's cameras and one offscreen renderer that draws them in turn.
pub struct CameraRig {
    /// Dropped by [`CameraRig`]'s `Drop`, under [`GL_CONTEXTS`].
    renderer: ManuallyDrop<MjRenderer>,
    cameras: Vec<(String, usize)>,
    size: usize,
    far: f32,
}

impl std::fmt::Debug for CameraRig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CameraRig").field("cameras", &self.cameras).field("size", &self.size).finish()
    }
}

impl Drop for CameraRig {
    fn drop(&mut self) {
        let _guard = gl_contexts();
        // SAFETY: the renderer is dropped exactly once, here, and never used after.
        unsafe { ManuallyDrop::drop(&mut self.renderer) };
    }
}

impl CameraRig {
    /// An offscreen EGL renderer for every camera of the world's scene, at `size` x `size`.
    pub fn new(world: &World, size: usize, visuals: Visuals) -> Result<Self, SimError> {
        let model = world.model();
        let global = &model.vis().global;
        let (max_w, max_h) = (global.offwidth as usize, global.offheight as usize);
        if size == 0 || size > max_w || size > max_h {
            return Err(SimError::InvalidInput {
                what: "image size",
                detail: format!(
                    "{size} px; this scene renders 1 to {} px (raise <visual><global offwidth/offheight> in the scene to go larger)",
                    max_w.min(max_h)
                ),
            });
        }
        let cameras: Vec<(String, usize)> = world.camera_names().into_iter().zip(0..).collect();
        let mut options = MjvOption::default();
        options.flags[MjtVisFlag::mjVIS_CONVEXHULL as usize] = u8::from(visuals == Visuals::Fast);
        let guard = gl_contexts();
        let renderer = MjRenderer::builder()
            .width(size as u32)
            .height(size as u32)
            .rgb(true)
            .depth(true)
            .opts(options)
            .build(model)
            .map_err(|e| {
                SimError::Render(format!("{e} (offscreen EGL; Mesa's llvmpipe driver provides it headless)"))
            })?;
        drop(guard);
        let far = (model.vis().map.zfar * model.stat().extent as f32) * 0.999;
        Ok(Self { renderer: ManuallyDrop::new(renderer), cameras, size, far })
    }

    pub fn size(&self) -> usize {
        self.size
    }

    /// Camera names in model order.
    pub fn camera_names(&self) -> impl Iterator<Item = &str> {
        self.cameras.iter().map(|(n, _)| n.as_str())
    }

    /// Index of a camera by name; the error lists the valid names.
    pub fn camera_index(&self, name: &str) -> Result<usize, SimError> {
        self.cameras.iter().position(|(n, _)| n == name).ok_or_else(|| SimError::UnknownCamera {
            name: name.into(),
            valid: self.cameras.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>().join(", "),
        })
    }

    /// Intrinsics of camera `index` at this rig's image size.
    pub fn intrinsics(&self, world: &World, index: usize) -> Intrinsics {
        let id = self.cameras[index].1;
        Intrinsics::from_fovy(world.model().cam_fovy()[id], self.size, self.size)
    }

    /// Camera-to-world pose (OpenCV axes) of camera `index` in the world's current state.
    pub fn extrinsics(&self, world: &World, index: usize) -> Isometry3<f64> {
        let id = self.cameras[index].1;
        let data = world.data();
        let r_mj = Matrix3::from_row_slice(&data.cam_xmat()[id]);
        let r_cv =
            Rotation3::from_matrix_unchecked(r_mj * Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, -1.0, -1.0)));
        let p = data.cam_xpos()[id];
        Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), UnitQuaternion::from_rotation_matrix(&r_cv))
    }

    /// Renders camera `index` of the world's current state into `frame` (reusing its buffers).
    pub fn render_into(&mut self, world: &mut World, index: usize, frame: &mut RgbdFrame) -> Result<(), SimError> {
        self.draw(world.data_mut(), index)?;
        let name = &self.cameras[index].0;
        let rgb = self.renderer.rgb_flat().ok_or_else(|| SimError::Render("no RGB buffer".into()))?;
        let depth = self.renderer.depth_flat().ok_or_else(|| SimError::Render("no depth buffer".into()))?;
        frame.camera.clone_from(name);
        frame.intrinsics = self.intrinsics(world, index);
        frame.extrinsics = self.extrinsics(world, index);
        frame.rgb.clear();
        frame.rgb.extend_from_slice(rgb);
        frame.depth.clear();
        let far = self.far;
        frame.depth.extend(depth.iter().map(|&d| if d >= far { 0.0 } else { d }));
        Ok(())
    }

    /// Draws camera `index` of `data` into the renderer's buffers.
    pub(crate) fn draw(
        &mut self,
        data: &mut mujoco_rs::prelude::MjData<Box<mujoco_rs::prelude::MjModel>>,
        index: usize,
    ) -> Result<(), SimError> {
        self.renderer.set_camera(MjvCamera::new_fixed(self.cameras[index].1));
        self.renderer.sync_data(data).map_err(|e| SimError::Render(e.to_string()))?;
        self.renderer.render().map_err(|e| SimError::Render(e.to_string()))
    }

    /// The RGB image of the last draw.
    pub(crate) fn last_rgb(&self) -> &[u8] {
        self.renderer.rgb_flat().unwrap_or_default()
    }

    /// Renders camera `index` of the world's current state.
    pub fn render(&mut self, world: &mut World, index: usize) -> Result<RgbdFrame, SimError> {
        let mut frame = RgbdFrame {
            camera: String::new(),
            intrinsics: self.intrinsics(world, index),
            extrinsics: Isometry3::identity(),
            rgb: Vec::new(),
            depth: Vec::new(),
        };
        self.render_into(world, index, &mut frame)?;
        Ok(frame)
    }
}
