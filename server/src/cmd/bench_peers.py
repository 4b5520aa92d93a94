"""The peers of `isochron bench --peers PYTHON`: filterpy's extended Kalman
filter and the Robotics Toolbox's C++ Levenberg-Marquardt IK, timed on the
same inputs as isochron's filter step and per-cycle IK in the same run.

Input (argv[1], JSON, written by the bench): the pendulum model and filter
settings with the measurement sequences isochron's filter was timed on, and
the flange poses isochron's IK reached along its path with the joints it
found. Output (stdout, one JSON object): per-call times (ns and us), the
libraries' versions, and checks that the peers did the same job (the filter's
final angle against isochron's, every IK solution's pose against its target).

Both peers are used as their documentation shows: filterpy's
ExtendedKalmanFilter with `predict_x` replaced by the model's RK4 step and
`F`, `Q` set before `predict()`, then `update(z, HJacobian, Hx)`; the
toolbox's `ETS.ik_LM` (its C++ solver) with the target as a 4x4 array, the
previous cycle's solution as the seed, and `tol` from the input (its default
1e-6 bounds half the squared error, so it takes a seed 1.3 mm away as solved
without an iteration; 1e-10 reaches the targets to 0.3 um in two iterations,
isochron's analytic solution is exact). Times include the call from Python.
"""

import json
import math
import sys
import time
import warnings

import numpy as np


def quantiles(xs):
    s = sorted(xs)
    n = len(s)

    def q(p):
        # As isochron's quantile_sorted: linear between the ranks around p (n - 1).
        pos = p * (n - 1)
        lo = int(math.floor(pos))
        hi = min(lo + 1, n - 1)
        return s[lo] + (s[hi] - s[lo]) * (pos - lo)

    return {"p50": q(0.5), "p99": q(0.99), "max": s[-1], "count": n}


def pendulum_filter(spec):
    from filterpy.kalman import ExtendedKalmanFilter

    length = spec["length_m"]
    k = spec["gravity_mps2"] / length
    r = spec["measurement_noise_m"] ** 2
    q_acc = spec["accel_psd_rad2ps3"]
    q_damp = spec["damping_psd_per_s3"]
    max_step = spec["max_step_s"]

    def deriv(x):
        # State [phi, phi', alpha, k, b]; phi'' = -k sin(phi) - alpha phi'.
        return np.array([x[1], -x[3] * math.sin(x[0]) - x[2] * x[1], 0.0, 0.0, 0.0])

    def jac(x):
        a = np.zeros((5, 5))
        a[0, 1] = 1.0
        a[1, 0] = -x[3] * math.cos(x[0])
        a[1, 1] = -x[2]
        a[1, 2] = -x[1]
        a[1, 3] = -math.sin(x[0])
        return a

    eye = np.eye(5)

    def rk4(x, h):
        """One RK4 step and its exact Jacobian (chain rule through the stages)."""
        k1 = deriv(x)
        j1 = jac(x)
        x2 = x + 0.5 * h * k1
        d2 = eye + 0.5 * h * j1
        k2 = deriv(x2)
        j2 = jac(x2) @ d2
        x3 = x + 0.5 * h * k2
        d3 = eye + 0.5 * h * j2
        k3 = deriv(x3)
        j3 = jac(x3) @ d3
        x4 = x + h * k3
        d4 = eye + h * j3
        k4 = deriv(x4)
        j4 = jac(x4) @ d4
        xn = x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        f = eye + h / 6.0 * (j1 + 2.0 * j2 + 2.0 * j3 + j4)
        return xn, f

    class PendulumEKF(ExtendedKalmanFilter):
        def predict_x(self, u=0):
            self.x = self.x_pred

    def hjac(x):
        return np.array([[length * math.cos(x[0, 0]), 0.0, 0.0, 0.0, 1.0]])

    def hx(x):
        return np.array([[length * math.sin(x[0, 0]) + x[4, 0]]])

    def step(ekf, dt, z):
        n = max(1, math.ceil(dt / max_step - 1e-9))
        h = dt / n
        x = ekf.x[:, 0].copy()
        f_total = eye
        q_total = np.zeros((5, 5))
        for _ in range(n):
            x, f = rk4(x, h)
            q = np.zeros((5, 5))
            q[0, 0] = q_acc * h**3 / 3.0
            q[0, 1] = q[1, 0] = q_acc * h**2 / 2.0
            q[1, 1] = q_acc * h
            q[2, 2] = q_damp * h
            q_total = f @ q_total @ f.T + q
            f_total = f @ f_total
        ekf.x_pred = x.reshape(5, 1)
        ekf.F = f_total
        ekf.Q = q_total
        ekf.predict()
        ekf.update(np.array([[z]]), hjac, hx)

    times = []
    final_diff = 0.0
    for run in spec["runs"]:
        t, z = run["t"], run["z"]
        ekf = PendulumEKF(dim_x=5, dim_z=1)
        ekf.R = np.array([[r]])
        # Initialised from the first two measurements as isochron's filter is.
        p0 = math.asin(max(-1.0, min(1.0, z[0] / length)))
        p1 = math.asin(max(-1.0, min(1.0, z[1] / length)))
        dt0 = t[1] - t[0]
        ekf.x = np.array([[p1], [(p1 - p0) / dt0], [spec["damping_per_s"]], [k], [0.0]])
        s_phi = math.sqrt(r) / length
        ekf.P = np.diag(
            [s_phi**2, 2.0 * s_phi**2 / dt0**2, spec["damping_std_per_s"] ** 2, 0.0, 0.0]
        )
        for i in range(2, len(t)):
            started = time.perf_counter_ns()
            step(ekf, t[i] - t[i - 1], z[i])
            times.append(time.perf_counter_ns() - started)
        final_diff = max(final_diff, abs(float(ekf.x[0, 0]) - run["phi_final"]))
    return {"step_ns": quantiles(times), "final_angle_max_diff_rad": final_diff}


def toolbox_ik(spec):
    import roboticstoolbox as rtb

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        robot = rtb.Robot.URDF(spec["urdf"])
    ets = robot.ets(end="flange")
    targets = [np.array(t, dtype=float).reshape(4, 4) for t in spec["flange_poses"]]
    q_ours = [np.array(q, dtype=float) for q in spec["q"]]
    # The model check: the toolbox's forward kinematics of isochron's solutions
    # are the targets.
    fk_err = max(float(np.linalg.norm(ets.fkine(q).A[:3, 3] - t[:3, 3])) for q, t in zip(q_ours, targets))
    times = []
    ok = 0
    worst = 0.0
    q = np.array(spec["q_home"], dtype=float)
    for i, tep in enumerate(targets):
        if i % spec["path_len"] == 0:
            q = np.array(spec["q_home"], dtype=float)
        started = time.perf_counter_ns()
        sol = ets.ik_LM(tep, q0=q, tol=spec["tol"])
        times.append((time.perf_counter_ns() - started) * 1e-3)
        q_sol, success = (sol.q, sol.success) if hasattr(sol, "q") else (sol[0], sol[1])
        if success:
            ok += 1
            q = np.asarray(q_sol, dtype=float)
            worst = max(worst, float(np.linalg.norm(ets.fkine(q).A[:3, 3] - tep[:3, 3])))
    return {
        "solve_us": quantiles(times),
        "solved": ok,
        "targets": len(targets),
        "max_position_error_m": worst,
        "fk_max_error_m": fk_err,
    }


def main():
    with open(sys.argv[1]) as f:
        spec = json.load(f)
    import filterpy
    import roboticstoolbox

    out = {
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "filterpy": filterpy.__version__,
        "roboticstoolbox": roboticstoolbox.__version__,
        "ekf": pendulum_filter(spec["ekf"]),
        "ik": toolbox_ik(spec["ik"]),
    }
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
