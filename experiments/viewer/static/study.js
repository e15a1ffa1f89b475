// The study overview page: every trial of the data directory the viewer was pointed at (GET api/study), their
// stretch profiles on one plot coloured by surface, and a click through to each trial (POST api/study/open/i).
"use strict";

// Okabe-Ito, one colour per surface in the order they appear.
const SURFACE_COLORS = ["#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000"];
const $ = (id) => document.getElementById(id);
window.studyStats = { errors: [] };

function pct(v) { return v === null || v === undefined ? "–" : `${(100 * v).toFixed(3)}`; }
function cell(text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  return td;
}

async function load() {
  const r = await fetch("api/study");
  const data = await r.json();
  if (!data.available) {
    $("status").textContent = data.reason;
    return data;
  }
  $("title").textContent = `skinstretch study overview: ${data.directory}`;
  $("status").textContent = `${data.trials.length} trials${data.following ? ", following the newest" : ""}`;
  const head = ["trial", "subject", "protocol", "surface", "status", "method", "frames", "travel mm",
    "edge p5 %", "edge p95 %", "cum. e1 %", "cum. e2 %", "warnings"];
  $("trials").tHead.innerHTML = "<tr>" + head.map((h) => `<th>${h}</th>`).join("") + "</tr>";
  const body = $("trials").tBodies[0];
  body.innerHTML = "";
  const surfaces = [...new Set(data.trials.map((t) => t.surface))];
  data.trials.forEach((t, i) => {
    const tr = document.createElement("tr");
    tr.dataset.index = String(i);
    tr.className = "trial" + (t.shown ? " shown" : "");
    tr.title = "open this trial in the viewer";
    const color = SURFACE_COLORS[surfaces.indexOf(t.surface) % SURFACE_COLORS.length];
    tr.append(cell(t.name), cell(t.subject), cell(t.protocol), cell(t.surface), cell(t.status), cell(t.method || "–"),
      cell(String(t.n_frames)), cell(t.travel_mm === null ? "–" : t.travel_mm.toFixed(2)), cell(pct(t.edge_change_p5)),
      cell(pct(t.edge_change_p95)), cell(pct(t.cumulative_e1)), cell(pct(t.cumulative_e2)),
      cell(t.warnings.join(" · "), t.warnings.length ? "warn" : ""));
    tr.children[3].style.borderLeft = `6px solid ${color}`;
    tr.addEventListener("click", () => openTrial(i));
    body.appendChild(tr);
  });
  drawProfiles(data.trials, surfaces);
  return data;
}

async function openTrial(i) {
  const r = await fetch(`api/study/open/${i}`, { method: "POST" });
  if (!r.ok) { window.studyStats.errors.push(await r.text()); return; }
  window.location.href = "./";
}

function drawProfiles(trials, surfaces) {
  const c = $("profiles"), g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  const withProfile = trials.filter((t) => t.profile);
  let x0 = Infinity, x1 = -Infinity, lo = 0, hi = 0;
  for (const t of withProfile) {
    t.profile.position_mm.forEach((x, i) => {
      const v = t.profile.change[i];
      if (v === null) return;
      x0 = Math.min(x0, x); x1 = Math.max(x1, x); lo = Math.min(lo, v); hi = Math.max(hi, v);
    });
  }
  const L = 56, R = 150, T = 10, B = 34, w = c.width - L - R, h = c.height - T - B;
  g.strokeStyle = "#999"; g.strokeRect(L, T, w, h);
  g.fillStyle = "#111"; g.font = "12px system-ui, sans-serif";
  if (!Number.isFinite(x0)) { g.fillText("no analysed trial has a stretch profile", L + 10, T + 20); return; }
  if (hi - lo < 1e-5) { hi += 1e-5; lo -= 1e-5; }
  const X = (x) => L + ((x - x0) / Math.max(1e-9, x1 - x0)) * w, Y = (v) => T + (1 - (v - lo) / (hi - lo)) * h;
  g.strokeStyle = "#ccc"; g.beginPath(); g.moveTo(L, Y(0)); g.lineTo(L + w, Y(0)); g.stroke();
  g.textAlign = "right";
  for (const v of [lo, 0, hi]) g.fillText(`${(100 * v).toPrecision(2)} %`, L - 4, Y(v) + 4);
  g.textAlign = "center";
  g.fillText("position along the sliding direction (mm)", L + w / 2, c.height - 6);
  g.fillText(x0.toFixed(1), L, T + h + 14); g.fillText(x1.toFixed(1), L + w, T + h + 14);
  for (const t of withProfile) {
    g.strokeStyle = SURFACE_COLORS[surfaces.indexOf(t.surface) % SURFACE_COLORS.length];
    g.lineWidth = 1.5; g.beginPath();
    let on = false;
    t.profile.position_mm.forEach((x, i) => {
      const v = t.profile.change[i];
      if (v === null) { on = false; return; }
      if (on) g.lineTo(X(x), Y(v)); else g.moveTo(X(x), Y(v));
      on = true;
    });
    g.stroke();
  }
  g.textAlign = "left";
  surfaces.forEach((s, i) => {
    g.fillStyle = SURFACE_COLORS[i % SURFACE_COLORS.length];
    g.fillRect(L + w + 12, T + 6 + 18 * i, 14, 4);
    g.fillStyle = "#111";
    g.fillText(`${s} (${withProfile.filter((t) => t.surface === s).length})`, L + w + 32, T + 12 + 18 * i);
  });
}

$("follow").addEventListener("click", async () => {
  await fetch("api/study/follow", { method: "POST" });
  window.location.href = "./";
});
load().catch((e) => { window.studyStats.errors.push(String(e)); $("status").textContent = String(e); });
