use super::*;
use crate::control::Controller;
use crate::fri::client::{FriClient, FriClientParams};
use crate::params::Scenario;
use crate::sim::kuka::{FriSimParams, SimController};

const PERIOD_NS: u64 = 5_000_000;

struct Rig {
    sim: SimController,
    client: FriClient,
    ctl: FriLoopStep,
    t_ns: u64,
}

impl Rig {
    fn new() -> Self {
        let mut s = Scenario::default();
        s.robot.fri_period_ms = 5;
        s.camera.vision = crate::params::VisionMode::Model;
        let controller = Controller::new(&s.beliefs(), 0.005).unwrap();
        let mut p = FriSimParams::from_robot(&s.robot);
        p.seed = 7;
        let mut sim = SimController::new(p, 0).unwrap();
        sim.request_commanding();
        Self {
            sim,
            client: FriClient::new(FriClientParams::default()).unwrap(),
            ctl: FriLoopStep::new(controller),
            t_ns: 0,
        }
    }

    /// One period; returns whether the controller's message was answered.
    fn tick(&mut self) -> bool {
        self.t_ns += PERIOD_NS;
        let now = self.t_ns;
        self.client.poll(now, &mut self.ctl);
        let Some(bytes) = self.sim.tick(now) else {
            return false;
        };
        match self.client.on_datagram(bytes, now, &mut self.ctl) {
            Some(reply) => {
                self.sim.on_reply(reply, now + 20_000);
                true
            }
            None => false,
        }
    }

    fn until(&mut self, max_ticks: usize, mut done: impl FnMut(&Self) -> bool) {
        for _ in 0..max_ticks {
            if done(self) {
                return;
            }
            self.tick();
        }
        assert!(done(self), "condition not reached in {max_ticks} periods");
    }

    fn commanding(&mut self) {
        self.until(400, |r| r.sim.state() == SessionState::CommandingActive);
        // One more period so the client has seen COMMANDING_ACTIVE.
        self.tick();
    }

    fn arm(&mut self) {
        let s = {
            let mut s = Scenario::default();
            s.camera.vision = crate::params::VisionMode::Model;
            s
        };
        let plan = Controller::plan(&s.beliefs(), 0.5).unwrap();
        let t = self.ctl.last_t_s();
        self.ctl.controller_mut().arm(t, &plan).unwrap();
        self.until(4000, |r| r.ctl.controller().state() == TrialState::Armed);
    }
}

#[test]
fn the_session_runs_the_controller_and_its_commands_move_the_joints() {
    let mut r = Rig::new();
    r.commanding();
    let q0 = *r.sim.joint_rad();
    r.arm();
    // The arm went home in the motion's posture through the session.
    let home = r.ctl.controller().arm_plan().unwrap().posture.q_home;
    let q = r.sim.joint_rad();
    let moved = (0..7).map(|j| (q[j] - q0[j]).abs()).fold(0.0, f64::max);
    assert!(moved > 0.05, "the joints did not move: {moved}");
    let off = (0..7).map(|j| (q[j] - home[j]).abs()).fold(0.0, f64::max);
    assert!(off < 0.2f64.to_radians(), "not at home: {off} rad");
    let c = r.ctl.controller().counters();
    assert!(c.steps > 100);
    assert_eq!(c.limit_violations(), 0);
    let st = r.client.stats().snapshot();
    assert!(st.commands > 100, "{st:?}");
    assert_eq!(st.guard_step + st.guard_position + st.guard_non_finite, 0);
    assert_eq!(
        r.sim
            .stats()
            .violations
            .load(std::sync::atomic::Ordering::Relaxed),
        0
    );
    assert_eq!(r.ctl.stops(), 0);
    // The controller's last command is what the client sent.
    let sent = r.client.stats().commanded_rad.load();
    let last: [f64; 7] = (*r.ctl.controller().q_command()).into();
    assert_eq!(sent, last);
}

#[test]
fn a_session_that_leaves_commanding_aborts_the_running_trial() {
    let mut r = Rig::new();
    r.commanding();
    let plan = Controller::plan(&Scenario::default().beliefs(), 0.5).unwrap();
    let t = r.ctl.last_t_s();
    r.ctl.controller_mut().arm(t, &plan).unwrap();
    for _ in 0..20 {
        r.tick();
    }
    assert_eq!(r.ctl.controller().state(), TrialState::Arming);
    // The controller stops getting answers: the quality drops and the
    // controller leaves commanding.
    for _ in 0..400 {
        r.t_ns += PERIOD_NS;
        let now = r.t_ns;
        if let Some(b) = r.sim.tick(now) {
            let _ = r.client.on_datagram(b, now, &mut r.ctl);
        }
        if r.ctl.last_stop().is_some() {
            break;
        }
    }
    assert!(
        matches!(r.ctl.last_stop(), Some(StopReason::LeftCommanding(_))),
        "{:?}",
        r.ctl.last_stop()
    );
    assert_eq!(r.ctl.controller().state(), TrialState::Aborted);
    assert_eq!(
        r.ctl.controller().abort_reason(),
        Some(AbortReason::FriLost)
    );
    assert_eq!(r.ctl.trial_aborts(), 1);
}

#[test]
fn a_silent_controller_aborts_and_an_idle_controller_is_not_a_trial_abort() {
    let mut r = Rig::new();
    r.commanding();
    let plan = Controller::plan(&Scenario::default().beliefs(), 0.5).unwrap();
    let t = r.ctl.last_t_s();
    r.ctl.controller_mut().arm(t, &plan).unwrap();
    r.tick();
    // Silence: no datagram for two periods.
    r.t_ns += 3 * PERIOD_NS;
    assert!(r.client.poll(r.t_ns, &mut r.ctl));
    assert_eq!(r.ctl.last_stop(), Some(StopReason::ControllerSilent));
    assert_eq!(r.ctl.controller().state(), TrialState::Aborted);
    assert_eq!(
        r.ctl.controller().abort_reason(),
        Some(AbortReason::FriLost)
    );
    // Back to idle; closing the session now stops, but aborts no trial.
    let t = r.ctl.last_t_s();
    r.ctl.controller_mut().reset(t).unwrap();
    r.ctl.clear_stop();
    r.tick(); // the controller is back: the client sees COMMANDING_ACTIVE again
    r.sim.request_close();
    r.until(10, |r| r.ctl.last_stop().is_some());
    assert_eq!(r.ctl.last_stop(), Some(StopReason::SessionClosed));
    assert_eq!(r.ctl.controller().state(), TrialState::Idle);
    assert_eq!(r.ctl.trial_aborts(), 1);
    assert_eq!(r.ctl.stops(), 2);
}
