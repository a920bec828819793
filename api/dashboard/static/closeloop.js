/* /ui/close-loop : start a close-the-loop analysis (POST /close-loop: declared model, training run,
   held-out run); /ui/close-loop/{id} : its report (GET /close-loop/{id}, polled until done): per
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
  const effects = (r.effects_added || []).map((e) => el("li", typeof e === "object" ? JSON.stringify(e) : String(e)));
  const coeffs = Object.entries(r.final_coefficients || {}).map(([term, value]) =>
    el("tr", el("td", term), el("td.num", typeof value === "number" ? value.toPrecision(7) : String(value))));
  return el("div.card", { dataset: { channel } },
    el("h2", `Channel ${channel}: `, el("span", { class: `verdict-${r.verdict}` }, String(r.verdict || "").replace(/_/g, " "))),
    el("p", r.findings || ""),
    el("p.muted", `declared ${r.declared_model}; primary probe ${r.primary_probe || "–"}; noise floor ${fmtNum(r.noise_floor_dph, 4)} deg/h`),
    el("table", el("thead", el("tr", el("th", "error (deg/h)"), el("th.num", "before"), el("th.num", "after"))), el("tbody", metricRows)),
    el("h3", "Effects added"), effects.length ? el("ul", effects) : el("p.muted", "none"),
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

function buildForm() {
  const num = (id, label) => el("label", { dataset: { field: id } }, label, el(`input#${id}`, { type: "number", min: "1", step: "1", required: true }), el("span.field-error"));
  content().replaceChildren(el("form#closeloop-form.card", {
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
} else if (!Number.isInteger(ANALYSIS_ID) || ANALYSIS_ID < 1) {
  showAlert(`Not an analysis id in the address: ${location.pathname}`);
} else {
  onTokenReady(poll);
}
