/* /ui/gyros and /ui/gyros/{gyro_id} : look a gyro up; its accepted coefficients per model (GET
   /gyros/{id}/coefficients) and every fit version (GET /gyros/{id}/fits) with links to each version's
   page and report, its firmware export, and (admin) accepting a version. */
"use strict";

const GYRO_ID = pathParam(2);

function coefficientTable(channels) {
  const rows = [];
  for (const [channel, entry] of Object.entries(channels || {})) {
    const units = entry.units || {};
    for (const [term, value] of Object.entries(entry.coefficients || {})) {
      rows.push(el("tr", { dataset: { channel, term } }, el("td", channel), el("td", term),
        el("td.num", typeof value === "number" ? value.toPrecision(9) : fmtValue(value)), el("td", units[term] || "")));
    }
  }
  return el("table.coefficients", el("thead", el("tr", ["Channel", "Term", "Value", "Unit"].map((h) => el("th", h)))), el("tbody", rows));
}

/* A fit's signal key as words and unit: "temp:temp_t1" -> temp_t1 (°C), "rate:temp_t1" -> dT/dt of temp_t1 (°C/min). */
function signalLabel(key) {
  const [op, column] = key.includes(":") ? key.split(/:(.*)/s) : ["", key];
  if (op === "temp") return [column, "°C"];
  if (op === "rate") return [`dT/dt of ${column}`, "°C/min"];
  return [column || key, ""];
}

/* "temp_t1 25 to 26.1 °C, ...": the signal ranges the fit is valid for (channels with the same ranges merged). */
function validityText(channels) {
  const byText = new Map();
  for (const [channel, entry] of Object.entries(channels || {})) {
    const v = entry.validity;
    if (!v) continue;
    let text;
    if (v.signals && typeof v.signals === "object") {
      text = Object.entries(v.signals).map(([key, range]) => {
        const [name, unit] = signalLabel(key);
        return Array.isArray(range) && range.length === 2
          ? `${name} ${fmtNum(range[0])} to ${fmtNum(range[1])}${unit ? ` ${unit}` : ""}` : `${name} ${fmtValue(range)}`;
      }).join(", ");
      if (v.outside) text += ` (outside: ${v.outside})`;
    } else {
      text = fmtValue(v);
    }
    byText.set(text, [...(byText.get(text) || []), channel]);
  }
  return [...byText].map(([text, chs]) => `Valid for ${chs.join(", ")}: ${text}`).join(" · ");
}

function renderCoefficients(doc) {
  const box = document.getElementById("coefficients");
  box.replaceChildren(...doc.models.map((m) => el("div.card", { dataset: { model: m.model } },
    el("h2", `${m.model} v${m.version} `, m.accepted ? statusBadge("accepted") : statusBadge("not accepted")),
    el("p.muted", `fit #${m.fit_id} of ${fmtTime(m.created_at)} on runs `,
      ...(m.run_ids || []).flatMap((r, i) => [i ? ", " : "", el("a", { href: `/ui/runs/${r}` }, `#${r}`)]),
      " · ", el("a", { href: `/ui/fits/${m.fit_id}` }, "details and report")),
    coefficientTable(m.channels),
    el("p.muted.validity", validityText(m.channels)))));
}

function accept(id) {
  return acceptFit(id, load);
}

function renderFits(doc) {
  const rows = doc.fits.map((f) => el("tr", { dataset: { fit: String(f.id) } },
    el("td", el("a", { href: `/ui/fits/${f.id}` }, `#${f.id}`)), el("td", f.model), el("td.num", String(f.version)),
    el("td", f.accepted ? statusBadge("accepted") : "–"), el("td", Object.keys(f.channels || {}).join(", ")),
    el("td", (f.run_ids || []).map((r) => `#${r}`).join(", ")), el("td", fmtTime(f.created_at)),
    el("td", el("div.actions",
      el("a", { href: `/ui/fits/${f.id}` }, "report"),
      el("button.small.secondary", { type: "button", on: { click: () => downloadWithToken(`/fits/${f.id}/export`, `${doc.gyro_id}-${f.model}-v${f.version}.json`) } }, "export"),
      f.accepted ? null : el("button.small", { type: "button", on: { click: () => accept(f.id) } }, "accept (admin)")))));
  document.getElementById("fits").replaceChildren(el("table",
    el("thead", el("tr", ["Fit", "Model", "Version", "Accepted", "Channels", "Runs", "Created", ""].map((h) => el("th", h)))),
    el("tbody", rows.length ? rows : el("tr", el("td.muted", { colSpan: 8 }, "No fits yet.")))));
}

async function load() {
  if (!GYRO_ID) return;
  clearAlert();
  const coeffBox = document.getElementById("coefficients");
  try {
    renderCoefficients(await api(`/gyros/${encodeURIComponent(GYRO_ID)}/coefficients`));
  } catch (err) {
    if (err instanceof ApiError && err.status === 404) {
      coeffBox.replaceChildren(el("p.card.muted#no-coefficients", `${err.title}: ${err.detail}`));
    } else {
      coeffBox.replaceChildren();
      reportError(err, "coefficients");
    }
  }
  try {
    renderFits(await api(`/gyros/${encodeURIComponent(GYRO_ID)}/fits`));
  } catch (err) {
    if (err instanceof ApiError && err.status === 404) document.getElementById("fits").replaceChildren(el("p.muted", err.detail));
    else reportError(err, "fit versions");
  }
  try {
    const runs = await api(`/runs?gyro_id=${encodeURIComponent(GYRO_ID)}&limit=50`);
    document.getElementById("gyro-runs").replaceChildren(...runs.runs.map((r) => el("li",
      el("a", { href: `/ui/runs/${r.id}` }, `#${r.id}`), ` ${r.procedure} · `, statusBadge(r.status, r.outcome), ` · ${fmtTime(r.created_at)}`)));
  } catch (err) {
    reportError(err, "runs of the gyro");
  }
}

function build() {
  const form = el("form#gyro-form.actions", {
    on: {
      submit: (ev) => {
        ev.preventDefault();
        const id = document.getElementById("gyro-input").value.trim();
        if (id) location.assign(`/ui/gyros/${encodeURIComponent(id)}`);
      },
    },
  }, el("label.inline", "Gyro ID ", el("input#gyro-input", { type: "text", required: true, value: GYRO_ID || "" })),
  el("button#gyro-lookup", { type: "submit" }, "Look up"));
  if (!GYRO_ID) {
    content().replaceChildren(form);
    return;
  }
  setTitle(`Gyro ${GYRO_ID}`);
  content().replaceChildren(form,
    el("h2", "Accepted coefficients"), el("div#coefficients", el("p.muted", "Loading…")),
    el("h2", "Fit versions"), el("div#fits"),
    el("h2", "Runs"), el("ul#gyro-runs"));
}

initPage();
build();
onTokenReady(load);
