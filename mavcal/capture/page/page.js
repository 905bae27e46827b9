// mavcal capture page: draws the pose to hold next and the vehicle now, from rotation matrices
// C (body FRD -> NED, magnetic north) sent by the server over Server-Sent Events.
// No external script; every request carries the session token of this page's URL.
"use strict";

const TOKEN = new URLSearchParams(location.search).get("t") || "";
const SVGNS = "http://www.w3.org/2000/svg";
const $ = (id) => document.getElementById(id);
let state = {};
let lastN = null;
let countedUntil = 0;

// ------------------------------------------------------------------ small vector helpers
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const mul = (C, v) => [dot(C[0], v), dot(C[1], v), dot(C[2], v)];  // body -> world
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.sqrt(dot(a, a));
const unit = (a) => scale(a, 1 / (norm(a) || 1));
const col = (C, j) => [C[0][j], C[1][j], C[2][j]];
const deg = (r) => r * 180 / Math.PI;

function el(name, attrs, parent) {
  const e = document.createElementNS(SVGNS, name);
  for (const k in attrs) e.setAttribute(k, attrs[k]);
  if (parent) parent.appendChild(e);
  return e;
}

// ------------------------------------------------------------------ camera
// World NED. The camera looks along f (azimuth az from north, el below the horizon).
function camera(azDeg, elDeg, cx, cy, k, dist) {
  const az = azDeg * Math.PI / 180, e = elDeg * Math.PI / 180;
  const f = [Math.cos(e) * Math.cos(az), Math.cos(e) * Math.sin(az), Math.sin(e)];
  const r = unit(cross(f, [0, 0, -1]));
  const u = cross(r, f);
  const eye = scale(f, -dist);
  return {
    f, eye,
    project(p) {
      const q = sub(p, eye);
      const depth = dot(q, f);
      const s = dist / depth;
      return [cx + k * s * dot(q, r), cy - k * s * dot(q, u), depth];
    },
  };
}

// ------------------------------------------------------------------ the vehicle model (body FRD)
const L = 1.1, W = 0.8, H = 0.24, GROUND = 1.25, G_HALF = 2.5;
const V = [];  // box corners: index bits x(+), y(+), z(+)
for (let i = 0; i < 8; i++) V.push([(i & 1) ? L : -L, (i & 2) ? W : -W, (i & 4) ? H : -H]);
// faces as corner lists with their outward normal and colour
const FACES = [
  { idx: [0, 1, 3, 2], n: [0, 0, -1], fill: "#1e88e5", name: "top" },      // z = -H: top
  { idx: [4, 6, 7, 5], n: [0, 0, 1], fill: "#f57c00", name: "bottom" },    // z = +H: bottom
  { idx: [1, 5, 7, 3], n: [1, 0, 0], fill: "#b0bec5", name: "front" },
  { idx: [0, 2, 6, 4], n: [-1, 0, 0], fill: "#90a4ae", name: "back" },
  { idx: [2, 3, 7, 6], n: [0, 1, 0], fill: "#a7b6bd", name: "right" },
  { idx: [0, 4, 5, 1], n: [0, -1, 0], fill: "#a7b6bd", name: "left" },
];
const NOSE_TIP = [L + 0.75, 0, 0];
const NOSE_BASE = [[L, -0.32, -H * 0.9], [L, 0.32, -H * 0.9], [L, 0.32, H * 0.9], [L, -0.32, H * 0.9]];
// a white arrow printed on the top (towards the nose) and a dark cross on the bottom
const TOP_ARROW = [[0.75, 0, -H - 0.001], [0.05, -0.42, -H - 0.001], [0.05, -0.16, -H - 0.001], [-0.7, -0.16, -H - 0.001],
                   [-0.7, 0.16, -H - 0.001], [0.05, 0.16, -H - 0.001], [0.05, 0.42, -H - 0.001]];
const BOTTOM_X = [[[-0.6, -0.45, H + 0.001], [0.6, 0.45, H + 0.001]], [[-0.6, 0.45, H + 0.001], [0.6, -0.45, H + 0.001]]];

function polyPoints(pts) { return pts.map((p) => p[0].toFixed(1) + "," + p[1].toFixed(1)).join(" "); }

function hull(pts) {  // convex hull (monotone chain) of 2-D points
  const p = pts.slice().sort((a, b) => a[0] - b[0] || a[1] - b[1]);
  const turn = (o, a, b) => (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
  const lower = [], upper = [];
  for (const q of p) { while (lower.length >= 2 && turn(lower[lower.length - 2], lower[lower.length - 1], q) <= 0) lower.pop(); lower.push(q); }
  for (const q of p.slice().reverse()) { while (upper.length >= 2 && turn(upper[upper.length - 2], upper[upper.length - 1], q) <= 0) upper.pop(); upper.push(q); }
  return lower.slice(0, -1).concat(upper.slice(0, -1));
}

function inside(p, poly) {  // p within the convex polygon (either winding)
  let sign = 0;
  for (let i = 0; i < poly.length; i++) {
    const a = poly[i], b = poly[(i + 1) % poly.length];
    const z = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]);
    if (z !== 0) { if (sign && Math.sign(z) !== sign) return false; sign = Math.sign(z); }
  }
  return true;
}

function drawGround(svg, cam) {
  const g = GROUND, s = G_HALF;
  const corners = [[s, -s, g], [s, s, g], [-s, s, g], [-s, -s, g]].map((p) => cam.project(p));
  el("polygon", { points: polyPoints(corners), fill: "#e8efe6", stroke: "#9fb39a", "stroke-width": 2 }, svg);
  for (let i = -2; i <= 2; i++) {  // grid lines
    const a = cam.project([i, -s, g]), b = cam.project([i, s, g]);
    const c = cam.project([-s, i, g]), d = cam.project([s, i, g]);
    el("line", { x1: a[0], y1: a[1], x2: b[0], y2: b[1], stroke: "#cbd8c7", "stroke-width": 1 }, svg);
    el("line", { x1: c[0], y1: c[1], x2: d[0], y2: d[1], stroke: "#cbd8c7", "stroke-width": 1 }, svg);
  }
  // magnetic north: an arrow on the ground and a big N at its end
  const tail = cam.project([-s + 0.3, 0, g]), head = cam.project([s + 0.2, 0, g]);
  const l = cam.project([s - 0.35, -0.35, g]), r = cam.project([s - 0.35, 0.35, g]);
  el("line", { x1: tail[0], y1: tail[1], x2: head[0], y2: head[1], stroke: "#14202b", "stroke-width": 5 }, svg);
  el("polygon", { points: polyPoints([head, l, r]), fill: "#14202b" }, svg);
  const n = cam.project([s + 0.75, 0, g]);
  el("circle", { cx: n[0], cy: n[1], r: 19, fill: "#fff", stroke: "#14202b", "stroke-width": 3 }, svg);
  const t = el("text", { x: n[0], y: n[1] + 10, "text-anchor": "middle", "font-size": 28, "font-weight": "bold", fill: "#14202b" }, svg);
  t.textContent = "N";
  for (const [lab, p] of [["E", [0, s + 0.35, g]], ["S", [-s - 0.35, 0, g]], ["W", [0, -s - 0.35, g]]]) {
    const q = cam.project(p);
    const u = el("text", { x: q[0], y: q[1] + 7, "text-anchor": "middle", "font-size": 20, fill: "#6b7b68" }, svg);
    u.textContent = lab;
  }
}

function drawVehicle(svg, cam, C, ghost) {
  const W3 = V.map((v) => mul(C, v));
  // shadow on the ground, straight below
  const shadow = hull(W3.concat([mul(C, NOSE_TIP)]).map((p) => cam.project([p[0], p[1], GROUND])));
  el("polygon", { points: polyPoints(shadow), fill: "#000", opacity: 0.16 }, svg);
  // a pole from the centre to the ground makes the height readable
  const c0 = cam.project([0, 0, 0]), c1 = cam.project([0, 0, GROUND]);
  el("line", { x1: c0[0], y1: c0[1], x2: c1[0], y2: c1[1], stroke: "#7a8a86", "stroke-width": 2, "stroke-dasharray": "5 5" }, svg);
  const polys = [];
  for (const f of FACES) {
    const pts = f.idx.map((i) => W3[i]);
    const centre = scale(pts.reduce(add), 0.25);
    const nW = mul(C, f.n);
    if (dot(nW, sub(cam.eye, centre)) <= 0) continue;  // facing away
    polys.push({ pts, fill: f.fill, depth: dot(sub(centre, cam.eye), cam.f), name: f.name });
  }
  // the nose: a red pyramid on the front face
  const tip = mul(C, NOSE_TIP), base = NOSE_BASE.map((b) => mul(C, b));
  const nosePolys = [];
  for (let i = 0; i < 4; i++) {
    const a = base[i], b = base[(i + 1) % 4];
    const centre = scale(add(add(a, b), tip), 1 / 3);
    const nW = cross(sub(b, a), sub(tip, a));
    const out = dot(nW, sub(centre, mul(C, [L, 0, 0]))) > 0 ? nW : scale(nW, -1);
    if (dot(out, sub(cam.eye, centre)) <= 0) continue;
    nosePolys.push({ pts: [a, b, tip], fill: "#d32f2f", depth: dot(sub(centre, cam.eye), cam.f) - 0.05 });
  }
  polys.push(...nosePolys);
  // a nose behind the body (pointing away, or down under it) shows through, faint and dashed
  const outline = hull(W3.map((p) => cam.project(p)));
  const noseHidden = dot(mul(C, [1, 0, 0]), sub(cam.eye, mul(C, [L, 0, 0]))) < 0 && inside(cam.project(tip), outline);
  polys.sort((p, q) => q.depth - p.depth);
  const g = el("g", { opacity: ghost ? 0.55 : 1 }, svg);
  for (const p of polys) {
    el("polygon", { points: polyPoints(p.pts.map((q) => cam.project(q))), fill: p.fill, stroke: "#263238",
                    "stroke-width": 2, "stroke-linejoin": "round" }, g);
    if (p.name === "top") {
      el("polygon", { points: polyPoints(TOP_ARROW.map((q) => cam.project(mul(C, q)))), fill: "#fff", opacity: 0.95 }, g);
    } else if (p.name === "bottom") {
      for (const [a, b] of BOTTOM_X) {
        const pa = cam.project(mul(C, a)), pb = cam.project(mul(C, b));
        el("line", { x1: pa[0], y1: pa[1], x2: pb[0], y2: pb[1], stroke: "#5d2c00", "stroke-width": 5 }, g);
      }
    }
  }
  if (noseHidden) {  // a nose pointing away shows through the body, faint and dashed
    const pts = [tip].concat(base).map((q) => cam.project(q));
    el("polygon", { points: polyPoints(hull(pts)), fill: "#d32f2f", opacity: 0.45, stroke: "#8e0000",
                    "stroke-width": 2, "stroke-dasharray": "6 4" }, g);
  }
}

const SCENE_CAM = () => camera(25, 55, 220, 134, 60, 11);

// a vehicle that cannot be turned over (--max-tilt): its raised edge rests on a block (a beam) on the ground
function drawBlock(svg, cam, C) {
  if (C[2][2] > Math.cos(2 * Math.PI / 180)) return;  // (nearly) level: no block
  const bottom = V.filter((v) => v[2] > 0).map((v) => mul(C, v));  // the bottom face's corners (FRD: +z down)
  bottom.sort((a, b) => a[2] - b[2]);
  // the raised edge: its two highest corners, or the highest one alone when tilted towards a corner
  const a = bottom[0], b = bottom[1][2] - bottom[0][2] < 0.25 ? bottom[1] : bottom[0];
  const along = unit(sub([b[0], b[1], 0], [a[0], a[1], 0]));
  const u = norm(sub(b, a)) > 1e-6 ? along : [1, 0, 0];
  const out = unit(sub([a[0] + b[0], a[1] + b[1], 0], [0, 0, 0]));  // away from the centre, on the ground
  const d = 0.3, top = Math.min(a[2], b[2]);
  const e0 = add(add(a, scale(u, -0.15)), scale(out, -d)), e1 = add(add(b, scale(u, 0.15)), scale(out, -d));
  const e2 = add(e1, scale(out, 2 * d)), e3 = add(e0, scale(out, 2 * d));
  const tops = [e0, e1, e2, e3].map((x) => [x[0], x[1], top]), base = tops.map((x) => [x[0], x[1], GROUND]);
  const faces = [];
  for (let i = 0; i < 4; i++) {
    const j = (i + 1) % 4, f = [tops[i], tops[j], base[j], base[i]];
    faces.push({ f, depth: dot(sub(scale(f.reduce(add), 0.25), cam.eye), cam.f) });
  }
  faces.push({ f: tops, depth: dot(sub(scale(tops.reduce(add), 0.25), cam.eye), cam.f) });
  faces.sort((x, y) => y.depth - x.depth);
  const g = el("g", { "data-block": "1" }, svg);
  for (const x of faces) {
    el("polygon", { points: polyPoints(x.f.map((pt) => cam.project(pt))), fill: "#c49a5c", stroke: "#5d4322",
                    "stroke-width": 2, "stroke-linejoin": "round" }, g);
  }
  const c = cam.project([(e0[0] + e2[0]) / 2, (e0[1] + e2[1]) / 2, GROUND]);
  const t = el("text", { x: c[0], y: c[1] + 22, "text-anchor": "middle", "font-size": 16, fill: "#5d4322" }, g);
  t.textContent = "block";
}

function drawScene(id, C, waiting, block) {
  const svg = $(id);
  svg.textContent = "";
  const cam = SCENE_CAM();
  drawGround(svg, cam);
  if (C && block) drawBlock(svg, cam, C);
  if (C) drawVehicle(svg, cam, C, false);
  else {
    const t = el("text", { x: 220, y: 140, "text-anchor": "middle", "font-size": 24, fill: "#4a5a68" }, svg);
    t.textContent = waiting || "waiting for the vehicle...";
  }
}

// ------------------------------------------------------------------ the sphere of poses done
function drawSphere(downDirs, next) {
  const svg = $("sphere");
  svg.textContent = "";
  // the body frame seen from front-left, a little above; the vehicle level in the middle
  const cam = camera(-140, 28, 150, 132, 48, 12);
  const R = 2.1;
  el("circle", { cx: 150, cy: 132, r: 48 * R * 12 / 12.0, fill: "#f3f6f9", stroke: "#b8c4ce", "stroke-width": 2 }, svg);
  // equator
  const eq = [];
  for (let i = 0; i <= 48; i++) { const a = i / 48 * 2 * Math.PI; eq.push(cam.project([R * Math.cos(a), R * Math.sin(a), 0])); }
  el("polyline", { points: polyPoints(eq), fill: "none", stroke: "#d0d9e0", "stroke-width": 1.5 }, svg);
  const dots = downDirs.map((d) => ({ p: scale(unit(d), R), kind: "done" }));
  if (next) dots.push({ p: scale(unit(next), R), kind: "next" });
  const behind = (d) => dot(sub(d.p, cam.eye), cam.f) > dot(scale(cam.eye, -1), cam.f);
  const drawDot = (d) => {
    const q = cam.project(d.p);
    const far = behind(d);
    if (d.kind === "next") {
      el("circle", { cx: q[0], cy: q[1], r: 13, fill: "none", stroke: "#b25b00", "stroke-width": 5,
                     "stroke-dasharray": far ? "4 4" : "", class: "next-dot" }, svg);
    } else {
      el("circle", { cx: q[0], cy: q[1], r: far ? 8 : 11, fill: "#1b7f3b", opacity: far ? 0.4 : 0.95,
                     stroke: "#fff", "stroke-width": 2 }, svg);
    }
  };
  dots.filter(behind).forEach(drawDot);
  drawVehicle(svg, cam, [[0.8, 0, 0], [0, 0.8, 0], [0, 0, 0.8]], false);
  dots.filter((d) => !behind(d)).forEach(drawDot);
}

// ------------------------------------------------------------------ hold ring and bars
function setRing(frac, text, done) {
  const c = 2 * Math.PI * 80;
  const f = $("ring-fill");
  f.setAttribute("stroke-dasharray", c.toFixed(1));
  f.setAttribute("stroke-dashoffset", (c * (1 - Math.max(0, Math.min(1, frac)))).toFixed(1));
  f.classList.toggle("done", !!done);
  $("ring-text").textContent = text;
}

function sensorName(s) {
  const m = /^(accel|compass)(\d+)$/.exec(s);
  if (!m) return s;
  return (m[1] === "accel" ? "Accelerometer " : "Compass ") + m[2];  // numbered from 0, as the verdicts
}

function drawBars(sensors, st) {
  const box = $("bars");
  box.textContent = "";
  if (!sensors || !sensors.length) {
    const p = document.createElement("p");
    p.className = "bar-label";
    p.textContent = st && st.n < 6 ? "measured after the first six poses" : "measuring...";
    box.appendChild(p);
    return;
  }
  for (const s of sensors) {
    const row = document.createElement("div");
    row.className = "bar-row";
    const lab = document.createElement("div");
    lab.className = "bar-label";
    const name = document.createElement("span");
    name.textContent = (s.met ? "\u2713 " : "") + sensorName(s.sensor);
    const num = document.createElement("span");
    num.className = "num";
    num.textContent = s.bound_deg == null ? s.what : s.determined === false ?
      `${s.what} not determined (95 % bound above ${s.what === "heading" ? 90 : 45}\u00b0)` :
      `${s.what} ${s.bound_deg.toFixed(2)}\u00b0 (aim ${s.target_deg}\u00b0)`;
    lab.append(name, num);
    if (s.dropped) num.textContent = "left out";
    const bar = document.createElement("div");
    bar.className = "bar" + (s.met ? " met" : "") + (s.bound_deg == null ? " none" : "") +
      (s.blocked ? " blocked" : "") + (s.dropped ? " dropped" : "");
    bar.setAttribute("role", "meter");
    bar.setAttribute("aria-label", sensorName(s.sensor) + " " + s.what);
    const fill = document.createElement("div");
    const frac = s.bound_deg == null ? 1 : Math.min(1, s.target_deg / Math.max(s.bound_deg, 1e-9));
    fill.style.width = (100 * frac).toFixed(0) + "%";
    bar.appendChild(fill);
    row.append(lab, bar);
    if (s.needs && !s.blocked && !s.dropped) {
      const more = document.createElement("p");
      more.className = "needs-why";
      more.textContent = "more poses needed: " + s.needs;
      row.appendChild(more);
    }
    if (s.blocked && !s.dropped) {
      const why = document.createElement("p");
      why.className = "blocked-why";
      why.textContent = "\u2717 cannot get there: " + s.blocked;
      row.appendChild(why);
    }
    box.appendChild(row);
  }
  const offer = (st && st.finish_without) || [];
  const fin = $("finish");
  fin.hidden = offer.length === 0;
  fin.textContent = "Finish without " + offer.map(sensorName).join(", ");
}

// ------------------------------------------------------------------ matching the pose
function angleBetween(Ca, Cb) {  // rotation angle of Ca^T Cb, degrees
  let tr = 0;
  for (let i = 0; i < 3; i++) tr += dot(col(Ca, i), col(Cb, i));
  return deg(Math.acos(Math.max(-1, Math.min(1, (tr - 1) / 2))));
}
function downAngle(Ca, Cb) {  // between the body directions that point down
  return deg(Math.acos(Math.max(-1, Math.min(1, dot(Ca[2], Cb[2])))));
}

// Before the first fit the compass is uncalibrated: its heading can be tens of degrees off. Then
// the live vehicle is drawn with its measured tilt turned to the target's heading (the rotation
// about the vertical that brings it closest), and only the side down has to match.
function shownLive(st, live) {
  if (!live || !live.C) return null;
  if (live.heading_source === "fit" || !st || !st.next) return live.C;
  const T = st.next.C, Cl = live.C;
  const M = [0, 1, 2].map((i) => [0, 1, 2].map((j) => dot(Cl[i], T[j])));  // Cl T^T
  const psi = Math.atan2(M[0][1] - M[1][0], M[0][0] + M[1][1]);
  const c = Math.cos(psi), s = Math.sin(psi);
  const Rz = [[c, -s, 0], [s, c, 0], [0, 0, 1]];
  return [0, 1, 2].map((i) => [0, 1, 2].map((j) => Rz[i][0] * Cl[0][j] + Rz[i][1] * Cl[1][j] + Rz[i][2] * Cl[2][j]));
}

function instruction(st, live) {
  if (!st || !st.next) return ["Waiting for the vehicle...", ""];
  if (!live || !live.C) return ["Hold the vehicle as shown", ""];
  const dn = downAngle(st.next.C, live.C), all = angleBetween(st.next.C, live.C);
  const rough = live.heading_source !== "fit";  // heading not measured yet: the side down must match
  const match = dn < 25 && (rough || all < 35);
  $("live-figure").classList.toggle("match", match);
  $("live-figure").classList.toggle("near", !match && dn < 25);
  if (performance.now() < countedUntil) return ["\u2713 Pose counted. Now move to the next one", "good"];
  if (dn >= 25) return ["Tip it over until the same side faces down", "warn"];
  if (!match) return ["Good side down. Now turn it until the nose points the same way", "warn"];
  if (!live.still) return ["That's it. Now hold it still", "good"];
  return ["\u2713 That's it. Keep holding still...", "good"];
}

// ------------------------------------------------------------------ rendering the state
const PHASES = {
  starting: ["connecting...", ""], capturing: ["capturing", ""], fitting: ["calculating...", "warn"],
  result: ["check and write", "warn"], writing: ["writing...", "warn"], written: ["written", "good"],
  declined: ["nothing written", ""], failed: ["write failed", "bad"], aborted: ["aborted", "bad"],
  ended: ["finished", ""],
};

function renderCapture(st, live) {
  const [text, cls] = instruction(st, live);
  const ins = $("instruction");
  ins.textContent = st && st.done && !state.result ? (st.aborted ? "Stopped: " + st.reason : "Done capturing. Calculating...") : text;
  ins.className = "instruction " + (st && st.aborted ? "bad" : cls);
  drawScene("scene-target", st && st.next ? st.next.C : null, st && st.done ? "done" : "waiting for the first advice...",
            Boolean(st && st.max_tilt));
  $("skip").hidden = !(st && st.next && !st.done);
  drawScene("scene-live", shownLive(st, live));
  $("pose-words").textContent = st && st.next ? "In words: " + st.next.words : "";
  $("pose-for").textContent = st && st.next && st.advice_for ? "This pose helps " + sensorName(st.advice_for) + " most." : "";
  drawSphere(st ? st.down_dirs : [], st && st.next ? st.next.down : null);
  const n = st ? st.n : 0;
  $("poses-count").textContent = `${n} pose${n === 1 ? "" : "s"} held` + (st ? ` (at least ${st.min_poses})` : "");
  const hold = $("hold-text");
  if (performance.now() < countedUntil) { setRing(1, "\u2713", true); hold.textContent = "Counted!"; hold.className = "hold-text good"; }
  else if (live && live.still) {
    const frac = live.still_s / live.hold_s;
    setRing(frac, "", false);
    hold.textContent = frac >= 1 ? "Still... counting" : "Still: keep holding";
    hold.className = "hold-text warn";
  } else { setRing(0, "", false); hold.textContent = live ? "Moving" : "-"; hold.className = "hold-text"; }
  $("live-note").textContent = !live || !live.C ? "" : live.heading_source === "fit"
    ? "direction from the compass as calibrated so far"
    : "direction not measured yet (six poses): point the nose as drawn";
  drawBars(st ? st.sensors : [], st);
}

function td(text, cls) { const c = document.createElement("td"); c.textContent = text; if (cls) c.className = cls; return c; }

function renderResult(res, phase, write) {
  $("capture").hidden = true;
  $("side").hidden = true;
  $("result").hidden = false;
  $("capture").parentElement.classList.add("result-mode");
  const ok = res.verdicts.filter((v) => v.accepted).length, all = res.verdicts.length;
  const banner = $("banner");
  if (ok === all) { banner.textContent = "\u2713 Every sensor is good"; banner.className = "banner good"; }
  else if (ok > 0) { banner.textContent = `${ok} of ${all} sensors are good: only theirs will be written`; banner.className = "banner warn"; }
  else { banner.textContent = "\u2717 No sensor is good enough: nothing can be written"; banner.className = "banner bad"; }
  const box = $("verdicts");
  box.textContent = "";
  for (const v of res.verdicts) {
    const card = document.createElement("div");
    card.className = "card " + (v.accepted ? "good" : "bad");
    const head = document.createElement("div");
    head.className = "head";
    head.textContent = (v.accepted ? "\u2713 " : "\u2717 ") + sensorName(v.sensor) + (v.accepted ? " good" : " not good");
    card.appendChild(head);
    for (const r of v.reasons) { const p = document.createElement("p"); p.className = "why"; p.textContent = r; card.appendChild(p); }
    box.appendChild(card);
  }
  $("next-step").textContent = ["written", "declined", "failed"].includes(phase) ? "" : res.next_step;
  const body = $("params").tBodies[0];
  body.textContent = "";
  const done = phase === "written";
  for (const r of res.params) {
    const tr = document.createElement("tr");
    let mark;
    if (!r.write) { mark = "not written (" + (r.why_not || "rejected") + ")"; tr.className = "not-written"; }
    else if (!r.changed) mark = "no change";
    else mark = done ? "\u2713 written" : "will be written";
    tr.append(td(sensorName(r.sensor)), td(r.name), td(r.old), td(r.new), td(mark, "state" + (r.write && r.changed ? " yes" : "")));
    body.appendChild(tr);
  }
  const can = phase === "result";
  $("write").disabled = !can || res.n_write === 0;
  $("decline").disabled = !can;
  $("write").hidden = $("decline").hidden = ["written", "declined", "failed"].includes(phase);
  $("write").textContent = res.n_write ? `Write ${res.n_write} parameter${res.n_write === 1 ? "" : "s"} to the vehicle` : "Nothing to write";
  $("confirm-text").textContent = `Write ${res.n_write} parameter${res.n_write === 1 ? "" : "s"} to the vehicle now?`;
  if (state.report) { $("report").hidden = false; $("report").href = state.report; }
  const out = $("write-outcome");
  const msg = {
    writing: ["Writing... keep the vehicle connected.", "warn"],
    written: ["\u2713 Written and read back from the vehicle. Reboot the vehicle to use the new calibration.", "good"],
    failed: ["\u2717 The write failed: " + ((write && write.message) || "see the terminal"), "bad"],
    declined: ["Nothing was written to the vehicle.", ""],
  }[phase] || (res.n_write ? ["Check the parameters, then press Write.", ""] : ["", ""]);
  out.textContent = msg[0];
  out.className = "outcome " + msg[1];
  if (write && write.text) { $("write-text-box").hidden = false; $("write-text").textContent = write.text; }
}

function render() {
  const phase = state.phase || "starting";
  const [label, cls] = PHASES[phase] || [phase, ""];
  const pill = $("phase");
  pill.textContent = label;
  pill.className = "pill " + cls;
  const st = state.status;
  if (st && lastN !== null && st.n > lastN) countedUntil = performance.now() + 2500;
  if (st) lastN = st.n;
  if (state.result && ["result", "writing", "written", "failed", "declined", "ended"].includes(phase)) {
    renderResult(state.result, phase === "ended" ? (state.final_phase || phase) : phase, state.write);
  } else {
    renderCapture(st, state.live);
  }
  const msgs = (st && st.messages) || [];
  $("messages").textContent = (state.error ? state.error + " " : "") + msgs.join(" ");
}

// ------------------------------------------------------------------ events and actions
function connect() {
  const es = new EventSource("events?t=" + encodeURIComponent(TOKEN));
  es.onmessage = (e) => { state = JSON.parse(e.data); render(); };
  es.addEventListener("end", () => {
    es.close();
    $("footer").textContent = "This calibration session has ended; you can close this tab.";
    if (state.phase !== "ended") { state.final_phase = state.phase; }
    render();
  });
  es.onerror = () => { $("footer").textContent = "Connection to mavcal lost (is the capture still running?)."; };
}

async function post(path, body) {
  const r = await fetch(path + "?t=" + encodeURIComponent(TOKEN), {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
    credentials: "omit", cache: "no-store",
  });
  return r.json().catch(() => ({ ok: false, message: "HTTP " + r.status }));
}

function setup() {
  const dlg = $("confirm");
  $("write").addEventListener("click", () => { dlg.showModal(); $("confirm-no").focus(); });
  $("confirm-no").addEventListener("click", () => dlg.close());
  $("confirm-yes").addEventListener("click", async () => {
    dlg.close();
    $("write").disabled = true; $("decline").disabled = true;
    const r = await post("write", { csrf: state.csrf, confirmed: true });
    if (!r.ok) { $("write-outcome").textContent = r.message; }
  });
  $("finish").addEventListener("click", async () => {
    $("finish").disabled = true;
    const r = await post("finish", { csrf: state.csrf });
    $("finish").disabled = false;
    if (!r.ok) $("messages").textContent = r.message;
  });
  $("skip").addEventListener("click", async () => {
    $("skip").disabled = true;
    const r = await post("skip", { csrf: state.csrf });
    $("skip").disabled = false;
    if (!r.ok) $("messages").textContent = r.message;
  });
  $("decline").addEventListener("click", async () => {
    $("write").disabled = true; $("decline").disabled = true;
    await post("decline", { csrf: state.csrf });
  });
  render();
  connect();
}

setup();
