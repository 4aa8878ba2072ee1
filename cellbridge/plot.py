"""``cellbridge plot``: figures of the tactile model (the tactile layer itself does no I/O).

matplotlib is an optional extra (``pip install 'cellbridge[plot]'``); it is imported
only when a figure is drawn, with the Agg backend so no display is needed.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

import numpy as np

from cellbridge.tactile import DEFAULT_NOISE, ElementParams, InverseStatus, branch_info, forward, solve
from cellbridge.tactile.element import DEFAULT_PARAMS

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.figure import Figure

DEFAULT_DIAMETERS_MM = (10.0, 16.0, 20.0, 26.0, 30.0, 40.0)
DEFAULT_FORCE_RANGE = (0.0, 20.0)
DEFAULT_FORCE_LINES = (1.0, 2.0, 5.0, 10.0, 15.0, 20.0)

_RESPONSE_HELP = """\
Draw the element's response, the paper's Fig. 2, to a PNG file.

Left panel: the capacitance changes (ΔC1, ΔC2) in pF of one element pressed at
its centre by a disk of diameter D with force F. Coloured lines hold D constant
(default D = 10, 16, 20, 26, 30, 40 mm, the paper's stimulators) and sweep F over
the force range (default 0-20 N); they are solid where the inverse returns a valid
(F, S) and dashed where it refuses. Grey lines hold F constant (default 1, 2, 5,
10, 15, 20 N, those inside the force range) and sweep D. The background is the
inverse's verdict for every reading of the plane: green valid, orange ambiguous
(a low-pressure contact gives the same reading), grey ill-conditioned or needing an
area beyond the element, white where no contact on one element produces it.

Right panel: the same lines and verdict against the ratio ΔC1/ΔC2, which depends on
the pressure F/S only; there the thin ambiguous wedge near the origin of the left
panel opens up between ρ(0) and the ratio's peak.

Element: the defaults of cellbridge.tactile.ElementParams (40 mm square,
E1 = 4.8 kPa, E2 = 15 kPa). Example:

    cellbridge plot response -o response.png --force-range 0 10
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Attach the figure subcommands (one per figure) to ``cellbridge plot``."""
    parser.description = "Draw figures of the tactile model to PNG (needs matplotlib)."
    sub = parser.add_subparsers(dest="figure", metavar="FIGURE")
    p = sub.add_parser(
        "response",
        help="ΔC1 vs ΔC2 for a grid of force and contact diameter (paper Fig. 2)",
        description=_RESPONSE_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("-o", "--output", required=True, metavar="FILE.png",
                   help="PNG file to write (overwritten if it exists)")
    p.add_argument("--force-range", nargs=2, type=float, metavar=("FMIN", "FMAX"),
                   default=DEFAULT_FORCE_RANGE,
                   help="force sweep of the constant-D lines, in N (default: 0 20)")
    p.add_argument("--diameters", nargs="+", type=float, metavar="MM",
                   default=list(DEFAULT_DIAMETERS_MM),
                   help="contact diameters of the constant-D lines, in mm "
                        "(default: 10 16 20 26 30 40; at most the element's 45.1 mm)")
    p.add_argument("--force-lines", nargs="*", type=float, metavar="N",
                   default=list(DEFAULT_FORCE_LINES),
                   help="forces of the constant-F lines, in N; those outside the force "
                        "range are skipped; give none for no such lines "
                        "(default: 1 2 5 10 15 20)")
    p.add_argument("--noise", type=float, default=DEFAULT_NOISE * 1e15, metavar="FF",
                   help="rms noise of each ΔC given to the inverse, in fF "
                        "(default: %(default).2g, about two counter counts at a 2 ms gate)")
    p.add_argument("--dpi", type=int, default=150, help="resolution (default: %(default)s)")
    parser.set_defaults(_plot_parser=parser)


def _check(args: argparse.Namespace, p: ElementParams) -> str | None:
    fmin, fmax = args.force_range
    if not (np.isfinite(fmin) and np.isfinite(fmax) and 0 <= fmin < fmax):
        return f"--force-range needs 0 <= FMIN < FMAX, got {fmin} {fmax}"
    dmax = 2e3 * np.sqrt(p.area / np.pi)
    for d in args.diameters:
        if not 0 < d <= dmax:
            return f"--diameters: {d} mm is outside (0, {dmax:.1f}] mm (the element's area)"
    if not (np.isfinite(args.noise) and args.noise >= 0):
        return f"--noise must be >= 0 fF, got {args.noise}"
    if args.dpi <= 0:
        return "--dpi must be > 0"
    return None


def response_figure(
    diameters_mm: tuple[float, ...] | list[float] = DEFAULT_DIAMETERS_MM,
    force_range: tuple[float, float] = DEFAULT_FORCE_RANGE,
    force_lines: tuple[float, ...] | list[float] = DEFAULT_FORCE_LINES,
    noise: float = DEFAULT_NOISE,
    params: ElementParams | None = None,
) -> Figure:
    """The response figure as a matplotlib Figure (Agg canvas, no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    if TYPE_CHECKING:  # pragma: no cover
        from matplotlib.axes import Axes

    p = DEFAULT_PARAMS if params is None else params
    fmin, fmax = force_range
    pf = 1e12
    fig = Figure(figsize=(13.0, 6.0))
    FigureCanvasAgg(fig)
    ax, axr = fig.subplots(1, 2, gridspec_kw={"width_ratios": (1.15, 1.0)})

    forces = np.linspace(max(fmin, 1e-6), fmax, 600)
    curves = []
    for d_mm in diameters_mm:
        area = np.pi * (1e-3 * d_mm) ** 2 / 4
        c1, c2 = forward(forces, area, p)
        curves.append((d_mm, c1 * pf, c2 * pf, solve(c1, c2, p, noise=noise).valid))
    diam = np.linspace(1e-3 * min(diameters_mm), 1e-3 * max(diameters_mm), 200)
    flines = []
    for f in force_lines:
        if fmin <= f <= fmax and f > 0:
            c1, c2 = forward(f, np.pi * diam**2 / 4, p)
            flines.append((f, c1 * pf, c2 * pf))

    info = branch_info(p)
    x_max = 1.05 * max(float(c[1].max()) for c in curves)
    y_max = 1.05 * max(float(c[2].max()) for c in curves)
    palette = ["#1b5e9c", "#d1495b", "#2e933c", "#8f4fb0", "#e08a00", "#00798c",
               "#6b4226", "#5c5c5c"]
    cmap = ListedColormap(["#d8f0d0", "#e4e4e4", "#fcdcb4"])

    def draw(target: Axes, x_hi: float, y_lo: float, y_hi: float, ratio_y: bool) -> None:
        """One panel; ``ratio_y`` puts ΔC1/ΔC2 on the y axis instead of ΔC2."""

        def yv(c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
            return c1 / c2 if ratio_y else c2

        # Verdict of the inverse over the visible plane, one solve per pixel.
        gx = np.linspace(x_hi / 1200, x_hi * (1 - 1 / 1200), 600)
        gy = np.linspace(y_lo, y_hi, 601)[:-1] + (y_hi - y_lo) / 1200
        X, Y = np.meshgrid(gx, gy)
        res = solve(X / pf, (X / Y if ratio_y else Y) / pf, p, noise=noise)
        verdict = np.full(X.shape, np.nan)  # NaN (white): no contact gives this reading
        verdict[(res.status & (InverseStatus.ILL_CONDITIONED | InverseStatus.AREA_EXCEEDS)) != 0] = 1
        verdict[(res.status & InverseStatus.AMBIGUOUS) != 0] = 2
        verdict[res.valid] = 0
        target.imshow(verdict, origin="lower", extent=(0, x_hi, y_lo, y_hi), aspect="auto",
                      cmap=cmap, vmin=-0.5, vmax=2.5, interpolation="nearest", zorder=0)
        for i, (d_mm, c1, c2, ok) in enumerate(curves):
            col = palette[i % len(palette)]
            y = yv(c1, c2)
            target.plot(np.where(ok, c1, np.nan), np.where(ok, y, np.nan), "-",
                        color=col, lw=2.0, label=f"D = {d_mm:g} mm", zorder=3)
            target.plot(c1, y, "--", color=col, lw=1.0, zorder=2)
        for f, c1, c2 in flines:
            y = yv(c1, c2)
            target.plot(c1, y, color="0.35", lw=0.8, zorder=2.5)
            if c1[-1] < x_hi and y_lo < y[-1] < y_hi:
                target.annotate(f"{f:g} N", (c1[-1], y[-1]), textcoords="offset points",
                                xytext=(3, 2), fontsize=8, color="0.25", zorder=4)
        target.set_xlim(0, x_hi)
        target.set_ylim(y_lo, y_hi)
        target.grid(True, lw=0.3, color="0.8", zorder=1)
        target.set_xlabel("ΔC1 (soft layer) [pF]")

    draw(ax, x_max, 0.0, y_max, ratio_y=False)
    ax.set_ylabel("ΔC2 (hard layer) [pF]")
    ax.set_title(
        f"Element response (paper Fig. 2): F = {fmin:g}–{fmax:g} N along each D;"
        " grey: constant F",
        fontsize=10,
    )
    handles, _ = ax.get_legend_handles_labels()
    handles += [
        Patch(color="#d8f0d0", label="inverse valid"),
        Patch(color="#fcdcb4", label="ambiguous (low-pressure twin)"),
        Patch(color="#e4e4e4", label="ill-conditioned / area > element"),
    ]
    ax.legend(handles=handles, loc="upper left", fontsize=8, framealpha=0.9)

    # The ratio depends on pressure only; in these coordinates the thin ambiguous
    # wedge of the left panel opens up.
    r_lo = info.ratio_inf - 0.1 * (info.ratio_peak - info.ratio_inf)
    r_hi = info.ratio_peak + 0.12 * (info.ratio_peak - info.ratio_inf)
    draw(axr, x_max, r_lo, r_hi, ratio_y=True)
    for r, text in ((info.ratio_zero, "ρ(0)"), (info.ratio_peak, "peak")):
        axr.axhline(r, color="0.3", lw=0.6, ls=":", zorder=2)
        axr.annotate(text, (x_max, r), textcoords="offset points", xytext=(-28, 2),
                     fontsize=8, color="0.25")
    axr.set_ylabel("ratio ΔC1/ΔC2 (depends on pressure F/S only)")
    axr.set_title(
        f"Same readings against the ratio; verdict at {noise * 1e15:g} fF rms noise per channel",
        fontsize=10,
    )
    fig.tight_layout()
    return fig


def run(args: argparse.Namespace) -> int:
    figure = getattr(args, "figure", None)
    if figure is None:
        args._plot_parser.print_help()
        return 2
    p = DEFAULT_PARAMS
    err = _check(args, p)
    if err:
        print(f"cellbridge plot {figure}: {err}", file=sys.stderr)
        return 2
    try:
        import matplotlib

        matplotlib.use("Agg")
    except ImportError:
        print(
            "cellbridge plot: matplotlib is not installed; plotting is an optional extra:\n"
            "    pip install 'cellbridge[plot]'",
            file=sys.stderr,
        )
        return 1
    fig = response_figure(
        diameters_mm=args.diameters,
        force_range=tuple(args.force_range),
        force_lines=args.force_lines,
        noise=args.noise * 1e-15,
        params=p,
    )
    try:
        fig.savefig(args.output, dpi=args.dpi, format="png")
    except OSError as exc:
        print(f"cellbridge plot {figure}: cannot write {args.output}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(f"wrote {args.output}")
    return 0
