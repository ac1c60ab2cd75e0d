"use strict";
// Live dashboard: one panel per sensor, drawn at the display rate from the
// latest frame of each sensor (the stream is decimated server-side).

const panels = new Map();
const GRID_MAX_N = 5;      // colour scale top, newtons per taxel
const QUAD_MAX_N = 10;     // arrow and bar scale, newtons

function heatColour(f) {
  const x = Math.max(0, Math.min(1, f / GRID_MAX_N));
  const r = Math.round(255 * Math.min(1, 2 * x));
  const g = Math.round(255 * Math.max(0, 2 * x - 1));
  const b = Math.round(80 * (1 - x));
  return `rgb(${r},${g},${b})`;
}

function makePanel(frame) {
  const el = document.createElement("section");
  el.className = "panel";
  el.dataset.sensor = frame.sensor;
  el.dataset.kind = frame.kind;
  const title = document.createElement("h2");
  title.textContent = `sensor ${frame.sensor} · ${frame.kind}` + (frame.kind === "grid" ? ` ${frame.rows}×${frame.cols}` : "");
  const canvas = document.createElement("canvas");
  const cell = 44;
  canvas.width = frame.kind === "grid" ? frame.cols * cell : 320;
  canvas.height = frame.kind === "grid" ? frame.rows * cell : 240;
  const meta = document.createElement("div");
  meta.className = "meta";
  el.append(title, canvas, meta);
  document.getElementById("sensors").append(el);
  const panel = { el, canvas, meta, cell, frame, changes: 0 };
  panels.set(frame.sensor, panel);
  return panel;
}

function drawGrid(panel) {
  const { canvas, cell, frame } = panel;
  const ctx = canvas.getContext("2d");
  ctx.font = "11px system-ui";
  ctx.textAlign = "center";
  ctx.textBaseline = "middle";
  let total = 0;
  frame.taxels_N.forEach((f, i) => {
    const r = Math.floor(i / frame.cols), c = i % frame.cols;
    ctx.fillStyle = f === null ? "#444" : heatColour(f);
    ctx.fillRect(c * cell + 1, r * cell + 1, cell - 2, cell - 2);
    ctx.fillStyle = f !== null && f > GRID_MAX_N * 0.6 ? "#000" : "#ddd";
    ctx.fillText(f === null ? "—" : f.toFixed(2), c * cell + cell / 2, r * cell + cell / 2);
    if (f !== null && f > 0) total += f;
  });
  panel.meta.textContent = `seq ${frame.seq} · ΣF ${total.toFixed(2)} N` + (frame.flags.length ? ` · ${frame.flags.join(", ")}` : "");
}

function drawQuad(panel) {
  const { canvas, frame } = panel;
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const [fx, fy, fz] = frame.fxyz_N;
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

let dirty = false;
function render() {
  if (dirty) {
    for (const panel of panels.values()) {
      if (panel.frame.kind === "grid") drawGrid(panel); else drawQuad(panel);
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
      const panel = panels.get(frame.sensor) || makePanel(frame);
      panel.frame = frame;
      panel.changes += 1;
      panel.el.dataset.frames = panel.changes;
    }
    dirty = true;
  };
  ws.onclose = () => setTimeout(connect, 1000);
}

async function pollHealth() {
  try {
    const health = await (await fetch("/health")).json();
    const link = document.getElementById("link");
    link.textContent = health.link.up ? `link up · ${health.link.source}` : `link down · ${health.link.last_error || ""}`;
    link.className = "badge " + (health.link.up ? "up" : "down");
    const rates = Object.entries(health.sensors).map(([id, s]) => `#${id} ${s.rate_hz} Hz`).join(" · ");
    document.getElementById("stats").textContent =
      `${rates} · CRC errors ${health.stream.crc_errors} · discarded ${health.stream.bytes_discarded} B` +
      (health.replay ? " · REPLAY" : "");
    const rec = health.recording;
    recordButton.textContent = rec && rec.active ? `Stop recording (${rec.messages} msgs)` : "Record";
    recordButton.title = rec && rec.error ? rec.error : "";
  } catch (err) {
    document.getElementById("link").textContent = "service unreachable";
  }
}

document.getElementById("tare").addEventListener("click", () => fetch("/tare", { method: "POST" }));

const recordButton = document.getElementById("record");
recordButton.addEventListener("click", async () => {
  const status = await (await fetch("/record")).json();
  if (status && status.active) {
    await fetch("/record/stop", { method: "POST" });
  } else {
    const stamp = new Date().toISOString().replace(/[:.]/g, "-");
    await fetch("/record/start", { method: "POST", headers: { "Content-Type": "application/json" },
                                   body: JSON.stringify({ path: `tactile-${stamp}.mcap` }) });
  }
  pollHealth();
});
connect();
pollHealth();
setInterval(pollHealth, 1000);
requestAnimationFrame(render);
