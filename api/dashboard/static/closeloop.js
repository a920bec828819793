/* /ui/close-loop : past close-the-loop analyses (GET /close-loop, filtered by gyro, model and date:
   verdict and validation error before / after per channel) and a form to start one (POST /close-loop:
   declared model, training run, held-out run); /ui/close-loop/{id} : its report (GET /close-loop/{id}, polled until done): per
   channel the verdict, the findings, validation and training errors before / after the added effects
   (bar chart), the effects added and the final coefficients; on request the HTML report with its
   plots (GET /close-loop/{id}/report). */
"use strict";

const ANALYSIS_ID = pathParam(2) === null ? null : Number(pathParam(2));
const METRICS = [["validation_std100_dph", "validation std of 100-s means"], ["validation_rms_dph", "validation RMS"],
  ["train_std100_dph", "training std of 100-s means"], ["train_rms_dph", "training RMS"]];

function renderChannel(channel, r) {
  const metricRows = METRICS.map(([key, label]) => el("tr", el("td", label),
    el("td.num", fmtNum((r.before || {})[key], 5)), el("td.num", fmtNum((r.after || {})[key], 5))));
  const effects = (r.effects_added || []).map((e) => {
    const ev = e.evidence || {};
    return el("tr", { dataset: { effect: e.kind } }, el("td", String(e.kind)), el("td.wrap", fmtValue(e.params, 4)),
      el("td.wrap", Object.entries(e.coefficients || {}).map(([t, v]) => `${t} = ${fmtNum(v, 5)}`).join("; ") || "–"),
      el("td.num", fmtNum(ev.delta_bic, 4)), el("td.num", fmtNum(ev.hac_wald_p, 3)),
      el("td.num", fmtQty(e.validation_std100_dph, "deg/h")));
  });
  const coeffs = Object.entries(r.final_coefficients || {}).map(([term, value]) =>
    el("tr", el("td", term), el("td.num", typeof value === "number" ? value.toPrecision(7) : String(value))));
  return el("div.card", { dataset: { channel } },
    el("h2", `Channel ${channel}: `, el("span", { class: `verdict-${r.verdict}` }, String(r.verdict || "").replace(/_/g, " "))),
    el("p", r.findings || ""),
    el("p.muted", `declared ${r.declared_model}; primary probe ${r.primary_probe || "–"}; noise floor ${fmtNum(r.noise_floor_dph, 4)} deg/h`),
    el("table", el("thead", el("tr", el("th", "error (deg/h)"), el("th.num", "before"), el("th.num", "after"))), el("tbody", metricRows)),
    el("h3", "Effects added"), effects.length ? el("table.effects", el("thead", el("tr",
      ["Effect", "Parameters", "Coefficients", "ΔBIC", "HAC Wald p", "Validation std of 100-s means after"].map((h) => el("th", h)))),
    el("tbody", effects)) : el("p.muted", "none"),
    el("h3", "Final terms and coefficients"), el("table", el("tbody", coeffs)));
}

function renderReport(doc) {
  setTitle(`Close the loop #${doc.id}`);
  const req = doc.request || {};
  const head = el("div.card",
    el("p", statusBadge(doc.status === "done" ? "completed" : doc.status), ` model ${req.model}: training run `,
      el("a", { href: `/ui/runs/${req.train_run_id}` }, `#${req.train_run_id}`), ", held-out run ",
      el("a", { href: `/ui/runs/${req.validation_run_id}` }, `#${req.validation_run_id}`),
      doc.gyro_id ? ` · gyro ${doc.gyro_id}` : "", ` · requested ${fmtTime(doc.created_at)} by ${doc.requested_by}`),
    doc.error ? el("p.alert.error", doc.error) : null);
  head.dataset.status = doc.status;
  const parts = [head];
  const result = doc.result;
  if (doc.status === "done" && result) {
    const channels = Object.entries(result.channels || {});
    parts.push(el("div.card", el("h2", "Validation std of 100-s means, before and after (deg/h)"),
      barChartSvg(channels.map(([ch, r]) => ({
        label: ch,
        bars: [{ name: "before", value: (r.before || {}).validation_std100_dph },
          { name: "after", value: (r.after || {}).validation_std100_dph },
          { name: "noise floor", value: r.noise_floor_dph }],
      })), { unit: "deg/h" })));
    for (const [ch, r] of channels) parts.push(renderChannel(ch, r));
    parts.push(el("div.card", el("h2", "Report with plots"),
      el("p.muted", "Residuals before / after against time, temperature and its rate; Allan deviation. "
        + "The server re-runs the analysis to draw them, which takes a while."),
      el("button#load-report", { type: "button", on: { click: loadReport } }, "Show the report"),
      el("div#cl-report")));
  } else if (doc.status !== "failed") {
    parts.push(el("p.muted", "The analysis is running; this page updates when it is done."));
  }
  content().replaceChildren(...parts);
  return doc.status === "done" || doc.status === "failed";
}

/* GET /close-loop/{id}/report (HTML) in a sandboxed frame: no script of it runs. */
async function loadReport() {
  const box = document.getElementById("cl-report");
  document.getElementById("load-report").disabled = true;
  box.replaceChildren(el("p.muted", "Rendering…"));
  try {
    const html = await api(`/close-loop/${ANALYSIS_ID}/report`);
    const frame = el("iframe#cl-report-frame.report", { sandbox: "", title: "close-the-loop report" });
    frame.srcdoc = html;
    box.replaceChildren(frame);
  } catch (err) {
    box.replaceChildren();
    document.getElementById("load-report").disabled = false;
    reportError(err, "close-the-loop report");
  }
}

async function poll() {
  try {
    const finished = renderReport(await api(`/close-loop/${ANALYSIS_ID}`));
    if (!finished) setTimeout(poll, 2000);
  } catch (err) {
    reportError(err, `close-loop analysis ${ANALYSIS_ID}`);
  }
}

function analysisRow(a) {
  const req = a.request || {};
  const chs = Object.entries(a.channels || {});
  return el("tr", { dataset: { analysis: String(a.id), gyro: a.gyro_id || "", model: a.model || "" } },
    el("td", el("a", { href: `/ui/close-loop/${a.id}` }, `#${a.id}`)),
    el("td", a.gyro_id ? el("a", { href: `/ui/gyros/${encodeURIComponent(a.gyro_id)}` }, a.gyro_id) : "–"),
    el("td.wrap", a.model || "–"),
    el("td", el("a", { href: `/ui/runs/${req.train_run_id}` }, `#${req.train_run_id}`), " → ",
      el("a", { href: `/ui/runs/${req.validation_run_id}` }, `#${req.validation_run_id}`)),
    el("td", statusBadge(a.status)),
    el("td.wrap", chs.length ? chs.map(([ch, c]) => el("div", `${ch}: `,
      el("span", { class: `verdict-${c.verdict}` }, String(c.verdict || "").replace(/_/g, " ")),
      c.effects_added.length ? ` (+ ${c.effects_added.join(", ")})` : "")) : a.error || "–"),
    el("td.wrap", chs.length ? chs.map(([ch, c]) => el("div", `${ch}: ${fmtNum(c.before_validation_std100_dph, 3)} → `
      + `${fmtNum(c.after_validation_std100_dph, 3)} deg/h`)) : "–"),
    el("td", fmtTime(a.created_at)));
}

async function loadList(query = filterQuery()) {
  try {
    const doc = await api(`/close-loop?${query}`);
    const rows = doc.analyses.map(analysisRow);
    document.getElementById("analysis-list").replaceChildren(el("table.list#analyses-table",
      el("thead", el("tr", ["Analysis", "Gyro", "Declared model", "Runs (training → held-out)", "Status", "Verdict",
        "Validation std of 100-s means, before → after", "Requested"].map((h) => el("th", h)))),
      el("tbody", rows.length ? rows : el("tr", el("td.muted", { colSpan: 8 }, "No analysis matches.")))));
  } catch (err) {
    reportError(err, "close-the-loop analyses");
  }
}

function buildList() {
  content().append(el("h2", "Past analyses"), filterBar("analysis-filters", loadList),
    el("div#analysis-list", el("p.muted", "Loading…")));
}

function buildForm() {
  const num = (id, label) => el("label", { dataset: { field: id } }, label, el(`input#${id}`, { type: "number", min: "1", step: "1", required: true }), el("span.field-error"));
  content().replaceChildren(el("h2", "New analysis"), el("form#closeloop-form.card", {
    on: {
      submit: async (ev) => {
        ev.preventDefault();
        clearAlert();
        const body = {
          model: document.getElementById("model").value.trim(),
          train_run_id: Number(document.getElementById("train_run_id").value),
          validation_run_id: Number(document.getElementById("validation_run_id").value),
        };
        try {
          const doc = await api("/close-loop", { method: "POST", json: body });
          location.assign(`/ui/close-loop/${doc.id}`);
        } catch (err) {
          reportError(err, "start the analysis");
        }
      },
    },
  }, el("p.muted", "Fit the declared model on the training run, look for effects it misses, keep those that help on the held-out run."),
  el("div.params",
    el("label", { dataset: { field: "model" } }, "Declared model", el("input#model", { type: "text", required: true, value: "static" }),
      el("span.hint", "a model name (static, dynamic, …) or a formula"), el("span.field-error")),
    num("train_run_id", "Training run"), num("validation_run_id", "Held-out run")),
  el("div.actions", el("button", { type: "submit" }, "Analyse"))));
}

initPage();
if (ANALYSIS_ID === null) {
  buildForm();
  buildList();
  onTokenReady(() => loadList());
} else if (!Number.isInteger(ANALYSIS_ID) || ANALYSIS_ID < 1) {
  showAlert(`Not an analysis id in the address: ${location.pathname}`);
} else {
  onTokenReady(poll);
}
