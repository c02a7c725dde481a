// The plan's timeline: scrub, play and a playback speed over every phase of the motion, the
// arm drawn where it is at that instant, the waypoint's margins read out, and the plots (TCP
// speed against the requested speed, joint angles against their limits, joint speeds against
// theirs, clearance to the cell) with a cursor at the same instant. A click on a plot moves
// the time there. Every number comes from the server's preview (GET .../preview).

const SVG = "http://www.w3.org/2000/svg";
const JOINT_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b"];
// The 3-D path's phase colours, pale: blue process, brown approach and retract, grey transit.
const PHASE_FILL = { transit: "#f0f1f5", approach: "#f4ece4", process: "#e8f0ff", retract: "#f4ece4", return: "#f0f1f5" };

const svg = (tag, attrs = {}) => {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  return node;
};

/** The index of the last sample at or before `t` (binary search over increasing times). */
export function sampleAt(times, t) {
  let lo = 0, hi = times.length - 1;
  if (t <= times[0]) return 0;
  if (t >= times[hi]) return hi;
  while (hi - lo > 1) {
    const mid = (lo + hi) >> 1;
    if (times[mid] <= t) lo = mid; else hi = mid;
  }
  return lo;
}

/** One plot: series against time, horizontal reference lines, shaded phases and a cursor. */
export class Plot {
  constructor(root, { title, unit, series, references = [], spans = [], t, phases, phaseOf, top, bottom = 0 }) {
    this.t = t;
    this.width = 600; this.height = 120;
    this.pad = { left: 44, right: 8, top: 16, bottom: 16 };
    const node = svg("svg", { viewBox: `0 0 ${this.width} ${this.height}`, class: "plot", role: "img", "aria-label": title });
    const values = series.flatMap((s) => s.values.filter(Number.isFinite));
    this.bottom = bottom;
    this.top = top ?? Math.max(...values, ...references.map((r) => r.value), 1e-9) * 1.1;
    const x = (time) => this.x(time);
    const y = (v) => this.y(v);
    // Phases shaded behind, named at the top.
    let start = 0;
    for (let i = 1; phaseOf && i <= t.length; i++) {
      if (i === t.length || phaseOf[i] !== phaseOf[start]) {
        const name = phases[phaseOf[start]];
        node.append(svg("rect", { x: x(t[start]), y: this.pad.top, width: Math.max(0.5, x(t[i - 1]) - x(t[start])),
          height: this.height - this.pad.top - this.pad.bottom, fill: PHASE_FILL[name] || "#f6f7f9", "data-phase": name }));
        start = i;
      }
    }
    for (const span of spans) {
      node.append(svg("rect", { x: x(span.start_s), y: this.pad.top, width: Math.max(1, x(span.end_s) - x(span.start_s)),
        height: this.height - this.pad.top - this.pad.bottom, fill: "rgba(214,39,40,.18)", class: "drop" }));
    }
    for (const ref of references) {
      node.append(svg("line", { x1: this.pad.left, x2: this.width - this.pad.right, y1: y(ref.value), y2: y(ref.value),
        stroke: ref.colour || "#2ca02c", "stroke-dasharray": "4 3", "stroke-width": 1 }));
    }
    for (const s of series) {
      const points = [];
      s.values.forEach((v, i) => { if (Number.isFinite(v)) points.push(`${x(t[i]).toFixed(1)},${y(Math.min(v, this.top)).toFixed(1)}`); });
      node.append(svg("polyline", { points: points.join(" "), fill: "none", stroke: s.colour, "stroke-width": 1.3 }));
    }
    // Values above the scale are never hidden: a red bar on the top edge where they are, and the
    // largest named in the title (the transit's TCP speed is far above the process path's).
    const over = values.filter((v) => v > this.top);
    for (const s of series) {
      let first = null;
      s.values.forEach((v, i) => {
        const above = Number.isFinite(v) && v > this.top;
        if (above && first === null) first = i;
        if ((!above || i === s.values.length - 1) && first !== null) {
          const end = above ? i : i - 1;
          node.append(svg("rect", { x: x(t[first]) - 1, y: this.pad.top - 3, width: Math.max(2, x(t[end]) - x(t[first]) + 2),
            height: 4, fill: "#d62728", class: "clipped" }));
          first = null;
        }
      });
    }
    const label = svg("text", { x: this.pad.left, y: 11, "font-size": 11 });
    const largest = over.length ? Math.max(...over) : null;
    label.textContent = `${title} [${unit}]` + (largest === null ? ""
      : ` · off the scale (red on top): up to ${Math.abs(largest) >= 100 ? largest.toFixed(0) : largest.toPrecision(3)} ${unit}`);
    node.dataset.offScale = largest === null ? "" : String(largest);
    node.append(label);
    for (const v of [this.bottom, this.top]) {
      const tick = svg("text", { x: this.pad.left - 4, y: y(v) + 4, "font-size": 10, "text-anchor": "end" });
      tick.textContent = Math.abs(v) >= 100 ? v.toFixed(0) : v.toPrecision(2);
      node.append(tick);
    }
    this.cursor = svg("line", { y1: this.pad.top, y2: this.height - this.pad.bottom, stroke: "#111", "stroke-width": 1.5 });
    node.append(this.cursor);
    this.node = node;
    root.append(node);
  }

  x(time) {
    const t0 = this.t[0], t1 = this.t[this.t.length - 1] || 1;
    return this.pad.left + ((time - t0) / (t1 - t0 || 1)) * (this.width - this.pad.left - this.pad.right);
  }

  y(value) {
    const f = (value - this.bottom) / (this.top - this.bottom || 1);
    return this.height - this.pad.bottom - f * (this.height - this.pad.top - this.pad.bottom);
  }

  /** The time at a click's x position (in the SVG's own units). */
  timeAt(clientX) {
    const box = this.node.getBoundingClientRect();
    const xs = ((clientX - box.left) / box.width) * this.width;
    const f = (xs - this.pad.left) / (this.width - this.pad.left - this.pad.right);
    return this.t[0] + Math.min(1, Math.max(0, f)) * (this.t[this.t.length - 1] - this.t[0]);
  }

  mark(time) {
    const xs = this.x(time).toFixed(1);
    this.cursor.setAttribute("x1", xs); this.cursor.setAttribute("x2", xs);
  }
}

const mm = (m, digits = 1) => (m == null ? "–" : `${(m * 1000).toFixed(digits)} mm`);

export class Timeline {
  /**
   * @param {HTMLElement} root  the timeline's panel (controls, readout and plots inside)
   * @param {(joints: number[][], tcp: number[]) => void} onPose  draws the arm at an instant
   */
  constructor(root, onPose) {
    this.root = root;
    this.onPose = onPose;
    this.scrub = root.querySelector("#timeline-scrub");
    this.play = root.querySelector("#timeline-play");
    this.rate = root.querySelector("#timeline-rate");
    this.now = root.querySelector("#timeline-now");
    this.readout = root.querySelector("#waypoint-readout");
    this.plots = root.querySelector("#plan-plots");
    this.preview = null;
    this.time = 0;
    this.playing = false;
    this.scrub.addEventListener("input", () => { this.pause(); this.seek(Number(this.scrub.value)); });
    this.play.addEventListener("click", () => (this.playing ? this.pause() : this.start()));
    this.plots.addEventListener("click", (event) => {
      const plot = this.plotList?.find((p) => p.node.contains(event.target));
      if (plot) { this.pause(); this.seek(plot.timeAt(event.clientX)); }
    });
  }

  /** Show a plan's preview (null: none, the panel hides); the same plan again keeps the
   * time the operator was looking at. */
  load(preview, id = null) {
    this.pause();
    const keep = id !== null && id === this.id ? this.time : null;
    this.id = id;
    this.preview = preview;
    this.root.hidden = !preview;
    this.plots.replaceChildren();
    if (!preview) return;
    const t = preview.t_s;
    this.scrub.min = t[0]; this.scrub.max = t[t.length - 1]; this.scrub.step = "any";
    const common = { t, phases: preview.phases, phaseOf: preview.phase };
    const requested = preview.requested_speed_m_s * 1000;
    // An endless joint has no limit (null): its angles set the scale instead.
    const limits = [...new Set([...preview.q_min_deg, ...preview.q_max_deg])].filter((v) => v != null);
    const angles = preview.q_deg.flat();
    const process = preview.phase.map((p, i) => (preview.phases[p] === "process" ? preview.speed_m_s[i] * 1000 : 0));
    this.plotList = [
      new Plot(this.plots, { ...common, title: "TCP speed (requested dashed, slow-downs red)", unit: "mm/s",
        series: [{ values: preview.speed_m_s.map((v) => v * 1000), colour: "#1f77ff" }],
        references: [{ value: requested }], spans: preview.speed_drops,
        // The transit's joint moves are far faster at the TCP: scale to the process path.
        top: 1.6 * Math.max(requested, ...process) }),
      new Plot(this.plots, { ...common, title: "joint angles (limits dashed)", unit: "deg",
        series: JOINT_COLOURS.map((colour, j) => ({ values: preview.q_deg.map((q) => q[j]), colour })),
        references: limits.map((v) => ({ value: v, colour: "#b00020" })),
        bottom: Math.min(...limits, ...angles), top: Math.max(...limits, ...angles) }),
      new Plot(this.plots, { ...common, title: "fastest joint (limit dashed)", unit: "% of its limit",
        series: [{ values: preview.qd_share.map((v) => v * 100), colour: "#9467bd" }],
        references: [{ value: 100, colour: "#b00020" }], top: 110 }),
    ];
    const clearances = (preview.clearance_m || []).filter((v) => v != null);
    if (clearances.length) {
      this.plotList.push(new Plot(this.plots, { ...common, title: "closest to the cell", unit: "mm",
        series: [{ values: preview.clearance_m.map((v) => (v == null ? NaN : v * 1000)), colour: "#8c564b" }],
        top: Math.min(200, Math.max(...clearances) * 1000), bottom: Math.min(0, ...clearances) * 1000 }));
    }
    this.seek(keep ?? t[0]);
  }

  seek(time) {
    const p = this.preview;
    if (!p) return;
    const t = p.t_s;
    this.time = Math.min(Math.max(time, t[0]), t[t.length - 1]);
    const i = sampleAt(t, this.time);
    const j = Math.min(i + 1, t.length - 1);
    const f = j > i ? (this.time - t[i]) / (t[j] - t[i]) : 0;
    const lerp = (a, b) => a.map((v, k) => v + f * (b[k] - v));
    const joints = p.joints_m[i].map((point, k) => lerp(point, p.joints_m[j][k]));
    this.onPose(joints, joints[joints.length - 1]);
    this.scrub.value = this.time;
    this.now.textContent = `${this.time.toFixed(2)} s / ${t[t.length - 1].toFixed(2)} s`;
    const drop = p.speed_drops.find((d) => d.start_s <= this.time && this.time <= d.end_s);
    const rows = [
      ["phase", p.phases[p.phase[i]]],
      ["TCP speed", `${Math.round(p.speed_m_s[i] * 1000)} mm/s of ${Math.round(p.requested_speed_m_s * 1000)}`],
      ["slowed by", drop ? `${drop.cause} (down to ${Math.round(drop.min_speed_m_s * 1000)} mm/s)` : "–"],
      ["joint-limit margin", `${p.limit_margin_deg[i].toFixed(1)}°`],
      ["wrist singularity |sin q5|", p.wrist_singularity[i].toFixed(3)],
      ["elbow singularity |sin q3|", p.elbow_singularity[i].toFixed(3)],
      ["fastest joint", `${Math.round(p.qd_share[i] * 100)} % of its limit`],
      ["closest to the cell", !p.clearance_m ? "not checked" : p.clearance_m[i] == null ? "nothing in reach" : mm(p.clearance_m[i])],
    ];
    this.readout.replaceChildren(...rows.map(([k, v]) => {
      const tr = document.createElement("tr");
      const th = document.createElement("th"); th.textContent = k;
      const td = document.createElement("td"); td.textContent = v; td.dataset.key = k;
      tr.append(th, td);
      return tr;
    }));
    for (const plot of this.plotList) plot.mark(this.time);
  }

  start() {
    const p = this.preview;
    if (!p) return;
    const t = p.t_s;
    if (this.time >= t[t.length - 1]) this.time = t[0];
    this.playing = true;
    this.play.textContent = "Pause";
    let last = performance.now();
    const step = (now) => {
      if (!this.playing) return;
      this.seek(this.time + ((now - last) / 1000) * Number(this.rate.value));
      last = now;
      if (this.time >= t[t.length - 1]) return this.pause();
      this.frame = requestAnimationFrame(step);
    };
    this.frame = requestAnimationFrame(step);
  }

  pause() {
    this.playing = false;
    if (this.frame) cancelAnimationFrame(this.frame);
    this.frame = null;
    this.play.textContent = "Play";
  }
}
