// Roost flight records: the Missions' bundles, and one flight plotted in SVG.
// The server parses the tlog (pymavlink) and sends small series; this only draws.
"use strict";
const COLOURS = ["#4aa3ff", "#ff9f43", "#a3e635", "#f472b6"];
const LEVELS = ["OK", "WARN", "STARTING", "ERROR", "STALE"];
const SVG = "http://www.w3.org/2000/svg";
const state = { bundles: [], manifest: null, plot: null };
window.__roostRecords = state;

function el(tag, attrs, parent, text) {
  const node = document.createElementNS(tag === "tr" || tag === "td" || tag === "li" ? "http://www.w3.org/1999/xhtml" : SVG, tag);
  for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, v);
  if (text !== undefined) node.textContent = text;
  if (parent) parent.appendChild(node);
  return node;
}

async function getJSON(url) {
  const answer = await fetch(url, { cache: "no-store" });
  const doc = await answer.json();
  if (!answer.ok) throw new Error(doc.error || answer.statusText);
  return doc;
}

function showError(error) {
  document.getElementById("records-error").textContent = error ? String(error.message || error) : "";
}

async function loadBundles() {
  try {
    state.bundles = (await getJSON("/api/records")).bundles;
    showError(null);
  } catch (error) { showError(error); return; }
  const body = document.querySelector("#bundles tbody");
  body.replaceChildren();
  for (const bundle of state.bundles) {
    const row = el("tr", { "data-bundle": bundle.bundle }, body);
    const mission = bundle.mission || {};
    el("td", {}, row, `${mission.namespace}/${mission.name}`);
    el("td", { class: "state" }, row, bundle.state);
    el("td", {}, row, (mission.completionTime || "").replace("T", " ").slice(0, 19));
    el("td", {}, row, String((bundle.vehicles || []).length));
    row.addEventListener("click", () => selectBundle(bundle.bundle));
  }
}

async function selectBundle(name) {
  for (const row of document.querySelectorAll("#bundles tbody tr")) {
    row.classList.toggle("selected", row.dataset.bundle === name);
  }
  try { state.manifest = await getJSON(`/api/records/${encodeURIComponent(name)}`); showError(null); }
  catch (error) { showError(error); return; }
  document.getElementById("flights-title").hidden = false;
  const list = document.getElementById("flights");
  list.replaceChildren();
  for (const flight of state.manifest.flights || []) {
    const item = el("li", { "data-flight": flight.flightId }, list,
      `${flight.vehicle}: ${flight.flightId} (${flight.state})`);
    item.addEventListener("click", () => selectFlight(name, flight.flightId));
  }
  const missing = document.getElementById("missing");
  missing.replaceChildren();
  for (const gap of state.manifest.missing || []) {
    el("li", {}, missing, `missing ${[gap.vehicle, gap.flightId, gap.path].filter(Boolean).join("/")}: ${gap.reason}`);
  }
}

async function selectFlight(bundle, flight) {
  for (const item of document.querySelectorAll("#flights li")) {
    item.classList.toggle("selected", item.dataset.flight === flight);
  }
  document.getElementById("plot-title").textContent = `${flight}: loading…`;
  try {
    state.plot = await getJSON(`/api/records/${encodeURIComponent(bundle)}/plot?flight=${encodeURIComponent(flight)}`);
    showError(null);
  } catch (error) { showError(error); return; }
  draw(state.plot);
}

function extent(values, floor) {
  let lo = Infinity, hi = -Infinity;
  for (const v of values) { if (v < lo) lo = v; if (v > hi) hi = v; }
  if (!isFinite(lo)) { lo = 0; hi = 1; }
  if (floor !== undefined) lo = Math.min(lo, floor);
  return hi > lo ? [lo, hi] : [lo, lo + 1];
}

function drawChart(svg, plot, key, tMax) {
  svg.replaceChildren();
  const [lo, hi] = extent(plot.autopilots.flatMap((a) => a[key]), 0);
  const x = (t) => (t / tMax) * 1000;
  const y = (v) => 175 - ((v - lo) / (hi - lo)) * 170;
  el("text", { x: 4, y: 12, class: "mode" }, svg, `${hi.toFixed(1)}`);
  plot.autopilots.forEach((ap, i) => {
    const points = ap.t.map((t, j) => `${x(t).toFixed(1)},${y(ap[key][j]).toFixed(1)}`).join(" ");
    el("polyline", { class: `series ap-${i}`, points, stroke: COLOURS[i % COLOURS.length], "data-autopilot": ap.name }, svg);
  });
  for (const marker of plot.markers) {
    const line = el("line", { class: `marker ${marker.kind}`, x1: x(marker.t), x2: x(marker.t), y1: 0, y2: 180 }, svg);
    el("title", {}, line, `${marker.kind}: ${marker.message || marker.reason || ""}`);
  }
}

function drawBands(svg, plot, tMax) {
  svg.replaceChildren();
  const x = (t) => (t / tMax) * 1000;
  const rows = plot.autopilots.length || 1;
  const height = 110 / rows;
  plot.autopilots.forEach((ap, i) => {
    const top = i * height;
    ap.modes.forEach((mode, j) => {
      const end = j + 1 < ap.modes.length ? ap.modes[j + 1].t : tMax;
      el("rect", { class: "mode", x: x(mode.t), y: top, width: Math.max(x(end) - x(mode.t), 1), height: height / 2 }, svg);
      el("text", { class: "mode", x: x(mode.t) + 3, y: top + height / 2 - 4, "data-mode": mode.mode }, svg, mode.mode);
    });
    const levels = plot.health.filter((h) => h.autopilot === ap.name);
    levels.forEach((h, j) => {
      const end = j + 1 < levels.length ? levels[j + 1].t : tMax;
      const level = LEVELS.includes(h.level) ? h.level : "unknown";
      el("rect", { class: `health lvl-${level}`, "data-level": h.level, x: x(h.t), y: top + height / 2, width: Math.max(x(end) - x(h.t), 1), height: height / 2 - 2 }, svg);
    });
  });
}

function drawTrajectory(svg, plot) {
  svg.replaceChildren();
  const norths = plot.autopilots.flatMap((a) => a.north), easts = plot.autopilots.flatMap((a) => a.east);
  const [n0, n1] = extent(norths), [e0, e1] = extent(easts);
  const span = Math.max(n1 - n0, e1 - e0, 10) * 1.2;
  const cx = (e0 + e1) / 2, cy = -(n0 + n1) / 2;
  svg.setAttribute("viewBox", `${cx - span / 2} ${cy - span / 2} ${span} ${span}`);
  plot.autopilots.forEach((ap, i) => {
    const points = ap.east.map((e, j) => `${e.toFixed(2)},${(-ap.north[j]).toFixed(2)}`).join(" ");
    el("polyline", { class: `series ap-${i}`, points, stroke: COLOURS[i % COLOURS.length], "data-autopilot": ap.name }, svg);
  });
}

function draw(plot) {
  const tMax = Math.max(1, ...plot.autopilots.flatMap((a) => a.t), ...plot.markers.map((m) => m.t), ...plot.health.map((h) => h.t));
  document.getElementById("plot-title").textContent = `${plot.vehicle}: ${plot.flight} (${plot.state})`;
  const legend = document.getElementById("legend");
  legend.replaceChildren();
  plot.autopilots.forEach((ap, i) => {
    const span = document.createElement("span");
    span.style.color = COLOURS[i % COLOURS.length];
    span.textContent = `■ ${ap.name}`;
    legend.appendChild(span);
  });
  drawChart(document.getElementById("alt"), plot, "alt", tMax);
  drawChart(document.getElementById("speed"), plot, "speed", tMax);
  drawBands(document.getElementById("bands"), plot, tMax);
  drawTrajectory(document.getElementById("trajectory"), plot);
  const list = document.getElementById("markers");
  list.replaceChildren();
  for (const marker of plot.markers) {
    const item = document.createElement("li");
    item.className = `marker-item ${marker.kind}`;
    item.textContent = `t+${marker.t.toFixed(1)} s ${marker.kind}${marker.autopilot ? " (" + marker.autopilot + ")" : ""}: ${marker.message || marker.reason || ""}`;
    list.appendChild(item);
  }
}

loadBundles();
