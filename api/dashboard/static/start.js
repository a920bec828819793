/* /ui/start : start a run.  The parameter form is built from the procedure's pydantic JSON schema and
   filled with its defaults (GET /procedures); POST /runs queues the run and the page goes to it.

   Widgets by schema: number / integer -> number input (minimum, maximum, exclusiveMinimum checked
   here and again by the server), boolean -> checkbox, enum -> select, string or null -> text (empty =
   null), list of numbers / strings -> comma-separated text, anything else (objects, lists of
   objects) -> a JSON text area.  A 422 answer marks the fields it names. */
"use strict";

let procedures = [];

function resolveRef(schema, root) {
  if (schema && schema.$ref) {
    const name = schema.$ref.split("/").pop();
    return Object.assign({}, (root.$defs || {})[name] || {}, schema, { $ref: undefined });
  }
  return schema || {};
}

/* The widget kind of a property: number, integer, boolean, enum, text, list, json. */
function widgetKind(prop, root) {
  const p = resolveRef(prop, root);
  let types = p.type ? [p.type] : [];
  let nullable = false;
  if (p.anyOf) {
    for (const alt of p.anyOf.map((a) => resolveRef(a, root))) {
      if (alt.type === "null") nullable = true;
      else if (alt.type) types.push(alt.type);
      else types.push("object");
    }
  }
  if (p.enum) return { kind: "enum", nullable, options: p.enum };
  if (types.length === 1) {
    const t = types[0];
    if (t === "number" || t === "integer" || t === "boolean") return { kind: t, nullable };
    if (t === "string") return { kind: "text", nullable };
    if (t === "array") {
      const items = resolveRef(p.items || {}, root);
      if (["number", "integer", "string"].includes(items.type)) return { kind: "list", nullable, itemType: items.type };
    }
  }
  return { kind: "json", nullable };
}

function fieldFor(name, prop, root, value, required) {
  const p = resolveRef(prop, root);
  const w = widgetKind(prop, root);
  const id = `param-${name}`;
  let input;
  if (w.kind === "boolean") {
    input = el("input", { type: "checkbox", id, name, checked: !!value });
  } else if (w.kind === "enum") {
    input = el("select", { id, name }, w.options.map((o) => el("option", { value: String(o), selected: o === value }, String(o))));
  } else if (w.kind === "number" || w.kind === "integer") {
    input = el("input", { type: "number", id, name, step: w.kind === "integer" ? "1" : "any",
      value: value === null || value === undefined ? "" : String(value) });
    if (p.minimum !== undefined) input.min = String(p.minimum);
    if (p.maximum !== undefined) input.max = String(p.maximum);
  } else if (w.kind === "list") {
    input = el("input", { type: "text", id, name, value: Array.isArray(value) ? value.join(", ") : "" });
  } else if (w.kind === "text") {
    input = el("input", { type: "text", id, name, value: value === null || value === undefined ? "" : String(value) });
  } else {
    input = el("textarea", { id, name }, value === undefined ? "" : JSON.stringify(value, null, 1));
  }
  input.dataset.kind = w.kind;
  if (w.itemType) input.dataset.itemType = w.itemType;
  if (w.nullable) input.dataset.nullable = "1";
  const hints = [];
  if (w.kind === "list") hints.push(`comma-separated ${w.itemType === "string" ? "texts" : "numbers"}`);
  if (w.kind === "json") hints.push("JSON");
  if (w.nullable) hints.push("empty = none");
  if (p.exclusiveMinimum !== undefined) hints.push(`> ${p.exclusiveMinimum}`);
  if (p.minimum !== undefined) hints.push(`≥ ${p.minimum}`);
  if (p.maximum !== undefined) hints.push(`≤ ${p.maximum}`);
  if (p.minItems) hints.push(`at least ${p.minItems}`);
  const label = el("label", { dataset: { field: name } },
    el("span", p.title || name, required ? " *" : ""),
    input,
    el("span.hint", [p.description, hints.join(", ")].filter(Boolean).join(" · ")),
    el("span.field-error"));
  if (w.kind === "boolean") label.className = "inline-field";
  return label;
}

/* Read one field; throws Error naming the field when the text is not what the widget expects. */
function readField(input, prop) {
  const kind = input.dataset.kind;
  const text = kind === "boolean" ? null : input.value.trim();
  const title = input.name;
  if (kind === "boolean") return input.checked;
  if (text === "" && input.dataset.nullable) return null;
  if (kind === "number" || kind === "integer") {
    if (text === "") throw new Error(`${title}: a number is required`);
    const v = Number(text);
    if (!Number.isFinite(v) || (kind === "integer" && !Number.isInteger(v))) throw new Error(`${title}: not ${kind === "integer" ? "an integer" : "a number"}: ${text}`);
    if (prop.exclusiveMinimum !== undefined && !(v > prop.exclusiveMinimum)) throw new Error(`${title}: must be greater than ${prop.exclusiveMinimum}`);
    if (prop.minimum !== undefined && v < prop.minimum) throw new Error(`${title}: must be at least ${prop.minimum}`);
    if (prop.maximum !== undefined && v > prop.maximum) throw new Error(`${title}: must be at most ${prop.maximum}`);
    return v;
  }
  if (kind === "list") {
    if (text === "") return [];
    return text.split(",").map((part) => part.trim()).filter((part) => part !== "").map((part) => {
      if (input.dataset.itemType === "string") return part;
      const v = Number(part);
      if (!Number.isFinite(v)) throw new Error(`${title}: ${JSON.stringify(part)} is not a number`);
      return v;
    });
  }
  if (kind === "json") {
    if (text === "") return undefined;
    try {
      return JSON.parse(text);
    } catch (err) {
      throw new Error(`${title}: not valid JSON (${err.message})`);
    }
  }
  return text;
}

function currentProcedure() {
  const name = document.getElementById("procedure").value;
  return procedures.find((p) => p.name === name);
}

function renderParams() {
  const proc = currentProcedure();
  const box = document.getElementById("params");
  if (!proc) {
    box.replaceChildren(el("p.muted", "No procedure selected."));
    return;
  }
  const schema = proc.parameters_schema || {};
  const required = new Set(schema.required || []);
  const fields = Object.entries(schema.properties || {}).map(([name, prop]) =>
    fieldFor(name, prop, schema, (proc.defaults || {})[name], required.has(name)));
  document.getElementById("proc-description").textContent = proc.description || "";
  box.replaceChildren(...fields);
}

function markErrors(errors) {
  for (const label of document.querySelectorAll("#params label[data-field]")) {
    label.querySelector(".field-error").textContent = "";
    const input = label.querySelector("input, select, textarea");
    if (input) input.classList.remove("invalid");
  }
  for (const e of errors || []) {
    const parts = String(e.where || "").split(".");
    const i = parts.indexOf("params");
    const name = i >= 0 ? parts[i + 1] : parts[parts.length - 1];
    const label = document.querySelector(`#params label[data-field="${CSS.escape(name || "")}"]`)
      || document.querySelector(`#run-fields label[data-field="${CSS.escape(parts[parts.length - 1] || "")}"]`);
    if (!label) continue;
    label.querySelector(".field-error").textContent = e.problem;
    const input = label.querySelector("input, select, textarea");
    if (input) input.classList.add("invalid");
  }
}

function startAtIso() {
  const text = document.getElementById("start_at").value;
  if (!text) return null;
  const local = new Date(text);                      // datetime-local is the browser's local time
  if (Number.isNaN(local.getTime())) throw new Error(`start_at: not a date and time: ${text}`);
  return local.toISOString();                       // with "Z": the API needs a time zone
}

async function submit(ev) {
  ev.preventDefault();
  clearAlert();
  markErrors([]);
  const proc = currentProcedure();
  const schema = proc.parameters_schema || {};
  const params = {};
  const problems = [];
  for (const [name, prop] of Object.entries(schema.properties || {})) {
    const input = document.getElementById(`param-${name}`);
    try {
      const value = readField(input, resolveRef(prop, schema));
      if (value !== undefined) params[name] = value;
    } catch (err) {
      problems.push({ where: `params.${name}`, problem: err.message });
    }
  }
  let startAt = null;
  try {
    startAt = startAtIso();
  } catch (err) {
    problems.push({ where: "start_at", problem: err.message });
  }
  if (problems.length) {
    markErrors(problems);
    showAlert(`Check the form: ${problems.map((p) => p.problem).join("; ")}`);
    return;
  }
  const body = {
    procedure: proc.name,
    bench: document.getElementById("bench").value,
    gyro_id: document.getElementById("gyro_id").value.trim(),
    params,
  };
  if (startAt) body.start_at = startAt;
  const operator = document.getElementById("operator").value.trim();
  if (operator) body.operator = operator;
  const button = document.getElementById("start-run");
  button.disabled = true;
  try {
    const run = await api("/runs", { method: "POST", json: body });
    showAlert(`Run #${run.id} queued (estimated ${fmtDuration(run.estimated_total_bench_s)} of bench time).`, "ok");
    location.assign(`/ui/runs/${run.id}`);
  } catch (err) {
    if (err instanceof ApiError && err.status === 422) markErrors(err.errors);
    reportError(err, "start the run");
    button.disabled = false;
  }
}

function build() {
  content().replaceChildren(
    el("form#start-form.card", { on: { submit }, novalidate: true },
      el("div#run-fields.params",
        el("label", { dataset: { field: "procedure" } }, "Procedure", el("select#procedure", { on: { change: renderParams } }), el("span.field-error")),
        el("label", { dataset: { field: "bench" } }, "Bench", el("select#bench"), el("span.field-error")),
        el("label", { dataset: { field: "gyro_id" } }, "Gyro ID *",
          el("input#gyro_id", { type: "text", required: true, pattern: "[A-Za-z0-9][A-Za-z0-9._\\-]{0,63}", placeholder: "e.g. RLG-7" }),
          el("span.hint", "1-64 letters, digits, '.', '_' or '-'"), el("span.field-error")),
        el("label", { dataset: { field: "start_at" } }, "Start at (optional)", el("input#start_at", { type: "datetime-local" }),
          el("span.hint", "empty = as soon as the bench is free"), el("span.field-error")),
        el("label", { dataset: { field: "operator" } }, "Operator (optional)", el("input#operator", { type: "text", maxLength: 64 }),
          el("span.field-error"))),
      el("p#proc-description.muted"),
      el("h2", "Parameters"),
      el("div#params.params"),
      el("div.actions",
        el("button#start-run", { type: "submit" }, "Start run"),
        el("button#reset-defaults.secondary", { type: "button", on: { click: renderParams } }, "Reset to defaults"))));
  document.getElementById("run-fields").className = "params";
  document.getElementById("params").className = "params";
}

async function load() {
  try {
    const [procs, benches] = await Promise.all([api("/procedures"), api("/benches")]);
    procedures = procs.procedures;
    const sel = document.getElementById("procedure");
    const wanted = new URLSearchParams(location.search).get("procedure") || sel.value;
    sel.replaceChildren(...procedures.map((p) => el("option", { value: p.name, selected: p.name === wanted }, p.name)));
    const bsel = document.getElementById("bench");
    bsel.replaceChildren(...(benches.benches.length
      ? benches.benches.map((b) => el("option", { value: b.name }, `${b.name} (${b.online ? b.state : "offline"})`))
      : [el("option", { value: "" }, "no bench configured")]));
    renderParams();
  } catch (err) {
    reportError(err, "load procedures and benches");
  }
}

initPage();
build();
onTokenReady(load);
