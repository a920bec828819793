/* /ui/fits : every stored fit version (GET /fits), newest first, filtered by gyro, model and creation
   date; per version its channels' validation (or, without validation runs, training) std of 100-s
   means, with links to the version's page and report. */
"use strict";

function runLinks(ids) {
  return (ids || []).flatMap((r, i) => [i ? ", " : "", el("a", { href: `/ui/runs/${r}` }, `#${r}`)]);
}

function errorCell(channels) {
  const parts = Object.entries(channels || {}).map(([ch, c]) => {
    const val = c.validation_std100_dph;
    const value = val ?? c.train_std100_dph;
    return `${ch} ${fmtQty(value, "deg/h", 3)}${val == null && value != null ? " (training)" : ""}`;
  });
  return el("td.wrap", parts.join(" · ") || "–");
}

function renderFits(doc) {
  const rows = doc.fits.map((f) => el("tr", { dataset: { fit: String(f.id), gyro: f.gyro_id, model: f.model } },
    el("td", el("a", { href: `/ui/fits/${f.id}` }, `#${f.id}`)),
    el("td", el("a", { href: `/ui/gyros/${encodeURIComponent(f.gyro_id)}` }, f.gyro_id)),
    el("td.wrap", f.model), el("td.num", String(f.version)),
    el("td", f.accepted ? statusBadge("accepted") : "–"),
    el("td", Object.entries(f.channels || {}).map(([ch, c]) => (c.probe ? `${ch} (${c.probe})` : ch)).join(", ")),
    el("td", runLinks(f.run_ids)), el("td", f.validation_run_ids.length ? runLinks(f.validation_run_ids) : "–"),
    errorCell(f.channels), el("td", fmtTime(f.created_at))));
  document.getElementById("fit-list").replaceChildren(el("table.list#fits-table",
    el("thead", el("tr", ["Fit", "Gyro", "Model", "Version", "Accepted", "Channels (probe)", "Training runs",
      "Validation runs", "Std of 100-s means", "Created"].map((h) => el("th", h)))),
    el("tbody", rows.length ? rows : el("tr", el("td.muted", { colSpan: 10 }, "No fit matches.")))));
}

async function load(query = filterQuery()) {
  clearAlert();
  try {
    renderFits(await api(`/fits?${query}`));
  } catch (err) {
    reportError(err, "fits");
  }
}

initPage();
content().replaceChildren(filterBar("fit-filters", load), el("div#fit-list", el("p.muted", "Loading…")));
onTokenReady(() => load());
