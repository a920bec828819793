"""Line and point plots drawn as SVG text, for the self-contained HTML reports.

A report page holds dozens of plots; drawing each through a general plotting library costs a tenth of
a second or more (text layout, tick machinery, PNG encoding), which made the report the slowest part of
a close-the-loop analysis.  The reports need only axes with "nice" ticks (linear or log), grid, lines,
points, a zero line, a legend and titles, which a page of numpy and string formatting draws in
milliseconds.  The SVG scales with the page (crisp at any width) and needs no fonts, scripts or
external resources: ``svg_img`` embeds it as a base64 ``data:`` URI in an ``<img>``.

    fig = Figure("Residual", columns=2)
    ax = fig.panel("before", xlabel="T (C)", ylabel="deg/h")
    ax.line(x, y, label="100-s means")
    html = svg_img(fig.render(), "Residual")
"""
from __future__ import annotations

import base64
import html
import math
from dataclasses import dataclass, field

import numpy as np

COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")
FLAG_COLOR = "#d62728"
WIDTH_PX = 1200                      # drawn for the page width (the <img> scales it)
PANEL_HEIGHT_PX = 240
_M_LEFT, _M_RIGHT, _M_TOP, _M_BOTTOM = 72, 16, 26, 42      # margins of each panel (px)
_TITLE_PX = 30                      # figure title band
_FONT = 'font-family="sans-serif" font-size="12"'


@dataclass
class _Series:
    x: np.ndarray
    y: np.ndarray
    label: str | None
    color: str
    points: bool


@dataclass
class Panel:
    """One set of axes: its series, labels and scales (``log``: base-10 axis, non-positive values left out)."""
    title: str = ""
    xlabel: str = ""
    ylabel: str = ""
    xlog: bool = False
    ylog: bool = False
    zero_line: bool = False
    series: list[_Series] = field(default_factory=list)

    def line(self, x, y, label: str | None = None, color: str | None = None) -> "Panel":
        """A polyline; NaN in x or y breaks it (no line drawn across a gap)."""
        return self._add(x, y, label, color, points=False)

    def points(self, x, y, label: str | None = None, color: str | None = None) -> "Panel":
        return self._add(x, y, label, color, points=True)

    def _add(self, x, y, label, color, points) -> "Panel":
        x, y = np.asarray(x, float).ravel(), np.asarray(y, float).ravel()
        if x.shape != y.shape:
            raise ValueError(f"plot {self.title!r}: x has {x.size} values, y {y.size}")
        self.series.append(_Series(x, y, label, color or COLORS[len(self.series) % len(COLORS)], points))
        return self


class Figure:
    """Panels on a grid of ``columns`` columns, filled row by row.  ``sharey``: one y range for all
    panels (before / after side by side or one above the other compare at a glance)."""

    def __init__(self, title: str = "", columns: int = 1, sharey: bool = False, sharex: bool = False,
                 panel_height_px: int = PANEL_HEIGHT_PX, width_px: int = WIDTH_PX) -> None:
        if columns < 1:
            raise ValueError(f"plot {title!r}: columns must be >= 1, got {columns}")
        self.title, self.columns, self.sharey, self.sharex = title, columns, sharey, sharex
        self.panel_height_px, self.width_px = panel_height_px, width_px
        self.panels: list[Panel] = []

    def panel(self, title: str = "", **kwargs) -> Panel:
        p = Panel(title=title, **kwargs)
        self.panels.append(p)
        return p

    def render(self) -> str:
        rows = max(1, math.ceil(len(self.panels) / self.columns))
        top = _TITLE_PX if self.title else 4
        height = top + rows * self.panel_height_px
        w = self.width_px / self.columns
        yshared = _limits([s.y for p in self.panels for s in p.series], self.panels[0].ylog) \
            if self.sharey and self.panels else None
        xshared = _limits([s.x for p in self.panels for s in p.series], self.panels[0].xlog) \
            if self.sharex and self.panels else None
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{self.width_px}" height="{height}" '
               f'viewBox="0 0 {self.width_px} {height}" {_FONT}>',
               f'<rect width="{self.width_px}" height="{height}" fill="white"/>']
        if self.title:
            out.append(f'<text x="{self.width_px / 2:.0f}" y="20" text-anchor="middle" font-size="15">'
                       f'{_esc(self.title)}</text>')
        for i, p in enumerate(self.panels):
            r, c = divmod(i, self.columns)
            out.append(_draw_panel(p, i, c * w, top + r * self.panel_height_px, w, self.panel_height_px,
                                   xshared, yshared))
        out.append("</svg>")
        return "\n".join(out)


def svg_img(svg: str, alt: str) -> str:
    """``svg`` as an ``<img>`` with a base64 ``data:`` URI (self-contained, no script)."""
    data = base64.b64encode(svg.encode("utf-8")).decode("ascii")
    return f'<img alt="{html.escape(alt, quote=True)}" src="data:image/svg+xml;base64,{data}">'


# ------------------------------------------------------------------------------------------ internals
def _esc(text: str) -> str:
    return html.escape(str(text), quote=True)


def _finite(values: np.ndarray, log: bool) -> np.ndarray:
    v = values[np.isfinite(values)]
    return v[v > 0] if log else v


def _limits(arrays: list[np.ndarray], log: bool) -> tuple[float, float]:
    """Data range padded by 4 % (in log space on a log axis); a flat or empty range gets a width."""
    finite = [_finite(a, log) for a in arrays]
    finite = [a for a in finite if a.size]
    if not finite:
        return (1.0, 10.0) if log else (0.0, 1.0)
    lo, hi = min(float(a.min()) for a in finite), max(float(a.max()) for a in finite)
    if log:
        lo, hi = math.log10(lo), math.log10(hi)
    if hi - lo <= 0:
        pad = abs(lo) * 0.05 or 0.5
        lo, hi = lo - pad, hi + pad
    pad = 0.04 * (hi - lo)
    lo, hi = lo - pad, hi + pad
    return (10 ** lo, 10 ** hi) if log else (lo, hi)


def _ticks(lo: float, hi: float, log: bool, target: int) -> list[float]:
    if log:
        d0, d1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
        mantissas = (1.0,) if d1 - d0 > 2 else (1.0, 2.0, 5.0)
        return [m * 10.0 ** d for d in range(d0, d1 + 1) for m in mantissas if lo <= m * 10.0 ** d <= hi]
    ticks: list[float] = []
    for want in range(max(1, target), max(1, target) + 4):      # at least three ticks on a short axis
        raw = (hi - lo) / want
        power = 10.0 ** math.floor(math.log10(raw))
        step = next((m * power for m in (1, 2, 2.5, 5, 10) if m * power >= raw), 10 * power)
        ticks = [k * step for k in range(math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9) + 1)]
        if len(ticks) >= 3:
            break
    return ticks


def _tick_label(v: float, ticks: list[float], log: bool) -> str:
    if log:
        return f"{v:g}"
    step = ticks[1] - ticks[0] if len(ticks) > 1 else abs(v) or 1.0
    if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-4):
        return f"{v:.2e}"
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    if abs(round(step * 10 ** decimals) - step * 10 ** decimals) > 1e-6:        # a step of 2.5 x 10^k
        decimals += 1
    return f"{v:.{min(decimals, 6)}f}"


class _Scale:
    def __init__(self, lo: float, hi: float, log: bool, p0: float, p1: float) -> None:
        self.log = log
        self.lo, self.hi = (math.log10(lo), math.log10(hi)) if log else (lo, hi)
        self.p0, self.p1 = p0, p1

    def __call__(self, v):
        v = np.asarray(v, float)
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.where(v > 0, np.log10(np.where(v > 0, v, 1.0)), np.nan)
        return self.p0 + (v - self.lo) / (self.hi - self.lo) * (self.p1 - self.p0)


def _path(px: np.ndarray, py: np.ndarray, points: bool) -> str:
    ok = np.isfinite(px) & np.isfinite(py)
    if points:
        return "".join(f"M{a:.1f} {b:.1f}h0" for a, b in zip(px[ok], py[ok]))
    parts, pen = [], False
    for a, b, good in zip(px, py, ok):
        if good:
            parts.append(f"{'L' if pen else 'M'}{a:.1f} {b:.1f}")
        pen = bool(good)
    return "".join(parts)


def _draw_panel(p: Panel, index: int, x0: float, y0: float, w: float, h: float,
                xshared: tuple[float, float] | None, yshared: tuple[float, float] | None) -> str:
    left, right, top, bottom = x0 + _M_LEFT, x0 + w - _M_RIGHT, y0 + _M_TOP, y0 + h - _M_BOTTOM
    xl = xshared or _limits([s.x for s in p.series], p.xlog)
    yl = yshared or _limits([s.y for s in p.series], p.ylog)
    sx, sy = _Scale(*xl, p.xlog, left, right), _Scale(*yl, p.ylog, bottom, top)
    out = [f'<clipPath id="c{index}"><rect x="{left:.1f}" y="{top:.1f}" width="{right - left:.1f}" '
           f'height="{bottom - top:.1f}"/></clipPath>']
    xt = _ticks(*xl, p.xlog, max(3, int((right - left) / 90)))
    yt = _ticks(*yl, p.ylog, max(3, int((bottom - top) / 40)))
    grid = "".join(f"M{float(sx(v)):.1f} {top:.1f}V{bottom:.1f}" for v in xt) + \
        "".join(f"M{left:.1f} {float(sy(v)):.1f}H{right:.1f}" for v in yt)
    out.append(f'<path d="{grid}" stroke="#ddd" stroke-width="1" fill="none"/>')
    for v in xt:
        out.append(f'<text x="{float(sx(v)):.1f}" y="{bottom + 15:.1f}" text-anchor="middle">'
                   f'{_tick_label(v, xt, p.xlog)}</text>')
    for v in yt:
        out.append(f'<text x="{left - 5:.1f}" y="{float(sy(v)) + 4:.1f}" text-anchor="end">'
                   f'{_tick_label(v, yt, p.ylog)}</text>')
    if p.zero_line and not p.ylog and yl[0] < 0 < yl[1]:
        out.append(f'<path d="M{left:.1f} {float(sy(0.0)):.1f}H{right:.1f}" stroke="black" stroke-width="0.8"/>')
    for s in p.series:
        d = _path(sx(s.x), sy(s.y), s.points)
        if not d:
            continue
        if s.points:
            out.append(f'<path d="{d}" stroke="{s.color}" stroke-width="3" stroke-linecap="round" '
                       f'clip-path="url(#c{index})"/>')
        else:
            out.append(f'<path d="{d}" stroke="{s.color}" stroke-width="1.3" fill="none" '
                       f'stroke-linejoin="round" clip-path="url(#c{index})"/>')
    out.append(f'<rect x="{left:.1f}" y="{top:.1f}" width="{right - left:.1f}" height="{bottom - top:.1f}" '
               f'fill="none" stroke="#444" stroke-width="1"/>')
    if p.title:
        out.append(f'<text x="{left:.1f}" y="{top - 8:.1f}">{_esc(p.title)}</text>')
    if p.xlabel:
        out.append(f'<text x="{(left + right) / 2:.1f}" y="{bottom + 34:.1f}" text-anchor="middle">'
                   f'{_esc(p.xlabel)}</text>')
    if p.ylabel:
        cy = (top + bottom) / 2
        out.append(f'<text x="{x0 + 14:.1f}" y="{cy:.1f}" text-anchor="middle" '
                   f'transform="rotate(-90 {x0 + 14:.1f} {cy:.1f})">{_esc(p.ylabel)}</text>')
    labelled = [s for s in p.series if s.label]
    for k, s in enumerate(labelled):
        ly = top + 14 + 16 * k
        mark = (f'<path d="M{right - 150:.1f} {ly - 4:.1f}h0" stroke="{s.color}" stroke-width="5" '
                f'stroke-linecap="round"/>' if s.points else
                f'<path d="M{right - 160:.1f} {ly - 4:.1f}h20" stroke="{s.color}" stroke-width="2"/>')
        out.append(f'<rect x="{right - 166:.1f}" y="{ly - 13:.1f}" width="160" height="16" fill="white" '
                   f'fill-opacity="0.8"/>{mark}<text x="{right - 134:.1f}" y="{ly:.1f}">{_esc(s.label)}</text>')
    return "\n".join(out)
