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
