// The page: one WebSocket to scara-gui, the state it sends drawn at the browser's frame rate,
// the typed and mouse-edited task, and the buttons that send the bridge's commands.
"use strict";

const PLOT_SECONDS = 10; // k_T and k_C over this many seconds
const EVENTS_SHOWN = 8;
const PLOT_PERIOD = 100; // ms between two redraws of the plot (the weights come at 10 Hz)
const SOON = 50; // ms what is not the arm's motion may wait for the motion's next frame
const STILL = 100; // ms without a move after which the next is a start (as the bridge's STILL)
const $ = (id) => document.getElementById(id);

const page = {
  socket: null,
  hello: null,
  robot: null,
  latest: {}, // the latest payload of each state key
  path: [], trace: [], events: [], plan: [],
  time: 0,
  draft: { waypoints: [], obstacle: null }, // the task being edited
  edited: false, // the draft differs from the robot's task: a new task does not replace it
  // what to draw again: a part is drawn only when what it shows changed (a run's start brings
  // a status, events and weights; the arm's views drawn again for them held up its first move)
  numbersChanged: true, // the left panel's numbers and states
  armChanged: true, // the joints, a path or the task: the top view and the 3D view
  taskChanged: true, // the draft task to draw again in 3D
  jointsMoved: false, // new joints to draw
  movedAt: -Infinity, // when a frame last drew new joints (ms)
  planChanged: true, pathRestarted: true, eventsChanged: true, // to draw again, not extend
  stats: { messages: 0, frames: 0 }, // read by the tests: updates received, frames drawn
  commandId: 0,
  plotted: 0, // when the plot was last drawn (ms)
  plotStale: true,
  framePending: false, // a browser frame is asked for
  soonTimer: null, // a frame is to be asked for SOON, unless the arm's motion asks first
  plotTimer: null, // the plot's next turn is waited for
};
window.scara = page;

// --- the socket ---

function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const socket = new WebSocket(`${scheme}://${location.host}/ws`);
  page.socket = socket;
  socket.onmessage = (event) => onMessage(JSON.parse(event.data));
  socket.onclose = () => {
    $("connection").textContent = "disconnected: retrying";
    setTimeout(connect, 1000);
  };
}

function send(message) {
  page.socket.send(JSON.stringify(message));
}

function onMessage(message) {
  page.stats.messages += 1;
  if (message.type === "hello") onHello(message);
  else if (message.type === "robots") onRobots(message.robots);
  else if (message.type === "state") onState(message);
  else if (message.type === "reply") onReply(message);
  else if (message.type === "playback") onPlayback(message);
}

function onHello(hello) {
  const first = page.hello === null;
  page.hello = hello;
  page.robot = hello.robot;
  const who = hello.mode === "recording" ? "recording" : `live as ${hello.user || "anonymous"}`;
  $("connection").textContent = who + (hello.read_only ? " (read-only)" : "");
  if (hello.mode === "recording") setUpPlayback(hello);
  if (first) {
    page.view3d = make3D(hello.geometry);
    page.topView = new TopView($("top"), hello.geometry, page.draft, onDraftEdited);
    page.plot = makePlot();
    requestFrame();
  }
  lockEditing();
}

// A read-only page (a recording, a read-only user): every button and every control that
// edits the task disabled, the mouse on the top view edits nothing.
function lockEditing() {
  const readOnly = page.hello !== null && page.hello.read_only;
  for (const control of document.querySelectorAll("[data-command], .edits")) {
    const noObstacle = control.closest("#obstacle") !== null && page.draft.obstacle === null;
    control.disabled = readOnly || noObstacle;
  }
  if (page.topView) page.topView.editable = !readOnly;
}

function make3D(geometry) {
  try {
    return new Arm3D($("view3d"), geometry, requestFrame);
  } catch (error) { // no WebGL in this browser: the other panels still work
    $("view3d").textContent = `no 3D view: ${error.message}`;
    return null;
  }
}

function onRobots(robots) {
  const select = $("robot");
  select.innerHTML = "";
  for (const robot of robots) {
    select.add(new Option(robot.name + (robot.online ? "" : " (offline)"), robot.name));
  }
  if (!robots.some((robot) => robot.name === page.robot)) {
    select.add(new Option(`${page.robot} (not heard)`, page.robot));
  }
  select.value = page.robot;
}

function onState(message) {
  if (message.robot !== page.robot) return; // sent before a switch was seen
  // the server sends a key again only when it shows something new (gui/state.py); an update
  // of the plot's weights alone has nothing else to draw again
  if (message.full || message.events.length || Object.keys(message.latest).length > 0) {
    page.numbersChanged = true;
  }
  if (message.full || message.restarted || message.path.length || message.plan
    || message.latest.joints || message.latest.scenario) page.armChanged = true;
  if (message.latest.joints && !message.full) page.jointsMoved = true;
  if (message.full) {
    Object.assign(page, { latest: {}, path: [], trace: [], events: [] });
    page.pathRestarted = page.eventsChanged = true;
  }
  if (message.restarted) { // a run started: its path is sent whole, nothing else is
    page.path = [];
    page.pathRestarted = true;
  }
  Object.assign(page.latest, message.latest);
  page.path.push(...message.path);
  if (page.path.length > PATH_CAPACITY) { // as the server keeps it: the newest points
    page.path.splice(0, page.path.length - PATH_CAPACITY);
    page.pathRestarted = true;
  }
  page.trace.push(...message.trace);
  page.trace = page.trace.filter(([t]) => t >= message.time - PLOT_SECONDS);
  if (message.events.length) {
    page.events.push(...message.events);
    page.events = page.events.slice(-EVENTS_SHOWN);
    page.eventsChanged = true;
  }
  if (message.plan) {
    page.plan = message.plan;
    page.planChanged = true;
  }
  page.time = message.time;
  if (message.latest.scenario && !page.edited) takeTask(message.latest.scenario);
  if (message.full && !message.latest.scenario && !page.edited) takeTask(null);
  if (message.full || message.trace.length) page.plotStale = true;
  // the arm's motion is drawn at once (scara-gui paces it: gui/state.py, MOTION_KEYS)
  if (message.full || message.latest.joints || message.latest.tcp) requestFrame();
  else if (somethingToDraw()) requestFrameSoon();
}

// --- drawing, in a browser frame asked for when something changed ---

// A page that asked for every browser frame cost the browser a frame's work 60 times a
// second, at rest too: with two pages open, that was CPU the robot's first move waited for.
function requestFrame() {
  if (page.framePending) return;
  page.framePending = true;
  requestAnimationFrame(frame);
}

// What is not the arm's motion (a status, events, the weights, a plan) waits up to SOON for
// the motion's next frame and is drawn in it. As a run starts those came just before the arm
// moved, each a frame of its own that both pages' browsers laid out, painted and composited
// while the first move was waited for.
function requestFrameSoon() {
  if (page.framePending || page.soonTimer !== null) return;
  page.soonTimer = setTimeout(() => {
    page.soonTimer = null;
    if (somethingToDraw()) requestFrame();
  }, SOON);
}

const somethingToDraw = () => page.numbersChanged || page.armChanged || page.plotStale;

// The first frame of a move after the arm stood still draws the arm alone; the numbers and the
// plot follow in the motion's next frame. As a run started they came due in that same frame
// (the weights and the status had changed) and held the arm's first move up 5-30 ms.
function frame(now) {
  page.framePending = false;
  const starting = page.jointsMoved && now - page.movedAt > STILL;
  if (page.jointsMoved) {
    page.jointsMoved = false;
    page.movedAt = now;
  }
  const numbers = page.numbersChanged && !starting;
  const drawn = numbers || page.armChanged;
  if (numbers) {
    page.numbersChanged = false;
    drawNumbers();
  }
  if (page.armChanged) {
    page.armChanged = false;
    drawArm();
  }
  if (drawn) page.stats.frames += 1;
  if (starting) requestFrameSoon();
  else if (page.plotStale && now - page.plotted >= PLOT_PERIOD) {
    page.plotStale = false;
    page.plotted = now;
    drawPlot();
  } else if (page.plotStale && page.plotTimer === null) { // its turn comes without an update
    page.plotTimer = setTimeout(() => { page.plotTimer = null; requestFrame(); },
      page.plotted + PLOT_PERIOD - now);
  }
  if (page.view3d) page.view3d.render();
}

// A text written only when it changed: the same text written again still costs the browser a
// layout and a paint of its panel, every frame.
function show(id, text) {
  const element = $(id);
  if (element.textContent !== text) element.textContent = text;
}

function drawArm() {
  const joints = page.latest.joints;
  const topView = page.topView;
  topView.joints = joints ? joints.position : null;
  topView.path = page.path;
  topView.plan = page.plan;
  topView.draw();
  if (page.view3d) {
    if (joints) page.view3d.setJoints(joints.position);
    page.view3d.extendLine(page.view3d.travelled, page.path, page.pathRestarted);
    if (page.planChanged) page.view3d.setLine(page.view3d.plan, page.plan);
    if (page.taskChanged) page.view3d.setTask(page.draft);
  }
  page.taskChanged = page.planChanged = page.pathRestarted = false;
}

const degrees = (radians) => (radians * 180 / Math.PI).toFixed(2);

function drawNumbers() {
  const { joints, tcp, coordination, status, scenario } = page.latest;
  if (joints) {
    const [q1, q2, d3] = joints.position, [v1, v2, v3] = joints.velocity;
    show("theta1", `${degrees(q1)}°`);
    show("theta2", `${degrees(q2)}°`);
    show("d3", `${(d3 * 1000).toFixed(1)} mm`);
    show("theta1-rate", `${degrees(v1)}°/s`);
    show("theta2-rate", `${degrees(v2)}°/s`);
    show("d3-rate", `${(v3 * 1000).toFixed(1)} mm/s`);
  }
  if (tcp) show("tcp", `${tcp.x.toFixed(3)}, ${tcp.y.toFixed(3)}, ${tcp.z.toFixed(3)} m`);
  show("weights", coordination
    ? `k_T ${coordination.k_t.toFixed(2)} k_C ${coordination.k_c.toFixed(2)} (${coordination.behaviour})`
    : "");
  if (status) {
    for (const node of ["controller", "plant"]) {
      const seen = status[node];
      show(`${node}-state`, seen.alive ? seen.state : "silent");
      show(`${node}-faults`, seen.faults.join(", "));
      $(`${node}-faults`).classList.toggle("fault", seen.faults.length > 0);
    }
    const controller = status.controller;
    if ($("progress").value !== controller.progress) $("progress").value = controller.progress;
    show("progress-text",
      `${controller.progress} %, waypoints ${controller.waypoints_reached}, holds ${controller.holds}`);
  }
  show("task-name", scenario ? scenario.name : "no task");
  // the task's mode is the one set; the controller's status tells it from its next run on
  const mode = scenario ? scenario.mode : status && status.controller.mode;
  show("mode", mode || "–");
  if (!page.eventsChanged) return;
  page.eventsChanged = false;
  const list = $("events");
  list.innerHTML = "";
  for (const event of page.events) {
    const item = document.createElement("li");
    const detail = Object.entries(event.detail).map(([k, v]) => `${k}=${v}`).join(" ");
    item.textContent = `${event.event} ${detail}`;
    list.appendChild(item);
  }
}

function makePlot() {
  const dataset = (label, color) => ({ label, data: [], borderColor: color, pointRadius: 0, borderWidth: 2, stepped: true });
  return new Chart($("plot"), {
    type: "line",
    data: { datasets: [dataset("k_T", "#1e88e5"), dataset("k_C", "#e53935")] },
    options: {
      animation: false, parsing: false, normalized: true, maintainAspectRatio: false,
      scales: {
        x: { type: "linear", min: -PLOT_SECONDS, max: 0, title: { display: true, text: "s" } },
        y: { min: 0, max: 1.05 },
      },
      plugins: { legend: { position: "top", labels: { boxWidth: 12 } } },
    },
  });
}

function drawPlot() {
  const [kT, kC] = page.plot.data.datasets;
  const points = page.trace.map(([t, kt, kc]) => [t - page.time, kt, kc]);
  if (points.length) { // the weights hold until they change: draw them on to now
    const [, kt, kc] = points[points.length - 1];
    points.push([0, kt, kc]);
  }
  kT.data = points.map(([x, y]) => ({ x, y }));
  kC.data = points.map(([x, , y]) => ({ x, y }));
  page.plot.update("none");
}

// --- the task being edited: typed inputs and the mouse share page.draft ---

function takeTask(task) {
  page.draft.waypoints = task ? task.waypoints.map((w) => ({ ...w })) : [];
  page.draft.obstacle = task && task.obstacle ? { ...task.obstacle } : null;
  page.edited = false;
  page.taskChanged = true;
  fillInputs();
}

function onDraftEdited() {
  page.edited = true;
  page.armChanged = true;
  page.taskChanged = true;
  fillInputs();
  requestFrame();
}

function fillInputs() {
  const body = $("waypoints").querySelector("tbody");
  body.innerHTML = "";
  page.draft.waypoints.forEach((waypoint, index) => {
    const row = body.insertRow();
    for (const field of ["t", "x", "y", "z"]) {
      const input = document.createElement("input");
      Object.assign(input, { type: "number", step: field === "t" ? "0.1" : "0.005", value: waypoint[field] });
      input.className = "edits";
      input.dataset.field = field;
      input.onchange = () => { waypoint[field] = Number(input.value); onDraftEdited(); };
      row.insertCell().appendChild(input);
    }
    const remove = document.createElement("button");
    Object.assign(remove, { type: "button", textContent: "×", title: "delete this waypoint", className: "edits" });
    remove.onclick = () => { page.draft.waypoints.splice(index, 1); onDraftEdited(); };
    row.insertCell().appendChild(remove);
  });
  const obstacle = page.draft.obstacle;
  $("has-obstacle").checked = obstacle !== null;
  for (const input of $("obstacle").querySelectorAll("input")) {
    if (obstacle) input.value = obstacle[input.dataset.field];
  }
  lockEditing();
}

function setUpInputs() {
  $("add-waypoint").onclick = () => {
    const last = page.draft.waypoints[page.draft.waypoints.length - 1];
    page.draft.waypoints.push(last ? { ...last, t: last.t + 1.5 } : { t: 0, x: 0.3, y: 0, z: 0.22 });
    onDraftEdited();
  };
  $("has-obstacle").onchange = (event) => {
    page.draft.obstacle = event.target.checked ? defaultObstacle() : null;
    onDraftEdited();
  };
  for (const input of $("obstacle").querySelectorAll("input")) {
    input.onchange = () => {
      page.draft.obstacle[input.dataset.field] = Number(input.value);
      onDraftEdited();
    };
  }
  for (const radio of document.querySelectorAll("input[name=edit]")) {
    radio.onchange = () => { page.topView.mode = radio.value; showHint(); };
  }
  $("robot").onchange = (event) => {
    page.robot = event.target.value;
    page.edited = false;
    send({ type: "select", robot: page.robot });
  };
  showHint();
}

function showHint() {
  const obstacle = page.topView && page.topView.mode === "obstacle";
  $("hint").textContent = obstacle
    ? "click: place · drag: move · wheel: size · shift+wheel: yaw"
    : "click: add · drag: move · right click: delete";
}

// --- the buttons: each sends the bridge's command; its answer shows beside it ---

function commandBody(name) {
  if (name === "waypoints") return { waypoints: page.draft.waypoints };
  if (name === "obstacle") return { obstacle: page.draft.obstacle };
  if (name === "mode") return { mode: $("mode-choice").value };
  return null;
}

function setUpButtons() {
  for (const button of document.querySelectorAll("[data-command]")) {
    const name = button.dataset.command;
    button.onclick = () => {
      showAnswer(name, "sent…", "");
      page.commandId += 1;
      send({ type: "command", id: page.commandId, name, body: commandBody(name) });
    };
  }
}

function onReply(message) {
  if (message.reply) {
    const reply = message.reply;
    if (reply.accepted && (message.name === "waypoints" || message.name === "obstacle")) {
      page.edited = false; // the robot's task is the draft now
    }
    showAnswer(message.name, reply.accepted ? "accepted" : refusal(reply), reply.accepted ? "accepted" : "refused");
  } else {
    showAnswer(message.name, refusal(message.error), "refused");
  }
}

function refusal({ reason, error, field, message }) {
  const where = field ? ` (${field})` : "";
  return `refused: ${reason || error}${where}${message ? `: ${message}` : ""}`;
}

function showAnswer(name, text, kind) {
  const answer = $(`answer-${name}`);
  if (!answer) return;
  answer.textContent = text;
  answer.className = `answer ${kind}`;
}

// --- a recording: slider, play and pause, speed ---

function setUpPlayback(hello) {
  $("playback").hidden = false;
  const slider = $("slider");
  slider.max = hello.duration;
  slider.oninput = () => send({ type: "seek", value: Number(slider.value) });
  $("play").onclick = () => send({ type: "play", value: $("play").textContent === "play" });
  const speed = $("speed");
  speed.innerHTML = "";
  for (const value of hello.speeds) speed.add(new Option(`${value}×`, value));
  speed.value = 1;
  speed.onchange = () => send({ type: "speed", value: Number(speed.value) });
}

function onPlayback(message) {
  $("slider").value = message.position;
  $("position").textContent = `${message.position.toFixed(2)} s`;
  $("play").textContent = message.playing ? "pause" : "play";
}

setUpButtons();
connect();
addEventListener("load", setUpInputs);
