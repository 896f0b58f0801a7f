// The 2D map: the server's semantic tiles (z/x/y, see GET /api/v1/maps/{id}) on a
// canvas with pan and zoom, classes toggled off by recolouring tile pixels, the
// trajectory and the current pose on top. Coordinates are the map frame (metres,
// z up); the screen shows x east, y north.

import { authed } from "./token.js";

const BACKGROUND = "#0c1014";
const TILE_PX = 256;

/// Rotates v by the unit quaternion q = [x, y, z, w].
export function rotate(q, v) {
  const [x, y, z, w] = q;
  const [vx, vy, vz] = v;
  // t = 2 q × v; v' = v + w t + q × t
  const tx = 2 * (y * vz - z * vy), ty = 2 * (z * vx - x * vz), tz = 2 * (x * vy - y * vx);
  return [vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz), vz + w * tz + (x * ty - y * tx)];
}

function hexToRgb(hex) {
  const n = parseInt(hex.slice(1), 16);
  return [(n >> 16) & 255, (n >> 8) & 255, n & 255];
}

export class Map2D {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.session = null;
    this.info = null;
    this.view = { x: 0, y: 0, pxPerM: 60 }; // centre (map metres) and scale
    this.tiles = new Map(); // url -> { img, ready, filtered }
    // Tile position (url without the version) -> its newest loaded tile: shown while the
    // map's next version loads, so a live map never blinks to the background.
    this.shown = new Map();
    this.hidden = new Set(); // legend colours switched off
    this.legend = [];
    this.tilesDrawn = 0;
    this.onChange = () => {};
    this.path = [];
    this.pose = null;
    this.installControls();
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
  }

  resize() {
    const r = this.canvas.getBoundingClientRect();
    if (r.width > 0 && (this.canvas.width !== Math.round(r.width) || this.canvas.height !== Math.round(r.height))) {
      this.canvas.width = Math.round(r.width);
      this.canvas.height = Math.round(r.height);
      this.onChange();
    }
  }

  installControls() {
    let drag = null;
    this.canvas.addEventListener("pointerdown", (e) => { drag = { x: e.clientX, y: e.clientY }; this.canvas.setPointerCapture(e.pointerId); });
    this.canvas.addEventListener("pointermove", (e) => {
      if (!drag) return;
      this.view.x -= (e.clientX - drag.x) / this.view.pxPerM;
      this.view.y += (e.clientY - drag.y) / this.view.pxPerM;
      drag = { x: e.clientX, y: e.clientY };
      this.onChange();
    });
    this.canvas.addEventListener("pointerup", () => { drag = null; });
    this.canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      const r = this.canvas.getBoundingClientRect();
      const before = this.toMap(e.clientX - r.left, e.clientY - r.top);
      this.view.pxPerM = Math.min(2000, Math.max(0.5, this.view.pxPerM * Math.exp(-e.deltaY * 0.0015)));
      const after = this.toMap(e.clientX - r.left, e.clientY - r.top);
      this.view.x += before[0] - after[0];
      this.view.y += before[1] - after[1];
      this.onChange();
    }, { passive: false });
    this.canvas.addEventListener("dblclick", () => { this.fit(); this.onChange(); });
  }

  toScreen(x, y) {
    return [this.canvas.width / 2 + (x - this.view.x) * this.view.pxPerM, this.canvas.height / 2 - (y - this.view.y) * this.view.pxPerM];
  }

  toMap(sx, sy) {
    return [this.view.x + (sx - this.canvas.width / 2) / this.view.pxPerM, this.view.y - (sy - this.canvas.height / 2) / this.view.pxPerM];
  }

  setMap(session, info, legend, fit) {
    const changed = session !== this.session;
    this.session = session;
    this.info = info;
    this.legend = legend;
    if (changed) { this.tiles.clear(); this.shown.clear(); }
    if (fit || changed) this.fit();
  }

  fit() {
    const b = this.info?.bounds_xy;
    if (!b) return;
    this.view.x = (b[0] + b[2]) / 2;
    this.view.y = (b[1] + b[3]) / 2;
    const span = Math.max(b[2] - b[0], b[3] - b[1], 0.5);
    this.view.pxPerM = 0.9 * Math.min(this.canvas.width, this.canvas.height) / span;
  }

  invalidateFilters() {
    for (const t of this.tiles.values()) t.filtered = null;
  }

  /// The tile image with hidden classes made transparent.
  filtered(tile) {
    if (!this.hidden.size) return tile.img;
    if (tile.filtered) return tile.filtered;
    const c = document.createElement("canvas");
    c.width = c.height = TILE_PX;
    const g = c.getContext("2d");
    g.drawImage(tile.img, 0, 0);
    const data = g.getImageData(0, 0, TILE_PX, TILE_PX);
    const hidden = [...this.hidden].map(hexToRgb);
    const greyHidden = this.legend.some((l) => l.class_id === null && this.hidden.has(l.color));
    const px = data.data;
    for (let i = 0; i < px.length; i += 4) {
      if (px[i + 3] === 0) continue;
      const [r, gg, b] = [px[i], px[i + 1], px[i + 2]];
      // Unlabelled surfaces are grey (shaded by height): one legend entry hides them all.
      if ((greyHidden && r === gg && gg === b) || hidden.some((h) => h[0] === r && h[1] === gg && h[2] === b)) px[i + 3] = 0;
    }
    g.putImageData(data, 0, 0);
    tile.filtered = c;
    return c;
  }

  draw(path, pose) {
    const { ctx, canvas } = this;
    ctx.fillStyle = BACKGROUND;
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    this.tilesDrawn = 0;
    const info = this.info;
    if (info && info.tiles) {
      const zooms = info.tiles.zooms;
      // The zoom whose pixels are closest to (not coarser than twice) the screen's.
      const mPerScreenPx = 1 / this.view.pxPerM;
      let zoom = zooms.length - 1;
      while (zoom > 0 && zooms[zoom - 1].metres_per_pixel <= mPerScreenPx * 1.5) zoom--;
      const span = TILE_PX * zooms[zoom].metres_per_pixel;
      const [x0, y1] = this.toMap(0, 0);
      const [x1, y0] = this.toMap(canvas.width, canvas.height);
      const visible = new Set();
      for (let tx = Math.floor(x0 / span); tx <= Math.floor(x1 / span); tx++) {
        for (let ty = Math.floor(-y1 / span); ty <= Math.floor(-y0 / span); ty++) {
          const position = `/api/v1/maps/${encodeURIComponent(this.session)}/tiles/${zoom}/${tx}/${ty}.png`;
          const url = `${position}?v=${info.version}`;
          let tile = this.tiles.get(url);
          if (!tile) {
            tile = { img: new Image(), ready: false, filtered: null, version: info.version };
            const session = this.session;
            tile.img.onload = () => {
              tile.ready = true;
              const current = this.shown.get(position);
              if (session === this.session && !(current && current.version > tile.version)) this.shown.set(position, tile);
              this.onChange();
            };
            tile.img.src = authed(url);
            this.tiles.set(url, tile);
          }
          visible.add(position);
          const show = tile.ready ? tile : this.shown.get(position);
          if (!show) continue;
          tile = show;
          const [sx, sy] = this.toScreen(tx * span, -ty * span);
          const size = span * this.view.pxPerM;
          ctx.imageSmoothingEnabled = false;
          ctx.drawImage(this.filtered(tile), sx, sy, size, size);
          this.tilesDrawn++;
        }
      }
      // Keep the cache to the current version, and the stand-ins to the view.
      for (const key of this.tiles.keys()) if (!key.endsWith(`?v=${info.version}`)) this.tiles.delete(key);
      for (const key of this.shown.keys()) if (!visible.has(key)) this.shown.delete(key);
    }
    // Trajectory and current pose. The trail has a dark casing so it shows over any
    // tile; zoomed out until it spans a few pixels, a ring marks where it is.
    if (path.length > 1) {
      const screen = path.map((p) => this.toScreen(p[0], p[1]));
      const trace = () => { ctx.beginPath(); screen.forEach(([sx, sy], i) => (i ? ctx.lineTo(sx, sy) : ctx.moveTo(sx, sy))); ctx.stroke(); };
      ctx.lineJoin = "round";
      ctx.strokeStyle = "#0c1014";
      ctx.lineWidth = 4;
      trace();
      ctx.strokeStyle = "#ffb000";
      ctx.lineWidth = 2;
      trace();
      const xs = screen.map((p) => p[0]), ys = screen.map((p) => p[1]);
      const extent = Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys));
      if (extent < 16) {
        ctx.beginPath();
        ctx.arc((Math.max(...xs) + Math.min(...xs)) / 2, (Math.max(...ys) + Math.min(...ys)) / 2, 12, 0, 2 * Math.PI);
        ctx.stroke();
      }
    }
    if (pose) {
      const [sx, sy] = this.toScreen(pose.t[0], pose.t[1]);
      const f = pose.forward;
      const n = Math.hypot(f[0], f[1]) || 1;
      // Hollow, so the trail beneath it stays visible.
      ctx.strokeStyle = "#ff4d6d";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.arc(sx, sy, 5, 0, 2 * Math.PI);
      ctx.stroke();
      ctx.beginPath();
      ctx.moveTo(sx, sy);
      ctx.lineTo(sx + (18 * f[0]) / n, sy - (18 * f[1]) / n);
      ctx.stroke();
    }
    // Scale bar.
    const metres = [0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100].find((m) => m * this.view.pxPerM >= 60) || 100;
    ctx.fillStyle = "#8a97a5";
    ctx.fillRect(12, canvas.height - 14, metres * this.view.pxPerM, 3);
    ctx.font = "11px system-ui";
    ctx.fillText(`${metres} m`, 12, canvas.height - 20);
  }
}
