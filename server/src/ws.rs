//! The WebSocket streams: `/ws` (state and events, JSON) and `/ws/camera`
//! (JPEG frames, binary). Every client has its own task fed by bounded
//! broadcast channels: a slow client skips state messages (counted), a client
//! that stalls longer than the send timeout is dropped (counted); neither ever
//! delays other clients or the control thread.

use std::{
    sync::{Arc, atomic::Ordering},
    time::Duration,
};

use axum::{
    extract::{
        State,
        ws::{Message, Utf8Bytes, WebSocket, WebSocketUpgrade},
    },
    response::Response,
};
use futures_util::{SinkExt, StreamExt};
use serde::Serialize;
use tokio::sync::broadcast::error::RecvError;

use crate::{AppError, AppState, lab::Lab};

/// The first message of `/ws`.
#[derive(Serialize, ts_rs::TS, utoipa::ToSchema)]
pub struct Hello {
    /// Always `hello`.
    #[serde(rename = "type")]
    #[ts(type = "\"hello\"")]
    #[schema(value_type = String, pattern = "^hello$")]
    pub kind: &'static str,
    /// The latest state's time, control clock, seconds.
    pub t_s: f64,
    /// The service's version.
    pub version: &'static str,
    /// State messages per second.
    pub state_hz: f64,
    /// Whether commands need a bearer token.
    pub token_required: bool,
}

/// `GET /ws`: state and event messages.
///
/// # Errors
///
/// [`AppError::Unavailable`] when the lab is not running; [`AppError::Internal`]
/// when the hello message cannot be serialised.
pub async fn state_stream(
    State(state): State<Arc<AppState>>,
    ws: WebSocketUpgrade,
) -> Result<Response, AppError> {
    let lab = lab_of(&state)?;
    let hello = Hello {
        kind: "hello",
        t_s: lab.latest().map_or(0.0, |(s, _)| s.t_s),
        version: crate::VERSION,
        state_hz: lab.options().state_hz,
        token_required: state.token.is_some(),
    };
    let hello: Utf8Bytes = serde_json::to_string(&hello)
        .map_err(|e| AppError::Internal(e.into()))?
        .into();
    Ok(ws.on_upgrade(move |socket| state_client(socket, lab, hello)))
}

/// `GET /ws/camera`: camera frames.
///
/// # Errors
///
/// [`AppError::Unavailable`] when the lab is not running.
pub async fn camera_stream(
    State(state): State<Arc<AppState>>,
    ws: WebSocketUpgrade,
) -> Result<Response, AppError> {
    let lab = lab_of(&state)?;
    Ok(ws.on_upgrade(move |socket| camera_client(socket, lab)))
}

fn lab_of(state: &AppState) -> Result<Arc<Lab>, AppError> {
    state
        .lab
        .clone()
        .ok_or_else(|| AppError::Unavailable("the lab is not running".into()))
}

/// Counts a connected client for as long as it lives.
struct ClientGuard(Arc<Lab>);

impl ClientGuard {
    fn new(lab: &Arc<Lab>) -> Self {
        lab.stream().clients.fetch_add(1, Ordering::Relaxed);
        Self(Arc::clone(lab))
    }
}

impl Drop for ClientGuard {
    fn drop(&mut self) {
        self.0.stream().clients.fetch_sub(1, Ordering::Relaxed);
    }
}

enum Sent {
    Ok,
    Closed,
    Stalled,
}

async fn send_timed(
    sink: &mut futures_util::stream::SplitSink<WebSocket, Message>,
    msg: Message,
    timeout: Duration,
) -> Sent {
    match tokio::time::timeout(timeout, sink.send(msg)).await {
        Ok(Ok(())) => Sent::Ok,
        Ok(Err(_)) => Sent::Closed,
        Err(_) => Sent::Stalled,
    }
}

async fn state_client(socket: WebSocket, lab: Arc<Lab>, hello: Utf8Bytes) {
    let _guard = ClientGuard::new(&lab);
    let mut states = lab.subscribe_state();
    let mut events = lab.subscribe_events();
    let timeout = lab.options().ws_send_timeout;
    let (mut sink, mut incoming) = socket.split();
    if !matches!(
        send_timed(&mut sink, Message::Text(hello), timeout).await,
        Sent::Ok
    ) {
        return;
    }
    loop {
        let msg = tokio::select! {
            biased;
            ev = events.recv() => match ev {
                Ok(text) => text,
                Err(RecvError::Lagged(n)) => {
                    lab.stream().skipped.fetch_add(n, Ordering::Relaxed);
                    continue;
                }
                Err(RecvError::Closed) => break,
            },
            st = states.recv() => match st {
                Ok(text) => text,
                Err(RecvError::Lagged(n)) => {
                    lab.stream().skipped.fetch_add(n, Ordering::Relaxed);
                    continue;
                }
                Err(RecvError::Closed) => break,
            },
            inc = incoming.next() => match inc {
                // Viewers send nothing the service acts on; pings are answered by the library.
                Some(Ok(Message::Close(_)) | Err(_)) | None => break,
                Some(Ok(_)) => continue,
            },
        };
        match send_timed(&mut sink, Message::Text(msg), timeout).await {
            Sent::Ok => {}
            Sent::Closed => break,
            Sent::Stalled => {
                // What it will never get counts as skipped.
                let lost = (states.len() + events.len()) as u64 + 1;
                lab.stream().skipped.fetch_add(lost, Ordering::Relaxed);
                lab.stream().dropped_clients.fetch_add(1, Ordering::Relaxed);
                tracing::info!("dropped a WebSocket client that stopped reading");
                break;
            }
        }
    }
}

async fn camera_client(socket: WebSocket, lab: Arc<Lab>) {
    let _guard = ClientGuard::new(&lab);
    let mut frames = lab.subscribe_frames();
    let timeout = lab.options().ws_send_timeout;
    let (mut sink, mut incoming) = socket.split();
    loop {
        let frame = tokio::select! {
            f = frames.recv() => match f {
                Ok(f) => f,
                Err(RecvError::Lagged(n)) => {
                    lab.stream().skipped.fetch_add(n, Ordering::Relaxed);
                    continue;
                }
                Err(RecvError::Closed) => break,
            },
            inc = incoming.next() => match inc {
                Some(Ok(Message::Close(_)) | Err(_)) | None => break,
                Some(Ok(_)) => continue,
            },
        };
        match send_timed(&mut sink, Message::Binary(frame), timeout).await {
            Sent::Ok => {}
            Sent::Closed => break,
            Sent::Stalled => {
                let lost = frames.len() as u64 + 1;
                lab.stream().skipped.fetch_add(lost, Ordering::Relaxed);
                lab.stream().dropped_clients.fetch_add(1, Ordering::Relaxed);
                break;
            }
        }
    }
}
