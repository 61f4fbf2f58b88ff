"""A realistic simulated flight: a Cessna 172 in JSBSim, flown by its own autopilot.

The kinematic simulator (``mavest.sim.kinematic``) follows the filter's own
process model; this one does not. The truth here comes from a six-degree-of-
freedom flight-dynamics model (JSBSim's ``c172x``, aerodynamics, engine,
propeller and all) in light Dryden turbulence, flown through a sequence of
coordinated-ish turns by the autopilot that ships with the aircraft
(``aircraft/c172x/c172ap.xml``): heading hold on the ailerons, altitude hold on
the elevator. That gives the specific force and body rates of a real airframe —
sustained load factor in turns, sideslip, phugoid, gusts — which no sum of
sinusoids has.

Frames and units are mavest's: body FRD, world NED, quaternions (w, x, y, z)
body → NED, rates in rad/s, specific force in m/s². JSBSim works in feet;
``FT = 0.3048`` converts.

Where the numbers come from (JSBSim ≥ 1.2, checked on 1.3.3):

* attitude: ``attitude/phi-rad``, ``theta-rad``, ``psi-rad``, the ZYX Euler
  angles of the body relative to the local NED frame; converted to a quaternion
  here.
* body rate: ``velocities/{p,q,r}-rad_sec``, the body rate relative to the Earth
  (ECEF) in body axes. The Earth rate (7.3e-5 rad/s) is left out on purpose, so
  that integrating the gyro reproduces ``q_true`` exactly; it is far below any
  gyro bias. The rotation of the NED frame itself (v/R ≈ 1e-5 rad/s) is also
  ignored.
* specific force: ``forces/fb{x,y,z}-total-lbs / inertia/mass-slugs``, the sum
  of every non-gravitational force (aero, propulsion, gear) over the mass, at
  the centre of gravity, in body FRD axes: exactly what an accelerometer at the
  CG measures. Its sign was checked, not assumed: in trimmed level flight it is
  (0.46, 0.08, −32.17) ft/s² = (0.14, 0.02, −9.81) m/s², i.e. ≈ (0, 0, −g) FRD
  (x is g·sin θ at θ = 0.8°); and at 1000 Hz, rotated to NED, it matches the
  central difference of the NED velocity minus (0, 0, g) to ~0.01–0.03 m/s² RMS
  over a turning flight in turbulence (JSBSim's gravity is the J2 field of a
  rotating Earth, which accounts for a few mm/s² of mean).
  ``accelerations/Nx/Ny/Nz`` carry the same quantity in g (Nz positive up) but
  one frame late (FGAuxiliary runs before FGAccelerations), and
  ``accelerations/a-pilot-*`` is at the pilot's eye point, not the CG, and one
  frame late too; neither is used.
* timing: JSBSim's ``run()`` integrates first (FGPropagate is the first model)
  and then evaluates every force model at the new state, so after each
  ``run()`` the state and the forces read belong to the same instant; sample i
  is read right after the run that reaches t = i/rate (sample 0 is the trimmed
  initial state). No interpolation anywhere.

JSBSim steps at ``1/(rate·k)`` for the smallest integer ``k`` that keeps its own
rate at or above ``min_model_rate`` (500 Hz by default), so a 50 Hz flight is
the same physics as a 1000 Hz one, only sampled more sparsely.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mavest.so3 import quats_from_euler_zyx

FT = 0.3048  # m per ft

# The aircraft and the properties read at every sample, in the order of the
# columns of the internal sample rows.
AIRCRAFT = "c172x"
_SAMPLED = (
    "velocities/p-rad_sec",
    "velocities/q-rad_sec",
    "velocities/r-rad_sec",
    "forces/fbx-total-lbs",
    "forces/fby-total-lbs",
    "forces/fbz-total-lbs",
    "inertia/mass-slugs",
    "attitude/phi-rad",
    "attitude/theta-rad",
    "attitude/psi-rad",
    "position/lat-geod-deg",
    "position/long-gc-deg",
    "position/h-sl-ft",
    "velocities/v-north-fps",
    "velocities/v-east-fps",
    "velocities/v-down-fps",
    "velocities/vtrue-fps",
)
_COLUMNS = len(_SAMPLED)

# JSBSim's turbulence models (FGWinds::tType): 4 is the Tustin-discretised
# Dryden model of MIL-F-8785C, whose filters are exact for any time step.
_TURBULENCE_TUSTIN = 4


@dataclass(frozen=True)
class FlightPlan:
    """What the autopilot is asked to fly, and in what weather.

    The aircraft starts trimmed in straight and level flight at ``altitude``
    and ``airspeed``, flies straight for ``first_turn`` s, and then, every
    ``turn_interval`` s (drawn uniformly from the range, per seed), turns the
    heading setpoint by ``turn_angle`` degrees left or right (random sign).
    The c172x heading hold commands a bank proportional to the heading error
    clipped at 30°, so a 90° change holds ~30° of bank for ~10 s and rolls out
    over another ~10 s; the rest of each interval is straight and level.
    Altitude is held within ~±20 m; the throttle stays at its trim setting, so
    the airspeed sags by up to ~15 % in turns and recovers after.

    ``turbulence`` is the MIL-F-8785C probability-of-exceedance index (0 off,
    1–7): 2, the default, is mild (gust σ ≈ 1 m/s at 1000 m, vertical specific
    force σ ≈ 0.8 m/s²), 3 is "light" (σ ≈ 2 m/s). Fuel is frozen so that the
    mass, and with it the trim, stays constant for a flight of any length.
    """

    altitude: float = 1000.0  # m above sea level (the terrain is at sea level)
    airspeed: float = 95.0  # kt, calibrated
    latitude: float = 47.4  # deg, geodetic
    longitude: float = 8.5  # deg
    heading: float | None = None  # deg true; None: drawn uniformly per seed
    first_turn: float = 10.0  # s of straight flight before the first turn
    turn_interval: tuple[float, float] = (25.0, 35.0)  # s between heading changes
    turn_angle: float = 90.0  # deg per heading change
    turbulence: int = 2  # MIL-F-8785C severity index, 0 = calm air
    min_model_rate: float = 500.0  # Hz, the slowest JSBSim is stepped


@dataclass(frozen=True)
class Flight:
    """True kinematics sampled at ``rate`` Hz; sample i is the model state at t[i].

    Frames as everywhere in mavest: body FRD, world NED. ``gyro`` and ``accel``
    are what an ideal IMU at the centre of gravity would read at t[i] (body rate
    relative to the Earth, specific force); ``q_true`` maps body to NED.
    """

    rate: float  # Hz
    t: np.ndarray  # (N,) s
    gyro: np.ndarray  # (N, 3) rad/s, FRD
    accel: np.ndarray  # (N, 3) m/s², specific force, FRD
    q_true: np.ndarray  # (N, 4) (w, x, y, z), body → NED
    latitude: np.ndarray  # (N,) deg, geodetic
    longitude: np.ndarray  # (N,) deg
    altitude: np.ndarray  # (N,) m above sea level
    velocity: np.ndarray  # (N, 3) m/s, NED, relative to the ground
    airspeed: np.ndarray  # (N,) m/s, true airspeed
    heading_setpoint: np.ndarray  # (N,) deg, the autopilot's target at t[i]

    def __len__(self) -> int:
        return len(self.t)


def _flight_from_rows(rate: float, t: np.ndarray, rows: np.ndarray, setpoint: np.ndarray) -> Flight:
    """Convert the raw property rows (feet, slugs) into a Flight (SI)."""
    force = rows[:, 3:6] / rows[:, 6:7]  # lbf/slug = ft/s²
    return Flight(
        rate=rate,
        t=t,
        gyro=rows[:, 0:3].copy(),
        accel=force * FT,
        q_true=quats_from_euler_zyx(rows[:, 7:10]),
        latitude=rows[:, 10].copy(),
        longitude=rows[:, 11].copy(),
        altitude=rows[:, 12] * FT,
        velocity=rows[:, 13:16] * FT,
        airspeed=rows[:, 16] * FT,
        heading_setpoint=setpoint,
    )


class SimulatorMissingError(RuntimeError):
    """JSBSim is not installed (it comes with the ``sim`` extra)."""


class FlightModel:
    """A JSBSim flight stepped on demand: the streaming form of ``fly``.

    A live vehicle calls ``advance(n)`` or ``advance_to(t)`` as its clock runs
    and gets the next samples; the autopilot keeps turning for as long as it is
    stepped. Two models with the same rate, seed and plan produce the same
    samples however the calls are chunked.

    Construction loads and trims the aircraft in ~0.02 s (plus ~0.2 s for the
    first import of jsbsim). Stepping runs at ~30× real time at 1000 Hz (JSBSim
    alone: ~40×), ~80× at 50 Hz (JSBSim at 500 Hz). Each call also costs
    ~0.1 ms of array building, so a live vehicle should fetch its samples in
    chunks (``advance_to`` its clock every few ms), not one call per sample.
    """

    def __init__(self, rate: float = 1000.0, seed: int = 0, plan: FlightPlan | None = None) -> None:
        try:  # the sim extra: only flights need it, so it is imported when one is made
            import jsbsim
        except ImportError:
            raise SimulatorMissingError(
                "the simulated vehicle needs JSBSim: pip install 'mavest[sim]'"
            ) from None

        if not (math.isfinite(rate) and rate > 0.0):
            raise ValueError(f"rate must be a positive number of Hz, got {rate}")
        self.plan = plan if plan is not None else FlightPlan()
        self.rate = float(rate)
        self.seed = int(seed)
        self.substeps = max(1, math.ceil(self.plan.min_model_rate / self.rate - 1e-9))
        self._rng = np.random.default_rng(self.seed)  # the turn schedule
        heading = self.plan.heading
        if heading is None:
            heading = float(self._rng.uniform(0.0, 360.0))

        # Startup messages go to stdout unless the (process-wide) level is 0.
        jsbsim.FGJSBBase().debug_lvl = 0
        fdm = jsbsim.FGFDMExec(jsbsim.get_default_root_dir())
        fdm.disable_output()  # the c172x file declares a CSV output; write nothing
        if not fdm.load_model(AIRCRAFT):
            raise RuntimeError(f"JSBSim could not load the {AIRCRAFT} model")
        fdm.set_dt(1.0 / (self.rate * self.substeps))
        jsb_seed = self.seed % 2_147_483_647  # JSBSim seeds are C ints
        for name in (
            "simulation/randomseed",  # turbulence draws from this generator
            "fcs/attitude/sensor/phi-rad/randomseed",  # the autopilot's (unused) noisy sensor
            "navigation/actual-heading-rad/randomseed",
        ):
            fdm[name] = jsb_seed
        # Position before altitude and speed: the IC recomputes the others.
        fdm["ic/lat-geod-deg"] = self.plan.latitude
        fdm["ic/long-gc-deg"] = self.plan.longitude
        fdm["ic/h-sl-ft"] = self.plan.altitude / FT
        fdm["ic/psi-true-deg"] = heading
        fdm["ic/vc-kts"] = self.plan.airspeed
        fdm.get_propulsion().init_running(-1)
        if not fdm.run_ic():
            raise RuntimeError("JSBSim rejected the initial conditions")
        try:
            fdm.do_trim(1)  # full longitudinal and lateral trim, wings level
        except jsbsim.TrimFailureError as error:
            raise RuntimeError(f"JSBSim could not trim {self.plan}") from error
        fdm["propulsion/fuel_freeze"] = 1
        fdm["atmosphere/turb-type"] = _TURBULENCE_TUSTIN
        fdm["atmosphere/turbulence/milspec/severity"] = self.plan.turbulence
        fdm["atmosphere/turbulence/milspec/windspeed_at_20ft_AGL-fps"] = (
            15.0 if self.plan.turbulence else 0.0  # only used below 2000 ft
        )
        # The c172x autopilot (c172ap.xml): heading in degrees true, altitude in
        # ft above ground level.
        fdm["ap/altitude_setpoint"] = fdm["position/h-agl-ft"]
        fdm["ap/altitude_hold"] = 1
        fdm["ap/heading_setpoint"] = heading
        fdm["ap/heading_hold"] = 1

        manager = fdm.get_property_manager()
        self._read = [manager.get_node(name).get_double_value for name in _SAMPLED]
        self.fdm = fdm
        self._heading_setpoint = heading
        self._next_turn = self.plan.first_turn
        self._index = 0  # the index of the next sample to return
        self._pending = [read() for read in self._read]  # sample 0, the trimmed state

    @property
    def time(self) -> float:
        """The time of the next sample to be returned, s."""
        return self._index / self.rate

    @property
    def heading_setpoint(self) -> float:
        """The autopilot's current heading setpoint, deg true."""
        return self._heading_setpoint

    def _schedule_turns(self, t: float) -> None:
        """Move the heading setpoint at the scheduled times up to t."""
        while t >= self._next_turn:
            sign = 1.0 if self._rng.random() < 0.5 else -1.0
            self._heading_setpoint = (self._heading_setpoint + sign * self.plan.turn_angle) % 360.0
            self.fdm["ap/heading_setpoint"] = self._heading_setpoint
            low, high = self.plan.turn_interval
            self._next_turn += float(self._rng.uniform(low, high))

    def advance(self, steps: int = 1) -> Flight:
        """The next ``steps`` samples (the first call starts with t = 0)."""
        if steps < 0:
            raise ValueError(f"steps must be ≥ 0, got {steps}")
        rows = np.empty((steps, _COLUMNS))
        setpoint = np.empty(steps)
        run, read, substeps = self.fdm.run, self._read, self.substeps
        start = self._index
        for i in range(steps):
            # A turn scheduled for time t takes effect from the step that starts at t.
            self._schedule_turns((start + i) / self.rate)
            rows[i] = self._pending
            setpoint[i] = self._heading_setpoint
            for _ in range(substeps):
                if not run():
                    raise RuntimeError("JSBSim stopped")
            self._pending = [r() for r in read]
        self._index = start + steps
        t = np.arange(start, start + steps) / self.rate
        return _flight_from_rows(self.rate, t, rows, setpoint)

    def advance_to(self, t: float) -> Flight:
        """All samples not yet returned with time ≤ t (for a vehicle on a wall clock)."""
        last = math.floor(t * self.rate + 1e-9)
        return self.advance(max(0, last + 1 - self._index))


def fly(
    duration: float, rate: float = 1000.0, seed: int = 0, plan: FlightPlan | None = None
) -> Flight:
    """A flight of ``duration`` s sampled at ``rate`` Hz: round(duration·rate) + 1 samples.

    Deterministic for a seed (turn directions and intervals, initial heading
    if the plan leaves it open, turbulence).
    """
    if not (math.isfinite(duration) and duration >= 0.0):
        raise ValueError(f"duration must be ≥ 0 s, got {duration}")
    return FlightModel(rate, seed, plan).advance(round(duration * rate) + 1)


# --------------------------------------------------------------------------
# IMU errors
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuErrors:
    """Sensor errors of one IMU: white noise and a constant bias per axis.

    Densities as in the filter's configuration (per-sample σ = density·√rate).
    The defaults are a MEMS IMU with some airframe vibration folded into the
    noise; they are below the filter's default assumptions on purpose, so the
    filter is conservatively tuned for them. The biases are drawn once per
    seed, N(0, σ²) on each axis, and then held: what is left of the sensor's
    offset in what the autopilot sends, the error the filter must estimate.

    The gyro's is a residual, not a raw MEMS turn-on bias (~0.5 °/s): ArduPilot
    subtracts the offsets it measures at boot (INS_GYR_CAL; in
    ``AP_InertialSensor_Backend::_rotate_and_correct_gyro``) before RAW_IMU,
    and the ArduPilot tlogs in the shared data read 0.005–0.04 °/s per axis at
    rest (one 0.4 °/s). 0.1 °/s is that residual, on the generous side.
    """

    gyro_noise_density: float = 1e-3  # rad/s/√Hz
    accel_noise_density: float = 0.01  # m/s²/√Hz
    gyro_bias_sigma: float = math.radians(0.1)  # rad/s per axis
    accel_bias_sigma: float = 0.05  # m/s² per axis


class NoisyImu:
    """``ImuErrors`` applied to a stream of true samples at a fixed rate.

    The biases are drawn at construction; the noise comes from generators of
    its own (one for the gyro, one for the accelerometer), so the measurements
    of a flight are the same whether it is measured at once or chunk by chunk.
    """

    def __init__(
        self, errors: ImuErrors | None = None, rate: float = 1000.0, seed: int = 0
    ) -> None:
        self.errors = errors if errors is not None else ImuErrors()
        self.rate = float(rate)
        bias_seed, gyro_seed, accel_seed = np.random.SeedSequence(seed).spawn(3)
        bias_rng = np.random.default_rng(bias_seed)
        self.gyro_bias = bias_rng.normal(0.0, self.errors.gyro_bias_sigma, 3)
        self.accel_bias = bias_rng.normal(0.0, self.errors.accel_bias_sigma, 3)
        self._gyro_rng = np.random.default_rng(gyro_seed)
        self._accel_rng = np.random.default_rng(accel_seed)

    def measure(self, gyro: np.ndarray, accel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Measured (gyro rad/s, accel m/s²) of (N, 3) true ones, SI, not quantised."""
        gyro = np.asarray(gyro, dtype=float)
        accel = np.asarray(accel, dtype=float)
        root_rate = math.sqrt(self.rate)
        gyro_sigma = self.errors.gyro_noise_density * root_rate
        accel_sigma = self.errors.accel_noise_density * root_rate
        measured_gyro = (
            gyro + self.gyro_bias + gyro_sigma * self._gyro_rng.standard_normal(gyro.shape)
        )
        measured_accel = (
            accel + self.accel_bias + accel_sigma * self._accel_rng.standard_normal(accel.shape)
        )
        return measured_gyro, measured_accel


def apply_imu_errors(
    flight: Flight, errors: ImuErrors | None = None, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Measured (gyro, accel) of a whole flight; ``NoisyImu(errors, flight.rate, seed)``
    holds the biases that were applied."""
    return NoisyImu(errors, flight.rate, seed).measure(flight.gyro, flight.accel)
