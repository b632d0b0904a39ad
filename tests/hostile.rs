//! Truncated, bit-flipped and malformed files: the loader returns an error or a scene, never
//! panics, and never takes unbounded time or memory.

#[allow(dead_code)] // the helpers serve several test binaries; this one uses a part
mod common;

use common::{Doc, QUAD, QUAD_INDICES};
use radiosity::loader::{LoadOptions, load};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use serde_json::json;

/// Seed files covering the loader's paths: GLB and JSON containers, animation of every kind,
/// skins, morph targets, textures, sparse accessors.
fn corpus() -> Vec<(String, Vec<u8>)> {
    let mut files = Vec::new();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    for name in ["SimpleMorph.gltf", "SimpleSkin.gltf"] {
        let bytes = std::fs::read(dir.join("../shared/gltf-samples").join(name)).unwrap();
        files.push((name.to_string(), bytes));
    }
    for entry in std::fs::read_dir(dir.join("scenes")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "gltf" || e == "glb") {
            let name = path.file_name().unwrap().to_string_lossy().into_owned();
            files.push((name, std::fs::read(&path).unwrap()));
        }
    }
    let mut d = Doc::new();
    let png = {
        let img = image::RgbImage::from_pixel(2, 2, image::Rgb([200, 100, 50]));
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).unwrap();
        out.into_inner()
    };
    let offset = d.bin.len();
    d.bin.extend_from_slice(&png);
    let view = d.push(
        "bufferViews",
        json!({"buffer": 0, "byteOffset": offset, "byteLength": png.len()}),
    );
    let image = d.push(
        "images",
        json!({"bufferView": view, "mimeType": "image/png"}),
    );
    let texture = d.push("textures", json!({"source": image}));
    let material = d.push(
        "materials",
        json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": texture}}, "emissiveFactor": [1, 1, 1],
               "emissiveTexture": {"index": texture}, "doubleSided": true}),
    );
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), Some(material));
    // A sparse accessor: zeros with one replaced element.
    let idx = d.indices(&[2], 5125);
    let vals = d.floats(&[0.0, 0.0, 1.0], "VEC3");
    let idx_view = d.json["accessors"][idx]["bufferView"].clone();
    let val_view = d.json["accessors"][vals]["bufferView"].clone();
    let sparse = d.push(
        "accessors",
        json!({"componentType": 5126, "count": 4, "type": "VEC3", "min": [0,0,0], "max": [0,0,1],
               "sparse": {"count": 1, "indices": {"bufferView": idx_view, "componentType": 5125},
                          "values": {"bufferView": val_view}}}),
    );
    d.json["meshes"][mesh]["primitives"][0]["targets"] = json!([{"POSITION": sparse}]);
    d.json["meshes"][mesh]["weights"] = json!([0.5]);
    let a = d.node(json!({"mesh": mesh}));
    let b = d.node(json!({"mesh": mesh, "matrix": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,3,1]}));
    let c = d.node(json!({"children": [a]}));
    d.scene(&[c, b]);
    d.animation(
        "all",
        &[
            (
                c,
                "translation",
                &[0.0, 1.0],
                &[0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
                "STEP",
            ),
            (
                c,
                "rotation",
                &[0.0, 1.0],
                &[0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0],
                "LINEAR",
            ),
            (
                c,
                "scale",
                &[0.0, 1.0],
                &[
                    0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0,
                    1.0, 1.0,
                ],
                "CUBICSPLINE",
            ),
            (a, "weights", &[0.0, 1.0], &[0.0, 1.0], "LINEAR"),
        ],
    );
    files.push(("built.glb".into(), d.glb()));
    files.push(("built.gltf".into(), d.gltf()));
    files
}

/// Mutations per corpus file; `HOSTILE_ROUNDS=20000 cargo test --release --test hostile` runs a
/// deeper search than CI does.
fn rounds(default: usize) -> usize {
    std::env::var("HOSTILE_ROUNDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Seed of the mutations (`HOSTILE_SEED` overrides it for a deeper search).
fn seed(default: u64) -> u64 {
    std::env::var("HOSTILE_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Options small enough that no mutation can make a test slow.
fn options() -> LoadOptions {
    LoadOptions {
        max_frames: 2_000,
        max_patches: 200_000,
        max_work: 5_000_000,
        ..LoadOptions::default()
    }
}

#[test]
fn the_corpus_itself_loads() {
    for (name, bytes) in corpus() {
        if let Err(e) = load(&bytes, &options()) {
            panic!("{name}: {e}");
        }
    }
}

#[test]
fn every_truncation_is_an_error_not_a_panic() {
    for (name, bytes) in corpus() {
        let step = (bytes.len() / 300).max(1);
        for len in (0..bytes.len()).step_by(step) {
            // Any prefix is incomplete JSON or a GLB with chunks cut short.
            assert!(
                load(&bytes[..len], &options()).is_err(),
                "{name} cut at {len} loaded"
            );
        }
    }
}

#[test]
fn bit_flips_and_byte_stomps_never_panic() {
    let mut rng = StdRng::seed_from_u64(seed(0x5eed));
    let interesting: [u8; 8] = [0, 0xff, 0x7f, 0x80, b'9', b'-', b'"', b'e'];
    let (mut ok, mut refused) = (0, 0);
    for (name, bytes) in corpus() {
        for round in 0..rounds(400) {
            let mut b = bytes.clone();
            for _ in 0..rng.random_range(1..=4) {
                let at = rng.random_range(0..b.len());
                if rng.random_bool(0.5) {
                    b[at] ^= 1 << rng.random_range(0..8);
                } else {
                    b[at] = interesting[rng.random_range(0..interesting.len())];
                }
            }
            match std::panic::catch_unwind(|| load(&b, &options())) {
                Ok(Ok(_)) => ok += 1,
                Ok(Err(_)) => refused += 1,
                Err(_) => panic!("{name} round {round}: the loader panicked"),
            }
        }
    }
    // Both outcomes occur: the mutations reach past the JSON parser.
    assert!(ok > 50 && refused > 100, "{ok} loaded, {refused} refused");
}

/// Replaces numbers in the JSON with extreme values: counts, offsets, indices, times, factors.
#[test]
fn extreme_numbers_in_the_json_never_panic() {
    let mut rng = StdRng::seed_from_u64(seed(42));
    let extremes = [
        "-1",
        "0",
        "1e308",
        "-1e308",
        "4294967295",
        "18446744073709551615",
        "2147483648",
        "3.5",
        "1e-320",
        "65535",
        "256",
    ];
    for (name, bytes) in corpus() {
        let Ok(text) = std::str::from_utf8(&bytes) else {
            continue;
        };
        // Byte ranges of the numbers outside strings.
        let mut numbers = Vec::new();
        let (mut in_string, mut start) = (false, None);
        for (i, c) in text.char_indices() {
            if c == '"' {
                in_string = !in_string;
            }
            let numeric = !in_string
                && (c.is_ascii_digit() || c == '-' || c == '.' || c == 'e' || c == 'E' || c == '+');
            match (numeric, start) {
                (true, None) => start = Some(i),
                (false, Some(s)) => {
                    numbers.push(s..i);
                    start = None;
                }
                _ => {}
            }
        }
        for round in 0..rounds(300) {
            let range = numbers[rng.random_range(0..numbers.len())].clone();
            let value = extremes[rng.random_range(0..extremes.len())];
            let mutated = format!("{}{}{}", &text[..range.start], value, &text[range.end..]);
            let result = std::panic::catch_unwind(|| load(mutated.as_bytes(), &options()));
            assert!(
                result.is_ok(),
                "{name} round {round}: the loader panicked with {value} at {range:?}"
            );
        }
    }
}

#[test]
fn hostile_sizes_are_refused_before_allocation() {
    // A huge count on an accessor without a buffer view.
    let mut d = Doc::new();
    let mesh = d.mesh(&QUAD, Some(&QUAD_INDICES), None);
    let view = d.json["accessors"][1]["bufferView"].clone();
    d.json["accessors"][0] = json!({"componentType": 5126, "count": 4_000_000_000u64, "type": "VEC3",
        "min": [0, 0, 0], "max": [1, 1, 0], "sparse": {"count": 1,
        "indices": {"bufferView": view, "componentType": 5123}, "values": {"bufferView": view}}});
    let n = d.node(json!({"mesh": mesh}));
    d.scene(&[n]);
    let e = load(&d.gltf(), &options()).err().unwrap().to_string();
    assert!(e.contains("accessor 0") && e.contains("limit"), "{e}");
    // A long animation of a deforming mesh at a high frame rate exceeds the work budget.
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/gltf-samples");
    let skin = std::fs::read(dir.join("SimpleSkin.gltf")).unwrap();
    let many = LoadOptions {
        fps: 300.0,
        max_work: 10_000,
        ..options()
    };
    let e = load(&skin, &many).err().unwrap().to_string();
    assert!(e.contains("budget"), "{e}");
}
