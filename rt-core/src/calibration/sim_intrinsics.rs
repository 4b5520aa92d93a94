//! The camera step on the simulated world: a virtual operator holds a printed
//! chessboard in front of the true camera at varied poses; each frame is
//! rendered through the true camera (its lens bends the board's lines) over
//! the lab's rendered scene, and the board's corners are found as a real lab
//! finds them (`cv::findChessboardCorners` + `cv::cornerSubPix`). The procedure
//! never reads a true corner pixel: it hands the detections to
//! [`fit_intrinsics`](super::fit_intrinsics).

use opencv::core::MatTraitConst;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::intrinsics::{BoardView, CameraCalibration, Chessboard, detect_corners, fit_intrinsics};
use super::simworld::{HiddenWorld, ProcedureError};
use super::view::{StepView, ViewKind, Watch};
use crate::params::Scenario;
use crate::sim::camera::{SimCamera, SimCameraParams};
use crate::sim::world::board::{draw_board, plan_holds, render_view};
use crate::vision::CameraIntrinsics;

/// The camera step on the simulated world, with the truth beside the result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraRun {
    /// What the step measured.
    pub result: CameraCalibration,
    /// The true camera's intrinsics and lens.
    pub truth: CameraIntrinsics,
}

/// The camera step: `views` holds of `board` in front of the true camera of
/// `world`, one frame each, corners detected and fitted. `board_in_view =
/// false`: the operator holds it outside the camera's view (the step must then
/// refuse, "no board visible"). Reports each view to `watch`.
///
/// # Errors
///
/// [`ProcedureError::Params`] for an invalid scenario; [`ProcedureError::Views`]
/// for `views` outside 1..=200; [`ProcedureError::Calibration`] for a bad board or
/// when [`fit_intrinsics`] refuses the views (e.g. no board visible);
/// [`ProcedureError::Vision`] when rendering or corner detection fails.
pub fn run_camera(
    scenario: &Scenario,
    world: &HiddenWorld,
    seed: u64,
    board: &Chessboard,
    views: usize,
    board_in_view: bool,
    watch: &mut dyn Watch,
) -> Result<CameraRun, ProcedureError> {
    scenario.validate()?;
    board.validate()?;
    if !(1..=200).contains(&views) {
        return Err(ProcedureError::Views { views });
    }
    let cam = world.world_camera(scenario);
    let (w, h) = (scenario.camera.width_px, scenario.camera.height_px);
    let size = (f64::from(w), f64::from(h));
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xc4e5_5b0a);
    let holds = plan_holds(&cam, board, views, size, &mut rng);
    // The lab's scene (background, clutter, lighting, noise) from the renderer.
    let mut scene_cam = SimCamera::new(
        &scenario.camera,
        &SimCameraParams::default(),
        scenario.pendulum.ball_radius_m,
        seed,
    )?;
    let mut seen = Vec::with_capacity(views);
    for (i, hold) in holds.iter().enumerate() {
        let drawn = if board_in_view {
            draw_board(&cam, board, hold, size)
        } else {
            None
        };
        let scene = scene_cam.render(None)?.try_clone()?;
        let gray = render_view(
            &scene,
            drawn.as_ref(),
            scenario.camera.image_noise,
            &mut rng,
        )?;
        let corners = detect_corners(&gray, board)?;
        watch.seen(StepView {
            progress: (i + 1) as f64 / (views + 1) as f64,
            message: match &corners {
                Some(c) => format!("board view {} of {views}: {} corners", i + 1, c.len()),
                None => format!("board view {} of {views}: no board found", i + 1),
            },
            kind: ViewKind::Image,
            points: corners.clone().unwrap_or_default(),
            fit: Vec::new(),
        });
        seen.push(BoardView {
            corners_px: corners,
        });
    }
    let fit = fit_intrinsics(board, &seen, w, h)?;
    for v in fit.views(&seen, views) {
        watch.seen(v);
    }
    Ok(CameraRun {
        result: fit.calibration,
        truth: cam.true_intrinsics(),
    })
}
