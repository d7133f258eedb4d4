(function () {
"use strict";
const NS = "http://www.w3.org/2000/svg";
const SHORT = {truth: "truth", per_step: "per step", segments: "segments", prior: "prior"};
const EMPTY = "#e4e4e4";  // type 0 in timelines: visible as "nothing", lighter than any type colour
const TL = {left: 128, head: 22, row: 10, gap: 8};
const R = 6;  // agent dot radius, px
const $ = (id) => document.getElementById(id);
const state = {pos: 0, frame: 0, source: "segments", zero: "hidden", activeOnly: false, forecast: true, timer: null};
let cur = null;  // the decoded current clip

function el(tag, attrs, parent) {
  const node = document.createElementNS(NS, tag);
  for (const k in attrs) node.setAttribute(k, attrs[k]);
  if (parent) parent.appendChild(node);
  return node;
}
function unrle(runs) {
  const out = [];
  for (const r of runs) {
    if (Array.isArray(r)) { for (let i = 0; i < r[1]; i++) out.push(r[0]); } else out.push(r);
  }
  return out;
}
function decodeAgent(a, d) {
  const q = Math.pow(10, -d), pts = [];
  let x = 0, y = 0;
  for (let i = 0; i < a.xy.length; i += 2) {
    if (a.xy[i] === null) { pts.push(null); continue; }
    x += a.xy[i]; y += a.xy[i + 1];
    pts.push([x * q, y * q]);
  }
  const name = DATA.agent_names.length && a.id >= 0 && a.id < DATA.agent_names.length
    ? DATA.agent_names[a.id] : String(a.id);
  return {slot: a.k, id: a.id, name: name, f0: a.f0, pts: pts};
}
// Long ids (e.g. provider player ids) shortened on the scene and the timelines; the full id shows on hover.
function posAt(agent, f) {
  const i = f - agent.f0;
  return agent && i >= 0 && i < agent.pts.length ? agent.pts[i] : null;
}
function decodeEdge(raw) {
  const e = {};
  DATA.edge_fields.forEach((k, i) => { e[k] = raw[i]; });
  const out = {e: e.e, s: e.s, r: e.r, p: unrle(e.p), sp: e.sp ? unrle(e.sp) : null, types: {}};
  for (const src of DATA.sources) if (e[src]) out.types[src] = unrle(e[src]);
  // per-step flickers alone do not make an edge "interacting": the segments or the truth must say so
  out.active = ["segments", "truth"].some((src) => out.types[src] && out.types[src].some((v) => v > 0));
  return out;
}
function decodeClip(c) {
  const agents = new Map();
  for (const a of c.agents) agents.set(a.k, decodeAgent(a, c.d));
  const bg = c.bg === null ? null : DATA.backgrounds[c.bg];
  let fc = null;
  const decodeFc = (list) => list.map((a) => decodeAgent({k: a.k, id: a.k, f0: c.fc.start, xy: a.xy}, c.d));
  if (c.fc) fc = {start: c.fc.start, paths: decodeFc(c.fc.agents), samples: (c.fc.samples || []).map(decodeFc)};
  return {raw: c, T: c.T, agents: agents, edges: c.edges.map(decodeEdge), bg: bg, fc: fc};
}

// Fit the clip's paths into the scene, equal aspect. y points up unless the scene image's extent says
// top < bottom (image coordinates), as matplotlib's imshow would show it.
function projection(clip, W, H) {
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (const a of clip.agents.values()) for (const p of a.pts) if (p) {
    x0 = Math.min(x0, p[0]); x1 = Math.max(x1, p[0]); y0 = Math.min(y0, p[1]); y1 = Math.max(y1, p[1]);
  }
  if (!isFinite(x0)) { x0 = 0; x1 = 1; y0 = 0; y1 = 1; }
  const span = Math.max(x1 - x0, y1 - y0, 1e-9), m = 28;
  const k = Math.min((W - 2 * m) / Math.max(x1 - x0, span * 0.05), (H - 2 * m) / Math.max(y1 - y0, span * 0.05));
  const up = !clip.bg || clip.bg.extent[3] >= clip.bg.extent[2];
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  return {k: k, px: (x) => W / 2 + (x - cx) * k, py: (y) => H / 2 + (up ? cy - y : y - cy) * k};
}

function typeName(v) { return v < 0 ? "absent" : v + " " + (DATA.type_names[v] || ""); }
function agentId(slot) { const a = cur.agents.get(slot); return a ? a.id : slot; }
function agentName(slot) { const a = cur.agents.get(slot); return a ? a.name : String(slot); }
// The source's frame number of step f: data.downsample keeps every frame_step-th frame of the input.
function inputFrame(f) { return cur.raw.frame + f * (DATA.frame_step || 1); }
function transitionAt(f) { return Math.max(0, Math.min(f, cur.T - 2)); }
function stepText(t) {
  let s = "step " + t + " (frames " + t + "\u2192" + (t + 1) + ")";
  if (cur.raw.frame !== null) s += ", input frames " + inputFrame(t) + "\u2192" + inputFrame(t + 1);
  return s;
}
function pairText(e) {
  return "agent " + agentName(e.s) + " \u2192 agent " + agentName(e.r) + "   (slots " + e.s + "\u2192" + e.r + ")";
}
function valueText(e, src, t) {
  const v = e.types[src][t];
  let s = SHORT[src] + ": " + typeName(v);
  if (src === "segments" && v >= 0) s += "   p = " + (e.p[t] / 100).toFixed(2);
  if (src === "per_step" && v >= 0 && e.sp) s += "   p = " + (e.sp[t] / 100).toFixed(2);
  return s;
}
function edgeDetails(e, t, only) {
  const lines = [pairText(e), stepText(t)];
  for (const src of only ? [only] : DATA.sources) if (e.types[src]) lines.push(valueText(e, src, t));
  return lines.join("\n");
}

// ---------------------------------------------------------------- scene
function drawScene() {
  const svg = $("scene"), W = +svg.getAttribute("width"), H = +svg.getAttribute("height");
  cur.proj = projection(cur, W, H);
  const P = cur.proj, bg = $("bg"), paths = $("paths");
  bg.textContent = ""; paths.textContent = "";
  if (cur.bg) {
    const [l, r, b, t] = cur.bg.extent;
    el("image", {href: "data:image/png;base64," + cur.bg.png, preserveAspectRatio: "none",
      x: Math.min(P.px(l), P.px(r)), y: Math.min(P.py(b), P.py(t)),
      width: Math.abs(P.px(r) - P.px(l)), height: Math.abs(P.py(t) - P.py(b))}, bg);
  }
  for (const a of cur.agents.values()) {
    el("path", {class: "path", d: pathD(a, a.f0 + a.pts.length - 1)}, paths);
    a.past = el("path", {class: "past", d: ""}, paths);
  }
  drawForecast();
  drawScaleBar(W, H);
}
// The forecast from the last burn-in frame on, dashed, beside the true path it should follow.
function drawForecast() {
  const g = $("forecast");
  g.textContent = "";
  if (!cur.fc) return;
  // the sampled futures first, thin, under the forecast: the spread of what the model thinks may happen
  cur.fc.samples.forEach((paths, k) => drawPaths(g, paths, "fcs", "sampled future " + (k + 1) + " of agent "));
  drawPaths(g, cur.fc.paths, "fc", "forecast of agent ");
}
function drawPaths(g, paths, cls, what) {
  const P = cur.proj;
  for (const f of paths) {
    const from = posAt(cur.agents.get(f.slot), cur.fc.start - 1);
    const pts = (from ? [from] : []).concat(f.pts.filter((p) => p));
    if (pts.length < 2) continue;
    const path = el("path", {class: cls, "data-agent": agentId(f.slot),
      d: pts.map((p, i) => (i ? "L" : "M") + P.px(p[0]).toFixed(1) + " " + P.py(p[1]).toFixed(1)).join("")}, g);
    el("title", {}, path).textContent = what + agentName(f.slot) + " from frame " + cur.fc.start;
  }
}
// A scale bar of a round length (1, 2 or 5 x 10^n data units) near a fifth of the scene's width.
function drawScaleBar(W, H) {
  const g = $("scalebar"), k = cur.proj.k;
  g.textContent = "";
  const want = W / 5 / k, p = Math.pow(10, Math.floor(Math.log10(want)));
  const len = [5, 2, 1].map((m) => m * p).find((v) => v <= want) || p;
  const x0 = 14, y0 = H - 14, x1 = x0 + len * k;
  el("line", {x1: x0, x2: x1, y1: y0, y2: y0}, g);
  for (const x of [x0, x1]) el("line", {x1: x, x2: x, y1: y0 - 4, y2: y0 + 4}, g);
  const label = +len.toPrecision(3) + (DATA.units ? " " + DATA.units : " (data units)");
  el("text", {x: (x0 + x1) / 2, y: y0 - 6, "text-anchor": "middle"}, g).textContent = label;
  g.setAttribute("data-length", len);
}
function pathD(a, last) {
  const P = cur.proj;
  let d = "", pen = false;
  for (let i = 0; i < a.pts.length && a.f0 + i <= last; i++) {
    const p = a.pts[i];
    if (!p) { pen = false; continue; }
    d += (pen ? "L" : "M") + P.px(p[0]).toFixed(1) + " " + P.py(p[1]).toFixed(1);
    pen = true;
  }
  return d;
}
function arrow(e, type, a, b, t, parent) {
  const P = cur.proj;
  const g = el("g", {class: "arrow", "data-edge": e.s + "-" + e.r, "data-e": e.e, "data-type": type,
    "data-sender": agentId(e.s), "data-receiver": agentId(e.r), "data-t": t}, parent);
  const x1 = P.px(a[0]), y1 = P.py(a[1]), x2 = P.px(b[0]), y2 = P.py(b[1]);
  const len = Math.hypot(x2 - x1, y2 - y1);
  if (len < 2 * R + 2) return g;  // agents on top of each other: nothing to draw, the cell says it
  const ux = (x2 - x1) / len, uy = (y2 - y1) / len, ox = -uy * 3, oy = ux * 3;  // a->b and b->a side by side
  const sx = x1 + ux * R + ox, sy = y1 + uy * R + oy, ex = x2 - ux * (R + 1) + ox, ey = y2 - uy * (R + 1) + oy;
  const color = DATA.colors[type] || "#000", head = Math.min(9, len / 3);
  el("line", {class: "hit", x1: sx, y1: sy, x2: ex, y2: ey}, g);
  el("line", {class: "body", x1: sx, y1: sy, x2: ex - ux * head * 0.8, y2: ey - uy * head * 0.8, stroke: color}, g);
  const bx = ex - ux * head, by = ey - uy * head, w = head * 0.5;
  el("polygon", {class: "head", fill: color,
    points: ex + "," + ey + " " + (bx - uy * w) + "," + (by + ux * w) + " " + (bx + uy * w) + "," + (by - ux * w)}, g);
  return g;
}
function drawFrame() {
  const f = state.frame, t = transitionAt(f), P = cur.proj;
  for (const a of cur.agents.values()) a.past.setAttribute("d", pathD(a, f));
  const arrows = $("arrows"), agents = $("agents");
  arrows.textContent = ""; agents.textContent = "";
  let active = 0;
  for (const e of cur.edges) {
    const types = e.types[state.source];
    const type = types ? types[t] : -1;
    const a = posAt(cur.agents.get(e.s), f), b = posAt(cur.agents.get(e.r), f);
    if (type === undefined || type < 0 || !a || !b) continue;
    arrow(e, type, a, b, t, arrows);
    if (type > 0) active++;
  }
  for (const a of cur.agents.values()) {
    const p = posAt(a, f);
    if (!p) continue;
    const g = el("g", {class: "agent", "data-agent": a.id}, agents);
    el("title", {}, g).textContent = "agent " + a.name;
    el("circle", {cx: P.px(p[0]), cy: P.py(p[1]), r: R}, g);
    el("text", {x: P.px(p[0]) + R + 2, y: P.py(p[1]) - R - 1}, g).textContent = a.name;
  }
  const cursor = $("cursor");
  if (cursor) cursor.setAttribute("x", TL.left + t * cur.cw);
  $("slider").value = f;
  let label = "frame " + f + " / " + (cur.T - 1) + " \u00b7 step " + t + "\u2192" + (t + 1);
  if (cur.raw.frame !== null) label += " \u00b7 input frame " + inputFrame(f);
  $("frameLabel").textContent = label + " \u00b7 " + active + " interacting";
  const ds = document.body.dataset;
  ds.clip = cur.raw.row; ds.frame = f; ds.transition = t; ds.source = state.source;
  if (state.timer === null) saveHash();
}

// ------------------------------------------------------------- timelines
function drawTimelines() {
  const svg = $("tl");
  svg.textContent = "";
  const edges = cur.edges.filter((e) => !state.activeOnly || e.active);
  const srcs = DATA.sources, n = Math.max(cur.T - 1, 1);
  const wrap = getComputedStyle($("tlwrap"));  // clientWidth includes the padding
  const inner = $("tlwrap").clientWidth - parseFloat(wrap.paddingLeft) - parseFloat(wrap.paddingRight);
  const W = Math.max(500, inner - 2), block = srcs.length * TL.row + TL.gap;
  // the pair labels in full, however long the ids: the label column grows with the longest (about 6.5 px a
  // character at the page's font size, beside the source names)
  const longest = Math.max(0, ...edges.map((e) => agentName(e.s).length + agentName(e.r).length + 1));
  TL.left = Math.max(128, Math.ceil(6 + 6.5 * longest + 44));
  cur.cw = (W - TL.left - 16) / n;  // room for the last tick's label
  cur.shown = edges;
  svg.setAttribute("width", W);
  svg.setAttribute("height", TL.head + Math.max(edges.length, 1) * block + 4);
  const every = [1, 2, 5, 10, 20, 50, 100, 200, 500].find((k) => n / k <= 24) || 1000;
  for (let t = 0; t <= n; t += every) {
    const x = TL.left + t * cur.cw;
    el("line", {x1: x, x2: x, y1: TL.head - 5, y2: TL.head - 1, stroke: "#888"}, svg);
    el("text", {x: x, y: TL.head - 8, "text-anchor": "middle", fill: "#666"}, svg).textContent = t;
  }
  el("text", {x: 6, y: TL.head - 8, fill: "#666"}, svg).textContent = edges.length ? "step" : "no edges";
  el("rect", {id: "rowhl", x: 0, y: -100, width: W, height: block - 2}, svg);
  edges.forEach((e, i) => {
    const y0 = TL.head + i * block;
    el("text", {class: "edgelabel", x: 6, y: y0 + srcs.length * TL.row / 2 + 4}, svg).textContent =
      agentName(e.s) + "\u2192" + agentName(e.r);
    srcs.forEach((src, j) => {
      const y = y0 + j * TL.row;
      const label = el("text", {class: "srclabel", x: TL.left - 4, y: y + TL.row - 1.5, "text-anchor": "end"}, svg);
      label.textContent = SHORT[src];
      if (e.types[src]) runs(e.types[src], (v, a, b) => el("rect", {x: TL.left + a * cur.cw, y: y + 0.5,
        width: (b - a) * cur.cw, height: TL.row - 1, fill: v === 0 ? EMPTY : DATA.colors[v] || "#000"}, svg));
    });
  });
  el("rect", {id: "cursor", x: TL.left + transitionAt(state.frame) * cur.cw, y: TL.head - 2, width: cur.cw,
    height: Math.max(edges.length, 1) * block}, svg);
}
function runs(values, draw) {
  let a = 0;
  for (let t = 1; t <= values.length; t++) {
    if (t === values.length || values[t] !== values[a]) {
      if (values[a] >= 0) draw(values[a], a, t);
      a = t;
    }
  }
}
// Client coordinates of the middle of a timeline cell: row i of the shown edges, a source, step t.
function cellCentre(i, src, t) {
  const box = $("tl").getBoundingClientRect(), block = DATA.sources.length * TL.row + TL.gap;
  return {x: box.left + TL.left + (t + 0.5) * cur.cw,
    y: box.top + TL.head + i * block + (DATA.sources.indexOf(src) + 0.5) * TL.row};
}
function cellAt(evt) {
  const box = $("tl").getBoundingClientRect(), x = evt.clientX - box.left, y = evt.clientY - box.top;
  const block = DATA.sources.length * TL.row + TL.gap, i = Math.floor((y - TL.head) / block);
  const j = Math.floor((y - TL.head - i * block) / TL.row), t = Math.floor((x - TL.left) / cur.cw);
  if (i < 0 || i >= cur.shown.length || t < 0 || t >= cur.T - 1) return null;
  return {e: cur.shown[i], i: i, src: j < DATA.sources.length ? DATA.sources[j] : null, t: t};
}

// ------------------------------------------------------------- hover
function showTip(evt, text) {
  const tip = $("tip");
  tip.textContent = text;
  tip.style.display = "block";
  tip.style.left = Math.min(evt.clientX + 14, window.innerWidth - tip.offsetWidth - 4) + "px";
  tip.style.top = Math.min(evt.clientY + 14, window.innerHeight - tip.offsetHeight - 4) + "px";
}
function hideTip() { $("tip").style.display = "none"; highlight(null); }
function highlight(e) {
  for (const g of $("arrows").querySelectorAll(".arrow.hl")) g.classList.remove("hl");
  const hl = $("rowhl");
  if (!e) { if (hl) hl.setAttribute("y", -100); return; }
  const g = $("arrows").querySelector('.arrow[data-e="' + e.e + '"]');
  if (g) g.classList.add("hl");
  const i = cur.shown.indexOf(e), block = DATA.sources.length * TL.row + TL.gap;
  if (hl && i >= 0) hl.setAttribute("y", TL.head + i * block - 1);
}
function edgeOf(g) { const k = +g.getAttribute("data-e"); return cur.edges.find((e) => e.e === k); }

// ------------------------------------------------------------- state
function setClip(row) {
  const pos = DATA.clips.findIndex((c) => c.row === +row);
  if (pos < 0) return false;
  state.pos = pos;
  cur = decodeClip(DATA.clips[pos]);
  $("clipSel").value = pos;
  $("slider").max = cur.T - 1;
  state.frame = Math.min(state.frame, cur.T - 1);
  drawInfo(); drawScene(); drawTimelines(); drawFrame();
  return true;
}
function setFrame(f) {
  state.frame = Math.max(0, Math.min(Math.round(+f) || 0, cur.T - 1));
  drawFrame();
  return state.frame;
}
function setSource(src) {
  if (DATA.sources.indexOf(src) < 0) return false;
  state.source = src; $("sourceSel").value = src;
  drawFrame();
  return true;
}
function setZero(mode) {
  state.zero = mode === "faint" ? "faint" : "hidden"; $("zeroSel").value = state.zero;
  $("scene").classList.toggle("hide0", state.zero === "hidden");
}
function setForecast(on) {
  state.forecast = !!on; $("showFc").checked = state.forecast;
  $("scene").classList.toggle("hidefc", !state.forecast);
}
function setActiveOnly(on) { state.activeOnly = !!on; $("activeOnly").checked = state.activeOnly; drawTimelines(); }
function play() {
  if (state.timer !== null) return;
  if (state.frame >= cur.T - 1) setFrame(0);
  state.timer = setInterval(() => {
    if (state.frame >= cur.T - 1) pause(); else setFrame(state.frame + 1);
  }, 125);
  $("play").textContent = "\u275a\u275a pause";
}
function pause() {
  if (state.timer !== null) clearInterval(state.timer);
  state.timer = null;
  $("play").innerHTML = "&#9654; play";
  saveHash();
}
function saveHash() {
  const h = "#clip=" + cur.raw.row + "&frame=" + state.frame + "&source=" + state.source;
  if (location.hash !== h) try { history.replaceState(null, "", h); } catch (err) { /* some file: setups refuse */ }
}
function readHash() {
  const q = new URLSearchParams(location.hash.replace(/^#/, ""));
  if (DATA.sources.indexOf(q.get("source")) >= 0) state.source = $("sourceSel").value = q.get("source");
  if (q.has("zero")) setZero(q.get("zero"));
  if (q.has("frame")) state.frame = Math.max(0, Math.round(+q.get("frame")) || 0);
  if (!(q.has("clip") && setClip(q.get("clip"))) && !cur) setClip(DATA.clips[0].row);
  setFrame(state.frame);
}
function arrowsNow() {
  return Array.from($("arrows").querySelectorAll(".arrow")).map((g) => ({
    edge: g.getAttribute("data-edge"), type: +g.getAttribute("data-type"),
    sender: +g.getAttribute("data-sender"), receiver: +g.getAttribute("data-receiver")}));
}

// ------------------------------------------------------------- static parts
function drawInfo() {
  const c = cur.raw, rows = [["row", c.row + " of " + DATA.total], ["clip", c.clip]];
  if (c.scene !== null) rows.push(["scene", c.scene]);
  if (c.frame !== null) rows.push(["input frames", c.frame + "\u2013" + inputFrame(c.T - 1)]);
  rows.push(["agents", Array.from(cur.agents.values()).map((a) => a.name).join(", ")]);
  if (cur.fc) rows.push(["forecast", "dashed, from frame " + cur.fc.start + " (after the burn-in)"]);
  rows.push(["edges", cur.edges.length + " present, " + cur.edges.filter((e) => e.active).length + " interacting"]);
  rows.push(["image", cur.bg ? "yes" : "none"]);
  $("info").innerHTML = "";
  for (const [k, v] of rows) {
    const tr = $("info").insertRow();
    tr.insertCell().textContent = k; tr.insertCell().textContent = v;
  }
}
function setup() {
  $("title").textContent = DATA.model;
  $("title").title = DATA.path;
  $("note").textContent = DATA.note;
  DATA.clips.forEach((c, i) => {
    const o = document.createElement("option");
    o.value = i;
    o.textContent = "#" + c.row + " \u00b7 clip " + c.clip + (c.scene !== null ? " \u00b7 scene " + c.scene : "")
      + (c.frame !== null ? " \u00b7 frame " + c.frame : "");
    $("clipSel").appendChild(o);
  });
  for (const src of DATA.sources) {
    const o = document.createElement("option");
    o.value = src; o.textContent = SHORT[src];
    $("sourceSel").appendChild(o);
  }
  $("sourceSel").value = state.source;
  DATA.type_names.forEach((name, k) => {
    const d = document.createElement("div");
    d.innerHTML = '<span class="sw"></span>';
    d.firstChild.style.background = k === 0 ? EMPTY : DATA.colors[k];
    d.appendChild(document.createTextNode(k + ": " + name + (k === 0 ? " (arrows hidden or faint)" : "")));
    if (DATA.type_notes[k]) {  // what the type means: its pairs while it holds, beside the others
      const n = document.createElement("div");
      n.className = "note"; n.textContent = DATA.type_notes[k];
      d.appendChild(n);
    }
    $("legend").appendChild(d);
  });
  wire();
}
function wire() {
  $("clipSel").onchange = (ev) => setClip(DATA.clips[+ev.target.value].row);
  $("prevClip").onclick = () => stepClip(-1);
  $("nextClip").onclick = () => stepClip(1);
  $("slider").oninput = (ev) => setFrame(ev.target.value);
  $("play").onclick = () => (state.timer === null ? play() : pause());
  $("sourceSel").onchange = (ev) => setSource(ev.target.value);
  $("zeroSel").onchange = (ev) => setZero(ev.target.value);
  $("activeOnly").onchange = (ev) => setActiveOnly(ev.target.checked);
  $("showFc").onchange = (ev) => setForecast(ev.target.checked);
  $("fcLabel").style.display = DATA.clips.some((c) => c.fc) ? "" : "none";
  const arrows = $("arrows");
  arrows.onmousemove = (ev) => {
    const g = ev.target.closest(".arrow");
    if (!g) return hideTip();
    const e = edgeOf(g);
    highlight(e);
    showTip(ev, edgeDetails(e, +g.getAttribute("data-t")));
  };
  arrows.onmouseleave = hideTip;
  arrows.onclick = (ev) => {
    const g = ev.target.closest(".arrow"), i = g ? cur.shown.indexOf(edgeOf(g)) : -1;
    if (i >= 0) window.scrollTo(0, $("tl").getBoundingClientRect().top + window.scrollY
      + TL.head + i * (DATA.sources.length * TL.row + TL.gap) - 80);
  };
  const tl = $("tl");
  tl.onmousemove = (ev) => {
    const c = cellAt(ev);
    if (!c) return hideTip();
    highlight(c.e);
    showTip(ev, edgeDetails(c.e, c.t, c.src));
  };
  tl.onmouseleave = hideTip;
  tl.onclick = (ev) => { const c = cellAt(ev); if (c) setFrame(c.t); };
  window.addEventListener("hashchange", readHash);
  window.addEventListener("keydown", onKey);
  let pending = null;
  window.addEventListener("resize", () => { clearTimeout(pending); pending = setTimeout(drawTimelines, 150); });
}
function stepClip(d) {
  const pos = Math.max(0, Math.min(state.pos + d, DATA.clips.length - 1));
  setClip(DATA.clips[pos].row);
}
function onKey(ev) {
  if (["INPUT", "SELECT", "BUTTON"].indexOf(ev.target.tagName) >= 0) return;  // they handle their own keys
  const keys = {ArrowLeft: () => setFrame(state.frame - 1), ArrowRight: () => setFrame(state.frame + 1),
    " ": () => (state.timer === null ? play() : pause()), PageUp: () => stepClip(-1), PageDown: () => stepClip(1)};
  if (keys[ev.key]) { ev.preventDefault(); keys[ev.key](); }
}

setup();
readHash();
window.explorer = {setFrame: setFrame, setClip: setClip, setSource: setSource, setZero: setZero,
  setActiveOnly: setActiveOnly, setForecast: setForecast, play: play, pause: pause, arrows: arrowsNow, cellCentre: cellCentre, data: DATA,
  clips: () => DATA.clips.map((c) => c.row),
  state: () => ({clip: cur.raw.row, frame: state.frame, transition: transitionAt(state.frame),
    source: state.source, zero: state.zero, forecast: state.forecast, playing: state.timer !== null})};
document.body.dataset.ready = "1";
})();
