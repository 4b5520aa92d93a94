// Generated from the Rust types by ts-rs (server/src/typescript.rs): do not edit.
// Regenerate with `make types`; `cargo test -p server --lib typescript` fails while stale.
// A number that may be NaN in Rust is `null` here (serde_json writes NaN as null).

export type TrialState = "idle" | "arming" | "armed" | "released" | "tracking" | "intercepting" | "holding" | "done" | "aborted";

export type MeasurementView = { 
/**
 * False until a measurement arrived (then the other fields are meaningless).
 */
valid: boolean, 
/**
 * Capture time, control clock, seconds.
 */
t_s: number, 
/**
 * Lateral ball position x = l sin(phi), metres (+y of the robot base).
 */
x_m: number, };

export type HorizonPoint = { 
/**
 * Time, control clock, seconds.
 */
t_s: number, 
/**
 * Predicted lateral position, metres.
 */
x_m: number, 
/**
 * One standard deviation of `x_m`, metres.
 */
sigma_m: number, };

export type PendulumView = { 
/**
 * Last measurement.
 */
measured: MeasurementView, 
/**
 * Where the pendulum hangs now: the robot base axis to the ball at
 * rest, horizontal, metres (the simulated lab's stand, or a real lab's
 * fixed distance; null: each trial's own, not known between trials).
 */
rest_distance_m: number | null, 
/**
 * Estimated angle from the vertical, radians (positive towards +y).
 */
phi_rad: number, 
/**
 * Estimated angular velocity, rad/s.
 */
dphi_radps: number, 
/**
 * One standard deviation of `phi_rad`.
 */
sigma_phi_rad: number | null, 
/**
 * One standard deviation of `dphi_radps`.
 */
sigma_dphi_radps: number | null, 
/**
 * Estimated lateral position l sin(phi), metres.
 */
x_m: number, 
/**
 * One standard deviation of `x_m`, metres.
 */
sigma_x_m: number | null, 
/**
 * Estimated ball centre in the robot base frame, metres.
 */
ball_m: (number | null)[], 
/**
 * True ball centre (simulated lab only; NaN, shown as null, otherwise).
 */
truth_ball_m: (number | null)[], 
/**
 * Predicted time the ball next crosses the intercept point, seconds (NaN if none).
 */
crossing_t_s: number | null, 
/**
 * One standard deviation of `crossing_t_s`, seconds.
 */
crossing_sigma_s: number | null, 
/**
 * The predicted horizon; only the first `horizon_len` points are meaningful.
 */
horizon: Array<HorizonPoint>, };

export type HopfView = { 
/**
 * True while the timing system drives a motion.
 */
active: boolean, 
/**
 * Oscillator state a.
 */
a: number, 
/**
 * Oscillator state b.
 */
b: number, 
/**
 * Activation of the initial-posture neuron.
 */
u_init: number, 
/**
 * Activation of the Hopf (moving) neuron.
 */
u_hopf: number, 
/**
 * Activation of the final-posture neuron.
 */
u_final: number, };

export type PathView = { 
/**
 * Planned tool speed along the path now, m/s.
 */
speed_planned_mps: number, 
/**
 * Executed (measured) tool speed along the path now, m/s.
 */
speed_executed_mps: number, 
/**
 * Planned progress along the path, 0..1.
 */
progress_planned: number, 
/**
 * Executed progress along the path, 0..1.
 */
progress_executed: number, 
/**
 * Path length, metres.
 */
length_m: number, 
/**
 * Motion start, control clock, seconds (NaN before a motion).
 */
start_t_s: number | null, 
/**
 * Planned arrival at the intercept point, control clock, seconds (NaN before a motion).
 */
arrival_t_s: number | null, 
/**
 * Planned movement time, seconds.
 */
movement_time_s: number | null, 
/**
 * Intercept point, robot base frame, metres.
 */
intercept_m: (number | null)[], };

export type RobotView = { 
/**
 * Measured joint angles, radians.
 */
q_rad: [number, number, number, number, number, number, number], 
/**
 * Commanded joint angles, radians.
 */
q_cmd_rad: [number, number, number, number, number, number, number], 
/**
 * Symmetric position limits |q| <= limit, radians.
 */
q_limit_rad: [number, number, number, number, number, number, number], 
/**
 * Tool point, robot base frame, metres.
 */
tool_m: (number | null)[], 
/**
 * Estimated command-to-motion latency of the robot, milliseconds.
 */
actuation_latency_ms: number | null, 
/**
 * FRI's external joint torques of the latest message, N m (null: the
 * robot sends none).
 */
tau_ext_nm: (number | null)[], };

export type FriSessionState = "disconnected" | "monitoring_wait" | "monitoring_ready" | "commanding_wait" | "commanding_active" | "idle";

export type FriQuality = "unknown" | "poor" | "fair" | "good" | "excellent";

export type FriView = { 
/**
 * Session state.
 */
session: FriSessionState, 
/**
 * Connection quality.
 */
quality: FriQuality, 
/**
 * Controller send period, milliseconds.
 */
period_ms: number | null, 
/**
 * Message receive -> reply sent of the last cycle, microseconds.
 */
reply_latency_us: number | null, 
/**
 * Replies sent after their deadline, since start.
 */
late_replies: number, 
/**
 * Controller messages not answered, since start.
 */
missed_cycles: number, 
/**
 * Times the controller went silent (the client's safe reaction ran), since start.
 */
silences: number, 
/**
 * Times the controller left commanding (abort, quality drop), since start.
 */
commanding_lost: number, };

export type MagnetState = "unknown" | "on" | "off" | "fault";

export type LoopTiming = { 
/**
 * Duration of the last control step, microseconds.
 */
step_us: number, 
/**
 * Longest control step since start, microseconds.
 */
step_max_us: number, 
/**
 * Mean period between steps over the last window, microseconds.
 */
period_mean_us: number, 
/**
 * Longest period between steps over the last window, microseconds.
 */
period_max_us: number, 
/**
 * Steps that missed their deadline, since start.
 */
deadline_misses: number, };

export type Counters = { 
/**
 * Control steps run.
 */
steps: number, 
/**
 * Camera measurements folded into the filter.
 */
measurements: number, 
/**
 * Camera measurements lost because their ring was full.
 */
measurement_overflows: number, 
/**
 * Commands the guard limited or refused.
 */
guard_interventions: number, 
/**
 * Joint limit violations detected.
 */
limit_violations: number, 
/**
 * Trials finished (with a result or aborted).
 */
trials: number, 
/**
 * Trials stopped because no operator heartbeat came within the dead-man time.
 */
operator_timeouts: number, };

export type CameraView = { 
/**
 * Width of the camera image the pixel coordinates refer to.
 */
width_px: number, 
/**
 * Height of the camera image the pixel coordinates refer to.
 */
height_px: number, 
/**
 * Number of the latest processed frame.
 */
frame: number, 
/**
 * Its capture time, control clock, seconds.
 */
t_s: number | null, 
/**
 * Whether the detector found the ball in it.
 */
found: boolean, 
/**
 * The camera stopped delivering frames (none for over a second; a real
 * camera unplugged or its stream broken): trials are refused until it
 * delivers again.
 */
lost: boolean, 
/**
 * Detections dropped so far as inconsistent with the track and shape
 * (a ball-like blob where the tracked ball cannot be).
 */
rejected: number, 
/**
 * Ball centre, image column, pixels (pixel centres at integers).
 */
x_px: number | null, 
/**
 * Ball centre, image row, pixels.
 */
y_px: number | null, 
/**
 * Apparent ball radius, pixels.
 */
r_px: number | null, 
/**
 * Focal length along columns, pixels.
 */
fx_px: number, 
/**
 * Focal length along rows, pixels.
 */
fy_px: number, 
/**
 * Principal point, column, pixels.
 */
cx_px: number, 
/**
 * Principal point, row, pixels.
 */
cy_px: number, 
/**
 * Radial distortion, r^2 term.
 */
k1: number, 
/**
 * Radial distortion, r^4 term.
 */
k2: number, 
/**
 * The ball's rest position (the intercept point), camera frame, metres.
 */
rest_c_m: (number | null)[], 
/**
 * The lateral axis (robot base +y), camera frame, unit.
 */
lateral_c: (number | null)[], 
/**
 * Up (robot base +z), camera frame, unit.
 */
up_c: (number | null)[], };

export type AbortKind = "stop" | "disarmed" | "camera_lost" | "fri_lost" | "magnet_fault" | "operator_lost" | "infeasible" | "limit_violation" | "timeout" | "internal" | "service_restarted";

export type AbortView = { 
/**
 * The trial aborted (0: none since the lab started, or a new trial runs).
 */
trial_id: number, 
/**
 * Why (`null` while no trial was aborted).
 */
reason: AbortKind | null, 
/**
 * The reason as a sentence (empty while none).
 */
message: string, 
/**
 * What the lab saw, when more is known (e.g. how the FRI link was lost; else empty).
 */
detail: string, };

export type Refusal = "busy" | "not_armed" | "motion_running" | "checks_failed" | "infeasible" | "device_unavailable" | "robot_not_commanding" | "invalid";

export type Readiness = { 
/**
 * A trial posted now would start.
 */
trial: boolean, 
/**
 * Why not (`null` when it would): `busy` (a trial runs, is being planned
 * or is finishing its record), `robot_not_commanding`, `device_unavailable`.
 */
reason: Refusal | null, 
/**
 * The reason as a sentence (empty when ready).
 */
message: string, };

export type Snapshot = { 
/**
 * Control clock, seconds since the lab started.
 */
t_s: number, 
/**
 * Control step number (increases by one per step).
 */
seq: number, 
/**
 * The trial this step belongs to (0: none).
 */
trial_id: number, 
/**
 * Trial state.
 */
trial_state: TrialState, 
/**
 * Pendulum: measured, estimated, predicted.
 */
pendulum: PendulumView, 
/**
 * Hopf oscillator and neurons.
 */
hopf: HopfView, 
/**
 * Path and speed profile.
 */
path: PathView, 
/**
 * Joints and tool.
 */
robot: RobotView, 
/**
 * FRI link.
 */
fri: FriView, 
/**
 * Electromagnet.
 */
magnet: MagnetState, 
/**
 * Loop timing.
 */
timing: LoopTiming, 
/**
 * Counters.
 */
counters: Counters, 
/**
 * The camera's latest detection and calibration, for the overlays.
 */
camera: CameraView, 
/**
 * Why the last trial was aborted (kept until the next trial starts).
 */
abort: AbortView, 
/**
 * Whether the control loop would take a trial now, and if not, why.
 */
ready: Readiness, };

export type PredictedRebound = { 
/**
 * The believed restitution of ball and tool (`pendulum.contact_restitution`).
 */
restitution: number, 
/**
 * The planned tool speed at contact along the return (the strike
 * speed times the cosine of its elevation), m/s.
 */
tool_return_speed_mps: number, 
/**
 * The ball's speed at the committed pass as the filter predicted it
 * at the commit, m/s.
 */
ball_in_speed_mps: number, 
/**
 * The predicted outgoing speed along the return, m/s.
 */
ball_speed_mps: number, 
/**
 * The pendulum's angular frequency used, `sqrt(k)` (the filter's `k`
 * at the commit, else the believed `g / l`), rad/s.
 */
omega_radps: number, 
/**
 * The damping `alpha` used (the filter's, else the believed), 1/s.
 */
damping_per_s: number, 
/**
 * The rebound's first swing away from the contact point: its lateral
 * amplitude (damped to its turn), m.
 */
amplitude_m: number, 
/**
 * From the contact to that turn, s.
 */
turn_s: number, };

export type MeasuredStrike = { 
/**
 * The planned tool speed at contact (`task.strike_speed_mps`), m/s.
 */
planned_tool_speed_mps: number, 
/**
 * The measured tool point's speed at the contact's onset, m/s (absent
 * without a contact).
 */
tool_speed_mps: number | null, 
/**
 * The target outgoing ball speed, m/s (as the physical judge's).
 */
target_ball_speed_mps: number, 
/**
 * The ball's measured outgoing speed at the contact's onset (the
 * rebound's fitted swing), m/s; absent without a contact or with too
 * few detections after it.
 */
ball_speed_mps: number | null, 
/**
 * Its standard deviation (the detections' noise), m/s.
 */
ball_speed_std_mps: number | null, 
/**
 * `(ball_speed - target) / target`.
 */
speed_error: number | null, 
/**
 * Whether the ball left along the return (against its pass).
 */
returned: boolean, 
/**
 * Detections the rebound was fitted to.
 */
rebound_used: number, 
/**
 * Contact seen and `|timing error|` within the tolerance.
 */
in_time: boolean, 
/**
 * The ball returned and `|speed_error| <=` [`STRIKE_SPEED_TOLERANCE`].
 */
speed_ok: boolean, 
/**
 * The controller's predicted rebound at its commit (from its beliefs:
 * the believed restitution, the filter's pass speed and frequency),
 * beside the seen one (`ball_speed_mps`); absent when none was made
 * (and in records from before it was kept).
 */
predicted?: PredictedRebound, };

export type MeasuredJudgement = { 
/**
 * The ball's measured pass through the intercept point (the filter's
 * rest point), control clock, s.
 */
pass_t_s: number | null, 
/**
 * The measured arrival: the measured tool settled within the settling
 * radius of its final point, control clock, s.
 */
arrival_t_s: number | null, 
/**
 * `arrival - pass`, ms (negative: early).
 */
timing_error_ms: number | null, 
/**
 * Its standard deviation (the measured pass's: the camera's noise and,
 * anchored on a contact, the torque samples' period), ms.
 */
timing_std_ms: number | null, 
/**
 * Whether the external joint torques showed a contact in the pass's window.
 */
contact: boolean, 
/**
 * When, control clock, s.
 */
contact_t_s: number | null, 
/**
 * Contact seen and `|timing error|` within the tolerance.
 */
success: boolean, 
/**
 * Whether the external joint torques carried a signal
 * ([`torque_signal`]); without one no contact can be seen and the
 * judge does not decide (records written before this field: `true`).
 */
torque_signal: boolean, 
/**
 * The longest pause of the robot's messages (its measured joints or
 * external torques) around the pass or the arrival, when it was longer
 * than [`ROBOT_GAP_LIMIT_PERIODS`] torque periods: the arrival and the
 * contact cannot be seen through it, so the judge does not decide
 * (a starved machine's FRI silence), ms. Absent when there was none.
 */
robot_gap_ms?: number, 
/**
 * How late the camera's stamps (after the controller's offset) showed
 * the pass against the contact's, ms: the camera pass minus the pass
 * anchored on the contact (the robot's clock). What the controller's
 * camera offset still missed, whatever the magnet's release delay
 * (`control.camera_offset_from_contact`). Absent without an anchored pass.
 */
camera_clock_error_ms?: number, 
/**
 * Its standard deviation (both passes'), ms.
 */
camera_clock_error_std_ms?: number, 
/**
 * A strike's figures (`task.mode = "strike"`, issue #38); then
 * `arrival_t_s` is the measured tool point's crossing of the intercept
 * lateral along the stroke, `pass_t_s` the ball's pass from the
 * contact's onset, and `success` needs the outgoing speed too. Absent
 * for a stop.
 */
strike?: MeasuredStrike, };

export type JudgedBy = "truth" | "physical" | "measured";

export type TrialResult = { 
/**
 * Position and timing within tolerance, no limit violation or abort.
 */
success: boolean, 
/**
 * |arrival - t*|, milliseconds.
 */
timing_error_ms: number, 
/**
 * Tool point to ball centre at t*, metres.
 */
position_error_m: number, 
/**
 * Arrival - start of the fitted profile, seconds.
 */
movement_time_s: number, 
/**
 * Robot base axis -> intercept point, horizontal, metres.
 */
distance_m: number, 
/**
 * When the ball centre passed the intercept point, control clock, seconds.
 */
t_star_s: number, 
/**
 * Fitted arrival time of the tool, control clock, seconds.
 */
arrival_t_s: number, 
/**
 * Filter's predicted crossing time minus the truth, at motion start, milliseconds.
 */
prediction_time_error_ms: number, 
/**
 * Joint limit violations during the trial.
 */
limit_violations: number, 
/**
 * Why the outcome could not be judged (`null`: judged; then `success`
 * is the verdict). A real lab, or a trial with no motion to judge.
 */
not_judged: string | null, 
/**
 * The measured judge's verdict (camera, measured joints, external
 * torques; no ground truth), when there was a committed motion. The
 * real lab's judgement; beside the true one in the simulated lab.
 */
measured: MeasuredJudgement | null, 
/**
 * Which judge's verdict `success` and the figures above are (`null`:
 * not judged, `not_judged` says why).
 */
judged_by: JudgedBy | null, };

export type Event = { "kind": "state_changed", 
/**
 * Before.
 */
from: TrialState, 
/**
 * After.
 */
to: TrialState, } | { "kind": "aborted", 
/**
 * Why.
 */
reason: AbortKind, 
/**
 * What the lab saw, when more is known (else empty), e.g. how the
 * FRI link was lost.
 */
detail: string, } | { "kind": "trial_finished", 
/**
 * The result.
 */
result: TrialResult, };

export type EventRecord = { 
/**
 * Control clock, seconds.
 */
t_s: number, 
/**
 * The trial concerned (0: none).
 */
trial_id: number, 
/**
 * What happened.
 */
event: Event, };

export type BridgeCounters = { 
/**
 * Snapshots published by the control thread.
 */
published: number, 
/**
 * Snapshots the recorder lost (telemetry ring full).
 */
telemetry_overflows: number, 
/**
 * Events lost (event ring full).
 */
event_overflows: number, 
/**
 * Commands refused because the command ring was full.
 */
command_overflows: number, 
/**
 * Acknowledgements lost (ack ring full).
 */
ack_overflows: number, 
/**
 * Camera frames dropped (frame ring full).
 */
frame_overflows: number, 
/**
 * Emergency stops requested.
 */
stop_requests: number, 
/**
 * Operator heartbeats received.
 */
heartbeats: number, };

export type StreamCounters = { 
/**
 * Clients connected now.
 */
clients: number, 
/**
 * State messages produced.
 */
state_messages: number, 
/**
 * Messages slow clients skipped.
 */
skipped: number, 
/**
 * Clients dropped because they stalled.
 */
dropped_clients: number, 
/**
 * Camera frames forwarded.
 */
frames: number, };

export type StateMessage = { 
/**
 * Always `state`.
 */
type: "state", 
/**
 * Bridge hand-off counters.
 */
bridge: BridgeCounters, 
/**
 * WebSocket stream counters.
 */
stream: StreamCounters, 
/**
 * Control clock, seconds since the lab started.
 */
t_s: number, 
/**
 * Control step number (increases by one per step).
 */
seq: number, 
/**
 * The trial this step belongs to (0: none).
 */
trial_id: number, 
/**
 * Trial state.
 */
trial_state: TrialState, 
/**
 * Pendulum: measured, estimated, predicted.
 */
pendulum: PendulumView, 
/**
 * Hopf oscillator and neurons.
 */
hopf: HopfView, 
/**
 * Path and speed profile.
 */
path: PathView, 
/**
 * Joints and tool.
 */
robot: RobotView, 
/**
 * FRI link.
 */
fri: FriView, 
/**
 * Electromagnet.
 */
magnet: MagnetState, 
/**
 * Loop timing.
 */
timing: LoopTiming, 
/**
 * Counters.
 */
counters: Counters, 
/**
 * The camera's latest detection and calibration, for the overlays.
 */
camera: CameraView, 
/**
 * Why the last trial was aborted (kept until the next trial starts).
 */
abort: AbortView, 
/**
 * Whether the control loop would take a trial now, and if not, why.
 */
ready: Readiness, };

export type EventMessage = { 
/**
 * Always `event`.
 */
type: "event", 
/**
 * A sentence for people, for aborts.
 */
message?: string, 
/**
 * Control clock, seconds.
 */
t_s: number, 
/**
 * The trial concerned (0: none).
 */
trial_id: number, 
/**
 * What happened.
 */
event: Event, };

export type Hello = { 
/**
 * Always `hello`.
 */
type: "hello", 
/**
 * The latest state's time, control clock, seconds.
 */
t_s: number, 
/**
 * The service's version.
 */
version: string, 
/**
 * State messages per second.
 */
state_hz: number, 
/**
 * Whether commands need a bearer token.
 */
token_required: boolean, };

export type TrialRecord = { 
/**
 * Trial id (> 0).
 */
id: number, 
/**
 * `running`, `done` or `aborted` (a trial the service stopped in is
 * closed at its next start as `aborted`, `abort_reason` `service_restarted`).
 */
status: string, 
/**
 * Why it ended so, a sentence (null while running): the abort's reason
 * and what the lab saw, `not judged: ...` for a trial whose outcome
 * could not be judged (then `success` is null), or the judge's verdict.
 */
reason: string | null, 
/**
 * Unix time the trial was started, seconds.
 */
started_unix_s: number, 
/**
 * Unix time it ended, seconds.
 */
finished_unix_s: number | null, 
/**
 * Hit within the tolerances (`done` and judged; null when not judged).
 */
success: boolean | null, 
/**
 * |arrival - t*|, milliseconds.
 */
timing_error_ms: number | null, 
/**
 * Tool point to ball centre at t*, metres.
 */
position_error_m: number | null, 
/**
 * Fitted movement time, seconds (a real lab's: fitted on the measured
 * tool point, also for a trial that was not judged).
 */
movement_time_s: number | null, 
/**
 * Distance of the intercept point, metres.
 */
distance_m: number | null, 
/**
 * Predicted minus true crossing time at motion start, milliseconds.
 */
prediction_time_error_ms: number | null, 
/**
 * Joint limit violations.
 */
limit_violations: number | null, 
/**
 * Why it was aborted (snake_case reason).
 */
abort_reason: string | null, 
/**
 * Rows in the recording.
 */
samples: number, 
/**
 * The scenario that ran (null for trials recorded before it was stored).
 */
scenario: string | null, 
/**
 * The software revision that ran it.
 */
revision: string | null, 
/**
 * The measured judge's verdict (camera detections, measured joints,
 * FRI's external torques; never the ground truth), when the trial had a
 * committed motion: the real lab's judgement (then `success` is its
 * verdict), beside the true one in a simulated lab.
 */
measured: MeasuredJudgement | null, 
/**
 * Which judge gave `success` and the figures above: `truth` (a truthful
 * simulated world's ground truth), `physical` (the reality lab's true
 * world) or `measured` (the measured judge: a real lab; then
 * `timing_error_ms` is `|measured.timing_error_ms|` and
 * `position_error_m` null). Null while running, when aborted or not
 * judged, and for trials recorded before it was stored.
 */
judged_by: JudgedBy | null, };

export type Distances = number | Array<number>;

export type TaskMode = "stop" | "strike";

export type RunRequest = { 
/**
 * How many trials (1..=10000).
 */
n: number, 
/**
 * The trials' distances, metres: one for all, or a list the trials take
 * in turn (trial i: `distance_m[i % len]`). Absent: drawn as usual.
 */
distance_m: Distances | null, 
/**
 * Distances spread evenly over `[lo, hi]` metres across the run
 * (trial i: `lo + (hi - lo) i / (n - 1)`); not with `distance_m`.
 */
distance_range_m: [number, number] | null, 
/**
 * Every trial's planned movement time, seconds (else the lab's).
 */
movement_time_s: number | null, 
/**
 * Every trial's release angle magnitude, degrees (else drawn).
 */
release_deg: number | null, 
/**
 * Every trial's task, `stop` or `strike` (else the lab's `task.mode`).
 */
mode: TaskMode | null, 
/**
 * Every strike's tool speed at contact, m/s (else the lab's); only
 * for strikes.
 */
strike_speed_mps: number | null, 
/**
 * Every strike's direction above the swing's horizontal, degrees (else
 * the lab's); only for strikes.
 */
strike_direction_deg: number | null, };

export type RunStatus = { 
/**
 * The run's id.
 */
id: number, 
/**
 * `running`, `done` (all trials ran), `stopped` (by `DELETE`) or
 * `failed` (the lab could not take a trial; `message` says why).
 */
status: string, 
/**
 * Trials asked for.
 */
n: number, 
/**
 * Trials started so far, in order (their records: `/api/trials/{id}`).
 */
trial_ids: number[], 
/**
 * Trials whose records finished.
 */
finished: number, 
/**
 * Finished trials judged (not `not judged`, not aborted without a verdict).
 */
judged: number, 
/**
 * Judged trials that succeeded.
 */
successes: number, 
/**
 * Successes / finished trials (0 when none finished).
 */
success_rate: number, 
/**
 * Wilson 95% interval of the success rate over the finished trials.
 */
success_ci95: [number, number], 
/**
 * |timing error| of the judged trials, median, milliseconds (null: none).
 */
timing_error_ms_p50: number | null, 
/**
 * |timing error| of the judged trials, 95th percentile (linear
 * interpolation, numpy's default), milliseconds (null: none).
 */
timing_error_ms_p95: number | null, 
/**
 * Unix time the run started, seconds.
 */
started_unix_s: number, 
/**
 * Unix time it ended, seconds (null while running).
 */
finished_unix_s: number | null, 
/**
 * Why it failed or stopped (null otherwise).
 */
message: string | null, };

export type DemoStatus = { 
/**
 * The service was started with `--demo`.
 */
enabled: boolean, 
/**
 * `off` (no `--demo`), `running` (a demo trial runs), `waiting` (for the
 * next trial's time, or for another trial to finish), `paused` (the lab
 * cannot run a trial now: `reason` and `message` say why) or
 * `operator_needed` (a real lab: no operator holds the demo enabled).
 */
state: "off" | "running" | "waiting" | "paused" | "operator_needed", 
/**
 * Why it is paused or waiting: `/api/health`'s `not_ready.reason`
 * (`uncalibrated`, `calibrating`, `robot_not_commanding`,
 * `device_unavailable`, `busy`, ...), `operator` (no heartbeat) or
 * `infeasible` (the parameters in force make its motions infeasible).
 */
reason: string | null, 
/**
 * The state as a sentence a visitor reads.
 */
message: string, 
/**
 * The lab's own sentence for why it is paused (an operator's detail;
 * null when not paused).
 */
detail: string | null, 
/**
 * Seconds from one trial's start to the next.
 */
interval_s: number, 
/**
 * Trials run only while an operator holds the demo enabled (a real lab).
 */
operator_required: boolean, 
/**
 * The demo trial running now, or the last one.
 */
trial_id: number | null, 
/**
 * Seconds until the next trial may start (null: not waiting for time).
 */
next_in_s: number | null, 
/**
 * The next trial's distance, metres.
 */
next_distance_m: number | null, 
/**
 * The next trial's planned movement time, seconds.
 */
next_movement_time_s: number | null, 
/**
 * Demo trials whose records finished (across restarts: `demo.json`).
 */
trials: number, 
/**
 * Of them, judged (not aborted, not `not judged`).
 */
judged: number, 
/**
 * Of the judged, precisely timed (the judge's success).
 */
successes: number, 
/**
 * Wilson 95% interval of successes / judged (`[0, 1]` before any).
 */
success_ci95: [number, number], 
/**
 * Demo trials aborted (the lab stopped them: a device, the operator, ...).
 */
aborted: number, };

export type ViewKind = "image" | "series";

export type StepView = { 
/**
 * Fraction of the step done, 0..=1.
 */
progress: number, 
/**
 * What the step is doing, for people ("board view 7 of 15: 54 corners").
 */
message: string, 
/**
 * How to draw `points` and `fit`.
 */
kind: ViewKind, 
/**
 * What was measured.
 */
points: Array<[number, number]>, 
/**
 * What the fit or the model says at the same places (a fitted swing, the
 * reprojected corners); may be empty.
 */
fit: Array<[number, number]>, };

export type StepStatus = { 
/**
 * The step's name (`camera-robot`), as in `POST /api/calibration/{step}`.
 */
name: string, 
/**
 * What it measures.
 */
title: string, 
/**
 * The steps it builds on.
 */
prerequisites: Array<string>, 
/**
 * Of those, the ones the calibration file does not hold yet (the step is
 * refused while any is missing).
 */
missing: Array<string>, 
/**
 * The file holds this step's result.
 */
done: boolean, 
/**
 * The step's record in the file (date, revision, source, result), or null.
 */
record: Record<string, unknown> | null, };

export type Change = { 
/**
 * Dotted key in the step's result (`swing.length_m`).
 */
key: string, 
/**
 * The previous calibration's value.
 */
before: number, 
/**
 * The new value.
 */
after: number, };

export type CalibrationJob = { 
/**
 * The step (null: none has run since the service started).
 */
step: string | null, 
/**
 * `idle`, `running`, `done` or `failed`.
 */
state: string, 
/**
 * Fraction done, 0..=1.
 */
progress: number, 
/**
 * What the step is doing, or why it failed.
 */
message: string, 
/**
 * What the step sees now (its last view), or null.
 */
view: StepView | null, 
/**
 * The result written (done), or null.
 */
result: Record<string, unknown> | null, 
/**
 * Every number of the result that differs from the previous calibration
 * of this step (empty: the first, or nothing changed).
 */
changes: Array<Change>, 
/**
 * The file had no result of this step before (done).
 */
first: boolean, 
/**
 * Job number since the service started (also the simulated world's noise seed).
 */
id: number, };

export type CalibrationStatus = { 
/**
 * The calibration file the lab loads and the steps write.
 */
file: string, 
/**
 * Where the steps run (`simulated world (truthful: the lab's own simulators)`, or
 * the real lab).
 */
source: string, 
/**
 * The steps in the order a lab runs them.
 */
steps: Array<StepStatus>, 
/**
 * The running or last job.
 */
job: CalibrationJob, 
/**
 * Why trials are refused for want of calibration (null: they are not).
 */
trials_refused: string | null, };
