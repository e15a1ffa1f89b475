// skinstretch viewer page: one canvas for the frame and its overlays, a tactile-movie canvas, colour bars, a readout.
// Plain script, no build step. Talks to the server of skinstretch/experiments/viewer/server.py.
"use strict";

const KIND_STYLE = {  // Okabe-Ito colours (colour-blind safe)
  0: { color: "#E69F00", shape: "circle", label: "valley ending" },
  1: { color: "#56B4E9", shape: "square", label: "valley bifurcation" },
  2: { color: "#009E73", shape: "dot", label: "pore" },
};
// ColorBrewer RdBu, reversed: blue = shrinking, red = stretching (the same map as matplotlib's RdBu_r).
const STRAIN_MAP = ["#053061", "#2166ac", "#4393c3", "#92c5de", "#d1e5f0", "#f7f7f7", "#fddbc7", "#f4a582",
  "#d6604d", "#b2182b", "#67001f"];
// ColorBrewer PuOr, reversed: purple = towards the start of the sliding axis, orange = towards its end.
const TACTILE_MAP = ["#2d004b", "#542788", "#8073ac", "#b2abd2", "#d8daeb", "#f7f7f7", "#fee0b6", "#fdb863",
  "#e08214", "#b35806", "#7f3b08"];
const TACTILE_RANGE_UM = 50;
const DEFAULT_ARROW_GAIN = 5;
// What each map quantity is, for the colour bar and the readout (docs/viewer.md, "Strain maps").
const MAP_TITLES = {
  area: (r) => `area change ${r} − 1; grey = flipped`,
  edge: (r) => `edge length change ${r.replace(/A/g, "L")} − 1`,
  exx: () => "Green-Lagrange exx (image x)", eyy: () => "Green-Lagrange eyy (image y)",
  exy: () => "Green-Lagrange exy (tensor shear, half the engineering shear)",
  e1: () => "major principal strain e1", e2: () => "minor principal strain e2",
};
const HIT_RADIUS_SCREEN_PX = 10;
const TAIL_FRAMES = 12;  // session_data.TAIL_FRAMES: the server sends each tail through its last 12 frames

const S = {
  info: null, sid: 0, n: 0, k: 0, span: 1, scale: 1, playing: false, follow: false,
  overlays: new Map(), images: new Map(), current: null, pinned: null, hover: null,
  on: { features: true, matches: false, tails: true, mesh: true, arrows: false, outline: true, window: true },
  busy: false, pendingFrame: null, direction: 1, maxSigma: 0,
  quantity: "area", fixedRange: null, arrowGain: DEFAULT_ARROW_GAIN, tool: "inspect", gauge: null, gaugeQuery: null,
  drag: null,
};
// Measurements the browser tests and the live bench read: per shown frame, how long it took and, for a live
// frame, its exposure time (host clock, s) and when it was on screen (same clock: Date.now()).
window.viewerStats = { shown: [], live: [], liveReceived: [], errors: [] };

const $ = (id) => document.getElementById(id);
const view = $("view");
const ctx = view.getContext("2d");

function colorOf(map, t) {  // t in [-1, 1]
  const u = Math.max(0, Math.min(1, (t + 1) / 2)) * (map.length - 1);
  const i = Math.min(map.length - 2, Math.floor(u));
  const f = u - i;
  const a = hex(map[i]), b = hex(map[i + 1]);
  return `rgb(${Math.round(a[0] + f * (b[0] - a[0]))},${Math.round(a[1] + f * (b[1] - a[1]))},${Math.round(a[2] + f * (b[2] - a[2]))})`;
}
function hex(h) { return [1, 3, 5].map((i) => parseInt(h.slice(i, i + 2), 16)); }
function pct(v, digits = 2) { return `${v >= 0 ? "+" : ""}${(100 * v).toFixed(digits)} %`; }

// ------------------------------------------------------------------------------------------- loading
async function getJSON(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: ${r.status}`);
  return r.json();
}

async function loadInfo() {
  const info = await getJSON("api/info");
  S.info = info;
  S.sid = info.sid;
  S.n = info.n_frames;
  S.overlays.clear();
  S.images.clear();
  $("title").textContent = info.waiting ? "skinstretch viewer: waiting for a trial" :
    `skinstretch viewer: ${[info.metadata && info.metadata.trial, info.trial_dir, info.path_name].filter(Boolean).join(" / ")}`;
  if (info.width) {
    const avail = Math.max(320, $("stage").clientWidth - 4);
    S.scale = Math.min(2, avail / info.width);
    view.width = Math.round(info.width * S.scale);
    view.height = Math.round(info.height * S.scale);
  }
  const spans = info.results ? info.results.spans.slice() : [1];
  const cumulative = info.results && info.results.reference_frame >= 0;
  if (cumulative) spans.push(0);  // 0: the cumulative strain, from the reference frame
  $("span").innerHTML = spans.map((s) => s === 0 ?
    `<option value="0">cumulative from frame ${info.results.reference_frame}</option>` :
    `<option value="${s}">${s}</option>`).join("");
  const quantities = info.results && info.results.map_quantities ? info.results.map_quantities : ["area"];
  $("map-quantity").innerHTML = quantities.map((q) => `<option value="${q}">${q}</option>`).join("");
  S.quantity = quantities.includes(S.quantity) ? S.quantity : quantities[0];
  $("map-quantity").value = S.quantity;
  $("study-link").hidden = !info.study_available;
  for (const id of ["tool-gauge", "tool-extensometer"]) $(id).disabled = !cumulative;
  clearGauge();
  S.span = spans.includes(S.span) ? S.span : spans[0];
  $("span").value = String(S.span);
  showAnalysisList("analysis-warnings", "Warnings", info.results ? info.results.warnings : []);
  showAnalysisList("analysis-notes", "Analysis notes", info.results ? info.results.notes : []);
  showAnalysisPlan(info.results ? info.results.plan : []);
  buildLegend();
  setStatus(info);
  S.follow = info.status === "recording" || info.follows_directory;
  $("follow").checked = S.follow;
  $("slider").max = String(Math.max(0, S.n - 1));
  drawTactile(null);
  if (S.n > 0) await showFrame(S.follow ? S.n - 1 : Math.min(S.k, S.n - 1));
}

// Above the frame for as long as the results are shown, so a doubtful number comes with its caveat: the
// analysis' warnings (self-checks that failed, in red) and notes (a short clip, a lossy source, a shape's shading).
function showAnalysisList(id, heading, items) {
  const box = $(id);
  box.innerHTML = "";
  box.hidden = !items || items.length === 0;
  if (box.hidden) return;
  const title = document.createElement("strong");
  title.textContent = heading;
  const ul = document.createElement("ul");
  for (const n of items) {
    const li = document.createElement("li");
    li.textContent = n;
    ul.appendChild(li);
  }
  box.append(title, ul);
}

// The analysis plan (the choices made for this surface and clip, any parameter not applied as asked): collapsed
// under the notes, one row each.
function showAnalysisPlan(rows) {
  const box = $("analysis-plan");
  const table = box.querySelector("table");
  table.innerHTML = "";
  box.hidden = !rows || rows.length === 0;
  if (box.hidden) return;
  for (const [what, value] of rows) {
    const tr = document.createElement("tr");
    for (const text of [what, value]) {
      const td = document.createElement("td");
      td.textContent = text;
      tr.appendChild(td);
    }
    table.appendChild(tr);
  }
}

// An arrow is drawn when its predicted standard error is known and within the chosen limit (none: every arrow).
function arrowShown(ov, i) {
  const s = ov.arrow_sigma ? ov.arrow_sigma[i] : -1;
  return !(S.maxSigma > 0) || (s >= 0 && s <= S.maxSigma);
}

function setStatus(st) {  // only what changed: every change of the page costs it a repaint
  const b = $("status");
  setText("status", st.status + (st.live ? `, live analysis ${st.live_fps} frames/s` : ""));
  if (b.className !== "badge " + st.status) b.className = "badge " + st.status;
}

function buildLegend() {
  const ul = $("legend-items");
  ul.innerHTML = "";
  for (const kind of Object.keys(KIND_STYLE)) {
    const li = document.createElement("li");
    const c = document.createElement("canvas");
    c.width = 18; c.height = 18;
    const g = c.getContext("2d");
    drawMarker(g, 9, 9, Number(kind), 1);
    li.appendChild(c);
    const span = document.createElement("span");
    span.textContent = KIND_STYLE[kind].label;
    span.id = `legend-kind-${kind}`;
    li.appendChild(span);
    ul.appendChild(li);
  }
  const extra = [["#ff4fd8", "match: line from the previous frame"], ["rgba(255,140,60,0.85)", `trajectory tail (last ${TAIL_FRAMES} frames)`],
    ["#ffd400", "fingertip outline (hull of measured points)"],
    ["#00e5ff", "visibility window (seed 5.2)"], ["#7CFC00", `displacement ×${S.arrowGain}`]];
  for (const [color, text] of extra) {
    const li = document.createElement("li");
    li.innerHTML = `<svg width="18" height="18"><line x1="2" y1="9" x2="16" y2="9" stroke="${color}" stroke-width="3"/></svg><span>${text}</span>`;
    ul.appendChild(li);
  }
}

async function imageFor(sid, k) {
  const key = `${sid}/${k}`;
  if (S.images.has(key)) return S.images.get(key);
  const p = fetch(`api/s/${sid}/frame/${k}.bmp`).then((r) => {
    if (!r.ok) throw new Error(`frame ${k}: ${r.status}`);
    return r.blob();
  }).then((b) => createImageBitmap(b));
  S.images.set(key, p);
  p.catch(() => S.images.delete(key));
  if (S.images.size > 96) S.images.delete(S.images.keys().next().value);
  return p;
}

async function overlaysFor(sid, k, span) {
  const key = `${sid}/${k}/${span}`;
  if (S.overlays.has(key)) return S.overlays.get(key);
  const p = getJSON(`api/s/${sid}/overlay/${k}?span=${span}`);
  // Live overlays are kept only once the trial's results replace them (see the "state" event).
  S.overlays.set(key, p);
  p.catch(() => S.overlays.delete(key));
  if (S.overlays.size > 96) S.overlays.delete(S.overlays.keys().next().value);
  return p;
}

async function showFrame(k, live = false) {  // live: drawn because the live analysis reached frame k
  if (!S.info || S.n === 0) return;
  k = Math.max(0, Math.min(S.n - 1, k));
  if (S.busy) { S.pendingFrame = [k, live]; return; }  // newest request wins; never queue up
  S.busy = true;
  const t0 = performance.now();
  const sid = S.sid;
  try {
    const [img, ov] = await Promise.all([imageFor(sid, k), overlaysFor(sid, k, S.span)]);
    if (sid !== S.sid) return;
    S.k = k;
    S.current = { img, ov };
    reselect();
    draw();
    const ms = performance.now() - t0;
    window.viewerStats.shown.push({ frame: k, ms });
    if (live && ov.source === "live" && ov.exposure_time) {
      window.viewerStats.live.push({ frame: k, exposure: ov.exposure_time, analysed: ov.analysed_time, shown: Date.now() / 1000 });
    }
    setSliderMax();
    if ($("slider").value !== String(k)) $("slider").value = String(k);
    const fps = S.info.fps || 60;
    setText("frame-label", `frame ${k} / ${S.n - 1}  (t = ${(k / fps).toFixed(3)} s)`);
    setText("source-label", ov.source === "results" ? `results: ${S.info.results.method}` :
      ov.source === "live" ? "live analysis" : "");
    setText("notes", ov.notes.join(" · "));
    drawTactile(ov);
    drawColorbar(mapScale(ov), ov.mesh);
    updateReadout();
    drawGaugePlot();
    prefetch(k + S.direction);
  } catch (e) {
    window.viewerStats.errors.push(String(e));
    $("notes").textContent = String(e);
  } finally {
    S.busy = false;
    if (S.pendingFrame) { const [pk, pl] = S.pendingFrame; S.pendingFrame = null; showFrame(pk, pl); }
  }
}

function prefetch(k) {  // the frame the user will most likely ask for next (not while following a recording)
  if (k >= 0 && k < S.n && S.info && !S.info.live && !S.follow) { imageFor(S.sid, k).catch(() => {}); overlaysFor(S.sid, k, S.span).catch(() => {}); }
}

// --------------------------------------------------------------------------------------------- drawing
function draw() {
  if (!S.current) return;
  const { img, ov } = S.current;
  ctx.setTransform(1, 0, 0, 1, 0, 0);
  ctx.clearRect(0, 0, view.width, view.height);
  ctx.imageSmoothingEnabled = S.scale < 1;
  ctx.drawImage(img, 0, 0, view.width, view.height);
  ctx.setTransform(S.scale, 0, 0, S.scale, 0, 0);
  const lw = 1 / S.scale;
  if (S.on.mesh && ov.mesh) {
    if (S.quantity === "edge") drawEdges(ov.mesh, mapScale(ov), lw); else drawMesh(ov.mesh, mapScale(ov), lw);
  }
  if (S.on.window && ov.window) {
    const [x0, y0, x1, y1] = ov.window;
    ctx.setLineDash([6 * lw, 4 * lw]);
    ctx.strokeStyle = "#00e5ff"; ctx.lineWidth = 2 * lw;
    ctx.strokeRect(x0, y0, x1 - x0, y1 - y0);
    ctx.setLineDash([]);
  }
  if (S.on.outline && ov.outline.length >= 3) {
    ctx.beginPath();
    ov.outline.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    ctx.closePath();
    ctx.setLineDash([3 * lw, 3 * lw]);
    ctx.strokeStyle = "#ffd400"; ctx.lineWidth = 2 * lw; ctx.stroke();
    ctx.setLineDash([]);
  }
  if (S.on.tails) {
    ctx.strokeStyle = "rgba(255,140,60,0.85)"; ctx.lineWidth = 1.3 * lw;
    ctx.beginPath();
    for (const t of ov.tails) {
      ctx.moveTo(t[0][0], t[0][1]);
      for (let i = 1; i < t.length; i++) ctx.lineTo(t[i][0], t[i][1]);
    }
    ctx.stroke();
  }
  if (S.on.matches) {
    ctx.strokeStyle = "#ff4fd8"; ctx.lineWidth = 1.5 * lw;
    ctx.beginPath();
    for (const [x0, y0, x1, y1] of ov.matches) { ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); }
    ctx.stroke();
    ctx.beginPath();
    for (const [x0, y0] of ov.matches) { ctx.moveTo(x0 + 2.5 * lw, y0); ctx.arc(x0, y0, 2.5 * lw, 0, 2 * Math.PI); }
    ctx.stroke();
  }
  if (S.on.arrows) {
    ctx.strokeStyle = "#7CFC00"; ctx.lineWidth = 1.4 * lw;
    ctx.beginPath();
    // From the feature onwards, in the direction it moved (its tail lies behind it: the two do not overlap).
    ov.arrows.forEach(([x, y, dx, dy], i) => {
      if (arrowShown(ov, i)) arrow(x, y, x + S.arrowGain * dx, y + S.arrowGain * dy, 4 * lw);
    });
    ctx.stroke();
  }
  if (S.on.features) {
    const f = ov.features;
    for (let i = 0; i < f.x.length; i++) drawMarker(ctx, f.x[i], f.y[i], f.kind[i], lw);
  }
  drawHighlight(lw);
  drawGaugeMarks(lw);
}

// The colour scale of the map shown: fixed by the user, or the session's own for this quantity and span (one scale
// for every frame, so colours compare across frames).
function mapScale(ov) {
  if (S.fixedRange) return S.fixedRange;
  const r = S.info && S.info.results;
  const scales = r && r.map_scales ? r.map_scales[String(S.span)] : null;
  return scales && scales[S.quantity] ? scales[S.quantity] : ov.strain_scale;
}

function meshValues(mesh) {
  if (S.quantity === "area" || !mesh.values || !mesh.values[S.quantity]) return mesh.change;
  return mesh.values[S.quantity];
}

function drawEdges(mesh, scale, lw) {
  if (!mesh.edge_xy) return;
  const groups = new Map();
  for (let i = 0; i < mesh.edge_xy.length; i++) {
    const key = Math.round(Math.max(-1, Math.min(1, mesh.edge_change[i] / scale)) * MESH_STEPS);
    if (!groups.has(key)) groups.set(key, []);
    groups.get(key).push(mesh.edge_xy[i]);
  }
  ctx.lineWidth = 2.2 * lw;
  for (const [key, segs] of groups) {
    ctx.strokeStyle = colorOf(STRAIN_MAP, key / MESH_STEPS);
    ctx.beginPath();
    for (const [x0, y0, x1, y1] of segs) { ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); }
    ctx.stroke();
  }
}

// The gauge (a ring of its radius) or the extensometer (a line) where it is in the frame shown; the line being
// dragged.
function drawGaugeMarks(lw) {
  ctx.strokeStyle = "#ff2da0"; ctx.lineWidth = 2.5 * lw;
  if (S.drag && S.drag.to) {
    ctx.beginPath(); ctx.moveTo(S.drag.from[0], S.drag.from[1]); ctx.lineTo(S.drag.to[0], S.drag.to[1]); ctx.stroke();
  }
  const g = S.gauge;
  if (!g) return;
  const c = g.columns, k = S.k;
  if (!c.ok[k]) return;
  ctx.beginPath();
  if (g.kind === "gauge") {
    ctx.arc(c.x[k], c.y[k], g.radius_px, 0, 2 * Math.PI);
    ctx.moveTo(c.x[k] - 4 * lw, c.y[k]); ctx.lineTo(c.x[k] + 4 * lw, c.y[k]);
    ctx.moveTo(c.x[k], c.y[k] - 4 * lw); ctx.lineTo(c.x[k], c.y[k] + 4 * lw);
  } else {
    ctx.moveTo(c.x1[k], c.y1[k]); ctx.lineTo(c.x2[k], c.y2[k]);
    ctx.moveTo(c.x1[k] + 4 * lw, c.y1[k]); ctx.arc(c.x1[k], c.y1[k], 4 * lw, 0, 2 * Math.PI);
    ctx.moveTo(c.x2[k] + 4 * lw, c.y2[k]); ctx.arc(c.x2[k], c.y2[k], 4 * lw, 0, 2 * Math.PI);
  }
  ctx.stroke();
}

// Triangles are filled one path per colour step (MESH_STEPS over the scale; flipped ones grey): a canvas fill per
// triangle cost the live view most of its drawing time, and the steps are finer than the eye tells apart.
const MESH_STEPS = 50;
function drawMesh(mesh, scale, lw) {
  const xy = mesh.xy, groups = new Map(), values = meshValues(mesh);
  for (let i = 0; i < xy.length; i++) {
    const key = mesh.flipped[i] ? "flipped" :
      Math.round(Math.max(-1, Math.min(1, values[i] / scale)) * MESH_STEPS);
    if (!groups.has(key)) groups.set(key, []);
    groups.get(key).push(xy[i]);
  }
  for (const [key, tris] of groups) {
    ctx.beginPath();
    for (const [x0, y0, x1, y1, x2, y2] of tris) { ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.lineTo(x2, y2); ctx.closePath(); }
    if (key === "flipped") {
      ctx.fillStyle = "rgba(60,60,60,0.65)";
    } else {
      ctx.fillStyle = colorOf(STRAIN_MAP, key / MESH_STEPS);
      ctx.globalAlpha = 0.55;
    }
    ctx.fill();
    ctx.globalAlpha = 1;
  }
  ctx.strokeStyle = "rgba(255,255,255,0.35)"; ctx.lineWidth = 0.8 * lw;
  ctx.beginPath();
  for (const [x0, y0, x1, y1, x2, y2] of xy) { ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.lineTo(x2, y2); ctx.closePath(); }
  ctx.stroke();
}

function arrow(x0, y0, x1, y1, head) {
  ctx.moveTo(x0, y0); ctx.lineTo(x1, y1);
  const a = Math.atan2(y1 - y0, x1 - x0);
  if (Math.hypot(x1 - x0, y1 - y0) < head) return;
  ctx.moveTo(x1, y1); ctx.lineTo(x1 - head * Math.cos(a - 0.45), y1 - head * Math.sin(a - 0.45));
  ctx.moveTo(x1, y1); ctx.lineTo(x1 - head * Math.cos(a + 0.45), y1 - head * Math.sin(a + 0.45));
}

function drawMarker(g, x, y, kind, lw) {
  const st = KIND_STYLE[kind] || KIND_STYLE[2];
  g.strokeStyle = st.color; g.fillStyle = st.color; g.lineWidth = 2 * lw;
  const r = 4.5 * lw;
  g.beginPath();
  if (st.shape === "circle") { g.arc(x, y, r, 0, 2 * Math.PI); g.stroke(); }
  else if (st.shape === "square") { g.rect(x - r, y - r, 2 * r, 2 * r); g.stroke(); }
  else { g.arc(x, y, 2.6 * lw, 0, 2 * Math.PI); g.fill(); }
}

function drawHighlight(lw) {
  const sel = S.pinned || S.hover;
  if (!sel) return;
  ctx.strokeStyle = "#fff"; ctx.lineWidth = 2.5 * lw;
  if (sel.tri) {
    const [x0, y0, x1, y1, x2, y2] = sel.tri.xy;
    ctx.beginPath(); ctx.moveTo(x0, y0); ctx.lineTo(x1, y1); ctx.lineTo(x2, y2); ctx.closePath(); ctx.stroke();
  }
  if (sel.feature) {
    ctx.beginPath(); ctx.arc(sel.feature.x, sel.feature.y, 8 * lw, 0, 2 * Math.PI); ctx.stroke();
  }
}

// A horizontal colour bar on canvas ``c``: ``map`` from -limit to +limit, five ticks labelled by ``label(t)``.
function drawBar(c, map, label, title) {
  const key = `${label(1)}|${title}`;
  if (c.dataset.drawn === key) return;  // unchanged: a canvas redrawn costs the page a raster pass
  c.dataset.drawn = key;
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  const x0 = 12, w = c.width - 24;
  const grad = g.createLinearGradient(x0, 0, x0 + w, 0);  // the map's stops, interpolated in RGB as colorOf does
  map.forEach((color, i) => grad.addColorStop(i / (map.length - 1), color));
  g.fillStyle = grad; g.fillRect(x0, 2, w, 14);
  g.strokeStyle = "#333"; g.strokeRect(x0, 2, w, 14);
  g.fillStyle = "#111"; g.font = "11px system-ui, sans-serif"; g.textAlign = "center";
  for (const t of [-1, -0.5, 0, 0.5, 1]) {
    const x = x0 + ((t + 1) / 2) * w;
    g.fillRect(x, 16, 1, 4);
    g.fillText(t === 0 ? "0" : `${t > 0 ? "+" : "−"}${label(Math.abs(t))}`, x, 31);
  }
  g.fillText(title, c.width / 2, 44);
}

function drawColorbar(scale, mesh) {
  // Written with k, the frame shown, so that the bar stays the same from frame to frame (the readout names the pair).
  const n = mesh ? mesh.frame_b - mesh.frame_a : 1;
  const ratio = !mesh ? "Ab / Aa" : mesh.span === 0 ? `A(k) / A(${mesh.frame_a})` :
    mesh.drawn_at === "frame_a" ? `A(k+${n}) / A(k)` : `A(k) / A(k−${n})`;
  const title = MAP_TITLES[S.quantity] ? MAP_TITLES[S.quantity](ratio) : S.quantity;
  const pair = !mesh ? "" : mesh.span === 0 ? `, frame ${mesh.frame_a} to k` : "";
  drawBar($("colorbar"), STRAIN_MAP, (t) => fmt(t * scale * 100), `%   (${title}${pair}${S.fixedRange ? ", fixed" : ""})`);
  $("colorbar").dataset.scale = String(scale);
  setText("map-title", `${S.quantity === "area" ? "Area change" : S.quantity === "edge" ? "Edge length change" : S.quantity} of each ${S.quantity === "edge" ? "edge" : "triangle"}`);
}
function fmt(v) { return v >= 1 ? v.toFixed(v % 1 ? 1 : 0) : v.toPrecision(2).replace(/0+$/, ""); }

function setSliderMax() {
  const max = String(Math.max(0, S.n - 1));
  if ($("slider").max !== max) $("slider").max = max;
}

function setText(id, text) {  // an unchanged text is left alone (setting it again invalidates the page's layout)
  const el = $(id);
  if (el.textContent !== text) el.textContent = text;
}

function drawTactile(ov) {
  const c = $("tactile"), g = c.getContext("2d");
  const has = ov && ov.tactile_um;
  const axis = S.info && S.info.results ? S.info.results.motion_axis : 0;
  setText("tactile-note", has ?
    `Columns run along the sliding axis (image ${axis ? "y" : "x"}); each dot is offset by its contactor's position. Hollow: reset; black ring: clipped at ±50 µm.` :
    (ov && ov.source === "live" ? "The tactile movie comes with the analysis after the trial." :
      "No tactile movie for this frame (no results, or no visibility window)."));
  if (!has && c.dataset.drawn === "empty") return;  // the empty grid is already there
  c.dataset.drawn = has ? "" : "empty";
  g.clearRect(0, 0, c.width, c.height);
  const pitch = c.width / 10;
  for (let r = 0; r < 10; r++) for (let col = 0; col < 10; col++) {
    const cx = (col + 0.5) * pitch, cy = (r + 0.5) * pitch;
    g.strokeStyle = "#ddd"; g.lineWidth = 1;
    g.strokeRect(col * pitch + 1, r * pitch + 1, pitch - 2, pitch - 2);
    if (!has) continue;
    const um = ov.tactile_um[r][col];
    const x = cx + (um / TACTILE_RANGE_UM) * 0.45 * pitch;
    g.beginPath(); g.arc(x, cy, pitch * 0.3, 0, 2 * Math.PI);
    if (ov.tactile_reset[r][col]) { g.strokeStyle = "#999"; g.lineWidth = 1.5; g.stroke(); }
    else { g.fillStyle = colorOf(TACTILE_MAP, um / TACTILE_RANGE_UM); g.fill(); g.strokeStyle = "#555"; g.lineWidth = 0.8; g.stroke(); }
    if (ov.tactile_clipped[r][col]) { g.strokeStyle = "#000"; g.lineWidth = 2.5; g.stroke(); }
  }
  drawBar($("tactile-bar"), TACTILE_MAP, (t) => String(t * TACTILE_RANGE_UM),
    "contactor position along the sliding axis (µm)");
}

// --------------------------------------------------------------------------------------------- readout
function hitTest(px, py) {
  if (!S.current) return null;
  const ov = S.current.ov;
  const out = {};
  const f = ov.features;
  let best = (HIT_RADIUS_SCREEN_PX / S.scale) ** 2;
  for (let i = 0; i < f.x.length; i++) {
    const d = (f.x[i] - px) ** 2 + (f.y[i] - py) ** 2;
    if (d < best) { best = d; out.feature = { i, x: f.x[i], y: f.y[i] }; }
  }
  if (ov.mesh && S.on.mesh) {
    const xy = ov.mesh.xy;
    for (let i = 0; i < xy.length; i++) {
      const [x0, y0, x1, y1, x2, y2] = xy[i];
      const d1 = (px - x1) * (y0 - y1) - (x0 - x1) * (py - y1);
      const d2 = (px - x2) * (y1 - y2) - (x1 - x2) * (py - y2);
      const d3 = (px - x0) * (y2 - y0) - (x2 - x0) * (py - y0);
      if (!((d1 < 0 || d2 < 0 || d3 < 0) && (d1 > 0 || d2 > 0 || d3 > 0))) { out.tri = { i, xy: xy[i] }; break; }
    }
  }
  out.x = px; out.y = py;
  return out;
}

// The selection on a new frame: the hovered point is looked up again under the resting cursor; a pinned feature
// follows its track and a pinned triangle its three tracks (a feature's index, and an untracked feature's id,
// belong to one frame only).
function reselect() {
  if (S.hover) S.hover = hitTest(S.hover.x, S.hover.y);
  const p = S.pinned;
  if (!p) return;
  const ov = S.current.ov;
  if (p.track !== undefined) {
    const i = p.track >= 0 ? ov.features.track.indexOf(p.track) : -1;
    p.feature = i >= 0 ? { i, x: ov.features.x[i], y: ov.features.y[i] } : null;
    if (p.feature) { p.x = p.feature.x; p.y = p.feature.y; }
  }
  if (p.triIds !== undefined) {
    p.tri = null;
    const m = ov.mesh;
    if (m && S.on.mesh) {
      for (let i = 0; i < m.flipped.length; i++) {
        const ids = m.ids.slice(3 * i, 3 * i + 3).sort((a, b) => a - b).join(",");
        if (ids === p.triIds) { p.tri = { i, xy: m.xy[i] }; break; }
      }
    }
  }
}

function pin(sel) {  // what a pinned selection follows from frame to frame (see reselect)
  if (!sel || !S.current) return sel;
  const ov = S.current.ov;
  if (sel.feature) sel.track = ov.features.track[sel.feature.i];
  if (sel.tri) sel.triIds = ov.mesh.ids.slice(3 * sel.tri.i, 3 * sel.tri.i + 3).sort((a, b) => a - b).join(",");
  return sel;
}

function updateReadout() {
  const sel = S.pinned || S.hover;
  const el = $("readout");
  if (!S.current) return;
  const ov = S.current.ov, info = S.info, mm = info.px_per_mm;
  if (!sel) { el.textContent = `frame ${S.k}: ${ov.features.x.length} features` + (ov.mesh ? `, ${ov.mesh.xy.length} triangles` : "") + "\nhover the image"; return; }
  const lines = [`frame ${S.k}${S.pinned ? " (pinned: click to release)" : ""}`,
    `cursor x ${sel.x.toFixed(1)} px, y ${sel.y.toFixed(1)} px (${(sel.x / mm).toFixed(3)}, ${(sel.y / mm).toFixed(3)} mm)`];
  if (S.pinned && sel.track !== undefined && !sel.feature) {
    lines.push(sel.track >= 0 ? `track ${sel.track}: not measured in this frame` : "the pinned feature was not tracked: it belongs to its own frame only");
  }
  if (S.pinned && sel.triIds !== undefined && !sel.tri) lines.push(`triangle of tracks ${sel.triIds}: not in this frame's mesh`);
  if (sel.feature) {
    const f = ov.features, i = sel.feature.i;
    const kind = KIND_STYLE[f.kind[i]] ? KIND_STYLE[f.kind[i]].label : `kind ${f.kind[i]}`;
    lines.push(`feature ${f.id[i]}${f.track[i] >= 0 ? ` (track ${f.track[i]})` : ""}: ${kind}`);
    lines.push(`  x ${f.x[i].toFixed(2)} px, y ${f.y[i].toFixed(2)} px; quality ${f.quality[i].toFixed(2)}`);
    const a = ov.arrow_ids.indexOf(f.track[i]);
    const meas = a >= 0 ? ov.arrows[a] : null;
    if (meas) {
      const sg = ov.arrow_sigma ? ov.arrow_sigma[a] : -1;
      const sigma = sg < 0 ? "not estimated" : sg >= 1e9 ? "unbounded (its windows do not match)" : `${sg.toFixed(3)} px`;
      lines.push(`  displacement from the previous frame: dx ${meas[2].toFixed(3)}, dy ${meas[3].toFixed(3)} px; ` +
        `standard error ${sigma}`);
    }
    if (ov.truth) {
      const t = ov.truth, r2 = (0.1 * mm) ** 2;
      let tb = -1, td = r2;
      for (let j = 0; j < t.x.length; j++) {
        if (t.kind[j] !== f.kind[i]) continue;
        const d = (t.x[j] - f.x[i]) ** 2 + (t.y[j] - f.y[i]) ** 2;
        if (d < td) { td = d; tb = j; }
      }
      if (tb >= 0) {
        const err = Math.sqrt(td);
        lines.push(`  truth: feature ${t.id[tb]} at x ${t.x[tb].toFixed(2)}, y ${t.y[tb].toFixed(2)} px; ` +
          `position error ${err.toFixed(3)} px (${(1000 * err / mm).toFixed(1)} µm)`);
        if (meas && S.k > 0) {
          const tdx = t.x[tb] - t.prev_x[tb], tdy = t.y[tb] - t.prev_y[tb];
          lines.push(`  true displacement: dx ${tdx.toFixed(3)}, dy ${tdy.toFixed(3)} px; ` +
            `error ${Math.hypot(meas[2] - tdx, meas[3] - tdy).toFixed(3)} px`);
        }
      } else {
        lines.push("  truth: no true feature of this kind within 0.1 mm (a false feature?)");
      }
    }
  }
  if (sel.tri && ov.mesh) {
    const m = ov.mesh, i = sel.tri.i, ids = m.ids.slice(3 * i, 3 * i + 3);
    lines.push(`triangle of tracks ${ids.join(", ")}, frames ${m.frame_a}→${m.frame_b}:`);
    lines.push(m.flipped[i] ? "  flipped (orientation changed: a tracking error or a fold, not a strain)" :
      `  area change (strain) ${pct(m.change[i], 3)}`);
    if (!m.flipped[i] && m.values && m.values.exx) {
      const v = (q) => pct(m.values[q][i], 3);
      lines.push(`  exx ${v("exx")}, eyy ${v("eyy")}, exy ${v("exy")}`);
      lines.push(`  e1 ${v("e1")}, e2 ${v("e2")}`);
      for (const q of Object.keys(m.values)) if (!["area", "exx", "eyy", "exy", "e1", "e2"].includes(q)) lines.push(`  ${q} ${v(q)}`);
    }
  }
  el.textContent = lines.join("\n");
}

function canvasPoint(ev) {
  const r = view.getBoundingClientRect();
  return [((ev.clientX - r.left) * (view.width / r.width)) / S.scale, ((ev.clientY - r.top) * (view.height / r.height)) / S.scale];
}

// ---------------------------------------------------------------------------------------- interaction
function toggle(name, value) {
  const box = document.querySelector(`input[data-overlay="${name}"]`);
  S.on[name] = value === undefined ? !S.on[name] : value;
  if (box) box.checked = S.on[name];
  draw();
}

function setPlaying(on) {
  S.playing = on;
  $("play").innerHTML = on ? "&#10074;&#10074; pause" : "&#9654; play";
  if (on) { S.follow = false; $("follow").checked = false; tick(); }
}

async function tick() {
  if (!S.playing) return;
  const t0 = performance.now();
  const next = S.k + 1 >= S.n ? 0 : S.k + 1;
  await showFrame(next);
  const wait = Math.max(0, 1000 / Number($("speed").value) - (performance.now() - t0));
  setTimeout(() => requestAnimationFrame(tick), wait);
}

function step(d) { setPlaying(false); setFollow(false); S.direction = d < 0 ? -1 : 1; showFrame(S.k + d); }
function setFollow(on) { S.follow = on; $("follow").checked = on; if (on) showFrame(S.n - 1); }

document.querySelectorAll("input[data-overlay]").forEach((box) => {
  S.on[box.dataset.overlay] = box.checked;
  box.addEventListener("change", () => toggle(box.dataset.overlay, box.checked));
});
$("play").addEventListener("click", () => setPlaying(!S.playing));
$("prev").addEventListener("click", () => step(-1));
$("next").addEventListener("click", () => step(1));
$("slider").addEventListener("input", (e) => { setPlaying(false); setFollow(false); showFrame(Number(e.target.value)); });
$("follow").addEventListener("change", (e) => setFollow(e.target.checked));
$("span").addEventListener("change", (e) => { S.span = Number(e.target.value); showFrame(S.k); });
$("max-sigma").addEventListener("input", (e) => { S.maxSigma = Number(e.target.value) || 0; if (S.current) draw(); });
view.addEventListener("mousemove", (ev) => {
  const [x, y] = canvasPoint(ev);
  S.hover = hitTest(x, y);
  if (!S.pinned) { draw(); updateReadout(); }
});
view.addEventListener("mouseleave", () => { S.hover = null; if (!S.pinned) { draw(); updateReadout(); } });
view.addEventListener("click", (ev) => {
  if (S.tool !== "inspect") return;  // the gauge tools place on mouse up
  const [x, y] = canvasPoint(ev);
  S.pinned = S.pinned ? null : pin(hitTest(x, y));
  draw(); updateReadout();
});
view.addEventListener("mousedown", (ev) => {
  if (S.tool === "inspect") return;
  S.drag = { from: canvasPoint(ev), to: null };
});
view.addEventListener("mousemove", (ev) => {
  if (!S.drag || S.tool !== "extensometer") return;
  S.drag.to = canvasPoint(ev);
  draw();
});
view.addEventListener("mouseup", (ev) => {
  if (!S.drag) return;
  const from = S.drag.from, to = canvasPoint(ev);
  S.drag = null;
  if (S.tool === "gauge") placeGauge(from);
  else if (Math.hypot(to[0] - from[0], to[1] - from[1]) >= 3) placeGauge(from, to);
  else draw();
});

// ------------------------------------------------------------------------------------ map and gauge controls
$("map-quantity").addEventListener("change", (e) => { S.quantity = e.target.value; syncRange(); refreshMap(); });
$("range-fixed").addEventListener("change", () => syncRange());
$("range-value").addEventListener("change", () => syncRange());
$("arrow-gain-input").addEventListener("change", (e) => {
  const v = Number(e.target.value);
  S.arrowGain = Number.isFinite(v) && v > 0 ? v : DEFAULT_ARROW_GAIN;
  $("arrow-gain").textContent = String(S.arrowGain);
  buildLegend(); draw();
});
document.querySelectorAll('input[name="tool"]').forEach((r) => r.addEventListener("change", () => {
  S.tool = document.querySelector('input[name="tool"]:checked').value;
  view.style.cursor = S.tool === "inspect" ? "crosshair" : "cell";
}));
$("save-png").addEventListener("click", () => download(view.toDataURL("image/png"), `frame-${S.k}-${S.quantity}.png`));
$("save-csv").addEventListener("click", () => {
  if (S.gaugeQuery) download(`api/s/${S.sid}/gauge.csv?${S.gaugeQuery}`, `${S.gauge.kind}.csv`);
});

// A fixed colour range (± the value, in %) holds for every frame and quantity until unticked; unticked, each
// quantity has the session's own scale. Ticking it starts from the scale shown.
function syncRange() {
  if ($("range-fixed").checked) {
    const v = Number($("range-value").value);
    S.fixedRange = Number.isFinite(v) && v > 0 ? v / 100 : null;
  } else {
    S.fixedRange = null;
    if (S.current) $("range-value").value = String(+(100 * mapScale(S.current.ov)).toPrecision(3));
  }
  refreshMap();
}

function refreshMap() {
  if (!S.current) return;
  draw();
  drawColorbar(mapScale(S.current.ov), S.current.ov.mesh);
}

function download(href, name) {
  const a = document.createElement("a");
  a.href = href; a.download = name;
  document.body.appendChild(a); a.click(); a.remove();
}

function clearGauge() {
  S.gauge = null; S.gaugeQuery = null;
  $("gauge-panel").hidden = true;
  $("save-csv").disabled = true;
}

async function placeGauge(a, b = null) {
  const q = new URLSearchParams({ frame: String(S.k), x: a[0].toFixed(2), y: a[1].toFixed(2),
    radius_mm: String(Number($("gauge-radius").value) || 1) });
  if (b) { q.set("x2", b[0].toFixed(2)); q.set("y2", b[1].toFixed(2)); }
  const r = await fetch(`api/s/${S.sid}/gauge?${q}`);
  if (!r.ok) { setText("notes", `gauge: ${await r.text()}`); return; }
  S.gauge = await r.json();
  S.gaugeQuery = q.toString();
  $("gauge-panel").hidden = false;
  $("save-csv").disabled = false;
  draw();
  drawGaugePlot();
}

// The gauge's time plot: its cumulative strain components (or the extensometer's length change) in % against the
// frame, the frame shown marked.
const GAUGE_SERIES = { gauge: [["exx", "#d55e00"], ["eyy", "#0072b2"], ["exy", "#009e73"], ["e1", "#cc79a7"], ["e2", "#56b4e9"]],
  extensometer: [["length_change", "#d55e00"]] };
function drawGaugePlot() {
  const g = S.gauge;
  if (!g) return;
  const c = $("gauge-plot"), p = c.getContext("2d"), cols = g.columns, n = cols.frame.length;
  const series = GAUGE_SERIES[g.kind];
  let lo = 0, hi = 0;
  for (const [name] of series) cols[name].forEach((v, i) => { if (cols.ok[i] && v !== null) { lo = Math.min(lo, v); hi = Math.max(hi, v); } });
  if (hi - lo < 1e-4) { hi += 5e-5; lo -= 5e-5; }
  const L = 56, R = 8, T = 8, B = 30, w = c.width - L - R, h = c.height - T - B;
  const X = (i) => L + (n > 1 ? (i / (n - 1)) * w : 0), Y = (v) => T + (1 - (v - lo) / (hi - lo)) * h;
  p.clearRect(0, 0, c.width, c.height);
  p.strokeStyle = "#999"; p.lineWidth = 1; p.strokeRect(L, T, w, h);
  p.fillStyle = "#111"; p.font = "10px system-ui, sans-serif"; p.textAlign = "right";
  for (const v of [lo, 0, hi]) { p.fillText(`${(100 * v).toPrecision(2)} %`, L - 3, Y(v) + 3); }
  p.strokeStyle = "#ccc"; p.beginPath(); p.moveTo(L, Y(0)); p.lineTo(L + w, Y(0)); p.stroke();
  p.textAlign = "center"; p.fillText("frame", L + w / 2, c.height - 4);
  p.fillText("0", L, T + h + 12); p.fillText(String(n - 1), L + w, T + h + 12);
  let lx = L + 4;
  for (const [name, color] of series) {
    p.strokeStyle = color; p.lineWidth = 1.5; p.beginPath();
    let on = false;
    cols[name].forEach((v, i) => {
      if (!cols.ok[i] || v === null) { on = false; return; }
      if (on) p.lineTo(X(i), Y(v)); else p.moveTo(X(i), Y(v));
      on = true;
    });
    p.stroke();
    p.fillStyle = color; p.textAlign = "left"; p.fillText(name, lx, T + 10); lx += p.measureText(name).width + 8;
  }
  p.strokeStyle = "#000"; p.setLineDash([3, 3]); p.beginPath(); p.moveTo(X(S.k), T); p.lineTo(X(S.k), T + h); p.stroke();
  p.setLineDash([]);
  const k = S.k, mm = S.info.px_per_mm;
  let note;
  if (!cols.ok[k]) note = `frame ${k}: ${cols.reason[k] || "not measured"}`;
  else if (g.kind === "gauge") {
    note = `frame ${k}: at x ${cols.x[k].toFixed(1)}, y ${cols.y[k].toFixed(1)} px, moved ${cols.dx[k].toFixed(2)}, ${cols.dy[k].toFixed(2)} px` +
      ` since frame ${g.reference_frame}; exx ${pct(cols.exx[k], 3)} ± ${(100 * cols.exx_sigma[k]).toFixed(3)}, ` +
      `eyy ${pct(cols.eyy[k], 3)} ± ${(100 * cols.eyy_sigma[k]).toFixed(3)}, exy ${pct(cols.exy[k], 3)} ± ${(100 * cols.exy_sigma[k]).toFixed(3)}, ` +
      `e1 ${pct(cols.e1[k], 3)}, e2 ${pct(cols.e2[k], 3)} (${cols.n_points[k]} points within ${(g.radius_px / mm).toFixed(2)} mm)`;
  } else {
    note = `frame ${k}: length ${cols.length_px[k].toFixed(2)} px (${(cols.length_px[k] / mm).toFixed(3)} mm), change ${pct(cols.length_change[k], 3)} ± ${(100 * cols.length_change_sigma[k]).toFixed(3)} % since frame ${g.reference_frame}`;
  }
  setText("gauge-title", g.kind === "gauge" ? `Gauge at (${g.at[0].toFixed(1)}, ${g.at[1].toFixed(1)}) px of frame ${g.reference_frame}` :
    `Extensometer (${g.at[0].toFixed(1)}, ${g.at[1].toFixed(1)}) to (${g.to[0].toFixed(1)}, ${g.to[1].toFixed(1)}) px of frame ${g.reference_frame}`);
  setText("gauge-note", note);
}
document.addEventListener("keydown", (ev) => {
  if (ev.target.tagName === "SELECT" || (ev.target.tagName === "INPUT" && ev.target.type !== "checkbox" && ev.target.type !== "range")) return;
  const big = ev.shiftKey ? 10 : 1;
  if (ev.key === "ArrowRight") { step(big); ev.preventDefault(); }
  else if (ev.key === "ArrowLeft") { step(-big); ev.preventDefault(); }
  else if (ev.key === "Home") { step(-S.k); ev.preventDefault(); }
  else if (ev.key === "End") { step(S.n - 1 - S.k); ev.preventDefault(); }
  else if (ev.key === " ") { setPlaying(!S.playing); ev.preventDefault(); }
  else if (ev.key === "f" || ev.key === "F") setFollow(!S.follow);
  else if (/^[1-7]$/.test(ev.key)) toggle(["features", "matches", "tails", "mesh", "arrows", "outline", "window"][Number(ev.key) - 1]);
});

// ------------------------------------------------------------------------------------------ following
function listen() {
  const es = new EventSource("api/events");
  es.addEventListener("state", async (e) => {
    const st = JSON.parse(e.data);
    if (!S.info || st.sid !== S.sid) { await loadInfo(); return; }
    const resultsNow = st.has_results && !S.info.results;
    S.n = st.n_frames;
    S.info.status = st.status;
    if (!S.follow) setSliderMax();  // while following, the frame drawn moves it (one repaint, not two)
    setStatus(st);
    if (resultsNow) { await loadInfo(); return; }  // the trial's analysis replaced the live overlays
    if (S.follow && !st.live && S.n > 0) showFrame(S.n - 1);
  });
  es.addEventListener("live", (e) => {  // frame k was analysed live; its overlays are fetched when drawn
    const ev = JSON.parse(e.data);
    if (ev.frame >= S.n) S.n = ev.frame + 1;  // ahead of the last "state"
    window.viewerStats.liveReceived.push({ frame: ev.frame, exposure: ev.exposure_time, received: Date.now() / 1000 });
    S.overlays.delete(`${S.sid}/${ev.frame}/${S.span}`);  // fetched before it was analysed: not live yet
    if (S.follow) showLive(ev.frame);
  });
}

// A live frame is drawn at most every LIVE_DRAW_MS (the newest one waiting when the time comes): drawing is most of
// the page's CPU, and the live analysis runs on the same machine.
const LIVE_DRAW_MS = 66;
let liveTimer = null, liveNext = -1, liveDrawn = 0;
function showLive(k) {
  liveNext = k;
  if (liveTimer !== null) return;
  liveTimer = setTimeout(() => {
    liveTimer = null; liveDrawn = performance.now();
    if (S.follow) showFrame(liveNext, true);
  }, Math.max(0, liveDrawn + LIVE_DRAW_MS - performance.now()));
}

loadInfo().then(listen).catch((e) => { window.viewerStats.errors.push(String(e)); $("notes").textContent = String(e); });
