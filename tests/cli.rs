//! The CLI writes what it says, in the documented formats.
mod common;

use std::io::Read;

fn decode_png(path: &std::path::Path) -> (png::OutputInfo, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info, buf)
}

#[test]
fn render_writes_images_clouds_and_camera_models() {
    let dir = tempfile::tempdir().unwrap();
    let out = common::flowram().args(["render", "--size", "64", "--json", "--out"]).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).expect("--json prints one JSON object");
    assert_eq!(report["cameras"].as_array().unwrap().len(), 4);
    assert!(report["seconds"].as_f64().unwrap() > 0.0);
    let files: Vec<String> = report["files"].as_array().unwrap().iter().map(|f| f.as_str().unwrap().to_owned()).collect();
    assert_eq!(files.len(), 4 * 4 + 1, "4 files per camera + merged.ply");

    for camera in ["front", "left_shoulder", "right_shoulder", "wrist"] {
        let cam_dir = dir.path().join(camera);
        let (info, rgb) = decode_png(&cam_dir.join("rgb.png"));
        assert_eq!((info.width, info.height, info.color_type, info.bit_depth), (64, 64, png::ColorType::Rgb, png::BitDepth::Eight));
        assert!(rgb.iter().any(|&c| c != rgb[0]));
        let (info, depth) = decode_png(&cam_dir.join("depth.png"));
        assert_eq!((info.color_type, info.bit_depth), (png::ColorType::Grayscale, png::BitDepth::Sixteen));
        let mm: Vec<u16> = depth.chunks(2).map(|b| u16::from_be_bytes([b[0], b[1]])).collect();
        let valid: Vec<u16> = mm.iter().copied().filter(|&d| d > 0).collect();
        assert!(valid.len() > 64 * 64 / 2, "{camera}: most pixels have depth");
        assert!(valid.iter().all(|&d| (50..5000).contains(&d)), "{camera}: depths in millimetres of a table scene");

        let mut ply = Vec::new();
        std::fs::File::open(cam_dir.join("cloud.ply")).unwrap().read_to_end(&mut ply).unwrap();
        let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let header = std::str::from_utf8(&ply[..header_end]).unwrap();
        let n: usize = header.lines().find_map(|l| l.strip_prefix("element vertex ")).unwrap().parse().unwrap();
        assert_eq!(n, valid.len(), "{camera}: one point per pixel with depth");
        assert_eq!(ply.len() - header_end, n * 15, "{camera}: 3 floats + 3 bytes per point");

        let model: serde_json::Value = serde_json::from_slice(&std::fs::read(cam_dir.join("camera.json")).unwrap()).unwrap();
        assert_eq!(model["intrinsics"][0][2].as_f64(), Some(31.5));
        assert_eq!(model["extrinsics"][3][3].as_f64(), Some(1.0));
    }
}

#[test]
fn benchmarks_print_their_figures_as_json() {
    let out = common::flowram().args(["bench", "sim", "--steps", "500", "--repeats", "1", "--json"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let sim: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(sim["steps_per_s"].as_f64().unwrap() > 0.0);
    assert!(sim["realtime_factor"].as_f64().unwrap() > 0.0);

    let out = common::flowram().args(["bench", "render", "--frames", "3", "--repeats", "1", "--size", "32", "--json"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let render: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(render["size"].as_u64(), Some(32));
    assert_eq!(render["cameras"].as_u64(), Some(1));
    assert!(render["frames_per_s"].as_f64().unwrap() > 0.0);
}
