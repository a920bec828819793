/* A small line plotter on <canvas>: several series sharing one x axis, "nice" ticks (1-2-5 steps),
   a legend, gaps where a value is null / NaN, sharp on high-DPI screens.  Hand-written because the
   dashboard must work offline with no third-party assets.

     const plot = new LinePlot(canvas, { xLabel: "bench time (h)", yLabel: "°C" });
     plot.setData(xs, [{ name: "PV", values: ys, color: "#c0392b" }, ...]);

   Zoom with the mouse wheel (about the pointer; x only), pan by dragging, double-click to see all;
   the pointer shows a read-out of every series at the nearest sample.

   After each draw the canvas carries data-points (number of finite points drawn), data-series
   (the series names), data-view ("lo,hi" of the x range shown, empty when showing all) and
   data-cursor (the read-out text) so the page state can be checked. */
"use strict";

const PLOT_COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf"];

function niceStep(span, maxTicks) {
  const raw = span / Math.max(1, maxTicks);
  const power = Math.pow(10, Math.floor(Math.log10(raw)));
  for (const m of [1, 2, 2.5, 5, 10]) {
    if (m * power >= raw) return m * power;
  }
  return 10 * power;
}

function niceTicks(lo, hi, maxTicks) {
  if (!(hi > lo)) {
    const pad = Math.abs(lo) > 0 ? Math.abs(lo) * 0.01 : 1;
    lo -= pad;
    hi += pad;
  }
  const step = niceStep(hi - lo, maxTicks);
  const start = Math.floor(lo / step) * step;
  const end = Math.ceil(hi / step) * step;
  const ticks = [];
  for (let v = start; v <= end + step * 1e-9; v += step) ticks.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return { lo: start, hi: end, step, ticks };
}

function tickLabel(v, step) {
  // as many decimals as the step has (0.025 needs three: 0.125 is not "0.13"), so neighbouring
  // labels differ by exactly the step
  let decimals = 0;
  while (decimals < 6 && Math.abs(step * 10 ** decimals - Math.round(step * 10 ** decimals)) > 1e-6 * step * 10 ** decimals) decimals += 1;
  if (Math.abs(v) >= 1e5 || (Math.abs(v) > 0 && Math.abs(v) < 1e-4)) return v.toExponential(2);
  return v.toFixed(decimals);
}

function fmtPlotNum(v) {
  if (!Number.isFinite(v)) return "–";
  if (v !== 0 && (Math.abs(v) >= 1e5 || Math.abs(v) < 1e-3)) return v.toExponential(3);
  return Number(v.toPrecision(5)).toString();
}

class LinePlot {
  constructor(canvas, options = {}) {
    this.canvas = canvas;
    this.options = Object.assign({ xLabel: "", yLabel: "", height: 240, emptyText: "no data yet" }, options);
    this.x = [];
    this.series = [];
    canvas.style.width = "100%";
    canvas.style.height = `${this.options.height}px`;
    this.view = null;        // [lo, hi] of x when zoomed or panned; null = everything
    this.cursorPx = null;    // pointer x in CSS pixels inside the plot area
    this._resize = () => this.draw();
    window.addEventListener("resize", this._resize);
    canvas.title = "wheel: zoom · drag: pan · double-click: all";
    canvas.style.cursor = "crosshair";
    this._wire();
  }

  setData(x, series) {
    this.x = x || [];
    this.series = (series || []).filter(Boolean)
      .map((s, i) => Object.assign({ color: PLOT_COLORS[i % PLOT_COLORS.length] }, s));
    this.draw();
  }

  /* x range of everything, and the range shown */
  _fullX() {
    return this._range(this.x);
  }

  _shownX() {
    return this.view || this._fullX();
  }

  /* pixel -> data x with the last drawn scale */
  _xAt(px) {
    const sc = this._scale;
    return sc ? sc.lo + ((px - sc.left) / sc.w) * (sc.hi - sc.lo) : null;
  }

  zoom(factor, centre) {
    const [lo, hi] = this._shownX();
    if (!Number.isFinite(lo) || !(hi > lo)) return;
    const c = centre === undefined ? (lo + hi) / 2 : centre;
    const [flo, fhi] = this._fullX();
    let nlo = c - (c - lo) * factor;
    let nhi = c + (hi - c) * factor;
    if (nlo <= flo && nhi >= fhi) {
      this.view = null;
    } else {
      this.view = [Math.max(nlo, flo - (fhi - flo)), Math.min(nhi, fhi + (fhi - flo))];
    }
    this.draw();
  }

  pan(dxData) {
    const [lo, hi] = this._shownX();
    if (!Number.isFinite(lo)) return;
    this.view = [lo + dxData, hi + dxData];
    this.draw();
  }

  reset() {
    this.view = null;
    this.draw();
  }

  _wire() {
    const c = this.canvas;
    const local = (ev) => ev.clientX - c.getBoundingClientRect().left;
    c.addEventListener("wheel", (ev) => {
      if (!this._scale) return;
      ev.preventDefault();
      this.zoom(ev.deltaY < 0 ? 0.8 : 1.25, this._xAt(local(ev)));
    }, { passive: false });
    let drag = null;
    c.addEventListener("mousedown", (ev) => { drag = { px: local(ev) }; });
    window.addEventListener("mouseup", () => { drag = null; });
    c.addEventListener("mousemove", (ev) => {
      const px = local(ev);
      if (drag && this._scale && px !== drag.px) {
        this.pan(this._xAt(drag.px) - this._xAt(px));
        drag.px = px;
      }
      this.cursorPx = px;
      this.draw();
    });
    c.addEventListener("mouseleave", () => { this.cursorPx = null; this.draw(); });
    c.addEventListener("dblclick", () => this.reset());
  }

  /* index of the sample nearest to data x (x is increasing) */
  _nearest(xv) {
    const xs = this.x;
    let lo = 0;
    let hi = xs.length - 1;
    while (hi - lo > 1) {
      const mid = (lo + hi) >> 1;
      if (xs[mid] < xv) lo = mid;
      else hi = mid;
    }
    return Math.abs(xs[lo] - xv) <= Math.abs(xs[hi] - xv) ? lo : hi;
  }

  _range(values) {
    let lo = Infinity;
    let hi = -Infinity;
    for (const v of values) {
      if (v === null || v === undefined || !Number.isFinite(v)) continue;
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
    return [lo, hi];
  }

  draw() {
    const canvas = this.canvas;
    const ratio = window.devicePixelRatio || 1;
    const cssWidth = canvas.clientWidth || 600;
    const cssHeight = this.options.height;
    canvas.width = Math.round(cssWidth * ratio);
    canvas.height = Math.round(cssHeight * ratio);
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, cssWidth, cssHeight);
    ctx.font = "12px system-ui, sans-serif";

    const pad = { left: 64, right: 12, top: 26, bottom: 38 };
    const w = cssWidth - pad.left - pad.right;
    const h = cssHeight - pad.top - pad.bottom;
    const [xlo, xhi] = this._shownX();
    let ylo = Infinity;
    let yhi = -Infinity;
    for (const s of this.series) {
      const n = Math.min(this.x.length, s.values.length);
      for (let i = 0; i < n; i++) {
        const v = s.values[i];
        if (v === null || v === undefined || !Number.isFinite(v) || this.x[i] < xlo || this.x[i] > xhi) continue;
        if (v < ylo) ylo = v;
        if (v > yhi) yhi = v;
      }
    }
    let drawn = 0;
    if (!Number.isFinite(xlo) || !Number.isFinite(ylo) || w < 20 || h < 20) {
      ctx.fillStyle = "#777";
      ctx.fillText(this.options.emptyText, pad.left + 8, pad.top + h / 2);
      this._mark(0);
      return;
    }
    // all data: round the x axis to nice ticks; zoomed: exactly the range asked for
    const xt = this.view ? Object.assign(niceTicks(xlo, xhi, Math.max(2, Math.floor(w / 90))), { lo: xlo, hi: xhi })
      : niceTicks(xlo, xhi, Math.max(2, Math.floor(w / 90)));
    xt.ticks = xt.ticks.filter((v) => v >= xt.lo - 1e-12 && v <= xt.hi + 1e-12);
    this._scale = { left: pad.left, w, lo: xt.lo, hi: xt.hi };
    const yt = niceTicks(ylo, yhi, Math.max(2, Math.floor(h / 40)));
    const X = (v) => pad.left + ((v - xt.lo) / (xt.hi - xt.lo)) * w;
    const Y = (v) => pad.top + h - ((v - yt.lo) / (yt.hi - yt.lo)) * h;

    // grid and tick labels
    ctx.strokeStyle = "#e3e3e3";
    ctx.lineWidth = 1;
    ctx.fillStyle = "#444";
    ctx.textAlign = "right";
    ctx.textBaseline = "middle";
    for (const v of yt.ticks) {
      const y = Math.round(Y(v)) + 0.5;
      ctx.beginPath();
      ctx.moveTo(pad.left, y);
      ctx.lineTo(pad.left + w, y);
      ctx.stroke();
      ctx.fillText(tickLabel(v, yt.step), pad.left - 6, y);
    }
    ctx.textAlign = "center";
    ctx.textBaseline = "top";
    for (const v of xt.ticks) {
      const x = Math.round(X(v)) + 0.5;
      ctx.beginPath();
      ctx.moveTo(x, pad.top);
      ctx.lineTo(x, pad.top + h);
      ctx.stroke();
      ctx.fillText(tickLabel(v, xt.step), x, pad.top + h + 5);
    }
    ctx.strokeStyle = "#888";
    ctx.strokeRect(pad.left + 0.5, pad.top + 0.5, w, h);
    // axis titles
    ctx.fillStyle = "#222";
    ctx.fillText(this.options.xLabel, pad.left + w / 2, pad.top + h + 20);
    ctx.save();
    ctx.translate(14, pad.top + h / 2);
    ctx.rotate(-Math.PI / 2);
    ctx.textBaseline = "middle";
    ctx.fillText(this.options.yLabel, 0, 0);
    ctx.restore();

    // series (clipped to the plot area; a gap in the data breaks the line)
    ctx.save();
    ctx.beginPath();
    ctx.rect(pad.left, pad.top, w, h);
    ctx.clip();
    for (const s of this.series) {
      ctx.strokeStyle = s.color;
      ctx.lineWidth = s.width || 1.6;
      ctx.setLineDash(s.dash || []);
      ctx.beginPath();
      let pen = false;
      const n = Math.min(this.x.length, s.values.length);
      for (let i = 0; i < n; i++) {
        const xv = this.x[i];
        const yv = s.values[i];
        if (yv === null || yv === undefined || !Number.isFinite(yv) || !Number.isFinite(xv)) {
          pen = false;
          continue;
        }
        if (pen) ctx.lineTo(X(xv), Y(yv));
        else ctx.moveTo(X(xv), Y(yv));
        pen = true;
        if (xv >= xt.lo && xv <= xt.hi) drawn++;
      }
      ctx.stroke();
    }
    ctx.restore();
    ctx.setLineDash([]);

    // legend
    ctx.textAlign = "left";
    ctx.textBaseline = "middle";
    let lx = pad.left;
    for (const s of this.series) {
      ctx.fillStyle = s.color;
      ctx.fillRect(lx, 8, 14, 4);
      ctx.fillStyle = "#222";
      ctx.fillText(s.name, lx + 18, 10);
      lx += 26 + ctx.measureText(s.name).width;
    }
    this._cursor(ctx, pad, w, h, X, Y);
    this._mark(drawn);
  }

  /* vertical line at the pointer, a dot on each series and their values at the nearest sample */
  _cursor(ctx, pad, w, h, X, Y) {
    this.canvas.dataset.cursor = "";
    if (this.cursorPx === null || this.cursorPx < pad.left || this.cursorPx > pad.left + w || !this.x.length) return;
    const i = this._nearest(this._xAt(this.cursorPx));
    const xv = this.x[i];
    const x = X(xv);
    ctx.strokeStyle = "#555";
    ctx.setLineDash([3, 3]);
    ctx.beginPath();
    ctx.moveTo(x, pad.top);
    ctx.lineTo(x, pad.top + h);
    ctx.stroke();
    ctx.setLineDash([]);
    // the x value with the axis' unit: "bench time ... (h)" reads "bench time ...: 0.1672 h"
    const xUnit = (this.options.xLabel.match(/\(([^()]*)\)$/) || [])[1];
    const lines = [`${this.options.xLabel.replace(/\s*\(.*\)$/, "") || "x"}: ${fmtPlotNum(xv)}${xUnit ? ` ${xUnit}` : ""}`];
    for (const s of this.series) {
      const v = s.values[i];
      if (v === null || v === undefined || !Number.isFinite(v)) continue;
      ctx.fillStyle = s.color;
      ctx.beginPath();
      ctx.arc(x, Y(v), 3, 0, 2 * Math.PI);
      ctx.fill();
      lines.push(`${s.name}: ${fmtPlotNum(v)} ${this.options.yLabel}`);
    }
    ctx.font = "12px system-ui, sans-serif";
    const boxW = 12 + Math.max(...lines.map((t) => ctx.measureText(t).width));
    const boxH = 6 + 15 * lines.length;
    const bx = x + 10 + boxW > pad.left + w ? x - 10 - boxW : x + 10;
    ctx.fillStyle = "rgba(255,255,255,0.92)";
    ctx.strokeStyle = "#999";
    ctx.fillRect(bx, pad.top + 4, boxW, boxH);
    ctx.strokeRect(bx + 0.5, pad.top + 4.5, boxW, boxH);
    ctx.fillStyle = "#222";
    ctx.textAlign = "left";
    ctx.textBaseline = "top";
    lines.forEach((t, k) => ctx.fillText(t, bx + 6, pad.top + 8 + 15 * k));
    this.canvas.dataset.cursor = lines.join("; ");
  }

  _mark(points) {
    this.canvas.dataset.points = String(points);
    this.canvas.dataset.series = this.series.map((s) => s.name).join(",");
    this.canvas.dataset.view = this.view ? this.view.map((v) => fmtPlotNum(v)).join(",") : "";
  }
}

/* A grouped bar chart as inline SVG (for before/after comparisons): groups = [{label, bars: [{name, value}]}]. */
function barChartSvg(groups, { unit = "", width = 520, height = 220 } = {}) {
  const NS = "http://www.w3.org/2000/svg";
  const svg = document.createElementNS(NS, "svg");
  svg.setAttribute("viewBox", `0 0 ${width} ${height}`);
  svg.setAttribute("class", "barchart");
  const pad = { left: 60, right: 10, top: 24, bottom: 30 };
  const values = groups.flatMap((g) => g.bars.map((b) => b.value)).filter((v) => Number.isFinite(v));
  const max = values.length ? Math.max(...values, 0) : 1;
  const ticks = niceTicks(0, max > 0 ? max : 1, 4);
  const h = height - pad.top - pad.bottom;
  const w = width - pad.left - pad.right;
  const Y = (v) => pad.top + h - (v / ticks.hi) * h;
  const add = (tag, attrs, text) => {
    const node = document.createElementNS(NS, tag);
    for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
    if (text !== undefined) node.textContent = text;
    svg.append(node);
    return node;
  };
  for (const v of ticks.ticks) {
    add("line", { x1: pad.left, x2: pad.left + w, y1: Y(v), y2: Y(v), stroke: "#e3e3e3" });
    add("text", { x: pad.left - 6, y: Y(v) + 4, "text-anchor": "end", "font-size": 11 }, tickLabel(v, ticks.step));
  }
  add("text", { x: 4, y: 14, "font-size": 11 }, unit);
  const groupW = w / Math.max(1, groups.length);
  const names = [...new Set(groups.flatMap((g) => g.bars.map((b) => b.name)))];
  groups.forEach((g, gi) => {
    const barW = (groupW * 0.7) / Math.max(1, g.bars.length);
    g.bars.forEach((b, bi) => {
      const x = pad.left + gi * groupW + groupW * 0.15 + bi * barW;
      const v = Number.isFinite(b.value) ? b.value : 0;
      const color = PLOT_COLORS[names.indexOf(b.name) % PLOT_COLORS.length];
      const rect = add("rect", { x, y: Y(v), width: Math.max(1, barW - 2), height: Math.max(0, pad.top + h - Y(v)), fill: color });
      const title = document.createElementNS(NS, "title");
      title.textContent = `${g.label} ${b.name}: ${Number.isFinite(b.value) ? b.value.toPrecision(4) : "n/a"} ${unit}`;
      rect.append(title);
    });
    add("text", { x: pad.left + gi * groupW + groupW / 2, y: height - 10, "text-anchor": "middle", "font-size": 12 }, g.label);
  });
  let lx = pad.left;
  names.forEach((name, i) => {
    add("rect", { x: lx, y: 6, width: 12, height: 8, fill: PLOT_COLORS[i % PLOT_COLORS.length] });
    add("text", { x: lx + 16, y: 14, "font-size": 11 }, name);
    lx += 24 + name.length * 7;
  });
  return svg;
}
