// The dashboard: one WebSocket to /api speaking the daemon's JSON-RPC 2.0 (docs/api.md).
// No framework and no build step: state comes in as notifications and is drawn as it comes.
"use strict";

const $ = (id) => document.getElementById(id);
const fmt = (v, digits = 3) => (typeof v === "number" ? v.toFixed(digits) : "–");

// --- JSON-RPC over the WebSocket ------------------------------------------------

class Rpc {
  constructor(onNotify, onState) {
    this.onNotify = onNotify;
    this.onState = onState;
    this.next = 1;
    this.waiting = new Map();
    this.delay = 500;
    this.open();
  }

  open() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    this.ws = new WebSocket(`${scheme}://${location.host}/api`);
    this.ws.onopen = () => { this.delay = 500; this.onState(true); };
    this.ws.onmessage = (event) => this.receive(JSON.parse(event.data));
    this.ws.onclose = () => {
      for (const { reject } of this.waiting.values()) reject(new Error("disconnected"));
      this.waiting.clear();
      this.onState(false);
      // A revoked token or a restarted daemon ends the session: back to the login page.
      fetch("/session").then((r) => { if (r.status === 401) location.replace("/login"); }, () => {});
      setTimeout(() => this.open(), this.delay);
      this.delay = Math.min(this.delay * 2, 10000);
    };
  }

  receive(message) {
    if (Array.isArray(message)) { message.forEach((m) => this.receive(m)); return; }
    if (message.id !== undefined && this.waiting.has(message.id)) {
      const { resolve, reject } = this.waiting.get(message.id);
      this.waiting.delete(message.id);
      if (message.error) reject(Object.assign(new Error(message.error.message), message.error));
      else resolve(message.result);
    } else if (message.method) {
      this.onNotify(message.method, message.params);
    }
  }

  call(method, params) {
    const id = this.next++;
    const request = { jsonrpc: "2.0", id, method };
    if (params !== undefined) request.params = params;
    return new Promise((resolve, reject) => {
      if (this.ws.readyState !== WebSocket.OPEN) { reject(new Error("not connected")); return; }
      this.waiting.set(id, { resolve, reject });
      this.ws.send(JSON.stringify(request));
    });
  }
}

// --- state ------------------------------------------------------------------------

const view = {
  control: true,
  machine: null, // the machine shown
  snapshots: new Map(),
  files: [],
  program: null, // {name, moves, bounds, sendable}
  analysis: null, // the daemon's file.analyze of the program, for the machine shown
  analyzed: null, // what it was asked for: "file|machine|homed"
  rate: null, // {acked, at, perSecond}
  console: [],
  consoleSub: null, // this connection's console subscription (job lines or not, as the box says)
  macros: [],
  preview: { mode: "top", zoom: 1, panX: 0, panY: 0, toCanvas: null },
  keyJog: null, // the key whose continuous jog runs ("hold key" step)
  faultsShown: null, // the fault list drawn, as JSON: redrawn only when it changes
};

function toast(text, bad = false) {
  const el = $("toast");
  el.textContent = text;
  el.className = bad ? "toast bad" : "toast";
  el.hidden = false;
  clearTimeout(toast.timer);
  toast.timer = setTimeout(() => { el.hidden = true; }, 4000);
}

async function act(method, params) {
  try {
    return await rpc.call(method, params);
  } catch (error) {
    toast(`${method}: ${error.message}`, true);
    return null;
  }
}

// A long request (homing, probing, a test fire) keeps its button disabled until answered:
// a second click would only be refused (1003, an operation under way).
async function pending(button, work) {
  button.dataset.pending = "1";
  updateEnabled();
  try {
    return await work();
  } finally {
    delete button.dataset.pending;
    updateEnabled();
  }
}

function confirmFirst(text) {
  const dialog = $("confirm");
  $("confirm-text").textContent = text;
  dialog.returnValue = "";
  dialog.showModal();
  return new Promise((resolve) => {
    dialog.addEventListener("close", () => resolve(dialog.returnValue === "yes"), { once: true });
  });
}

// --- which button the daemon accepts now ------------------------------------------------
//
// Each control names what it needs (data-need); the page derives it from the snapshot
// (supervisor state, lockout, job, faults) by the daemon's own rules, and disables the
// control, with the reason as its title, where the daemon would refuse it. The table is
// in docs/web.md ("Which control is enabled when").

const LOCKOUTS = ["ALARM", "SHUTDOWN", "PANIC"];

function needs(snap) {
  const connected = Boolean(snap) && snap.supervisor !== "disconnected";
  // Still connecting, the board found busy with moves of before: its realtime bytes go
  // (hold, reset), nothing else until the handshake is through (docs/web.md).
  const reachable = connected || Boolean(snap && snap.occupied);
  const lockout = connected ? snap.lockout : null;
  const locked = Boolean(lockout && LOCKOUTS.includes(lockout.state));
  const idle = connected && snap.supervisor === "idle" && !lockout;
  const job = connected && snap.job && ["running", "paused"].includes(snap.job.state) ? snap.job : null;
  const blocking = connected ? (snap.faults || []).filter((f) => !f.overridden && f.severity !== "recoverable") : [];
  const held = connected && (snap.supervisor === "paused" || (snap.state && snap.state.name === "HOLD"));
  // A job waiting at M6: paused; the daemon serves jogs (as the job's lines) and
  // job.tool_change_done, and refuses resume and jog_stop (1003) until then.
  const toolChange = connected && snap.tool_change ? snap.tool_change : null;
  const why = (ok, reason) => (ok ? null : reason);
  const notConnected = "the machine is not connected";
  const lockedText = lockout ? `refused in ${lockout.state}: ${lockoutExit(lockout)}` : "";
  const busy = connected ? `refused while the machine is ${snap.supervisor}` : notConnected;
  const move = !connected ? notConnected : lockout ? lockedText : why(idle, busy);
  // A fault that blocks a job also refuses what moves the machine or powers its spindle
  // or beam (1007), after the lockout's own code; setting zero and Off stay (docs/web.md).
  const faulted = why(!blocking.length, `refused while a fault is active: ${blocking.map((f) => f.id).join(", ")}`);
  return {
    connected: why(connected, notConnected),
    hold: why(reachable, notConnected),
    reset: why(reachable, notConnected),
    move,
    // Home is a move, but the daemon also takes it in a lockout whose first way out names
    // machine.home (grbl's `$H` in ALARM, where its `$22` homes; never g2core's G28.2,
    // which its ALARM refuses): the board's own rule, as the lockout's `clear` says it.
    home: (connected && lockout && lockout.clear.split(", then ")[0].includes("machine.home") ? null : move)
      || faulted,
    powered: move || faulted,
    jog: (toolChange && !lockout ? null : move) || faulted,
    "jog-stop": why(connected, notConnected) || why(!toolChange, "refused while a tool change waits: press Done"),
    job: move || faulted,
    // A board found in Door while connecting reads nothing until it is resumed: Resume
    // is its way out then too (the daemon takes `~` while connecting).
    resume: !connected ? (snap && snap.occupied && snap.occupied.state === "Door" ? null : notConnected)
      : locked ? lockedText
      : toolChange ? "a tool change waits: press Done"
      : why(held || (lockout && lockout.state === "INTERLOCK"), "nothing is held"),
    cancel: why(Boolean(job), "no job is running"),
    clear: why(Boolean(lockout && lockout.clear.includes("machine.clear")), "no alarm or shutdown to clear"),
    override: !connected ? notConnected : locked ? lockedText
      : why(Boolean(snap.overrides), "the board reports no overrides"),
    "tool-change": why(Boolean(connected && snap.tool_change), "no tool change is waiting"),
  };
}

// An active fault with its way out, where the page can give it (docs/web.md, "Faults"):
// Clear for one that software clears, Override (asked first) or its removal for one that
// may be overridden; one that only a reset clears says so. Red while it blocks or alerts,
// amber once overridden, as the indicator's rule has it.
function faultItem(fault) {
  const li = document.createElement("li");
  li.className = `fault ${fault.overridden ? "warning" : "alert"}`;
  const text = document.createElement("span");
  text.textContent = `${fault.id}: ${fault.message || fault.severity}${fault.overridden ? " (overridden)" : ""}`;
  li.append(text);
  if (fault.clears === "reset") li.append(" · Reset clears it");
  if (fault.clears === "software") li.append(faultButton(fault.id, "clear", "Clear"));
  if (fault.overridable) {
    const button = faultButton(fault.id, "override", fault.overridden ? "Remove override" : "Override");
    button.dataset.override = fault.overridden ? "off" : "on";
    li.append(button);
  }
  return li;
}

function faultButton(id, kind, label) {
  const button = document.createElement("button");
  button.className = "small control";
  button.textContent = label;
  button.dataset.fault = id;
  button.dataset.faultAction = kind;
  return button;
}

async function faultAction(button) {
  const id = button.dataset.fault;
  const machine = view.machine;
  if (button.dataset.faultAction === "clear") {
    if (await act("fault.clear", { machine, fault: id })) toast(`${id}: cleared`);
    return;
  }
  const on = button.dataset.override === "on";
  const question = `Override ${id}? While it lasts, jobs, jogs and what moves the machine or powers its spindle or beam are no longer refused for it.`;
  if (on && !(await confirmFirst(question))) return;
  if (await act("fault.override", { machine, fault: id, override: on })) {
    toast(`${id}: ${on ? "overridden" : "override removed"}`);
  }
}

function updateEnabled() {
  const snap = view.snapshots.get(view.machine);
  const reasons = needs(snap);
  for (const el of document.querySelectorAll("[data-need]")) {
    if (el.dataset.hint === undefined) el.dataset.hint = el.title; // its own title, when enabled
    let reason = reasons[el.dataset.need] ?? null;
    if (!reason && el.id === "start" && view.analysis && (view.analysis.beyond_travel || []).length) {
      reason = "the program leaves the machine's travel";
    }
    // The frame is the program's XY box at a safe height: refused (1008) only when that
    // box leaves the travel. A program only too deep in Z can still be framed.
    if (!reason && el.id === "frame" && view.analysis && (view.analysis.frame_beyond_travel || []).length) {
      reason = "the program's outline leaves the machine's travel";
    }
    if (!reason && ["start", "frame"].includes(el.id) && !$("files").value) reason = "upload or pick a file first";
    if (!reason && el.dataset.pending) reason = "under way…";
    el.disabled = Boolean(reason);
    el.title = reason || el.dataset.hint || "";
  }
}

// --- drawing the machine ------------------------------------------------------------

const EXITS = { clear: "Clear", reset: "Reset", cycle_start: "Resume", home: "Home", feedhold: "Hold" };

// The API's method names in a text, as the page's buttons are named (machine.reset: Reset).
function pageWords(text) {
  return text.replace(/machine\.(\w+)/g, (_, m) => EXITS[m] || m);
}

function lockoutExit(lockout) {
  return pageWords(lockout.clear);
}

function showSnapshot(snap) {
  view.snapshots.set(snap.id, snap);
  if (snap.id !== view.machine) return;
  $("supervisor").textContent = snap.supervisor;
  $("controller").textContent = snap.state ? snap.state.name : "–";
  $("homed").textContent = snap.homed === true ? "yes" : snap.homed === false ? "no" : "–";
  $("tool").textContent = typeof snap.tool === "number" ? `T${snap.tool}` : "–";
  const spindle = snap.spindle;
  $("spindle").textContent = spindle
    ? `${spindle.state ?? "–"}${typeof spindle.speed === "number" ? ` · S${fmt(spindle.speed, 0)}` : ""}`
    : "–";
  $("feed").textContent = fmt(snap.feed, 0);
  $("velocity").textContent = fmt(snap.velocity, 0);
  // Each column in what the board reports it in: g2core's machine position is mm under
  // G20 too, grbl's both follow its $13, not G20 (docs/api.md, position_units).
  const units = snap.position_units || { work: snap.units, machine: snap.units };
  $("work-units").textContent = units.work || "";
  $("machine-units").textContent = units.machine || "";
  // A jog's step and feed are in the units mode in force (api.md: "in the machine's
  // units"): under G20 a step of 1 is an inch, a feed of 1000 is 1000 in/min.
  const mode = snap.units === "in" ? "in" : "mm";
  $("jog-units").textContent = mode;
  $("jog-feed-units").textContent = `${mode}/min`;
  $("wcs").textContent = snap.wcs || "";
  const work = snap.work_position || snap.position || {};
  const mach = snap.machine_position || {};
  for (const axis of ["x", "y", "z"]) {
    $(`w${axis}`).textContent = fmt(work[axis]);
    $(`m${axis}`).textContent = fmt(mach[axis]);
  }
  // A controller lockout (ALARM, SHUTDOWN, PANIC, INTERLOCK) outranks the fault table: the
  // light goes red, and says why and what ends it.
  const lockout = snap.lockout;
  // The link waits on a board busy with moves it was given before (a daemon that died
  // mid-job): amber, what the board does, and what ends it.
  const occupied = !lockout && snap.supervisor === "disconnected" ? snap.occupied : null;
  const level = lockout ? "alert" : occupied ? "warning" : snap.indicator || "normal";
  $("indicator").dataset.level = level;
  $("indicator-text").textContent = lockout ? lockout.state : occupied ? `connecting: ${occupied.state}` : level;
  $("lockout").hidden = !(lockout || occupied);
  $("lockout").classList.toggle("waiting", Boolean(occupied));
  // A message of hostd's own names API methods: said in the page's words.
  $("lockout-message").textContent = pageWords(lockout ? lockout.message : occupied ? occupied.message : "");
  $("lockout-clear").textContent = lockout ? `To end it: ${lockoutExit(lockout)}`
    : occupied ? "To end it: Reset (the board drops those moves), or wait for them to end" : "";
  for (const action of ["clear", "reset"]) {
    const button = document.querySelector(`[data-action=${action}]`);
    const needed = lockout ? lockout.clear.includes(`machine.${action}`) : Boolean(occupied) && action === "reset";
    if (button) button.classList.toggle("needed", needed);
  }
  const faultsNow = JSON.stringify(snap.faults || []);
  if (faultsNow !== view.faultsShown) { // redrawn on a change only: a click must land
    view.faultsShown = faultsNow;
    $("faults").replaceChildren(...(snap.faults || []).map(faultItem));
  }
  const overrides = snap.overrides || {};
  for (const key of ["feed", "spindle", "rapid"]) {
    $(`ov-${key}`).textContent = typeof overrides[key] === "number" ? `${Math.round(overrides[key])}%` : "–";
  }
  $("laser-set").hidden = !(snap.laser_mode || snap.laser);
  // The example in the console's box in the board's own words (grbl has no JSON).
  $("send-line").placeholder = `a line for the controller, e.g. ${snap.dialect === "grbl" ? "$G" : "{sr:n}"} or G0 X10`;
  showToolChange(snap);
  document.body.dataset.supervisor = snap.supervisor;
  if (view.program && analysisKey(view.program.name) !== view.analyzed) analyzeProgram(view.program.name);
  showJob(snap.job);
  updateEnabled();
  drawPreview();
}

// A job waiting at M6 (snapshot.tool_change): a banner, not a modal, so the jog pad and
// the position stay usable while the operator changes the tool.
function showToolChange(snap) {
  const wait = snap.tool_change;
  $("toolchange").hidden = !wait;
  if (!wait) return;
  const line = typeof wait.line === "number" ? ` (line ${wait.line})` : "";
  $("toolchange-text").textContent = `Change to tool ${wait.tool}${line}`;
}

function showJob(job) {
  const snap = view.snapshots.get(view.machine);
  if (snap) snap.job = job;
  if (!job) {
    $("job-title").textContent = "no job";
    $("job-progress").value = 0;
    $("job-progress").classList.remove("finishing");
    for (const id of ["job-lines", "job-at", "job-rate", "job-eta"]) $(id).textContent = "–";
    view.rate = null;
    return;
  }
  $("job-title").textContent = `#${job.id} ${job.file || job.kind} · ${job.state}`;
  const total = job.lines_total || 0;
  $("job-progress").value = total ? job.lines_acked / total : 0;
  $("job-lines").textContent = total ? `${job.lines_acked} / ${total}` : String(job.lines_acked);
  // Answered is planned, not run: the line the board says it runs is the job's true place
  // (a lower bound; none where the board never says, grbl 1.1 without Ln: or Bf:).
  $("job-at").textContent = typeof job.line_executed === "number" ? String(job.line_executed) : "–";
  const now = performance.now() / 1000;
  if (!view.rate || view.rate.job !== job.id) {
    if (view.rate) refreshHistory();
    view.rate = { job: job.id, acked: job.lines_acked, at: now, perSecond: null };
  } else if (now - view.rate.at >= 1) {
    const sample = (job.lines_acked - view.rate.acked) / (now - view.rate.at);
    view.rate.perSecond = view.rate.perSecond === null ? sample : 0.7 * view.rate.perSecond + 0.3 * sample;
    view.rate.acked = job.lines_acked;
    view.rate.at = now;
  }
  const perSecond = view.rate.perSecond;
  // A rate is a running job's: an ended or paused one shows none, not its last.
  $("job-rate").textContent =
    job.state !== "running" || perSecond === null ? "–" : `${perSecond.toFixed(1)} lines/s`;
  // Every line answered is not the end: the board still runs what its planner holds, and
  // the job is running until it rests. Said so, not "0 s".
  const left = total - job.lines_acked;
  const finishing = job.state === "running" && total > 0 && left <= 0;
  $("job-eta").textContent =
    job.state !== "running" ? "–"
      : finishing ? "finishing"
        : perSecond > 0 ? duration(left / perSecond) : "…";
  // A full bar reads as done: while the board still runs what it holds, the bar pulses.
  const bar = $("job-progress");
  bar.classList.toggle("finishing", finishing);
  bar.title = finishing ? "every line is sent; the machine is still running the last ones" : "";
  // The preview shows the file picked in the list, never the job's behind its back
  // (that once made the preview and Start disagree).
  if (["completed", "failed", "cancelled", "interrupted"].includes(job.state)) refreshHistory();
}

function duration(seconds) {
  if (!Number.isFinite(seconds)) return "–";
  const s = Math.round(seconds);
  const h = Math.floor(s / 3600);
  const m = Math.floor((s % 3600) / 60);
  return h ? `${h} h ${m} min` : m ? `${m} min ${s % 60} s` : `${s} s`;
}

// --- programs: parse, analyse, preview --------------------------------------------------

// The arc's plane: its two axes (indices into [x, y, z]) and the third, moved linearly (a
// helix), as grbl's gcode.c and g2core's canonical machine take G17, G18 and G19.
const PLANES = { 17: [0, 1, 2], 18: [2, 0, 1], 19: [1, 2, 0] };
const ARC_EPSILON = 5e-7; // rad: grbl's ARC_ANGULAR_TRAVEL_EPSILON, start = end is a full circle
const ARC_STEP = 0.05; // rad between the points an arc is drawn with
// G-codes whose axis words are not a move in work coordinates: drawn as nothing.
const NOT_MOVES = [4, 10, 28, 28.1, 30, 30.1, 43.1, 53, 92, 92.1];

// Enough G-code for a picture: G0/G1, G2/G3 (I J K or R, any plane, helical), G38.x,
// G90/G91, G90.1/G91.1, G20/G21. Each move is a polyline in work coordinates (mm).
function parseProgram(name, text) {
  const moves = [];
  const at = [0, 0, 0];
  let absolute = true, arcAbsolute = false, scale = 1, feed = null, motion = 0, plane = 17;
  let sendable = 0, seconds = 0;
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  let fileLine = 0; // numbered as the daemon numbers a file's lines (line_executed): a
  // line ends at \n, \r\n or a lone \r, as Python reads a text file (universal newlines)
  for (const raw of text.split(/\r\n|\r|\n/)) {
    fileLine += 1;
    const line = raw.replace(/\([^)]*\)/g, "").replace(/;.*/, "").trim().toUpperCase();
    if (!line || line.startsWith("%")) continue;
    sendable += 1;
    const words = line.match(/[A-Z]\s*[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)/g) || [];
    const axis = [null, null, null], offset = [null, null, null];
    let radius = null, skip = false;
    for (const word of words) {
      const letter = word[0], value = parseFloat(word.slice(1));
      if (letter === "G") {
        if ([0, 1, 2, 3, 38.2, 38.3, 38.4, 38.5].includes(value)) motion = value;
        else if (value === 80) motion = null;
        else if (PLANES[value]) plane = value;
        else if (value === 90) absolute = true;
        else if (value === 91) absolute = false;
        else if (value === 90.1) arcAbsolute = true;
        else if (value === 91.1) arcAbsolute = false;
        else if (value === 20) scale = 25.4;
        else if (value === 21) scale = 1;
        else if (NOT_MOVES.includes(value)) skip = true;
      } else if ("XYZ".includes(letter)) axis["XYZ".indexOf(letter)] = value;
      else if ("IJK".includes(letter)) offset["IJK".indexOf(letter)] = value;
      else if (letter === "R") radius = value;
      else if (letter === "F") feed = value * scale;
    }
    const arc = motion === 2 || motion === 3;
    const hasAxis = axis.some((v) => v !== null);
    if (skip || motion === null || !(hasAxis || (arc && offset.some((v) => v !== null)))) continue;
    const start = at.slice();
    const end = axis.map((v, i) => (v === null ? start[i] : absolute ? v * scale : start[i] + v * scale));
    let points = [start, end];
    if (arc) {
      const scaled = offset.map((v) => (v === null ? null : v * scale));
      points = arcPoints(start, end, motion === 2, PLANES[plane], scaled, radius === null ? null : radius * scale, arcAbsolute);
    }
    moves.push({ points, rapid: motion === 0, line: fileLine });
    let length = 0;
    for (let i = 0; i < points.length; i += 1) {
      const p = points[i];
      for (let a = 0; a < 3; a += 1) { lo[a] = Math.min(lo[a], p[a]); hi[a] = Math.max(hi[a], p[a]); }
      if (i) length += Math.hypot(p[0] - points[i - 1][0], p[1] - points[i - 1][1], p[2] - points[i - 1][2]);
    }
    if (motion !== 0 && feed) seconds += (length / feed) * 60;
    at.splice(0, 3, ...end);
  }
  const bounds = moves.length ? { lo, hi } : null;
  return { name, moves, bounds, sendable, seconds };
}

// The points of one arc from `start` to `end`: the centre from the offsets (relative to the
// start, or absolute under G90.1) or from R (negative: the long way round), the sweep
// clockwise or not, a full circle where start and end meet.
function arcPoints(start, end, clockwise, [a, b, lin], offset, radius, arcAbsolute) {
  let ca, cb;
  if (radius !== null && offset[a] === null && offset[b] === null) {
    const da = end[a] - start[a], db = end[b] - start[b], d = Math.hypot(da, db);
    if (d === 0) return [start, end]; // R cannot make a full circle: the board refuses it
    const h = Math.sqrt(Math.max(radius * radius - (d * d) / 4, 0));
    const side = (clockwise ? 1 : -1) * (radius < 0 ? -1 : 1);
    ca = (start[a] + end[a]) / 2 + (side * h * db) / d;
    cb = (start[b] + end[b]) / 2 - (side * h * da) / d;
  } else {
    ca = arcAbsolute ? offset[a] ?? start[a] : start[a] + (offset[a] ?? 0);
    cb = arcAbsolute ? offset[b] ?? start[b] : start[b] + (offset[b] ?? 0);
  }
  const r = Math.hypot(start[a] - ca, start[b] - cb);
  const from = Math.atan2(start[b] - cb, start[a] - ca);
  let sweep = Math.atan2(end[b] - cb, end[a] - ca) - from;
  if (clockwise) { if (sweep >= -ARC_EPSILON) sweep -= 2 * Math.PI; }
  else if (sweep <= ARC_EPSILON) sweep += 2 * Math.PI;
  const steps = Math.min(720, Math.max(2, Math.ceil(Math.abs(sweep) / ARC_STEP)));
  const points = [start];
  for (let i = 1; i < steps; i += 1) {
    const angle = from + (sweep * i) / steps;
    const p = start.slice();
    p[a] = ca + r * Math.cos(angle);
    p[b] = cb + r * Math.sin(angle);
    p[lin] = start[lin] + ((end[lin] - start[lin]) * i) / steps;
    points.push(p);
  }
  points.push(end);
  return points;
}

async function loadProgram(name) {
  if (!name) return;
  view.program = { name, moves: [], bounds: null, sendable: 0, seconds: 0 };
  view.analysis = null;
  resetView();
  const response = await fetch(`/files/${encodeURIComponent(name)}`);
  if (!view.program || view.program.name !== name) return; // another file was picked meanwhile
  if (!response.ok) { $("analysis").textContent = `${name}: cannot read (${response.status})`; return; }
  const program = parseProgram(name, await response.text());
  if (!view.program || view.program.name !== name) return;
  view.program = program;
  showAnalysis(program, null);
  drawPreview();
  await analyzeProgram(name);
}

// The travel check depends on the machine and on whether it is homed: asked again when they change.
function analysisKey(name) {
  const snap = view.snapshots.get(view.machine);
  return `${name}|${view.machine}|${snap ? snap.homed : null}`;
}

// file.analyze {file, machine}: the daemon's figures, warnings and travel check (docs/api.md).
async function analyzeProgram(name) {
  const key = analysisKey(name);
  view.analyzed = key;
  const params = { file: name };
  if (view.machine) params.machine = view.machine;
  let analysis = null;
  try {
    analysis = await rpc.call("file.analyze", params);
  } catch (error) {
    analysis = { failed: error.message };
  }
  if (view.analyzed !== key || !view.program || view.program.name !== name) return; // superseded
  view.analysis = analysis;
  showAnalysis(view.program, analysis);
}

function showAnalysis(program, analysis) {
  const ok = analysis && !analysis.failed;
  const parts = [`${program.name}: ${ok ? analysis.lines : program.sendable} lines`];
  const bounds = ok ? analysis.bounds || {} : {};
  const axes = ["x", "y", "z"].filter((axis) => Array.isArray(bounds[axis]));
  if (axes.length) parts.push(axes.map((a) => `${a.toUpperCase()} ${bounds[a][0].toFixed(1)}…${bounds[a][1].toFixed(1)}`).join(", ") + " mm");
  else if (program.bounds) {
    const { lo, hi } = program.bounds;
    parts.push(`X ${lo[0].toFixed(1)}…${hi[0].toFixed(1)}, Y ${lo[1].toFixed(1)}…${hi[1].toFixed(1)} mm`);
  }
  if (ok && typeof analysis.duration_s === "number") parts.push(`about ${duration(analysis.duration_s)}`);
  else if (program.seconds) parts.push(`about ${duration(program.seconds)} of feed moves (estimated here)`);
  if (analysis && analysis.failed) parts.push(`not analysed: ${analysis.failed}`);
  else if (!analysis) parts.push("analysing…");
  $("analysis").textContent = parts.join(" · ");
  const beyond = ok ? analysis.beyond_travel || [] : [];
  const travel = $("travel");
  travel.hidden = beyond.length === 0;
  travel.textContent = beyond.length
    ? `Start is refused: the program leaves ${view.machine}'s travel. ${beyond.join("; ")}`
    : "";
  const warnings = ok ? (analysis.warnings || []).filter((text) => !beyond.includes(text)) : [];
  $("warnings").replaceChildren(...warnings.map((text) => {
    const li = document.createElement("li");
    li.textContent = text;
    return li;
  }));
  updateEnabled();
}

function resetView() {
  Object.assign(view.preview, { zoom: 1, panX: 0, panY: 0 });
}

// A grid step of 1, 2 or 5 times a power of ten, at least `pixels` apart on the screen.
function gridStep(scale, pixels = 48) {
  const raw = pixels / scale;
  const power = 10 ** Math.floor(Math.log10(raw));
  return [1, 2, 5, 10].map((m) => m * power).find((step) => step >= raw);
}

function drawPreview() {
  const canvas = $("preview");
  const ratio = window.devicePixelRatio || 1;
  const width = canvas.clientWidth, height = canvas.clientHeight;
  if (canvas.width !== Math.round(width * ratio) || canvas.height !== Math.round(height * ratio)) {
    canvas.width = Math.round(width * ratio);
    canvas.height = Math.round(height * ratio);
  }
  const g = canvas.getContext("2d");
  g.setTransform(ratio, 0, 0, ratio, 0, 0);
  g.clearRect(0, 0, width, height);
  const program = view.program;
  const pv = view.preview;
  pv.toCanvas = null;
  if (!program || !program.bounds || !width || !height) return;
  // Top: X across, Y up. Side: X across, Z up.
  const [h, v] = pv.mode === "top" ? [0, 1] : [0, 2];
  const { lo, hi } = program.bounds, pad = 24;
  const spanH = hi[h] - lo[h], spanV = hi[v] - lo[v];
  const fit = Math.min(spanH > 1e-9 ? (width - 2 * pad) / spanH : Infinity,
                       spanV > 1e-9 ? (height - 2 * pad) / spanV : Infinity);
  const scale = (Number.isFinite(fit) ? fit : 10) * pv.zoom;
  const midH = (lo[h] + hi[h]) / 2, midV = (lo[v] + hi[v]) / 2;
  const px = (x) => width / 2 + (x - midH) * scale + pv.panX;
  const py = (y) => height / 2 - (y - midV) * scale + pv.panY;
  pv.toCanvas = (x, y) => [px(x), py(y)];
  pv.toWorld = (cx, cy) => [midH + (cx - width / 2 - pv.panX) / scale, midV - (cy - height / 2 - pv.panY) / scale];
  pv.scale = scale;
  const style = getComputedStyle(document.body);
  drawGrid(g, width, height, scale, pv, style, [h, v]);
  const snap = view.snapshots.get(view.machine);
  const job = snap && snap.job && snap.job.file === program.name ? snap.job : null;
  // Done is what the board ran: the lines before the one it last said it was running
  // (line_executed, a lower bound, never ahead; docs/api.md). Not the lines it answered:
  // an answer means planned, and a planner holds many moves ahead of the tool.
  const done = !job ? 0 : job.state === "completed" ? Infinity : job.line_executed || 0;
  const stroke = (moves, color, dash) => {
    g.beginPath();
    g.strokeStyle = color;
    g.setLineDash(dash);
    for (const m of moves) {
      const [first, ...rest] = m.points;
      g.moveTo(px(first[h]), py(first[v]));
      for (const p of rest) g.lineTo(px(p[h]), py(p[v]));
    }
    g.stroke();
  };
  g.lineWidth = 2; // at least one whole pixel wide, wherever it falls
  const left = program.moves.filter((m) => m.line >= done);
  const past = program.moves.filter((m) => m.line < done);
  stroke(left.filter((m) => m.rapid), style.getPropertyValue("--rapid"), [3, 4]);
  stroke(left.filter((m) => !m.rapid), style.getPropertyValue("--left"), []);
  stroke(past, style.getPropertyValue("--done"), []);
  g.setLineDash([]);
  const work = snap && (snap.work_position || snap.position);
  const axisName = ["x", "y", "z"];
  if (work && typeof work[axisName[h]] === "number" && typeof work[axisName[v]] === "number") {
    g.fillStyle = style.getPropertyValue("--tool");
    g.beginPath();
    g.arc(px(work[axisName[h]]), py(work[axisName[v]]), 5, 0, 2 * Math.PI);
    g.fill();
  }
}

function drawGrid(g, width, height, scale, pv, style, [h, v]) {
  const step = gridStep(scale);
  const [x0, y1] = pv.toWorld(0, 0);
  const [x1, y0] = pv.toWorld(width, height);
  g.save();
  g.lineWidth = 1;
  g.font = "10px ui-monospace, monospace";
  g.fillStyle = style.getPropertyValue("--muted");
  const names = ["X", "Y", "Z"];
  const line = (ax, ay, bx, by, axis) => {
    g.strokeStyle = style.getPropertyValue(axis ? "--axis" : "--grid");
    g.beginPath();
    g.moveTo(ax, ay);
    g.lineTo(bx, by);
    g.stroke();
  };
  const digits = step < 1 ? Math.ceil(-Math.log10(step)) : 0;
  for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
    const [cx] = pv.toCanvas(x, 0);
    line(cx + 0.5, 0, cx + 0.5, height, Math.abs(x) < step / 2);
    g.fillText(x.toFixed(digits), cx + 2, height - 3);
  }
  for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
    const [, cy] = pv.toCanvas(0, y);
    line(0, cy + 0.5, width, cy + 0.5, Math.abs(y) < step / 2);
    g.fillText(y.toFixed(digits), 2, cy - 2);
  }
  g.fillText(`${names[h]} →  ${names[v]} ↑  grid ${step} mm`, width - 150, 12);
  g.restore();
}

function zoomPreview(factor, cx, cy) {
  const pv = view.preview;
  const canvas = $("preview");
  const width = canvas.clientWidth, height = canvas.clientHeight;
  const atX = cx ?? width / 2, atY = cy ?? height / 2;
  const zoom = Math.min(Math.max(pv.zoom * factor, 0.1), 2000);
  const applied = zoom / pv.zoom;
  // Keep the point under the cursor where it is.
  pv.panX = atX - width / 2 - (atX - width / 2 - pv.panX) * applied;
  pv.panY = atY - height / 2 - (atY - height / 2 - pv.panY) * applied;
  pv.zoom = zoom;
  drawPreview();
}

function setViewMode(mode) {
  view.preview.mode = mode;
  resetView();
  for (const [id, m] of [["view-top", "top"], ["view-side", "side"]]) {
    $(id).classList.toggle("on", m === mode);
    $(id).setAttribute("aria-pressed", String(m === mode));
  }
  drawPreview();
}

function wirePreview() {
  const canvas = $("preview");
  canvas.addEventListener("wheel", (event) => {
    event.preventDefault();
    const rect = canvas.getBoundingClientRect();
    zoomPreview(event.deltaY < 0 ? 1.25 : 0.8, event.clientX - rect.left, event.clientY - rect.top);
  }, { passive: false });
  let drag = null;
  canvas.addEventListener("pointerdown", (event) => {
    drag = { x: event.clientX, y: event.clientY, panX: view.preview.panX, panY: view.preview.panY };
    canvas.setPointerCapture(event.pointerId);
  });
  canvas.addEventListener("pointermove", (event) => {
    if (!drag) return;
    view.preview.panX = drag.panX + event.clientX - drag.x;
    view.preview.panY = drag.panY + event.clientY - drag.y;
    drawPreview();
  });
  const end = () => { drag = null; };
  canvas.addEventListener("pointerup", end);
  canvas.addEventListener("pointercancel", end);
  $("zoom-in").addEventListener("click", () => zoomPreview(1.5));
  $("zoom-out").addEventListener("click", () => zoomPreview(1 / 1.5));
  $("zoom-fit").addEventListener("click", () => { resetView(); drawPreview(); });
  $("view-top").addEventListener("click", () => setViewMode("top"));
  $("view-side").addEventListener("click", () => setViewMode("side"));
}

// --- files, history, console --------------------------------------------------------------

async function refreshFiles(select) {
  const files = await act("file.list");
  if (!files) return;
  const list = $("files");
  // At first, a running job's file; then whatever the operator picked.
  const snap = view.snapshots.get(view.machine);
  const running = snap && snap.job && snap.job.state === "running" ? snap.job.file : null;
  const current = select || list.value || running;
  list.replaceChildren(...files.map((f) => new Option(`${f.name} (${f.size} B)`, f.name)));
  if (current && files.some((f) => f.name === current)) list.value = current;
  if (list.value && (!view.program || view.program.name !== list.value)) loadProgram(list.value);
  updateEnabled();
}

// When a job started, short enough that the row's Resume button stays in the card: the time
// for today's jobs, the day and time for older ones.
function shortTime(at) {
  const today = at.toDateString() === new Date().toDateString();
  const clock = { hour: "2-digit", minute: "2-digit" };
  return at.toLocaleString([], today ? clock : { month: "short", day: "numeric", ...clock });
}

async function refreshHistory() {
  const jobs = await act("job.list", { machine: view.machine, limit: 20 });
  if (!jobs) return;
  $("history").tBodies[0].replaceChildren(...jobs.map((job) => {
    const tr = document.createElement("tr");
    const lines = job.lines_total ? `${job.lines_acked}/${job.lines_total}` : String(job.lines_acked);
    const at = job.started_at ? new Date(job.started_at) : null;
    for (const text of [job.id, job.file || "–", job.kind, job.state, lines, at ? shortTime(at) : "–"]) {
      const td = document.createElement("td");
      td.textContent = text;
      tr.append(td);
    }
    if (at) tr.cells[5].title = at.toLocaleString(); // the whole date and time on hover
    const td = document.createElement("td");
    td.className = "control";
    if (job.kind === "make" && ["interrupted", "failed", "cancelled"].includes(job.state)) {
      const button = document.createElement("button");
      button.className = "small";
      button.textContent = "Resume…";
      button.dataset.need = "connected";
      button.addEventListener("click", () => planResume({ job: job.id }));
      td.append(button);
    }
    tr.append(td);
    tr.className = job.state;
    return tr;
  }));
  updateEnabled();
}

// A control byte shown as its caret name, as the boards' own messages name them ("Job
// killed by ^d"): the job kill 0x04 is ^D, grbl's reset 0x18 ^X. As text it drew a box.
const visible = (text) =>
  text.replace(/[\x00-\x08\x0a-\x1f\x7f]/g, (c) => `^${String.fromCharCode(c.charCodeAt(0) ^ 0x40)}`);

function showConsole(params) {
  if (params.machine !== view.machine) return;
  const arrow = { tx: "→", rx: "←" }[params.direction] || "=";
  view.console.push(`${arrow} ${visible(params.text)}`);
  if (view.console.length > 300) view.console.splice(0, view.console.length - 300);
  const pre = $("console");
  const atEnd = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
  pre.textContent = view.console.join("\n");
  if (atEnd) pre.scrollTop = pre.scrollHeight;
}

// --- macros ------------------------------------------------------------------------------

// macro.list's params: {name: {min, max, default, integer}} (docs/api.md); a list of names
// is taken too.
function macroParams(params) {
  if (!params) return [];
  if (Array.isArray(params)) {
    return params.map((p) => (typeof p === "string" ? { name: p } : { ...p }));
  }
  return Object.entries(params).map(([name, spec]) => (
    spec && typeof spec === "object" ? { name, ...spec } : { name, default: spec }));
}

async function refreshMacros() {
  let macros = [];
  try {
    macros = await rpc.call("macro.list", { machine: view.machine });
  } catch (error) {
    macros = []; // a daemon without macros (-32601) or none configured: no card
  }
  view.macros = macros || [];
  $("macros-card").hidden = view.macros.length === 0;
  $("macros").replaceChildren(...view.macros.map((macro) => {
    const li = document.createElement("li");
    const form = document.createElement("form");
    form.className = "row macro";
    const title = document.createElement("strong");
    title.textContent = macro.name;
    title.title = macro.text || "";
    form.append(title);
    for (const param of macroParams(macro.params)) {
      const label = document.createElement("label");
      label.textContent = `${param.name} `;
      const input = document.createElement("input");
      input.name = param.name;
      input.type = "number";
      input.required = true;
      if (param.default !== undefined && param.default !== null) input.value = param.default;
      if (typeof param.min === "number") input.min = param.min;
      if (typeof param.max === "number") input.max = param.max;
      input.step = param.integer ? "1" : "any";
      label.append(input);
      form.append(label);
    }
    const run = document.createElement("button");
    run.type = "submit";
    run.textContent = "Run";
    run.dataset.need = "job";
    form.append(run);
    form.addEventListener("submit", async (event) => {
      event.preventDefault();
      const params = {};
      for (const input of form.querySelectorAll("input")) params[input.name] = Number(input.value);
      const body = { machine: view.machine, name: macro.name };
      if (Object.keys(params).length) body.params = params;
      const started = await act("macro.run", body);
      if (started) toast(`macro ${macro.name}: job ${started.job}`);
    });
    li.append(form);
    return li;
  }));
  updateEnabled();
}

// --- resume from a line: the CLI's plan (job.recovery), then job.start from there ----------

async function planResume(params) {
  const plan = await act("job.recovery", params);
  if (!plan) return;
  $("plan-title").textContent = `Resume ${plan.file} from line ${plan.line}`;
  const position = Object.entries(plan.position || {}).map(([a, v]) => `${a.toUpperCase()} ${fmt(v)}`).join(" ");
  $("plan-summary").textContent = `The tool goes to ${position || "the start"}${plan.units ? ` (${plan.units})` : ""}, then line ${plan.line} on.`;
  $("plan-preamble").textContent = [...(plan.preamble || []), ...(plan.approach || [])].join("\n") || "nothing";
  const uncertain = plan.uncertain || [];
  $("plan-uncertain").replaceChildren(...(uncertain.length ? uncertain : ["nothing"]).map((text) => {
    const li = document.createElement("li");
    li.textContent = text;
    return li;
  }));
  $("plan-start").textContent = `Start from line ${plan.line}`;
  const dialog = $("plan");
  dialog.returnValue = "";
  dialog.showModal();
  const answer = await new Promise((resolve) => {
    dialog.addEventListener("close", () => resolve(dialog.returnValue), { once: true });
  });
  if (answer !== "yes") return;
  const started = await act("job.start", { machine: plan.machine || view.machine, file: plan.file, start_line: plan.line });
  if (started) toast(`job ${started.job} started from line ${plan.line}`);
}

// --- keyboard jogging ----------------------------------------------------------------------

const JOG_KEYS = {
  ArrowLeft: ["x", -1], ArrowRight: ["x", 1], ArrowUp: ["y", 1], ArrowDown: ["y", -1],
  PageUp: ["z", 1], PageDown: ["z", -1],
};
const HOLD_JOG_SECONDS = 5; // a held key's jog runs at most this long if its keyup is lost

function typing() {
  const el = document.activeElement;
  return Boolean(el && (el.isContentEditable || ["INPUT", "SELECT", "TEXTAREA"].includes(el.tagName)));
}

function jogFeed() {
  return parseFloat($("jog-feed").value) || 1000;
}

async function jog(axis, distance) {
  await act("machine.jog", { machine: view.machine, axes: { [axis]: distance }, feed: jogFeed() });
}

function stopKeyJog() {
  if (!view.keyJog) return;
  view.keyJog = null;
  act("machine.jog_stop", { machine: view.machine });
}

function wireKeys() {
  document.addEventListener("keydown", (event) => {
    const key = JOG_KEYS[event.key];
    if (!key || !view.control || typing() || !document.hasFocus() || document.querySelector("dialog[open]")) return;
    if (event.altKey || event.ctrlKey || event.metaKey) return;
    event.preventDefault();
    if (event.repeat || view.keyJog) return; // one jog a press; auto-repeat queues nothing
    if (needs(view.snapshots.get(view.machine)).jog) { toast("jog refused: the machine is not ready", true); return; }
    const [axis, dir] = key;
    const step = $("jog-step").value;
    if (step === "hold") {
      // Its release sends machine.jog_stop, which a tool change's hold refuses: steps only.
      const snap = view.snapshots.get(view.machine);
      if (snap && snap.tool_change) { toast("during a tool change the keys jog by steps: pick a step", true); return; }
      view.keyJog = event.key;
      jog(axis, (dir * jogFeed() * HOLD_JOG_SECONDS) / 60);
    } else {
      jog(axis, dir * parseFloat(step));
    }
  });
  document.addEventListener("keyup", (event) => { if (event.key === view.keyJog) stopKeyJog(); });
  // Never a jog left running: the tab or the window losing the focus stops it.
  window.addEventListener("blur", stopKeyJog);
  document.addEventListener("visibilitychange", () => { if (document.hidden) stopKeyJog(); });
  // A step picked with the keyboard leaves the select, so the arrows jog again.
  $("jog-step").addEventListener("change", () => $("jog-step").blur());
}

// --- wiring ----------------------------------------------------------------------------------

function onNotify(method, params) {
  if (method === "status") showSnapshot(params.snapshot);
  else if (method === "job" && params.machine === view.machine) { showJob(params.job); updateEnabled(); drawPreview(); }
  else if (method === "console") showConsole(params);
  else if (["supervisor", "fault", "exception"].includes(method)) {
    if (params.machine === view.machine) refreshMachine();
    if (method === "exception") showConsole({ machine: params.machine, direction: "rx", text: JSON.stringify(params.report) });
  }
}

async function refreshMachine() {
  const snap = await act("machine.status", { machine: view.machine });
  if (snap) showSnapshot(snap);
}

async function onLink(up) {
  $("link").textContent = up ? "live" : "offline";
  $("link").className = up ? "link up" : "link down";
  if (!up) { stopKeyJog(); view.snapshots.clear(); view.consoleSub = null; updateEnabled(); return; }
  const info = await act("daemon.info");
  if (!info) return;
  const select = $("machine");
  select.replaceChildren(...info.machines.map((id) => new Option(id, id)));
  view.machine = info.machines.includes(view.machine) ? view.machine : info.machines[0] || null;
  select.value = view.machine || "";
  await act("subscribe", { topics: ["status", "supervisor", "fault", "job", "exception"] });
  await subscribeConsole();
  if (view.machine) { await refreshMachine(); await refreshHistory(); await refreshMacros(); }
  await refreshFiles();
}

// Unless the "job lines" box is ticked, a running job's own lines and their plain `ok`s stay
// out of the console (job_lines: false, docs/api.md): a laser sends 1,000-2,000 a second, two
// messages each, which no one reads; the job row shows the progress. Unless the "status
// reports" box is ticked, so do the status polls and reports (grbl's `?` and `<...>`, g2core's
// `{"sr":null}` and `{"sr":...}`, several a second: status_traffic: false); the status panel
// shows what they say. The daemon leaves them out: it no longer makes and sends what the page
// would throw away. The new subscription is made before the old one ends: one client gets
// each notification once, so nothing is lost.
async function subscribeConsole() {
  const jobs = $("console-job");
  const polls = $("console-polls");
  const previous = view.consoleSub;
  const sub = await act("subscribe", {
    topics: ["console"], job_lines: jobs.checked, status_traffic: polls.checked,
  });
  view.consoleSub = sub ? sub.subscription : previous;
  if (sub && previous !== null) await act("unsubscribe", { subscription: previous });
  if (!sub) return;
  jobs.dataset.subscribed = String(jobs.checked); // what the daemon sends now
  polls.dataset.subscribed = String(polls.checked);
  $("console-hidden").textContent = polls.checked ? "" : "(hidden)";
}

async function upload(event) {
  event.preventDefault();
  const file = $("upload-file").files[0];
  if (!file) { toast("choose a file first", true); return; }
  const response = await fetch(`/files/${encodeURIComponent(file.name)}`, { method: "POST", body: file });
  const body = await response.json().catch(() => ({}));
  if (!response.ok) { toast(`upload: ${body.error || response.status}`, true); return; }
  toast(`uploaded ${body.name} (${body.size} B)`);
  view.program = null;
  await refreshFiles(body.name);
}

const ACTIONS = {
  hold: "machine.feedhold",
  resume: "machine.cycle_start",
  cancel: "job.cancel",
  clear: "machine.clear",
  reset: "machine.reset",
};

function overrideValue(key, button) {
  const snap = view.snapshots.get(view.machine);
  const now = snap && snap.overrides && typeof snap.overrides[key] === "number" ? snap.overrides[key] : 100;
  if (button.dataset.set) return parseInt(button.dataset.set, 10);
  return Math.min(Math.max(Math.round(now + parseInt(button.dataset.step, 10)), 10), 200);
}

function wireOperations() {
  $("home").addEventListener("click", () => pending($("home"), async () => {
    toast("homing…");
    if (await act("machine.home", { machine: view.machine })) toast("homed");
  }));
  for (const button of document.querySelectorAll("[data-zero]")) {
    button.addEventListener("click", async () => {
      const axes = Object.fromEntries([...button.dataset.zero].map((a) => [a, 0]));
      if (await act("machine.zero", { machine: view.machine, axes })) toast(`work zero set: ${button.dataset.zero.toUpperCase()}`);
    });
  }
  $("goto-zero").addEventListener("click", async () => {
    if (!(await confirmFirst("Go to work zero? Z rises to the safe height first, then X and Y, then Z comes down to 0."))) return;
    await pending($("goto-zero"), async () => {
      if (await act("machine.goto_zero", { machine: view.machine })) toast("at work zero");
    });
  });
  $("probe-kind").addEventListener("change", () => { $("probe-tool").hidden = $("probe-kind").value !== "xyz"; });
  $("probe").addEventListener("click", async () => {
    const kind = $("probe-kind").value;
    const params = { machine: view.machine, kind };
    const plate = parseFloat($("probe-plate").value);
    if (Number.isFinite(plate)) params.plate = plate; // else the machine's [machines.probe] plate
    if (kind === "xyz") {
      const diameter = parseFloat($("probe-diameter").value);
      if (!Number.isFinite(diameter)) { toast("give the bit's diameter (mm) for an XYZ probe", true); return; }
      params.tool_diameter = diameter;
    }
    if ($("probe-confirmed").checked) params.confirmed = true;
    const what = kind === "xyz" ? "the XYZ corner" : "Z";
    const on = Number.isFinite(plate) ? `a ${plate} mm plate` : "the configured plate";
    if (!(await confirmFirst(`Probe ${what} on ${on}? The clip is on the bit and the plate under it.`))) return;
    // The daemon first waits to see the probe input work: the operator touches the plate
    // to the bit and lets go (docs/api.md, machine.probe).
    const status = $("probe-status");
    status.hidden = false;
    status.textContent = "Touch the plate to the bit, then let go: hostd waits up to 30 s to see the probe input work, then probes.";
    const result = await pending($("probe"), () => act("machine.probe", params));
    if (result) {
      const where = Object.entries(result.position || {}).map(([a, v]) => `${a.toUpperCase()} ${fmt(v)}`).join(" ");
      status.textContent = `Touched at ${where} (machine); work zero set on ${(result.zeroed || []).join(", ").toUpperCase() || "nothing"}.`;
    } else {
      status.textContent = "The probe did not run or did not touch (the reason is above).";
    }
  });
  for (const row of document.querySelectorAll("[data-override]")) {
    for (const button of row.querySelectorAll("button")) {
      button.addEventListener("click", async () => {
        const key = row.dataset.override;
        const now = await act("machine.override", { machine: view.machine, [key]: overrideValue(key, button) });
        if (now && typeof now[key] === "number") $(`ov-${key}`).textContent = `${Math.round(now[key])}%`;
      });
    }
  }
  for (const button of document.querySelectorAll("[data-spindle]")) {
    button.addEventListener("click", async () => {
      const params = { machine: view.machine, state: button.dataset.spindle };
      const speed = parseFloat($("spindle-speed").value);
      if (params.state !== "off" && Number.isFinite(speed)) params.speed = speed;
      if (await act("machine.spindle", params)) toast(`spindle ${params.state}`);
    });
  }
  $("laser-test").addEventListener("click", async () => {
    const power = parseFloat($("laser-power").value);
    const seconds = Math.min(parseFloat($("laser-duration").value) || 0.5, 2);
    if (!(await confirmFirst(`Fire the laser at ${power}% for ${seconds} s? Eyewear on, the lid closed.`))) return;
    const fired = await pending($("laser-test"), () => act("machine.laser_test", { machine: view.machine, power, duration_s: seconds }));
    if (fired) toast("laser test done");
  });
  $("frame").addEventListener("click", async () => {
    const file = $("files").value;
    const started = await act("machine.frame", { machine: view.machine, file });
    if (started) toast(`framing ${file}: job ${started.job}`);
  });
  $("toolchange-done").addEventListener("click", async () => {
    if (await act("job.tool_change_done", { machine: view.machine })) toast("tool changed: the job goes on");
  });
  $("from-line").addEventListener("submit", (event) => {
    event.preventDefault();
    const file = $("files").value;
    const line = parseInt($("from-line-number").value, 10);
    if (!file) { toast("upload or pick a file first", true); return; }
    planResume({ machine: view.machine, file, line });
  });
}

function wire() {
  for (const button of document.querySelectorAll("[data-action]")) {
    button.addEventListener("click", async () => {
      const question = button.dataset.confirm;
      if (question && !(await confirmFirst(question))) return;
      if (await act(ACTIONS[button.dataset.action], { machine: view.machine })) toast(`${button.textContent}: sent`);
    });
  }
  for (const button of document.querySelectorAll("[data-jog]")) {
    button.addEventListener("click", () => {
      const step = $("jog-step").value === "hold" ? 1 : parseFloat($("jog-step").value);
      jog(button.dataset.jog.toLowerCase(), step * parseInt(button.dataset.dir, 10));
    });
  }
  $("jog-stop").addEventListener("click", () => act("machine.jog_stop", { machine: view.machine }));
  $("faults").addEventListener("click", (event) => {
    const button = event.target.closest("button[data-fault]");
    if (button) faultAction(button);
  });
  $("machine").addEventListener("change", () => {
    stopKeyJog();
    view.machine = $("machine").value;
    view.console = [];
    view.analyzed = null;
    refreshMachine();
    refreshHistory();
    refreshMacros();
  });
  $("files").addEventListener("change", () => { loadProgram($("files").value); updateEnabled(); });
  $("upload").addEventListener("submit", upload);
  $("start").addEventListener("click", async () => {
    const file = $("files").value;
    if (!file) { toast("upload or pick a file first", true); return; }
    const started = await act("job.start", { machine: view.machine, file });
    if (started) toast(`job ${started.job} started`);
  });
  $("send").addEventListener("submit", async (event) => {
    event.preventDefault();
    const line = $("send-line").value.trim();
    if (!line) return;
    const answer = await act("machine.send", { machine: view.machine, line });
    if (!answer) return;
    $("send-line").value = "";
    // The board's own lines are already in the console (its `ok`, grbl's `[GC:...]`: the
    // answer's `lines`); the answer's values are shown once, as the daemon's ("="), for
    // what the console may have left out: `{sr:n}`'s report while status reports are off.
    const { lines, ...values } = answer.r || {};
    if (Object.keys(values).length) {
      showConsole({ machine: view.machine, direction: "answer", text: JSON.stringify(values) });
    }
  });
  $("console-polls").addEventListener("change", subscribeConsole);
  $("console-job").addEventListener("change", subscribeConsole);
  $("logout").addEventListener("click", async () => {
    await fetch("/logout", { method: "POST" });
    location.replace("/login");
  });
  window.addEventListener("resize", drawPreview);
  wireOperations();
  wirePreview();
  wireKeys();
  updateEnabled();
}

let rpc;

async function main() {
  const session = await fetch("/session");
  if (session.status === 401) { location.replace("/login"); return; }
  view.control = (await session.json()).control;
  document.body.classList.toggle("watch", !view.control);
  $("watch-only").hidden = view.control;
  wire();
  rpc = new Rpc(onNotify, onLink);
}

main();
