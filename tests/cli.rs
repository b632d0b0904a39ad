//! The command line, end to end: `radiosity bake` on the sample scenes.

use std::path::{Path, PathBuf};
use std::process::Command;

fn radiosity() -> Command {
    Command::new(env!("CARGO_BIN_EXE_radiosity"))
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("radiosity-cli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn sample(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name)
}

#[test]
fn a_directory_bakes_skips_when_unchanged_and_survives_a_broken_scene() {
    let input = scratch("input");
    let out = scratch("out");
    for name in ["cornell_moving.gltf", "parallel_squares.gltf"] {
        std::fs::copy(sample(name), input.join(name)).unwrap();
    }
    std::fs::write(input.join("broken.gltf"), b"{\"asset\": {\"version\": \"2.0\"}, \"buffers\": [{\"uri\": \"/etc/passwd\", \"byteLength\": 4}]}").unwrap();
    let run = || {
        radiosity()
            .args([
                "bake",
                input.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--lines",
                "5000",
                "--fps",
                "2",
            ])
            .output()
            .unwrap()
    };
    let first = run();
    let log = String::from_utf8_lossy(&first.stderr).to_string();
    assert!(!first.status.success(), "{log}");
    assert!(
        log.contains("1 of 3 scenes failed")
            && log.contains("broken.gltf")
            && log.contains("external URI"),
        "{log}"
    );
    for name in ["cornell_moving", "parallel_squares"] {
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join(name).join("summary.json")).unwrap())
                .unwrap();
        let frames = summary["frames"].as_u64().unwrap() as usize;
        let patches = summary["patches"].as_u64().unwrap() as usize;
        let bin = std::fs::read(out.join(name).join("radiance.bin")).unwrap();
        assert_eq!(&bin[..4], b"RADB");
        assert_eq!(bin.len(), 16 + frames * (8 + patches * 28), "{name}");
        assert!(summary["converged"].as_bool().unwrap());
    }
    assert!(!out.join("broken").exists());
    // Nothing half-written is left behind.
    let partial = std::fs::read_dir(out.join("cornell_moving"))
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "partial")
        })
        .count();
    assert_eq!(partial, 0);
    // Unchanged: skipped. Forced, or with other parameters: baked again.
    let again = run();
    let log = String::from_utf8_lossy(&again.stderr).to_string();
    assert_eq!(log.matches("up to date").count(), 2, "{log}");
    let forced = radiosity()
        .args([
            "bake",
            input.join("parallel_squares.gltf").to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--lines",
            "5000",
            "--fps",
            "2",
            "--force",
        ])
        .output()
        .unwrap();
    assert!(forced.status.success());
    assert!(String::from_utf8_lossy(&forced.stderr).contains("baked"));
    let _ = std::fs::remove_dir_all(&input);
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn outputs_are_byte_identical_whatever_the_thread_count() {
    let outputs: Vec<(Vec<u8>, Vec<u8>)> = [1, 2]
        .iter()
        .map(|threads| {
            let out = scratch(&format!("threads{threads}"));
            let output = radiosity()
                .env("RAYON_NUM_THREADS", threads.to_string())
                .args([
                    "bake",
                    sample("cornell_moving.gltf").to_str().unwrap(),
                    "--out",
                    out.to_str().unwrap(),
                    "--lines",
                    "20000",
                    "--fps",
                    "4",
                    "--seed",
                    "9",
                ])
                .output()
                .unwrap();
            assert!(
                output.status.success(),
                "{}",
                String::from_utf8_lossy(&output.stderr)
            );
            let dir = out.join("cornell_moving");
            let result = (
                std::fs::read(dir.join("radiance.bin")).unwrap(),
                std::fs::read(dir.join("summary.json")).unwrap(),
            );
            let _ = std::fs::remove_dir_all(&out);
            result
        })
        .collect();
    assert!(
        outputs[0].0 == outputs[1].0,
        "radiance.bin differs between 1 and 2 threads"
    );
    assert_eq!(outputs[0].1, outputs[1].1);
}
