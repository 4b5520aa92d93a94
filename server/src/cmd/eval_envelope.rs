//! `isochron eval --envelope --reality FILE` (issue #36, item 4): the reality
//! lab's robustness envelope. For every `[world]` factor alone, then for all
//! of them together, the largest multiple `k` of the reality lab's range at
//! which the success rate stays >= 95%, found by bisection on `k` in
//! `[1, --max-multiple]`; every step is an `isochron trials` run of a scenario
//! written to `OUT/cells/` ([`super::eval::run_cell`]), so every number is
//! reproducible by the command printed beside it.
//!
//! The factors are a table ([`factors`]): one line per physical thing, naming
//! the `[world]` key(s) it scales, the benign value the scaling is anchored at
//! and how it scales. Keys that are no world effect are listed in
//! [`NOT_FACTORS`]; a test fails while a `[world]` key is in neither.
//!
//! `--shard I/N` runs the I-th of N contiguous slices of the items (the
//! factors, then "all factors together") and writes
//! `OUT/envelope/shard-I-of-N.json`; every run then writes `OUT/envelope.md`
//! and `OUT/envelope.svg` from the shard files of the same run found in
//! `OUT/envelope/` (the items of missing shards are listed as such).
//! `--combine` only writes the report, from the shard files there (e.g. copied
//! from other machines). Unsharded is one shard of one.

use std::{
    collections::HashMap,
    fmt::Write as _,
    path::{Path, PathBuf},
};

use anyhow::{Context, bail};
use rt_core::{
    control::stats::wilson_ci95,
    params::{
        RangeParam, Scenario, VisionMode,
        world::{MAX_SERVO_NATURAL_HZ, WorldParams},
    },
};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::{
    eval::{EvalArgs, run_cell},
    eval_reality::{check_judge_fits, signed_ms},
    trials::Shard,
};
use crate::plot::{self, Bar};

/// The success rate a multiple must reach to pass (point estimate).
pub const PASS_PERCENT: usize = 95;

/// The goals: every factor alone, and all of them together.
pub const GOAL_EACH: f64 = 3.0;
/// See [`GOAL_EACH`].
pub const GOAL_ALL: f64 = 2.0;

/// Format of the shard files (`OUT/envelope/shard-I-of-N.json`).
pub const SHARD_FORMAT: u32 = 1;

/// The arguments of `isochron eval` that belong to the envelope.
#[derive(Debug, Clone, clap::Args)]
pub struct EnvelopeArgs {
    /// The robustness envelope of the reality lab `--reality FILE` (instead of
    /// the evaluation): per `[world]` factor, then all together, the largest
    /// multiple of its range at which >= 95% of the trials succeed (bisection
    /// on the multiple, `--n` trials per step, the same `--seed` at every step).
    /// Writes OUT/envelope/shard-I-of-N.json, then OUT/envelope.md and
    /// OUT/envelope.svg from every shard file of the same run in OUT/envelope/.
    #[arg(long, conflicts_with = "scenario")]
    pub envelope: bool,
    /// Largest multiple of the reality lab's ranges tried (>= 1).
    #[arg(long, default_value_t = 8.0, requires = "envelope")]
    pub max_multiple: f64,
    /// Halvings of the bracket after trying 1 and --max-multiple: the
    /// resolution is (max - 1) / 2^steps.
    #[arg(long, default_value_t = 4, requires = "envelope")]
    pub steps: usize,
    /// Run only the I-th (from 0) of N slices of the items (the factors, then
    /// all factors together), e.g. `--shard 2/6`; the report is written from
    /// whichever shards' files are in OUT/envelope/.
    #[arg(long, requires = "envelope")]
    pub shard: Option<Shard>,
    /// Run nothing: write OUT/envelope.md and OUT/envelope.svg from the shard
    /// files in OUT/envelope/ (all of one run; a missing shard's items are listed).
    #[arg(long, requires = "envelope")]
    pub combine: bool,
    /// The camera's vision mode for every step, over the scenario's own
    /// (`model`: the measurement model, about 15 times faster than `full`,
    /// rendered frames through the detector).
    #[arg(long, requires = "envelope", value_parser = ["full", "model"])]
    pub vision: Option<String>,
}

impl Default for EnvelopeArgs {
    fn default() -> Self {
        Self {
            envelope: false,
            max_multiple: 8.0,
            steps: 4,
            shard: None,
            combine: false,
            vision: None,
        }
    }
}

// ---------------------------------------------------------------------------
// The factor table.

/// Where a key lives in [`WorldParams`] and what kind of value it holds.
#[derive(Clone, Copy)]
pub enum Slot {
    /// A `[lo, hi]` range.
    Range(fn(&mut WorldParams) -> &mut RangeParam),
    /// A range whose unset value is a belief (the benign value).
    Optional(fn(&mut WorldParams) -> &mut Option<RangeParam>),
    /// A plain number.
    Number(fn(&mut WorldParams) -> &mut f64),
}

/// The value a key's scaling is anchored at: the truthful one.
#[derive(Clone, Copy)]
pub enum Benign {
    /// A number (0 for an offset or a noise, 1 for a scale).
    Value(f64),
    /// A belief of the scenario, named (e.g. `control.release_delay_prior_ms`).
    Belief(&'static str, fn(&Scenario) -> f64),
}

/// How a multiple `k` acts on a key's value `v` (`b`: the benign value).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scaling {
    /// `v -> b + k (v - b)` (written `k v + (1 - k) b`, exact at k = 0 and 1):
    /// the range's distance from the benign value grows k-fold.
    Spread,
    /// Harsher is *lower* (a servo's natural frequency, a saturation limit):
    /// `v -> v / k`, i.e. its inverse (the servo's time constant `1/v`) grows
    /// k-fold; the benign value is infinite (an infinitely stiff servo, no
    /// limit). 0, where it means "none" or another model (the truthful
    /// first-order lag), stays 0.
    Inverse,
}

/// One `[world]` key of a factor.
#[derive(Clone, Copy)]
pub struct Key {
    /// Its path under `[world]`, e.g. `camera.latency_ms`.
    pub path: &'static str,
    /// Where it is.
    pub slot: Slot,
    /// Its benign value.
    pub benign: Benign,
    /// How it scales.
    pub scaling: Scaling,
    /// Its bounds in [`WorldParams::validate`]; a scaled value is clamped into them.
    pub bounds: (f64, f64),
}

/// A `[lo, hi]` key, spread about `benign`.
fn range(
    path: &'static str,
    slot: fn(&mut WorldParams) -> &mut RangeParam,
    benign: f64,
    bounds: (f64, f64),
) -> Key {
    Key {
        path,
        slot: Slot::Range(slot),
        benign: Benign::Value(benign),
        scaling: Scaling::Spread,
        bounds,
    }
}

/// A plain number, spread about `benign`.
fn number(
    path: &'static str,
    slot: fn(&mut WorldParams) -> &mut f64,
    benign: f64,
    bounds: (f64, f64),
) -> Key {
    Key {
        path,
        slot: Slot::Number(slot),
        benign: Benign::Value(benign),
        scaling: Scaling::Spread,
        bounds,
    }
}

/// A range whose unset value is the belief `belief`, spread about that belief.
fn optional(
    path: &'static str,
    slot: fn(&mut WorldParams) -> &mut Option<RangeParam>,
    belief: (&'static str, fn(&Scenario) -> f64),
    bounds: (f64, f64),
) -> Key {
    Key {
        path,
        slot: Slot::Optional(slot),
        benign: Benign::Belief(belief.0, belief.1),
        scaling: Scaling::Spread,
        bounds,
    }
}

impl Key {
    /// The key scaled as [`Scaling::Inverse`] (harsher is lower: `v -> v / k`).
    fn inverse(self) -> Self {
        Self {
            scaling: Scaling::Inverse,
            benign: Benign::Value(f64::INFINITY),
            ..self
        }
    }
}

/// A world effect: one physical thing, scaled as one.
#[derive(Clone)]
pub struct Factor {
    /// Its name in the report.
    pub name: &'static str,
    /// The keys it scales, all by the same multiple.
    pub keys: Vec<Key>,
}

fn factor(name: &'static str, keys: &[Key]) -> Factor {
    Factor {
        name,
        keys: keys.to_vec(),
    }
}

/// The factors of the envelope, one line each: name, then the key(s) with
/// their slot, benign value and `validate()` bounds. Adding a `[world]` key:
/// one line here, or its name in [`NOT_FACTORS`] (a test fails until then).
///
/// The choices:
/// - offsets, errors, noises, jitters, delays that the truthful world does
///   not have (camera latency offset, rolling shutter, exposure, lens, pose,
///   geometry errors, drag, pivot friction, out-of-plane release,
///   disturbance, latency drift, joint noise, inertia error): benign 0, the
///   range's distance from 0 grows k-fold (a symmetric `[-a, a]` becomes
///   `[-k a, k a]`);
/// - `pendulum.damping_scale`: benign 1 (the believed linear damping); its
///   distance from 1 grows in both directions (reality's `[0.2, 0.6]` reaches
///   0, "drag only", from k = 1.25 at its low end: the clamp is reported);
/// - `pendulum.release_delay_ms`: benign the believed
///   `control.release_delay_prior_ms` (unset = that belief);
///   `robot.latency_ms`: benign the believed `robot.latency_ms` (unset = it);
/// - `robot.servo_natural_hz`: harsher is a *lower* natural frequency, so the
///   servo's time constant `1/f` scales ([`Scaling::Inverse`]: `f -> f / k`,
///   clamped at the 2 Hz floor of `validate()`); its benign limit (k -> 0) is
///   the stiffest servo `validate()` allows (200 Hz), not 0, which selects
///   another model (the truthful first-order lag) and stays 0. A saturation
///   limit whose 0 means "none" (harsher = lower) is scaled the same way:
///   `number(...).inverse()`, its bounds the smallest limit allowed and the largest;
/// - `robot.servo_damping_ratio`: benign 0.7 (the default, a well-damped
///   servo); its distance from 0.7 grows both ways (reality's `[0.7, 1.0]`
///   becomes more overdamped, i.e. slower; a range below 0.7 would become
///   more oscillatory), clamped into `[0.2, 3]`;
/// - `robot.torque_limit_scale`: benign 1 (KUKA's specification); below 1
///   moves further below (it matters only with `robot.torque_trip`).
/// - `pendulum.contact_pulse_ms` and `robot.torque_lag_periods`: benign the
///   measured judge's default beliefs (4 ms, 1 period: `success.*`); their
///   distance from them grows both ways.
///
/// Lens distortion (`k1`, `k2`, `p1`, `p2`) is one factor, "lens"; the
/// camera's rotation and position errors are one, "camera pose"; the
/// auto-exposure's wander and the mains flicker are "lighting"; datagram
/// loss both ways is "FRI datagram loss", the one-way latency and its
/// jitter "FRI network latency" (benign 0 each). The drives' speed and
/// acceleration saturation (`velocity_limit_scale`,
/// `acceleration_limit_scale`: 0 = none, harsher = lower) scale inversely.
#[rustfmt::skip]
pub fn factors() -> Vec<Factor> {
    let belief_release: (&'static str, fn(&Scenario) -> f64) =
        ("control.release_delay_prior_ms", |s| {
            s.control.release_delay_prior_ms
        });
    let belief_latency: (&'static str, fn(&Scenario) -> f64) =
        ("robot.latency_ms", |s| s.robot.latency_ms);
    vec![
        // The pendulum.
        factor("pendulum length", &[range("pendulum.length_error_m", |w| &mut w.pendulum.length_error_m, 0.0, (-0.5, 0.5))]),
        factor("linear damping", &[range("pendulum.damping_scale", |w| &mut w.pendulum.damping_scale, 1.0, (0.0, 20.0))]),
        factor("air drag", &[range("pendulum.drag_coefficient", |w| &mut w.pendulum.drag_coefficient, 0.0, (0.0, 2.0))]),
        factor("pivot friction", &[range("pendulum.pivot_friction_mps2", |w| &mut w.pendulum.pivot_friction_mps2, 0.0, (0.0, 1.0))]),
        factor("out-of-plane release", &[range("pendulum.out_of_plane_deg", |w| &mut w.pendulum.out_of_plane_deg, 0.0, (0.0, 10.0))]),
        factor("magnet release delay", &[optional("pendulum.release_delay_ms", |w| &mut w.pendulum.release_delay_ms, belief_release, (0.0, 500.0))]),
        factor("air disturbance", &[range("pendulum.disturbance_mps2", |w| &mut w.pendulum.disturbance_mps2, 0.0, (0.0, 1.0))]),
        factor("contact pulse", &[range("pendulum.contact_pulse_ms", |w| &mut w.pendulum.contact_pulse_ms, 4.0, (0.5, 50.0))]),
        // The camera.
        factor("camera latency offset", &[range("camera.latency_ms", |w| &mut w.camera.latency_ms, 0.0, (-500.0, 500.0))]),
        factor("camera latency jitter", &[range("camera.latency_jitter_ms", |w| &mut w.camera.latency_jitter_ms, 0.0, (0.0, 100.0))]),
        factor("rolling shutter", &[range("camera.rolling_shutter_ms", |w| &mut w.camera.rolling_shutter_ms, 0.0, (0.0, 100.0))]),
        factor("exposure", &[range("camera.exposure_ms", |w| &mut w.camera.exposure_ms, 0.0, (0.0, 100.0))]),
        factor("transfer after the readout", &[range("camera.transfer_ms", |w| &mut w.camera.transfer_ms, 0.0, (0.0, 100.0))]),
        factor("lens", &[
            range("camera.distortion_k1", |w| &mut w.camera.distortion_k1, 0.0, (-1.0, 1.0)),
            range("camera.distortion_k2", |w| &mut w.camera.distortion_k2, 0.0, (-1.0, 1.0)),
            range("camera.distortion_p1", |w| &mut w.camera.distortion_p1, 0.0, (-0.1, 0.1)),
            range("camera.distortion_p2", |w| &mut w.camera.distortion_p2, 0.0, (-0.1, 0.1)),
        ]),
        factor("camera pose", &[
            range("camera.pose_error_deg", |w| &mut w.camera.pose_error_deg, 0.0, (-10.0, 10.0)),
            range("camera.pose_error_m", |w| &mut w.camera.pose_error_m, 0.0, (-0.5, 0.5)),
        ]),
        factor("camera clock drift", &[range("camera.clock_drift_ppm", |w| &mut w.camera.clock_drift_ppm, 0.0, (-1000.0, 1000.0))]),
        factor("frame-time jitter", &[range("camera.frame_jitter_ms", |w| &mut w.camera.frame_jitter_ms, 0.0, (0.0, 20.0))]),
        factor("lighting", &[
            range("camera.exposure_gain_variation", |w| &mut w.camera.exposure_gain_variation, 0.0, (0.0, 0.9)),
            range("camera.flicker", |w| &mut w.camera.flicker, 0.0, (0.0, 0.9)),
        ]),
        factor("passing shadows", &[range("camera.shadow_depth", |w| &mut w.camera.shadow_depth, 0.0, (0.0, 0.95))]),
        // The robot.
        factor("robot latency", &[optional("robot.latency_ms", |w| &mut w.robot.latency_ms, belief_latency, (0.0, 200.0))]),
        factor("robot latency drift", &[range("robot.latency_drift_ms", |w| &mut w.robot.latency_drift_ms, 0.0, (0.0, 50.0))]),
        factor("servo bandwidth", &[range("robot.servo_natural_hz", |w| &mut w.robot.servo_natural_hz, 0.0, (2.0, MAX_SERVO_NATURAL_HZ)).inverse()]),
        factor("servo damping", &[range("robot.servo_damping_ratio", |w| &mut w.robot.servo_damping_ratio, 0.7, (0.2, 3.0))]),
        factor("joint position noise", &[number("robot.position_noise_rad", |w| &mut w.robot.position_noise_rad, 0.0, (0.0, 0.01))]),
        factor("link inertia error", &[number("robot.inertia_error", |w| &mut w.robot.inertia_error, 0.0, (0.0, 0.5))]),
        factor("torque limit", &[number("robot.torque_limit_scale", |w| &mut w.robot.torque_limit_scale, 1.0, (0.05, 2.0))]),
        factor("joint velocity saturation", &[number("robot.velocity_limit_scale", |w| &mut w.robot.velocity_limit_scale, 0.0, (0.05, 2.0)).inverse()]),
        factor("joint acceleration saturation", &[number("robot.acceleration_limit_scale", |w| &mut w.robot.acceleration_limit_scale, 0.0, (0.05, 10.0)).inverse()]),
        factor("FRI datagram loss", &[
            range("robot.packet_loss", |w| &mut w.robot.packet_loss, 0.0, (0.0, 0.5)),
            range("robot.reply_loss", |w| &mut w.robot.reply_loss, 0.0, (0.0, 0.5)),
        ]),
        factor("FRI network latency", &[
            range("robot.message_latency_ms", |w| &mut w.robot.message_latency_ms, 0.0, (0.0, 20.0)),
            range("robot.message_jitter_ms", |w| &mut w.robot.message_jitter_ms, 0.0, (0.0, 20.0)),
        ]),
        factor("command jitter", &[range("robot.command_jitter_ms", |w| &mut w.robot.command_jitter_ms, 0.0, (0.0, 50.0))]),
        factor("torque estimate lag", &[range("robot.torque_lag_periods", |w| &mut w.robot.torque_lag_periods, 1.0, (0.0, 10.0))]),
        // The geometry.
        factor("intercept point", &[range("geometry.intercept_error_m", |w| &mut w.geometry.intercept_error_m, 0.0, (-0.1, 0.1))]),
        factor("tool length", &[range("geometry.tool_length_error_m", |w| &mut w.geometry.tool_length_error_m, 0.0, (-0.05, 0.05))]),
        factor("DH link lengths", &[range("geometry.dh_length_error_m", |w| &mut w.geometry.dh_length_error_m, 0.0, (-0.01, 0.01))]),
        factor("joint zero offsets", &[range("geometry.joint_offset_error_deg", |w| &mut w.geometry.joint_offset_error_deg, 0.0, (-2.0, 2.0))]),
    ]
}

/// `[world]` keys that are not factors, and why.
pub const NOT_FACTORS: &[(&str, &str)] = &[
    (
        "sessions.trials_per_session",
        "how draws are grouped into reboots, not an effect",
    ),
    (
        "pendulum.ball_mass_kg",
        "a constant of the drag (scaled by `pendulum.drag_coefficient`)",
    ),
    (
        "pendulum.air_density_kgpm3",
        "a constant of the drag (scaled by `pendulum.drag_coefficient`)",
    ),
    (
        "robot.torque_trip",
        "a switch (check the torques), not a magnitude",
    ),
    (
        "robot.step_time_delays_reply",
        "a switch (the control step's CPU time in virtual time), not a magnitude",
    ),
    (
        "camera.arm_occludes",
        "a switch (the arm hides the ball where it stands), not a magnitude",
    ),
    (
        "robot.contact_push",
        "a switch (the contact's impulse moves the arm), not a magnitude",
    ),
    (
        "geometry.contact_disc_radius_m",
        "the judge's tool disc (what counts as a hit), not an error of the world",
    ),
    (
        "pendulum.contact_restitution",
        "a property of ball and tool that sets a strike's rebound (issue #38), not an \
         error of the world against a belief; a stop trial is judged at its contact, before any rebound",
    ),
];

impl Key {
    /// The benign value in scenario `s`.
    pub fn benign_of(&self, s: &Scenario) -> f64 {
        match self.benign {
            Benign::Value(v) => v,
            Benign::Belief(_, f) => f(s),
        }
    }

    /// The benign value as the report says it.
    pub fn benign_text(&self, s: &Scenario) -> String {
        match (self.scaling, self.benign) {
            (Scaling::Inverse, _) => {
                format!("∞ (k -> 0: {}, the upper bound)", num(self.bounds.1))
            }
            (_, Benign::Value(v)) => num(v),
            (_, Benign::Belief(name, f)) => format!("{} (`{name}`)", num(f(s))),
        }
    }

    /// The key's value in `w` (a number is a range of one value); None: unset,
    /// i.e. the benign belief.
    pub fn get(&self, w: &WorldParams) -> Option<RangeParam> {
        let mut w = w.clone();
        match self.slot {
            Slot::Range(f) => Some(*f(&mut w)),
            Slot::Optional(f) => *f(&mut w),
            Slot::Number(f) => Some(RangeParam::fixed(*f(&mut w))),
        }
    }

    fn set(&self, w: &mut WorldParams, r: RangeParam) {
        match self.slot {
            Slot::Range(f) => *f(w) = r,
            Slot::Optional(f) => *f(w) = Some(r),
            Slot::Number(f) => *f(w) = r.lo,
        }
    }

    /// One end `v` at multiple `k` of benign `b`, before the clamp.
    fn unclamped(&self, v: f64, b: f64, k: f64) -> f64 {
        match self.scaling {
            Scaling::Spread => k * v + (1.0 - k) * b,
            Scaling::Inverse => v / k,
        }
    }

    /// `r` at multiple `k` (benign value `b`), clamped into the bounds; true
    /// when the clamp changed it.
    pub fn scale(&self, r: RangeParam, b: f64, k: f64) -> (RangeParam, bool) {
        let one = |v: f64| -> (f64, bool) {
            if self.scaling == Scaling::Inverse && v == 0.0 {
                return (0.0, false);
            }
            let x = self.unclamped(v, b, k);
            let c = x.clamp(self.bounds.0, self.bounds.1);
            (c, c != x)
        };
        let ((lo, a), (hi, z)) = (one(r.lo), one(r.hi));
        (RangeParam::new(lo, hi), a || z)
    }

    /// The smallest multiple >= 1 past which `r`'s scaling is clamped (None: never).
    pub fn clamp_onset(&self, r: RangeParam, b: f64) -> Option<f64> {
        let (lo_b, hi_b) = self.bounds;
        [r.lo, r.hi]
            .into_iter()
            .filter_map(|v| match self.scaling {
                Scaling::Spread if v > b => Some((hi_b - b) / (v - b)),
                Scaling::Spread if v < b => Some((lo_b - b) / (v - b)),
                Scaling::Inverse if v > 0.0 => Some(v / lo_b),
                Scaling::Spread | Scaling::Inverse => None,
            })
            .filter(|k| k.is_finite() && *k >= 1.0)
            .min_by(f64::total_cmp)
    }
}

/// Reality's world at multiple `k` of `factors` (every other key as in
/// reality); the keys the clamp limited. An unset optional key stays unset
/// (it is its benign value at every multiple).
pub fn scaled(
    reality: &Scenario,
    factors: &[&Factor],
    k: f64,
) -> anyhow::Result<(Scenario, Vec<&'static str>)> {
    let Some(world) = &reality.world else {
        bail!(
            "--reality: scenario {} has no [world]: it is a truthful world, it has no ranges to scale",
            reality.name
        );
    };
    let mut w = world.clone();
    let mut clamped = Vec::new();
    for f in factors {
        for key in &f.keys {
            if let Some(r) = key.get(world) {
                let (s, c) = key.scale(r, key.benign_of(reality), k);
                key.set(&mut w, s);
                if c {
                    clamped.push(key.path);
                }
            }
        }
    }
    let mut s = reality.clone();
    s.world = Some(w);
    s.validate()
        .with_context(|| format!("the world at {k}x does not validate"))?;
    Ok((s, clamped))
}

/// Whether reality gives the factor anything to scale (some key away from
/// its benign value).
pub fn is_active(reality: &Scenario, f: &Factor) -> bool {
    scaled(reality, &[f], 2.0).is_ok_and(|(s, _)| s.world != reality.world)
}

// ---------------------------------------------------------------------------
// The bisection.

/// Where a factor's bisection ended.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Outcome {
    /// Reality's own range (k = 1) already fails.
    FailsAtOne,
    /// The largest multiple tried passes.
    PassesAtMax {
        /// That multiple.
        max: f64,
    },
    /// `pass` passes, `fail` fails, `fail - pass` is the resolution.
    Bracket {
        /// Largest multiple passing.
        pass: f64,
        /// Smallest multiple failing.
        fail: f64,
    },
    /// Reality leaves every key of the factor at its benign value: nothing
    /// to scale, nothing run.
    NotScaled,
}

impl Outcome {
    /// The largest multiple that passed (None: none did, or nothing ran).
    pub fn largest_passing(&self) -> Option<f64> {
        match *self {
            Self::PassesAtMax { max } => Some(max),
            Self::Bracket { pass, .. } => Some(pass),
            Self::FailsAtOne | Self::NotScaled => None,
        }
    }

    /// The first multiple that failed.
    pub fn first_failing(&self) -> Option<f64> {
        match *self {
            Self::FailsAtOne => Some(1.0),
            Self::Bracket { fail, .. } => Some(fail),
            Self::PassesAtMax { .. } | Self::NotScaled => None,
        }
    }
}

/// The resolution of a bisection of `[1, max]` in `steps` halvings.
pub fn resolution(max: f64, steps: usize) -> f64 {
    (max - 1.0) / 2f64.powi(i32::try_from(steps).unwrap_or(i32::MAX))
}

/// Bisection of the multiple on `[1, max]`: `run` at 1 (failing: stop), at
/// `max` (passing: stop), then `steps` halvings of the bracket, each moving
/// the passing end up or the failing end down. Assumes success falls with
/// the multiple; every step's result is returned with its multiple.
pub fn bisect<S>(
    max: f64,
    steps: usize,
    mut run: impl FnMut(f64) -> anyhow::Result<S>,
    passes: impl Fn(&S) -> bool,
) -> anyhow::Result<(Vec<(f64, S)>, Outcome)> {
    let mut done = Vec::new();
    let at_one = run(1.0)?;
    let ok = passes(&at_one);
    done.push((1.0, at_one));
    if !ok {
        return Ok((done, Outcome::FailsAtOne));
    }
    if max <= 1.0 {
        return Ok((done, Outcome::PassesAtMax { max: 1.0 }));
    }
    let at_max = run(max)?;
    let ok = passes(&at_max);
    done.push((max, at_max));
    if ok {
        return Ok((done, Outcome::PassesAtMax { max }));
    }
    let (mut pass, mut fail) = (1.0, max);
    for _ in 0..steps {
        let k = 0.5 * (pass + fail);
        let s = run(k)?;
        if passes(&s) {
            pass = k;
        } else {
            fail = k;
        }
        done.push((k, s));
    }
    Ok((done, Outcome::Bracket { pass, fail }))
}

// ---------------------------------------------------------------------------
// Items and shards.

/// The name of the last item, every factor scaled together.
pub const ALL_TOGETHER: &str = "all factors together";

/// The items' names: the factors, then all together.
pub fn item_names(factors: &[Factor]) -> Vec<String> {
    factors
        .iter()
        .map(|f| f.name.to_owned())
        .chain([ALL_TOGETHER.to_owned()])
        .collect()
}

/// The items shard `shard` runs of `len`: `index * len / count .. (index + 1) * len / count`.
pub fn shard_items(len: usize, shard: Shard) -> std::ops::Range<usize> {
    shard.index * len / shard.count..(shard.index + 1) * len / shard.count
}

/// A key's range as written to the shard file (None: unset, the benign belief).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeyRange {
    /// The key's path under `[world]`.
    pub key: String,
    /// Its `[lo, hi]`.
    pub range: Option<[f64; 2]>,
}

/// One step of a bisection: one `isochron trials` run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Step {
    /// The multiple.
    pub k: f64,
    /// Trials judged.
    pub trials: usize,
    /// Of which succeeded.
    pub successes: usize,
    /// Wilson 95% interval of the success rate.
    pub ci95: [f64; 2],
    /// |timing error| p50 and p95 of the judged trials, ms (None: none judged).
    pub timing_error_p50_ms: Option<f64>,
    /// See `timing_error_p50_ms`.
    pub timing_error_p95_ms: Option<f64>,
    /// The factor's keys the clamp limited at this multiple.
    pub clamped: Vec<String>,
    /// The factor's keys' ranges at this multiple.
    pub ranges: Vec<KeyRange>,
    /// The `isochron trials` command line (run in OUT).
    pub command: String,
}

impl Step {
    /// Whether the success rate is >= 95%.
    pub fn passes(&self) -> bool {
        self.trials > 0 && 100 * self.successes >= PASS_PERCENT * self.trials
    }

    fn rate(&self) -> f64 {
        self.successes as f64 / self.trials.max(1) as f64
    }
}

/// One item's result.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ItemResult {
    /// The item's index in [`item_names`].
    pub index: usize,
    /// Its name.
    pub name: String,
    /// The keys it scales with their reality range.
    pub reality: Vec<KeyRange>,
    /// The smallest multiple (>= 1) past which a key is clamped, and the key.
    pub clamp_onset: Option<(f64, String)>,
    /// The bisection's steps, in the order run.
    pub steps: Vec<Step>,
    /// Where it ended.
    pub outcome: Outcome,
}

/// What makes two shard files parts of one run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunKey {
    /// The reality lab, as TOML.
    pub scenario_toml: String,
    /// Trials per step.
    pub n: usize,
    /// Seed of every step.
    pub seed: u64,
    /// Largest multiple tried.
    pub max_multiple: f64,
    /// Halvings.
    pub steps: usize,
    /// Shards of the run.
    pub shard_count: usize,
    /// Every item's name, in order.
    pub items: Vec<String>,
}

/// `OUT/envelope/shard-I-of-N.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ShardFile {
    /// [`SHARD_FORMAT`].
    pub format: u32,
    /// The run it belongs to.
    pub run: RunKey,
    /// This shard's index.
    pub shard_index: usize,
    /// The `isochron eval` command that wrote it.
    pub command: String,
    /// Its items' results.
    pub results: Vec<ItemResult>,
}

fn shard_file_name(shard: Shard) -> String {
    format!("shard-{}-of-{}.json", shard.index, shard.count)
}

// ---------------------------------------------------------------------------
// Running.

fn check_args(args: &EvalArgs) -> anyhow::Result<()> {
    let e = &args.envelope;
    if args.n == 0 || args.n > 10_000 {
        bail!("--n = {} is out of range: must be in [1, 10000]", args.n);
    }
    if !e.max_multiple.is_finite() || !(1.0..=1000.0).contains(&e.max_multiple) {
        bail!(
            "--max-multiple = {} is out of range: must be a finite number in [1, 1000]",
            e.max_multiple
        );
    }
    if e.steps > 20 {
        bail!("--steps = {} is out of range: must be in [0, 20]", e.steps);
    }
    if args.reality.is_none() {
        bail!(
            "--envelope needs --reality FILE (a scenario with [world], e.g. scenarios/reality.toml)"
        );
    }
    Ok(())
}

/// A short, file-name-safe form of `s`.
fn slug(s: &str, max: usize) -> String {
    let mut out = String::new();
    for c in s.chars() {
        if c.is_ascii_alphanumeric() {
            out.push(c.to_ascii_lowercase());
        } else if !out.ends_with('-') {
            out.push('-');
        }
    }
    out.trim_matches('-').chars().take(max).collect()
}

fn key_ranges(keys: &[Key], w: &WorldParams) -> Vec<KeyRange> {
    keys.iter()
        .map(|k| KeyRange {
            key: k.path.to_owned(),
            range: k.get(w).map(|r| [r.lo, r.hi]),
        })
        .collect()
}

/// Runs `isochron eval --envelope`; returns what to print.
pub fn run(args: &EvalArgs) -> anyhow::Result<String> {
    let e = &args.envelope;
    if e.combine {
        let path = combine(&args.out, None)?;
        return Ok(format!("envelope report: {}", path.display()));
    }
    check_args(args)?;
    let path = args
        .reality
        .as_deref()
        .context("--envelope needs --reality FILE")?;
    let mut reality = Scenario::from_file(path)?;
    match e.vision.as_deref() {
        Some("model") => reality.camera.vision = VisionMode::Model,
        Some("full") => reality.camera.vision = VisionMode::Full,
        Some(v) => bail!("--vision {v}: must be full or model"),
        None => {}
    }
    let table = factors();
    // Refuses a truthful world before anything runs.
    scaled(&reality, &[], 1.0)?;
    check_judge_fits(&reality)?;
    let items = item_names(&table);
    let shard = e.shard.unwrap_or(Shard { index: 0, count: 1 });
    if shard.count > items.len() {
        bail!(
            "--shard {}/{}: the envelope has {} items ({} factors and all together), fewer than {} shards",
            shard.index,
            shard.count,
            items.len(),
            table.len(),
            shard.count
        );
    }
    std::fs::create_dir_all(args.out.join("cells"))
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let env_dir = args.out.join("envelope");
    std::fs::create_dir_all(&env_dir)
        .with_context(|| format!("cannot create {}", env_dir.display()))?;
    let exe = std::env::current_exe().context("cannot find the isochron binary")?;
    let run_key = RunKey {
        scenario_toml: reality.to_toml_string(),
        n: args.n,
        seed: args.seed,
        max_multiple: e.max_multiple,
        steps: e.steps,
        shard_count: shard.count,
        items: items.clone(),
    };
    let base = slug(&reality.name, 16);
    let mut cache: HashMap<String, (Vec<Value>, String)> = HashMap::new();
    let mut results = Vec::new();
    for index in shard_items(items.len(), shard) {
        let name = &items[index];
        let chosen: Vec<&Factor> = match table.get(index) {
            Some(f) => vec![f],
            None => table.iter().filter(|f| is_active(&reality, f)).collect(),
        };
        let keys: Vec<Key> = chosen.iter().flat_map(|f| f.keys.clone()).collect();
        let world = reality.world.clone().unwrap_or_default();
        let onset = keys
            .iter()
            .filter_map(|k| {
                let r = k.get(&world)?;
                Some((k.clamp_onset(r, k.benign_of(&reality))?, k.path.to_owned()))
            })
            .min_by(|a, b| a.0.total_cmp(&b.0));
        let reality_ranges = key_ranges(&keys, &world);
        if chosen.is_empty() || (index < table.len() && !is_active(&reality, chosen[0])) {
            eprintln!("envelope: {name}: reality.toml leaves it benign, nothing to scale");
            results.push(ItemResult {
                index,
                name: name.clone(),
                reality: reality_ranges,
                clamp_onset: onset,
                steps: Vec::new(),
                outcome: Outcome::NotScaled,
            });
            continue;
        }
        let slug_item = format!("{index:02}-{}", slug(name, 24));
        let (steps, outcome) = bisect(
            e.max_multiple,
            e.steps,
            |k| {
                let (mut sc, clamped) = scaled(&reality, &chosen, k)?;
                let mut key = sc.clone();
                key.name = String::new();
                let key = key.to_toml_string();
                sc.name = if k == 1.0 {
                    format!("{base}-env-k1")
                } else {
                    format!("{base}-env-{slug_item}-k{k}")
                };
                let (trials, command) = if let Some(hit) = cache.get(&key) {
                    hit.clone()
                } else {
                    eprintln!("envelope: {name} at {}x: {} trials", num(k), args.n);
                    let (_, trials, command) = run_cell(&exe, &args.out, &sc, args.n, args.seed)?;
                    cache.insert(key, (trials.clone(), command.clone()));
                    (trials, command)
                };
                let w = sc.world.clone().unwrap_or_default();
                Ok(step_of(
                    k,
                    &trials,
                    command,
                    clamped.iter().map(|s| (*s).to_owned()).collect(),
                    key_ranges(&keys, &w),
                ))
            },
            Step::passes,
        )?;
        results.push(ItemResult {
            index,
            name: name.clone(),
            reality: reality_ranges,
            clamp_onset: onset,
            steps: steps.into_iter().map(|(_, s)| s).collect(),
            outcome,
        });
    }
    let file = ShardFile {
        format: SHARD_FORMAT,
        run: run_key.clone(),
        shard_index: shard.index,
        command: shard_command(path, args, shard),
        results,
    };
    let shard_path = env_dir.join(shard_file_name(shard));
    write_atomically(&shard_path, &serde_json::to_string_pretty(&file)?)?;
    let report = combine(&args.out, Some(&run_key))?;
    Ok(format!(
        "envelope shard {}/{}: {}\nenvelope report: {}",
        shard.index,
        shard.count,
        shard_path.display(),
        report.display()
    ))
}

fn shard_command(reality: &Path, args: &EvalArgs, shard: Shard) -> String {
    format!(
        "isochron eval --envelope --reality {} --out {} --n {} --seed {} --max-multiple {} --steps {} --shard {}/{}",
        reality.display(),
        args.out.display(),
        args.n,
        args.seed,
        args.envelope.max_multiple,
        args.envelope.steps,
        shard.index,
        shard.count
    )
}

fn step_of(
    k: f64,
    trials: &[Value],
    command: String,
    clamped: Vec<String>,
    ranges: Vec<KeyRange>,
) -> Step {
    let n = trials.len();
    let ok = trials
        .iter()
        .filter(|v| v["success"].as_bool() == Some(true))
        .count();
    let mut abs: Vec<f64> = trials
        .iter()
        .map(|v| signed_ms(v).abs())
        .filter(|x| x.is_finite())
        .collect();
    abs.sort_by(f64::total_cmp);
    Step {
        k,
        trials: n,
        successes: ok,
        ci95: wilson_ci95(ok, n),
        timing_error_p50_ms: rt_core::quantile::quantile(&abs, 0.5),
        timing_error_p95_ms: rt_core::quantile::quantile(&abs, 0.95),
        clamped,
        ranges,
        command,
    }
}

/// Writes `text` to `path` through a temporary file and a rename, so that a
/// reader (another shard combining) never sees half a file.
fn write_atomically(path: &Path, text: &str) -> anyhow::Result<()> {
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    std::fs::write(&tmp, text).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("cannot write {}", path.display()))
}

/// Reads the shard files in `OUT/envelope/`: of run `want`, or (None) of
/// one run, refusing files of different runs. Returns the run, the files and
/// the names of files left out.
fn read_shards(
    dir: &Path,
    want: Option<&RunKey>,
) -> anyhow::Result<(RunKey, Vec<ShardFile>, Vec<String>)> {
    let env_dir = dir.join("envelope");
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&env_dir)
        .with_context(|| format!("cannot read {}", env_dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name().and_then(|n| n.to_str()).is_some_and(|n| {
                n.starts_with("shard-")
                    && std::path::Path::new(n)
                        .extension()
                        .is_some_and(|e| e.eq_ignore_ascii_case("json"))
            })
        })
        .collect();
    paths.sort();
    let mut files: Vec<ShardFile> = Vec::new();
    let mut left_out = Vec::new();
    let mut run: Option<RunKey> = want.cloned();
    for p in paths {
        let text =
            std::fs::read_to_string(&p).with_context(|| format!("cannot read {}", p.display()))?;
        let f: ShardFile = serde_json::from_str(&text)
            .with_context(|| format!("{}: not an envelope shard file", p.display()))?;
        if f.format != SHARD_FORMAT {
            bail!(
                "{}: shard file format {} (this isochron reads {SHARD_FORMAT})",
                p.display(),
                f.format
            );
        }
        match &run {
            Some(r) if *r != f.run => {
                if want.is_some() {
                    left_out.push(p.display().to_string());
                    continue;
                }
                bail!(
                    "{}: a shard of another run (another scenario, --n, --seed, --max-multiple, \
                     --steps or shard count) than the files before it; remove the stale files",
                    p.display()
                );
            }
            Some(_) => {}
            None => run = Some(f.run.clone()),
        }
        if files.iter().any(|g| g.shard_index == f.shard_index) {
            bail!("{}: shard {} twice", p.display(), f.shard_index);
        }
        files.push(f);
    }
    let Some(run) = run else {
        bail!(
            "no envelope shard files in {} (run isochron eval --envelope --shard I/N first)",
            env_dir.display()
        );
    };
    files.sort_by_key(|f| f.shard_index);
    Ok((run, files, left_out))
}

/// Writes `OUT/envelope.md` and `OUT/envelope.svg` from the shard files in
/// `OUT/envelope/` (of run `want` when given); returns the report's path.
pub fn combine(dir: &Path, want: Option<&RunKey>) -> anyhow::Result<PathBuf> {
    let (run, files, left_out) = read_shards(dir, want)?;
    for f in &left_out {
        eprintln!("envelope: {f} is of another run: left out of the report");
    }
    let reality = Scenario::from_toml_str(&run.scenario_toml)
        .context("the shard files' scenario does not parse")?;
    let mut results: Vec<Option<ItemResult>> = vec![None; run.items.len()];
    for f in &files {
        for r in &f.results {
            if let Some(slot) = results.get_mut(r.index) {
                *slot = Some(r.clone());
            }
        }
    }
    let md = report(&run, &reality, &files, &results);
    let svg = figure(&run, &results)?;
    write_atomically(&dir.join("envelope.svg"), &svg)?;
    let path = dir.join("envelope.md");
    write_atomically(&path, &md)?;
    Ok(path)
}

// ---------------------------------------------------------------------------
// The report.

/// A number as the report writes it: up to 4 significant digits, no trailing zeros.
fn num(v: f64) -> String {
    if !v.is_finite() {
        return if v > 0.0 { "∞".into() } else { "–".into() };
    }
    if v == 0.0 {
        return "0".into();
    }
    let digits = (3 - v.abs().log10().floor() as i32).clamp(0, 12) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_owned()
    } else {
        s
    }
}

fn range_text(r: &KeyRange) -> String {
    match r.range {
        None => "unset (benign)".into(),
        Some([lo, hi]) if lo == hi => num(lo),
        Some([lo, hi]) => format!("[{}, {}]", num(lo), num(hi)),
    }
}

fn mult(k: f64) -> String {
    format!("{}x", num(k))
}

fn success_text(s: &Step) -> String {
    format!(
        "{}/{} = {:.1}% ({:.1}..{:.1}%)",
        s.successes,
        s.trials,
        100.0 * s.rate(),
        100.0 * s.ci95[0],
        100.0 * s.ci95[1]
    )
}

fn step_at(r: &ItemResult, k: f64) -> Option<&Step> {
    r.steps.iter().find(|s| s.k == k)
}

/// The "what limits it" cell.
fn limit_text(r: &ItemResult, run: &RunKey) -> String {
    let clamp = |k: f64| -> Option<String> {
        let s = step_at(r, k)?;
        (!s.clamped.is_empty()).then(|| {
            format!(
                "clamped at {}: {}",
                mult(k),
                s.clamped
                    .iter()
                    .map(|c| format!("`{c}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })
    };
    match r.outcome {
        Outcome::NotScaled => "nothing to scale: reality.toml leaves it benign".into(),
        Outcome::FailsAtOne => "success < 95% already at reality.toml's range".into(),
        Outcome::PassesAtMax { max } => match clamp(max) {
            Some(c) => format!(
                "{c} (validate()'s bound{}: the range grows no further at that end)",
                r.clamp_onset
                    .as_ref()
                    .map(|(k, key)| format!(", `{key}` reaches it from {}", mult(*k)))
                    .unwrap_or_default()
            ),
            None => format!(
                "none found: passes at the largest multiple tried (--max-multiple {})",
                num(run.max_multiple)
            ),
        },
        Outcome::Bracket { fail, .. } => match clamp(fail) {
            Some(c) => format!("success < 95% ({c})"),
            None => "success < 95%".into(),
        },
    }
}

fn largest_text(r: &ItemResult) -> String {
    match r.outcome {
        Outcome::NotScaled => "–".into(),
        Outcome::FailsAtOne => "none (fails at 1x)".into(),
        Outcome::PassesAtMax { max } => format!(">= {}", mult(max)),
        Outcome::Bracket { pass, .. } => mult(pass),
    }
}

fn goal_of(r: &ItemResult) -> f64 {
    if r.name == ALL_TOGETHER {
        GOAL_ALL
    } else {
        GOAL_EACH
    }
}

fn report(
    run: &RunKey,
    reality: &Scenario,
    files: &[ShardFile],
    results: &[Option<ItemResult>],
) -> String {
    let table = factors();
    let mut md = String::new();
    let vision = match reality.camera.vision {
        VisionMode::Full => "full (rendered frames through the OpenCV detector)",
        VisionMode::Model => "model (a noisy projection of the true ball, no images)",
    };
    let res = resolution(run.max_multiple, run.steps);
    let _ = writeln!(
        md,
        "# isochron robustness envelope: `{name}`\n\n\
         ## Robustness envelope (reality-lab figures)\n\n\
         Every figure here is a **reality-lab** figure: scenario `{name}` (its `[world]` is a lab \
         that is not what the controller believes), judged by the physical judge. \
         Camera vision mode: **{vision}** (`camera.vision`). Task: the scenario's own, movement \
         time {t} s, distances {dlo}..{dhi} m. **{n} trials per step, seed {seed}** (the same \
         seed at every step, so the steps differ only by the world's ranges).\n\n\
         **Baseline.** A factor is scaled *on top of the reality lab*: at multiple k its keys' \
         ranges are k times reality.toml's (measured from the benign value), and every other \
         `[world]` key stays as in reality.toml. Not on a truthful world: the question is how \
         much worse than we expect this one thing may be while the rest of the lab is as we \
         expect it; alone in a truthful world a factor would meet none of the effects it adds \
         to, and its margin would be optimistic. \"All factors together\" scales every factor \
         by the same k.\n\n\
         **Scaling.** Multiple k maps a range [lo, hi] to [b + k(lo - b), b + k(hi - b)], b \
         the key's benign (truthful) value (table below), clamped into the key's bounds in \
         `validate()`; a servo's natural frequency f maps to f / k (its time constant grows \
         k-fold). k = 1 is reality.toml. A clamp stops the factor growing: the table says where.\n\n\
         **Bisection.** Trials at k = 1 (failing: stop), at k = {max} (passing: stop, \
         \">= {max}x\"), then {steps} halvings of the bracket: a step whose success rate \
         (point estimate) is >= {PASS_PERCENT}% moves the passing end up, else the failing end \
         down. Resolution: {res}x. It assumes success falls with k; the steps' rows below show \
         whether it did.\n\n\
         **Goal** (issue #36): every factor >= {GOAL_EACH}x, all factors together >= {GOAL_ALL}x.\n",
        name = reality.name,
        t = reality.task.movement_time_s,
        dlo = reality.task.distance_m.lo,
        dhi = reality.task.distance_m.hi,
        n = run.n,
        seed = run.seed,
        max = num(run.max_multiple),
        steps = run.steps,
        res = num(res),
    );
    // The goal, in one line.
    let done: Vec<&ItemResult> = results.iter().flatten().collect();
    let short: Vec<String> = done
        .iter()
        .filter(|r| r.outcome != Outcome::NotScaled)
        .filter(|r| r.outcome.largest_passing().is_none_or(|k| k < goal_of(r)))
        .map(|r| format!("{} ({})", r.name, largest_text(r)))
        .collect();
    let missing: Vec<usize> = (0..results.len())
        .filter(|&i| results[i].is_none())
        .collect();
    let _ = writeln!(
        md,
        "Goal met for {} of {} items run{}{}.\n",
        done.iter()
            .filter(|r| r.outcome != Outcome::NotScaled)
            .count()
            - short.len(),
        done.iter()
            .filter(|r| r.outcome != Outcome::NotScaled)
            .count(),
        if short.is_empty() {
            String::new()
        } else {
            format!("; not shown for: {}", short.join(", "))
        },
        if missing.is_empty() {
            String::new()
        } else {
            format!(
                "; {} item(s) not run yet (their shard files are missing, below)",
                missing.len()
            )
        }
    );
    let _ = writeln!(
        md,
        "| factor | keys | reality.toml range | largest multiple passing | range at that multiple | success at it (95% CI) | first failing multiple: success | what limits it |\n|---|---|---|---|---|---|---|---|"
    );
    for (i, slot) in results.iter().enumerate() {
        let name = run.items.get(i).map_or("?", String::as_str);
        let Some(r) = slot else {
            let s = (0..run.shard_count)
                .find(|&s| {
                    shard_items(
                        run.items.len(),
                        Shard {
                            index: s,
                            count: run.shard_count,
                        },
                    )
                    .contains(&i)
                })
                .unwrap_or(0);
            let _ = writeln!(
                md,
                "| {name} | | | not run: shard {s}/{} missing | | | | |",
                run.shard_count
            );
            continue;
        };
        let all = r.name == ALL_TOGETHER;
        let keys = if all {
            "every factor above that reality.toml sets".into()
        } else {
            r.reality
                .iter()
                .map(|k| format!("`{}`", k.key))
                .collect::<Vec<_>>()
                .join("<br>")
        };
        let reality_range = if all {
            "–".into()
        } else {
            r.reality
                .iter()
                .map(range_text)
                .collect::<Vec<_>>()
                .join("<br>")
        };
        let at_pass = r.outcome.largest_passing().and_then(|k| step_at(r, k));
        let at_fail = r.outcome.first_failing().and_then(|k| step_at(r, k));
        let _ = writeln!(
            md,
            "| {} | {keys} | {reality_range} | {} | {} | {} | {} | {} |",
            r.name,
            largest_text(r),
            match at_pass {
                Some(_) if all => "every range at that multiple".into(),
                Some(s) => s
                    .ranges
                    .iter()
                    .map(range_text)
                    .collect::<Vec<_>>()
                    .join("<br>"),
                None => "–".into(),
            },
            at_pass.map_or("–".into(), success_text),
            at_fail.map_or("–".into(), |s| format!(
                "{}: {}",
                mult(s.k),
                success_text(s)
            )),
            limit_text(r, run),
        );
    }
    // The figure.
    let _ = writeln!(
        md,
        "\n![Largest multiple of reality.toml's range passing >= 95% per factor](envelope.svg)\n\n\
         Largest multiple of reality.toml's range at which >= {PASS_PERCENT}% of the trials \
         succeed, per factor and all together; the whisker spans the bracket (largest \
         passing to first failing multiple); dashed: the goals ({GOAL_EACH}x per factor, \
         {GOAL_ALL}x all together). A bar at 0 failed at 1x; a bar at {max} passed there.\n",
        max = num(run.max_multiple)
    );
    // Every step.
    let _ = writeln!(
        md,
        "### The bisection's steps\n\n\
         | factor | k | trials | successes | rate | 95% CI | timing error p50 / p95 (ms) | clamped | command (in this folder) |\n|---|---|---|---|---|---|---|---|---|"
    );
    let ms = |v: Option<f64>| v.map_or("–".into(), |x| format!("{x:.1}"));
    for r in results.iter().flatten() {
        for s in &r.steps {
            let _ = writeln!(
                md,
                "| {} | {} | {} | {} | {:.1}% | {:.1}..{:.1}% | {} / {} | {} | `{}` |",
                r.name,
                mult(s.k),
                s.trials,
                s.successes,
                100.0 * s.rate(),
                100.0 * s.ci95[0],
                100.0 * s.ci95[1],
                ms(s.timing_error_p50_ms),
                ms(s.timing_error_p95_ms),
                s.clamped
                    .iter()
                    .map(|c| format!("`{c}`"))
                    .collect::<Vec<_>>()
                    .join(", "),
                s.command
            );
        }
    }
    // The factor table.
    let world = reality.world.clone().unwrap_or_default();
    let _ = writeln!(
        md,
        "\n### The factors: benign values and scalings\n\n\
         The table is `factors()` in `server/src/cmd/eval_envelope.rs` (its doc comment says \
         why each benign value and scaling).\n\n\
         | factor | key | benign value b | scaling | bounds (validate()) | clamped past |\n|---|---|---|---|---|---|"
    );
    for f in &table {
        for k in &f.keys {
            let onset = k
                .get(&world)
                .and_then(|r| k.clamp_onset(r, k.benign_of(reality)));
            let _ = writeln!(
                md,
                "| {} | `{}` | {} | {} | [{}, {}] | {} |",
                f.name,
                k.path,
                k.benign_text(reality),
                match k.scaling {
                    Scaling::Spread => "[b + k(lo - b), b + k(hi - b)]",
                    Scaling::Inverse => "v / k (harsher is lower: 1/v times k; 0 stays 0)",
                },
                num(k.bounds.0),
                num(k.bounds.1),
                onset.map_or("–".into(), mult)
            );
        }
    }
    let _ = writeln!(md, "\nNot factors (no world effect to scale):\n");
    for (key, why) in NOT_FACTORS {
        let _ = writeln!(md, "- `{key}`: {why}");
    }
    // Reproduce.
    let _ = writeln!(
        md,
        "\n### Reproduce\n\nThe shards that wrote this report (each its \
         `envelope/shard-I-of-{}.json`); `isochron eval --envelope --combine --out OUT` \
         rewrites the report from the shard files:\n",
        run.shard_count
    );
    for f in files {
        let _ = writeln!(md, "    {}", f.command);
    }
    if !missing.is_empty() {
        let shards: Vec<usize> = (0..run.shard_count)
            .filter(|&s| files.iter().all(|f| f.shard_index != s))
            .collect();
        let _ = writeln!(
            md,
            "\nMissing shards (their items are not in this report yet): {}",
            shards
                .iter()
                .map(|s| format!("{s}/{}", run.shard_count))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    md
}

fn figure(run: &RunKey, results: &[Option<ItemResult>]) -> anyhow::Result<String> {
    let bars: Vec<Bar> = results
        .iter()
        .flatten()
        .filter(|r| r.outcome != Outcome::NotScaled)
        .map(|r| {
            let (value, interval, note) = match r.outcome {
                Outcome::FailsAtOne => (0.0, None, "<1x".to_owned()),
                Outcome::PassesAtMax { max } => (max, None, format!(">={}x", num(max))),
                Outcome::Bracket { pass, fail } => (
                    pass,
                    Some((pass, fail)),
                    format!("{}-{}x", num(pass), num(fail)),
                ),
                Outcome::NotScaled => (0.0, None, String::new()),
            };
            Bar {
                label: r.name.replace(' ', "\n"),
                value,
                interval,
                note,
            }
        })
        .collect();
    let goal_each = format!("goal {}x", num(GOAL_EACH));
    let goal_all = format!("all: {}x", num(GOAL_ALL));
    plot::bar_chart_with_lines(
        &format!(
            "Robustness envelope: largest multiple of reality.toml's range with >= {PASS_PERCENT}% success"
        ),
        "world factor",
        "multiple of reality.toml's range",
        &bars,
        (0.0, run.max_multiple),
        &[
            (GOAL_EACH, goal_each.as_str()),
            (GOAL_ALL, goal_all.as_str()),
        ],
    )
}

#[cfg(test)]
mod tests;
