"""Odometry EKF: wheel speeds + gyro → pose in odom, body velocity and gyro bias (pure stage).

State `[x, y, θ, v, ω, b]`: pose in the odom frame (m, m, rad), body speed (m/s), yaw rate
(rad/s) and the gyro's z bias (rad/s). Each `WheelIncrement` is one cycle:

1. predict over the base-clock `dt` with a constant-velocity unicycle (nonlinear, midpoint
   heading); v, ω and b are random walks driven by acceleration / bias-drift noise, Q built
   here for this dt (filterpy never scales Q for us);
2. wheel update, gated by the Mahalanobis distance (χ², 2 dof): z = [v_wheel, heading_wheel]
   (`wheel_heading: cumulative`, the default) or z = [v_wheel, ω_wheel] (`rate`), all from this
   increment's travel;
3. gyro update, z = [gyro_z] with h = ω + b, gated (χ², 1 dof);
4. the position is put where the increment's travel took it, along the mean of the start and
   the fused end heading: dead reckoning on the fused heading. The speed update alone corrects
   only part of the prediction's along-track error, which builds up wherever frames are
   missing (the speed changed during the longer increment). Travel is taken from every
   increment, gated or not: wheel counts are cumulative, so a wrong reading that got past the
   driver is undone by the next increment, and dropping either of the two would keep its
   error for good. The gate keeps such a pair (and a slip) out of speed and heading; a slip's
   travel stays in the position, as in any wheel odometry.

An increment spanning more than `MAX_UNCONFIRMED_DT_S` (a gap: frames lost or rejected) is no
speed measurement at all; the driver releases it only once two frames in a row agreed on it,
and it moves the pose by its own travel and turn (`_bridge_gap`).

Why a cumulative wheel heading: encoder error is on each *reading* (quantisation, count jitter),
so the difference of two readings has a large error that does not accumulate. Fed to the filter
as a white-noise rate (`rate`), it is almost worthless next to the gyro, the heading then follows
the gyro and any bias error integrates (a 0.001 rad/s bias error is 3.4° a minute). The sum of
the *accepted* wheel heading increments has that error once, not once per frame, so it is the
right measurement of θ; v stays a rate (its error does not integrate into heading). A rejected
increment is replaced in the sum by the filter's predicted turn, so a slip never enters it; if
the raw sum fits again after a run of rejections (a spike that cancelled itself: count jumps up,
then back) the replacement is undone, so glitches cost no heading. Wheel heading is fused once
and wheel ω not at all (no double use).

Observability: wheels and gyro both see the turn, so their disagreement is the bias. Standing
still pins it fastest: the wheels then report no turn at all. Slip (a wheel spins, the body and
the gyro do not) makes the wheel innovation jump by far more than encoder noise and fails the
gate; a glitched frame that got past the converter fails it the same way. Rejections are counted by
reason in `rejected`. If wheels or gyro are rejected many times in a row the filter, not the
sensor, is assumed lost: the affected states' variance is re-inflated and the measurement taken
(counted as `*_reacquire`), so a gate can never lock a sensor out for good.

No clock and no I/O: time comes only from the increments.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from runtime.config.schema import setting
from runtime.geometry import wrap_angle
from runtime.types import MAX_UNCONFIRMED_DT_S, Odometry, WheelIncrement

X, Y, TH, V, W, B = range(6)
DIM_X = 6

# χ² quantiles at 99.9 %: with feedback at 50 Hz a 1 % gate would throw away a good wheel
# measurement every ~2 s; at 99.9 % one every ~20 s, while slip and glitches sit tens of σ out.
CHI2_999_2DOF = 13.816
CHI2_999_1DOF = 10.828


@dataclass(frozen=True)
class OdometryFilterConfig:
    """Noise model and gates of the odometry EKF (the `odometry:` section of the runtime config)."""

    accel_sigma_m_s2: float = setting(
        1.0,
        "process noise: σ of the body's forward acceleration (white, per √s); the Spark's wheels"
        " ramp at up to 1 m/s²",
        "m/s²",
        min=0.01,
        max=20.0,
    )
    angular_accel_sigma_rad_s2: float = setting(
        4.0,
        "process noise: σ of the yaw acceleration (white, per √s); 1 m/s² differential wheel"
        " ramp on a 0.266 m axle is up to 7.5 rad/s²",
        "rad/s²",
        min=0.01,
        max=100.0,
    )
    bias_walk_rad_s_sqrt_s: float = setting(
        1e-4,
        "process noise: gyro bias random walk (thermal drift)",
        "rad/s/√s",
        min=0.0,
        max=0.1,
    )
    wheel_travel_sigma_m: float = setting(
        0.0006,
        "σ of one wheel's measured travel over one increment (quantisation + count jitter; about"
        " 2 ticks); becomes a speed σ by dividing by dt",
        "m",
        min=1e-6,
        max=0.05,
    )
    wheel_speed_sigma_m_s: float = setting(
        0.005,
        "extra σ per wheel speed, independent of dt (tyre deformation, small slip, lag of the"
        " average speed over an increment behind the state at its end)",
        "m/s",
        min=0.0,
        max=1.0,
    )
    wheel_heading: str = setting(
        "cumulative",
        "how the wheels' turn is fused: 'cumulative' (sum of accepted increments as a heading"
        " measurement; right for encoder error that does not accumulate) or 'rate' (ω per frame)",
        choices=("cumulative", "rate"),
    )
    wheel_heading_sigma_rad: float = setting(
        0.002,
        "extra σ of the cumulative wheel heading (tyre scrub, axle calibration), on top of the"
        " per-reading error from wheel_travel_sigma_m",
        "rad",
        min=0.0,
        max=1.0,
    )
    gyro_sigma_rad_s: float = setting(
        0.01, "σ of one gyro z reading (white noise)", "rad/s", min=1e-5, max=1.0
    )
    initial_bias_sigma_rad_s: float = setting(
        0.05,
        "σ of the gyro bias before any data (prior mean 0); typical MEMS bias is a few 0.01 rad/s",
        "rad/s",
        min=1e-5,
        max=1.0,
    )
    wheel_gate_chi2: float = setting(
        CHI2_999_2DOF,
        "Mahalanobis² gate of the wheel update (χ², 2 dof; 13.82 = 99.9 %: one good frame in"
        " 1000 rejected, slip and glitches are far beyond)",
        min=1.0,
        max=1000.0,
    )
    gyro_gate_chi2: float = setting(
        CHI2_999_1DOF,
        "Mahalanobis² gate of the gyro update (χ², 1 dof; 10.83 = 99.9 %)",
        min=1.0,
        max=1000.0,
    )
    max_consecutive_rejects: int = setting(
        25,
        "after this many rejections in a row of one sensor the filter is assumed lost: the"
        " velocity (wheels) or bias (gyro) variance is re-inflated and the measurement taken",
        "frames",
        min=1,
        max=10000,
    )


def _mahalanobis2(y: np.ndarray, S: np.ndarray) -> float:
    """yᵀ S⁻¹ y for the 1- and 2-dimensional innovations used here, in closed form (a general
    solve costs more than the rest of the gate at 50 Hz); inf for a singular S."""
    if S.shape == (1, 1):
        s = float(S[0, 0])
        return float(y[0, 0]) ** 2 / s if s > 0 else math.inf
    a, b, c, d = float(S[0, 0]), float(S[0, 1]), float(S[1, 0]), float(S[1, 1])
    det = a * d - b * c
    if not det > 0:
        return math.inf
    y0, y1 = float(y[0, 0]), float(y[1, 0])
    return (d * y0 * y0 - (b + c) * y0 * y1 + a * y1 * y1) / det


class _UnicycleEKF(ExtendedKalmanFilter):
    """filterpy's EKF with the nonlinear unicycle prediction (its own predict_x is linear)."""

    dt: float = 0.0

    def predict_x(self, u: object = 0) -> None:
        x = self.x
        dt = self.dt
        heading = x[TH, 0] + 0.5 * x[W, 0] * dt
        ds = x[V, 0] * dt
        x[X, 0] += ds * math.cos(heading)
        x[Y, 0] += ds * math.sin(heading)
        x[TH, 0] = wrap_angle(x[TH, 0] + x[W, 0] * dt)


class OdometryEKF:
    """Fuses wheel increments and the gyro into `Odometry`; see the module docstring."""

    def __init__(self, axle_m: float, config: OdometryFilterConfig | None = None) -> None:
        if not (math.isfinite(axle_m) and axle_m > 0):
            raise ValueError(f"axle_m must be > 0, got {axle_m}")
        self.axle_m = float(axle_m)
        self.config = config or OdometryFilterConfig()
        self._ekf = _UnicycleEKF(dim_x=DIM_X, dim_z=2)
        self._ekf.x = np.zeros((DIM_X, 1))
        # The pose starts at the odom origin (by definition; a 1 mm / 1 mrad σ keeps P positive
        # definite); v and ω are unknown until the first frame.
        self._ekf.P = np.diag([1e-6, 1e-6, 1e-6, 1.0, 1.0, self.config.initial_bias_sigma_rad_s**2])
        self._H_wheel = np.zeros((2, DIM_X))
        self._H_wheel[0, V] = 1.0
        self._cumulative = self.config.wheel_heading == "cumulative"
        self._H_wheel[1, TH if self._cumulative else W] = 1.0
        # Cumulative mode: wheel heading = sum of every finite increment's turn + an offset that
        # swaps each rejected increment for the predicted turn. `_offset_undo` remembers the
        # offset before a run of rejections: if the raw sum agrees better afterwards, the bad
        # frames were a spike that cancelled itself (glitch up, then back) and it is restored.
        self._turn_raw = 0.0
        self._turn_offset = 0.0
        self._offset_undo: float | None = None
        self._H_gyro = np.zeros((1, DIM_X))
        self._H_gyro[0, W] = 1.0
        self._H_gyro[0, B] = 1.0
        self._z_wheel = np.zeros((2, 1))
        self._z_gyro = np.zeros((1, 1))
        self._R_wheel = np.zeros((2, 2))
        self._R_gyro = np.array([[self.config.gyro_sigma_rad_s**2]])
        self._run = Counter({"wheel": 0, "gyro": 0})
        self.rejected: Counter[str] = Counter()
        self.accepted: Counter[str] = Counter()
        self._t = 0.0
        self._distance = 0.0

    # --- read-outs ---------------------------------------------------------------------------

    @property
    def x(self) -> np.ndarray:
        """State [x, y, θ, v, ω, b] as a copy (1-D)."""
        return self._ekf.x[:, 0].copy()

    @property
    def covariance(self) -> np.ndarray:
        """State covariance (6×6) as a copy."""
        return self._ekf.P.copy()

    @property
    def bias(self) -> float:
        """Estimated gyro z bias (rad/s)."""
        return float(self._ekf.x[B, 0])

    @property
    def bias_sigma(self) -> float:
        return math.sqrt(max(self._ekf.P[B, B], 0.0))

    def odometry(self) -> Odometry:
        s = self._ekf.x[:, 0]
        return Odometry(
            t=self._t,
            x=float(s[X]),
            y=float(s[Y]),
            theta=float(s[TH]),
            v=float(s[V]),
            omega=float(s[W]),
            distance=self._distance,
        )

    # --- the stage ---------------------------------------------------------------------------

    def step(self, inc: WheelIncrement) -> Odometry:
        """Predict over inc.dt, then fuse the wheel speeds and the gyro (each gated)."""
        self._t = inc.t
        dt = inc.dt
        if not (math.isfinite(dt) and dt > 0):
            self.rejected["bad_dt"] += 1
            return self.odometry()
        ekf = self._ekf
        start = (float(ekf.x[X, 0]), float(ekf.x[Y, 0]), float(ekf.x[TH, 0]))
        if dt > MAX_UNCONFIRMED_DT_S:
            self._bridge_gap(inc, start)
            return self.odometry()
        v_prior = float(ekf.x[V, 0])
        predicted_turn = self._predict(dt)
        v_wheel = 0.5 * (inc.d_right + inc.d_left) / dt
        turn = (inc.d_right - inc.d_left) / self.axle_m
        if math.isfinite(v_wheel) and math.isfinite(turn):
            self._z_wheel[0, 0] = v_wheel
            if self._cumulative:
                self._turn_raw += turn
                self._z_wheel[1, 0] = self._cumulative_heading()
            else:
                self._z_wheel[1, 0] = turn / dt
            self._set_wheel_R(dt)
            taken = self._gated_update("wheel", self._z_wheel, self._H_wheel, self._R_wheel)
            if self._cumulative:
                if taken:
                    self._offset_undo = None
                else:
                    if self._offset_undo is None:
                        self._offset_undo = self._turn_offset
                    self._turn_offset += predicted_turn - turn
        else:
            self.rejected["wheel_nonfinite"] += 1
            self._turn_offset += predicted_turn
        if inc.gyro_z is not None:
            if math.isfinite(inc.gyro_z):
                self._z_gyro[0, 0] = inc.gyro_z
                self._gated_update("gyro", self._z_gyro, self._H_gyro, self._R_gyro)
            else:
                self.rejected["gyro_nonfinite"] += 1
        if math.isfinite(v_wheel) and math.isfinite(turn):
            self._move_by_travel(start, v_wheel * dt)
        else:
            self._distance += abs(v_prior) * dt
        P = self._ekf.P
        self._ekf.P = 0.5 * (P + P.T)
        return self.odometry()

    def _move_by_travel(self, start: tuple[float, float, float], ds: float) -> None:
        """Put the position where the increment's travel `ds` took it from `start`, along the
        mean of the start and the fused end heading (see step 4 of the module doc)."""
        x0, y0, th0 = start
        heading = th0 + 0.5 * wrap_angle(float(self._ekf.x[TH, 0]) - th0)
        self._ekf.x[X, 0] = x0 + ds * math.cos(heading)
        self._ekf.x[Y, 0] = y0 + ds * math.sin(heading)
        self._distance += abs(ds)

    def _bridge_gap(self, inc: WheelIncrement, start: tuple[float, float, float]) -> None:
        """An increment over a gap (frames lost or rejected): the pose moves by its travel.

        Predicting at the speed from before the gap would be wrong by whatever happened in it (a
        robot that braked during an outage would be carried on at cruise speed: 0.3 m over a 3 s
        gap at 0.1 m/s), and a speed averaged over the gap is no measurement of the speed now.
        The driver releases such an increment only once two frames in a row agreed on it, so
        its travel and turn are taken as they are, ungated, like dead reckoning over one step;
        the pose variance grows by their error, the bias by its walk over the gap, and v is left
        for the next increments to pin down (its variance is re-inflated). ω keeps its estimate, which the gyro updates this step:
        re-inflating it too would open the heading gate to a corrupted turn in the next one.
        """
        ekf, c = self._ekf, self.config
        ds = 0.5 * (inc.d_left + inc.d_right)
        turn = (inc.d_right - inc.d_left) / self.axle_m
        if not (math.isfinite(ds) and math.isfinite(turn)):
            self.rejected["wheel_nonfinite"] += 1
            return
        ekf.x[TH, 0] = wrap_angle(start[2] + turn)
        ekf.x[V, 0] = ds / inc.dt
        self._turn_raw += turn
        P = ekf.P
        travel_var = c.wheel_travel_sigma_m**2
        P[X, X] += travel_var
        P[Y, Y] += travel_var
        P[TH, TH] += 2.0 * travel_var / self.axle_m**2 + c.wheel_heading_sigma_rad**2
        P[B, B] += c.bias_walk_rad_s_sqrt_s**2 * inc.dt
        keep = P[V, V]
        P[V, :] = 0.0
        P[:, V] = 0.0
        P[V, V] = keep + 1.0
        self.accepted["wheel_gap"] += 1
        if inc.gyro_z is not None and math.isfinite(inc.gyro_z):
            self._z_gyro[0, 0] = inc.gyro_z
            self._gated_update("gyro", self._z_gyro, self._H_gyro, self._R_gyro)
        self._move_by_travel(start, ds)

    def _cumulative_heading(self) -> float:
        """Wheel heading measurement (wrapped), restoring the offset from before a rejection run
        when the raw sum now fits the predicted heading better (a self-cancelling spike)."""
        theta = self._ekf.x[TH, 0]
        z = wrap_angle(self._turn_raw + self._turn_offset)
        if self._offset_undo is not None:
            alt = wrap_angle(self._turn_raw + self._offset_undo)
            if abs(wrap_angle(alt - theta)) < abs(wrap_angle(z - theta)):
                self._turn_offset = self._offset_undo
                self._offset_undo = None
                z = alt
        return z

    def _predict(self, dt: float) -> float:
        """Predict over dt; return the predicted turn (rad)."""
        c = self.config
        ekf = self._ekf
        th, v, w = float(ekf.x[TH, 0]), float(ekf.x[V, 0]), float(ekf.x[W, 0])
        heading = th + 0.5 * w * dt
        cos_h, sin_h = math.cos(heading), math.sin(heading)
        F = np.eye(DIM_X)
        F[X, TH] = -v * dt * sin_h
        F[X, V] = dt * cos_h
        F[X, W] = -0.5 * v * dt * dt * sin_h
        F[Y, TH] = v * dt * cos_h
        F[Y, V] = dt * sin_h
        F[Y, W] = 0.5 * v * dt * dt * cos_h
        F[TH, W] = dt
        # Continuous white acceleration integrated over dt: travel along the heading and v are
        # correlated ([dt³/3, dt²/2; dt²/2, dt]); the same for θ and ω; the bias walks.
        Q = np.zeros((DIM_X, DIM_X))
        qa = c.accel_sigma_m_s2**2
        s3, s2 = dt**3 / 3.0, dt**2 / 2.0
        Q[X, X] = qa * s3 * cos_h * cos_h
        Q[Y, Y] = qa * s3 * sin_h * sin_h
        Q[X, Y] = Q[Y, X] = qa * s3 * cos_h * sin_h
        Q[X, V] = Q[V, X] = qa * s2 * cos_h
        Q[Y, V] = Q[V, Y] = qa * s2 * sin_h
        Q[V, V] = qa * dt
        qw = c.angular_accel_sigma_rad_s2**2
        Q[TH, TH] = qw * s3
        Q[TH, W] = Q[W, TH] = qw * s2
        Q[W, W] = qw * dt
        Q[B, B] = c.bias_walk_rad_s_sqrt_s**2 * dt
        ekf.F = F
        ekf.Q = Q
        ekf.dt = dt
        ekf.predict()
        return w * dt

    def _set_wheel_R(self, dt: float) -> None:
        c = self.config
        # Per-wheel speed variance; v = (r + l)/2 and ω = (r − l)/axle are uncorrelated when the
        # two wheels' errors are independent and equal.
        var = (c.wheel_travel_sigma_m / dt) ** 2 + c.wheel_speed_sigma_m_s**2
        self._R_wheel[0, 0] = 0.5 * var
        if self._cumulative:
            # A heading summed from accepted increments carries the error of one reading pair.
            self._R_wheel[1, 1] = (
                c.wheel_travel_sigma_m**2 / self.axle_m**2 + c.wheel_heading_sigma_rad**2
            )
        else:
            self._R_wheel[1, 1] = 2.0 * var / self.axle_m**2

    def _residual(self, z: np.ndarray, hx: np.ndarray) -> np.ndarray:
        y = z - hx
        if self._cumulative and y.shape[0] == 2:
            y[1, 0] = wrap_angle(y[1, 0])
        return y

    def _gated_update(self, name: str, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> bool:
        """Fuse z unless it fails the gate; True when it was fused."""
        ekf = self._ekf
        y = self._residual(z, H @ ekf.x)
        d2 = _mahalanobis2(y, H @ ekf.P @ H.T + R)
        gate = self.config.wheel_gate_chi2 if name == "wheel" else self.config.gyro_gate_chi2
        if not d2 <= gate:
            self._run[name] += 1
            if self._run[name] < self.config.max_consecutive_rejects:
                self.rejected[f"{name}_gate"] += 1
                return False
            self._reacquire(name)
        self._run[name] = 0
        self.accepted[name] += 1
        ekf.update(z, lambda _x, H=H: H, lambda x, H=H: H @ x, R=R, residual=self._residual)
        ekf.x[TH, 0] = wrap_angle(ekf.x[TH, 0])
        return True

    def _reacquire(self, name: str) -> None:
        """A sensor failed the gate too often in a row: trust it again, forgetting what it fixes."""
        self.rejected[f"{name}_reacquire"] += 1
        P = self._ekf.P
        idx = ((TH, V, W) if self._cumulative else (V, W)) if name == "wheel" else (B,)
        for i in idx:
            keep = P[i, i]
            P[i, :] = 0.0
            P[:, i] = 0.0
            P[i, i] = keep + (1.0 if name == "wheel" else self.config.initial_bias_sigma_rad_s**2)
