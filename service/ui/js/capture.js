// Live capture: start and stop a capture (NatNet from Motive, or a replay of a stored
// recording), draw the trace over the scan while the operator traces (GET .../samples, read
// with fetch), and show where tracking was lost. One click, one POST; after a reload the
// running capture is followed again from its first sample (nothing is sent again).

import { api, events } from "./api.js";

const CAPTURE_KEY = "teachpath.capture"; // + session id: the capture this page started

/**
 * @param {object} deps
 * @param {() => object|null} deps.session  the open session
 * @param {() => object[]} deps.recordings  the session's recordings (to replay)
 * @param {() => object|null} deps.workspace  the 3-D view (may be missing)
 * @param {(box: HTMLElement, err: object) => void} deps.showError
 * @param {(kind: string, key: string, value: string|null) => void} deps.remember
 * @param {(kind: string, key: string) => string|null} deps.recall
 * @param {() => Promise<void>} deps.refresh  reloads the session (the new recording)
 */
export function wireCapture(deps) {
  const form = document.querySelector("#capture-form");
  const box = form.querySelector(".message");
  const startButton = form.querySelector("button[type=submit]");
  const stopButton = form.querySelector("#capture-stop");
  const status = form.querySelector("#capture-status");
  const kind = form.elements.kind;
  let following = null; // {id, sid, abort}: the capture this page draws
  let checking = null; // the session whose remembered capture is being looked up

  const showKind = () => {
    for (const set of form.querySelectorAll("fieldset[data-kind]")) {
      set.hidden = set.dataset.kind !== kind.value;
      set.disabled = set.hidden;
    }
  };
  kind.addEventListener("change", showKind);
  showKind();

  /** The replay choices: the session's recordings, newest first. */
  function listRecordings() {
    const select = form.elements.recording_id;
    const chosen = select.value;
    select.replaceChildren(...[...deps.recordings()].reverse().map((r) => {
      const option = document.createElement("option");
      option.value = r.id;
      option.textContent = `${r.source_name || r.id} (${r.summary.n_samples} samples)`;
      return option;
    }));
    if ([...select.options].some((o) => o.value === chosen)) select.value = chosen;
  }

  function body() {
    if (kind.value === "replay") {
      return { kind: "replay", recording_id: form.elements.recording_id.value, speed: Number(form.elements.speed.value) };
    }
    return {
      kind: "natnet",
      server: form.elements.server.value.trim(),
      rigid_body: form.elements.rigid_body.value.trim(),
      local: form.elements.local.value.trim(),
      command_port: Number(form.elements.command_port.value),
      units: form.elements.units.value,
    };
  }

  function running(on) {
    startButton.disabled = on;
    stopButton.hidden = !on;
    stopButton.disabled = !on;
  }

  /** Follow a capture's samples to its end, drawing them as they come. A stream that breaks
   * while the capture runs (a network blip) is opened again from the next sample. */
  async function follow(sid, capture) {
    following?.abort.abort();
    const abort = new AbortController();
    const mine = { id: capture.id, sid, abort };
    following = mine;
    running(true);
    const trace = { points: [], lost: [], lostSamples: 0, stretches: 0, n: 0, wasLost: false, lastGood: null, lostAt: null, t0: null };
    status.textContent = "waiting for the first samples…";
    let last = capture;
    const take = (data) => {
      trace.t0 ??= data.t_s[0];
      data.points_m.forEach((p, i) => {
        trace.n += 1;
        if (p) {
          if (trace.wasLost && trace.lastGood) trace.lost.push(trace.lastGood, p); // where it was lost and found
          trace.points.push(p);
          trace.lastGood = p;
          trace.wasLost = false;
        } else {
          trace.lostSamples += 1;
          if (!trace.wasLost) { trace.stretches += 1; trace.lostAt = data.t_s[i] - trace.t0; }
          trace.wasLost = true;
        }
      });
      deps.workspace()?.showLive(trace.points, trace.lost);
      status.textContent = describe(trace);
    };
    try {
      for (;;) {
        try {
          for await (const { event, data } of events(`/sessions/${sid}/captures/${capture.id}/samples?from_sample=${trace.n}`, abort.signal)) {
            if (event === "samples") take(data);
            else if (event === "capture") last = data;
            else if (event === "error") deps.showError(box, { code: "capture_unreadable", message: data.message });
          }
        } catch (err) {
          if (err.name === "AbortError" || err.status === 404) throw err;
        }
        // The stream ended: with the capture, or broken while it runs (then open it again).
        const pause = () => new Promise((resolve) => setTimeout(resolve, 500));
        try {
          last = await api(`/sessions/${sid}/captures/${capture.id}`, { signal: abort.signal });
        } catch (err) {
          if (err.name === "AbortError" || err.status !== 0) throw err;
          await pause(); // the server out of reach: look again
          continue;
        }
        if (last.state !== "running") break;
        await pause();
      }
    } catch (err) {
      if (err.name !== "AbortError") deps.showError(box, err);
    } finally {
      if (following === mine) {
        following = null;
        running(false);
        if (last.state !== "running") deps.remember("sessionStorage", CAPTURE_KEY + sid, null);
        deps.workspace()?.showLive(null);
        await deps.refresh().catch(() => {});
        if (last.state === "failed") deps.showError(box, { code: "capture_failed", message: last.error || "the capture failed" });
        else if (last.recording_id) kept(last);
      }
    }
  }

  /** Stop drawing a capture (it runs on; its session's page follows it again when opened). */
  function detach() {
    const was = following;
    following = null;
    was?.abort.abort();
    running(false);
    status.textContent = "";
    deps.workspace()?.showLive(null);
  }

  /** What the capture left: the recording, and what cleaning it took (a lost stretch splits
   * the trace; the longest piece is the one kept). */
  function kept(capture) {
    const rec = deps.recordings().find((r) => r.id === capture.recording_id);
    box.className = "message ok";
    const pieces = rec?.summary.n_pieces > 1 ? ` (piece ${rec.summary.piece + 1} of ${rec.summary.n_pieces}, the longest)` : "";
    const lines = [`Capture ${capture.state}: ${capture.n_samples} samples received; recording ${capture.recording_id} keeps ${rec?.summary.n_samples ?? "?"}${pieces}.`];
    box.replaceChildren(...[...lines, ...(rec?.summary.gap_report || [])].map((text) => {
      const p = document.createElement("p");
      p.textContent = text;
      return p;
    }));
  }

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    if (!form.reportValidity() || following) return;
    box.className = "message";
    box.replaceChildren();
    const sid = deps.session().id;
    startButton.disabled = true;
    try {
      const capture = await api(`/sessions/${sid}/captures`, { method: "POST", json: { source: body() } });
      deps.remember("sessionStorage", CAPTURE_KEY + sid, capture.id);
      follow(sid, capture);
    } catch (err) {
      deps.showError(box, err);
      startButton.disabled = false;
    }
  });

  stopButton.addEventListener("click", async () => {
    if (!following) return;
    stopButton.disabled = true;
    try {
      // The stream then ends with the capture's last samples; `follow` tidies up.
      await api(`/sessions/${following.sid}/captures/${following.id}/stop`, { method: "POST" });
    } catch (err) {
      deps.showError(box, err);
      stopButton.disabled = false;
    }
  });

  return {
    /** A session was opened or refreshed: the replay list; a capture still running is
     * followed again (after a reload). */
    async sessionShown(sid) {
      listRecordings();
      if (following?.sid === sid || checking === sid) return;
      if (following) detach(); // another session's capture: it runs on, undrawn here
      running(false);
      const id = deps.recall("sessionStorage", CAPTURE_KEY + sid);
      if (!id) return;
      checking = sid; // one look at a time (refreshes come in pairs on opening)
      try {
        const capture = await api(`/sessions/${sid}/captures/${id}`);
        if (capture.state === "running" && deps.session()?.id === sid) follow(sid, capture);
        else if (capture.state !== "running") deps.remember("sessionStorage", CAPTURE_KEY + sid, null);
      } catch (err) {
        if (err.status === 404) deps.remember("sessionStorage", CAPTURE_KEY + sid, null);
      } finally {
        checking = null;
      }
    },
    /** The session is closed: stop drawing (the capture itself runs on). */
    sessionClosed: detach,
  };
}

function describe(trace) {
  const lost = trace.stretches
    ? `tracking lost ${trace.stretches}× (${trace.lostSamples} samples; first ${trace.lostAt.toFixed(2)} s into the capture)`
    : "tracking: no sample lost";
  const now = trace.wasLost ? " — TRACKING LOST NOW: bring the pen back into view" : "";
  return `${trace.n} samples received; ${lost}${now}`;
}
