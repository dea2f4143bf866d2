"""The `calibrate` command line.

Every verb works with no arguments (on the built-in scenes), takes ``--json``
(machine-readable output on stdout, nothing else there), shows progress on
stderr for anything slow, and writes files atomically.  A user mistake prints
one line ``calibrate: error: ...`` and exits with status 2; Ctrl-C exits 130.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from ._io import UserError

EXIT_USER_ERROR = 2
EXIT_FIT_FAILED = 3
EXIT_INTERRUPTED = 130
DEFAULT_CALIBRATION = "calibration.json"


class _Parser(argparse.ArgumentParser):
    """argparse whose errors are one line and exit 2, like every other user mistake."""

    def error(self, message):
        raise UserError(message)


#: Width of tables when the output is not a terminal (a file or a pipe).
PIPE_WIDTH = 120


def _console(stderr: bool = False):
    """Reports go to stdout (tables) or stderr (progress, warnings); wide when piped."""
    from rich.console import Console

    stream = sys.stderr if stderr else sys.stdout
    return Console(file=stream, highlight=False, width=None if stream.isatty() else PIPE_WIDTH)


def _stderr_is_tty() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # a replaced or closed stream
        return False


class _Progress:
    """A rich progress bar on stderr, fed by ``progress(done, total, label)`` callbacks.

    Drawn only when ``enabled`` and stderr is a terminal: a log file or a pipe gets
    no bar (and a caller reading stderr sees only warnings and errors).
    """

    def __init__(self, enabled: bool, description: str):
        self.enabled = enabled and _stderr_is_tty()
        self.description = description
        self._bar = None
        self._task = None

    def __enter__(self):
        if self.enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), TextColumn("{task.fields[label]}"), console=_console(stderr=True),
                                 transient=True)
            self._bar.__enter__()
            self._task = self._bar.add_task(self.description, total=None, label="")
        return self

    def __call__(self, done: int, total: int, label: str = "") -> None:
        if self._bar is not None:
            self._bar.update(self._task, completed=done, total=total or None, label=label[:48])

    def status(self, text: str) -> None:
        if self._bar is not None:
            self._bar.update(self._task, description=text[:60])

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.__exit__(*exc)


def positive_number(what: str = "the value"):
    """An argparse type: a finite number > 0, with messages naming ``what``."""

    def parse(text: str) -> float:
        try:
            x = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number, got {text!r}") from None
        if not (math.isfinite(x) and x > 0):
            raise argparse.ArgumentTypeError(f"{what} must be a positive number, got {text!r}")
        return x

    return parse


#: Binary multiples a byte size may end with (``--cache 16MiB``, ``12M``, ``512k``).
BYTE_UNITS = {"": 1, "b": 1, "k": 2**10, "kib": 2**10, "m": 2**20, "mib": 2**20, "g": 2**30, "gib": 2**30}


def byte_size(text: str) -> int:
    """An argparse type: a number of bytes, as bytes or with a binary unit (k/KiB, M/MiB, G/GiB),
    at least a cache line (64 bytes) and under 2^50."""
    t = text.strip()
    i = len(t)
    while i > 0 and t[i - 1].isalpha():
        i -= 1
    number, unit = t[:i].strip(), t[i:].lower()
    if unit not in BYTE_UNITS:
        raise argparse.ArgumentTypeError(f"the size's unit must be one of k, KiB, M, MiB, G, GiB (or none: bytes), "
                                         f"got {text!r}")
    try:
        x = float(number) * BYTE_UNITS[unit]
    except ValueError:
        raise argparse.ArgumentTypeError(f"the size must be a number of bytes, e.g. 16MiB, got {text!r}") from None
    if not (math.isfinite(x) and 64 <= x < 2**50):
        raise argparse.ArgumentTypeError(f"the size must be from 64 bytes to under 1 PiB, got {text!r}")
    return int(round(x))


def seed_number(text: str) -> int:
    """An argparse type: a random seed, a whole number from 0 to 2^32 - 1."""
    try:
        x = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"the seed must be a whole number, got {text!r}") from None
    if not 0 <= x < 2**32:
        raise argparse.ArgumentTypeError(f"the seed must be from 0 to 2^32 - 1, got {text!r}")
    return x


def _print_json(obj) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, allow_nan=False) + "\n")


def _fmt_est(est) -> tuple[str, str, str]:
    if est is None:
        return ("-", "-", "-")
    return (f"{est['median']:.4g}", f"[{est['ci68'][0]:.4g}, {est['ci68'][1]:.4g}]" if "ci68" in est else "-",
            f"[{est['ci95'][0]:.4g}, {est['ci95'][1]:.4g}]")


CONSTANT_LABELS = [("t_setup_ns", "T_setup (ns/ray)"), ("t_step_ns", "T_step (ns/cell)"),
                   ("t_int_ns", "T_int (ns/test)"), ("t_sub_ns", "T_sub (ns/subgrid)"),
                   ("t_mem_ns", "T_mem (ns/line beyond cache)"), ("t_visit_ns", "T_visit (ns/occupied cell or change)"),
                   ("t_hit_ns", "T_hit (ns/ray that hits)"), ("ratio", "r = T_int/T_step")]


def _ratio_line(r: dict, label: str = "r = T_int/T_step") -> str:
    half = 0.5 * (r["ci95"][1] - r["ci95"][0]) / r["median"]
    return (f"{label} = {r['median']:.3f}, 95% interval [{r['ci95'][0]:.3f}, {r['ci95'][1]:.3f}] "
            f"(half-width {100 * half:.1f}% of the median)")


def _constants_by_rays(cal: dict) -> dict:
    """Ray set -> constants of each ray set fitted alone (``by_rays``); {} when there are none."""
    return {name: entry["constants"] for name, entry in (cal.get("by_rays") or {}).items()}


def _by_rays_table(cal: dict, title: str):
    """The constants of each ray set fitted alone (``by_rays``), or None when there are none."""
    from rich.table import Table

    by_rays = cal.get("by_rays") or {}
    if not by_rays:
        return None
    mare = (cal.get("meta") or {}).get("holdout_mare_by_rays") or {}
    table = Table(title=title)
    table.add_column("constant")
    for name in by_rays:
        table.add_column(f"{name} rays: median [95%]", justify="right")
    for key, label in CONSTANT_LABELS:
        cells = []
        for entry in by_rays.values():
            est = entry["constants"].get(key)
            cells.append("-" if est is None else f"{est['median']:.4g} {_fmt_est(est)[2]}")
        table.add_row(label, *cells)
    if mare:
        table.add_row("held-back error (median)", *[f"{100 * mare[n]:.1f}%" if n in mare else "-" for n in by_rays])
    return table


def _print_cross_validated(console, cal: dict) -> None:
    """The run's cross-validated error (``meta.cv_mare``), when the calibration has one."""
    meta = cal.get("meta") or {}
    if meta.get("cv_mare") is None:
        return
    n_ctx = sum(1 for m in cal["measurements"] if m["kind"] == "in_context" and m["values_ns"])
    per_set = ", ".join(f"{n} {100 * v:.1f}%" for n, v in (meta.get("cv_mare_by_rays") or {}).items())
    console.print(f"cross-validated over all {n_ctx} in-context configurations ({meta.get('cv_folds')} folds, each "
                  f"predicted by a fit to the others): {100 * meta['cv_mare']:.1f}%"
                  + (f" ({per_set})" if per_set else ""))


def _constants_table(cal: dict, title: str):
    from rich.table import Table

    table = Table(title=title)
    table.add_column("constant")
    table.add_column("median", justify="right")
    table.add_column("68% interval", justify="right")
    table.add_column("95% interval", justify="right")
    table.add_column("isolated (95%)", justify="right")
    iso = cal.get("isolated") or {}
    for key, label in CONSTANT_LABELS:
        med, c68, c95 = _fmt_est(cal["constants"].get(key))
        i = iso.get(key)
        iso_txt = f"{i['median']:.4g} {_fmt_est(i)[2]}" if i else "-"
        table.add_row(label, med, c68, c95, iso_txt)
    return table


# -- verbs -------------------------------------------------------------------------

def cmd_run(args) -> int:
    from .run import run_calibration

    out = Path(args.out)
    console = _console()
    t0 = getattr(args, "started", None) or time.monotonic()
    with _Progress(not args.quiet, "measuring") as bar:
        result = run_calibration(out, budget_s=args.budget, target_rel_width=args.target_rel_width,
                                 intersector=args.intersector, seed=args.seed, resume=args.resume,
                                 progress=bar, status=bar.status, started=t0, cache_bytes=args.cache)
    cal = result.calibration
    if args.json:
        _print_warnings(result.warnings)
        _print_json(dict(constants=cal["constants"], wall_s=result.wall_s, holdout_mare=result.holdout_mare,
                         holdout_mare_pooled=result.holdout_mare_pooled,
                         holdout_mare_by_rays=result.holdout_mare_by_rays or {},
                         cv_mare=None if math.isnan(result.cv_mare) else result.cv_mare,
                         cv_mare_by_rays=result.cv_mare_by_rays or {},
                         constants_by_rays=_constants_by_rays(cal),
                         constants_isolated=cal.get("isolated") or {},
                         ratio_rel_width=result.ratio_rel_width, cache_bytes=cal["meta"].get("cache_bytes"),
                         warnings=list(result.warnings), out=str(out)))
        return 0
    console.print(_constants_table(cal, f"calibration of this host ({cal['meta']['intersector']} intersector), "
                                        "all ray sets"))
    table = _by_rays_table(cal, "each ray set fitted alone (what predict --rays uses)")
    # With ray sets fitted alone, the pooled fit is not the one predict, export and compare
    # plan with (each takes a ray set's, isotropic by default): its r is labelled so.
    console.print(_ratio_line(cal["constants"]["ratio"], "r = T_int/T_step" if table is None else
                              "all ray sets pooled (not what predict, export and compare use): r"))
    if table is not None:
        console.print(table)
        for name, entry in cal["by_rays"].items():
            console.print(_ratio_line(entry["constants"]["ratio"], f"{name} rays: r"))
    if (cal.get("isolated") or {}).get("ratio"):
        console.print(_ratio_line(cal["isolated"]["ratio"], "isolating suites (a step's and a test's marginal "
                                                            "costs, in cache): r"))
    n_held = sum(1 for m in cal["measurements"] if m.get("held_back"))
    console.print(f"held-back configurations ({n_held}): median absolute relative error of predicted batch "
                  f"times {100 * result.holdout_mare:.1f}%"
                  + (f" (each by its ray set's constants; by the pooled constants "
                     f"{100 * result.holdout_mare_pooled:.1f}%)" if result.holdout_mare_by_rays else ""))
    _print_cross_validated(console, cal)
    if cal["meta"].get("cache_bytes"):
        console.print(_cache_line(cal["meta"]))
    console.print(f"wall time {time.monotonic() - t0:.1f} s; written to {out}")
    _print_warnings(result.warnings)
    return 0


def _cache_line(meta) -> str:
    """The memory term's cache size as a run chose it: the size, how it was chosen, and the sizes
    within ten log units of the best score (the choice flips between close ones from run to run)."""
    line = f"memory term counted against a {meta['cache_bytes'] / 2**20:.4g} MiB cache"
    scores = {int(c): v for c, v in (meta.get("cache_scores") or {}).items() if v is not None}
    if scores:
        best = max(scores.values())
        near = ", ".join(f"{c / 2**20:.4g} MiB {v - best:+.1f}" for c, v in sorted(scores.items()) if v >= best - 10)
        line += (f", chosen by the fit among {len(meta['cache_scores'])} sizes (log posterior against the best: "
                 f"{near})")
    elif meta.get("cache_source"):
        line += f": {meta['cache_source']}"
    return line


def _print_warnings(warnings: list) -> None:
    """A run's warnings on stderr, the first ten (all of them are in --json's ``warnings``)."""
    for w in warnings[:10]:
        _console(stderr=True).print(f"[yellow]warning:[/yellow] {w}")
    if len(warnings) > 10:
        _console(stderr=True).print(f"[yellow]... and {len(warnings) - 10} more warnings in the file's "
                                    "measurements[/yellow]")


def cmd_fit(args) -> int:
    from . import calfile
    from ._io import check_writable

    src = Path(args.file)
    cal = calfile.load(src)
    out = check_writable(Path(args.out) if args.out else src)  # before fitting, not after
    from .run import refit_calibration

    with _Progress(not args.quiet, "fitting") as _:
        new, warnings = refit_calibration(cal, seed=args.seed, cache_bytes=args.cache)
    calfile.save(out, new)
    meta = new.get("meta", {})
    if args.json:
        _print_warnings(warnings)
        _print_json(dict(constants=new["constants"],
                         constants_by_rays=_constants_by_rays(new),
                         constants_isolated=new.get("isolated") or {},
                         holdout_mare=meta.get("holdout_mare"), cv_mare=meta.get("cv_mare"),
                         cache_bytes=calfile.cache_bytes_of(new), warnings=warnings, out=str(out)))
    else:
        console = _console()
        console.print(_constants_table(new, f"re-fit of {src.name}"))
        table = _by_rays_table(new, "each ray set fitted alone")
        if table is not None:
            console.print(table)
        if meta.get("holdout_mare") is not None:
            console.print(f"held-back median absolute relative error: {100 * meta['holdout_mare']:.1f}% "
                          f"(pooled constants: {100 * meta['holdout_mare_pooled']:.1f}%)")
        if meta.get("cv_mare") is not None:
            console.print(f"cross-validated ({meta.get('cv_folds', 5)} folds): {100 * meta['cv_mare']:.1f}%")
        if args.cache is not None:
            console.print(f"cache lines counted against {args.cache / 2**20:.4g} MiB (--cache)")
        console.print(f"written to {out}")
        _print_warnings(warnings)
    return 0


def cmd_show(args) -> int:
    from . import calfile

    cal = calfile.load(Path(args.file))
    if args.plot:
        from ._io import check_writable
        from .plots import calibration_plots, plot_paths

        for path in plot_paths(Path(args.plot)):  # all, before drawing: never some plots of three
            check_writable(path)
        written = calibration_plots(cal, Path(args.plot))
    else:
        written = []
    if args.json:
        _print_json(dict(constants=cal["constants"], isolated=cal.get("isolated", {}),
                         constants_by_rays=_constants_by_rays(cal),
                         diagnostics=cal["diagnostics"], meta=cal.get("meta", {}), plots=[str(p) for p in written]))
        return 0
    console = _console()
    console.print(_constants_table(cal, f"{args.file}"))
    table = _by_rays_table(cal, "each ray set fitted alone (what predict --rays uses)")
    if table is not None:
        console.print(table)
    fp = cal["fingerprint"]
    console.print(f"host: {fp.get('cpu_model')}, {fp.get('logical_cores')} cores, governor {fp.get('governor')}, "
                  f"huge pages {fp.get('huge_pages')}, measured {fp.get('date_utc')}")
    meta = cal.get("meta", {})
    if meta.get("holdout_mare") is not None:
        console.print(f"held-back median absolute relative error: {100 * meta['holdout_mare']:.1f}%"
                      + (f" (pooled constants: {100 * meta['holdout_mare_pooled']:.1f}%)"
                         if meta.get("holdout_mare_pooled") is not None and meta.get("holdout_mare_by_rays")
                         else ""))
    _print_cross_validated(console, cal)
    d = cal["diagnostics"]
    console.print(f"posterior: {d.get('n_steps')} steps, acceptance {d.get('acceptance', float('nan')):.2f}, "
                  f"converged {d.get('converged')}")
    for p in written:
        console.print(f"plot written to {p}")
    return 0


def cmd_scenes(args) -> int:
    from ._grid import Scene
    from .scenes import BUILTIN

    rows = []
    for name, (description, _) in BUILTIN.items():
        scene = Scene.builtin(name)
        st = scene.stats
        rows.append(dict(name=name, description=description, triangles=scene.n_triangles,
                         box=[float(x) for x in scene.box_hi - scene.box_lo], k=float(st.k),
                         aspect_median=float(st.aspect_median), aspect_p95=float(st.aspect_p95),
                         watertight=bool(st.watertight), scene_class=_scene_class(st)))
    if args.json:
        _print_json(rows)
        return 0
    from rich.table import Table

    table = Table(title="built-in scenes (use a name wherever a mesh file is accepted)")
    for col in ("name", "triangles", "box", "k", "AR median / p95", "watertight", "class"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["name"], f"{r['triangles']:,}", " x ".join(f"{x:.3g}" for x in r["box"]), f"{r['k']:.2f}",
                      f"{r['aspect_median']:.1f} / {r['aspect_p95']:.1f}", "yes" if r["watertight"] else "no",
                      r["scene_class"])
    _console().print(table)
    return 0


def _scene_class(stats) -> str:
    from models.stats import scene_class

    c = scene_class(stats)
    return c[0] if isinstance(c, tuple) else str(c)


# -- parser ------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="calibrate", description="Measure this host's grid ray-tracing costs and predict optimal "
                                              "grid resolutions.")
    sub = p.add_subparsers(dest="verb", parser_class=_Parser)

    def verb(name, help_text):
        sp = sub.add_parser(name, help=help_text, description=help_text)
        sp.add_argument("--json", action="store_true", help="machine-readable output on stdout")
        sp.add_argument("--quiet", action="store_true", help="no progress bar")
        return sp

    sp = verb("run", "measure T_setup, T_step, T_int and T_sub on this host and fit them")
    sp.add_argument("--budget", type=positive_number("the budget in seconds"), default=60.0, metavar="SECONDS",
                    help="wall-clock budget (default 60)")
    sp.add_argument("--target-rel-width", type=positive_number("the target relative width"), default=0.06, metavar="W",
                    help="stop once the pooled fit's r (both ray sets' batches fitted together) has a 95%% "
                         "interval narrower than W times its median (default 0.06)")
    sp.add_argument("--out", default=DEFAULT_CALIBRATION, metavar="FILE", help="calibration file to write")
    sp.add_argument("--intersector", default="watertight", choices=["watertight", "moller-trumbore"])
    sp.add_argument("--seed", type=seed_number, default=0)
    sp.add_argument("--resume", action="store_true", help="continue an interrupted run from FILE.partial")
    sp.add_argument("--cache", type=byte_size, metavar="SIZE",
                    help="the memory term's cache size (e.g. 16MiB) instead of the best fit among the sizes from "
                         "the level-2 to the last-level cache")
    sp.set_defaults(func=cmd_run)

    sp = verb("fit", "re-fit a calibration file's stored measurements without measuring again")
    sp.add_argument("file", nargs="?", default=DEFAULT_CALIBRATION)
    sp.add_argument("--out", metavar="FILE", help="write here instead of replacing FILE")
    sp.add_argument("--seed", type=seed_number, default=0)
    sp.add_argument("--cache", type=byte_size, metavar="SIZE",
                    help="count the memory term's lines against this cache size (e.g. 16MiB) instead of the one "
                         "the run chose, and fit again")
    sp.set_defaults(func=cmd_fit)

    sp = verb("show", "print a calibration's constants; --plot writes a corner plot, residuals and the isolating suites")
    sp.add_argument("file", nargs="?", default=DEFAULT_CALIBRATION)
    sp.add_argument("--plot", metavar="PREFIX", help="write PREFIX-corner.png, PREFIX-residuals.png and PREFIX-isolated.png")
    sp.set_defaults(func=cmd_show)

    sp = verb("scenes", "list the built-in scenes with their statistics")
    sp.set_defaults(func=cmd_scenes)

    from . import bench as _bench
    from . import compare as _compare
    from . import export as _export
    from . import paper as _paper
    from . import predict as _predict
    from . import render as _render
    from . import tradeoff as _tradeoff

    _predict.add_parser(sub)
    _export.add_parser(sub)
    _render.add_parser(sub)
    _paper.add_parser(sub)
    _bench.add_parser(sub)
    _compare.add_parser(sub)
    _tradeoff.add_parser(sub)
    return p


def main(argv=None) -> int:
    started = time.monotonic()  # a run's budget counts its imports (about 1.6 s: jax, emcee, nlopt)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        args.started = started
        if args.verb is None:
            parser.print_help(sys.stderr)
            return EXIT_USER_ERROR
        return int(args.func(args) or 0)
    except KeyboardInterrupt as exc:
        kept = getattr(exc, "measurements", None)
        extra = f"; {len(kept)} configurations' values kept: continue with --resume" if kept else ""
        print(f"calibrate: interrupted{extra}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (UserError, ValueError, OSError) as exc:
        print(f"calibrate: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_USER_ERROR
    except Exception as exc:  # a fit that cannot converge, and anything unforeseen: one line, not a traceback
        from .fit import ConvergenceError

        if isinstance(exc, ConvergenceError):
            print(f"calibrate: fit failed: {_one_line(exc)}", file=sys.stderr)
            return EXIT_FIT_FAILED
        raise


def _one_line(exc) -> str:
    text = str(exc) or type(exc).__name__
    return " ".join(text.split())


if __name__ == "__main__":
    sys.exit(main())
