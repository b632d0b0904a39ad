//! The Kubernetes manifests of `deploy/kubernetes/`: they parse, the Jobs run the project's
//! image on the shared volume with the completion index as the part, the trace and the merge
//! agree on the scene and the options, every Job's options are ones the command line takes,
//! and the Jobs' own commands, run here with the volume a directory, bake the scene (no
//! cluster needed: the local N-process test in `tests/cli.rs` proves the sharding itself).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use yaml_rust2::{Yaml, YamlLoader};

fn manifest(name: &str) -> Yaml {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("deploy/kubernetes")
        .join(name);
    let text = std::fs::read_to_string(&path).unwrap();
    let mut docs = YamlLoader::load_from_str(&text).unwrap();
    assert_eq!(docs.len(), 1, "{name}: one document");
    docs.remove(0)
}

fn text<'a>(yaml: &'a Yaml, what: &str) -> &'a str {
    yaml.as_str()
        .unwrap_or_else(|| panic!("{what} is not text: {yaml:?}"))
}

/// A Job's one container, its environment and its shell command, after checking what every
/// Job of the bake shares: the image, the volume's claim mounted at /bakes.
fn job(name: &str, claim: &str) -> (Yaml, HashMap<String, String>, String) {
    let job = manifest(name);
    assert_eq!(text(&job["apiVersion"], "apiVersion"), "batch/v1", "{name}");
    assert_eq!(text(&job["kind"], "kind"), "Job", "{name}");
    let pod = &job["spec"]["template"]["spec"];
    assert_eq!(text(&pod["restartPolicy"], "restartPolicy"), "Never");
    let containers = pod["containers"].as_vec().unwrap();
    assert_eq!(containers.len(), 1, "{name}");
    let container = &containers[0];
    let image = text(&container["image"], "image");
    assert!(image.contains("/radiosity:"), "{name}: image {image}");
    let volumes = pod["volumes"].as_vec().unwrap();
    let volume = &volumes[0];
    assert_eq!(
        text(&volume["persistentVolumeClaim"]["claimName"], "claim"),
        claim
    );
    let mounts = container["volumeMounts"].as_vec().unwrap();
    assert_eq!(mounts[0]["name"], volume["name"]);
    assert_eq!(text(&mounts[0]["mountPath"], "mountPath"), "/bakes");
    let env: HashMap<String, String> = (container["env"].as_vec().unwrap().iter())
        .map(|e| {
            (
                text(&e["name"], "name").into(),
                text(&e["value"], "value").into(),
            )
        })
        .collect();
    let command: Vec<&str> = (container["command"].as_vec().unwrap().iter())
        .map(|c| text(c, "command"))
        .collect();
    assert_eq!(command, ["sh", "-c"], "{name}");
    let args = container["args"].as_vec().unwrap();
    assert_eq!(args.len(), 1, "{name}");
    let script = text(&args[0], "args").to_string();
    (job, env, script)
}

/// The part count of an Indexed Job: its completions, which its SHARDS must equal, the
/// index its command's part.
fn indexed(name: &str, job: &Yaml, env: &HashMap<String, String>, script: &str) -> u32 {
    let spec = &job["spec"];
    assert_eq!(text(&spec["completionMode"], "completionMode"), "Indexed");
    let completions = spec["completions"].as_i64().unwrap();
    assert!(spec["parallelism"].as_i64().unwrap() <= completions);
    assert_eq!(env["SHARDS"], completions.to_string(), "{name}");
    assert!(
        script.contains("--shard \"$JOB_COMPLETION_INDEX/$SHARDS\""),
        "{name}: {script}"
    );
    completions as u32
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("radiosity-deploy-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs a Job's `script` as its pod would, with the volume at `volume`, `env` (OPTIONS made
/// small, so that the bake is quick) and `index` as the completion index.
fn run(script: &str, volume: &Path, env: &HashMap<String, String>, index: Option<u32>) {
    let binary = Path::new(env!("CARGO_BIN_EXE_radiosity"));
    let path = format!(
        "{}:{}",
        binary.parent().unwrap().display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let volume = volume.to_str().unwrap();
    let mut command = Command::new("sh");
    command
        .arg("-c")
        .arg(script.replace("/bakes", volume))
        .env("PATH", path);
    for (name, value) in env {
        command.env(name, value.replace("/bakes", volume));
    }
    command.env("OPTIONS", "--lines 20000 --fps 2 --preview-size 64x48");
    if let Some(index) = index {
        command.env("JOB_COMPLETION_INDEX", index.to_string());
    }
    let output = command.output().unwrap();
    assert!(
        output.status.success(),
        "{script}: {}",
        String::from_utf8_lossy(&output.stderr)
    );
}

/// `radiosity COMMAND... FILE OPTIONS` (`scene` validates options as `bake` does); its
/// stderr, asserting it succeeded when the command is `scene`.
fn options_are_taken(command: &[&str], options: &str, file: &Path) -> String {
    let output = Command::new(env!("CARGO_BIN_EXE_radiosity"))
        .args(command)
        .arg(file)
        .args(options.split_whitespace())
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&output.stderr).to_string();
    if command == ["scene"] {
        assert!(output.status.success(), "{options}: {log}");
    }
    log
}

#[test]
fn the_manifests_bake_a_scene_in_parts_and_many_scenes_by_index() {
    let volume = manifest("volume.yaml");
    assert_eq!(text(&volume["kind"], "kind"), "PersistentVolumeClaim");
    let modes = volume["spec"]["accessModes"].as_vec().unwrap();
    assert!(modes.iter().any(|m| m.as_str() == Some("ReadWriteMany")));
    let claim = text(&volume["metadata"]["name"], "claim");

    let (trace, trace_env, trace_script) = job("trace-job.yaml", claim);
    let parts = indexed("trace-job.yaml", &trace, &trace_env, &trace_script);
    let (_, merge_env, merge_script) = job("merge-job.yaml", claim);
    let (scenes, scenes_env, scenes_script) = job("scenes-job.yaml", claim);
    indexed("scenes-job.yaml", &scenes, &scenes_env, &scenes_script);
    // The merge takes the trace's scene (and its options, from the parts).
    let scene = PathBuf::from(&trace_env["SCENE"]);
    assert!(scene.starts_with("/bakes/scenes"), "{}", scene.display());
    assert_eq!(
        scene.file_stem().unwrap().to_str().unwrap(),
        merge_env["SCENE_NAME"]
    );
    assert!(trace_script.contains("--out /bakes/parts"));
    assert!(merge_script.contains("merge /bakes/parts/\"$SCENE_NAME\"/shard-*.part"));
    assert!(merge_script.contains("--out /bakes/out $OUTPUTS"));

    // The Jobs' commands, on a directory for the volume and the sample level as the scene.
    let dir = scratch("volume");
    let scenes_dir = dir.join("scenes");
    std::fs::create_dir_all(&scenes_dir).unwrap();
    let level = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/level.gltf");
    let placed = scenes_dir.join(scene.file_name().unwrap());
    std::fs::copy(&level, &placed).unwrap();
    for options in [&trace_env["OPTIONS"], &scenes_env["OPTIONS"]] {
        options_are_taken(&["scene"], options, &placed);
    }
    // (`merge` with a scene for a part refuses it once its options are taken.)
    let outputs = options_are_taken(&["merge", "--out", "x"], &merge_env["OUTPUTS"], &placed);
    assert!(outputs.contains("not a part file"), "{outputs}");
    for k in 0..parts {
        run(&trace_script, &dir, &trace_env, Some(k));
    }
    let name = &merge_env["SCENE_NAME"];
    for k in 0..parts {
        assert!(
            dir.join(format!("parts/{name}/shard-{k}-of-{parts}.part"))
                .exists()
        );
    }
    run(&merge_script, &dir, &merge_env, None);
    assert!(dir.join("out").join(name).join("radiance.bin").exists());

    // Many scenes, each on the pod of its index.
    std::fs::remove_dir_all(dir.join("out")).unwrap();
    let box_scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/cornell_box.gltf");
    std::fs::copy(box_scene, scenes_dir.join("cornell_box.gltf")).unwrap();
    for k in [0, 1] {
        run(&scenes_script, &dir, &scenes_env, Some(k));
    }
    for scene in ["cornell_box", name] {
        assert!(
            dir.join("out").join(scene).join("radiance.bin").exists(),
            "{scene}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
