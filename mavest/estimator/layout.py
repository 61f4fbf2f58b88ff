"""The numeric layout shared by Python and the compiled kernels.

The filter's state and its coefficients are NumPy structured records: one
argument each for a compiled kernel, with named fields instead of offsets, and
no allocation on the hot path (scratch matrices live in the state record).
"""

from __future__ import annotations

import numpy as np

from mavest import timeline
from mavest.estimator.config import (
    CHARTS,
    ERROR_SIDES,
    RESET_POLICIES,
    UPDATE_KINDS,
    EstimatorConfig,
)

# The estimator takes the field in µT; ArduPilot's COMPASS_OFS is in milligauss.
MICROTESLA_PER_MILLIGAUSS = 0.1

# Type names for one element of the record arrays below, as the kernels receive them.
StateRecord = np.void
CoefficientsRecord = np.void

N_ERROR = 6  # the estimated error: δθ (3) and δb (3)
# considered only: the low-passed accelerometer's error ε, the low-pass's rate
# ḟ, and the vehicle's velocity v, each along the horizontal world axes x, y.
# Their vertical components are not carried: the gravity update does not measure
# ε_z (a vertical error of f̄ changes its norm, not its direction), the prediction
# moves ε's x, y only, each axis's low-pass is its own, and a reset turns the
# considered states by its turn about the vertical alone (frames.world_move_into),
# so nothing measured depends on them. (Turned by the reset's
# whole rotation, as the low-pass's vectors are, its tilt would mix vertical
# components into the horizontal: components of nearly the same statistics.)
N_AXES = 2
N_CONSIDER = 3 * N_AXES
N_STATE_MAX = N_ERROR + N_CONSIDER
N_SIGMA_MAX = 2 * N_STATE_MAX + 1

# The modules of mavest.estimator that own scratch buffers in the state record (its
# w_<module>_… fields, STATE_DTYPE), each working in its own alone.
SCRATCH_OWNERS = (
    "frames",
    "propagation",
    "lowpass",
    "gravity_update",
    "heading",
    "rest",
    "alignment",
    "health",
    "online",
)

# One row of the online estimator's output block (float64), filled by the compiled step:
# what an Estimate shows. The arrays first, at these offsets, then the step's scalars
# (the flags and counts are integers, exact in a float64).
ROW_Q = 0  # 4: w, x, y, z
ROW_BIAS = 4  # 3
ROW_EULER = 7  # 3: roll, pitch, yaw
ROW_INNOVATION = 10  # 2
ROW_COV = 12  # N_ERROR × N_ERROR, row by row
ROW_T = ROW_COV + N_ERROR * N_ERROR
ROW_NIS = ROW_T + 1
ROW_ACCEL_USED = ROW_T + 2
ROW_FLAGS = ROW_T + 3
ROW_ITERATIONS = ROW_T + 4
ROW_AT_REST = ROW_T + 5
ROW_HEADING_INNOVATION = ROW_T + 6
ROW_HEADING_NIS = ROW_T + 7
ROW_MAG_USED = ROW_T + 8
ROW_WIDTH = ROW_T + 9

# Integer codes of the structural choices: their position in the config's tuples.
UPDATE_EKF, UPDATE_ITERATED, UPDATE_SIGMA_POINT = range(len(UPDATE_KINDS))
ERROR_LEFT, ERROR_RIGHT = range(len(ERROR_SIDES))
CHART_EXP, CHART_HEADING_TILT = range(len(CHARTS))
RESET_NONE, RESET_FIRST_ORDER, RESET_FULL = range(len(RESET_POLICIES))


class StepFlags:
    """Bits of the per-sample ``flags`` field: what happened to this sample."""

    INITIALISED = 1  # this sample set the initial attitude from the accelerometer
    NOT_INITIALISED = 2  # no usable sample yet: the output is a placeholder
    ACCEL_INVALID = 4  # accelerometer not finite, zero or beyond 50 g: not used
    ACCEL_REJECTED_NORM = 8  # |‖a‖ − g| beyond tolerance: not gravity
    ACCEL_DISTURBED = 16  # innovation beyond the χ² gate: used with its noise inflated to match
    GYRO_INVALID = 32  # gyroscope not finite or beyond MAX_ANGULAR_RATE: sample skipped
    # t not after the previous sample's (a duplicate, a step back within
    # mavest.timeline.REORDER_WINDOW) or NaN: skipped
    TIME_NOT_INCREASING = 64
    GAP_REALIGNED = 128  # Δt > max_dt: attitude re-aligned from the accelerometer
    TILT_REOPENED = 256  # disturbed too long: tilt given its initial uncertainty again
    LOWPASS_RESTARTED = 512  # a large correction: the accelerometer low-pass starts again
    ACCEL_DEFERRED = 1024  # the low-pass has not averaged enough yet to be used
    MAG_INVALID = 2048  # magnetometer zero, (nearly) vertical or not finite: no heading
    MAG_DISTURBED = 4096  # field norm or dip off the reference: not used
    MAG_REJECTED = 8192  # heading innovation beyond the χ² gate: not used
    HEADING_ALIGNED = 16384  # heading set from the magnetometer (first sample, or again)
    MAG_REFERENCE_CHANGED = 32768  # a steady new field became the reference
    HEADING_REOPENED = 65536  # magnetometer rejected too long: heading uncertain again
    ACCEL_AIDED = 131072  # the vehicle's known acceleration (GPS) was removed from the sample
    # the state failed its health check (not finite, covariance not positive
    # definite or beyond bounds): re-initialised from this sample
    UNHEALTHY_RESET = 262144
    # the accelerometer contradicted the attitude again soon after tilt was
    # reopened (divergence_window): re-initialised from this sample
    DIVERGED = 524288
    # a gyro axis at or beyond gyro_clip: the rotation missed is unknown; the
    # accelerometer is not used until the vehicle is calm again
    GYRO_CLIPPED = 1048576
    # calm again after a clipped gyro: attitude re-aligned from the accelerometer
    # (heading kept, or set again by the magnetometer)
    CLIP_REALIGNED = 2097152
    # no gravity or zero-rate update at this sample: the last was less than the
    # update interval ago (EstimatorConfig.update_rate); the sample was predicted
    # and its accelerometer taken into the low-pass
    BETWEEN_UPDATES = 4194304
    # this sample's magnetometer reading was not used: the last one taken was less
    # than the update interval ago
    MAG_BETWEEN_UPDATES = 8388608
    # this sample's magnetometer reading was not looked at: the attitude it would
    # correct is not known (re-aligned after a gap, or waiting for calm after a
    # clipped gyro)
    MAG_SET_ASIDE = 16777216
    # t far off the timeline (back by more than mavest.timeline.REORDER_WINDOW, forward
    # by more than EstimatorConfig.max_jump, or infinite), and not (yet) continued by
    # the samples after it: a corrupted timestamp, skipped
    TIME_OFF_TIMELINE = 33554432
    # time went back and stayed back (EstimatorConfig.timeline_confirm samples in a
    # row): the clock restarted, the estimate re-initialised from this sample
    TIME_RESTARTED = 67108864
    # not initialised, and the accelerometer's norm over the first samples is g in
    # another unit than m/s² (g, mg, mm/s²: recursion.ACCEL_UNITS)
    ACCEL_WRONG_UNIT = 134217728

    SKIPPED = GYRO_INVALID | TIME_NOT_INCREASING | TIME_OFF_TIMELINE

    @classmethod
    def describe(cls, flags: int) -> list[str]:
        """Names of the bits set in ``flags``."""
        return [
            name
            for name, bit in vars(cls).items()
            if name.isupper() and name != "SKIPPED" and flags & bit
        ]


COEFFICIENTS_DTYPE = np.dtype(
    [
        ("update", np.int64),
        ("error", np.int64),
        ("chart", np.int64),
        ("reset", np.int64),
        ("n_state", np.int64),  # covariance dimension: N_ERROR, or N_STATE_MAX with the low-pass
        ("max_iterations", np.int64),
        ("iteration_tolerance", np.float64),
        ("sigma_spread", np.float64),  # n + λ
        ("sigma_w0_mean", np.float64),
        ("sigma_w0_cov", np.float64),
        ("sigma_wi", np.float64),
        ("gyro_var_density", np.float64),  # σ_g², rad²/s
        ("gyro_scale_var_density", np.float64),  # σ_s², s (× |ω|²: rad²/s)
        ("bias_var_density", np.float64),  # σ_b², rad²/s³
        ("accel_var_density", np.float64),  # σ_a², m²/s³
        ("gravity", np.float64),
        ("accel_norm_inflation", np.float64),
        ("accel_norm_tolerance", np.float64),
        ("accel_gate", np.float64),
        ("accel_max_disturbance_time", np.float64),
        ("divergence_window", np.float64),
        ("initial_tilt_var", np.float64),
        ("initial_heading_var", np.float64),
        ("initial_bias_var", np.float64),
        ("initial_bias", np.float64, 3),
        ("max_dt", np.float64),
        ("max_jump", np.float64),  # s forward beyond which a step needs confirming
        ("reorder_window", np.float64),  # s back that is a late sample, not a new timeline
        ("timeline_confirm", np.int64),  # samples in a row that confirm a new timeline
        ("timeline_max_step", np.float64),  # s between a new timeline's samples, at most
        ("gyro_clip", np.float64),
        ("accel_lowpass_time", np.float64),
        ("accel_lowpass_damping", np.float64),
        ("lowpass_restart_angle", np.float64),
        ("update_interval", np.float64),  # s between measurement updates (0: every sample)
        # 1: between updates the covariance's transition is accumulated and applied
        # at the next update (propagation's "pending transition"); 0: every sample's
        ("accumulate", np.int64),
        ("alignment_var", np.float64),  # rad², the accelerometer's, each horizontal axis
        ("imu_delay", np.float64),  # s the estimate reported is carried forward
        ("velocity_var", np.float64),
        ("velocity_time", np.float64),
        ("velocity_adapt_time", np.float64),  # s; 0: σ_v fixed
        ("velocity_adapt_gain", np.float64),
        ("velocity_var_min", np.float64),
        ("aided_velocity_var", np.float64),
        ("aided_max_heading_var", np.float64),
        ("rest_detection", np.int64),
        ("rest_filter_time", np.float64),
        ("rest_gyro_threshold", np.float64),
        ("rest_accel_threshold", np.float64),
        ("rest_min_time", np.float64),
        ("rest_rate_var", np.float64),
        ("mag_heading_var_density", np.float64),  # rad²·s
        ("mag_tilt_leak_time", np.float64),  # s
        ("mag_reopened_heading_var", np.float64),
        ("mag_offsets", np.float64, 3),  # µT
        ("mag_soft_iron", np.float64, (3, 3)),
        ("mag_declination", np.float64),
        ("mag_norm_tolerance", np.float64),
        ("mag_dip_tolerance", np.float64),
        ("mag_gate", np.float64),
        ("mag_reference_time", np.float64),
        ("mag_reference_adapt_time", np.float64),
        ("mag_new_reference_time", np.float64),
        ("mag_max_rejection_time", np.float64),
        ("mag_recovery_time", np.float64),
    ]
)

STATE_DTYPE = np.dtype(
    [
        # the estimate
        ("q", np.float64, 4),  # nominal attitude, body → NED, (w, x, y, z)
        ("b", np.float64, 3),  # nominal gyro bias, rad/s
        # error covariance of [δθ (chart), δb, ε, ḟ, v]; the first 6×6 is the estimate's
        ("P", np.float64, (N_STATE_MAX, N_STATE_MAX)),
        ("t", np.float64),  # time of the last sample taken, s
        ("t_accel", np.float64),  # time of the last undisturbed accelerometer update
        ("initialised", np.int64),
        ("samples", np.int64),
        ("accel_rejections", np.int64),  # samples not used (norm beyond tolerance)
        ("accel_disturbances", np.int64),  # samples used with inflated noise
        ("t_reopened", np.float64),  # when tilt was last reopened, s
        # after a clipped gyro: how long the vehicle has been calm (−1: not clipped)
        ("clip_calm_time", np.float64),
        ("unhealthy_resets", np.int64),  # re-initialisations after a failed health check
        ("divergence_resets", np.int64),  # re-initialisations after a divergence
        # samples in a row far off the timeline (0: none), and the last one's time
        ("timeline_count", np.int64),
        ("t_timeline", np.float64),
        # the accelerometer's unit, judged over the first samples while none aligns:
        # 0 not judged yet, −1 m/s² (or no verdict), k ≥ 1 ACCEL_UNITS[k − 1]; the
        # samples judged so far (since unit_t0), how many of them are g in each of
        # ACCEL_UNITS, and the sum of those norms
        ("accel_unit", np.int64),
        ("unit_t0", np.float64),
        ("unit_samples", np.int64),
        ("unit_votes", np.int64, 3),
        ("unit_norm_sum", np.float64, 3),
        ("unit_warned", np.int64),  # the caller has been told (once)
        # filters feeding the measurements
        # low-passed specific force f̄ and its rate ḟ, estimated world frame
        ("accel_world_lp", np.float64, (2, 3)),
        ("lowpass_time", np.float64),  # time averaged since the low-pass started, s
        # the vehicle's motion level: the horizontal velocity's fast part (the specific
        # force less its low-pass, leakily integrated) and the velocity variance it shows
        ("motion_velocity", np.float64, 3),  # (its vertical is kept 0)
        ("motion_var", np.float64),
        # what depends on Δt alone, for the Δt below: the low-pass's Φ₀₀, Φ₀₁, Φ₁₀, Φ₁₁,
        # Γ₀, Γ₁, the velocity's γ and the rest detector's α
        ("step_coefficients", np.float64, 8),
        ("step_coefficients_dt", np.float64),
        ("rest_gyro_lp", np.float64, 3),  # low-passed gyro and accel of the rest detector
        ("rest_accel_lp", np.float64, 3),
        ("rest_time", np.float64),  # how long the rest criteria have held, s
        # the gyro samples since the last update while the rest criteria held
        # (their mean is what the zero-rate update measures), and their time
        ("rest_gyro_sum", np.float64, 3),
        ("rest_samples", np.int64),
        ("rest_sum_time", np.float64),
        ("t_update", np.float64),  # time of the last update sample (gravity, zero rate)
        # The covariance's transition since P's considered rows were last brought up to
        # date (propagation.flush_pending): the steps in it, P's 6×6 then, and the
        # linear map of the error x = [δθ, δb, u] (u = ε, ḟ, v) over them,
        #   δθ ← Θθ δθ + Θb δb,   u ← (A ⊗ I₂) u + U [δθ; δb],
        # with the low-pass's own noise N (per axis, in ε, ḟ, v) added. P's 6×6 itself
        # is kept up to date every sample.
        ("pending_steps", np.int64),
        ("pending_P6", np.float64, (N_ERROR, N_ERROR)),
        ("pending_theta", np.float64, (3, 3)),  # Θθ
        ("pending_bias", np.float64, (3, 3)),  # Θb
        ("pending_U", np.float64, (N_CONSIDER, N_ERROR)),
        ("pending_stage", np.float64, (3, 3)),  # A: on (ε, ḟ, v) of each axis alike
        ("pending_noise", np.float64, (3, 3)),  # N
        ("pending_aided", np.int64),  # U's δθ columns are not zero
        ("health_checks", np.int64),
        ("filters_primed", np.int64),  # the three low-passes hold a sample
        # the magnetometer: 0 heading free (6-D), 1 heading set and the reference
        # field being learned, 2 reference set
        ("mag_state", np.int64),
        ("mag_ref_norm", np.float64),  # µT
        ("mag_ref_dip", np.float64),  # rad
        ("mag_learn_time", np.float64),  # s averaged into the reference so far
        ("mag_candidate_norm", np.float64),  # a disturbed but steady field
        ("mag_candidate_dip", np.float64),
        ("mag_candidate_time", np.float64),  # how long it has been steady, s
        ("mag_lp_norm", np.float64),  # norm and dip low-passed for the disturbance check
        ("mag_lp_dip", np.float64),
        ("mag_clear_time", np.float64),  # how long the field has been undisturbed, s
        ("linear_accel", np.float64, 3),  # this sample's known acceleration, NED; NaN: unknown
        ("t_mag", np.float64),  # time of the last valid magnetometer sample
        ("t_mag_used", np.float64),  # time of the last heading update (or alignment)
        ("mag_disturbances", np.int64),  # samples not used: norm/dip off or gated
        # what the last step did
        ("innovation", np.float64, 2),  # gravity residual before the update, rad
        ("nis", np.float64),  # normalised innovation squared (χ², 2 dof)
        ("accel_used", np.int64),
        ("flags", np.int64),  # StepFlags bits
        ("iterations", np.int64),
        ("at_rest", np.int64),  # rest detected: the bias got a zero-rate update
        ("heading_innovation", np.float64),  # magnetometer azimuth − declination, rad
        ("heading_nis", np.float64),  # its normalised square (χ², 1 dof)
        ("mag_used", np.int64),
        # ω − b of the last sample stepped on: what an estimate is carried forward by
        # over imu_delay (frames.report_attitude_into), held over skipped samples
        ("reported_rate", np.float64, 3),
        # Scratch, so that the hot path allocates nothing. A w_ buffer belongs to the
        # module named in its prefix, w_<module>_… (mavest.estimator.<module>: see
        # SCRATCH_OWNERS); nothing else reads or writes it. A kernel that calls another
        # module's kernel leaves that kernel to work in its own module's scratch; a
        # value one kernel hands to another is an argument, or a named field above —
        # never a buffer both write. Then what a callee may overwrite is its own
        # module's scratch alone (tests/test_layout.py holds the rule).
        # frames: the reset, and covariances between frames
        ("w_frames_R", np.float64, (3, 3)),
        ("w_frames_m33", np.float64, (3, 3)),  # T_θ, or M (world → error frame) to go back
        ("w_frames_n33", np.float64, (3, 3)),
        ("w_frames_W", np.float64, (2, 2)),  # the considered states' turn at a reset
        ("w_frames_q4", np.float64, 4),
        # the nominal before move_nominal moved it: reset_covariance's reference
        ("w_frames_q_from", np.float64, 4),
        # propagation
        ("w_propagation_phi", np.float64, 3),  # the step's rotation ω̂ Δt
        ("w_propagation_R", np.float64, (3, 3)),  # R̄ before the step
        ("w_propagation_R_tilt", np.float64, (3, 3)),
        ("w_propagation_m33", np.float64, (3, 3)),  # Φ_θb
        ("w_propagation_n33", np.float64, (3, 3)),  # Exp(−φ)
        ("w_propagation_q4", np.float64, 4),
        ("w_propagation_p4", np.float64, 4),
        ("w_propagation_G", np.float64, (2, 3)),  # G Φ_θb: ε's rows of Φ
        ("w_propagation_tilt", np.float64, (2, 3)),  # g E W: how δθ moves ε
        ("w_propagation_tilt_before", np.float64, (2, 3)),  # the same before the step
        ("w_propagation_GQ", np.float64, (N_ERROR, 2)),
        ("w_propagation_A", np.float64, (N_STATE_MAX, N_STATE_MAX)),
        ("w_propagation_B", np.float64, (N_STATE_MAX, N_STATE_MAX)),
        ("w_propagation_T", np.float64, (N_STATE_MAX, N_STATE_MAX)),
        ("w_propagation_aid", np.float64, (3, 3)),  # [a]× W of an aided sample
        ("w_propagation_prior_q", np.float64, 4),
        ("w_propagation_sigma_chi", np.float64, (N_SIGMA_MAX, N_STATE_MAX)),
        ("w_propagation_point_q", np.float64, 4),
        ("w_propagation_dx", np.float64, N_STATE_MAX),
        # lowpass
        ("w_lowpass_sample", np.float64, 3),  # R̄ a (less the known acceleration)
        ("w_lowpass_aid", np.float64, (3, 3)),  # [a]× W of an aided sample
        # gravity_update
        ("w_gravity_update_f", np.float64, 3),  # the specific force measured, body frame
        ("w_gravity_update_v3", np.float64, 3),
        ("w_gravity_update_z", np.float64, 3),  # the measured direction
        ("w_gravity_update_Bz", np.float64, (3, 2)),  # its tangent basis
        ("w_gravity_update_R", np.float64, (3, 3)),
        ("w_gravity_update_h", np.float64, 3),
        ("w_gravity_update_rho", np.float64, 3),
        ("w_gravity_update_m33", np.float64, (3, 3)),
        ("w_gravity_update_n33", np.float64, (3, 3)),
        ("w_gravity_update_q4", np.float64, 4),
        ("w_gravity_update_H", np.float64, (2, N_STATE_MAX)),
        ("w_gravity_update_C", np.float64, (N_STATE_MAX, 2)),
        ("w_gravity_update_K", np.float64, (N_STATE_MAX, 2)),
        ("w_gravity_update_S", np.float64, (2, 2)),
        ("w_gravity_update_r", np.float64, 2),
        ("w_gravity_update_W", np.float64, (2, 2)),
        ("w_gravity_update_A", np.float64, (N_STATE_MAX, N_STATE_MAX)),
        ("w_gravity_update_d", np.float64, N_STATE_MAX),
        ("w_gravity_update_m", np.float64, N_STATE_MAX),
        ("w_gravity_update_dx", np.float64, N_STATE_MAX),
        ("w_gravity_update_prior_q", np.float64, 4),
        ("w_gravity_update_prior_b", np.float64, 3),
        ("w_gravity_update_q_before", np.float64, 4),
        ("w_gravity_update_sigma_chi", np.float64, (N_SIGMA_MAX, N_STATE_MAX)),
        ("w_gravity_update_point_q", np.float64, 4),
        ("w_gravity_update_sigma_r", np.float64, (N_SIGMA_MAX, 2)),
        # rest
        ("w_rest_S", np.float64, (3, 3)),
        ("w_rest_S_inv", np.float64, (3, 3)),
        ("w_rest_y", np.float64, 3),
        ("w_rest_K", np.float64, (N_STATE_MAX, 3)),
        ("w_rest_C", np.float64, (N_STATE_MAX, 3)),
        ("w_rest_dx", np.float64, N_STATE_MAX),
        # heading
        ("w_heading_field", np.float64, 3),  # the calibrated field, body frame
        ("w_heading_world_field", np.float64, 3),
        ("w_heading_H", np.float64, 3),
        ("w_heading_H_psi", np.float64, 3),
        ("w_heading_R", np.float64, (3, 3)),
        ("w_heading_M", np.float64, (3, 3)),  # world → error frame
        ("w_heading_C", np.float64, (N_STATE_MAX, 1)),
        ("w_heading_K", np.float64, (N_STATE_MAX, 1)),
        ("w_heading_S", np.float64, (1, 1)),
        ("w_heading_dx", np.float64, N_STATE_MAX),
        # health
        ("w_health_T", np.float64, (N_STATE_MAX, N_STATE_MAX)),
        ("w_health_level_accel", np.float64, 3),  # what a level accelerometer at rest reads
        # alignment
        ("w_alignment_euler", np.float64, 3),
        # online: the step's gyro, accel, magnetometer, linear accel
        ("w_online_sample", np.float64, 12),
    ]
)


def make_coefficients(config: EstimatorConfig) -> np.ndarray:
    """The (1,) coefficient record the kernels read, derived once from a config."""
    c = np.zeros(1, dtype=COEFFICIENTS_DTYPE)
    c["update"] = UPDATE_KINDS.index(config.update)
    c["error"] = ERROR_SIDES.index(config.error)
    c["chart"] = CHARTS.index(config.chart)
    c["reset"] = RESET_POLICIES.index(config.reset)
    c["max_iterations"] = 1 if config.update == "ekf" else config.max_iterations
    c["iteration_tolerance"] = config.iteration_tolerance
    n = N_STATE_MAX if config.accel_lowpass_time > 0.0 else N_ERROR
    c["n_state"] = n
    # scaled unscented transform with α² = spread/n, κ = 0
    spread = config.sigma_spread
    lam = spread - n
    c["sigma_spread"] = spread
    c["sigma_w0_mean"] = lam / spread
    c["sigma_w0_cov"] = lam / spread + (1.0 - spread / n + config.sigma_beta)
    c["sigma_wi"] = 0.5 / spread
    c["gyro_var_density"] = config.gyro_noise_density**2
    c["gyro_scale_var_density"] = config.gyro_scale_noise_density**2
    c["bias_var_density"] = config.gyro_bias_random_walk**2
    c["accel_var_density"] = config.accel_noise_density**2
    c["gravity"] = config.gravity
    c["accel_norm_inflation"] = config.accel_norm_inflation
    c["accel_norm_tolerance"] = config.accel_norm_tolerance
    c["accel_gate"] = config.accel_gate
    c["accel_max_disturbance_time"] = config.accel_max_disturbance_time
    c["divergence_window"] = config.divergence_window
    c["initial_tilt_var"] = config.initial_tilt_sigma**2
    c["initial_heading_var"] = config.initial_heading_sigma**2
    c["initial_bias_var"] = config.initial_bias_sigma**2
    c["initial_bias"] = config.initial_bias
    c["max_dt"] = config.max_dt
    c["max_jump"] = config.max_jump
    c["reorder_window"] = timeline.REORDER_WINDOW
    c["timeline_confirm"] = config.timeline_confirm
    c["timeline_max_step"] = timeline.MAX_STEP
    c["gyro_clip"] = config.gyro_clip
    c["accel_lowpass_time"] = config.accel_lowpass_time
    c["accel_lowpass_damping"] = config.accel_lowpass_damping
    c["lowpass_restart_angle"] = config.accel_lowpass_restart_angle
    c["update_interval"] = (
        1.0 / config.update_rate if config.update_rate > 0.0 and n > N_ERROR else 0.0
    )
    # (the sigma-point prediction is not linear: it keeps propagating every sample)
    c["accumulate"] = int(c["update_interval"][0] > 0.0 and config.update != "sigma_point")
    c["alignment_var"] = config.accel_alignment_sigma**2
    c["imu_delay"] = config.imu_delay
    c["velocity_var"] = config.velocity_sigma**2
    c["velocity_time"] = config.velocity_time
    c["velocity_adapt_time"] = config.velocity_adapt_time
    c["velocity_adapt_gain"] = config.velocity_adapt_gain
    c["velocity_var_min"] = config.velocity_sigma_min**2
    c["aided_velocity_var"] = config.aided_velocity_sigma**2
    c["aided_max_heading_var"] = config.aided_max_heading_sigma**2
    c["rest_detection"] = int(config.rest_detection)
    c["rest_filter_time"] = config.rest_filter_time
    c["rest_gyro_threshold"] = config.rest_gyro_threshold
    c["rest_accel_threshold"] = config.rest_accel_threshold
    c["rest_min_time"] = config.rest_min_time
    c["rest_rate_var"] = config.rest_rate_sigma**2
    c["mag_heading_var_density"] = config.mag_heading_noise_density**2
    c["mag_tilt_leak_time"] = config.mag_tilt_leak_time
    c["mag_reopened_heading_var"] = config.mag_reopened_heading_sigma**2
    c["mag_offsets"] = np.asarray(config.compass_ofs) * MICROTESLA_PER_MILLIGAUSS
    c["mag_soft_iron"] = config.soft_iron
    c["mag_declination"] = config.compass_dec
    c["mag_norm_tolerance"] = config.mag_norm_tolerance
    c["mag_dip_tolerance"] = config.mag_dip_tolerance
    c["mag_gate"] = config.mag_gate
    c["mag_reference_time"] = config.mag_reference_time
    c["mag_reference_adapt_time"] = config.mag_reference_adapt_time
    c["mag_new_reference_time"] = config.mag_new_reference_time
    c["mag_max_rejection_time"] = config.mag_max_rejection_time
    c["mag_recovery_time"] = config.mag_recovery_time
    return c


def new_state(coefficients: np.ndarray) -> np.ndarray:
    """A (1,) state record before the first sample.

    Identity attitude, the configured initial bias, and the initial covariance
    (heading on the vertical, in the world frame): a valid, positive-definite
    estimate even before the first usable sample arrives.
    """
    c = coefficients[0]
    s = np.zeros(1, dtype=STATE_DTYPE)
    s["q"][0, 0] = 1.0
    s["b"][0] = c["initial_bias"]
    s["P"][0, :N_ERROR, :N_ERROR] = np.diag(
        [c["initial_tilt_var"], c["initial_tilt_var"], c["initial_heading_var"]]
        + [c["initial_bias_var"]] * 3
    )
    if c["n_state"] > N_ERROR:  # the vehicle's velocity, the last considered block
        velocity = slice(N_STATE_MAX - N_AXES, N_STATE_MAX)
        s["P"][0, velocity, velocity] = c["velocity_var"] * np.eye(N_AXES)
    s["motion_var"] = c["velocity_var"]
    s["t"] = -np.inf
    s["t_accel"] = -np.inf
    s["t_update"] = -np.inf
    s["step_coefficients_dt"] = np.nan
    s["nis"] = np.nan
    s["heading_innovation"] = np.nan
    s["heading_nis"] = np.nan
    s["t_mag"] = -np.inf
    s["t_mag_used"] = -np.inf
    s["innovation"] = np.nan
    s["t_reopened"] = -np.inf
    s["clip_calm_time"] = -1.0
    s["t_timeline"] = np.nan
    s["unit_t0"] = np.nan
    return s
