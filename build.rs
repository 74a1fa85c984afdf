//! Build script: finds the native dependencies installed by `scripts/setup.sh` and bakes
//! their location into the binaries (rpath for libmujoco, default asset folder), so nothing
//! needs `LD_LIBRARY_PATH` at run time.
use std::path::PathBuf;

fn main() {
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    println!("cargo::rerun-if-env-changed=FLOWRAM_DEPS");
    println!("cargo::rerun-if-env-changed=MUJOCO_DYNAMIC_LINK_DIR");
    println!("cargo::rerun-if-changed=build.rs");

    let deps = std::env::var_os("FLOWRAM_DEPS").map(PathBuf::from).unwrap_or_else(|| root.join(".deps"));
    let mujoco_lib = std::env::var_os("MUJOCO_DYNAMIC_LINK_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| deps.join("mujoco/lib"));
    if !mujoco_lib.join("libmujoco.so").is_file() {
        println!(
            "cargo::error=MuJoCo not found at {} (expected libmujoco.so there). \
             Run scripts/setup.sh first, or set MUJOCO_DYNAMIC_LINK_DIR to the folder holding libmujoco.so.",
            mujoco_lib.display()
        );
        return;
    }
    // rpath for every target of this package (lib tests, bin, integration tests).
    println!("cargo::rustc-link-arg=-Wl,-rpath,{}", mujoco_lib.display());
    println!("cargo::rustc-env=FLOWRAM_BUILD_DEPS_DIR={}", deps.display());
}
