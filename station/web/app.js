// shoal station page: draws the snapshot the station pushes (see
// station/src/view.rs for its fields). Plain JS + SVG, no external assets.
"use strict";

const SVG_NS = "http://www.w3.org/2000/svg";
const W = 600, H = 460, MARGIN = 30;
const VEHICLE_COLORS = ["#e64d33", "#3399e6", "#4dcc4d", "#f2bf33", "#b366d9", "#4dd9d9"];
// One colour per verdict; rejected edges are dashed.
const VERDICT_COLORS = {
  accepted: "#2ca02c",
  ChiSquare: "#d62728",
  FlippedHypothesis: "#ff7f0e",
  Inconsistent: "#1f77b4",
  Stale: "#9467bd",
  ClockSkew: "#e377c2",
  ObserverMismatch: "#17becf",
  UnknownMarker: "#7f7f7f",
  AmbiguousMarker: "#bcbd22",
  SelfObservation: "#8c564b",
  Invalid: "#ffffff",
  Duplicate: "#aaaaaa",
};

// Each view maps map coordinates (reference body frame, FRD) to the screen.
// top: x forward is up, y starboard is right. side: x forward is right, z down is down.
const VIEWS = {
  top: { h: (p) => p[1], v: (p) => -p[0], hLabel: "y", vLabel: "x" },
  side: { h: (p) => p[0], v: (p) => p[2], hLabel: "x", vLabel: "z" },
};
const scales = { top: null, side: null };

let lastMessageAt = 0;
let received = 0;
let source = null;

function el(tag, attrs, parent) {
  const e = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}

function vehicleColor(id) {
  return VEHICLE_COLORS[id % VEHICLE_COLORS.length];
}

function fmt(x, digits) {
  return x === null || x === undefined || !isFinite(x) ? "–" : x.toFixed(digits);
}

// Fit the view to everything drawn (centred on the swarm, not on the
// reference vehicle), zooming out at once and in slowly so the picture does
// not jump with every update.
function fitScale(name, snap) {
  const view = VIEWS[name];
  let lo = [Infinity, Infinity], hi = [-Infinity, -Infinity];
  for (const v of snap.vehicles) {
    for (const pose of [v.estimate, v.truth]) {
      if (!pose) continue;
      const r = v.hull_length_m * 0.6 + 0.3;
      const p = [view.h(pose.position_m), view.v(pose.position_m)];
      for (const i of [0, 1]) {
        lo[i] = Math.min(lo[i], p[i] - r);
        hi[i] = Math.max(hi[i], p[i] + r);
      }
    }
  }
  if (!isFinite(lo[0])) { lo = [-1.5, -1.5]; hi = [1.5, 1.5]; }
  const center = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2];
  const target = Math.min((W - 2 * MARGIN) / Math.max(hi[0] - lo[0], 1), (H - 2 * MARGIN) / Math.max(hi[1] - lo[1], 1));
  const old = scales[name];
  if (old === null) {
    scales[name] = { s: target, c: center };
  } else {
    old.s = target < old.s ? target : old.s + 0.05 * (target - old.s);
    old.c = [old.c[0] + 0.2 * (center[0] - old.c[0]), old.c[1] + 0.2 * (center[1] - old.c[1])];
  }
  return scales[name];
}

function project(name, fit, p) {
  const view = VIEWS[name];
  return [W / 2 + fit.s * (view.h(p) - fit.c[0]), H / 2 + fit.s * (view.v(p) - fit.c[1])];
}

function drawAxes(svg, name, fit) {
  // Axes through the reference vehicle (the map's origin).
  const [ox, oy] = project(name, fit, [0, 0, 0]);
  el("line", { class: "axis", x1: 0, y1: oy, x2: W, y2: oy }, svg);
  el("line", { class: "axis", x1: ox, y1: 0, x2: ox, y2: H }, svg);
  // A scale bar of a round number of metres.
  const s = fit.s;
  const metres = [0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50].find((m) => m * s > 60) || 100;
  const g = el("g", { class: "scale" }, svg);
  el("line", { x1: 12, y1: H - 12, x2: 12 + metres * s, y2: H - 12, stroke: "#8b9aa8", "stroke-width": 2 }, g);
  el("text", { x: 12, y: H - 18 }, g).textContent = metres + " m";
}

// A hull: a rounded bar along the body's x axis, length x diameter.
function drawHull(svg, name, s, v, pose, ghost) {
  const [cx, cy] = project(name, s, pose.position_m);
  const half = v.hull_length_m / 2;
  const f = pose.forward;
  const bow = project(name, s, pose.position_m.map((c, i) => c + half * f[i]));
  const stern = project(name, s, pose.position_m.map((c, i) => c - half * f[i]));
  const width = Math.max(5, v.hull_diameter_m * s.s);
  const color = vehicleColor(v.id);
  el("line", {
    x1: stern[0], y1: stern[1], x2: bow[0], y2: bow[1],
    stroke: color, "stroke-width": width, "stroke-linecap": "round",
    "stroke-opacity": ghost ? 0.25 : 0.9,
    "stroke-dasharray": ghost ? "4 3" : "none",
  }, svg);
  if (!ghost) {
    el("circle", { cx: bow[0], cy: bow[1], r: Math.max(2, width / 3), fill: "#ffffff" }, svg);
  }
  return [cx, cy];
}

function drawEllipse(svg, name, s, pose, e, color) {
  if (!e) return;
  // The ellipse's major axis, mapped to the screen through the view.
  const axes = name === "top" ? [0, 1] : [0, 2];
  const dir = [0, 0, 0];
  dir[axes[0]] = Math.cos(e.angle_rad);
  dir[axes[1]] = Math.sin(e.angle_rad);
  const c = project(name, s, pose.position_m);
  const tip = project(name, s, pose.position_m.map((p, i) => p + dir[i]));
  const angle = (Math.atan2(tip[1] - c[1], tip[0] - c[0]) * 180) / Math.PI;
  el("ellipse", {
    cx: c[0], cy: c[1],
    rx: Math.max(1, e.semi_major_m * s.s), ry: Math.max(1, e.semi_minor_m * s.s),
    transform: `rotate(${angle} ${c[0]} ${c[1]})`,
    fill: color, "fill-opacity": 0.12, stroke: color, "stroke-width": 1.2,
  }, svg);
}

function drawEdges(svg, name, s, snap, positions) {
  // Several edges between the same two vehicles are spread side by side.
  const perPair = {};
  for (const e of snap.edges) {
    const a = positions[e.observer], b = positions[e.target];
    if (!a || !b || e.observer === e.target) continue;
    const key = Math.min(e.observer, e.target) + "-" + Math.max(e.observer, e.target);
    const k = (perPair[key] = (perPair[key] || 0) + 1) - 1;
    const pa = project(name, s, a), pb = project(name, s, b);
    const dx = pb[0] - pa[0], dy = pb[1] - pa[1];
    const len = Math.hypot(dx, dy) || 1;
    const off = (k % 2 ? -1 : 1) * Math.ceil(k / 2) * 5;
    const nx = (-dy / len) * off, ny = (dx / len) * off;
    const color = VERDICT_COLORS[e.verdict] || "#ffffff";
    const line = el("line", {
      x1: pa[0] + nx, y1: pa[1] + ny, x2: pb[0] + nx, y2: pb[1] + ny,
      stroke: color, "stroke-width": e.verdict === "accepted" ? 2 : 1.5,
      "stroke-dasharray": e.verdict === "accepted" ? "none" : "6 4",
      "stroke-opacity": 0.85, "marker-end": "url(#arrow-" + name + ")",
    }, svg);
    el("title", {}, line).textContent = `${e.observer} cam ${e.camera} → ${e.target} (marker ${e.marker}): ${e.verdict} ×${e.count}`;
  }
}

function drawView(name, snap) {
  const svg = document.getElementById(name);
  while (svg.firstChild) svg.removeChild(svg.firstChild);
  const defs = el("defs", {}, svg);
  const marker = el("marker", {
    id: "arrow-" + name, viewBox: "0 0 10 10", refX: 18, refY: 5,
    markerWidth: 6, markerHeight: 6, orient: "auto-start-reverse",
  }, defs);
  el("path", { d: "M 0 0 L 10 5 L 0 10 z", fill: "#8b9aa8" }, marker);
  const s = fitScale(name, snap);
  drawAxes(svg, name, s);
  const positions = {};
  for (const v of snap.vehicles) if (v.estimate) positions[v.id] = v.estimate.position_m;
  drawEdges(svg, name, s, snap, positions);
  for (const v of snap.vehicles) {
    const color = vehicleColor(v.id);
    if (v.truth) {
      const [gx, gy] = drawHull(svg, name, s, v, v.truth, true);
      if (v.estimate) {
        const [ex, ey] = project(name, s, v.estimate.position_m);
        el("line", { x1: gx, y1: gy, x2: ex, y2: ey, stroke: color, "stroke-width": 1, "stroke-dasharray": "2 2" }, svg);
      }
    }
    if (v.estimate) {
      drawEllipse(svg, name, s, v.estimate, name === "top" ? v.ellipse_top : v.ellipse_side, color);
      let [cx, cy] = drawHull(svg, name, s, v, v.estimate, false);
      // In the side view vehicles abreast overlap: stagger their labels.
      const dy = name === "side" ? 34 * snap.vehicles.indexOf(v) - 34 : 0;
      cy += dy;
      const label = el("text", { x: cx + 10, y: cy - 10, "font-weight": "bold" }, svg);
      label.textContent = v.id + (v.is_reference ? " (ref)" : "");
      if (v.error_mm !== null && v.error_mm !== undefined) {
        el("text", { x: cx + 10, y: cy + 4, "font-size": 11 }, svg).textContent = "err " + fmt(v.error_mm, 0) + " mm";
      }
      if (v.state !== "live" && !v.is_reference) {
        el("text", { x: cx + 10, y: cy + 18, "font-size": 11, fill: "#f0c040" }, svg).textContent = v.state;
      }
    }
  }
}

function drawLegend(snap) {
  const legend = document.getElementById("legend");
  const parts = [];
  const names = Object.keys(VERDICT_COLORS);
  for (const name of names) {
    const n = snap.verdicts[name] || 0;
    if (name !== "accepted" && n === 0) continue;
    const cls = name === "accepted" ? "" : "dash";
    parts.push(`<span><i class="${cls}" style="border-color:${VERDICT_COLORS[name]}"></i>${name} ${n}</span>`);
  }
  parts.push(`<span>ellipses: ${snap.ellipse_sigmas}σ position</span>`);
  parts.push(`<span>faint dashed hulls: ground truth (simulation)</span>`);
  if (snap.messages_rejected > 0) parts.push(`<span class="bad">${snap.messages_rejected} messages rejected</span>`);
  legend.innerHTML = parts.join("");
}

function ageClass(age, warn, bad) {
  if (age === null || age === undefined) return "";
  return age > bad ? "bad" : age > warn ? "warn" : "ok";
}

function text(tr, value, cls) {
  const td = document.createElement("td");
  td.textContent = value;
  if (cls) td.className = cls;
  tr.appendChild(td);
  return td;
}

function fillTables(snap) {
  const vb = document.querySelector("#vehicles tbody");
  vb.textContent = "";
  const positions = [];
  for (const v of snap.vehicles) {
    const tr = document.createElement("tr");
    tr.id = "veh-" + v.id;
    text(tr, v.id + (v.is_reference ? " (ref)" : "")).style.color = vehicleColor(v.id);
    text(tr, v.name);
    text(tr, v.state, v.state === "live" || v.is_reference ? "ok" : v.state === "absent" ? "bad" : "warn");
    text(tr, v.alive === null ? "?" : v.alive ? "yes" : "NO", v.alive === false ? "bad" : v.alive ? "ok" : "");
    text(tr, v.last_seen_age_s === null ? "–" : fmt(v.last_seen_age_s, 1) + " s", ageClass(v.last_seen_age_s, 1, 3));
    text(tr, v.sigma_m ? v.sigma_m.map((x) => fmt(x * 1e3, 0)).join(" / ") : "–");
    text(tr, v.error_mm === null ? "–" : fmt(v.error_mm, 0) + " mm, " + fmt(v.error_deg, 1) + "°");
    text(tr, v.status_age_s === null ? "–" : fmt(v.status_age_s, 1) + " s", ageClass(v.status_age_s, 2.5, 5));
    text(tr, v.observations_sent === null ? "–" : v.observations_sent);
    vb.appendChild(tr);
    if (v.estimate) positions.push(v.id + ":" + v.estimate.position_m.map((x) => x.toFixed(3)).join(","));
  }
  document.getElementById("positions").textContent = "positions " + positions.join(" ");

  const cb = document.querySelector("#cameras tbody");
  cb.textContent = "";
  for (const v of snap.vehicles) {
    for (const c of v.cameras) {
      const tr = document.createElement("tr");
      text(tr, v.id).style.color = vehicleColor(v.id);
      text(tr, c.name);
      text(tr, fmt(c.frame_rate_hz, 1), c.frame_rate_hz > 0 ? "" : "warn");
      text(tr, fmt(c.detection_rate_hz, 2));
      text(tr, fmt(c.detections_per_frame, 2));
      text(tr, fmt(c.latency_ms, 0));
      text(tr, c.frames_dropped, c.frames_dropped > 0 ? "warn" : "");
      text(tr, c.frames_invalid, c.frames_invalid > 0 ? "bad" : "");
      cb.appendChild(tr);
    }
  }

  const eb = document.querySelector("#edges tbody");
  eb.textContent = "";
  for (const e of snap.edges) {
    const tr = document.createElement("tr");
    text(tr, e.observer);
    text(tr, e.camera);
    text(tr, e.target === null ? "?" : e.target);
    text(tr, e.marker);
    text(tr, e.verdict).style.color = VERDICT_COLORS[e.verdict] || "";
    text(tr, e.count);
    text(tr, fmt(e.max_chi2, 1));
    eb.appendChild(tr);
  }
}

function render(snap) {
  document.getElementById("fleet").textContent = snap.fleet ? "— fleet " + snap.fleet : "";
  document.getElementById("update").textContent = snap.update;
  const m = snap.map;
  document.getElementById("map-info").textContent = m
    ? `map #${m.seq} (${m.producer}) t=${fmt(m.stamp_s, 1)} s, solve ${fmt(m.solve_ms, 1)} ms, ` +
      `${m.edges_accepted} accepted / ${m.edges_rejected} rejected, received ${fmt(m.age_s, 1)} s ago`
    : "no map yet";
  const mapInfo = document.getElementById("map-info");
  mapInfo.className = m && m.age_s > 2 ? "warn" : "";
  document.getElementById("truth-info").textContent =
    snap.truth_stamp_s === null || snap.truth_stamp_s === undefined ? "" : "truth t=" + fmt(snap.truth_stamp_s, 1) + " s";
  drawView("top", snap);
  drawView("side", snap);
  drawLegend(snap);
  fillTables(snap);
}

function setConn(text, cls) {
  const c = document.getElementById("conn");
  c.textContent = text;
  c.className = cls;
}

function connect() {
  if (source) source.close();
  source = new EventSource("/events");
  source.onopen = () => setConn("live", "conn-live");
  source.onmessage = (ev) => {
    lastMessageAt = Date.now();
    setConn("live", "conn-live");
    try {
      render(JSON.parse(ev.data));
      received += 1;
      document.getElementById("received").textContent = received;
    } catch (err) {
      setConn("bad snapshot: " + err, "conn-down");
    }
  };
  source.onerror = () => {
    setConn("connection lost — reconnecting…", "conn-down");
    if (source.readyState === EventSource.CLOSED) setTimeout(connect, 2000);
  };
}

// The stream can stall without an error (a proxy, a sleeping laptop): say so,
// and start over after a while.
setInterval(() => {
  if (!lastMessageAt) return;
  const silent = (Date.now() - lastMessageAt) / 1000;
  if (silent > 3) setConn(`no update for ${silent.toFixed(0)} s — reconnecting…`, "conn-down");
  if (silent > 10) {
    lastMessageAt = Date.now();
    connect();
  }
}, 1000);

// The server embeds the snapshot current when the page was requested, so the
// first picture needs no round trip (and a screenshot at load shows the swarm).
try {
  const initial = JSON.parse(document.getElementById("initial-snapshot").textContent);
  if (initial && initial.vehicles) render(initial);
} catch (err) {
  setConn("bad initial snapshot: " + err, "conn-down");
}
connect();
