/* /ui/ : benches with their live state (GET /benches) and the runs list with status and progress
   (GET /runs), refreshed every 2 s. */
"use strict";

const STATUSES = ["queued", "running", "paused", "stopping", "suspended", "completed", "aborted", "failed"];
let refreshTimer = null;

function benchRow(b) {
  const run = b.current_run;
  const devices = b.devices || {};
  const probes = Object.keys(devices.probes || {});
  return el("tr", { dataset: { bench: b.name } },
    el("td", el("strong", b.name)),
    el("td", statusBadge(b.online ? (b.state || "online") : "offline")),
    el("td", b.worker || el("span.muted", "no worker")),
    el("td", run ? el("span", el("a", { href: `/ui/runs/${run.id}` }, `#${run.id}`), ` ${run.procedure} · ${run.gyro_id} · `,
      statusBadge(run.status), " ", `${fmtNum(run.progress_percent, 3)} %`) : el("span.muted", "none")),
    el("td.num", String(b.queued_runs)),
    el("td.muted", [
      devices.chamber && devices.chamber.transport ? `chamber ${devices.chamber.transport}` : null,
      devices.gyro && devices.gyro.frame ? `gyro ${devices.gyro.frame} @ ${devices.gyro.data_rate_hz} Hz` : null,
      probes.length ? `${probes.length} probes` : null,
    ].filter(Boolean).join(" · ")),
    el("td.muted", fmtTime(b.heartbeat_at)));
}

function runRow(r) {
  return el("tr", { dataset: { run: String(r.id), status: r.status } },
    el("td", el("a", { href: `/ui/runs/${r.id}` }, `#${r.id}`)),
    el("td", r.procedure),
    el("td", r.gyro_id ? el("a", { href: `/ui/gyros/${encodeURIComponent(r.gyro_id)}` }, r.gyro_id) : "–"),
    el("td", r.bench || "–"),
    el("td", statusBadge(r.status, r.outcome)),
    el("td", progressBar(r.progress_percent)),
    el("td.num", r.step_index === null || r.step_index === undefined ? "–" : String(r.step_index)),
    el("td", r.eta_utc ? fmtTime(r.eta_utc) : "–"),
    el("td", fmtTime(r.created_at)),
    el("td.muted", r.error || (r.worker_alive === false ? "worker not answering" : "")));
}

function table(headers, rows, emptyText) {
  return el("table",
    el("thead", el("tr", headers.map((h) => el("th", h)))),
    el("tbody", rows.length ? rows : el("tr", el("td.muted", { colSpan: headers.length }, emptyText))));
}

async function refresh() {
  const filter = document.getElementById("status-filter").value;
  const query = filter ? `?status=${encodeURIComponent(filter)}&limit=100` : "?limit=100";
  try {
    const [benches, runs] = await Promise.all([api("/benches"), api(`/runs${query}`)]);
    const bt = document.getElementById("benches");
    bt.replaceChildren(table(["Bench", "State", "Worker", "Current run", "Queued", "Devices", "Heartbeat"],
      benches.benches.map(benchRow), "No bench is configured: start a worker (bench worker --bench NAME)."));
    const rt = document.getElementById("runs");
    rt.replaceChildren(table(["Run", "Procedure", "Gyro", "Bench", "Status", "Progress", "Step", "ETA", "Created", ""],
      runs.runs.map(runRow), "No runs yet."));
    document.getElementById("runs-total").textContent = `${runs.total} run${runs.total === 1 ? "" : "s"}`;
    document.getElementById("updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
  } catch (err) {
    reportError(err, "refresh");
  }
}

function build() {
  const filter = el("select#status-filter", { on: { change: refresh } },
    el("option", { value: "" }, "all statuses"), STATUSES.map((s) => el("option", { value: s }, s)));
  content().replaceChildren(
    el("div.actions", el("a", { href: "/ui/start" }, el("button", { type: "button" }, "Start a run…")),
      el("span#updated.muted")),
    el("h2", "Benches"),
    el("div#benches"),
    el("h2", "Runs ", el("span#runs-total.muted")),
    el("div.actions", el("label.inline", "Show ", filter)),
    el("div#runs"));
}

initPage();
build();
onTokenReady(() => {
  refresh();
  if (!refreshTimer) refreshTimer = setInterval(refresh, 2000);
});
