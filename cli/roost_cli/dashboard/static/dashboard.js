// Roost fleet dashboard: renders the documents the server pushes on /ws (at most 10 a
// second). Plain DOM and SVG, keyed by vehicle, so a document changes only what changed.
// window.__roost keeps measurements the browser tests and the benchmark read:
// frames (ms spent applying each document) and latencies (ms from an agent's sample to
// the DOM showing it).
"use strict";

const R = (window.__roost = { frames: [], latencies: [], documents: 0, doc: null });
const KEEP = 2000;
const SVG = "http://www.w3.org/2000/svg";
const $ = (id) => document.getElementById(id);
const LEVEL_CLASS = (level) =>
  ["OK", "WARN", "STARTING", "ERROR", "STALE"].includes(level) ? `lvl-${level}` : "lvl-unknown";

function el(tag, attrs = {}, text) {
  const node = tag.startsWith("svg:")
    ? document.createElementNS(SVG, tag.slice(4))
    : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (text !== undefined) node.textContent = text;
  return node;
}

function setText(node, text) {
  if (node.textContent !== text) node.textContent = text;
}

function setAttr(node, name, value) {
  const v = String(value);
  if (node.getAttribute(name) !== v) node.setAttribute(name, v);
}

// ---- arena ----------------------------------------------------------------------------
let view = null; // current viewBox [x, y, w, h], widened as vehicles move, never jittering

function fencePoints(f) {
  // The points that bound a fence in the arena: its vertices, or its circle's box.
  if (f.circle) {
    const [n, e, r] = f.circle;
    return [[n - r, e - r], [n + r, e + r]];
  }
  return f.polygon || [];
}

function fitArena(vehicles, fences) {
  let minX = -10, maxX = 10, minY = -10, maxY = 10;
  const points = vehicles.flatMap((v) => v.trail || []);
  for (const f of fences) points.push(...fencePoints(f));
  for (const [n, e] of points) {
    minX = Math.min(minX, e); maxX = Math.max(maxX, e);
    minY = Math.min(minY, -n); maxY = Math.max(maxY, -n);
  }
  const pad = 5;
  const size = Math.max(maxX - minX, maxY - minY) + 2 * pad;
  const cx = (minX + maxX) / 2, cy = (minY + maxY) / 2;
  const wanted = [cx - size / 2, cy - size / 2, size, size];
  const inside = view && wanted[0] >= view[0] && wanted[1] >= view[1] &&
    wanted[0] + size <= view[0] + view[2] && wanted[1] + size <= view[1] + view[3] &&
    size > view[2] / 3;
  if (!inside) {
    view = wanted.map((x) => Math.round(x));
    $("arena").setAttribute("viewBox", view.join(" "));
    drawGrid();
  }
}

function drawGrid() {
  const grid = $("grid");
  grid.replaceChildren();
  const [x, y, w] = view;
  const step = w > 200 ? 50 : w > 80 ? 20 : w > 30 ? 10 : 5;
  for (let gx = Math.ceil(x / step) * step; gx <= x + w; gx += step) {
    grid.append(el("svg:line", { x1: gx, x2: gx, y1: y, y2: y + w }));
    if (gx > x + step / 2) grid.append(el("svg:text", { x: gx + 0.2, y: y + w - 0.3 }, `${gx} E`));
  }
  for (let gy = Math.ceil(y / step) * step; gy <= y + w; gy += step) {
    grid.append(el("svg:line", { x1: x, x2: x + w, y1: gy, y2: gy }));
    grid.append(el("svg:text", { x: x + 0.2, y: gy - 0.2 }, `${-gy} N`));
  }
  drawTiles();
}

let tileOrigin = null;
function drawTiles() {
  // Optional background for an outdoor field: XYZ tiles from the URL given with --tiles
  // (a local tile server). Nothing is fetched when no URL was given.
  const tiles = $("tiles");
  tiles.replaceChildren();
  if (!window.ROOST.tiles || !tileOrigin || !view) return;
  const z = 19, lat = tileOrigin.lat, lon = tileOrigin.lon;
  const n = 2 ** z;
  const tx = ((lon + 180) / 360) * n;
  const rad = (lat * Math.PI) / 180;
  const ty = ((1 - Math.log(Math.tan(rad) + 1 / Math.cos(rad)) / Math.PI) / 2) * n;
  const metres = (40075016.686 * Math.cos(rad)) / n; // one tile's width at this latitude
  const [x, y, w] = view;
  for (let i = Math.floor(tx + x / metres); i <= tx + (x + w) / metres; i++) {
    for (let j = Math.floor(ty + y / metres); j <= ty + (y + w) / metres; j++) {
      const href = window.ROOST.tiles.replace("{z}", z).replace("{x}", i).replace("{y}", j);
      tiles.append(el("svg:image", {
        href, x: (i - tx) * metres, y: (j - ty) * metres, width: metres, height: metres,
      }));
    }
  }
}

const drawn = new Map(); // vehicle -> {g, trail, last}
let fencesDrawn = "";

function renderFences(missions) {
  // Each unfinished Mission's fence: its polygon or circle, dashed, named after it.
  const key = JSON.stringify([view, missions.map((m) => [m.name, m.fence])]);
  if (key === fencesDrawn) return;
  fencesDrawn = key;
  const group = $("fences");
  group.replaceChildren();
  for (const m of missions) {
    const f = m.fence;
    if (!f) continue;
    const g = el("svg:g", { class: "fence", "data-mission": m.name, "data-action": f.action,
      "data-max-altitude": f.maxAltitudeM });
    let label;
    if (f.circle) {
      const [n, e, r] = f.circle;
      g.append(el("svg:circle", { cx: e, cy: -n, r }));
      label = [e - r, -n - r];
    } else {
      g.append(el("svg:polygon", { points: f.polygon.map(([n, e]) => `${e},${-n}`).join(" ") }));
      const top = f.polygon.reduce((a, b) => (b[0] > a[0] ? b : a));
      label = [top[1], -top[0]];
    }
    const size = Math.max(1.2, view[2] / 50); // readable however wide the arena is
    g.append(el("svg:text", { x: label[0], y: label[1] - size / 2, "font-size": size },
      `${m.name} fence ≤${f.maxAltitudeM} m, ${f.action}`));
    group.append(g);
  }
}

function renderArena(vehicles, missions = []) {
  const fences = missions.map((m) => m.fence).filter(Boolean);
  fitArena(vehicles, fences);
  renderFences(missions);
  const markers = $("markers"), trails = $("trails");
  const seen = new Set();
  for (const v of vehicles) {
    seen.add(v.name);
    let entry = drawn.get(v.name);
    if (!entry) {
      const g = el("svg:g", { class: "marker", "data-vehicle": v.name });
      g.append(el("svg:circle", { r: 0.9 }), el("svg:line", { x1: 0, y1: 0, x2: 0, y2: -2 }),
        el("svg:text", { x: 1.2, y: -1 }, v.name));
      markers.append(g);
      const trail = el("svg:polyline", { class: "trail", "data-vehicle": v.name });
      trails.append(trail);
      entry = { g, trail, last: null };
      drawn.set(v.name, entry);
    }
    const { g, trail } = entry;
    const cls = LEVEL_CLASS(v.worst);
    setAttr(g, "class", `marker ${cls}${v.telemetry === "live" ? "" : " stale"}`);
    setAttr(g, "data-worst", v.worst);
    setAttr(trail, "class", `trail ${cls}`);
    const p = v.position;
    if (p && p.n !== undefined) {
      const heading = p.heading === null ? 0 : p.heading;
      setAttr(g, "transform", `translate(${p.e} ${-p.n})`);
      setAttr(g.children[1], "transform", `rotate(${heading})`);
      g.style.display = "";
    } else if (!g.getAttribute("transform")) {
      g.style.display = "none"; // never reported a position: nowhere to draw it
    }
    const points = v.trail || [];
    const last = points.length ? `${points.length}:${points[points.length - 1]}` : "";
    if (entry.last !== last) { // a trail changes only when a new position arrived
      entry.last = last;
      trail.setAttribute("points", points.map(([n, e]) => `${e},${-n}`).join(" "));
    }
  }
  for (const [name, entry] of drawn) {
    if (!seen.has(name)) {
      entry.g.remove();
      entry.trail.remove();
      drawn.delete(name);
    }
  }
}

// ---- fleet table ----------------------------------------------------------------------
const rowsByName = new Map();

function renderFleet(doc) {
  const body = $("fleet").tBodies[0];
  const seen = new Set();
  for (const v of doc.vehicles) {
    seen.add(v.name);
    let row = rowsByName.get(v.name);
    if (!row) {
      row = el("tr", { "data-vehicle": v.name });
      for (let i = 0; i < 9; i++) row.append(el("td"));
      row.cells[4].className = "health";
      const stop = el("button", { class: "danger estop", "data-vehicle": v.name }, "E-stop");
      stop.addEventListener("click", () => confirmEstop([v.name], false));
      row.cells[8].append(stop);
      body.append(row);
      rowsByName.set(v.name, row);
    }
    setAttr(row, "class", `worst-${v.worst}`);
    setAttr(row, "data-worst", v.worst);
    setAttr(row, "data-active", v.active);
    setAttr(row, "data-landed", v.landed === null ? "unknown" : v.landed);
    setAttr(row, "data-telemetry", v.telemetry);
    setText(row.cells[0], v.name);
    setText(row.cells[1], v.node);
    setText(row.cells[2], v.ready + (v.readyReason ? ` (${v.readyReason})` : ""));
    setText(row.cells[3], v.active + (v.latched ? " (latched)" : ""));
    const health = v.autopilots
      .map((a) => `${a.active ? "*" : ""}${a.name}:${a.level}:${a.reason}`).join("|");
    if (row.cells[4].dataset.key !== health) {
      row.cells[4].dataset.key = health;
      row.cells[4].replaceChildren(...v.autopilots.map((a) => {
        const span = el("span", { class: `${LEVEL_CLASS(a.level)}${a.active ? " active" : ""}`,
          "data-autopilot": a.name, "data-level": a.level }, `${a.name} ${a.level}`);
        if (a.reason) span.title = a.reason;
        return span;
      }));
    }
    setText(row.cells[5], v.altitude === null ? "-" :
      (v.landed ? "landed" : `${v.altitude.toFixed(1)} m`));
    setText(row.cells[6], v.mission);
    setText(row.cells[7], v.lastFailover);
    row.cells[7].title = v.failoverDetail;
    row.cells[8].firstChild.hidden = doc.readOnly;
  }
  for (const [name, row] of rowsByName) {
    if (!seen.has(name)) {
      row.remove();
      rowsByName.delete(name);
    }
  }
}

// ---- missions -------------------------------------------------------------------------
const missionBoxes = new Map(); // mission -> {div, phase, assigned, message, abort, table, key}

function missionBox(m) {
  const div = el("div", { class: "mission", "data-mission": m.name });
  const h = el("h3");
  const phase = el("span", { class: "phase" });
  const assigned = el("span");
  const message = el("small");
  // Created once and kept: a button must not be replaced under the user's pointer.
  const abort = el("button", { class: "danger abort", "data-mission": m.name }, "Abort");
  abort.addEventListener("click", () => confirmAbort(missionBoxes.get(m.name).mission));
  h.append(el("span", {}, m.name), phase, assigned, message, abort);
  const table = el("table");
  div.append(h, table);
  $("missions").append(div);
  return { div, phase, assigned, message, abort, table, key: "", mission: m };
}

function renderMissions(doc) {
  const seen = new Set();
  for (const m of doc.missions) {
    seen.add(m.name);
    const box = missionBoxes.get(m.name) || missionBox(m);
    missionBoxes.set(m.name, box);
    box.mission = m;
    setAttr(box.div, "data-phase", m.phase);
    setText(box.phase, m.phase);
    setText(box.assigned, `${m.assigned} vehicles`);
    setText(box.message, m.message);
    box.abort.hidden = doc.readOnly || m.abort || ["Succeeded", "Failed", "Aborted"].includes(m.phase);
    const key = JSON.stringify(m.perVehicle);
    if (box.key !== key) {
      box.key = key;
      const head = el("tr");
      head.append(el("th", {}, "Vehicle"), el("th", {}, "Phase"),
        el("th", {}, "Preflight / reason"), el("th", {}, "Message"));
      box.table.replaceChildren(head, ...m.perVehicle.map((v) => {
        const tr = el("tr", { "data-vehicle": v.name, "data-phase": v.phase });
        tr.append(el("td", {}, v.name), el("td", {}, v.phase), el("td", {}, v.reason),
          el("td", {}, v.message));
        return tr;
      }));
    }
  }
  for (const [name, box] of missionBoxes) {
    if (!seen.has(name)) {
      box.div.remove();
      missionBoxes.delete(name);
    }
  }
}

// ---- timeline -------------------------------------------------------------------------
const entryKey = (e) => `${e.time}|${e.object}|${e.reason}|${e.message}`;
let shownKeys = []; // the timeline's entries as shown, oldest first

function timelineItem(e) {
  const li = el("li", { "data-kind": e.kind, "data-object": e.object, "data-reason": e.reason,
    "data-source": e.source, class: e.warning ? "warning" : "" });
  const when = e.time ? new Date(e.time).toLocaleTimeString() : "";
  li.append(el("span", { class: "when" }, when), el("span", { class: "lane" }, e.kind),
    el("b", {}, `${e.object} `), el("span", { class: "reason" }, `${e.reason} `),
    el("span", {}, e.message));
  return li;
}

function renderTimeline(doc) {
  // Newest first. A new document usually drops some oldest entries and adds new ones at
  // the end: then only those change in the DOM; anything else rebuilds the list.
  const list = $("timeline");
  const keys = doc.timeline.map(entryKey);
  const old = shownKeys;
  const dropped = keys.length && old.length ? old.indexOf(keys[0]) : -1;
  let continues = dropped >= 0;
  for (let i = dropped; continues && i < old.length; i++) continues = old[i] === keys[i - dropped];
  if (continues) {
    for (let i = 0; i < dropped; i++) list.lastElementChild.remove();
    const added = doc.timeline.slice(old.length - dropped);
    if (added.length) list.prepend(...added.reverse().map(timelineItem));
  } else if (keys.join("\n") !== old.join("\n")) {
    list.replaceChildren(...doc.timeline.slice().reverse().map(timelineItem));
  }
  shownKeys = keys;
}

// ---- guarded actions ------------------------------------------------------------------
async function post(path, body) {
  const response = await fetch(path, {
    method: "POST",
    headers: { "Content-Type": "application/json", "X-Roost-Token": window.ROOST.token },
    body: JSON.stringify(body),
  });
  const answer = await response.json();
  if (!response.ok) throw new Error(answer.error || response.statusText);
  return answer;
}

function ask(title, text, targets, okLabel, act) {
  const dialog = $("confirm");
  setText($("confirm-title"), title);
  setText($("confirm-text"), text);
  $("confirm-targets").replaceChildren(...targets.map((t) => el("li", { "data-target": t }, t)));
  setText($("confirm-result"), "");
  setText($("confirm-ok"), okLabel);
  $("confirm-ok").disabled = false;
  dialog.returnValue = "";
  dialog.onclose = async () => {
    if (dialog.returnValue !== "ok") return;
    try {
      const answer = await act();
      R.lastAction = { ok: true, answer };
    } catch (error) {
      R.lastAction = { ok: false, error: String(error.message || error) };
      alert(`${title} failed: ${R.lastAction.error}`);
    }
  };
  dialog.showModal();
}

function confirmAbort(mission) {
  const vehicles = mission.perVehicle.map((v) => v.name).sort();
  ask(`Abort mission ${mission.name}?`,
    "Every assigned vehicle runs its safety routine (hold, then land). Targets:",
    [mission.name, ...vehicles], "Abort mission",
    () => post("/api/abort", { mission: mission.name, confirmed: [mission.name, ...vehicles] }));
}

function confirmEstop(vehicles, everything) {
  const names = vehicles.slice().sort();
  ask(everything ? "EMERGENCY STOP every vehicle?" : `EMERGENCY STOP ${names.join(", ")}?`,
    "Force-disarm the active autopilot: motors stop immediately; a flying vehicle falls. Targets:",
    names, "Force-disarm",
    () => post("/api/estop", everything ? { all: true, confirmed: names }
      : { vehicles: names, confirmed: names }));
}

$("estop-all").addEventListener("click", () => {
  if (R.doc) confirmEstop(R.doc.vehicles.map((v) => v.name), true);
});

// ---- the stream -----------------------------------------------------------------------
const sampled = new Map(); // vehicle -> last sampledAt shown

function apply(doc) {
  const started = performance.now();
  R.doc = doc;
  R.documents += 1;
  setText($("server"), doc.server);
  setText($("cluster-error"), doc.clusterError || "");
  $("estop-all").hidden = doc.readOnly || doc.vehicles.length === 0;
  $("read-only").hidden = !doc.readOnly;
  if (doc.origin) tileOrigin = doc.origin;
  renderArena(doc.vehicles, doc.missions);
  renderFleet(doc);
  renderMissions(doc);
  renderTimeline(doc);
  const now = Date.now();
  for (const v of doc.vehicles) {
    if (v.sampledAt && sampled.get(v.name) !== v.sampledAt) {
      sampled.set(v.name, v.sampledAt);
      R.latencies.push(now - v.sampledAt * 1000);
    }
  }
  R.frames.push(performance.now() - started);
  if (R.frames.length > KEEP) R.frames.splice(0, R.frames.length - KEEP);
  if (R.latencies.length > KEEP * 10) R.latencies.splice(0, R.latencies.length - KEEP * 10);
}

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.onopen = () => { $("link").className = "link up"; setText($("link"), "live"); };
  ws.onmessage = (message) => apply(JSON.parse(message.data));
  ws.onclose = () => {
    $("link").className = "link down";
    setText($("link"), "reconnecting…");
    setTimeout(connect, 1000);
  };
}
connect();
