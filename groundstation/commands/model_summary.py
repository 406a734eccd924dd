"""What the commands print and write about an identified model: the model file written atomically, the
terminal summary (cost, match degree, parameters, held-out verdicts, the configuration chosen).
Shared by ``identify`` and its frequency-domain variants; not a command itself."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from groundstation.jsonio import write_atomic
from groundstation.sysid.fit_section import Selection
from groundstation.sysid.model import PARAM_NAMES


def write_json(path: Path, doc: dict) -> None:
    write_atomic(path, doc)


def print_model(model, con=None) -> None:
    con = con or Console()
    fit = model.fit
    con.print(f"[bold]{str(fit.algorithm).upper()}[/]: cost F={fit.cost:.4f} (search {fit.search_cost:.4f}), "
              f"fitness {fit.fitness:.4f}, {fit.evaluations} evaluations, {fit.seconds} s")
    t = Table(title="match degree (eq. 19) on the training windows, %")
    for ch in fit.match_degree:
        t.add_column(ch, justify="right")
    t.add_row(*[f"{v:.1f}" for v in fit.match_degree.values()])
    con.print(t)
    p = Table(title="parameters")
    p.add_column("name")
    p.add_column("value", justify="right")
    p.add_column("std error", justify="right")
    p.add_column("note")
    for n in PARAM_NAMES:
        s = model.parameter_std.get(n)
        note = "fixed (not identifiable)" if n in fit.fixed else ("PINNED at bound" if n in model.pinned else "")
        p.add_row(n, f"{model.params[n]:.4g}", "-" if s is None else f"{s:.3g}", note)
    con.print(p)

    for r in fit.fixed_reasons + fit.notes:
        con.print(f"note: {escape(r)}")
    print_verdicts(model, con)


def print_verdicts(model, con) -> None:
    """Held-out match, channels predicted or not, unusable subsystems, bounds, instability, prior."""
    fit = model.fit
    for name, why in fit.pinned_reasons.items():
        con.print(f"[yellow]bound[/]: {name} {why}")
    for u in fit.unstable_modes:
        con.print(f"[yellow]unstable[/]: {u}")
    pr = fit.prior
    if pr is not None and pr.prior_dominated:
        con.print(f"prior ({pr.source}): not determined by this flight, kept near the prior with its "
                  f"uncertainty: {', '.join(pr.prior_dominated)}")
    for line in selection_lines(fit.selection):
        con.print(line)
    ho = fit.heldout
    if ho is not None and ho.has("channel_mean"):
        chans = ", ".join(f"{c} {v:.1f}" for c, v in ho.channel_mean.items())
        con.print(f"held-out match over {ho.k} contiguous folds ({ho.window_s:g}-s windows from the measured "
                  f"states): mean {ho.mean_match:.1f} % ({chans})")
        con.print(f"the model predicts: {', '.join(ho.predicted) or 'no channel'}; "
                  f"it does not predict: {', '.join(ho.not_predicted) or 'none'}")
        for sub in ho.unusable_subsystems:
            con.print(f"[red]unusable[/]: the {sub} subsystem's held-out prediction runs away "
                      f"({'; '.join(f'{f}: {chs}' for f, chs in ho.runaway.items())}): not a model of the aircraft")
    for c in fit.closed_loop:
        con.print(f"closed loop: {c}")
    ch = fit.structure_choice
    if ch is not None:
        con.print(f"structure: {ch.chosen} ({ch.reason})", markup=False)
    for c in fit.command_response:
        con.print(f"stabilised aircraft: {c}", markup=False)


def selection_lines(sel: Selection | None) -> list[str]:
    """What the held-out selection of the configuration compared and chose, one line per candidate."""
    if sel is None:
        return []
    if sel.skipped is not None:
        return [f"configuration not compared by held-out prediction: {sel.skipped}"]
    rows = sel.candidates
    if len(rows) < 2:
        return []
    out = [f"configuration chosen by held-out prediction over {sel.k} folds: {sel.chosen} ({sel.rule})"]
    for r in rows:
        gain = "" if r.gain is None else f", gain {r.gain:+.1f} +- {r.gain_se:.1f} points per fold"
        if r.gain_folds is not None:
            gain += f" (better on {r.gain_folds} of {len(r.fold_score)} folds)"
        why = f"; {r.reason}" if r.reason else ""
        ran = "" if not r.runaway or r.reason else "; runs away on " + ", ".join(r.runaway)
        out.append(f"  {r.name}: held-out mean {r.mean_match:.1f} %{gain}{why}{ran}")
    return out
