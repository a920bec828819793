/* /ui/runs/{id} : one run.  State from GET /runs/{id}; pause / resume / stop / abort (POST
   /runs/{id}/<command>); live plots of chamber set point and air temperature, probe temperatures and
   gyro output from GET /runs/{id}/data (aligned 1-s means, fetched incrementally with t_from and
   decimated with every=N so a long run stays near MAX_POINTS points); events and status changes live
   from the SSE stream GET /runs/{id}/events?follow=true (read with fetch, which can send the token).
   A multi-gyro run (several gyros in one chamber) also lists its gyros (GET /runs/{id} "units": each
   gyro's own run, state, gaps, latest readings) with plots of each gyro's 1-s means and of its own
   probes from that gyro's run (GET /runs/{unit run}/data, refetched at most every UNIT_REFRESH_MS);
   the parent run stores no frames, so its chamber plot reads the first gyro's run (every gyro's run
   holds the chamber's readings) and the run-wide probe and gyro plots give way to the per-gyro ones. */
"use strict";

const RUN_ID = Number(pathParam(2));
const TERMINAL = ["completed", "aborted", "failed"];
const MAX_POINTS = 2000;
const UNIT_POINTS = 500;
const UNIT_REFRESH_MS = 10000;
const CONTROLS = {
  pause: { label: "Pause", allowed: ["running", "suspended"] },
  resume: { label: "Resume", allowed: ["paused"] },
  stop: { label: "Stop", allowed: ["queued", "running", "paused", "stopping", "suspended"],
          confirm: "Stop the run? It finishes the current recording, then puts the bench in a safe state." },
  abort: { label: "Abort", allowed: ["queued", "running", "paused", "stopping", "suspended"], danger: true,
           confirm: "Abort the run now? The bench goes to a safe state immediately." },
};

const state = {
  run: null,
  series: { t: [], cols: {} },   // plotted data: t = hours since the first second, cols[name] = values
  lastBenchT: null,
  every: 1,
  loadingData: false,
  refreshing: false,
  refreshAgain: false,
  events: [],
  lastEventId: 0,
  stream: null,
  plots: {},
  unitPlots: {},          // slot -> LinePlot of that gyro's 1-s means
  unitProbePlots: {},     // slot -> LinePlot of that gyro's probes
  unitsLoadedAt: 0,
};

/* -------------------------------------------------------------------------------- run state */
function dl(pairs) {
  return el("dl.kv", pairs.flatMap(([k, v]) => [el("dt", k), el("dd", v === null || v === undefined ? "–" : v)]));
}

function renderSummary(run) {
  setTitle(`Run #${run.id}: ${run.procedure}`);
  const step = run.step ? `${run.step.index + 1} of ${run.step.n_steps}: ${run.step.kind} (${run.step.status})` : "–";
  const box = document.getElementById("summary");
  fill(box,
    el("div.grid",
      dl([
        ["Status", statusBadge(run.status, run.outcome)],
        ["Progress", progressBar(run.progress_percent)],
        ["Step", step],
        ["Gyro", run.gyro_id ? el("a", { href: `/ui/gyros/${encodeURIComponent(run.gyro_id)}` }, run.gyro_id) : "–"],
        ["Bench", run.bench],
      ]),
      dl([
        ["ETA", run.eta_utc ? fmtTime(run.eta_utc) : "–"],
        ["Elapsed (bench)", fmtDuration(run.elapsed_bench_s)],
        ["Remaining (bench)", fmtDuration(run.remaining_bench_s)],
        // one total that always agrees with the two lines above; the plan's own estimate only beside it
        ["Total (elapsed + remaining)", el("span#total-bench", { dataset: {
          elapsed: String(run.elapsed_bench_s ?? ""), remaining: String(run.remaining_bench_s ?? "") } }, totalText(run))],
        ["Worker", run.worker ? `${run.worker}${run.worker_alive === false ? " (not answering)" : ""}` : "–"],
      ]),
      dl([
        ["Operator", run.operator],
        ["Created", fmtTime(run.created_at)],
        ["Scheduled", run.start_at ? fmtTime(run.start_at) : "–"],
        ["Started", fmtTime(run.started_at)],
        ["Finished", fmtTime(run.finished_at)],
      ])),
    run.error ? el("p.alert.error", run.error) : null,
    (run.pending_requests || []).length
      ? el("p.muted", `Pending requests: ${run.pending_requests.map((r) => r.command).join(", ")} (the worker applies them at its next tick)`)
      : null);
  document.getElementById("run-status").textContent = run.status;
  if (TERMINAL.includes(run.status)) document.getElementById("live").textContent = `run ${run.status}`;
  document.getElementById("run-progress").textContent = String(run.progress_percent);
  for (const [command, spec] of Object.entries(CONTROLS)) {
    document.getElementById(`btn-${command}`).disabled = !spec.allowed.includes(run.status);
  }
  renderLatest(run.latest || {});
  renderSampling(run.sampling);
  renderSteps(run);
  renderUnits(run);
  fill(document.getElementById("params"), paramTable(run.parameters || {}));
}

/* -------------------------------------------------------------------------------- gyros of a multi-gyro run */
function renderUnits(run) {
  const units = run.units || [];
  const card = document.getElementById("units-card");
  card.hidden = units.length === 0;
  for (const id of ["probes", "gyro"]) document.getElementById(`card-${id}`).hidden = units.length > 0;
  if (!units.length) return;
  const rows = units.map((u) => {
    const m = u.latest && u.latest.gyro && u.latest.gyro.mean_1s;
    const mean = m && m.gyro.some((v) => v !== null && v !== undefined)
      ? `${m.gyro.map((v) => fmtNum(v, 5)).join(", ")} (${m.output_unit})` : "–";
    return el("tr", { dataset: { slot: u.slot } },
      el("td", u.slot),
      el("td", el("a", { href: `/ui/gyros/${encodeURIComponent(u.gyro_id)}` }, u.gyro_id)),
      el("td", el("a", { href: `/ui/runs/${u.run_id}` }, `#${u.run_id}`)),
      el("td", statusBadge(u.status, u.outcome)),
      el("td.num", u.latest && u.latest.gyro ? String(u.latest.gyro.frames) : "–"),
      el("td", mean),
      el("td.num", u.gaps.length ? `${u.gaps.length} (${fmtDuration(u.bench_seconds_lost)})` : "0"),
      el("td.wrap", u.error || ""));
  });
  fill(document.getElementById("units"),
    el("table#units-table", el("thead", el("tr", ["Slot", "Gyro", "Its run", "State", "Frames", "Latest 1-s mean",
      "Gaps (bench time lost)", "Fault"].map((h) => el("th", h)))), el("tbody", rows)));
  const plots = document.getElementById("unit-plots");
  for (const u of units) {
    if (state.unitPlots[u.slot]) continue;
    const canvas = el(`canvas#plot-unit-${u.slot}.plot`);
    const probes = el(`canvas#plot-unit-probes-${u.slot}.plot`);
    plots.append(el("div.card", { dataset: { slot: u.slot } },
      el("h3", `${u.slot}: gyro ${u.gyro_id}, 1-s means (deg/h)`), canvas,
      el("h3", `${u.slot}: its probes (°C)`), probes));
    const xLabel = "bench time since the run's first second (h)";
    state.unitPlots[u.slot] = new LinePlot(canvas, { xLabel, yLabel: "deg/h" });
    state.unitProbePlots[u.slot] = new LinePlot(probes, { xLabel, yLabel: "°C" });
  }
  if (Date.now() - state.unitsLoadedAt >= UNIT_REFRESH_MS || TERMINAL.includes(run.status)) loadUnitData(run);
}

async function loadUnitData(run) {
  state.unitsLoadedAt = Date.now();
  const every = Math.max(1, Math.ceil((run.elapsed_bench_s || 0) / UNIT_POINTS));
  for (const u of run.units || []) {
    try {
      const doc = await api(`/runs/${u.run_id}/data?stream=seconds&format=json&every=${every}`);
      const t = doc.columns.bench_time_s || [];
      const t0 = state.t0 !== undefined ? state.t0 : (t.length ? Math.floor(t[0]) : 0);
      const hours = t.map((v) => (v - t0) / 3600);
      const pick = (test) => Object.keys(doc.columns).filter(test).sort();
      state.unitPlots[u.slot].setData(hours,
        pick((n) => n.startsWith("gyro_")).map((n) => ({ name: n.replace(/^gyro_/, ""), values: doc.columns[n] })));
      state.unitProbePlots[u.slot].setData(hours, pick((n) => n.startsWith("temp_") && n !== "temp_point_c")
        .map((n) => ({ name: n === "temp_gyro" ? "gyro sensor" : n.replace(/^temp_/, ""), values: doc.columns[n] })));
    } catch (err) {
      reportError(err, `the data of gyro ${u.gyro_id} (run ${u.run_id})`);
    }
  }
  // the run's status these plots were loaded for (a finished run's are final)
  document.getElementById("unit-plots").dataset.loadedFor = run.status;
}

/* elapsed + remaining, and the plan's estimate when they differ noticeably (holds that waited for
   stability, suspensions): never a total shorter than the time already elapsed. */
function totalText(run) {
  const e = run.elapsed_bench_s;
  const r = run.remaining_bench_s;
  if (!Number.isFinite(e) || !Number.isFinite(r)) return fmtDuration(run.estimated_total_bench_s);
  const total = e + r;
  const planned = run.estimated_total_bench_s;
  const note = Number.isFinite(planned) && Math.abs(planned - total) > 0.02 * Math.max(planned, total)
    ? ` (planned ${fmtDuration(planned)})` : "";
  return `${fmtDuration(total)}${note}`;
}

function renderLatest(latest) {
  const rows = [];
  if (latest.chamber) {
    // the set point the controller works to, as the chamber plot draws it: the ramping one while a ramp
    // runs (the set-point register keeps the ramp's start until it ends), else the register
    const ramping = Number.isFinite(latest.chamber.ramp_setpoint_c);
    const sp = ramping ? latest.chamber.ramp_setpoint_c : latest.chamber.setpoint_c;
    rows.push(["Chamber air", `${fmtNum(latest.chamber.pv_c)} °C (set point ${fmtNum(sp)} °C${ramping ? ", ramping" : ""})`]);
    if (latest.chamber.alarm) rows.push(["Chamber alarm", String(latest.chamber.alarm)]);
  }
  if (latest.probes) {
    for (const [name, c] of Object.entries(latest.probes.celsius || {})) {
      const fault = (latest.probes.faults || {})[name];
      rows.push([`Probe ${name}`, fault ? `fault: ${fault}` : `${fmtNum(c)} °C`]);
    }
  }
  if (latest.gyro) {
    const m = latest.gyro.mean_1s;
    rows.push(["Gyro frames", `${latest.gyro.frames}`]);
    if (m && m.gyro.some((v) => v !== null && v !== undefined)) {
      rows.push(["Gyro 1-s mean", `${m.gyro.map((v) => fmtNum(v, 5)).join(", ")} (${m.output_unit}); sensor ${fmtNum(m.temperature_c)} °C`]);
    } else if (m) {
      rows.push(["Gyro 1-s mean", "no complete second stored yet"]);
    }
    if (latest.gyro.mean_1s_error) rows.push(["Gyro", latest.gyro.mean_1s_error]);
  }
  if (latest.turntable) rows.push(["Turntable", `axis 1 ${fmtNum(latest.turntable.axis1_deg)}°, axis 2 ${fmtNum(latest.turntable.axis2_deg)}°`]);
  if (latest.psu) rows.push(["Power supply", `${latest.psu.on ? "on" : "off"}, ${fmtNum(latest.psu.volts)} V, ${fmtNum(latest.psu.amps)} A`]);
  document.getElementById("latest").replaceChildren(rows.length ? dl(rows) : el("p.muted", "No readings yet."));
}

function renderSampling(sampling) {
  // readings and intervals per device, in bench seconds (GET /runs/{id} "sampling")
  const devices = [["probes", "Probes (bus reads)"], ["chamber", "Chamber"], ["turntable", "Turntable"], ["psu", "Power supply"], ["gyro", "Gyro frames"]];
  // a multi-gyro run: probes and frames are stored per gyro, so they are listed per fixture slot
  const units = (sampling && sampling.units) || null;
  const row = (label, d) => el("tr", el("td", label), el("td.num", String(d.readings)),
    el("td.num", d.median_interval_s === null ? "–" : fmtNum(d.median_interval_s, 3)),
    el("td.num", d.max_interval_s === null ? "–" : fmtNum(d.max_interval_s, 3)));
  const rows = devices.filter(([key]) => sampling && sampling[key] && !(units && (key === "probes" || key === "gyro")))
    .map(([key, label]) => row(label, sampling[key]));
  for (const [slot, unit] of Object.entries(units || {})) {
    rows.push(row(`${slot}: probes (bus reads)`, unit.probes));
    rows.push(row(`${slot}: gyro frames`, unit.gyro));
  }
  document.getElementById("sampling").replaceChildren(rows.length
    ? el("table#sampling-table", el("thead", el("tr", ["Device", "Readings", "Median interval (bench s)", "Max interval (bench s)"].map((h) => el("th", h)))),
      el("tbody", rows))
    : el("p.muted", "No readings yet."));
}

/* {a: 1, b: {c: 2}} -> rows "a | 1", "b.c | 2" */
function paramTable(params) {
  const rows = [];
  const walk = (prefix, value) => {
    if (value && typeof value === "object" && !Array.isArray(value)) {
      for (const [k, v] of Object.entries(value)) walk(prefix ? `${prefix}.${k}` : k, v);
    } else {
      rows.push(el("tr", { dataset: { param: prefix } }, el("td", prefix), el("td", fmtValue(value))));
    }
  };
  walk("", params);
  return el("table#params-table", el("thead", el("tr", el("th", "Parameter"), el("th", "Value"))), el("tbody", rows));
}

function fitsTable(fits) {
  // a multi-gyro run's fit step fits every gyro's run: one row per gyro (its slot and ID)
  const entries = Object.entries(fits).flatMap(([stepIndex, f]) => (f.units
    ? Object.entries(f.units).map(([slot, u]) => ({ stepIndex, f: u, slot, gyro: u.gyro_id }))
    : [{ stepIndex, f }]));
  const perGyro = entries.some((e) => e.slot);
  const rows = entries.map(({ stepIndex, f, slot, gyro }) => el("tr", { dataset: slot ? { step: stepIndex, slot } : { step: stepIndex } },
    el("td.num", String(Number(stepIndex) + 1)), perGyro ? el("td", slot ? `${slot}${gyro ? ` (${gyro})` : ""}` : "–") : null,
    el("td", statusBadge(f.status)),
    el("td", Object.entries(f.versions || {}).map(([m, v]) => `${m} v${v}`).join(", ") || "–"),
    el("td.wrap", (f.fitted || []).join(", ") || "–"), el("td", f.accepted ? "yes" : "no"),
    el("td.wrap", f.reason || f.error || Object.entries(f.errors || {}).map(([k, v]) => `${k}: ${v}`).join("; ") || "")));
  const heads = ["Step", ...(perGyro ? ["Gyro"] : []), "Status", "Versions", "Fitted", "Accepted", "Notes"];
  return el("table#run-fits", el("thead", el("tr", heads.map((h) => el("th", h)))), el("tbody", rows));
}

function renderSteps(run) {
  // bench times shown from the first step's start
  const t0 = (run.steps || []).map((s) => s.started_t).find((t) => t !== null && t !== undefined);
  const rel = (t) => (t === null || t === undefined || t0 === undefined ? "–" : `+${fmtDuration(t - t0)}`);
  const rows = (run.steps || []).map((s) => el("tr", { class: s.index === run.step_index ? "current" : null },
    el("td.num", String(s.index + 1)), el("td", s.kind), el("td", statusBadge(s.status)),
    el("td.num", rel(s.started_t)), el("td.num", rel(s.finished_t))));
  const extra = [];
  if ((run.gaps || []).length) extra.push(el("li", `lost: ${run.frames_lost} frames, ${fmtDuration(run.bench_seconds_lost)} of bench time`));
  for (const g of run.gaps || []) extra.push(el("li", `gap ${rel(g.t_from)} to ${rel(g.t_to)}: ${g.reason} (${g.frames_missing} frames missing)`));
  for (const s of run.suspensions || []) extra.push(el("li", `suspended ${rel(s.t_from)} to ${rel(s.t_to)}: ${s.reason}`));
  fill(document.getElementById("steps"),
    el("table", el("thead", el("tr", ["#", "Step", "Status", "Started (bench time)", "Finished (bench time)"].map((h) => el("th", h)))),
      el("tbody", rows.length ? rows : el("tr", el("td.muted", { colSpan: 5 }, "The worker has not planned the steps yet.")))),
    extra.length ? el("ul", extra) : null,
    run.fits ? el("h3", "Fits of this run") : null,
    run.fits ? fitsTable(run.fits) : null);
}

/* -------------------------------------------------------------------------------- data + plots */
function appendData(columns) {
  const t = columns.bench_time_s || [];
  if (!t.length) return 0;
  const s = state.series;
  if (state.t0 === undefined) state.t0 = Math.floor(t[0]);
  const names = Object.keys(columns).filter((n) => n === "chamber_sp" || n === "chamber_pv" || n === "chamber_ramp_sp"
    || (n.startsWith("temp_") && n !== "temp_point_c") || n.startsWith("gyro_"));
  const before = s.t.length;
  for (let i = 0; i < t.length; i++) {
    if (state.lastBenchT !== null && t[i] <= state.lastBenchT) continue;
    s.t.push((t[i] - state.t0) / 3600);
    for (const n of names) {
      if (!s.cols[n]) s.cols[n] = new Array(s.t.length - 1).fill(null);
      s.cols[n].push(columns[n][i]);
    }
    for (const n of Object.keys(s.cols)) {
      if (s.cols[n].length < s.t.length) s.cols[n].push(null);
    }
    state.lastBenchT = t[i];
  }
  // keep the plots light: past MAX_POINTS, drop every other point and fetch at half the rate
  while (s.t.length > MAX_POINTS) {
    s.t = s.t.filter((_, i) => i % 2 === 0);
    for (const n of Object.keys(s.cols)) s.cols[n] = s.cols[n].filter((_, i) => i % 2 === 0);
    state.every *= 2;
  }
  return s.t.length - before;
}

function drawPlots() {
  const s = state.series;
  const pick = (prefix) => Object.keys(s.cols).filter((n) => n.startsWith(prefix)).sort();
  // the controller's working set point moves along a ramp while the set-point register does not follow
  // it: plot the ramping one while the chamber reports it, the register before and after the ramp (one
  // continuous trace through soak, ramp and hold)
  const rampSp = s.cols.chamber_ramp_sp || [];
  const ramp = rampSp.some((v) => v !== null && Number.isFinite(v));
  const working = (s.cols.chamber_sp || []).map((v, i) => (Number.isFinite(rampSp[i]) ? rampSp[i] : v));
  state.plots.chamber.setData(s.t, [
    ramp ? { name: "set point (ramping)", values: working, color: "#1f77b4", dash: [5, 4] }
      : { name: "set point", values: s.cols.chamber_sp || [], color: "#7f7f7f", dash: [5, 4] },
    { name: "chamber air", values: s.cols.chamber_pv || [], color: "#d62728" },
  ]);
  const temps = pick("temp_").filter((n) => n !== "temp_point_c");
  state.plots.probes.setData(s.t, temps.map((n) => ({ name: n === "temp_gyro" ? "gyro sensor" : n.replace(/^temp_/, ""), values: s.cols[n] })));
  state.plots.gyro.setData(s.t, pick("gyro_").map((n) => ({ name: n.replace(/^gyro_/, ""), values: s.cols[n] })));
  document.getElementById("data-info").textContent = s.t.length
    ? `${s.t.length} points, every ${state.every} s of data (1-s means)` : "";
}

async function loadData() {
  if (state.loadingData) return;
  state.loadingData = true;
  try {
    // first load: size the decimation from the run's elapsed bench time
    if (state.lastBenchT === null && state.run && state.run.elapsed_bench_s) {
      state.every = Math.max(1, Math.ceil(state.run.elapsed_bench_s / MAX_POINTS));
    }
    const from = state.lastBenchT === null ? "" : `&t_from=${encodeURIComponent(state.lastBenchT + 0.5)}`;
    // a multi-gyro run: its chamber's readings as stored with its first gyro's run (see the top)
    const units = (state.run && state.run.units) || [];
    const source = units.length ? units[0].run_id : RUN_ID;
    const doc = await api(`/runs/${source}/data?stream=seconds&format=json&every=${state.every}${from}`);
    if (appendData(doc.columns) > 0 || !state.drawnOnce) {
      drawPlots();
      state.drawnOnce = true;
    }
  } catch (err) {
    reportError(err, "load the run's data");
  } finally {
    state.loadingData = false;
  }
}

/* -------------------------------------------------------------------------------- refresh loop */
async function refresh() {
  if (state.refreshing) {
    state.refreshAgain = true;
    return;
  }
  state.refreshing = true;
  try {
    const run = await api(`/runs/${RUN_ID}`);
    state.run = run;
    renderSummary(run);
    await loadData();
  } catch (err) {
    reportError(err, `run ${RUN_ID}`);
  } finally {
    state.refreshing = false;
    if (state.refreshAgain) {
      state.refreshAgain = false;
      setTimeout(refresh, 300);
    }
  }
}

/* -------------------------------------------------------------------------------- events */
function addEvent(e) {
  if (e.id <= state.lastEventId) return;
  state.lastEventId = e.id;
  state.events.unshift(e);
  if (state.events.length > 300) state.events.pop();
  const list = document.getElementById("events");
  list.prepend(el("li", { class: `level-${e.level || "info"}`, dataset: { kind: e.kind } },
    el("span.muted", `${fmtTime(e.time)} `), el("strong", e.kind), ` ${e.message || ""}`));
  while (list.children.length > 300) list.lastChild.remove();
}

/* Refresh at most once a second however fast status events arrive. */
function scheduleRefresh() {
  if (state.refreshTimer) return;
  const wait = Math.max(0, 1000 - (Date.now() - (state.lastRefreshAt || 0)));
  state.refreshTimer = setTimeout(() => {
    state.refreshTimer = null;
    state.lastRefreshAt = Date.now();
    refresh();
  }, wait);
}

async function followLoop() {
  if (state.following) return;
  state.following = true;
  try {
    for (;;) {
      const controller = new AbortController();
      state.stream = controller;
      try {
        await followEvents(`/runs/${RUN_ID}/events?follow=true&after=${state.lastEventId}`, (kind, data) => {
          if (kind === "status") {
            // the progress figure is the bar above (refreshed now); this line only says the stream is live
            document.getElementById("live").textContent = `live: ${data.status}`;
            scheduleRefresh();
          } else if (kind !== "end" && data && typeof data === "object" && data.id !== undefined) {
            addEvent(data);
          }
        }, controller);
      } catch (err) {
        if (err instanceof ApiError && [401, 403, 404].includes(err.status)) {
          reportError(err, "live events");
          return;
        }
        if (err.name === "AbortError") return;
        document.getElementById("live").textContent = "live events interrupted; reconnecting…";
      }
      await refresh();
      if (state.run && TERMINAL.includes(state.run.status)) break;
      await new Promise((resolve) => setTimeout(resolve, 1500));
    }
    document.getElementById("live").textContent = `run ${state.run.status}`;
  } finally {
    state.following = false;
  }
}

/* -------------------------------------------------------------------------------- controls */
async function control(command) {
  const spec = CONTROLS[command];
  if (spec.confirm && !window.confirm(spec.confirm)) return;
  clearAlert();
  try {
    const answer = await api(`/runs/${RUN_ID}/${command}`, { method: "POST" });
    showAlert(answer.cancelled ? `Run #${RUN_ID} cancelled before it started.`
      : `${spec.label} requested: ${answer.detail || "sent"}.`, "ok");
  } catch (err) {
    reportError(err, `${command} run ${RUN_ID}`);
  }
  refresh();
}

function build() {
  const plotCard = (id, title) => el(`div.card#card-${id}`, el("h2", title), el(`canvas#plot-${id}.plot`));
  content().replaceChildren(
    el("div.card",
      el("div#summary", el("p.muted", "Loading…")),
      el("div.actions",
        Object.entries(CONTROLS).map(([command, spec]) => el(`button#btn-${command}`, {
          type: "button", class: spec.danger ? "danger" : null, disabled: true, on: { click: () => control(command) },
        }, spec.label)),
        el("button#btn-csv.secondary", { type: "button", on: { click: () => downloadWithToken(`/runs/${RUN_ID}/data?stream=seconds&format=csv`, `run${RUN_ID}-seconds.csv`) } }, "Download 1-s data (CSV)"),
        el("span#live.muted")),
      el("span#run-status", { hidden: true }), el("span#run-progress", { hidden: true })),
    el("div.grid",
      el("div.card", el("h2", "Latest readings"), el("div#latest")),
      el("div.card", el("h2", "Events"), el("ul#events.events"))),
    plotCard("chamber", "Chamber: set point and air temperature (°C)"),
    plotCard("probes", "Probe temperatures (°C)"),
    plotCard("gyro", "Gyro output, 1-s means (deg/h)"),
    el("p#data-info.muted"),
    el("div.card#units-card", { hidden: true }, el("h2", "Gyros in this run"), el("div#units"), el("div#unit-plots")),
    el("div.card", el("h2", "Sampling"), el("div#sampling")),
    el("div.card", el("h2", "Steps"), el("div#steps")),
    el("div.card", el("h2", "Parameters"), el("div#params")));
  const xLabel = "bench time since the first recorded second (h)";
  state.plots.chamber = new LinePlot(document.getElementById("plot-chamber"), { xLabel, yLabel: "°C" });
  state.plots.probes = new LinePlot(document.getElementById("plot-probes"), { xLabel, yLabel: "°C" });
  state.plots.gyro = new LinePlot(document.getElementById("plot-gyro"), { xLabel, yLabel: "deg/h" });
}

initPage();
if (!Number.isInteger(RUN_ID) || RUN_ID < 1) {
  showAlert(`Not a run id in the address: ${location.pathname}`);
} else {
  build();
  setInterval(() => {
    if (state.run && !TERMINAL.includes(state.run.status)) refresh();
  }, 3000);
  onTokenReady(() => {
    refresh().then(followLoop);
  });
}
