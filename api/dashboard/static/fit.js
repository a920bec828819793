/* /ui/fits/{id} : one fit version (GET /fits/{id}) with its coefficients and error metrics, and its HTML
   report (GET /fits/{id}/report: before/after plots) shown in a sandboxed frame: the report is fetched
   with the token and given to the frame as srcdoc; the sandbox lets no script of it run. */
"use strict";

const FIT_ID = Number(pathParam(2));

function metricsTable(channels) {
  const rows = [];
  for (const [channel, entry] of Object.entries(channels || {})) {
    for (const [set, values] of Object.entries(entry.metrics || {})) {
      if (!values || typeof values !== "object") continue;
      for (const [name, value] of Object.entries(values)) {
        if (typeof value === "number") rows.push(el("tr", el("td", channel), el("td", set), el("td", name), el("td.num", fmtNum(value, 5))));
      }
    }
  }
  return rows.length ? el("table", el("thead", el("tr", ["Channel", "Data", "Metric", "Value"].map((h) => el("th", h)))), el("tbody", rows)) : null;
}

function renderFit(doc) {
  setTitle(`Fit #${doc.id}: ${doc.gyro_id} ${doc.model} v${doc.version}`);
  const coeffRows = [];
  for (const [channel, entry] of Object.entries(doc.channels || {})) {
    const units = entry.units || {};
    for (const [term, value] of Object.entries(entry.coefficients || {})) {
      coeffRows.push(el("tr", el("td", channel), el("td", term),
        el("td.num", typeof value === "number" ? value.toPrecision(9) : fmtValue(value)), el("td", units[term] || "")));
    }
  }
  fill(document.getElementById("fit"),
    el("p", doc.accepted ? statusBadge("accepted") : statusBadge("not accepted"), " ",
      el("a", { href: `/ui/gyros/${encodeURIComponent(doc.gyro_id)}` }, `gyro ${doc.gyro_id}`),
      ` · created ${fmtTime(doc.created_at)} · training runs `,
      ...(doc.run_ids || []).flatMap((r, i) => [i ? ", " : "", el("a", { href: `/ui/runs/${r}` }, `#${r}`)])),
    el("div.actions",
      el("button.secondary", { type: "button", on: { click: () => downloadWithToken(`/fits/${doc.id}/export`, `${doc.gyro_id}-${doc.model}-v${doc.version}.json`) } }, "Firmware export (JSON)"),
      doc.accepted ? null : el("button#accept", { type: "button", on: { click: () => accept(doc.id) } }, "Accept as the gyro's coefficients (admin)")),
    el("table", el("thead", el("tr", ["Channel", "Term", "Value", "Unit"].map((h) => el("th", h)))), el("tbody", coeffRows)),
    metricsTable(doc.channels));
}

function accept(id) {
  return acceptFit(id, load);
}

async function loadReport() {
  const box = document.getElementById("report");
  box.replaceChildren(el("p.muted", "Loading the report…"));
  try {
    /* 202: not rendered yet; a worker renders it (job in the answer): ask again until it is there */
    let html = await api(`/fits/${FIT_ID}/report`);
    while (typeof html !== "string") {
      if (html.status === "failed") throw new Error(html.error || "the report job failed");
      box.replaceChildren(el("p.muted", `Rendering the report (job ${html.id}, ${html.status})…`));
      await new Promise((resolve) => setTimeout(resolve, 1000));
      html = await api(`/fits/${FIT_ID}/report`);
    }
    const frame = el("iframe#report-frame.report", { sandbox: "", title: "fit report" });
    frame.srcdoc = html;
    box.replaceChildren(frame);
  } catch (err) {
    box.replaceChildren(el("p.muted", "No report."));
    reportError(err, "fit report");
  }
}

async function load() {
  try {
    renderFit(await api(`/fits/${FIT_ID}`));
  } catch (err) {
    reportError(err, `fit ${FIT_ID}`);
    return;
  }
  loadReport();
}

initPage();
if (!Number.isInteger(FIT_ID) || FIT_ID < 1) {
  showAlert(`Not a fit id in the address: ${location.pathname}`);
} else {
  content().replaceChildren(el("div#fit.card", el("p.muted", "Loading…")), el("h2", "Report"), el("div#report"));
  onTokenReady(load);
}
