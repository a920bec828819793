/* Shared by every dashboard page: the token, API calls with problem+json errors, small DOM helpers,
   Server-Sent Events over fetch (EventSource cannot send an Authorization header).

   The token lives in sessionStorage (this tab) or, when "remember" is ticked, localStorage (this
   computer).  Every API call sends it as "Authorization: Bearer <token>".  A 401 or 403 answer is
   shown as a message naming what the server said, and 401 opens the token form. */
"use strict";

const TOKEN_KEY = "gyrobench.token";

const Token = {
  get() {
    return sessionStorage.getItem(TOKEN_KEY) || localStorage.getItem(TOKEN_KEY) || "";
  },
  remembered() {
    return !!localStorage.getItem(TOKEN_KEY);
  },
  set(token, remember) {
    this.clear();
    (remember ? localStorage : sessionStorage).setItem(TOKEN_KEY, token);
  },
  clear() {
    sessionStorage.removeItem(TOKEN_KEY);
    localStorage.removeItem(TOKEN_KEY);
  },
};

/* An error answer of the API: status, title, detail and the per-field errors of a 422. */
class ApiError extends Error {
  constructor(status, title, detail, errors) {
    super(`${status} ${title}: ${detail}`);
    this.status = status;
    this.title = title;
    this.detail = detail;
    this.errors = errors || [];
  }
}

async function problemFrom(response) {
  let body = null;
  try {
    body = await response.json();
  } catch (_) {
    /* not JSON: keep the status line */
  }
  const title = (body && body.title) || response.statusText || "Error";
  const detail = (body && body.detail) || `the server answered ${response.status}`;
  return new ApiError(response.status, title, detail, body && body.errors);
}

/* fetch() against the API with the token; resolves to the Response, throws ApiError on a non-2xx. */
async function apiFetch(path, options = {}) {
  const headers = Object.assign({}, options.headers || {});
  const token = Token.get();
  if (token) headers["Authorization"] = `Bearer ${token}`;
  if (options.json !== undefined) {
    headers["Content-Type"] = "application/json";
    options = Object.assign({}, options, { body: JSON.stringify(options.json) });
  }
  let response;
  try {
    response = await fetch(path, Object.assign({}, options, { headers, cache: "no-store" }));
  } catch (err) {
    throw new ApiError(0, "Server unreachable", `${path}: ${err.message}`);
  }
  if (!response.ok) {
    const problem = await problemFrom(response);
    if (problem.status === 401 || problem.status === 403) showAuthProblem(problem);
    throw problem;
  }
  return response;
}

async function api(path, options = {}) {
  const response = await apiFetch(path, options);
  const type = response.headers.get("content-type") || "";
  return type.includes("json") ? response.json() : response.text();
}

/* ---------------------------------------------------------------------------------- messages */
function showAlert(text, kind = "error") {
  const box = document.getElementById("alert");
  box.textContent = text;
  box.className = `alert ${kind}`;
  box.hidden = false;
}

function clearAlert() {
  const box = document.getElementById("alert");
  box.hidden = true;
  box.textContent = "";
}

function showAuthProblem(problem) {
  const what = problem.status === 401
    ? "Not signed in: enter a valid API token."
    : "Your token's role may not do this.";
  showAlert(`${what} (${problem.status} ${problem.title}: ${problem.detail})`, "auth");
  if (problem.status === 401) openTokenForm();
}

/* Report an error of an action; auth problems are already shown by apiFetch. */
function reportError(err, where) {
  if (err instanceof ApiError) {
    if (err.status === 401 || err.status === 403) return;
    showAlert(`${where ? where + ": " : ""}${err.status ? err.status + " " : ""}${err.title}: ${err.detail}`);
  } else {
    showAlert(`${where ? where + ": " : ""}${err && err.message ? err.message : err}`);
  }
}

/* ---------------------------------------------------------------------------------- token UI */
function openTokenForm() {
  const form = document.getElementById("token-form");
  form.hidden = false;
  document.getElementById("token-remember").checked = Token.remembered();
  document.getElementById("token-input").focus();
}

function renderTokenState() {
  const token = Token.get();
  const state = document.getElementById("token-state");
  if (!token) {
    state.textContent = "no token";
    state.className = "token-state missing";
  } else {
    state.textContent = `token …${token.slice(-4)}${Token.remembered() ? " (remembered)" : ""}`;
    state.className = "token-state set";
  }
  document.getElementById("token-forget").hidden = !token;
}

function setupTokenUi() {
  const form = document.getElementById("token-form");
  document.getElementById("token-change").addEventListener("click", openTokenForm);
  document.getElementById("token-cancel").addEventListener("click", () => { form.hidden = true; });
  document.getElementById("token-forget").addEventListener("click", () => {
    Token.clear();
    renderTokenState();
    showAlert("Token forgotten. Enter a token to use the API.", "info");
  });
  form.addEventListener("submit", (ev) => {
    ev.preventDefault();
    const value = document.getElementById("token-input").value.trim();
    if (!value) return;
    Token.set(value, document.getElementById("token-remember").checked);
    document.getElementById("token-input").value = "";
    form.hidden = true;
    renderTokenState();
    clearAlert();
    document.dispatchEvent(new CustomEvent("token-changed"));
  });
  renderTokenState();
  if (!Token.get()) {
    showAlert("Enter an API token (Token… at the top right) to see the bench.", "info");
    openTokenForm();
  }
}

/* ---------------------------------------------------------------------------------- DOM helpers */
/* el("div.card#id", {attrs, on: {click: fn}}, children...) */
function el(spec, attrs, ...children) {
  const m = /^([a-z0-9]+)((?:[.#][\w-]+)*)$/i.exec(spec);
  const node = document.createElement(m ? m[1] : spec);
  if (m && m[2]) {
    for (const part of m[2].match(/[.#][\w-]+/g)) {
      if (part[0] === ".") node.classList.add(part.slice(1));
      else node.id = part.slice(1);
    }
  }
  if (attrs && (typeof attrs !== "object" || attrs instanceof Node || Array.isArray(attrs))) {
    children.unshift(attrs);
    attrs = null;
  }
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (key === "on") {
      for (const [evt, fn] of Object.entries(value)) node.addEventListener(evt, fn);
    } else if (key === "dataset") {
      Object.assign(node.dataset, value);
    } else if (key in node && typeof value !== "string") {
      node[key] = value;
    } else {
      node.setAttribute(key, value === true ? "" : String(value));
    }
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

/* replaceChildren that skips null / undefined / false (conditional parts of a page). */
function fill(node, ...children) {
  node.replaceChildren(...children.flat().filter((c) => c !== null && c !== undefined && c !== false));
  return node;
}

function content() {
  return document.getElementById("content");
}

function setTitle(text) {
  document.getElementById("page-title").textContent = text;
  document.title = `${text} · Gyro bench`;
}

function fmtNum(value, digits = 4) {
  if (value === null || value === undefined || value === "") return "–";
  if (typeof value !== "number") return String(value);
  if (!Number.isFinite(value)) return "–";
  if (value !== 0 && (Math.abs(value) >= 1e6 || Math.abs(value) < 1e-3)) return value.toExponential(digits - 1);
  return Number(value.toPrecision(digits)).toString();
}

function fmtDuration(seconds) {
  if (seconds === null || seconds === undefined || !Number.isFinite(seconds)) return "–";
  const s = Math.max(0, Math.round(seconds));
  const h = Math.floor(s / 3600);
  const m = Math.floor((s % 3600) / 60);
  const sec = s % 60;
  return h ? `${h} h ${String(m).padStart(2, "0")} min` : m ? `${m} min ${String(sec).padStart(2, "0")} s` : `${sec} s`;
}

function fmtTime(iso) {
  if (!iso) return "–";
  const d = new Date(iso);
  return Number.isNaN(d.getTime()) ? iso : d.toLocaleString();
}

function statusBadge(status, outcome) {
  const label = outcome && outcome !== status ? `${status} (${outcome})` : status || "–";
  return el("span.badge", { class: `badge status-${status}`, dataset: { status: status || "" } }, label);
}

function progressBar(percent) {
  const p = Math.max(0, Math.min(100, Number(percent) || 0));
  const bar = el("div.progress", { title: `${p.toFixed(1)} %` },
    el("div.progress-fill", { style: `width:${p}%` }),
    el("span.progress-label", `${p.toFixed(1)} %`));
  bar.dataset.percent = String(p);
  return bar;
}

function pathParam(index) {
  /* /ui/runs/12 -> pathParam(2) === "12" */
  const parts = location.pathname.replace(/\/+$/, "").split("/").filter(Boolean);
  const value = parts[index];
  return value === undefined ? null : decodeURIComponent(value);
}

/* Download an API resource (which needs the token) as a file. */
async function downloadWithToken(path, filename) {
  try {
    const response = await apiFetch(path);
    const blob = await response.blob();
    const url = URL.createObjectURL(blob);
    const a = el("a", { href: url, download: filename });
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  } catch (err) {
    reportError(err, `download ${filename}`);
  }
}

/* ---------------------------------------------------------------------------------- SSE */
/* Follow a text/event-stream with the token.  onEvent(kind, data, id) for each event; resolves when
   the stream ends (server "end" event or closed connection); abort with controller.abort(). */
async function followEvents(path, onEvent, controller) {
  const response = await apiFetch(path, { headers: { Accept: "text/event-stream" }, signal: controller.signal });
  const reader = response.body.getReader();
  const decoder = new TextDecoder();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += decoder.decode(value, { stream: true });
    let cut;
    while ((cut = buffer.search(/\r?\n\r?\n/)) >= 0) {
      const block = buffer.slice(0, cut);
      buffer = buffer.slice(cut).replace(/^\r?\n\r?\n/, "");
      let kind = "message";
      let id = null;
      const data = [];
      for (const line of block.split(/\r?\n/)) {
        if (line.startsWith(":")) continue;
        const colon = line.indexOf(":");
        const field = colon < 0 ? line : line.slice(0, colon);
        const val = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
        if (field === "event") kind = val;
        else if (field === "data") data.push(val);
        else if (field === "id") id = val;
      }
      if (!data.length) continue;
      let parsed = data.join("\n");
      try {
        parsed = JSON.parse(parsed);
      } catch (_) {
        /* plain text data */
      }
      onEvent(kind, parsed, id);
      if (kind === "end") return;
    }
  }
}

/* Mark the current page in the navigation and wire the token UI; pages call this first. */
function initPage() {
  const page = document.body.dataset.page;
  for (const a of document.querySelectorAll("nav a")) {
    if (a.dataset.nav === page) a.classList.add("current");
  }
  setupTokenUi();
}

/* Run fn now and again whenever the token changes (pages reload their data then). */
function onTokenReady(fn) {
  document.addEventListener("token-changed", fn);
  if (Token.get()) fn();
}

/* ---------------------------------------------------------------------------------- values */
/* A stored value as text for a table cell: numbers with a few significant digits, lists joined,
   objects as "key value" pairs; never raw JSON. */
function fmtValue(value, digits = 6) {
  if (value === null || value === undefined) return "–";
  if (typeof value === "number") return fmtNum(value, digits);
  if (typeof value === "boolean") return value ? "yes" : "no";
  if (Array.isArray(value)) return value.map((v) => fmtValue(v, digits)).join(", ");
  if (typeof value === "object") return Object.entries(value).map(([k, v]) => `${k} ${fmtValue(v, digits)}`).join("; ");
  return String(value);
}

/* A number with its unit ("0.0123 deg/h"), or "–". */
function fmtQty(value, unit, digits = 4) {
  const text = fmtNum(value, digits);
  return text === "–" ? text : `${text} ${unit}`;
}

/* ---------------------------------------------------------------------------------- list filters */
/* A filter bar (gyro, model, from, to) whose values live in the page address (?gyro_id=&model=&
   date_from=&date_to=), so a filtered list can be bookmarked.  onApply(query string for the API). */
const FILTER_FIELDS = [["gyro_id", "Gyro", "text"], ["model", "Model", "text"], ["date_from", "From", "date"],
  ["date_to", "To", "date"]];

function filterQuery() {
  const here = new URLSearchParams(location.search);
  const q = new URLSearchParams();
  for (const [name] of FILTER_FIELDS) {
    const v = (here.get(name) || "").trim();
    if (v) q.set(name, v);
  }
  return q;
}

function filterBar(id, onApply) {
  const current = filterQuery();
  const inputs = FILTER_FIELDS.map(([name, label, type]) => el("label", { dataset: { filter: name } }, label,
    el(`input#${id}-${name}`, { type, name, value: current.get(name) || "" })));
  const form = el(`form#${id}.filters.actions`, {
    on: {
      submit: (ev) => {
        ev.preventDefault();
        const q = new URLSearchParams();
        for (const input of form.querySelectorAll("input")) if (input.value.trim()) q.set(input.name, input.value.trim());
        history.replaceState(null, "", `${location.pathname}${q.toString() ? `?${q}` : ""}`);
        onApply(q);
      },
    },
  }, inputs, el("button", { type: "submit" }, "Filter"),
  el("button.secondary", { type: "button", on: { click: () => { for (const i of form.querySelectorAll("input")) i.value = ""; form.requestSubmit(); } } }, "Clear"));
  return form;
}

/* Make fit #id the gyro's accepted coefficients for its model (admin), then call reload(). */
async function acceptFit(id, reload) {
  if (!window.confirm(`Make fit #${id} the gyro's accepted coefficients for its model?`)) return;
  try {
    await api(`/fits/${id}/accept`, { method: "POST" });
    showAlert(`Fit #${id} accepted.`, "ok");
    reload();
  } catch (err) {
    reportError(err, `accept fit ${id}`);
  }
}
