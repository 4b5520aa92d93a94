//! isochron's lab service: the HTTP API, the WebSocket stream and the dashboard.
//!
//! [`app`] builds the router from an [`AppState`], so tests can serve it on a
//! real port (or call it directly) exactly as `isochron serve` does.

pub mod error;

use std::{
    net::SocketAddr,
    path::PathBuf,
    sync::Arc,
    time::{Instant, SystemTime, UNIX_EPOCH},
};

use axum::{Json, Router, extract::State, routing::get};
use serde::Serialize;
use tower_http::services::{ServeDir, ServeFile};

pub use error::AppError;

/// The revision this binary was built from (`git rev-parse --short HEAD`).
pub const GIT_REV: &str = env!("ISOCHRON_GIT_REV");

/// `0.1.0 (git 1234abcd)`: what `--version` and `/api/health` show.
pub const VERSION: &str = concat!(
    env!("CARGO_PKG_VERSION"),
    " (git ",
    env!("ISOCHRON_GIT_REV"),
    ")"
);

/// The built dashboard (`web/dist`) as found from this source tree.
pub fn default_web_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../web/dist"))
}

/// What every handler shares.
#[derive(Debug)]
pub struct AppState {
    /// Folder of the built dashboard, served at `/`.
    pub web_dir: PathBuf,
    /// When the service started.
    pub started: Instant,
}

impl AppState {
    /// A state serving the dashboard from `web_dir`.
    pub fn new(web_dir: PathBuf) -> Self {
        Self {
            web_dir,
            started: Instant::now(),
        }
    }
}

/// `GET /api/health`.
#[derive(Debug, Serialize)]
pub struct Health {
    /// Always `"ok"` when the service answers.
    pub status: &'static str,
    /// Version and git revision.
    pub version: &'static str,
    /// Seconds since the service started.
    pub uptime_s: f64,
    /// Unix time of the answer, seconds.
    pub t_s: f64,
}

async fn health(State(state): State<Arc<AppState>>) -> Json<Health> {
    let t_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    Json(Health {
        status: "ok",
        version: VERSION,
        uptime_s: state.started.elapsed().as_secs_f64(),
        t_s,
    })
}

async fn api_not_found() -> AppError {
    AppError::NotFound("no such API endpoint".to_owned())
}

/// The service's router: the API under `/api`, the dashboard everywhere else.
pub fn app(state: Arc<AppState>) -> Router {
    let index = state.web_dir.join("index.html");
    let web = ServeDir::new(&state.web_dir).fallback(ServeFile::new(index));
    let api = Router::new()
        .route("/health", get(health))
        .fallback(api_not_found);
    Router::new()
        .nest("/api", api)
        .fallback_service(web)
        .with_state(state)
}

/// Why `isochron serve` refuses to start.
#[derive(Debug, thiserror::Error)]
pub enum ServeConfigError {
    /// Binding beyond loopback needs a token, or anyone on the network could command the robot.
    #[error(
        "refusing to bind {0} without --token: anyone on that network could command the robot; \
         bind 127.0.0.1 or set a token"
    )]
    OpenWithoutToken(SocketAddr),
}

/// Checks the bind address against the access-control rule of CONTRACT.md.
pub fn check_bind(addr: SocketAddr, token: Option<&str>) -> Result<(), ServeConfigError> {
    if addr.ip().is_loopback() || token.is_some_and(|t| !t.is_empty()) {
        Ok(())
    } else {
        Err(ServeConfigError::OpenWithoutToken(addr))
    }
}
