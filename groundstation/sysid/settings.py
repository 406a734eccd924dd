"""The identification's settings (``[identify]``), apart from the numerics: the configuration, the
identification and the held-out selection of settings (:mod:`groundstation.sysid.select`) share them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class IdentifyConfig:
    """Identification settings (``[identify]`` TOML table). ``maxiter`` None = algorithm default."""

    window_s: float = 3.0
    #: a refinement window starts every this many seconds (0 = every ``window_s``: non-overlapping).
    #: Overlapping windows give the fit more starting points of the same data to predict from: on the
    #: real TREX 550 log 5-s windows every 2.5 s raised the 5-fold held-out match from 27.5 to 31 %.
    window_step_s: float = 0.0
    search_window_s: float = 1.0
    #: on a lossy link, windows restart after each bridged hole of the inputs (from the first sample
    #: measured again) instead of simulating through the straight line into the samples they count
    #: (:mod:`groundstation.sysid.holes`); a flight without bridged inputs has the same windows either way.
    #: Off: at 10 % loss it helped on 50 Hz streams (8/8 key parameters on 6 of 8 flights, against 4) but
    #: did worse on fresh 25 Hz flights (19 key parameters within 10 % on 4 flights, against 25)
    restart_after_holes: bool = False
    #: on a lossy link, the inputs inside the bridged holes are estimated from the outputs around them
    #: with the identified model, and the model refitted on them (:mod:`groundstation.sysid.hole_inputs`),
    #: this many times (0 = off: the holes keep the straight line); a flight without bridged inputs is
    #: identified the same either way. At 10 % bursty loss on 50 Hz streams it kept all 8 key parameters
    #: within 10 % on 7 of 8 flights (seeds 1-8; 4 with the lines) and 4 of 4 fresh ones (2); see
    #: ``hole_input_max_stride`` for slower streams
    hole_input_passes: int = 3
    #: hole inputs: the correction's band, in multiples of the rotor's corner frequency (1/tau_s)/2 pi;
    #: a hole of h s gets ceil(2 h band) half-sine shapes per input
    hole_input_band: float = 1.0
    #: hole inputs: how they are estimated. "stretch": each hole from the outputs of a stretch around it
    #: (``hole_input_horizon_s``) with its own initial state and input offset; "windows": the coefficients
    #: that minimise the refinement's own cost at the model (its windows, initial states and weights, with
    #: the prior), all holes in one linear solve, so that the passes meet at the joint minimum of one
    #: cost. "windows" estimated the inputs worse (each window's states restart, so a hole late in a window
    #: is seen by few outputs) and kept 8/8 key parameters on 5 of 8 flights at 10 % loss, against 7
    hole_input_solve: str = "stretch"
    #: hole inputs: the estimate and the refits count the outputs right after each hole, which data
    #: preparation leaves out while the rotor settles after a straight line (``[prepare]
    #: settle_after_bridge_tau``): with the inputs estimated, they show what the inputs did
    hole_input_count_settling: bool = True
    #: hole inputs: the prior variance of each hole's coefficients is the straight line's error over holes
    #: of its length measured on the inputs within this long either side of it (s; 0: over its whole
    #: segment), so that it follows how busy the inputs are there. 1 s against 0 at 10 % loss (seeds
    #: 1-8): the same 7 of 8 flights with 8/8 key parameters, errors 6 % smaller, rms z 1.05 against 1.14
    hole_input_prior_s: float = 1.0
    #: hole inputs ("stretch"): outputs counted from this long before each hole to this long after it (s)
    hole_input_horizon_s: float = 1.0
    #: hole inputs: the subsystems whose inputs are estimated ("horizontal": lat, lon; "vertical": col,
    #: ped; comma-separated); the others keep the straight line
    hole_input_subsystems: str = "horizontal"
    #: hole inputs: estimated only when the inputs (lat, lon) arrive at least every this many grid steps
    #: (median). A slower stream is a straight line between every two samples on the grid anyway; on
    #: 25 Hz streams the estimate changed the key parameters up and down (84 within 10 % on 12 flights
    #: at 10 % loss, against 83 with the lines) and made the standard errors less honest
    hole_input_max_stride: float = 1.5
    #: on a lossy link, the standard errors include what the straight lines bridged over the holes of the
    #: inputs that are not estimated (``hole_input_*``) may be wrong by: each hole's line error, measured
    #: per half-sine shape (``hole_input_band``) on the received inputs within ``hole_input_prior_s`` of
    #: it, through the model's response and the fit
    #: (:meth:`~groundstation.sysid.hole_inputs.WindowHoles.line_covariance`). No estimate changes. On
    #: 25 Hz streams at 10 % bursty loss (seeds 1-8) it took the key parameters' rms z from 1.20 to 0.98
    #: (loss-free 0.90): the standard errors widen x1.34, where the samples not counted alone predict x1.18
    line_error_in_std: bool = True
    search_stride: int = 3
    refine_starts: int = 9
    #: independent searches per subsystem, each screened and refined; the lowest refined cost wins.
    #: One colony can settle in a wrong basin (a simulated R-50 flight: L_b with the wrong sign, cost
    #: 0.98 against 0.36 from most other seeds) and the search cost does not tell the basins apart;
    #: the refined cost does. Each restart costs a whole search and refinement; two (CABC, then DE)
    #: is the default everywhere (command line, service, diagnosis): a wrong basin costs more than
    #: a second search.
    search_restarts: int = 2
    #: optimiser of the searches after the first ("" = the same as the first). A different method is
    #: a more independent second opinion than another seed: on the R-50 flight above both CABC
    #: restarts of one seed stream agreed on the wrong basin, DE (3 seeds) found the right one, and
    #: on the trex600 DE reached the same refined cost in 60 % of CABC's time.
    restart_algorithm: str = "de"
    #: bee colonies (cabc, abc; :mod:`groundstation.sysid.optimizers`): food sources (employed bees)
    colony_size: int = 20
    #: bee colonies: trials without improvement before a food source is abandoned (the scout)
    colony_limit: int = 5
    #: cabc's chaotic search around the best source (the paper's step 7): points per iteration
    chaos_points: int = 10
    #: cabc: the chaotic search's first radius, a fraction of each parameter's range (it shrinks
    #: geometrically to ``chaos_radius_end`` over the iterations)
    chaos_radius0: float = 0.05
    #: cabc: the chaotic search's last radius (a fraction of the range)
    chaos_radius_end: float = 1e-4
    #: ga: population size
    ga_population: int = 20
    #: ga: probability of the blend crossover of two parents
    ga_crossover: float = 0.8
    #: ga: probability that a child mutates (one random gene)
    ga_mutation: float = 0.2
    #: ga: best individuals kept unchanged each generation
    ga_elite: int = 2
    #: ga: tournament size of the parent selection
    ga_tournament: int = 2
    #: ga: standard deviation of a mutation, a fraction of the gene's range
    ga_mutation_scale: float = 0.1
    #: de: population per free parameter (scipy's ``popsize``)
    de_popsize: int = 1
    #: de: scipy's relative convergence tolerance ``tol``: the search stops once the spread of its
    #: population's costs is at most this fraction of their mean (0 = every iteration runs)
    de_tol: float = 0.0
    screen_max_nfev: int = 5
    maxiter: int | None = None
    maxfev: int | None = None
    refine_passes: int = 2
    refine_max_nfev: int = 60
    estimate_all_initial: bool = True
    varpro: bool = True
    #: the vertical/yaw searches' iterations over the horizontal ones'. 0.5: half as many. Twice as
    #: many (an earlier default) cost 0.8 s of CPU per simulated flight and changed no model: the
    #: same refined cost and parameters within 0.001 % on five simulated trex600 and two R-50
    #: flights, and the same model of the real TREX 550 log (seeds 0 and 1); the refinement starts
    #: from the screened best points, and the few vertical parameters are found by either search.
    #: Half as many as the horizontal ones (1 before) saves about 0.2 s of CPU per flight and gives the
    #: same models (parameters within 3e-7 relative, key ones within 1e-9, the same held-out verdicts)
    #: on three simulated trex600 and two R-50 flights and on the TREX 550 log (identification seeds 0-2)
    vertical_iter_factor: float = 0.5
    estimate_trim: bool = True
    #: velocity channels (of u, v, w) whose measured kinematic/gravity terms enter as known forcing in the
    #: refinement (``kinematic_forcing`` of simulate); "" = none. Default w: on the trex600 sim flight the
    #: heave terms ``q u - p v + g (cos phi cos theta - 1)`` were what biased Z_col (7-11 % low, worse
    #: with less collective excitation); u and v terms did not help (they bias X_u: the rotor terms
    #: ``T sin a_s`` they would need are not measured).
    kinematic_forcing: str = "w"
    #: residual weighting of the refinement per channel: "noise" (the residual RMS, maximum likelihood)
    #: or "signal" (the signal's spread, the paper's eq. 11); see :func:`groundstation.sysid.refine.refine`
    channel_weighting: str = "noise"
    #: further refinement starts besides the search's, comma-separated: "prior" (the prior's nominal),
    #: "zero" (every parameter 0, inside the bounds); the lowest refined (MAP) cost wins. On real flights
    #: the search's best point on short windows can sit in a basin that predicts worse than these.
    extra_starts: str = ""
    #: how the data rows count against an aircraft file's prior: "logged" (every sample; the prior
    #: holds what the flight does not determine) or "effective" (samples over the residual's
    #: autocorrelation time: a stronger prior). See :func:`groundstation.sysid.refine.refine`.
    prior_weighting: str = "logged"
    #: the prior's standard deviations are multiplied by this (a weaker prior above 1): one of the
    #: settings the held-out selection can compare (choosing the prior's weight by cross-validation)
    prior_scale: float = 1.0
    #: other configurations to compare with this one by held-out prediction, ";"-separated: a preset
    #: name (see :data:`groundstation.sysid.select.PRESETS`) or ``key=value,key=value`` overrides of
    #: these fields. "" = no comparison. Each is refined from this configuration's model and scored
    #: over ``select_folds`` contiguous folds; one replaces this configuration only when it predicts
    #: the held-out blocks better by more than the folds' spread (:mod:`groundstation.sysid.select`).
    #: "|" starts a further round, applied to the winner, that runs only when the round before it
    #: switched: the default tries overlapping windows only once the 5-s prediction fit has won.
    select_candidates: str = "predictive | window_step_s=2.5"
    #: contiguous folds of the selection (< 2 = no selection)
    select_folds: int = 5
    #: a candidate replaces the configuration when its mean held-out gain over the folds exceeds this many
    #: standard errors of that gain (the "one-standard-error rule" of cross-validated model choice:
    #: Hastie, Tibshirani & Friedman, ESL 7.10), or it gains on every fold (3 or more)
    select_gain_z: float = 1.0
    #: a fold's score is the mean over channels of the held-out match (%), each channel floored at this
    #: (a prediction that runs away counts as twice as bad as predicting no motion, so one fold cannot
    #: swamp the others)
    select_match_floor_pct: float = -100.0
    #: Jacobians per subsystem of each fold's refit in the selection (a local polish from a whole-flight
    #: fit: on a simulated flight 4, 8, 20 and 60 gave the same held-out scores to 0.3 %; on the real
    #: TREX 550 log fewer make a candidate whose screening fit is far from its optimum look worse, which
    #: keeps the configuration: the cautious side). 6 keeps the selection within half the identification's time.
    select_refit_nfev: int = 6
    #: a held-out fold's refit (the selection's folds and the held-out check) stops once an accepted step
    #: lowers its cost by less than this fraction: far below the cost's own sampling spread (sqrt(2 / N)
    #: relative, N the independent residual samples: about 1e-2 on a 150-s flight), so the steps it saves
    #: cannot move a held-out score beyond the folds' noise; a refit from a start far from the fold's
    #: optimum still takes every step ``select_refit_nfev`` allows (1e-10: the full refinement's own tolerance).
    fold_refit_ftol: float = 1e-4
    #: held-out prediction (the selection's folds and the held-out check): each left-out block is
    #: predicted in windows of this length (s), each from its measured initial state
    heldout_window_s: float = 5.0
    #: a channel's held-out prediction "runs away" when its error is more than this many times the
    #: signal itself (the subsystem is then not usable)
    runaway_factor: float = 3.0
    #: the closed-loop notes of the model file (``fit.closed_loop``, written by identify; the diagnosis's
    #: stabilising-controller finding runs the same test with [diagnose] controller_window_s and
    #: controller_feedback_*): the model's output error is simulated in windows of this length (s) from
    #: the measured states ...
    feedback_window_s: float = 5.0
    #: ... and an input "follows" it when the input's change up to this lag (s) later correlates with it ...
    feedback_max_lag_s: float = 1.0
    #: ... beyond this many times 1 / sqrt(effective samples) (the chance level)
    feedback_z: float = 3.0
    #: two refinement starts taken from the search's best points are at least this far apart (the RMS
    #: over the parameters of their difference as a fraction of each parameter's search range); a later
    #: search whose screened winner is this close to an earlier one's, with screened scores within their
    #: sampling spread, shares that one's full refinement
    refine_start_min_dist: float = 0.2
    #: what the inputs are (the aircraft file's ``[inputs] kind``): "blade" (the eq.-8 hover model only),
    #: "rate_command" / "attitude_command" (also the stabilised aircraft's command-response structure,
    #: which then predicts), "unknown" (both, held-out prediction chooses):
    #: :mod:`groundstation.sysid.structure`
    input_kind: str = "blade"
    #: the command-response structure's fit: windows of this length (s), each from its measured
    #: initial state
    command_window_s: float = 5.0
    #: the command-response structure's fit: a window starts every this many seconds
    command_step_s: float = 2.5
    #: least-squares iterations per axis of the command-response fit (each delay of the grid)
    command_maxiter: int = 60
    #: one constant offset per input in each refinement window (and each held-out window), estimated
    #: with the window's unmeasured initial states: a stabiliser's integrator trim, or a stick held away
    #: from its logged value, that changes from window to window. Replaces ``estimate_trim``'s single
    #: offset per flight. The model file records it (``window_input_offsets``), and every prediction of
    #: the model then estimates them too
    window_input_offsets: bool = False

    @property
    def input_offsets(self) -> bool:
        """Input offsets are estimated at all (one per flight or one per window)."""
        return self.estimate_trim or self.window_input_offsets

    @property
    def flight_trim(self) -> bool:
        """One input offset per flight (the trim): ``estimate_trim`` without per-window offsets."""
        return self.estimate_trim and not self.window_input_offsets

    def search_options(self, algorithm: str) -> dict[str, Any]:
        """The keyword arguments of ``algorithm``'s optimiser (:data:`groundstation.sysid.optimizers.ALGORITHMS`)
        from these settings."""
        bees: dict[str, Any] = {"colony_size": self.colony_size, "limit": self.colony_limit}
        options: dict[str, dict[str, Any]] = {
            "cabc": {**bees, "chaos_points": self.chaos_points, "radius0": self.chaos_radius0,
                     "radius_end": self.chaos_radius_end},
            "abc": bees,
            "ga": {"population": self.ga_population, "crossover": self.ga_crossover, "mutation": self.ga_mutation,
                   "elite": self.ga_elite, "tournament": self.ga_tournament, "mutation_scale": self.ga_mutation_scale},
            "de": {"popsize": self.de_popsize, "tol": self.de_tol}}
        return options.get(algorithm, {})
