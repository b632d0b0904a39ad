//! The HTTP service over a real socket (127.0.0.1:0) with a real HTTP client.

use std::time::{Duration, Instant};

use radiosity::service::{AppState, Config, serve};
use serde_json::Value;

/// A server on an ephemeral port; stops when the test's runtime ends.
async fn start(config: Config) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(serve(
        listener,
        AppState::new(config).unwrap(),
        std::future::pending(),
    ));
    format!("http://{addr}")
}

/// GETs a JSON document.
async fn get_json(client: &reqwest::Client, url: String) -> Value {
    client.get(url).send().await.unwrap().json().await.unwrap()
}

fn scene(name: &str) -> Vec<u8> {
    std::fs::read(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scenes")
            .join(name),
    )
    .unwrap()
}

async fn post(
    client: &reqwest::Client,
    base: &str,
    query: &str,
    content_type: &str,
    body: Vec<u8>,
) -> reqwest::Response {
    client
        .post(format!("{base}/v1/timelines?{query}"))
        .header("content-type", content_type)
        .body(body)
        .send()
        .await
        .unwrap()
}

/// POSTs headers that declare a body of `declared` bytes and sends none of it, then reads the
/// answer on a raw socket: status, head and body. (A real client streaming the body would race
/// the server's early close and could see a broken pipe instead of the 413; here the server
/// must answer from the declared length alone, or the read times out.)
async fn declare_oversize_body(base: &str, declared: usize) -> (u16, String, String) {
    let addr = base.trim_start_matches("http://").to_string();
    tokio::task::spawn_blocking(move || {
        use std::io::{Read, Write};
        let mut stream = std::net::TcpStream::connect(&addr).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
        write!(
            stream,
            "POST /v1/timelines HTTP/1.1\r\nhost: {addr}\r\n\
             content-type: model/gltf+json\r\ncontent-length: {declared}\r\n\
             connection: close\r\n\r\n"
        )
        .unwrap();
        let mut answer = Vec::new();
        stream.read_to_end(&mut answer).unwrap();
        let answer = String::from_utf8(answer).unwrap();
        let (head, body) = answer.split_once("\r\n\r\n").unwrap();
        let status = head.split(' ').nth(1).unwrap().parse().unwrap();
        (status, head.to_string(), body.to_string())
    })
    .await
    .unwrap()
}

/// The red channel of a frame document's radiance, per patch.
fn radiance(frame: Value) -> Vec<f64> {
    frame["radiance"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l[0].as_f64().unwrap())
        .collect()
}

/// POSTs a relighting (`/materials`) body to a timeline.
async fn relight(
    client: &reqwest::Client,
    base: &str,
    id: &str,
    body: &Value,
) -> reqwest::Response {
    client
        .post(format!("{base}/v1/timelines/{id}/materials"))
        .json(body)
        .send()
        .await
        .unwrap()
}

/// How long a job may take before a test calls it hung: a guard against hangs, not a check of
/// speed (a debug build, with the file's tests sharing two cores, took over 60 s for a job
/// that takes 16 s alone).
const HANG: Duration = Duration::from_secs(240);

/// Polls a timeline until it ends; its final status document.
async fn wait(client: &reqwest::Client, base: &str, id: &str, limit: Duration) -> Value {
    let start = Instant::now();
    loop {
        let status: Value = get_json(client, format!("{base}/v1/timelines/{id}")).await;
        if ["done", "failed", "cancelled"].contains(&status["status"].as_str().unwrap()) {
            return status;
        }
        assert!(start.elapsed() < limit, "timeline {id} still {status}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

async fn create(client: &reqwest::Client, base: &str, query: &str, name: &str) -> (String, Value) {
    let response = post(client, base, query, "model/gltf+json", scene(name)).await;
    assert_eq!(response.status(), 202, "{name}");
    let location = response.headers()["location"].to_str().unwrap().to_string();
    let body: Value = response.json().await.unwrap();
    let id = body["id"].as_str().unwrap().to_string();
    assert_eq!(location, format!("/v1/timelines/{id}"));
    (id, body)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_sample_scene_bakes_and_serves_every_frame() {
    let base = start(Config {
        max_running: 2,
        ..Config::default()
    })
    .await;
    let client = reqwest::Client::new();
    for name in [
        "cornell_box.gltf",
        "cornell_moving.gltf",
        "furnace.gltf",
        "parallel_squares.gltf",
        "level.gltf",
        "level_lamps.gltf",
        "morph_box.gltf",
    ] {
        let (id, created) = create(&client, &base, "lines=20000&fps=4", name).await;
        let frames = created["frames"].as_u64().unwrap() as usize;
        let loaded = created["patches"].as_u64().unwrap() as usize;
        let status = wait(&client, &base, &id, HANG).await;
        assert_eq!(status["status"], "done", "{name}: {status}");
        // The loaded patches, cut where the light needs them and merged where it does not
        // (patch_size=auto by default), within the budget: one patch per 200 lines, or the
        // loaded patches if more.
        let patches = status["patches"].as_u64().unwrap() as usize;
        assert!(
            patches > 0 && patches <= loaded.max(20_000 / 200),
            "{name}: {loaded} then {patches}"
        );
        assert_eq!(status["progress"]["frames_solved"], frames);
        // Every frame's iterations, now that all are solved.
        let iterations = status["iterations"].as_array().unwrap();
        assert_eq!(iterations.len(), frames, "{name}");
        assert!(iterations.iter().all(Value::is_u64), "{name}: {status}");
        let table: Value = get_json(&client, format!("{base}/v1/timelines/{id}/patches")).await;
        assert_eq!(table["patches"].as_array().unwrap().len(), patches);
        // Each patch names its material, and the materials their names.
        let materials = table["materials"].as_array().unwrap();
        for patch in table["patches"].as_array().unwrap() {
            let m = patch["material"].as_u64().unwrap() as usize;
            assert_eq!(materials[m]["index"], m, "{name}");
        }
        for f in 0..frames {
            let frame: Value =
                get_json(&client, format!("{base}/v1/timelines/{id}/frames/{f}")).await;
            assert_eq!(frame["frame"], f);
            assert_eq!(frame["radiance"].as_array().unwrap().len(), patches);
            assert_eq!(frame["samples"].as_array().unwrap().len(), patches);
        }
        // The binary layout: frame, patch count, time, then the arrays.
        let bytes = client
            .get(format!("{base}/v1/timelines/{id}/frames/0"))
            .header("accept", "application/octet-stream")
            .send()
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap();
        assert_eq!(bytes.len(), 16 + patches * 28, "{name}");
        assert_eq!(
            u32::from_le_bytes(bytes[4..8].try_into().unwrap()) as usize,
            patches
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn identical_requests_give_identical_numbers_and_hostile_ones_get_4xx() {
    let base = start(Config {
        max_body_bytes: 1 << 20,
        max_running: 2,
        ..Config::default()
    })
    .await;
    let client = reqwest::Client::new();
    let query = "lines=30000&fps=4&seed=7";
    let (first, _) = create(&client, &base, query, "cornell_moving.gltf").await;
    // While the good job runs: a corpus of bad requests, each with its own 4xx.
    let good = scene("cornell_moving.gltf");
    let mut truncated = good.clone();
    truncated.truncate(good.len() / 2);
    let mut flipped = good.clone();
    flipped[good.len() / 3] ^= 0x40;
    let gltf = "model/gltf+json";
    let cases: Vec<(&str, &str, Vec<u8>, u16)> = vec![
        ("", "text/plain", good.clone(), 415),
        ("", "application/json", good.clone(), 415),
        ("", "", good.clone(), 415),
        ("bogus=1", gltf, good.clone(), 400),
        ("fps=0", gltf, good.clone(), 400),
        ("fps=-3", gltf, good.clone(), 400),
        ("fps=1e9", gltf, good.clone(), 400),
        ("fps=abc", gltf, good.clone(), 400),
        ("fps=NaN", gltf, good.clone(), 400),
        ("lines=5", gltf, good.clone(), 400),
        ("lines=1e99", gltf, good.clone(), 400),
        ("lines=1000&preset=draft", gltf, good.clone(), 400),
        ("preset=ultra", gltf, good.clone(), 400),
        ("seed=-1", gltf, good.clone(), 400),
        ("patch_size=0", gltf, good.clone(), 400),
        ("sky=1,2", gltf, good.clone(), 400),
        ("sky=1,2,-3", gltf, good.clone(), 400),
        ("animation=nope", gltf, good.clone(), 400),
        ("start=2&end=1", gltf, good.clone(), 400),
        ("max_reflectance=0", gltf, good.clone(), 400),
        ("max_reflectance=1.5", gltf, good.clone(), 400),
        ("max_reflectance=high", gltf, good.clone(), 400),
        ("", gltf, Vec::new(), 400),
        ("", gltf, b"not json at all".to_vec(), 400),
        ("", gltf, truncated, 400),
        ("", gltf, b"{\"asset\":{\"version\":\"2.0\"},\"buffers\":[{\"byteLength\":4,\"uri\":\"/etc/passwd\"}]}".to_vec(), 400),
        ("", gltf, b"{\"asset\":{\"version\":\"2.0\"},\"buffers\":[{\"byteLength\":4,\"uri\":\"http://example.com/x.bin\"}]}".to_vec(), 400),
        ("", gltf, b"{\"asset\":{\"version\":\"2.0\"},\"nodes\":[{\"children\":[0]}],\"scenes\":[{\"nodes\":[0]}]}".to_vec(), 400),
        ("", "model/gltf-binary", b"glTF\x02\x00\x00\x00\xff\xff\xff\xff".to_vec(), 400),
        ("patch_size=0.0001", gltf, good.clone(), 422),
    ];
    for (query, content_type, body, expected) in cases {
        let response = post(&client, &base, query, content_type, body).await;
        let status = response.status().as_u16();
        let kind = response
            .headers()
            .get("content-type")
            .map(|v| v.to_str().unwrap().to_string());
        let text = response.text().await.unwrap();
        assert_eq!(status, expected, "{query:?} {content_type:?}: {text}");
        assert_eq!(
            kind.as_deref(),
            Some("application/problem+json"),
            "{query:?}"
        );
        let problem: Value = serde_json::from_str(&text).unwrap();
        assert_eq!(problem["status"], expected);
        assert!(!problem["detail"].as_str().unwrap().is_empty());
    }
    // Over the body limit: 413 from the declared length alone, before any of the body is sent.
    let (status, head, body) = declare_oversize_body(&base, 2 << 20).await;
    assert_eq!(status, 413, "{head}");
    assert!(
        head.to_ascii_lowercase()
            .contains("content-type: application/problem+json"),
        "{head}"
    );
    let problem: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(problem["status"], 413);
    // Flipped bytes may or may not make a valid file, but never a 5xx.
    let response = post(&client, &base, "lines=2000", gltf, flipped).await;
    assert!(response.status().as_u16() < 500);
    for path in [
        "/v1/timelines/nope",
        "/v1/timelines/nope/frames/0",
        "/v1/nothing",
    ] {
        assert_eq!(
            client
                .get(format!("{base}{path}"))
                .send()
                .await
                .unwrap()
                .status(),
            404,
            "{path}"
        );
    }
    let (second, _) = create(&client, &base, query, "cornell_moving.gltf").await;
    for id in [&first, &second] {
        assert_eq!(wait(&client, &base, id, HANG).await["status"], "done");
    }
    for f in 0..9 {
        let get = |id: &str| {
            client
                .get(format!("{base}/v1/timelines/{id}/frames/{f}"))
                .send()
        };
        let a: Value = get(&first).await.unwrap().json().await.unwrap();
        let b: Value = get(&second).await.unwrap().json().await.unwrap();
        assert_eq!(a["radiance"], b["radiance"], "frame {f}");
        assert_eq!(a["stderr"], b["stderr"], "frame {f}");
    }
    let missing = client
        .get(format!("{base}/v1/timelines/{first}/frames/99"))
        .send()
        .await
        .unwrap();
    assert_eq!(missing.status(), 404);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_long_job_is_cancelled_within_a_second() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let (id, _) = create(&client, &base, "lines=20000000&fps=30", "level.gltf").await;
    // Let it start tracing.
    let start = Instant::now();
    loop {
        let status: Value = get_json(&client, format!("{base}/v1/timelines/{id}")).await;
        if status["status"] == "tracing" {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(20), "{status}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // A queued job behind it.
    let (queued, created) = create(&client, &base, "lines=2000", "furnace.gltf").await;
    assert_eq!(created["status"], "queued");
    let deleted = Instant::now();
    let response = client
        .delete(format!("{base}/v1/timelines/{id}"))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 204);
    // The cancelled job gives its slot up within a second: the queued job starts.
    loop {
        let status: Value = get_json(&client, format!("{base}/v1/timelines/{queued}")).await;
        if status["status"] != "queued" {
            break;
        }
        assert!(
            deleted.elapsed() < Duration::from_secs(1),
            "still queued after {:?}",
            deleted.elapsed()
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert_eq!(
        wait(&client, &base, &queued, Duration::from_secs(20)).await["status"],
        "done"
    );
    // Cancelled, not gone: the state can be seen until the timeline is deleted again.
    let cancelled: Value = get_json(&client, format!("{base}/v1/timelines/{id}")).await;
    assert_eq!(cancelled["status"], "cancelled", "{cancelled}");
    // Statuses read in messages as in documents.
    let refine = client
        .post(format!("{base}/v1/timelines/{id}/lines?add=1000"))
        .send()
        .await
        .unwrap();
    assert_eq!(refine.status(), 409);
    let message = refine.text().await.unwrap();
    assert!(message.contains("is cancelled:"), "{message}");
    let response = client
        .delete(format!("{base}/v1/timelines/{id}"))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 204);
    assert_eq!(
        client
            .get(format!("{base}/v1/timelines/{id}"))
            .send()
            .await
            .unwrap()
            .status(),
        404
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_stream_in_order_as_they_are_solved() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let (id, created) = create(&client, &base, "lines=100000&fps=24", "level.gltf").await;
    let frames = created["frames"].as_u64().unwrap();
    // Ask for the stream at once: frames arrive while the job runs, in order.
    let mut response = client
        .get(format!("{base}/v1/timelines/{id}/frames"))
        .header("accept", "application/x-ndjson")
        .send()
        .await
        .unwrap();
    assert_eq!(response.headers()["content-type"], "application/x-ndjson");
    let mut buffer = Vec::new();
    let mut seen = 0u64;
    let mut status_at_first = None;
    while let Some(chunk) = response.chunk().await.unwrap() {
        buffer.extend_from_slice(&chunk);
        while let Some(end) = buffer.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = buffer.drain(..=end).collect();
            let frame: Value = serde_json::from_slice(&line).unwrap();
            assert_eq!(frame["frame"], seen);
            if seen == 0 {
                let status: Value = get_json(&client, format!("{base}/v1/timelines/{id}")).await;
                status_at_first = Some(status["status"].clone());
            }
            seen += 1;
        }
    }
    assert_eq!(seen, frames);
    // The first frame came before the job ended.
    assert_eq!(status_at_first, Some(Value::from("solving")));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refine_lowers_the_error_and_relight_needs_no_tracing() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let (id, _) = create(&client, &base, "lines=20000&fps=2", "cornell_moving.gltf").await;
    let done = wait(&client, &base, &id, HANG).await;
    let frame = |v: u64| {
        let client = client.clone();
        let url = format!("{base}/v1/timelines/{id}/frames/0");
        async move {
            let f: Value = client.get(url).send().await.unwrap().json().await.unwrap();
            assert_eq!(f["version"], v);
            f
        }
    };
    let before = frame(1).await;
    let mean_error = |f: &Value| {
        let e = f["stderr"].as_array().unwrap();
        e.iter()
            .filter_map(|x| x.as_array())
            .map(|x| x[0].as_f64().unwrap())
            .sum::<f64>()
            / e.len() as f64
    };
    // Refine: four times the lines, about half the error.
    let response = client
        .post(format!("{base}/v1/timelines/{id}/lines?add=60000"))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 202);
    let refined = wait(&client, &base, &id, HANG).await;
    assert_eq!(refined["status"], "done");
    // The progress counts the added lines.
    assert_eq!(refined["progress"]["lines_total"], 80_000);
    assert_eq!(refined["progress"]["lines_traced"], 80_000);
    let after = frame(2).await;
    assert!(
        mean_error(&after) < 0.7 * mean_error(&before),
        "{} → {}",
        mean_error(&before),
        mean_error(&after)
    );
    let hits = refined["memory"]["hits"].clone();
    assert!(hits.as_u64() > done["memory"]["hits"].as_u64());
    // Relight: double the light's emission (material "light"): every radiance doubles, and no
    // line is traced (the list holds the same crossings).
    let lamp_emission: Vec<f64> = vec![30.0, 30.0, 30.0];
    let body = serde_json::json!({"materials": [{"material": "light", "emission": lamp_emission}]});
    let response = relight(&client, &base, &id, &body).await;
    assert_eq!(response.status(), 202, "{}", response.text().await.unwrap());
    let relit = wait(&client, &base, &id, HANG).await;
    assert_eq!(relit["memory"]["hits"], hits);
    assert_eq!(relit["timings"]["trace"], refined["timings"]["trace"]);
    let doubled = frame(3).await;
    for (a, b) in after["radiance"]
        .as_array()
        .unwrap()
        .iter()
        .zip(doubled["radiance"].as_array().unwrap())
    {
        for c in 0..3 {
            let (a, b) = (a[c].as_f64().unwrap(), b[c].as_f64().unwrap());
            assert!(
                (b - 2.0 * a).abs() <= 1e-9 * a.abs().max(1e-12),
                "{a} → {b}"
            );
        }
    }
    // Bad relighting requests.
    for bad in [
        serde_json::json!({"materials": [{"material": "nope", "emission": [1, 1, 1]}]}),
        serde_json::json!({"materials": [{"material": 0, "reflectance": [2, 0, 0]}]}),
        serde_json::json!({"materials": [{"material": 0, "colour": [1, 1, 1]}]}),
        serde_json::json!({"paint": []}),
    ] {
        let response = relight(&client, &base, &id, &bad).await;
        assert_eq!(response.status(), 400, "{bad}");
    }
    // The statistics of the lines.
    let stats: Value = get_json(&client, format!("{base}/v1/timelines/{id}/stats?frame=1")).await;
    assert_eq!(stats["frame"], 1);
    let (measured, predicted) = (
        stats["mean_hits_per_line"].as_f64().unwrap(),
        stats["predicted_hits_per_line"].as_f64().unwrap(),
    );
    assert!(
        (measured / predicted - 1.0).abs() < 0.02,
        "{measured} vs {predicted}"
    );
    // The visibility information, every patch's share of its gap only when asked for.
    let information = &stats["information"];
    assert!(information["continuous"].as_f64().unwrap().is_finite());
    assert!(information.get("patch_gap").is_none());
    let with_patches: Value = get_json(
        &client,
        format!("{base}/v1/timelines/{id}/stats?frame=1&patches=true"),
    )
    .await;
    let information = &with_patches["information"];
    if let Some(gap) = information["gap"].as_f64() {
        let shares = information["patch_gap"].as_array().unwrap();
        let sum: f64 = shares.iter().map(|s| s.as_f64().unwrap()).sum();
        assert!((sum - gap).abs() < 1e-6, "{sum} vs {gap}");
    } else {
        assert!(information["discrete"].is_null());
    }
    let response = client
        .get(format!("{base}/v1/timelines/{id}/stats?patches=maybe"))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 400);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_served_description_is_the_checked_in_one_and_covers_every_route() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let served = client
        .get(format!("{base}/openapi.json"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let file = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("api/openapi.json"),
    )
    .unwrap();
    assert_eq!(served, file);
    let spec: Value = serde_json::from_str(&file).unwrap();
    // Every described path and method is routed (an unknown timeline is "no timeline", not
    // "no such path"), and the server answers nothing that is not described.
    for (path, methods) in spec["paths"].as_object().unwrap() {
        let url = format!(
            "{base}{}",
            path.replace("{id}", "nope").replace("{frame}", "0")
        );
        for method in methods.as_object().unwrap().keys() {
            let request = match method.as_str() {
                "get" => client.get(&url),
                "post" => client.post(&url),
                "delete" => client.delete(&url),
                other => panic!("method {other}"),
            };
            let text = request.send().await.unwrap().text().await.unwrap();
            assert!(
                !text.contains("no such path"),
                "{method} {path} is not routed"
            );
        }
    }
    let undescribed = client
        .get(format!("{base}/v1/nothing"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(undescribed.contains("no such path"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn progress_arrives_as_server_sent_events() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let (id, _) = create(&client, &base, "lines=50000&fps=12", "cornell_moving.gltf").await;
    let mut response = client
        .get(format!("{base}/v1/timelines/{id}/events"))
        .send()
        .await
        .unwrap();
    assert!(
        response.headers()["content-type"]
            .to_str()
            .unwrap()
            .starts_with("text/event-stream")
    );
    let mut text = String::new();
    while let Some(chunk) = response.chunk().await.unwrap() {
        text.push_str(std::str::from_utf8(&chunk).unwrap());
    }
    let statuses: Vec<Value> = text
        .lines()
        .filter_map(|l| l.strip_prefix("data: "))
        .map(|d| serde_json::from_str(d).unwrap())
        .collect();
    assert!(statuses.len() >= 2, "{text}");
    assert_eq!(statuses.last().unwrap()["status"], "done");
    let solved: Vec<u64> = statuses
        .iter()
        .map(|s| s["progress"]["frames_solved"].as_u64().unwrap())
        .collect();
    assert!(solved.windows(2).all(|w| w[0] <= w[1]), "{solved:?}");
}

/// POSTs `body` to timeline `id`'s materials and waits until it is done again.
async fn relight_to_the_end(client: &reqwest::Client, base: &str, id: &str, body: &'static str) {
    let url = format!("{base}/v1/timelines/{id}/materials");
    let response = client.post(url).body(body).send().await.unwrap();
    assert_eq!(response.status(), 202);
    assert_eq!(wait(client, base, id, HANG).await["status"], "done");
}

/// An empty data directory of its own (named `name`) and a configuration that uses it.
fn fresh_data_dir(name: &str) -> (std::path::PathBuf, Config) {
    let dir = std::env::temp_dir().join(format!("radiosity-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let config = Config {
        data_dir: Some(dir.clone()),
        ..Config::default()
    };
    (dir, config)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn finished_results_survive_a_restart_and_unfinished_jobs_resume() {
    let (dir, config) = fresh_data_dir("restart");
    let first = start(config.clone()).await;
    let client = reqwest::Client::new();
    let frame = |base: &str, id: &str| format!("{base}/v1/timelines/{id}/frames/5");
    let (done, _) = create(&client, &first, "lines=20000&fps=4", "cornell_moving.gltf").await;
    assert_eq!(wait(&client, &first, &done, HANG).await["status"], "done");
    let before: Value = get_json(&client, frame(&first, &done)).await;
    let patches: Value = get_json(&client, format!("{first}/v1/timelines/{done}/patches")).await;
    // A job the server stops while it traces: made so by its files (a finished job's, with
    // its status set back to tracing, its frames gone and its traced state the one from
    // before its refinement), so the test does not race it. It was refined and relit first:
    // both are done again when it resumes (the refinement traced on the state read back).
    let query = "lines=20000&fps=4&seed=5&patch_size=auto";
    let (cut, _) = create(&client, &first, query, "cornell_moving.gltf").await;
    assert_eq!(wait(&client, &first, &cut, HANG).await["status"], "done");
    let traced = dir.join(&cut).join("traced.bin");
    let unrefined = std::fs::read(&traced).unwrap();
    let refine = format!("{first}/v1/timelines/{cut}/lines?add=5000");
    assert_eq!(client.post(refine).send().await.unwrap().status(), 202);
    assert_eq!(wait(&client, &first, &cut, HANG).await["status"], "done");
    let red = r#"{"materials": [{"material": "red", "reflectance": [0.2, 0.6, 0.2]}]}"#;
    relight_to_the_end(&client, &first, &cut, red).await;
    let clean: Value = get_json(&client, frame(&first, &cut)).await;
    let record = dir.join(&cut).join("job.json");
    let mut saved: Value = serde_json::from_slice(&std::fs::read(&record).unwrap()[24..]).unwrap();
    saved["status"] = "tracing".into();
    std::fs::write(&record, saved.to_string()).unwrap();
    std::fs::remove_file(dir.join(&cut).join("frames.bin")).unwrap();
    assert_ne!(
        std::fs::read(&traced).unwrap(),
        unrefined,
        "not saved refined"
    );
    std::fs::write(&traced, unrefined).unwrap();

    // A second server on the same data directory: the restart.
    let second = start(config).await;
    let status = wait(&client, &second, &done, Duration::from_secs(5)).await;
    assert_eq!(status["status"], "done");
    assert_eq!(status["progress"]["lines_traced"], 20_000);
    assert_eq!(status["progress"]["lines_total"], 20_000);
    assert_eq!(before, get_json(&client, frame(&second, &done)).await);
    let patches_after: Value =
        get_json(&client, format!("{second}/v1/timelines/{done}/patches")).await;
    assert_eq!(patches, patches_after);
    // The interrupted job starts again and ends as an uninterrupted run does, counted.
    let resumed = wait(&client, &second, &cut, HANG).await;
    assert_eq!(resumed["status"], "done", "{resumed}");
    assert_eq!(resumed["restarts"], 1);
    assert_eq!(resumed["progress"]["lines_total"], 25_000);
    assert_eq!(clean, get_json(&client, frame(&second, &cut)).await);

    // The restored timeline's traced state is read back when a route needs it: previews,
    // statistics, and a relight that gives what the never-restarted server gives.
    let preview = client
        .get(format!("{second}/v1/timelines/{done}/frames/0/preview.png"))
        .send()
        .await
        .unwrap();
    assert_eq!(preview.status(), 200);
    let rebuilt = get_json(&client, format!("{second}/v1/timelines/{done}")).await;
    assert!(
        rebuilt["rebuild_seconds"].as_f64().unwrap() > 0.0,
        "{rebuilt}"
    );
    assert_eq!(rebuilt["rebuilt_from"], "traced_state", "{rebuilt}");
    let stats = client
        .get(format!("{second}/v1/timelines/{done}/stats?frame=0"))
        .send()
        .await
        .unwrap();
    assert_eq!(stats.status(), 200);
    let mut relit = Vec::new();
    let light = r#"{"materials": [{"material": "light", "emission": [30, 30, 30]}]}"#;
    for base in [&first, &second] {
        relight_to_the_end(&client, base, &done, light).await;
        relit.push(get_json(&client, frame(base, &done)).await);
    }
    assert_ne!(relit[0]["radiance"], before["radiance"]);
    assert_eq!(relit[0], relit[1]);

    // Deleting removes the saved results.
    for id in [&done, &cut] {
        let response = client
            .delete(format!("{second}/v1/timelines/{id}"))
            .send()
            .await
            .unwrap();
        assert_eq!(response.status(), 204);
        assert!(!dir.join(id).exists());
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_timeline_from_a_data_directory_without_its_scene_is_served_but_not_rebuilt() {
    let (dir, config) = fresh_data_dir("unstored");
    let first = start(config.clone()).await;
    let client = reqwest::Client::new();
    let (done, _) = create(&client, &first, "lines=20000&fps=4", "cornell_moving.gltf").await;
    assert_eq!(wait(&client, &first, &done, HANG).await["status"], "done");
    let (running, _) = create(&client, &first, "lines=20000&fps=4", "cornell_moving.gltf").await;
    assert_eq!(
        wait(&client, &first, &running, HANG).await["status"],
        "done"
    );
    // As written before scenes were stored: no scene, and one job left unfinished.
    for id in [&done, &running] {
        std::fs::remove_file(dir.join(id).join("scene.bin")).unwrap();
        std::fs::remove_file(dir.join(id).join("request.json")).unwrap();
    }
    let record = dir.join(&running).join("job.json");
    let mut saved: Value = serde_json::from_slice(&std::fs::read(&record).unwrap()[24..]).unwrap();
    saved["status"] = "solving".into();
    std::fs::write(&record, saved.to_string()).unwrap();
    std::fs::remove_file(dir.join(&running).join("frames.bin")).unwrap();

    let second = start(config).await;
    let frame = format!("{second}/v1/timelines/{done}/frames/5");
    assert_eq!(client.get(frame).send().await.unwrap().status(), 200);
    let refine = client
        .post(format!("{second}/v1/timelines/{done}/lines?add=1000"))
        .send()
        .await
        .unwrap();
    assert_eq!(refine.status(), 409);
    let preview = client
        .get(format!("{second}/v1/timelines/{done}/frames/0/preview.png"))
        .send()
        .await
        .unwrap();
    assert_eq!(preview.status(), 409);
    assert!(preview.text().await.unwrap().contains("restored"));
    let interrupted: Value = get_json(&client, format!("{second}/v1/timelines/{running}")).await;
    assert_eq!(interrupted["status"], "failed");
    let error = interrupted["error"].as_str().unwrap();
    assert!(error.starts_with("interrupted"), "{interrupted}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_over_the_memory_budget_is_refused_before_tracing() {
    let base = start(Config {
        memory_budget: 16 << 20,
        ..Config::default()
    })
    .await;
    let client = reqwest::Client::new();
    let response = post(
        &client,
        &base,
        "lines=10000000&fps=24",
        "model/gltf+json",
        scene("level.gltf"),
    )
    .await;
    assert_eq!(response.status(), 422);
    let problem: Value = response.json().await.unwrap();
    assert_eq!(problem["type"], "/problems/memory-budget");
    assert!(
        problem["detail"].as_str().unwrap().contains("GiB"),
        "{problem}"
    );
    // A small job fits, and its measured memory is within the estimate's order.
    let (id, _) = create(&client, &base, "lines=20000&fps=4", "level.gltf").await;
    let status = wait(&client, &base, &id, HANG).await;
    assert_eq!(status["status"], "done");
    assert!(status["memory"]["bytes"].as_u64().unwrap() < 16 << 20);
    let listed: Value = get_json(&client, format!("{base}/v1/timelines")).await;
    assert_eq!(listed["timelines"].as_array().unwrap().len(), 1);
}

/// A service with one finished timeline, `scenes/cornell_moving.gltf` with the settings of
/// [`cornell_baked_by_the_command_line`]: the service's address and the timeline's id.
async fn cornell_timeline_done(client: &reqwest::Client) -> (String, String) {
    let base = start(Config::default()).await;
    let (id, _) = create(
        client,
        &base,
        "lines=20000&fps=4&seed=9",
        "cornell_moving.gltf",
    )
    .await;
    assert_eq!(wait(client, &base, &id, HANG).await["status"], "done");
    (base, id)
}

/// Checks that `file` of frame 3 of timeline `id` with each of `queries` is a 400 problem, and
/// of frames 99 (past the end) and `x` a 404.
async fn bad_frame_requests_are_refused(
    client: &reqwest::Client,
    base: &str,
    id: &str,
    file: &str,
    queries: &[&str],
) {
    for query in queries {
        let url = format!("{base}/v1/timelines/{id}/frames/3/{file}{query}");
        let response = client.get(url).send().await.unwrap();
        assert_eq!(response.status(), 400, "{query}");
        assert_eq!(
            response.headers()["content-type"],
            "application/problem+json"
        );
    }
    for frame in ["99", "x"] {
        let url = format!("{base}/v1/timelines/{id}/frames/{frame}/{file}");
        let response = client.get(url).send().await.unwrap();
        assert_eq!(response.status(), 404, "{frame}");
    }
}

/// The file `file` (under the scene's output directory) that `radiosity bake` writes for
/// `scenes/cornell_moving.gltf` with the service jobs' settings of these tests (20,000 lines,
/// 4 fps, seed 9, no GIF), the outputs `wanted` and not `unwanted`.
fn cornell_baked_by_the_command_line(wanted: &[&str], unwanted: &[&str], file: &str) -> Vec<u8> {
    let out = std::env::temp_dir().join(format!(
        "radiosity-cli-{}-{}",
        std::process::id(),
        file.replace('/', "-")
    ));
    let _ = std::fs::remove_dir_all(&out);
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_radiosity"))
        .args(["bake", "--lines", "20000", "--fps", "4", "--seed", "9"])
        .args(wanted)
        .args(unwanted)
        .args(["--no-gif", "--out"])
        .arg(&out)
        .arg(
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("scenes")
                .join("cornell_moving.gltf"),
        )
        .status()
        .unwrap();
    assert!(status.success());
    let written = std::fs::read(out.join("cornell_moving").join(file)).unwrap();
    let _ = std::fs::remove_dir_all(&out);
    written
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_preview_is_the_png_the_command_line_writes() {
    let client = reqwest::Client::new();
    let (base, id) = cornell_timeline_done(&client).await;
    let url = format!("{base}/v1/timelines/{id}/frames/3/preview.png");
    let response = client
        .get(format!("{url}?width=160&height=120"))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 200);
    assert_eq!(response.headers()["content-type"], "image/png");
    assert!(response.headers().contains_key("x-exposure"));
    let served = response.bytes().await.unwrap().to_vec();
    let image = image::load_from_memory(&served).unwrap().into_rgb8();
    assert_eq!(image.dimensions(), (160, 120));
    let background = *image.get_pixel(0, 0);
    assert!(image.pixels().filter(|p| **p != background).count() > 160 * 120 / 20);

    // The same bake from the command line writes the same image.
    let written = cornell_baked_by_the_command_line(
        &["--preview-size", "160x120", "--preview-frames", "3"],
        &["--glb-frames", "none"],
        "preview/frame_0003.png",
    );
    assert!(written == served, "the service and the CLI previews differ");
    // Flat shading, per patch: another image of the same frame, as the CLI's --preview-shading.
    let flat = client
        .get(format!("{url}?width=160&height=120&shading=flat"))
        .send()
        .await
        .unwrap();
    assert_eq!(flat.status(), 200);
    assert!(flat.bytes().await.unwrap().to_vec() != served);

    // Bad requests get their 4xx.
    let bad = [
        "?width=0",
        "?height=99999",
        "?exposure=-1",
        "?exposure=nan",
        "?zoom=2",
        "?shading=glossy",
    ];
    bad_frame_requests_are_refused(&client, &base, &id, "preview.png", &bad).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_s_baked_gltf_is_the_file_the_command_line_writes() {
    let client = reqwest::Client::new();
    let (base, id) = cornell_timeline_done(&client).await;
    let url = format!("{base}/v1/timelines/{id}/frames/3/baked.glb");
    let response = client.get(&url).send().await.unwrap();
    assert_eq!(response.status(), 200);
    assert_eq!(response.headers()["content-type"], "model/gltf-binary");
    let exposure: f64 = response.headers()["x-exposure"]
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    assert!(exposure > 0.0);
    let served = response.bytes().await.unwrap().to_vec();
    // A GLB: magic, version 2, its own length.
    assert_eq!(&served[..4], b"glTF");
    assert_eq!(u32::from_le_bytes(served[4..8].try_into().unwrap()), 2);
    assert_eq!(
        u32::from_le_bytes(served[8..12].try_into().unwrap()) as usize,
        served.len()
    );

    // The same bake from the command line writes the same file.
    let written = cornell_baked_by_the_command_line(
        &["--glb-frames", "3"],
        &["--preview-frames", "none"],
        "baked/frame_0003.glb",
    );
    assert!(written == served, "the service's and the CLI's glTF differ");

    // Another exposure: other vertex colours, the same size, and the exposure given back.
    let brighter = client
        .get(format!("{url}?exposure={}", exposure * 4.0))
        .send()
        .await
        .unwrap();
    assert_eq!(brighter.status(), 200);
    let given: f64 = brighter.headers()["x-exposure"]
        .to_str()
        .unwrap()
        .parse()
        .unwrap();
    assert!((given - exposure * 4.0).abs() <= 1e-12 * given);
    let brighter = brighter.bytes().await.unwrap().to_vec();
    assert_eq!(brighter.len(), served.len());
    assert!(brighter != served);

    // Bad requests get their 4xx.
    let bad = ["?exposure=0", "?exposure=nan", "?width=10"];
    bad_frame_requests_are_refused(&client, &base, &id, "baked.glb", &bad).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lamps_relight_by_intensity_without_tracing() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let (id, _) = create(&client, &base, "lines=20000&fps=1", "level_lamps.gltf").await;
    let done = wait(&client, &base, &id, HANG).await;
    assert_eq!(done["status"], "done");
    let traced = done["progress"]["lines_traced"].clone();
    let before = radiance(get_json(&client, format!("{base}/v1/timelines/{id}/frames/1")).await);
    assert!(before.iter().any(|&l| l > 0.0), "the lamps light the level");
    // Twice the warm lamp and the spot, the swinging lamp off: by name and by index.
    let body = serde_json::json!({"lights": [
        {"light": "warm_lamp", "intensity": 120.0},
        {"light": 1, "intensity": 300.0},
        {"light": "swinging_lamp", "intensity": 0.0},
    ]});
    let response = relight(&client, &base, &id, &body).await;
    assert_eq!(response.status(), 202);
    let done = wait(&client, &base, &id, HANG).await;
    assert_eq!(
        done["progress"]["lines_traced"], traced,
        "relighting traced lines"
    );
    // All lights off but two, doubled: with no emitters, the level is linear in them. Check
    // against turning the swinging lamp off alone, at the old intensities, and doubling.
    let doubled = radiance(get_json(&client, format!("{base}/v1/timelines/{id}/frames/1")).await);
    let body = serde_json::json!({"lights": [
        {"light": "warm_lamp", "intensity": 60.0},
        {"light": "spot", "intensity": 150.0},
    ]});
    relight(&client, &base, &id, &body).await;
    wait(&client, &base, &id, HANG).await;
    let single = radiance(get_json(&client, format!("{base}/v1/timelines/{id}/frames/1")).await);
    // Relative to |d|: a patch the lamps leave dark can read a hair below zero (the
    // conjugate gradients' stopping error, −2e-10 here), exactly doubled too.
    for (d, s) in doubled.iter().zip(&single) {
        assert!(
            (d - 2.0 * s).abs() <= 1e-5 * d.abs().max(1e-30),
            "{d} against 2 × {s}"
        );
    }
    assert!(
        single.iter().zip(&before).any(|(s, b)| s < b),
        "the swinging lamp is off"
    );
    // Unknown lights and bad values are refused, naming what is wrong.
    for (body, needle) in [
        (
            serde_json::json!({"lights": [{"light": "sun", "intensity": 1.0}]}),
            "warm_lamp",
        ),
        (
            serde_json::json!({"lights": [{"light": 0, "intensity": -1.0}]}),
            "intensity",
        ),
        (
            serde_json::json!({"lights": [{"light": 0, "color": [1.0, "x", 0.0]}]}),
            "body",
        ),
        (
            serde_json::json!({"lights": [{"light": 0, "power": 1.0}]}),
            "power",
        ),
    ] {
        let response = relight(&client, &base, &id, &body).await;
        assert_eq!(response.status(), 400, "{body}");
        let text = response.text().await.unwrap();
        assert!(text.contains(needle), "{body}: {text}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_relights_apply_exactly_the_one_accepted() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let (id, _) = create(&client, &base, "lines=20000&fps=1", "level_lamps.gltf").await;
    assert_eq!(wait(&client, &base, &id, HANG).await["status"], "done");
    // Only the warm lamp, at intensity k, from eight clients at once.
    let only = |k: f64| {
        serde_json::json!({"lights": [
            {"light": 0, "intensity": k}, {"light": 1, "intensity": 0.0}, {"light": 2, "intensity": 0.0},
        ]})
    };
    let requests = (1..=8).map(|k| {
        let (client, base, id, body) = (client.clone(), base.clone(), id.clone(), only(k as f64));
        async move { (k, relight(&client, &base, &id, &body).await.status()) }
    });
    let answers = futures_util::future::join_all(requests).await;
    let accepted: Vec<u64> = answers
        .iter()
        .filter(|(_, s)| *s == 202)
        .map(|(k, _)| *k)
        .collect();
    assert_eq!(accepted.len(), 1, "{answers:?}");
    assert!(
        answers.iter().all(|(_, s)| *s == 202 || *s == 409),
        "{answers:?}"
    );
    wait(&client, &base, &id, HANG).await;
    let url = format!("{base}/v1/timelines/{id}/frames/0");
    let raced = radiance(get_json(&client, url.clone()).await);
    assert_eq!(relight(&client, &base, &id, &only(1.0)).await.status(), 202);
    wait(&client, &base, &id, HANG).await;
    let unit = radiance(get_json(&client, url).await);
    let k = accepted[0] as f64;
    for (r, u) in raced.iter().zip(&unit) {
        assert!(
            (r - k * u).abs() <= 1e-5 * r.max(1e-30),
            "{r} against {k} × {u}"
        );
    }
}

/// Regression (issue 11): parameters are strict. `start > end` is refused, also for a static
/// scene (it was accepted); `sky` is exactly r,g,b (`1,x,2,3` was read as `1,2,3`); and every
/// route refuses a query parameter it does not take, naming it (`/frames/0?side=x` was a 200).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parameters_are_strict_and_their_refusals_name_them() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let refused = |response: reqwest::Response, what: String, needles: Vec<String>| async move {
        assert_eq!(response.status(), 400, "{what}");
        assert_eq!(
            response.headers()["content-type"],
            "application/problem+json",
            "{what}"
        );
        let problem: Value = response.json().await.unwrap();
        let detail = problem["detail"].as_str().unwrap();
        for needle in needles {
            assert!(
                detail.contains(&needle),
                "{what}: {detail:?} lacks {needle:?}"
            );
        }
    };
    for (query, needles) in [
        ("start=2&end=1", vec!["start", "end"]),
        ("start=0.5&end=-0.5", vec!["start", "end"]),
        ("sky=1,x,2,3", vec!["sky", "1,x,2,3"]),
        ("sky=1,2,3,4", vec!["sky", "1,2,3,4"]),
        ("sky=1,,2,3", vec!["sky", "1,,2,3"]),
        ("sky=1,2,3,", vec!["sky", "1,2,3,"]),
        ("sky=1,inf,3", vec!["sky", "1,inf,3"]),
        ("fps=abc", vec!["fps", "abc"]),
        ("seed=-1", vec!["seed", "-1"]),
    ] {
        let query = format!("lines=2000&{query}");
        let response = post(
            &client,
            &base,
            &query,
            "model/gltf+json",
            scene("cornell_box.gltf"),
        )
        .await;
        let needles = needles.into_iter().map(String::from).collect();
        refused(response, query, needles).await;
    }
    // Equal times (one frame) and a well-formed sky are accepted.
    let (id, _) = create(
        &client,
        &base,
        "lines=2000&start=1&end=1&sky=0.5,0.5,0.5",
        "cornell_box.gltf",
    )
    .await;
    assert_eq!(wait(&client, &base, &id, HANG).await["status"], "done");
    // Every described route, each with a parameter it does not take (beside one it takes,
    // where it takes some): 400, naming it, and nothing done.
    let spec: Value = serde_json::from_str(radiosity::service::OPENAPI).unwrap();
    for (path, methods) in spec["paths"].as_object().unwrap() {
        let url = format!(
            "{base}{}",
            path.replace("{id}", &id).replace("{frame}", "0")
        );
        for (method, operation) in methods.as_object().unwrap() {
            let known = operation["parameters"]
                .as_array()
                .into_iter()
                .flatten()
                .find(|p| p["in"] == "query")
                .map(|p| format!("{}=1&", p["name"].as_str().unwrap()))
                .unwrap_or_default();
            let url = format!("{url}?{known}side=x");
            let request = match method.as_str() {
                "get" => client.get(&url),
                "post" => client.post(&url),
                "delete" => client.delete(&url),
                other => panic!("method {other}"),
            };
            let response = request.send().await.unwrap();
            refused(response, format!("{method} {url}"), vec!["side".into()]).await;
        }
    }
    assert_eq!(
        get_json(&client, format!("{base}/v1/timelines/{id}")).await["status"],
        "done",
        "the refused DELETE deleted nothing"
    );
}

/// `furnace.gltf` reflecting everything: baseColorFactor 1, metallic 0, as glTF allows.
fn white_furnace() -> Vec<u8> {
    let mut json: Value = serde_json::from_slice(&scene("furnace.gltf")).unwrap();
    json["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"] =
        serde_json::json!([1.0, 1.0, 1.0, 1.0]);
    serde_json::to_vec(&json).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reflectance_1_is_capped_with_a_warning_and_relit_only_up_to_the_cap() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let gltf = "model/gltf+json";
    let response = post(&client, &base, "lines=5000", gltf, white_furnace()).await;
    assert_eq!(response.status(), 202);
    let created: Value = response.json().await.unwrap();
    let id = created["id"].as_str().unwrap().to_string();
    let warnings = created["warnings"].to_string();
    assert!(
        warnings.contains("max_reflectance 0.999") && warnings.contains("furnace"),
        "{warnings}"
    );
    let done = wait(&client, &base, &id, HANG).await;
    assert_eq!(done["status"], "done", "{done}");
    assert_eq!(done["warnings"], created["warnings"]);
    // The white furnace at the cap: Le / (1 − 0.999) on every sampled patch (exact: closed and
    // watertight; the JSON carries f64).
    let frame = get_json(&client, format!("{base}/v1/timelines/{id}/frames/0")).await;
    let samples = frame["samples"].as_array().unwrap();
    for (l, n) in radiance(frame.clone()).iter().zip(samples) {
        if n.as_u64().unwrap() > 0 {
            assert!((l / 1000.0 - 1.0).abs() < 1e-6, "{l}");
        }
    }
    // Relighting above the cap is refused, naming the material; at or below it, accepted.
    let above = serde_json::json!({"materials": [{"material": 0, "reflectance": [1.0, 0.5, 0.5]}]});
    let response = relight(&client, &base, &id, &above).await;
    assert_eq!(response.status(), 400);
    let detail = response.json::<Value>().await.unwrap()["detail"].to_string();
    assert!(
        detail.contains("material 0 (furnace)") && detail.contains("max_reflectance"),
        "{detail}"
    );
    let half =
        serde_json::json!({"materials": [{"material": "furnace", "reflectance": [0.5, 0.5, 0.5]}]});
    assert_eq!(relight(&client, &base, &id, &half).await.status(), 202);
    let done = wait(&client, &base, &id, HANG).await;
    assert_eq!(done["status"], "done", "{done}");
    let frame = get_json(&client, format!("{base}/v1/timelines/{id}/frames/0")).await;
    assert!((radiance(frame)[0] - 2.0).abs() < 1e-9);
    // Without the cap there is no steady state: the job fails, saying why.
    let response = post(
        &client,
        &base,
        "lines=5000&max_reflectance=1",
        gltf,
        white_furnace(),
    )
    .await;
    assert_eq!(response.status(), 202);
    let created: Value = response.json().await.unwrap();
    assert_eq!(created["warnings"], serde_json::json!([]));
    let id = created["id"].as_str().unwrap();
    let failed = wait(&client, &base, id, HANG).await;
    assert_eq!(failed["status"], "failed", "{failed}");
    let error = failed["error"].as_str().unwrap();
    assert!(error.contains("frame 0 did not converge"), "{error}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_solve_that_does_not_converge_fails_the_job_with_its_reason() {
    let base = start(Config {
        max_iterations: 1,
        ..Config::default()
    })
    .await;
    let client = reqwest::Client::new();
    let (id, _) = create(&client, &base, "lines=5000&fps=4", "cornell_moving.gltf").await;
    let failed = wait(&client, &base, &id, HANG).await;
    assert_eq!(failed["status"], "failed", "{failed}");
    let error = failed["error"].as_str().unwrap();
    assert!(
        error.contains("frame 0 did not converge")
            && error.contains("residual")
            && error.contains("after 1 iterations"),
        "{error}"
    );
    // No frame is served as if it were an answer, and the stream ends.
    assert_eq!(failed["progress"]["frames_solved"], 0);
    let response = client
        .get(format!("{base}/v1/timelines/{id}/frames/0"))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 409);
    let stream = tokio::time::timeout(
        Duration::from_secs(10),
        client
            .get(format!("{base}/v1/timelines/{id}/frames"))
            .send()
            .await
            .unwrap()
            .text(),
    )
    .await
    .expect("the stream of a failed job ends")
    .unwrap();
    assert!(stream.is_empty(), "{stream}");
}

/// Issue 11: what the lines find (faces overlapping in one plane) is in the status document.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overlapping_faces_are_named_in_the_status_document() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let mut doc: Value = serde_json::from_slice(&scene("parallel_squares.gltf")).unwrap();
    // A second receiver on the same mesh: node 2, coplanar with node 1 and overlapping it.
    doc["nodes"]
        .as_array_mut()
        .unwrap()
        .push(serde_json::json!({"mesh": 1, "name": "receiver copy"}));
    doc["scenes"][0]["nodes"] = serde_json::json!([0, 1, 2]);
    let body = serde_json::to_vec(&doc).unwrap();
    let response = post(&client, &base, "lines=20000", "model/gltf+json", body).await;
    assert_eq!(response.status(), 202);
    let id = response.json::<Value>().await.unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let done = wait(&client, &base, &id, HANG).await;
    assert_eq!(done["status"], "done", "{done}");
    let warnings = done["warnings"].as_array().unwrap();
    assert!(
        warnings.iter().any(|w| w.as_str().unwrap().starts_with(
            r#"node 1 ("receiver") and node 2 ("receiver copy") have faces that overlap"#
        )),
        "{warnings:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_patches_are_cut_after_tracing_and_served_with_their_table() {
    let base = start(Config::default()).await;
    let client = reqwest::Client::new();
    let (id, created) = create(
        &client,
        &base,
        "lines=100000&patch_size=auto",
        "panel_room.gltf",
    )
    .await;
    let loaded = created["patches"].as_u64().unwrap();
    let status = wait(&client, &base, &id, Duration::from_secs(120)).await;
    assert_eq!(status["status"], "done", "{status}");
    let patches = status["patches"].as_u64().unwrap();
    // The panel's light behind it, 1 cm from the ceiling, is where the cuts go.
    assert!(
        patches > 2 * loaded,
        "{loaded} patches loaded, {patches} after"
    );
    let table = get_json(&client, format!("{base}/v1/timelines/{id}/patches")).await;
    assert_eq!(table["patches"].as_array().unwrap().len() as u64, patches);
    let frame = get_json(&client, format!("{base}/v1/timelines/{id}/frames/0")).await;
    assert_eq!(radiance(frame).len() as u64, patches);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn solved_frames_are_served_as_glb_while_the_others_are_solved() {
    let client = reqwest::Client::new();
    let base = start(Config::default()).await;
    // 121 frames of the sliding block: a solve long enough to be seen under way.
    let query = "lines=20000&fps=60&patch_size=source";
    let (id, _) = create(&client, &base, query, "cornell_moving.gltf").await;
    let started = Instant::now();
    let status = loop {
        let status = get_json(&client, format!("{base}/v1/timelines/{id}")).await;
        let solved = status["progress"]["frames_solved"].as_u64().unwrap();
        if status["status"] == "solving" && solved >= 1 {
            break status;
        }
        assert_ne!(
            status["status"], "done",
            "the solve ended before it was seen"
        );
        assert!(started.elapsed() < HANG, "{status}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    };
    let response = (client.get(format!("{base}/v1/timelines/{id}/frames/0/baked.glb")))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 200, "{status}");
    assert_eq!(&response.bytes().await.unwrap()[..4], b"glTF");
    let last = (client.get(format!("{base}/v1/timelines/{id}/frames/120/baked.glb")))
        .send()
        .await
        .unwrap();
    let after = get_json(&client, format!("{base}/v1/timelines/{id}")).await;
    // The last frame, unless solved meanwhile, is not ready.
    if after["status"] == "solving" {
        assert_eq!(last.status(), 409, "{after}");
    }
    assert_eq!(wait(&client, &base, &id, HANG).await["status"], "done");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn over_the_resident_budget_finished_timelines_are_traced_again_when_needed() {
    let [(budget_dir, budget), (reference_dir, reference)] =
        ["budget", "reference"].map(fresh_data_dir);
    let dirs = [budget_dir, reference_dir];
    // One byte: no finished timeline keeps its traced state.
    let budget = start(Config {
        resident_budget: Some(1),
        ..budget
    })
    .await;
    // The reference keeps every timeline in memory, and writes no traced state.
    let reference = start(Config {
        traced_files: false,
        ..reference
    })
    .await;
    let client = reqwest::Client::new();
    let mut ids = [Vec::new(), Vec::new()];
    for (base, ids) in [&budget, &reference].into_iter().zip(&mut ids) {
        for seed in 1..=3 {
            let query = format!("lines=20000&fps=4&seed={seed}");
            let (id, _) = create(&client, base, &query, "cornell_moving.gltf").await;
            assert_eq!(wait(&client, base, &id, HANG).await["status"], "done");
            ids.push(id);
        }
    }
    let health = get_json(&client, format!("{budget}/healthz")).await;
    assert_eq!(health["memory"]["traced_bytes"], 0, "{health}");
    assert_eq!(health["memory"]["solved_bytes"], 0, "{health}");
    assert_eq!(health["memory"]["budget_bytes"], 1, "{health}");
    assert_eq!(health["timelines"]["total"], 3, "{health}");
    assert_eq!(health["timelines"]["traced_in_memory"], 0, "{health}");
    assert_eq!(health["timelines"]["solved_in_memory"], 0, "{health}");
    assert_eq!(health["timelines"]["on_disk"], 3, "{health}");
    // Frames dropped from memory are served from the data directory, the same numbers.
    for (budget_id, kept_id) in ids[0].iter().zip(&ids[1]) {
        for frame in [0, 3] {
            let path = |base: &str, id: &str| format!("{base}/v1/timelines/{id}/frames/{frame}");
            assert_eq!(
                get_json(&client, path(&budget, budget_id)).await,
                get_json(&client, path(&reference, kept_id)).await
            );
        }
    }
    assert!(
        health["memory"]["resident_bytes"].as_u64().unwrap() > 0,
        "{health}"
    );
    assert!(health["data_dir_bytes"].as_u64().unwrap() > 0, "{health}");
    let kept = get_json(&client, format!("{reference}/healthz")).await;
    assert_eq!(kept["timelines"]["traced_in_memory"], 3, "{kept}");
    assert_eq!(kept["timelines"]["solved_in_memory"], 3, "{kept}");
    assert!(
        kept["memory"]["traced_bytes"].as_u64().unwrap() > 0,
        "{kept}"
    );
    let status = get_json(&client, format!("{budget}/v1/timelines/{}", ids[0][0])).await;
    assert_eq!(status["traced_in_memory"], false, "{status}");

    // A preview reads its traced state back, and the budget drops it after.
    let preview = format!("{budget}/v1/timelines/{}/frames/2/preview.png", ids[0][0]);
    assert_eq!(client.get(preview).send().await.unwrap().status(), 200);
    let status = get_json(&client, format!("{budget}/v1/timelines/{}", ids[0][0])).await;
    assert!(
        status["rebuild_seconds"].as_f64().unwrap() > 0.0,
        "{status}"
    );
    assert_eq!(status["rebuilt_from"], "traced_state", "{status}");
    let health = get_json(&client, format!("{budget}/healthz")).await;
    assert_eq!(health["timelines"]["traced_in_memory"], 0, "{health}");

    // Relit and refined after eviction, the numbers are the kept server's: one timeline
    // without its traced state on disk (traced again from its scene, and saved), one refined
    // on the state read back, then relit on that state read back again.
    let traced = |id: &str| dirs[0].join(id).join("traced.bin");
    std::fs::remove_file(traced(&ids[0][1])).unwrap();
    let exposure = async |base: &str, id: &str| -> String {
        let preview = format!("{base}/v1/timelines/{id}/frames/1/preview.png");
        let response = client.get(preview).send().await.unwrap();
        assert_eq!(response.status(), 200);
        response.headers()["x-exposure"]
            .to_str()
            .unwrap()
            .to_string()
    };
    let before = exposure(&budget, &ids[0][2]).await;
    let relight = r#"{"materials": [{"material": "light", "emission": [5, 5, 5]}]}"#;
    let mut after = [Vec::new(), Vec::new()];
    for ((base, ids), after) in [&budget, &reference].into_iter().zip(&ids).zip(&mut after) {
        let url = format!("{base}/v1/timelines/{}/materials", ids[1]);
        let response = client.post(url).body(relight).send().await.unwrap();
        assert_eq!(response.status(), 202);
        let url = format!("{base}/v1/timelines/{}/lines?add=3000", ids[2]);
        assert_eq!(client.post(url).send().await.unwrap().status(), 202);
        for id in &ids[1..] {
            assert_eq!(wait(&client, base, id, HANG).await["status"], "done");
        }
        let url = format!("{base}/v1/timelines/{}/materials", ids[2]);
        let response = client.post(url).body(relight).send().await.unwrap();
        assert_eq!(response.status(), 202);
        for id in &ids[1..] {
            let status = wait(&client, base, id, HANG).await;
            assert_eq!(status["status"], "done");
            after.push(status["rebuilt_from"].clone());
            let frame = format!("{base}/v1/timelines/{id}/frames/3");
            after.push(get_json(&client, frame).await);
        }
    }
    // The timeline's exposure is the relit frames' (not the one kept for the frames before).
    let relit = exposure(&budget, &ids[0][2]).await;
    assert_ne!(relit, before);
    assert_eq!(relit, exposure(&reference, &ids[1][2]).await);
    // What the budget server's were rebuilt from; the kept server's never were.
    assert_eq!(after[0][0], "scene");
    assert_eq!(after[0][2], "traced_state");
    assert!(after[1][0].is_null() && after[1][2].is_null());
    assert_eq!([&after[0][1], &after[0][3]], [&after[1][1], &after[1][3]]);
    assert!(traced(&ids[0][1]).exists(), "traced again, not saved");
    for id in &ids[1] {
        assert!(dirs[1].join(id).join("job.json").exists());
        assert!(!dirs[1].join(id).join("traced.bin").exists(), "written");
    }
    for dir in dirs {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// Timelines of sample `name` posted with each of `queries` in turn, each waited for until it
/// is done: their ids.
async fn done_timelines(
    client: &reqwest::Client,
    base: &str,
    queries: impl Iterator<Item = String>,
    name: &str,
) -> Vec<String> {
    let mut ids = Vec::new();
    for query in queries {
        let (id, _) = create(client, base, &query, name).await;
        assert_eq!(wait(client, base, &id, HANG).await["status"], "done");
        ids.push(id);
    }
    ids
}

/// Flips one bit of the byte at `at` (from the end if negative) of `path`.
fn flip(path: &std::path::Path, at: i64) {
    let mut bytes = std::fs::read(path).unwrap();
    let at = if at < 0 { bytes.len() as i64 + at } else { at } as usize;
    bytes[at] ^= 0x04;
    std::fs::write(path, bytes).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn damaged_files_are_reported_never_served_and_kept() {
    let (dir, config) = fresh_data_dir("damage");
    let first = start(config.clone()).await;
    let client = reqwest::Client::new();
    let queries = (1..=6).map(|seed| format!("lines=20000&fps=4&seed={seed}"));
    let ids = done_timelines(&client, &first, queries, "cornell_moving.gltf").await;
    let [
        flipped_frame,
        cut_frames,
        flipped_record,
        flipped_scene,
        flipped_traced,
        intact,
    ] = ids.clone().try_into().unwrap();
    let frame = |base: &str, id: &str, f: usize| format!("{base}/v1/timelines/{id}/frames/{f}");
    let intact_frame = get_json(&client, frame(&first, &intact, 4)).await;
    // A bit flipped in the last frame's numbers, a file cut short, a bit flipped in a record
    // and in a stored scene.
    flip(&dir.join(&flipped_frame).join("frames.bin"), -100);
    let frames = dir.join(&cut_frames).join("frames.bin");
    let bytes = std::fs::read(&frames).unwrap();
    std::fs::write(&frames, &bytes[..bytes.len() - 1]).unwrap();
    flip(&dir.join(&flipped_record).join("job.json"), 200);
    // (The scene is read only when no traced state is.)
    flip(&dir.join(&flipped_scene).join("scene.bin"), 1000);
    std::fs::remove_file(dir.join(&flipped_scene).join("traced.bin")).unwrap();
    flip(&dir.join(&flipped_traced).join("traced.bin"), -1000);
    let files = |id: &str| {
        let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir.join(id))
            .unwrap()
            .map(|f| f.unwrap())
            .map(|f| {
                (
                    f.file_name().into_string().unwrap(),
                    std::fs::read(f.path()).unwrap(),
                )
            })
            .collect();
        files.sort();
        files
    };
    let damaged_files: Vec<_> = ids[..5].iter().map(|id| files(id)).collect();

    // The server starts, and serves what is whole.
    let second = start(config).await;
    assert_eq!(
        intact_frame,
        get_json(&client, frame(&second, &intact, 4)).await
    );
    let listed: Value = get_json(&client, format!("{second}/v1/timelines")).await;
    assert_eq!(listed["timelines"].as_array().unwrap().len(), 6, "{listed}");
    let failed = |status: &Value, words: &[&str]| {
        assert_eq!(status["status"], "failed", "{status}");
        let error = status["error"].as_str().unwrap();
        for word in words {
            assert!(error.contains(word), "{word:?} not in {error:?}");
        }
    };
    // Found at start-up: a cut file, a damaged record.
    let status = get_json(&client, format!("{second}/v1/timelines/{cut_frames}")).await;
    failed(&status, &["frames.bin is damaged", "bytes of", "kept in"]);
    let status = get_json(&client, format!("{second}/v1/timelines/{flipped_record}")).await;
    failed(&status, &["job.json is damaged", "checksum"]);
    // Found when read: a frame's numbers, the scene traced again and the traced state read
    // back for a preview.
    let whole = get_json(&client, frame(&second, &flipped_frame, 0)).await;
    assert_eq!(whole["frame"], 0, "{whole}");
    let status = get_json(&client, format!("{second}/v1/timelines/{flipped_frame}")).await;
    let last = status["frames"].as_u64().unwrap() as usize - 1;
    let response = client
        .get(frame(&second, &flipped_frame, last))
        .send()
        .await
        .unwrap();
    assert_eq!(response.status(), 409);
    let problem: Value = response.json().await.unwrap();
    let checksum = format!("frame {last}'s checksum");
    assert!(
        problem["detail"].as_str().unwrap().contains(&checksum),
        "{problem}"
    );
    let status = get_json(&client, format!("{second}/v1/timelines/{flipped_frame}")).await;
    failed(&status, &["frames.bin is damaged", &checksum]);
    // Nothing more of it is read from disk.
    let again = client
        .get(frame(&second, &flipped_frame, 0))
        .send()
        .await
        .unwrap();
    assert_eq!(again.status(), 409);
    let preview = format!("{second}/v1/timelines/{flipped_scene}/frames/0/preview.png");
    let response = client.get(preview).send().await.unwrap();
    assert_eq!(response.status(), 409);
    let status = get_json(&client, format!("{second}/v1/timelines/{flipped_scene}")).await;
    failed(&status, &["scene.bin is damaged", "checksum"]);
    let preview = format!("{second}/v1/timelines/{flipped_traced}/frames/0/preview.png");
    let response = client.get(preview).send().await.unwrap();
    assert_eq!(response.status(), 409);
    let status = get_json(&client, format!("{second}/v1/timelines/{flipped_traced}")).await;
    failed(&status, &["traced.bin is damaged", "checksum"]);
    for id in &ids[..5] {
        let relight = format!("{second}/v1/timelines/{id}/materials");
        let body = r#"{"materials": [{"material": "light", "emission": [5, 5, 5]}]}"#;
        let response = client.post(relight).body(body).send().await.unwrap();
        assert_eq!(response.status(), 409, "{id}");
    }
    // Every damaged file is kept as it was, for inspection.
    let after: Vec<_> = ids[..5].iter().map(|id| files(id)).collect();
    assert!(
        after == damaged_files,
        "the damaged timelines' files changed"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_fails_the_job_and_leaves_the_files_before_whole() {
    let (dir, config) = fresh_data_dir("full");
    let base = start(config).await;
    let client = reqwest::Client::new();
    // A disk that fills when the frames are written: their temporary file is the full device.
    let full = |id: &str| {
        std::os::unix::fs::symlink("/dev/full", dir.join(id).join("frames.tmp")).unwrap();
    };
    let (id, _) = create(&client, &base, "lines=20000&fps=4", "cornell_moving.gltf").await;
    full(&id);
    let status = wait(&client, &base, &id, HANG).await;
    assert_eq!(status["status"], "failed", "{status}");
    let error = status["error"].as_str().unwrap();
    assert!(
        error.contains("could not be saved") && error.contains("No space left"),
        "{error}"
    );
    assert!(!dir.join(&id).join("frames.bin").exists());
    assert!(!dir.join(&id).join("frames.tmp").exists());

    // A refinement of a done timeline, the disk full when its frames are written: the job
    // fails, and the frames of the version before stay on disk as they were.
    let (done, _) = create(&client, &base, "lines=20000&fps=4", "cornell_moving.gltf").await;
    assert_eq!(wait(&client, &base, &done, HANG).await["status"], "done");
    let before = std::fs::read(dir.join(&done).join("frames.bin")).unwrap();
    full(&done);
    let refine = format!("{base}/v1/timelines/{done}/lines?add=2000");
    assert_eq!(client.post(refine).send().await.unwrap().status(), 202);
    let status = wait(&client, &base, &done, HANG).await;
    assert_eq!(status["status"], "failed", "{status}");
    assert_eq!(
        std::fs::read(dir.join(&done).join("frames.bin")).unwrap(),
        before
    );

    // The disk full when the traced state is written: the job is done all the same (its
    // traced state is traced again when it is needed).
    let (traced, _) = create(&client, &base, "lines=20000&fps=4", "cornell_moving.gltf").await;
    std::os::unix::fs::symlink("/dev/full", dir.join(&traced).join("traced.tmp")).unwrap();
    assert_eq!(wait(&client, &base, &traced, HANG).await["status"], "done");
    assert!(!dir.join(&traced).join("traced.bin").exists());
    assert!(!dir.join(&traced).join("traced.tmp").exists());

    // A scene that cannot be stored (the data directory gone, a file in its place) is refused
    // with 507 before anything is accepted.
    let listed = async || {
        let list = get_json(&client, format!("{base}/v1/timelines")).await;
        list["timelines"].as_array().unwrap().len()
    };
    let count = listed().await;
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::write(&dir, b"not a directory").unwrap();
    let response = post(
        &client,
        &base,
        "lines=20000&fps=4",
        "model/gltf+json",
        scene("cornell_box.gltf"),
    )
    .await;
    assert_eq!(response.status(), 507);
    let problem: Value = response.json().await.unwrap();
    let detail = problem["detail"].as_str().unwrap();
    assert!(detail.contains("nothing was accepted"), "{problem}");
    assert_eq!(listed().await, count);
    std::fs::remove_file(&dir).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retention_removes_finished_timelines_past_a_count_or_an_age() {
    let (dir, config) = fresh_data_dir("retain-count");
    let counted = start(Config {
        retention: radiosity::service::Retention {
            days: None,
            count: Some(2),
        },
        ..config
    })
    .await;
    let client = reqwest::Client::new();
    let queries = (1..=3).map(|seed| format!("lines=5000&fps=2&seed={seed}"));
    let ids = done_timelines(&client, &counted, queries, "cornell_box.gltf").await;
    // Removed once the third has ended: the oldest, from memory and disk.
    let gone = |base: String, id: String| {
        let client = client.clone();
        async move {
            let start = Instant::now();
            loop {
                let url = format!("{base}/v1/timelines/{id}");
                if client.get(url).send().await.unwrap().status() == 404 {
                    return;
                }
                assert!(start.elapsed() < Duration::from_secs(10), "{id} kept");
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
    };
    gone(counted.clone(), ids[0].clone()).await;
    assert!(!dir.join(&ids[0]).exists());
    for id in &ids[1..] {
        let status = get_json(&client, format!("{counted}/v1/timelines/{id}")).await;
        assert_eq!(status["status"], "done");
        assert!(dir.join(id).exists());
    }
    let health = get_json(&client, format!("{counted}/healthz")).await;
    assert_eq!(health["retention"]["count"], 2, "{health}");

    // By age (three seconds): the first is removed when the next ends past it.
    let (dir, config) = fresh_data_dir("retain-days");
    let aged = start(Config {
        retention: radiosity::service::Retention {
            days: Some(3.0 / 86_400.0),
            count: None,
        },
        ..config
    })
    .await;
    let (old, _) = create(&client, &aged, "lines=5000&fps=2", "cornell_box.gltf").await;
    assert_eq!(wait(&client, &aged, &old, HANG).await["status"], "done");
    let ended = Instant::now();
    let (new, _) = create(&client, &aged, "lines=5000&fps=2", "cornell_box.gltf").await;
    assert_eq!(wait(&client, &aged, &new, HANG).await["status"], "done");
    if ended.elapsed() < Duration::from_secs(2) {
        // Not yet past its age.
        let status = get_json(&client, format!("{aged}/v1/timelines/{old}")).await;
        assert_eq!(status["status"], "done");
    }
    tokio::time::sleep(Duration::from_secs(4).saturating_sub(ended.elapsed())).await;
    let (last, _) = create(&client, &aged, "lines=5000&fps=2", "cornell_box.gltf").await;
    assert_eq!(wait(&client, &aged, &last, HANG).await["status"], "done");
    gone(aged.clone(), old.clone()).await;
    assert!(!dir.join(&old).exists());
    let status = get_json(&client, format!("{aged}/v1/timelines/{last}")).await;
    assert_eq!(status["status"], "done");
    let _ = std::fs::remove_dir_all(&dir);
}
