// The operator console's page: follows /api/events (Server-Sent Events) and draws the model.
// Plain JS, no build step and nothing fetched from elsewhere.
"use strict";

const PALETTE = ["#2563eb", "#d97706", "#059669", "#db2777", "#7c3aed", "#0891b2", "#65a30d", "#dc2626"];
const $ = (sel) => document.querySelector(sel);

let state = null;           // the last model received
let lastVersion = -1;
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

// The token comes once in the address (…/?token=…). The page keeps it in sessionStorage
// (this tab, this origin: this port only) and sends it as a Bearer; never a cookie, which a
// browser would send to every port of this host. It leaves the address bar (and the
// history, and what a screenshot shows); a reload finds it in sessionStorage.
const TOKEN_KEY = "dyknow-console-token";
const TOKEN = (() => {
  const params = new URLSearchParams(location.search);
  const given = params.get("token");
  if (given !== null) {
    sessionStorage.setItem(TOKEN_KEY, given);
    params.delete("token");
    const rest = params.toString();
    history.replaceState(null, "", location.pathname + (rest ? `?${rest}` : "") + location.hash);
  }
  return sessionStorage.getItem(TOKEN_KEY);
})();

function withToken(headers = {}) {
  return TOKEN ? { ...headers, Authorization: `Bearer ${TOKEN}` } : headers;
}

function refused(conn) {
  conn.dataset.state = "refused";
  conn.textContent = "refused: open the URL the console printed (…/?token=…)";
}

// /api/events read with fetch, not EventSource: an EventSource cannot send a header, and
// the token must not go in a URL (logs, history) nor in a cookie.
async function follow(conn) {
  const r = await fetch("/api/events", { headers: withToken({ Accept: "text/event-stream" }), cache: "no-store" });
  if (r.status === 401 || r.status === 403) return false;  // retrying would not help
  if (!r.ok || !r.body) throw new Error(`HTTP ${r.status}`);
  const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) throw new Error("the stream ended");
    buffer += value.replace(/\r\n?/g, "\n");
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let event = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event:")) event = line.slice(6).trim();
        else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
      }
      if (event !== "state" || !data.length) continue;
      conn.dataset.state = "live";
      conn.textContent = "live";
      try { render(JSON.parse(data.join("\n"))); } catch (e) { console.error(e); }
    }
  }
}

async function connect() {
  const conn = $("#connection");
  if (!TOKEN) { refused(conn); return; }
  for (let delay = 1000; ; delay = Math.min(delay * 2, 10000)) {
    try {
      if (!(await follow(conn))) { refused(conn); return; }
    } catch (e) {
      if (conn.dataset.state === "live") delay = 1000;  // it was up: try again soon
      conn.dataset.state = "lost";
      conn.textContent = "reconnecting…";
    }
    await new Promise((resolve) => setTimeout(resolve, delay));
  }
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
  requestDraw();
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
        el("div", { class: "p-area" }),
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
    const area = p.area && p.state !== "gone"
      ? `monitors area ${p.area.index ?? "?"}` + (p.area["delegated-by"] ? `, delegated by ${p.area["delegated-by"]}` : "")
      : "";
    const areaEl = li.querySelector(".p-area");
    if (areaEl.textContent !== area) areaEl.textContent = area;
    const body = li.querySelector("tbody");
    for (const st of p.streams) renderStream(body, p, st);
  }
  for (const li of [...list.children]) if (!seen.has(li.dataset.platform)) li.remove();
  $("#no-platforms").hidden = s.platforms.length > 0;
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
        el("td", { title: String(c.id) }, el("span", { class: "sw", style: `background:${colourOf(p.name)}` }), String(c.id).split("/").pop()),
        el("td", { text: p.name }),
        el("td", { text: `${fmtNum(c.speed)} m/s` }),
        el("td", { text: c.road ?? "–" }),
        el("td", { text: `${fmtNum(c.x, 0)}, ${fmtNum(c.y, 0)}` })));
    }
  }
  $("#cars tbody").replaceChildren(...rows);
  $("#car-count").textContent = String(rows.length);
}

// every violation reported (any kind: speeding too), newest first: when, what, which car, who
function renderViolations(s) {
  const items = s.violations.map((v) => {
    const who = v.platform || v["reported-by"];
    const cars = carsOf(v);
    return el("li", { "data-kind": v.kind, "data-car": Array.isArray(v.cars) ? v.cars.join(" ") : v.car, "data-platform": who },
      el("span", { class: "time", title: "world time of its end", text: fmtClock(v.end ?? v.valid) }),
      el("span", { class: "kind", text: v.kind }),
      el("span", { class: "car", title: cars, text: cars }),
      el("span", { class: "platform" }, who ?? "–", v.fused ? el("span", { class: "fused", title: "seen with another UAV's states", text: "fused" }) : null));
  });
  $("#violations").replaceChildren(...items);
  $("#violation-count").textContent = String(items.length);
  $("#no-violations").hidden = items.length > 0;
  $("#violations-head").hidden = items.length === 0;
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
// Drawn on a canvas, zoomed and panned by the operator; its labels are HTML boxes over it,
// each put at the first free place around its mark: one with no free place is not shown
// (hovering the mark shows it). Every kind of mark drawn is in the legend.

const LABEL_FONT = "600 12px system-ui, -apple-system, \"Segoe UI\", Roboto, \"DejaVu Sans\", sans-serif";
const LABEL_H = 16;     // px: a label's box (line height)
const LABEL_PAD = 3;    // px each side of its text
const ZOOM_MIN = 0.5, ZOOM_MAX = 40;
const WORLD_BG = "#eef2ea";
const VIOLATION = "#c2410c";
const OBSERVATION_INK = "#0f766e";
const GONE = "#9aa3ad";
// every kind of mark, in the legend's order, with what it means
const MARKS = [
  ["uav", "UAV or other platform (its colour)"],
  ["uav-area", "area it monitors (its colour)"],
  ["car", "car (its colour, ringed in its tracker's)"],
  ["violation", "violation (the newest strongest)"],
  ["observation", "operator's observation"],
  ["road", "road (dashes between lanes)"],
  ["crossing", "crossing"],
  ["parking", "parking lot"],
  ["world-area", "area no one monitors (dashed)"],
  ["pick", "point picked for an observation"],
];

const mapView = { zoom: 1, cx: null, cy: null };  // centre in world units; null: the map's
let view = null;         // the last frame's transform
let marks = [];          // what the last frame drew at a point (hover, label placement)
let areasDrawn = [];     // the areas of the last frame (hover)
let drawRequested = false;
const measure = document.createElement("canvas").getContext("2d");

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

// world -> canvas: zoom 1 shows the whole map; world y grows upwards, the canvas' downwards
function frame(s, cw, ch) {
  const b = bounds(s);
  const margin = 20;
  const fit = Math.max(1e-9, Math.min((cw - 2 * margin) / (b.x1 - b.x0), (ch - 2 * margin) / (b.y1 - b.y0)));
  const scale = fit * mapView.zoom;
  const cx = mapView.cx ?? (b.x0 + b.x1) / 2, cy = mapView.cy ?? (b.y0 + b.y1) / 2;
  return {
    b, scale, cx, cy, cw, ch,
    X: (x) => cw / 2 + (x - cx) * scale,
    Y: (y) => ch / 2 - (y - cy) * scale,
    toWorld: (sx, sy) => ({ x: cx + (sx - cw / 2) / scale, y: cy - (sy - ch / 2) / scale }),
  };
}

function requestDraw() {
  if (drawRequested) return;
  drawRequested = true;
  requestAnimationFrame(() => { drawRequested = false; drawMap(); });
}

function drawMap() {
  const canvas = $("#map");
  const dpr = window.devicePixelRatio || 1;
  const cw = canvas.clientWidth, ch = canvas.clientHeight;
  if (canvas.width !== Math.round(cw * dpr) || canvas.height !== Math.round(ch * dpr)) {
    canvas.width = Math.round(cw * dpr);
    canvas.height = Math.round(ch * dpr);
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, cw, ch);
  marks = [];
  areasDrawn = [];
  const drawn = new Set();
  const labels = [];   // {key, text, sx, sy, r, priority, kind, colour}
  const titles = [];   // area titles: {key, polygon, texts, colour}
  if (!state) { placeLabels(null, titles, labels); return; }
  const v = view = frame(state, cw, ch);
  const { X, Y, scale } = v;
  const w = state.world || {};

  if (w.width && w.height) {
    ctx.fillStyle = WORLD_BG;
    ctx.fillRect(X(0), Y(w.height), w.width * scale, w.height * scale);
  }
  // areas: what each UAV monitors now (its colour), the others dashed
  const monitored = new Set();
  for (const p of state.platforms) {
    if (!p.area || p.state === "gone") continue;
    monitored.add(p.area.index);
    const c = colourOf(p.name);
    polygon(ctx, p.area.polygon, X, Y, c + "1a", c, []);
    drawn.add("uav-area");
    const i = p.area.index ?? "";
    titles.push({ key: `area:${p.name}`, polygon: p.area.polygon, colour: c,
      texts: [`area ${i} · ${p.name}`, `${i} · ${p.name}`, p.name] });
    areasDrawn.push({ polygon: p.area.polygon, tip: areaTip(p) });
  }
  for (const a of w.areas || []) {
    if (monitored.has(a.index)) continue;
    polygon(ctx, a.polygon, X, Y, "rgba(100,116,139,0.05)", "rgba(100,116,139,0.6)", [5, 4]);
    drawn.add("world-area");
    titles.push({ key: `area:${a.index}`, polygon: a.polygon, colour: "#64748b",
      texts: [`area ${a.index} · no one`, `area ${a.index}`, String(a.index)] });
    areasDrawn.push({ polygon: a.polygon, tip: `area ${a.index}: no platform monitors it now` });
  }
  for (const pk of w.parking || []) {
    drawParking(ctx, pk.map(([x, y]) => [X(x), Y(y)]));
    drawn.add("parking");
    const xs = pk.map((q) => q[0]), ys = pk.map((q) => q[1]);
    marks.push({ kind: "parking", sx: X((Math.min(...xs) + Math.max(...xs)) / 2), sy: Y((Math.min(...ys) + Math.max(...ys)) / 2),
      r: Math.max(6, (Math.max(...xs) - Math.min(...xs)) * scale / 2), tip: "parking lot", obstacle: false });
  }
  // roads and crossings
  for (const r of w.roads || []) {
    drawRoad(ctx, X(r.a[0]), Y(r.a[1]), X(r.b[0]), Y(r.b[1]), Math.max(3, 3.5 * (r.lanes || 1) * scale), r.lanes || 1);
    drawn.add("road");
  }
  for (const c of w.crossings || []) {
    const rad = Math.max(4, (c.radius || 10) * scale);
    drawCrossing(ctx, X(c.x), Y(c.y), rad);
    drawn.add("crossing");
    marks.push({ kind: "crossing", sx: X(c.x), sy: Y(c.y), r: rad,
      tip: `crossing ${c.id ?? ""}${c.roads ? " · roads " + c.roads.join(", ") : ""}`, obstacle: false });
  }
  // violations where they happened, the newest last (on top) and strongest
  const shown = state.violations.slice(0, 30);
  for (let i = shown.length - 1; i >= 0; i--) {
    const viol = shown[i];
    if (!isFinite(viol.x) || !isFinite(viol.y)) continue;
    const x = X(viol.x), y = Y(viol.y);
    drawViolation(ctx, x, y, Math.max(0.25, 1 - i / 12));
    drawn.add("violation");
    marks.push({ kind: "violation", sx: x, sy: y, r: 10, tip: violationTip(viol), obstacle: true });
    if (i < 4) labels.push({ key: `v:${i}:${viol.kind}:${carsOf(viol)}`, text: viol.kind, sx: x, sy: y, r: 10, priority: 3, kind: "violation" });
  }
  // cars
  const carR = Math.min(9, Math.max(4.5, 2.2 * scale));
  for (const p of state.platforms) {
    if (p.state === "gone") continue;
    const c = colourOf(p.name);
    for (const car of p.cars) {
      const x = X(car.x), y = Y(car.y);
      const fill = car.colour && CSS.supports("color", car.colour) ? car.colour : c;
      drawCar(ctx, x, y, carR, fill, c);
      drawn.add("car");
      const id = String(car.id);
      marks.push({ kind: "car", sx: x, sy: y, r: carR + 1, tip: carTip(car, p), obstacle: true });
      // short names repeat across trackers (car2 of each): the label is in the tracker's colour
      labels.push({ key: `car:${id}`, text: shortCar(id), sx: x, sy: y, r: carR + 1, priority: 2, kind: "car", colour: darker(c) });
    }
  }
  // UAVs
  for (const p of state.platforms) {
    if (!p.position) continue;
    const alive = p.state === "alive";
    const x = X(p.position.x), y = Y(p.position.y);
    drawUav(ctx, x, y, alive ? colourOf(p.name) : GONE);
    drawn.add("uav");
    marks.push({ kind: "uav", sx: x, sy: y, r: 10, tip: uavTip(p), obstacle: true });
    labels.push({ key: `uav:${p.name}`, text: alive ? p.name : `${p.name} (${p.state})`, sx: x, sy: y, r: 10,
      priority: alive ? 0 : 1, kind: "uav", colour: alive ? darker(colourOf(p.name)) : GONE });
  }
  // the operator's observations
  state.observations.slice(0, 50).forEach((o, i) => {
    if (!isFinite(o.x) || !isFinite(o.y)) return;
    const x = X(o.x), y = Y(o.y);
    drawObservation(ctx, x, y);
    drawn.add("observation");
    marks.push({ kind: "observation", sx: x, sy: y - 6, r: 7, tip: `observation: ${o.text} (${fmtNum(o.x, 0)}, ${fmtNum(o.y, 0)})`, obstacle: true });
    labels.push({ key: `obs:${i}:${o.text}`, text: compact(o.text, 32), sx: x, sy: y - 6, r: 7, priority: 4, kind: "observation" });
  });
  if (pendingClick) {
    drawPick(ctx, X(pendingClick.x), Y(pendingClick.y));
    drawn.add("pick");
  }
  drawScale(ctx, v);
  placeLabels(v, titles, labels);
  renderLegend(drawn);
  const canvasEl = $("#map");
  canvasEl.dataset.marks = [...drawn].sort().join(" ");
  canvasEl.dataset.zoom = mapView.zoom.toFixed(2);
}

// -- marks (the map and the legend draw them alike) -----------------------------------

function drawUav(ctx, x, y, colour) {
  ctx.fillStyle = colour;
  ctx.strokeStyle = "#ffffff";
  ctx.lineWidth = 2;
  ctx.beginPath();
  ctx.moveTo(x, y - 10); ctx.lineTo(x + 9, y + 7); ctx.lineTo(x, y + 3); ctx.lineTo(x - 9, y + 7);
  ctx.closePath(); ctx.fill(); ctx.stroke();
}

function drawCar(ctx, x, y, r, fill, ring) {
  ctx.fillStyle = fill;
  ctx.strokeStyle = ring;
  ctx.lineWidth = 2;
  ctx.beginPath(); ctx.arc(x, y, r, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
}

function drawViolation(ctx, x, y, alpha) {
  ctx.save();
  ctx.globalAlpha = alpha;
  ctx.strokeStyle = VIOLATION;
  ctx.lineWidth = 2.5;
  line(ctx, x - 6, y - 6, x + 6, y + 6);
  line(ctx, x - 6, y + 6, x + 6, y - 6);
  ctx.beginPath(); ctx.arc(x, y, 9, 0, 2 * Math.PI); ctx.stroke();
  ctx.restore();
}

function drawObservation(ctx, x, y) {
  ctx.fillStyle = OBSERVATION_INK;
  ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x - 6, y - 12); ctx.lineTo(x + 6, y - 12); ctx.closePath(); ctx.fill();
}

function drawRoad(ctx, x0, y0, x1, y1, width, lanes) {
  ctx.save();
  ctx.lineCap = "round";
  ctx.strokeStyle = "#b8bec6";
  ctx.lineWidth = width;
  line(ctx, x0, y0, x1, y1);
  if (lanes > 1) {
    ctx.strokeStyle = "#ffffff";
    ctx.lineWidth = 1;
    ctx.setLineDash([6, 6]);
    line(ctx, x0, y0, x1, y1);
  }
  ctx.restore();
}

function drawCrossing(ctx, x, y, r) {
  ctx.fillStyle = "#cfd4da";
  ctx.strokeStyle = "#9aa3ad";
  ctx.lineWidth = 1;
  ctx.beginPath(); ctx.arc(x, y, r, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
}

function drawParking(ctx, pts) {
  ctx.beginPath();
  pts.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
  ctx.closePath();
  ctx.fillStyle = "rgba(148,163,184,0.3)"; ctx.fill();
  ctx.strokeStyle = "rgba(100,116,139,0.7)"; ctx.lineWidth = 1; ctx.stroke();
  const xs = pts.map((q) => q[0]), ys = pts.map((q) => q[1]);
  const side = Math.min(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys));
  if (side >= 11) {
    ctx.fillStyle = "rgba(71,85,105,0.8)";
    ctx.font = `700 ${Math.min(14, Math.floor(side * 0.7))}px system-ui, sans-serif`;
    ctx.textAlign = "center"; ctx.textBaseline = "middle";
    ctx.fillText("P", (Math.min(...xs) + Math.max(...xs)) / 2, (Math.min(...ys) + Math.max(...ys)) / 2 + 0.5);
    ctx.textAlign = "left"; ctx.textBaseline = "alphabetic";
  }
}

// a scale bar in the bottom-left corner: a round length about 100 px long
function drawScale(ctx, v) {
  const want = 100 / v.scale;
  const step = 10 ** Math.floor(Math.log10(want));
  const metres = [1, 2, 5, 10].map((k) => k * step).reduce((a, b) => (Math.abs(b - want) < Math.abs(a - want) ? b : a));
  const len = metres * v.scale, x = 12, y = v.ch - 12;
  ctx.save();
  ctx.strokeStyle = "#475569"; ctx.lineWidth = 1.5;
  ctx.beginPath(); ctx.moveTo(x, y - 5); ctx.lineTo(x, y); ctx.lineTo(x + len, y); ctx.lineTo(x + len, y - 5); ctx.stroke();
  ctx.fillStyle = "#475569"; ctx.font = "11px system-ui, sans-serif"; ctx.textBaseline = "bottom";
  ctx.fillText(metres >= 1000 ? `${metres / 1000} km` : `${metres} m`, x + 4, y - 2);
  ctx.restore();
}

function drawPick(ctx, x, y) {
  ctx.strokeStyle = OBSERVATION_INK; ctx.lineWidth = 1.5;
  ctx.beginPath(); ctx.arc(x, y, 8, 0, 2 * Math.PI); ctx.stroke();
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

function line(ctx, x0, y0, x1, y1) {
  ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.stroke();
}

// one legend sample of a kind of mark, drawn by the map's own code
function drawSwatch(ctx, kind, w, h) {
  const x = w / 2, y = h / 2;
  const accent = PALETTE[0];
  ctx.fillStyle = WORLD_BG; ctx.fillRect(0, 0, w, h);
  const rect = (fill, stroke, dash) => polygon(ctx, [[3, 3], [w - 3, 3], [w - 3, h - 3], [3, h - 3]], (a) => a, (a) => a, fill, stroke, dash);
  if (kind === "uav") drawUav(ctx, x, y + 1, accent);
  else if (kind === "uav-area") rect(accent + "1a", accent, []);
  else if (kind === "world-area") rect("rgba(100,116,139,0.05)", "rgba(100,116,139,0.8)", [4, 3]);
  else if (kind === "car") drawCar(ctx, x, y, 5, "#dc2626", accent);
  else if (kind === "violation") drawViolation(ctx, x, y, 1);
  else if (kind === "observation") drawObservation(ctx, x, y + 6);
  else if (kind === "road") drawRoad(ctx, 2, y, w - 2, y, 8, 2);
  else if (kind === "crossing") drawCrossing(ctx, x, y, 6);
  else if (kind === "parking") drawParking(ctx, [[x - 7, y - 7], [x + 7, y - 7], [x + 7, y + 7], [x - 7, y + 7]]);
  else if (kind === "pick") drawPick(ctx, x, y);
}

function renderLegend(drawn) {
  const list = $("#legend");
  const kinds = MARKS.filter(([k]) => drawn.has(k));
  const platforms = state ? state.platforms.map((p) => `${p.name}:${p.state}`).join(",") : "";
  const key = kinds.map(([k]) => k).join(",") + "|" + platforms;
  if (list.dataset.key === key) return;
  list.dataset.key = key;
  const items = kinds.map(([kind, text]) => {
    const c = el("canvas", { width: "26", height: "18", "aria-hidden": "true" });
    const dpr = window.devicePixelRatio || 1;
    c.width = 26 * dpr; c.height = 18 * dpr;
    const cx = c.getContext("2d");
    cx.setTransform(dpr, 0, 0, dpr, 0, 0);
    drawSwatch(cx, kind, 26, 18);
    return el("li", { "data-mark": kind }, c, text);
  });
  // each platform's colour, kept together on one line
  const owners = (state ? state.platforms : []).map((p) =>
    el("span", { "data-platform": p.name, class: "owner" },
      el("span", { class: "sw", style: `background:${p.state === "alive" ? colourOf(p.name) : GONE}` }),
      p.state === "alive" ? p.name : `${p.name} (${p.state})`));
  list.replaceChildren(...items, ...(owners.length ? [el("li", { class: "owners" }, ...owners)] : []));
}

// -- labels ---------------------------------------------------------------------------

const widths = new Map();  // text -> its label's width (the same few texts, frame after frame)

function textWidth(text) {
  let w = widths.get(text);
  if (w === undefined) {
    measure.font = LABEL_FONT;
    w = Math.ceil(measure.measureText(text).width) + 2 * LABEL_PAD;
    if (widths.size > 2000) widths.clear();
    widths.set(text, w);
  }
  return w;
}

function overlaps(a, b, pad = 1) {
  return a.x < b.x + b.w + pad && b.x < a.x + a.w + pad && a.y < b.y + b.h + pad && b.y < a.y + a.h + pad;
}

function coversMark(box, m) {
  const nx = Math.max(box.x, Math.min(m.sx, box.x + box.w));
  const ny = Math.max(box.y, Math.min(m.sy, box.y + box.h));
  return Math.hypot(nx - m.sx, ny - m.sy) < m.r + 1;
}

function placeLabels(v, titles, labels) {
  const boxes = [];
  const out = [];
  if (v) {
    const tools = $(".map-tools");
    const canvasBox = $("#map").getBoundingClientRect();
    if (tools) {
      const t = tools.getBoundingClientRect();
      boxes.push({ x: t.left - canvasBox.left, y: t.top - canvasBox.top, w: t.width, h: t.height });
    }
    boxes.push({ x: 0, y: v.ch - 30, w: 130, h: 30 });  // the scale bar
    const inside = (b) => b.x >= 2 && b.y >= 2 && b.x + b.w <= v.cw - 2 && b.y + b.h <= v.ch - 2;
    // area titles: in the area's top-left corner (what is visible of it), the longest text that fits
    for (const t of titles) {
      const xs = t.polygon.map((q) => v.X(q[0])), ys = t.polygon.map((q) => v.Y(q[1]));
      const left = Math.max(Math.min(...xs), 0) + 6, right = Math.min(Math.max(...xs), v.cw) - 6;
      const top = Math.max(Math.min(...ys), 0) + 5;
      const text = t.texts.find((s) => textWidth(s) <= right - left);
      if (text === undefined) continue;
      const box = { x: left, y: top, w: textWidth(text), h: LABEL_H };
      if (!inside(box) || boxes.some((b) => overlaps(b, box))) continue;
      boxes.push(box);
      out.push({ key: t.key, text, box, kind: "area-title", colour: darker(t.colour) });
    }
    const obstacles = marks.filter((m) => m.obstacle);
    labels.sort((a, b) => a.priority - b.priority);
    for (const l of labels) {
      const w = textWidth(l.text), h = LABEL_H, r = l.r + 3, d = r * 0.72;
      const candidates = [
        [l.sx + r, l.sy - h / 2],          // right
        [l.sx + d, l.sy - d - h],          // above right
        [l.sx + d, l.sy + d],              // below right
        [l.sx - w / 2, l.sy - r - h],      // above
        [l.sx - w / 2, l.sy + r],          // below
        [l.sx - r - w, l.sy - h / 2],      // left
        [l.sx - d - w, l.sy - d - h],      // above left
        [l.sx - d - w, l.sy + d],          // below left
      ];
      let placed = null;
      for (const [x, y] of candidates) {
        const box = { x: Math.round(x), y: Math.round(y), w, h };
        if (inside(box) && !boxes.some((b) => overlaps(b, box)) && !obstacles.some((m) => coversMark(box, m))) {
          placed = box;
          break;
        }
      }
      if (!placed) continue;  // no room: hovering its mark shows it
      boxes.push(placed);
      out.push({ key: l.key, text: l.text, box: placed, kind: l.kind, colour: l.colour });
    }
  }
  const layer = $("#map-labels");
  const existing = new Map([...layer.children].map((n) => [n.dataset.key, n]));
  const keep = new Set();
  for (const o of out) {
    let node = existing.get(o.key);
    if (!node) {
      node = el("div", { class: "map-label", "data-key": o.key });
      layer.append(node);
    }
    keep.add(o.key);
    node.dataset.kind = o.kind;
    if (node.textContent !== o.text) node.textContent = o.text;
    node.style.left = `${o.box.x}px`;
    node.style.top = `${o.box.y}px`;
    node.style.width = `${o.box.w}px`;
    node.style.color = o.colour || "";
  }
  for (const [key, node] of existing) if (!keep.has(key)) node.remove();
  $("#map").dataset.labels = String(out.length);
  $("#map").dataset.unlabelled = String(labels.length + titles.length - out.length);
}

// -- what a mark is, on hover -----------------------------------------------------------

function shortCar(id) {
  // "uav-b/uav_b_car3" -> "car3": the ring's colour says whose
  const name = id.split("/").pop();
  const m = name.match(/_([A-Za-z]+\d+)$/);
  return m ? m[1] : name;
}

function carsOf(v) {
  if (Array.isArray(v.cars)) return v.cars.join(", ");
  return `${v.car ?? "–"}${v.other ? " vs " + v.other : ""}`;
}

function carTip(car, p) {
  const parts = [`${car.id} · tracked by ${p.name}`];
  if (isFinite(car.speed)) parts.push(`${fmtNum(car.speed)} m/s${car.road ? " on " + car.road : ""}`);
  if (car.colour) parts.push(String(car.colour));
  return parts.join(" · ");
}

function uavTip(p) {
  const parts = [`${p.name} (${p.state})`];
  if (p.area) parts.push(`monitors area ${p.area.index ?? "?"}${p.area["delegated-by"] ? ", delegated by " + p.area["delegated-by"] : ""}`);
  if (p.position && isFinite(p.position.z)) parts.push(`at ${fmtNum(p.position.z, 0)} m`);
  return parts.join(" · ");
}

function areaTip(p) {
  return `area ${p.area.index ?? "?"}: monitored by ${p.name}` +
    (p.area["delegated-by"] ? `, delegated by ${p.area["delegated-by"]}` : "");
}

function violationTip(v) {
  return `${v.kind}: ${carsOf(v)} · by ${v.platform || v["reported-by"]} · ${fmtClock(v.end ?? v.valid)}`;
}

function insidePolygon(x, y, pts) {
  let inside = false;
  for (let i = 0, j = pts.length - 1; i < pts.length; j = i++) {
    const [xi, yi] = pts[i], [xj, yj] = pts[j];
    if ((yi > y) !== (yj > y) && x < ((xj - xi) * (y - yi)) / (yj - yi) + xi) inside = !inside;
  }
  return inside;
}

function showTip(e) {
  const tip = $("#map-tip");
  if (!view) return;
  const r = $("#map").getBoundingClientRect();
  const sx = e.clientX - r.left, sy = e.clientY - r.top;
  let best = null, bestD = Infinity;
  for (const m of marks) {
    const d = Math.hypot(m.sx - sx, m.sy - sy);
    // a point mark first; a parking lot or crossing only when nothing else is near
    const reach = m.r + 6, rank = d + (m.obstacle ? 0 : 20);
    if (d <= reach && rank < bestD) { best = m; bestD = rank; }
  }
  let text = best ? best.tip : null;
  if (!text) {
    const w = view.toWorld(sx, sy);
    const area = areasDrawn.find((a) => insidePolygon(w.x, w.y, a.polygon));
    text = area ? area.tip : null;
  }
  if (!text) { tip.hidden = true; return; }
  tip.textContent = text;
  tip.hidden = false;
  const left = Math.min(sx + 14, r.width - tip.offsetWidth - 4);
  const top = sy + 16 + tip.offsetHeight > r.height ? sy - tip.offsetHeight - 10 : sy + 16;
  tip.style.left = `${Math.max(4, left)}px`;
  tip.style.top = `${Math.max(4, top)}px`;
}

function darker(hex) {
  // a label's ink: its mark's colour, darkened to read on the map's light ground
  const m = /^#([0-9a-f]{6})/i.exec(hex || "");
  if (!m) return hex;
  const n = parseInt(m[1], 16);
  const f = (c) => Math.round(c * 0.7).toString(16).padStart(2, "0");
  return `#${f(n >> 16)}${f((n >> 8) & 255)}${f(n & 255)}`;
}

// -- zoom, pan, pick ------------------------------------------------------------------

function clampView() {
  if (!view) return;
  const b = view.b;
  if (mapView.cx !== null) mapView.cx = Math.min(b.x1, Math.max(b.x0, mapView.cx));
  if (mapView.cy !== null) mapView.cy = Math.min(b.y1, Math.max(b.y0, mapView.cy));
}

function zoomAt(factor, sx, sy) {
  if (!view) return;
  const zoom = Math.min(ZOOM_MAX, Math.max(ZOOM_MIN, mapView.zoom * factor));
  const at = view.toWorld(sx, sy);
  const scale = view.scale * (zoom / mapView.zoom);
  // the point under the cursor stays where it is
  mapView.zoom = zoom;
  mapView.cx = at.x - (sx - view.cw / 2) / scale;
  mapView.cy = at.y + (sy - view.ch / 2) / scale;
  clampView();
  requestDraw();
}

function resetView() {
  mapView.zoom = 1; mapView.cx = null; mapView.cy = null;
  requestDraw();
}

let drag = null;
const mapCanvas = $("#map");
mapCanvas.addEventListener("pointerdown", (e) => {
  if (e.button !== 0 || !view) return;
  drag = { x: e.clientX, y: e.clientY, cx: view.cx, cy: view.cy, moved: false };
  mapCanvas.setPointerCapture(e.pointerId);
});
mapCanvas.addEventListener("pointermove", (e) => {
  if (!drag) { showTip(e); return; }
  const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
  if (!drag.moved && Math.hypot(dx, dy) < 4) return;  // a click that shook a little
  drag.moved = true;
  mapCanvas.classList.add("dragging");
  $("#map-tip").hidden = true;
  mapView.cx = drag.cx - dx / view.scale;
  mapView.cy = drag.cy + dy / view.scale;
  clampView();
  requestDraw();
});
mapCanvas.addEventListener("pointerup", (e) => {
  const d = drag;
  drag = null;
  mapCanvas.classList.remove("dragging");
  if (d && !d.moved) pick(e);
});
mapCanvas.addEventListener("pointercancel", () => { drag = null; mapCanvas.classList.remove("dragging"); });
mapCanvas.addEventListener("pointerleave", () => { if (!drag) $("#map-tip").hidden = true; });
mapCanvas.addEventListener("wheel", (e) => {
  e.preventDefault();
  const r = mapCanvas.getBoundingClientRect();
  const unit = e.deltaMode === 1 ? 16 : e.deltaMode === 2 ? 400 : 1;  // lines, pages, pixels
  zoomAt(Math.exp(-e.deltaY * unit * 0.0015), e.clientX - r.left, e.clientY - r.top);
}, { passive: false });
$("#zoom-in").addEventListener("click", () => zoomAt(1.5, mapCanvas.clientWidth / 2, mapCanvas.clientHeight / 2));
$("#zoom-out").addEventListener("click", () => zoomAt(1 / 1.5, mapCanvas.clientWidth / 2, mapCanvas.clientHeight / 2));
$("#zoom-fit").addEventListener("click", resetView);

// click on the map: its coordinates go into the observation form
function pick(e) {
  if (!view) return;
  const r = mapCanvas.getBoundingClientRect();
  const at = view.toWorld(e.clientX - r.left, e.clientY - r.top);
  pendingClick = at;
  $("#obs-x").value = at.x.toFixed(1);
  $("#obs-y").value = at.y.toFixed(1);
  $("#obs-text").focus();
  requestDraw();
}
new ResizeObserver(requestDraw).observe($("#map-wrap"));

// what the map drew, where (canvas pixels): for tests and for a look from the devtools
window.dyknowMap = {
  marks: () => marks.map(({ kind, sx, sy, r, tip }) => ({ kind, x: sx, y: sy, r, tip })),
  view: () => ({ zoom: mapView.zoom, cx: view && view.cx, cy: view && view.cy, scale: view && view.scale }),
};

// -- requests -----------------------------------------------------------------------------

async function post(url, body) {
  try {
    const r = await fetch(url, { method: "POST", headers: withToken({ "Content-Type": "application/json" }), body: JSON.stringify(body) });
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

// a label search: every platform's answer, and why an answer is empty
$("#search-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  const out = $("#query-result");
  out.replaceChildren(el("p", { class: "caption", text: "searching the federation…" }));
  const r = await post("/api/search", { formula: $("#search-formula").value });
  if (!r.ok) return showError(out, r.body.error);
  const rows = [];
  let found = 0;
  const byName = (a, b) => (a[0] < b[0] ? -1 : a[0] > b[0] ? 1 : 0);
  for (const [p, labels] of Object.entries(r.body.answers).sort(byName)) {
    found += labels.length;
    rows.push(el("tr", { "data-platform": p, "data-labels": String(labels.length) }, el("td", { text: p }),
      labels.length
        ? el("td", {}, el("code", { class: "v", text: labels.join(", ") }))
        : el("td", { class: "empty", text: "none: nothing this platform provides satisfies it" })));
  }
  for (const [p, why] of Object.entries(r.body.refused).sort(byName)) {
    rows.push(el("tr", { "data-platform": p, "data-labels": "0" }, el("td", { text: p }), el("td", { class: "error", text: `refused: ${why}` })));
  }
  for (const p of [...r.body.no_answer].sort()) {
    rows.push(el("tr", { "data-platform": p, "data-labels": "0" }, el("td", { text: p }), el("td", { class: "empty", text: "no answer within the search's 2 s" })));
  }
  for (const p of [...(r.body.unlisted || [])].sort()) {
    rows.push(el("tr", { "data-platform": p, "data-labels": "0" }, el("td", { text: p }), el("td", { class: "empty", text: "not asked: a member the directory does not list yet" })));
  }
  const asked = rows.length;
  let caption;
  if (!asked) caption = "no member answered: is the federation empty?";
  else if (found) caption = `${found} label(s) matching ${r.body.formula}`;
  else if (Object.keys(r.body.answers).length) caption = `no platform provides a label for what ${r.body.formula} describes`;
  else caption = `no member answered ${r.body.formula}`;
  out.replaceChildren(
    el("p", { class: "caption", "data-found": String(found), text: caption }),
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
  requestDraw();
});

connect();
