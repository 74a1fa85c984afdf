//! `flowram render`: writes what each camera sees, for a person (PNG) and for point-cloud tools
//! (PLY), plus each camera's model (camera.json).
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use flowram::files::write_atomic;
use flowram::sim::{CameraRig, PointCloud, RgbdFrame, Visuals, Workspace, World, image};
use serde::Serialize;

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// Scene name in models/ (`default` = models/scene.xml) or a path to a scene MJCF.
    #[arg(long, default_value = "default")]
    scene: String,
    /// Camera name, or `all`.
    #[arg(long, default_value = "all")]
    camera: String,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = flowram::sim::camera::DEFAULT_IMAGE_SIZE)]
    size: usize,
    /// Output folder; DIR/<camera>/{rgb.png, depth.png, cloud.ply, camera.json} are written.
    #[arg(long)]
    out: PathBuf,
    /// Arm meshes: full visual meshes, or convex hulls (faster on a software renderer).
    #[arg(long, value_enum, default_value_t = super::VisualsArg::Full)]
    visuals: super::VisualsArg,
    /// Keep only cloud points inside the table workspace box.
    #[arg(long)]
    crop: bool,
    /// Print one JSON object (files written, seconds) instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Serialize)]
struct RenderReport {
    scene: String,
    size: usize,
    visuals: Visuals,
    cameras: Vec<String>,
    files: Vec<PathBuf>,
    points: usize,
    seconds: f64,
}

/// Camera model as written to camera.json.
#[derive(Serialize)]
struct CameraJson<'a> {
    camera: &'a str,
    width: usize,
    height: usize,
    /// 3x3 row-major pinhole matrix, pixel centres at integer coordinates.
    intrinsics: [[f64; 3]; 3],
    /// 4x4 row-major camera-to-world transform, OpenCV axes (x right, y down, z forward).
    extrinsics: [[f64; 4]; 4],
    depth_png_unit: &'static str,
}

pub fn run(args: RenderArgs) -> anyhow::Result<()> {
    let start = Instant::now();
    let mut world = World::load_named(&args.scene)?;
    let mut rig = CameraRig::new(&world, args.size, args.visuals.into())?;
    let indices: Vec<usize> = if args.camera == "all" {
        (0..rig.camera_names().count()).collect()
    } else {
        vec![rig.camera_index(&args.camera)?]
    };
    let crop = args.crop.then_some(Workspace::TABLE);
    let mut files = Vec::new();
    let mut merged = PointCloud::default();
    let mut cameras = Vec::new();
    for index in indices {
        let frame = rig.render(&mut world, index)?;
        let cloud = PointCloud::from_frame(&frame, crop.as_ref());
        files.extend(write_camera(&args.out.join(&frame.camera), &frame, &cloud)?);
        merged.extend_from_frame(&frame, crop.as_ref());
        cameras.push(frame.camera);
    }
    if cameras.len() > 1 {
        let path = args.out.join("merged.ply");
        write_atomic(&path, &merged.to_ply()).with_context(|| format!("writing {}", path.display()))?;
        files.push(path);
    }
    let report = RenderReport {
        scene: world.scene_path().display().to_string(),
        size: args.size,
        visuals: args.visuals.into(),
        cameras,
        files,
        points: merged.len(),
        seconds: start.elapsed().as_secs_f64(),
    };
    if args.json {
        super::print_json(&report)?;
    } else {
        for f in &report.files {
            println!("wrote {}", f.display());
        }
        println!("{} cameras, {} points, {:.2} s", report.cameras.len(), report.points, report.seconds);
    }
    Ok(())
}

fn write_camera(dir: &Path, frame: &RgbdFrame, cloud: &PointCloud) -> anyhow::Result<Vec<PathBuf>> {
    let k = frame.intrinsics.matrix();
    let t = frame.extrinsics.to_homogeneous();
    let camera = CameraJson {
        camera: &frame.camera,
        width: frame.intrinsics.width,
        height: frame.intrinsics.height,
        intrinsics: std::array::from_fn(|r| std::array::from_fn(|c| k[(r, c)])),
        extrinsics: std::array::from_fn(|r| std::array::from_fn(|c| t[(r, c)])),
        depth_png_unit: "millimetre (u16, 0 = no depth)",
    };
    let outputs = [
        ("rgb.png", image::rgb_png(frame)?),
        ("depth.png", image::depth_png(frame)?),
        ("cloud.ply", cloud.to_ply()),
        ("camera.json", serde_json::to_vec_pretty(&camera)?),
    ];
    let mut written = Vec::new();
    for (name, bytes) in outputs {
        let path = dir.join(name);
        write_atomic(&path, &bytes).with_context(|| format!("writing {}", path.display()))?;
        written.push(path);
    }
    Ok(written)
}
