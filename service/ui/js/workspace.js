// The 3-D workspace (three.js): the scan, the raw trace, the reconstruction coloured by its
// displacement from the trace, and the planned TCP path, in the robot's base frame when the
// session is calibrated (else the tracker frame). Each layer's geometry is made once and its
// buffers refilled; GPU objects are disposed of when they are replaced.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { api } from "./api.js";

/** The layers that show the workpiece (framed by default). */
const WORKPIECE = ["scan", "trace", "reconstruction"];
const COLOURS = { scan: 0x8a8f98, trace: 0xff8c00, path: 0x1f77ff };
/** Displacement colour ramp: blue (none) -> green -> yellow -> red (the largest). */
const RAMP = [[0.0, [0.15, 0.3, 0.9]], [0.33, [0.1, 0.75, 0.35]], [0.66, [0.95, 0.85, 0.1]], [1.0, [0.9, 0.1, 0.1]]];

function ramp(t) {
  for (let i = 1; i < RAMP.length; i++) {
    const [t1, c1] = RAMP[i];
    const [t0, c0] = RAMP[i - 1];
    if (t <= t1) {
      const f = (t - t0) / (t1 - t0 || 1);
      return c0.map((v, k) => v + f * (c1[k] - v));
    }
  }
  return RAMP[RAMP.length - 1][1];
}

/** CSV text -> {columns: name -> Float64Array}; lines starting with # are skipped. */
function parseCsv(text, wanted, every = 1) {
  const lines = text.split("\n").filter((line) => line && !line.startsWith("#"));
  const header = lines[0].split(",");
  const index = wanted.map((name) => header.indexOf(name));
  if (index.some((i) => i < 0)) throw new Error(`the CSV lacks ${wanted.join(", ")}`);
  const rows = lines.slice(1).filter((_, i) => i % every === 0);
  const out = Object.fromEntries(wanted.map((name) => [name, new Float64Array(rows.length)]));
  rows.forEach((line, r) => {
    const cells = line.split(",");
    wanted.forEach((name, k) => { out[name][r] = Number(cells[index[k]]); });
  });
  return { n: rows.length, ...out };
}

function matrix(rows) {
  const m = new THREE.Matrix4();
  if (rows) m.set(...rows.flat());
  return m;
}

export class Workspace {
  constructor(container, layers, legend) {
    this.container = container;
    this.legend = legend;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.renderer.setClearColor(0xf6f7f9);
    container.append(this.renderer.domElement);
    this.renderer.domElement.setAttribute("aria-label", "3-D workspace");
    this.scene = new THREE.Scene();
    this.scene.up = new THREE.Vector3(0, 0, 1);
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.001, 100);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(1, -1, 1);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.render());
    this.scene.add(new THREE.AxesHelper(0.1));
    this.pointSize = 2;
    this.layers = {};
    this.shown = null; // what the layers were filled from (ids), so nothing is fetched twice
    for (const box of layers.querySelectorAll("input[type=checkbox]")) {
      box.addEventListener("change", () => {
        const layer = this.layers[box.name];
        if (layer) layer.visible = box.checked;
        this.render();
      });
    }
    this.view = "workpiece";
    for (const button of layers.querySelectorAll("button[data-view]")) {
      button.addEventListener("click", () => this.frame(button.dataset.view));
    }
    this.visibility = (name) => layers.querySelector(`input[name=${name}]`)?.checked ?? true;
    layers.querySelector("#point-size").addEventListener("input", (event) => {
      this.pointSize = Number(event.target.value);
      for (const name of ["scan", "reconstruction"]) {
        if (this.layers[name]) this.layers[name].material.size = this.pointSize;
      }
      this.render();
    });
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  resize() {
    const width = this.container.clientWidth || 400;
    const height = this.container.clientHeight || 300;
    this.renderer.setSize(width, height, false);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() {
    this.renderer.render(this.scene, this.camera);
  }

  /** A layer of `count` points or a line, made once per kind and refilled after. */
  layer(name, kind, positions, colours) {
    let object = this.layers[name];
    const n = positions.length / 3;
    if (object && object.geometry.attributes.position.array.length < positions.length) {
      this.scene.remove(object);
      object.geometry.dispose();
      object.material.dispose();
      object = null;
    }
    if (!object) {
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(new Float32Array(positions.length), 3));
      if (colours) geometry.setAttribute("color", new THREE.BufferAttribute(new Float32Array(colours.length), 3));
      const material = kind === "points"
        ? new THREE.PointsMaterial({ size: this.pointSize, sizeAttenuation: false, vertexColors: Boolean(colours), color: colours ? 0xffffff : COLOURS[name] })
        : new THREE.LineBasicMaterial({ color: COLOURS[name] });
      object = kind === "points" ? new THREE.Points(geometry, material) : new THREE.Line(geometry, material);
      object.name = name;
      this.layers[name] = object;
      this.scene.add(object);
    }
    const position = object.geometry.attributes.position;
    position.array.set(positions);
    // Past the draw range: the last point again, so that the bounds stay those of the data.
    for (let i = positions.length; i < position.array.length; i += 3) {
      position.array.copyWithin(i, positions.length - 3, positions.length);
    }
    position.needsUpdate = true;
    if (colours) {
      object.geometry.attributes.color.array.set(colours);
      object.geometry.attributes.color.needsUpdate = true;
    }
    object.geometry.setDrawRange(0, n);
    object.geometry.computeBoundingSphere();
    object.visible = this.visibility(name);
    return object;
  }

  clear(name) {
    const object = this.layers[name];
    if (!object) return;
    this.scene.remove(object);
    object.geometry.dispose();
    object.material.dispose();
    delete this.layers[name];
  }

  /** Fill the layers from a session's artifacts (each fetched only when it changed). */
  async show(sid, { session, reconstructions, trajectories }) {
    const rec = reconstructions[reconstructions.length - 1] || null;
    const traj = rec ? [...trajectories].reverse().find((t) => t.inputs.reconstruction_id === rec.id) : null;
    const key = [sid, session.recording_id, session.scan_id, rec?.id, traj?.id].join("/");
    if (key === this.shown) return;
    this.shown = key;
    // The base frame when calibrated; the scan through the registration the reconstruction found.
    const baseTracker = matrix(session.T_base_tracker);
    const scanTracker = matrix(rec?.summary.T_scan_tracker || session.T_scan_tracker);
    const baseScan = baseTracker.clone().multiply(scanTracker.clone().invert());
    const transformed = (xyz, m) => {
      const v = new THREE.Vector3();
      const out = new Float32Array(xyz.length);
      for (let i = 0; i < xyz.length; i += 3) {
        v.set(xyz[i], xyz[i + 1], xyz[i + 2]).applyMatrix4(m);
        out[i] = v.x; out[i + 1] = v.y; out[i + 2] = v.z;
      }
      return out;
    };
    const interleave = (c) => {
      const out = new Float32Array(c.n * 3);
      for (let i = 0; i < c.n; i++) { out[3 * i] = c.x[i]; out[3 * i + 1] = c.y[i]; out[3 * i + 2] = c.z[i]; }
      return out;
    };

    if (session.scan_id) {
      const response = await api(`/sessions/${sid}/scans/${session.scan_id}/points?max_points=200000`, { raw: true });
      this.layer("scan", "points", transformed(new Float32Array(await response.arrayBuffer()), baseScan));
    } else this.clear("scan");

    if (session.recording_id) {
      const csv = parseCsv(await api(`/sessions/${sid}/recordings/${session.recording_id}/csv`), ["x", "y", "z"]);
      this.layer("trace", "line", transformed(interleave(csv), baseTracker));
    } else this.clear("trace");

    if (rec) {
      const csv = parseCsv(await api(`/sessions/${sid}/reconstructions/${rec.id}/csv`), ["x", "y", "z", "displacement_m"]);
      const top = Math.max(...csv.displacement_m, 1e-9);
      const colours = new Float32Array(csv.n * 3);
      for (let i = 0; i < csv.n; i++) colours.set(ramp(csv.displacement_m[i] / top), 3 * i);
      this.layer("reconstruction", "points", transformed(interleave(csv), baseTracker), colours);
      this.legend.querySelector("#legend-max").textContent = `${(top * 1000).toFixed(2)} mm`;
    } else this.clear("reconstruction");

    if (traj) {
      const text = await api(`/sessions/${sid}/trajectories/${traj.id}/csv`);
      const rows = text.split("\n").length;
      const csv = parseCsv(text, ["x", "y", "z"], Math.max(1, Math.floor(rows / 5000)));
      this.layer("path", "line", interleave(csv));
    } else this.clear("path");

    this.frame();
  }

  /** Aim the camera at the workpiece (scan, trace, reconstruction: what the operator checks
   * first; the planned motion's transit from the arm's pose spans metres and would shrink it
   * to a few pixels), or at everything shown (`view` "all"). */
  frame(view = this.view) {
    this.view = view;
    const names = view === "all" ? Object.keys(this.layers) : WORKPIECE.filter((n) => this.layers[n]);
    const box = new THREE.Box3();
    for (const name of names.length ? names : Object.keys(this.layers)) box.expandByObject(this.layers[name]);
    if (box.isEmpty()) return this.render();
    const centre = box.getCenter(new THREE.Vector3());
    const size = Math.max(box.getSize(new THREE.Vector3()).length(), 0.05);
    this.controls.target.copy(centre);
    this.camera.position.copy(centre).add(new THREE.Vector3(0.6, -0.9, 0.7).multiplyScalar(size));
    this.camera.near = size / 100;
    this.camera.far = size * 100;
    this.camera.updateProjectionMatrix();
    this.controls.update();
    this.render();
  }

  dispose() {
    for (const name of Object.keys(this.layers)) this.clear(name);
    this.controls.dispose();
    this.renderer.dispose();
  }
}
