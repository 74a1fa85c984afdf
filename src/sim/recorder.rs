//! The video recorder: frames of one camera captured at a fixed rate of simulated time while the
//! [`World`] steps (for videos of episodes), handed back as a [`Video`] of RGB frames.
use super::{CameraRig, SimError, Visuals, World};

/// Frames of one camera captured while the world steps (for videos of episodes).
pub(super) struct Recorder {
    rig: CameraRig,
    camera: usize,
    period: f64,
    next: f64,
    frames: Vec<Vec<u8>>,
    error: Option<SimError>,
}

/// A recorded video: RGB frames (row 0 at the top) at a fixed rate.
#[derive(Debug, Clone, PartialEq)]
pub struct Video {
    pub width: usize,
    pub height: usize,
    pub fps: f64,
    pub frames: Vec<Vec<u8>>,
}

impl World {
    /// Starts capturing `camera` at `fps` frames per second of simulated time while stepping
    /// (square images of `size` pixels). Rendering costs a few ms per frame.
    pub fn start_recording(&mut self, camera: &str, size: usize, fps: f64) -> Result<(), SimError> {
        if !(fps > 0.0 && fps <= 1000.0) {
            return Err(SimError::InvalidInput {
                what: "video frame rate",
                detail: format!("{fps} fps; expected (0, 1000]"),
            });
        }
        let rig = CameraRig::new(self, size, Visuals::Full)?;
        let index = rig.camera_index(camera)?;
        self.recorder = Some(Recorder {
            rig,
            camera: index,
            period: 1.0 / fps,
            next: self.time(),
            frames: Vec::new(),
            error: None,
        });
        Ok(())
    }

    /// Stops capturing and returns the video, which ends on a frame of the world as it is now
    /// (what changed since the last step shows: a task's last event, e.g. push_buttons' ring
    /// turning lime after the press that ends a policy's episode).
    pub fn stop_recording(&mut self) -> Result<Option<Video>, SimError> {
        if let Some(r) = self.recorder.as_mut()
            && r.error.is_none()
        {
            match r.rig.draw(&mut self.data, r.camera) {
                Ok(()) => r.frames.push(r.rig.last_rgb().to_vec()),
                Err(e) => r.error = Some(e),
            }
        }
        let Some(r) = self.recorder.take() else { return Ok(None) };
        if let Some(e) = r.error {
            return Err(e);
        }
        let size = r.rig.size();
        Ok(Some(Video { width: size, height: size, fps: 1.0 / r.period, frames: r.frames }))
    }

    /// Captures a frame if recording and its time has come (called after every step). A
    /// rendering error stops the capture and is returned by [`World::stop_recording`].
    pub(super) fn capture_frame(&mut self) {
        if let Some(r) = self.recorder.as_mut()
            && r.error.is_none()
            && self.data.ffi().time >= r.next
        {
            r.next += r.period;
            match r.rig.draw(&mut self.data, r.camera) {
                Ok(()) => r.frames.push(r.rig.last_rgb().to_vec()),
                Err(e) => r.error = Some(e),
            }
        }
    }
}
