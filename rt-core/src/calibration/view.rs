//! What a calibration step sees while it runs: the dashboard's live view
//! (`GET /api/calibration`, the Calibration panel) and nothing else. A procedure
//! hands a [`StepView`] to its [`Watch`] now and then (a few times a second of the
//! procedure's own progress, never per frame in a loop that must be fast).

use serde::{Deserialize, Serialize};

/// How to draw a view's points.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ts_rs::TS, utoipa::ToSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum ViewKind {
    /// Image pixels (x right, y down) of a `width x height` camera frame: board
    /// corners, the LED, the hanging ball, the marker.
    Image,
    /// A time series: `[t s, value]` (the swing's lateral position, the LED's
    /// brightness, a joint's command and measurement).
    Series,
}

/// One look at what a step sees.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ts_rs::TS, utoipa::ToSchema)]
pub struct StepView {
    /// Fraction of the step done, 0..=1.
    pub progress: f64,
    /// What the step is doing, for people ("board view 7 of 15: 54 corners").
    pub message: String,
    /// How to draw `points` and `fit`.
    pub kind: ViewKind,
    /// What was measured.
    pub points: Vec<[f64; 2]>,
    /// What the fit or the model says at the same places (a fitted swing, the
    /// reprojected corners); may be empty.
    pub fit: Vec<[f64; 2]>,
}

/// Where a procedure reports its views.
pub trait Watch {
    /// One view (the procedure keeps going whatever the watcher does).
    fn seen(&mut self, view: StepView);
}

impl<F: FnMut(StepView)> Watch for F {
    fn seen(&mut self, view: StepView) {
        self(view);
    }
}

/// A watcher that looks at nothing (the CLI and the accuracy runs).
#[derive(Debug, Clone, Copy, Default)]
pub struct Unwatched;

impl Watch for Unwatched {
    fn seen(&mut self, _view: StepView) {}
}

/// Keeps at most `max` points of `points`, evenly spaced (a view is for the eye;
/// a 20 s swing at 30 fps is 600 samples).
pub fn thin(points: &[[f64; 2]], max: usize) -> Vec<[f64; 2]> {
    if points.len() <= max || max == 0 {
        return points.to_vec();
    }
    let step = points.len() as f64 / max as f64;
    (0..max)
        .map(|i| points[((i as f64 * step) as usize).min(points.len() - 1)])
        .collect()
}
