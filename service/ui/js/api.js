// The REST API: the token, JSON and multipart calls, server-sent events read with fetch()
// (EventSource cannot send the Authorization header), jobs followed by their event stream.

const TOKEN_KEY = "teachpath.token";

/** The token from the start-up URL (?token=...), kept in sessionStorage and removed from the
 * address bar and the history; afterwards from sessionStorage. */
export function takeToken() {
  const url = new URL(window.location.href);
  const fromUrl = url.searchParams.get("token");
  let stored = null;
  try {
    if (fromUrl) sessionStorage.setItem(TOKEN_KEY, fromUrl);
    stored = sessionStorage.getItem(TOKEN_KEY);
  } catch {
    // Storage refused (site data blocked): the token lives in this page only.
  }
  if (fromUrl) {
    url.searchParams.delete("token");
    history.replaceState(history.state, "", url.pathname + url.search + url.hash);
  }
  return fromUrl || stored || "";
}

/** Sign in with a pasted token: through the start-up URL's path, so it is kept (and taken out
 * of the address bar) exactly as the printed URL's is. */
export function signIn(value) {
  const url = new URL(window.location.href);
  url.searchParams.set("token", value.trim());
  window.location.replace(url.href);
}

let token = "";
export const setToken = (value) => { token = value; };
const auth = () => ({ Authorization: `Bearer ${token}` });

/** An error answer of the API: {code, message, detail} with its HTTP status. */
export class ApiError extends Error {
  constructor(status, body) {
    super(body.message || `HTTP ${status}`);
    this.status = status;
    this.code = body.code || `http_${status}`;
    this.detail = body.detail ?? null;
  }
}

/** One API call. `json`: a body sent as JSON; `form`: a FormData sent as multipart. */
export async function api(path, { method = "GET", json, form, signal, raw = false } = {}) {
  const headers = auth();
  let body;
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  } else if (form !== undefined) {
    body = form;
  }
  let response;
  try {
    response = await fetch(path, { method, headers, body, signal });
  } catch (err) {
    if (err.name === "AbortError") throw err;
    throw new ApiError(0, { code: "unreachable", message: "the server cannot be reached" });
  }
  if (!response.ok) {
    let answer;
    try {
      answer = await response.json();
    } catch {
      answer = { code: `http_${response.status}`, message: response.statusText };
    }
    throw new ApiError(response.status, answer);
  }
  if (raw) return response;
  if (response.status === 204) return null;
  const type = response.headers.get("content-type") || "";
  return type.includes("json") ? response.json() : response.text();
}

/** Server-sent events of `path`, as {event, data} with data parsed as JSON. */
export async function* events(path, signal) {
  const response = await fetch(path, { headers: auth(), signal });
  if (!response.ok) {
    let answer = {};
    try { answer = await response.json(); } catch { /* not JSON */ }
    throw new ApiError(response.status, answer);
  }
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  try {
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return;
      buffer += value.replaceAll("\r\n", "\n");
      let end;
      while ((end = buffer.indexOf("\n\n")) >= 0) {
        const block = buffer.slice(0, end);
        buffer = buffer.slice(end + 2);
        let event = "message";
        const data = [];
        for (const line of block.split("\n")) {
          if (line.startsWith("event:")) event = line.slice(6).trim();
          else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
        }
        if (data.length) yield { event, data: JSON.parse(data.join("\n")) };
      }
    }
  } finally {
    reader.cancel().catch(() => {});
  }
}

export const FINISHED = ["succeeded", "failed", "cancelled"];

/** Follow a job to its end through GET /jobs/{id}/events (then, if the stream broke, by GET
 * /jobs/{id}); never sends the request that started it again. */
export async function followJob(job, onUpdate, signal) {
  onUpdate(job);
  try {
    for await (const { data } of events(`/jobs/${job.id}/events`, signal)) {
      job = data;
      onUpdate(job);
    }
  } catch (err) {
    if (err.name === "AbortError") throw err;
  }
  while (!FINISHED.includes(job.state)) {
    await new Promise((resolve) => setTimeout(resolve, 500));
    job = await api(`/jobs/${job.id}`, { signal });
    onUpdate(job);
  }
  return job;
}

/** What the operator does about each refusal or error code. */
export const INSTRUCTIONS = {
  confirmation_required: "Confirm the run in the dialog: the arm moves only after you confirm.",
  dry_run_required:
    "Dry-run this trajectory in the same mode first (press “Dry run”) and wait for it to pass.",
  speed_cap: "The plan is faster than the server's speed cap: plan again at a lower speed.",
  arm_busy: "Another execution owns the arm: wait until it ends, or stop it.",
  start_moved:
    "The arm is no longer where the plan starts: move it there (Move to the plan’s start, in the Run step), or plan again from where it stands.",
  protective_stop:
    "The arm is in a protective stop: remove its cause, then press Unlock in the safety bar.",
  emergency_stop:
    "The emergency stop is pressed: release it at the robot, power on and release the brakes.",
  remote_control_off: "The arm is in local control: switch the UR pendant to Remote Control.",
  robot_unavailable: "The arm's state cannot be read: check its power and network cable.",
  robot_connection_lost: "The connection to the arm was lost: check its network cable.",
  no_robot:
    "No real arm is configured on this server (SIM only): start the server with " +
    "TEACHPATH_UR_HOST set to run on an arm.",
  trajectory_mismatch: "The plan is for another robot model: plan again for the configured arm.",
  trajectory_unreadable: "The plan's record cannot be read: plan again.",
  real_arm_refused: "The server refused to move the arm: read its message below.",
  stopped: "The motion was stopped.",
  cancelled:
    "Stopped at your request: the arm stands where it stopped. Check the cell before you run " +
    "again: the plan runs from its start (Move to the plan’s start, in the Run step, takes the " +
    "arm back there).",
  dry_run_stopped: "The dry run was stopped: nothing moved and it did not pass. Run it again " +
    "to check the plan before the arm runs it.",
  invalid_file: "The file could not be read: check its format and units, then upload it again.",
  unknown_format: "The file's format is not known: choose the format in the list.",
  upload_too_large: "The file is larger than the server accepts.",
  invalid_request: "A value is out of range: correct it and submit again.",
  unauthorized:
    "This screen is not signed in (or its token is wrong): type a pairing code or paste the " +
    "access token below (or open the URL the server printed).",
  pairing_failed: "The pairing code was not accepted: ask for a new one with “Pair a screen”.",
  unreachable: "The server cannot be reached: is it running?",
  collision: "The motion would collide: change the plan's options (configuration, start).",
  infeasible_trajectory: "The arm cannot follow this path: change the plan's options.",
  registration_failed: "The trace could not be matched to the scan: check the calibration.",
  no_overlap: "The trace and the scan do not overlap: check the calibration and the units.",
  units_mismatch:
    "A file’s size says its numbers are in another unit (or it is not of a workpiece): pick " +
    "its Units (m or mm) as the message below says, and upload it again.",
  cell_changed:
    "Another pendant saved the cell since you started editing: press “Discard changes” to see " +
    "theirs, then edit again.",
  cell_unreadable:
    "The saved cell cannot be read: set its boxes and planes again (Calibration, Cell) and save.",
  arm_running: "The arm is running: edit the cell once the run has ended (or press Stop).",
  at_start: "The arm already stands where the plan starts: dry-run and run the plan.",
  arm_outside_limits: "The arm stands outside its joint limits: jog it back on the UR pendant.",
  outdated_inputs:
    "The plan is outdated (its inputs or the cell changed): plan again, or pick it on purpose.",
  not_streamed:
    "This run is a movePath, timed by the controller: its speed is fixed here. Use the UR " +
    "pendant's speed slider, or Stop.",
  not_moving: "The run has not started to move yet: there is nothing to pause (Stop cancels it).",
  not_running: "The run has ended: there is nothing to change.",
  bad_speed: "Set the run speed between 5 and 100 % of the plan's speed.",
  not_confirmed: "Confirm the resume in the dialog: the arm moves only after you confirm.",
  approval_mismatch:
    "The plan on the server is not the one you approved: reload the page and approve it again.",
  poor_fit:
    "The fit is worse than its tolerance and was not stored: measure again (touch the points " +
    "again, pivot again), or tick “store it even if the fit is poor”.",
};

/** The instruction for an error, and the server's own message. */
export function explain(err) {
  const code = err.code || "error";
  return { code, instruction: INSTRUCTIONS[code] || "", message: err.message || String(err) };
}
