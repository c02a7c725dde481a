// The teach pendant: the safety bar, sessions and the steps of one session, on the REST API.
// Nothing here resends a request that moves or computes by itself: every POST comes from one
// click, and the button stays disabled until its job has finished.

import { api, events, explain, followJob, FINISHED, setToken, signIn, takeToken } from "./api.js";
import { wireCapture } from "./capture.js";

const $ = (selector, root = document) => root.querySelector(selector);
const el = (tag, attrs = {}, ...children) => {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (key === "class") node.className = value;
    else if (key === "text") node.textContent = value;
    else node.setAttribute(key, value);
  }
  node.append(...children);
  return node;
};
const mm = (metres, digits = 2) => (metres == null || !Number.isFinite(metres) ? "–" : `${(metres * 1000).toFixed(digits)} mm`);
const mmps = (m_s) => `${Math.round(m_s * 1000)} mm/s`;
// Where a plan starts (the trajectory summary's start_from), in the operator's words.
const START_FROM = {
  arm: "the arm's joints when it was planned (the run refuses if the arm has moved since)",
  home: "the simulated arm's home pose",
  given: "the joints given with the request",
};
const startFrom = (key) => START_FROM[key] || key || "–";
const seconds = (s) => (s == null ? "–" : `${s.toFixed(1)} s`);

const state = {
  robot: null,
  session: null,
  recordings: [],
  scans: [],
  reconstructions: [],
  trajectories: [],
  executions: [],
  madeHere: new Set(), // executions a job of this server made (an imported dry run is not one)
  busy: null, // the step whose job runs now
  moving: null, // {executionId, jobId} of an execution that may move the arm
  speedSending: false, // a run speed is on its way to the server
  schema: null,
  workspace: null,
  pick: null, // {id, outdated}: a plan taken on purpose instead of the newest, and what had changed then
  pickView: null, // the plan the choice of plan shows (its inputs are read before taking it)
};

// -- errors shown as instructions ---------------------------------------------------------------

function showError(box, err) {
  const { code, instruction } = explain(err);
  let { message } = explain(err);
  // A refusal names the API's fields: say them as the form does ("radius_m: ..." is the
  // "neighbourhood radius (mm) (radius_m): ..." the operator sees above).
  if (code === "invalid_request") {
    message = message.replace(/(body: )?Value error, /g, "");
    message = message.replace(/\b([a-z_]+): /g, (all, field) => (DISPLAY_NAMES[field] ? `${DISPLAY_NAMES[field]} (${field}): ` : all));
  }
  box.replaceChildren(
    el("p", { class: "instruction", text: instruction || message }),
    el("p", { class: "server-message" }, el("code", { text: code }), ` ${message}`),
  );
  box.className = "message error";
  box.dataset.code = code;
}
const clearMessage = (box) => {
  box.replaceChildren();
  box.className = "message";
  delete box.dataset.code;
};
function banner(text) {
  const node = $("#banner");
  node.textContent = text || "";
  node.hidden = !text;
}

// -- the safety bar -------------------------------------------------------------------------------

function showRobot(robot) {
  state.robot = robot;
  const kind = $("#arm-kind");
  kind.textContent = robot.real_arm ? "REAL ARM" : "SIM";
  kind.className = `badge ${robot.real_arm ? "real" : "sim"}`;
  $("#robot-model").textContent = robot.robot + (robot.host ? ` @ ${robot.host}` : "");
  $("#robot-mode").textContent = robot.reachable ? robot.robot_mode : "unreachable";
  $("#safety-status").textContent = robot.emergency_stop ? "EMERGENCY STOP" : robot.safety_status;
  const stopped = robot.protective_stop;
  $("#protective-stop").textContent = stopped
    ? robot.unlock_in_s > 0 ? `YES (unlock in ${robot.unlock_in_s.toFixed(0)} s)` : "YES"
    : "no";
  // Shown when there is one (the safety status says NORMAL otherwise): the bar stays one line
  // wider before it wraps.
  $("#protective-stop-field").hidden = !stopped;
  const unlock = $("#unlock");
  unlock.hidden = !stopped;
  unlock.disabled = !stopped || robot.unlock_in_s > 0;
  $("#remote-control").textContent =
    robot.remote_control == null ? "–" : robot.remote_control ? "on" : "OFF (local)";
  $("#arm-owner").textContent = robot.owner_execution_id || "none";
  $("#speed-cap").textContent = mmps(robot.max_speed_m_s);
  const notRunning = robot.real_arm && robot.reachable && robot.robot_mode !== "RUNNING"; // powered off, brakes on
  $("#safety-bar").classList.toggle("alarm", stopped || robot.emergency_stop || !robot.reachable || notRunning);
  state.workspace?.showLiveArm(robot.reachable ? robot.joints_m : null);
  updateStop();
  showRunSpeed(robot.run_speed);
  updatePlanSpeed();
  // The plan is for the arm the server drives, unless the operator chose another model.
  const model = $("#plan-robot");
  if (model && !model.dataset.chosen && [...model.options].some((o) => o.value === robot.robot)) model.value = robot.robot;
  renderSteps();
}

async function followRobot() {
  const link = $("#link-state");
  for (;;) {
    try {
      showRobot(await api("/robot"));
      link.textContent = "live";
      for await (const { data } of events("/robot/events")) {
        showRobot(data);
        link.textContent = "live";
      }
    } catch (err) {
      link.textContent = `no robot state: ${explain(err).message}`;
      if (err.status === 401) return askToken(explain(err).instruction);
    }
    link.textContent = "reconnecting…";
    await new Promise((resolve) => setTimeout(resolve, 1000));
  }
}

function canMove() {
  const robot = state.robot;
  return Boolean(state.moving || robot?.program_running || robot?.owner_execution_id);
}

function updateStop() {
  const show = canMove();
  if (!show) state.stopping = null;  // nothing moves any more: the stop is confirmed
  $("#stop").hidden = !show;
  $("#stop").textContent = state.stopping ? "Stopping…" : "Stop";
  $("#stop-hint").hidden = !show;
  document.body.classList.toggle("moving", show);
}

async function stop() {
  const id = state.moving?.executionId || state.robot?.owner_execution_id;
  if (!id) return;
  // "Stopping…" from the press until the run has ended (the job finished, or the arm is free):
  // the button stays live, pressing again sends the stop again.
  state.stopping = id;
  updateStop();
  renderSteps();
  try {
    await api(`/executions/${id}/stop`, { method: "POST" });
    banner("");
  } catch (err) {
    // Not sent: the page must not say it is stopping (press again, or use the arm's own stop).
    state.stopping = null;
    updateStop();
    renderSteps();
    banner(`Stop: ${explain(err).message}`);
  }
}

// -- the run's speed override and pause (beside Stop) ---------------------------------------------

const percent = (fraction) => `${Math.round(fraction * 100)} %`;

/** The speed group of the safety bar, from the owning run's state (robot.run_speed). */
function showRunSpeed(run) {
  const group = $("#run-speed");
  group.hidden = !run;
  group.classList.toggle("paused", Boolean(run?.paused));
  if (!run) return;
  const slider = $("#run-speed-slider");
  const value = $("#run-speed-value");
  const status = $("#run-speed-state");
  if (!run.overridable) {
    slider.hidden = value.hidden = $("#run-speed-unit").hidden = true;
    $("#pause").hidden = $("#resume").hidden = true;
    status.textContent = "fixed: a movePath run is timed by the controller";
    return;
  }
  // A screen that is not signed in shows the speed; changing it, pausing and resuming take the
  // token (Stop does not).
  const signedOut = document.body.classList.contains("signed-out");
  slider.hidden = value.hidden = $("#run-speed-unit").hidden = signedOut;
  // Never overwrite what the operator is setting.
  if (![slider, value].includes(document.activeElement) && !state.speedSending) {
    slider.value = String(Math.round(run.speed_fraction * 100));
    value.value = slider.value;
  }
  if (run.paused) {
    status.textContent = run.speed_now === 0 ? "PAUSED, at rest on the path" : "pausing…";
  } else if (!run.moving) {
    status.textContent = `at ${percent(run.speed_fraction)} from the start`;
  } else if (Math.abs(run.speed_now - run.speed_fraction) > 0.005) {
    status.textContent = `${percent(run.speed_now)}, going to ${percent(run.speed_fraction)}`;
  } else {
    status.textContent = `at ${percent(run.speed_fraction)}`; // of the plan's speed, as the group's title says
  }
  $("#pause").hidden = signedOut || run.paused || !run.moving;
  $("#pause").disabled = Boolean(state.stopping);
  $("#resume").hidden = signedOut || !run.paused;
  $("#resume").disabled = Boolean(state.stopping) || run.speed_now !== 0;
}

async function sendRunSpeed(source) {
  const run = state.robot?.run_speed;
  if (!run) return;
  const typed = Number(String(source.value).trim().replace(",", "."));
  const value = $("#run-speed-value");
  if (!Number.isFinite(typed) || typed < 5 || typed > 100) {
    value.setCustomValidity("5 to 100 %");
    value.reportValidity();
    banner("Run speed: type 5 to 100 (per cent of the plan's speed). Nothing was changed.");
    return;
  }
  value.setCustomValidity("");
  $("#run-speed-slider").value = String(Math.round(typed));
  value.value = String(Math.round(typed * 10) / 10);
  state.speedSending = true;
  try {
    const shown = await api(`/executions/${run.execution_id}/speed`, { method: "POST", json: { fraction: typed / 100 } });
    banner("");
    showRunSpeed(shown);
  } catch (err) {
    banner(`Run speed: ${explain(err).message}`);
  } finally {
    state.speedSending = false;
  }
}

async function pauseRun() {
  const run = state.robot?.run_speed;
  if (!run) return;
  try {
    showRunSpeed(await api(`/executions/${run.execution_id}/pause`, { method: "POST" }));
    banner("");
  } catch (err) {
    banner(`Pause: ${explain(err).message}`);
  }
}

async function resumeRun() {
  const run = state.robot?.run_speed;
  if (!run || !(await confirmResume(run))) return;
  try {
    showRunSpeed(await api(`/executions/${run.execution_id}/resume`, {
      method: "POST", json: { confirm: true, approved_sha256: run.approved_sha256 },
    }));
    banner("");
  } catch (err) {
    banner(`Resume: ${explain(err).message}`);
  }
}

/** The approval of a resume: what runs, from where, at what speed. */
function confirmResume(run) {
  const robot = state.robot;
  const traj = state.trajectories.find((t) => t.id === run.trajectory_id);
  const rows = [
    ["robot", `${robot.real_arm ? "REAL ARM" : "SIM"} ${robot.robot}${robot.host ? ` @ ${robot.host}` : ""}`],
    ["run", run.execution_id],
    ["plan file", `${run.trajectory_id}, sha256 ${(run.approved_sha256 || "").slice(0, 12)}…` +
      (traj ? `, ${new Date(traj.created_at).toLocaleString()}` : " (not in this session's list)")],
    ["goes on", "from where it paused, along the same path to the plan's end"],
    ["speed", `${percent(run.speed_fraction)} of the plan's speed (never faster than planned)`],
  ];
  return askDialog("Resume the run on the arm?", "Confirm: resume", rows);
}

// -- sessions -------------------------------------------------------------------------------------

async function loadSessions() {
  const list = $("#session-list");
  const sessions = await api("/sessions");
  state.sessions = sessions;
  list.replaceChildren(
    ...sessions.map((s) => {
      const open = el("button", { type: "button", class: "open", text: s.name });
      open.addEventListener("click", () => openSession(s.id));
      const remove = el("button", { type: "button", class: "delete", text: "Delete" });
      remove.setAttribute("aria-label", `Delete ${s.name}`);
      remove.addEventListener("click", async () => {
        if (!window.confirm(`Delete the session “${s.name}”?`)) return;
        await api(`/sessions/${s.id}`, { method: "DELETE" });
        if (state.session?.id === s.id) closeSession();
        await loadSessions();
      });
      const item = el("li", { "data-session": s.id }, open, " ", remove);
      item.classList.toggle("selected", state.session?.id === s.id);
      return item;
    }),
  );
  if (!sessions.length) list.append(el("li", { class: "muted", text: "no sessions yet" }));
}

function closeSession() {
  Object.assign(state, { session: null, pick: null, pickView: null });
  state.capture.sessionClosed();
  state.workspace?.showLive(null);
  remember("sessionStorage", SESSION_KEY, null);
  $("#session-view").hidden = true;
}

const SESSION_KEY = "teachpath.session";
// Storage may be refused (site data blocked; then even reading window.sessionStorage throws):
// the pendant works on without remembering. `kind`: "sessionStorage" or "localStorage".
function remember(kind, key, value) {
  try {
    if (value) window[kind].setItem(key, value);
    else window[kind].removeItem(key);
  } catch {
    /* nothing remembered */
  }
}
function recall(kind, key) {
  try {
    return window[kind].getItem(key);
  } catch {
    return null;
  }
}

async function openSession(id) {
  state.session = await api(`/sessions/${id}`);
  Object.assign(state, { pick: null, pickView: null }); // a plan is taken in its own session
  remember("sessionStorage", SESSION_KEY, id);
  $("#session-view").hidden = false;
  $("#session-title").textContent = `Session ${state.session.name}`;
  for (const box of document.querySelectorAll("#session-view .message")) clearMessage(box);
  await refresh();
  for (const item of document.querySelectorAll("#session-list li")) {
    item.classList.toggle("selected", item.dataset.session === id);
  }
  await resumeJobs(id);
}

// After a reload (or on a second pendant), the session's unfinished job is followed again, its
// button disabled until it ends: nothing is sent again.
const JOB_STEPS = { reconstruction: "reconstruct", trajectory: "plan" };
function stepOfJob(job) {
  if (job.kind === "trajectory" && job.params.move_to_start_of) return "move-plan";
  if (job.kind === "execution") {
    const ofMove = isMove(state.trajectories.find((t) => t.id === job.params.trajectory_id));
    return `${ofMove ? "move-" : ""}${job.params.backend === "sim" ? "dryrun" : "run"}`;
  }
  return JOB_STEPS[job.kind] || null;
}
/** The form whose button started a job of `step` (its progress and messages go there). */
const formOfStep = (step) => (step.startsWith("move-") ? $(`#${step}-form`) : $(`#step-${step} form`));

async function resumeJobs(sid) {
  if (state.busy) return;
  const jobs = await api(`/sessions/${sid}/jobs`);
  const job = jobs.find((j) => !FINISHED.includes(j.state) && stepOfJob(j));
  if (!job) return;
  const step = stepOfJob(job);
  runJob(step, formOfStep(step), async () => {
    if (step === "run" || step === "move-run") {
      state.moving = { executionId: job.params.execution_id, jobId: job.id };
      // The arm's state may have come first (it owns the arm already): say "moving" now.
      updateStop();
      renderSteps();
    }
    return job;
  });
}

async function refresh() {
  const sid = state.session.id;
  const [session, recordings, scans, reconstructions, trajectories, executions, touches, jobs] = await Promise.all([
    api(`/sessions/${sid}`),
    api(`/sessions/${sid}/recordings`),
    api(`/sessions/${sid}/scans`),
    api(`/sessions/${sid}/reconstructions`),
    api(`/sessions/${sid}/trajectories`),
    api(`/sessions/${sid}/executions`),
    api(`/sessions/${sid}/touches`),
    api(`/sessions/${sid}/jobs`),
  ]);
  // The server's gate counts only dry runs its own jobs made: a bundle carries no jobs.
  const madeHere = new Set(
    jobs.filter((j) => j.kind === "execution" && j.state === "succeeded").map((j) => j.params.execution_id),
  );
  Object.assign(state, { session, recordings, scans, reconstructions, trajectories, executions, touches, madeHere });
  await reloadCell(); // another pendant may have edited it
  renderSteps();
  state.capture.sessionShown(sid);
  showWorkspace();
}

/** Draw the session in the 3-D view; the review is of the execution the tables show (the last
 * run on the arm of this plan, else its dry run in the chosen mode). */
function showWorkspace() {
  if (!state.session) return;
  state.reviewExecution = [lastRun(), dryRun()].find((e) => e?.summary.n_samples > 0) || null;
  state.workspace?.show(state.session.id, { ...state, plan: trajectory() }).catch((err) => {
    $("#workspace-note").textContent = `workspace: ${err.message}`;
  });
}

// -- what each step needs and has -----------------------------------------------------------------

const last = (list) => list[list.length - 1] || null;
const recording = () => state.recordings.find((r) => r.id === state.session?.recording_id) || null;
const scan = () => state.scans.find((s) => s.id === state.session?.scan_id) || null;
const reconstruction = () => last(state.reconstructions);
// A move to a plan's start is a trajectory of its own (move_to_start_of names the plan): never
// "the plan".
const isMove = (t) => Boolean(t?.inputs.move_to_start_of);
/** The session's plans (not the moves to their starts), newest first. */
const plans = () => state.trajectories.filter((t) => !isMove(t)).reverse();
/** The newest plan of the newest reconstruction: the plan used unless the operator picks another. */
const newestPlan = () => {
  const rec = reconstruction();
  return last(state.trajectories.filter((t) => t.inputs.reconstruction_id === rec?.id && !isMove(t)));
};
/** The plan shown, dry-run and run: the one the operator picked on purpose, else the newest. */
const trajectory = () => (state.pick && state.trajectories.find((t) => t.id === state.pick.id)) || newestPlan();
/** Whether the operator took `traj` (or, for a move, the plan it moves to the start of) on purpose
 * after a confirmation that named what had changed since it was made: true only while nothing
 * more has changed (a new change needs a new look). */
function acceptedOutdated(traj) {
  const id = isMove(traj) ? traj.inputs.move_to_start_of : traj?.id;
  if (!id || state.pick?.id !== id) return false;
  return outdated(traj).every((reason) => state.pick.outdated.includes(reason));
}
/** How far the tracker-to-base calibration `traj` was planned with is from the session's, when
 * the service would refuse it on the arm for that (service/executions.py, _placement_here: its
 * scan would be checked in the wrong place); null when it is the same or either is missing. */
function otherCalibration(traj) {
  const [a, b] = [traj?.params?.T_base_tracker, state.session?.T_base_tracker];
  if (!a || !b) return null;
  const movedM = Math.hypot(...[0, 1, 2].map((i) => a[i][3] - b[i][3]));
  let trace = 0;
  for (let i = 0; i < 3; i += 1) for (let k = 0; k < 3; k += 1) trace += a[k][i] * b[k][i];
  const turnedRad = Math.acos(Math.min(1, Math.max(-1, (trace - 1) / 2)));
  return movedM > SAME_PLACEMENT_M || turnedRad > SAME_PLACEMENT_RAD ? { movedM, turnedRad } : null;
}
const [SAME_PLACEMENT_M, SAME_PLACEMENT_RAD] = [1e-4, 1e-4];
const OTHER_CALIBRATION = (gap) => `This plan was made with another tracker-to-base calibration than the session's `
  + `(${(gap.movedM * 1000).toFixed(1)} mm, ${(gap.turnedRad * 180 / Math.PI).toFixed(2)}° apart): the service refuses it on the arm, `
  + "since its motion would be checked against the workpiece in the wrong place. Plan again with the session's calibration.";
/** A plan the arm may be offered: current, or outdated and taken on purpose; never one made
 * with another calibration. */
const usable = (traj) => Boolean(traj) && (!outdated(traj).length || acceptedOutdated(traj)) && !otherCalibration(traj);
// The server's gate: a run starts only with the arm this close to the plan's first sample (rad).
const START_TOLERANCE_RAD = 0.01;
/** How far the real arm stands from where `traj` starts: the largest joint difference (rad) and
 * its joint (1-6); null when not known (no real arm, no reading). */
function startGap(traj) {
  const q = state.robot?.q_rad;
  const start = traj?.summary.start_q_rad;
  if (!state.robot?.real_arm || !state.robot.reachable || !q || !start) return null;
  const gaps = start.map((v, i) => Math.abs(v - q[i]));
  const rad = Math.max(...gaps);
  return { rad, joint: gaps.indexOf(rad) + 1 };
}
const awayFromStart = (traj) => (startGap(traj)?.rad ?? 0) > START_TOLERANCE_RAD;
/** The newest move to `traj`'s start. */
const moveTo = (traj) => (traj ? last(state.trajectories.filter((t) => t.inputs.move_to_start_of === traj.id)) : null);
const mode = () => $("#exec-mode").value;
const passed = (e) => e.summary.completed === true && e.summary.faults.length === 0;
// A passed dry run counts for the arm only if this server made it (not one imported with a bundle).
const passedHere = (e) => Boolean(e) && passed(e) && state.madeHere.has(e.id);
const IMPORTED_DRY_RUN =
  "The passed dry run on record was imported with the session and does not count here: press “Dry run” to dry-run this plan on this server.";
function dryRun(traj = trajectory(), m = mode()) {
  if (!traj) return null;
  return last(
    state.executions.filter(
      (e) => e.inputs.trajectory_id === traj.id && e.params.dry_run === true && e.params.mode === m,
    ),
  );
}
function lastRun(traj = trajectory()) {
  if (!traj) return null;
  return last(state.executions.filter((e) => e.inputs.trajectory_id === traj.id && !e.params.dry_run));
}

/** What changed in the session since an artifact was made (the server's words; empty: current). */
const outdated = (artifact) => artifact?.outdated || [];
const outdatedText = (artifact) => `Outdated: made before ${outdated(artifact).join("; ")}.`;

function stepStates() {
  const s = state.session;
  const rec = reconstruction();
  const traj = trajectory();
  const dry = dryRun();
  // A result made from inputs that are no longer the session's is shown, but is not a done step:
  // the steps after it wait for it to be made again.
  const recStates = outdated(rec).length ? { reconstruct: { done: false, needs: `${outdatedText(rec)} Press Reconstruct.` } } : {};
  if (traj && outdated(traj).length && acceptedOutdated(traj)) {
    // An older plan the operator took on purpose, having seen what changed since: it may be
    // dry-run and run (the run says so to the server, and its record keeps what was accepted).
    return {
      ...stepStatesOf(s, rec, traj, dry),
      ...recStates,
      plan: { done: true, needs: `Older plan ${traj.id} in use, taken on purpose: made before ${outdated(traj).join("; ")}.` },
    };
  }
  if (traj && outdated(traj).length) {
    const again = outdated(rec).length ? "Reconstruct and plan again" : "Plan again";
    const waiting = { done: false, needs: `The plan is outdated: ${again} first, or take it on purpose in the Plan step.` };
    return {
      ...stepStatesOf(s, rec, traj, dry),
      ...recStates,
      plan: { done: false, needs: `${outdatedText(traj)} ${again}, or press “Use this plan…” to see its inputs and take it anyway.` },
      dryrun: waiting,
      run: waiting,
    };
  }
  if (rec && outdated(rec).length) {
    const waiting = { done: false, needs: "Needs a reconstruction of the current inputs." };
    return {
      ...stepStatesOf(s, rec, traj, dry),
      reconstruct: { done: false, needs: `${outdatedText(rec)} Press Reconstruct.` },
      plan: traj ? waiting : { done: false, needs: waiting.needs }, dryrun: waiting, run: waiting,
    };
  }
  return stepStatesOf(s, rec, traj, dry);
}

function stepStatesOf(s, rec, traj, dry) {
  const haveInputs = Boolean(s.recording_id && s.scan_id);
  return {
    inputs: haveInputs
      ? { done: true, needs: "" }
      : { done: false, needs: `Needs ${[!s.recording_id && "a recording", !s.scan_id && "a scan"].filter(Boolean).join(" and ")}.` },
    calibration: s.T_base_tracker
      ? { done: true, needs: "" }
      : { done: false, needs: "Needs the tracker-to-base calibration (T_base_tracker) before planning." },
    reconstruct: rec
      ? { done: true, needs: "" }
      : { done: false, needs: s.recording_id ? "Ready: choose the parameters and press Reconstruct." : "Needs a recording." },
    plan: traj
      ? { done: true, needs: "" }
      : { done: false, needs: !rec ? "Needs a reconstruction." : !s.T_base_tracker ? "Needs the calibration." : "Ready: choose the speed and press Plan." },
    dryrun: passedHere(dry)
      ? { done: true, needs: "" }
      : { done: false, needs: !traj ? "Needs a plan." : dry && passed(dry) ? IMPORTED_DRY_RUN : dry ? "The last dry run did not pass: read its report, plan again or dry-run again." : `Ready: press “Dry run” (mode ${mode()}).` },
    run: runState(dry),
  };
}

/** Why the arm cannot take a run now, whatever the plan (null: it can). */
function armBlocker() {
  const robot = state.robot;
  if (!robot) return "Waiting for the arm's state…";
  if (!robot.real_arm) {
    return "No real arm on this server (simulation only): the dry run is as far as a plan goes here. "
      + "To run on an arm, start the service with TEACHPATH_UR_HOST set to the controller's address.";
  }
  // As the server's gate decides (service/gate.py, check_arm_state), in the same order.
  if (!robot.reachable) return "The arm's controller does not answer: check its network and power.";
  if (robot.emergency_stop) return "The arm is in an emergency stop: release it on the teach pendant, then power it on.";
  if (robot.protective_stop) return "The arm is in a protective stop: clear its cause, then press Unlock in the safety bar.";
  if (robot.robot_mode !== "RUNNING") {
    return `The arm is not running (mode ${robot.robot_mode}): power it on and release its brakes on the UR teach pendant.`;
  }
  if (robot.remote_control === false) return "The arm is in local control: switch the UR teach pendant to Remote Control.";
  return null;
}

function runState(dry) {
  const owner = state.robot?.owner_execution_id;
  // This session's run (started here, or found again after a reload or on a second pendant).
  if (state.stopping) return { done: false, needs: "Stopping: the stop was sent; waiting for the server to confirm the arm stands still." };
  if (state.moving && state.robot?.run_speed?.paused) {
    return { done: false, needs: "The run is paused: the arm rests on its path. Resume… in the bar goes on after you approve it again; Stop (or Esc) ends the run." };
  }
  if (state.moving) return { done: false, needs: "The arm is moving: press Stop (or Esc) to stop it at once." };
  if (owner) {
    return { done: false, needs: `The arm is busy: execution ${owner} owns it. Wait until it ends, or press Stop.` };
  }
  const traj = trajectory();
  const gap = otherCalibration(traj);
  if (gap) return { done: false, needs: OTHER_CALIBRATION(gap) }; // whatever ran before
  if (lastRun()?.summary.completed) return { done: true, needs: "" };
  const blocker = armBlocker();
  if (blocker) return { done: false, needs: blocker };
  if (dry && passed(dry) && !passedHere(dry)) return { done: false, needs: IMPORTED_DRY_RUN };
  if (passedHere(dry) && awayFromStart(traj)) {
    const away = startGap(traj);
    return { done: false, needs: `The arm is not where the plan starts (joint ${away.joint} is ${(away.rad * 180 / Math.PI).toFixed(1)}° away): move it there first (below), or plan again from where it stands.` };
  }
  return { done: false, needs: passedHere(dry) ? "Ready: press “Run on arm” and confirm." : "Needs a passed dry run of this plan in this mode." };
}

const STEPS = [
  ["inputs", "Inputs"],
  ["calibration", "Calibration"],
  ["reconstruct", "Reconstruct"],
  ["plan", "Plan"],
  ["dryrun", "Dry run"],
  ["run", "Run"],
];

function renderSteps() {
  if (!state.session) return;
  const states = stepStates();
  $("#steps").replaceChildren(
    ...STEPS.map(([key, label]) => {
      const st = states[key];
      const item = el("li", { "data-step": key, class: st.done ? "done" : "todo" },
        el("a", { href: `#step-${key}`, text: label }),
        el("span", { class: "mark", text: st.done ? " ✓" : "" }));
      if (state.busy === key) item.classList.add("running");
      return item;
    }),
  );
  for (const [key] of STEPS) {
    const card = $(`#step-${key}`);
    card.classList.toggle("done", states[key].done);
    $(".state", card).textContent = state.busy === key ? "running…" : states[key].done ? "done" : "";
    $(".needs", card).textContent = states[key].needs;
  }
  renderInputs();
  renderCalibration();
  renderReconstruction();
  renderPlan();
  renderDryRun();
  renderRun();
  updateButtons();
}

function updateButtons() {
  const s = state.session;
  const busy = Boolean(state.busy);
  const traj = trajectory();
  const dry = dryRun();
  const set = (selector, enabled) => { $(selector).disabled = !enabled; };
  set("#recording-form button[type=submit]", !busy);
  set("#scan-form button[type=submit]", !busy);
  set("#touches-form button[type=submit]", !busy);
  set("#reconstruct-form button[type=submit]", !busy && Boolean(s?.recording_id) && Boolean(state.schema));
  set("#plan-form button[type=submit]", !busy && Boolean(reconstruction()) && Boolean(s?.T_base_tracker));
  set("#dryrun-form button[type=submit]", !busy && Boolean(traj));
  // An outdated plan is offered for the arm only when taken on purpose (the server refuses it
  // too, outdated_inputs, unless the run says it was accepted).
  set("#run-form button[type=submit]",
    !busy && passedHere(dry) && !canMove() && usable(traj) && !armBlocker() && !awayFromStart(traj));
  const move = moveTo(traj);
  const fresh = move && !awayFromStart(move) && usable(move); // it starts where the arm stands
  set("#move-plan-form button[type=submit]", !busy && !canMove() && usable(traj));
  set("#plan-use", !busy && !canMove() && canTakeViewedPlan());
  set("#move-dryrun-form button[type=submit]", !busy && Boolean(fresh));
  set("#move-run-form button[type=submit]",
    !busy && Boolean(fresh) && passedHere(dryRun(move)) && !canMove() && !armBlocker());
}

// -- provenance and downloads of an artifact --------------------------------------------------------

/** What each kind of artifact can be downloaded as: [label, path suffix, file suffix]. */
const DOWNLOADS = {
  recording: [["trace CSV", "csv", ".csv"]],
  scan: [["scan PLY", "ply", ".ply"]],
  reconstruction: [["path CSV", "csv", ".csv"]],
  trajectory: [["trajectory CSV", "csv", ".csv"], ["URScript", "urscript", ".script"], ["plan picture", "plot.png", ".png"]],
  execution: [["record CSV", "csv", ".csv"]],
};

/** The API's collection of each kind of artifact (not always the kind plus "s"). */
const COLLECTIONS = {
  recording: "recordings", scan: "scans", touches: "touches", reconstruction: "reconstructions",
  trajectory: "trajectories", execution: "executions",
};

/** Fetch with the token and hand the bytes to the browser as a file (a plain link cannot send
 * the Authorization header). */
async function download(path, filename, box) {
  try {
    const response = await api(path, { raw: true });
    const url = URL.createObjectURL(await response.blob());
    const link = el("a", { href: url, download: filename });
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10_000);
  } catch (err) {
    const { instruction, message } = explain(err);
    box.textContent = `Download failed: ${instruction || ""} ${message}`.replace(/\s+/g, " ");
  }
}

function provenance(kind, artifact) {
  if (!artifact) return [];
  const sid = state.session.id;
  // Not a step's ".message" box (each form has one of its own) nor a ".report".
  const box = el("p", { class: "download-error", role: "alert" });
  const json = (value) => el("pre", { class: "json", text: JSON.stringify(value, null, 1) });
  const buttons = (DOWNLOADS[kind] || []).map(([label, suffix, extension]) => {
    const button = el("button", { type: "button", class: "download", text: `Download ${label}` });
    button.addEventListener("click", () =>
      download(`/sessions/${sid}/${COLLECTIONS[kind]}/${artifact.id}/${suffix}`, `${artifact.id}${extension}`, box));
    return button;
  });
  const details = el("details", { class: "provenance", "data-artifact": artifact.id },
    el("summary", { text: `Provenance and files of ${artifact.id}` }),
    table([
      ["id", artifact.id],
      ["created", artifact.created_at],
      ["checksum (sha256)", artifact.sha256],
      ["size", `${(artifact.size / 1024).toFixed(1)} KiB`],
      ...(artifact.source_name ? [["uploaded as", artifact.source_name]] : []),
    ]),
    el("h4", { text: "Inputs" }), json(artifact.inputs),
    el("h4", { text: "Parameters" }), json(artifact.params),
    el("p", {}, ...buttons), box);
  // The steps are drawn again on every change of the arm's state: an opened box stays open.
  details.open = openProvenance.has(artifact.id);
  details.addEventListener("toggle", () => {
    if (details.open) openProvenance.add(artifact.id);
    else openProvenance.delete(artifact.id);
  });
  return [details];
}
const openProvenance = new Set();

function table(rows) {
  return el("table", {}, ...rows.map(([k, v]) => el("tr", {}, el("th", { text: k }), el("td", { text: v }))));
}
const report = (lines) => el("pre", { class: "report", text: (lines || []).join("\n") });

function renderInputs() {
  const rec = recording();
  const sc = scan();
  $("#recording-current").textContent = rec
    ? `${rec.source_name || rec.id}: ${rec.summary.n_samples} samples, ${mm(rec.summary.length_m, 0)} long`
    : "none yet";
  // Its size on the card, in mm: a scan read in the wrong unit shows at once.
  const size = sc?.summary.bounds_m
    ? `, ${sc.summary.bounds_m[1].map((hi, i) => ((hi - sc.summary.bounds_m[0][i]) * 1000).toFixed(0)).join(" × ")} mm`
    : "";
  $("#scan-current").textContent = sc
    ? `${sc.source_name || sc.id}: ${sc.summary.n_points} points${size}`
    : "none yet";
  $("#recording-files").replaceChildren(...provenance("recording", rec));
  $("#scan-files").replaceChildren(...provenance("scan", sc));
}

/** Where a calibration of the session came from: the newest entry of its report that set
 * `field` (point pairs, a pivot, a loaded file), in words. */
function calibrationSource(s, field) {
  const sets = { base: "T_base_tracker", pivot: "tip_offset_m" };
  const entries = Object.entries(s.calibration_report || {})
    .filter(([name, entry]) => (entry.field || sets[name]) === field)
    .sort(([, a], [, b]) => String(a.at || "").localeCompare(String(b.at || "")));
  if (!entries.length) return "";
  const [name, entry] = entries[entries.length - 1];
  const how = name === "base" ? "point pairs" : name === "pivot" ? "pivoting"
    : entry.source_name ? `file ${entry.source_name}` : name.startsWith("set:") ? "set directly" : name;
  return ` (${how}${entry.at ? `, ${new Date(entry.at).toLocaleString()}` : ""})`;
}

/** The rotation of a 4x4 (rows) in degrees, and its translation in mm. */
function transformText(T) {
  const turn = Math.acos(Math.min(1, Math.max(-1, (T[0][0] + T[1][1] + T[2][2] - 1) / 2))) * 180 / Math.PI;
  return `translation (${T.slice(0, 3).map((row) => (row[3] * 1000).toFixed(1)).join(", ")}) mm, turned ${turn.toFixed(1)}°`;
}

/** Every calibration the session and the cell use, one line each: what a plan and a run
 * depend on, read at a glance. */
function calibrationLines() {
  const s = state.session;
  const touches = (state.touches || []).at(-1);
  const cell = state.cell;
  const boxes = cell?.keep_out_boxes_m.length ?? 0;
  const planes = cell?.cell_planes.length ?? 0;
  return [
    ["tracker → base", s.T_base_tracker ? `${transformText(s.T_base_tracker)}${calibrationSource(s, "T_base_tracker")}` : "not calibrated (plans need it)"],
    ["tracker → scan", s.T_scan_tracker ? `first guess set: ${transformText(s.T_scan_tracker)}${calibrationSource(s, "T_scan_tracker")}` : "no first guess (the registration finds it)"],
    ["pen tip", s.tip_offset_m ? `(${s.tip_offset_m.map((v) => (v * 1000).toFixed(1)).join(", ")}) mm from the rigid body${calibrationSource(s, "tip_offset_m")}` : "not calibrated (the rigid body's origin is taken as the tip)"],
    ["touches", touches ? `${touches.summary.n_touches} points touched (${touches.source_name || touches.id}): they place the scan` : "none"],
    ["arm", cell ? `${cell.robot}: ${cell.arm_kinematics}` : "–"],
    ["cell", cell ? `${boxes} keep-out box${boxes === 1 ? "" : "es"}, ${planes} plane${planes === 1 ? "" : "s"} besides the mounting one (drawn in the 3-D view); ${cell.source}` : "cannot be read: set it again below"],
  ];
}

function renderCalibration() {
  const s = state.session;
  $("#calibration-current").replaceChildren(table(calibrationLines()));
  renderCell();
  // Another session's tracker -> base, to use here (the same cell, the tracker not moved).
  const select = $("#copycal-form select");
  const others = (state.sessions || []).filter((o) => o.id !== s.id && o.T_base_tracker);
  const chosen = select.value;
  select.replaceChildren(el("option", { value: "", text: others.length ? "choose one" : "no other session is calibrated" }),
    ...others.map((o) => el("option", { value: o.id, text: `${o.name} (${transformText(o.T_base_tracker)})` })));
  if (others.some((o) => o.id === chosen)) select.value = chosen;
  // The newest touches place the scan for the next reconstructions (unless use_touches is off).
  const touches = (state.touches || []).at(-1);
  $("#touches-summary").replaceChildren(...(touches ? [
    table([
      ["touches", `${touches.summary.n_touches} rests found in ${touches.source_name || touches.id}`],
      ...touches.summary.touches_m.map((p, i) => [`touch ${i + 1}`, `(${p.map((v) => (v * 1000).toFixed(1)).join(", ")}) mm`]),
    ]),
    ...(touches.summary.notes.length ? [report(touches.summary.notes)] : []),
    ...provenance("touches", touches),
  ] : []));
}

function renderReconstruction() {
  const rec = reconstruction();
  const box = $("#reconstruct-summary");
  if (!rec) return box.replaceChildren();
  const sm = rec.summary;
  const modes = Object.entries(sm.modes).filter(([, n]) => n).map(([m, n]) => `${m} ${n}`).join(", ");
  const rows = [
    ["reconstruction", rec.id],
    ["points", String(sm.n_points)],
    ["modes", modes],
    ["mean displacement", mm(sm.mean_displacement_m)],
    ["max displacement", mm(sm.max_displacement_m)],
  ];
  const reg = sm.registration;
  if (reg && reg.target === "touches") {
    rows.push(["registration", `by ${reg.n_pairs} touches of the workpiece: residual ${mm(reg.rmse_m, 3)} RMS`]);
    rows.push(["motions the touches fixed", `${reg.constrained_dof} of 6`]);
  } else if (reg) {
    rows.push(["registration", `to the scan's ${reg.target}: rmse ${mm(reg.rmse_m, 3)}, fitness ${reg.fitness.toFixed(2)}, ${reg.n_pairs} pairs`]);
    // An edge fixes fewer of the six motions than a surface with relief: say how many.
    rows.push(["motions the scan fixed", `${reg.constrained_dof} of 6${reg.constrained_dof < 6 ? " (the rest kept from the given frames)" : ""}`]);
  }
  if (reg) {
    if (reg.reason) rows.push(["why", reg.reason]);
    if (reg.path_moved_mean_m != null) {
      // Millimetres of sliding along a nearly flat patch say little about the scanner: say how
      // much of the move was toward or away from the feature.
      const across = reg.target === "edge" ? "across the edge" : "off the surface";
      const off = reg.path_moved_off_feature_median_m != null ? ` (${mm(reg.path_moved_off_feature_median_m)} of it ${across} on median, the rest along it)` : "";
      rows.push(["path moved by it", `${mm(reg.path_moved_mean_m)} on average, ${mm(reg.path_moved_max_m)} at most${off}`]);
    }
  }
  rows.push(["segments", sm.segments.map((g) => `${g.kind} (points ${g.start}–${g.stop - 1})`).join(", ") || "–"]);
  for (const [i, g] of sm.segments.entries()) {
    if (g.kind !== "edge" && !g.fallen_back) continue;
    const parts = [];
    if (g.kind === "edge") parts.push(`the scan's edge along ${(g.edge_fraction * 100).toFixed(0)} %`);
    if (g.edge_distance_m != null) parts.push(`${mm(g.edge_distance_m)} from the trace on median`);
    if (g.kind === "edge") parts.push(g.next_edge_m == null ? "no other edge near" : `the next edge ${mm(g.next_edge_m, 1)} away`);
    if (g.fallen_back) parts.push(`${(g.fallen_back * 100).toFixed(0)} % of its points kept the trace${g.fallen_back > 0.05 ? ": scan not trusted here" : ""}`);
    rows.push([`segment ${i} evidence`, parts.join("; ")]);
  }
  const reasons = Object.entries(sm.reasons || {});
  if (reasons.length) rows.push(["points off the scan's evidence", reasons.map(([r, n]) => `${n} ${r.replaceAll("_", " ")}`).join(", ")]);
  for (const c of sm.corners || []) rows.push([`turn at point ${c.index}`, `${c.split ? "corner" : "not split"}: ${c.reason}`]);
  if (sm.demonstrations && sm.demonstrations.length) {
    const used = sm.demonstrations.filter((d) => d.used).length;
    rows.push(["demonstrations", `${used} of ${sm.demonstrations.length} fused`]);
  }
  if (sm.uncertainty_max_m != null) rows.push(["uncertainty (1σ)", `${mm(sm.uncertainty_mean_m)} on average, ${mm(sm.uncertainty_max_m)} at most`]);
  box.replaceChildren(
    ...(outdated(rec).length ? [el("p", { class: "outdated", role: "status", text: outdatedText(rec) })] : []),
    table(rows), ...(sm.notes.length ? [report(sm.notes)] : []), ...provenance("reconstruction", rec),
    ...comparison());
}

/** All reconstructions of the session side by side: parameters and figures (the newest is the
 * one planned from and drawn). */
function comparison() {
  if (state.reconstructions.length < 2) return [];
  const heads = ["reconstruction", "method", "radius", "alpha", "beta", "points", "mean displacement", "max displacement", "registration rmse"];
  const rows = state.reconstructions.map((r, i) => {
    const p = r.params;
    const sm = r.summary;
    const cells = [r.id, p.method ?? "–", mm(p.radius_m, 1), String(p.alpha ?? "–"), String(p.beta ?? "–"),
      String(sm.n_points), mm(sm.mean_displacement_m), mm(sm.max_displacement_m),
      sm.registration ? mm(sm.registration.rmse_m, 3) : "–"];
    const row = el("tr", { "data-reconstruction": r.id }, ...cells.map((c) => el("td", { text: c })));
    const current = i === state.reconstructions.length - 1;
    if (current) row.classList.add("current");
    // Any other one can be drawn over the current one, coloured by how far it lies from it.
    const button = el("button", { type: "button", class: "overlay", text: current ? "current" : "Overlay" });
    button.disabled = current;
    button.addEventListener("click", () => overlay(r.id));
    row.append(el("td", {}, button));
    return row;
  });
  return [el("h4", { text: `All ${state.reconstructions.length} reconstructions of this session` }),
    el("table", { class: "comparison" }, el("tr", {}, ...heads.map((h) => el("th", { text: h })), el("th", { text: "3-D" })), ...rows),
    el("p", { class: "small", id: "overlay-note" })];
}

/** Draw reconstruction `id` over the current one, each point coloured by its distance from
 * the current one's path; say the mean and the largest. */
async function overlay(id) {
  const current = reconstruction();
  const note = $("#overlay-note");
  try {
    const diff = await api(`/sessions/${state.session.id}/reconstructions/${id}/difference?against=${current.id}`);
    if (reconstruction()?.id !== current.id) return; // a newer one came meanwhile: not against it
    state.workspace?.showOverlay(diff);
    note.textContent = `${id} over ${current.id}: ${mm(diff.mean_m, 3)} apart on average, ${mm(diff.max_m, 3)} at most `
      + `(its point ${diff.at_index}); drawn coloured by the difference, the current one as before.`;
  } catch (err) {
    note.textContent = `The overlay failed: ${explain(err).message}`;
  }
}

function renderPlan() {
  renderPlanChoice();
  const traj = trajectory();
  const box = $("#plan-summary");
  if (!traj) return box.replaceChildren();
  const sm = traj.summary;
  const feasible = sm.checks.length ? `passed: ${sm.checks.join(", ")}` : "";
  box.replaceChildren(
    ...(outdated(traj).length ? [el("p", { class: "outdated", role: "status",
      text: `${outdatedText(traj)}${acceptedOutdated(traj) ? " Taken on purpose for the dry run and the run." : ""}` })] : []),
    table([
      ["trajectory", traj.id],
      ["robot", sm.robot],
      ["speed", mmps(sm.requested_speed_m_s)],
      ["duration", seconds(sm.duration_s)],
      ["configuration", sm.configuration || "–"],
      ["starts from", startFrom(sm.start_from)],
      ["approach", mm(sm.approach_m, 0)],
      ["closest to the cell", mm(sm.min_clearance_m, 1)],
      ["TCP", tcpText(sm.tcp_pose)],
      ["payload", payloadText(sm, state.robot)],
    ]),
    el("h4", { text: "Duration and fastest TCP speed per phase" }),
    el("table", { class: "phases" }, ...Object.entries(sm.phase_durations_s).map(([phase, s]) =>
      el("tr", { "data-phase": phase }, el("th", { text: phase }), el("td", { text: phaseText(sm, phase, s) })))),
    el("h4", { text: "Feasibility" }),
    el("p", { class: "small", text: feasible }),
    report(sm.report),
    ...provenance("trajectory", traj),
  );
}

/** The plan the choice shows (the operator's selection, else the plan in use). */
const viewedPlan = () => plans().find((t) => t.id === state.pickView) || trajectory();

/** What an operator reads of a plan before taking it: when it was made, what changed in the
 * session since, and what it was made from. */
function planRows(t) {
  const sm = t.summary;
  return [
    ["changed since it was made", outdated(t).join("; ") || "nothing: made from the session's current inputs"],
    ["speed", mmps(sm.requested_speed_m_s)],
    ["duration", seconds(sm.duration_s)],
    ["starts from", startFrom(sm.start_from)],
    ["TCP", tcpText(sm.tcp_pose)],
    ...approvedInputs(t),
  ];
}

/** The choice of plan: shown when the session has more than one, or the plan in use is
 * outdated. A plan is taken only through a confirmation that names its inputs and what changed
 * since it was made. */
function renderPlanChoice() {
  const panel = $("#plan-choice");
  const all = plans();
  const traj = trajectory();
  panel.hidden = !traj || (all.length < 2 && !outdated(traj).length);
  if (panel.hidden) return;
  const newest = newestPlan();
  const label = (t) => [
    `${t.id}, ${new Date(t.created_at).toLocaleString()}, ${mmps(t.summary.requested_speed_m_s)}`,
    t.id === newest?.id ? "newest" : "",
    outdated(t).length ? "OUTDATED" : "",
    t.id === traj.id ? "in use" : "",
  ].filter(Boolean).join(" · ");
  const options = all.map((t) => [t.id, label(t)]);
  const select = $("#plan-pick");
  const key = JSON.stringify(options);
  if (select.dataset.key !== key) {
    select.replaceChildren(...options.map(([id, text]) => el("option", { value: id, text })));
    select.dataset.key = key;
  }
  // The row the operator is reading stays selected (the steps are drawn on every arm state).
  if (!all.some((t) => t.id === state.pickView)) state.pickView = traj.id;
  select.value = state.pickView;
  $("#plan-pick-inputs").replaceChildren(table(planRows(viewedPlan())));
}

/** Whether the viewed plan can be taken: another plan than the one in use, or the one in use
 * while it is outdated and not yet taken on purpose. */
function canTakeViewedPlan() {
  const viewed = viewedPlan();
  const traj = trajectory();
  if (!viewed || !traj) return false;
  return viewed.id !== traj.id || (outdated(traj).length > 0 && !acceptedOutdated(traj));
}

/** Take the viewed plan for the dry run and the run, after a confirmation naming its inputs. */
async function takeViewedPlan() {
  const t = viewedPlan();
  if (!t || !canTakeViewedPlan()) return;
  const changed = outdated(t);
  const ok = await askDialog(
    changed.length ? "Use this outdated plan?" : "Use this plan?",
    "Confirm: use this plan",
    [
      ["plan", `${t.id}, made ${new Date(t.created_at).toLocaleString()}`],
      ...planRows(t),
      ["then", otherCalibration(t) ? `It can be dry-run, not run. ${OTHER_CALIBRATION(otherCalibration(t))}`
        : changed.length
          ? "Its dry run and run use it as it is, made from the inputs above and not the session's current ones. The run tells the server you accepted that; its record keeps what had changed."
          : "Its dry run and run use it instead of the newest plan."],
    ],
    "Nothing moves now. The dry run and the run each ask again before they start.",
  );
  if (!ok) return;
  // The newest current plan is the default: taking it is forgetting the pick.
  state.pick = t.id === newestPlan()?.id && !changed.length ? null : { id: t.id, outdated: changed };
  renderSteps();
  showWorkspace();
}

/** The largest deviation anywhere in an execution and the phase it was in (from the record's
 * per-phase figures: the review shows the same). */
function worstDeviation(sm) {
  const entries = Object.entries(sm.max_deviation_by_phase_m || {});
  if (!entries.length) return null;
  const [phase, value] = entries.reduce((a, b) => (b[1] > a[1] ? b : a));
  return { phase, value };
}

function execSummary(ex) {
  const sm = ex.summary;
  const worst = worstDeviation(sm);
  const got = Object.keys(sm.executed_phase_durations_s || {});
  return [
    table([
      ["execution", ex.id],
      ["result", passed(ex) ? (state.madeHere.has(ex.id) ? "passed" : "passed at another site (imported): not counted here") : sm.completed ? `completed with faults` : `not completed${sm.stopped_in ? ` (stopped in ${sm.stopped_in})` : ""}`],
      ["mode", sm.mode],
      ["motion time", `${seconds(sm.duration_s)} of ${seconds(sm.planned_duration_s)} planned`
        + (sm.completed ? "" : got.length ? ` (reached: ${got.join(", ")})` : " (the arm did not move)")],
      ["largest deviation along the path (process)", mm(sm.max_path_deviation_m, 3)],
      ["largest deviation anywhere", worst ? `${mm(worst.value, 3)} (${worst.phase})` : "–"],
      ["faults", sm.faults.join("; ") || "none"],
    ]),
    report(sm.report),
    ...provenance("execution", ex),
  ];
}

function renderDryRun() {
  const dry = dryRun();
  $("#dryrun-summary").replaceChildren(...(dry ? execSummary(dry) : []));
}

function renderRun() {
  const run = lastRun();
  const previous = state.busy === "run" && run
    ? [el("p", { class: "small", text: "The last run before this one (this one is reported when it ends):" })] : [];
  $("#run-summary").replaceChildren(...previous, ...(run ? execSummary(run) : []));
  renderMove();
}

/** The move to the plan's start: offered while the real arm stands away from it (after a jog,
 * or another plan's run), as a motion of its own that is planned, dry-run and approved. */
function renderMove() {
  const traj = trajectory();
  const panel = $("#move-to-start");
  const gap = startGap(traj);
  const move = moveTo(traj);
  const away = usable(traj) && awayFromStart(traj) && !state.moving;
  // Shown while the arm is away, and while a move of this plan is being made.
  panel.hidden = !away && !["move-plan", "move-dryrun", "move-run"].includes(state.busy);
  state.workspace?.showMove(state.session.id, panel.hidden ? null : move).catch(() => {});
  if (panel.hidden) return;
  const degrees = (rad) => `${(rad * 180 / Math.PI).toFixed(1)}°`;
  const stale = move && awayFromStart(move);
  const dry = move ? dryRun(move) : null;
  const busyMove = { "move-plan": "Planning the move…", "move-dryrun": "Dry-running the move…",
    "move-run": "The arm is moving to the plan's start: Stop (or Esc) stops it." }[state.busy];
  $("#move-status").textContent = busyMove || (!gap ? "" : !move
    ? `The arm stands ${degrees(gap.rad)} (joint ${gap.joint}) from where the plan starts. Plan a move there: a joint move of its own (first straight off the workpiece if the tool stands on it), checked against the cell, which you dry-run and approve before it runs.`
    : stale ? "The arm has moved since this move was planned: plan the move again from where it stands."
      : !passedHere(dry) ? "Dry-run the move (it is drawn in teal in the 3-D view), then move the arm to the start."
        : "The move passed its dry run: press “Move to start on the arm” and confirm. The plan can run after it.");
  if (!move) return $("#move-summary").replaceChildren();
  const sm = move.summary;
  $("#move-summary").replaceChildren(
    table([
      ["move", `${move.id}${stale ? " (planned from another pose of the arm)" : ""}`],
      ["motion", moveWords(sm)],
      ["duration", seconds(sm.duration_s)],
      ["fastest TCP", moveFastest(sm)],
      ["smallest clearance (arm, tool, cell, scan)", mm(sm.min_clearance_m, 1)],
      ["dry run", !dry ? "not yet" : passedHere(dry) ? "passed" : passed(dry) ? "imported: does not count here" : "did not pass: read its report"],
    ]),
    report(sm.report),
  );
}

// -- the workspace's readouts: a picked point, an execution against its plan -------------------

const MODE_WORDS = { path: "the trace alone", surface: "a surface of the scan", edge: "an edge of the scan", unchanged: "unchanged (too few points for a fit)" };
/** Why the scan's evidence was not used at a point (the CSV's reason column), in words. */
const REASON_WORDS = {
  no_feature: "the scan shows no such feature here: the trace was kept",
  far_from_trace: "the scan's feature is farther than the hand's error explains: the trace was kept",
  off_evidence: "the fitted feature is not where the scan's points are: the trace was kept",
  segment_disagrees: "the whole segment runs far from the scan: the trace was kept",
  one_face: "no edge found here: the height comes from the face under the point",
  continued: "past the end of the scan's edge: its line continued",
  past_end: "too far past the end of the scan's edge: the trace was kept",
};

function showPick(picked) {
  const box = $("#pick-readout");
  if (!picked) return (box.textContent = "Nothing under the cursor: click on a point of a shown layer.");
  const at = `(${[picked.point.x, picked.point.y, picked.point.z].map((v) => (v * 1000).toFixed(1)).join(", ")}) mm`;
  const words = { reconstruction: "reconstruction point", trace: "trace point", scan: "scan point", path: "planned waypoint", overlay: "overlaid reconstruction point" };
  const parts = [`${words[picked.layer] || picked.layer} ${picked.index} at ${at}`];
  const d = picked.diagnostics;
  if (d) {
    parts.push(`displacement ${mm(d.displacement_m, 3)}`, `mode: ${MODE_WORDS[d.mode] || d.mode}`, `segment ${d.segment}`,
      `fit residuals: path ${mm(d.residual_path_m, 3)}, surface ${mm(d.residual_surface_m, 3)}`,
      `neighbours: ${d.n_path} path, ${d.n_surface} scan`, `alpha ${Number.isFinite(d.alpha) ? d.alpha.toFixed(2) : "–"}`);
    if (Number.isFinite(d.uncertainty_m)) parts.push(`uncertainty ±${mm(d.uncertainty_m, 2)} (1σ)`);
    if (d.reason) parts.push(REASON_WORDS[d.reason] || d.reason);
  }
  if (picked.time_s != null) parts.push(`at ${picked.time_s.toFixed(2)} s of the plan`);
  if (picked.difference_m != null) parts.push(`${mm(picked.difference_m, 3)} from the current reconstruction`);
  if (picked.distance_m != null) parts.push(`distance from the previous point: ${mm(picked.distance_m, 2)}`);
  box.replaceChildren(...parts.map((text, i) => el("span", { class: i === parts.length - 1 && picked.distance_m != null ? "distance" : "", text: `${text}${i < parts.length - 1 ? "; " : ""}` })));
}

function showReview(review, execution) {
  const panel = $("#review");
  panel.hidden = !review?.t_s.length;
  if (panel.hidden) return;
  const sm = execution.summary;
  const kind = sm.dry_run ? `dry run, ${sm.mode}` : `run on the arm, ${sm.mode}`;
  const worst = worstDeviation(sm);
  // The record's figures, as in the execution's table; the review's own maximum is the same
  // measure over the same samples (tests/service/test_execution_summaries.py).
  $("#review-summary").textContent = `${execution.id} (${kind}): along the path (process) the arm was at most `
    + `${mm(sm.max_path_deviation_m, 3)} from the plan; anywhere ${mm(worst ? worst.value : review.max_off_path_m, 3)}`
    + `${worst ? ` (${worst.phase})` : ""}, at ${review.at_s.toFixed(2)} s. The executed path is drawn in red.`;
  import("./timeline.js").then(({ Plot }) => {
    $("#review-plot").replaceChildren();
    new Plot($("#review-plot"), { title: "distance from the planned path", unit: "mm", t: review.t_s,
      series: [{ values: review.off_path_m.map((v) => v * 1000), colour: "#d62728" }], phases: [], phaseOf: null });
  });
}

// -- jobs: one click, one POST, followed to the end -----------------------------------------------

async function runJob(step, form, start, onDone) {
  if (state.busy) return;
  const box = $(".message", form);
  const bar = $("progress", form);
  const label = $(".job-state", form);
  clearMessage(box);
  state.busy = step;
  renderSteps();
  try {
    const job = await start();
    bar.hidden = false;
    // Progress never goes back on the page (an event and a poll can arrive out of order).
    let shown = 0;
    const finished = await followJob(job, (j) => {
      shown = Math.max(shown, j.progress);
      bar.value = shown;
      label.textContent = `${j.state} ${Math.round(shown * 100)} %`;
    });
    if (finished.state === "cancelled") {
      // A Stop (or a cancel): say where it ended, not just the state twice.
      const where = finished.result?.stopped_in;
      const message = where ? `cancelled by Stop: the arm stopped in ${where}`
        : finished.error?.message || "cancelled before it started";
      // A stopped dry run moved nothing: its instruction is not the arm's.
      showError(box, { code: step.endsWith("dryrun") ? "dry_run_stopped" : "cancelled", message });
    } else if (finished.state !== "succeeded") {
      showError(box, { code: finished.error?.code || finished.state, message: finished.error?.message || finished.state });
    }
    await onDone?.(finished);
  } catch (err) {
    showError(box, err);
  } finally {
    state.busy = null;
    state.moving = null;
    state.stopping = null;
    bar.hidden = true;
    updateStop();
    await refresh().catch(() => {});
  }
}

// -- inputs ---------------------------------------------------------------------------------------

function upload(kind, form) {
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const box = $(".message", form);
    clearMessage(box);
    const data = new FormData();
    const file = form.elements.file.files[0];
    if (!file) return;
    data.append("file", file, file.name);
    for (const name of ["format", "units"]) {
      if (form.elements[name].value) data.append(name, form.elements[name].value);
    }
    const button = $("button[type=submit]", form);
    button.disabled = true;
    try {
      await api(`/sessions/${state.session.id}/${kind}`, { method: "PUT", form: data });
      box.replaceChildren(el("p", { text: `${file.name} uploaded.` }));
      box.className = "message ok";
      form.elements.file.value = "";
    } catch (err) {
      showError(box, err);
    } finally {
      await refresh();
    }
  });
}

// -- calibration: the pen's tip and tracker -> base, with their figures -----------------------------

/** Point pairs typed one per line ("bx by bz, tx ty tz"; commas or blanks) -> [{base, tracker}];
 * throws naming the line that is not six numbers. */
function parsePairs(text, scale) {
  const pairs = [];
  text.split("\n").forEach((line, i) => {
    if (!line.trim()) return;
    const numbers = line.split(/[\s,;]+/).filter(Boolean).map(Number);
    if (numbers.length !== 6 || numbers.some((v) => !Number.isFinite(v))) {
      throw { code: "invalid_request", message: `line ${i + 1}: “${line.trim()}” is not six numbers (base x y z, tracker x y z)` };
    }
    pairs.push({ base: numbers.slice(0, 3).map((v) => v * scale), tracker: numbers.slice(3).map((v) => v * scale) });
  });
  if (pairs.length < 3) throw { code: "invalid_request", message: `${pairs.length} pair(s): at least 3 are needed` };
  return pairs;
}

function pairsTable(fit) {
  const rows = fit.residuals_m.map((r, i) => el("tr", { class: fit.suspect[i] ? "suspect" : "" },
    el("td", { text: String(i + 1) }),
    el("td", { text: mm(r, 3) }),
    el("td", { text: mm(fit.leave_one_out_m[i], 3) }),
    el("td", { text: fit.suspect[i] ? "suspect" : "ok" }),
    el("td", { text: fit.used[i] ? "used" : "left out" })));
  return [
    table([["RMS of the pairs used", mm(fit.residual_rms_m, 3)], ["tolerance", mm(fit.tolerance_m, 3)]]),
    el("table", { class: "pairs" },
      el("tr", {}, ...["pair", "residual", "left out, residual", "", "in the fit"].map((h) => el("th", { text: h }))),
      ...rows),
  ];
}

/** A calibration form: on submit, `send(form)` makes the request (it may throw before sending,
 * naming what to correct); its result, or the figures of a refused fit (the error's detail), are
 * drawn into `summary` by `show`. One click, one request; the button is held meanwhile. */
function fitForm(form, summary, send, show) {
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const box = $(".message", form);
    const button = $("button[type=submit]", form);
    clearMessage(box);
    summary.replaceChildren();
    if (!form.reportValidity()) return;
    button.disabled = true;
    try {
      summary.replaceChildren(...show((await send(form)).result));
    } catch (err) {
      showError(box, err);
      if (err.detail) summary.replaceChildren(...show(err.detail, true));
    } finally {
      button.disabled = false;
      if (state.session) await refresh();
    }
  });
}

// -- the cell: keep-out boxes and planes, edited as a draft drawn in 3-D ------------------------

const CELL_COLUMNS = { box: ["x min", "y min", "z min", "x max", "y max", "z max"], plane: ["nx", "ny", "nz", "d"] };
// The size of a box added around a picked point (m).
const PICK_BOX_M = 0.1;

/** One editable row: a box's corners or a plane's normal and offset, in the operator's units
 * (mm; a plane's normal has none). */
function cellRow(kind, number, values) {
  const scale = (i) => (kind === "box" || i === 3 ? 1000 : 1);
  const cells = values.map((v, i) => el("td", {}, el("input", {
    type: "text", inputmode: "decimal", required: "", "aria-label": `${kind} ${number} ${CELL_COLUMNS[kind][i]}${scale(i) === 1000 ? " (mm)" : ""}`,
    value: String(Number((v * scale(i)).toFixed(3))), "data-scale": String(scale(i)),
  })));
  const remove = el("button", { type: "button", class: "remove", text: "✕", title: "Remove", "aria-label": `remove ${kind} ${number}` });
  remove.addEventListener("click", () => {
    remove.closest("tr").remove();
    renumberCell();
    cellEdited();
  });
  return el("tr", { "data-kind": kind }, el("td", { text: String(number) }), ...cells, el("td", {}, remove));
}

function renumberCell() {
  for (const kind of ["box", "plane"]) {
    [...$(`#cell-${kind === "box" ? "boxes" : "planes"} tbody`).rows].forEach((row, i) => {
      row.cells[0].textContent = String(i + 1);
      for (const control of row.querySelectorAll("[aria-label]")) {
        control.setAttribute("aria-label", control.getAttribute("aria-label").replace(/^(remove )?(box|plane) \d+/, `$1$2 ${i + 1}`));
      }
    });
  }
}

/** The saved cell in the form, unless the operator is editing it (a draft is never overwritten
 * by a refresh; "Discard changes" reads the saved one again). */
function renderCell({ force = false } = {}) {
  const form = $("#cell-form");
  const cell = state.cell;
  // Rows are rebuilt only when the saved cell changed: the steps are drawn again on every state
  // of the arm, and a rebuilt row would take the field the operator is about to type in.
  const shown = JSON.stringify(cell);
  if ((!state.cellDirty && shown !== state.cellShown) || force) {
    state.cellDirty = false;
    state.cellShown = shown;
    // The revision an edit of these rows is made from: a save names it, and is refused if
    // another pendant saved since (never the newer revision a refresh has read meanwhile).
    state.cellBase = cell ? cell.revision : state.cellRevision;
    $("#cell-boxes tbody").replaceChildren(...(cell?.keep_out_boxes_m || []).map((box, i) => cellRow("box", i + 1, box)));
    $("#cell-planes tbody").replaceChildren(...(cell?.cell_planes || []).map((plane, i) => cellRow("plane", i + 1, plane)));
    $("#cell-draft").textContent = "";
    state.workspace?.showCell(cell);
    state.workspace?.showCell(null, { draft: true });
  }
  const newer = state.cellDirty && cell && cell.revision !== state.cellBase;
  $("#cell-source").textContent = (cell
    ? `Saved: ${cell.source}.${cell.editable ? "" : " The arm is running: the cell cannot be changed until the run ends."}`
    : "The saved cell cannot be read: set the boxes and planes again, or go back to the start-up settings.")
    + (newer ? " It was changed by another pendant since you started editing: press Discard changes to see it." : "");
  const locked = Boolean(cell && !cell.editable) || Boolean(state.cellSaving);
  for (const control of form.querySelectorAll("input, button")) control.disabled = locked;
  $("#cell-box-at-pick").disabled = locked || !state.pickedBase;
}

/** The boxes and planes typed, in metres, or null with the first bad field marked. */
function cellDraft() {
  const read = (kind) => [...$(`#cell-${kind === "box" ? "boxes" : "planes"} tbody`).rows].map((row) => {
    row.classList.remove("invalid");
    return [...row.querySelectorAll("input")].map((input) => {
      const value = Number(input.value.trim().replace(",", "."));
      const ok = input.value.trim() !== "" && Number.isFinite(value);
      input.setCustomValidity(ok ? "" : "a number (a comma or a point for decimals)");
      if (!ok) row.classList.add("invalid");
      return value / Number(input.dataset.scale);
    });
  });
  const boxes = read("box");
  const planes = read("plane");
  // What the server would refuse, said on the field: a maximum not above its minimum, a zero
  // normal (the rows stay as typed).
  const mark = (kind, index, column, why) => {
    const row = $(`#cell-${kind === "box" ? "boxes" : "planes"} tbody`).rows[index];
    row.querySelectorAll("input")[column].setCustomValidity(why);
    row.classList.add("invalid");
  };
  boxes.forEach((b, i) => [0, 1, 2].forEach((axis) => {
    if (b[axis + 3] <= b[axis]) mark("box", i, axis + 3, `must be above ${CELL_COLUMNS.box[axis]}`);
  }));
  planes.forEach((p, i) => {
    if (p.slice(0, 3).every((v) => v === 0)) mark("plane", i, 0, "the normal (nx, ny, nz) cannot be zero");
  });
  return $("#cell-form").querySelector("input:invalid") ? null : { keep_out_boxes_m: boxes, cell_planes: planes };
}

/** Typed: the draft drawn in 3-D dashed, and said to be unsaved. */
function cellEdited() {
  state.cellDirty = true;
  const draft = cellDraft();
  if (draft) state.workspace?.showCell(draft, { draft: true });
  const boxes = draft?.keep_out_boxes_m.length;
  $("#cell-draft").textContent = draft
    ? `Not saved: ${boxes} box${boxes === 1 ? "" : "es"} and ${draft.cell_planes.length} plane${draft.cell_planes.length === 1 ? "" : "s"}, drawn dashed in the 3-D view. Save the cell to plan and run with it.`
    : `Not saved: ${$("#cell-form input:invalid")?.validationMessage || "a field is not valid"} (the field is marked in red).`;
}

async function reloadCell() {
  try {
    state.cell = await api("/cell");
  } catch (err) {
    if (err.status !== 409) throw err;
    state.cell = null; // unreadable: the form says so; a save repairs it
    state.cellRevision = err.detail?.revision ?? state.cellRevision;
  }
  if (state.cell) state.cellRevision = state.cell.revision;
}

function wireCell() {
  const form = $("#cell-form");
  form.addEventListener("input", cellEdited);
  const add = (kind, values) => {
    const body = $(`#cell-${kind === "box" ? "boxes" : "planes"} tbody`);
    body.append(cellRow(kind, body.rows.length + 1, values));
    cellEdited();
    body.rows[body.rows.length - 1].querySelector("input").focus();
  };
  // A new box in front of the arm, a new plane a wall 1 m behind it: the operator types over.
  $("#cell-add-box").addEventListener("click", () => add("box", [0.5, -0.1, 0, 0.6, 0.1, 0.1]));
  $("#cell-add-plane").addEventListener("click", () => add("plane", [1, 0, 0, -1]));
  $("#cell-box-at-pick").addEventListener("click", () => {
    const p = state.pickedBase;
    if (!p) return;
    const h = PICK_BOX_M / 2;
    add("box", [p.x - h, p.y - h, p.z - h, p.x + h, p.y + h, p.z + h]);
  });
  $("#cell-reload").addEventListener("click", async () => {
    if (state.cellDirty && !window.confirm("Discard the changes you typed? The saved cell stays as it is.")) return;
    clearMessage($(".message", form));
    await reloadCell();
    renderCell({ force: true });
  });
  const save = async (json, said) => {
    const box = $(".message", form);
    clearMessage(box);
    if (state.cellSaving) return;
    // One request at a time (a double click would send a second one from the same revision).
    state.cellSaving = true;
    for (const button of form.querySelectorAll("button")) button.disabled = true;
    try {
      state.cell = await (json ? api("/cell", { method: "PUT", json }) : api(`/cell?revision=${state.cellBase ?? 0}`, { method: "DELETE" }));
      state.cellRevision = state.cell.revision;
      renderCell({ force: true });
      box.textContent = said(state.cell);
      box.className = "message ok";
    } catch (err) {
      showError(box, err);
    } finally {
      state.cellSaving = false;
      renderCell();
    }
    if (state.session) await refresh();
  };
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const draft = cellDraft();
    if (!draft) return form.reportValidity();
    await save({ ...draft, revision: state.cellBase ?? 0 },
      (cell) => `Cell saved (revision ${cell.revision}): plans made in another cell are now outdated.`);
  });
  $("#cell-reset").addEventListener("click", () => {
    if (!window.confirm("Drop the cell edited in the pendant and go back to the server's start-up settings? It applies at once to every pendant, plan and run.")) return;
    save(null, (cell) => `Back to the start-up settings (revision ${cell.revision}).`);
  });
  // Another pendant's save shows here within a few seconds (a draft is kept, and said older).
  setInterval(async () => {
    if (document.hidden || !state.session || state.cellSaving) return;
    try {
      await reloadCell();
      renderCell();
    } catch {
      // the next refresh says what is wrong
    }
  }, 5000);
}

/** A form that sets something of the session: on submit, `send(form)` makes the request and
 * returns what to say; an error is shown as an instruction. One click, one request; the button
 * is held meanwhile, and the session is read again after. */
function setForm(form, send) {
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const box = $(".message", form);
    const button = $("button[type=submit]", form);
    clearMessage(box);
    if (!form.reportValidity()) return;
    button.disabled = true;
    try {
      box.textContent = await send(form);
    } catch (err) {
      showError(box, err);
    } finally {
      button.disabled = false;
      if (state.session) await refresh();
    }
  });
}

function wireCalibration() {
  // A stored calibration file: sent whole, read and checked by the server as the CLI reads it.
  setForm($("#calfile-form"), async (form) => {
    const file = form.elements.file.files[0];
    const data = new FormData();
    data.append("file", file, file.name);
    await api(`/sessions/${state.session.id}/calibration/file`, { method: "POST", form: data });
    return `Loaded ${file.name}.`;
  });
  // Another session's tracker -> base (the same cell, the tracker not moved).
  setForm($("#copycal-form"), async (form) => {
    const from = (state.sessions || []).find((o) => o.id === form.elements.from.value);
    if (!from) return "";
    await api(`/sessions/${state.session.id}/calibration`, { method: "PUT", json: { T_base_tracker: from.T_base_tracker } });
    return `Tracker → base of “${from.name}” set.`;
  });

  fitForm($("#pivot-form"), $("#pivot-summary"), (form) => {
    const data = new FormData();
    const file = form.elements.file.files[0];
    data.append("file", file, file.name);
    data.append("tolerance_m", String(Number(form.elements.tolerance_mm.value) / 1000));
    data.append("accept_poor_fit", form.elements.accept_poor_fit.checked ? "true" : "false");
    return api(`/sessions/${state.session.id}/calibration/pivot`, { method: "POST", form: data });
  }, (result, refused) => {
    if (refused) {
      return result.residual_rms_m == null ? []
        : [table([["residual", `${mm(result.residual_rms_m, 3)} RMS (tolerance ${mm(result.tolerance_m, 3)})`]])];
    }
    return [table([
      ["tip offset", result.tip_offset_m.map((v) => mm(v, 2)).join(", ")],
      ["residual", `${mm(result.residual_rms_m, 3)} RMS, ${mm(result.residual_max_m, 3)} max`],
      ["pen turned", `${result.rotation_spread_deg.toFixed(0)} deg`],
      ["samples", `${result.n_used} used, ${result.n_rejected} rejected, ${result.n_lost} lost`],
    ])];
  });

  fitForm($("#pairs-form"), $("#pairs-summary"), (form) => {
    const scale = form.elements.units.value === "mm" ? 1e-3 : 1;
    const body = {
      pairs: parsePairs(form.elements.pairs.value, scale),
      tolerance_m: Number(form.elements.tolerance_mm.value) / 1000,
      accept_poor_fit: form.elements.accept_poor_fit.checked,
    };
    return api(`/sessions/${state.session.id}/calibration/base`, { method: "POST", json: body });
  }, (fit) => (fit.residuals_m ? pairsTable(fit) : []));
}

// -- reconstruct: the parameters from the API's own schema ----------------------------------------

const RECONSTRUCTION_FIELDS = ["radius_m", "alpha", "beta", "degree", "method", "spacing_m", "use_scan", "registration", "use_touches"];
/** The plan's parameters on the form (the speed has its slider). */
const PLAN_FIELDS = ["robot", "orientation", "lead_deg", "tilt_deg", "smooth_m", "tcp_pose", "approach_m",
  "shoulder", "elbow", "wrist", "tool_radius_m", "clearance_m", "payload_kg", "return_to_start"];

function numberField(name, spec) {
  const input = el("input", { name, type: "number", step: "any" });
  const scale = DISPLAY_SCALES[name] ?? 1;
  if (spec.type === "integer") input.step = "1";
  if (spec.minimum !== undefined) input.min = inFormUnits(spec.minimum, scale);
  if (spec.maximum !== undefined) input.max = inFormUnits(spec.maximum, scale);
  if (spec.default !== undefined && spec.default !== null) input.value = inFormUnits(spec.default, scale);
  input.dataset.scale = scale;
  return input;
}

/** One input for a parameter of the API's schema, with its range and default. */
const DEG_PER_RAD = 180 / Math.PI;
/** Fields the form shows in other units than the API's SI: factor from the API's to the form's. */
const DISPLAY_SCALES = {
  tcp_pose: [1000, 1000, 1000, DEG_PER_RAD, DEG_PER_RAD, DEG_PER_RAD],
  radius_m: 1000, spacing_m: 1000, smooth_m: 1000, approach_m: 1000, tool_radius_m: 1000, clearance_m: 1000,
};
/** The parameters in the operator's words and units (the API keeps its SI names; a refusal
 * from the server names the API's field, given beside the label as "(api: name)"). */
const DISPLAY_NAMES = {
  tcp_pose: "TCP: x, y, z (mm), rx, ry, rz (deg)",
  radius_m: "neighbourhood radius (mm)", alpha: "trace weight α", beta: "correction amount β",
  degree: "fit degree", method: "method", spacing_m: "point spacing (mm)", use_scan: "use the scan",
  registration: "align the scan to the trace", use_touches: "use the touches",
  robot: "robot model", orientation: "tool axis from", lead_deg: "lead (°)", tilt_deg: "tilt (°)",
  smooth_m: "axis smoothing (mm)", approach_m: "approach height (mm)", shoulder: "shoulder",
  elbow: "elbow", wrist: "wrist", tool_radius_m: "tool body radius (mm)", clearance_m: "clearance (mm)",
  payload_kg: "payload (kg)", return_to_start: "return to the start",
};
/** What each field does, in those units; a checkbox's hint says what its current state does. */
const DISPLAY_HINTS = {
  tcp_pose: "the tool centre point in the flange frame, as on UR's pendant",
  radius_m: "how far around each point the trace and the scan are fitted; 0.5 to 200 mm",
  alpha: "how much the trace counts against the scan: 1 the trace only, 0 the scan only; auto: per point",
  beta: "how much of the correction is applied: 0 none, 1 all of it",
  degree: "degree of the curves fitted along the path: 1 (straight) to 5",
  method: "anchored: ours, held to the scan's position; paper: the paper's equation (4)",
  spacing_m: "distance between the points of the result; 0.1 to 10 mm",
  use_scan: { on: "ticked: the scan corrects the trace", off: "not ticked: the trace alone, smoothed (the scan is not used)" },
  registration: { on: "ticked: the scan is aligned to the trace first (ICP)", off: "not ticked: the calibrated frames are trusted as they are" },
  use_touches: { on: "ticked: the touched points place the scan", off: "not ticked: the trace places the scan, even with touches" },
  robot: "the UR model the plan is for",
  lead_deg: "the tool leaning along the travel; -60 to 60°",
  tilt_deg: "the tool leaning across the travel; -60 to 60°",
  smooth_m: "length over which the tool's axis is smoothed along the path (0: off); 0 to 100 mm",
  approach_m: "approach and retract distance along the tool's axis; 5 to 500 mm",
  tool_radius_m: "radius of the tool's body for the collision check; 0.5 to 200 mm",
  clearance_m: "distance the arm and the tool keep from obstacles; 0 to 100 mm",
  payload_kg: "mass set before the motion; empty: the controller's installation keeps its own",
  return_to_start: { on: "ticked: the arm moves back to where it started at the end", off: "not ticked: the arm stays above the path's end" },
};
/** A number in the form's units (rounded: 0.008 m is "8", not "8.000000000000002"). */
const inFormUnits = (value, scale) => +(value * scale).toPrecision(12);

function paramInput(name, spec) {
  if (spec.type === "boolean") {
    const input = el("input", { name, type: "checkbox" });
    input.checked = spec.default !== false;
    return input;
  }
  if (spec.enum) {
    const input = el("select", { name }, ...spec.enum.map((v) => el("option", { value: v, text: v })));
    input.value = spec.default;
    return input;
  }
  if (name === "robot") {
    // The models the API names in its description (the kinematics it knows).
    const models = (spec.description.match(/\(([^)]*)\)/)?.[1] || spec.default).split(/,\s*/);
    const input = el("select", { name }, ...models.map((v) => el("option", { value: v, text: v })));
    input.value = state.robot?.robot || spec.default;
    return input;
  }
  if (spec.prefixItems) {
    // x, y, z (or six numbers): typed on one line, each checked against its range. Shown in the
    // operator's units where the field has them (the TCP in mm and degrees, as on UR's pendant).
    const input = el("input", { name, type: "text", inputmode: "decimal" });
    const scales = DISPLAY_SCALES[name] || spec.prefixItems.map(() => 1);
    input.value = (spec.default || []).map((v, i) => +(v * scales[i]).toFixed(6)).join(", ");
    input.dataset.items = JSON.stringify(spec.prefixItems.map((s) => [s.minimum, s.maximum]));
    input.dataset.scales = JSON.stringify(scales);
    return input;
  }
  if (spec.anyOf && spec.anyOf.some((s) => s.type === "null")) {
    // A number that may be left out (empty: not given, e.g. the payload: the controller's stays).
    const number = spec.anyOf.find((s) => s.type === "number") || {};
    const input = numberField(name, number);
    input.value = spec.default == null ? "" : inFormUnits(spec.default, DISPLAY_SCALES[name] ?? 1);
    input.placeholder = "not set";
    return input;
  }
  if (spec.anyOf) {
    // A number or a word ("auto"): typed as text, checked against both.
    const number = spec.anyOf.find((s) => s.type === "number");
    const word = spec.anyOf.find((s) => s.const);
    const input = el("input", { name, type: "text", inputmode: "decimal" });
    input.value = spec.default;
    input.dataset.word = word?.const || "";
    input.dataset.min = number?.minimum ?? "";
    input.dataset.max = number?.maximum ?? "";
    input.pattern = `${word ? `${word.const}|` : ""}[0-9]*[.,]?[0-9]+`;
    return input;
  }
  return numberField(name, spec);
}

/** The parameters `fields` of the API's `schemaName` as labelled inputs in `box`. */
function buildParams(schema, schemaName, fields, box, prefix) {
  const props = schema.components.schemas[schemaName].properties;
  box.replaceChildren();
  for (const name of fields) {
    const spec = props[name];
    if (!spec) continue;
    const input = paramInput(name, spec);
    input.id = `${prefix}-${name}`;
    const nullable = spec.anyOf?.some((s) => s.type === "null");
    input.dataset.kind = spec.prefixItems ? "tuple" : nullable ? "optional-number" : spec.type || (spec.anyOf ? "mixed" : "string");
    const words = DISPLAY_HINTS[name];
    const hint = el("span", { class: "hint" });
    const describe = () => {
      hint.textContent = typeof words === "object" ? (input.checked ? words.on : words.off) : words || spec.description || "";
    };
    describe();
    if (typeof words === "object") input.addEventListener("change", describe);
    const label = el("span", { class: "name", text: DISPLAY_NAMES[name] || name });
    if (DISPLAY_NAMES[name]) label.title = `API field: ${name}`;
    box.append(el("label", { for: input.id }, label, input, hint));
  }
}

function buildReconstructForm(schema) {
  buildParams(schema, "ReconstructionCreate", RECONSTRUCTION_FIELDS, $("#reconstruct-params"), "recon");
  buildParams(schema, "TrajectoryCreate", PLAN_FIELDS, $("#plan-params"), "plan");
}

/** The request body of a parameter form; throws {code, message} naming a bad tuple. */
function paramsBody(form, fields) {
  const body = {};
  for (const name of fields) {
    const input = form.elements[name];
    if (!input) continue;
    const kind = input.dataset.kind;
    const scale = Number(input.dataset.scale || 1);
    if (input.type === "checkbox") body[name] = input.checked;
    else if (kind === "integer") body[name] = Number(input.value);
    else if (kind === "number") body[name] = Number(input.value) / scale;
    else if (kind === "optional-number") { if (input.value.trim() !== "") body[name] = Number(input.value) / scale; }
    // A comma decimal ("0,8") is the same number: many operators' keyboards type it.
    else if (kind === "mixed") body[name] = input.value === input.dataset.word ? input.value : Number(input.value.replace(",", "."));
    else if (kind === "tuple") {
      const ranges = JSON.parse(input.dataset.items);
      const scales = JSON.parse(input.dataset.scales || "null") || ranges.map(() => 1);
      const values = input.value.split(/[\s,;]+/).filter(Boolean).map((v, i) => Number(v) / (scales[i] ?? 1));
      const bad = values.length !== ranges.length || values.some((v, i) => !Number.isFinite(v) || v < ranges[i][0] || v > ranges[i][1]);
      if (bad) {
        const shown = ranges.map(([lo, hi], i) => `[${+(lo * scales[i]).toFixed(1)}, ${+(hi * scales[i]).toFixed(1)}]`);
        throw { code: "invalid_request", message: `${DISPLAY_NAMES[name] || name}: give ${ranges.length} numbers separated by commas, in ${[...new Set(shown)].join(" / ")} (you typed “${input.value}”)` };
      }
      body[name] = values;
    } else body[name] = input.value;
  }
  return body;
}

const reconstructBody = (form) => paramsBody(form, RECONSTRUCTION_FIELDS);

// -- plan -----------------------------------------------------------------------------------------

function updatePlanSpeed() {
  const slider = $("#plan-speed");
  const specMax = state.schema?.components.schemas.TrajectoryCreate.properties.speed_m_s.maximum ?? 2;
  const cap = Math.min(specMax, state.robot?.max_speed_m_s ?? specMax);
  slider.max = cap;
  if (Number(slider.value) > cap) slider.value = cap;
  const field = $("#plan-speed-mm");
  field.max = Math.round(cap * 1000);
  // The field follows the slider, unless the operator is typing in it.
  if (document.activeElement !== field) field.value = Math.round(Number(slider.value) * 1000);
  $("#plan-speed-cap").textContent = `at most ${mmps(cap)} (the server's cap)`;
}

// -- run on the arm: behind a confirmation ---------------------------------------------------------

/** The mount a plan was made for, in words, and whether it is this cell's. */
function mountText(up, robot) {
  if (!up) return "–";
  const words = up[2] > 0.99 ? "floor" : up[2] < -0.99 ? "ceiling" : Math.abs(up[2]) < 0.01 ? "wall" : "tilted";
  const here = robot?.mount_up;
  const same = here && here.every((v, i) => Math.abs(v - up[i]) < 1e-6);
  return `${words} (up ${up.map((v) => v.toFixed(2)).join(", ")} in the base frame)${here && !same ? " — NOT this cell's mount" : ""}`;
}

/** The TCP (flange frame) as an operator checks it on PolyScope: mm and degrees. */
function tcpText(pose) {
  if (!pose) return "–";
  const [x, y, z, rx, ry, rz] = pose;
  const deg = (v) => (v * 180 / Math.PI).toFixed(1);
  return `x ${(x * 1000).toFixed(1)}, y ${(y * 1000).toFixed(1)}, z ${(z * 1000).toFixed(1)} mm; rx ${deg(rx)}, ry ${deg(ry)}, rz ${deg(rz)} deg`;
}

/** The payload the arm will run with: the plan's, or (none set) the controller's, read now. */
function payloadText(sm, robot) {
  if (sm.payload_kg != null) {
    const cog = (sm.payload_cog_m || [0, 0, 0]).map((v) => (v * 1000).toFixed(0)).join(", ");
    return `${sm.payload_kg} kg set before motion (centre of gravity ${cog} mm)`;
  }
  if (robot?.payload_kg != null) return `not set by the plan: the controller's ${robot.payload_kg} kg stays`;
  return "not set by the plan: the controller's own stays";
}

/** A phase's duration and, where the plan says, its fastest TCP speed. */
function phaseText(sm, phase, duration) {
  const fastest = sm.phase_max_tcp_speed_m_s?.[phase];
  return fastest == null ? seconds(duration) : `${seconds(duration)}, TCP up to ${mmps(fastest)}`;
}

/** What the plan was made from, named with checksums and times, as approved in the dialog. */
function approvedInputs(traj) {
  const rec = state.reconstructions.find((r) => r.id === traj.inputs.reconstruction_id);
  const named = (list, id) => {
    const row = list.find((a) => a.id === id);
    return row ? `${row.source_name || row.id} (${row.id}, sha256 ${row.sha256.slice(0, 12)}…, ${new Date(row.created_at).toLocaleString()})` : id || "none";
  };
  const recordings = rec ? (rec.inputs.recording_ids || [rec.inputs.recording_id]) : [];
  const sm = traj.summary;
  const T = traj.params?.T_base_tracker;
  // The session's calibration is the plan's when they agree (then where it came from, and when).
  const base = !T ? "–" : `${transformText(T)}${!state.session.T_base_tracker ? "" : otherCalibration(traj)
    ? " — NOT the session's calibration now" : `, the session's${calibrationSource(state.session, "T_base_tracker")}`}`;
  const registered = rec?.summary.T_scan_tracker;
  const touches = rec?.inputs.touches_id ? `, placed by touches ${named(state.touches || [], rec.inputs.touches_id)}` : "";
  const armModel = sm.calibration
    ? `${sm.kinematics || sm.robot}, calibration ${sm.calibration.source || "(unnamed)"}` : sm.kinematics || `${sm.robot}, UR's nominal model`;
  return [
    ["plan file", `${traj.id}, sha256 ${traj.sha256.slice(0, 12)}…, ${new Date(traj.created_at).toLocaleString()}`],
    ["trace", recordings.map((id) => named(state.recordings, id)).join("; ") || "–"],
    ["scan", named(state.scans, rec?.inputs.scan_id)],
    ["tracker → base", base],
    ["tracker → scan", registered ? `${transformText(registered)} (${rec.summary.registration
      ? `registered by ${rec.id}, ${rec.summary.registration.target}${touches}` : "as given, not registered"})` : "–"],
    ["arm kinematics", armModel],
  ];
}

/** What a move to a plan's start does, in words: a joint move, after a straight retract off
 * the workpiece when the arm stood with the tool on it. */
function moveWords(sm) {
  const retract = sm.phase_durations_s?.retract != null;
  return retract ? `straight off the workpiece, ${mm(sm.approach_m, 0)} back along the tool's axis, then a joint move` : "a joint move";
}

/** A move's fastest TCP speed, of every phase it has, named. */
function moveFastest(sm) {
  const speeds = Object.entries(sm.phase_max_tcp_speed_m_s || {});
  return speeds.length ? speeds.map(([phase, v]) => `${mmps(v)} (${phase})`).join(", ") : "–";
}

/** What a real-arm request says of an outdated plan taken on purpose (nothing for a current one:
 * the server then refuses a plan that became outdated meanwhile). */
const acceptance = (traj) => (outdated(traj).length && acceptedOutdated(traj) ? { accept_outdated: true } : {});

function confirmRun(traj) {
  const sm = traj.summary;
  const robot = state.robot;
  const degrees = (q) => `${q.map((v) => (v * 180 / Math.PI).toFixed(1)).join(", ")}°`;
  const arm = ["robot", `${robot.real_arm ? "REAL ARM" : "SIM (no real arm configured)"} ${sm.robot}${robot.host ? ` @ ${robot.host}` : ""}`];
  const move = isMove(traj);
  // An outdated plan (or a move to its start) runs only when taken on purpose: said first.
  const taken = outdated(traj).length
    ? [["OUTDATED, taken on purpose", `made before ${outdated(traj).join("; ")}`, "warning"]] : [];
  const rows = move ? [
    arm,
    ["motion", `${moveWords(sm)} to the start of plan ${sm.move_to_start_of}`],
    ["mode", mode()],
    ["duration", seconds(sm.duration_s)],
    ["fastest TCP", moveFastest(sm)],
    ["smallest clearance (arm, tool, cell, scan)", mm(sm.min_clearance_m, 1)],
    ["from (joints)", degrees(sm.start_q_rad)],
    ["to (joints)", sm.goal_q_rad ? degrees(sm.goal_q_rad) : "–"],
    ["TCP", tcpText(sm.tcp_pose)],
    ["payload", payloadText(sm, robot)],
    ["move file", `${traj.id}, sha256 ${traj.sha256.slice(0, 12)}…, ${new Date(traj.created_at).toLocaleString()}`],
  ] : [
    arm,
    ["speed", mmps(sm.requested_speed_m_s)],
    ["mode", mode()],
    ["duration", seconds(sm.duration_s)],
    ...Object.entries(sm.phase_durations_s).map(([phase, s]) => [`  ${phase}`, phaseText(sm, phase, s)]),
    ["starts from", startFrom(sm.start_from)],
    ["approach", `${mm(sm.approach_m, 0)} along the tool axis`],
    ["configuration", sm.configuration || "–"],
    ["mount", mountText(traj.params?.mount_up, robot)],
    ["TCP", tcpText(sm.tcp_pose)],
    ["payload", payloadText(sm, robot)],
    ...approvedInputs(traj),
  ];
  return askDialog(
    move ? "Move the arm to the plan's start?" : "Run on the arm?",
    move ? "Confirm: move to start" : "Confirm: run on arm",
    [...taken, ...rows],
  );
}

const MOVES_WARNING = "The arm will move. Keep clear of it; Stop (or Esc) stops it.";

/** The confirmation dialog: a title, rows of what will happen, a warning, Cancel focused. */
function askDialog(title, button, rows, warning = MOVES_WARNING) {
  $("#confirm-title").textContent = title;
  $("#confirm-warning").textContent = warning;
  $("#confirm-run").textContent = button;
  // A row's optional third item is its class ("warning": what the operator must not miss).
  $("#confirm-table").replaceChildren(...rows.map(([k, v, kind]) =>
    el("tr", kind ? { class: kind } : {}, el("th", { text: k }), el("td", { text: v }))));
  const dialog = $("#confirm-dialog");
  dialog.returnValue = "";
  dialog.showModal();
  // From its top (what runs where, first), with Cancel focused: Enter never confirms.
  $("#confirm-dialog button[value=cancel]").focus({ preventScroll: true });
  dialog.scrollTop = 0;
  return new Promise((resolve) => {
    dialog.addEventListener("close", () => resolve(dialog.returnValue === "confirm"), { once: true });
  });
}

// -- wiring ---------------------------------------------------------------------------------------

// Stop first: whatever fails later in the start-up, Stop and Escape work.
function wireStop() {
  $("#stop").addEventListener("click", stop);
  $("#pause").addEventListener("click", pauseRun);
  $("#resume").addEventListener("click", resumeRun);
  $("#run-speed-slider").addEventListener("input", (event) => { $("#run-speed-value").value = event.target.value; });
  $("#run-speed-slider").addEventListener("change", (event) => sendRunSpeed(event.target));
  $("#run-speed-value").addEventListener("change", (event) => sendRunSpeed(event.target));
  $("#run-speed-value").addEventListener("keydown", (event) => {
    if (event.key === "Enter") event.target.blur();  // sends it (change), off the field
  });
  document.addEventListener("keydown", (event) => {
    if (event.key === "Escape" && canMove()) {
      event.preventDefault();
      stop();
    }
  });
}

function wire() {
  $("#new-session").addEventListener("submit", async (event) => {
    event.preventDefault();
    const name = $("#new-session-name").value.trim() || "session";
    const created = await api("/sessions", { method: "POST", json: { name } });
    await loadSessions();
    await openSession(created.id);
  });
  state.capture = wireCapture({
    session: () => state.session,
    recordings: () => state.recordings,
    workspace: () => state.workspace,
    showError,
    remember,
    recall,
    refresh,
  });
  upload("recording", $("#recording-form"));
  upload("touches", $("#touches-form"));
  upload("scan", $("#scan-form"));
  wireCalibration();
  wireCell();

  $("#reconstruct-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const form = event.currentTarget;
    if (!form.reportValidity()) return;
    const body = reconstructBody(form);
    runJob("reconstruct", form, () =>
      api(`/sessions/${state.session.id}/reconstructions`, { method: "POST", json: body }));
  });

  $("#plan-speed").addEventListener("input", updatePlanSpeed);
  // Typed in mm/s: the slider follows. Out of range it is left as typed (never replaced by the
  // slider's value): the form refuses it when Plan is pressed, saying the range.
  $("#plan-speed-mm").addEventListener("input", (event) => {
    const value = Number(event.target.value) / 1000;
    if (event.target.checkValidity() && Number.isFinite(value) && value > 0) $("#plan-speed").value = value;
  });
  $("#plan-speed-mm").addEventListener("change", (event) => {
    if (event.target.checkValidity()) updatePlanSpeed();
  });
  $("#plan-params").addEventListener("change", (event) => {
    if (event.target.name === "robot") event.target.dataset.chosen = "1";
  });
  $("#plan-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const form = event.currentTarget;
    if (!form.reportValidity()) return;
    let body;
    try {
      body = { reconstruction_id: reconstruction().id, ...paramsBody(form, PLAN_FIELDS), speed_m_s: Number($("#plan-speed-mm").value) / 1000 };
    } catch (err) {
      return showError($(".message", form), err);
    }
    runJob("plan", form, () => api(`/sessions/${state.session.id}/trajectories`, { method: "POST", json: body }),
      (finished) => {
        if (finished.state === "succeeded") Object.assign(state, { pick: null, pickView: null }); // the new plan is used
      });
  });

  // The move to the plan's start: planned, dry-run and approved as a plan is, then run.
  $("#move-plan-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const traj = trajectory();
    if (!traj) return;
    runJob("move-plan", event.currentTarget, () =>
      api(`/sessions/${state.session.id}/trajectories/${traj.id}/move-to-start`, { method: "POST" }));
  });
  $("#move-dryrun-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const move = moveTo(trajectory());
    if (!move) return;
    const body = { trajectory_id: move.id, backend: "sim", mode: mode() };
    runJob("move-dryrun", event.currentTarget, () =>
      api(`/sessions/${state.session.id}/executions`, { method: "POST", json: body }));
  });
  $("#move-run-form").addEventListener("submit", async (event) => {
    event.preventDefault();
    const form = event.currentTarget;
    const move = moveTo(trajectory());
    if (!move || !passedHere(dryRun(move)) || state.busy) return;
    if (!(await confirmRun(move))) return;
    const body = { trajectory_id: move.id, backend: "ur_rtde", mode: mode(), confirm: true, approved_sha256: move.sha256,
      ...acceptance(move) };
    runJob("move-run", form, async () => {
      const job = await api(`/sessions/${state.session.id}/executions`, { method: "POST", json: body });
      state.moving = { executionId: job.params.execution_id, jobId: job.id };
      updateStop();
      renderSteps();
      return job;
    }, (finished) => {
      if (finished.state !== "succeeded") return;
      // At the start: what the stopped run said no longer holds.
      const box = $("#run-form .message");
      clearMessage(box);
      box.textContent = "The arm stands at the plan's start: the plan can run.";
      box.className = "message ok";
      $("#run-form .job-state").textContent = "";
    });
  });

  $("#exec-mode").addEventListener("change", () => { renderSteps(); showWorkspace(); });
  $("#dryrun-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const body = { trajectory_id: trajectory().id, backend: "sim", mode: mode() };
    // A dry run moves no arm (and runs to its end): no Stop for it.
    runJob("dryrun", event.currentTarget, () =>
      api(`/sessions/${state.session.id}/executions`, { method: "POST", json: body }));
  });

  $("#run-form").addEventListener("submit", async (event) => {
    event.preventDefault();
    const form = event.currentTarget;
    const traj = trajectory();
    const dry = dryRun(traj);
    if (!traj || !passedHere(dry) || state.busy) return;
    if (!(await confirmRun(traj))) return;
    // The plan's checksum as shown in the confirmation: the server runs only that file.
    const body = { trajectory_id: traj.id, backend: "ur_rtde", mode: mode(), confirm: true, approved_sha256: traj.sha256,
      ...acceptance(traj) };
    runJob("run", form, async () => {
      const job = await api(`/sessions/${state.session.id}/executions`, { method: "POST", json: body });
      state.moving = { executionId: job.params.execution_id, jobId: job.id };
      // The arm's state may have come first (it owns the arm already): say "moving" now.
      updateStop();
      renderSteps();
      return job;
    });
  });

  const contrast = $("#contrast");
  const theme = (on) => {
    document.body.classList.toggle("contrast", on);
    remember("localStorage", "teachpath.contrast", on ? "1" : null);
  };
  contrast.checked = recall("localStorage", "teachpath.contrast") === "1";
  theme(contrast.checked);
  contrast.addEventListener("change", () => theme(contrast.checked));
  $("#pair-screen").addEventListener("click", pairScreen);
  $("#plan-pick").addEventListener("change", (event) => {
    state.pickView = event.target.value;
    renderSteps();
  });
  $("#plan-use").addEventListener("click", takeViewedPlan);
  $("#unlock").addEventListener("click", async () => {
    try {
      showRobot(await api("/robot/unlock", { method: "POST" }));
    } catch (err) {
      banner(`${explain(err).instruction} ${explain(err).message}`);
    }
  });
}

/** No token, or a wrong one: say so, and offer to sign in (a second screen has no start-up URL)
 * with the pairing code or the token. The safety bar and Stop work meanwhile (no token needed). */
function askToken(instruction) {
  banner(instruction);
  document.body.classList.add("signed-out");
  const form = $("#sign-in");
  if (!form.hidden) return;
  form.hidden = false;
  const message = $("#sign-in-message");
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const code = $("#sign-in-code").value.trim();
    const token = $("#sign-in-token").value.trim();
    message.textContent = "";
    if (token) return signIn(token);
    if (!/^[0-9]{6}$/.test(code)) {
      message.textContent = "Type the six digits of the pairing code, or paste the access token.";
      return;
    }
    try {
      const answer = await api("/pairing", { method: "POST", json: { code } });
      signIn(answer.token);
    } catch (err) {
      message.textContent = explain(err).message;
      $("#sign-in-code").select();
    }
  });
  $("#sign-in-code").focus();
}

/** "Pair a screen": a new one-time code for a tablet or a second browser to sign in with. */
async function pairScreen() {
  const out = $("#pairing-code");
  try {
    const { code, expires_in_s: expiresInS } = await api("/pairing/code", { method: "POST" });
    const until = new Date(Date.now() + expiresInS * 1000);
    const time = until.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit" });
    out.replaceChildren(
      el("b", { class: "code", text: code }),
      el("span", { text: `type it on the other screen before ${time} (it works once)` }),
    );
    out.dataset.code = code;
  } catch (err) {
    out.textContent = `No code: ${explain(err).message}`;
  }
}

async function main() {
  wireStop();
  setToken(takeToken());
  wire();
  followRobot();
  try {
    state.schema = await api("/openapi.json");
    await reloadCell();
    buildReconstructForm(state.schema);
    updatePlanSpeed();
    await loadSessions();
    const last = recall("sessionStorage", SESSION_KEY);
    if (last && document.querySelector(`#session-list li[data-session="${CSS.escape(last)}"]`)) {
      await openSession(last);
    }
  } catch (err) {
    const { instruction, message } = explain(err);
    if (err.status === 401) askToken(instruction);
    else banner(`${instruction} (${message})`);
  }
  try {
    const [{ Workspace }, { Timeline }] = await Promise.all([import("./workspace.js"), import("./timeline.js")]);
    let timeline = null;
    state.workspace = new Workspace($("#workspace"), $("#layers"), $("#legend"), {
      onPlan: (preview, review, execution, trajectoryId) => {
        timeline.load(preview, trajectoryId);
        showReview(review, execution);
      },
      onPick: (picked) => {
        showPick(picked);
        state.pickedBase = picked && state.workspace.inBaseFrame ? picked.point : null;
        renderCell();
        if (picked?.time_s != null) timeline.seek(picked.time_s);
      },
    });
    timeline = new Timeline($("#timeline"), (joints) => state.workspace.pose(joints));
    if (state.robot?.reachable) state.workspace.showLiveArm(state.robot.joints_m);
    if (state.cell) state.workspace.showCell(state.cell);
    if (state.session) await refresh();
  } catch (err) {
    $("#workspace-note").textContent = `The 3-D view is unavailable: ${err.message}`;
  }
  document.body.dataset.ready = "true";
}

main();
export { state, FINISHED };
