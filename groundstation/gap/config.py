"""The diagnosis configuration: every threshold and hyper-parameter of the gap diagnosis, documented.

:class:`DiagnoseConfig` is a frozen dataclass with defaults; the diagnosis reads nothing else.
No field is a level of a signal in physical units fitted to one simulator: levels are multiples
of the noise measured in the data, probabilities, or counts; the two physical floors
(``gust_min_rms_m_s``, ``ground_effect_min_height_span_m``) say so and why. Pure.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DiagnoseConfig:
    """Hyper-parameters of the diagnosis (none is a threshold on a raw signal level)."""

    # ------------------------------------------------------------------ windows and base model
    #: scoring window (s): the held-out unit; every window rotates through the folds
    window_s: float = 3.0
    #: rotating hold-out folds over windows
    folds: int = 3
    #: the start of each window (s) not scored: the initial transient of the states estimated from the
    #: window (at most a quarter of the window)
    window_start_s: float = 0.4
    #: Levenberg-Marquardt polish of the base model on the windows
    refine_iterations: int = 8
    #: fewest windows a diagnosis needs (fewer: "too little in-air data")
    min_windows: int = 6
    #: damping of the per-fold linear re-fit
    ridge: float = 1e-2
    #: starting Levenberg damping (relative to the mean diagonal of the normal matrix) of every
    #: refinement of the base model on all windows (the polish, the re-identifications with an effect
    #: in place, the air-mass scan's)
    refine_ridge: float = 1e-3
    #: independent identification searches when no model is given (CABC, then DE; the lowest
    #: refined cost wins): on one simulated R-50 flight 2 of 14 CABC searches landed in a wrong
    #: basin (roll flapping sign flipped, p match 49 % instead of 95 %), and the diagnosis then
    #: "finds" an effect
    identify_restarts: int = 2
    #: a channel is kept when measured in at least this share of the in-air time (segments lacking
    #: it are left out); below it the channel is "not measured"
    channel_share_min: float = 0.7

    # ------------------------------------------------------------------ excitation and locate
    #: a channel (input or output) whose std is below this many times its own measured noise std
    #: is "too little excitation"
    excitation_snr: float = 3.0
    #: an input whose std is below this (normalised stick units) never moved (a constant logged trim)
    input_std_min: float = 1e-4
    #: held-out normalised RMS error over the noise floor above which a channel departs ...
    gap_ratio_significant: float = 3.0
    #: ... in at least this many excited channels for the gap to be "significant" (one channel
    #: alone is more often a sensor whose noise is not white, e.g. velocities resampled from a
    #: slower estimate)
    gap_channels_min: int = 2

    # ------------------------------------------------------------------ significance
    #: family-wise false-alarm probability of the whole named ``effects`` list
    alpha: float = 0.01
    #: bootstrap resamples of every paired test
    n_boot: int = 2000
    #: bootstrap resamples of a shrink interval (cheaper: an interval, not a tail probability)
    score_n_boot: int = 1000
    #: coarse whole-window check accompanying the block-level test: when the window-level
    #: p-value is below this, the block-level one decides; else the larger of the two
    window_alpha: float = 0.1
    #: practical significance: an effect is named only if it lowers the held-out cost by more than
    #: this percentage AND shrinks the gap on the channels it acts on. Long flights make a 0.2 %
    #: improvement statistically significant; that is not what is wrong with a model (measured:
    #: every effect the simulator injects scores >= 1.5 %, the false calls below 0.3 % or with a
    #: gap that grows on the effect's own channels).
    min_score_pct: float = 1.0

    # ------------------------------------------------------------------ input effects
    #: re-identifications of the base around a significant input effect
    outer_iterations: int = 2
    #: Levenberg-Marquardt iterations of each re-identification with an effect in place
    refit_iterations: int = 3
    #: a deadband must be wider than this many steps of the recorded input's resolution (narrower
    #: is quantisation)
    deadband_min_quanta: float = 3.0

    # ------------------------------------------------------------------ disturbances
    #: smallest air-mass motion (rms, m/s) reported as a gust: the WMO "calm" / "light air" boundary.
    #: A hover model's slow structure error in u or v is soaked up by a fitted air velocity of
    #: 0.05-0.16 m/s (measured on effect-free simulated trex600 and R-50 flights); injected gusts of
    #: 0.65-1.7 m/s sigma were fitted at 1.8-8 m/s. The resolvable level is the larger of this and
    #: ``excitation_snr`` x the velocity sensors' measured white noise.
    gust_min_rms_m_s: float = 0.3
    #: the air-mass scan's within-window cross-validation: initial states and the air velocity are
    #: fitted on alternate chunks of this length (s) and scored on the chunks between them
    gust_chunk_s: float = 0.5
    #: spacing (s) of the knots of the smooth (piecewise-linear) air velocity under which the base is
    #: re-identified for the air-mass scan
    gust_knot_s: float = 1.5
    #: Levenberg-Marquardt iterations re-identifying the base under the per-window air velocity (0:
    #: the base as it is)
    gust_refine_iterations: int = 6
    #: significance of the rank correlation between a window's residual energy and a flight condition
    #: (input amplitude, input rate, height) that the report names as the gap's ``conditions``
    conditions_alpha: float = 0.01
    #: ground effect is untestable when the in-air height spans less than this (m): below a rotor
    #: radius of a small helicopter the excess lift hardly varies over the flight
    ground_effect_min_height_span_m: float = 0.5

    # ------------------------------------------------------------------ rotor vibration
    #: bootstrap resamples of the vibration shrink interval
    vibration_n_boot: int = 500
    #: the chance share of white-noise energy left after fitting sinusoids is never taken below this
    vibration_chance_floor: float = 0.5
    #: a per-window sinusoid fit can raise a window's cost at most by this factor (a fit to pure
    #: noise in a short window is bounded, not unbounded)
    vibration_cost_cap: float = 1.5
    #: periodogram window (s) of the vibration lines in the log's own high-rate gyro (a dataflash IMU
    #: faster than twice the grid)
    native_line_window_s: float = 2.0
    #: lowest frequency (Hz) tested for a line in the log's own high-rate gyro (below it: the flown motion)
    native_line_min_hz: float = 10.0
    #: significance of a line in the log's own high-rate gyro (Bonferroni over bins and axes)
    native_line_alpha: float = 1e-3
    #: how far (amplitude ratio) the model's response may be wrong before a residual line the sticks also
    #: carry is said not to come from them
    line_stick_reach_factor: float = 10.0

    # ------------------------------------------------------------------ unexplained
    #: with nothing named and the gap significant, the first decision calls it "unexplained" when at
    #: least this share of the excess residual energy is in flagged windows; the share rule then calls
    #: any significant gap with nothing named "unexplained" (0 % explained), spread evenly or not
    unexplained_flagged_share: float = 0.5
    #: a structure the linear model cannot have (input asymmetry, amplitude dependence) counts only
    #: when the residual part it explains has an RMS above this many times the noise floor measured
    #: on at least one output (on a long flight a structure a fraction of the noise is significant
    #: and still no departure: 1 = as large as the noise, the rule of data compatibility's findings)
    structure_min_effect_to_noise: float = 1.0

    # ------------------------------------------------------------------ shares and consistency
    #: the verdict names effects unless, together, they remove less than this share (percent) of
    #: the held-out gap above the noise floor with the whole 5-95 % interval (bootstrap over
    #: held-out windows) below it; then the verdict is ``unexplained`` and they are partial findings
    explained_share_min_pct: float = 50.0
    #: bootstrap resamples (over held-out windows) of every share interval
    share_n_boot: int = 1000
    #: a channel's own share is given only where its held-out gap-to-noise ratio (RMS) is at least
    #: this (below it the channel's excess over the noise is a small difference of two large numbers)
    share_min_gap_ratio: float = 1.2
    #: a named effect "changes through the flight" only when the other half's value gives up more
    #: than this fraction of the effect's own gain in a half (besides being rejected at the level)
    consistency_min_loss: float = 0.25

    #: the verdict is reported ``borderline`` (``verdict_margin``) when a test that decided it has its
    #: statistic within this many of its own standard errors of the threshold: a verdict that close
    #: to an edge can come out either way when the same flight is cut into windows half a second later
    borderline_se: float = 1.0

    # ------------------------------------------------------------------ data compatibility
    #: window over which the kinematics are integrated (s): long enough to lever a scale factor,
    #: short enough that the integrated gyro noise (a random walk) stays near the angle noise
    compat_window_s: float = 4.0
    #: a significant sensor scale error is a finding only when the error it makes on its channel
    #: (scale x rms of the channel) exceeds this many times the channel's measured white noise
    compat_min_effect_to_noise: float = 1.0
    #: the horizontal velocity checks' u and v scale errors are pooled into one finding only when
    #: they agree within this many combined standard errors
    compat_z_agree: float = 3.0
    #: a kinematic regression slope beyond this is not a calibration error but two signals that do not
    #: measure the same motion (a held or filtered height, a rate that is not this attitude's derivative)
    compat_max_slope: float = 0.5
    #: input lags (s) over which the residual-input cross-correlation is reported
    xcorr_max_lag_s: float = 1.0

    # ------------------------------------------------------------------ a stabilising controller
    #: prediction windows (s) of the command-response and hover models over the held-out folds (from
    #: the measured states), and of the closed-loop evidence the finding carries
    controller_window_s: float = 5.0
    #: the finding's closed-loop evidence (the gap report's; the model file's closed-loop notes run the
    #: same test with [identify] feedback_*): an input "follows the output error" when its change up to
    #: this lag (s) later correlates with the error ...
    controller_feedback_max_lag_s: float = 1.0
    #: ... beyond this many times 1 / sqrt(effective samples) (the chance level)
    controller_feedback_z: float = 3.0
    #: a fold's prediction error counts at most this many times the signal (a runaway block)
    controller_runaway_cap: float = 3.0

    # ------------------------------------------------------------------ numerical constants
    #: seed of the Monte-Carlo calibration of noise floors for interpolated streams: a property of
    #: the stream's stride, not of the data, so a fixed seed makes it a constant
    noise_calibration_seed: int = 12345
