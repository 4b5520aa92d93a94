//! The ball detector: colour first, shape as the confirmation.
//!
//! Per search region: BGR -> HSV, `in_range` on the ball's colour, morphological
//! open (specks) and close (holes), external contours; each blob is measured by
//! its image moments (sub-pixel centroid, the moment ellipse) and accepted only
//! if its size, elongation, fill and the fit of its outline to the moment ellipse
//! (the shape confirmation) are those of a ball, possibly motion-blurred.
//! Tracking searches a window around the position predicted from the last two
//! detections; on a miss, the whole frame is searched at half resolution and the
//! candidates are refined at full resolution.

use opencv::{
    core::{self, Mat, MatTraitConst, Point, Rect, Scalar, Size, ToInputArray, Vector},
    imgproc,
};
use serde::{Deserialize, Serialize};

use super::VisionError;
use crate::check::{self, ParamError};

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
    /// Downscale factor for the full-frame search (1 = full resolution).
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
    pub fn validate(&self) -> Result<(), ParamError> {
        self.validate_at("vision.detector")
    }

    /// Checks every field under the dotted path `prefix`.
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
}

/// The ball detector with its scratch buffers and track.
///
/// Not for the control thread (OpenCV allocates); it runs on the vision thread or
/// in the virtual-time simulation.
pub struct Detector {
    params: DetectorParams,
    lower: Scalar,
    upper: Scalar,
    kernel_open: Mat,
    kernel_close: Mat,
    small: Mat,
    hsv: Mat,
    mask: Mat,
    tmp: Mat,
    contours: Vector<Vector<Point>>,
    candidates: Vec<Detection>,
    coarse: Vec<Detection>,
    track: Option<Track>,
}

impl std::fmt::Debug for Detector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Detector")
            .field("params", &self.params)
            .field("track", &self.track)
            .finish_non_exhaustive()
    }
}

/// A blob's measurements, in the coordinates of the image it was found in.
struct Blob {
    x: f64,
    y: f64,
    r: f64,
    elongation: f64,
    confidence: f64,
}

impl Detector {
    /// A detector with validated parameters; limits OpenCV to one thread.
    pub fn new(params: DetectorParams) -> Result<Self, VisionError> {
        params.validate()?;
        super::limit_opencv_threads()?;
        // OpenCV's 8-bit HSV: hue 0..180 (half degrees), saturation and value 0..255.
        let lower = Scalar::new(
            (params.hue_deg[0] / 2.0).floor(),
            (params.saturation_min * 255.0).round(),
            (params.value_min * 255.0).round(),
            0.0,
        );
        let upper = Scalar::new((params.hue_deg[1] / 2.0).ceil(), 255.0, 255.0, 0.0);
        let kernel_open =
            imgproc::get_structuring_element_def(imgproc::MORPH_ELLIPSE, Size::new(3, 3))?;
        let kernel_close =
            imgproc::get_structuring_element_def(imgproc::MORPH_ELLIPSE, Size::new(5, 5))?;
        Ok(Self {
            params,
            lower,
            upper,
            kernel_open,
            kernel_close,
            small: Mat::default(),
            hsv: Mat::default(),
            mask: Mat::default(),
            tmp: Mat::default(),
            contours: Vector::new(),
            candidates: Vec::with_capacity(16),
            coarse: Vec::with_capacity(16),
            track: None,
        })
    }

    /// The parameters in use.
    pub fn params(&self) -> &DetectorParams {
        &self.params
    }

    /// Forgets the track: the next frame is searched whole.
    pub fn reset(&mut self) {
        self.track = None;
    }

    /// Finds the ball in an 8-bit BGR image taken at `t_s` (seconds, any clock;
    /// used to predict the tracking window).
    pub fn detect(&mut self, image: &Mat, t_s: f64) -> Result<Option<Detection>, VisionError> {
        if image.empty() || image.typ() != core::CV_8UC3 {
            return Err(VisionError::BadFrame(format!(
                "expected a non-empty 8-bit 3-channel BGR image, got {}x{} of type {}",
                image.cols(),
                image.rows(),
                image.typ()
            )));
        }
        let (w, h) = (image.cols(), image.rows());
        if let Some(tr) = self.track.filter(|tr| {
            let dt = t_s - tr.t_s;
            (0.0..=self.params.track_timeout_s).contains(&dt)
        }) {
            let dt = t_s - tr.t_s;
            let (px, py) = (tr.x + tr.vx * dt, tr.y + tr.vy * dt);
            let speed = tr.vx.hypot(tr.vy);
            let half = (self.params.window_radii * tr.r).max(40.0) + 0.5 * speed * dt;
            if let Some(rect) = window(px, py, half, w, h) {
                let roi = Mat::roi(image, rect)?;
                self.candidates.clear();
                self.search(&roi, rect, 1, w, h)?;
                if let Some(mut best) = self.best(Some((px, py))) {
                    best.tracked = true;
                    self.update_track(&best, t_s);
                    return Ok(Some(best));
                }
            }
        }
        let found = self.full_frame(image)?;
        match found {
            Some(det) => self.update_track(&det, t_s),
            None => self.track = None,
        }
        Ok(found)
    }

    fn update_track(&mut self, det: &Detection, t_s: f64) {
        let (vx, vy) = match self.track {
            Some(tr) if t_s > tr.t_s && t_s - tr.t_s <= self.params.track_timeout_s => {
                let dt = t_s - tr.t_s;
                ((det.x_px - tr.x) / dt, (det.y_px - tr.y) / dt)
            }
            _ => (0.0, 0.0),
        };
        self.track = Some(Track {
            x: det.x_px,
            y: det.y_px,
            vx,
            vy,
            r: det.r_px,
            t_s,
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
        let mut small = std::mem::take(&mut self.small);
        imgproc::resize(
            image,
            &mut small,
            Size::new(w / scale, h / scale),
            0.0,
            0.0,
            imgproc::INTER_AREA,
        )?;
        let res = self.search(
            &small,
            Rect::new(0, 0, small.cols(), small.rows()),
            scale,
            w,
            h,
        );
        self.small = small;
        res?;
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
        let ok = self
            .candidates
            .iter()
            .filter(|c| c.confidence >= self.params.confidence_min);
        match near {
            Some((x, y)) => ok
                .min_by(|a, b| {
                    let da = (a.x_px - x).hypot(a.y_px - y);
                    let db = (b.x_px - x).hypot(b.y_px - y);
                    da.total_cmp(&db)
                })
                .copied(),
            None => ok
                .max_by(|a, b| a.confidence.total_cmp(&b.confidence))
                .copied(),
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
        imgproc::cvt_color_def(img, &mut self.hsv, imgproc::COLOR_BGR2HSV)?;
        core::in_range(&self.hsv, &self.lower, &self.upper, &mut self.tmp)?;
        imgproc::morphology_ex_def(
            &self.tmp,
            &mut self.mask,
            imgproc::MORPH_OPEN,
            &self.kernel_open,
        )?;
        imgproc::morphology_ex_def(
            &self.mask,
            &mut self.tmp,
            imgproc::MORPH_CLOSE,
            &self.kernel_close,
        )?;
        std::mem::swap(&mut self.mask, &mut self.tmp);
        imgproc::find_contours_def(
            &self.mask,
            &mut self.contours,
            imgproc::RETR_EXTERNAL,
            imgproc::CHAIN_APPROX_NONE,
        )?;
        let (iw, ih) = (img.cols(), img.rows());
        let s = f64::from(scale);
        let coarse = scale > 1;
        // Coarse candidates only need to be roughly ball-like; refinement decides.
        let loosen = if coarse { 1.5 } else { 1.0 };
        let r_min = self.params.radius_min_px / s / loosen;
        let r_max = self.params.radius_max_px / s * loosen;
        for contour in &self.contours {
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
