// The 3-D workspace (three.js): the scan, the raw trace, the reconstruction coloured by its
// displacement from the trace, and the planned TCP path, in the robot's base frame when the
// session is calibrated (else the tracker frame). Each layer's geometry is made once and its
// buffers refilled; GPU objects are disposed of when they are replaced.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { api } from "./api.js";

/** Which shown layer a click picks first, when several have a point under the finger. */
const PICK_ORDER = ["overlay", "reconstruction", "path", "trace", "scan"];

/** The live arm is redrawn at most this often (ms): each redraw renders the whole scene (the
 * scan's points too), which on a software-rendered screen costs the CPU the server may need. */
const LIVE_ARM_MS = 500;
/** A pose that moved less than this (m, at every joint) is not redrawn. */
const LIVE_ARM_STILL_M = 5e-4;

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

/** CSV text -> {n, name -> Float64Array (or Array of strings for `text` columns)}; lines
 * starting with # are skipped; empty cells are NaN. */
function parseCsv(text, wanted, every = 1, textColumns = []) {
  const lines = text.split("\n").filter((line) => line && !line.startsWith("#"));
  const header = lines[0].split(",");
  const index = wanted.map((name) => header.indexOf(name));
  if (index.some((i) => i < 0)) throw new Error(`the CSV lacks ${wanted.join(", ")}`);
  const rows = lines.slice(1).filter((_, i) => i % every === 0);
  const out = Object.fromEntries(wanted.map((name) => [name, textColumns.includes(name) ? new Array(rows.length) : new Float64Array(rows.length)]));
  rows.forEach((line, r) => {
    const cells = line.split(",");
    wanted.forEach((name, k) => {
      const cell = cells[index[k]];
      out[name][r] = textColumns.includes(name) ? cell : cell === "" ? NaN : Number(cell);
    });
  });
  return { n: rows.length, ...out };
}

/** The reconstruction's per-point diagnostics the pendant shows on a click. */
const DIAGNOSTICS = ["displacement_m", "mode", "segment", "n_path", "n_surface", "residual_path_m", "residual_surface_m", "alpha", "uncertainty_m", "reason"];
const MODE_COLOURS = { edge: [0.85, 0.1, 0.1], surface: [0.1, 0.55, 0.2], path: [0.15, 0.3, 0.9], unchanged: [0.5, 0.5, 0.5] };
/** One colour, one meaning in the view: orange is the trace alone (recorded or live), so the
 * lifts on and off the path are brown, and the cell being edited is the cell's magenta, dashed.
 * Vertex colours are linear (the screen shows them in sRGB: the brown here is about #8c5424). */
const PHASE_COLOURS = { transit: [0.55, 0.6, 0.75], approach: [0.26, 0.09, 0.02], process: [0.12, 0.47, 1.0], retract: [0.26, 0.09, 0.02], return: [0.55, 0.6, 0.75] };
const CELL_COLOUR = 0xc2185b;
/** The cell being edited: dashes of this length and gap (metres, in the scene). */
const DRAFT_DASH_M = 0.02;
const DRAFT_GAP_M = 0.012;

/** How the planned path is coloured: per waypoint, 0 (fine, blue) .. 1 (the limit, red). */
const PATH_COLOURING = {
  phase: { legend: "path by phase: blue process, brown approach and retract, grey transit" },
  speed: { legend: "path by speed: blue at the requested speed, red slowed to a stop",
    risk: (p, i) => 1 - Math.min(1, p.speed_m_s[i] / p.requested_speed_m_s) },
  clearance: { legend: "path by clearance: blue 50 mm or more from the cell, red touching",
    unknown: "path by clearance: grey, this plan was not checked against the cell",
    known: (p) => Boolean(p.clearance_m),
    // null at a sample: nothing of the cell within reach (as far from it as can be).
    risk: (p, i) => (p.clearance_m[i] == null ? 0 : 1 - Math.min(1, Math.max(0, p.clearance_m[i]) / 0.05)) },
  limits: { legend: "path by joint-limit margin: blue 30° or more, red at a limit",
    risk: (p, i) => 1 - Math.min(1, Math.max(0, p.limit_margin_deg[i]) / 30) },
  singularity: { legend: "path by singularity: blue |sin q| ≥ 0.2 at wrist and elbow, red singular",
    risk: (p, i) => 1 - Math.min(1, Math.min(p.wrist_singularity[i], p.elbow_singularity[i]) / 0.2) },
};

/** The 12 edges of a box (x_min, y_min, z_min, x_max, y_max, z_max) as segment ends. */
function boxEdges([x0, y0, z0, x1, y1, z1]) {
  const c = [[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0], [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]];
  const edges = [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]];
  return edges.flatMap(([a, b]) => [...c[a], ...c[b]]);
}

/** A plane n . p = d (n, d in the base frame) drawn as a 1 m square with a grid, centred on the
 * plane's point nearest the base. */
function planeGrid([nx, ny, nz, d], half = 0.5, lines = 5) {
  const n = new THREE.Vector3(nx, ny, nz).normalize();
  const centre = n.clone().multiplyScalar(d / Math.hypot(nx, ny, nz));
  const u = new THREE.Vector3().crossVectors(n, Math.abs(n.z) < 0.9 ? new THREE.Vector3(0, 0, 1) : new THREE.Vector3(1, 0, 0)).normalize();
  const v = new THREE.Vector3().crossVectors(n, u);
  const at = (a, b) => centre.clone().addScaledVector(u, a).addScaledVector(v, b).toArray();
  const out = [];
  for (let i = 0; i < lines; i++) {
    const t = -half + (2 * half * i) / (lines - 1);
    out.push(...at(t, -half), ...at(t, half), ...at(-half, t), ...at(half, t));
  }
  return out;
}

/** A text label drawn into a sprite (for the frames' names). */
function label(text, colour = "#111") {
  const canvas = document.createElement("canvas");
  const font = "bold 36px sans-serif";
  const measure = canvas.getContext("2d");
  measure.font = font;
  canvas.width = Math.ceil(measure.measureText(text).width) + 8; canvas.height = 64;
  const context = canvas.getContext("2d");
  context.font = font;
  context.fillStyle = colour;
  context.fillText(text, 4, 44);
  const texture = new THREE.CanvasTexture(canvas);
  const sprite = new THREE.Sprite(new THREE.SpriteMaterial({ map: texture, depthTest: false, sizeAttenuation: false }));
  sprite.scale.set(0.03 * (canvas.width / canvas.height), 0.03, 1);
  return sprite;
}

function matrix(rows) {
  const m = new THREE.Matrix4();
  if (rows) m.set(...rows.flat());
  return m;
}

export class Workspace {
  /**
   * @param {HTMLElement} container  where the canvas goes, with the view's framing buttons
   * @param {HTMLElement} layers  the layer toggles, point size and colourings
   * @param {HTMLElement} legend  the colour legend
   * @param {{onPlan?: Function, onPick?: Function}} hooks  called with the plan's preview and
   *   the execution's review when they change, and with a picked point's description
   */
  constructor(container, layers, legend, hooks = {}) {
    this.container = container;
    this.legend = legend;
    this.hooks = hooks;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.renderer.setClearColor(0xf6f7f9);
    container.append(this.renderer.domElement);
    this.renderer.domElement.setAttribute("aria-label", "3-D workspace");
    container.workspace = this; // for the browser tests: where a point is on the screen
    this.scene = new THREE.Scene();
    this.scene.up = new THREE.Vector3(0, 0, 1);
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.001, 100);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(1, -1, 1);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.render());
    this.controls.addEventListener("start", () => { this.steered = true; }); // the operator's camera now
    this.pointSize = 2;
    this.layers = {};
    this.inBaseFrame = true; // nothing shown yet: the arm's own frame
    this.shown = null; // what the layers were filled from (ids), so nothing is fetched twice
    this.preview = null;
    this.reconstruction = null; // the shown reconstruction's CSV columns (for picking)
    this.picks = [];
    for (const box of layers.querySelectorAll("input[type=checkbox]")) {
      box.addEventListener("change", () => {
        for (const name of this.members(box.name)) if (this.layers[name]) this.layers[name].visible = box.checked;
        this.render();
      });
    }
    this.view = "workpiece";
    for (const button of container.querySelectorAll("button[data-view]")) {
      button.addEventListener("click", () => this.frame(button.dataset.view));
    }
    this.visibility = (name) => layers.querySelector(`input[name=${this.toggleOf(name)}]`)?.checked ?? true;
    layers.querySelector("#point-size").addEventListener("input", (event) => {
      this.pointSize = Number(event.target.value);
      for (const name of ["scan", "reconstruction"]) {
        if (this.layers[name]) this.layers[name].material.size = this.pointSize;
      }
      this.render();
    });
    this.pathColour = layers.querySelector("#path-colour");
    this.pathColour.addEventListener("change", () => { this.colourPath(); this.render(); });
    this.reconColour = layers.querySelector("#recon-colour");
    this.reconColour.addEventListener("change", () => { this.colourReconstruction(); this.render(); });
    this.measure = layers.querySelector("#measure");
    this.measure.addEventListener("change", () => { this.picks = []; this.clear("measure"); this.render(); });
    this.renderer.domElement.addEventListener("pointerdown", (event) => { this.down = [event.clientX, event.clientY]; });
    this.renderer.domElement.addEventListener("pointerup", (event) => {
      // A click, not the end of an orbit drag.
      if (this.down && Math.hypot(event.clientX - this.down[0], event.clientY - this.down[1]) < 5) this.pick(event);
    });
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  /** The objects a layer toggle switches (the arm figure is two; the frames three). */
  members(toggle) {
    return { arm: ["arm", "arm-joints"], "live-arm": ["live-arm", "live-arm-joints"], frames: ["frames"], path: ["path", "tool-axes"], cell: ["cell", "cell-draft"] }[toggle] || [toggle];
  }

  toggleOf(name) {
    return { "arm-joints": "arm", "live-arm-joints": "live-arm", "tool-axes": "path", "cell-draft": "cell" }[name] || name;
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

  /** A layer of points or a line, made once per kind and refilled after. */
  layer(name, kind, positions, colours, colour = COLOURS[name], capacity = positions.length) {
    let object = this.layers[name];
    const n = positions.length / 3;
    if (object && (object.geometry.attributes.position.array.length < positions.length
        || Boolean(object.geometry.attributes.color) !== Boolean(colours))) {
      this.clear(name);
      object = null;
    }
    if (!object) {
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(new Float32Array(Math.max(capacity, positions.length)), 3));
      if (colours) geometry.setAttribute("color", new THREE.BufferAttribute(new Float32Array(colours.length), 3));
      const material = kind === "points"
        ? new THREE.PointsMaterial({ size: name.endsWith("arm-joints") ? 8 : this.pointSize, sizeAttenuation: false, vertexColors: Boolean(colours), color: colours ? 0xffffff : colour })
        : new THREE.LineBasicMaterial({ color: colours ? 0xffffff : colour, vertexColors: Boolean(colours) });
      object = kind === "points" ? new THREE.Points(geometry, material)
        : kind === "segments" ? new THREE.LineSegments(geometry, material) : new THREE.Line(geometry, material);
      object.name = name;
      this.layers[name] = object;
      this.scene.add(object);
    }
    if (!colours) object.material.color.set(colour); // a reused layer takes the colour asked for now
    const position = object.geometry.attributes.position;
    position.array.set(positions);
    // Past the draw range: the last point again, so that the bounds stay those of the data.
    for (let i = positions.length; i < position.array.length; i += 3) {
      position.array.copyWithin(i, positions.length - 3, positions.length);
    }
    position.needsUpdate = true;
    if (colours) this.recolour(name, colours);
    object.geometry.setDrawRange(0, n);
    object.geometry.computeBoundingSphere();
    object.visible = this.visibility(name);
    return object;
  }

  recolour(name, colours) {
    const attribute = this.layers[name]?.geometry.attributes.color;
    if (!attribute) return;
    attribute.array.set(colours);
    attribute.needsUpdate = true;
  }

  clear(name) {
    const object = this.layers[name];
    if (!object) return;
    this.scene.remove(object);
    object.traverse((child) => {
      child.geometry?.dispose();
      child.material?.map?.dispose();
      child.material?.dispose();
    });
    delete this.layers[name];
  }

  /** Fill the layers from a session's artifacts (each fetched only when it changed);
   * `plan` is the plan in use (the page chooses it; a move to its start is drawn by showMove),
   * `reviewExecution` the execution reviewed against it (null: none). */
  async show(sid, { session, reconstructions, plan: traj = null, reviewExecution = null, touches: allTouches = [] }) {
    const rec = reconstructions[reconstructions.length - 1] || null;
    // The execution the page's tables show (the caller chooses), if it is of this plan.
    const exec = traj && reviewExecution?.inputs.trajectory_id === traj.id ? reviewExecution : null;
    const calibration = JSON.stringify([session.T_base_tracker, session.T_scan_tracker, rec?.summary.T_scan_tracker]);
    const touches = allTouches[allTouches.length - 1] || null;
    const key = [sid, session.recording_id, session.scan_id, rec?.id, traj?.id, exec?.id, touches?.id, calibration].join("/");
    if (key === this.shown || key === this.showing) return;
    // The newest call wins: an older one still loading stops at its next step.
    this.showing = key;
    const current = () => this.showing === key;
    try {
      await this.fill(sid, key, current, { session, rec, traj, exec, touches });
    } finally {
      if (current()) this.showing = null;
    }
  }

  /** The layers for one state of the session (see show); `current()` is false once a newer
   * state is being shown, and then nothing more is drawn from this one. */
  async fill(sid, key, current, { session, rec, traj, exec, touches }) {
    // The base frame when calibrated; the scan through the registration the reconstruction found.
    const baseTracker = matrix(session.T_base_tracker);
    this.baseTracker = baseTracker;
    this.inBaseFrame = Boolean(session.T_base_tracker);
    this.showLiveArm(this.liveArm);
    this.showCell(this.cell);
    this.showCell(this.cellDraft, { draft: true });
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
    this.picks = [];
    this.clear("measure");
    this.clear("pick");
    this.showOverlay(null);

    if (session.scan_id) {
      const response = await api(`/sessions/${sid}/scans/${session.scan_id}/points?max_points=200000`, { raw: true });
      const xyz = new Float32Array(await response.arrayBuffer());
      if (!current()) return;
      this.layer("scan", "points", transformed(xyz, baseScan));
    } else this.clear("scan");

    if (session.recording_id) {
      const csv = parseCsv(await api(`/sessions/${sid}/recordings/${session.recording_id}/csv`), ["x", "y", "z"]);
      if (!current()) return;
      this.layer("trace", "line", transformed(interleave(csv), baseTracker));
    } else this.clear("trace");

    // The touched points (tracker frame, the pen's tip) of the newest touches, where the
    // reconstructions place the scan by them.
    const touched = touches?.summary?.touches_m || [];
    if (touched.length) {
      const layer = this.layer("touches", "points", transformed(Float32Array.from(touched.flat()), baseTracker), null, 0x7b1fa2);
      layer.material.size = 12;
    } else this.clear("touches");

    if (rec) {
      const csv = parseCsv(await api(`/sessions/${sid}/reconstructions/${rec.id}/csv`), ["x", "y", "z", ...DIAGNOSTICS], 1, ["mode", "reason"]);
      if (!current()) return;
      this.reconstruction = { id: rec.id, ...csv };
      this.layer("reconstruction", "points", transformed(interleave(csv), baseTracker), new Float32Array(csv.n * 3));
      this.colourReconstruction();
    } else {
      this.reconstruction = null;
      this.clear("reconstruction");
      // No reconstruction shown: no colour scale for it either.
      this.legend.querySelector("#legend-displacement").hidden = true;
      this.legend.querySelector("#legend-modes").hidden = true;
    }

    this.showFrames(session.T_base_tracker ? baseTracker : null, baseTracker, session.scan_id ? baseScan : null);

    const preview = traj ? await api(`/sessions/${sid}/trajectories/${traj.id}/preview?max_samples=2000`) : null;
    if (!current()) return;
    this.preview = preview;
    if (this.preview) {
      const p = this.preview;
      this.layer("path", "line", Float32Array.from(p.tcp_m.flat()), new Float32Array(p.tcp_m.length * 3));
      this.colourPath();
      this.toolAxes(p);
      this.pose(p.joints_m[0]);
    } else {
      for (const name of ["path", "tool-axes", "arm", "arm-joints"]) this.clear(name);
    }
    const review = exec ? await api(`/sessions/${sid}/executions/${exec.id}/review?max_samples=2000`) : null;
    if (!current()) return;
    if (review?.actual_tcp_m.length) this.layer("executed", "line", Float32Array.from(review.actual_tcp_m.flat()), null, 0xd62728);
    else this.clear("executed");
    this.hooks.onPlan?.(this.preview, review, exec, traj?.id ?? null);
    this.frame();
    // Only a state drawn whole counts as shown (a failed fetch is tried again next refresh).
    this.shown = key;
    this.container.dataset.shown = key;
  }

  /** The trace of a running capture (tracker-frame points, [[x, y, z], ...]) over the scan,
   * with markers where tracking was lost and found again; null clears it. The buffers grow by
   * doubling, so a capture's stream refills them instead of making new ones each time. */
  showLive(points, lost = []) {
    if (!points) {
      this.liveBase = null;
      this.clear("live");
      this.clear("lost");
      return this.render();
    }
    const m = this.baseTracker || new THREE.Matrix4();
    const toBase = (list, out = new Float32Array(list.length * 3), from = 0) => {
      const v = new THREE.Vector3();
      for (let i = from; i < list.length; i++) {
        v.set(list[i][0], list[i][1], list[i][2]).applyMatrix4(m);
        out[3 * i] = v.x; out[3 * i + 1] = v.y; out[3 * i + 2] = v.z;
      }
      return out;
    };
    const capacity = (n) => 3 * 2 ** Math.ceil(Math.log2(Math.max(n, 256)));
    if (points.length) {
      // Only the new points are carried into the base frame (a long capture streams on).
      let cache = this.liveBase;
      if (!cache || cache.list !== points || cache.n > points.length) {
        cache = { list: points, xyz: new Float32Array(capacity(points.length)), n: 0 };
      } else if (cache.xyz.length < 3 * points.length) {
        const grown = new Float32Array(capacity(points.length));
        grown.set(cache.xyz);
        cache.xyz = grown;
      }
      toBase(points, cache.xyz, cache.n);
      cache.n = points.length;
      this.liveBase = cache;
      const live = this.layer("live", "points", cache.xyz.subarray(0, 3 * points.length), null, 0xff8c00, capacity(points.length));
      live.material.size = Math.max(3, this.pointSize + 1);
    }
    if (lost.length) {
      const marks = this.layer("lost", "points", toBase(lost), null, 0xd00000, capacity(lost.length));
      marks.material.size = 10;
    } else this.clear("lost");
    // Framed on the growing trace while nothing else of the workpiece is shown, until the
    // operator turns the camera (then it is theirs).
    if (points.length && !this.steered && !WORKPIECE.some((n) => this.layers[n])) this.frame("live");
    this.render();
  }

  /** Another reconstruction over the current one (tracker-frame ``points_m``), coloured by
   * ``difference_m`` on the displacement ramp (blue none .. red ``max_m``); null clears it. */
  showOverlay(diff) {
    if (!diff) {
      this.clear("overlay");
      this.legend.querySelector("#legend-overlay").hidden = true;
      return this.render();
    }
    const n = diff.points_m.length;
    const positions = new Float32Array(n * 3);
    const colours = new Float32Array(n * 3);
    const v = new THREE.Vector3();
    const top = Math.max(diff.max_m, 1e-9);
    diff.points_m.forEach((p, i) => {
      v.set(p[0], p[1], p[2]).applyMatrix4(this.baseTracker || new THREE.Matrix4());
      positions.set([v.x, v.y, v.z], 3 * i);
      colours.set(ramp(diff.difference_m[i] / top), 3 * i);
    });
    const object = this.layer("overlay", "points", positions, colours);
    this.overlayDifference = diff.difference_m;
    object.material.size = this.pointSize + 2;
    const legend = this.legend.querySelector("#legend-overlay");
    legend.hidden = false;
    legend.querySelector(".max").textContent = `${(top * 1000).toFixed(3)} mm`;
    this.render();
  }

  /** The base (when calibrated), tracker and scan frames as labelled axes. */
  showFrames(base, tracker, scan) {
    this.clear("frames");
    const group = new THREE.Group();
    group.name = "frames";
    const add = (name, m, size) => {
      const axes = new THREE.AxesHelper(size);
      // x red, y green, z blue, whole (three.js fades x and y to orange: orange is the trace).
      axes.setColors(0xe00000, 0x00a000, 0x0050e0);
      axes.applyMatrix4(m);
      const tag = label(name);
      tag.position.copy(new THREE.Vector3().setFromMatrixPosition(m));
      group.add(axes, tag);
    };
    add(base ? "base" : "tracker (no calibration)", base ? new THREE.Matrix4() : tracker, 0.1);
    if (base) add("tracker", tracker, 0.05);
    if (scan) add("scan", scan, 0.05);
    this.layers.frames = group;
    this.scene.add(group);
    group.visible = this.visibility("frames");
  }

  /** Colour the reconstruction by its displacement from the trace, its mode, or its 1-sigma
   * uncertainty (grey where a stored reconstruction has none). */
  colourReconstruction() {
    const c = this.reconstruction;
    if (!c) return;
    const colours = new Float32Array(c.n * 3);
    const how = this.reconColour.value;
    const byMode = how === "mode";
    const values = how === "uncertainty" ? c.uncertainty_m : c.displacement_m;
    const finite = Array.from(values).filter(Number.isFinite);
    const top = Math.max(...finite, 1e-9);
    for (let i = 0; i < c.n; i++) {
      const value = values[i];
      colours.set(byMode ? MODE_COLOURS[c.mode[i]] || MODE_COLOURS.unchanged
        : Number.isFinite(value) ? ramp(value / top) : [0.6, 0.6, 0.6], 3 * i);
    }
    this.recolour("reconstruction", colours);
    this.legend.querySelector("#legend-displacement").hidden = byMode;
    this.legend.querySelector("#legend-modes").hidden = !byMode;
    this.legend.querySelector("#legend-quantity").textContent = how === "uncertainty" ? "uncertainty (1σ)" : "displacement";
    this.legend.querySelector("#legend-max").textContent = finite.length ? `${(top * 1000).toFixed(2)} mm` : "– (not kept)";
  }

  /** Colour the planned path per waypoint by the chosen feasibility margin. */
  colourPath() {
    const p = this.preview;
    if (!p) return;
    const how = PATH_COLOURING[this.pathColour.value] || PATH_COLOURING.phase;
    // A margin the plan does not have is grey, never the colour of "fine".
    const known = !how.known || how.known(p);
    const colours = new Float32Array(p.t_s.length * 3);
    for (let i = 0; i < p.t_s.length; i++) {
      colours.set(!known ? [0.6, 0.6, 0.6] : how.risk ? ramp(how.risk(p, i)) : PHASE_COLOURS[p.phases[p.phase[i]]], 3 * i);
    }
    this.recolour("path", colours);
    this.legend.querySelector("#legend-path").textContent = known ? how.legend : how.unknown;
  }

  /** Glyphs of the tool's axis along the process path (about 40, 15 mm up the tool from the
   * TCP): how the tool meets the workpiece, waypoint by waypoint. */
  toolAxes(p) {
    const process = p.phase.map((ph, i) => [ph, i]).filter(([ph]) => p.phases[ph] === "process").map(([, i]) => i);
    if (!process.length) return this.clear("tool-axes");
    const every = Math.max(1, Math.floor(process.length / 40));
    const picked = process.filter((_, k) => k % every === 0);
    const positions = new Float32Array(picked.length * 6);
    picked.forEach((i, k) => {
      const [x, y, z] = p.tcp_m[i];
      const [ax, ay, az] = p.tool_axis[i];
      positions.set([x, y, z, x - 0.015 * ax, y - 0.015 * ay, z - 0.015 * az], 6 * k);
    });
    this.layer("tool-axes", "segments", positions, null, 0x0b3d91);
  }

  /** The arm where it stands now (base frame, [[x, y, z], ...]: base, DH frames, flange, TCP),
   * from the robot's state stream, beside the planned one; null hides it. Drawn only while the
   * view is in the base frame (a session without a tracker-to-base calibration is shown in the
   * tracker's), and redrawn at most every LIVE_ARM_MS (the stream may send 20 states a second). */
  showLiveArm(points) {
    const drawn = this.liveArmShown;
    const still = points && drawn && points.length === drawn.length && this.liveArmFrame === this.inBaseFrame
      && points.every((p, i) => Math.hypot(p[0] - drawn[i][0], p[1] - drawn[i][1], p[2] - drawn[i][2]) < LIVE_ARM_STILL_M);
    this.liveArm = points;
    if (still || this.liveArmTimer) return;
    this.liveArmTimer = setTimeout(() => {
      this.liveArmTimer = null;
      const now = this.liveArm;
      this.liveArmShown = now;
      this.liveArmFrame = this.inBaseFrame;
      if (!now || !this.inBaseFrame) {
        this.clear("live-arm");
        this.clear("live-arm-joints");
        this.container.dataset.liveArm = now ? "not in the base frame" : "none";
      } else {
        const flat = Float32Array.from(now.flat());
        const first = !this.layers["live-arm"];
        this.layer("live-arm", "line", flat, null, 0x0a8f3c);
        this.layer("live-arm-joints", "points", flat, null, 0x0a8f3c);
        this.container.dataset.liveArm = JSON.stringify(now[now.length - 1]);
        // Nothing of a session shown (a screen not signed in, or none opened): aim at the arm.
        if (first && !this.shown && !this.showing && !this.steered) {
          const view = this.view;
          this.frame("all");
          this.view = view; // a session shown later is framed as the operator chose
        }
      }
      this.render();
    }, this.liveArmDrawn ? LIVE_ARM_MS : 0);
    this.liveArmDrawn = true;
  }

  /** A move to the plan's start (a trajectory of its own), drawn as its TCP's way in teal; null
   * clears it. Fetched once per move. */
  async showMove(sid, move) {
    const id = move?.id ?? null;
    if (id === this.moveShown || id === this.moveLoading) return;
    this.moveLoading = id;
    if (!id) {
      this.moveShown = null;
      this.clear("move");
      this.container.dataset.move = "";
      return this.render();
    }
    let preview;
    try {
      preview = await api(`/sessions/${sid}/trajectories/${id}/preview?max_samples=1000`);
    } finally {
      if (this.moveLoading === id) this.moveLoading = undefined; // a failed fetch is tried again
    }
    if (this.moveLoading !== undefined) return; // another move (or none) asked for since
    this.moveShown = id;
    this.layer("move", "line", Float32Array.from(preview.tcp_m.flat()), null, 0x00838f);
    // Over the planned and executed paths it shares its ends with (else hidden under them).
    this.layers.move.material.depthTest = false;
    this.layers.move.renderOrder = 10;
    this.container.dataset.move = id;
    // A new move is shown whole (it spans the cell), unless the operator has turned the view.
    if (!this.steered) {
      const view = this.view;
      this.frame("all");
      this.view = view;
    }
    this.render();
  }

  /** This server's cell (GET /cell): the keep-out boxes' edges and the planes as grids, in the
   * base frame (not drawn while the view is in the tracker's). A `draft` (the cell being edited,
   * not saved) is drawn dashed beside it; `showCell(saved)` draws the saved one again. */
  showCell(cell, { draft = false } = {}) {
    const name = draft ? "cell-draft" : "cell";
    if (draft) this.cellDraft = cell;
    else this.cell = cell;
    const ends = cell ? [...cell.keep_out_boxes_m.flatMap(boxEdges), ...cell.cell_planes.flatMap((p) => planeGrid(p))] : [];
    if (!ends.length || !this.inBaseFrame) this.clear(name);
    else {
      const object = this.layer(name, "segments", Float32Array.from(ends), null, CELL_COLOUR);
      if (draft) {
        if (!object.material.isLineDashedMaterial) {
          object.material.dispose();
          object.material = new THREE.LineDashedMaterial({ color: CELL_COLOUR, dashSize: DRAFT_DASH_M, gapSize: DRAFT_GAP_M });
        }
        object.computeLineDistances(); // the dashes follow the edges as typed now
      }
    }
    // Segments drawn: the saved cell's (data-cell) and the draft's (data-cell-draft).
    this.container.dataset[draft ? "cellDraft" : "cell"] = this.layers[name] ? String(ends.length / 6) : "0";
    const drafting = Boolean(this.layers["cell-draft"]);
    this.legend.querySelector("#legend-cell-draft").hidden = !drafting;
    this.legend.querySelector("#legend-cell-draft-text").hidden = !drafting;
    this.render();
  }

  /** Draw the arm's stick figure: base, the DH frames' origins, the flange and the TCP. */
  pose(joints) {
    const flat = Float32Array.from(joints.flat());
    this.layer("arm", "line", flat, null, 0x30343b);
    this.layer("arm-joints", "points", flat, null, 0x30343b);
    this.render();
  }

  /** Where point `index` of a layer is drawn, in page (client) pixels. */
  screenOf(name, index) {
    const object = this.layers[name];
    const point = new THREE.Vector3().fromBufferAttribute(object.geometry.attributes.position, index).project(this.camera);
    const box = this.renderer.domElement.getBoundingClientRect();
    return { x: box.left + ((point.x + 1) / 2) * box.width, y: box.top + ((1 - point.y) / 2) * box.height };
  }

  /** A click: the nearest shown point under the cursor; its diagnostics, or a distance. */
  pick(event) {
    const box = this.renderer.domElement.getBoundingClientRect();
    const pointer = new THREE.Vector2(((event.clientX - box.left) / box.width) * 2 - 1, -((event.clientY - box.top) / box.height) * 2 + 1);
    const caster = new THREE.Raycaster();
    caster.setFromCamera(pointer, this.camera);
    // A finger's reach (22 px, half a 44 px target) on a touch screen, 10 px with a mouse, at the
    // target's distance.
    const radiusPx = event.pointerType === "touch" || event.pointerType === "pen" ? 22 : 10;
    const distance = this.camera.position.distanceTo(this.controls.target);
    caster.params.Points.threshold = (radiusPx / box.height) * 2 * distance * Math.tan(THREE.MathUtils.degToRad(this.camera.fov / 2));
    caster.params.Line.threshold = caster.params.Points.threshold;
    // The layer the operator looks at first: the overlay and the reconstruction over the path,
    // the raw trace, and the dense scan behind them all (a click near a reconstruction point
    // landed on the scan point that happened to be nearer the ray).
    const targets = PICK_ORDER.map((n) => this.layers[n]).filter((o) => o?.visible);
    const rank = (h) => PICK_ORDER.indexOf(h.object.name);
    const hit = caster.intersectObjects(targets, false).filter((h) => h.index < h.object.geometry.drawRange.count)
      .sort((a, b) => rank(a) - rank(b) || a.distanceToRay - b.distanceToRay)[0];
    if (!hit) return this.hooks.onPick?.(null);
    const position = hit.object.geometry.attributes.position;
    const point = new THREE.Vector3().fromBufferAttribute(position, hit.index);
    const picked = { layer: hit.object.name, index: hit.index, point };
    if (hit.object.name === "reconstruction" && this.reconstruction) {
      picked.diagnostics = Object.fromEntries(DIAGNOSTICS.map((k) => [k, this.reconstruction[k][hit.index]]));
    }
    if (hit.object.name === "overlay") picked.difference_m = this.overlayDifference?.[hit.index];
    if (hit.object.name === "path" && this.preview) picked.time_s = this.preview.t_s[hit.index];
    this.layer("pick", "points", Float32Array.of(point.x, point.y, point.z), null, 0x000000);
    this.layers.pick.material.size = 12;
    if (this.measure.checked) {
      this.picks = [...this.picks, point].slice(-2);
      if (this.picks.length === 2) {
        const [a, b] = this.picks;
        picked.distance_m = a.distanceTo(b);
        this.layer("measure", "line", Float32Array.of(a.x, a.y, a.z, b.x, b.y, b.z), null, 0x000000);
      }
    }
    this.render();
    this.hooks.onPick?.(picked);
  }

  /** Aim the camera at the workpiece (scan, trace, reconstruction: what the operator checks
   * first; the planned motion's transit from the arm's pose spans metres and would shrink it
   * to a few pixels), or at everything shown (`view` "all"). */
  frame(view = this.view) {
    this.view = view;
    const names = view === "all" ? Object.keys(this.layers)
      : view === "live" ? ["live"] : WORKPIECE.filter((n) => this.layers[n]); // workpiece, top, side
    if (view === "live") this.view = "workpiece";
    else this.steered = false;
    const box = new THREE.Box3();
    for (const name of names.length ? names : Object.keys(this.layers)) {
      if (name !== "frames") box.expandByObject(this.layers[name]);
    }
    if (box.isEmpty()) return this.render();
    const centre = box.getCenter(new THREE.Vector3());
    const size = Math.max(box.getSize(new THREE.Vector3()).length(), 0.05);
    this.controls.target.copy(centre);
    // Looking from the front-right above (the default), straight down, or from the front.
    const direction = { top: [0, -0.001, 1.2], side: [0, -1.2, 0.05] }[view] || [0.6, -0.9, 0.7];
    this.camera.position.copy(centre).add(new THREE.Vector3(...direction).multiplyScalar(size));
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
