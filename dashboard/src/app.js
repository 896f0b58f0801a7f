// stillmap dashboard: sessions table, fleets, 2D semantic map, 3D point cloud.
// Live data comes from the server's event stream (/api/v1/events, Server-Sent
// Events): a sessions snapshot twice a second and every new pose. Map tiles and
// the cloud are fetched again only when a session's map version changes.

import { Map2D, rotate } from "./map2d.js";
import { authed } from "./token.js";

const SPARK_FRAMES = 60; // latency history per stage
// Stages on the tracking path (map fusion runs off it, in /metrics only).
const SPARK_STAGES = ["total", "track", "perception_flow", "segmentation"];
const CLOUD_REFRESH_MS = 5000; // the 3D cloud is re-fetched at most this often

const state = {
  sessions: new Map(), // id -> snapshot
  history: new Map(), // id -> { stage -> [ms] }
  trajectories: new Map(), // id -> [[x, y, z] world]
  loadedTrajectory: new Set(),
  selected: null,
  mapInfo: new Map(), // id -> /api/v1/maps/{id}
  mapVersion: new Map(),
  legend: [],
};

// Exposed for the browser test and for debugging.
window.__stillmap = { tilesDrawn: 0, trajectoryPoints: 0, cloudPoints: 0, events: 0 };

const $ = (sel) => document.querySelector(sel);
const map2d = new Map2D($("#map2d"));
let view3d = null;
let view3dFailed = null;
import("./view3d.js")
  .then((m) => { view3d = new m.View3D($("#map3d"), $("#map3d-status")); refreshCloud(true); })
  .catch((e) => { view3dFailed = e; $("#map3d-status").textContent = `3D view unavailable (${e.message}): run make dashboard`; });

document.querySelectorAll(".host").forEach((el) => { el.textContent = location.hostname || "localhost"; });

function fmt(v, digits = 1) { return Number.isFinite(v) ? v.toFixed(digits) : "–"; }

// A sparkline of the last SPARK_FRAMES values (a single value is a dot, not an empty box).
function sparkline(values) {
  const w = 60, h = 16;
  const max = Math.max(...values, 1e-3);
  const xy = (v, i) => [(i / (SPARK_FRAMES - 1)) * w, h - 1 - (v / max) * (h - 2)];
  if (values.length === 1) {
    const [x, y] = xy(values[0], 0);
    return `<svg width="${w}" height="${h}"><circle cx="${x + 1.5}" cy="${y}" r="1.5" fill="#5aa9e6"/></svg>`;
  }
  const pts = values.map((v, i) => xy(v, i).join(",")).join(" ");
  return `<svg width="${w}" height="${h}"><polyline points="${pts}" fill="none" stroke="#5aa9e6" stroke-width="1"/></svg>`;
}

// The latency cell: live sessions get sparklines of their recent frames; a finished
// one (no new frames will come) its last frame's times as text, or a dash.
function latencyCell(s, hist) {
  if (!s.connected) {
    const last = SPARK_STAGES.filter((st) => Number.isFinite(s.latency_ms?.[st])).map((st) => `<span class="spark">${st} ${fmt(s.latency_ms[st])}</span>`);
    return last.length ? `<span class="muted" title="the last frame's times (ms)">last frame:</span> ${last.join("")}` : `<span class="muted">–</span>`;
  }
  return SPARK_STAGES.filter((st) => hist[st]?.length)
    .map((st) => `<span class="spark">${st} ${fmt(hist[st].at(-1))}${sparkline(hist[st])}</span>`)
    .join("");
}

// Session ids are long (robot, boot, counter): the robot column has the robot, so
// the cell shows the rest; the whole id is its tooltip.
function shortId(s) {
  const id = s.session_id;
  if (id.startsWith(`${s.robot_id}-`)) return `…${id.slice(s.robot_id.length + 1)}`;
  return id.length > 14 ? `${id.slice(0, 12)}…` : id;
}

function linkBadge(s) {
  if (s.archived) return `<span class="badge">stored</span>`;
  return s.connected ? `<span class="badge ok">connected</span>` : `<span class="badge bad">disconnected</span>`;
}

function trackingBadge(t) {
  const name = t.replace("TRACKING_STATE_", "").toLowerCase();
  const kind = name === "tracking" || name === "relocalized" ? "ok" : name === "lost" ? "bad" : "warn";
  return `<span class="badge ${kind}">${escapeHtml(name)}</span>`;
}

function renderTable() {
  const sessions = [...state.sessions.values()];
  $("#empty").hidden = sessions.length > 0;
  $("#session-table").hidden = sessions.length === 0;
  const body = $("#session-table tbody");
  const rows = sessions.map((s) => {
    const hist = state.history.get(s.session_id) || {};
    const sparks = latencyCell(s, hist);
    const t = s.pose?.translation;
    const pose = t ? `${fmt(t[0], 2)}, ${fmt(t[1], 2)}, ${fmt(t[2], 2)}` : "–";
    const map = s.map ? `${Number(s.map.keyframes)} kf · ${Number(s.map.occupied_voxels).toLocaleString()} voxels` : "–";
    const sel = s.session_id === state.selected ? "selected" : "";
    // Escaped: on servers sharing a Zenoh network, rows come from other servers too.
    return `<tr data-session="${escapeHtml(s.session_id)}" class="${sel}">
      <td>${escapeHtml(s.robot_id)}</td><td class="muted id" title="${escapeHtml(s.session_id)}">${escapeHtml(shortId(s))}</td><td class="link">${linkBadge(s)}</td>
      <td>${trackingBadge(String(s.tracking_state))}</td><td class="frames">${Number(s.frames_processed)}</td>
      <td class="fps">${fmt(s.fps)}</td><td class="dropped">${Number(s.frames_dropped)}</td><td class="sparks">${sparks}</td>
      <td>${pose}</td><td class="map">${map}</td></tr>`;
  });
  body.innerHTML = rows.join("");
}

$("#session-table tbody").addEventListener("click", (e) => {
  const row = e.target.closest("tr[data-session]");
  if (row) select(row.dataset.session);
});

async function getJson(url) {
  const r = await fetch(authed(url), { cache: "no-cache" });
  if (!r.ok) throw new Error(`${url}: ${r.status}`);
  return r.json();
}

async function select(id) {
  if (state.selected === id) return;
  state.selected = id;
  $("#map-title").textContent = id;
  renderTable();
  await loadTrajectory(id);
  await refreshMap(id, true);
  refreshCloud(true);
}

async function loadTrajectory(id) {
  if (state.loadedTrajectory.has(id)) return;
  try {
    // Answered in pages (200,000 poses each): follow next_start_ns. It is a
    // nanosecond count beyond a JS number's exact range, so each next page is
    // asked from a microsecond earlier and poses already seen are skipped.
    const path = `/api/v1/sessions/${encodeURIComponent(id)}/trajectory`;
    const poses = [];
    const seen = new Set();
    let t = await getJson(path);
    for (;;) {
      for (const p of t.poses) {
        if (!seen.has(p.sequence)) {
          seen.add(p.sequence);
          poses.push(p);
        }
      }
      if (t.next_start_ns == null) break;
      t = await getJson(`${path}?start_ns=${BigInt(Math.max(0, t.next_start_ns - 1000)).toString()}`);
    }
    const live = state.trajectories.get(id) || [];
    const first = live.length ? live[0].sequence : Infinity;
    const stored = poses.filter((p) => p.sequence < first).map((p) => ({ sequence: p.sequence, t: p.translation, q: p.rotation_xyzw }));
    state.trajectories.set(id, stored.concat(live));
    state.loadedTrajectory.add(id);
  } catch (e) {
    console.warn(e);
  }
}

async function refreshMap(id, fit) {
  try {
    const info = await getJson(`/api/v1/maps/${encodeURIComponent(id)}`);
    state.mapInfo.set(id, info);
    const legend = await getJson(`/api/v1/maps/${encodeURIComponent(id)}/legend`);
    if (id !== state.selected) return;
    state.legend = legend.classes;
    renderLegend();
    map2d.setMap(id, info, state.legend, fit);
    drawMap();
  } catch (e) {
    // A session without a map (mapping disabled) just shows its trajectory.
    console.warn(e);
  }
}

function renderLegend() {
  const hidden = map2d.hidden;
  $("#legend").innerHTML = state.legend
    .map((c) => `<label><input type="checkbox" data-color="${c.color}" ${hidden.has(c.color) ? "" : "checked"}>
      <span class="swatch" style="background:${c.color}"></span>${c.name} <span class="muted">${c.cells}</span></label>`)
    .join("");
}

$("#legend").addEventListener("change", (e) => {
  const color = e.target.dataset.color;
  if (!color) return;
  if (e.target.checked) map2d.hidden.delete(color); else map2d.hidden.add(color);
  map2d.invalidateFilters();
  drawMap();
  if (view3d) view3d.setHidden(map2d.hidden);
});

$("#rgb").addEventListener("change", (e) => { if (view3d) view3d.setColourByRgb(e.target.checked); });

function drawMap() {
  const id = state.selected;
  const traj = state.trajectories.get(id) || [];
  const info = state.mapInfo.get(id);
  const q = info?.map_from_world_xyzw;
  const points = traj.map((p) => (q ? rotate(q, p.t) : p.t));
  const last = traj.at(-1);
  map2d.draw(points, last ? { t: q ? rotate(q, last.t) : last.t, forward: q ? rotate(q, rotateCamZ(last.q)) : rotateCamZ(last.q) } : null);
  window.__stillmap.trajectoryPoints = points.length;
  window.__stillmap.tilesDrawn = map2d.tilesDrawn;
}

// The camera's viewing direction (its +z) in the world, from world_from_camera's rotation.
function rotateCamZ(q) { return rotate(q, [0, 0, 1]); }

let lastCloud = 0;
let cloudTimer = null;
async function refreshCloud(now) {
  const id = state.selected;
  if (!view3d || !id) return;
  const wait = now ? 0 : Math.max(0, lastCloud + CLOUD_REFRESH_MS - Date.now());
  clearTimeout(cloudTimer);
  cloudTimer = setTimeout(async () => {
    lastCloud = Date.now();
    const info = state.mapInfo.get(id);
    const n = await view3d.load(`/api/v1/maps/${encodeURIComponent(id)}/cloud.ply`, state.legend, info?.map_from_world_xyzw);
    window.__stillmap.cloudPoints = n;
    update3dTrajectory();
  }, wait);
}

function update3dTrajectory() {
  if (!view3d) return;
  const id = state.selected;
  const q = state.mapInfo.get(id)?.map_from_world_xyzw;
  view3d.setTrajectory((state.trajectories.get(id) || []).map((p) => (q ? rotate(q, p.t) : p.t)));
}

// ---------------------------------------------------------------- fleets
// Every merged robot of each fleet on one top-down view: its trajectory moved by
// its fleet_from_session and the pose graph's latest correction, then into the
// anchor's map frame (z up); unmerged robots
// listed apart. The fleets are polled; the poses come from the event stream.
const FLEET_REFRESH_MS = 2000;
const ROBOT_COLOURS = ["#e6194b", "#3cb44b", "#4363d8", "#f58231", "#911eb4", "#42d4f4", "#f032e6", "#bfef45"];
state.fleets = [];
window.__stillmap.fleets = 0;
window.__stillmap.fleetRobots = 0;
window.__stillmap.fleetPoints = 0;
window.__stillmap.fleetTilesDrawn = 0;
// The fleet map (its tiles) under the trails: refreshed at most this often, since
// each change of a member's map rebuilds the fleet map on the server.
const FLEET_TILES_REFRESH_MS = 10000;
state.fleetTiles = new Map(); // fleet -> { bounds, loadedAt, images: Map(url -> Image) }

function escapeHtml(text) {
  return String(text).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
}

async function refreshFleets() {
  try {
    const list = await getJson("/api/v1/fleets");
    state.fleets = await Promise.all(list.fleets.map((f) => getJson(`/api/v1/fleets/${encodeURIComponent(f.fleet)}`)));
    for (const f of state.fleets) {
      for (const m of f.sessions) if (m.merged) await loadTrajectory(m.session_id);
      const anchor = f.sessions.find((m) => m.fleet_from_session?.anchor);
      if (anchor && !state.mapInfo.has(anchor.session_id)) {
        try { state.mapInfo.set(anchor.session_id, await getJson(`/api/v1/maps/${encodeURIComponent(anchor.session_id)}`)); } catch (e) { /* no map: world frame */ }
      }
      await refreshFleetTiles(f);
    }
    renderFleets();
  } catch (e) {
    console.warn(e);
  }
  setTimeout(refreshFleets, FLEET_REFRESH_MS);
}

async function refreshFleetTiles(f) {
  const prev = state.fleetTiles.get(f.fleet);
  if (prev && Date.now() - prev.loadedAt < FLEET_TILES_REFRESH_MS) return;
  try {
    const legend = await getJson(f.tiles.legend);
    state.fleetTiles.set(f.fleet, { bounds: legend.bounds_xy, loadedAt: Date.now(), images: new Map() });
  } catch (e) { /* no fleet map yet */ }
}

// The fleet's tiles under the view: the coarsest zoom whose pixels are no larger
// than the canvas's, every tile the view covers.
function drawFleetTiles(ctx, f, anchorInfo, x0, y0, x1, y1, scale, px) {
  const tiles = state.fleetTiles.get(f.fleet);
  const zooms = anchorInfo?.tiles?.zooms;
  if (!tiles || !zooms) return 0;
  const fine = zooms.filter((z) => z.metres_per_pixel <= 1 / scale);
  const zoom = fine.length ? fine[0] : zooms.at(-1);
  const span = 256 * zoom.metres_per_pixel;
  let drawn = 0;
  for (let tx = Math.floor(x0 / span); tx <= Math.floor(x1 / span); tx++) {
    for (let ty = Math.floor(-y1 / span); ty <= Math.floor(-y0 / span); ty++) {
      const url = f.tiles.url.replace("{z}", zoom.zoom).replace("{x}", tx).replace("{y}", ty) + `?v=${tiles.loadedAt}`;
      let img = tiles.images.get(url);
      if (!img) {
        img = new Image();
        img.onload = scheduleDraw;
        img.src = authed(url);
        tiles.images.set(url, img);
      }
      if (!img.complete || !img.naturalWidth) continue;
      const [u, v] = px([tx * span, -ty * span]);
      ctx.drawImage(img, u, v, span * scale, span * scale);
      drawn++;
    }
  }
  return drawn;
}

function renderFleets() {
  const el = $("#fleets");
  if (!state.fleets.length) return;
  el.className = "fleets";
  el.innerHTML = state.fleets.map((f) => {
    const merged = f.sessions.filter((m) => m.merged);
    const unmerged = f.sessions.filter((m) => !m.merged);
    const robots = merged.map((m, i) => `<span><span class="swatch" style="background:${ROBOT_COLOURS[i % ROBOT_COLOURS.length]}"></span>${escapeHtml(m.robot_id)}${m.fleet_from_session?.anchor ? ' <span class="muted">(anchor)</span>' : ""}</span>`).join("");
    const apart = unmerged.length ? `<div class="muted">not merged yet: ${unmerged.map((m) => escapeHtml(m.robot_id)).join(", ")}</div>` : "";
    return `<div class="fleet"><h3>${escapeHtml(f.fleet)} <span class="muted">${merged.length} merged · ${f.indexed_keyframes} keyframes indexed${f.pose_graph_pending ? " · pose graph update pending" : ""}</span></h3>
      <canvas data-fleet="${escapeHtml(f.fleet)}" width="480" height="320"></canvas><div class="robots">${robots}</div>${apart}</div>`;
  }).join("");
  drawFleets();
}

function drawFleets() {
  let robots = 0, points = 0, tilesDrawn = 0;
  for (const f of state.fleets) {
    const canvas = [...document.querySelectorAll("#fleets canvas")].find((c) => c.dataset.fleet === f.fleet);
    if (!canvas) continue;
    const anchor = f.sessions.find((m) => m.fleet_from_session?.anchor);
    const up = anchor ? state.mapInfo.get(anchor.session_id)?.map_from_world_xyzw : null;
    const tracks = f.sessions.filter((m) => m.merged).map((m, i) => {
      const t = m.fleet_from_session;
      // The pose graph's correction of the robot's latest keyframe, over the whole trail.
      const c = m.latest_correction;
      const poses = (state.trajectories.get(m.session_id) || []).map((p) => {
        let inFleet = rotate(t.rotation_xyzw, p.t).map((v, k) => v + t.translation[k]);
        if (c) inFleet = rotate(c.rotation_xyzw, inFleet).map((v, k) => v + c.translation[k]);
        return up ? rotate(up, inFleet) : inFleet;
      });
      return { colour: ROBOT_COLOURS[i % ROBOT_COLOURS.length], poses };
    });
    const all = tracks.flatMap((t) => t.poses);
    const ctx = canvas.getContext("2d");
    ctx.fillStyle = "#0c1014";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    if (!all.length) continue;
    const xs = all.map((p) => p[0]), ys = all.map((p) => p[1]);
    const b = state.fleetTiles.get(f.fleet)?.bounds;
    if (b) { xs.push(b[0], b[2]); ys.push(b[1], b[3]); }
    const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
    const scale = Math.min((canvas.width - 40) / Math.max(x1 - x0, 0.2), (canvas.height - 40) / Math.max(y1 - y0, 0.2));
    const px = (p) => [20 + (p[0] - x0) * scale, canvas.height - 20 - (p[1] - y0) * scale];
    tilesDrawn += drawFleetTiles(ctx, f, anchor && state.mapInfo.get(anchor.session_id), x0, y0, x1, y1, scale, px);
    for (const t of tracks) {
      if (!t.poses.length) continue;
      robots++;
      points += t.poses.length;
      ctx.strokeStyle = t.colour;
      ctx.lineWidth = 1.5;
      ctx.beginPath();
      t.poses.forEach((p, k) => { const [u, v] = px(p); if (k) ctx.lineTo(u, v); else ctx.moveTo(u, v); });
      ctx.stroke();
      const [u, v] = px(t.poses.at(-1));
      ctx.fillStyle = t.colour;
      ctx.beginPath();
      ctx.arc(u, v, 5, 0, 2 * Math.PI);
      ctx.fill();
    }
  }
  window.__stillmap.fleets = state.fleets.length;
  window.__stillmap.fleetRobots = robots;
  window.__stillmap.fleetPoints = points;
  window.__stillmap.fleetTilesDrawn = tilesDrawn;
}

let drawPending = false;
function scheduleDraw() {
  if (drawPending) return;
  drawPending = true;
  requestAnimationFrame(() => { drawPending = false; drawMap(); update3dTrajectory(); drawFleets(); });
}

map2d.onChange = scheduleDraw;

// ---------------------------------------------------------------- the event stream
function connect() {
  const events = new EventSource(authed("/api/v1/events"));
  events.onopen = () => { $("#link").textContent = "live"; $("#link").className = "badge ok"; };
  events.onerror = () => { $("#link").textContent = "server unreachable, retrying…"; $("#link").className = "badge bad"; };
  events.addEventListener("sessions", (e) => {
    window.__stillmap.events++;
    const { sessions, stored_not_shown: notShown = 0 } = JSON.parse(e.data);
    // The snapshot lists every session in memory and the newest stored ones.
    $("#not-shown").hidden = notShown === 0;
    $("#not-shown").textContent = `${notShown} older stored sessions not shown (GET /api/v1/sessions lists them all, page by page)`;
    const seen = new Set();
    for (const s of sessions) {
      seen.add(s.session_id);
      const prev = state.sessions.get(s.session_id);
      state.sessions.set(s.session_id, s);
      const hist = state.history.get(s.session_id) || {};
      if (!prev || prev.frames_processed !== s.frames_processed) {
        const lat = { ...s.latency_ms };
        for (const [stage, ms] of Object.entries(lat)) {
          (hist[stage] ||= []).push(ms);
          if (hist[stage].length > SPARK_FRAMES) hist[stage].shift();
        }
      }
      state.history.set(s.session_id, hist);
      const version = s.map?.version;
      if (version !== undefined && state.mapVersion.get(s.session_id) !== version) {
        state.mapVersion.set(s.session_id, version);
        if (s.session_id === state.selected) { refreshMap(s.session_id, false); refreshCloud(false); }
      }
    }
    for (const id of [...state.sessions.keys()]) if (!seen.has(id)) state.sessions.delete(id);
    if (!state.selected && sessions.length) select(sessions[0].session_id);
    renderTable();
  });
  // New poses of every session, every http.pose_event_interval_ms (250 ms), oldest first.
  events.addEventListener("poses", (e) => {
    let draw = false;
    for (const p of JSON.parse(e.data)) {
      const list = state.trajectories.get(p.session_id) || [];
      list.push({ sequence: p.sequence, t: p.translation, q: p.rotation_xyzw });
      state.trajectories.set(p.session_id, list);
      draw ||= p.session_id === state.selected || state.fleets.length > 0;
    }
    if (draw) scheduleDraw();
  });
}

connect();
renderTable();
refreshFleets();
