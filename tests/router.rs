//! The router called directly (`tower::ServiceExt::oneshot`, no socket): every parameter error
//! is a 400 problem naming the parameter, and every route's query parameters are the ones
//! `api/openapi.json` documents for it (the document cannot drift from the code's query types).

use std::collections::BTreeSet;

use axum::body::Body;
use axum::http::{Method, Request, StatusCode, header};
use radiosity::service::{AppState, Config, app};
use serde_json::Value;
use tower::ServiceExt;

/// The router's answer to `method uri` with `body` (a glTF when it is not empty): status and
/// JSON document (`null` when the answer is not JSON).
async fn call(method: Method, uri: &str, body: Vec<u8>) -> (StatusCode, Value) {
    let router = app(AppState::new(Config::default()).unwrap());
    let mut request = Request::builder().method(method).uri(uri);
    if !body.is_empty() {
        request = request.header(header::CONTENT_TYPE, "model/gltf+json");
    }
    let response = router
        .oneshot(request.body(Body::from(body)).unwrap())
        .await
        .unwrap();
    let status = response.status();
    let bytes = axum::body::to_bytes(response.into_body(), usize::MAX)
        .await
        .unwrap();
    (
        status,
        serde_json::from_slice(&bytes).unwrap_or(Value::Null),
    )
}

fn furnace() -> Vec<u8> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/furnace.gltf");
    std::fs::read(path).unwrap()
}

#[tokio::test]
async fn a_bad_bake_request_is_a_400_naming_the_parameter() {
    for (query, needle) in [
        ("lines=5", "lines must be a whole number from 1000"),
        ("lines=2000&preset=draft", "give lines or preset, not both"),
        ("preset=ultra", "preset: unknown preset \"ultra\""),
        ("sky=1,x,2,3", "sky: \"1,x,2,3\" is not r,g,b"),
        ("fps=0", "fps must be in (0, 1000], not 0"),
        ("fps=abc", "fps: \"abc\" is not a finite number"),
        ("start=2&end=1", "start (2 s) is after end (1 s)"),
        (
            "patch_size=source&patch_budget=5",
            "patch_budget applies to patch_size=auto only, not source",
        ),
        ("patch_budget=0", "patch_budget must be at least 1"),
        ("patch_size=-1", "patch_size: \"-1\" is not auto, source"),
        ("seed=-1", "seed: \"-1\" is not a whole number"),
        (
            "lines=1000&lines=2000",
            "parameter `lines` is given more than once",
        ),
        (
            "line=1000",
            "unknown parameter `line`, expected one of `fps`",
        ),
    ] {
        let (status, problem) =
            call(Method::POST, &format!("/v1/timelines?{query}"), furnace()).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{query}: {problem}");
        let detail = problem["detail"].as_str().unwrap_or_default();
        assert!(detail.contains(needle), "{query}: {detail}");
        assert_eq!(problem["status"], 400, "{query}: {problem}");
    }
    // The same request, well formed, is taken.
    let (status, created) = call(Method::POST, "/v1/timelines?preset=draft", furnace()).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{created}");
}

/// The query parameters the router takes on `method path`, from its answer to a parameter it
/// cannot have: the names a 400 lists as expected (none for a request that takes none).
async fn taken(method: Method, path: &str) -> BTreeSet<String> {
    let body = if method == Method::POST {
        furnace()
    } else {
        Vec::new()
    };
    let (status, problem) = call(method.clone(), &format!("{path}?zz_probe=1"), body).await;
    let detail = problem["detail"].as_str().unwrap_or_default().to_string();
    assert_eq!(
        status,
        StatusCode::BAD_REQUEST,
        "{method} {path}: {problem}"
    );
    if detail.ends_with("this request takes no parameters") {
        return BTreeSet::new();
    }
    // serde's words: "expected `a`", "expected `a` or `b`", "expected one of `a`, `b`, `c`".
    let (_, expected) =
        (detail.split_once("expected ")).unwrap_or_else(|| panic!("{method} {path}: {detail}"));
    expected
        .split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_string)
        .collect()
}

#[tokio::test]
async fn every_route_takes_the_query_parameters_the_openapi_document_lists() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("api/openapi.json");
    let document: Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let mut routes = 0;
    for (template, operations) in document["paths"].as_object().unwrap() {
        for (method, operation) in operations.as_object().unwrap() {
            let method: Method = method.to_uppercase().parse().unwrap();
            let documented: BTreeSet<String> = (operation["parameters"].as_array())
                .into_iter()
                .flatten()
                .filter(|p| p["in"] == "query")
                .map(|p| p["name"].as_str().unwrap().to_string())
                .collect();
            let path = template
                .replace("{id}", "0123456789abcdef")
                .replace("{frame}", "0");
            let code = taken(method.clone(), &path).await;
            assert_eq!(
                code, documented,
                "{method} {template}: the code, the document"
            );
            routes += 1;
        }
    }
    assert!(routes >= 14, "{routes} routes documented");
}

/// The schema `schema` points to in `document` (following `$ref`).
fn resolve<'a>(document: &'a Value, schema: &'a Value) -> &'a Value {
    match schema["$ref"].as_str() {
        Some(reference) => {
            let path = reference.trim_start_matches("#/");
            (path.split('/')).fold(document, |node, key| &node[key])
        }
        None => schema,
    }
}

/// Every field of `value` that `schema` does not document, and every field it requires that
/// `value` lacks, as `where: field`, through nested objects and arrays.
fn undocumented(document: &Value, schema: &Value, value: &Value, at: &str) -> Vec<String> {
    let schema = resolve(document, schema);
    let mut found = Vec::new();
    match value {
        Value::Object(fields) => {
            let Some(properties) = schema["properties"].as_object() else {
                return found;
            };
            for (name, field) in fields {
                match properties.get(name) {
                    Some(inner) => {
                        let at = format!("{at}.{name}");
                        found.extend(undocumented(document, inner, field, &at));
                    }
                    None => found.push(format!("{at}: {name} (not documented)")),
                }
            }
            for name in schema["required"].as_array().into_iter().flatten() {
                let name = name.as_str().unwrap();
                if !fields.contains_key(name) {
                    found.push(format!("{at}: {name} (required, missing)"));
                }
            }
        }
        Value::Array(items) if schema["items"].is_object() => {
            for (k, item) in items.iter().enumerate() {
                let at = format!("{at}[{k}]");
                found.extend(undocumented(document, &schema["items"], item, &at));
            }
        }
        _ => {}
    }
    found
}

#[tokio::test]
async fn every_json_answer_has_the_fields_the_openapi_document_gives_it() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("api/openapi.json");
    let document: Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let state = AppState::new(Config::default()).unwrap();
    let send = |method: Method, uri: String, body: Option<(&'static str, Vec<u8>)>| {
        let router = app(state.clone());
        async move {
            let mut request = Request::builder().method(method).uri(uri);
            let body = match body {
                Some((kind, bytes)) => {
                    request = request.header(header::CONTENT_TYPE, kind);
                    Body::from(bytes)
                }
                None => Body::empty(),
            };
            let response = router.oneshot(request.body(body).unwrap()).await.unwrap();
            let status = response.status();
            let bytes = axum::body::to_bytes(response.into_body(), usize::MAX)
                .await
                .unwrap();
            (
                status,
                serde_json::from_slice::<Value>(&bytes).unwrap_or(Value::Null),
            )
        }
    };
    let schema = |path: &str, method: &str, status: &str| {
        document["paths"][path][method]["responses"][status]["content"]["application/json"]
            ["schema"]
            .clone()
    };
    let mut checked = Vec::new();
    let mut check = |name: &str, schema: Value, value: &Value| {
        assert!(!schema.is_null(), "{name}: no schema documented");
        let wrong = undocumented(&document, &schema, value, name);
        assert!(wrong.is_empty(), "{wrong:#?}\n{value:#}");
        checked.push(name.to_string());
    };
    let scene = Some(("model/gltf+json", furnace()));
    let (status, created) = send(Method::POST, "/v1/timelines?preset=draft".into(), scene).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{created}");
    check("created", schema("/v1/timelines", "post", "202"), &created);
    let id = created["id"].as_str().unwrap().to_string();
    let timeline = format!("/v1/timelines/{id}");
    let started = std::time::Instant::now();
    let status = loop {
        let (_, status) = send(Method::GET, timeline.clone(), None).await;
        if status["status"] == "done" || started.elapsed().as_secs() > 120 {
            break status;
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    };
    assert_eq!(status["status"], "done", "{status}");
    check(
        "status",
        schema("/v1/timelines/{id}", "get", "200"),
        &status,
    );
    for (name, path, template) in [
        ("list", "/v1/timelines".to_string(), "/v1/timelines"),
        (
            "patches",
            format!("{timeline}/patches"),
            "/v1/timelines/{id}/patches",
        ),
        (
            "frame",
            format!("{timeline}/frames/0"),
            "/v1/timelines/{id}/frames/{frame}",
        ),
        (
            "stats",
            format!("{timeline}/stats"),
            "/v1/timelines/{id}/stats",
        ),
        ("health", "/healthz".to_string(), "/healthz"),
        (
            "probes",
            format!("{timeline}/frames/0/probes.json?spacing=0.5"),
            "/v1/timelines/{id}/frames/{frame}/probes.json",
        ),
        (
            "lightmaps' manifest",
            format!("{timeline}/lightmap.json?texels_per_unit=4"),
            "/v1/timelines/{id}/lightmap.json",
        ),
    ] {
        let (status, value) = send(Method::GET, path, None).await;
        assert_eq!(status, StatusCode::OK, "{name}: {value}");
        check(name, schema(template, "get", "200"), &value);
    }
    let relight =
        serde_json::json!({"materials": [{"material": 0, "reflectance": [0.5, 0.5, 0.5]}]});
    let body = Some(("application/json", relight.to_string().into_bytes()));
    let path = format!("{timeline}/materials");
    let (status, rerun) = send(Method::POST, path, body).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{rerun}");
    check(
        "relight",
        schema("/v1/timelines/{id}/materials", "post", "202"),
        &rerun,
    );
    let (status, problem) = send(Method::GET, format!("{timeline}/frames/99"), None).await;
    assert!(status.is_client_error(), "{problem}");
    let problem_schema = document["components"]["schemas"]["Problem"].clone();
    check("problem", problem_schema.clone(), &problem);
    // Probes: a spacing that is not positive, or too fine for the scene, is the request's fault.
    for (spacing, needle) in [("0", "positive"), ("1e-5", "more than")] {
        let path = format!("{timeline}/frames/0/probes.json?spacing={spacing}");
        let (status, problem) = send(Method::GET, path, None).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{problem}");
        assert!(
            problem["detail"].as_str().unwrap().contains(needle),
            "{problem}"
        );
        check("probes' problem", problem_schema.clone(), &problem);
    }
    // Lightmaps: the geometry and each file of a frame, by their first bytes; a density that
    // is not positive or too fine for the service is the request's fault.
    let bytes = |path: String| {
        let router = app(state.clone());
        async move {
            let request = Request::builder().uri(path).body(Body::empty()).unwrap();
            let response = router.oneshot(request).await.unwrap();
            let status = response.status();
            let body = axum::body::to_bytes(response.into_body(), usize::MAX)
                .await
                .unwrap();
            (status, body.to_vec())
        }
    };
    for (file, magic) in [
        ("lightmap.glb", &b"glTF"[..]),
        ("frames/0/lightmap.exr", &[0x76, 0x2f, 0x31, 0x01]),
        (
            "frames/0/lightmap.ktx2",
            &[0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB],
        ),
        ("frames/0/lightmap.png", &[0x89, b'P', b'N', b'G']),
    ] {
        let (status, body) = bytes(format!("{timeline}/{file}?texels_per_unit=4")).await;
        assert_eq!(
            status,
            StatusCode::OK,
            "{file}: {}",
            String::from_utf8_lossy(&body)
        );
        assert!(body.starts_with(magic), "{file}");
        for (density, needle) in [("0", "positive"), ("1e6", "allowed")] {
            let path = format!("{timeline}/{file}?texels_per_unit={density}");
            let (status, problem) = send(Method::GET, path, None).await;
            assert_eq!(status, StatusCode::BAD_REQUEST, "{file}: {problem}");
            let detail = problem["detail"].as_str().unwrap();
            assert!(detail.contains(needle), "{file}: {problem}");
        }
    }
    // The manifest's files are these routes, holding the quantity asked for.
    let path = format!("{timeline}/lightmap.json?quantity=light");
    let (_, manifest) = send(Method::GET, path.clone(), None).await;
    assert_eq!(manifest["quantity"], "light", "{manifest}");
    let first = &manifest["frames"][0];
    assert_eq!(first["state"], 0, "{manifest}");
    assert!(
        first["lightmap"]
            .as_str()
            .unwrap()
            .ends_with("&quantity=light")
    );
    let (status, problem) = send(Method::GET, format!("{path}x"), None).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{problem}");
    for (key, magic) in [
        ("lightmap", &[0x76, 0x2f, 0x31, 0x01][..]),
        ("rgbm", b"\x89PNG"),
    ] {
        let (status, body) = bytes(first[key].as_str().unwrap().to_string()).await;
        assert_eq!(status, StatusCode::OK, "{key}");
        assert!(body.starts_with(magic), "{key}");
    }
    // The three.js example's page and what it imports.
    for (path, start) in [
        (
            format!("{timeline}/lightmapped?frame=0&texels_per_unit=4"),
            "<!doctype html>",
        ),
        (
            "/viewer/lightmapped.js".to_string(),
            "// The service's lightmaps",
        ),
        ("/viewer/three/three.module.min.js".to_string(), "/**"),
        (
            "/viewer/three/addons/loaders/GLTFLoader.js".to_string(),
            "import",
        ),
    ] {
        let (status, body) = bytes(path.clone()).await;
        assert_eq!(status, StatusCode::OK, "{path}");
        assert!(String::from_utf8_lossy(&body).starts_with(start), "{path}");
    }
    for (path, status) in [
        (
            format!("{timeline}/lightmapped?probe_spacing=0"),
            StatusCode::BAD_REQUEST,
        ),
        (
            format!("{timeline}/lightmapped?overlay=error"),
            StatusCode::BAD_REQUEST,
        ),
        (
            "/v1/timelines/0123456789abcdef/lightmapped".to_string(),
            StatusCode::NOT_FOUND,
        ),
        (
            "/viewer/three/../Cargo.toml".to_string(),
            StatusCode::NOT_FOUND,
        ),
    ] {
        let (got, problem) = send(Method::GET, path.clone(), None).await;
        assert_eq!(got, status, "{path}: {problem}");
    }
    assert_eq!(checked.len(), 13, "{checked:?}");
}
