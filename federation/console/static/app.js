// The operator console's page: follows /api/events (Server-Sent Events) and draws the model.
// Plain JS, no build step and nothing fetched from elsewhere.
"use strict";

const PALETTE = ["#2563eb", "#d97706", "#059669", "#db2777", "#7c3aed", "#0891b2", "#65a30d", "#dc2626"];
const $ = (sel) => document.querySelector(sel);

let state = null;           // the last model received
let lastVersion = -1;
let view = null;            // world -> canvas transform
let pendingClick = null;    // where the operator clicked, in world coordinates

// -- small helpers ------------------------------------------------------------------------

function colourOf(name) {
  let h = 0;
  for (const ch of name) h = (h * 31 + ch.charCodeAt(0)) >>> 0;
  return PALETTE[h % PALETTE.length];
}

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === null || v === undefined) continue;
    if (k === "class") node.className = v;
    else if (k === "text") node.textContent = v;
    else node.setAttribute(k, v);
  }
  for (const c of children) if (c !== null && c !== undefined) node.append(c);
  return node;
}

function fmtNum(v, digits = 1) {
  return typeof v === "number" && isFinite(v) ? v.toFixed(digits) : "–";
}

function fmtAge(t, now) {
  if (t === null || t === undefined) return "never";
  const s = Math.max(0, now - t);
  return s < 1 ? "just now" : s < 90 ? `${s.toFixed(0)} s ago` : `${(s / 60).toFixed(0)} min ago`;
}

function fmtClock(t) {
  if (typeof t !== "number") return "–";
  if (Math.abs(t) < 1e8) return `t ${t.toFixed(1)} s`;  // a simulation's time, not the epoch
  const d = new Date(t * 1000);
  return d.toTimeString().slice(0, 8) + "." + String(Math.floor((t % 1) * 10));
}

function fmtPeriod(p) {
  return p === null || p === undefined ? "every sample" : `${p} s`;
}

function compact(value, max = 90) {
  const s = typeof value === "string" ? value : JSON.stringify(value);
  return s.length > max ? s.slice(0, max - 1) + "…" : s;
}

// -- the model from the server ------------------------------------------------------------

function connect() {
  const conn = $("#connection");
  const source = new EventSource("/api/events");
  source.addEventListener("state", (ev) => {
    conn.dataset.state = "live";
    conn.textContent = "live";
    try { render(JSON.parse(ev.data)); } catch (e) { console.error(e); }
  });
  source.onerror = () => {
    if (source.readyState === EventSource.CLOSED) {
      // refused (401/403: no token, a wrong one): retrying would not help
      conn.dataset.state = "refused";
      conn.textContent = "refused: open the URL the console printed (…/?token=…)";
      return;
    }
    conn.dataset.state = "lost";
    conn.textContent = "reconnecting…";  // EventSource retries by itself
  };
}

// The token came once in the address (…/?token=…); the server answered with a cookie, so
// it leaves the address bar (and the history, and what a screenshot shows).
if (new URLSearchParams(location.search).has("token")) {
  history.replaceState(null, "", location.pathname);
}

function render(s) {
  state = s;
  $("#operator-name").textContent = s.operator;
  renderPlatforms(s);
  renderCars(s);
  if (s.version !== lastVersion) {
    renderViolations(s);
    renderObservations(s);
    renderQueryPlatforms(s);
    renderQueryLabels(s);
    lastVersion = s.version;
  }
  drawMap();
}

// -- platforms panel (updated in place: the policy inputs keep what is typed) -------------

function renderPlatforms(s) {
  const list = $("#platforms");
  const seen = new Set();
  for (const p of s.platforms) {
    seen.add(p.name);
    let li = list.querySelector(`li[data-platform="${CSS.escape(p.name)}"]`);
    if (!li) {
      li = el("li", { "data-platform": p.name });
      li.style.setProperty("--c", colourOf(p.name));
      li.append(
        el("div", { class: "p-head" },
          el("span", { class: "p-name", text: p.name }),
          el("span", { class: "badge" }),
          el("span", { class: "p-meta" })),
        el("table", { class: "grid streams" },
          el("thead", {}, el("tr", {},
            el("th", { text: "stream" }), el("th", { text: "state" }), el("th", { text: "rate" }),
            el("th", { text: "samples" }), el("th", { text: "policy" }))),
          el("tbody")));
      list.append(li);
    }
    li.dataset.state = p.state;
    const badge = li.querySelector(".badge");
    badge.dataset.state = p.state;
    badge.textContent = p.state;
    li.querySelector(".p-meta").textContent =
      `${p.samples} samples · last ${fmtAge(p.last, s.now)}`;
    const body = li.querySelector("tbody");
    for (const st of p.streams) renderStream(body, p, st);
  }
  for (const li of [...list.children]) if (!seen.has(li.dataset.platform)) li.remove();
  $("#no-platforms").hidden = s.platforms.length > 0;
  // the legend: one colour per platform
  const legend = $("#legend");
  legend.replaceChildren(...s.platforms.map((p) =>
    el("span", { "data-platform": p.name },
      el("span", { class: "sw", style: `background:${p.state === "alive" ? colourOf(p.name) : "#9aa3ad"}` }),
      p.name)));
}

function renderStream(body, p, st) {
  let tr = body.querySelector(`tr[data-stream="${CSS.escape(st.label)}"]`);
  if (!tr) {
    const input = el("input", {
      type: "number", step: "any", min: "0", placeholder: "s",
      "data-testid": `policy-input-${p.name}-${st.label}`, "aria-label": `sample period of ${st.label}`,
    });
    const button = el("button", { type: "button", "data-testid": `policy-set-${p.name}-${st.label}`, text: "set" });
    button.addEventListener("click", () => setPolicy(p.name, st.label, input));
    input.addEventListener("keydown", (e) => { if (e.key === "Enter") setPolicy(p.name, st.label, input); });
    tr = el("tr", { "data-stream": st.label },
      el("td", { text: st.label }),
      el("td", {}, el("span", { class: "st" })),
      el("td", { class: "rate" }),
      el("td", { class: "samples" }),
      el("td", { class: "policy-cell" }, el("span", { class: "policy", "data-testid": "policy" }), " ", input, button));
    body.append(tr);
  }
  const stEl = tr.querySelector(".st");
  stEl.dataset.state = st.state;
  stEl.textContent = st.state;
  stEl.title = st.error || "";
  tr.querySelector(".rate").textContent = st.state === "active" ? `${fmtNum(st.rate, 1)}/s` : "–";
  tr.querySelector(".samples").textContent = String(st.samples);
  const pol = tr.querySelector(".policy");
  pol.textContent = fmtPeriod(st.sample_period);
  pol.dataset.period = st.sample_period === null ? "" : String(st.sample_period);
  const disabled = p.state !== "alive";
  for (const c of tr.querySelectorAll("input, button")) c.disabled = disabled;
}

async function setPolicy(platform, label, input) {
  const raw = input.value.trim();
  const period = raw === "" ? null : Number(raw);
  const answer = await post("/api/policy", { platform, label, sample_period: period });
  if (answer.ok) input.value = "";
  else alert(`policy of ${label} at ${platform}: ${answer.body.error}`);
}

// -- cars, violations, observations -------------------------------------------------------

function renderCars(s) {
  const rows = [];
  for (const p of s.platforms) {
    if (p.state === "gone") continue;
    for (const c of p.cars) {
      rows.push(el("tr", { "data-car": c.id, "data-platform": p.name },
        el("td", {}, el("span", { class: "sw" }), String(c.id)),
        el("td", { text: p.name }),
        el("td", { text: `${fmtNum(c.speed)} m/s` }),
        el("td", { text: c.road ?? "–" }),
        el("td", { text: `${fmtNum(c.x, 0)}, ${fmtNum(c.y, 0)}` })));
    }
  }
  $("#cars tbody").replaceChildren(...rows);
  $("#car-count").textContent = String(rows.length);
}

function renderViolations(s) {
  const items = s.violations.map((v) => el("li", { "data-kind": v.kind, "data-car": v.car },
    el("span", { class: "kind", text: v.kind }),
    el("span", {}, `${v.car}${v.other ? " vs " + v.other : ""}`, v.fused ? el("span", { class: "fused", text: "fused" }) : null),
    el("span", { class: "who",
      text: `by ${v.platform || v["reported-by"]} · ${fmtClock(v.end ?? v.valid)} · at ${fmtNum(v.x, 0)}, ${fmtNum(v.y, 0)}` })));
  $("#violations").replaceChildren(...items);
  $("#violation-count").textContent = String(items.length);
  $("#no-violations").hidden = items.length > 0;
}

function renderObservations(s) {
  $("#observations").replaceChildren(...s.observations.map((o) =>
    el("li", { "data-text": o.text },
      document.createTextNode(o.text),
      el("span", { class: "xy", text: `(${fmtNum(o.x, 0)}, ${fmtNum(o.y, 0)}) · ${fmtClock(o.valid)}` }))));
}

function renderQueryPlatforms(s) {
  const select = $("#query-platform");
  const names = [...s.platforms.filter((p) => p.state === "alive").map((p) => p.name), s.operator];
  const current = select.value;
  if ([...select.options].map((o) => o.value).join() === names.join()) return;
  select.replaceChildren(...names.map((n) => el("option", { value: n, text: n })));
  if (names.includes(current)) select.value = current;
}

// -- the map ------------------------------------------------------------------------------

function bounds(s) {
  const w = s.world;
  if (w && w.width && w.height) return { x0: 0, y0: 0, x1: w.width, y1: w.height };
  const xs = [], ys = [];
  const add = (x, y) => { if (isFinite(x) && isFinite(y)) { xs.push(x); ys.push(y); } };
  for (const p of s.platforms) {
    if (p.position) add(p.position.x, p.position.y);
    if (p.area) for (const [x, y] of p.area.polygon) add(x, y);
    for (const c of p.cars) add(c.x, c.y);
  }
  for (const v of s.violations) add(v.x, v.y);
  for (const o of s.observations) add(o.x, o.y);
  if (w) {
    for (const r of w.roads || []) { add(r.a[0], r.a[1]); add(r.b[0], r.b[1]); }
    for (const a of w.areas || []) for (const [x, y] of a.polygon) add(x, y);
  }
  if (!xs.length) return { x0: 0, y0: 0, x1: 1000, y1: 1000 };
  const pad = 0.08 * Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys), 50);
  return { x0: Math.min(...xs) - pad, y0: Math.min(...ys) - pad, x1: Math.max(...xs) + pad, y1: Math.max(...ys) + pad };
}

function drawMap() {
  const canvas = $("#map");
  const dpr = window.devicePixelRatio || 1;
  if (state) {
    // as tall as the world's shape needs, within reason
    const b0 = bounds(state);
    const want = Math.round(canvas.clientWidth * (b0.y1 - b0.y0) / (b0.x1 - b0.x0)) + 32;
    const h = Math.max(240, Math.min(620, want));
    if (Math.abs(canvas.clientHeight - h) > 2) canvas.style.height = `${h}px`;
  }
  const cw = canvas.clientWidth, ch = canvas.clientHeight;
  if (canvas.width !== Math.round(cw * dpr) || canvas.height !== Math.round(ch * dpr)) {
    canvas.width = Math.round(cw * dpr);
    canvas.height = Math.round(ch * dpr);
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, cw, ch);
  if (!state) return;
  const b = bounds(state);
  const margin = 16;
  const scale = Math.min((cw - 2 * margin) / (b.x1 - b.x0), (ch - 2 * margin) / (b.y1 - b.y0));
  const ox = (cw - scale * (b.x1 - b.x0)) / 2, oy = (ch - scale * (b.y1 - b.y0)) / 2;
  // world y grows upwards, the canvas' downwards
  const X = (x) => ox + (x - b.x0) * scale;
  const Y = (y) => ch - (oy + (y - b.y0) * scale);
  view = { b, scale, ox, oy, ch };
  const w = state.world || {};

  // areas: the world's partition, then what each UAV monitors now (its colour)
  for (const a of w.areas || []) polygon(ctx, a.polygon, X, Y, "rgba(100,116,139,0.06)", "rgba(100,116,139,0.35)", [4, 4]);
  for (const p of state.platforms) {
    if (!p.area || p.state === "gone") continue;
    const c = colourOf(p.name);
    polygon(ctx, p.area.polygon, X, Y, c + "1f", c, []);
    // labelled in its top-left corner, clear of the roads
    const xs = p.area.polygon.map((q) => q[0]), ys = p.area.polygon.map((q) => q[1]);
    ctx.fillStyle = c;
    ctx.font = "600 12px system-ui, sans-serif";
    ctx.textAlign = "left";
    const delegated = p.area["delegated-by"] ? ` · delegated by ${p.area["delegated-by"]}` : "";
    haloText(ctx, `area ${p.area.index ?? ""} · ${p.name}${delegated}`, X(Math.min(...xs)) + 6, Y(Math.max(...ys)) + 16);
  }
  for (const pk of w.parking || []) polygon(ctx, pk, X, Y, "rgba(148,163,184,0.25)", "rgba(148,163,184,0.6)", []);
  // roads and crossings
  ctx.lineCap = "round";
  for (const r of w.roads || []) {
    ctx.strokeStyle = "#b8bec6";
    ctx.lineWidth = Math.max(3, 3.5 * (r.lanes || 1) * Math.min(scale, 1.5));
    line(ctx, X(r.a[0]), Y(r.a[1]), X(r.b[0]), Y(r.b[1]));
    ctx.strokeStyle = "#ffffff";
    ctx.lineWidth = 1;
    ctx.setLineDash([6, 6]);
    line(ctx, X(r.a[0]), Y(r.a[1]), X(r.b[0]), Y(r.b[1]));
    ctx.setLineDash([]);
  }
  for (const c of w.crossings || []) {
    ctx.fillStyle = "#cfd4da";
    ctx.beginPath();
    ctx.arc(X(c.x), Y(c.y), Math.max(5, (c.radius || 10) * scale), 0, 2 * Math.PI);
    ctx.fill();
  }
  // violations, where they happened
  state.violations.slice(0, 30).forEach((v, i) => {
    if (!isFinite(v.x) || !isFinite(v.y)) return;
    ctx.globalAlpha = Math.max(0.25, 1 - i / 12);  // the newest stand out
    ctx.strokeStyle = "#c2410c";
    ctx.lineWidth = 2.5;
    const x = X(v.x), y = Y(v.y);
    line(ctx, x - 7, y - 7, x + 7, y + 7);
    line(ctx, x - 7, y + 7, x + 7, y - 7);
    ctx.beginPath(); ctx.arc(x, y, 11, 0, 2 * Math.PI); ctx.stroke();
  });
  ctx.globalAlpha = 1;
  // cars
  ctx.font = "11px system-ui, sans-serif";
  ctx.textAlign = "left";
  for (const p of state.platforms) {
    if (p.state === "gone") continue;
    const c = colourOf(p.name);
    for (const car of p.cars) {
      const x = X(car.x), y = Y(car.y);
      ctx.fillStyle = car.colour && CSS.supports("color", car.colour) ? car.colour : c;
      ctx.strokeStyle = c;
      ctx.lineWidth = 2;
      ctx.beginPath(); ctx.arc(x, y, 5, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
      ctx.fillStyle = "#1f2933";
      haloText(ctx, String(car.id).split("/").pop(), x + 7, y - 6);
    }
  }
  // UAVs
  for (const p of state.platforms) {
    if (!p.position) continue;
    const alive = p.state === "alive";
    const c = alive ? colourOf(p.name) : "#9aa3ad";
    const x = X(p.position.x), y = Y(p.position.y);
    ctx.fillStyle = c;
    ctx.strokeStyle = "#ffffff";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(x, y - 10); ctx.lineTo(x + 9, y + 7); ctx.lineTo(x, y + 3); ctx.lineTo(x - 9, y + 7);
    ctx.closePath(); ctx.fill(); ctx.stroke();
    ctx.fillStyle = alive ? "#1f2933" : "#9aa3ad";
    ctx.font = "600 12px system-ui, sans-serif";
    haloText(ctx, alive ? p.name : `${p.name} (gone)`, x + 11, y + 4);
  }
  // the operator's observations
  for (const o of state.observations) {
    const x = X(o.x), y = Y(o.y);
    ctx.fillStyle = "#0f766e";
    ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x - 6, y - 12); ctx.lineTo(x + 6, y - 12); ctx.closePath(); ctx.fill();
    ctx.font = "italic 11px system-ui, sans-serif";
    haloText(ctx, compact(o.text, 40), x + 8, y - 8);
  }
  if (pendingClick) {
    ctx.strokeStyle = "#0f766e"; ctx.lineWidth = 1.5;
    ctx.beginPath(); ctx.arc(X(pendingClick.x), Y(pendingClick.y), 8, 0, 2 * Math.PI); ctx.stroke();
  }
}

function polygon(ctx, pts, X, Y, fill, stroke, dash) {
  if (!pts || pts.length < 3) return;
  ctx.beginPath();
  pts.forEach(([x, y], i) => (i ? ctx.lineTo(X(x), Y(y)) : ctx.moveTo(X(x), Y(y))));
  ctx.closePath();
  ctx.fillStyle = fill; ctx.fill();
  ctx.setLineDash(dash); ctx.strokeStyle = stroke; ctx.lineWidth = 1.5; ctx.stroke();
  ctx.setLineDash([]);
}

// text with a white outline: readable over roads and areas alike
function haloText(ctx, text, x, y) {
  ctx.save();
  ctx.strokeStyle = "rgba(255,255,255,0.85)";
  ctx.lineWidth = 3;
  ctx.lineJoin = "round";
  ctx.setLineDash([]);
  ctx.strokeText(text, x, y);
  ctx.restore();
  ctx.fillText(text, x, y);
}

function line(ctx, x0, y0, x1, y1) {
  ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke();
}

$("#map").addEventListener("click", (e) => {
  if (!view) return;
  const r = e.currentTarget.getBoundingClientRect();
  const cx = e.clientX - r.left, cy = e.clientY - r.top;
  const x = view.b.x0 + (cx - view.ox) / view.scale;
  const y = view.b.y0 + (view.ch - cy - view.oy) / view.scale;
  pendingClick = { x, y };
  $("#obs-x").value = x.toFixed(1);
  $("#obs-y").value = y.toFixed(1);
  $("#obs-text").focus();
  drawMap();
});
window.addEventListener("resize", drawMap);

// -- requests -----------------------------------------------------------------------------

async function post(url, body) {
  try {
    const r = await fetch(url, { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
    const data = await r.json().catch(() => ({ error: `HTTP ${r.status}` }));
    return { ok: r.ok, status: r.status, body: data };
  } catch (e) {
    return { ok: false, status: 0, body: { error: `the console cannot be reached: ${e}` } };
  }
}

// the labels offered for a query: the console's streams (its config's), and its observations
function renderQueryLabels(s) {
  const labels = [...s.streams, ...(s.observation_label ? [s.observation_label] : [])];
  const list = $("#label-options");
  if (list.dataset.labels === labels.join("\n")) return;
  list.dataset.labels = labels.join("\n");
  list.replaceChildren(...labels.map((label) => el("option", { value: label })));
  const input = $("#query-label");
  if (!input.dataset.offered) {
    input.dataset.offered = "1";  // once: what the operator typed since stays
    if (!input.value) input.value = s.roles.tracks ?? s.streams[0] ?? "";
  }
}

function showError(where, message) {
  where.replaceChildren(el("p", { class: "error", "data-testid": "error", text: message }));
}

const queryForm = $("#query-form");
const syncKind = () => { queryForm.dataset.kind = $("#query-kind").value; };
$("#query-kind").addEventListener("change", syncKind);
syncKind();

queryForm.addEventListener("submit", async (e) => {
  e.preventDefault();
  const out = $("#query-result");
  const body = {
    platform: $("#query-platform").value,
    label: $("#query-label").value.trim(),
    kind: $("#query-kind").value,
  };
  if (body.kind === "at") body.at = Number($("#query-at").value);
  if (body.kind === "between") { body.from = Number($("#query-from").value); body.to = Number($("#query-to").value); }
  out.replaceChildren(el("p", { class: "caption", text: "asking…" }));
  const r = await post("/api/query", body);
  if (!r.ok) return showError(out, r.body.error);
  out.replaceChildren(
    el("p", { class: "caption", text: `${r.body.label} at ${r.body.platform} (${r.body.kind}): ${r.body.samples.length} sample(s)` }),
    samplesTable(r.body));
});

function samplesTable(answer) {
  const rows = answer.samples;
  // plain objects get a column per key; anything else one value column
  const keys = [];
  for (const s of rows) {
    if (s.value && typeof s.value === "object" && !Array.isArray(s.value)) {
      for (const k of Object.keys(s.value)) if (!keys.includes(k)) keys.push(k);
    }
  }
  const cols = keys.length && keys.length <= 10 ? keys : null;
  const head = el("tr", {}, el("th", { text: "valid" }), el("th", { text: "how old" }),
    ...(cols ? cols.map((k) => el("th", { text: k })) : [el("th", { text: "value" })]));
  const body = rows.map((s) => el("tr", {},
    el("td", { text: fmtClock(s.valid) }),
    el("td", { text: answer.query_time != null ? `${fmtNum(answer.query_time - s.valid, 1)} s ago` : "–" }),
    ...(cols
      ? cols.map((k) => el("td", {}, el("code", { class: "v", text: s.value && k in s.value ? cellText(s.value[k]) : "" })))
      : [el("td", {}, el("code", { class: "v", text: cellText(s.value) }))])));
  if (!rows.length) body.push(el("tr", {}, el("td", { colspan: String(2 + (cols ? cols.length : 1)), class: "empty", text: "no samples" })));
  return el("table", { class: "grid", "data-testid": "result-table" }, el("thead", {}, head), el("tbody", {}, ...body));
}

function cellText(v) {
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toFixed(2);
  if (Array.isArray(v) && v.length && typeof v[0] === "object" && v[0] && "id" in v[0]) {
    return `${v.length}: ` + compact(v.map((c) => c.id).join(", "), 120);
  }
  return compact(v, 120);
}

$("#search-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const out = $("#query-result");
  out.replaceChildren(el("p", { class: "caption", text: "searching the federation…" }));
  const r = await post("/api/search", { formula: $("#search-formula").value });
  if (!r.ok) return showError(out, r.body.error);
  const rows = [];
  for (const [p, labels] of Object.entries(r.body.answers)) {
    rows.push(el("tr", { "data-platform": p }, el("td", { text: p }), el("td", {}, el("code", { class: "v", text: labels.length ? labels.join(", ") : "—" }))));
  }
  for (const [p, why] of Object.entries(r.body.refused)) {
    rows.push(el("tr", { "data-platform": p }, el("td", { text: p }), el("td", { class: "error", text: why })));
  }
  for (const p of r.body.no_answer) {
    rows.push(el("tr", { "data-platform": p }, el("td", { text: p }), el("td", { class: "empty", text: "no answer" })));
  }
  out.replaceChildren(
    el("p", { class: "caption", text: `labels matching ${r.body.formula}` }),
    el("table", { class: "grid", "data-testid": "result-table" },
      el("thead", {}, el("tr", {}, el("th", { text: "platform" }), el("th", { text: "labels" }))),
      el("tbody", {}, ...rows)));
});

$("#observation-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const msg = $("#obs-message");
  const body = { x: Number($("#obs-x").value), y: Number($("#obs-y").value), text: $("#obs-text").value };
  const r = await post("/api/observation", body);
  msg.classList.toggle("error", !r.ok);
  if (!r.ok) { msg.textContent = r.body.error; return; }
  msg.textContent = `added: ${r.body.observation.text}`;
  $("#obs-text").value = "";
  pendingClick = null;
});

connect();
