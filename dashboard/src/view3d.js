// The 3D view: the static semantic point cloud (binary PLY from the server) with
// three.js, coloured by class or by RGB, orbit controls, the trajectory as a line.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { authed } from "./token.js";

const UNLABELLED = 65535;
const VERTEX_BYTES = 21; // x y z float, r g b uchar, class ushort, confidence float

function hexToRgb(hex) {
  const n = parseInt(hex.slice(1), 16);
  return [((n >> 16) & 255) / 255, ((n >> 8) & 255) / 255, (n & 255) / 255];
}

/// Parses the server's binary PLY (the layout of GET /api/v1/maps/{id}/cloud.ply).
export function parsePly(buffer) {
  const bytes = new Uint8Array(buffer);
  const marker = new TextEncoder().encode("end_header\n");
  let end = -1;
  for (let i = 0; i + marker.length <= Math.min(bytes.length, 65536); i++) {
    let ok = true;
    for (let k = 0; k < marker.length && ok; k++) ok = bytes[i + k] === marker[k];
    if (ok) { end = i + marker.length; break; }
  }
  if (end < 0) throw new Error("not a PLY file");
  const header = new TextDecoder().decode(bytes.subarray(0, end));
  const n = Number(/element vertex (\d+)/.exec(header)?.[1] ?? NaN);
  if (!Number.isFinite(n) || bytes.length - end !== n * VERTEX_BYTES) throw new Error("unexpected PLY layout");
  const view = new DataView(buffer, end);
  const xyz = new Float32Array(3 * n), rgb = new Float32Array(3 * n), cls = new Uint16Array(n);
  for (let i = 0; i < n; i++) {
    const o = i * VERTEX_BYTES;
    xyz[3 * i] = view.getFloat32(o, true);
    xyz[3 * i + 1] = view.getFloat32(o + 4, true);
    xyz[3 * i + 2] = view.getFloat32(o + 8, true);
    rgb[3 * i] = view.getUint8(o + 12) / 255;
    rgb[3 * i + 1] = view.getUint8(o + 13) / 255;
    rgb[3 * i + 2] = view.getUint8(o + 14) / 255;
    cls[i] = view.getUint16(o + 15, true);
  }
  return { n, xyz, rgb, cls };
}

export class View3D {
  constructor(container, status) {
    this.container = container;
    this.status = status;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0x0c1014);
    this.camera = new THREE.PerspectiveCamera(55, 1, 0.01, 500);
    this.camera.up.set(0, 0, 1); // the map frame is z up
    this.camera.position.set(3, -3, 3);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = true;
    container.appendChild(this.renderer.domElement);
    this.points = null;
    this.line = null;
    this.cloud = null;
    this.byRgb = false;
    this.hidden = new Set();
    this.classColors = new Map();
    this.fitted = false;
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
    const loop = () => { this.controls.update(); this.renderer.render(this.scene, this.camera); requestAnimationFrame(loop); };
    loop();
  }

  resize() {
    const w = this.container.clientWidth, h = this.container.clientHeight;
    if (!w || !h) return;
    this.renderer.setSize(w, h);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
  }

  async load(url, legend, _mapFromWorld) {
    const r = await fetch(authed(url), { cache: "no-cache" });
    if (!r.ok) { this.status.textContent = `no map yet (${r.status})`; return 0; }
    this.cloud = parsePly(await r.arrayBuffer());
    this.classColors = new Map(legend.filter((c) => c.class_id !== null).map((c) => [c.class_id, c.color]));
    this.status.textContent = this.cloud.n ? "" : "the map is empty so far";
    this.rebuild();
    return this.cloud.n;
  }

  colours() {
    const { n, rgb, cls, xyz } = this.cloud;
    if (this.byRgb) return rgb;
    const out = new Float32Array(3 * n);
    for (let i = 0; i < n; i++) {
      const hex = this.classColors.get(cls[i]);
      let c;
      if (cls[i] !== UNLABELLED && hex) c = hexToRgb(hex);
      else { const g = 0.3 + 0.55 * Math.min(1, Math.max(0, (xyz[3 * i + 2] + 1.5) / 2.5)); c = [g, g, g]; }
      out.set(c, 3 * i);
    }
    return out;
  }

  rebuild() {
    if (!this.cloud) return;
    const { n, xyz, cls } = this.cloud;
    // Hidden classes (legend toggles) leave the cloud too.
    const keep = [];
    const hiddenIds = new Set([...this.classColors].filter(([, hex]) => this.hidden.has(hex)).map(([id]) => id));
    const hideGrey = this.hidden.has("#919191");
    for (let i = 0; i < n; i++) {
      if (hiddenIds.has(cls[i]) || (hideGrey && (cls[i] === UNLABELLED || !this.classColors.has(cls[i])))) continue;
      keep.push(i);
    }
    const colours = this.colours();
    const pos = new Float32Array(3 * keep.length), col = new Float32Array(3 * keep.length);
    keep.forEach((i, k) => { pos.set(xyz.subarray(3 * i, 3 * i + 3), 3 * k); col.set(colours.subarray(3 * i, 3 * i + 3), 3 * k); });
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(pos, 3));
    geometry.setAttribute("color", new THREE.BufferAttribute(col, 3));
    if (this.points) { this.scene.remove(this.points); this.points.geometry.dispose(); }
    this.points = new THREE.Points(geometry, new THREE.PointsMaterial({ size: 0.02, vertexColors: true }));
    this.scene.add(this.points);
    if (!this.fitted && keep.length) {
      geometry.computeBoundingSphere();
      const s = geometry.boundingSphere;
      this.controls.target.copy(s.center);
      this.camera.position.copy(s.center).add(new THREE.Vector3(s.radius, -s.radius, s.radius));
      this.fitted = true;
    }
  }

  setTrajectory(points) {
    if (this.line) { this.scene.remove(this.line); this.line.geometry.dispose(); }
    if (points.length < 2) return;
    const geometry = new THREE.BufferGeometry().setFromPoints(points.map((p) => new THREE.Vector3(p[0], p[1], p[2])));
    this.line = new THREE.Line(geometry, new THREE.LineBasicMaterial({ color: 0xffb000 }));
    this.scene.add(this.line);
  }

  setColourByRgb(on) { this.byRgb = on; this.rebuild(); }

  setHidden(hidden) { this.hidden = new Set(hidden); this.rebuild(); }
}
