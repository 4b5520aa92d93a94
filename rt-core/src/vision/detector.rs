//! The ball detector: colour first, shape as the confirmation.
//!
//! Per search region: the ball's colour range in HSV ([`super::colour`]: OpenCV's
//! BGR -> HSV and `in_range`, fused into one pass), morphological
//! open (specks) and close (holes) ([`super::morphology`]: OpenCV's
//! `morphologyEx` with its elliptic kernels, in row passes), external contours; each blob is measured by
//! its image moments (sub-pixel centroid, the moment ellipse) and accepted only
//! if its size, elongation, fill and the fit of its outline to the moment ellipse
//! (the shape confirmation) are those of a ball, possibly motion-blurred.
//! Tracking searches a window around the position predicted from the last two
//! detections; on a miss, the whole frame is searched at half resolution and the
//! candidates are refined at full resolution.

use opencv::{
    core::{
        self, Mat, MatTraitConst, MatTraitConstManual, MatTraitManual, Point, Rect, Scalar,
        ToInputArray, Vector,
    },
    imgproc,
};
use serde::{Deserialize, Serialize};

use super::colour::HsvRange;
use super::morphology::{Morphology, RunKernel};
use super::{FrameProblem, VisionError};
use crate::check::{self, ParamError};

/// The arc fit's sampling seed (deterministic for the same frames).
const RNG_SEED: u64 = 0x9E37_79B9_7F4A_7C15;

/// A blob at least this elongated is read as a motion streak.
const STREAK_ELONGATION: f64 = 1.15;

/// A blob at least this elongated may be a (short) motion streak: it is one
/// when its long axis is along the track's motion and it is not narrower
/// than the ball.
const BLUR_ELONGATION: f64 = 1.04;

/// A streak's long axis is within this angle of the track's velocity, radians.
const STREAK_ANGLE_RAD: f64 = 0.35;

/// Outline pixels within this distance of a fitted circle lie on it, pixels.
const ARC_TOL_PX: f64 = 1.2;

/// A ball is seen whole when at least this share of its outline lies on the
/// circle fitted to all of it (a cap cut off by the tool, or a look-alike
/// merged in, puts a larger share off it).
const WHOLE_SHARE: f64 = 0.95;

/// Detector settings: `[vision.detector]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DetectorParams {
    /// Ball hue range, degrees on the 0..360 colour wheel (optic yellow ~ 70).
    pub hue_deg: [f64; 2],
    /// Smallest saturation of a ball pixel, 0..1.
    pub saturation_min: f64,
    /// Smallest value (brightness) of a ball pixel, 0..1.
    pub value_min: f64,
    /// Smallest apparent ball radius accepted, pixels.
    pub radius_min_px: f64,
    /// Largest apparent ball radius accepted, pixels.
    pub radius_max_px: f64,
    /// Largest ratio of the blob's long to short axis (motion blur stretches the ball).
    pub elongation_max: f64,
    /// Largest RMS distance of the outline from the moment ellipse, as a fraction of
    /// the radius (never below 1 px).
    pub outline_rms_max: f64,
    /// Smallest confidence to report a detection, 0..1.
    pub confidence_min: f64,
    /// Half-size of the tracking window, in ball radii (never below 40 px).
    pub window_radii: f64,
    /// Downscale factor for the full-frame search (1 = full resolution): the
    /// colour test looks at every `coarse_scale`-th pixel of every
    /// `coarse_scale`-th row.
    pub coarse_scale: u32,
    /// Longest gap between detections over which the track is kept, seconds.
    pub track_timeout_s: f64,
}

impl Default for DetectorParams {
    fn default() -> Self {
        Self {
            hue_deg: [48.0, 100.0],
            saturation_min: 0.35,
            value_min: 0.30,
            radius_min_px: 6.0,
            radius_max_px: 90.0,
            elongation_max: 2.5,
            outline_rms_max: 0.08,
            confidence_min: 0.3,
            window_radii: 4.0,
            coarse_scale: 2,
            track_timeout_s: 0.25,
        }
    }
}

impl DetectorParams {
    /// Checks every field; the error names the first bad one.
    ///
    /// # Errors
    ///
    /// As [`Self::validate_at`].
    pub fn validate(&self) -> Result<(), ParamError> {
        self.validate_at("vision.detector")
    }

    /// Checks every field under the dotted path `prefix`.
    ///
    /// # Errors
    ///
    /// [`ParamError::NotFinite`] or [`ParamError::OutOfRange`] naming the first field
    /// outside its range; [`ParamError::Reversed`] for a reversed hue or radius range.
    pub fn validate_at(&self, prefix: &str) -> Result<(), ParamError> {
        let f = |name: &str| format!("{prefix}.{name}");
        check::within(&f("hue_deg[0]"), self.hue_deg[0], 0.0, 360.0)?;
        check::within(&f("hue_deg[1]"), self.hue_deg[1], 0.0, 360.0)?;
        if self.hue_deg[0] > self.hue_deg[1] {
            return Err(ParamError::Reversed {
                field: f("hue_deg"),
                lo: self.hue_deg[0],
                hi: self.hue_deg[1],
            });
        }
        check::probability(&f("saturation_min"), self.saturation_min)?;
        check::probability(&f("value_min"), self.value_min)?;
        check::within(&f("radius_min_px"), self.radius_min_px, 2.0, 500.0)?;
        check::within(&f("radius_max_px"), self.radius_max_px, 2.0, 1000.0)?;
        if self.radius_min_px > self.radius_max_px {
            return Err(ParamError::Reversed {
                field: f("radius_min_px/radius_max_px"),
                lo: self.radius_min_px,
                hi: self.radius_max_px,
            });
        }
        check::within(&f("elongation_max"), self.elongation_max, 1.0, 10.0)?;
        check::within(&f("outline_rms_max"), self.outline_rms_max, 0.01, 1.0)?;
        check::probability(&f("confidence_min"), self.confidence_min)?;
        check::within(&f("window_radii"), self.window_radii, 2.0, 50.0)?;
        check::within_u32(&f("coarse_scale"), self.coarse_scale, 1, 4)?;
        check::within(&f("track_timeout_s"), self.track_timeout_s, 0.0, 10.0)
    }
}

/// A ball found in an image.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Detection {
    /// Centre, image column, pixels (pixel centres at integers).
    pub x_px: f64,
    /// Centre, image row, pixels.
    pub y_px: f64,
    /// Radius (the short semi-axis of the moment ellipse), pixels.
    pub r_px: f64,
    /// Confidence 0..1 from the outline fit and the fill.
    pub confidence: f64,
    /// Long / short axis of the blob.
    pub elongation: f64,
    /// Whether this came from the tracking window (true) or a full-frame search.
    pub tracked: bool,
}

#[derive(Debug, Clone, Copy)]
struct Track {
    x: f64,
    y: f64,
    vx: f64,
    vy: f64,
    r: f64,
    t_s: f64,
    /// Whether `vx, vy` were measured (two detections in a row), not assumed zero.
    moving: bool,
}

/// The ball detector with its scratch buffers and track.
///
/// Not for the control thread (OpenCV allocates); it runs on the vision thread or
/// in the virtual-time simulation.
pub struct Detector {
    params: DetectorParams,
    colour: HsvRange,
    /// OpenCV's 3x3 and 5x5 `MORPH_ELLIPSE`.
    kernel_open: RunKernel,
    kernel_close: RunKernel,
    morph: Morphology,
    mask: Mat,
    tmp: Mat,
    contours: Vector<Vector<Point>>,
    candidates: Vec<Detection>,
    /// `outline[i]`: `candidates[i]`'s outline (index in `contours`) and
    /// the direction of its long axis.
    outline: Vec<Outline>,
    coarse: Vec<Detection>,
    track: Option<Track>,
    points: Vec<(f64, f64)>,
    rng: u64,
    rejected: u64,
    arc_fits: u64,
}

impl std::fmt::Debug for Detector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Detector")
            .field("params", &self.params)
            .field("track", &self.track)
            .finish_non_exhaustive()
    }
}

/// Where a candidate's outline is and which way its long axis points.
#[derive(Debug, Clone, Copy)]
struct Outline {
    /// Index in the detector's `contours`.
    contour: usize,
    /// Direction of the moment ellipse's long axis, radians (image x right, y down).
    axis_rad: f64,
}

/// A blob's measurements, in the coordinates of the image it was found in.
struct Blob {
    x: f64,
    y: f64,
    r: f64,
    elongation: f64,
    axis_rad: f64,
    confidence: f64,
}

impl Detector {
    /// A detector with validated parameters; limits OpenCV to one thread.
    ///
    /// # Errors
    ///
    /// [`VisionError::Param`] for invalid `params`; [`VisionError::OpenCv`] when
    /// OpenCV's thread count cannot be set.
    pub fn new(params: DetectorParams) -> Result<Self, VisionError> {
        params.validate()?;
        super::limit_opencv_threads()?;
        // OpenCV's 8-bit HSV: hue 0..180 (half degrees), saturation and value
        // 0..255 (the parameters are validated: within those scales).
        let colour = HsvRange::new(
            [
                (params.hue_deg[0] / 2.0).floor() as u8,
                (params.saturation_min * 255.0).round() as u8,
                (params.value_min * 255.0).round() as u8,
            ],
            [(params.hue_deg[1] / 2.0).ceil() as u8, 255, 255],
        );
        let kernel_open = RunKernel::ellipse(3);
        let kernel_close = RunKernel::ellipse(5);
        Ok(Self {
            params,
            colour,
            kernel_open,
            kernel_close,
            morph: Morphology::default(),
            mask: Mat::default(),
            tmp: Mat::default(),
            contours: Vector::new(),
            candidates: Vec::with_capacity(16),
            outline: Vec::with_capacity(16),
            coarse: Vec::with_capacity(16),
            track: None,
            points: Vec::with_capacity(1024),
            rng: RNG_SEED,
            rejected: 0,
            arc_fits: 0,
        })
    }

    /// The parameters in use.
    pub fn params(&self) -> &DetectorParams {
        &self.params
    }

    /// Forgets the track: the next frame is searched whole (and the arc
    /// fit's sampling restarts: the same frames give the same detections).
    pub fn reset(&mut self) {
        self.track = None;
        self.rng = RNG_SEED;
    }

    /// Detections dropped so far because they were inconsistent with the
    /// track (a ball-like blob far from where the tracked ball can be).
    pub fn rejected(&self) -> u64 {
        self.rejected
    }

    /// Detections so far whose centre came from a circle fitted to the arc of
    /// the outline that belongs to the ball (touching look-alike, occluder).
    pub fn arc_fits(&self) -> u64 {
        self.arc_fits
    }

    /// Finds the ball in an 8-bit BGR image taken at `t_s` (seconds, any clock;
    /// used to predict the tracking window).
    ///
    /// # Errors
    ///
    /// [`VisionError::BadFrame`] when `image` is empty or not 8-bit BGR;
    /// [`VisionError::OpenCv`] when an OpenCV call fails (no ball found is `Ok(None)`).
    pub fn detect(&mut self, image: &Mat, t_s: f64) -> Result<Option<Detection>, VisionError> {
        if image.empty() || image.typ() != core::CV_8UC3 {
            return Err(FrameProblem::NotBgr {
                width_px: image.cols(),
                height_px: image.rows(),
                cv_type: image.typ(),
            }
            .into());
        }
        let (w, h) = (image.cols(), image.rows());
        let fresh = self.track.filter(|tr| {
            let dt = t_s - tr.t_s;
            (0.0..=self.params.track_timeout_s).contains(&dt)
        });
        let mut gate: Option<(f64, f64, f64)> = None;
        if let Some(tr) = fresh {
            let dt = t_s - tr.t_s;
            let (px, py) = (tr.x + tr.vx * dt, tr.y + tr.vy * dt);
            let speed = tr.vx.hypot(tr.vy);
            let half = (self.params.window_radii * tr.r).max(40.0) + 0.5 * speed * dt;
            gate = Some((px, py, half));
            if let Some(rect) = window(px, py, half, w, h) {
                let roi = Mat::roi(image, rect)?;
                self.candidates.clear();
                self.search(&roi, rect, 1, w, h)?;
                let best = self.best_index(Some((px, py)));
                let whole = best.and_then(|i| self.whole(i, &tr));
                let found = match (best, whole) {
                    (Some(i), Some(round)) => Some((self.candidates[i], round)),
                    // The arc fit needs a trusted prediction: not on the first
                    // frame after a full-frame find (no velocity yet).
                    _ if tr.moving => self.arc_fit(rect, (px, py), tr.r).map(|d| (d, false)),
                    _ => None,
                };
                if let Some((mut best, round)) = found {
                    best.tracked = true;
                    self.update_track(&best, t_s, round);
                    return Ok(Some(best));
                }
            }
        }
        let found = self.full_frame(image)?;
        match (found, gate) {
            // The tracked ball cannot be there: a look-alike (or the ball merged
            // with one while the real one is hidden). Dropped and counted; the
            // track is kept until it times out.
            (Some(det), Some((px, py, half)))
                if (det.x_px - px).hypot(det.y_px - py) > half + det.r_px
                    || fresh.is_some_and(|tr| !self.consistent(&det, &tr)) =>
            {
                self.rejected += 1;
                Ok(None)
            }
            (Some(det), _) => {
                self.update_track(&det, t_s, true);
                Ok(Some(det))
            }
            (None, Some(_)) => Ok(None),
            (None, None) => {
                self.track = None;
                Ok(None)
            }
        }
    }

    /// Whether candidate `i` of the tracking window is the tracked ball seen
    /// whole: `Some(true)` a round ball (its radius matches the track's and
    /// its whole outline lies on one circle), `Some(false)` a motion streak
    /// (its short semi-axis, the radius, is at least the track's: blur only
    /// adds width), `None` otherwise. A ball partly covered, or merged with a
    /// look-alike, has part of its outline off the circle, or a short
    /// semi-axis below the radius, and goes to [`Self::arc_fit`].
    fn whole(&self, i: usize, tr: &Track) -> Option<bool> {
        let c = &self.candidates[i];
        if !self.consistent(c, tr) {
            return None;
        }
        let outline = *self.outline.get(i)?;
        // Motion blur stretches the ball along its motion and never narrows it.
        let along = !tr.moving || {
            let a = (outline.axis_rad - tr.vy.atan2(tr.vx)).rem_euclid(std::f64::consts::PI);
            a.min(std::f64::consts::PI - a) <= STREAK_ANGLE_RAD
        };
        let wide = c.r_px >= 0.95 * tr.r - 0.3;
        // (A track just acquired has no velocity yet, and its radius may be a
        // streak's width: a streak is taken as it is.)
        if c.elongation >= BLUR_ELONGATION && along && (wide || !tr.moving) {
            return Some(false);
        }
        if c.elongation >= STREAK_ELONGATION {
            return None;
        }
        let contour = self.contours.get(outline.contour).ok()?;
        let n = contour.len();
        let pts = || contour.iter().map(|p| (f64::from(p.x), f64::from(p.y)));
        let (sx, sy) = pts().fold((0.0, 0.0), |(a, b), (x, y)| (a + x, b + y));
        let origin = (sx / n as f64, sy / n as f64);
        // Kasa's fit over the whole outline (no inlier selection).
        let (cx, cy, rr) = kasa(pts(), origin)?;
        let k = pts()
            .filter(|&(x, y)| ((x - cx).hypot(y - cy) - rr).abs() <= ARC_TOL_PX)
            .count();
        (k as f64 >= WHOLE_SHARE * n as f64).then_some(true)
    }

    /// Whether a detection's radius is the track's: within 8% + 0.5 px for a
    /// round blob, 0.92..1.2 of it for a streak (a streak's short semi-axis
    /// grows to 1.155 r as it lengthens; a covered ball's shrinks).
    fn consistent(&self, c: &Detection, tr: &Track) -> bool {
        if c.elongation < STREAK_ELONGATION {
            (c.r_px - tr.r).abs() <= 0.08 * tr.r + 0.5
        } else {
            c.r_px >= 0.92 * tr.r - 0.5 && c.r_px <= 1.2 * tr.r + 0.5
        }
    }

    /// Fits a circle of about the track's radius `r` to the outline pixels of
    /// the tracking window's blobs near `pred` (RANSAC over point triples, then
    /// least squares on the inliers). Accepted when the inliers cover at
    /// least 150 degrees of the circle, at least 40% of its circumference, and
    /// the mask fills at least 40% of it: the arc that belongs to the ball when
    /// it touches a same-coloured object or the tool covers up to half of it.
    fn arc_fit(&mut self, rect: Rect, pred: (f64, f64), r: f64) -> Option<Detection> {
        let (px, py) = (pred.0 - f64::from(rect.x), pred.1 - f64::from(rect.y));
        let reach = 2.5 * r + 4.0;
        self.points.clear();
        for contour in &self.contours {
            for p in &contour {
                let (x, y) = (f64::from(p.x), f64::from(p.y));
                if (x - px).hypot(y - py) <= reach && self.points.len() < self.points.capacity() {
                    self.points.push((x, y));
                }
            }
        }
        let n = self.points.len();
        if n < 12 {
            return None;
        }
        let tol = ARC_TOL_PX;
        let (r_lo, r_hi) = (0.85 * r, 1.15 * r);
        let mut best: Option<(usize, (f64, f64, f64))> = None;
        for _ in 0..120 {
            let (i, j, k) = (self.next_index(n), self.next_index(n), self.next_index(n));
            let (a, b, c) = (self.points[i], self.points[j], self.points[k]);
            let Some((cx, cy, rr)) = circumcircle(a, b, c) else {
                continue;
            };
            if !(r_lo..=r_hi).contains(&rr) || (cx - px).hypot(cy - py) > reach {
                continue;
            }
            let inl = self
                .points
                .iter()
                .filter(|&&(x, y)| ((x - cx).hypot(y - cy) - rr).abs() <= tol)
                .count();
            if best.is_none_or(|(k, _)| inl > k) {
                best = Some((inl, (cx, cy, rr)));
            }
        }
        let (_, (mut cx, mut cy, mut rr)) = best?;
        // Least squares on the inliers with a free radius (Kasa's algebraic
        // fit), re-selecting the inliers around each new circle.
        for _ in 0..6 {
            (cx, cy, rr) = fit_circle(&self.points, (cx, cy, rr), tol)?;
        }
        if !(r_lo - 0.5..=r_hi).contains(&rr) || (cx - px).hypot(cy - py) > reach {
            return None;
        }
        // Angular coverage of the inliers (360 minus the largest gap).
        let mut bins = [false; 72];
        let mut inliers = 0usize;
        for &(x, y) in &self.points {
            if ((x - cx).hypot(y - cy) - rr).abs() <= tol {
                inliers += 1;
                let a = (y - cy).atan2(x - cx).to_degrees().rem_euclid(360.0);
                bins[(a / 5.0) as usize % 72] = true;
            }
        }
        let mut gap = 0usize;
        let mut run = 0usize;
        for i in 0..144 {
            if bins[i % 72] {
                run = 0;
            } else {
                run += 1;
                gap = gap.max(run.min(72));
            }
        }
        let coverage_deg = 360.0 - 5.0 * gap as f64;
        let circumference = std::f64::consts::TAU * rr;
        if coverage_deg < 150.0 || (inliers as f64) < 0.4 * circumference {
            return None;
        }
        // The mask must fill a good part of the circle (not a ring or a gap).
        let (mut inside, mut on) = (0u32, 0u32);
        let step = (rr / 6.0).max(1.0);
        let mut yy = cy - rr;
        while yy <= cy + rr {
            let mut xx = cx - rr;
            while xx <= cx + rr {
                if (xx - cx).hypot(yy - cy) <= rr - 1.0 {
                    let (ix, iy) = (xx.round() as i32, yy.round() as i32);
                    if ix >= 0 && iy >= 0 && ix < self.mask.cols() && iy < self.mask.rows() {
                        inside += 1;
                        if self.mask.at_2d::<u8>(iy, ix).is_ok_and(|v| *v > 0) {
                            on += 1;
                        }
                    }
                }
                xx += step;
            }
            yy += step;
        }
        if inside == 0 || f64::from(on) < 0.4 * f64::from(inside) {
            return None;
        }
        self.arc_fits += 1;
        // Outline pixels lie half a pixel inside the ball's edge.
        Some(Detection {
            x_px: f64::from(rect.x) + cx,
            y_px: f64::from(rect.y) + cy,
            r_px: r,
            confidence: (coverage_deg / 360.0).clamp(0.0, 1.0),
            elongation: 1.0,
            tracked: true,
        })
    }

    fn next_index(&mut self, n: usize) -> usize {
        // xorshift64*: deterministic, no allocation.
        self.rng ^= self.rng >> 12;
        self.rng ^= self.rng << 25;
        self.rng ^= self.rng >> 27;
        (self.rng.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 33) as usize % n
    }

    /// Moves the track to `det`; its radius follows `det` only when `round`
    /// (a ball seen whole and round: a streak's short semi-axis overstates the
    /// radius, a covered ball's understates it, an arc fit reports the track's).
    fn update_track(&mut self, det: &Detection, t_s: f64, round: bool) {
        let (vx, vy, moving) = match self.track {
            Some(tr) if t_s > tr.t_s && t_s - tr.t_s <= self.params.track_timeout_s => {
                let dt = t_s - tr.t_s;
                ((det.x_px - tr.x) / dt, (det.y_px - tr.y) / dt, true)
            }
            _ => (0.0, 0.0, false),
        };
        let r = match self.track {
            Some(tr) if !round || det.elongation >= STREAK_ELONGATION => tr.r,
            Some(tr) if det.tracked => 0.7 * tr.r + 0.3 * det.r_px,
            _ => det.r_px,
        };
        self.track = Some(Track {
            x: det.x_px,
            y: det.y_px,
            vx,
            vy,
            r,
            t_s,
            moving,
        });
    }

    /// Searches the whole image (at the coarse scale) and refines the candidates.
    fn full_frame(&mut self, image: &Mat) -> Result<Option<Detection>, VisionError> {
        let (w, h) = (image.cols(), image.rows());
        let scale = self.params.coarse_scale.max(1) as i32;
        self.candidates.clear();
        if scale == 1 {
            self.search(image, Rect::new(0, 0, w, h), 1, w, h)?;
            return Ok(self.best(None));
        }
        self.colour.mask_sampled(image, scale, &mut self.tmp)?;
        let (sw, sh) = (self.tmp.cols(), self.tmp.rows());
        self.search_mask(Rect::new(0, 0, sw, sh), sw, sh, scale, w, h)?;
        // Refine the coarse candidates at full resolution, best first.
        let mut coarse = std::mem::take(&mut self.coarse);
        coarse.clear();
        coarse.extend_from_slice(&self.candidates);
        coarse.sort_by(|a, b| b.confidence.total_cmp(&a.confidence));
        coarse.truncate(4);
        let mut refined: Option<Detection> = None;
        for c in &coarse {
            let half = 2.0 * c.r_px + 8.0;
            let Some(rect) = window(c.x_px, c.y_px, half, w, h) else {
                continue;
            };
            let roi = Mat::roi(image, rect)?;
            self.candidates.clear();
            self.search(&roi, rect, 1, w, h)?;
            if let Some(d) = self.best(Some((c.x_px, c.y_px)))
                && refined.is_none_or(|r| d.confidence > r.confidence)
            {
                refined = Some(d);
            }
        }
        self.coarse = coarse;
        Ok(refined)
    }

    /// The best candidate: the most confident, or the nearest to `near` among the
    /// confident ones.
    fn best(&self, near: Option<(f64, f64)>) -> Option<Detection> {
        self.best_index(near).map(|i| self.candidates[i])
    }

    /// [`Self::best`]'s index in `candidates`.
    fn best_index(&self, near: Option<(f64, f64)>) -> Option<usize> {
        let ok = self
            .candidates
            .iter()
            .enumerate()
            .filter(|(_, c)| c.confidence >= self.params.confidence_min);
        match near {
            Some((x, y)) => ok
                .min_by(|(_, a), (_, b)| {
                    let da = (a.x_px - x).hypot(a.y_px - y);
                    let db = (b.x_px - x).hypot(b.y_px - y);
                    da.total_cmp(&db)
                })
                .map(|(i, _)| i),
            None => ok
                .max_by(|(_, a), (_, b)| a.confidence.total_cmp(&b.confidence))
                .map(|(i, _)| i),
        }
    }

    /// Segments `img` (a view of the frame at `rect`, downscaled by `scale`) and
    /// appends ball-like blobs to `self.candidates` in full-frame pixels.
    fn search(
        &mut self,
        img: &(impl ToInputArray + MatTraitConst),
        rect: Rect,
        scale: i32,
        frame_w: i32,
        frame_h: i32,
    ) -> Result<(), VisionError> {
        self.colour.mask(img, &mut self.tmp)?;
        self.search_mask(rect, img.cols(), img.rows(), scale, frame_w, frame_h)
    }

    /// [`Self::search`] from the colour mask in `self.tmp` (`iw` x `ih`).
    fn search_mask(
        &mut self,
        rect: Rect,
        iw: i32,
        ih: i32,
        scale: i32,
        frame_w: i32,
        frame_h: i32,
    ) -> Result<(), VisionError> {
        let (mw, mh) = (self.tmp.cols(), self.tmp.rows());
        if self.mask.cols() != mw || self.mask.rows() != mh || self.mask.typ() != core::CV_8UC1 {
            self.mask = Mat::new_rows_cols_with_default(mh, mw, core::CV_8UC1, Scalar::all(0.0))?;
        }
        let (uw, uh) = (mw as usize, mh as usize);
        self.morph.open(
            self.tmp.data_bytes()?,
            self.mask.data_bytes_mut()?,
            uw,
            uh,
            &self.kernel_open,
        )?;
        self.morph.close(
            self.mask.data_bytes()?,
            self.tmp.data_bytes_mut()?,
            uw,
            uh,
            &self.kernel_close,
        )?;
        std::mem::swap(&mut self.mask, &mut self.tmp);
        imgproc::find_contours_def(
            &self.mask,
            &mut self.contours,
            imgproc::RETR_EXTERNAL,
            imgproc::CHAIN_APPROX_NONE,
        )?;
        let s = f64::from(scale);
        let coarse = scale > 1;
        // Coarse candidates only need to be roughly ball-like; refinement decides.
        let loosen = if coarse { 1.5 } else { 1.0 };
        let r_min = self.params.radius_min_px / s / loosen;
        let r_max = self.params.radius_max_px / s * loosen;
        for (ci, contour) in self.contours.iter().enumerate() {
            let n = contour.len();
            if n < 5 {
                continue;
            }
            let br = imgproc::bounding_rect(&contour)?;
            // A blob cut by the search region's edge is not measurable here; one cut
            // by the frame's edge is not fully visible.
            let touches = br.x <= 0 || br.y <= 0 || br.x + br.width >= iw || br.y + br.height >= ih;
            if touches && !coarse {
                continue;
            }
            let r_box = 0.5 * f64::from(br.width.min(br.height));
            if r_box < r_min - 1.0
                || 0.5 * f64::from(br.width.max(br.height))
                    > r_max * self.params.elongation_max + 1.0
            {
                continue;
            }
            let sub = Mat::roi(&self.mask, br)?;
            let m = imgproc::moments(&sub, true)?;
            if m.m00 < 4.0 {
                continue;
            }
            let Some(blob) = measure(&m, &contour, br, &self.params, loosen) else {
                continue;
            };
            if blob.r < r_min || blob.r > r_max {
                continue;
            }
            // Back to full-frame pixels (pixel centres at integers at every scale).
            let x = f64::from(rect.x) + (blob.x + 0.5) * s - 0.5;
            let y = f64::from(rect.y) + (blob.y + 0.5) * s - 0.5;
            if !coarse {
                let r = blob.r;
                if x - r < -0.5
                    || y - r < -0.5
                    || x + r > f64::from(frame_w) - 0.5
                    || y + r > f64::from(frame_h) - 0.5
                {
                    continue;
                }
            }
            if self.candidates.len() < self.candidates.capacity() {
                self.outline.truncate(self.candidates.len());
                self.outline.push(Outline {
                    contour: ci,
                    axis_rad: blob.axis_rad,
                });
                self.candidates.push(Detection {
                    x_px: x,
                    y_px: y,
                    r_px: blob.r * s,
                    confidence: blob.confidence,
                    elongation: blob.elongation,
                    tracked: false,
                });
            }
        }
        Ok(())
    }
}

/// Measures one blob from its mask moments (relative to `br`) and outline.
fn measure(
    m: &core::Moments,
    contour: &Vector<Point>,
    br: Rect,
    p: &DetectorParams,
    loosen: f64,
) -> Option<Blob> {
    let cx = m.m10 / m.m00;
    let cy = m.m01 / m.m00;
    let (a, b, c) = (m.mu20 / m.m00, m.mu11 / m.m00, m.mu02 / m.m00);
    let mean = 0.5 * (a + c);
    let diff = (0.25 * (a - c) * (a - c) + b * b).sqrt();
    let (l1, l2) = (mean + diff, (mean - diff).max(1e-9));
    // A uniform disc of radius r has variance r^2/4 along every axis.
    let (semi_long, semi_short) = (2.0 * l1.sqrt(), 2.0 * l2.sqrt());
    let elongation = semi_long / semi_short;
    if elongation > p.elongation_max * loosen {
        return None;
    }
    // Fill: pixel count over the moment ellipse's area (1 for a disc or ellipse).
    let fill = m.m00 / (std::f64::consts::PI * semi_long * semi_short);
    // Outline fit: each outline pixel's distance from the centre, measured in the
    // moment ellipse's metric, should be constant for an ellipse. Its spread, in
    // pixels, is the shape residual (squares, crosses and crescents score badly).
    let theta = 0.5 * (2.0 * b).atan2(a - c);
    let (st, ct) = theta.sin_cos();
    let g = (semi_long * semi_short).sqrt();
    let (mut sum, mut sum2) = (0.0, 0.0);
    let n = contour.len() as f64;
    for pt in contour {
        let dx = f64::from(pt.x - br.x) - cx;
        let dy = f64::from(pt.y - br.y) - cy;
        let xl = dx * ct + dy * st;
        let yl = -dx * st + dy * ct;
        let rho = ((xl / semi_long).powi(2) + (yl / semi_short).powi(2)).sqrt() * g;
        sum += rho;
        sum2 += rho * rho;
    }
    let mean_rho = sum / n;
    let rms = (sum2 / n - mean_rho * mean_rho).max(0.0).sqrt();
    let limit = (p.outline_rms_max * semi_short).max(1.0) * loosen;
    if rms > limit {
        return None;
    }
    let fill_err = (fill - 1.0).abs();
    if fill_err > 0.25 * loosen {
        return None;
    }
    let shape_score = 1.0 - 0.5 * rms / limit;
    let fill_score = 1.0 - fill_err / (0.25 * loosen);
    let confidence = (shape_score * fill_score).sqrt().clamp(0.0, 1.0);
    Some(Blob {
        x: cx + f64::from(br.x),
        y: cy + f64::from(br.y),
        r: semi_short,
        elongation,
        axis_rad: theta,
        confidence,
    })
}

/// A square window of half-size `half` around `(x, y)`, clipped to the frame.
fn window(x: f64, y: f64, half: f64, w: i32, h: i32) -> Option<Rect> {
    if !(x.is_finite() && y.is_finite() && half.is_finite()) {
        return None;
    }
    let x0 = ((x - half).floor() as i32).clamp(0, w);
    let y0 = ((y - half).floor() as i32).clamp(0, h);
    let x1 = ((x + half).ceil() as i32 + 1).clamp(0, w);
    let y1 = ((y + half).ceil() as i32 + 1).clamp(0, h);
    (x1 - x0 >= 8 && y1 - y0 >= 8).then(|| Rect::new(x0, y0, x1 - x0, y1 - y0))
}

/// The circle through three points: (centre x, centre y, radius).
fn circumcircle(a: (f64, f64), b: (f64, f64), c: (f64, f64)) -> Option<(f64, f64, f64)> {
    let d = 2.0 * (a.0 * (b.1 - c.1) + b.0 * (c.1 - a.1) + c.0 * (a.1 - b.1));
    if d.abs() < 1e-6 {
        return None;
    }
    let (a2, b2, c2) = (
        a.0 * a.0 + a.1 * a.1,
        b.0 * b.0 + b.1 * b.1,
        c.0 * c.0 + c.1 * c.1,
    );
    let ux = (a2 * (b.1 - c.1) + b2 * (c.1 - a.1) + c2 * (a.1 - b.1)) / d;
    let uy = (a2 * (c.0 - b.0) + b2 * (a.0 - c.0) + c2 * (b.0 - a.0)) / d;
    Some((ux, uy, (a.0 - ux).hypot(a.1 - uy)))
}

/// Kasa's algebraic circle fit, `x^2 + y^2 + D x + E y + F = 0` in least
/// squares, over the `points` within `tol` of the circle `around`
/// (coordinates taken relative to its centre for conditioning). `None` with
/// fewer than 6 such points or a degenerate arc.
fn fit_circle(points: &[(f64, f64)], around: (f64, f64, f64), tol: f64) -> Option<(f64, f64, f64)> {
    let (ox, oy, r0) = around;
    let near = points
        .iter()
        .copied()
        .filter(|&(x, y)| ((x - ox).hypot(y - oy) - r0).abs() <= tol);
    kasa(near, (ox, oy))
}

/// Kasa's algebraic circle fit, `x^2 + y^2 + D x + E y + F = 0` in least
/// squares, with coordinates relative to `origin` (near the centre, for
/// conditioning): (centre x, centre y, radius). `None` with fewer than 6
/// points or a degenerate arc. No allocation.
fn kasa(points: impl Iterator<Item = (f64, f64)>, origin: (f64, f64)) -> Option<(f64, f64, f64)> {
    let (ox, oy) = origin;
    let (mut sxx, mut sxy, mut syy, mut sx, mut sy, mut n) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let (mut sxz, mut syz, mut sz) = (0.0, 0.0, 0.0);
    for (px, py) in points {
        let (x, y) = (px - ox, py - oy);
        let z = x * x + y * y;
        sxx += x * x;
        sxy += x * y;
        syy += y * y;
        sx += x;
        sy += y;
        n += 1.0;
        sxz += x * z;
        syz += y * z;
        sz += z;
    }
    if n < 6.0 {
        return None;
    }
    let a = nalgebra::Matrix3::new(sxx, sxy, sx, sxy, syy, sy, sx, sy, n);
    let b = nalgebra::Vector3::new(-sxz, -syz, -sz);
    let s = a.lu().solve(&b)?;
    let (cx, cy) = (-0.5 * s.x, -0.5 * s.y);
    let r2 = cx * cx + cy * cy - s.z;
    (r2 > 0.0 && r2.is_finite()).then(|| (ox + cx, oy + cy, r2.sqrt()))
}
