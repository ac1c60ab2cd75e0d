"use strict";
// Live dashboard: one panel per sensor, drawn at the display rate from the
// latest frame of each sensor (the stream is decimated server-side), plus a
// force-history plot (total grid force, quad Fz and |Fxy|) over 10 s.

const panels = new Map();
const GRID_MAX_N = 5;      // colour scale top, newtons per taxel
const QUAD_MAX_N = 10;     // arrow and bar scale, newtons
const HISTORY_S = 10;
const token = new URLSearchParams(location.search).get("token");
const authHeaders = token ? { Authorization: `Bearer ${token}` } : {};

function heatColour(f) {
  const x = Math.max(0, Math.min(1, f / GRID_MAX_N));
  const r = Math.round(255 * Math.min(1, 2 * x));
  const g = Math.round(255 * Math.max(0, 2 * x - 1));
  const b = Math.round(80 * (1 - x));
  return `rgb(${r},${g},${b})`;
}

function makePanel(frame) {
  const h = frame.header;
  const el = document.createElement("section");
  el.className = "panel";
  el.dataset.sensor = h.sensor_id;
  el.dataset.kind = h.kind;
  const title = document.createElement("h2");
  title.textContent = `${h.sensor_name} · ${h.kind}` + (h.kind === "grid" ? ` ${frame.rows}×${frame.cols}` : "");
  const canvas = document.createElement("canvas");
  canvas.className = "live";
  const cell = 44;
  canvas.width = h.kind === "grid" ? frame.cols * cell : 320;
  canvas.height = h.kind === "grid" ? frame.rows * cell : 240;
  const history = document.createElement("canvas");
  history.className = "history";
  history.width = canvas.width;
  history.height = 90;
  const meta = document.createElement("div");
  meta.className = "meta";
  el.append(title, canvas, history, meta);
  document.getElementById("sensors").append(el);
  const panel = { el, canvas, history, meta, cell, frame, changes: 0, series: [] };
  panels.set(h.sensor_id, panel);
  return panel;
}

function drawGrid(panel) {
  const { canvas, cell, frame } = panel;
  const ctx = canvas.getContext("2d");
  const flags = frame.taxel_flags || {};
  const flagged = (name, i) => (flags[name] || []).includes(i);
  ctx.font = "11px system-ui";
  ctx.textAlign = "center";
  ctx.textBaseline = "middle";
  const threshold = 0.05;
  frame.force_N.forEach((f, i) => {
    const r = Math.floor(i / frame.cols), c = i % frame.cols;
    ctx.fillStyle = f === null ? "#444" : heatColour(f);
    ctx.fillRect(c * cell + 1, r * cell + 1, cell - 2, cell - 2);
    ctx.fillStyle = f !== null && f > GRID_MAX_N * 0.6 ? "#000" : "#ddd";
    ctx.fillText(f === null ? "—" : f.toFixed(2), c * cell + cell / 2, r * cell + cell / 2);
    const mark = flagged("saturated", i) ? "S" : flagged("out_of_range", i) ? "R" : flagged("crosstalk_corrected", i) ? "x"
      : flagged("stale", i) ? "?" : "";
    if (mark) { ctx.fillStyle = "#ff5252"; ctx.fillText(mark, c * cell + cell - 8, r * cell + 9); }
  });
  // Contact outlines: edges between a loaded taxel and one that is not.
  const loaded = (r, c) => r >= 0 && c >= 0 && r < frame.rows && c < frame.cols &&
    frame.force_N[r * frame.cols + c] !== null && frame.force_N[r * frame.cols + c] > threshold;
  ctx.strokeStyle = "#00e5ff"; ctx.lineWidth = 2; ctx.beginPath();
  for (let r = 0; r < frame.rows; r++) for (let c = 0; c < frame.cols; c++) {
    if (!loaded(r, c)) continue;
    const x = c * cell, y = r * cell;
    if (!loaded(r - 1, c)) { ctx.moveTo(x, y); ctx.lineTo(x + cell, y); }
    if (!loaded(r + 1, c)) { ctx.moveTo(x, y + cell); ctx.lineTo(x + cell, y + cell); }
    if (!loaded(r, c - 1)) { ctx.moveTo(x, y); ctx.lineTo(x, y + cell); }
    if (!loaded(r, c + 1)) { ctx.moveTo(x + cell, y); ctx.lineTo(x + cell, y + cell); }
  }
  ctx.stroke(); ctx.lineWidth = 1;
  const contact = frame.contact;
  if (contact && contact.cop_x_mm !== null) {
    // Array frame: origin at the centre, 4 mm pitch, x along columns, y along rows.
    const px = (contact.cop_x_mm / 4 + (frame.cols - 1) / 2 + 0.5) * cell;
    const py = (contact.cop_y_mm / 4 + (frame.rows - 1) / 2 + 0.5) * cell;
    ctx.strokeStyle = "#fff"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(px, py, 7, 0, 2 * Math.PI); ctx.moveTo(px - 11, py); ctx.lineTo(px + 11, py);
    ctx.moveTo(px, py - 11); ctx.lineTo(px, py + 11); ctx.stroke(); ctx.lineWidth = 1;
  }
  const total = contact ? contact.total_N : 0;
  panel.meta.textContent = `seq ${frame.header.seq} · ΣF ${total.toFixed(2)} N · contacts ${contact ? contact.contacts : 0}` +
    (frame.flags.length ? ` · ${frame.flags.join(", ")}` : "");
}

function drawQuad(panel) {
  const { canvas, frame } = panel;
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const { x: fx, y: fy, z: fz } = frame.wrench.force;
  const cx = 120, cy = 120, radius = 100;
  ctx.strokeStyle = "#555";
  ctx.beginPath(); ctx.arc(cx, cy, radius, 0, 2 * Math.PI); ctx.stroke();
  ctx.beginPath(); ctx.moveTo(cx - radius, cy); ctx.lineTo(cx + radius, cy); ctx.moveTo(cx, cy - radius); ctx.lineTo(cx, cy + radius); ctx.stroke();
  if (fx !== null && fy !== null) {
    const ex = cx + (fx / QUAD_MAX_N) * radius, ey = cy - (fy / QUAD_MAX_N) * radius;
    ctx.strokeStyle = "#4fc3f7"; ctx.lineWidth = 4;
    ctx.beginPath(); ctx.moveTo(cx, cy); ctx.lineTo(ex, ey); ctx.stroke();
    ctx.lineWidth = 1;
  }
  const barX = 260, barH = 200, top = 20;
  ctx.strokeStyle = "#555"; ctx.strokeRect(barX, top, 30, barH);
  if (fz !== null) {
    const h = Math.max(0, Math.min(1, fz / (2 * QUAD_MAX_N))) * barH;
    ctx.fillStyle = "#ffb74d"; ctx.fillRect(barX, top + barH - h, 30, h);
  }
  ctx.fillStyle = "#ddd"; ctx.font = "12px system-ui";
  ctx.fillText("Fz", barX + 8, top + barH + 15);
  const fmt = v => (v === null ? "—" : v.toFixed(2));
  panel.meta.textContent = `Fx ${fmt(fx)} · Fy ${fmt(fy)} · Fz ${fmt(fz)} N` + (frame.flags.length ? ` · ${frame.flags.join(", ")}` : "");
}

function record(panel) {
  const f = panel.frame;
  const t = f.header.stamp;
  const values = f.header.kind === "grid" ? [f.contact ? f.contact.total_N : 0]
    : [f.wrench.force.z || 0, Math.hypot(f.wrench.force.x || 0, f.wrench.force.y || 0)];
  panel.series.push([t, values]);
  while (panel.series.length && panel.series[0][0] < t - HISTORY_S) panel.series.shift();
}

function drawHistory(panel) {
  const { history, series } = panel;
  const ctx = history.getContext("2d");
  ctx.clearRect(0, 0, history.width, history.height);
  if (series.length < 2) return;
  const t1 = series[series.length - 1][0], t0 = t1 - HISTORY_S;
  const top = Math.max(1, ...series.flatMap(([, v]) => v));
  const colours = ["#ffb74d", "#4fc3f7"];
  series[0][1].forEach((_, k) => {
    ctx.strokeStyle = colours[k]; ctx.beginPath();
    series.forEach(([t, v], i) => {
      const x = ((t - t0) / HISTORY_S) * history.width, y = history.height - 4 - (v[k] / top) * (history.height - 8);
      if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    });
    ctx.stroke();
  });
  ctx.fillStyle = "#999"; ctx.font = "10px system-ui";
  ctx.fillText(`${top.toFixed(1)} N · last ${HISTORY_S} s`, 4, 11);
}

let dirty = false;
function render() {
  if (dirty) {
    for (const panel of panels.values()) {
      if (panel.frame.header.kind === "grid") drawGrid(panel); else drawQuad(panel);
      drawHistory(panel);
    }
    dirty = false;
  }
  requestAnimationFrame(render);
}

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws?max_rate=30`);
  ws.onmessage = (event) => {
    const msg = JSON.parse(event.data);
    if (msg.type !== "frames") return;
    for (const frame of msg.frames) {
      const panel = panels.get(frame.header.sensor_id) || makePanel(frame);
      panel.frame = frame;
      panel.changes += 1;
      panel.el.dataset.frames = panel.changes;
      record(panel);
    }
    dirty = true;
  };
  ws.onclose = () => setTimeout(connect, 1000);
}

const recordButton = document.getElementById("record");

async function pollHealth() {
  try {
    const health = await (await fetch("/health")).json();
    const link = document.getElementById("link");
    link.textContent = health.link.up ? `link up · ${health.link.source}` : `link down · ${health.link.last_error || ""}`;
    link.className = "badge " + (health.link.up ? "up" : "down");
    const rates = Object.entries(health.sensors).map(([id, s]) => `#${id} ${s.rate_hz} Hz`).join(" · ");
    document.getElementById("stats").textContent =
      `${rates} · CRC errors ${health.stream.crc_errors} · discarded ${health.stream.bytes_discarded} B · gaps ` +
      Object.values(health.sensors).reduce((n, s) => n + (s.seq_gaps || 0), 0) +
      (health.latency.published.p99_ms === null ? "" : ` · latency p99 ${health.latency.published.p99_ms.toFixed(1)} ms`) +
      (health.replay ? " · REPLAY" : "");
    const rec = health.recording;
    recordButton.textContent = rec && rec.active ? `Stop recording (${rec.messages} msgs)` : "Record";
    recordButton.title = rec && rec.error ? rec.error : "";
  } catch (err) {
    document.getElementById("link").textContent = "service unreachable";
  }
}

document.getElementById("tare").addEventListener("click", () => fetch("/tare", { method: "POST", headers: authHeaders }));

recordButton.addEventListener("click", async () => {
  const status = await (await fetch("/record")).json();
  if (status && status.active) {
    await fetch("/record/stop", { method: "POST", headers: authHeaders });
  } else {
    const stamp = new Date().toISOString().replace(/[:.]/g, "-");
    await fetch("/record/start", { method: "POST", headers: { "Content-Type": "application/json", ...authHeaders },
                                   body: JSON.stringify({ path: `tactile-${stamp}.mcap` }) });
  }
  pollHealth();
});

connect();
pollHealth();
setInterval(pollHealth, 1000);
requestAnimationFrame(render);
