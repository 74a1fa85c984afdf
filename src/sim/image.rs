//! PNG encodings of rendered frames: 8-bit RGB, and depth as 16-bit grayscale millimetres
//! (0 = no depth; values clamp at 65.535 m), the convention of RGB-D datasets and Open3D; and
//! animated GIFs of recorded videos.
use super::camera::RgbdFrame;

/// The frame's RGB image as PNG bytes.
pub fn rgb_png(frame: &RgbdFrame) -> Result<Vec<u8>, png::EncodingError> {
    let k = &frame.intrinsics;
    encode(k.width, k.height, png::ColorType::Rgb, png::BitDepth::Eight, &frame.rgb)
}

/// The frame's depth as a 16-bit grayscale PNG in millimetres.
pub fn depth_png(frame: &RgbdFrame) -> Result<Vec<u8>, png::EncodingError> {
    let k = &frame.intrinsics;
    let bytes: Vec<u8> =
        frame.depth.iter().flat_map(|&d| ((d * 1000.0).round().clamp(0.0, 65535.0) as u16).to_be_bytes()).collect();
    encode(k.width, k.height, png::ColorType::Grayscale, png::BitDepth::Sixteen, &bytes)
}

fn encode(
    w: usize,
    h: usize,
    color: png::ColorType,
    depth: png::BitDepth,
    data: &[u8],
) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, w as u32, h as u32);
    encoder.set_color(color);
    encoder.set_depth(depth);
    encoder.write_header()?.write_image_data(data)?;
    Ok(out)
}

/// An animated GIF of a recorded video (loops forever).
pub fn video_gif(video: &super::Video) -> Result<Vec<u8>, gif::EncodingError> {
    let mut out = Vec::new();
    {
        let mut encoder = gif::Encoder::new(&mut out, video.width as u16, video.height as u16, &[])?;
        encoder.set_repeat(gif::Repeat::Infinite)?;
        let delay = (100.0 / video.fps).round().max(2.0) as u16; // hundredths of a second
        for rgb in &video.frames {
            let mut frame = gif::Frame::from_rgb_speed(video.width as u16, video.height as u16, rgb, 10);
            frame.delay = delay;
            encoder.write_frame(&frame)?;
        }
    }
    Ok(out)
}
