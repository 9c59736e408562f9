// lidarmap viewer: shows the glb embedded in the page (lidarmap view), with orbit, picking and layer toggles.
// Bundled with three.js (MIT, see THREE_LICENSE) into static/viewer.bundle.js by scripts/build_viewer.sh.
import {
  Box3, BoxHelper, Color, DirectionalLight, HemisphereLight, PerspectiveCamera, Raycaster, Scene, Vector2, Vector3, WebGLRenderer,
} from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";

// Which toggle shows which surface kind (the material names written by lidarmap.export.gltf).
const TOGGLES = { roofs: ["roof"], walls: ["wall", "ground"], openings: ["window", "door"], unknown: ["unknown"] };
// Attributes shown first in the panel (then every other attribute of the building).
const MAIN_ATTRIBUTES = [
  ["ground_z", "ground height (m)"], ["height", "height (m)"], ["roof_z_max", "highest point (m)"],
  ["measuredHeight", "measured height (m)"], ["coverage", "coverage"], ["status", "status"],
  ["lidarmap_windows", "windows"], ["lidarmap_doors", "doors"], ["epsilon_mean_windows", "mean window ε"],
  ["epsilon_max_windows", "max window ε"], ["lidarmap_facades", "façades"], ["lidarmap_unknown", "unknown regions"],
  ["lidarmap_campaigns", "campaigns"],
];

// The browser's own base64 decoder (a data: URL, allowed from file:// pages) is much faster than atob + a loop.
async function base64ToBuffer(text) {
  const response = await fetch(`data:application/octet-stream;base64,${text.trim()}`);
  return response.arrayBuffer();
}

// Milliseconds since navigation start at each step (window.lidarmapViewerTimings, read by the benchmark).
const timings = { script: performance.now() };

function formatValue(value) {
  if (value === null || value === undefined) return "–";
  if (typeof value === "number") return Number.isInteger(value) ? String(value) : value.toFixed(3);
  if (Array.isArray(value)) return value.map(formatValue).join(", ") || "–";
  if (typeof value === "object") return JSON.stringify(value);
  return String(value);
}

function el(tag, attrs = {}, text = "") {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (text) node.textContent = text;
  return node;
}

class Viewer {
  constructor(container, data) {
    this.data = data;
    this.container = container;
    this.renderer = new WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.renderer.setSize(container.clientWidth, container.clientHeight);
    container.appendChild(this.renderer.domElement);
    this.scene = new Scene();
    this.scene.background = new Color(0xdfe8f0);
    this.scene.add(new HemisphereLight(0xffffff, 0x606060, 1.6));
    const sun = new DirectionalLight(0xffffff, 1.6);
    sun.position.set(0.5, 1.0, 0.8);
    this.scene.add(sun);
    this.camera = new PerspectiveCamera(45, container.clientWidth / container.clientHeight, 0.1, 1e6);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.render());
    this.raycaster = new Raycaster();
    this.buildings = new Map(); // id -> Object3D
    this.selection = null;
    window.addEventListener("resize", () => this.resize());
    this.bindPicking();
  }

  async load(glbBase64) {
    const buffer = await base64ToBuffer(glbBase64);
    timings.decoded = performance.now();
    return new Promise((resolve, reject) => {
      new GLTFLoader().parse(buffer, "", (gltf) => resolve(this.setScene(gltf)), reject);
    });
  }

  setScene(gltf) {
    const root = gltf.scene;
    const extras = (gltf.parser.json.asset || {}).extras || {};
    this.origin = extras.origin || [0, 0, 0];
    root.traverse((node) => {
      // Draw in the file's local coordinates: float32 keeps mm there; the CRS offset is only shown in the panel.
      if (node.name === "lidarmap_origin") node.position.set(0, 0, 0);
    });
    root.updateMatrixWorld(true);
    root.traverse((node) => {
      if (node.userData && node.userData.id !== undefined && !node.isMesh) this.buildings.set(String(node.userData.id), node);
      if (node.isMesh) node.userData.kind = node.material.name;
    });
    this.model = root;
    this.scene.add(root);
    timings.parsed = performance.now();
    this.frame();
    return this.buildings.size;
  }

  frame() {
    const box = new Box3().setFromObject(this.model);
    if (box.isEmpty()) box.set(new Vector3(-10, -10, -10), new Vector3(10, 10, 10));
    const centre = box.getCenter(new Vector3());
    const radius = 0.8 * Math.max(box.getSize(new Vector3()).length() / 2, 1); // a city is flat: tighter
    const distance = radius / Math.sin((this.camera.fov * Math.PI) / 360);
    this.camera.position.copy(centre).add(this.viewDirection().multiplyScalar(distance));
    this.camera.near = distance / 1000;
    this.camera.far = distance * 10;
    this.centreRightOfPanel();
    this.controls.target.copy(centre);
    this.controls.update();
    this.render();
  }

  // Shift the picture so that the scene's centre is in the middle of what the side panel leaves free.
  centreRightOfPanel() {
    const w = this.container.clientWidth, h = this.container.clientHeight;
    const side = document.getElementById("side");
    const covered = side ? side.offsetLeft + side.offsetWidth : 0;
    if (covered > 0 && w > 2 * covered) this.camera.setViewOffset(w, h, -covered / 2, 0, w, h);
    else this.camera.clearViewOffset();
    this.camera.updateProjectionMatrix();
  }

  // Where to look from: square to the façades when most face one axis (a façade map: two rows facing their
  // street), from the side most of them face, turned 25° for depth; else from the south-east. Above, in both cases.
  viewDirection() {
    const sum = new Vector3(), a = new Vector3(), b = new Vector3(), c = new Vector3();
    let cxx = 0, cxz = 0, czz = 0;
    this.model.traverse((mesh) => {
      if (!mesh.isMesh || !["wall", "window"].includes(mesh.userData.kind)) return;
      const pos = mesh.geometry.attributes.position, index = mesh.geometry.index;
      const count = index ? index.count / 3 : pos.count / 3;
      for (let t = 0; t < count; t++) {
        const [i, j, k] = [0, 1, 2].map((n) => (index ? index.getX(3 * t + n) : 3 * t + n));
        a.fromBufferAttribute(pos, i).applyMatrix4(mesh.matrixWorld);
        b.fromBufferAttribute(pos, j).applyMatrix4(mesh.matrixWorld);
        c.fromBufferAttribute(pos, k).applyMatrix4(mesh.matrixWorld);
        const n = b.sub(a).cross(c.sub(a)).setY(0); // horizontal part; |n| ~ twice the area of a wall triangle
        const len = n.length();
        if (len === 0) continue;
        cxx += (n.x * n.x) / len; cxz += (n.x * n.z) / len; czz += (n.z * n.z) / len;
        sum.add(n);
      }
    });
    const trace = cxx + czz;
    const spread = Math.sqrt(((cxx - czz) / 2) ** 2 + cxz ** 2); // (λ1 - λ2) / 2
    if (trace > 0 && spread > 0.3 * trace) {
      const angle = 0.5 * Math.atan2(2 * cxz, cxx - czz);
      const axis = new Vector3(Math.cos(angle), 0, Math.sin(angle));
      if (axis.dot(sum) < 0) axis.negate();
      return axis.applyAxisAngle(new Vector3(0, 1, 0), (25 * Math.PI) / 180).setY(0.75).normalize();
    }
    return new Vector3(0.55, 0.65, 0.55).normalize();
  }

  render() {
    this.renderer.render(this.scene, this.camera);
  }

  resize() {
    const w = this.container.clientWidth, h = this.container.clientHeight;
    this.camera.aspect = w / h;
    this.centreRightOfPanel();
    this.renderer.setSize(w, h);
    this.render();
  }

  setKindsVisible(kinds, visible) {
    this.model.traverse((node) => {
      if (node.isMesh && kinds.includes(node.userData.kind)) node.visible = visible;
    });
    this.render();
  }

  // The building under the canvas pixel (x, y) (CSS pixels from the canvas' top left), or null.
  buildingAt(x, y) {
    const canvas = this.renderer.domElement;
    const ndc = new Vector2((x / canvas.clientWidth) * 2 - 1, -(y / canvas.clientHeight) * 2 + 1);
    this.raycaster.setFromCamera(ndc, this.camera);
    const hits = this.raycaster.intersectObject(this.model, true).filter((h) => h.object.visible);
    for (const hit of hits) {
      for (let node = hit.object; node; node = node.parent) {
        if (this.buildings.get(String(node.userData.id)) === node) return { id: String(node.userData.id), point: hit.point };
      }
    }
    return null;
  }

  bindPicking() {
    const canvas = this.renderer.domElement;
    let down = null;
    canvas.addEventListener("pointerdown", (e) => { down = [e.clientX, e.clientY]; });
    canvas.addEventListener("pointerup", (e) => {
      if (!down || Math.hypot(e.clientX - down[0], e.clientY - down[1]) > 4) return; // a drag orbits, a click picks
      const rect = canvas.getBoundingClientRect();
      const hit = this.buildingAt(e.clientX - rect.left, e.clientY - rect.top);
      this.select(hit ? hit.id : null, hit ? hit.point : null);
    });
  }

  select(id, point) {
    if (this.selection) this.scene.remove(this.selection);
    this.selection = null;
    const panel = document.getElementById("building-panel");
    panel.replaceChildren();
    if (id === null) {
      panel.appendChild(el("p", { class: "hint" }, "Click a building to see its attributes."));
      this.render();
      return;
    }
    const node = this.buildings.get(id);
    this.selection = new BoxHelper(node, 0x1060ff);
    this.scene.add(this.selection);
    panel.appendChild(el("h2", { id: "picked-id" }, id));
    const table = el("table");
    const attrs = node.userData;
    const row = (label, value) => {
      const tr = el("tr");
      tr.appendChild(el("th", {}, label));
      tr.appendChild(el("td", {}, formatValue(value)));
      table.appendChild(tr);
    };
    const shown = new Set(["id"]);
    for (const [key, label] of MAIN_ATTRIBUTES) {
      if (key in attrs) { row(label, attrs[key]); shown.add(key); }
    }
    if (point) {
      // back to the CRS: undo the y-up rotation and add the origin (float64 in JavaScript numbers)
      row("picked point (CRS)", [point.x + this.origin[0], -point.z + this.origin[1], point.y + this.origin[2]]);
    }
    for (const [key, value] of Object.entries(attrs)) {
      if (!shown.has(key) && key !== "kind" && key !== "name") row(key, value);
    }
    panel.appendChild(table);
    this.render();
  }

  // For tests: a canvas pixel (CSS px) where a click reaches the canvas and hits building ``id`` (a projected
  // triangle centre), or null.
  screenPointOf(id) {
    const node = this.buildings.get(String(id));
    if (!node) return null;
    const canvas = this.renderer.domElement;
    const candidates = [];
    node.traverse((mesh) => {
      if (!mesh.isMesh || !mesh.visible) return;
      const pos = mesh.geometry.attributes.position, index = mesh.geometry.index;
      const count = index ? index.count / 3 : pos.count / 3;
      const step = Math.max(1, Math.floor(count / 50));
      for (let t = 0; t < count; t += step) {
        const c = new Vector3();
        for (let k = 0; k < 3; k++) {
          const i = index ? index.getX(3 * t + k) : 3 * t + k;
          c.add(new Vector3().fromBufferAttribute(pos, i));
        }
        candidates.push(mesh.localToWorld(c.divideScalar(3)));
      }
    });
    for (const c of candidates) {
      const p = c.clone().project(this.camera);
      const x = ((p.x + 1) / 2) * canvas.clientWidth, y = ((1 - p.y) / 2) * canvas.clientHeight;
      if (x < 1 || y < 1 || x > canvas.clientWidth - 1 || y > canvas.clientHeight - 1) continue;
      const rect = canvas.getBoundingClientRect();
      if (document.elementFromPoint(rect.left + x, rect.top + y) !== canvas) continue; // under the side panel
      const hit = this.buildingAt(x, y);
      if (hit && hit.id === String(id)) return { x, y };
    }
    return null;
  }
}

function buildControls(viewer, data) {
  document.getElementById("building-count").textContent = String(viewer.buildings.size);
  const toggles = document.getElementById("toggles");
  for (const [name, kinds] of Object.entries(TOGGLES)) {
    const label = el("label");
    const box = el("input", { type: "checkbox", id: `toggle-${name}` });
    box.checked = true;
    box.addEventListener("change", () => viewer.setKindsVisible(kinds, box.checked));
    label.appendChild(box);
    label.appendChild(document.createTextNode(` ${name}`));
    toggles.appendChild(label);
  }
  const campaigns = document.getElementById("campaigns");
  const list = data.campaigns || [];
  if (!list.length) campaigns.appendChild(el("li", {}, "none (an aerial run, not a map)"));
  for (const c of list) {
    campaigns.appendChild(el("li", {}, `${c.campaign_id}: ${c.kind} · ${c.source} · ${c.created.slice(0, 10)}`));
  }
  viewer.select(null, null);
}

async function main() {
  const data = JSON.parse(document.getElementById("lidarmap-data").textContent);
  const viewer = new Viewer(document.getElementById("view"), data);
  window.lidarmapViewer = viewer;
  try {
    await viewer.load(document.getElementById("lidarmap-glb").textContent);
    buildControls(viewer, data);
    viewer.render();
    viewer.renderer.getContext().finish(); // the frame is drawn, not only queued
    timings.drawn = performance.now();
    window.lidarmapViewerTimings = timings;
    window.lidarmapViewerReady = true;
  } catch (err) {
    window.lidarmapViewerError = String(err && err.message ? err.message : err);
    document.getElementById("building-panel").textContent = `could not load the model: ${window.lidarmapViewerError}`;
  }
}

main();
