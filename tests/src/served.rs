//! A lab served over HTTP inside the test's process, as `isochron serve` runs
//! it, and the WebSocket's trial-end events of any served lab.

use std::{
    net::SocketAddr,
    path::Path,
    sync::Arc,
    time::{Duration, Instant},
};

use futures_util::StreamExt;
use rt_core::{bridge::FriSessionState, lab::LabSetup};
use serde_json::Value;
use server::{AppState, Lab, LabOptions, Records, app, runtime::LabRuntime};
use tokio_tungstenite::tungstenite::Message;

/// A lab (`setup`: e.g. [`rt_core::sim::wall_lab::simulated`]) behind the service on a free
/// loopback port, with trial records in a data folder. Stop it with
/// [`ServedLab::stop`] (the records stay in the folder).
pub struct ServedLab {
    /// The service's address.
    pub addr: SocketAddr,
    /// The server side of the lab.
    pub lab: Arc<Lab>,
    /// The trial records.
    pub records: Arc<Records>,
    /// The HTTP server's task.
    pub server: tokio::task::JoinHandle<()>,
    /// The lab's threads (FRI session, simulated controller, camera, magnet);
    /// dropping it stops them.
    pub runtime: LabRuntime,
}

impl ServedLab {
    /// Starts `setup`'s lab with its records in `data` and serves it (no
    /// token, an empty web folder in `data/web`).
    ///
    /// # Panics
    /// When the records, the lab or the listener cannot be set up.
    pub async fn start(setup: LabSetup, data: &Path) -> Self {
        let records = Arc::new(Records::open(data).expect("the trial records"));
        let (lab, runtime) =
            server::runtime::start_lab(setup, Some(Arc::clone(&records)), LabOptions::default())
                .expect("the lab starts");
        let web = data.join("web");
        std::fs::create_dir_all(&web).expect("the web folder");
        let state = AppState::new(web)
            .with_lab(Arc::clone(&lab))
            .with_records(Arc::clone(&records));
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("a loopback port");
        let addr = listener.local_addr().expect("the listener's address");
        let server = tokio::spawn(async move {
            let _ = axum::serve(server::tuned_listener(listener), app(Arc::new(state))).await;
        });
        Self {
            addr,
            lab,
            records,
            server,
            runtime,
        }
    }

    /// Waits (at most 30 s) until the FRI session is COMMANDING_ACTIVE and the
    /// lab would take a trial (the camera delivering: a loaded machine's vision
    /// thread can take a while to start).
    ///
    /// # Panics
    /// When it is not so within 30 s, with the session and readiness it saw.
    pub async fn until_ready(&self) {
        let deadline = Instant::now() + Duration::from_secs(30);
        while self.lab.latest().is_none_or(|(s, _)| {
            s.fri.session != FriSessionState::CommandingActive || !s.ready.trial
        }) {
            assert!(
                Instant::now() < deadline,
                "the lab does not take a trial: {:?}",
                self.lab.latest().map(|(s, _)| (s.fri.session, s.ready))
            );
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    /// Stops the service and the lab and its threads.
    pub fn stop(self) {
        self.server.abort();
        self.lab.shutdown();
        drop(self.runtime);
    }
}

/// The trial-end events (`trial_finished`, `aborted`) a service's WebSocket
/// (`/ws`) announces, whole and in order, read by a task of their own.
pub struct TrialEnds {
    rx: tokio::sync::mpsc::Receiver<Value>,
    seen: Vec<Value>,
    task: tokio::task::JoinHandle<()>,
}

impl Drop for TrialEnds {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl TrialEnds {
    /// Connects to `ws://addr/ws` and collects from now on.
    ///
    /// # Panics
    /// When the WebSocket does not connect.
    pub async fn connect(addr: SocketAddr) -> Self {
        let (ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
            .await
            .expect("the WebSocket connects");
        let (tx, rx) = tokio::sync::mpsc::channel(4096);
        let task = tokio::spawn(async move {
            let (_sink, mut stream) = ws.split();
            while let Some(Ok(m)) = stream.next().await {
                if let Message::Text(t) = m
                    && let Ok(v) = serde_json::from_str::<Value>(&t)
                    && v["type"] == "event"
                    && matches!(
                        v["event"]["kind"].as_str(),
                        Some("aborted" | "trial_finished")
                    )
                {
                    let _ = tx.send(v).await;
                }
            }
        });
        Self {
            rx,
            seen: Vec::new(),
            task,
        }
    }

    /// Every end event so far, in the order the WebSocket sent them.
    pub fn events(&mut self) -> &[Value] {
        while let Ok(v) = self.rx.try_recv() {
            self.seen.push(v);
        }
        &self.seen
    }

    /// The trial ids of the end events so far, in order (0 for an event
    /// without one).
    pub fn ids(&mut self) -> Vec<u64> {
        self.events()
            .iter()
            .map(|v| v["trial_id"].as_u64().unwrap_or(0))
            .collect()
    }

    /// How many end events trial `id` had so far.
    pub fn count(&mut self, id: u64) -> usize {
        self.ids().into_iter().filter(|&i| i == id).count()
    }

    /// Waits until every trial in `ids` has an end event (at most `timeout`).
    ///
    /// # Panics
    /// When one has none by then, with the ids it saw.
    pub async fn wait_all(&mut self, ids: &[u64], timeout: Duration) {
        let deadline = Instant::now() + timeout;
        loop {
            let seen = self.ids();
            if ids.iter().all(|i| seen.contains(i)) {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "the WebSocket announced the ends of {seen:?} only, of {ids:?}"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}
