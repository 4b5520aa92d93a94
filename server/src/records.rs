//! Trial records (SQLite, bundled) and recordings (CSV on disk, MCAP on export).
//!
//! Layout of the data directory:
//! ```text
//! DATA_DIR/trials.sqlite          one row per trial
//! DATA_DIR/recordings/<id>.csv    the trial's signals at the control rate
//! ```
//! A recording is appended while the trial runs (flushed every pump tick) and
//! fsynced when it ends, so a crash of the service loses at most the last
//! moments of a running trial; a trial left `running` by a crash (or a stop
//! of the service mid-trial) is closed at the next start as `aborted` with
//! `abort_reason` `service_restarted`: no record stays `running`.

use std::{
    fs::{File, OpenOptions},
    io::Write,
    path::{Path, PathBuf},
    sync::Mutex,
    time::{SystemTime, UNIX_EPOCH},
};

use anyhow::{Context, anyhow};
use rt_core::bridge::{JudgedBy, Snapshot, TrialResult};
use rt_core::control::measured::MeasuredJudgement;
use rusqlite::{Connection, OptionalExtension, params};
use serde::Serialize;
use utoipa::ToSchema;

/// Unix time now, seconds.
pub fn unix_now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// One trial as stored.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema, ts_rs::TS)]
pub struct TrialRecord {
    /// Trial id (> 0).
    #[ts(type = "number")]
    pub id: u64,
    /// `running`, `done` or `aborted` (a trial the service stopped in is
    /// closed at its next start as `aborted`, `abort_reason` `service_restarted`).
    pub status: String,
    /// Why it ended so, a sentence (null while running): the abort's reason
    /// and what the lab saw, `not judged: ...` for a trial whose outcome
    /// could not be judged (then `success` is null), or the judge's verdict.
    pub reason: Option<String>,
    /// Unix time the trial was started, seconds.
    pub started_unix_s: f64,
    /// Unix time it ended, seconds.
    pub finished_unix_s: Option<f64>,
    /// Hit within the tolerances (`done` and judged; null when not judged).
    pub success: Option<bool>,
    /// |arrival - t*|, milliseconds.
    pub timing_error_ms: Option<f64>,
    /// Tool point to ball centre at t*, metres.
    pub position_error_m: Option<f64>,
    /// Fitted movement time, seconds (a real lab's: fitted on the measured
    /// tool point, also for a trial that was not judged).
    pub movement_time_s: Option<f64>,
    /// Distance of the intercept point, metres.
    pub distance_m: Option<f64>,
    /// Predicted minus true crossing time at motion start, milliseconds.
    pub prediction_time_error_ms: Option<f64>,
    /// Joint limit violations.
    #[ts(type = "number | null")]
    pub limit_violations: Option<u64>,
    /// Why it was aborted (snake_case reason).
    pub abort_reason: Option<String>,
    /// Rows in the recording.
    #[ts(type = "number")]
    pub samples: u64,
    /// The scenario that ran (null for trials recorded before it was stored).
    pub scenario: Option<String>,
    /// The software revision that ran it.
    pub revision: Option<String>,
    /// The measured judge's verdict (camera detections, measured joints,
    /// FRI's external torques; never the ground truth), when the trial had a
    /// committed motion: the real lab's judgement (then `success` is its
    /// verdict), beside the true one in a simulated lab.
    pub measured: Option<MeasuredJudgement>,
    /// Which judge gave `success` and the figures above: `truth` (a truthful
    /// simulated world's ground truth), `physical` (the reality lab's true
    /// world) or `measured` (the measured judge: a real lab; then
    /// `timing_error_ms` is `|measured.timing_error_ms|` and
    /// `position_error_m` null). Null while running, when aborted or not
    /// judged, and for trials recorded before it was stored.
    pub judged_by: Option<JudgedBy>,
}

/// How a trial ended.
#[derive(Debug, Clone, Copy, PartialEq)]
#[expect(
    clippy::large_enum_variant,
    reason = "built from a bridge::Event by value, once a trial: no box needed"
)]
pub enum TrialEnd {
    /// With a result.
    Done(TrialResult),
    /// Aborted: why, and what the lab saw (may be empty).
    Aborted(rt_core::bridge::AbortKind, &'static str),
}

/// The trial database and the recordings folder.
#[derive(Debug)]
pub struct Records {
    dir: PathBuf,
    db: Mutex<Connection>,
}

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS trials (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    status TEXT NOT NULL,
    started_unix_s REAL NOT NULL,
    finished_unix_s REAL,
    success INTEGER,
    timing_error_ms REAL,
    position_error_m REAL,
    movement_time_s REAL,
    distance_m REAL,
    prediction_time_error_ms REAL,
    limit_violations INTEGER,
    abort_reason TEXT,
    samples INTEGER NOT NULL DEFAULT 0,
    scenario TEXT,
    params_toml TEXT,
    revision TEXT
);";

/// Columns added after the first schema (older databases get them on open).
const ADDED_COLUMNS: [(&str, &str); 6] = [
    ("scenario", "TEXT"),
    ("params_toml", "TEXT"),
    ("revision", "TEXT"),
    ("reason", "TEXT"),
    // The measured judge's verdict as JSON (`MeasuredJudgement`).
    ("measured", "TEXT"),
    // Which judge gave the verdict (`JudgedBy::as_str`).
    ("judged_by", "TEXT"),
];

/// What produced a trial: stored in its row when it starts.
#[derive(Debug, Clone, Default)]
pub struct TrialOrigin {
    /// The scenario's name.
    pub scenario: String,
    /// The parameters in effect, as TOML.
    pub params_toml: String,
    /// The software revision (`0.1.0 (git ...)`).
    pub revision: String,
}

impl Records {
    /// Opens (creating if needed) the records in `data_dir`.
    ///
    /// # Errors
    ///
    /// When the data directory cannot be created, or the database cannot be opened,
    /// set up, migrated or its left-running trials closed.
    pub fn open(data_dir: &Path) -> anyhow::Result<Self> {
        let rec = data_dir.join("recordings");
        std::fs::create_dir_all(&rec)
            .with_context(|| format!("cannot create the data directory {}", rec.display()))?;
        let db_path = data_dir.join("trials.sqlite");
        let db = Connection::open(&db_path)
            .with_context(|| format!("cannot open {}", db_path.display()))?;
        db.pragma_update(None, "journal_mode", "WAL")?;
        db.pragma_update(None, "synchronous", "FULL")?;
        db.execute_batch(SCHEMA)?;
        let have: Vec<String> = db
            .prepare("SELECT name FROM pragma_table_info('trials')")?
            .query_map([], |r| r.get(0))?
            .collect::<Result<_, _>>()?;
        for (name, ty) in ADDED_COLUMNS {
            if !have.iter().any(|h| h == name) {
                db.execute_batch(&format!("ALTER TABLE trials ADD COLUMN {name} {ty}"))?;
            }
        }
        // Trials a crash or a stop of the service left `running` (and rows an
        // older version marked `interrupted`) are closed as aborted.
        let restarted = rt_core::bridge::AbortKind::ServiceRestarted;
        let closed = db.execute(
            "UPDATE trials SET status = 'aborted', success = 0, abort_reason = ?1,
               reason = ?2, finished_unix_s = COALESCE(finished_unix_s, ?3)
             WHERE status IN ('running', 'interrupted')",
            params![
                restarted.as_str(),
                abort_sentence(restarted, ""),
                unix_now_s()
            ],
        )?;
        if closed > 0 {
            tracing::warn!(
                closed,
                "trials left running by the last run closed as aborted (service_restarted)"
            );
        }
        Ok(Self {
            dir: data_dir.to_path_buf(),
            db: Mutex::new(db),
        })
    }

    fn db(&self) -> anyhow::Result<std::sync::MutexGuard<'_, Connection>> {
        self.db
            .lock()
            .map_err(|_| anyhow!("trial database lock poisoned"))
    }

    /// The data directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The MCAP recording of a trial (written live by the bridge thread).
    pub fn mcap_path(&self, id: u64) -> PathBuf {
        self.dir.join("recordings").join(format!("{id}.mcap"))
    }

    /// The recording file of a trial.
    pub fn recording_path(&self, id: u64) -> PathBuf {
        self.dir.join("recordings").join(format!("{id}.csv"))
    }

    /// Adds a running trial and returns its id.
    ///
    /// # Errors
    ///
    /// When the database lock is poisoned or the insert fails.
    pub fn create_trial(&self, origin: &TrialOrigin) -> anyhow::Result<u64> {
        let db = self.db()?;
        db.execute(
            "INSERT INTO trials (status, started_unix_s, scenario, params_toml, revision)
             VALUES ('running', ?1, ?2, ?3, ?4)",
            params![
                unix_now_s(),
                origin.scenario,
                origin.params_toml,
                origin.revision
            ],
        )?;
        u64::try_from(db.last_insert_rowid()).context("negative row id")
    }

    /// Removes a trial that never started (the control thread refused it).
    ///
    /// # Errors
    ///
    /// When the database lock is poisoned or the delete fails.
    pub fn delete_trial(&self, id: u64) -> anyhow::Result<()> {
        self.db()?
            .execute("DELETE FROM trials WHERE id = ?1", params![id as i64])?;
        Ok(())
    }

    /// Records how a running trial ended; a trial already ended is left alone.
    ///
    /// # Errors
    ///
    /// When the database lock is poisoned or the update fails.
    pub fn finish_trial(&self, id: u64, end: TrialEnd, samples: u64) -> anyhow::Result<bool> {
        let db = self.db()?;
        let n = match end {
            TrialEnd::Done(r) => db.execute(
                "UPDATE trials SET status = 'done', finished_unix_s = ?2, success = ?3,
                   timing_error_ms = ?4, position_error_m = ?5, movement_time_s = ?6,
                   distance_m = ?7, prediction_time_error_ms = ?8, limit_violations = ?9,
                   samples = ?10, reason = ?11, measured = ?12, judged_by = ?13
                 WHERE id = ?1 AND status = 'running'",
                params![
                    id as i64,
                    unix_now_s(),
                    r.not_judged.is_none().then_some(r.success),
                    finite(r.timing_error_ms),
                    finite(r.position_error_m),
                    finite(r.movement_time_s),
                    finite(r.distance_m),
                    finite(r.prediction_time_error_ms),
                    r.limit_violations as i64,
                    samples as i64,
                    done_reason(&r),
                    r.measured.and_then(|m| serde_json::to_string(&m).ok()),
                    r.judged_by.map(JudgedBy::as_str)
                ],
            )?,
            TrialEnd::Aborted(reason, detail) => db.execute(
                "UPDATE trials SET status = 'aborted', finished_unix_s = ?2, success = 0,
                   abort_reason = ?3, samples = ?4, reason = ?5
                 WHERE id = ?1 AND status = 'running'",
                params![
                    id as i64,
                    unix_now_s(),
                    reason.as_str(),
                    samples as i64,
                    abort_sentence(reason, detail)
                ],
            )?,
        };
        Ok(n > 0)
    }

    /// What produced a trial (scenario, parameters, revision) as its row stores it.
    ///
    /// # Errors
    ///
    /// When the database lock is poisoned or the query fails (no such trial is `Ok(None)`).
    pub fn origin(&self, id: u64) -> anyhow::Result<Option<TrialOrigin>> {
        let db = self.db()?;
        let mut st =
            db.prepare_cached("SELECT scenario, params_toml, revision FROM trials WHERE id = ?1")?;
        Ok(st
            .query_row(params![id as i64], |r| {
                Ok(TrialOrigin {
                    scenario: r.get::<_, Option<String>>(0)?.unwrap_or_default(),
                    params_toml: r.get::<_, Option<String>>(1)?.unwrap_or_default(),
                    revision: r.get::<_, Option<String>>(2)?.unwrap_or_default(),
                })
            })
            .optional()?)
    }

    /// One trial.
    ///
    /// # Errors
    ///
    /// When the database lock is poisoned or the query fails (no such trial is `Ok(None)`).
    pub fn get(&self, id: u64) -> anyhow::Result<Option<TrialRecord>> {
        let db = self.db()?;
        let mut st = db.prepare_cached(&format!("{SELECT} WHERE id = ?1"))?;
        Ok(st.query_row(params![id as i64], row).optional()?)
    }

    /// The newest trials first, at most `limit`.
    ///
    /// # Errors
    ///
    /// When the database lock is poisoned, the query fails or a row cannot be read.
    pub fn list(&self, limit: u32) -> anyhow::Result<Vec<TrialRecord>> {
        let db = self.db()?;
        let mut st = db.prepare_cached(&format!("{SELECT} ORDER BY id DESC LIMIT ?1"))?;
        let rows = st.query_map(params![limit], row)?;
        Ok(rows.collect::<Result<_, _>>()?)
    }
}

/// A finished trial's `reason`, as its record stores it.
pub fn end_reason(end: &TrialEnd) -> String {
    match end {
        TrialEnd::Done(r) => done_reason(r),
        TrialEnd::Aborted(reason, detail) => abort_sentence(*reason, detail),
    }
}

/// A done trial's `reason`: why it was not judged, or the verdict.
fn done_reason(r: &TrialResult) -> String {
    // The real lab's verdict is the measured judge's (it has no ground truth).
    let measured = r
        .measured
        .filter(|_| r.judged_by == Some(JudgedBy::Measured));
    match r.not_judged {
        Some(why) => why.to_owned(),
        None if measured.is_some() && r.success => {
            "judged (measured): a hit within the tolerances".to_owned()
        }
        None if r.limit_violations > 0 => "judged: a miss (joint limit violated)".to_owned(),
        None if measured.is_some_and(|m| !m.contact) => {
            "judged (measured): a miss (no contact seen in the external joint torques)".to_owned()
        }
        // A strike in time whose ball left too slow, too fast or not back.
        None if measured.and_then(|m| m.strike).is_some_and(|k| k.in_time) => {
            strike_miss(measured.and_then(|m| m.strike))
        }
        None if measured.is_some() => format!(
            "judged (measured): a miss (timing error {:+.1} ms outside the tolerance)",
            measured.and_then(|m| m.timing_error_ms).unwrap_or(f64::NAN)
        ),
        None if r.success => "judged: a hit within the tolerances".to_owned(),
        None if r.limit_violations > 0 => "judged: a miss (joint limit violated)".to_owned(),
        None => "judged: a miss (outside the tolerances)".to_owned(),
    }
}

/// Why a measured strike in time missed: its ball's outgoing speed.
fn strike_miss(k: Option<rt_core::control::measured::MeasuredStrike>) -> String {
    match k.map(|k| {
        (
            k.ball_speed_mps,
            k.speed_error,
            k.returned,
            k.target_ball_speed_mps,
        )
    }) {
        Some((Some(v), Some(e), true, target)) => format!(
            "judged (measured): a miss (strike: ball out at {v:.2} m/s, {:+.0}% of the \
             {target:.2} m/s target)",
            e * 100.0
        ),
        _ => "judged (measured): a miss (strike: the ball did not return)".to_owned(),
    }
}

/// An aborted trial's `reason`: `aborted (REASON): MESSAGE[: DETAIL]`.
pub fn abort_sentence(reason: rt_core::bridge::AbortKind, detail: &str) -> String {
    let mut s = format!("aborted ({}): {}", reason.as_str(), reason.message());
    if !detail.is_empty() {
        s.push_str(": ");
        s.push_str(detail);
    }
    s
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

const SELECT: &str = "SELECT id, status, started_unix_s, finished_unix_s, success, timing_error_ms,
    position_error_m, movement_time_s, distance_m, prediction_time_error_ms, limit_violations,
    abort_reason, samples, scenario, revision, reason, measured, judged_by FROM trials";

fn row(r: &rusqlite::Row<'_>) -> rusqlite::Result<TrialRecord> {
    Ok(TrialRecord {
        id: r.get::<_, i64>(0)? as u64,
        status: r.get(1)?,
        started_unix_s: r.get(2)?,
        finished_unix_s: r.get(3)?,
        success: r.get(4)?,
        timing_error_ms: r.get(5)?,
        position_error_m: r.get(6)?,
        movement_time_s: r.get(7)?,
        distance_m: r.get(8)?,
        prediction_time_error_ms: r.get(9)?,
        limit_violations: r.get::<_, Option<i64>>(10)?.map(|v| v as u64),
        abort_reason: r.get(11)?,
        samples: r.get::<_, i64>(12)? as u64,
        scenario: r.get(13)?,
        revision: r.get(14)?,
        reason: r.get(15)?,
        measured: r
            .get::<_, Option<String>>(16)?
            .and_then(|j| serde_json::from_str(&j).ok()),
        judged_by: r
            .get::<_, Option<String>>(17)?
            .as_deref()
            .and_then(JudgedBy::parse),
    })
}

/// One recorded signal: its CSV column and how it is read from a snapshot.
struct Column {
    name: &'static str,
    get: fn(&Snapshot) -> f64,
}

macro_rules! col {
    ($name:literal, |$s:ident| $e:expr) => {
        Column {
            name: $name,
            get: |$s: &Snapshot| $e,
        }
    };
}

fn b(v: bool) -> f64 {
    if v { 1.0 } else { 0.0 }
}

/// The recorded signals, in CSV column order (besides `trial_state`, all numbers;
/// NaN when unknown). Documented in server/README.md.
const COLUMNS: &[Column] = &[
    col!("t_s", |s| s.t_s),
    col!("seq", |s| s.seq as f64),
    col!("measured_valid", |s| b(s.pendulum.measured.valid)),
    col!("measured_t_s", |s| s.pendulum.measured.t_s),
    col!("measured_x_m", |s| s.pendulum.measured.x_m),
    col!("phi_rad", |s| s.pendulum.phi_rad),
    col!("dphi_radps", |s| s.pendulum.dphi_radps),
    col!("sigma_phi_rad", |s| s.pendulum.sigma_phi_rad),
    col!("sigma_dphi_radps", |s| s.pendulum.sigma_dphi_radps),
    col!("x_m", |s| s.pendulum.x_m),
    col!("sigma_x_m", |s| s.pendulum.sigma_x_m),
    col!("ball_x_m", |s| s.pendulum.ball_m[0]),
    col!("ball_y_m", |s| s.pendulum.ball_m[1]),
    col!("ball_z_m", |s| s.pendulum.ball_m[2]),
    col!("truth_ball_x_m", |s| s.pendulum.truth_ball_m[0]),
    col!("truth_ball_y_m", |s| s.pendulum.truth_ball_m[1]),
    col!("truth_ball_z_m", |s| s.pendulum.truth_ball_m[2]),
    col!("crossing_t_s", |s| s.pendulum.crossing_t_s),
    col!("crossing_sigma_s", |s| s.pendulum.crossing_sigma_s),
    col!("hopf_active", |s| b(s.hopf.active)),
    col!("hopf_a", |s| s.hopf.a),
    col!("hopf_b", |s| s.hopf.b),
    col!("u_init", |s| s.hopf.u_init),
    col!("u_hopf", |s| s.hopf.u_hopf),
    col!("u_final", |s| s.hopf.u_final),
    col!("speed_planned_mps", |s| s.path.speed_planned_mps),
    col!("speed_executed_mps", |s| s.path.speed_executed_mps),
    col!("progress_planned", |s| s.path.progress_planned),
    col!("progress_executed", |s| s.path.progress_executed),
    col!("arrival_t_s", |s| s.path.arrival_t_s),
    col!("q1_rad", |s| s.robot.q_rad[0]),
    col!("q2_rad", |s| s.robot.q_rad[1]),
    col!("q3_rad", |s| s.robot.q_rad[2]),
    col!("q4_rad", |s| s.robot.q_rad[3]),
    col!("q5_rad", |s| s.robot.q_rad[4]),
    col!("q6_rad", |s| s.robot.q_rad[5]),
    col!("q7_rad", |s| s.robot.q_rad[6]),
    col!("q_cmd1_rad", |s| s.robot.q_cmd_rad[0]),
    col!("q_cmd2_rad", |s| s.robot.q_cmd_rad[1]),
    col!("q_cmd3_rad", |s| s.robot.q_cmd_rad[2]),
    col!("q_cmd4_rad", |s| s.robot.q_cmd_rad[3]),
    col!("q_cmd5_rad", |s| s.robot.q_cmd_rad[4]),
    col!("q_cmd6_rad", |s| s.robot.q_cmd_rad[5]),
    col!("q_cmd7_rad", |s| s.robot.q_cmd_rad[6]),
    col!("tool_x_m", |s| s.robot.tool_m[0]),
    col!("tool_y_m", |s| s.robot.tool_m[1]),
    col!("tool_z_m", |s| s.robot.tool_m[2]),
    col!("actuation_latency_ms", |s| s.robot.actuation_latency_ms),
    col!("fri_reply_latency_us", |s| s.fri.reply_latency_us),
    col!("fri_late_replies", |s| s.fri.late_replies as f64),
    col!("fri_missed_cycles", |s| s.fri.missed_cycles as f64),
    col!("step_us", |s| s.timing.step_us),
];

/// The CSV header fields: `trial_state`, then [`COLUMNS`].
pub fn csv_header() -> impl Iterator<Item = &'static str> {
    std::iter::once("trial_state").chain(COLUMNS.iter().map(|c| c.name))
}

/// Writes one snapshot as a CSV row (`buf` is scratch space for the numbers).
fn csv_row<W: Write>(w: &mut csv::Writer<W>, s: &Snapshot, buf: &mut String) -> csv::Result<()> {
    use std::fmt::Write as _;
    w.write_field(s.trial_state.as_str())?;
    for c in COLUMNS {
        buf.clear();
        // `{}` on f64 is the shortest text that reads back to the same number.
        let _ = write!(buf, "{}", (c.get)(s));
        w.write_field(buf.as_bytes())?;
    }
    w.write_record(None::<&[u8]>)
}

/// Writes the running trial's recording (owned by the server's bridge thread).
#[derive(Debug, Default)]
pub struct Recorder {
    current: Option<Recording>,
    buf: String,
}

#[derive(Debug)]
struct Recording {
    id: u64,
    file: csv::Writer<File>,
    samples: u64,
}

impl Recorder {
    /// Appends a snapshot of trial `path`'s recording, opening it on its first row.
    ///
    /// # Errors
    ///
    /// When the recording file cannot be opened or a row cannot be written.
    pub fn append(&mut self, path: &Path, trial_id: u64, s: &Snapshot) -> anyhow::Result<()> {
        if self.current.as_ref().is_none_or(|r| r.id != trial_id) {
            // A new trial: the previous one is closed (synced) first.
            self.finish();
            let file = OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)
                .with_context(|| format!("cannot open {}", path.display()))?;
            let empty = file.metadata().map_or(true, |m| m.len() == 0);
            let mut file = csv::Writer::from_writer(file);
            if empty {
                file.write_record(csv_header())?;
            }
            self.current = Some(Recording {
                id: trial_id,
                file,
                samples: 0,
            });
        }
        if let Some(r) = self.current.as_mut() {
            csv_row(&mut r.file, s, &mut self.buf)?;
            r.samples += 1;
        }
        Ok(())
    }

    /// The trial being recorded.
    pub fn current(&self) -> Option<u64> {
        self.current.as_ref().map(|r| r.id)
    }

    /// Hands buffered rows to the operating system (each pump tick).
    pub fn flush(&mut self) {
        if let Some(r) = self.current.as_mut() {
            if let Err(e) = r.file.flush() {
                tracing::error!(trial = r.id, error = %e, "cannot write the recording");
            }
        }
    }

    /// Ends the current recording: flush and fsync. Returns (trial id, rows).
    pub fn finish(&mut self) -> Option<(u64, u64)> {
        let r = self.current.take()?;
        let (id, samples) = (r.id, r.samples);
        match r.file.into_inner() {
            Ok(f) => {
                if let Err(e) = f.sync_all() {
                    tracing::error!(trial = id, error = %e, "cannot sync the recording");
                }
            }
            Err(e) => tracing::error!(trial = id, error = %e, "cannot write the recording"),
        }
        Some((id, samples))
    }
}

/// Converts a CSV recording to MCAP: one JSON message per row on the topic
/// `/isochron/state`, with a JSON schema, log time = the control clock `t_s`.
///
/// # Errors
///
/// When the CSV cannot be opened or read, has no data columns, or the MCAP cannot
/// be written.
pub fn csv_to_mcap(csv_path: &Path) -> anyhow::Result<Vec<u8>> {
    csv_to_mcap_with(csv_path, None)
}

/// [`csv_to_mcap`], and for a strike trial (`trial`: its id and the measured
/// judge's verdict, as its record keeps it) one message on
/// [`crate::viz::STRIKE_TOPIC`] after the rows (log time the last row's):
/// the tool's speed at contact planned and executed, the outgoing ball
/// speed predicted (with the rebound's curve) and seen.
///
/// # Errors
///
/// As [`csv_to_mcap`].
pub fn csv_to_mcap_with(
    csv_path: &Path,
    trial: Option<(u64, &MeasuredJudgement)>,
) -> anyhow::Result<Vec<u8>> {
    let mut reader = csv::ReaderBuilder::new()
        .flexible(true)
        .from_path(csv_path)
        .with_context(|| format!("cannot open {}", csv_path.display()))?;
    let names: Vec<String> = reader
        .headers()
        .context("empty recording")?
        .iter()
        .map(str::to_owned)
        .collect();
    anyhow::ensure!(names.len() > 1, "empty recording: {}", csv_path.display());
    let mut props = serde_json::Map::new();
    for n in &names {
        let ty = if n == "trial_state" {
            serde_json::json!({"type": "string"})
        } else {
            serde_json::json!({"type": ["number", "null"]})
        };
        props.insert(n.clone(), ty);
    }
    let schema = serde_json::json!({
        "type": "object",
        "title": "isochron.State",
        "properties": props,
    });
    let mut w = mcap::Writer::new(std::io::Cursor::new(Vec::new()))?;
    let schema_id = w.add_schema(
        "isochron.State",
        "jsonschema",
        serde_json::to_string(&schema)?.as_bytes(),
    )?;
    let channel = w.add_channel(
        schema_id,
        "/isochron/state",
        "json",
        &std::collections::BTreeMap::new(),
    )?;
    let mut seq = 0u32;
    let mut last_t_ns = 0u64;
    for row in reader.records() {
        let fields = match row {
            Ok(r) if r.len() == names.len() => r,
            // A line cut short by a crash: the rows before it are kept.
            _ => {
                tracing::warn!(file = %csv_path.display(), "skipping a truncated recording row");
                continue;
            }
        };
        let mut obj = serde_json::Map::new();
        let mut t_s = f64::NAN;
        for (n, f) in names.iter().zip(&fields) {
            let v = if n == "trial_state" {
                serde_json::Value::String(f.to_owned())
            } else {
                let x: f64 = f.parse().unwrap_or(f64::NAN);
                if n == "t_s" {
                    t_s = x;
                }
                serde_json::Number::from_f64(x).map_or(serde_json::Value::Null, Into::into)
            };
            obj.insert(n.clone(), v);
        }
        let t_ns = if t_s.is_finite() && t_s >= 0.0 {
            (t_s * 1e9) as u64
        } else {
            last_t_ns
        };
        last_t_ns = t_ns;
        let data = serde_json::to_vec(&obj)?;
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: channel,
                sequence: seq,
                log_time: t_ns,
                publish_time: t_ns,
            },
            &data,
        )?;
        seq = seq.wrapping_add(1);
    }
    let strike = trial.and_then(|(id, m)| {
        crate::viz::StrikeMessage::of(id, m, m.contact_t_s.unwrap_or(f64::NAN))
    });
    if let Some(k) = strike {
        let schema = w.add_schema(
            crate::viz::STRIKE_SCHEMA_NAME,
            "jsonschema",
            crate::viz::STRIKE_SCHEMA.as_bytes(),
        )?;
        let channel = w.add_channel(
            schema,
            crate::viz::STRIKE_TOPIC,
            "json",
            &std::collections::BTreeMap::new(),
        )?;
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: channel,
                sequence: 0,
                log_time: last_t_ns,
                publish_time: last_t_ns,
            },
            &serde_json::to_vec(&k)?,
        )?;
    }
    w.finish()?;
    Ok(w.into_inner().into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        // A fresh private directory (`tempfile`); `name/` inside it does not exist yet.
        tempfile::Builder::new()
            .prefix("isochron-rec-")
            .tempdir()
            .expect("a temporary directory")
            .keep()
            .join(name)
    }

    #[test]
    fn header_and_rows_have_the_same_width() {
        let mut w = csv::Writer::from_writer(Vec::new());
        csv_row(&mut w, &Snapshot::default(), &mut String::new()).unwrap();
        let line = String::from_utf8(w.into_inner().unwrap()).unwrap();
        let row = csv::ReaderBuilder::new()
            .has_headers(false)
            .from_reader(line.as_bytes())
            .records()
            .next()
            .unwrap()
            .unwrap();
        assert_eq!(row.len(), csv_header().count());
        assert!(line.starts_with("idle,0,0,"));
        assert!(line.contains("NaN"), "unknown values are NaN: {line}");
    }

    #[test]
    fn trials_survive_reopening_and_running_ones_are_closed_as_service_restarted() {
        let dir = tmp("reopen");
        {
            let r = Records::open(&dir).unwrap();
            let a = r.create_trial(&TrialOrigin::default()).unwrap();
            let b = r.create_trial(&TrialOrigin::default()).unwrap();
            assert!(b > a);
            let stop = TrialEnd::Aborted(rt_core::bridge::AbortKind::Stop, "");
            assert!(r.finish_trial(a, stop, 7).unwrap());
            assert!(!r.finish_trial(a, stop, 7).unwrap());
        }
        let r = Records::open(&dir).unwrap();
        let list = r.list(10).unwrap();
        assert_eq!(list.len(), 2);
        assert_eq!(list[0].status, "aborted");
        assert_eq!(list[0].abort_reason.as_deref(), Some("service_restarted"));
        assert_eq!(list[0].success, Some(false));
        assert!(list[0].finished_unix_s.is_some());
        assert_eq!(
            list[0].reason.as_deref(),
            Some("aborted (service_restarted): the service stopped while the trial ran")
        );
        assert_eq!(list[1].status, "aborted");
        assert_eq!(list[1].abort_reason.as_deref(), Some("stop"));
        assert_eq!(
            list[1].reason.as_deref(),
            Some("aborted (stop): emergency stop")
        );
        assert_eq!(list[1].samples, 7);
        assert_eq!(r.get(999).unwrap(), None);
    }

    fn result(judged_by: Option<JudgedBy>, measured: Option<MeasuredJudgement>) -> TrialResult {
        TrialResult {
            success: false,
            timing_error_ms: 31.0,
            position_error_m: 0.004,
            movement_time_s: 1.5,
            distance_m: 0.6,
            t_star_s: 10.0,
            arrival_t_s: 10.031,
            prediction_time_error_ms: 0.5,
            limit_violations: 0,
            not_judged: None,
            measured,
            judged_by,
        }
    }

    #[test]
    fn the_verdicts_judge_is_stored_and_an_older_database_gains_its_column() {
        let dir = tmp("judged_by");
        std::fs::create_dir_all(&dir).unwrap();
        // A database from before `judged_by` (the schema and the columns
        // added up to `measured`), with a done trial in it.
        {
            let db = Connection::open(dir.join("trials.sqlite")).unwrap();
            db.execute_batch(SCHEMA).unwrap();
            for (name, ty) in &ADDED_COLUMNS[3..5] {
                db.execute_batch(&format!("ALTER TABLE trials ADD COLUMN {name} {ty}"))
                    .unwrap();
            }
            db.execute_batch(
                "INSERT INTO trials (status, started_unix_s, success, reason)
                 VALUES ('done', 1.0, 1, 'judged: a hit within the tolerances')",
            )
            .unwrap();
        }
        let r = Records::open(&dir).unwrap();
        let old = r.get(1).unwrap().unwrap();
        assert_eq!((old.success, old.judged_by), (Some(true), None));
        let m = MeasuredJudgement {
            pass_t_s: Some(10.0),
            arrival_t_s: Some(10.031),
            timing_error_ms: Some(31.0),
            timing_std_ms: Some(0.8),
            contact: true,
            contact_t_s: Some(10.01),
            success: false,
            torque_signal: true,
            robot_gap_ms: None,
            camera_clock_error_ms: None,
            camera_clock_error_std_ms: None,
            strike: None,
        };
        // The measured judge's verdict is read from `judged_by`, not from
        // a missing position error: a finite one does not hide it.
        let cases = [
            (
                Some(JudgedBy::Measured),
                "judged (measured): a miss (timing error +31.0 ms outside the tolerance)",
            ),
            (
                Some(JudgedBy::Truth),
                "judged: a miss (outside the tolerances)",
            ),
            (
                Some(JudgedBy::Physical),
                "judged: a miss (outside the tolerances)",
            ),
        ];
        for (judged_by, reason) in cases {
            let id = r.create_trial(&TrialOrigin::default()).unwrap();
            let end = TrialEnd::Done(result(judged_by, Some(m)));
            assert!(r.finish_trial(id, end, 3).unwrap());
            let rec = r.get(id).unwrap().unwrap();
            assert_eq!(rec.judged_by, judged_by);
            assert_eq!(rec.reason.as_deref(), Some(reason));
            assert_eq!(rec.measured, Some(m));
            let json = serde_json::to_value(&rec).unwrap();
            assert_eq!(
                json["judged_by"],
                serde_json::json!(judged_by.map(JudgedBy::as_str))
            );
        }
        // Not judged: no judge, `success` null.
        let id = r.create_trial(&TrialOrigin::default()).unwrap();
        let mut nj = result(None, Some(m));
        nj.not_judged = Some("not judged: because");
        r.finish_trial(id, TrialEnd::Done(nj), 3).unwrap();
        let rec = r.get(id).unwrap().unwrap();
        assert_eq!((rec.success, rec.judged_by), (None, None));
        assert_eq!(rec.reason.as_deref(), Some("not judged: because"));
        // A strike in time whose ball left too slow: the record keeps its
        // speeds at contact and says why it missed.
        let strike = rt_core::control::measured::MeasuredStrike {
            planned_tool_speed_mps: 0.5,
            tool_speed_mps: Some(0.49),
            target_ball_speed_mps: 0.47,
            ball_speed_mps: Some(0.30),
            ball_speed_std_mps: Some(0.006),
            speed_error: Some(-0.36),
            returned: true,
            rebound_used: 10,
            in_time: true,
            speed_ok: false,
            predicted: rt_core::control::PredictedRebound::new(0.0, 0.47, 0.9, 9.81 / 1.93, 0.03),
        };
        let slow = MeasuredJudgement {
            timing_error_ms: Some(3.0),
            strike: Some(strike),
            ..m
        };
        let id = r.create_trial(&TrialOrigin::default()).unwrap();
        let end = TrialEnd::Done(result(Some(JudgedBy::Measured), Some(slow)));
        assert!(r.finish_trial(id, end, 3).unwrap());
        let rec = r.get(id).unwrap().unwrap();
        assert_eq!(
            rec.reason.as_deref(),
            Some(
                "judged (measured): a miss (strike: ball out at 0.30 m/s, -36% of the 0.47 m/s target)"
            )
        );
        assert_eq!(rec.measured.and_then(|m| m.strike), Some(strike));
    }

    #[test]
    fn a_recording_converts_to_mcap_that_reads_back() {
        let dir = tmp("mcap");
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("1.csv");
        let mut rec = Recorder::default();
        for i in 0..10u64 {
            let mut s = Snapshot {
                seq: i,
                t_s: i as f64 * 0.005,
                ..Snapshot::default()
            };
            s.robot.q_rad[3] = 0.1 * i as f64;
            rec.append(&path, 1, &s).unwrap();
        }
        assert_eq!(rec.finish(), Some((1, 10)));
        let bytes = csv_to_mcap(&path).unwrap();
        let msgs: Vec<_> = mcap::MessageStream::new(&bytes)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(msgs.len(), 10);
        assert_eq!(msgs[4].channel.topic, "/isochron/state");
        assert_eq!(msgs[4].log_time, 20_000_000);
        let j: serde_json::Value = serde_json::from_slice(&msgs[4].data).unwrap();
        assert!((j["q4_rad"].as_f64().unwrap() - 0.4).abs() < 1e-12);
        assert!(j["tool_x_m"].is_null());
    }

    /// A strike trial's MCAP (converted from its CSV with its record's
    /// measured verdict) carries the strike on `/trial/strike`: the tool's
    /// speed at contact planned and executed, the ball's outgoing speed
    /// predicted and seen, and the predicted rebound's curve (its first
    /// swing: out to the amplitude at the turn and back); a stop's has none.
    #[test]
    fn a_strike_recordings_mcap_carries_the_predicted_and_seen_rebound() {
        let dir = tmp("mcap-strike");
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("2.csv");
        let mut rec = Recorder::default();
        for i in 0..5u64 {
            let s = Snapshot {
                seq: i,
                t_s: 10.0 + i as f64 * 0.005,
                ..Snapshot::default()
            };
            rec.append(&path, 2, &s).unwrap();
        }
        rec.finish();
        let predicted =
            rt_core::control::PredictedRebound::new(0.2, 0.47, 1.8, 9.81 / 1.93, 0.03).unwrap();
        let strike = rt_core::control::measured::MeasuredStrike {
            planned_tool_speed_mps: 0.5,
            tool_speed_mps: Some(0.49),
            target_ball_speed_mps: 0.47,
            ball_speed_mps: Some(0.88),
            ball_speed_std_mps: Some(0.01),
            speed_error: Some(0.87),
            returned: true,
            rebound_used: 10,
            in_time: true,
            speed_ok: false,
            predicted: Some(predicted),
        };
        let m = MeasuredJudgement {
            pass_t_s: Some(10.0),
            arrival_t_s: Some(10.003),
            timing_error_ms: Some(3.0),
            timing_std_ms: Some(0.8),
            contact: true,
            contact_t_s: Some(10.01),
            success: false,
            torque_signal: true,
            robot_gap_ms: None,
            camera_clock_error_ms: None,
            camera_clock_error_std_ms: None,
            strike: Some(strike),
        };
        let read = |bytes: &[u8]| -> Vec<(String, serde_json::Value)> {
            mcap::MessageStream::new(bytes)
                .unwrap()
                .map(|m| {
                    let m = m.unwrap();
                    (
                        m.channel.topic.clone(),
                        serde_json::from_slice(&m.data).unwrap(),
                    )
                })
                .collect()
        };
        let msgs = read(&csv_to_mcap_with(&path, Some((2, &m))).unwrap());
        assert_eq!(msgs.len(), 6);
        let k: Vec<_> = msgs
            .iter()
            .filter(|(t, _)| t == crate::viz::STRIKE_TOPIC)
            .map(|(_, j)| j)
            .collect();
        assert_eq!(k.len(), 1, "{msgs:?}");
        let k = k[0];
        assert_eq!(k["trial_id"], 2);
        assert_eq!(k["planned_tool_speed_mps"], 0.5);
        assert_eq!(k["executed_tool_speed_mps"], 0.49);
        assert_eq!(k["seen_ball_speed_mps"], 0.88);
        let v = k["predicted_ball_speed_mps"].as_f64().unwrap();
        assert!((v - (1.2 * 0.47 + 0.2 * 1.8)).abs() < 1e-9, "{k}");
        assert_eq!(k["predicted"]["restitution"], 0.2);
        let curve = k["predicted_curve"].as_array().unwrap();
        let lat = |p: &serde_json::Value| p["lateral_m"].as_f64().unwrap();
        let peak = curve.iter().map(lat).fold(f64::NEG_INFINITY, f64::max);
        // Sampled: at most the amplitude, within a percent of it.
        assert!(
            peak <= predicted.amplitude_m + 1e-12 && peak > 0.99 * predicted.amplitude_m,
            "{peak} vs {predicted:?}"
        );
        assert!(lat(&curve[0]).abs() < 1e-12 && lat(&curve[curve.len() - 1]).abs() < 1e-3);
        assert!((curve[0]["t_s"].as_f64().unwrap() - 10.01).abs() < 1e-12);
        // A stop's record: no strike message.
        let stop = MeasuredJudgement { strike: None, ..m };
        let msgs = read(&csv_to_mcap_with(&path, Some((2, &stop))).unwrap());
        assert!(msgs.iter().all(|(t, _)| t == "/isochron/state"), "{msgs:?}");
    }
}
