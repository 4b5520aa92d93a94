//! Vision costs at 1280x720: full-frame and tracking detection, rendering, the
//! simulated camera's whole frame (render + detect + convert), the plane conversion.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::Vector3;
use rt_core::{
    params::CameraParams,
    sim::camera::{BallState, SimCamera, SimCameraParams, SimVision},
    vision::{Detector, DetectorParams},
};

const L: f64 = 1.93;

fn swing(t: f64) -> BallState {
    let w = (9.81 / L).sqrt();
    let a = 25f64.to_radians();
    let phi = a * (w * t).cos();
    let dphi = -a * w * (w * t).sin();
    let pivot = Vector3::new(0.6, 0.0, 0.30 + L);
    BallState {
        centre_m: pivot + L * Vector3::new(0.0, phi.sin(), -phi.cos()),
        velocity_mps: L * dphi * Vector3::new(0.0, phi.cos(), phi.sin()),
    }
}

fn camera() -> SimCamera {
    SimCamera::new(
        &CameraParams::default(),
        &SimCameraParams::default(),
        0.0335,
        1,
    )
    .expect("camera")
}

fn bench(c: &mut Criterion) {
    let mut cam = camera();
    // The ball in mid-swing (moving: blurred).
    let image = cam.render(Some(&swing(0.2))).expect("render").clone();
    let mut det = Detector::new(DetectorParams::default()).expect("detector");
    assert!(det.detect(&image, 0.0).expect("detect").is_some());

    c.bench_function("vision/detect_full_frame_1280x720", |b| {
        b.iter(|| {
            det.reset();
            black_box(det.detect(black_box(&image), 0.0).expect("detect"))
        });
    });

    let mut t = 0.0;
    det.reset();
    c.bench_function("vision/detect_tracking_1280x720", |b| {
        b.iter(|| {
            t += 1.0 / 30.0;
            let d = det.detect(black_box(&image), t).expect("detect");
            debug_assert!(d.is_some_and(|d| d.tracked));
            black_box(d)
        });
    });

    let mut t = 0.0;
    c.bench_function("vision/sim_render_1280x720", |b| {
        b.iter(|| {
            t += 1.0 / 30.0;
            black_box(cam.render(Some(&swing(t))).is_ok())
        });
    });

    let cam = camera();
    let cal = cam.true_calibration(&Vector3::new(0.6, 0.0, 0.30));
    let mut vision = SimVision::new(cam, DetectorParams::default(), cal).expect("vision");
    let mut t = 0.0;
    c.bench_function("vision/sim_capture_render_detect_convert", |b| {
        b.iter(|| {
            t += 1.0 / 30.0;
            black_box(vision.capture(t, Some(&swing(t))).expect("capture"))
        });
    });

    let cal = camera().true_calibration(&Vector3::new(0.6, 0.0, 0.30));
    c.bench_function("vision/lateral_m", |b| {
        b.iter(|| black_box(cal.lateral_m(black_box(812.3), black_box(401.7))));
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
