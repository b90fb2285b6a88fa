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

function confirmFirst(text) {
  const dialog = $("confirm");
  $("confirm-text").textContent = text;
  dialog.returnValue = "";
  dialog.showModal();
  return new Promise((resolve) => {
    dialog.addEventListener("close", () => resolve(dialog.returnValue === "yes"), { once: true });
  });
}

// --- drawing the machine ------------------------------------------------------------

function showSnapshot(snap) {
  view.snapshots.set(snap.id, snap);
  if (snap.id !== view.machine) return;
  $("supervisor").textContent = snap.supervisor;
  $("controller").textContent = snap.state ? snap.state.name : "–";
  $("feed").textContent = fmt(snap.feed, 0);
  $("velocity").textContent = fmt(snap.velocity, 0);
  $("units").textContent = snap.units || "";
  const work = snap.work_position || snap.position || {};
  const mach = snap.machine_position || {};
  for (const axis of ["x", "y", "z"]) {
    $(`w${axis}`).textContent = fmt(work[axis]);
    $(`m${axis}`).textContent = fmt(mach[axis]);
  }
  // A controller lockout (ALARM, SHUTDOWN, PANIC, INTERLOCK) outranks the fault table: the
  // light goes red, and says why and what ends it.
  const lockout = snap.lockout;
  const level = lockout ? "alert" : snap.indicator || "normal";
  $("indicator").dataset.level = level;
  $("indicator-text").textContent = lockout ? lockout.state : level;
  $("lockout").hidden = !lockout;
  $("lockout-message").textContent = lockout ? lockout.message : "";
  const buttons = { clear: "Clear", reset: "Reset", cycle_start: "Resume" };
  $("lockout-clear").textContent = lockout
    ? `To end it: ${lockout.clear.replace(/machine\.(\w+)/g, (_, m) => buttons[m] || m)}`
    : "";
  for (const action of ["clear", "reset"]) {
    const button = document.querySelector(`[data-action=${action}]`);
    if (button) button.classList.toggle("needed", Boolean(lockout && lockout.clear.includes(`machine.${action}`)));
  }
  const faults = $("faults");
  faults.replaceChildren(...(snap.faults || []).map((fault) => {
    const li = document.createElement("li");
    li.className = `fault ${fault.severity}`;
    li.textContent = `${fault.id}: ${fault.message || fault.severity}${fault.overridden ? " (overridden)" : ""}`;
    return li;
  }));
  document.body.dataset.supervisor = snap.supervisor;
  if (view.program && analysisKey(view.program.name) !== view.analyzed) analyzeProgram(view.program.name);
  showJob(snap.job);
  drawPreview();
}

function showJob(job) {
  const snap = view.snapshots.get(view.machine);
  if (snap) snap.job = job;
  if (!job) {
    $("job-title").textContent = "no job";
    $("job-progress").value = 0;
    for (const id of ["job-lines", "job-rate", "job-eta"]) $(id).textContent = "–";
    view.rate = null;
    return;
  }
  $("job-title").textContent = `#${job.id} ${job.file || job.kind} · ${job.state}`;
  const total = job.lines_total || 0;
  $("job-progress").value = total ? job.lines_acked / total : 0;
  $("job-lines").textContent = total ? `${job.lines_acked} / ${total}` : String(job.lines_acked);
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
  $("job-rate").textContent = perSecond === null ? "–" : `${perSecond.toFixed(1)} lines/s`;
  const left = total - job.lines_acked;
  $("job-eta").textContent =
    job.state !== "running" ? "–" : perSecond > 0 ? duration(left / perSecond) : "…";
  if (job.file && (!view.program || view.program.name !== job.file)) loadProgram(job.file);
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

// Enough G-code for a picture: G0/G1 (and G2/G3 drawn as chords), G90/G91, G20/G21.
function parseProgram(name, text) {
  const moves = [];
  let x = 0, y = 0, absolute = true, scale = 1, feed = null, motion = 0, sendable = 0, seconds = 0;
  let minX = Infinity, minY = Infinity, maxX = -Infinity, maxY = -Infinity;
  for (const raw of text.split("\n")) {
    const line = raw.replace(/\([^)]*\)/g, "").replace(/;.*/, "").trim().toUpperCase();
    if (!line || line.startsWith("%")) continue;
    sendable += 1;
    const words = line.match(/[A-Z][-+]?[0-9]*\.?[0-9]+/g) || [];
    let nx = null, ny = null;
    for (const word of words) {
      const letter = word[0], value = parseFloat(word.slice(1));
      if (letter === "G") {
        if ([0, 1, 2, 3].includes(value)) motion = value;
        else if (value === 90) absolute = true;
        else if (value === 91) absolute = false;
        else if (value === 20) scale = 25.4;
        else if (value === 21) scale = 1;
      } else if (letter === "X") nx = value * scale;
      else if (letter === "Y") ny = value * scale;
      else if (letter === "F") feed = value * scale;
    }
    if (nx === null && ny === null) continue;
    const tx = nx === null ? x : absolute ? nx : x + nx;
    const ty = ny === null ? y : absolute ? ny : y + ny;
    moves.push({ x0: x, y0: y, x1: tx, y1: ty, rapid: motion === 0, at: sendable });
    if (motion !== 0 && feed) seconds += (Math.hypot(tx - x, ty - y) / feed) * 60;
    for (const [px, py] of [[x, y], [tx, ty]]) {
      minX = Math.min(minX, px); maxX = Math.max(maxX, px);
      minY = Math.min(minY, py); maxY = Math.max(maxY, py);
    }
    x = tx; y = ty;
  }
  const bounds = moves.length ? { minX, minY, maxX, maxY } : null;
  return { name, moves, bounds, sendable, seconds };
}

async function loadProgram(name) {
  if (!name) return;
  view.program = { name, moves: [], bounds: null, sendable: 0, seconds: 0 };
  const response = await fetch(`/files/${encodeURIComponent(name)}`);
  if (!response.ok) { $("analysis").textContent = `${name}: cannot read (${response.status})`; return; }
  const program = parseProgram(name, await response.text());
  if (!view.program || view.program.name !== name) return;
  view.program = program;
  view.analysis = null;
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
    const b = program.bounds;
    parts.push(`X ${b.minX.toFixed(1)}…${b.maxX.toFixed(1)}, Y ${b.minY.toFixed(1)}…${b.maxY.toFixed(1)} mm`);
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
  $("start").disabled = beyond.length > 0;
  $("start").title = beyond.length ? "the program leaves the machine's travel" : "";
  const warnings = ok ? (analysis.warnings || []).filter((text) => !beyond.includes(text)) : [];
  $("warnings").replaceChildren(...warnings.map((text) => {
    const li = document.createElement("li");
    li.textContent = text;
    return li;
  }));
}

function drawPreview() {
  const canvas = $("preview");
  const ratio = window.devicePixelRatio || 1;
  const width = canvas.clientWidth, height = canvas.clientHeight;
  if (canvas.width !== Math.round(width * ratio)) {
    canvas.width = Math.round(width * ratio);
    canvas.height = Math.round(height * ratio);
  }
  const g = canvas.getContext("2d");
  g.setTransform(ratio, 0, 0, ratio, 0, 0);
  g.clearRect(0, 0, width, height);
  const program = view.program;
  if (!program || !program.bounds) return;
  const b = program.bounds, pad = 12;
  const scale = Math.min((width - 2 * pad) / Math.max(b.maxX - b.minX, 1e-6),
                         (height - 2 * pad) / Math.max(b.maxY - b.minY, 1e-6));
  const px = (v) => pad + (v - b.minX) * scale;
  const py = (v) => height - pad - (v - b.minY) * scale;
  const snap = view.snapshots.get(view.machine);
  const job = snap && snap.job && snap.job.file === program.name ? snap.job : null;
  const done = job ? job.lines_acked : 0;
  const style = getComputedStyle(document.body);
  const stroke = (moves, color, dash) => {
    g.beginPath();
    g.strokeStyle = color;
    g.setLineDash(dash);
    for (const m of moves) { g.moveTo(px(m.x0), py(m.y0)); g.lineTo(px(m.x1), py(m.y1)); }
    g.stroke();
  };
  g.lineWidth = 1.5;
  const left = program.moves.filter((m) => m.at > done);
  const past = program.moves.filter((m) => m.at <= done);
  stroke(left.filter((m) => m.rapid), style.getPropertyValue("--rapid"), [3, 4]);
  stroke(left.filter((m) => !m.rapid), style.getPropertyValue("--left"), []);
  stroke(past, style.getPropertyValue("--done"), []);
  g.setLineDash([]);
  const work = snap && (snap.work_position || snap.position);
  if (work && typeof work.x === "number" && typeof work.y === "number") {
    g.fillStyle = style.getPropertyValue("--tool");
    g.beginPath();
    g.arc(px(work.x), py(work.y), 5, 0, 2 * Math.PI);
    g.fill();
  }
}

// --- files, history, console --------------------------------------------------------------

async function refreshFiles(select) {
  const files = await act("file.list");
  if (!files) return;
  const list = $("files");
  const current = select || list.value;
  list.replaceChildren(...files.map((f) => new Option(`${f.name} (${f.size} B)`, f.name)));
  if (current && files.some((f) => f.name === current)) list.value = current;
  if (list.value && (!view.program || view.program.name !== list.value)) loadProgram(list.value);
}

async function refreshHistory() {
  const jobs = await act("job.list", { machine: view.machine, limit: 20 });
  if (!jobs) return;
  $("history").tBodies[0].replaceChildren(...jobs.map((job) => {
    const tr = document.createElement("tr");
    const lines = job.lines_total ? `${job.lines_acked}/${job.lines_total}` : String(job.lines_acked);
    const started = job.started_at ? new Date(job.started_at).toLocaleString() : "–";
    for (const text of [job.id, job.file || "–", job.kind, job.state, lines, started]) {
      const td = document.createElement("td");
      td.textContent = text;
      tr.append(td);
    }
    tr.className = job.state;
    return tr;
  }));
}

function showConsole(params) {
  if (params.machine !== view.machine) return;
  view.console.push(`${params.direction === "tx" ? "→" : "←"} ${params.text}`);
  if (view.console.length > 300) view.console.splice(0, view.console.length - 300);
  const pre = $("console");
  const atEnd = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
  pre.textContent = view.console.join("\n");
  if (atEnd) pre.scrollTop = pre.scrollHeight;
}

// --- wiring ----------------------------------------------------------------------------------

function onNotify(method, params) {
  if (method === "status") showSnapshot(params.snapshot);
  else if (method === "job" && params.machine === view.machine) { showJob(params.job); drawPreview(); }
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
  if (!up) return;
  const info = await act("daemon.info");
  if (!info) return;
  const select = $("machine");
  select.replaceChildren(...info.machines.map((id) => new Option(id, id)));
  view.machine = info.machines.includes(view.machine) ? view.machine : info.machines[0] || null;
  select.value = view.machine || "";
  await act("subscribe", { topics: ["status", "supervisor", "fault", "job", "console", "exception"] });
  if (view.machine) { await refreshMachine(); await refreshHistory(); }
  await refreshFiles();
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
      const step = parseFloat($("jog-step").value) * parseInt(button.dataset.dir, 10);
      const feed = parseFloat($("jog-feed").value) || 1000;
      act("machine.jog", { machine: view.machine, axes: { [button.dataset.jog.toLowerCase()]: step }, feed });
    });
  }
  $("machine").addEventListener("change", () => {
    view.machine = $("machine").value;
    view.console = [];
    view.analyzed = null;
    refreshMachine();
    refreshHistory();
  });
  $("files").addEventListener("change", () => loadProgram($("files").value));
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
    if (answer) { $("send-line").value = ""; showConsole({ machine: view.machine, direction: "rx", text: JSON.stringify(answer) }); }
  });
  $("logout").addEventListener("click", async () => {
    await fetch("/logout", { method: "POST" });
    location.replace("/login");
  });
  window.addEventListener("resize", drawPreview);
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
