"""Every threshold of the identification and the diagnosis is a configuration field.

A number written as a default in a function signature of ``groundstation.gap`` or
``groundstation.sysid`` is a setting nobody can change from the configuration file. Such a default
must be the configuration's own (``DiagnoseConfig.alpha``, ``IdentifyConfig.heldout_window_s``), or
be listed below with why it is not a threshold. Reads the source (AST); imports nothing heavy.
"""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / "groundstation"

#: "module.function.parameter" -> why its literal default is not a setting of the analysis
NOT_SETTINGS = {
    # seeds: every caller passes the configuration's seed ([identification] seed)
    "controller.stabilising_controller.seed": "seed",
    "diagnose.diagnose.seed": "seed",
    "diagnose.run_diagnosis.seed": "seed",
    "identify.identify.seed": "seed",
    "structure.fit_axis.rng": "seed",
    "structure.identify_command.rng": "seed",
    # indices, shapes, memory and presentation
    "evaluate.heldout_many.chunk_bytes": "memory per block of the computation, not a result",
    "evaluate.__init__.size": "base states a Jacobian memo keeps (memory, not a result)",
    "linsim.simulate.start": "first sample index",
    "fingerprints.kinematic_rate_offsets.start": "samples a finite difference loses at a window's edge",
    "fingerprints._line_stats.half": "periodogram bins of a line's local background (the estimator's shape)",
    "fingerprints._line_stats.guard": "periodogram bins left out next to a line (the taper's leakage)",
    "hypotheses.deadzone.centre": "an argument of the deadband function, not a setting",
    "hypotheses._air_columns.n_knots": "every caller passes it (from [diagnose] gust_knot_s)",
    "fingerprints.spectral_lines.alpha": "every caller passes the level ([diagnose] alpha, or the shares' own)",
    "cost.make_windows.step_s": "every caller passes [identify] window_step_s (0 = non-overlapping windows)",
    "structure.command_windows.step_s": "0 = non-overlapping windows; its callers pass the step",
    "holes.restart_windows.step_s": "as cost.make_windows (0 = non-overlapping windows); identify passes [identify] window_step_s",
    "pictures.gap_pictures.max_effects": "how many effects the report draws",
    "report._r.nd": "digits written to the report",
    "report.frequency_rows.limit": "rows of the report's frequency table",
    "plots.plot_fit.max_windows": "windows drawn",
    # numerical guards and tolerances, physical constants
    "locate.merge_intervals.gap_s": "rounding guard when merging touching intervals",
    "heldout.unstable_modes.min_real_1_s": "rounding guard: an eigenvalue on the imaginary axis is not unstable",
    "refine.levenberg_marquardt.ftol": "convergence tolerance of the numerics",
    "refine.refine.ftol": "convergence tolerance of the numerics (a fold's refit passes [identify] fold_refit_ftol)",
    "refine.levenberg_marquardt.xtol": "convergence tolerance of the numerics",
    "refine.levenberg_marquardt.gtol": "convergence tolerance of the numerics",
    "refine.residual_tau.max_lag": "autocorrelation lags summed for the effective sample count (numerics)",
    "refine.coloured_cov.max_lag": "autocorrelation lags of the coloured-residual covariance (numerics)",
    "refine.coloured_std.max_lag": "autocorrelation lags of the coloured-residual covariance (numerics)",
    "refine._sandwiches.max_lag": "autocorrelation lags of the coloured-residual covariance (numerics)",
    "simulate.__init__.ridge": "relative Tikhonov weight keeping unobservable initial states finite (numerics)",
    "simulate.kinematic_forcing.g": "gravity (m/s^2)",
    "optimizers.logistic_step.mu": "the logistic map's chaotic parameter (the paper's method: 4)",
    "optimizers.logistic_step.eps": "keeps the logistic map off its fixed points",
    "optimizers._avoid_bad.eps": "keeps the logistic map off its fixed points",
    "hole_inputs.estimate_hole_inputs.sweeps": "Gauss-Seidel sweeps over a window's holes, each hole with "
                                               "the others as estimated so far; the passes that matter are "
                                               "[identify] hole_input_passes",
    "structure.predict_command.window_s": "its callers pass the window ([identify] heldout_window_s, "
                                          "[diagnose] controller_window_s)",
}
#: the optimisers are a library with scipy's shape: their own defaults; the identification passes
#: every hyper-parameter from [identify] (``IdentifyConfig.search_options``, checked below)
LIBRARIES = ("optimizers.minimize_",)


def _literal_defaults() -> list[tuple[str, str]]:
    out = []
    for pkg in ("gap", "sysid"):
        for path in sorted((ROOT / pkg).glob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    continue
                a = node.args
                pos = a.posonlyargs + a.args
                pairs = list(zip(pos[len(pos) - len(a.defaults):], a.defaults, strict=True))
                pairs += [(k, d) for k, d in zip(a.kwonlyargs, a.kw_defaults, strict=True) if d is not None]
                for arg, d in pairs:
                    v = d.operand if isinstance(d, ast.UnaryOp) else d
                    if isinstance(v, ast.Constant) and type(v.value) in (int, float):
                        out.append((f"{path.stem}.{node.name}.{arg.arg}", ast.unparse(d)))
    return out


def test_no_threshold_hides_in_a_signature_default():
    """A new literal default in gap/ or sysid/ fails here: make it a field of DiagnoseConfig or
    IdentifyConfig (and default.toml, docs/configuration.md) and use ``Config.field`` as the default."""
    found = _literal_defaults()
    new = [f"{k} = {v}" for k, v in found if k not in NOT_SETTINGS and not k.startswith(LIBRARIES)]
    assert not new, f"literal defaults that are no configuration field: {new}"
    stale = sorted(set(NOT_SETTINGS) - {k for k, _ in found})
    assert not stale, f"listed in NOT_SETTINGS but gone: {stale}"


def test_the_identification_passes_every_search_setting_to_its_optimiser():
    from groundstation.sysid.optimizers import ALGORITHMS
    from groundstation.sysid.settings import IdentifyConfig

    cfg = IdentifyConfig()
    for name in ("cabc", "abc", "ga", "de"):
        params = inspect.signature(ALGORITHMS[name]).parameters
        numeric = {p for p, v in params.items() if type(v.default) in (int, float) and p not in ("maxiter", "maxfev")}
        opts = cfg.search_options(name)
        assert set(opts) == numeric, name
        assert all(opts[p] == params[p].default for p in opts), f"{name}: a default of [identify] differs"
