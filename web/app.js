"use strict";
// Live dashboard: one panel per sensor, sorted by id (grouped by board when the
// service reads several), redrawn at the display rate from the latest frame of
// each sensor (the stream is decimated server-side), with a force history of
// the last 10 s, a link status banner and the recording's path. A sensor that
// is silent when the page opens (a replay that has ended) is drawn from its
// last seconds, which the service keeps.

const GRID_MAX_N = 5;             // colour scale top, newtons per taxel
// The service's contact rule (reconstruct/contact.py, docs/reconstruction.md): above 0.05 N and 4 σ of the
// taxel's own force, σ capped at 0.5 N; without σ, 0.05 N alone.
const CONTACT_THRESHOLD_N = 0.05, CONTACT_NOISE_SIGMAS = 4, CONTACT_NOISE_CAP_N = 0.5;
const PITCH_MM = 4;
const SHEAR_MAX_N = 10;           // quad arrow full scale
const FZ_MAX_N = 20;              // quad bar full scale
const HISTORY_S = 10;
const STREAM_RATE_HZ = 30;        // frames a second per sensor, decimated server-side
const RECENT_S = 5;               // as much as /sensors/…/history keeps
const STALE_AFTER_S = 1;          // only for services that do not report link.stale_after_s
const FLAG_HOLD_MS = 1500;        // a flag raised for one frame stays long enough to be read
const TAXEL_MARKS = [["saturated", "S"], ["out_of_range", "R"], ["crosstalk_corrected", "x"], ["stale", "?"]];
const FLAG_SEVERITY = {
  open_channel: "error", shorted_channel: "error", electrode_fault: "error", board_restart: "error",
  unidentified: "error", taring: "info", crosstalk_corrected: "info",
};
const token = new URLSearchParams(location.search).get("token");
const authHeaders = token ? { Authorization: `Bearer ${token}` } : {};

const panels = new Map();         // sensor address (board/id) → panel
let streamOpen = false;
let dirty = false;

// ---- DOM helpers --------------------------------------------------------

function element(tag, className, text) {
  const node = document.createElement(tag);
  if (className) node.className = className;
  if (text !== undefined) node.textContent = text;
  return node;
}

const resizer = new ResizeObserver((entries) => {
  for (const entry of entries) fitCanvas(entry.target);
  dirty = true;
});

// The backing store follows the element's CSS size, so drawings stay sharp at any window width.
function fitCanvas(canvas) {
  const ratio = window.devicePixelRatio || 1;
  const width = Math.round(canvas.clientWidth * ratio), height = Math.round(canvas.clientHeight * ratio);
  if (canvas.width !== width || canvas.height !== height) { canvas.width = width; canvas.height = height; }
}

// Clears the whole canvas, so nothing of an earlier frame survives, and returns
// a context drawing in CSS pixels.
function beginDraw(canvas) {
  if (!canvas.clientWidth || !canvas.width) return null;
  const ctx = canvas.getContext("2d");
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const scale = canvas.width / canvas.clientWidth;
  ctx.setTransform(scale, 0, 0, scale, 0, 0);
  return { ctx, w: canvas.clientWidth, h: canvas.height / scale };
}

// A value as text, "—" where the service gave none (null): never shown as 0.
function shown(value, format) {
  return value === null || value === undefined ? "—" : format(value);
}

function haloText(ctx, text, x, y, colour = "#fff") {
  ctx.lineWidth = 3; ctx.strokeStyle = "rgba(0,0,0,0.85)"; ctx.lineJoin = "round";
  ctx.strokeText(text, x, y);
  ctx.fillStyle = colour; ctx.fillText(text, x, y);
}

// ---- panels, boards and their order ---------------------------------------

function boardGroup(board) {
  const root = document.getElementById("sensors");
  const key = board ?? "";
  let group = [...root.children].find((g) => g.dataset.board === key);
  if (!group) {
    group = element("section", "board");
    group.dataset.board = key;
    group.append(element("h2", "board-title", board ? `board ${board}` : "board"), element("div", "panels"));
    root.append(group);
  }
  return group;
}

function lowestId(group) {
  return Math.min(...[...group.querySelectorAll(".panel")].map((p) => Number(p.dataset.sensor)));
}

// Boards in the order of their lowest sensor id; headings only when there are several.
function arrangeBoards() {
  const root = document.getElementById("sensors");
  for (const empty of [...root.children].filter((g) => !g.querySelector(".panel"))) empty.remove();
  const groups = [...root.children];
  groups.sort((a, b) => lowestId(a) - lowestId(b)).forEach((g) => root.append(g));
  root.classList.toggle("several-boards", groups.length > 1);
}

function placePanel(panel) {
  const list = boardGroup(panel.board).querySelector(".panels");
  const next = [...list.children].find((other) => Number(other.dataset.sensor) > panel.id);
  list.insertBefore(panel.el, next || null);
  arrangeBoards();
}

function makeCanvas(className) {
  const canvas = element("canvas", className);
  resizer.observe(canvas);
  return canvas;
}

function colourScale() {
  const scale = element("div", "colour-scale");
  scale.append(element("span", "", "0"), element("div", "bar"), element("span", "", `${GRID_MAX_N} N`));
  return scale;
}

// A sensor's key: its address, board/id (a service before boards were named sends no board).
function sensorKey(board, id) {
  return `${board ?? ""}/${id}`;
}

function createPanel(id, info) {
  const el = element("section", "panel");
  el.dataset.sensor = id;
  el.dataset.board = info.board ?? "";
  const title = element("h3");
  const flags = element("span", "flags");
  const staleMark = element("span", "stale-mark");
  staleMark.hidden = true;
  const live = makeCanvas("live");
  const history = makeCanvas("history");
  const meta = element("div", "meta", "waiting for data…");
  const calibration = element("div", "calibration");
  const readout = element("div", "taxel-readout", READOUT_HINT);
  el.append(element("div", "panel-head"), live);
  el.firstChild.append(title, staleMark, flags);
  if (info.kind === "grid") el.append(readout, colourScale());
  el.append(history, meta, calibration);
  const panel = { id, el, title, flags, staleMark, live, readout, history, meta, calibration, board: info.board ?? null,
                  frame: null, frames: 0, series: [], flagSeen: new Map(), shownFlags: "", recentAsked: false,
                  stale: false, hover: null };
  live.addEventListener("mousemove", (event) => { panel.hover = taxelAt(panel, event); showReadout(panel); });
  live.addEventListener("mouseleave", () => { panel.hover = null; showReadout(panel); });
  describePanel(panel, info);
  placePanel(panel);
  return panel;
}

function describePanel(panel, info) {
  panel.kind = info.kind;
  panel.el.dataset.kind = info.kind;
  const shape = info.kind === "grid" && info.rows ? ` ${info.rows}×${info.cols}` : "";
  panel.title.textContent = `${info.name ?? `sensor ${panel.id}`} · ${info.kind}${shape}`;
  const aspect = info.kind === "grid" && info.rows ? info.cols / info.rows : 4 / 3;
  panel.live.style.setProperty("--aspect", aspect);
}

// One panel per sensor address, in its board's group.
function ensurePanel(id, info) {
  const key = sensorKey(info.board, id);
  if (!panels.has(key)) panels.set(key, createPanel(id, info));
  return panels.get(key);
}

function infoFromFrame(frame) {
  const h = frame.header;
  return { name: h.sensor_name, kind: h.kind, rows: frame.rows, cols: frame.cols, board: h.board ?? null };
}

async function loadSensors() {
  try {
    const answer = await (await fetch("/sensors")).json();
    const list = Array.isArray(answer) ? answer : answer.sensors || [];
    for (const s of [...list].sort((a, b) => a.id - b.id)) {
      ensurePanel(s.id, s);
    }
  } catch (err) {
    // The frames create their panels; /health reports why the service is unwell.
  }
}

// ---- grid drawing -------------------------------------------------------

function heatColour(f) {
  const x = Math.max(0, Math.min(1, f / GRID_MAX_N));
  const r = Math.round(255 * Math.min(1, 2 * x));
  const g = Math.round(255 * Math.max(0, 2 * x - 1));
  const b = Math.round(80 * (1 - x));
  return `rgb(${r},${g},${b})`;
}

function drawTaxels(ctx, frame, cell) {
  frame.force_N.forEach((f, i) => {
    const r = Math.floor(i / frame.cols), c = i % frame.cols;
    ctx.fillStyle = f === null ? "#444" : heatColour(f);
    ctx.fillRect(c * cell + 1, r * cell + 1, cell - 2, cell - 2);
  });
}

function isLoaded(frame, r, c) {
  if (r < 0 || c < 0 || r >= frame.rows || c >= frame.cols) return false;
  const i = r * frame.cols + c, f = frame.force_N[i];
  const sigma = frame.sigma_N ? frame.sigma_N[i] : null;
  const noise = sigma === null || sigma === undefined ? 0 : Math.min(CONTACT_NOISE_SIGMAS * sigma, CONTACT_NOISE_CAP_N);
  return f !== null && f > Math.max(CONTACT_THRESHOLD_N, noise);
}

// Edges between a taxel in contact and one that is not.
function drawContactOutline(ctx, frame, cell) {
  ctx.strokeStyle = "#00e5ff"; ctx.lineWidth = 2; ctx.beginPath();
  for (let r = 0; r < frame.rows; r++) {
    for (let c = 0; c < frame.cols; c++) {
      if (!isLoaded(frame, r, c)) continue;
      const x = c * cell, y = r * cell;
      if (!isLoaded(frame, r - 1, c)) { ctx.moveTo(x, y + 1); ctx.lineTo(x + cell, y + 1); }
      if (!isLoaded(frame, r + 1, c)) { ctx.moveTo(x, y + cell - 1); ctx.lineTo(x + cell, y + cell - 1); }
      if (!isLoaded(frame, r, c - 1)) { ctx.moveTo(x + 1, y); ctx.lineTo(x + 1, y + cell); }
      if (!isLoaded(frame, r, c + 1)) { ctx.moveTo(x + cell - 1, y); ctx.lineTo(x + cell - 1, y + cell); }
    }
  }
  ctx.stroke();
}

// A ring with ticks outside it: the centre stays open for the taxel's number.
function drawCentreOfPressure(ctx, frame, cell) {
  const contact = frame.contact;
  if (!contact || contact.cop_x_mm === null || contact.cop_y_mm === null) return;
  // Array frame: origin at the centre, x along columns, y along rows.
  const x = (contact.cop_x_mm / PITCH_MM + frame.cols / 2) * cell;
  const y = (contact.cop_y_mm / PITCH_MM + frame.rows / 2) * cell;
  const ring = cell * 0.42, tick = cell * 0.2;
  ctx.beginPath();
  ctx.arc(x, y, ring, 0, 2 * Math.PI);
  for (const [dx, dy] of [[1, 0], [-1, 0], [0, 1], [0, -1]]) {
    ctx.moveTo(x + dx * ring, y + dy * ring); ctx.lineTo(x + dx * (ring + tick), y + dy * (ring + tick));
  }
  ctx.lineWidth = 4; ctx.strokeStyle = "rgba(0,0,0,0.7)"; ctx.stroke();
  ctx.lineWidth = 2; ctx.strokeStyle = "#fff"; ctx.stroke();
}

function taxelMark(frame, i) {
  const flags = frame.taxel_flags || {};
  const found = TAXEL_MARKS.find(([name]) => (flags[name] || []).includes(i));
  return found ? found[1] : "";
}

function drawTaxelLabels(ctx, frame, cell) {
  const size = Math.max(9, Math.min(15, cell * 0.26));
  ctx.textAlign = "center"; ctx.textBaseline = "middle";
  frame.force_N.forEach((f, i) => {
    const r = Math.floor(i / frame.cols), c = i % frame.cols;
    ctx.font = `${size}px system-ui, sans-serif`;
    haloText(ctx, f === null ? "—" : f.toFixed(2), c * cell + cell / 2, r * cell + cell / 2);
    const mark = taxelMark(frame, i);
    if (mark) {
      ctx.font = `bold ${size}px system-ui, sans-serif`;
      haloText(ctx, mark, c * cell + cell - size * 0.6, r * cell + size * 0.7, "#ff6e6e");
    }
  });
}

// ---- a taxel's force ± σ ------------------------------------------------------

const READOUT_HINT = "point at a taxel: its force ± 1σ and flags";

// The row-major index of the taxel under the mouse, or null (no frame, or off the grid).
function taxelAt(panel, event) {
  const frame = panel.frame;
  if (!frame || panel.kind !== "grid") return null;
  const box = panel.live.getBoundingClientRect(), cell = box.width / frame.cols;
  const r = Math.floor((event.clientY - box.top) / cell), c = Math.floor((event.clientX - box.left) / cell);
  return r < 0 || c < 0 || r >= frame.rows || c >= frame.cols ? null : r * frame.cols + c;
}

// "1.69 ± 0.12 N" (1σ), "5.20 N (no σ)" where the service gives none (a saturated taxel), "—" without a force.
function forceText(frame, i) {
  const f = frame.force_N[i], sigma = frame.sigma_N ? frame.sigma_N[i] : null;
  if (f === null) return "—";
  return sigma === null || sigma === undefined ? `${f.toFixed(2)} N (no σ)` : `${f.toFixed(2)} ± ${sigma.toFixed(2)} N`;
}

function taxelFlagNames(frame, i) {
  return Object.entries(frame.taxel_flags || {}).filter(([, taxels]) => taxels.includes(i))
    .map(([name]) => name.replaceAll("_", " "));
}

// The hovered taxel's force ± σ and flags, following the frames while the mouse rests.
function showReadout(panel) {
  const frame = panel.frame, i = panel.hover;
  if (i === null || !frame || i >= frame.force_N.length) { panel.readout.textContent = READOUT_HINT; return; }
  const where = `taxel ${i} (row ${Math.floor(i / frame.cols)}, col ${i % frame.cols})`;
  panel.readout.textContent = [`${where}: ${forceText(frame, i)}`, ...taxelFlagNames(frame, i)].join(" · ");
}

// The most loaded taxel's force ± σ, for the panel's line; "" without any force.
function largestTaxel(frame) {
  let largest = -1;
  frame.force_N.forEach((f, i) => { if (f !== null && (largest < 0 || f > frame.force_N[largest])) largest = i; });
  return largest < 0 ? "" : `max ${forceText(frame, largest)} (taxel ${largest})`;
}

function drawGrid(panel) {
  const frame = panel.frame;
  const view = beginDraw(panel.live);
  if (!view) return;
  const cell = view.w / frame.cols;
  drawTaxels(view.ctx, frame, cell);
  drawContactOutline(view.ctx, frame, cell);
  drawCentreOfPressure(view.ctx, frame, cell);
  drawTaxelLabels(view.ctx, frame, cell); // last, so the numbers stay readable
  // No contact (null while the sensor tares): no value, not 0.
  const contact = frame.contact || {};
  panel.meta.textContent = [`seq ${frame.header.seq}`, `ΣF ${shown(contact.total_N, (v) => `${v.toFixed(2)} N`)}`,
    `contacts ${shown(contact.contacts, String)}`, `area ${shown(contact.area_mm2, (v) => `${v} mm²`)}`,
    largestTaxel(frame)].filter(Boolean).join(" · ");
  showReadout(panel);
}

// ---- quad drawing -------------------------------------------------------

function drawShearDial(ctx, cx, cy, radius, fx, fy) {
  ctx.strokeStyle = "#555"; ctx.lineWidth = 1; ctx.fillStyle = "#999";
  ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "left"; ctx.textBaseline = "bottom";
  for (const n of [SHEAR_MAX_N / 2, SHEAR_MAX_N]) {
    const r = radius * n / SHEAR_MAX_N;
    ctx.beginPath(); ctx.arc(cx, cy, r, 0, 2 * Math.PI); ctx.stroke();
    ctx.fillText(`${n} N`, cx + r * 0.72 + 3, cy - r * 0.72);
  }
  ctx.beginPath(); ctx.moveTo(cx - radius, cy); ctx.lineTo(cx + radius, cy);
  ctx.moveTo(cx, cy - radius); ctx.lineTo(cx, cy + radius); ctx.stroke();
  ctx.textAlign = "center"; ctx.textBaseline = "middle";
  ctx.fillText("+Fx", cx + radius + 16, cy); ctx.fillText("+Fy", cx, cy - radius - 9);
  if (fx === null || fy === null) return;
  const magnitude = Math.hypot(fx, fy);
  const shown = Math.min(1, SHEAR_MAX_N / Math.max(magnitude, 1e-9)); // beyond full scale: pinned to the rim, red
  const ex = cx + fx * shown / SHEAR_MAX_N * radius, ey = cy - fy * shown / SHEAR_MAX_N * radius;
  ctx.strokeStyle = magnitude > SHEAR_MAX_N ? "#ff5252" : "#4fc3f7"; ctx.lineWidth = 4; ctx.lineCap = "round";
  ctx.beginPath(); ctx.moveTo(cx, cy); ctx.lineTo(ex, ey); ctx.stroke();
  ctx.lineCap = "butt";
}

function drawFzBar(ctx, x, top, height, fz) {
  const width = 26;
  ctx.fillStyle = "#999"; ctx.strokeStyle = "#555"; ctx.lineWidth = 1;
  ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "left"; ctx.textBaseline = "middle";
  for (let n = 0; n <= FZ_MAX_N; n += 5) {
    const y = top + height - height * n / FZ_MAX_N;
    ctx.beginPath(); ctx.moveTo(x + width, y); ctx.lineTo(x + width + 5, y); ctx.stroke();
    ctx.fillText(n === FZ_MAX_N ? `${n} N` : `${n}`, x + width + 8, y);
  }
  if (fz !== null) {
    const h = Math.max(0, Math.min(1, fz / FZ_MAX_N)) * height;
    ctx.fillStyle = fz > FZ_MAX_N ? "#ff5252" : "#ffb74d";
    ctx.fillRect(x, top + height - h, width, h);
  }
  ctx.strokeRect(x, top, width, height);
  ctx.fillStyle = "#ddd"; ctx.textAlign = "center"; ctx.textBaseline = "top";
  ctx.fillText("Fz", x + width / 2, top + height + 6);
}

function drawQuad(panel) {
  const view = beginDraw(panel.live);
  if (!view) return;
  const { x: fx, y: fy, z: fz } = panel.frame.wrench.force;
  const barHeight = view.h - 44;
  const radius = Math.min(view.h / 2 - 24, view.w * 0.32);
  drawShearDial(view.ctx, view.w * 0.38, view.h / 2, radius, fx, fy);
  drawFzBar(view.ctx, view.w * 0.78, 18, barHeight, fz);
  const sigma = panel.frame.wrench_sigma ? panel.frame.wrench_sigma.force : {};
  const fmt = (v, s) => (v === null ? "—" : v.toFixed(2) + (s === null || s === undefined ? "" : ` ± ${s.toFixed(2)}`));
  panel.meta.textContent = `seq ${panel.frame.header.seq} · Fx ${fmt(fx, sigma.x)} · Fy ${fmt(fy, sigma.y)} · ` +
    `Fz ${fmt(fz, sigma.z)} N (± 1σ)`;
}

// ---- calibration ------------------------------------------------------------

function age(seconds) {
  if (seconds === null || seconds === undefined) return "";
  const days = seconds / 86400;
  return days >= 1 ? `, ${days.toFixed(0)} d old` : `, ${(seconds / 3600).toFixed(1)} h old`;
}

// Which calibration a sensor's forces rest on (from /health): a built-in one is
// the papers', not this sensor's, and says so; loaded taxels and load cycles too.
function showCalibration(panel, state, fatigue, sensor) {
  if (!state) return;
  const parts = sensor.serial ? [`serial ${sensor.serial}`] : [];
  // Another sensor plugged in at this address: say so, it is tared and calibrated as a new one.
  if (sensor.replaced) parts.push(`replaced: ${sensor.replaced.to} where ${sensor.replaced.from} was`);
  parts.push(state.builtin ? `calibration: built-in ${state.id} (the paper's, not measured on this sensor)`
                               : `calibration ${state.id}${age(state.age_s)}`);
  if (state.problem) parts.push(`its own could not be used: ${state.problem}`);
  if (state.loaded_at_tare && state.loaded_at_tare.length)
    parts.push(`loaded at tare: taxels ${state.loaded_at_tare.join(", ")} (zero from the calibration)`);
  if (fatigue && fatigue.cycles_max) {
    const factor = fatigue.sensitivity_factor === null ? "" : `, sensitivity ×${fatigue.sensitivity_factor.toFixed(3)}`;
    parts.push(`${fatigue.cycles_max} load cycles${factor}`);
  }
  panel.calibration.textContent = parts.join(" · ");
  panel.calibration.classList.toggle("builtin", state.builtin || Boolean(state.problem));
}

// ---- flags --------------------------------------------------------------

function updateFlags(panel, now) {
  for (const flag of panel.frame.flags || []) panel.flagSeen.set(flag, now);
  const shown = [...panel.flagSeen].filter(([, t]) => now - t < FLAG_HOLD_MS).map(([flag]) => flag).sort();
  const key = shown.join(",");
  if (key === panel.shownFlags) return;
  panel.shownFlags = key;
  panel.flags.replaceChildren(...shown.map((flag) =>
    element("span", `flag ${FLAG_SEVERITY[flag] || "warn"}`, flag.replaceAll("_", " "))));
}

// ---- history ------------------------------------------------------------

// The plotted values of a frame, N: [ΣF] of a grid, [Fz, |Fxy|] of a quad; null where the
// service gave none (a grid taring, an open electrode), drawn as a gap.
function historyValues(f) {
  if (f.header.kind === "grid") return [f.contact ? f.contact.total_N ?? null : null];
  const { x, y, z } = f.wrench.force;
  return [z ?? null, x === null || y === null ? null : Math.hypot(x, y)];
}

function recordHistory(panel) {
  const f = panel.frame;
  const t = f.header.stamp;
  if (panel.series.length && t < panel.series[panel.series.length - 1][0]) panel.series = []; // a replay restarted
  const values = historyValues(f);
  panel.series.push([t, values]);
  while (panel.series[0][0] < t - HISTORY_S) panel.series.shift();
}

// Round numbers for the axis, with 20 % headroom so a steady load stays off the top edge.
function niceScale(low, high) {
  const span = Math.max(high * 1.2 - Math.min(0, low * 1.2), 1);
  const raw = span / 4;
  const magnitude = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 2.5, 5, 10].map((k) => k * magnitude).find((s) => s >= raw);
  return { step, bottom: Math.floor(Math.min(0, low * 1.2) / step) * step, top: Math.ceil(Math.max(high * 1.2, 1) / step) * step };
}

// endLabel: what the plot's right end is ("now", or "last frame" of a stale sensor).
function drawHistoryAxes(ctx, plot, scale, endLabel) {
  ctx.strokeStyle = "#333"; ctx.fillStyle = "#999"; ctx.lineWidth = 1;
  ctx.font = "10px system-ui, sans-serif"; ctx.textAlign = "right"; ctx.textBaseline = "middle";
  for (let v = scale.bottom; v <= scale.top + scale.step / 2; v += scale.step) {
    const y = plot.y + plot.h - (v - scale.bottom) / (scale.top - scale.bottom) * plot.h;
    ctx.beginPath(); ctx.moveTo(plot.x, y); ctx.lineTo(plot.x + plot.w, y); ctx.stroke();
    ctx.fillText(`${+v.toFixed(2)}`, plot.x - 4, y);
  }
  ctx.textBaseline = "top";
  for (let s = HISTORY_S; s >= 0; s -= 2) {
    // The end labels stay inside the plot's span: clear of the y labels and of the canvas edge.
    ctx.textAlign = s === 0 ? "right" : s === HISTORY_S ? "left" : "center";
    ctx.fillText(s === 0 ? endLabel : `−${s} s`, plot.x + plot.w * (1 - s / HISTORY_S), plot.y + plot.h + 3);
  }
}

function drawHistoryLegend(ctx, plot, names, colours) {
  ctx.font = "10px system-ui, sans-serif"; ctx.textBaseline = "middle"; ctx.textAlign = "left";
  ctx.fillStyle = "#999";
  ctx.fillText("N", 6, 7);
  let x = plot.x;
  names.forEach((name, k) => {
    ctx.fillStyle = colours[k]; ctx.fillRect(x, 4, 14, 3);
    ctx.fillStyle = "#ccc"; ctx.fillText(name, x + 18, 6);
    x += 26 + ctx.measureText(name).width;
  });
}

function drawHistory(panel) {
  const view = beginDraw(panel.history);
  if (!view) return;
  const { ctx, w, h } = view;
  const plot = { x: 34, y: 16, w: w - 42, h: h - 34 };
  const names = panel.kind === "grid" ? ["ΣF"] : ["Fz", "|Fxy|"];
  const colours = ["#ffb74d", "#4fc3f7"];
  const values = panel.series.flatMap(([, v]) => v).filter((v) => v !== null);
  const scale = niceScale(Math.min(0, ...values), Math.max(0, ...values));
  const endLabel = panel.stale ? "last frame" : "now";
  panel.history.dataset.top = scale.top;
  panel.history.dataset.end = endLabel;
  drawHistoryAxes(ctx, plot, scale, endLabel);
  drawHistoryLegend(ctx, plot, names, colours);
  if (panel.series.length < 2) return;
  const t1 = panel.series[panel.series.length - 1][0];
  names.forEach((_, k) => {
    ctx.strokeStyle = colours[k]; ctx.lineWidth = 1.5; ctx.beginPath();
    let gap = true; // the line starts anew after a null
    for (const [t, v] of panel.series) {
      if (v[k] === null) { gap = true; continue; }
      const x = plot.x + plot.w * (1 - (t1 - t) / HISTORY_S);
      const y = plot.y + plot.h - (v[k] - scale.bottom) / (scale.top - scale.bottom) * plot.h;
      if (gap) ctx.moveTo(x, y); else ctx.lineTo(x, y);
      gap = false;
    }
    ctx.stroke();
  });
}

// ---- the live stream --------------------------------------------------------

function render() {
  if (dirty) {
    const now = performance.now();
    for (const panel of panels.values()) {
      if (!panel.frame) continue;
      if (panel.kind === "grid") drawGrid(panel); else drawQuad(panel);
      updateFlags(panel, now);
      drawHistory(panel);
    }
    dirty = false;
  }
  requestAnimationFrame(render);
}

function onFrames(frames) {
  for (const frame of frames) {
    const panel = ensurePanel(frame.header.sensor_id, infoFromFrame(frame));
    panel.frame = frame;
    panel.frames += 1;
    panel.el.dataset.frames = panel.frames;
    recordHistory(panel);
  }
  dirty = true;
}

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws?max_rate=${STREAM_RATE_HZ}`);
  ws.onopen = () => { streamOpen = true; loadSensors(); };
  ws.onmessage = (event) => {
    const msg = JSON.parse(event.data);
    if (msg.type === "frames") onFrames(msg.frames);
  };
  ws.onclose = () => { streamOpen = false; setTimeout(connect, 1000); };
}

// The stream sends nothing for a silent sensor (a replay that has ended, a
// board gone quiet): a page opened meanwhile starts such a panel from the
// sensor's last seconds instead, as dense as the stream and with its fields.
async function loadRecent(panel) {
  panel.recentAsked = true;
  const address = panel.board === null ? panel.id : `${encodeURIComponent(panel.board)}/${panel.id}`;
  try {
    const answer = await fetch(`/sensors/${address}/history?seconds=${RECENT_S}` +
                               `&max_points=${RECENT_S * STREAM_RATE_HZ}&fields=force,sigma,contact,flags`);
    if (answer.status === 429) panel.recentAsked = false; // heavy reads are admitted at a bounded rate: the next poll asks again
    if (!answer.ok) return;
    const frames = await answer.json();
    if (!panel.frame) onFrames(frames); // unless the sensor has spoken again meanwhile
  } catch (err) {
    // The banner says when the service is unreachable.
  }
}

// ---- status banner --------------------------------------------------------

// The link's state; "up" only while its last data is younger than /health's stale threshold,
// whatever link.state says (a service may report up while the data has stopped).
function linkState(link) {
  const silent = link.last_data_age_s > (link.stale_after_s ?? STALE_AFTER_S);
  if (link.state) return link.state === "up" && silent ? "stale" : link.state;
  if (!link.up) return "down";
  return silent ? "stale" : "up";
}

// The board whose link is in the worst state (every board's part is under
// health.boards; a service before boards were named has one link at the top).
const LINK_RANK = { down: 0, stale: 1, finished: 2, up: 3 };

function worstLink(health) {
  const boards = Object.entries(health.boards || {});
  if (!boards.length) return ["", health.link || {}];
  const ranked = boards.map(([name, part]) => [name, part.link || {}]);
  ranked.sort((a, b) => (LINK_RANK[linkState(a[1])] ?? 3) - (LINK_RANK[linkState(b[1])] ?? 3));
  return [boards.length > 1 ? `board ${ranked[0][0]}: ` : "", ranked[0][1]];
}

// /health's problem lines, most severe first: a link down or board lost, then no data (a stale
// link or sensor, a sensor whose frames are dropped), then forces null or failing, then the
// rest (in /health's order).
const PROBLEM_RANKS = [/(^|: )(lost|link down)\b/, /(^|: )(link stale|sensor \S+ stale$|sensor \S+: \d+ frames dropped\b)/,
  /\bnull\b|\bfails\b/];

function problemRank(text) {
  const rank = PROBLEM_RANKS.findIndex((pattern) => pattern.test(text));
  return rank < 0 ? PROBLEM_RANKS.length : rank;
}

function rankedProblems(health) {
  const problems = health.status === "degraded" ? health.problems || [] : [];
  return [...problems].sort((a, b) => problemRank(a) - problemRank(b));
}

function describeStatus(health) {
  const [which, link] = worstLink(health);
  const source = link.source ? ` · ${link.source}` : "";
  const age = link.last_data_age_s == null ? "" : ` for ${link.last_data_age_s.toFixed(1)} s`;
  const state = linkState(link);
  if (state === "finished") return ["finished", `Replay finished: the recording has ended, showing its last frames${source}`];
  if (state === "down") {
    const reconnects = link.reconnects ? ` · ${link.reconnects} reconnects` : "";
    return ["down", `${which}Link down · last error: ${link.last_error || "none reported"}${reconnects}${source}`];
  }
  if (state === "stale") return ["stale", `${which}Stale: no data${age}${source}`];
  if (!streamOpen) return ["stale", `Live stream disconnected, reconnecting…${source}`];
  // Degraded with the link up: say why (the most severe problem, and how many more: all are listed below).
  const problems = rankedProblems(health);
  const why = problems.length ? ` · ${problems[0]}${problems.length > 1 ? ` (+${problems.length - 1} more)` : ""}` : "";
  const degraded = health.status === "degraded" ? ` (service degraded${why})` : "";
  if (health.replay) return ["replay", `Replay${degraded}${source}`];
  return [degraded ? "degraded" : "ok", `Live${degraded}${source}`];
}

function showStatus(state, text) {
  const banner = document.getElementById("status");
  banner.dataset.state = state;
  banner.textContent = text;
}

// Every problem /health names, most severe first (the banner has room for one).
function showProblems(problems) {
  const list = document.getElementById("problems");
  list.hidden = !problems.length;
  list.querySelector("summary").textContent = `${problems.length} problem${problems.length === 1 ? "" : "s"}, most severe first`;
  list.querySelector("ol").replaceChildren(...problems.map((text) => element("li", "", text)));
}

// A sensor /health calls stale: its last values greyed, its age said, its history ending at its last frame.
function showStale(panel, stale, ageS) {
  const text = !stale ? "" : `stale${ageS == null ? "" : ` · last frame ${ageS.toFixed(1)} s ago`}`;
  if (stale === panel.stale && text === panel.staleMark.textContent) return;
  panel.stale = stale;
  panel.el.classList.toggle("stale", stale);
  panel.staleMark.hidden = !stale;
  panel.staleMark.textContent = text;
  dirty = true;
}

// The link of a sensor's board (a service before boards were named has one, at the top).
function boardLink(health, board) {
  return ((health.boards || {})[board] || {}).link || health.link || {};
}

function statsText(health) {
  const sensors = Object.entries(health.sensors || {});
  const parts = Object.values(health.boards || {});
  const stream = parts.length ? parts.reduce((sum, part) => {
    for (const [k, v] of Object.entries(part.stream || {})) if (typeof v === "number") sum[k] = (sum[k] || 0) + v;
    return sum;
  }, {}) : health.stream || {};
  const p99 = health.latency && health.latency.published ? health.latency.published.p99_ms : null;
  return [
    ...sensors.map(([id, s]) => `#${id} ${s.rate_hz} Hz`),
    stream.crc_errors === undefined ? "" : `CRC errors ${stream.crc_errors}`,
    stream.bytes_discarded === undefined ? "" : `discarded ${stream.bytes_discarded} B`,
    sensors.length ? `gaps ${sensors.reduce((n, [, s]) => n + (s.seq_gaps || 0), 0)}` : "",
    p99 == null ? "" : `latency p99 ${p99.toFixed(1)} ms`,
  ].filter(Boolean).join(" · ");
}

// ---- recording ------------------------------------------------------------

const recordButton = document.getElementById("record");

function showRecording(status, error) {
  const info = document.getElementById("record-info");
  const active = Boolean(status && status.active);
  recordButton.textContent = active ? "Stop recording" : "Record";
  recordButton.classList.toggle("recording", active);
  info.hidden = !(status || error);
  info.classList.toggle("error", Boolean(error || (status && status.error)));
  if (error) {
    document.getElementById("record-label").textContent = `Record failed: ${error}`;
    document.getElementById("record-path").textContent = "";
    return;
  }
  if (!status) return;
  const messages = status.messages === undefined ? "" : ` (${status.messages} msgs)`;
  document.getElementById("record-label").textContent =
    (active ? "● Recording" : "Saved") + messages + (status.error ? ` · ${status.error} ·` : "") + " to";
  document.getElementById("record-path").textContent = status.path;
}

// The API's detail of a refusal, as text (a detail may be a string, an object or a list).
async function errorText(response) {
  let detail;
  try { detail = (await response.json()).detail; } catch (err) { return response.statusText; }
  if (!detail) return response.statusText;
  return typeof detail === "string" ? detail : detail.error || JSON.stringify(detail);
}

function post(path, body) {
  return fetch(path, { method: "POST", headers: { "Content-Type": "application/json", ...authHeaders },
                       body: body === undefined ? undefined : JSON.stringify(body) });
}

// The service writes a bare name into its recordings directory; one that
// predates names requires {"path"} (422) and writes relative to its own
// directory: it is asked by path from then on, sparing a failed request each time.
let recordByPath = false;

async function startRecording() {
  const name = `recording-${new Date().toISOString().replace(/[:.]/g, "-")}.mcap`;
  if (!recordByPath) {
    const response = await post("/record/start", { name });
    if (response.status !== 422) return response;
    recordByPath = true;
  }
  return post("/record/start", { path: name });
}

async function toggleRecording() {
  recordButton.disabled = true;
  try {
    const current = await (await fetch("/record")).json();
    const response = current && current.active ? await post("/record/stop") : await startRecording();
    if (response.ok) showRecording(await response.json());
    else showRecording(null, await errorText(response));
  } catch (err) {
    showRecording(null, "service unreachable");
  } finally {
    recordButton.disabled = false;
  }
}

// ---- polling ----------------------------------------------------------------

async function pollHealth() {
  let health;
  try {
    health = await (await fetch("/health")).json();
  } catch (err) {
    showStatus("down", "Service unreachable: the dashboard cannot reach the tactile service");
    return;
  }
  showStatus(...describeStatus(health));
  showProblems(rankedProblems(health));
  document.getElementById("stats").textContent = statsText(health);
  for (const [id, sensor] of Object.entries(health.sensors || {})) {
    const panel = panels.get(sensorKey(sensor.board, sensor.id ?? Number(id)));
    if (!panel) continue;
    showCalibration(panel, sensor.calibration, sensor.fatigue, sensor);
    // A finished replay's sensors are all silent: the banner says so, their last frames are what is shown.
    const finished = linkState(boardLink(health, sensor.board)) === "finished";
    showStale(panel, Boolean(sensor.stale) && !finished, sensor.last_frame_age_s);
    if (sensor.stale && !panel.frame && !panel.recentAsked) loadRecent(panel);
  }
  const recording = "recording" in health ? health.recording : await (await fetch("/record")).json();
  if (recording) showRecording(recording);
}

// ---- tare -------------------------------------------------------------------

const tareButton = document.getElementById("tare");

function showTare(text, error) {
  const info = document.getElementById("tare-info");
  info.hidden = false;
  info.textContent = text;
  info.classList.toggle("error", error);
}

// The sensors shown, in page order, as a tare's answer names them: board/id with several boards, else the id.
function shownSensorNames() {
  const shown = [...document.querySelectorAll("section.panel")];
  const several = new Set(shown.map((p) => p.dataset.board)).size > 1;
  return shown.map((p) => (several ? `${p.dataset.board}/${p.dataset.sensor}` : p.dataset.sensor));
}

// What a tare did ({tared, frames, note?}): the sensors tared, and those shown that were not.
function tareOutcome(answer) {
  const tared = (answer.tared || []).map(String);
  const untouched = shownSensorNames().filter((name) => !tared.includes(name));
  return [`Tared ${tared.length ? `sensors ${tared.join(", ")}` : "no sensor"}`,
          untouched.length ? `not tared: ${untouched.join(", ")}` : "", answer.note || ""].filter(Boolean).join(" · ");
}

function postTare(query) {
  return fetch(`/tare${query}`, { method: "POST", headers: authHeaders });
}

// A tare with taxels loaded against their calibration's C0 is refused (409):
// say which, and tare anyway only if the user confirms the load is the zero.
// Returns the forced tare's answer, or null when the user declined (said so).
async function tareLoaded(refusal) {
  const detail = (await refusal.clone().json()).detail;
  if (typeof detail === "string" || !detail || !detail.loaded_taxels) return refusal; // e.g. a gateway's board: tare it on its service
  const loaded = Object.entries(detail.loaded_taxels).map(([s, t]) => `sensor ${s}: taxels ${t.join(", ")}`);
  if (window.confirm(`These taxels read loaded, so a tare would make the load their zero:\n${loaded.join("\n")}\n\nTare anyway?`))
    return postTare("?force=true");
  showTare(`Not tared: ${loaded.join("; ")} read loaded`, true);
  return null;
}

// Every answer is said: which sensors were tared (and which not), or why none was.
async function tare() {
  tareButton.disabled = true;
  try {
    let answer = await postTare("");
    if (answer.status === 409) answer = await tareLoaded(answer);
    if (!answer) return;
    if (answer.ok) showTare(tareOutcome(await answer.json()), false);
    else showTare(`Tare failed (${answer.status}): ${await errorText(answer)}`, true);
  } catch (err) {
    showTare("Tare failed: service unreachable", true);
  } finally {
    tareButton.disabled = false;
  }
}

tareButton.addEventListener("click", tare);
recordButton.addEventListener("click", toggleRecording);

loadSensors().then(pollHealth); // the panels first: the first poll fills those of silent sensors
connect();
setInterval(pollHealth, 1000);
requestAnimationFrame(render);
