//! The command line, end to end: `radiosity bake` on the sample scenes.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

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
        // The solve's iterations, frame by frame.
        let iterations = summary["iterations"].as_array().unwrap();
        assert_eq!(iterations.len(), frames, "{name}");
        assert!(
            iterations.iter().all(serde_json::Value::is_u64),
            "{name}: {iterations:?}"
        );
        // The Cornell box's small light is sampled as an area light; the parallel squares'
        // emitter covers half the scene and stays with the lines.
        let sampled: Vec<&str> = summary["area_lights"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| m[1].as_str().unwrap())
            .collect();
        let expected: &[&str] = if name == "cornell_moving" {
            &["light"]
        } else {
            &[]
        };
        assert_eq!(sampled, expected, "{name}");
    }
    assert!(!out.join("broken").exists());
    // Nothing half-written is left behind: no staging directory beside the outputs.
    let hidden: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(hidden.is_empty(), "{hidden:?}");
    baked_outputs_are_usable(&out.join("cornell_moving"));
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

/// The baked glTF files load with the gltf crate with a colour per vertex, the previews decode
/// and show something, the GIF has the timeline's frames.
fn baked_outputs_are_usable(dir: &Path) {
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("summary.json")).unwrap()).unwrap();
    let frames = summary["frames"].as_u64().unwrap() as usize;
    assert!(frames > 1);
    assert_eq!(summary["glb_frames"].as_array().unwrap().len(), frames);
    // The patch table: one entry per patch of radiance.bin, each with its named material.
    let table: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("patches.json")).unwrap()).unwrap();
    let patches = table["patches"].as_array().unwrap();
    assert_eq!(patches.len() as u64, summary["patches"].as_u64().unwrap());
    let materials = table["materials"].as_array().unwrap();
    for patch in patches {
        let m = &materials[patch["material"].as_u64().unwrap() as usize];
        assert!(m["name"].is_string(), "{m}");
    }
    for f in 0..frames {
        let bytes = std::fs::read(dir.join("baked").join(format!("frame_{f:04}.glb"))).unwrap();
        let gltf = gltf::Gltf::from_slice(&bytes).unwrap();
        let blob = gltf.blob.as_deref().unwrap();
        let mut triangles = 0;
        for mesh in gltf.meshes() {
            for primitive in mesh.primitives() {
                let reader = primitive.reader(|_| Some(blob));
                let vertices = reader.read_positions().unwrap().count();
                let colours = reader.read_colors(0).unwrap().into_rgb_f32().count();
                assert_eq!(colours, vertices);
                triangles += reader.read_indices().unwrap().into_u32().count() / 3;
            }
        }
        // One triangle per face of a traced triangle: one per patch at least (a merged patch
        // covers several).
        assert!(triangles >= summary["patches"].as_u64().unwrap() as usize);
    }
    let previews = summary["preview_frames"].as_array().unwrap();
    assert_eq!(previews.len(), 3, "first, middle and last by default");
    for f in previews {
        let name = format!("frame_{:04}.png", f.as_u64().unwrap());
        let image = image::open(dir.join("preview").join(name))
            .unwrap()
            .into_rgb8();
        assert_eq!(image.dimensions(), (640, 480));
        let background = *image.get_pixel(0, 0);
        let drawn = image.pixels().filter(|p| **p != background).count();
        assert!(drawn > 640 * 480 / 20, "only {drawn} pixels drawn");
        let mut distinct: Vec<[u8; 3]> = image.pixels().map(|p| p.0).collect();
        distinct.sort_unstable();
        distinct.dedup();
        assert!(
            distinct.len() > 20,
            "a flat image: {} colours",
            distinct.len()
        );
    }
    let gif = std::fs::read(dir.join("preview.gif")).unwrap();
    assert_eq!(&gif[..6], b"GIF89a");
    assert_eq!(
        summary["gif_frames"].as_array().unwrap().len(),
        frames,
        "a short timeline shows every frame"
    );
}

/// Every file under `dir` (relative path, bytes), sorted.
fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let bytes = std::fs::read(&path).unwrap();
                out.push((path.strip_prefix(dir).unwrap().to_path_buf(), bytes));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn outputs_are_byte_identical_whatever_the_thread_count() {
    let outputs: Vec<Vec<(PathBuf, Vec<u8>)>> = [1, 2]
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
                    "--preview-size",
                    "160x120",
                ])
                .output()
                .unwrap();
            assert!(
                output.status.success(),
                "{}",
                String::from_utf8_lossy(&output.stderr)
            );
            let mut result = files(&out.join("cornell_moving"));
            result.retain(|(name, _)| name != Path::new("timings.json"));
            let _ = std::fs::remove_dir_all(&out);
            result
        })
        .collect();
    let names: Vec<&PathBuf> = outputs[0].iter().map(|(n, _)| n).collect();
    assert!(names.len() > 10, "{names:?}");
    assert_eq!(names, outputs[1].iter().map(|(n, _)| n).collect::<Vec<_>>());
    for ((name, a), (_, b)) in outputs[0].iter().zip(&outputs[1]) {
        assert!(a == b, "{} differs between 1 and 2 threads", name.display());
    }
}

#[test]
fn bad_output_options_are_refused_before_baking() {
    for (flag, value) in [
        ("--preview-size", "0x10"),
        ("--preview-size", "640"),
        ("--preview-size", "99999x10"),
        ("--glb-frames", "5-2"),
        ("--preview-frames", "sometimes"),
        ("--exposure", "0"),
        ("--exposure", "-1"),
        ("--exposure", "inf"),
        ("--exposure", "bright"),
    ] {
        let output = radiosity()
            .args(["bake", "scenes", "--out", "/nonexistent", flag, value])
            .output()
            .unwrap();
        assert!(!output.status.success());
        let log = String::from_utf8_lossy(&output.stderr);
        assert!(log.contains(flag), "{flag} {value}: {log}");
    }
}

#[test]
fn bad_server_limits_are_refused_before_serving() {
    // A body limit whose byte count would wrap, and budgets that would refuse every job (NaN
    // compares false with every estimate) or none: refused with the flag named, not served.
    for (flag, value) in [
        ("--max-body-mib", "17592186044416"),
        ("--max-body-mib", "0"),
        ("--memory-budget-gib", "NaN"),
        ("--memory-budget-gib", "inf"),
        ("--memory-budget-gib", "0"),
    ] {
        let mut child = radiosity()
            .args(["serve", "--addr", "127.0.0.1:0", flag, value])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        // A server that took the value would run until killed: give it 10 s.
        let started = std::time::Instant::now();
        while child.try_wait().unwrap().is_none() {
            if started.elapsed() > std::time::Duration::from_secs(10) {
                child.kill().unwrap();
                panic!("{flag} {value}: the server started");
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        let output = child.wait_with_output().unwrap();
        assert!(!output.status.success(), "{flag} {value} served");
        let log = String::from_utf8_lossy(&output.stderr);
        assert!(log.contains(flag), "{flag} {value}: {log}");
    }
}

#[test]
fn the_server_log_to_a_pipe_has_no_colour_codes() {
    use std::io::BufRead;
    let data = scratch("log");
    let mut child = radiosity()
        .args(["serve", "--addr", "127.0.0.1:0", "--data-dir"])
        .arg(&data)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    let read = std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line);
    child.kill().unwrap();
    child.wait().unwrap();
    read.unwrap();
    assert!(line.contains("listening on"), "{line:?}");
    assert!(!line.contains('\u{1b}'), "{line:?}");
}

#[test]
fn ctrl_c_stops_a_bake_and_keeps_the_previous_outputs_whole() {
    let out = scratch("interrupt");
    let bake = |lines: &str| {
        let mut command = radiosity();
        command.args([
            "bake",
            sample("cornell_moving.gltf").to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--fps",
            "4",
            "--force",
            "--lines",
            lines,
        ]);
        command
    };
    assert!(bake("5000").output().unwrap().status.success());
    let before = files(&out.join("cornell_moving"));
    // A bake that would take minutes, interrupted while it traces.
    let child = bake("100000000")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1500));
    let killed = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let started = std::time::Instant::now();
    let output = child.wait_with_output().unwrap();
    assert!(
        started.elapsed() < std::time::Duration::from_secs(20),
        "Ctrl-C took {:?}",
        started.elapsed()
    );
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{log}");
    assert!(log.contains("interrupted"), "{log}");
    // The previous outputs are untouched, and nothing else is left.
    assert!(files(&out.join("cornell_moving")) == before);
    let names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, vec!["cornell_moving".to_string()]);
    let _ = std::fs::remove_dir_all(&out);
}

/// Regression (issue 11): `--start` after `--end` is refused by every subcommand that takes
/// them, before any work (a static scene was baked).
#[test]
fn start_after_end_is_refused_by_every_subcommand() {
    let out = scratch("span");
    let furnace = sample("furnace.gltf");
    let furnace = furnace.to_str().unwrap();
    let span = ["--start", "2", "--end", "1"];
    for command in [
        vec![
            "bake",
            furnace,
            "--out",
            out.to_str().unwrap(),
            "--lines",
            "2000",
        ],
        vec!["scene", furnace],
        vec!["bench", furnace, "--lines", "2000"],
    ] {
        let output = radiosity().args(&command).args(span).output().unwrap();
        let log = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{command:?}: {log}");
        assert!(
            log.contains("start") && log.contains("end") && log.contains("after"),
            "{command:?}: {log}"
        );
    }
    assert!(!out.join("furnace").exists());
    let _ = std::fs::remove_dir_all(&out);
}

/// Regression (issue 14): the command line checks a bake request by the service's rules, with
/// its messages (it took 0 lines, and a patch budget with any patch size).
#[test]
fn the_command_line_refuses_what_the_service_refuses() {
    let out = scratch("rules");
    let furnace = sample("furnace.gltf");
    let furnace = furnace.to_str().unwrap();
    for (args, needle) in [
        (
            vec!["--lines", "5"],
            "lines must be a whole number from 1000",
        ),
        (
            vec!["--lines", "0"],
            "lines must be a whole number from 1000",
        ),
        (
            vec!["--patch-size", "source", "--patch-budget", "9"],
            "patch_budget applies to patch_size=auto only",
        ),
        (
            vec!["--patch-budget", "0"],
            "patch_budget must be at least 1",
        ),
        (vec!["--fps", "2000"], "fps must be in (0, 1000]"),
        (vec!["--sky", "1,x,2,3"], "is not r,g,b"),
    ] {
        for command in [
            vec!["bake", furnace, "--out", out.to_str().unwrap()],
            vec!["scene", furnace],
        ] {
            let output = radiosity().args(&command).args(&args).output().unwrap();
            let log = String::from_utf8_lossy(&output.stderr);
            assert!(!output.status.success(), "{command:?} {args:?}: {log}");
            assert!(log.contains(needle), "{command:?} {args:?}: {log}");
        }
    }
    assert!(!out.join("furnace").exists());
    let _ = std::fs::remove_dir_all(&out);
}

/// `radiosity bake` of the two parallel squares (one frame) into `out` at 2,000 lines, without
/// GIF, forced, with `outputs` (the glb and preview frames) and then `extra`.
fn bake_squares(out: &Path, outputs: [&str; 2], extra: &[&str]) -> std::process::Output {
    let squares = sample("parallel_squares.gltf");
    radiosity()
        .args([
            "bake",
            squares.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .args(["--lines", "2000", "--no-gif", "--force"])
        .args(["--glb-frames", outputs[0], "--preview-frames", outputs[1]])
        .args(extra)
        .output()
        .unwrap()
}

/// Regression (issue 11): `--sky r,g,b` as the README documents (only `--sky 1 1 1` was read),
/// with the service's rule: exactly three finite numbers ≥ 0.
#[test]
fn the_sky_is_r_g_b_as_in_the_service() {
    let out = scratch("sky");
    let bake = |sky: &[&str]| bake_squares(&out, ["none", "none"], &[&["--sky"], sky].concat());
    let output = bake(&["1,0.5,0"]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let summary: serde_json::Value = serde_json::from_slice(
        &std::fs::read(out.join("parallel_squares").join("summary.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(summary["sky"], serde_json::json!([1.0, 0.5, 0.0]));
    // Refused, naming the value and the form; the old `--sky 1 1 1` too (its first value is
    // not r,g,b).
    for sky in [
        &["1,x,2,3"][..],
        &["1,2"],
        &["1,2,3,4"],
        &["1,-2,3"],
        &["1,inf,3"],
        &["1", "1", "1"],
    ] {
        let output = bake(sky);
        let log = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{sky:?}: {log}");
        assert!(
            log.contains(&format!("{:?}", sky[0])) && log.contains("r,g,b"),
            "{sky:?}: {log}"
        );
    }
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn reflectance_1_is_capped_in_the_summary_and_without_the_cap_the_bake_fails() {
    let dir = scratch("white");
    let out = dir.join("out");
    // The furnace reflecting everything (baseColorFactor 1, metallic 0), as glTF allows.
    let mut json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(sample("furnace.gltf")).unwrap()).unwrap();
    json["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"] =
        serde_json::json!([1.0, 1.0, 1.0, 1.0]);
    let input = dir.join("white.gltf");
    std::fs::write(&input, serde_json::to_vec(&json).unwrap()).unwrap();
    let bake = |extra: &[&str]| {
        radiosity()
            .arg("bake")
            .arg(&input)
            .arg("--out")
            .arg(&out)
            .args([
                "--lines",
                "5000",
                "--glb-frames",
                "none",
                "--preview-frames",
                "none",
            ])
            .args(extra)
            .output()
            .unwrap()
    };
    let capped = bake(&[]);
    assert!(
        capped.status.success(),
        "{}",
        String::from_utf8_lossy(&capped.stderr)
    );
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("white/summary.json")).unwrap()).unwrap();
    let warnings = summary["warnings"].to_string();
    assert!(
        warnings.contains("max_reflectance 0.999") && warnings.contains("furnace"),
        "{warnings}"
    );
    let before = std::fs::read(out.join("white/radiance.bin")).unwrap();
    // The first patch's radiance: Le / (1 − 0.999), to f32 rounding.
    let first = f32::from_le_bytes(before[24..28].try_into().unwrap());
    assert!((f64::from(first) / 1000.0 - 1.0).abs() < 1e-6, "{first}");
    // Without the cap: no steady state, the scene fails and its previous outputs stay.
    let uncapped = bake(&["--max-reflectance", "1", "--force"]);
    let log = String::from_utf8_lossy(&uncapped.stderr);
    assert!(!uncapped.status.success(), "{log}");
    assert!(
        log.contains("1 of 1 scenes failed") && log.contains("frame 0 did not converge"),
        "{log}"
    );
    assert_eq!(
        std::fs::read(out.join("white/radiance.bin")).unwrap(),
        before
    );
    let refused = bake(&["--max-reflectance", "0", "--force"]);
    let log = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success() && log.contains("max_reflectance must be in (0, 1]"),
        "{log}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Issue 11: a duplicated face was baked black without a word. The summary names the nodes
/// whose faces overlap.
#[test]
fn overlapping_faces_are_named_in_the_summary() {
    let dir = scratch("overlap");
    let mut doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(sample("parallel_squares.gltf")).unwrap()).unwrap();
    // A second receiver on the same mesh: node 2, coplanar with node 1 and overlapping it.
    doc["nodes"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"mesh": 1, "name": "receiver copy"}));
    doc["scenes"][0]["nodes"] = serde_json::json!([0, 1, 2]);
    let input = dir.join("doubled.gltf");
    std::fs::write(&input, serde_json::to_vec(&doc).unwrap()).unwrap();
    let out = dir.join("out");
    let output = radiosity()
        .args([
            "bake",
            input.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .args([
            "--lines",
            "20000",
            "--glb-frames",
            "none",
            "--preview-frames",
            "none",
        ])
        .arg("--no-gif")
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{log}");
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("doubled/summary.json")).unwrap()).unwrap();
    let warnings = summary["warnings"].as_array().unwrap();
    assert!(
        warnings.iter().any(|w| w.as_str().unwrap().starts_with(
            r#"node 1 ("receiver") and node 2 ("receiver copy") have faces that overlap"#
        )),
        "{warnings:?}"
    );
    assert_eq!(summary["unsampled_patches"], 0, "{summary}");
    assert!(
        log.contains(r#"warning: node 1 ("receiver") and node 2"#),
        "{log}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn frames_asked_past_the_end_are_named_not_dropped_silently() {
    let out = scratch("past_end");
    let output = bake_squares(&out, ["none", "0,99"], &[]);
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{log}");
    let said = "--preview-frames 0,99: the timeline has frame 0 only";
    assert!(log.contains(said), "{log}");
    let summary: serde_json::Value = serde_json::from_slice(
        &std::fs::read(out.join("parallel_squares").join("summary.json")).unwrap(),
    )
    .unwrap();
    let warnings = summary["warnings"].as_array().unwrap();
    assert!(
        warnings
            .iter()
            .any(|w| w.as_str().unwrap().starts_with(said)),
        "{summary}"
    );
}

#[test]
fn a_mistyped_option_gets_the_one_meant() {
    let squares = sample("parallel_squares.gltf");
    for (typed, meant) in [("--fsp", "--fps"), ("--linse", "--lines")] {
        let output = radiosity()
            .args(["bake", squares.to_str().unwrap(), typed, "5"])
            .output()
            .unwrap();
        let message = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(2), "{message}");
        let tip = format!("a similar argument exists: '{meant}'");
        assert!(message.contains(&tip), "{message}");
    }
}

#[test]
fn an_exposure_given_is_the_one_used() {
    let out = scratch("exposure");
    let bake = |exposure: &[&str]| {
        let output = bake_squares(&out, ["first", "none"], exposure);
        assert!(
            output.status.success(),
            "{}",
            String::from_utf8_lossy(&output.stderr)
        );
        let dir = out.join("parallel_squares");
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("summary.json")).unwrap()).unwrap();
        let glb = std::fs::read(dir.join("baked").join("frame_0000.glb")).unwrap();
        (summary["exposure"].as_f64().unwrap(), glb)
    };
    let (automatic, auto_glb) = bake(&[]);
    let (given, given_glb) = bake(&["--exposure", "3"]);
    assert_eq!(given, 3.0);
    assert_ne!(automatic, 3.0);
    // The vertex colours follow it.
    assert_ne!(auto_glb, given_glb);
}

/// `radiosity ARGS... OPTIONS` run to success, its stderr.
fn succeeds(args: &[&str], options: &[&str]) -> String {
    let output = radiosity().args(args).args(options).output().unwrap();
    let log = String::from_utf8_lossy(&output.stderr).to_string();
    assert!(output.status.success(), "{args:?}: {log}");
    log
}

/// `radiosity ARGS... OPTIONS` run to a failure, its stderr.
fn fails(args: &[&str], options: &[&str]) -> String {
    let output = radiosity().args(args).args(options).output().unwrap();
    let log = String::from_utf8_lossy(&output.stderr).to_string();
    assert!(!output.status.success(), "{args:?} succeeded: {log}");
    log
}

#[test]
fn a_bake_traced_in_parts_by_separate_processes_and_merged_is_the_single_bake() {
    let options = [
        "--lines",
        "30000",
        "--fps",
        "4",
        "--seed",
        "5",
        "--preview-size",
        "160x120",
    ];
    let scene = sample("cornell_moving.gltf");
    let scene = scene.to_str().unwrap();
    let single = scratch("shard-single");
    succeeds(
        &["bake", scene, "--out", single.to_str().unwrap()],
        &options,
    );
    let mut expected = files(&single.join("cornell_moving"));
    expected.retain(|(name, _)| name != Path::new("timings.json"));
    assert!(expected.len() > 10);
    for count in 1..=3 {
        let out = scratch(&format!("shard-{count}"));
        let out_str = out.to_str().unwrap();
        // The parts traced at once, as a cluster's machines trace them.
        let parts: Vec<_> = (0..count)
            .map(|k| {
                let shard = format!("{k}/{count}");
                radiosity()
                    .args(["bake", scene, "--shard", &shard, "--out", out_str])
                    .args(options)
                    .stderr(std::process::Stdio::piped())
                    .spawn()
                    .unwrap()
            })
            .collect();
        for part in parts {
            let output = part.wait_with_output().unwrap();
            let log = String::from_utf8_lossy(&output.stderr);
            assert!(output.status.success(), "{log}");
        }
        let dir = out.join("cornell_moving");
        // Given in reverse order.
        let parts: Vec<String> = (0..count)
            .rev()
            .map(|k| dir.join(format!("shard-{k}-of-{count}.part")))
            .map(|p| p.to_str().unwrap().to_string())
            .collect();
        let parts: Vec<&str> = parts.iter().map(String::as_str).collect();
        // The parts carry what the bake asks for; the outputs are the merge's to choose.
        let merge = [&["merge"], &parts[..], &["--out", out_str]].concat();
        succeeds(&merge, &["--preview-size", "160x120"]);
        let mut merged = files(&dir);
        merged.retain(|(name, _)| {
            name != Path::new("timings.json") && name.extension().is_none_or(|e| e != "part")
        });
        let names = |f: &[(PathBuf, Vec<u8>)]| f.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
        assert_eq!(names(&merged), names(&expected), "{count} parts");
        for ((name, a), (_, b)) in merged.iter().zip(&expected) {
            assert!(a == b, "{} differs with {count} parts", name.display());
        }
        // The parts are kept beside the outputs.
        assert!(Path::new(parts[0]).exists());
        let _ = std::fs::remove_dir_all(&out);
    }
    let _ = std::fs::remove_dir_all(&single);
}

#[test]
fn parts_of_another_scene_or_seed_or_a_part_missing_are_refused_by_name() {
    let out = scratch("shard-refused");
    let out_str = out.to_str().unwrap();
    let options = ["--lines", "5000", "--fps", "2"];
    let part = |scene: &str, shard: &str, extra: &[&str]| {
        let path = sample(scene);
        let args = [
            "bake",
            path.to_str().unwrap(),
            "--shard",
            shard,
            "--out",
            out_str,
        ];
        succeeds(&[&args[..], extra].concat(), &options);
    };
    part("cornell_moving.gltf", "0/2", &[]);
    part("cornell_moving.gltf", "1/2", &[]);
    part("cornell_box.gltf", "1/2", &[]);
    let path = |scene: &str, k: u32| {
        let file = out.join(scene).join(format!("shard-{k}-of-2.part"));
        file.to_str().unwrap().to_string()
    };
    let (moving, boxed) = (
        (path("cornell_moving", 0), path("cornell_moving", 1)),
        path("cornell_box", 1),
    );
    let merge = |parts: &[&str], extra: &[&str]| {
        let args = [&["merge"], parts, &["--out", out_str], extra].concat();
        fails(&args, &[])
    };
    let other_scene = merge(&[&moving.0, &boxed], &[]);
    assert!(
        other_scene.contains("parts of different bakes"),
        "{other_scene}"
    );
    let missing = merge(&[&moving.1], &[]);
    assert!(
        missing.contains("1/2") && missing.contains("every K"),
        "{missing}"
    );
    // What the bake asks for is the parts', not the merge's to change.
    let reseeded = merge(&[&moving.0, &moving.1], &["--seed", "2"]);
    assert!(
        reseeded.contains("unexpected argument '--seed'"),
        "{reseeded}"
    );
    // A part traced again with another seed, beside its sibling of the first seed.
    part("cornell_moving.gltf", "1/2", &["--seed", "2"]);
    let mixed = merge(&[&moving.0, &moving.1], &[]);
    assert!(mixed.contains("parts of different bakes"), "{mixed}");
    let wrong = fails(
        &[
            "bake",
            moving.0.as_str(),
            "--shard",
            "2/2",
            "--out",
            out_str,
        ],
        &[],
    );
    assert!(wrong.contains("\"2/2\" is not K/N"), "{wrong}");
    std::fs::write(&moving.1, b"not a part").unwrap();
    let damaged = merge(&[&moving.0, &moving.1], &[]);
    assert!(damaged.contains("not a part file"), "{damaged}");
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn a_directory_sharded_by_scene_bakes_each_scene_once() {
    let input = scratch("shard-scenes-in");
    let names = ["cornell_box", "cornell_moving", "parallel_squares"];
    for name in names {
        std::fs::copy(
            sample(&format!("{name}.gltf")),
            input.join(format!("{name}.gltf")),
        )
        .unwrap();
    }
    let out = scratch("shard-scenes-out");
    let mut baked = Vec::new();
    for k in 0..2 {
        let part = out.join(k.to_string());
        let shard = format!("{k}/2");
        let args = [
            "bake",
            input.to_str().unwrap(),
            "--shard",
            &shard,
            "--out",
            part.to_str().unwrap(),
        ];
        succeeds(&args, &["--lines", "5000", "--fps", "2"]);
        for entry in std::fs::read_dir(&part).unwrap() {
            baked.push((k, entry.unwrap().file_name().into_string().unwrap()));
        }
    }
    baked.sort_by(|a, b| a.1.cmp(&b.1));
    // Scene i (sorted) to part i mod 2.
    assert_eq!(
        baked,
        [
            (0, "cornell_box"),
            (1, "cornell_moving"),
            (0, "parallel_squares")
        ]
        .map(|(k, n)| (k, n.to_string()))
    );
    let _ = std::fs::remove_dir_all(&input);
    let _ = std::fs::remove_dir_all(&out);
}

/// `bake --probes` (issue 49): the probes' document (positions, convention, each frame's
/// state file), one file per lighting state with 27 coefficients and 18 irradiance error bars
/// per probe, frames that share their light sharing one file; a spacing that is not a positive
/// number, or that asks for too many probes, refused with a message naming it.
#[test]
fn bake_probes_writes_a_grid_and_one_file_per_lighting_state() {
    let out = scratch("probes");
    let level = sample("level.gltf");
    let bake = |extra: &[&str]| {
        radiosity()
            .args([
                "bake",
                level.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
            ])
            .args(["--lines", "20000", "--fps", "4", "--no-gif", "--force"])
            .args([
                "--glb-frames",
                "none",
                "--preview-frames",
                "none",
                "--probes",
            ])
            .args(extra)
            .output()
            .unwrap()
    };
    let output = bake(&[]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let dir = out.join("level").join("probes");
    let read = |name: &str| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(dir.join(name)).unwrap()).unwrap()
    };
    let grid = read("probes.json");
    let positions = grid["positions"].as_array().unwrap();
    let counts: Vec<u64> = (grid["counts"].as_array().unwrap().iter())
        .map(|c| c.as_u64().unwrap())
        .collect();
    assert!(!positions.is_empty());
    assert_eq!(
        positions.len() as u64 + grid["dropped_inside_geometry"].as_u64().unwrap(),
        counts.iter().product::<u64>()
    );
    assert_eq!(grid["convention"]["order"].as_array().unwrap().len(), 9);
    let frames = grid["frames"].as_array().unwrap();
    assert!(frames.len() > 2, "{frames:?}");
    let states: std::collections::BTreeSet<&str> = frames
        .iter()
        .map(|f| f["probes"].as_str().unwrap())
        .collect();
    let files = std::fs::read_dir(&dir).unwrap().count() - 1;
    assert_eq!(files, states.len(), "one file per lighting state");
    // The door opens and closes again: the frames on the way back share the way out's light.
    assert!(
        states.len() < frames.len(),
        "the frames that share their light share a file"
    );
    for state in &states {
        let probes = read(state);
        assert_eq!(probes["sh"].as_array().unwrap().len(), 27 * positions.len());
        assert_eq!(
            probes["stderr"].as_array().unwrap().len(),
            27 * positions.len()
        );
        let bars = probes["irradiance_stderr"].as_array().unwrap();
        assert_eq!(bars.len(), 18 * positions.len());
        // Every probe sees some light.
        let sh = probes["sh"].as_array().unwrap();
        assert!((0..positions.len()).all(|p| sh[27 * p].as_f64().unwrap() > 0.0));
    }
    // The door swings through probes: while it is there, they take their neighbours' light
    // (the check above), and the state's file lists them.
    let inside = |state: &&str| !read(state)["inside"].as_array().unwrap().is_empty();
    assert!(states.iter().any(inside), "no probe inside the door");
    for (spacing, needle) in [("0", "positive"), ("-1", "positive"), ("1e-4", "more than")] {
        let output = bake(&["--probe-spacing", spacing]);
        let log = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{spacing}: {log}");
        assert!(
            log.contains(needle) && log.contains("spacing"),
            "{spacing}: {log}"
        );
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// `bake --lightmaps --lightmap-quantity light`: one lightmap per lighting state, the manifest
/// mapping every frame to its state's files, and the geometry embedding the first state's
/// light for `MOZ_lightmap`, the same light as the state's KTX2 within the PNG's 8 bits.
#[test]
fn bake_lightmaps_writes_each_state_once_and_embeds_the_first_state_s_light() {
    let out = scratch("lightmaps");
    let scene = sample("cornell_moving.gltf");
    let output = radiosity()
        .args([
            "bake",
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .args(["--lines", "20000", "--fps", "4", "--no-gif", "--force"])
        .args(["--glb-frames", "none", "--preview-frames", "none"])
        .args(["--lightmaps", "--lightmap-quantity", "light"])
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let dir = out.join("cornell_moving").join("lightmaps");
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["quantity"], "light");
    let frames = manifest["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 9, "2 s at 4 fps");
    let mut states = std::collections::BTreeSet::new();
    for frame in frames {
        let state = frame["state"].as_u64().unwrap();
        assert!(state <= frame["frame"].as_u64().unwrap());
        states.insert(state);
        for kind in ["lightmap", "rgbm", "ktx2"] {
            assert!(dir.join(frame[kind].as_str().unwrap()).is_file(), "{frame}");
        }
    }
    let exrs = (std::fs::read_dir(&dir).unwrap())
        .filter(|e| e.as_ref().unwrap().path().extension() == Some("exr".as_ref()))
        .count();
    assert_eq!(exrs, states.len(), "one EXR per lighting state");

    let bytes = std::fs::read(dir.join("scene.glb")).unwrap();
    let gltf = gltf::Gltf::from_slice(&bytes).unwrap();
    let json: serde_json::Value = serde_json::from_str(
        &gltf
            .document
            .clone()
            .into_json()
            .to_string_pretty()
            .unwrap(),
    )
    .unwrap();
    assert!(
        (json["extensionsUsed"].as_array().unwrap()).contains(&"MOZ_lightmap".into()),
        "{}",
        json["extensionsUsed"]
    );
    let embedded = &json["scenes"][0]["extras"]["lightmap"]["embedded"];
    let scale = embedded["scale"].as_f64().unwrap() as f32;
    for material in json["materials"].as_array().unwrap() {
        let moz = &material["extensions"]["MOZ_lightmap"];
        assert_eq!((&moz["index"], &moz["texCoord"]), (&0.into(), &1.into()));
        let intensity = moz["intensity"].as_f64().unwrap();
        assert!((intensity - std::f64::consts::PI * f64::from(scale)).abs() < 1e-3 * intensity);
    }
    let view = gltf.images().next().unwrap();
    let gltf::image::Source::View { view, mime_type } = view.source() else {
        panic!("the lightmap is not embedded");
    };
    assert_eq!(mime_type, "image/png");
    let blob = gltf.blob.as_deref().unwrap();
    let png = &blob[view.offset()..view.offset() + view.length()];
    let png = image::load_from_memory(png).unwrap().to_rgb8();
    // State 0's light, as its KTX2 holds it.
    let ktx2 = std::fs::read(dir.join(frames[0]["ktx2"].as_str().unwrap())).unwrap();
    let reader = ktx2::Reader::new(&ktx2[..]).unwrap();
    let level = reader.levels().next().unwrap();
    let raw = zstd::bulk::decompress(level.data, level.uncompressed_byte_length as usize).unwrap();
    assert_eq!(raw.len(), 8 * png.pixels().len());
    let srgb = |linear: f32| {
        let c = linear.clamp(0.0, 1.0);
        let e = if c <= 0.003_130_8 {
            12.92 * c
        } else {
            1.055 * c.powf(1.0 / 2.4) - 0.055
        };
        e * 255.0
    };
    let mut lit = 0;
    for (k, pixel) in png.pixels().enumerate() {
        for c in 0..3 {
            let at = 8 * k + 2 * c;
            let light = common::half_float(u16::from_le_bytes([raw[at], raw[at + 1]]));
            let want = srgb(light / scale);
            // The half float's rounding, then the byte's.
            assert!(
                (f32::from(pixel[c]) - want).abs() <= 1.0,
                "texel {k}: {} for {want}",
                pixel[c]
            );
            lit += usize::from(pixel[c] > 16);
        }
    }
    assert!(lit > png.pixels().len() / 2, "{lit} lit channels");
    let _ = std::fs::remove_dir_all(&out);
}
