//! The dashboard's TypeScript declarations of the state, event and trial-record
//! messages, generated from the Rust types (`ts-rs`) into
//! `web/src/generated/types.ts`. The same types carry `utoipa::ToSchema`, so
//! `/api/openapi.json` describes them too.
//!
//! Regenerate with `make types` (`UPDATE_TS=1 cargo test -p server --lib
//! typescript`); the test fails while the committed file is stale.

use rt_core::bridge::{
    AbortKind, AbortView, BridgeCounters, CameraView, Counters, Event, EventRecord, FriQuality,
    FriSessionState, FriView, HopfView, HorizonPoint, JudgedBy, LoopTiming, MagnetState,
    MeasurementView, PathView, PendulumView, Readiness, Refusal, RobotView, Snapshot, TrialResult,
    TrialState,
};
use rt_core::calibration::{StepView, ViewKind};
use rt_core::control::PredictedRebound;
use rt_core::control::measured::{MeasuredJudgement, MeasuredStrike};
use rt_core::trajectory::TaskMode;
use ts_rs::TS;

use crate::{
    calibration::{CalibrationJob, CalibrationStatus, Change, StepStatus},
    demo::DemoStatus,
    lab::{EventMessage, StateMessage, StreamCounters},
    records::TrialRecord,
    runs::{Distances, RunRequest, RunStatus},
    ws::Hello,
};

/// Where the declarations live, relative to the repository root.
pub const PATH: &str = "web/src/generated/types.ts";

/// The whole file: every declaration, exported, in dependency order.
pub fn declarations() -> String {
    let decls = [
        TrialState::decl(),
        MeasurementView::decl(),
        HorizonPoint::decl(),
        PendulumView::decl(),
        HopfView::decl(),
        PathView::decl(),
        RobotView::decl(),
        FriSessionState::decl(),
        FriQuality::decl(),
        FriView::decl(),
        MagnetState::decl(),
        LoopTiming::decl(),
        Counters::decl(),
        CameraView::decl(),
        AbortKind::decl(),
        AbortView::decl(),
        Refusal::decl(),
        Readiness::decl(),
        Snapshot::decl(),
        PredictedRebound::decl(),
        MeasuredStrike::decl(),
        MeasuredJudgement::decl(),
        JudgedBy::decl(),
        TrialResult::decl(),
        Event::decl(),
        EventRecord::decl(),
        BridgeCounters::decl(),
        StreamCounters::decl(),
        StateMessage::decl(),
        EventMessage::decl(),
        Hello::decl(),
        TrialRecord::decl(),
        Distances::decl(),
        TaskMode::decl(),
        RunRequest::decl(),
        RunStatus::decl(),
        DemoStatus::decl(),
        ViewKind::decl(),
        StepView::decl(),
        StepStatus::decl(),
        Change::decl(),
        CalibrationJob::decl(),
        CalibrationStatus::decl(),
    ];
    let mut out = String::from(
        "// Generated from the Rust types by ts-rs (server/src/typescript.rs): do not edit.\n\
         // Regenerate with `make types`; `cargo test -p server --lib typescript` fails while stale.\n\
         // A number that may be NaN in Rust is `null` here (serde_json writes NaN as null).\n",
    );
    for d in decls {
        out.push('\n');
        out.push_str("export ");
        out.push_str(&d);
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_generated_typescript_is_current() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("..")
            .join(PATH);
        let want = declarations();
        if std::env::var_os("UPDATE_TS").is_some() {
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(&path, &want).unwrap();
        }
        let have = std::fs::read_to_string(&path).unwrap_or_default();
        assert!(
            have == want,
            "{PATH} is stale (the Rust types changed): run `make types` and commit it"
        );
    }

    #[test]
    fn the_declarations_follow_the_json() {
        let d = declarations();
        // u64 counters are plain numbers, NaN-able values nullable, tags literal.
        assert!(d.contains("type: \"state\""), "{d}");
        assert!(d.contains("type: \"event\""), "{d}");
        assert!(d.contains("type: \"hello\""), "{d}");
        assert!(d.contains("trial_id: number"), "{d}");
        assert!(d.contains("crossing_t_s: number | null"), "{d}");
        assert!(d.contains("\"kind\": \"trial_finished\""), "{d}");
        assert!(!d.contains("bigint"), "{d}");
    }
}
