"""SVG plots of the reports: well-formed, escaped, nice ticks inside the data range, gaps kept, shared
scales shared, log axes on decades."""
from __future__ import annotations

import base64
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from bench.fit.report import plot_against, plot_before_after
from bench.fit.svgplot import Figure, _ticks, svg_img

NS = "{http://www.w3.org/2000/svg}"


def _texts(svg: str) -> list[str]:
    return [t.text or "" for t in ET.fromstring(svg).iter(f"{NS}text")]


def _decode(img: str) -> str:
    src = re.search(r'src="data:image/svg\+xml;base64,([^"]+)"', img).group(1)
    return base64.b64decode(src).decode("utf-8")


def test_figure_is_well_formed_escaped_and_embedded():
    fig = Figure("drift <x> & y", columns=2)
    fig.panel("a<b", xlabel="T (C)", ylabel="deg/h").line([0, 1, 2], [0.1, -0.2, 0.3], label="1 & 2")
    fig.panel("c").points([0, 1], [1, 2])
    svg = fig.render()
    root = ET.fromstring(svg)                     # parses: text is escaped
    assert len(root.findall(f"{NS}clipPath")) == 2
    texts = _texts(svg)
    assert "drift <x> & y" in texts and "a<b" in texts and "1 & 2" in texts
    img = svg_img(svg, 'alt "q"')
    assert img.startswith('<img alt="alt &quot;q&quot;"') and _decode(img) == svg


def test_linear_ticks_are_nice_and_inside_the_range():
    for lo, hi in [(-0.083, 0.081), (2.0, 5.8), (-31.2, 52.4), (0.0012, 0.0013), (-1e6, 3e6)]:
        ticks = _ticks(lo, hi, False, 3)
        assert len(ticks) >= 3, (lo, hi, ticks)
        assert all(lo - 1e-9 * (hi - lo) <= v <= hi + 1e-9 * (hi - lo) for v in ticks)
        steps = np.diff(ticks)
        assert np.allclose(steps, steps[0])
        mantissa = steps[0] / 10 ** np.floor(np.log10(steps[0]))
        assert any(np.isclose(mantissa, m) for m in (1, 2, 2.5, 5)), (lo, hi, steps[0])


def test_log_ticks_on_decades():
    assert _ticks(0.8, 5000.0, True, 5) == [1.0, 10.0, 100.0, 1000.0]
    assert _ticks(0.011, 0.09, True, 5) == [0.02, 0.05]                  # inside one decade: 1-2-5


def test_nan_breaks_a_line_and_bad_shapes_are_refused():
    fig = Figure()
    fig.panel().line([0, 1, 2, 3, 4], [0, 1, np.nan, 3, 4])
    paths = [p.get("d") for p in ET.fromstring(fig.render()).iter(f"{NS}path") if p.get("fill") == "none"
             and p.get("stroke", "").startswith("#1f")]
    assert len(paths) == 1 and paths[0].count("M") == 2
    with pytest.raises(ValueError, match="x has 3 values, y 2"):
        Figure("bad").panel("p").line([0, 1, 2], [0, 1])


def _panel_y_ranges(svg: str) -> list[tuple[float, float]]:
    """(y of the top tick label, its value) per panel is enough to compare scales: collect the y tick
    labels (text-anchor end) with their pixel positions, grouped by panel clip rectangle."""
    root = ET.fromstring(svg)
    out = []
    for clip in root.iter(f"{NS}clipPath"):
        rect = clip.find(f"{NS}rect")
        top, height = float(rect.get("y")), float(rect.get("height"))
        labels = [(float(t.get("y")), float(t.text)) for t in root.iter(f"{NS}text")
                  if t.get("text-anchor") == "end" and top - 5 <= float(t.get("y")) <= top + height + 5]
        out.append(tuple(sorted(labels)))
    return out


def test_before_after_share_one_scale():
    t = np.arange(20000.0)
    rng = np.random.default_rng(1)
    before = 0.05 * np.sin(t / 3000.0) + rng.normal(0, 0.01, t.size)
    after = rng.normal(0, 0.01, t.size)
    svg = _decode(plot_before_after(t, before, after, "b/a"))
    a, b = _panel_y_ranges(svg)
    # same values at the same offsets from each panel's top: one scale
    assert [v for _, v in a] == [v for _, v in b]
    assert np.allclose(np.diff([y for y, _ in a]), np.diff([y for y, _ in b]))
    texts = _texts(svg)
    assert any(s.startswith("before: 100-s means, std 0.03") for s in texts), texts


def test_against_regressors_side_by_side_as_100s_means():
    t = np.arange(10000.0)
    temp = 40.0 - t / 300.0
    before, after = 0.01 * temp, np.zeros_like(temp)
    svg = _decode(plot_against(t, {"before": before, "after": after}, {"T (C)": temp, "dT/dt": np.gradient(temp)},
                               "against"))
    root = ET.fromstring(svg)
    assert len(root.findall(f"{NS}clipPath")) == 4                      # 2 regressors x (before, after)
    dots = [p.get("d") for p in root.iter(f"{NS}path") if p.get("stroke-linecap") == "round"
            and p.get("clip-path")]
    assert [d.count("M") for d in dots] == [100] * 4                    # 10,000 s as 100-s means
