//! The REST handlers (CONTRACT.md, "HTTP") and the OpenAPI document.

use std::sync::Arc;

use axum::{
    Json,
    body::Bytes,
    extract::{
        FromRequest, FromRequestParts, Path, Query, Request, State, rejection::BytesRejection,
    },
    http::{HeaderMap, HeaderValue, StatusCode, header, request::Parts},
    response::{IntoResponse, Response},
};
use rt_core::{
    bridge::{Command, Refusal, TrialSetup},
    control::ControlError,
    params::Scenario,
    trajectory::Infeasibility,
};
use serde::{Deserialize, Serialize, de::DeserializeOwned};
use utoipa::{
    OpenApi, ToSchema,
    openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme},
};

use crate::{
    AppError, AppState,
    lab::{CommandError, Lab},
    records::{Records, TrialRecord},
};

/// Proof that the request may command the lab: the bearer token matched (when
/// one is set) and the request does not come from a page of another origin.
#[derive(Debug, Clone, Copy)]
pub struct Operator;

impl FromRequestParts<Arc<AppState>> for Operator {
    type Rejection = AppError;

    async fn from_request_parts(
        parts: &mut Parts,
        state: &Arc<AppState>,
    ) -> Result<Self, Self::Rejection> {
        if let Some(token) = &state.token {
            let given = parts
                .headers
                .get(header::AUTHORIZATION)
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.strip_prefix("Bearer "));
            match given {
                Some(g) if constant_time_eq(g.trim().as_bytes(), token.as_bytes()) => {}
                Some(_) => return Err(AppError::Unauthorized("wrong bearer token".into())),
                None => {
                    return Err(AppError::Unauthorized(
                        "this endpoint needs `Authorization: Bearer TOKEN`; viewers can only watch"
                            .into(),
                    ));
                }
            }
        }
        check_origin(parts, state)?;
        Ok(Self)
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    let mut diff = a.len() ^ b.len();
    for (i, x) in a.iter().enumerate() {
        diff |= usize::from(x ^ b.get(i % b.len().max(1)).copied().unwrap_or(0));
    }
    diff == 0
}

/// A browser sends `Origin` with every POST/PUT; a page of another origin may
/// not command the lab (CORS is closed unless `cors_origins` lists it).
fn check_origin(parts: &Parts, state: &AppState) -> Result<(), AppError> {
    let Some(origin) = parts
        .headers
        .get(header::ORIGIN)
        .and_then(|v| v.to_str().ok())
    else {
        return Ok(());
    };
    let host = parts
        .headers
        .get(header::HOST)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let same = origin
        .split_once("://")
        .is_some_and(|(_, rest)| !host.is_empty() && rest == host);
    if same || state.cors_origins.iter().any(|o| o == origin) {
        Ok(())
    } else {
        Err(AppError::Forbidden(format!(
            "commands from the web origin {origin} are not allowed (CORS is closed)"
        )))
    }
}

fn lab(state: &AppState) -> Result<&Arc<Lab>, AppError> {
    state
        .lab
        .as_ref()
        .ok_or_else(|| AppError::Unavailable("the lab is not running".into()))
}

fn records(state: &AppState) -> Result<Arc<Records>, AppError> {
    state
        .records
        .clone()
        .ok_or_else(|| AppError::Unavailable("trial records are not kept by this service".into()))
}

fn body_bytes(body: Result<Bytes, BytesRejection>) -> Result<Bytes, AppError> {
    body.map_err(|r| {
        if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
            AppError::PayloadTooLarge("the request body is larger than the limit".into())
        } else {
            AppError::BadRequest {
                message: format!("cannot read the request body: {}", r.body_text()),
                field: None,
            }
        }
    })
}

/// A request body that is JSON or empty: a body sent with a `Content-Type`
/// other than `application/json` is refused with 415 before it is read as
/// JSON (a body without `Content-Type` is read as JSON).
#[derive(Debug)]
pub struct JsonBody(pub Bytes);

/// True when `Content-Type` says JSON (`application/json`, parameters allowed)
/// or is absent.
fn is_json(headers: &HeaderMap) -> bool {
    headers.get(header::CONTENT_TYPE).is_none_or(|v| {
        v.to_str().is_ok_and(|v| {
            v.split(';')
                .next()
                .unwrap_or("")
                .trim()
                .eq_ignore_ascii_case("application/json")
        })
    })
}

impl<S: Send + Sync> FromRequest<S> for JsonBody {
    type Rejection = AppError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let json = is_json(req.headers());
        let bytes = body_bytes(Bytes::from_request(req, state).await)?;
        if !bytes.is_empty() && !json {
            return Err(AppError::UnsupportedMediaType(
                "the request body must be JSON (Content-Type: application/json)".into(),
            ));
        }
        Ok(Self(bytes))
    }
}

/// Parses JSON, naming the field at fault (`task.movement_time_s`, `on`).
///
/// # Errors
///
/// [`AppError::BadRequest`] when `bytes` is not JSON, has trailing data, or does not
/// fit `T` (naming the field when it can).
pub fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, AppError> {
    let mut de = serde_json::Deserializer::from_slice(bytes);
    let value: T = serde_path_to_error::deserialize(&mut de).map_err(|e| json_error(&e))?;
    de.end().map_err(|e| AppError::BadRequest {
        message: format!("malformed JSON: {e}"),
        field: None,
    })?;
    Ok(value)
}

fn json_error(e: &serde_path_to_error::Error<serde_json::Error>) -> AppError {
    let path = e.path().to_string();
    let inner = e.inner();
    let msg = inner.to_string();
    // The unknown or missing key itself, when serde names it.
    let named = ["unknown field `", "missing field `"]
        .iter()
        .find_map(|p| msg.split_once(p))
        .and_then(|(_, rest)| rest.split_once('`'))
        .map(|(name, _)| name.to_owned());
    let syntax = inner.is_syntax() || inner.is_eof();
    let field = match (path.as_str(), named) {
        _ if syntax && path.contains('?') => None,
        ("." | "?", Some(n)) => Some(n),
        ("." | "?", None) => None,
        (p, Some(n)) if !p.ends_with(&n) => Some(format!("{p}.{n}")),
        (p, _) => Some(p.to_owned()),
    };
    let message = if syntax {
        format!("malformed JSON: {msg}")
    } else {
        match &field {
            Some(f) => format!("{f}: {msg}"),
            None => msg,
        }
    };
    AppError::BadRequest { message, field }
}

/// A body that must be empty or `{}`.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NoFields {}

/// An empty body or `{}` (nothing else: no other JSON value, no fields).
fn empty_body(JsonBody(bytes): JsonBody) -> Result<(), AppError> {
    if bytes.is_empty() {
        return Ok(());
    }
    let value: serde_json::Value = parse_json(&bytes)?;
    if !value.is_object() {
        return Err(AppError::BadRequest {
            message: "the body must be empty or a JSON object without fields ({})".into(),
            field: None,
        });
    }
    parse_json::<NoFields>(&bytes).map(|_| ())
}

fn command_error(e: CommandError) -> AppError {
    match e {
        CommandError::Refused(r) => AppError::Conflict {
            message: format!("refused: {}", r.message()),
            field: None,
            reason: Some(r.as_str()),
        },
        CommandError::NoAnswer => AppError::Unanswered { trial: None },
        other => AppError::Unavailable(other.to_string()),
    }
}

/// A command the control loop accepted.
#[derive(Debug, Serialize, ToSchema)]
pub struct Accepted {
    /// Always true.
    pub accepted: bool,
    /// The command (`arm`, `disarm`, `magnet`, `set_params`).
    pub command: &'static str,
}

async fn run(state: &AppState, command: Command) -> Result<Json<Accepted>, AppError> {
    let name = command.name();
    lab(state)?.command(command).await.map_err(command_error)?;
    Ok(Json(Accepted {
        accepted: true,
        command: name,
    }))
}

/// `GET /api/fri`: the FRI link's version and `isochron fri doctor`'s last report.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct FriInfo {
    /// The FRI version the lab's client speaks (`"1.15"`).
    pub version: &'static str,
    /// Its wire format in words.
    pub wire: &'static str,
    /// The doctor's last report (`isochron fri doctor --json`), or null when it
    /// has not run (or its file is unreadable).
    #[schema(value_type = Option<Object>)]
    pub doctor: Option<serde_json::Value>,
    /// When that report was written, Unix seconds.
    pub doctor_t_s: Option<f64>,
}

/// The FRI link's version and the connection doctor's last findings.
#[utoipa::path(get, path = "/api/fri", tag = "lab",
    responses((status = 200, description = "version and the last `fri doctor` report", body = FriInfo)))]
pub async fn get_fri(State(state): State<Arc<AppState>>) -> Json<FriInfo> {
    let (doctor, doctor_t_s) = match &state.fri_doctor_report {
        Some(path) => {
            let path = path.clone();
            tokio::task::spawn_blocking(move || {
                let text = std::fs::read(&path).ok()?;
                let value: serde_json::Value = serde_json::from_slice(&text).ok()?;
                let t = std::fs::metadata(&path)
                    .and_then(|m| m.modified())
                    .ok()
                    .and_then(|m| m.duration_since(std::time::UNIX_EPOCH).ok())
                    .map(|d| d.as_secs_f64());
                Some((value, t))
            })
            .await
            .ok()
            .flatten()
            .map_or((None, None), |(v, t)| (Some(v), t))
        }
        None => (None, None),
    };
    Json(FriInfo {
        version: state.fri_version.name(),
        wire: state.fri_version.wire_summary(),
        doctor,
        doctor_t_s,
    })
}

/// The latest state, as on the WebSocket (`"type": "state"`).
///
/// # Errors
///
/// [`AppError::Unavailable`] when the lab is not running or has not published a
/// state yet.
#[utoipa::path(get, path = "/api/state", tag = "lab",
    responses(
        (status = 200, description = "the latest state message (as on /ws)", body = crate::lab::StateMessage),
        (status = 503, description = "the lab is not running", body = crate::error::ErrorBody)))]
pub async fn get_state(State(state): State<Arc<AppState>>) -> Result<Response, AppError> {
    let (_, text) = lab(&state)?
        .latest()
        .ok_or_else(|| AppError::Unavailable("the lab has not published a state yet".into()))?;
    Ok((
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        )],
        text.as_str().to_owned(),
    )
        .into_response())
}

/// The parameters in force (a scenario, CONTRACT.md "Scenario file").
///
/// # Errors
///
/// [`AppError::Unavailable`] when the lab is not running.
#[utoipa::path(get, path = "/api/params", tag = "lab",
    responses(
        (status = 200, description = "the scenario in force", body = Object),
        (status = 503, description = "the lab is not running", body = crate::error::ErrorBody)))]
pub async fn get_params(State(state): State<Arc<AppState>>) -> Result<Json<Scenario>, AppError> {
    Ok(Json(lab(&state)?.params()))
}

/// Sections that may change while a trial runs (they do not move the arm).
const SAFE_WHILE_BUSY: [&str; 2] = ["name", "success"];

/// Merges a JSON object into the parameters in force, validates the result and
/// hands it to the control loop; on any error nothing changes.
///
/// # Errors
///
/// [`AppError::BadRequest`] for a body that is not a JSON object, a wrong type or
/// unknown key, an out-of-range value or a new `[world]`; [`AppError::Conflict`]
/// when a field other than `name` or `success` changes while a trial runs or the
/// control loop refuses; [`AppError::Unavailable`] when the lab does not run or answer.
#[utoipa::path(put, path = "/api/params", tag = "lab",
    request_body(content = Object, description = "a partial scenario, merged into the one in force: {\"task\": {\"movement_time_s\": 1.2}}. Only the scenario's keys, with its value types; each value's range is checked after merging (400 names the field)"),
    responses(
        (status = 200, description = "the scenario now in force", body = Object),
        (status = 400, description = "malformed, wrong type, unknown key or out of range; names the field", body = crate::error::ErrorBody),
        (status = 401, description = "token missing or wrong", body = crate::error::ErrorBody),
        (status = 409, description = "refused while a trial runs; names the field", body = crate::error::ErrorBody),
        (status = 413, description = "body too large", body = crate::error::ErrorBody),
        (status = 415, description = "a body that is not application/json", body = crate::error::ErrorBody)),
    security(("bearer" = [])))]
pub async fn put_params(
    State(state): State<Arc<AppState>>,
    _op: Operator,
    JsonBody(bytes): JsonBody,
) -> Result<Json<Scenario>, AppError> {
    let lab = lab(&state)?;
    let patch: serde_json::Value = parse_json(&bytes)?;
    if !patch.is_object() {
        return Err(AppError::BadRequest {
            message: "the body must be a JSON object (a partial scenario)".into(),
            field: None,
        });
    }
    let _guard = lab.params_update.lock().await;
    let current = lab.params();
    let current_json = serde_json::to_value(&current).map_err(anyhow::Error::from)?;
    let mut merged = current_json.clone();
    merge(&mut merged, &patch);
    let new: Scenario =
        serde_path_to_error::deserialize(merged.clone()).map_err(|e| json_error(&e))?;
    new.validate().map_err(|e| AppError::BadRequest {
        message: e.to_string(),
        field: e.field().map(str::to_owned),
    })?;
    if new.world.is_some() && current.world.is_none() {
        return Err(AppError::BadRequest {
            message: crate::serve::WORLD_IN_SERVE.into(),
            field: Some("world".into()),
        });
    }
    let changed = changed_fields(&current_json, &merged);
    if changed.is_empty() {
        return Ok(Json(current));
    }
    if let Some((snapshot, _)) = lab.latest() {
        if snapshot.trial_state.busy() {
            if let Some(f) = changed.iter().find(|f| {
                !SAFE_WHILE_BUSY
                    .iter()
                    .any(|s| f.split('.').next() == Some(*s))
            }) {
                return Err(AppError::Conflict {
                    message: format!(
                        "{f} cannot change while a trial runs (state: {})",
                        snapshot.trial_state.as_str()
                    ),
                    field: Some(f.clone()),
                    reason: Some(Refusal::Busy.as_str()),
                });
            }
        }
    }
    lab.command(Command::SetParams(Box::new(new.clone())))
        .await
        .map_err(command_error)?;
    lab.store_params(new.clone());
    Ok(Json(new))
}

/// JSON merge (RFC 7386 without deletion): objects merge key by key, anything
/// else replaces.
fn merge(into: &mut serde_json::Value, patch: &serde_json::Value) {
    match (into, patch) {
        (serde_json::Value::Object(a), serde_json::Value::Object(b)) => {
            for (k, v) in b {
                match a.get_mut(k) {
                    Some(slot) => merge(slot, v),
                    None => {
                        a.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        (slot, v) => *slot = v.clone(),
    }
}

fn changed_fields(a: &serde_json::Value, b: &serde_json::Value) -> Vec<String> {
    let mut out = Vec::new();
    fn walk(a: &serde_json::Value, b: &serde_json::Value, path: &str, out: &mut Vec<String>) {
        match (a, b) {
            (serde_json::Value::Object(x), serde_json::Value::Object(y)) => {
                for (k, vb) in y {
                    let p = if path.is_empty() {
                        k.clone()
                    } else {
                        format!("{path}.{k}")
                    };
                    match x.get(k) {
                        Some(va) => walk(va, vb, &p, out),
                        None => out.push(p),
                    }
                }
            }
            (x, y) if x != y => out.push(path.to_owned()),
            _ => {}
        }
    }
    walk(a, b, "", &mut out);
    out
}

/// Arm: move home, magnet on, run the checks.
///
/// # Errors
///
/// [`AppError::BadRequest`] for a body that is not empty or `{}`;
/// [`AppError::Conflict`] when the control loop refuses; [`AppError::Unavailable`]
/// when the lab is not running or does not answer.
#[utoipa::path(post, path = "/api/arm", tag = "commands",
    request_body(content = Option<NoFields>, description = "empty or {}"),
    responses(
        (status = 200, description = "accepted", body = Accepted),
        (status = 400, description = "a body other than empty or {} (fields, another JSON value, malformed)", body = crate::error::ErrorBody),
        (status = 413, description = "body too large", body = crate::error::ErrorBody),
        (status = 415, description = "a body that is not application/json", body = crate::error::ErrorBody),
        (status = 401, description = "token missing or wrong", body = crate::error::ErrorBody),
        (status = 409, description = "refused in this state (reason)", body = crate::error::ErrorBody),
        (status = 503, description = "the lab is not running or did not answer", body = crate::error::ErrorBody)),
    security(("bearer" = [])))]
pub async fn arm(
    State(state): State<Arc<AppState>>,
    _op: Operator,
    body: JsonBody,
) -> Result<Json<Accepted>, AppError> {
    empty_body(body)?;
    run(&state, Command::Arm).await
}

/// Disarm.
///
/// # Errors
///
/// [`AppError::BadRequest`] for a body that is not empty or `{}`;
/// [`AppError::Conflict`] when the control loop refuses; [`AppError::Unavailable`]
/// when the lab is not running or does not answer.
#[utoipa::path(post, path = "/api/disarm", tag = "commands",
    request_body(content = Option<NoFields>, description = "empty or {}"),
    responses(
        (status = 200, description = "accepted", body = Accepted),
        (status = 400, description = "a body other than empty or {} (fields, another JSON value, malformed)", body = crate::error::ErrorBody),
        (status = 413, description = "body too large", body = crate::error::ErrorBody),
        (status = 415, description = "a body that is not application/json", body = crate::error::ErrorBody),
        (status = 401, description = "token missing or wrong", body = crate::error::ErrorBody),
        (status = 409, description = "refused in this state (reason)", body = crate::error::ErrorBody),
        (status = 503, description = "the lab is not running or did not answer", body = crate::error::ErrorBody)),
    security(("bearer" = [])))]
pub async fn disarm(
    State(state): State<Arc<AppState>>,
    _op: Operator,
    body: JsonBody,
) -> Result<Json<Accepted>, AppError> {
    empty_body(body)?;
    run(&state, Command::Disarm).await
}

/// `POST /api/magnet` body.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MagnetRequest {
    /// true: hold the ball; false: drop it.
    pub on: bool,
}

/// Switch the magnet (`{"on": false}` drops the ball).
///
/// # Errors
///
/// [`AppError::BadRequest`] for a body that is not a [`MagnetRequest`];
/// [`AppError::Conflict`] when the control loop refuses; [`AppError::Unavailable`]
/// when the lab is not running or does not answer.
#[utoipa::path(post, path = "/api/magnet", tag = "commands",
    request_body = MagnetRequest,
    responses(
        (status = 200, description = "accepted", body = Accepted),
        (status = 400, description = "malformed; names the field", body = crate::error::ErrorBody),
        (status = 413, description = "body too large", body = crate::error::ErrorBody),
        (status = 415, description = "a body that is not application/json", body = crate::error::ErrorBody),
        (status = 401, description = "token missing or wrong", body = crate::error::ErrorBody),
        (status = 409, description = "refused in this state (reason)", body = crate::error::ErrorBody),
        (status = 503, description = "the lab is not running or did not answer", body = crate::error::ErrorBody)),
    security(("bearer" = [])))]
pub async fn magnet(
    State(state): State<Arc<AppState>>,
    _op: Operator,
    JsonBody(bytes): JsonBody,
) -> Result<Json<Accepted>, AppError> {
    let req: MagnetRequest = parse_json(&bytes)?;
    run(&state, Command::Magnet { on: req.on }).await
}

/// `POST /api/stop` answer.
#[derive(Debug, Serialize, ToSchema)]
pub struct StopAnswer {
    /// Always true: a stop is never refused.
    pub accepted: bool,
    /// The control loop confirmed it in time.
    pub acknowledged: bool,
}

/// Emergency stop: always accepted, from any state, with or without a token or body.
///
/// # Errors
///
/// [`AppError::Unavailable`] when the lab is not running.
#[utoipa::path(post, path = "/api/stop", tag = "commands",
    responses(
        (status = 200, description = "stop requested", body = StopAnswer),
        (status = 503, description = "no lab runs", body = crate::error::ErrorBody)))]
pub async fn stop(State(state): State<Arc<AppState>>) -> Result<Json<StopAnswer>, AppError> {
    let acknowledged = lab(&state)?.stop().await;
    Ok(Json(StopAnswer {
        accepted: true,
        acknowledged,
    }))
}

/// `POST /api/heartbeat` answer.
#[derive(Debug, Serialize, ToSchema)]
pub struct HeartbeatAnswer {
    /// The heartbeat's time on the lab's control clock, seconds.
    pub t_s: f64,
}

/// Operator heartbeat (the dead-man): while a trial runs with the dead-man on
/// (`[lab] dead_man`, on by default in the real lab), some operator must send
/// one at least every `[lab] operator_timeout_s`, or the motion stops safely
/// and the trial is recorded as aborted with `operator_lost`. The dashboard
/// sends them by itself while it can command.
///
/// # Errors
///
/// [`AppError::BadRequest`] for a body that is not empty or `{}`;
/// [`AppError::Unavailable`] when the lab is not running or its control clock has
/// not started.
#[utoipa::path(post, path = "/api/heartbeat", tag = "commands",
    request_body(content = Option<NoFields>, description = "empty or {}"),
    responses(
        (status = 200, description = "recorded", body = HeartbeatAnswer),
        (status = 400, description = "a body other than empty or {} (fields, another JSON value, malformed)", body = crate::error::ErrorBody),
        (status = 401, description = "token missing or wrong", body = crate::error::ErrorBody),
        (status = 413, description = "body too large", body = crate::error::ErrorBody),
        (status = 415, description = "a body that is not application/json", body = crate::error::ErrorBody),
        (status = 503, description = "the lab is not running", body = crate::error::ErrorBody)),
    security(("bearer" = [])))]
pub async fn heartbeat(
    State(state): State<Arc<AppState>>,
    _op: Operator,
    body: JsonBody,
) -> Result<Json<HeartbeatAnswer>, AppError> {
    empty_body(body)?;
    let t_s = lab(&state)?
        .heartbeat()
        .ok_or_else(|| AppError::Unavailable("the lab's control clock has not started".into()))?;
    Ok(Json(HeartbeatAnswer { t_s }))
}

fn desk(state: &AppState) -> Result<&Arc<crate::calibration::CalibrationDesk>, AppError> {
    state.calibration.as_ref().ok_or_else(|| {
        AppError::Unavailable("this service has no calibration file (no lab runs)".into())
    })
}

/// The calibration file's steps (done, missing prerequisites, their results)
/// and the running or last step with what it sees.
///
/// # Errors
///
/// [`AppError::Unavailable`] when the service has no calibration file or it cannot
/// be read; [`AppError::Internal`] when the blocking task fails.
#[utoipa::path(get, path = "/api/calibration", tag = "calibration",
    responses(
        (status = 200, description = "the steps and the job", body = crate::calibration::CalibrationStatus),
        (status = 503, description = "no lab (no calibration file) or the file is unreadable", body = crate::error::ErrorBody)))]
pub async fn get_calibration(
    State(state): State<Arc<AppState>>,
) -> Result<Json<crate::calibration::CalibrationStatus>, AppError> {
    let desk = Arc::clone(desk(&state)?);
    tokio::task::spawn_blocking(move || desk.status())
        .await
        .map_err(anyhow::Error::from)?
        .map(Json)
        .map_err(|e| AppError::Unavailable(format!("the calibration file: {e}")))
}

/// `POST /api/calibration/{step}` body: empty, `{}`, or the step's options.
#[derive(Debug, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CalibrationRequest {
    /// Pendulum step: the angle the magnet holds the ball at before the free
    /// swing, degrees, in (0, 60] (default 25; a swing under 5 cm is refused
    /// by the step: "swing too small").
    #[serde(default)]
    pub release_deg: Option<f64>,
}

/// `POST /api/calibration/{step}` answer.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationStarted {
    /// The step.
    pub step: &'static str,
    /// The job's number (`GET /api/calibration` job.id).
    pub id: u64,
}

/// Runs one calibration step on the lab (its result, residuals, date and
/// revision go into the calibration file, and the lab's beliefs take it when no
/// trial runs). Watch it with `GET /api/calibration`.
///
/// # Errors
///
/// [`AppError::NotFound`] for an unknown step; [`AppError::BadRequest`] for a bad
/// body or a `release_deg` out of range or given to another step;
/// [`AppError::Conflict`] while a trial or another step runs, or prerequisites are
/// missing; [`AppError::Unavailable`] without a running lab or calibration file.
#[utoipa::path(post, path = "/api/calibration/{step}", tag = "calibration",
    params(("step" = String, Path, description = "camera, latency, pendulum, camera-robot or robot")),
    request_body(content = Option<CalibrationRequest>, description = "empty, {} or {\"release_deg\": 25}"),
    responses(
        (status = 202, description = "the step started", body = CalibrationStarted),
        (status = 400, description = "malformed body, unknown field or value out of range; names the field", body = crate::error::ErrorBody),
        (status = 401, description = "token missing or wrong", body = crate::error::ErrorBody),
        (status = 404, description = "no such step", body = crate::error::ErrorBody),
        (status = 409, description = "refused: a step or a trial runs (busy), a prerequisite is not calibrated (prerequisites), or the lab cannot run it (not_available)", body = crate::error::ErrorBody),
        (status = 413, description = "body too large", body = crate::error::ErrorBody),
        (status = 415, description = "a body that is not application/json", body = crate::error::ErrorBody),
        (status = 503, description = "the lab is not running", body = crate::error::ErrorBody)),
    security(("bearer" = [])))]
pub async fn start_calibration(
    State(state): State<Arc<AppState>>,
    _op: Operator,
    Path(name): Path<String>,
    JsonBody(bytes): JsonBody,
) -> Result<(StatusCode, Json<CalibrationStarted>), AppError> {
    use crate::calibration::{StartRefused, Step};
    let step = Step::from_name(&name).ok_or_else(|| {
        AppError::NotFound(format!(
            "no calibration step {name:?}; the steps: camera, latency, pendulum, camera-robot, robot, contact"
        ))
    })?;
    let req: CalibrationRequest = if bytes.is_empty() {
        CalibrationRequest::default()
    } else {
        let value: serde_json::Value = parse_json(&bytes)?;
        if !value.is_object() {
            return Err(AppError::BadRequest {
                message: "the body must be empty or a JSON object ({\"release_deg\": 25})".into(),
                field: None,
            });
        }
        parse_json(&bytes)?
    };
    if let Some(d) = req.release_deg {
        if step != Step::Pendulum {
            return Err(AppError::BadRequest {
                message: format!("release_deg: only the pendulum step takes it, not {name}"),
                field: Some("release_deg".into()),
            });
        }
        if !(d.is_finite() && d > 0.0 && d <= 60.0) {
            return Err(AppError::BadRequest {
                message: format!("release_deg = {d} is out of range: must be in (0, 60] degrees"),
                field: Some("release_deg".into()),
            });
        }
    }
    // The angle is asked of the person who hangs the ball.
    let asked_release_deg = req.release_deg;
    let lab = Arc::clone(lab(&state)?);
    let desk = Arc::clone(desk(&state)?);
    // A trial's start checks for a running step under the same gate.
    let gate = lab.start_gate.lock().await;
    let running = lab
        .latest()
        .map(|(snapshot, _)| snapshot.trial_state)
        .filter(|t| t.busy())
        .map(rt_core::bridge::TrialState::as_str)
        .or_else(|| lab.trial_unshown().then_some("starting"));
    if let Some(trial_state) = running {
        return Err(AppError::Conflict {
            message: format!(
                "refused: a trial runs (state: {trial_state}); calibrate when it has finished"
            ),
            field: None,
            reason: Some(Refusal::Busy.as_str()),
        });
    }
    let id = desk.claim(step).map_err(|e| AppError::Conflict {
        message: format!("refused: {e}"),
        field: None,
        reason: Some(match e {
            StartRefused::Busy(_) => "busy",
            StartRefused::Prerequisites { .. } => "prerequisites",
            StartRefused::NotAvailable(_) => "not_available",
        }),
    })?;
    // Trials wait until the lab has taken the step's result, not only until
    // the job says it is done.
    desk.set_taking(true);
    drop(gate);
    tokio::spawn(async move {
        let scenario = lab.params();
        // Through the lab's own camera, robot and magnet.
        let beliefs = match step {
            Step::Camera => crate::calibration::run_real_camera(&lab, &desk, id, &scenario).await,
            Step::Latency => crate::calibration::run_real_latency(&lab, &desk, id, &scenario).await,
            Step::Robot => crate::calibration::run_real_robot(&lab, &desk, id, &scenario).await,
            Step::Contact => crate::calibration::run_real_contact(&lab, &desk, id, &scenario).await,
            Step::CameraRobot => {
                crate::calibration::run_real_camera_robot(&lab, &desk, id, &scenario).await
            }
            Step::Pendulum => {
                crate::calibration::run_real_pendulum(
                    &lab,
                    &desk,
                    id,
                    &scenario,
                    crate::calibration::REAL_SWING_RECORD_S,
                    asked_release_deg,
                )
                .await
            }
        };
        if let Some(beliefs) = beliefs {
            let _guard = lab.params_update.lock().await;
            let busy = lab.latest().is_some_and(|(s, _)| s.trial_state.busy());
            if busy {
                desk.note(id, "written to the calibration file; the lab takes it at its next start (a trial was running)".into());
            } else if lab
                .command(Command::SetParams(Box::new(beliefs.clone())))
                .await
                .is_ok()
            {
                lab.store_params(beliefs);
            } else {
                desk.note(id, "written to the calibration file; the control loop did not take the new beliefs (it takes them at the next start)".into());
            }
        }
        desk.set_taking(false);
    });
    Ok((
        StatusCode::ACCEPTED,
        Json(CalibrationStarted {
            step: step.name(),
            id,
        }),
    ))
}

/// `POST /api/trials` answer.
#[derive(Debug, Serialize, ToSchema)]
pub struct TrialStarted {
    /// The new trial's id.
    pub id: u64,
}

/// `POST /api/trials` body: what this trial sets for itself (each field
/// optional; the lab's parameters in force are not changed).
#[derive(Debug, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TrialRequest {
    /// Robot base axis to the intercept point, horizontal, metres (else
    /// drawn from `task.distance_m`); must be reachable in the movement time.
    /// A real lab's pendulum hangs where its `calibration.pivot_m` puts it:
    /// there (within 5 mm) or left out, else 400.
    #[schema(minimum = 0.1, maximum = 1.2)]
    pub distance_m: Option<f64>,
    /// The motion's planned duration, seconds (else `task.movement_time_s`);
    /// must be feasible within the joint limits at the distance.
    #[schema(minimum = 0.3, maximum = 10.0)]
    pub movement_time_s: Option<f64>,
    /// The release angle's magnitude, degrees (else drawn from
    /// `pendulum.release_angle_deg`; the side is drawn).
    #[schema(minimum = 1.0, maximum = 60.0)]
    pub release_deg: Option<f64>,
    /// This trial's task (else `task.mode`): `stop` (the tool arrives at
    /// rest) or `strike` (it meets the ball with speed, issue #38); the
    /// stroke must be feasible at the distance and movement time.
    pub mode: Option<rt_core::trajectory::TaskMode>,
    /// A strike's tool speed at contact, m/s (else `task.strike_speed_mps`);
    /// only for a strike (this trial's `mode` or the lab's).
    #[schema(minimum = 0.0, maximum = 5.0)]
    pub strike_speed_mps: Option<f64>,
    /// A strike's direction above the swing's horizontal, degrees (else
    /// `task.strike_direction_deg`); only for a strike.
    #[schema(minimum = -60.0, maximum = 60.0)]
    pub strike_direction_deg: Option<f64>,
}

/// The longest movement time a trial may ask for, seconds.
const MAX_MOVEMENT_TIME_S: f64 = 10.0;

/// Checks a trial's own fields against the parameters in force: each in
/// range, and the motion feasible within the joint limits (planned as the
/// lab plans it, without stretching to the shortest feasible duration), or a
/// 400 naming the field. `fixed_distance_m`: where the pendulum hangs in a
/// lab that cannot move it ([`crate::LabOptions::fixed_distance_m`]); a
/// distance more than [`FIXED_DISTANCE_TOLERANCE_M`] from it is refused.
/// How far a trial's `distance_m` may be from a fixed pendulum's, m (the
/// request's rounding; the tool's contact disc is 30 mm across).
pub const FIXED_DISTANCE_TOLERANCE_M: f64 = 0.005;

pub(crate) fn trial_setup(
    req: &TrialRequest,
    params: &Scenario,
    fixed_distance_m: Option<f64>,
) -> Result<TrialSetup, AppError> {
    let bad = |field: &str, message: String| AppError::BadRequest {
        message,
        field: Some(field.to_owned()),
    };
    let range = |field: &str, v: Option<f64>, lo: f64, hi: f64, unit: &str| match v {
        Some(x) if !(x.is_finite() && (lo..=hi).contains(&x)) => Err(bad(
            field,
            format!("{field} = {x} is out of range: must be in [{lo}, {hi}] {unit}"),
        )),
        _ => Ok(()),
    };
    range("distance_m", req.distance_m, 0.1, 1.2, "m")?;
    range(
        "movement_time_s",
        req.movement_time_s,
        0.3,
        MAX_MOVEMENT_TIME_S,
        "s",
    )?;
    range("release_deg", req.release_deg, 1.0, 60.0, "deg")?;
    range("strike_speed_mps", req.strike_speed_mps, 0.0, 5.0, "m/s")?;
    if req.strike_speed_mps == Some(0.0) {
        return Err(bad(
            "strike_speed_mps",
            "strike_speed_mps = 0: a strike meets the ball with speed (mode \"stop\" \
             arrives at rest)"
                .to_owned(),
        ));
    }
    range(
        "strike_direction_deg",
        req.strike_direction_deg,
        -60.0,
        60.0,
        "deg",
    )?;
    let mode = req.mode.unwrap_or(params.task.mode);
    if mode != rt_core::trajectory::TaskMode::Strike {
        for (field, given) in [
            ("strike_speed_mps", req.strike_speed_mps.is_some()),
            ("strike_direction_deg", req.strike_direction_deg.is_some()),
        ] {
            if given {
                return Err(bad(
                    field,
                    format!(
                        "{field} is a strike's: this trial stops the ball (set \"mode\": \
                         \"strike\")"
                    ),
                ));
            }
        }
    }
    if let (Some(d), Some(f)) = (req.distance_m, fixed_distance_m)
        && (d - f).abs() > FIXED_DISTANCE_TOLERANCE_M
    {
        // A real lab's pendulum hangs where it hangs: an intercept elsewhere
        // is a motion to where no ball passes.
        return Err(bad(
            "distance_m",
            format!(
                "distance_m = {d} m: this lab's pendulum hangs {f:.3} m from the robot's base \
                 (calibration.pivot_m) and the lab cannot move it; leave distance_m out (its \
                 trials are planned there), or move the pendulum and set calibration.pivot_m"
            ),
        ));
    }
    let setup = TrialSetup {
        distance_m: req.distance_m,
        movement_time_s: req.movement_time_s,
        release_deg: req.release_deg,
        mode: req.mode,
        strike_speed_mps: req.strike_speed_mps,
        strike_direction_deg: req.strike_direction_deg,
    };
    let own_task =
        req.mode.is_some() || req.strike_speed_mps.is_some() || req.strike_direction_deg.is_some();
    if req.distance_m.is_some() || req.movement_time_s.is_some() {
        let d = req
            .distance_m
            .or(fixed_distance_m)
            .unwrap_or_else(|| params.task.distance_m.lerp(0.5));
        // Reach and pace first, as a stop: a stroke refused there is
        // refused for its distance or movement time, not its speed.
        let stop_only = TrialSetup {
            mode: Some(rt_core::trajectory::TaskMode::Stop),
            ..setup
        };
        let mut b = rt_core::lab::step::trial_beliefs(params, &stop_only);
        b.control.allow_shortest_feasible = false;
        if let Err(e) = rt_core::control::Controller::plan(&b, d) {
            let mt = req.movement_time_s.unwrap_or(params.task.movement_time_s);
            // Blame the distance when it is out of reach at any pace (the
            // error says so: only a too fast motion has a shortest feasible
            // duration, and it must be within the longest one allowed), or
            // when no movement time was asked for; else the movement time.
            let any_pace = !matches!(
                e,
                ControlError::Infeasible(Infeasibility::TooFast { shortest_feasible_s, .. })
                    if shortest_feasible_s <= MAX_MOVEMENT_TIME_S
            );
            return Err(match (req.distance_m, req.movement_time_s) {
                (Some(d), mt_req) if mt_req.is_none() || any_pace => bad(
                    "distance_m",
                    format!("distance_m = {d} m is not reachable in {mt} s: {e}"),
                ),
                _ => bad(
                    "movement_time_s",
                    format!("movement_time_s = {mt} s is not feasible at {d} m: {e}"),
                ),
            });
        }
    }
    if own_task && mode == rt_core::trajectory::TaskMode::Strike {
        // The stroke itself (reach, speeds, torques, the swing's clearance)
        // at the trial's distance, or the middle one when it is drawn.
        let d = req
            .distance_m
            .or(fixed_distance_m)
            .unwrap_or_else(|| params.task.distance_m.lerp(0.5));
        let mut b = rt_core::lab::step::trial_beliefs(params, &setup);
        b.control.allow_shortest_feasible = false;
        if let Err(e) = rt_core::control::Controller::plan(&b, d) {
            let field = if req.strike_speed_mps.is_some() {
                "strike_speed_mps"
            } else if req.strike_direction_deg.is_some() {
                "strike_direction_deg"
            } else {
                "mode"
            };
            return Err(bad(
                field,
                format!(
                    "a strike at {:.2} m/s, {:.0} deg is not feasible at {d} m in {} s: {e}",
                    b.task.strike_speed_mps, b.task.strike_direction_deg, b.task.movement_time_s
                ),
            ));
        }
    }
    Ok(setup)
}

/// Runs one whole trial (arm, release, intercept); its result appears at
/// `/api/trials/{id}` when it ends. The body may set this trial's distance,
/// movement time and release angle (for this trial only).
///
/// # Errors
///
/// [`AppError::BadRequest`] for a bad body or a distance, movement time or release
/// angle out of range or infeasible; [`AppError::Conflict`] when the service or the
/// control loop refuses a trial; [`AppError::Unavailable`] without a running lab or
/// records; [`AppError::Internal`] when the record cannot be written.
#[utoipa::path(post, path = "/api/trials", tag = "trials",
    request_body(content = Option<TrialRequest>, description = "empty, {} or the trial's own fields"),
    responses(
        (status = 202, description = "the trial started", body = TrialStarted),
        (status = 400, description = "malformed, an unknown field, or a field out of range or infeasible (named)", body = crate::error::ErrorBody),
        (status = 413, description = "body too large", body = crate::error::ErrorBody),
        (status = 415, description = "a body that is not application/json", body = crate::error::ErrorBody),
        (status = 401, description = "token missing or wrong", body = crate::error::ErrorBody),
        (status = 409, description = "refused (a trial runs, a real lab is not calibrated, ...)", body = crate::error::ErrorBody),
        (status = 503, description = "the lab is not running or did not answer", body = crate::error::ErrorBody)),
    security(("bearer" = [])))]
pub async fn start_trial(
    State(state): State<Arc<AppState>>,
    _op: Operator,
    JsonBody(bytes): JsonBody,
) -> Result<(StatusCode, Json<TrialStarted>), AppError> {
    let req: TrialRequest = if bytes.is_empty() {
        TrialRequest::default()
    } else {
        parse_json(&bytes)?
    };
    let lab = lab(&state)?;
    let setup = trial_setup(&req, &lab.params(), lab.options().fixed_distance_m)?;
    let id = start_one(&state, setup).await?;
    Ok((StatusCode::ACCEPTED, Json(TrialStarted { id })))
}

/// Creates a trial's record and starts the trial (`POST /api/trials`, and
/// each trial of a run); a refused trial's record is removed.
pub(crate) async fn start_one(state: &AppState, setup: TrialSetup) -> Result<u64, AppError> {
    // A calibration step's start checks for a running trial under the same
    // gate: the check and the start are one step for both.
    let _gate = match state.lab.as_ref() {
        Some(lab) => Some(lab.start_gate.lock().await),
        None => None,
    };
    if let Some((reason, message)) = service_blocker(state) {
        return Err(AppError::Conflict {
            message,
            field: None,
            reason: Some(reason),
        });
    }
    let lab = lab(state)?;
    let records = records(state)?;
    let params = lab.params();
    let origin = crate::records::TrialOrigin {
        scenario: params.name.clone(),
        params_toml: toml::to_string(&params).unwrap_or_default(),
        revision: crate::VERSION.to_owned(),
    };
    let id = blocking({
        let r = Arc::clone(&records);
        move || r.create_trial(&origin)
    })
    .await?;
    if let Err(e) = lab.run_trial(id, setup).await {
        // Refused: the trial never ran, its record goes. Not answered in
        // time: the record stays, and the control loop's late answer settles
        // it (removed if refused; an accepted trial finishes as any other).
        if e == CommandError::NoAnswer {
            return Err(AppError::Unanswered { trial: Some(id) });
        }
        let r = Arc::clone(&records);
        blocking(move || r.delete_trial(id)).await?;
        return Err(command_error(e));
    }
    Ok(id)
}

/// What the service (not the control loop) refuses trials for now: a real
/// lab not calibrated (`uncalibrated`), a calibration step running
/// (`calibrating`); with the sentence a 409 carries.
pub(crate) fn service_blocker(state: &AppState) -> Option<(&'static str, String)> {
    let refused = state
        .calibration
        .as_ref()
        .map_or_else(|| state.trials_refused.clone(), |d| d.trials_refused());
    if let Some(why) = refused {
        return Some(("uncalibrated", why));
    }
    if state.calibration.as_ref().is_some_and(|d| d.running()) {
        return Some((
            "calibrating",
            "refused: a calibration step is running (GET /api/calibration); \
             start the trial when it has finished"
                .into(),
        ));
    }
    None
}

async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> anyhow::Result<T> + Send + 'static,
) -> Result<T, AppError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| AppError::Internal(e.into()))?
        .map_err(AppError::Internal)
}

/// `GET /api/trials` query.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ListQuery {
    /// At most this many trials, newest first (1..1000, default 100).
    #[param(value_type = u32, required = false, minimum = 1, maximum = 1000)]
    pub limit: Option<u32>,
}

/// The trials, newest first.
///
/// # Errors
///
/// [`AppError::BadRequest`] for a `limit` that is malformed or outside 1..=1000;
/// [`AppError::Unavailable`] when no records are kept; [`AppError::Internal`] when
/// the database fails.
#[utoipa::path(get, path = "/api/trials", tag = "trials", params(ListQuery),
    responses(
        (status = 200, description = "trials, newest first", body = Vec<TrialRecord>),
        (status = 400, description = "bad limit", body = crate::error::ErrorBody)))]
pub async fn list_trials(
    State(state): State<Arc<AppState>>,
    query: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<Vec<TrialRecord>>, AppError> {
    let Query(q) = query.map_err(|e| AppError::field("limit", e.body_text()))?;
    let limit = q.limit.unwrap_or(100);
    if !(1..=1000).contains(&limit) {
        return Err(AppError::field(
            "limit",
            format!("limit = {limit} is out of range: must be in [1, 1000]"),
        ));
    }
    let r = records(&state)?;
    Ok(Json(blocking(move || r.list(limit)).await?))
}

fn trial_id(raw: &str) -> Result<u64, AppError> {
    raw.parse::<u64>()
        .ok()
        .filter(|&id| id > 0)
        .ok_or_else(|| AppError::field("id", format!("id = {raw:?} is not a trial id (1, 2, ...)")))
}

async fn existing(state: &AppState, raw: &str) -> Result<(Arc<Records>, TrialRecord), AppError> {
    let id = trial_id(raw)?;
    let r = records(state)?;
    let rec = blocking({
        let r = Arc::clone(&r);
        move || r.get(id)
    })
    .await?
    .ok_or_else(|| AppError::NotFound(format!("no trial {id}")))?;
    Ok((r, rec))
}

/// One trial's result.
///
/// # Errors
///
/// [`AppError::BadRequest`] for an id that is not a trial id; [`AppError::NotFound`]
/// for no such trial; [`AppError::Unavailable`] when no records are kept;
/// [`AppError::Internal`] when the database fails.
#[utoipa::path(get, path = "/api/trials/{id}", tag = "trials",
    params(("id" = u64, Path, description = "trial id", minimum = 1, maximum = 9_223_372_036_854_775_807_u64)),
    responses(
        (status = 200, description = "the trial", body = TrialRecord),
        (status = 400, description = "not a trial id", body = crate::error::ErrorBody),
        (status = 404, description = "no such trial", body = crate::error::ErrorBody)))]
pub async fn get_trial(
    State(state): State<Arc<AppState>>,
    Path(raw): Path<String>,
) -> Result<Json<TrialRecord>, AppError> {
    Ok(Json(existing(&state, &raw).await?.1))
}

/// Starts a batch run: `n` trials one after another, each started when the
/// lab can take it, with the distances, movement time and release angle the
/// body gives (each checked as `POST /api/trials` checks one, before anything
/// starts). Progress: `GET /api/runs/{id}` and `{"type":"run"}` messages on `/ws`.
///
/// # Errors
///
/// [`AppError::BadRequest`] for a bad body or a trial setup out of range;
/// [`AppError::Conflict`] while another run is going; [`AppError::Unavailable`]
/// without a running lab or records.
#[utoipa::path(post, path = "/api/runs", tag = "trials",
    request_body = crate::runs::RunRequest,
    responses(
        (status = 202, description = "the run started", body = crate::runs::RunStarted),
        (status = 400, description = "malformed, an unknown field, or a field out of range or infeasible (named)", body = crate::error::ErrorBody),
        (status = 413, description = "body too large", body = crate::error::ErrorBody),
        (status = 415, description = "a body that is not application/json", body = crate::error::ErrorBody),
        (status = 401, description = "token missing or wrong", body = crate::error::ErrorBody),
        (status = 409, description = "another run is running", body = crate::error::ErrorBody),
        (status = 503, description = "the lab is not running", body = crate::error::ErrorBody)),
    security(("bearer" = [])))]
pub async fn start_run(
    State(state): State<Arc<AppState>>,
    _op: Operator,
    JsonBody(bytes): JsonBody,
) -> Result<(StatusCode, Json<crate::runs::RunStarted>), AppError> {
    let req: crate::runs::RunRequest = parse_json(&bytes)?;
    let id = crate::runs::start(Arc::clone(&state), &req)?;
    Ok((StatusCode::ACCEPTED, Json(crate::runs::RunStarted { id })))
}

/// The runs of this service, newest first (kept in memory: the last 64).
#[utoipa::path(get, path = "/api/runs", tag = "trials",
    responses((status = 200, description = "runs, newest first", body = Vec<crate::runs::RunStatus>)))]
pub async fn list_runs(State(state): State<Arc<AppState>>) -> Json<Vec<crate::runs::RunStatus>> {
    Json(state.runs.list())
}

fn run_id(raw: &str) -> Result<u64, AppError> {
    raw.parse::<u64>()
        .ok()
        .filter(|&id| id > 0)
        .ok_or_else(|| AppError::field("id", format!("id = {raw:?} is not a run id (1, 2, ...)")))
}

/// A run's progress: trials started and finished, successes with their 95%
/// interval, the timing error's p50 and p95, each trial's id.
///
/// # Errors
///
/// [`AppError::BadRequest`] for an id that is not a run id; [`AppError::NotFound`]
/// for no such run.
#[utoipa::path(get, path = "/api/runs/{id}", tag = "trials",
    params(("id" = u64, Path, description = "run id", minimum = 1, maximum = 9_223_372_036_854_775_807_u64)),
    responses(
        (status = 200, description = "the run", body = crate::runs::RunStatus),
        (status = 400, description = "not a run id", body = crate::error::ErrorBody),
        (status = 404, description = "no such run", body = crate::error::ErrorBody)))]
pub async fn get_run(
    State(state): State<Arc<AppState>>,
    Path(raw): Path<String>,
) -> Result<Json<crate::runs::RunStatus>, AppError> {
    let id = run_id(&raw)?;
    state
        .runs
        .get(id)
        .map(Json)
        .ok_or_else(|| AppError::NotFound(format!("no run {id}")))
}

/// Stops a run after its current trial (which finishes and is recorded).
///
/// # Errors
///
/// [`AppError::BadRequest`] for an id that is not a run id; [`AppError::NotFound`]
/// for no such run.
#[utoipa::path(delete, path = "/api/runs/{id}", tag = "trials",
    params(("id" = u64, Path, description = "run id", minimum = 1, maximum = 9_223_372_036_854_775_807_u64)),
    responses(
        (status = 200, description = "the run, asked to stop", body = crate::runs::RunStatus),
        (status = 400, description = "not a run id", body = crate::error::ErrorBody),
        (status = 401, description = "token missing or wrong", body = crate::error::ErrorBody),
        (status = 404, description = "no such run", body = crate::error::ErrorBody)),
    security(("bearer" = [])))]
pub async fn stop_run(
    State(state): State<Arc<AppState>>,
    _op: Operator,
    Path(raw): Path<String>,
) -> Result<Json<crate::runs::RunStatus>, AppError> {
    let id = run_id(&raw)?;
    if !state.runs.stop(id) {
        return Err(AppError::NotFound(format!("no run {id}")));
    }
    state
        .runs
        .get(id)
        .map(Json)
        .ok_or_else(|| AppError::NotFound(format!("no run {id}")))
}

/// Demo mode: whether the service runs trials unattended (`isochron serve
/// --demo`), what it does now (running, waiting, paused and why, waiting for
/// an operator's hold in a real lab) and its demo trials' counts with the
/// Wilson 95% interval of the precisely timed share.
#[utoipa::path(get, path = "/api/demo", tag = "trials",
    responses((status = 200, description = "the demo's status (state `off` without --demo)", body = crate::demo::DemoStatus)))]
pub async fn get_demo(State(state): State<Arc<AppState>>) -> Json<crate::demo::DemoStatus> {
    Json(state.demo.status())
}

/// A trial's signals at the control rate, as CSV (header row; NaN when unknown).
///
/// # Errors
///
/// As [`get_trial`] for the id; [`AppError::NotFound`] when the trial has no
/// recording.
#[utoipa::path(get, path = "/api/trials/{id}/recording.csv", tag = "trials",
    params(("id" = u64, Path, description = "trial id", minimum = 1, maximum = 9_223_372_036_854_775_807_u64)),
    responses(
        (status = 200, description = "CSV, one row per control step", content_type = "text/csv", body = String),
        (status = 400, description = "not a trial id", body = crate::error::ErrorBody),
        (status = 404, description = "no such trial or no recording", body = crate::error::ErrorBody)))]
pub async fn recording_csv(
    State(state): State<Arc<AppState>>,
    Path(raw): Path<String>,
) -> Result<Response, AppError> {
    let (r, rec) = existing(&state, &raw).await?;
    let path = r.recording_path(rec.id);
    let bytes = tokio::fs::read(&path)
        .await
        .map_err(|_| AppError::NotFound(format!("trial {} has no recording", rec.id)))?;
    Ok(download(
        bytes,
        "text/csv",
        &format!("trial-{}.csv", rec.id),
    ))
}

/// A trial's recording as MCAP: the file written live during the trial (Foxglove's
/// well-known schemas, Unix log times, metadata; `server/README.md`) once the
/// trial ended; for trials recorded before live MCAP, converted from the CSV
/// (topic `/isochron/state`, JSON messages with a JSON schema).
///
/// # Errors
///
/// As [`get_trial`] for the id; [`AppError::NotFound`] when the trial has no
/// recording; [`AppError::Internal`] when the CSV cannot be converted.
#[utoipa::path(get, path = "/api/trials/{id}/recording.mcap", tag = "trials",
    params(("id" = u64, Path, description = "trial id", minimum = 1, maximum = 9_223_372_036_854_775_807_u64)),
    responses(
        (status = 200, description = "MCAP file", content_type = "application/octet-stream", body = Vec<u8>),
        (status = 400, description = "not a trial id", body = crate::error::ErrorBody),
        (status = 404, description = "no such trial or no recording", body = crate::error::ErrorBody)))]
pub async fn recording_mcap(
    State(state): State<Arc<AppState>>,
    Path(raw): Path<String>,
) -> Result<Response, AppError> {
    let (r, rec) = existing(&state, &raw).await?;
    let live = r.mcap_path(rec.id);
    if rec.status != "running" && live.is_file() {
        let bytes = tokio::fs::read(&live)
            .await
            .map_err(|_| AppError::NotFound(format!("trial {} has no recording", rec.id)))?;
        return Ok(download(
            bytes,
            "application/octet-stream",
            &format!("trial-{}.mcap", rec.id),
        ));
    }
    let path = r.recording_path(rec.id);
    if !path.is_file() {
        return Err(AppError::NotFound(format!(
            "trial {} has no recording",
            rec.id
        )));
    }
    // A strike's figures from the record (a recording without the live MCAP).
    let measured = rec.measured.filter(|m| m.strike.is_some());
    let id = rec.id;
    let bytes = blocking(move || {
        crate::records::csv_to_mcap_with(&path, measured.as_ref().map(|m| (id, m)))
    })
    .await?;
    Ok(download(
        bytes,
        "application/octet-stream",
        &format!("trial-{}.mcap", rec.id),
    ))
}

/// The arm's URDF (KUKA LBR iiwa 7 R800, `rt-core/src/kinematics/iiwa7.urdf`)
/// with the tool length in effect: links `base`, `link_1` .. `link_7`, `flange`,
/// `tool`; joints `A1` .. `A7`. The dashboard's twin and Foxglove load it.
#[utoipa::path(get, path = "/api/robot.urdf", tag = "service",
    responses((status = 200, description = "URDF (XML)", content_type = "application/xml", body = String)))]
pub async fn robot_urdf(State(state): State<Arc<AppState>>) -> Response {
    let tool_m = state
        .lab
        .as_ref()
        .map_or(Scenario::default().task.tool_length_m, |l| {
            l.params().task.tool_length_m
        });
    (
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/xml"),
        )],
        rt_core::kinematics::iiwa7::urdf_with_tool(tool_m),
    )
        .into_response()
}

fn download(bytes: Vec<u8>, content_type: &'static str, name: &str) -> Response {
    let disposition = HeaderValue::from_str(&format!("attachment; filename=\"{name}\""))
        .unwrap_or_else(|_| HeaderValue::from_static("attachment"));
    (
        [
            (header::CONTENT_TYPE, HeaderValue::from_static(content_type)),
            (header::CONTENT_DISPOSITION, disposition),
        ],
        bytes,
    )
        .into_response()
}

/// Documents the WebSocket state/event stream (upgrade with `GET /ws`).
#[utoipa::path(get, path = "/ws", tag = "streams",
    responses((status = 101, description = "WebSocket: JSON text messages, each with \"type\" (hello, state, event) and \"t_s\"; state at the stream rate (100 Hz default). Schemas: Hello, StateMessage, EventMessage")))]
#[expect(
    dead_code,
    reason = "documents the WebSocket route in the OpenAPI document only"
)]
fn ws_doc() {}

/// Documents the camera stream (upgrade with `GET /ws/camera`).
#[utoipa::path(get, path = "/ws/camera", tag = "streams",
    responses((status = 101, description = "WebSocket: one binary message per camera frame (JPEG, its first segment a COM comment `isochron frame=N t_us=T`: N is the camera.frame of its detection in the state stream, T its capture time on the control clock in microseconds); slow clients get the newest frame only")))]
#[expect(
    dead_code,
    reason = "documents the WebSocket route in the OpenAPI document only"
)]
fn ws_camera_doc() {}

/// This document.
#[utoipa::path(get, path = "/api/openapi.json", tag = "service",
    responses((status = 200, description = "the OpenAPI description of this API", body = Object)))]
pub async fn openapi_json() -> Json<serde_json::Value> {
    Json(openapi_document())
}

/// The OpenAPI document as served. utoipa writes an optional body
/// (`Option<NoFields>`) as "JSON `null` or the object"; the handlers take no
/// body or the object, never `null`, so such a body is written as the object
/// with `required: false` (the document says exactly what is accepted).
pub fn openapi_document() -> serde_json::Value {
    let mut doc = serde_json::to_value(ApiDoc::openapi()).unwrap_or_default();
    if let Some(paths) = doc.get_mut("paths").and_then(|p| p.as_object_mut()) {
        for item in paths.values_mut() {
            let Some(ops) = item.as_object_mut() else {
                continue;
            };
            for op in ops.values_mut() {
                let Some(body) = op.get_mut("requestBody") else {
                    continue;
                };
                let mut optional = false;
                if let Some(content) = body.get_mut("content").and_then(|c| c.as_object_mut()) {
                    for media in content.values_mut() {
                        let Some(schema) = media.get_mut("schema") else {
                            continue;
                        };
                        let inner = schema
                            .get("oneOf")
                            .and_then(|o| o.as_array())
                            .and_then(|o| {
                                let rest: Vec<_> =
                                    o.iter().filter(|s| s["type"] != "null").cloned().collect();
                                (o.len() == 2 && rest.len() == 1).then(|| rest[0].clone())
                            });
                        if let Some(inner) = inner {
                            *schema = inner;
                            optional = true;
                        }
                    }
                }
                if optional {
                    body["required"] = serde_json::Value::Bool(false);
                }
            }
        }
    }
    // `PUT /api/params`: the partial scenario's keys and value types, as the
    // scenario has them (unknown keys and wrong types are refused with 400);
    // value ranges are checked after merging and named in the 400.
    if let Ok(scenario) = serde_json::to_value(Scenario::default())
        && let Some(media) =
            doc.pointer_mut("/paths/~1api~1params/put/requestBody/content/application~1json")
    {
        media["schema"] = patch_schema(&scenario);
        describe_params(&mut media["schema"], &scenario);
    }
    doc
}

/// The doc comments of rt-core's struct fields (`server/build.rs`).
mod param_docs {
    include!(concat!(env!("OUT_DIR"), "/param_docs.rs"));
}

/// The description of a scenario section's field (its doc comment's first
/// paragraph), if it has one.
pub fn param_description(section: &str, key: &str) -> Option<&'static str> {
    let docs = param_docs::PARAM_DOCS;
    let ty = docs
        .iter()
        .find(|(s, f, _, _)| *s == "Scenario" && *f == section)?
        .2;
    docs.iter()
        .find(|(s, f, _, _)| *s == ty && *f == key)
        .map(|d| d.3)
}

/// Gives every `section.key` of the partial scenario's schema its description
/// and its built-in default (`Scenario::default()`), which the dashboard's
/// Parameters panel shows beside each field.
fn describe_params(schema: &mut serde_json::Value, defaults: &serde_json::Value) {
    let Some(sections) = defaults.as_object() else {
        return;
    };
    for (section, values) in sections {
        let Some(values) = values.as_object() else {
            continue;
        };
        if let Some(d) = param_docs::PARAM_DOCS
            .iter()
            .find(|(s, f, _, _)| *s == "Scenario" && f == section)
        {
            schema["properties"][section]["description"] = d.3.into();
        }
        for (key, value) in values {
            let Some(prop) = schema
                .pointer_mut(&format!("/properties/{section}/properties/{key}"))
                .and_then(|p| p.as_object_mut())
            else {
                continue;
            };
            prop.insert("default".into(), value.clone());
            if let Some(d) = param_description(section, key) {
                prop.insert("description".into(), d.into());
            }
        }
    }
}

/// A JSON schema every partial version of `v` satisfies: objects with only
/// `v`'s keys (none required), arrays of `v`'s length, numbers, integers
/// (unsigned where `v`'s is), booleans and strings where `v` has them.
fn patch_schema(v: &serde_json::Value) -> serde_json::Value {
    use serde_json::{Value, json};
    match v {
        Value::Object(m) => {
            let props: serde_json::Map<String, Value> = m
                .iter()
                .map(|(k, x)| (k.clone(), patch_schema(x)))
                .collect();
            json!({"type": "object", "additionalProperties": false, "properties": props})
        }
        Value::Array(a) => json!({
            "type": "array", "minItems": a.len(), "maxItems": a.len(),
            "items": a.first().map_or(json!({}), patch_schema)
        }),
        Value::Number(n) if n.is_u64() => json!({"type": "integer", "minimum": 0}),
        Value::Number(n) if n.is_i64() => json!({"type": "integer"}),
        Value::Number(_) => json!({"type": "number"}),
        Value::Bool(_) => json!({"type": "boolean"}),
        Value::String(_) => json!({"type": "string"}),
        Value::Null => json!({}),
    }
}

struct BearerAuth;

impl utoipa::Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
    }
}

/// The OpenAPI description of the service.
#[derive(OpenApi)]
#[openapi(
    info(title = "isochron lab service", description = "Timed interception of a swinging ball by a KUKA LBR iiwa 7: state, commands, trials and recordings. Commands need `Authorization: Bearer TOKEN` when the service has a token; viewers can watch without one."),
    paths(crate::health, get_state, get_fri, get_params, put_params, arm, disarm, magnet, stop, heartbeat,
          get_calibration, start_calibration,
          start_trial, list_trials, get_trial, start_run, list_runs, get_run, stop_run, get_demo, recording_csv, recording_mcap, robot_urdf, openapi_json,
          ws_doc, ws_camera_doc),
    components(schemas(crate::Health, crate::error::ErrorBody, Accepted, MagnetRequest, StopAnswer, HeartbeatAnswer,
                       TrialStarted, TrialRecord, NoFields, TrialRequest,
                       crate::runs::RunRequest, crate::runs::RunStatus, crate::runs::RunStarted,
                       crate::runs::Distances, crate::demo::DemoStatus, CalibrationRequest, CalibrationStarted,
                       crate::calibration::CalibrationStatus, crate::calibration::StepStatus,
                       crate::calibration::CalibrationJob, crate::calibration::Change,
                       rt_core::calibration::StepView, rt_core::calibration::ViewKind, crate::lab::StreamCounters, FriInfo,
                       crate::lab::StateMessage, crate::lab::EventMessage, crate::ws::Hello,
                       rt_core::bridge::Snapshot, rt_core::bridge::EventRecord,
                       rt_core::bridge::Event, rt_core::bridge::TrialResult)),
    modifiers(&BearerAuth),
    tags((name = "service"), (name = "lab"), (name = "commands"), (name = "calibration"), (name = "trials"), (name = "streams"))
)]
pub struct ApiDoc;

#[cfg(test)]
mod tests {
    use super::*;

    /// The 400 body of a trial refused by `trial_setup`: status, `error`, `field`.
    async fn refused(req: &TrialRequest) -> (StatusCode, serde_json::Value) {
        let Err(e) = trial_setup(req, &Scenario::default(), None) else {
            panic!("{req:?} was accepted")
        };
        let resp = e.into_response();
        let status = resp.status();
        let body = axum::body::to_bytes(resp.into_body(), 1 << 16)
            .await
            .unwrap();
        (status, serde_json::from_slice(&body).unwrap())
    }

    /// A lab that cannot move its pendulum (0.6 m): a trial elsewhere is
    /// refused naming the distance, one there (within 5 mm) or without a
    /// distance is taken, its movement time checked where the pendulum hangs.
    #[tokio::test]
    async fn a_fixed_pendulum_refuses_a_trial_at_another_distance() {
        let params = Scenario::default();
        let at = |d: Option<f64>, mt: Option<f64>| {
            let req = TrialRequest {
                distance_m: d,
                movement_time_s: mt,
                ..TrialRequest::default()
            };
            trial_setup(&req, &params, Some(0.6))
        };
        let Err(e) = at(Some(0.4), None) else {
            panic!("0.4 m was taken by a pendulum at 0.6 m")
        };
        let resp = e.into_response();
        assert_eq!(resp.status(), StatusCode::BAD_REQUEST);
        let body = axum::body::to_bytes(resp.into_body(), 1 << 16)
            .await
            .unwrap();
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["field"], "distance_m", "{v}");
        let msg = v["error"].as_str().unwrap();
        assert!(
            msg.starts_with("distance_m = 0.4 m: this lab's pendulum hangs 0.600 m"),
            "{msg}"
        );
        let s = at(Some(0.603), Some(2.0)).unwrap();
        assert_eq!(s.distance_m, Some(0.603));
        assert!(at(None, Some(1.5)).is_ok());
        // Without a fixed pendulum, any distance the arm reaches.
        assert!(
            trial_setup(
                &TrialRequest {
                    distance_m: Some(0.4),
                    ..TrialRequest::default()
                },
                &params,
                None
            )
            .is_ok()
        );
    }

    #[tokio::test]
    async fn an_infeasible_trial_is_refused_with_the_joint_its_value_and_the_limit() {
        // Out of the arm's reach: the IK's numbers (the wrist centre's distance
        // and the arm's reach) survive to the body.
        let far = TrialRequest {
            distance_m: Some(1.1),
            ..TrialRequest::default()
        };
        let (status, v) = refused(&far).await;
        assert_eq!(status, StatusCode::BAD_REQUEST);
        assert_eq!(v["field"], "distance_m", "{v}");
        let e = v["error"].as_str().unwrap();
        assert!(
            e.starts_with(
                "distance_m = 1.1 m is not reachable in 1.5 s: infeasible motion: unreachable"
            ) && e.contains("from the shoulder, the arm reaches 0.800 m"),
            "{e}"
        );
        // Out of reach at any pace: the distance is at fault, also when a
        // movement time was asked for.
        let far_slow = TrialRequest {
            movement_time_s: Some(2.0),
            ..far
        };
        let (_, v) = refused(&far_slow).await;
        assert_eq!(v["field"], "distance_m", "{v}");
        // Too close to the base: the joint that leaves its margin, by how much,
        // and the margin.
        let near = TrialRequest {
            distance_m: Some(0.2),
            ..far
        };
        let (_, v) = refused(&near).await;
        assert_eq!(v["field"], "distance_m", "{v}");
        let e = v["error"].as_str().unwrap();
        assert!(
            e.contains("keeps every joint 5.0 deg inside its limits")
                && e.contains("A4 comes within -4.90 deg"),
            "{e}"
        );
        // Too fast: the binding joint, its share of the limit, the allowed
        // share and the shortest feasible duration.
        let fast = TrialRequest {
            distance_m: Some(0.8),
            movement_time_s: Some(0.9),
            ..TrialRequest::default()
        };
        let (_, v) = refused(&fast).await;
        assert_eq!(v["field"], "movement_time_s", "{v}");
        let e = v["error"].as_str().unwrap();
        assert!(
            e.starts_with("movement_time_s = 0.9 s is not feasible at 0.8 m: infeasible motion: A")
                && e.contains("limit in 0.90 s (allowed 90%); the shortest feasible duration is"),
            "{e}"
        );
    }

    /// A trial's own task: a strike on a stop lab (its stroke checked at
    /// the distance), and what is refused, naming the field: a strike's
    /// speed or direction on a stop, out of range, a stroke the arm cannot
    /// do, an unknown mode. Nothing is started by a refused one (the caller
    /// creates no record before `trial_setup` passes).
    #[tokio::test]
    async fn a_trial_may_strike_on_a_stop_lab_and_a_bad_stroke_is_refused_naming_its_field() {
        use rt_core::trajectory::TaskMode;
        let params = Scenario::default();
        assert_eq!(params.task.mode, TaskMode::Stop);
        let strike = TrialRequest {
            distance_m: Some(0.6),
            mode: Some(TaskMode::Strike),
            strike_speed_mps: Some(0.5),
            ..TrialRequest::default()
        };
        let s = trial_setup(&strike, &params, None).expect("a feasible strike");
        assert_eq!(
            (s.mode, s.strike_speed_mps, s.strike_direction_deg),
            (Some(TaskMode::Strike), Some(0.5), None)
        );
        // What the lab plans for it: a stroke at that speed.
        let b = rt_core::lab::step::trial_beliefs(&params, &s);
        let plan = rt_core::control::Controller::plan(&b, 0.6).expect("the stroke");
        assert!(plan.strike.is_some(), "planned as a stop");
        let stop = rt_core::control::Controller::plan(
            &rt_core::lab::step::trial_beliefs(&params, &TrialSetup::default()),
            0.6,
        )
        .unwrap();
        assert!(stop.strike.is_none());
        for (req, field, says) in [
            (
                TrialRequest {
                    strike_speed_mps: Some(0.5),
                    ..TrialRequest::default()
                },
                "strike_speed_mps",
                "this trial stops the ball",
            ),
            (
                TrialRequest {
                    mode: Some(TaskMode::Stop),
                    strike_direction_deg: Some(10.0),
                    ..TrialRequest::default()
                },
                "strike_direction_deg",
                "this trial stops the ball",
            ),
            (
                TrialRequest {
                    mode: Some(TaskMode::Strike),
                    strike_speed_mps: Some(f64::NAN),
                    ..TrialRequest::default()
                },
                "strike_speed_mps",
                "out of range",
            ),
            (
                TrialRequest {
                    mode: Some(TaskMode::Strike),
                    strike_speed_mps: Some(0.0),
                    ..TrialRequest::default()
                },
                "strike_speed_mps",
                "meets the ball with speed",
            ),
            (
                TrialRequest {
                    mode: Some(TaskMode::Strike),
                    strike_direction_deg: Some(75.0),
                    ..TrialRequest::default()
                },
                "strike_direction_deg",
                "out of range",
            ),
            (
                TrialRequest {
                    distance_m: Some(0.75),
                    mode: Some(TaskMode::Strike),
                    strike_speed_mps: Some(3.0),
                    ..TrialRequest::default()
                },
                "strike_speed_mps",
                "is not feasible at 0.75 m",
            ),
        ] {
            let (status, v) = refused(&req).await;
            assert_eq!(status, StatusCode::BAD_REQUEST, "{req:?}: {v}");
            assert_eq!(v["field"], field, "{req:?}: {v}");
            assert!(v["error"].as_str().unwrap().contains(says), "{req:?}: {v}");
        }
        // An unknown mode: the body's parse names the field.
        let e = parse_json::<TrialRequest>(br#"{"mode": "punch"}"#).unwrap_err();
        let resp = e.into_response();
        assert_eq!(resp.status(), StatusCode::BAD_REQUEST);
        let body = axum::body::to_bytes(resp.into_body(), 1 << 16)
            .await
            .unwrap();
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["field"], "mode", "{v}");
    }
}
