//! The service on a real port: health, the dashboard page, JSON 404s.

use std::sync::Arc;

use isochron_tests::http;
use server::{AppState, app};

async fn start(web_dir: std::path::PathBuf) -> std::net::SocketAddr {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let router = app(Arc::new(AppState::new(web_dir)));
    tokio::spawn(async move { axum::serve(listener, router).await });
    addr
}

/// A dashboard folder of its own for each test (tests run in parallel).
fn fake_web_dir() -> std::path::PathBuf {
    let dir = tempfile::Builder::new()
        .prefix("isochron-web-")
        .tempdir()
        .expect("a temporary directory")
        .keep();
    std::fs::write(
        dir.join("index.html"),
        "<!doctype html><title>isochron</title>",
    )
    .unwrap();
    dir
}

#[tokio::test]
async fn health_answers_ok_with_version() {
    let addr = start(fake_web_dir()).await;
    let r = http(addr, "GET", "/api/health", &[], b"").await.unwrap();
    assert_eq!(r.status, 200);
    let j = r.json().unwrap();
    assert_eq!(j["status"], "ok");
    assert!(j["version"].as_str().unwrap().contains("git"));
    assert!(j["uptime_s"].as_f64().unwrap() >= 0.0);
}

#[tokio::test]
async fn the_page_is_served_at_root_and_for_client_routes() {
    let addr = start(fake_web_dir()).await;
    for path in ["/", "/trials"] {
        let r = http(addr, "GET", path, &[], b"").await.unwrap();
        assert_eq!(r.status, 200, "{path}");
        assert!(String::from_utf8_lossy(&r.body).contains("<title>isochron</title>"));
    }
}

#[tokio::test]
async fn unknown_api_paths_are_json_404() {
    let addr = start(fake_web_dir()).await;
    let r = http(addr, "GET", "/api/nope", &[], b"").await.unwrap();
    assert_eq!(r.status, 404);
    assert!(r.json().unwrap()["error"].is_string());
}
