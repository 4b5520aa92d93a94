//! isochron's lab service: the HTTP API, the WebSocket stream and the dashboard.
//!
//! [`app`] builds the router from an [`AppState`], so tests can serve it on a
//! real port (or call it directly) exactly as `isochron serve` does. The
//! message schema of the WebSocket stream is in `server/README.md`.

// Outside tests the service returns errors and never panics on them: no
// `unwrap()`/`expect()` (tests may: clippy.toml's allow-*-in-tests).
#![cfg_attr(not(test), warn(clippy::unwrap_used, clippy::expect_used))]

pub mod api;
pub mod calibration;
pub mod config;
pub mod demo;
pub mod error;
pub mod lab;
pub mod records;
pub mod runs;
pub mod runtime;
pub mod serve;
pub mod typescript;
pub mod viz;
pub mod world;
pub mod ws;

use std::{
    net::SocketAddr,
    path::PathBuf,
    sync::Arc,
    time::{Instant, SystemTime, UNIX_EPOCH},
};

use axum::{
    Json, Router,
    extract::{DefaultBodyLimit, State},
    http::HeaderValue,
    routing::{get, post},
};
use serde::Serialize;
use tower_http::{
    cors::{AllowOrigin, CorsLayer},
    services::{ServeDir, ServeFile},
};

pub use error::AppError;
pub use lab::{Lab, LabOptions};
pub use records::Records;

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

/// File name of `isochron fri doctor`'s last report in the data folder.
pub const FRI_DOCTOR_REPORT_FILE: &str = "fri-doctor.json";

/// Default largest request body, bytes.
pub const DEFAULT_BODY_LIMIT_BYTES: usize = 64 * 1024;

/// What every handler shares.
#[derive(Debug)]
pub struct AppState {
    /// Folder of the built dashboard, served at `/`.
    pub web_dir: PathBuf,
    /// When the service started.
    pub started: Instant,
    /// Bearer token every command needs (none: commands are open, loopback only).
    pub token: Option<String>,
    /// The running lab (none: state and command endpoints answer 503).
    pub lab: Option<Arc<Lab>>,
    /// Trial records (none: trial endpoints answer 503).
    pub records: Option<Arc<Records>>,
    /// Largest request body, bytes.
    pub body_limit_bytes: usize,
    /// Other web origins allowed to call the API from a browser.
    pub cors_origins: Vec<String>,
    /// Why trials are refused (a real lab without calibration); none: allowed.
    /// The calibration desk's rule replaces it when there is a desk.
    pub trials_refused: Option<String>,
    /// The calibration file and its steps (`/api/calibration`); none: 503.
    pub calibration: Option<Arc<calibration::CalibrationDesk>>,
    /// The FRI version the lab's client speaks.
    pub fri_version: rt_core::fri::FriVersion,
    /// Where `isochron fri doctor` writes its last report (none: not shown).
    pub fri_doctor_report: Option<PathBuf>,
    /// Batch runs (`/api/runs`).
    pub runs: Arc<runs::Runs>,
    /// Demo mode (`--demo`, `/api/demo`): off unless the runner was started.
    pub demo: Arc<demo::Demo>,
}

impl AppState {
    /// A state serving the dashboard from `web_dir`, with no lab, no records, no token.
    pub fn new(web_dir: PathBuf) -> Self {
        Self {
            web_dir,
            started: Instant::now(),
            token: None,
            lab: None,
            records: None,
            trials_refused: None,
            calibration: None,
            body_limit_bytes: DEFAULT_BODY_LIMIT_BYTES,
            cors_origins: Vec::new(),
            fri_version: rt_core::fri::FriVersion::default(),
            fri_doctor_report: None,
            runs: Arc::default(),
            demo: Arc::default(),
        }
    }

    /// The FRI version of the lab and the file of `isochron fri doctor`'s last
    /// report (`GET /api/fri`).
    pub fn with_fri(mut self, version: rt_core::fri::FriVersion, doctor_report: PathBuf) -> Self {
        self.fri_version = version;
        self.fri_doctor_report = Some(doctor_report);
        self
    }

    /// Requires this bearer token for commands (an empty token means none).
    pub fn with_token(mut self, token: Option<String>) -> Self {
        self.token = token.filter(|t| !t.is_empty());
        self
    }

    /// Attaches the lab.
    pub fn with_lab(mut self, lab: Arc<Lab>) -> Self {
        self.lab = Some(lab);
        self
    }

    /// Refuses every trial with `reason` (409, `reason: "uncalibrated"`).
    pub fn with_trials_refused(mut self, reason: Option<String>) -> Self {
        self.trials_refused = reason;
        self
    }

    /// Attaches the calibration desk (`/api/calibration`; it decides whether
    /// trials are refused for want of calibration).
    pub fn with_calibration(mut self, desk: Arc<calibration::CalibrationDesk>) -> Self {
        self.calibration = Some(desk);
        self
    }

    /// Attaches the trial records.
    pub fn with_records(mut self, records: Arc<Records>) -> Self {
        self.records = Some(records);
        self
    }

    /// Sets the body limit.
    pub fn with_body_limit(mut self, bytes: usize) -> Self {
        self.body_limit_bytes = bytes;
        self
    }

    /// Allows these browser origins (CORS).
    pub fn with_cors_origins(mut self, origins: Vec<String>) -> Self {
        self.cors_origins = origins;
        self
    }
}

/// `GET /api/health`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct Health {
    /// Always `"ok"` when the service answers.
    pub status: &'static str,
    /// Version and git revision.
    pub version: &'static str,
    /// Seconds since the service started.
    pub uptime_s: f64,
    /// Unix time of the answer, seconds.
    pub t_s: f64,
    /// A lab (control loop) is attached.
    pub lab: bool,
    /// Trial records are kept.
    pub records: bool,
    /// Commands need a bearer token.
    pub token_required: bool,
    /// `POST /api/trials` would start a trial now.
    pub ready: bool,
    /// Why not (null when `ready`): what a script waits on instead of retrying 409s.
    pub not_ready: Option<NotReady>,
    /// The devices that keep the lab from running trials now, each naming
    /// what is wrong (empty when every device delivers, or without a lab).
    pub devices: Vec<crate::lab::DeviceProblem>,
}

/// Why the lab would not take a trial now.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct NotReady {
    /// `no_lab` (no control loop runs), `starting` (none has published a
    /// state yet), `uncalibrated`, `calibrating`, or the control loop's
    /// refusal: `busy` (a trial runs, is planned or is finishing its record),
    /// `robot_not_commanding`, `device_unavailable`.
    pub reason: &'static str,
    /// The reason as a sentence.
    pub message: String,
}

/// Why a trial posted now would not start (`None`: it would).
pub(crate) fn not_ready(state: &AppState) -> Option<NotReady> {
    if let Some((reason, message)) = api::service_blocker(state) {
        return Some(NotReady { reason, message });
    }
    let Some(lab) = state.lab.as_ref() else {
        return Some(NotReady {
            reason: "no_lab",
            message: "no lab (control loop) runs in this service".into(),
        });
    };
    let Some((snapshot, _)) = lab.latest() else {
        return Some(NotReady {
            reason: "starting",
            message: "the lab has not published a state yet".into(),
        });
    };
    snapshot.ready.reason.map(|r| NotReady {
        reason: r.as_str(),
        // "A device is not available": say which and why.
        message: match lab
            .device_problems()
            .into_iter()
            .find(|p| p.device != "robot")
        {
            Some(p) if r == rt_core::bridge::Refusal::DeviceUnavailable => p.message,
            _ => r.message().to_owned(),
        },
    })
}

/// The service is up, and whether the lab would take a trial now (and if not, why).
#[utoipa::path(get, path = "/api/health", tag = "service",
    responses((status = 200, description = "the service answers", body = Health)))]
pub async fn health(State(state): State<Arc<AppState>>) -> Json<Health> {
    let t_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    let not_ready = not_ready(&state);
    Json(Health {
        status: "ok",
        version: VERSION,
        uptime_s: state.started.elapsed().as_secs_f64(),
        t_s,
        lab: state.lab.is_some(),
        records: state.records.is_some(),
        token_required: state.token.is_some(),
        ready: not_ready.is_none(),
        not_ready,
        devices: state
            .lab
            .as_ref()
            .map(|l| l.device_problems())
            .unwrap_or_default(),
    })
}

async fn api_not_found() -> AppError {
    AppError::NotFound("no such API endpoint".to_owned())
}

/// The service's router: the API under `/api`, the streams under `/ws`, the
/// dashboard everywhere else.
pub fn app(state: Arc<AppState>) -> Router {
    let index = state.web_dir.join("index.html");
    let demo_page = ServeFile::new(state.web_dir.join("demo.html"));
    let web = ServeDir::new(&state.web_dir).fallback(ServeFile::new(index));
    let api = Router::new()
        .route("/health", get(health))
        .route("/state", get(api::get_state))
        .route("/fri", get(api::get_fri))
        .route("/params", get(api::get_params).put(api::put_params))
        .route("/arm", post(api::arm))
        .route("/disarm", post(api::disarm))
        .route("/magnet", post(api::magnet))
        .route("/stop", post(api::stop))
        .route("/heartbeat", post(api::heartbeat))
        .route("/calibration", get(api::get_calibration))
        .route("/calibration/{step}", post(api::start_calibration))
        .route("/trials", get(api::list_trials).post(api::start_trial))
        .route("/trials/{id}", get(api::get_trial))
        .route("/runs", get(api::list_runs).post(api::start_run))
        .route("/runs/{id}", get(api::get_run).delete(api::stop_run))
        .route("/demo", get(api::get_demo))
        .route("/trials/{id}/recording.csv", get(api::recording_csv))
        .route("/trials/{id}/recording.mcap", get(api::recording_mcap))
        .route("/robot.urdf", get(api::robot_urdf))
        .route("/openapi.json", get(api::openapi_json))
        .fallback(api_not_found);
    let mut router = Router::new()
        .nest("/api", api)
        .route("/ws", get(ws::state_stream))
        .route("/ws/camera", get(ws::camera_stream))
        .route_service("/demo", demo_page)
        .fallback_service(web)
        .layer(DefaultBodyLimit::max(state.body_limit_bytes));
    // CORS is closed unless origins are listed: browsers then refuse cross-origin
    // reads, and `api::Operator` refuses cross-origin commands.
    let origins: Vec<HeaderValue> = state
        .cors_origins
        .iter()
        .filter_map(|o| HeaderValue::from_str(o).ok())
        .collect();
    if !origins.is_empty() {
        router = router.layer(
            CorsLayer::new()
                .allow_origin(AllowOrigin::list(origins))
                .allow_methods(tower_http::cors::Any)
                .allow_headers([
                    axum::http::header::AUTHORIZATION,
                    axum::http::header::CONTENT_TYPE,
                ]),
        );
    }
    router.with_state(state)
}

/// Kernel send buffer asked for each connection, bytes (Linux doubles it). It
/// bounds how much a client that stops reading can have queued: beyond it the
/// client's sends stall, it skips state messages and is dropped after the send
/// timeout, instead of the kernel buffering megabytes (seconds of stale state).
pub const SOCKET_SEND_BUFFER_BYTES: usize = 256 * 1024;

/// Tunes every accepted connection (no Nagle delay, bounded send buffer);
/// `isochron serve` and the tests serve through this.
pub fn tuned_listener(
    listener: tokio::net::TcpListener,
) -> impl axum::serve::Listener<Io = tokio::net::TcpStream, Addr = SocketAddr> {
    use axum::serve::ListenerExt;
    listener.tap_io(|tcp: &mut tokio::net::TcpStream| {
        if let Err(e) = tcp.set_nodelay(true) {
            tracing::debug!(error = %e, "cannot set TCP_NODELAY");
        }
        if let Err(e) = socket2::SockRef::from(&*tcp).set_send_buffer_size(SOCKET_SEND_BUFFER_BYTES)
        {
            tracing::debug!(error = %e, "cannot set the send buffer size");
        }
    })
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
///
/// # Errors
///
/// [`ServeConfigError::OpenWithoutToken`] when `addr` is not loopback and no
/// (non-empty) token is given.
pub fn check_bind(addr: SocketAddr, token: Option<&str>) -> Result<(), ServeConfigError> {
    if addr.ip().is_loopback() || token.is_some_and(|t| !t.is_empty()) {
        Ok(())
    } else {
        Err(ServeConfigError::OpenWithoutToken(addr))
    }
}
