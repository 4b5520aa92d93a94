//! A control thread for the service tests: it runs a deterministic trial state
//! machine at a fixed period on the real bridge, publishes snapshots, answers
//! commands and reports events, and measures its own loop timing. The real
//! closed loop (`rt_core::control` + `sim`) replaces it in `isochron serve`.
#![allow(
    dead_code,
    missing_docs,
    reason = "a test helper: each of the modules using it takes a part"
)]

use std::{
    path::PathBuf,
    sync::{
        Arc,
        atomic::{AtomicBool, AtomicU64, Ordering},
    },
    thread::JoinHandle,
    time::{Duration, Instant},
};

use rt_core::{
    bridge::{
        AbortKind, BridgeCapacity, Command, ControlEnd, Event, EventRecord, FrameSender,
        HorizonPoint, MagnetState, Refusal, Snapshot, TrialResult, TrialState, bridge,
        frame_channel,
    },
    params::Scenario,
};
use server::{AppState, Lab, LabOptions, Records, app};

/// What the test control thread measured and saw.
#[derive(Debug, Default)]
pub struct LoopStats {
    pub steps: AtomicU64,
    pub commands: AtomicU64,
    pub stops: AtomicU64,
    /// Longest `publish` call, nanoseconds.
    pub publish_max_ns: AtomicU64,
    /// Periods longer than twice the nominal one.
    pub late_periods: AtomicU64,
}

pub struct TestLab {
    pub stats: Arc<LoopStats>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    pub frames: Option<FrameSender>,
}

impl Drop for TestLab {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

pub const PERIOD: Duration = Duration::from_millis(2);
/// Steps a trial spends in each moving state.
const STEPS_PER_STATE: u64 = 40;

struct Machine {
    control: ControlEnd,
    snap: Snapshot,
    params: Box<Scenario>,
    trial: u64,
    since: u64,
}

impl Machine {
    fn set_state(&mut self, to: TrialState) {
        let from = self.snap.trial_state;
        if from == to {
            return;
        }
        self.snap.trial_state = to;
        self.since = self.snap.seq;
        self.control.emit(EventRecord {
            t_s: self.snap.t_s,
            trial_id: self.trial,
            event: Event::StateChanged { from, to },
        });
    }

    fn abort(&mut self, reason: AbortKind) {
        if self.snap.trial_state.busy() {
            self.control.emit(EventRecord {
                t_s: self.snap.t_s,
                trial_id: self.trial,
                event: Event::Aborted { reason, detail: "" },
            });
            self.set_state(TrialState::Aborted);
        }
    }

    fn handle(&mut self, id: u64, cmd: Command) {
        let st = self.snap.trial_state;
        let (outcome, returned) = match cmd {
            Command::Stop => {
                self.abort(AbortKind::Stop);
                (Ok(()), None)
            }
            Command::Arm if st.busy() => (Err(Refusal::Busy), None),
            Command::Arm => {
                self.trial = 0;
                self.snap.magnet = MagnetState::On;
                self.set_state(TrialState::Armed);
                (Ok(()), None)
            }
            Command::Disarm if st != TrialState::Armed => (Err(Refusal::NotArmed), None),
            Command::Disarm => {
                self.set_state(TrialState::Idle);
                (Ok(()), None)
            }
            Command::Magnet { on } => {
                self.snap.magnet = if on {
                    MagnetState::On
                } else {
                    MagnetState::Off
                };
                (Ok(()), None)
            }
            Command::RunTrial { trial_id: 0, .. } => (Err(Refusal::Invalid), None),
            Command::RunTrial { .. } if st.busy() => (Err(Refusal::Busy), None),
            Command::RunTrial { trial_id, .. } => {
                self.trial = trial_id;
                self.snap.trial_id = trial_id;
                self.set_state(TrialState::Arming);
                (Ok(()), None)
            }
            Command::SetParams(p) if st.arm_in_motion() && p.task != self.params.task => {
                (Err(Refusal::MotionRunning), Some(p))
            }
            Command::SetParams(p) => {
                let old = std::mem::replace(&mut self.params, p);
                (Ok(()), Some(old))
            }
            Command::Excite(_) if st.busy() => (Err(Refusal::Busy), None),
            Command::Excite(_) => (Ok(()), None),
            Command::MoveTo(_) | Command::Knock(_) if st.busy() => (Err(Refusal::Busy), None),
            Command::MoveTo(_) | Command::Knock(_) => (Ok(()), None),
        };
        self.control.ack(id, outcome, returned);
    }

    fn step(&mut self) {
        use TrialState::*;
        let dwell = self.snap.seq - self.since;
        if self.trial != 0 && dwell >= STEPS_PER_STATE {
            let next = match self.snap.trial_state {
                Arming => Some(Armed),
                Armed => {
                    self.snap.magnet = MagnetState::Off;
                    Some(Released)
                }
                Released => Some(Tracking),
                Tracking => Some(Intercepting),
                Intercepting => Some(Holding),
                Holding => Some(Done),
                _ => None,
            };
            if let Some(next) = next {
                if next == Done {
                    let t = self.snap.t_s;
                    self.control.emit(EventRecord {
                        t_s: t,
                        trial_id: self.trial,
                        event: Event::TrialFinished {
                            result: TrialResult {
                                success: true,
                                timing_error_ms: 1.5,
                                position_error_m: 0.004,
                                movement_time_s: self.params.task.movement_time_s,
                                distance_m: 0.6,
                                t_star_s: t,
                                arrival_t_s: t + 0.0015,
                                prediction_time_error_ms: 0.7,
                                limit_violations: 0,
                                not_judged: None,
                                measured: None,
                                judged_by: Some(rt_core::bridge::JudgedBy::Truth),
                            },
                        },
                    });
                    self.snap.counters.trials += 1;
                }
                self.set_state(next);
            }
        }
        // Signals that move, so recordings and plots have something to show.
        let t = self.snap.t_s;
        self.snap.pendulum.phi_rad = 0.3 * (2.25 * t).cos();
        self.snap.pendulum.x_m = 1.93 * self.snap.pendulum.phi_rad.sin();
        self.snap.pendulum.measured.valid = true;
        self.snap.pendulum.measured.t_s = t;
        self.snap.pendulum.measured.x_m = self.snap.pendulum.x_m;
        self.snap.pendulum.horizon.len = 0;
        for i in 0..10 {
            let ti = t + 0.1 * f64::from(i);
            self.snap.pendulum.horizon.push(HorizonPoint {
                t_s: ti,
                x_m: 1.93 * (0.3 * (2.25 * ti).cos()).sin(),
                sigma_m: 0.002 + 0.001 * f64::from(i),
            });
        }
        self.snap.hopf.u_init = if self.snap.trial_state == Intercepting {
            0.0
        } else {
            1.0
        };
        self.snap.hopf.u_hopf = 1.0 - self.snap.hopf.u_init;
        self.snap.robot.q_rad = [0.1 * t.sin(); 7];
        self.snap.robot.tool_m = [0.3, 0.0, 0.5];
    }
}

/// Starts the test control thread on a fresh bridge. Returns it and the
/// server end (wrapped in a started [`Lab`]).
pub fn start_lab(records: Option<Arc<Records>>, options: LabOptions) -> (TestLab, Arc<Lab>) {
    let (control, end) = bridge(BridgeCapacity::default());
    let (frame_tx, frame_rx) = frame_channel(4, Arc::clone(&end.stats));
    let lab = Lab::start(end, Some(frame_rx), Scenario::default(), records, options).unwrap();
    let stats = Arc::new(LoopStats::default());
    let stop = Arc::new(AtomicBool::new(false));
    let mut m = Machine {
        control,
        snap: Snapshot::default(),
        params: Box::new(Scenario::default()),
        trial: 0,
        since: 0,
    };
    let thread = {
        let stats = Arc::clone(&stats);
        let stop = Arc::clone(&stop);
        std::thread::Builder::new()
            .name("isochron-test-control".into())
            .spawn(move || {
                let start = Instant::now();
                let mut next = start;
                let mut last = start;
                while !stop.load(Ordering::Acquire) {
                    let now = Instant::now();
                    if now - last > 2 * PERIOD {
                        stats.late_periods.fetch_add(1, Ordering::Relaxed);
                    }
                    last = now;
                    if m.control.take_stop_request() {
                        stats.stops.fetch_add(1, Ordering::Relaxed);
                        m.abort(AbortKind::Stop);
                    }
                    while let Some(env) = m.control.next_command() {
                        stats.commands.fetch_add(1, Ordering::Relaxed);
                        m.handle(env.id, env.command);
                    }
                    m.snap.seq += 1;
                    m.snap.t_s = (now - start).as_secs_f64();
                    m.snap.counters.steps = m.snap.seq;
                    m.step();
                    let t0 = Instant::now();
                    m.control.publish(&m.snap);
                    let ns = t0.elapsed().as_nanos() as u64;
                    stats.publish_max_ns.fetch_max(ns, Ordering::Relaxed);
                    stats.steps.fetch_add(1, Ordering::Relaxed);
                    next += PERIOD;
                    let now = Instant::now();
                    if next > now {
                        std::thread::sleep(next - now);
                    } else {
                        next = now;
                    }
                }
            })
            .unwrap()
    };
    (
        TestLab {
            stats,
            stop,
            thread: Some(thread),
            frames: Some(frame_tx),
        },
        lab,
    )
}

/// A fresh temporary directory.
pub fn temp_dir(tag: &str) -> PathBuf {
    tempfile::Builder::new()
        .prefix(&format!("isochron-{tag}-"))
        .tempdir()
        .expect("a temporary directory")
        .keep()
}

/// The service on a real port.
pub struct Service {
    pub addr: std::net::SocketAddr,
    pub lab: Arc<Lab>,
    pub test_lab: TestLab,
    pub records: Arc<Records>,
    pub data_dir: PathBuf,
    server: tokio::task::JoinHandle<()>,
}

impl Drop for Service {
    fn drop(&mut self) {
        self.server.abort();
        self.lab.shutdown();
    }
}

pub async fn start_service(token: Option<&str>, options: LabOptions) -> Service {
    start_service_in(temp_dir("data"), token, options).await
}

pub async fn start_service_in(
    data_dir: PathBuf,
    token: Option<&str>,
    options: LabOptions,
) -> Service {
    let records = Arc::new(Records::open(&data_dir).unwrap());
    let (test_lab, lab) = start_lab(Some(Arc::clone(&records)), options);
    let state = AppState::new(temp_dir("web"))
        .with_token(token.map(str::to_owned))
        .with_lab(Arc::clone(&lab))
        .with_records(Arc::clone(&records));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let router = app(Arc::new(state));
    let server = tokio::spawn(async move {
        let _ = axum::serve(server::tuned_listener(listener), router).await;
    });
    let svc = Service {
        addr,
        lab,
        test_lab,
        records,
        data_dir,
        server,
    };
    // Ready when the first state was published through the bridge.
    wait_for(Duration::from_secs(10), || svc.lab.latest().is_some()).await;
    svc
}

/// Waits for a condition, polling, with a timeout (panics on timeout).
pub async fn wait_for(timeout: Duration, mut cond: impl FnMut() -> bool) {
    let deadline = Instant::now() + timeout;
    while !cond() {
        assert!(
            Instant::now() < deadline,
            "condition not met within {timeout:?}"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// The latest trial state as the service sees it.
pub fn trial_state(svc: &Service) -> TrialState {
    svc.lab
        .latest()
        .map_or(TrialState::Idle, |(s, _)| s.trial_state)
}
